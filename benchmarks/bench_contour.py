"""Contouring: the planner's time and its distance from the programmed path against the
time-optimal bound, on the ISO 230-4 circle and CAM programs of short segments.

    python benchmarks/bench_contour.py [--grid 0.2] [--program FILE ...]

Per program on configs/gantry.yaml's limits (X: 2 m/s, 40 m/s², 4000 m/s³; Y: 1 m/s, 10 m/s²,
1000 m/s³), G64 P as programmed:

* **planned**: the setpoints' time from the first motion to the end of the last (every 0.2 ms:
  the rests at exact stops, machine words and dwells included);
* **TOPP-RA**: the time-optimal time on the same path with every line-line corner replaced by
  the largest tangent arc within P (its ends within half of each line: LinuxCNC's blend; under
  G64 without P none, the corners stop as the planner's do), each
  axis's v_max and a_max and the programmed feed (H. Pham, Q.-C. Pham, "A new approach to
  time-optimal path parameterization based on reachability analysis", IEEE Trans. Robotics
  34(3) 2018; the ``toppra`` package). Acceleration-limited, no jerk limit: a lower bound the
  jerk-limited planner cannot reach. The path is cut into chains from rest to rest where the
  program stops (a machine word, a dwell, a pause, G61, a rapid's ends) or turns where an arc
  meets a move by more than the spline below rounds within P (θ·grid/4 > P); each chain a cubic spline through points
  of the path every ``--grid`` mm or closer (a blend arc in 8 points at least); the program's
  dwells between its moves added;
* **distance**: the setpoints' largest distance from the programmed path (the program's lines
  and arcs as :func:`motorctl.motion.gcode.parse` reads them, not the planner's blended path;
  :func:`motorctl.motion.path.contour_error`) on every sample, against P.

Programs: the ISO 230-4 test of R 50 mm at 50 and 100 mm/s; configs/cut_path.ngc (lead-in arcs
1-3 mm, sharp corners, 0.5 mm chords, F5000/F3000); configs/dxf2gcode_lid_wing.ngc (DXF2GCODE's
output, 220 moves: scaled data, its header says from where); configs/plate_0932.ngc (346 moves of
a plasma post's format). Needs ``toppra`` (``pip install 'motorctl[bench]'``).
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from motorctl.motion import AxisLimits, GcodeSettings, contour_error, parse, plan  # noqa: E402
from motorctl.motion.circle import circle_program  # noqa: E402
from motorctl.motion.gcode import Arc, Dwell, Event, Line, Pause  # noqa: E402
from motorctl.motion.planner import EXACT_ARC_TOL_M  # noqa: E402

LIMITS = [AxisLimits(2.0, 40.0, 4000.0), AxisLimits(1.0, 10.0, 1000.0)]
SETTINGS = GcodeSettings(axes=["X", "Y"], words={"M3": "torch", "M5": "torch", "S": "ignore"})
H = 2e-4
PROGRAMS = ["configs/cut_path.ngc", "configs/dxf2gcode_lid_wing.ngc", "configs/plate_0932.ngc"]


# ---------------------------------------------------------------- the reference path (TOPP-RA's)
class _Seg:
    """A line (c None) or an arc of the reference path in XY [m]."""

    def __init__(self, a, b, feed, c=None, sweep=0.0, r=0.0):
        self.a, self.b, self.feed, self.c, self.sweep, self.r = np.asarray(a, float), np.asarray(b, float), feed, c, sweep, r

    @property
    def length(self):
        return float(np.linalg.norm(self.b - self.a)) if self.c is None else abs(self.sweep) * self.r

    def tangent(self, at_end):
        if self.c is None:
            d = self.b - self.a
            return d / np.linalg.norm(d)
        p = (self.b if at_end else self.a) - self.c
        t = np.array([-p[1], p[0]]) if self.sweep > 0 else np.array([p[1], -p[0]])
        return t / np.linalg.norm(t)

    def points(self, step):
        if self.c is None:
            n = max(2, int(math.ceil(self.length / step)) + 1)
            return self.a + np.linspace(0, 1, n)[:, None] * (self.b - self.a)
        phi0 = math.atan2(self.a[1] - self.c[1], self.a[0] - self.c[0])
        n = max(8, int(math.ceil(self.length / step)) + 1)
        phi = phi0 + np.linspace(0, self.sweep, n)
        return np.column_stack([self.c[0] + self.r * np.cos(phi), self.c[1] + self.r * np.sin(phi)])


def _chains(program, grid_m: float):
    """The program's feed moves in chains from rest to rest, the line-line corners blended within
    the tolerance by the largest tangent arc whose ends lie within half of each line; and the
    program's dwell seconds."""
    chains, cur, dwell = [], [], 0.0
    prev = None
    last_move = max((k for k, seg in enumerate(program.segments) if isinstance(seg, (Line, Arc))), default=-1)
    for k, seg in enumerate(program.segments):
        stop = isinstance(seg, (Dwell, Pause)) or (isinstance(seg, Event) and not seg.synchronized)
        if isinstance(seg, Dwell) and k < last_move:         # (the planned time ends with the motion)
            dwell += seg.seconds
        if stop or (isinstance(seg, Line) and seg.feed is None) or (isinstance(seg, (Line, Arc)) and prev is not None
                                                                    and prev.tolerance == 0.0):
            if cur:
                chains.append(cur)
            cur, prev = [], None
            if not isinstance(seg, (Line, Arc)) or seg.feed is None:
                if isinstance(seg, Line):          # a rapid: its own chain at the axes' limits
                    chains.append([_Seg(seg.start[:2], seg.end[:2], math.inf)])
                continue
        if not isinstance(seg, (Line, Arc)):
            continue
        if isinstance(seg, Line):
            s = _Seg(seg.start[:2], seg.end[:2], seg.feed)
        else:
            s = _Seg(seg.start[:2], seg.end[:2], seg.feed, seg.center[:2].copy(), seg.sweep, seg.radius)
        s.room_a = s.room_b = 0.5 * s.length
        if cur:
            p = cur[-1]
            ta, tb = p.tangent(True), s.tangent(False)
            theta = math.acos(float(np.clip(ta @ tb, -1, 1)))
            # G64 without P: the path exactly as the planner follows it (corners stop, its
            # arcs within EXACT_ARC_TOL_M); no blend
            tol = prev.tolerance if math.isfinite(prev.tolerance) else EXACT_ARC_TOL_M
            blends = math.isfinite(prev.tolerance)
            if blends and theta > 1e-3 and p.c is None and s.c is None and math.pi - theta > 1e-3:
                half = theta / 2
                r = min(min(p.room_b, s.room_a) / math.tan(half), tol / (1 / math.cos(half) - 1))
                lt = r * math.tan(half)
                v = p.b.copy()
                p.b = v - ta * lt
                s.a = v + tb * lt
                sgn = 1.0 if ta[0] * tb[1] - ta[1] * tb[0] > 0 else -1.0
                c = p.b + r * sgn * np.array([-ta[1], ta[0]])
                cur.append(_Seg(p.b, s.a, min(p.feed, s.feed), c, sgn * theta, r))
            elif theta * grid_m / 4 > tol:     # the spline through points grid_m apart rounds a kink
                chains.append(cur)                # by about theta·grid/4: within P, TOPP-RA passes it
                cur = []
        cur.append(s)
        prev = seg
    if cur:
        chains.append(cur)
    return chains, dwell


