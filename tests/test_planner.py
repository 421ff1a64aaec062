"""The path planner and point-to-point moves (motorctl.motion.planner): every axis within its
v/a/j limits, the end at the program's end point, corners within the G64 tolerance, soft limits
checked before anything is planned."""

import numpy as np
import pytest
from conftest import REPO, examples
from hypothesis import given, settings
from hypothesis import strategies as st

from motorctl.motion import (AxisLimits, GcodeSettings, LimitError, check_limits, contour_error, headroom, parse,
                             plan, point_to_point)
from motorctl.motion.planner import EXACT_ARC_TOL_M, PERIOD_S

#: configs/gantry.yaml's X and Y
LIMITS = [AxisLimits(2.0, 40.0, 4000.0), AxisLimits(1.0, 10.0, 1000.0)]
XY = GcodeSettings(axes=["X", "Y"], words={"M3": "torch", "M5": "torch", "M62": "dout", "S": "ignore"})
H = PERIOD_S


def _run(tr):
    """All setpoints of a trajectory on the loop's grid, one period past its end: (n, 3, n_axes)."""
    n = int(np.ceil(tr.duration / H)) + 2
    out = np.empty((n, 3, len(tr.axes)))
    tr.sample_into(0.0, H, out)
    return out


def _assert_within_limits(out, limits=LIMITS):
    v = np.array([lim.v_max for lim in limits])
    a = np.array([lim.a_max for lim in limits])
    j = np.array([lim.j_max for lim in limits])
    assert np.all(np.abs(out[:, 1]) <= v * (1 + 1e-9))
    assert np.all(np.abs(out[:, 2]) <= a * (1 + 1e-9))
    assert np.all(np.abs(np.diff(out[:, 2], axis=0)) / H <= j * (1 + 1e-6))
    # the setpoints are one motion: position changes as the velocity says (to the grid's order)
    dx = np.diff(out[:, 0], axis=0) / H
    assert np.all(np.abs(dx - 0.5 * (out[1:, 1] + out[:-1, 1])) <= 0.5 * a * H + 1e-9)


def _program(points, feed_mm_min, tol_mm, arcs):
    mode = "G61" if tol_mm == 0 else "G64" if tol_mm is None else f"G64 P{tol_mm}"
    lines = ["G21 G90 G17", mode, f"G1 F{feed_mm_min}"]
    for k, (x, y) in enumerate(points):
        if arcs[k % len(arcs)] and k and np.hypot(x - points[k - 1][0], y - points[k - 1][1]) > 1.0:
            px, py = points[k - 1]
            lines.append(f"G{2 + k % 2} X{x:.3f} Y{y:.3f} R{np.hypot(x - px, y - py):.4f}")
        else:
            lines.append(f"G1 X{x:.3f} Y{y:.3f}")
    return "\n".join(lines) + "\nM2\n"


coords = st.tuples(st.floats(0, 60), st.floats(0, 60)).filter(lambda p: p[0] > 1e-3)


@settings(max_examples=examples(30), deadline=None)
@given(points=st.lists(coords, min_size=2, max_size=6), feed=st.sampled_from([600, 3000, 6000, 12000, 60000]),
       tol=st.sampled_from([0, 0.005, 0.01, 0.1, 1.0, None]), arcs=st.lists(st.booleans(), min_size=1, max_size=3))
def test_planned_programs_keep_limits_end_point_and_tolerance(points, feed, tol, arcs):
    pts = [(round(x, 3), round(y, 3)) for x, y in points]
    prog = parse(_program(pts, feed, tol, arcs), "p.ngc", XY)
    tr = plan(prog, ["X", "Y"], LIMITS)
    out = _run(tr)
    _assert_within_limits(out)
    np.testing.assert_array_equal(out[-1, 0], prog.end[:2])
    np.testing.assert_array_equal(out[-1, 1:], 0.0)
    x, _, _ = tr.sample(tr.duration)
    np.testing.assert_array_equal(x, prog.end[:2])
    # G64 without P and G61: the path exactly (arcs within EXACT_ARC_TOL_M of 1 µm), corners stop
    dev = contour_error(prog, out[:, 0])
    assert dev.max() <= (tol * 1e-3 if tol else EXACT_ARC_TOL_M) + 1e-9


