"""An axis driven outside its soft limits is brought back by a jog at reduced speed, without a
restart: the latch is cleared only for the way back in (moving further out trips again)."""

from __future__ import annotations

import yaml

from motorctl.app.build import build
from motorctl.config import config_from_dict
from motorctl.loop.safety import FAULT_NAN, FAULT_SOFT_LIMIT, RECOVERY_MARGIN_M
from motorctl.loop.servo import IDLE, JOG
from motorctl.loop.trajectory import Move


def _asm(gantry_yaml):
    d = yaml.safe_load(open(gantry_yaml))
    x = d["axes"]["X"]
    x["driver"]["offset_N"] = 0.0
    x["trajectory"] = {"points": [0.0]}
    x["limits"].update(soft_min_m=-0.0005, min_following_error_m=0.002, following_error_m=0.004)
    d["daemon"]["stop_settle_s"] = 0.02
    asm = build(config_from_dict(d), ["X"], clock="virtual", capacity=20000, operated=True)
    return asm, asm.loop, asm.supervisor, asm.driver


def _outside(gantry_yaml):
    asm, lp, sup, drv = _asm(gantry_yaml)
    y0 = float(drv.position_m[0])
    lp.start_axis(0, Move(y0, 0.0, 1.0, 10.0, 1000.0))
    lp.run(500)
    drv.inject("push", "X", cycles=30, force_N=-2000.0)     # shoved past the soft minimum
    lp.run(1500)
    assert sup.fault[0] & FAULT_SOFT_LIMIT and lp.mode[0] == IDLE
    for _ in range(20):                                        # coasts to a standstill (bounded)
        y_before = float(drv.position_m[0])
        lp.run(1000)
        if abs(float(drv.position_m[0]) - y_before) < 2e-6:
            break
    y = float(drv.position_m[0])
    assert y < -0.0005
    return asm, lp, sup, drv, y


def test_jog_brings_an_axis_back_inside_its_soft_limits(gantry_yaml):
    asm, lp, sup, drv, y = _outside(gantry_yaml)
    ok, why = lp.fault_reset(0)
    assert not ok and "outside the soft limits" in why          # the plain reset is refused
    ok, why = sup.begin_recovery(0, y, 0.0, bool(drv.amp_fault[0]))
    assert ok, why
    tc = asm.loaded.axes["X"].trajectory
    lp.jog_axis(0, Move(y, 0.0, 0.1 * tc.v_max, 0.1 * tc.a_max, tc.j_max))
    assert lp.mode[0] == JOG
    lp.run(int(3.0 / lp.period_s))
    assert sup.fault[0] == 0, sup.reason(0)
    assert lp.mode[0] == IDLE and abs(float(drv.position_m[0])) < 1e-4
    # inside again: a normal start works
    y1 = float(drv.position_m[0])
    lp.start_axis(0, Move(y1, 0.0, 1.0, 10.0, 1000.0))
    lp.run(500)
    assert sup.fault[0] == 0


def test_recovery_refuses_a_target_outside_and_trips_when_moving_further_out(gantry_yaml):
    asm, lp, sup, drv, y = _outside(gantry_yaml)
    ok, why = sup.begin_recovery(0, y, -0.01, False)
    assert not ok and "outside the soft limits" in why
    ok, _ = sup.begin_recovery(0, y, 0.0, False)
    assert ok
    # a jog outwards instead of in: trips the soft limit again once past the margin
    tc = asm.loaded.axes["X"].trajectory
    lp.jog_axis(0, Move(y, y - 0.005, 0.1 * tc.v_max, 0.1 * tc.a_max, tc.j_max))
    lp.run(int(2.0 / lp.period_s))
    assert sup.fault[0] & FAULT_SOFT_LIMIT
    assert sup.value_at_fault[0] < y - RECOVERY_MARGIN_M + 1e-6


def test_recovery_clears_what_latched_with_the_soft_limit(gantry_yaml):
    """A NaN reading latched too (as when a NaN fault stops an axis at speed and it coasts out):
    the plain reset waits for the axis to be inside, so the recovery must not wait for the
    reset; it judges the other faults as the reset does (the reading is finite again)."""
    asm, lp, sup, drv, y = _outside(gantry_yaml)
    drv.inject("nan", "X", cycles=3)
    lp.run(10)
    assert sup.fault[0] & FAULT_NAN and sup.fault[0] & FAULT_SOFT_LIMIT, sup.reason(0)
    ok, why = lp.fault_reset(0)
    assert not ok and "outside the soft limits" in why
    y = float(drv.position_m[0])
    ok, why = sup.begin_recovery(0, y, 0.0, bool(drv.amp_fault[0]))
    assert ok, why
    tc = asm.loaded.axes["X"].trajectory
    lp.jog_axis(0, Move(y, 0.0, 0.1 * tc.v_max, 0.1 * tc.a_max, tc.j_max))
    lp.run(int(3.0 / lp.period_s))
    assert sup.fault[0] == 0 and abs(float(drv.position_m[0])) < 1e-4, sup.reason(0)
