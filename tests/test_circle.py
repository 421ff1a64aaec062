"""The ISO 230-4 circular test (motorctl.motion.circle): the figures from known paths, and the
test program planned on the gantry's limits."""

import json
from pathlib import Path

import numpy as np
import pytest
from conftest import REPO

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
    # the planner's filters shrink the radius by v^2 (T1^2 + T2^2) / (24 R) (4.2 um at 50 mm/s, R 20 mm);
    # it plans the arc on the radius they shrink back onto R, faded in and out where the arc meets
    # another curvature: the lead-in and lead-out joins, outside the measured circle behind the
    # overshoot arcs (the same circle: no fade at their joins), so the measured setpoints are on R
    assert -1e-9 < res.F_min <= res.F_max < 1e-9
    assert res.G_b < 1e-9 and res.H < 1e-9
    with pytest.raises(ValueError, match="direction"):
        circle_program(0.02, 0.05, directions=["up"])


# ------------------------------------------------------------------ motorctl circle-test as a record
def _lsc_geometric(x, y):
    """ISO 230-4's least-squares circle written here from its definition (the centre and radius
    minimising the sum of squared radial deviations), by Gauss-Newton from the centroid: the
    project's fit_circle is Kåsa's algebraic one, so this is a second computation, not a copy."""
    c = np.array([x.mean(), y.mean()])
    r = np.hypot(x - c[0], y - c[1]).mean()
    for _ in range(50):
        d = np.hypot(x - c[0], y - c[1])
        res = d - r                                                   # radial deviations
        jac = np.column_stack([-(x - c[0]) / d, -(y - c[1]) / d, -np.ones_like(d)])
        step = np.linalg.lstsq(jac, -res, rcond=None)[0]
        c, r = c + step[:2], r + step[2]
        if np.abs(step).max() < 1e-15:
            break
    return c, r


#: the independent fit reproduces G within this [m] (the two fits' centres differ by nanometres
#: on a path of micrometre deviations; observed below 1e-9)
G_FIT_TOL_M = 2e-9


#: the simulated encoder's largest departure from the carriage's true position [m]: half a step
#: (0.25 um), the interpolation error's amplitude (0.15 um) and six standard deviations of its
#: noise (0.6 um) in configs/gantry.yaml
ENCODER_BOUND_M = 1.0e-6