def toppra_time(chain, limits, grid_m: float) -> float:
    """TOPP-RA's time [s] over one chain of moves from rest to rest. Raises RuntimeError when
    TOPP-RA finds no parameterisation."""
    import toppra as ta
    import toppra.algorithm as algo
    import toppra.constraint as constraint
    ta.setup_logging("WARNING")
    pts = []
    for seg in chain:
        if seg.length <= 0:
            continue
        p = seg.points(min(grid_m, seg.length / 8 if seg.c is not None else grid_m))
        pts.append(p if not pts else p[1:])
    xy = np.concatenate(pts)
    ds = np.linalg.norm(np.diff(xy, axis=0), axis=1)
    keep = np.concatenate([[True], ds > 1e-12])
    xy = xy[keep]
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(xy, axis=0), axis=1))])
    feed = max(seg.feed for seg in chain)
    feed = min(feed, 1e3)
    way = np.column_stack([xy, s])                      # the third coordinate: s (the feed's limit)
    path = ta.SplineInterpolator(s, way)
    vlim = np.array([[-lim.v_max, lim.v_max] for lim in limits] + [[-feed, feed]])
    alim = np.array([[-lim.a_max, lim.a_max] for lim in limits] + [[-1e6, 1e6]])
    cons = [constraint.JointVelocityConstraint(vlim), constraint.JointAccelerationConstraint(alim)]
    inst = algo.TOPPRA(cons, path, gridpoints=s, parametrizer="ParametrizeConstAccel")
    inst.compute_parameterization(0.0, 0.0)
    sd = inst.problem_data.sd_vec
    if sd is None or not np.all(np.isfinite(sd)):
        raise RuntimeError(f"TOPP-RA: no parameterisation ({inst.problem_data.return_code})")
    return float(np.sum(2 * np.diff(s) / np.maximum(sd[1:] + sd[:-1], 1e-12)))


