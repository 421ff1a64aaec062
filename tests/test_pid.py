"""LinuxCNC-style PID+FF (motorctl.control.pid): each pid.c semantic against hand-computed values,
the published signals, no allocation per step, closed loop on the simulated gantry, and switching
an axis between C2 and the PID through ServoLoop.switch_axis."""

import math
import tracemalloc

import numpy as np
import pytest

from motorctl.app.build import build, run_cycles
from motorctl.config import load_config
from motorctl.control import configured_controllers, make_controller
from motorctl.control.base import SIG
from motorctl.control.params import ControllerConfig
from motorctl.control.pid import PID, PidConfig
from motorctl.loop.records import CONTROLLER_SIGNALS

TS = 2e-4
U_LIM = 10.0
THETA_SIGNALS = [n for n in CONTROLLER_SIGNALS if n.startswith("theta_hat")] + ["d_hat0"]


def _pid(**gains) -> PID:
    c = PID(PidConfig(**gains), TS, U_LIM)
    c.reset(0.0)
    return c


# ------------------------------------------------------------------ pid.c semantics, by hand
def test_proportional_on_error_command_minus_feedback():
    c = _pid(P=1000.0)
    # error = x_d − y = 0 − (−1 mm) = +1 mm → u = +1 V (pushes +x, toward the command)
    assert c.update(-1e-3, 0.0, 0.0, 0.0) == pytest.approx(1.0)
    assert c.e == pytest.approx(-1e-3)          # published e = y − x_d
    c.reset(0.0)
    assert c.update(0.0, -2e-3, 0.0, 0.0) == pytest.approx(-2.0)


def test_deadband_ignores_small_errors_and_reduces_large_ones():
    c = _pid(P=1000.0, deadband=2e-4)
    assert c.update(0.0, 1e-4, 0.0, 0.0) == 0.0                      # |ε| ≤ deadband → 0
    assert c.update(0.0, 2e-4, 0.0, 0.0) == 0.0                      # at the edge → 0
    assert c.update(0.0, 1e-3, 0.0, 0.0) == pytest.approx(0.8)       # (1e-3 − 2e-4)·1000
    assert c.update(0.0, -1e-3, 0.0, 0.0) == pytest.approx(-0.8)
    assert c.e == pytest.approx(1e-3)           # e is the raw error, before the deadband


def test_maxerror_clips_the_error_before_the_deadband():
    c = _pid(P=1000.0, maxerror=5e-4)
    assert c.update(0.0, 1e-3, 0.0, 0.0) == pytest.approx(0.5)
    assert c.update(0.0, -3e-3, 0.0, 0.0) == pytest.approx(-0.5)
    assert c.update(0.0, 3e-4, 0.0, 0.0) == pytest.approx(0.3)       # inside: unchanged
    c = _pid(P=1000.0, maxerror=5e-4, deadband=2e-4)
    assert c.update(0.0, 1e-3, 0.0, 0.0) == pytest.approx(0.3)       # (5e-4 − 2e-4)·1000 (pid.c order)


def test_integrator_sums_error_times_ts_including_this_sample():
    c = _pid(I=1e5)
    for k in range(1, 11):
        u = c.update(0.0, 1e-3, 0.0, 0.0)
        assert c.error_i == pytest.approx(k * 1e-3 * TS)
        assert u == pytest.approx(1e5 * k * 1e-3 * TS)               # k = 10: 0.2 V
    assert u == pytest.approx(0.2)


def test_maxerror_i_clamps_the_integral():
    c = _pid(I=1e5, maxerror_i=1e-6)
    for _ in range(100):                        # unclamped the integral would reach 2e-5 m s
        u = c.update(0.0, 1e-3, 0.0, 0.0)
    assert c.error_i == pytest.approx(1e-6)
    assert u == pytest.approx(0.1)              # I · maxerror_i
    for _ in range(100):
        c.update(0.0, -1e-3, 0.0, 0.0)
    assert c.error_i == pytest.approx(-1e-6)


def test_anti_windup_stops_integrating_into_the_limit_while_saturated():
    c = _pid(P=2e4, I=1e5, maxoutput=5.0)
    u = c.update(0.0, 1e-3, 0.0, 0.0)           # not yet in the limit: integrates once
    assert c.error_i == pytest.approx(2e-7)
    assert u == 5.0 and c.saturated
    assert c.v == pytest.approx(20.0 + 1e5 * 2e-7)
    for _ in range(50):                         # saturated high, error still positive: frozen
        assert c.update(0.0, 1e-3, 0.0, 0.0) == 5.0
    assert c.error_i == pytest.approx(2e-7)
    # the error reverses: integration resumes at once (ε·limit_state ≤ 0), the output leaves the limit
    u = c.update(0.0, -1e-5, 0.0, 0.0)
    assert c.error_i == pytest.approx(2e-7 - 1e-5 * TS)
    assert u == pytest.approx(2e4 * -1e-5 + 1e5 * (2e-7 - 1e-5 * TS))
    assert not c.saturated
    # and without a limit in the way it integrates every sample
    free = _pid(P=2e4, I=1e5, maxoutput=0.0)
    for _ in range(10):
        free.update(0.0, 1e-5, 0.0, 0.0)
    assert free.error_i == pytest.approx(10 * 1e-5 * TS)