def test_square_and_circle_ends_at_its_last_point_within_the_tolerance():
    text = (REPO / "configs" / "square_and_circle.ngc").read_text()
    prog = parse(text, "square_and_circle.ngc", XY)
    tr = plan(prog, ["X", "Y"], LIMITS, start=[0.0, 0.0])
    out = _run(tr)
    _assert_within_limits(out)
    np.testing.assert_array_equal(out[-1, 0], [0.010, 0.020])
    moving = tr.line_at(0.0) == 0 and [tr.line_at(t) for t in np.arange(0, tr.duration, 0.05)]
    assert sorted(set(moving) - {0}) == [5, 6, 7, 8, 9, 10, 11, 12]   # every move, in order
    assert moving == sorted(moving)
    first = int(1.0 / H)   # the square and the circle (after the first rapid from 0, 0)
    assert contour_error(prog, out[first:, 0]).max() <= 1e-5
    assert tr.duration < 12.0


def test_feed_scale_and_rapids_use_the_axis_limits():
    prog = parse("G21 G90 G61 G1 X400 F3000\nG0 X0\n", "p.ngc", XY)
    slow, fast = plan(prog, ["X", "Y"], LIMITS), plan(prog, ["X", "Y"], LIMITS, feed_scale=1.5)
    assert np.abs(_run(slow)[:, 1, 0]).max() == pytest.approx(2.0)       # G0 at X's v_max
    t_feed = [tr.duration for tr in (slow, fast)]
    assert t_feed[1] < t_feed[0]
    cut = _run(plan(parse("G21 G1 X100 F3000\n", "p.ngc", XY), ["X", "Y"], LIMITS, feed_scale=1.5))
    assert np.abs(cut[:, 1, 0]).max() == pytest.approx(0.075)


def test_headroom_keeps_the_limits_at_a_faster_time_scale():
    prog = parse("G21 G90 G64 P0.01\nG1 X100 Y50 F60000\nG2 X150 Y50 R25\nG0 X0 Y0\n", "p.ngc", XY)
    tr = plan(prog, ["X", "Y"], headroom(LIMITS, 1.5))
    out = _run(tr)                 # run 1.5 times faster: each period lasts H/1.5 of real time
    r = 1.5
    for i, lim in enumerate(LIMITS):
        assert np.abs(out[:, 1, i]).max() * r <= lim.v_max * (1 + 1e-9)
        assert np.abs(out[:, 2, i]).max() * r**2 <= lim.a_max * (1 + 1e-9)
        assert (np.abs(np.diff(out[:, 2, i])) * r**2 / (H / r)).max() <= lim.j_max * (1 + 1e-6)
        assert np.abs(out[:, 1, i]).max() * r > 0.5 * lim.v_max       # and not needlessly slow
    with pytest.raises(ValueError, match="speedup"):
        headroom(LIMITS, 0.5)


def test_events_and_pauses_happen_at_their_path_points():
    prog = parse("G21 G90 G64 P0.01\nG1 X50 F6000\nM62 P1\nG1 X100\nM3\nG4 P0.5\nG1 Y50\nM0\nG1 X0\nM5\nM2\n",
                 "p.ngc", XY)
    tr = plan(prog, ["X", "Y"], LIMITS)
    (t62, e62), (t3, e3), (t5, e5) = tr.events
    assert (e62.word, e3.word, e5.word) == ("M62", "M3", "M5")
    x, v, _ = tr.sample(t62)
    assert abs(x[0] - 0.050) < 0.1e-3 and v[0] > 0.09                 # on the fly, at X50
    x, v, _ = tr.sample(t3)
    np.testing.assert_allclose(x, [0.1, 0.0], atol=1e-12)
    np.testing.assert_array_equal(v, 0.0)                             # M3 once the axes stand
    x, _, _ = tr.sample(t3 + 0.5)
    np.testing.assert_allclose(x, [0.1, 0.0], atol=1e-12)             # the dwell
    ((ts, pause),) = tr.stops
    assert pause.line == 8
    x, v, a = tr.sample(ts)
    np.testing.assert_allclose(x, [0.1, 0.05], atol=1e-12)
    np.testing.assert_allclose(np.concatenate([v, a]), 0.0, atol=1e-12)
    assert tr.line_at(ts + 0.1) == 9 and t5 <= tr.duration