def planned_time(out: np.ndarray) -> float:
    """The setpoints' time [s] from the first sample that moves to the last (rests included)."""
    moving = np.flatnonzero(np.any(np.abs(out[:, 1]) > 0, axis=1))
    return (moving[-1] - moving[0] + 1) * H if moving.size else 0.0


def bench(name: str, text: str, grid_m: float) -> dict:
    prog = parse(text, name, SETTINGS)
    t0 = time.perf_counter()
    tr = plan(prog, ["X", "Y"], LIMITS)
    t_plan = time.perf_counter() - t0
    n = int(math.ceil(tr.duration / H)) + 2
    out = np.empty((n, 3, 2))
    tr.sample_into(0.0, H, out)
    err = contour_error(prog, out[:, 0])
    chains, dwell = _chains(prog, grid_m)
    t_top = dwell + sum(toppra_time(c, LIMITS, grid_m) for c in chains if sum(s.length for s in c) > 0)
    tol = min((s.tolerance for s in prog.moves if s.feed is not None), default=math.inf)
    j = np.abs(np.diff(out[:, 2], axis=0)).max(axis=0) / H
    return {"name": name, "moves": len(prog.moves), "planned": planned_time(out), "toppra": t_top,
            "err": float(err.max()), "tol": tol, "plan_s": t_plan,
            "limits": (np.abs(out[:, 1]).max(axis=0), np.abs(out[:, 2]).max(axis=0), j)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--grid", type=float, default=0.2, help="TOPP-RA's points along the path [mm] (default 0.2)")
    ap.add_argument("--program", action="append", help="a program instead of the default set (repeatable)")
    args = ap.parse_args(argv)
    rows = []
    if not args.program:
        for feed in (0.05, 0.1):
            text, _ = circle_program(0.05, feed, center=(0.2, 0.2))
            rows.append(bench(f"ISO 230-4 R 50 mm F{feed * 6e4:.0f}", text, args.grid * 1e-3))
    for p in args.program or PROGRAMS:
        path = Path(p) if Path(p).is_absolute() else ROOT / p
        rows.append(bench(p, path.read_text(), args.grid * 1e-3))
    print("| program | moves | planned s | TOPP-RA s | planned / TOPP-RA | largest distance µm | G64 P µm | "
          "largest v X/Y mm/s, a m/s², j m/s³ | planned in s |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        v, a, j = r["limits"]
        print(f"| {r['name']} | {r['moves']} | {r['planned']:.3f} | {r['toppra']:.3f} | {r['planned'] / r['toppra']:.3f} | "
              f"{r['err'] * 1e6:.2f} | {r['tol'] * 1e6:.0f} | {v[0] * 1e3:.0f}/{v[1] * 1e3:.0f}, {a[0]:.1f}/{a[1]:.1f}, "
              f"{j[0]:.0f}/{j[1]:.0f} | {r['plan_s']:.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