def test_anti_windup_also_acts_on_the_u_lim_clamp():
    c = _pid(P=1e5, I=1e5)                      # maxoutput 0: the clamp is u_lim
    for _ in range(20):
        assert c.update(0.0, 1e-3, 0.0, 0.0) == U_LIM
    assert c.error_i == pytest.approx(1e-3 * TS)     # the first sample only


def test_derivative_on_error_uses_analytic_command_velocity_and_measured_velocity():
    c = _pid(D=10.0)
    # y moves one 1 µm step in one sample (x2 = 5 mm/s), command velocity 10 mm/s, ε = 0
    u = c.update(1e-6, 1e-6, 0.01, 0.0)
    assert u == pytest.approx(10.0 * (0.01 - 0.005))
    s = c.signals
    assert s[SIG["x2"]] == pytest.approx(0.005)
    assert s[SIG["p"]] == pytest.approx(0.005 - 0.01)   # p = ė = x2 − ẋ_d [m/s]
    assert s[SIG["v"]] == pytest.approx(0.05)


def test_feedforward_terms_and_bias():
    c = PID(PidConfig(FF0=2.0, FF1=3.0, FF2=0.5, bias=-0.1), TS, U_LIM)
    c.reset(0.1)                                # y = x_d = 0.1 m, no motion measured
    u = c.update(0.1, 0.1, 0.2, 4.0)
    assert u == pytest.approx(-0.1 + 2.0 * 0.1 + 3.0 * 0.2 + 0.5 * 4.0)   # 2.7 V
    c.reset(0.1)
    assert c.update(0.1, 0.1, 0.0, 0.0) == pytest.approx(-0.1 + 0.2)       # bias + FF0 only


def test_maxoutput_and_u_lim_clamp_u_but_not_v():
    c = PID(PidConfig(FF2=1.0), TS, U_LIM)
    c.reset(0.0)
    assert c.update(0.0, 0.0, 0.0, 30.0) == U_LIM
    assert c.v == pytest.approx(30.0)
    assert c.update(0.0, 0.0, 0.0, -30.0) == -U_LIM
    c = PID(PidConfig(FF2=1.0, maxoutput=4.0), TS, U_LIM)
    c.reset(0.0)
    assert c.update(0.0, 0.0, 0.0, 30.0) == 4.0
    assert c.update(0.0, 0.0, 0.0, -30.0) == -4.0
    assert c.update(0.0, 0.0, 0.0, 3.0) == pytest.approx(3.0)
    c = PID(PidConfig(FF2=1.0, maxoutput=50.0), TS, U_LIM)       # never above u_lim
    assert c.u_max == U_LIM
    c.reset(0.0)
    assert c.update(0.0, 0.0, 0.0, 30.0) == U_LIM


def test_signals_published_theta_and_d0_nan():
    c = _pid(P=1000.0, I=10.0, D=5.0, FF2=0.2)
    u = c.update(2e-6, 1e-6, 0.1, 1.0)
    s = c.signals
    assert s.shape == (len(CONTROLLER_SIGNALS),)
    assert s[SIG["e"]] == pytest.approx(1e-6)
    assert s[SIG["x2"]] == pytest.approx(2e-6 / TS)
    assert s[SIG["p"]] == pytest.approx(2e-6 / TS - 0.1)
    assert s[SIG["v"]] == pytest.approx(u)
    for name in THETA_SIGNALS:
        assert math.isnan(s[SIG[name]]), name
    assert c.n_theta == 0 and c.theta_hat.shape == (0,)
    assert np.all(np.isnan(c.theta_vector()))


def test_reset_is_bumpless_and_clears_the_integrator():
    c = _pid(P=1000.0, I=1e5, D=10.0)
    for k in range(20):
        c.update(1e-6 * k, 0.0, 0.0, 0.0)
    assert c.error_i != 0.0
    c.reset(0.3)
    assert c.error_i == 0.0 and not c.saturated
    assert c.update(0.3, 0.3, 0.0, 0.0) == 0.0  # no error, no measured motion → 0 V
    assert c.x2 == 0.0


def test_config_and_registry():
    base = {"theta_min": [0.05, 0.08, 0.05, -0.5, -0.015, -0.002],
            "theta_max": [0.3, 0.5, 0.5, 0.5, 0.0, 0.0],
            "theta_hat0": [0.2, 0.2, 0.1, 0.0, 0.0, 0.0],
            "gamma0": [2.0, 50.0, 100.0, 500.0, 0.05, 0.005], "u_lim": 8.0}
    plain = ControllerConfig.model_validate(base)
    assert "pid" not in configured_controllers(plain)
    with pytest.raises(ValueError, match="pid"):
        PID.from_config(plain, TS)
    sec = ControllerConfig.model_validate({**base, "pid": {"P": 100.0, "maxoutput": 9.0}})
    assert configured_controllers(sec) == ["c1", "c2", "pid"]
    c = make_controller(sec, "pid", TS)
    assert isinstance(c, PID) and c.name == "pid" and c.u_max == 8.0 and c.u_lim == 8.0
    with pytest.raises(ValueError):        # the law's own model checks its own mapping
        ControllerConfig.model_validate({**base, "pid": {"P": -1.0}}).settings("pid")
    with pytest.raises(ValueError):
        ControllerConfig.model_validate({**base, "pid": {"Kp": 1.0}}).settings("pid")
    with pytest.raises(ValueError):
        PID(PidConfig(), 0.0, 10.0)