def test_sample_and_sample_into_agree():
    prog = parse("G21 G90 G64 P0.1\nG1 X50 Y20 F6000\nG3 X70 Y40 R20\n", "p.ngc", XY)
    tr = plan(prog, ["X", "Y"], LIMITS)
    grid = np.empty((600, 3, 2))
    tr.sample_into(0.1, H, grid)
    for k in (0, 17, 255, 256, 599):                   # on the grid: the same setpoints
        np.testing.assert_allclose(np.array(tr.sample(0.1 + k * H)), grid[k], rtol=0, atol=1e-9)
    off = np.empty((40, 3, 2))
    tr.sample_into(0.3, 0.0123, off)                   # off the grid: the filters anchored at t
    for k in (0, 17, 39):
        x, v, a = tr.sample(0.3 + k * 0.0123)          # interpolated between grid points
        np.testing.assert_allclose(x, off[k, 0], rtol=0, atol=1e-6)
        np.testing.assert_allclose(v, off[k, 1], rtol=0, atol=1e-3)
        np.testing.assert_allclose(a, off[k, 2], rtol=0, atol=LIMITS[0].j_max * H)


def test_axes_not_on_the_machine_are_refused():
    prog = parse("G21 G1 Z5 F100\n", "p.ngc", GcodeSettings())
    with pytest.raises(ValueError, match="p.ngc:1: the program moves Z"):
        plan(prog, ["X", "Y"], LIMITS)


@settings(max_examples=examples(25), deadline=None)
@given(start=st.tuples(st.floats(-0.02, 0.42), st.floats(-0.02, 0.42)),
       goal=st.tuples(st.floats(-0.02, 0.42), st.floats(-0.02, 0.42)),
       feed=st.one_of(st.none(), st.floats(0.01, 3.0)))
def test_point_to_point_is_a_straight_synchronised_move_within_limits(start, goal, feed):
    tr = point_to_point(start, goal, LIMITS, feed=feed, axes=["X", "Y"])
    out = _run(tr)
    _assert_within_limits(out)
    np.testing.assert_array_equal(out[-1, 0], goal)
    d = np.subtract(goal, start)
    if np.linalg.norm(d) > 1e-6:
        u = d / np.linalg.norm(d)
        rel = out[:, 0] - start
        off = rel - np.outer(rel @ u, u)
        assert np.abs(off).max() < 1e-9 + 1e-6 * np.linalg.norm(d)     # on the line
        moving = np.linalg.norm(out[:, 1], axis=1) > 1e-9
        if feed is not None:
            assert np.linalg.norm(out[:, 1], axis=1).max() <= feed * (1 + 1e-6)
        # both axes arrive together: each stops moving in the last period
        for i in range(2):
            if abs(d[i]) > 1e-6:
                last = np.nonzero(np.abs(out[:, 1, i]) > 1e-12)[0][-1]
                assert last >= np.nonzero(moving)[0][-1] - 1


def test_a_new_target_in_mid_move_stays_within_limits():
    first = point_to_point([0.0, 0.0], [0.3, 0.2], LIMITS)
    x, v, a = first.sample(0.2)
    second = point_to_point(x, [0.05, 0.3], LIMITS, velocity=v, acceleration=a)
    out = _run(second)
    _assert_within_limits(out)
    np.testing.assert_allclose(out[0, 1], v, atol=1e-9)               # no step in velocity
    np.testing.assert_array_equal(out[-1, 0], [0.05, 0.3])


