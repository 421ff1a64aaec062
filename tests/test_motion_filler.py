"""The motion filler (motorctl.app.daemon.motion_side) against its setpoint ring, without the
daemon, on the loop's cycle counter: a Python consumer takes one row a cycle, the filler tops the
ring up every FILL_EVERY_S of cycles, commands land between two cycles. Fast and deterministic."""

from pathlib import Path

import numpy as np
import pytest

from motorctl.app.daemon import motion_side as M
from motorctl.loop.cycle import STREAM
from motorctl.loop.stream import SP_READ, SP_WRITE, SetpointRing

REPO = Path(__file__).resolve().parents[1]
DT = 2e-4
#: configs/gantry.yaml's X and Y
LIMITS = [M.AxisLimits(2.0, 40.0, 4000.0, -0.02, 0.42), M.AxisLimits(1.0, 10.0, 1000.0, -0.02, 0.42)]
VMAX = np.array([lim.v_max for lim in LIMITS])
AMAX = np.array([lim.a_max for lim in LIMITS])
JMAX = np.array([lim.j_max for lim in LIMITS])
EVERY = int(round(M.FILL_EVERY_S / DT))


class Rig:
    """A MotionSide on a process-local ring and a consumer taking a row a cycle."""

    def __init__(self):
        self.ring = SetpointRing(int(0.5 / DT), 2, shared=False)
        self.ms = M.MotionSide(self.ring, lambda: np.zeros(4), ["X.x_d", "X.xd_dot", "Y.x_d", "Y.xd_dot"],
                               ["X", "Y"], LIMITS, lambda: np.array([STREAM, STREAM]), DT)
        self.cycle = 0
        self.rows: list[np.ndarray] = []

    def run(self, cycles: int, until_idle: bool = False) -> None:
        ring = self.ring
        for _ in range(cycles):
            if self.cycle % EVERY == 0:
                self.ms.fill()
            w, r = int(ring.ctl[SP_WRITE]), int(ring.ctl[SP_READ])
            if r < w:
                self.rows.append(ring.rows[r % ring.capacity, 1:].reshape(2, 3).copy())
                ring.ctl[SP_READ] = r + 1
            else:
                assert not self.rows or not np.any(self.rows[-1][:, 1:]), "underrun while moving"
                if until_idle and self.ms.idle():
                    return
            self.cycle += 1

    def setpoints(self) -> np.ndarray:
        """(n, 2 axes, x/v/a)"""
        return np.array(self.rows)


def _within_limits(sp: np.ndarray) -> None:
    assert np.all(np.abs(sp[:, :, 1]) <= VMAX * (1 + 1e-9))
    assert np.all(np.abs(sp[:, :, 2]) <= AMAX * (1 + 1e-6))
    assert np.all(np.abs(np.diff(sp[:, :, 2], axis=0)) / DT <= JMAX * (1 + 1e-6))


def test_override_above_one_keeps_every_axis_limit():
    rig = Rig()
    rig.ms.set_override(M.MAX_OVERRIDE)
    rig.ms.gcode((REPO / "configs/square_and_circle.ngc").read_text(), "square_and_circle.ngc")
    rig.run(200_000, until_idle=True)
    sp = rig.setpoints()
    _within_limits(sp)
    # the override acts where the limits leave room: the F6000 (0.1 m/s) square runs faster
    speed = np.linalg.norm(sp[:, :, 1], axis=1)
    assert speed.max() > 0.14
    np.testing.assert_allclose(sp[-1, :, 0], [0.010, 0.020], atol=1e-9)


def test_override_change_mid_program_keeps_limits():
    rig = Rig()
    rig.ms.gcode((REPO / "configs/square_and_circle.ngc").read_text(), "square_and_circle.ngc")
    for k, r in enumerate([1.5, 0.5, 1.5, 1.0, 1.5, 0.2, 1.5]):
        rig.run(2500)
        rig.ms.set_override(r)
    rig.run(300_000, until_idle=True)
    _within_limits(rig.setpoints())
    np.testing.assert_allclose(rig.rows[-1][:, 0], [0.010, 0.020], atol=1e-9)


@pytest.mark.parametrize("command", ["hold", "abort"])
def test_hold_and_abort_decelerate_within_the_guard(command):
    rig = Rig()
    rig.ms.gcode("G21 G90 G1 X300 F6000\nM2\n", "line.ngc")
    rig.run(5000)                                   # 1 s: cruising at 0.1 m/s, the ring 0.2 s ahead
    assert rig.ring.depth() > 0.15 / DT
    v0 = rig.rows[-1][0, 1]
    assert v0 == pytest.approx(0.1)
    n0 = len(rig.rows)
    getattr(rig.ms, command)()
    rig.run(3000)                                    # the filler wakes at its period (at worst)
    v = np.array([r[0, 1] for r in rig.rows[n0:]])
    first = int(np.argmax(v < v0 * (1 - 1e-9)))
    assert v[first] < v0
    assert first <= EVERY + rig.ms.guard + 1        # the wake, then GUARD_S of rows already taken
    assert v[-1] == 0.0
    _within_limits(rig.setpoints())
    if command == "hold":
        x_hold = rig.rows[-1][0, 0]
        rig.ms.resume()
        rig.run(200_000, until_idle=True)
        assert rig.rows[-1][0, 0] == pytest.approx(0.3, abs=1e-12)
        assert x_hold < 0.3
        _within_limits(rig.setpoints())
    else:
        rig.run(EVERY * 2)
        assert rig.ms.idle() and rig.ms.status()["stopped_because"] == "aborted"
        assert rig.rows[-1][0, 0] < 0.3
