"""Behaviours that used to depend on which of two places built the loop, on hand-counted record
offsets, or on two limits nobody compared (docs/architecture.md). Each test fails on the layout
before it."""

from __future__ import annotations

import math

import numpy as np
import pytest
import yaml

from motorctl.app.build import build
from motorctl.app.job import run_job
from motorctl.config import ConfigError, config_from_dict
from motorctl.loop.records import CONTROLLER_SIGNALS, RecordLayout
from motorctl.loop.trajectory import Move


def _cfg(gantry_yaml, edit=None):
    d = yaml.safe_load(open(gantry_yaml))
    d["loop"]["realtime"]["policy"] = "off"
    if edit:
        edit(d)
    return config_from_dict(d)


@pytest.mark.parametrize("policy,faults", [("ramp", True), ("count", False)])
def test_run_applies_the_configured_overrun_policy(gantry_yaml, monkeypatch, policy, faults):
    """``motorctl run`` builds its loop the same way as the daemon, so ``overrun_policy: ramp``
    turns a missed period into a latched overrun fault (it was silently ignored)."""
    from motorctl_drivers.sim import SimDriver
    calls = {"n": 0}
    write = SimDriver.write

    def stalling_write(self, u, en):
        calls["n"] += 1
        if calls["n"] == 300:          # one stall of 15 periods, well inside the run
            import time
            time.sleep(0.003)
        return write(self, u, en)

    monkeypatch.setattr(SimDriver, "write", stalling_write)
    loaded = _cfg(gantry_yaml, lambda d: d["loop"].update(overrun_policy=policy))
    res = run_job(loaded, axes=["X"], duration_s=0.2, clock="wall", realtime_policy="off")
    assert res.timing["overruns"] >= 1
    fault = res.axes["X"]["fault"]
    assert ("overrun" in fault) == faults, fault


def test_switch_leaves_no_stale_theta_in_the_record(gantry_yaml):
    """After a C2 -> C1 switch on a 1000-row ring, no C1 row holds C2's θ̂5/θ̂6: a signal a
    controller does not have is NaN in the record."""
    loaded = _cfg(gantry_yaml)
    asm = build(loaded, ["X"], clock="virtual", capacity=1000, operated=True, all_controllers=True)
    lp, lay = asm.loop, RecordLayout(["X"])
    y0 = float(asm.driver.position_m[0])
    lp.start_axis(0, Move(y0, y0, 1.0, 10.0, 1000.0), asm.controller(0, "c2"))
    lp.run(1500)
    th5 = lp.rows()[:, lay.index("X.theta_hat5")]
    assert np.isfinite(th5).all() and (th5 != 0.0).any()     # C2 adapts θ̂5
    lp.switch_axis(0, asm.controller(0, "c1"))
    lp.run(2500)                                              # the ring wraps 2.5 times
    rows = lp.rows()
    for j in (5, 6):
        assert np.isnan(rows[:, lay.index(f"X.theta_hat{j}")]).all()
    for j in (1, 2, 3, 4):
        assert np.isfinite(rows[:, lay.index(f"X.theta_hat{j}")]).all()
    # C1 took over C2's θ̂1..θ̂4 at the switch
    assert asm.controller(0, "c1").theta_hat[0] == pytest.approx(rows[0, lay.index("X.theta_hat1")], rel=0.2)


def test_record_layout_is_declared_once_by_name():
    lay = RecordLayout(["X", "Y"])
    assert lay.columns[:1] == ["t"] and len(lay.columns) == len(lay.units) == lay.width
    sig = [lay.index(f"Y.{s}") for s in CONTROLLER_SIGNALS]
    assert sig == list(range(sig[0], sig[0] + len(sig)))     # contiguous block, as the loop copies it
    assert lay.axis_base(1) + lay.axis_field("u") == lay.index("Y.u")
    with pytest.raises(KeyError, match="no column"):
        lay.index("Z.u")


def test_check_config_refuses_u_lim_above_the_drive_full_scale(repo):
    """On a 5 V drive a 10 V u_lim would be clipped by the drive while the log records 10 V."""
    d = yaml.safe_load(open(repo / "configs" / "gantry-serial.yaml"))
    _set_full_scale(d, 5.0)
    with pytest.raises(ConfigError) as exc:
        config_from_dict(d, "serial.yaml")
    assert exc.value.key == "axes.X.controller.u_lim"
    assert "full scale of 5 V" in str(exc.value) and "set u_lim to 5 or less" in str(exc.value)
    for ax in d["axes"].values():
        ax["controller"]["u_lim"] = 5.0
    loaded = config_from_dict(d, "serial.yaml")
    drv = loaded.make_driver()
    vout = {i.name: i for i in drv.command_interfaces("X")}["voltage_out"]
    assert (vout.min, vout.max, vout.unit) == (-5.0, 5.0, "V")


def _set_full_scale(d: dict, volts: float) -> None:
    """The serial driver's full scale, wherever the config keeps it (driver or axis section)."""
    if "voltage_full_scale_V" in d["driver"]:
        d["driver"]["voltage_full_scale_V"] = volts
    for ax in d["axes"].values():
        if "voltage_full_scale_V" in ax.get("driver", {}):
            ax["driver"]["voltage_full_scale_V"] = volts


def test_periods_become_cycles_in_one_place(gantry_yaml):
    loaded = _cfg(gantry_yaml, lambda d: d["daemon"].update(stop_settle_s=0.02))
    asm = build(loaded, ["X"], clock="virtual", capacity=10, operated=True)
    tb = loaded.timebase
    assert asm.loop.stop_settle == tb.cycles(0.02) == 100
    assert asm.loop.overrun_ramp == tb.cycles(loaded.cfg.loop.overrun_ramp_s)
    assert tb.cycles(1e-9, minimum=1) == 1 and math.isclose(tb.seconds(5000), 1.0)