def test_check_limits_names_the_first_offending_line_and_how_far():
    soft = {"X": (-0.02, 0.42), "Y": (-0.02, 0.42)}
    ok = parse((REPO / "configs" / "cam_sample.ngc").read_text(), "cam_sample.ngc",
               GcodeSettings(axes=["X", "Y"], words={"M3": "torch", "M5": "torch", "S": "ignore"}))
    check_limits(ok, soft)
    with pytest.raises(LimitError) as e:
        check_limits(ok, soft, offsets={"X": 0.1})        # the same program moved 100 mm in X
    assert e.value.axis == "X" and e.value.line > 0
    assert e.value.excess_m == pytest.approx(max(s.end[0] for s in ok.moves) + 0.1 - 0.42, abs=0.05)
    assert str(e.value).startswith(f"cam_sample.ngc:{e.value.line}: X reaches")
    check_limits(parse("G21 G90 G0 X400 Y100\nG3 X400 Y140 I0 J20 F600\n", "b.ngc", XY), soft)  # X420: on it
    with pytest.raises(LimitError) as e:                  # the arc's side at X425, not its ends
        check_limits(parse("G21 G90 G0 X405 Y100\nG3 X405 Y140 I0 J20 F600\n", "b.ngc", XY), soft)
    assert (e.value.line, e.value.axis) == (2, "X") and e.value.excess_m == pytest.approx(0.005)
    check_limits(parse("G21 G90 G0 X405 Y100\nG2 X405 Y140 I0 J20 F600\n", "b.ngc", XY), soft)  # CW: X385


