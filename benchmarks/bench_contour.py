"""Contouring: the planner's time and contour error against the time-optimal bound.

    python benchmarks/bench_contour.py [--grid 4000]

For each path (the ISO 230-4 test program of R 50 mm at 50 and 100 mm/s; a plasma cut path of
this file with lead-in arcs of 1-2 mm, rounded corners of 3 mm, a slot of 3 mm ends and a hole of
8 mm, M3/M5, F5000, G64 P0.01) on configs/gantry.yaml's limits (X: 2 m/s, 40 m/s², 4000 m/s³;
Y: 1 m/s, 10 m/s², 1000 m/s³):

* **planned**: the time :func:`motorctl.motion.plan` spends moving (its duration less its rests
  and the filters' delay (T1 + T2)/2 + one period);
* **TOPP-RA**: the time-optimal time of the same geometric path (H. Pham, Q.-C. Pham, "A new
  approach to time-optimal path parameterization based on reachability analysis", IEEE
  Trans. Robotics 34(3) 2018; the ``toppra`` package), acceleration-limited (each axis's a_max,
  no jerk limit: a lower bound the jerk-limited planner cannot reach), each axis's v_max and the
  programmed feed (a third coordinate s with v_max = feed). The path is cut where its tangent
  turns (a sharp corner: the exact path stops there) and at the machine words (the planner
  stops there too); each piece from rest to rest, a cubic spline of the path sampled every
  0.05 mm along its length (lines and arcs exactly at their ends);
* **contour error**: the largest distance of the planned setpoints (every 0.2 ms) from the
  programmed path (:func:`motorctl.motion.path.contour_error`) against the G64 P tolerance;
* per arc of the cut path: the planned path speed on it (the top of its profile before the
  filters), TOPP-RA's, and the centripetal bound √(a_max,Y·R) (Y's 10 m/s²: the axis that limits
  a circle).

``--uncompensated`` plans with the rule before 2026-11 (no compensation of the filters' radial
shrink, v ≤ √(12·R·P/(T1² + T2²))) for the comparison.

Prints two tables (Markdown). Needs ``toppra`` (``pip install 'motorctl[bench]'``).
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from motorctl.motion import AxisLimits, GcodeSettings, contour_error, parse, plan  # noqa: E402
from motorctl.motion.circle import circle_program  # noqa: E402
from motorctl.motion.gcode import Arc, Dwell, Event, Line, Pause  # noqa: E402

LIMITS = [AxisLimits(2.0, 40.0, 4000.0), AxisLimits(1.0, 10.0, 1000.0)]
SETTINGS = GcodeSettings(axes=["X", "Y"], words={"M3": "torch", "M5": "torch", "S": "ignore"})
H = 2e-4

#: the cut path: a plate 100 x 60 mm with corners rounded R 3 mm entered on a 2 mm lead-in arc,
#: a slot with R 3 mm ends on a 1.5 mm lead-in, an R 8 mm hole on a 1 mm lead-in
CUT = """%
(bench_contour: a plasma cut path, lead-in arcs 1-2 mm)
G17 G21 G90 G94 G64 P0.01
G0 X68 Y22
M3
G3 X70 Y20 I2 J0 F5000
G1 X117 Y20
G3 X120 Y23 I0 J3
G1 X120 Y77
G3 X117 Y80 I-3 J0
G1 X23 Y80
G3 X20 Y77 I0 J-3
G1 X20 Y23
G3 X23 Y20 I3 J0
G1 X72 Y20
G3 X74 Y22 I0 J2
M5
G0 X88.5 Y48.5
M3
G3 X90 Y47 I1.5 J0 F5000
G1 X100 Y47
G3 X100 Y53 I0 J3
G1 X80 Y53
G3 X80 Y47 I0 J-3
G1 X92 Y47
G3 X93.5 Y48.5 I0 J1.5
M5
G0 X57 Y51
M3
G2 X58 Y50 I0 J-1 F5000
G2 X58 Y50 I-8 J0
G2 X57 Y49 I-1 J0
M5
M2
%
"""


def _points(seg, step: float) -> np.ndarray:
    """Points along one move every ~step [m], both ends included: shape (n, 2)."""
    if isinstance(seg, Line):
        n = max(2, int(math.ceil(np.linalg.norm(seg.end[:2] - seg.start[:2]) / step)) + 1)
        f = np.linspace(0, 1, n)[:, None]
        return seg.start[:2] + f * (seg.end[:2] - seg.start[:2])
    c, sw = seg.center[:2], seg.sweep
    r = seg.radius
    phi0 = math.atan2(seg.start[1] - c[1], seg.start[0] - c[0])
    n = max(3, int(math.ceil(abs(sw) * r / step)) + 1)
    phi = phi0 + np.linspace(0, sw, n)
    return np.column_stack([c[0] + r * np.cos(phi), c[1] + r * np.sin(phi)])


def _tangent(seg, at_end: bool) -> np.ndarray:
    if isinstance(seg, Line):
        d = seg.end[:2] - seg.start[:2]
        return d / np.linalg.norm(d)
    p = (seg.end if at_end else seg.start)[:2] - seg.center[:2]
    t = np.array([-p[1], p[0]]) if seg.sweep > 0 else np.array([p[1], -p[0]])
    return t / np.linalg.norm(t)


def _pieces(program) -> list[list]:
    """The moves cut into chains from rest to rest: at a machine word, a dwell, a pause, a rapid
    and where the tangent turns by more than 1e-6 rad (the exact path stops there)."""
    out, cur, prev = [], [], None
    for seg in program.segments:
        if isinstance(seg, (Dwell, Pause, Event)) or (isinstance(seg, Line) and seg.feed is None):
            if cur:
                out.append(cur)
            cur, prev = [], None
            continue
        if not isinstance(seg, (Line, Arc)):
            continue
        if prev is not None and np.linalg.norm(_tangent(prev, True) - _tangent(seg, False)) > 1e-6:
            out.append(cur)
            cur = []
        cur.append(seg)
        prev = seg
    if cur:
        out.append(cur)
    return out


def toppra_time(chain: list, limits, grid: int) -> tuple[float, list[float]]:
    """TOPP-RA's time [s] over one chain of moves (from rest to rest) and each move's top speed
    [m/s] on it. Raises RuntimeError when TOPP-RA finds no parameterisation."""
    import toppra as ta
    import toppra.algorithm as algo
    import toppra.constraint as constraint
    ta.setup_logging("WARNING")
    pts, bounds = [], [0.0]
    for seg in chain:
        p = _points(seg, 5e-5)
        pts.append(p if not pts else p[1:])
    xy = np.concatenate(pts)
    ds = np.linalg.norm(np.diff(xy, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(ds)])
    for seg in chain:
        bounds.append(bounds[-1] + (seg.length))
    feed = max(seg.feed for seg in chain)
    way = np.column_stack([xy, s])                      # the third coordinate: s (feed limit)
    path = ta.SplineInterpolator(s, way)
    vlim = np.array([[-lim.v_max, lim.v_max] for lim in limits] + [[-feed, feed]])
    alim = np.array([[-lim.a_max, lim.a_max] for lim in limits] + [[-1e6, 1e6]])
    cons = [constraint.JointVelocityConstraint(vlim), constraint.JointAccelerationConstraint(alim)]
    n = max(grid, int(s[-1] / 2e-4))
    grid_s = np.linspace(0, s[-1], n + 1)
    inst = algo.TOPPRA(cons, path, gridpoints=grid_s, parametrizer="ParametrizeConstAccel")
    inst.compute_parameterization(0.0, 0.0)
    sd = inst.problem_data.sd_vec
    if sd is None or not np.all(np.isfinite(sd)):
        raise RuntimeError(f"TOPP-RA: no parameterisation ({inst.problem_data.return_code})")
    # constant path acceleration between grid points (the parametrizer's): Δt = 2 Δs / (ṡ0 + ṡ1)
    t = float(np.sum(2 * np.diff(grid_s) / np.maximum(sd[1:] + sd[:-1], 1e-12)))
    tops = [float(sd[(grid_s >= a) & (grid_s <= b)].max()) for a, b in zip(bounds[:-1], bounds[1:])]
    return t, tops


def planned_moving_time(traj) -> float:
    """The planner's duration less its rests (pieces of length 0) and the filters' delay."""
    rest = float(np.sum(np.where(traj._len == 0.0, traj._ta + traj._tc + traj._td, 0.0)))
    return traj.duration - rest - (traj._m + 1) * traj.period


def setpoints(traj) -> np.ndarray:
    n = int(math.ceil(traj.duration / H)) + 2
    out = np.empty((n, 3, len(traj.axes)))
    traj.sample_into(0.0, H, out)
    return out


def bench(name: str, text: str, tol: float, grid: int, arcs_table: list | None = None) -> dict:
    prog = parse(text, name, SETTINGS)
    t0 = time.perf_counter()
    tr = plan(prog, ["X", "Y"], LIMITS)
    t_plan = time.perf_counter() - t0
    sp = setpoints(tr)
    err = contour_error(prog, sp[:, 0])
    t_top, tops = 0.0, {}
    for chain in _pieces(prog):
        t, tp = toppra_time(chain, LIMITS, grid)
        t_top += t
        tops.update({seg.line: v for seg, v in zip(chain, tp)})
    if arcs_table is not None:
        vp = {int(ln): float(v) for ln, v, kind in zip(tr._lines, tr._vp, tr._kind) if kind == 1}
        for seg in prog.moves:
            if isinstance(seg, Arc) and seg.radius < 5e-3:
                arcs_table.append((name, seg.line, seg.radius, abs(seg.sweep), vp[seg.line], tops[seg.line],
                                   math.sqrt(LIMITS[1].a_max * seg.radius), seg.feed))
    return {"name": name, "planned": planned_moving_time(tr), "toppra": t_top, "err": float(err.max()),
            "tol": tol, "plan_s": t_plan}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--grid", type=int, default=4000, help="TOPP-RA grid points per piece, at least (default 4000)")
    ap.add_argument("--uncompensated", action="store_true",
                    help="the former arc rule: no shrink compensation, v <= sqrt(12 R P / (T1^2 + T2^2))")
    args = ap.parse_args(argv)
    if args.uncompensated:
        from motorctl.motion import planner
        planner.ARC_COMPENSATE, planner.ARC_RESIDUAL = False, 1.0
    rows, arcs = [], []
    for feed in (0.05, 0.1):
        text, _ = circle_program(0.05, feed, center=(0.2, 0.2))
        rows.append(bench(f"ISO 230-4 R 50 mm F{feed * 6e4:.0f}", text, 1e-5, args.grid))
    rows.append(bench("cut path (lead-ins 1-2 mm, F5000)", CUT, 1e-5, args.grid, arcs))
    print("| path | planned s | TOPP-RA s | planned / TOPP-RA | contour error µm | G64 P µm |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['name']} | {r['planned']:.3f} | {r['toppra']:.3f} | {r['planned'] / r['toppra']:.2f} | "
              f"{r['err'] * 1e6:.2f} | {r['tol'] * 1e6:.0f} |")
    print()
    print("| arc (line) | R mm | sweep ° | planned mm/s | TOPP-RA top mm/s | √(a_Y·R) mm/s | feed mm/s |")
    print("|---|---|---|---|---|---|---|")
    for name, line, r, sw, v, vt, vc, f in arcs:
        print(f"| {line} | {r * 1e3:g} | {math.degrees(sw):.0f} | {v * 1e3:.1f} | {vt * 1e3:.1f} | {vc * 1e3:.1f} | "
              f"{f * 1e3:.1f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
