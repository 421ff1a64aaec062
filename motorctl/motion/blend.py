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
        t = getattr(self, "_tangents", None)
        if t is None:
            _, _, r0, r1, phi0, sweep = self.arc
            out = []
            for phi, r in ((phi0, r0), (phi0 + sweep, r1)):
                # d/df of (c + r(f)·(cos φ, sin φ)), φ = φ0 + sweep·f, r = r0 + (r1 − r0)·f: the
                # radius's change (a centre-format arc whose radii differ) turns the tangent outwards
                d = self.u * self.length
                d[ix] = (r1 - r0) * math.cos(phi) - r * sweep * math.sin(phi)
                d[iy] = (r1 - r0) * math.sin(phi) + r * sweep * math.cos(phi)
                out.append(d / math.sqrt(float(d @ d)))
            t = self._tangents = (out[0], out[1])
        return t

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
    back onto themselves. The arc's ``dev`` is its distance from the corner plus the legs' own
    (a merged line's): its largest distance from the programmed moves."""
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
            (b.feed if a.feed is None else min(a.feed, b.feed)), tol, a.src, dev=r * sec_m1 + max(a.dev, b.dev),
            arc=(float(c[0]), float(c[1]), r, r, phi0, sweep), blend=True)
    return g, r * sec_m1, lt


def _seg_dist(pts: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distance [m] of points (shape (n, 2)) from the segment a-b (shape (2,) each)."""
    ab = b - a
    l2 = float(ab @ ab)
    t = np.clip((pts - a) @ ab / l2, 0.0, 1.0) if l2 > 0 else np.zeros(len(pts))
    return np.linalg.norm(pts - (a + t[:, None] * ab), axis=1)


def _arc_dist(pts: np.ndarray, c: np.ndarray, r0: float, r1: float, phi0: float, sweep: float,
              ends: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """Distance [m] of points (shape (n, 2)) from the arc of centre c from angle phi0 over
    ``sweep`` [rad] (|sweep| < 2π), its radius r0 at the start and r1 at the end (linear in the
    angle, as :func:`motorctl.motion.path.contour_error` reads it), its end points ``ends``."""
    rel = pts - c
    ang = np.arctan2(rel[:, 1], rel[:, 0])
    frac = (ang - phi0) % (2 * np.pi) if sweep > 0 else (phi0 - ang) % (2 * np.pi)
    rr = r0 + (r1 - r0) * np.clip(frac / abs(sweep), 0.0, 1.0)
    on = np.abs(np.linalg.norm(rel, axis=1) - rr)
    off = np.minimum(np.linalg.norm(pts - ends[0], axis=1), np.linalg.norm(pts - ends[1], axis=1))
    return np.where(frac <= abs(sweep), np.minimum(on, off), off)


def reblend_arc(a: Geo, g: Geo, b: Geo, tol: float, ix: int, iy: int) -> Geo | None:
    """A short programmed arc ``g`` between two lines ``a`` → ``g`` → ``b`` that turns the way their
    corner does (a CAM post's kerf or fillet arc, 0.3 mm at 7°) replaced by the largest tangent arc
    between the two lines that stays within ``tol`` [m] of the programmed path (a, g and b) and
    whose ends lie within half of each line beyond g's ends (LinuxCNC's blend rule, the arc
    standing for the corner it rounds): the planner then passes the corner at the speed of the
    larger radius. The distance is that of 33 points of the new arc from the programmed pieces.
    Returns the new arc (its ``dev`` that distance plus the lines' own, a merged line's: its
    largest distance from the programmed moves; a and b are to be cut to its ends by the caller), or None when it gains nothing (radius within 5 % of g's), the pieces move other axes
    than X and Y, or the arc does not round that corner."""
    if ix < 0 or iy < 0 or a.kind != 0 or b.kind != 0 or g.kind != 1 or not tol > 0:
        return None
    others = [i for i in range(a.u.size) if i not in (ix, iy)]
    if others and (np.any(a.u[others] != 0.0) or np.any(b.u[others] != 0.0) or np.any(g.u[others] != 0.0)):
        return None
    cx, cy, r0, r1, phi0, sweep = g.arc
    ua = np.array([a.u[ix], a.u[iy]])
    ub = np.array([b.u[ix], b.u[iy]])
    cross = float(ua[0] * ub[1] - ua[1] * ub[0])
    theta = math.acos(float(np.clip(ua @ ub, -1.0, 1.0)))
    if theta <= 1e-6 or theta > math.pi - 1e-2 or cross * sweep <= 0 or abs(abs(sweep) - theta) > 0.1 * theta + 1e-3:
        return None
    r = min(r0, r1)
    half = 0.5 * theta
    sec_m1 = 1.0 / math.cos(half) - 1.0
    pa, pb = np.array([a.p1[ix], a.p1[iy]]), np.array([b.p0[ix], b.p0[iy]])
    # the corner the arc rounds: where the two lines meet
    m = np.column_stack([ua, ub])
    try:
        sa, _ = np.linalg.solve(m, pb - pa)
    except np.linalg.LinAlgError:
        return None
    v = pa + sa * ua
    da = float(np.linalg.norm(v - pa))                # the corner beyond a's end, before b's start
    db = float(np.linalg.norm(pb - v))
    tan_h = math.tan(half)
    r_room = min(da + 0.5 * a.length, db + 0.5 * b.length) / tan_h
    a0 = np.array([a.p0[ix], a.p0[iy]])
    b1 = np.array([b.p1[ix], b.p1[iy]])
    sgn = 1.0 if cross > 0 else -1.0
    n_a = np.array([-ua[1], ua[0]]) * sgn

    def arc_of(radius):
        ta = v - ua * radius * tan_h
        c = ta + radius * n_a
        p0 = math.atan2(ta[1] - c[1], ta[0] - c[0])
        return ta, v + ub * radius * tan_h, c, p0

    def dev_of(radius):
        ta, tb, c, p0 = arc_of(radius)
        ph = p0 + sgn * theta * np.linspace(0.0, 1.0, 33)
        pts = np.column_stack([c[0] + radius * np.cos(ph), c[1] + radius * np.sin(ph)])
        gend = (np.array([g.p0[ix], g.p0[iy]]), np.array([g.p1[ix], g.p1[iy]]))
        d = np.minimum(np.minimum(_seg_dist(pts, a0, pa), _seg_dist(pts, pb, b1)),
                       _arc_dist(pts, np.array([cx, cy]), r0, r1, phi0, sweep, gend))
        return float(d.max())

    big = min(r + tol / sec_m1, r_room)
    if not big > 1.05 * r:
        return None
    if dev_of(big) > tol:                            # the arc not quite tangent: the largest that fits
        lo, hi = r, big
        for _ in range(12):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if dev_of(mid) <= tol else (lo, mid)
        big = lo
        if not big > 1.05 * r:
            return None
    ta, tb, c, p0 = arc_of(big)
    q0, q1 = a.p1.copy(), b.p0.copy()
    q0[ix], q0[iy] = ta
    q1[ix], q1[iy] = tb
    return Geo(1, q0, q1, np.zeros(a.u.size), big * theta, g.line, g.feed, g.tol, g.src, dev=dev_of(big) + max(a.dev, b.dev),
               arc=(float(c[0]), float(c[1]), big, big, p0, sgn * theta), q=g.q)
