"""The motion filler (motorctl.app.daemon.motion_side) against its setpoint ring, without the
daemon, on the loop's cycle counter: a Python consumer takes one row a cycle, the filler tops the
ring up every FILL_EVERY_S of cycles, commands land between two cycles. Fast and deterministic."""

from pathlib import Path

import numpy as np
import pytest

from motorctl.app.daemon import motion_side as M
from motorctl.loop.cycle import STREAM
from motorctl.loop.stream import SP_READ, SP_WRITE, SetpointRing
from motorctl.motion import GcodeSettings
from motorctl.motion.gcode import output_names

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

    def __init__(self, settings=None):
        outs, stop = output_names(settings) if settings is not None else ([], [])
        self.ring = SetpointRing(int(0.5 / DT), 2, shared=False, outputs=outs, stop_outputs=stop)
        self.ms = M.MotionSide(self.ring, lambda: np.zeros(4), ["X.x_d", "X.xd_dot", "Y.x_d", "Y.xd_dot"],
                               ["X", "Y"], LIMITS, lambda: np.array([STREAM, STREAM]), DT,
                               gcode_settings=settings, lead_s=0.5)
        self.cycle = 0
        self.rows: list[np.ndarray] = []
        self.outs: list[np.ndarray] = []     # the outputs each row taken carries

    def run(self, cycles: int, until_idle: bool = False) -> None:
        """``cycles`` cycles of the loop: the filler tops the ring up at every EVERY-th cycle; each
        cycle the machine words whose row was taken are noted (``issue_events``), then one row is
        taken if the ring holds one (an empty ring while the last row moved: an underrun; empty
        and the side idle with ``until_idle``: the run ends in that cycle). Between two fills
        nothing writes the ring, so the cycles up to the next fill are taken as one block: the same
        rows, outputs and events, cycle for cycle, as one cycle at a time (the events noted once
        at the block's last cycle see the rows taken before it, as that cycle's call does)."""
        ring = self.ring
        end = self.cycle + cycles
        while self.cycle < end:
            if self.cycle % EVERY == 0:
                self.ms.fill()
            m = min(end, (self.cycle // EVERY + 1) * EVERY) - self.cycle     # cycles up to the next fill
            w, r = int(ring.ctl[SP_WRITE]), int(ring.ctl[SP_READ])
            n = min(w - r, m)                       # the cycles that take a row
            if n:
                idx = np.arange(r, r + n) % ring.capacity
                self.rows.extend(ring.rows[idx, 1:ring.out0].reshape(n, ring.n_axes, 3))
                self.outs.extend(ring.rows[idx, ring.out0:].copy())
                ring.ctl[SP_READ] = r + n - 1
                self.ms.issue_events()              # (the last cycle's call: the rows before it taken)
                ring.ctl[SP_READ] = r + n
            if n < m:                               # the ring ran dry at cycle self.cycle + n
                self.ms.issue_events()
                assert not self.rows or not np.any(self.rows[-1][:, 1:]), "underrun while moving"
                if until_idle and self.ms.idle():   # (nothing the side decides on changes before the next fill)
                    self.cycle += n
                    return
            self.cycle += m

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


CAM = REPO / "configs/cam_sample.ngc"


def test_machine_words_switch_outputs_at_their_planned_rows():
    rig = Rig(GcodeSettings(axes=["X", "Y"], words={"M3": "torch", "M5": "torch", "S": "ignore"}))
    info = rig.ms.gcode(CAM.read_text(), "cam_sample.ngc")
    assert any("S4500 ignored" in w for w in info["warnings"])
    rig.run(2_000_000, until_idle=True)
    log = rig.ms.output_log
    n_on = CAM.read_text().count("M03")
    assert [v for _, _, v, _ in log] == [1.0, 0.0] * n_on
    rows, torch = rig.setpoints(), np.array(rig.outs)[:, 0]
    # the rows carry the output: it switches exactly at the rows of the log, nowhere else
    assert np.flatnonzero(np.diff(torch)).tolist() == [row - 1 for row, _, _, _ in log]
    for row, _, value, x in log:          # each at its row: at rest on the pierce / end point
        assert np.all(np.abs(rows[row, :, 1]) < 1e-12) and torch[row] == value
        np.testing.assert_array_equal(rows[row, :, 0], x)
    assert np.allclose(log[0][3], [0.035, 0.050], atol=1e-9)   # N70 G00 X35 Y50, then N80 M03


def test_unmapped_machine_word_refused_before_anything_moves():
    rig = Rig(GcodeSettings(axes=["X", "Y"], words={"M3": "torch"}))
    with pytest.raises(M.MotionError, match=r"cam_sample.ngc:13:\d+: .*gcode.words.S"):
        rig.ms.gcode(CAM.read_text(), "cam_sample.ngc")
    assert rig.ms.idle() and rig.ring.written() == 0


def test_progress_is_the_loops_row_not_the_fillers():
    rig = Rig()
    info = rig.ms.gcode((REPO / "configs/square_and_circle.ngc").read_text(), "square_and_circle.ngc")
    rig.run(10_000)                                  # 2.0 s of rows taken; the filler is ~0.2 s ahead
    st = rig.ms.status()
    assert st["time_left_s"] == pytest.approx(info["duration_s"] - 10_000 * DT, abs=1e-6)
    assert st["done"] == pytest.approx(10_000 * DT / info["duration_s"], abs=1e-9)
    assert st["line"] == 7                           # G1 X110 Y120 (after the rapid and 100 mm at 0.1 m/s)
    rig.ms.set_override(0.5)
    rig.run(1000)
    assert rig.ms.status()["time_left_s"] > 2 * (info["duration_s"] - 2.2)
    rig.run(300_000, until_idle=True)
    assert rig.ms.progress() == (0, 1.0, 0.0)


def test_program_outside_the_stroke_with_the_active_work_offset_refused_before_motion():
    rig = Rig()
    rig.ms.gcode("G21 G90\nG10 L2 P1 X100 (G54 origin at X 100 mm)\nG0 X10 Y10\nM2\n", "set.ngc")
    rig.run(100_000, until_idle=True)
    np.testing.assert_allclose(rig.rows[-1][:, 0], [0.110, 0.010], atol=1e-12)
    written = rig.ring.written()
    # the G54 offset stays active: X350 is machine 450 mm, 30 mm beyond soft_max 420 mm
    with pytest.raises(M.MotionError, match=r"cut.ngc:3: X reaches 450.0000 mm, 30.0000 mm beyond soft_max"):
        rig.ms.gcode("G21 G90\nG0 X10 Y10\nG1 X350 F3000\nG1 X500\nM2\n", "cut.ngc")
    rig.run(1000)
    assert rig.ring.written() == written and rig.ms.idle()


def test_abort_stops_a_move_that_is_wholly_in_the_ring_already():
    """A move shorter than the lead is in the ring before the abort comes: the abort rewrites the
    ring (it does not take the empty queue for 'nothing runs') and the axis stops short."""
    rig = Rig()
    rig.ms.move({0: 0.010}, feed=0.05)              # 0.2 s + ramps, within the 0.5 s lead
    rig.run(2 * EVERY)
    assert rig.ms.cur is None and not rig.ms.queue and rig.ring.depth() > 0
    rig.ms.abort()
    rig.run(20_000, until_idle=True)
    sp = rig.setpoints()
    assert rig.ms.status()["stopped_because"] == "aborted" and not rig.ms.status()["aborting"]
    assert 0.0 < sp[-1, 0, 0] < 0.008 and np.all(sp[-1, :, 1:] == 0.0)
    _within_limits(sp)


def test_abort_switches_the_torch_off_at_once_and_a_hold_keeps_it_on():
    """LinuxCNC's behaviour: a feed hold keeps the torch (M3) on; an abort switches it off at the
    first row it rewrites, while the axes still decelerate."""
    rig = Rig(GcodeSettings(axes=["X", "Y"], words={"M3": "torch", "M5": "torch"}))
    rig.ms.gcode("G21 G90\nM3\nG1 X100 F3000\nM5\nM2\n", "cut.ngc")
    rig.run(3000)                                   # 0.6 s: cutting at 50 mm/s
    rig.ms.hold()
    rig.run(5000)
    torch = np.array(rig.outs)[:, 0]
    assert rig.setpoints()[-1, 0, 1] == 0.0 and torch[-1] == 1.0      # held at rest, torch on
    rig.ms.resume()
    rig.run(1000)
    n0 = len(rig.rows)
    rig.ms.abort()
    rig.run(20_000, until_idle=True)
    sp, torch = rig.setpoints(), np.array(rig.outs)[:, 0]
    off = n0 + int(np.flatnonzero(torch[n0:] == 0.0)[0])     # the row the torch goes off
    assert np.all(torch[off:] == 0.0) and np.all(torch[n0:off] == 1.0)
    assert off - n0 <= rig.ms.guard + 1                      # within the guard of the abort
    assert abs(sp[off, 0, 1]) > 0.01                          # the axis still moving then
    assert rig.ms.status()["stopped_because"] == "aborted" and sp[-1, 0, 0] < 0.1


def test_a_digital_output_the_ring_does_not_carry_is_refused_before_motion():
    rig = Rig(GcodeSettings(axes=["X", "Y"], words={"M62": "dout", "M63": "dout"}))
    assert rig.ring.outputs == ("dout0", "dout1", "dout2", "dout3")
    with pytest.raises(M.MotionError, match=r"cut.ngc:2:\d+: M62: output dout7 is not one the loop carries"):
        rig.ms.gcode("G21 G90 G64 P0.01\nG1 X10 F600 M62 P7\nM2\n", "cut.ngc")
    assert rig.ms.idle() and rig.ring.written() == 0


@pytest.mark.parametrize("f0, f1", [(0.5, 1.5), (1.5, 1.5), (0.5, 0.5)])
def test_rows_off_the_grid_are_the_path_at_their_own_times(f0, f1):
    """Rows whose path times are not on the planner's grid (a feed-override ramp: s advances by
    f·Ts, f changing; or a steady override other than 1) are sampled on the path's own grid and
    interpolated (MotionSide._sample): x within 1 nm, ẋ within 1 µm/s and ẍ within 2 mm/s² of
    the path sampled at each row's own time. (Sampled off the grid, a block of 625 such rows
    took 40-80 ms on arcs and overrides flipped 0.5/1.5 ran the stream dry in the daemon.)"""
    rig = Rig()
    rig.ms.gcode((REPO / "configs/square_and_circle.ngc").read_text(), "square_and_circle.ngc")
    traj = rig.ms.queue[0]
    s = traj.duration - 1.5 + np.cumsum(np.linspace(f0, f1, 625) * DT)   # on the circle
    rows = np.empty((s.size, 2, 3))
    rig.ms._sample(traj, s, rows, f0 * DT if f0 == f1 else 0.0)
    exact = np.empty((s.size, 3, 2))
    for k, t in enumerate(s):
        traj.sample_into(float(t), 1.0, exact[k:k + 1])
    exact = exact.transpose(0, 2, 1)
    assert np.max(np.abs(rows[:, :, 0] - exact[:, :, 0])) < 1e-9
    assert np.max(np.abs(rows[:, :, 1] - exact[:, :, 1])) < 1e-6
    assert np.max(np.abs(rows[:, :, 2] - exact[:, :, 2])) < 2e-3


def _ramp_rows_reference(f, fd, s, holding, override, cap, cap_dt, lo, hi, pauses, duration, n):
    """The feed scale's rows as the filler made them in Python, one row at a time (the rule of
    MotionSide._target and _ramp, uncompiled)."""
    rows = []
    while len(rows) < n:
        if f == 0.0 and fd == 0.0 and holding:
            break
        target = 0.0 if holding else override
        if target > 1.0:
            target = min(target, max(1.0, float(cap[min(int(s / cap_dt), len(cap) - 1)])))
        if rows and f == target and fd == 0.0 and target > 0.0:
            break
        f, fd = M._ramp.py_func(f, fd, target, *(hi if target > 1.0 or f > 1.0 else lo), DT)
        s_new = s + f * DT
        for t in pauses:
            if s < t <= s_new:
                s_new, f, fd, holding = t, 0.0, 0.0, True
                break
        s = s_new
        rows.append((s, f, fd))
        if s >= duration:
            break
    return np.array(rows), (f, fd, s, holding)


@pytest.mark.parametrize("start, holding, override, pauses", [
    ((1.0, 0.0, 0.2), False, 2.0, []),            # up past 1 to the cap of its bins, 1.6
    ((2.0, 0.0, 0.2), False, 0.4, []),            # down from above 1 at the high rate, below at the low
    ((1.0, 0.0, 0.2), True, 1.0, []),             # a hold: to rest
    ((0.5, 0.0, 0.2), False, 1.0, [0.3, 0.5]),    # a programmed pause on the way: at rest there
])
def test_the_ramps_compiled_rows_are_the_rules(start, holding, override, pauses):
    """_ramp_rows (the filler's compiled ramp) row for row the rule written out in Python: the
    override's cap per bin, the high rate above 1, a hold to rest, a pause ending a row at it."""
    cap = np.array([3.0, 3.0, 1.6, 1.6, 1.6, 1.6])
    lo, hi = (1.0, 4.0), (0.5, 2.0)
    want, end = _ramp_rows_reference(*start, holding, override, cap, 0.1, lo, hi, pauses, 0.6, 4000)
    ss, ff, ffd = np.zeros(4000), np.zeros(4000), np.zeros(4000)
    m, f, fd, s, hold, paused, ended, settled = M._ramp_rows(
        *start, holding, override, cap, 0.1, *lo, *hi, DT, np.array(pauses, dtype=float), 0.6, ss, ff, ffd, 0, 4000,
        True)
    assert m == len(want) > 10
    assert np.array_equal(np.column_stack([ss[:m], ff[:m], ffd[:m]]), want)
    assert (f, fd, s, hold) == end
    assert paused == bool(pauses) and hold == (holding or bool(pauses))
    assert settled == (not hold and not ended)
