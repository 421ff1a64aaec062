"""The supervisor and the loop's per-axis sequencing, in-process on the simulated driver with
the virtual clock (deterministic), plus the overrun policy on the wall clock."""

from __future__ import annotations

import time

import numpy as np
import pytest
import yaml

from motorctl.config import config_from_dict
from motorctl.app.build import build
from motorctl.loop.safety import (FAULT_ENCODER_JUMP, FAULT_FOLLOWING_ERROR, FAULT_OVERRUN, FAULT_SOFT_LIMIT,
                                  Supervisor, describe_faults)
from motorctl.loop.servo import APPROACH, HOLD, IDLE, PROGRAM
from motorctl.loop.trajectory import Move


def _loop(gantry_yaml, clock="virtual", policy="count", axes=("X",), edit=None):
    """The daemon's loop (operated axes) built the one way, with the overrun policy, a 5-cycle
    hold, a 50-cycle (10 ms) ramp and a 100-cycle (20 ms) settle."""
    d = yaml.safe_load(open(gantry_yaml))
    d["loop"].update(overrun_policy=policy, overrun_hold_cycles=5, overrun_ramp_s=0.01)
    d["loop"]["realtime"]["spin_us"] = 50
    d["daemon"]["stop_settle_s"] = 0.02
    if edit:
        edit(d)
    ld = config_from_dict(d)
    asm = build(ld, list(axes), clock=clock, capacity=50000, operated=True)
    return ld, asm.driver, asm.supervisor, asm.loop


def _col(lp, name):
    return lp.rows()[:, lp.columns.index(name)]


def test_supervisor_following_error_limit_scales_with_velocity_and_has_a_floor(gantry_yaml):
    ld = config_from_dict(yaml.safe_load(open(gantry_yaml)))
    lim = ld.axes["X"].limits                  # 1 mm at 2 m/s, floor 0.3 mm
    sup = Supervisor([lim], ld.period_s)
    assert sup.check_output(0, 0.00029, 0.0, 1.0)
    assert not sup.check_output(0, 0.00031, 0.0, 1.0)
    sup.reset(0, 0.0, False)
    assert sup.check_output(0, 0.0009, 2.0, 1.0)      # 0.9 mm allowed at 2 m/s
    assert not sup.check_output(0, 0.0006, 1.0, 1.0)  # 0.5 mm at 1 m/s
    assert sup.fault[0] == FAULT_FOLLOWING_ERROR and "following error" in sup.reason(0)


def test_supervisor_encoder_jump_and_reset_refused_while_cause_persists(gantry_yaml):
    ld = config_from_dict(yaml.safe_load(open(gantry_yaml)))
    sup = Supervisor([ld.axes["X"].limits], ld.period_s)
    assert sup.check_input(0, 0.1, False, False)
    # 10 m/s at 5 kHz allows 2 mm per cycle; two lost answers widen it to 6 mm
    assert sup.check_input(0, 0.1019, False, False)
    assert sup.check_input(0, 0.0, True, False) and sup.check_input(0, 0.0, True, False)
    assert sup.check_input(0, 0.1019 + 0.0059, False, False)
    assert not sup.check_input(0, 0.1078 + 0.0021, False, False)
    assert sup.fault[0] == FAULT_ENCODER_JUMP
    assert "limit 0.002" in sup.reason(0)
    assert sup.reset(0, 0.5, False) == (False, sup.reset(0, 0.5, False)[1])
    assert "outside the soft limits" in sup.reset(0, 0.5, False)[1]
    assert "amplifier" in sup.reset(0, 0.1, True)[1]
    assert "not finite" in sup.reset(0, float("nan"), False)[1]
    assert sup.reset(0, 0.1, False) == (True, "")
    assert describe_faults(0) == "none"


def test_the_reading_trips_beyond_the_soft_limits_widened_by_the_following_error_at_rest(gantry_yaml):
    """A commanded target is judged by the soft limits themselves; the reading by the soft limits
    widened by min_following_error_m (a move that ends on a limit settles a count beyond it), and
    the reset by the same window as the trip."""
    ld = config_from_dict(yaml.safe_load(open(gantry_yaml)))
    lim = ld.axes["X"].limits
    lo, tol = lim.soft_min_m, lim.min_following_error_m
    sup = Supervisor([lim], ld.period_s)
    assert not sup.inside(0, lo - 5e-7) and sup.stands_inside(0, lo - 5e-7)
    for y in np.linspace(lo + 1e-3, lo - 0.999 * tol, 50):          # a count, ..., almost tol beyond
        assert sup.check_input(0, float(y), False, False), y
    assert not sup.check_input(0, lo - 1.001 * tol, False, False)
    assert sup.fault[0] == FAULT_SOFT_LIMIT and sup.limit_at_fault[0] == lo - tol
    assert "outside the soft limits" in sup.reset(0, lo - 1.001 * tol, False)[1]
    assert sup.reset(0, lo - 0.5 * tol, False) == (True, "")         # where the trip would not fire
    assert sup.check_input(0, lo - 0.6 * tol, False, False)


