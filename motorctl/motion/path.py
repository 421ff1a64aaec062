"""Geometry of a programmed path: the distance of points from it (the contour error of a
trajectory, the check of the planner's blend tolerance)."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from motorctl.motion.gcode import AXES, Line, Program


def contour_error(program: Program, points: np.ndarray, axes: Sequence[str] = ("X", "Y")) -> np.ndarray:
    """The distance [m] of each point from the program's path (its lines and arcs, the move from
    ``program.start`` included).

    points: shape (n, len(axes)) [m], machine coordinates of ``axes`` (letters among X Y Z); an
    arc is measured in X and Y with the other axes moving linearly. Returns shape (n,). Raises
    ValueError when ``points`` does not have one column per axis."""
    pts = np.asarray(points, dtype=float)
    if pts.ndim != 2 or pts.shape[1] != len(axes):
        raise ValueError(f"points: shape (n, {len(axes)}) expected, got {pts.shape}")
    idx = [AXES.index(a) for a in axes]
    d = np.full(len(pts), np.inf)
    for seg in program.moves:
        a, b = seg.start[idx], seg.end[idx]
        if isinstance(seg, Line) or not ("X" in axes and "Y" in axes):
            ab = b - a
            l2 = float(ab @ ab)
            t = np.clip(((pts - a) @ ab) / l2, 0.0, 1.0) if l2 > 0 else np.zeros(len(pts))
            dd = np.linalg.norm(pts - (a + t[:, None] * ab), axis=1)
        else:
            ix, iy = axes.index("X"), axes.index("Y")
            c = seg.center[:2]
            rel = np.column_stack([pts[:, ix] - c[0], pts[:, iy] - c[1]])
            ang = np.arctan2(rel[:, 1], rel[:, 0])
            phi0 = math.atan2(seg.start[1] - c[1], seg.start[0] - c[0])
            sw = seg.sweep
            frac = ((ang - phi0) % (2 * np.pi)) if sw > 0 else ((phi0 - ang) % (2 * np.pi))
            # the point of the arc at the point's angle (the nearest turn for multi-turn arcs)
            f = np.clip(frac / abs(sw), 0.0, 1.0)
            r0 = seg.radius
            r1 = float(math.hypot(seg.end[0] - c[0], seg.end[1] - c[1]))
            on = (frac <= abs(sw)) | (abs(sw) >= 2 * np.pi)
            q = a + f[:, None] * (b - a)
            rr = r0 + (r1 - r0) * f
            q[:, ix] = c[0] + rr * np.cos(ang)
            q[:, iy] = c[1] + rr * np.sin(ang)
            d_on = np.linalg.norm(pts - q, axis=1)
            d_ends = np.minimum(np.linalg.norm(pts - a, axis=1), np.linalg.norm(pts - b, axis=1))
            dd = np.where(on, np.minimum(d_on, d_ends), d_ends)
        d = np.minimum(d, dd)
    return d
