"""Jerk-limited point-to-point programs: limits, exact end points, move times, errors."""

import numpy as np
import pytest

from motorctl.loop.trajectory import Move, Program


def _samples(move, dt=1e-5):
    t = np.arange(move.t0 - 0.01, move.t0 + move.duration + 0.01, dt)
    return t, np.array([move.sample(x) for x in t])


@pytest.mark.parametrize("d,v,a,j", [(0.4, 2.0, 40.0, 4000.0), (0.4, 1.0, 10.0, 1000.0),
                                     (0.01, 2.0, 40.0, 4000.0), (-0.3, 2.0, 40.0, 4000.0),
                                     (0.0005, 2.0, 40.0, 4000.0)])
def test_limits_hold_and_end_points_are_exact(d, v, a, j):
    m = Move(0.1, 0.1 + d, v, a, j, t0=0.5)
    t, s = _samples(m)
    assert np.all(np.abs(s[:, 1]) <= v * (1 + 1e-9))
    assert np.all(np.abs(s[:, 2]) <= a * (1 + 1e-9))
    jerk = np.diff(s[:, 2]) / np.diff(t)
    assert np.all(np.abs(jerk) <= j * (1 + 1e-6))
    assert m.sample(m.t0 + m.duration) == (0.1 + d, 0.0, 0.0)
    assert m.sample(m.t0 + m.duration + 1.0) == (0.1 + d, 0.0, 0.0)
    assert m.sample(m.t0) == (0.1, 0.0, 0.0)
    # continuity of position and velocity (no steps)
    assert np.max(np.abs(np.diff(s[:, 0]))) < v * 1e-5 * 1.01
    # the velocity integrates to the distance
    assert np.trapezoid(s[:, 1], t) == pytest.approx(d, abs=1e-7)


def test_paper_programs_move_times():
    # configs/gantry.yaml: X move 0.26 s at 2 m/s, 40 m/s^2, 4000 m/s^3. In general the move lasts
    # 2 (v/a + a/j) + (D - v (v/a + a/j)) / v when it reaches v and a:
    def expected(d, v, a, j):
        ramp = v / a + a / j
        return 2 * ramp + (d - v * ramp) / v
    assert Move(0, 0.4, 2.0, 40.0, 4000.0).duration == pytest.approx(0.26)
    assert Move(0, 0.4, 2.0, 40.0, 4000.0).duration == pytest.approx(expected(0.4, 2.0, 40.0, 4000.0))
    assert Move(0, 0.4, 1.0, 10.0, 1000.0).duration == pytest.approx(expected(0.4, 1.0, 10.0, 1000.0))
    short = Move(0, 0.01, 2.0, 40.0, 4000.0)
    assert short.peak_velocity < 2.0


def test_program_repeats_and_holds():
    p = Program([0.0, 0.4], [0.5, 2.5], 4.0, 2.0, 40.0, 4000.0)
    assert p.sample(0.2) == (0.0, 0.0, 0.0)
    assert p.sample(1.0)[0] == 0.4
    assert p.sample(3.0)[0] == 0.0
    for k in range(3):
        np.testing.assert_allclose(p.sample(0.6 + 4 * k), p.sample(0.6), atol=1e-12)
    assert Program.hold(0.1).sample(12.3) == (0.1, 0.0, 0.0)


def test_program_errors():
    with pytest.raises(ValueError, match="overlaps"):
        Program([0.0, 0.4], [0.5, 0.6], 4.0, 2.0, 40.0, 4000.0)
    with pytest.raises(ValueError, match="fit in the period"):
        Program([0.0, 0.4], [0.5, 3.9], 4.0, 2.0, 40.0, 4000.0)
    with pytest.raises(ValueError, match="v_max"):
        Move(0, 1, 0.0, 1.0, 1.0)