def test_the_cam_program_plans_within_limits_and_tolerance():
    prog = parse((REPO / "configs" / "cam_sample.ngc").read_text(), "cam_sample.ngc",
                 GcodeSettings(axes=["X", "Y"], words={"M3": "torch", "M5": "torch", "S": "ignore"}))
    tr = plan(prog, ["X", "Y"], LIMITS)
    out = _run(tr)
    _assert_within_limits(out)
    np.testing.assert_array_equal(out[-1, 0], prog.end[:2])
    assert contour_error(prog, out[::40, 0]).max() <= 1e-5 + 1e-9     # every 8 ms of a 99 s program
    torch = [(t, e.value) for t, e in tr.events if e.output == "torch"]
    assert [v for _, v in torch] == [1.0, 0.0] * (len(torch) // 2)


def test_a_2mm_arc_at_f5000_enters_at_the_speed_its_curvature_step_allows_within_the_tolerance():
    """A 2 mm lead-in arc between two lines at F5000, G64 P0.01: the setpoints follow the path
    (the filters' shrink of the arc compensated), the curvature step 1/R where the arc meets a
    line is passed at √(JERK_STEP·j_max·T2·R) (44.7 mm/s on Y's 1000 m/s³) or faster; every axis
    within its limits, every setpoint within P of the programmed path."""
    prog = parse("G21 G90 G64 P0.01\nG0 X0 Y0\nG1 X10 Y0 F5000\nG3 X12 Y2 I0 J2\nG1 X12 Y10\nM2\n", "a.ngc", XY)
    out = _run(plan(prog, ["X", "Y"], LIMITS))
    _assert_within_limits(out)
    assert contour_error(prog, out[:, 0]).max() <= 1e-5
    rel = out[:, 0] - [0.010, 0.002]                                # about the arc's centre
    on = (rel[:, 0] > 0) & (rel[:, 1] < 0)                          # the setpoints in the arc's quadrant
    speed = np.hypot(out[on, 1, 0], out[on, 1, 1])
    assert on.sum() > 50 and speed.min() >= 0.0447


def _polygon(radius_mm, chord_mm, feed, mode="G64 P0.01"):
    """A closed polygon of equal chords about (60, 60) mm, entered on a line from its centre."""
    n = int(round(2 * np.pi * radius_mm / chord_mm))
    pts = [(60 + radius_mm * np.cos(2 * np.pi * k / n), 60 + radius_mm * np.sin(2 * np.pi * k / n)) for k in range(n + 1)]
    body = "".join(f"G1 X{x:.4f} Y{y:.4f}\n" for x, y in pts[1:])
    return f"G21 G90 {mode}\nG0 X60 Y60\nG1 X{pts[0][0]:.4f} Y{pts[0][1]:.4f} F{feed}\n{body}M2\n", n


def test_short_chords_are_blended_within_the_tolerance_at_the_feed():
    """0.5 mm chords turning 8 degrees (a R 3.6 mm curve as CAM posts it), F5000, G64 P0.01: every
    corner is blended (LinuxCNC's tangent arc within P, its ends within half of each chord), so
    the path runs at the feed with no stop on the polygon, every setpoint within P of the
    programmed chords, every axis within its limits. Under G61 the same program stops at every
    vertex (the speed comes to 0 there, the path the chords exactly) and takes over twice as
    long."""
    text, n = _polygon(3.6, 0.5, 5000)
    prog = parse(text, "p.ngc", XY)
    tr = plan(prog, ["X", "Y"], LIMITS)
    out = _run(tr)
    _assert_within_limits(out)
    assert contour_error(prog, out[:, 0]).max() <= 1e-5 + 1e-9
    speed = np.hypot(out[:, 1, 0], out[:, 1, 1])
    on = np.abs(np.hypot(out[:, 0, 0] - 0.06, out[:, 0, 1] - 0.06) - 3.6e-3) < 0.1e-3   # on the polygon
    mid = np.flatnonzero(on)
    core = speed[mid[len(mid) // 4]:mid[3 * len(mid) // 4]]
    assert core.min() >= 0.95 * 5000 / 6e4                          # the feed, no stop
    exact = parse(_polygon(3.6, 0.5, 5000, "G61")[0], "p.ngc", XY)
    tr61 = plan(exact, ["X", "Y"], LIMITS)
    out61 = _run(tr61)
    _assert_within_limits(out61)
    assert contour_error(exact, out61[:, 0]).max() <= 1e-9
    stands = np.hypot(out61[:, 1, 0], out61[:, 1, 1]) == 0.0
    stops = np.count_nonzero(stands[1:] & ~stands[:-1])              # moving, then at rest
    assert stops >= n + 1 and tr61.duration > 2 * tr.duration


def test_naive_cam_merges_a_jittered_line_within_q():
    """50 moves of 0.1 mm along X whose points zigzag by 1 µm (a CAM post's rounding), G64 P0.01
    (Q = P): run as one line at the feed (LinuxCNC's naive-CAM merge), within P of the
    programmed moves. With Q0 they are blended one by one, also within P, but the blends' turns
    alternate (a curvature step of 2/r at each join) and the jerk bounds the speed below the
    feed."""
    pts = "".join(f"G1 X{0.1 * k:.4f} Y{0.001 * (k % 2):.4f}\n" for k in range(1, 51))
    top = {}
    for mode in ("G64 P0.01", "G64 P0.01 Q0"):
        prog = parse(f"G21 G90 {mode}\nG1 X0 Y0 F6000\n{pts}M2\n", "q.ngc", XY)
        out = _run(plan(prog, ["X", "Y"], LIMITS))
        _assert_within_limits(out)
        assert contour_error(prog, out[:, 0]).max() <= 1e-5 + 1e-9
        top[mode] = np.hypot(out[:, 1, 0], out[:, 1, 1]).max()
    assert top["G64 P0.01"] == pytest.approx(0.1) and top["G64 P0.01 Q0"] < 0.09


@pytest.mark.parametrize("text", [
    "G21 G90\nG1 X120 Y120 F3000\nM2\n",                                      # from elsewhere: a first rapid
    "G21 G90 G64 P0.01\nG1 X10 Y0 F5000\nG3 X12 Y2 I0 J2\nG1 X12.3 Y9.7\nG1 X20 Y10\nM2\n",
    "G21 G90 G64 P0.01\nG1 X10 Y3 F9000\nG2 X14 Y3 I2 J0\nM2\n",           # ends on an arc
])
def test_a_programs_last_setpoint_is_its_end_point_exactly(text):
    """The setpoints a filler takes a block at a time (50 rows, each call going on where the
    last ended) end at the programmed end point exactly, the velocity and acceleration 0; the
    rows before, once at rest, within 1e-15 m of it."""
    prog = parse(text, "e.ngc", XY)
    tr = plan(prog, ["X", "Y"], LIMITS, start=[0.031, 0.047])
    n = int(np.ceil(tr.duration / H)) + 1
    out = np.empty((n + 49 - (n - 1) % 50, 3, 2))
    for k in range(0, len(out), 50):
        tr.sample_into(k * H, H, out[k:k + 50])
    np.testing.assert_array_equal(out[-1, 0], prog.end[:2])
    np.testing.assert_array_equal(out[-1, 1:], 0.0)
    rest = np.flatnonzero(np.any(out[:, 1] != 0.0, axis=1))[-1] + 1          # the first row at rest for good
    assert np.abs(out[rest:, 0] - prog.end[:2]).max() <= 1e-15


def test_a_fill_that_goes_on_where_the_last_ended_is_the_same_as_one_fill():
    prog = parse((REPO / "configs" / "plate_0932.ngc").read_text(), "plate_0932.ngc",
                 GcodeSettings(axes=["X", "Y"], words={"M3": "torch", "M5": "torch", "S": "ignore"}))
    tr = plan(prog, ["X", "Y"], LIMITS)
    one = np.empty((6000, 3, 2))
    tr.sample_into(1.5, H, one)
    blocks = np.empty_like(one)
    for k in range(0, 6000, 50):
        tr.sample_into(1.5 + k * H, H, blocks[k:k + 50])
    np.testing.assert_allclose(blocks, one, rtol=0, atol=1e-9)
    np.testing.assert_allclose(blocks[:, 0], one[:, 0], rtol=0, atol=1e-13)


def test_kerf_arcs_between_chords_are_blended_at_the_feed_within_the_tolerance():
    """A curve of 2 mm chords joined by 0.3 mm arcs turning with them (a DXF2GCODE kerf arc at
    each vertex), F3000, G64 P0.01: each small arc is run as the larger blend of its corner
    within P (its curvature step at 0.3 mm would hold the path to about 17 mm/s), so the curve
    runs at the feed, every setpoint within P of the programmed chords and arcs."""
    lines, x, y, hd = ["G21 G90 G64 P0.01 Q0", "G0 X20 Y20", "G1 F3000"], 20.0, 20.0, 0.0
    for _ in range(12):
        x, y = x + 2 * np.cos(hd), y + 2 * np.sin(hd)
        lines.append(f"G1 X{x:.4f} Y{y:.4f}")
        cx, cy = x - 0.3 * np.sin(hd), y + 0.3 * np.cos(hd)
        hd += 0.12
        x, y = cx + 0.3 * np.sin(hd), cy - 0.3 * np.cos(hd)
        lines.append(f"G3 X{x:.4f} Y{y:.4f} I{cx - float(lines[-1].split('X')[1].split()[0]):.4f} "
                     f"J{cy - float(lines[-1].split('Y')[1]):.4f}")
    prog = parse("\n".join(lines + ["M2"]) + "\n", "k.ngc", XY)
    out = _run(plan(prog, ["X", "Y"], LIMITS))
    _assert_within_limits(out)
    assert contour_error(prog, out[:, 0]).max() <= 1e-5 + 1e-9
    speed = np.hypot(out[:, 1, 0], out[:, 1, 1])
    moving = np.flatnonzero(speed > 0)
    core = speed[moving[len(moving) // 4]:moving[3 * len(moving) // 4]]
    assert core.min() >= 0.98 * 0.05


def test_g64_without_p_stops_at_every_corner_and_follows_the_path():
    """G64 without P (no tolerance given): the path exactly, an exact stop at each corner of a
    square, none where its lead-in arc meets it tangentially; every setpoint within
    EXACT_ARC_TOL_M of the program (LinuxCNC would blend the corners with no bound)."""
    text = ("G21 G90 G64\nG0 X10 Y5\nG3 X15 Y0 I5 J0 F6000\nG1 X40\nG1 Y25\nG1 X15\nG1 Y0\nM2\n")
    prog = parse(text, "s.ngc", XY)
    out = _run(plan(prog, ["X", "Y"], LIMITS))
    _assert_within_limits(out)
    assert contour_error(prog, out[:, 0]).max() <= EXACT_ARC_TOL_M + 1e-9
    stands = np.hypot(out[:, 1, 0], out[:, 1, 1]) == 0.0
    at = out[1:][stands[1:] & ~stands[:-1], 0]                          # where the motion comes to rest
    np.testing.assert_allclose(at, [[0.010, 0.005], [0.040, 0.0], [0.040, 0.025], [0.015, 0.025], [0.015, 0.0]],
                               rtol=0, atol=1e-12)


@pytest.mark.parametrize("offset", [0.0, 2e-6, 5e-6, 1e-5, 1.3e-5, 5e-5])
def test_leaving_a_stop_off_the_grid_moves_only_the_next_pieces_axes(offset):
    """Sampled off the planner's grid (a feed override moves the path time off it), the first
    sample leaving an exact stop has moved by less than the joins' rounding (A·δ²/2 < 1 nm):
    it is on the next piece all the same, so the axis that stopped does not move again and the
    one that starts keeps its jerk (a point kept on the last piece put X at 2.6e-7 m/s after its
    stop and Y's jerk 0.7 % above j_max)."""
    prog = parse("G21 G90 G61\nG1 X10 F6000\nG1 Y20\nM2\n", "l.ngc", XY)
    tr = plan(prog, ["X", "Y"], LIMITS)
    n = int(np.ceil(tr.duration / H)) + 2
    out = np.empty((n, 3, 2))
    tr.sample_into(offset, H, out)
    _assert_within_limits(out)
    y_moves = np.flatnonzero(out[:, 1, 1] != 0.0)[0]
    assert np.all(out[y_moves:, 1, 0] == 0.0) and np.all(out[y_moves:, 2, 0] == 0.0)
    np.testing.assert_allclose(out[y_moves:, 0, 0], 0.010, rtol=0, atol=1e-12)


def test_a_dwell_after_a_machine_word_adds_only_its_seconds():
    """At a stop the first rest holds both moving averages (T1 + T2 + h); a dwell after M3 at the
    same point adds its own seconds, not a second such rest."""
    base = "G21 G90 G64 P0.01\nG1 X10 F3000\nM3\n{}G1 X20\nM2\n"
    t = [plan(parse(base.format(d), "d.ngc", XY), ["X", "Y"], LIMITS).duration for d in ("", "G4 P0.05\n")]
    assert t[1] - t[0] == pytest.approx(0.05, abs=H)


def test_a_curvature_step_is_passed_within_the_jerk_of_the_axis_it_loads():
    """The same line into a R 2 mm arc at F12000, once with the step's normal acceleration on X
    (j_max 4000 m/s³), once on Y (1000): X's join is passed about twice as fast (√(j_X/j_Y), less
    the curve's own jerk there), both within limits."""
    top = []
    for text in ("G21 G90 G64 P0.01\nG1 X20 Y10 F12000\nG1 X20 Y20\nG2 X24 Y20 I2 J0\n",     # normal +X
                 "G21 G90 G64 P0.01\nG1 X10 Y20 F12000\nG1 X20 Y20\nG3 X20 Y24 I0 J2\n"):   # normal +Y
        prog = parse(text, "c.ngc", XY)
        tr = plan(prog, ["X", "Y"], LIMITS)
        out = _run(tr)
        _assert_within_limits(out)
        join = np.argmin(np.hypot(out[:, 0, 0] - 0.020, out[:, 0, 1] - 0.020))
        top.append(np.hypot(*out[join, 1]))
    assert 1.8 * top[1] <= top[0] <= 2.0 * top[1]