def test_axis_starts_disabled_then_bumpless_approach_program_and_stop(gantry_yaml):
    ld, drv, sup, lp = _loop(gantry_yaml)
    lp.run(100)
    assert not _col(lp, "X.enabled").any() and np.all(_col(lp, "X.u") == 0.0)
    # the carriage was moved by hand while disabled: start from where it stands
    drv.inject("push", "X", 50, force_N=400.0)
    lp.run(2000)
    y0 = float(drv.position_m[0])
    assert y0 > 0.002
    tc = ld.axes["X"].trajectory
    k0 = lp.k
    lp.start_axis(0, Move(y0, 0.0, tc.v_max, tc.a_max, tc.j_max))
    assert lp.mode[0] == APPROACH
    lp.run(3000)
    u, e, xd = _col(lp, "X.u"), _col(lp, "X.e"), _col(lp, "X.x_d")
    assert abs(u[k0]) < 0.5, f"first output step {u[k0]:.3f} V"
    assert xd[k0] == pytest.approx(y0) and abs(e[k0]) < 1e-6
    assert np.max(np.abs(np.diff(u[k0:k0 + 50]))) < 1.0, "no kick in the first cycles"
    assert lp.mode[0] == PROGRAM and sup.fault[0] == 0
    # stop in the middle of a move: it finishes the move (jerk-limited), holds, then 0 V
    while True:
        lp.run(1)
        if abs(_col(lp, "X.xd_dot")[-1]) > 1.0:
            break
    k_stop = lp.k
    lp.stop_axis(0)
    lp.run(3000)
    en, vd = _col(lp, "X.enabled"), _col(lp, "X.xd_dot")
    off = k_stop + int(np.flatnonzero(en[k_stop:] == 0)[0])
    assert lp.mode[0] == IDLE and not lp.enabled[0]
    assert (off - k_stop) * lp.period_s < 0.26 + 0.02 + 0.01, "bounded: the move's rest + settle"
    assert np.all(vd[off - 100:off] == 0.0)
    assert np.all(_col(lp, "X.u")[off:] == 0.0) and not drv.amp_enabled[0]


def test_fault_drops_the_operator_request_so_reset_never_moves_the_axis(gantry_yaml):
    ld, drv, sup, lp = _loop(gantry_yaml)
    tc = ld.axes["X"].trajectory
    lp.start_axis(0, Move(float(drv.position_m[0]), 0.0, tc.v_max, tc.a_max, tc.j_max))
    lp.run(500)
    drv.inject("nan", "X", 1)
    lp.run(1)
    assert _col(lp, "X.u")[-1] == 0.0 and _col(lp, "X.enabled")[-1] == 0.0
    assert lp.mode[0] == IDLE and not lp.enabled[0]
    with pytest.raises(RuntimeError, match="in fault"):
        lp.start_axis(0, Move(0.0, 0.0, 1, 1, 1))
    lp.run(10)
    assert lp.fault_reset(0) == (True, "")
    lp.run(100)
    assert not _col(lp, "X.enabled")[-100:].any(), "reset does not re-enable"


def test_overrun_policy_ramp_holds_then_ramps_to_zero_and_latches(gantry_yaml):
    """On the loop's own clock (virtual: no host overrun can come before or between): after
    cycle 199 the wake of cycle 200 is 15 periods late, as the pacer reports it to the loop
    (``ServoLoop._overran(late // period)``, what the wall clock's run calls; the pacer's own
    arithmetic is tests/test_pacing.py's). The policy's rows are then exact: cycle 200 the
    first held, 5 held, 50 ramping, the fault latched at 254."""
    ld, drv, sup, lp = _loop(gantry_yaml, clock="virtual", policy="ramp")
    tc = ld.axes["X"].trajectory
    lp.start_axis(0, Move(float(drv.position_m[0]), 0.0, tc.v_max, tc.a_max, tc.j_max))

    def late_wake(loop):
        if loop.k == 200:
            loop._overran(15)                  # the wake of cycle 200: 15 periods late

    lp.on_slack = late_wake
    lp.run(400)
    assert lp.overruns == 15
    u, en, fb = _col(lp, "X.u"), _col(lp, "X.enabled"), _col(lp, "X.fault_bits")
    ovr = _col(lp, "overruns")
    k = int(np.flatnonzero(ovr > 0)[0])
    assert k == 200 and not fb[:k].any() and u[k - 1] != 0.0
    assert np.all(u[k:k + 5] == u[k - 1]), "hold the last output"
    ramp = u[k + 5:k + 55]
    assert abs(ramp[-1]) <= abs(u[k - 1]) / 50 + 1e-12
    assert np.all(np.abs(np.diff(ramp)) <= abs(u[k - 1]) / 50 + 1e-9), "a linear ramp to 0 V"
    first = int(np.flatnonzero(fb)[0])
    assert int(fb[first]) & FAULT_OVERRUN and u[first] == 0.0 and en[first] == 0.0
    assert first == k + 54, "5 cycles held, 50 ramping (the last one at 0 V)"
    assert "overrun" in sup.reason(0)


def test_overrun_policy_count_only_counts(gantry_yaml):
    ld, drv, sup, lp = _loop(gantry_yaml, clock="wall", policy="count")
    tc = ld.axes["X"].trajectory
    lp.start_axis(0, Move(float(drv.position_m[0]), 0.0, tc.v_max, tc.a_max, tc.j_max))
    lp.on_slack = lambda loop: time.sleep(0.003) if loop.k == 200 else None
    lp.run(400)
    assert lp.overruns >= 1 and sup.fault[0] == 0 and lp.mode[0] in (APPROACH, PROGRAM, HOLD)


def test_run_keeps_the_legacy_behaviour(gantry_yaml):
    """Without the daemon's sequencing every axis follows its program from t = 0."""
    d = yaml.safe_load(open(gantry_yaml))
    ld = config_from_dict(d)
    lp = build(ld, ["X"], clock="virtual", capacity=5000).loop
    assert lp.run(5000) == 5000
    assert _col(lp, "X.enabled").all()
    assert _col(lp, "X.x_d")[-1] == pytest.approx(ld.axes["X"].trajectory.program().sample(4999 * ld.period_s)[0])