def test_the_circle_test_is_a_record_that_reproduces(tmp_path):
    """`motorctl circle-test` run twice (in this process, then as the command with --json --plot
    --log) gives the same figures bit for bit and the same measured positions; the run log's
    positions, fitted here, give its G and its largest contour error; --json prints one JSON
    document and nothing else. The simulated ballbar (the carriages' true positions) reads the
    same test circles, within the encoder's own error of what the encoders read, and its
    figures are in the log's header beside the encoders'."""
    from harness import run_cli

    from motorctl.app.circle_test import figures, run_circle_test
    from motorctl.config import load_config
    from motorctl.recorder.runlog import read_log
    cfg = REPO / "configs" / "gantry.yaml"
    r = run_circle_test(load_config(cfg), 0.005, 0.05, "c2", log_path=str(tmp_path / "one.log"))
    cp = run_cli(["circle-test", str(cfg), "--radius", "0.005", "--feed", "0.05", "--controller", "c2",
                  "--json", "--plot", str(tmp_path / "plots"), "--log", str(tmp_path / "two.log")], timeout_s=120)
    assert cp.returncode == 0, cp.stderr
    doc = json.loads(cp.stdout)                                     # the JSON alone: it parses whole
    assert len(doc) == 1
    two = doc[0]
    g = r.result
    assert Path(two["plot"]).is_file() and two["log"] == str(tmp_path / "two.log")
    logs = [read_log(str(tmp_path / "one.log")), read_log(two["log"])]
    for col in ("X.y", "Y.y", "X.x_d", "Y.x_d"):
        np.testing.assert_array_equal(logs[0].col(col), logs[1].col(col))
    lg = logs[1]
    assert lg.header["kind"] == "circle-test"
    for k in ("encoder", "ballbar"):                                # the command's, bit for bit
        assert lg.header["circle"]["figures_m"][k] == figures(r.readings[k]), k
    assert lg.header["circle"]["no_ballbar"] == "" and r.no_ballbar == ""
    c0 = np.array(r.center)
    spans, e_max = [], []
    for d, g_dir in (("cw", g.G_cw), ("ccw", g.G_ccw)):
        a, b = lg.header["circle"]["rows"][d]
        x, y = lg.col("X.y")[a:b], lg.col("Y.y")[a:b]
        # the rows are the test circle: its setpoints begin and end at its start point, (0, +R)
        # CCW, (0, -R) CW, after and before the overshoot arcs
        s = 1.0 if d == "ccw" else -1.0
        for k in (a, b - 1):
            p = np.array([lg.col("X.x_d")[k], lg.col("Y.x_d")[k]]) - c0
            assert np.hypot(p[0], p[1] - s * 0.005) < 0.2e-3
        assert (b - a) * lg.header["period_s"] > 2 * np.pi * 0.005 / 0.05 * 0.95   # a whole turn
        c, r_fit = _lsc_geometric(x, y)
        rad = np.hypot(x - c[0], y - c[1])
        assert abs((rad.max() - rad.min()) - g_dir) <= G_FIT_TOL_M, d
        e_max.append(np.abs(rad - r_fit).max())
        spans.append((x, y))
        # the ballbar: the same rows' true positions, within the encoder's error of its reading
        bx, by = r.readings["ballbar"].paths[d]
        assert bx.shape == x.shape
        dev = np.abs(np.concatenate([x - bx, y - by]))
        assert 0.1e-6 < dev.max() <= ENCODER_BOUND_M, (d, dev.max())
    assert abs(max(e_max) - r.readings["encoder"].e_max) <= G_FIT_TOL_M
    x, y = np.concatenate([s[0] for s in spans]), np.concatenate([s[1] for s in spans])
    c, _ = _lsc_geometric(x, y)
    rad = np.hypot(x - c[0], y - c[1])
    assert abs((rad.max() - rad.min()) - g.G_b) <= G_FIT_TOL_M
    assert 0 < g.G_b < 30e-6


def test_a_driver_without_a_true_position_gives_no_ballbar():
    """A driver that reads no true position (a real drive) gives no ballbar reading, and says so;
    the table shows the ballbar's row as none, the JSON summary null with the reason."""
    from dataclasses import replace

    from motorctl.app.circle_test import ENCODER, CircleRun, Reading, ballbar_of, summary, table

    class Drive:                                  # a bus driver: positions from its encoders only
        position_m = np.zeros(2)

    truth, why = ballbar_of(Drive(), 2)
    assert truth is None and "Drive" in why and "encoder" in why
    sim = type("Sim", (), {"true_position_m": np.zeros(2)})()
    assert ballbar_of(sim, 2) == (sim.true_position_m, "")
    x, y = _circle(0.0, 0.0, 0.01, n=400)
    paths = {"cw": (x, y), "ccw": (x, y)}
    rd = Reading(ENCODER, evaluate(paths["cw"], paths["ccw"], (0.0, 0.0), 0.01), 0.0, paths)
    run = CircleRun("c2", 0.05, 0.01, (0.0, 0.0), {ENCODER: rd}, 0, no_ballbar=why)
    rows = table([run, replace(run, readings={ENCODER: rd, "ballbar": replace(rd, instrument="ballbar")},
                               no_ballbar="")])
    assert [row[2] for row in rows[1:]] == ["encoder", "ballbar: none", "encoder", "ballbar"]
    assert rows[2][3:-1] == ["-"] * 7 and rows[4][3] == "0.00"
    doc = summary(run)
    assert doc["ballbar"] is None and doc["no_ballbar"] == why and doc["encoder"]["G_b_um"] == rd.result.G_b * 1e6
