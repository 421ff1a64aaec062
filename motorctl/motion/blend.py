"""The blended path: a program's moves with LinuxCNC's naive-CAM merge (G64 Q) and a tangent
arc at every line-line corner within the G64 tolerance (P), the geometry the planner follows
exactly (docs/motion.md, "The planner").

LinuxCNC's trajectory planner (tp) replaces the corner between two moves by a tangent circular
blend whose distance from the corner stays within P and whose ends use at most half of each move
(R. Ellis, "Parabolic and tangent arc blending in LinuxCNC's trajectory planner", LinuxCNC
docs, Trajectory Control); with G64 Q the interpreter first runs consecutive straight feed
moves whose points lie within Q of one line as that line ("naive CAM detector", LinuxCNC
G-code reference, G64). A corner's blend arc of radius r between legs turning by θ lies within
``r·(1/cos(θ/2) − 1)`` of the corner and touches each leg ``r·tan(θ/2)`` from it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

#: tangent directions closer than this [rad] are the same (a join without a kink)
TANGENT_RAD = 1e-9
#: the share of the tolerance a corner's blend arc may use; the rest is left to the planner's
#: short smoothing filter (its deviation from the blended path)
BLEND_SHARE = 0.9
#: the share of the tolerance the naive-CAM merge may use (Q is capped to it): a merged line's
#: own deviation is taken from what its corners' blends may use
MERGE_SHARE = 0.5


@dataclass
class Geo:
    """One piece of the blended path in the machine's axes (arrays shape (n_axes,) [m]).

    kind: 0 line, 1 arc (in X, Y; other axes linear along it). u: a line's unit tangent; an
    arc's other axes' displacement per metre of path. arc: (cx, cy, r0, r1, phi0, sweep) [m, rad].
    feed: path speed [m/s] (None: a rapid). tol: the G64 P at its end [m] (0: exact stop; inf:
    G64 without P). dev: its own largest distance from the programmed path [m]. src: the index
    of the programmed move it comes from (a blend: the move before its corner). q: naive-CAM
    tolerance [m]."""

    kind: int
    p0: np.ndarray
    p1: np.ndarray
    u: np.ndarray
    length: float
    line: int
    feed: float | None
    tol: float
    src: int
    dev: float = 0.0
    arc: tuple = (0.0,) * 6
    q: float = 0.0
    blend: bool = False
    merged: list = field(default_factory=list)

    def tangents(self, ix: int, iy: int) -> tuple[np.ndarray, np.ndarray]:
        """Unit tangents at the start and at the end."""
        if self.kind == 0:
            return self.u, self.u
        _, _, r0, r1, phi0, sweep = self.arc
        sgn = 1.0 if sweep > 0 else -1.0
        out = []
        for phi in (phi0, phi0 + sweep):
            t = self.u * self.length
            planar = abs(sweep) * 0.5 * (r0 + r1)
            t[ix] = -math.sin(phi) * sgn * planar
            t[iy] = math.cos(phi) * sgn * planar
            out.append(t / np.linalg.norm(t))
        return out[0], out[1]

    def curvature(self) -> float:
        """Signed curvature in XY [1/m]: + turning left (CCW), 0 for a line."""
        if self.kind == 0:
            return 0.0
        r = 0.5 * (self.arc[2] + self.arc[3])
        return (1.0 if self.arc[5] > 0 else -1.0) / r if r > 0 else 0.0


def line_geo(p0, p1, line, feed, tol, src, q=0.0) -> Geo | None:
    """A straight piece from p0 to p1 (None when they are the same point)."""
    d = p1 - p0
    length = float(np.linalg.norm(d))
    if length <= 0.0:
        return None
    return Geo(0, p0.copy(), p1.copy(), d / length, length, line, feed, tol, src, q=q)


def merge_collinear(geos: list[Geo], barrier: list[bool]) -> list[Geo]:
    """LinuxCNC's naive-CAM merge: a run of straight feed moves (the same feed and tolerance, no
    barrier between: an event, a stop) whose inner vertices lie within ``min(Q, MERGE_SHARE·P)``
    of the line from the run's first point to its last, and project onto it in order, becomes
    that line; its ``dev`` is the largest such distance (every point of the line is then within
    it of the programmed moves). ``barrier[k]``: nothing may merge across the end of geos[k]."""
    out: list[Geo] = []
    k = 0
    n = len(geos)
    while k < n:
        g = geos[k]
        q = min(g.q, MERGE_SHARE * g.tol) if g.kind == 0 and g.feed is not None else 0.0
        if q <= 0.0 or not math.isfinite(q) or barrier[k]:
            out.append(g)
            k += 1
            continue
        best, best_dev = k, 0.0
        pts = [g.p0, g.p1]
        j = k + 1
        while j < n:
            h = geos[j]
            if (h.kind != 0 or h.feed != g.feed or h.tol != g.tol or h.q != g.q
                    or barrier[j - 1]):
                break
            pts.append(h.p1)
            a, b = pts[0], pts[-1]
            ab = b - a
            l2 = float(ab @ ab)
            if l2 <= 0.0:
                break
            inner = np.array(pts[1:-1])
            t = (inner - a) @ ab / l2
            if np.any(np.diff(np.concatenate([[0.0], t, [1.0]])) <= 0.0):
                break
            dev = float(np.max(np.linalg.norm(inner - a - t[:, None] * ab, axis=1)))
            if dev > q:
                break
            best, best_dev = j, dev
            if barrier[j]:
                break
            j += 1
        if best == k:
            out.append(g)
            k += 1
            continue
        last = geos[best]
        m = line_geo(g.p0, last.p1, last.line, g.feed, last.tol, last.src, g.q)
        m.dev = best_dev
        m.merged = list(range(k, best + 1))
        out.append(m)
        k = best + 1
    return out


def corner_blend(a: Geo, b: Geo, tol: float, room_a: float, room_b: float, ix: int, iy: int
                 ) -> tuple[Geo, float, float] | None:
    """The tangent arc between two lines a → b in XY whose distance from the corner is within
    ``tol`` [m] and whose ends lie within ``room_a`` of the corner on a and ``room_b`` on b [m]
    (the largest such radius). Returns (arc, its distance from the corner [m], the distance of
    its ends from the corner [m]), or None when the legs move other axes than X and Y or turn
    back onto themselves."""
    if ix < 0 or iy < 0:
        return None
    others = [i for i in range(a.u.size) if i not in (ix, iy)]
    if others and (np.any(a.u[others] != 0.0) or np.any(b.u[others] != 0.0)):
        return None
    ua = np.array([a.u[ix], a.u[iy]])
    ub = np.array([b.u[ix], b.u[iy]])
    cos_t = float(np.clip(ua @ ub, -1.0, 1.0))
    theta = math.acos(cos_t)
    if theta <= TANGENT_RAD or theta > math.pi - 1e-3:
        return None
    half = 0.5 * theta
    tan_h = math.tan(half)
    sec_m1 = 1.0 / math.cos(half) - 1.0
    room = min(room_a, room_b)
    r = room / tan_h
    if math.isfinite(tol) and r * sec_m1 > tol:
        r = tol / sec_m1
    if not r > 0.0:
        return None
    lt = r * tan_h
    v = a.p1
    ta = v - a.u * lt
    tb = v + b.u * lt
    cross = ua[0] * ub[1] - ua[1] * ub[0]
    sgn = 1.0 if cross > 0 else -1.0
    # the centre: r from the tangent point along the leg's inward normal
    n_a = np.array([-ua[1], ua[0]]) * sgn
    c = np.array([ta[ix], ta[iy]]) + r * n_a
    phi0 = math.atan2(ta[iy] - c[1], ta[ix] - c[0])
    sweep = sgn * theta
    g = Geo(1, ta.copy(), tb.copy(), np.zeros(a.u.size), r * theta, a.line, a.feed if b.feed is None else
            (b.feed if a.feed is None else min(a.feed, b.feed)), tol, a.src, dev=r * sec_m1,
            arc=(float(c[0]), float(c[1]), r, r, phi0, sweep), blend=True)
    return g, r * sec_m1, lt
