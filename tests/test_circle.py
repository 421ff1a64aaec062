"""The ISO 230-4 circular test (motorctl.motion.circle): the figures from known paths, and the
test program planned on the gantry's limits."""

import numpy as np
import pytest

from motorctl.motion import AxisLimits, GcodeSettings, parse, plan
from motorctl.motion.circle import circle_program, circular_deviation, evaluate, fit_circle

LIMITS = [AxisLimits(2.0, 40.0, 4000.0), AxisLimits(1.0, 10.0, 1000.0)]


def _circle(cx, cy, r, n=2000, phase=0.0, wobble=0.0, k=0):
    t = np.linspace(0, 2 * np.pi, n, endpoint=False) + phase
    rr = r + wobble * np.cos(k * t)
    return cx + rr * np.cos(t), cy + rr * np.sin(t)


def test_fit_circle_recovers_centre_and_radius():
    x, y = _circle(0.1, -0.05, 0.02, n=50, phase=0.3)
    assert fit_circle(x, y) == pytest.approx((0.1, -0.05, 0.02), abs=1e-12)
    with pytest.raises(ValueError):
        fit_circle(np.arange(5.0), np.arange(5.0))          # collinear


def test_deviations_of_known_paths():
    # an ellipse-like 2-lobe error of +-2 um (a squareness/scale error's signature), and an offset CW path
    cw = _circle(0.1003e0, 0.1, 0.02, wobble=2e-6, k=2)
    ccw = _circle(0.1, 0.1, 0.02 + 1e-6, wobble=2e-6, k=2)
    res = evaluate(cw, ccw, center=(0.1, 0.1), radius=0.02)
    assert res.G_ccw == pytest.approx(4e-6, rel=1e-3)                 # span of +-2 um
    assert res.G_cw == pytest.approx(4e-6, rel=1e-3)                  # its offset is fitted away
    assert res.G_b > res.G_ccw                                        # the two paths do not coincide
    assert res.F_max == pytest.approx(0.3e-3 + 2e-6, rel=2e-2)        # about the nominal centre
    assert res.F_min < -0.29e-3
    same = evaluate(ccw, ccw, center=(0.1, 0.1), radius=0.02)
    assert same.H == pytest.approx(0.0, abs=1e-12) and same.G_b == pytest.approx(same.G_ccw)
    shifted = evaluate(_circle(0.1, 0.1, 0.02 - 1e-6), _circle(0.1, 0.1, 0.02 + 1e-6), (0.1, 0.1), 0.02)
    assert shifted.H == pytest.approx(2e-6, rel=1e-6)                 # the reversal band
    assert circular_deviation(*ccw) == pytest.approx(res.G_ccw)


def test_the_test_program_runs_both_directions_on_the_planner():
    text, where = circle_program(0.02, 0.05, center=(0.1, 0.1), tolerance=1e-5)
    assert set(where) == {"cw", "ccw"} and "G2" in text and "G3" in text
    prog = parse(text, "circle.ngc", GcodeSettings(axes=["X", "Y"]), start=[0.1, 0.1, 0.0])
    tr = plan(prog, ["X", "Y"], LIMITS)
    h = 2e-4
    out = np.empty((int(tr.duration / h) + 1, 3, 2))
    tr.sample_into(0.0, h, out)
    lines = np.array([tr.line_at(k * h) for k in range(len(out))])
    paths = {d: (out[lines == ln, 0, 0], out[lines == ln, 0, 1]) for d, ln in where.items()}
    res = evaluate(paths["cw"], paths["ccw"], (0.1, 0.1), 0.02)
    # the planner's filters shrink the radius by v^2 (T1^2 + T2^2) / (24 R): 4.2 um at 50 mm/s, R 20 mm
    assert -5e-6 < res.F_min <= res.F_max < -3e-6
    assert res.G_b < 1e-6 and res.H < 1e-7
    with pytest.raises(ValueError, match="direction"):
        circle_program(0.02, 0.05, directions=["up"])