def test_step_allocates_nothing():
    c = _pid(P=5e4, I=8e6, D=140.0, FF1=0.2, FF2=0.2, maxerror_i=1.2e-7, deadband=1e-7, maxerror=1e-3)
    for k in range(100):
        c.update(1e-6 * k, 0.0, 0.1, 1.0)
    tracemalloc.start()
    before = tracemalloc.take_snapshot()
    for k in range(2000):
        c.update(1e-6 * k, 1.1e-6 * k, 0.1, 1.0)
    after = tracemalloc.take_snapshot()
    tracemalloc.stop()
    grown = sum(s.size_diff for s in after.compare_to(before, "filename") if s.size_diff > 0)
    assert grown < 4096, grown  # 2000 steps would show >= 16 kB at 8 B per step


# ------------------------------------------------------------------ on the simulated gantry
@pytest.fixture(scope="module")
def gantry(gantry_yaml):
    return load_config(gantry_yaml)


def _run(asm, n):
    return run_cycles(asm, n)


def test_gantry_config_configures_pid_from_the_catalogue(gantry):
    from motorctl.cli.run import compared_controllers
    assert compared_controllers(gantry) == ["c1", "c2", "pid"]
    for a in ("X", "Y"):
        sec = gantry.axes[a].controller
        assert sec.settings("pid").FF2 == sec.theta_hat0[0] and sec.settings("pid").FF1 == sec.theta_hat0[1]
        assert sec.settings("pid").bias == -sec.theta_hat0[3]


@pytest.mark.parametrize("axis,bound_um", [("X", 40.0), ("Y", 120.0)])
def test_pid_closes_the_loop_on_the_simulated_gantry(gantry, axis, bound_um):
    n = gantry.timebase.cycles(4.0)             # one period of the program
    asm = build(gantry, [axis], "pid", clock="virtual", capacity=n)
    assert isinstance(asm.loop.controllers[0], PID)
    rows, lay = _run(asm, n)
    assert rows.shape[0] == n
    assert asm.supervisor.reason(0) == ""
    e = rows[:, lay.index(f"{axis}.e")]
    u = rows[:, lay.index(f"{axis}.u")]
    y = rows[:, lay.index(f"{axis}.y")]
    assert np.all(np.isfinite(e)) and np.all(np.isfinite(u))
    assert np.max(np.abs(e)) < bound_um * 1e-6          # measured: X 17.8 um, Y 53 um
    assert np.max(np.abs(u)) <= U_LIM
    assert y.max() == pytest.approx(0.4, abs=1e-4)      # it did the stroke
    for name in THETA_SIGNALS:
        assert np.all(np.isnan(rows[:, lay.index(f"{axis}.{name}")])), name
    assert np.all(np.isfinite(rows[:, lay.index(f"{axis}.p")]))


def test_switch_between_c2_and_pid_through_the_servo_loop(gantry):
    n = gantry.timebase.cycles(6.0)
    k_pid, k_c2 = gantry.timebase.cycles(0.6), gantry.timebase.cycles(3.0)   # mid-move, then at rest
    asm = build(gantry, ["X"], "c2", clock="virtual", capacity=n, all_controllers=True)
    c2, pid = asm.controller(0, "c2"), asm.controller(0, "pid")
    assert asm.loop.controllers[0] is c2

    def on_slack(loop):                         # between cycles, as the daemon does
        if loop.k == k_pid:
            loop.switch_axis(0, pid)
        elif loop.k == k_c2:
            loop.switch_axis(0, c2)

    asm.loop.on_slack = on_slack
    rows, lay = _run(asm, n)
    assert asm.supervisor.reason(0) == ""
    u = rows[:, lay.index("X.u")]
    e = rows[:, lay.index("X.e")]
    th = rows[:, [lay.index(f"X.{name}") for name in THETA_SIGNALS]]
    assert np.all(np.isfinite(u)) and np.all(np.isfinite(e))      # no NaN reaches u
    assert np.max(np.abs(u)) <= U_LIM
    assert np.all(np.isfinite(th[:k_pid]))                         # C2 drives: θ̂, d̂0 recorded
    assert np.all(np.isnan(th[k_pid:k_c2]))                        # PID drives: NaN
    assert np.all(np.isfinite(th[k_c2:]))                          # C2 again
    # bumpless: the output does not step at either switch
    for k in (k_pid, k_c2):
        assert abs(u[k] - u[k - 1]) < 0.5, (k, u[k - 1], u[k])
    assert np.max(np.abs(e)) < 60e-6
    assert asm.loop.controllers[0] is c2
