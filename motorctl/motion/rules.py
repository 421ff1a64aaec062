"""The planner's speed rules, axis by axis: the highest path speed and path acceleration each
piece of the blended path allows, and the highest speed through each join between two pieces
(docs/motion.md, "The planner").

Every rule is a limit of one axis projected on the path: on a piece whose unit tangent is t and
whose normal (towards the centre of its curvature κ) is n, axis i moves with

    ẋ_i = ṡ·t_i,    ẍ_i = s̈·t_i + ṡ²κ·n_i,    x⃛_i = (s⃛ − ṡ³κ²)·t_i + 3·s̈·ṡ·κ·n_i

(the Frenet frame of a curve of constant curvature), so a rule asks, for every axis i, that its
share of the tangent or the normal keeps within v_max_i, a_max_i and j_max_i. On an arc t and n
turn; each axis takes the largest |t_i| and |n_i| over the arc's sweep (:func:`extent`). A join's
curvature step v²·Δκ and kink v·Δt are spread by the second moving average over T2 (jerk
v²·Δκ·|n_i|/T2 and v·|Δt_i|/(T2·h)): with the curve's own v³κ², within ``JERK_STEP`` of each
axis's j_max. The path acceleration's own ramps, |Δs̈|/T1 through the first moving average
(``ramp`` = |Δs̈|/s̈ ≤ 2, or 1 where the profile's accelerations of opposite signs are T1
apart), and 3·s̈·ṡ·κ take the rest: on an arc what v³κ² leaves, about a join what its jerk
leaves (each zone's acceleration at its speed).

Per axis: ``vlim``, ``alim``, ``jlim`` (sequences of n_axes floats) [m/s, m/s², m/s³]; ``ix``,
``iy`` the indexes of X and Y among the axes (−1: absent).
"""

from __future__ import annotations

import math

from motorctl.motion.blend import Geo

#: share of each axis's a_max the normal acceleration v²κ may take on a curve (the speed it
#: bounds); the path acceleration takes what v²κ leaves at the piece's speed
NORMAL_SHARE = 0.75
#: share of each axis's j_max the jerk of moving on a curve at constant speed (ṡ³κ²) may take on
#: an arc (the speed it bounds); the path acceleration's ramps and 3·s̈·ṡ·κ take what is left
CURVE_SHARE = 0.75
#: share of each axis's j_max a join's curvature step and kink (spread over T2 by the second
#: moving average) take with the curve's own jerk there (the speed through the join); the path
#: acceleration's ramps about the join take what is left
JERK_STEP = 0.75


def _max_abs_cos(a: float, b: float) -> float:
    """max |cos φ| for φ between a and b [rad] (either order)."""
    lo, hi = min(a, b), max(a, b)
    if math.floor(hi / math.pi) >= math.ceil(lo / math.pi):
        return 1.0
    return max(abs(math.cos(lo)), abs(math.cos(hi)))


def extent(g: Geo, ix: int, iy: int) -> tuple[list[float], list[float]]:
    """(largest |t_i|, largest |n_i|) over the piece, per axis (lists of n_axes floats): a line's
    tangent is its direction (no normal); an arc's turn over its sweep (with the radius's change
    where its radii differ), its other axes moving along it (a helix)."""
    mt = [abs(float(x)) for x in g.u]
    mn = [0.0] * len(mt)
    if g.kind == 0:
        return mt, mn
    _, _, r0, r1, phi0, sweep = g.arc
    mc = _max_abs_cos(phi0, phi0 + sweep)
    ms = _max_abs_cos(phi0 - 0.5 * math.pi, phi0 + sweep - 0.5 * math.pi)
    length = g.length if g.length > 0 else 1.0
    turn = max(r0, r1) * abs(sweep) / length     # the path's d/ds: r·φ' along the circle,
    out = abs(r1 - r0) / length                   # r' outwards (radii that differ)
    mt[ix], mt[iy] = turn * ms + out * mc, turn * mc + out * ms   # t = r·φ'·(−sin φ, cos φ) + r'·(cos φ, sin φ)
    mn[ix], mn[iy] = mc, ms                       # n = −(cos φ, sin φ)
    return mt, mn


def _min_ratio(num, den) -> float:
    """min over the axes of num_i/den_i where den_i > 0 (inf when no axis has den_i > 0)."""
    out = math.inf
    for n, d in zip(num, den):
        if d > 0:
            out = min(out, n / d)
    return out


def piece_limits(g: Geo, vlim, alim, jlim, ix: int, iy: int, *,
                 tol_left: float, t1: float, t2: float, ramp: float) -> tuple[float, float]:
    """(path speed [m/s], path acceleration [m/s²]) a piece allows: the feed, each axis's v_max
    over its share of the tangent; a line's acceleration each a_max over |t_i|. On an arc of
    curvature κ also: the normal acceleration v²κ·|n_i| within NORMAL_SHARE·a_max_i, the second
    average's chord κ(v·T2)²/8 within ``tol_left`` [m] (what the blends left of P), the curve's
    jerk v³κ²·|t_i| within CURVE_SHARE·j_max_i; its acceleration what v²κ leaves of each
    a_max_i and what the ramps (ramp/T1 per unit of s̈) and 3·s̈·v·κ·|n_i| leave of j_max_i
    besides v³κ²·|t_i|, at that speed (X and Y, in the arc's plane, by the larger of the sum of
    the tangent's and the normal's shares and their root sum of squares, t ⊥ n). ``vlim``,
    ``alim``, ``jlim``: per axis."""
    mt, mn = extent(g, ix, iy)
    v = math.inf if g.feed is None else g.feed
    v = min(v, _min_ratio(vlim, mt))
    if g.kind == 0:
        return v, _min_ratio(alim, mt)
    kappa = 1.0 / max(min(g.arc[2], g.arc[3]), 1e-12)
    v = min(v, math.sqrt(_min_ratio([NORMAL_SHARE * a for a in alim], mn) / kappa))
    if math.isfinite(tol_left):
        v = min(v, math.sqrt(8.0 * max(tol_left, 0.0) / kappa) / t2)
    v = min(v, (_min_ratio([CURVE_SHARE * j for j in jlim], mt) / (kappa * kappa)) ** (1.0 / 3.0))
    a_n, j_n = v * v * kappa, v ** 3 * kappa * kappa          # normal acceleration, the curve's jerk
    acc = math.inf
    for i, (a, j, t, n) in enumerate(zip(alim, jlim, mt, mn)):
        # |A·t_i + a_n·n_i| ≤ A·|t_i| + a_n·|n_i|, and in the plane of the arc (t ⊥ n, t_i² + n_i²
        # ≤ 1) also ≤ √(A² + a_n²): the larger acceleration either bound allows; the jerk alike,
        # (ramp·A/T1 + ṡ³κ²) along t and 3·A·ṡ·κ along n
        a_sum = (a - a_n * n) / t if t > 0 else math.inf
        qa, qb = ramp / t1, 3.0 * v * kappa
        j_sum = (j - j_n * t) / (qa * t + qb * n) if qa * t + qb * n > 0 else math.inf
        if i in (ix, iy):
            a_sum = max(a_sum, math.sqrt(max(a * a - a_n * a_n, 0.0)))
            q2 = qa * qa + qb * qb
            disc = (qa * j_n) ** 2 - q2 * (j_n * j_n - j * j)
            if disc > 0:
                j_sum = max(j_sum, (-qa * j_n + math.sqrt(disc)) / q2)
        acc = min(acc, a_sum, j_sum)
    return v, max(acc, 0.0)


def join_frame(a: Geo, b: Geo, ix: int, iy: int) -> tuple[list[float], list[float], float]:
    """At the join a → b: (|n_i| of the normal, |Δt_i| of the tangent's step, per axis, and the
    kink [rad])."""
    ta, tb = a.tangents(ix, iy)[1], b.tangents(ix, iy)[0]
    dt = [float(q - p) for p, q in zip(ta, tb)]
    kink = 2.0 * math.asin(min(1.0, 0.5 * math.sqrt(sum(d * d for d in dt))))
    n = [0.0] * len(dt)
    if ix >= 0 and iy >= 0:
        mx, my = float(ta[ix] + tb[ix]), float(ta[iy] + tb[iy])
        h = math.hypot(mx, my)
        if h > 0:
            n[ix], n[iy] = abs(my) / h, abs(mx) / h
    return n, [abs(d) for d in dt], kink


def join_turn(a: Geo, b: Geo, ix: int, iy: int) -> float:
    """The signed angle [rad] the path turns by at the join a → b in XY (+ to the left, as
    :meth:`Geo.curvature`); 0 without X and Y."""
    if ix < 0 or iy < 0:
        return 0.0
    ta, tb = a.tangents(ix, iy)[1], b.tangents(ix, iy)[0]
    return math.atan2(float(ta[ix] * tb[iy] - ta[iy] * tb[ix]), float(ta[ix] * tb[ix] + ta[iy] * tb[iy]))


def _step_terms(a: Geo, b: Geo, ix: int, iy: int, t2: float, period: float, dkappa, kink: bool = True):
    """Per axis at the join a → b, the jerk's coefficients (c1, c2, c3) of v, v², v³ (the kink's
    v·|Δt_i|/(T2·h), the curvature step's v²·Δκ·|n_i|/T2, the curve's v³κ²·|t_i|), the normal
    |n_i|, the tangent's |t_i|, the larger curvature κ and the kink [rad]."""
    n, dt, angle = join_frame(a, b, ix, iy)
    ta, tb = a.tangents(ix, iy)[1], b.tangents(ix, iy)[0]
    t = [max(abs(float(p)), abs(float(q))) for p, q in zip(ta, tb)]
    dk = abs(b.curvature() - a.curvature()) if dkappa is None else dkappa
    kappa = max(abs(a.curvature()), abs(b.curvature()))
    c = [(d / (t2 * period) if kink else 0.0, dk * ni / t2, kappa * kappa * ti) for d, ni, ti in zip(dt, n, t)]
    return c, n, t, kappa, angle


def join_speed(a: Geo, b: Geo, jlim, ix: int, iy: int, *, t2: float, period: float, dev_left: float,
               dkappa: float | None = None, kink: bool = True) -> float:
    """The highest speed [m/s] through the join a → b: its curvature step Δκ (``dkappa``, else
    the two pieces' own) spread over T2 (jerk v²·Δκ·|n_i|/T2), its kink α's velocity step spread
    over T2 (an acceleration step v·|Δt_i|/T2 within one period h: jerk v·|Δt_i|/(T2·h)) and the
    curve's own jerk v³κ²·|t_i| there, their sum within JERK_STEP·j_max_i for every axis i; and
    the second average's distance from the path there within ``dev_left`` [m]: v·T2·α/8 across
    the kink (the window's centroid inside the corner), v²·Δκ·T2²/24 across the step. With
    ``kink`` False the step ``dkappa`` holds the kinks (as the curvature a sample sees) and the
    kink's own term is left out."""
    c, _, _, _, angle = _step_terms(a, b, ix, iy, t2, period, dkappa, kink)
    dk = abs(b.curvature() - a.curvature()) if dkappa is None else dkappa
    out = math.inf
    if math.isfinite(dev_left):
        if angle > 0:
            out = 8.0 * max(dev_left, 0.0) / (t2 * angle)
        if dk > 0:
            out = min(out, math.sqrt(24.0 * max(dev_left, 0.0) / (dk * t2 * t2)))
    for (c1, c2, c3), ji in zip(c, jlim):
        J = JERK_STEP * ji
        if c2 > 0:                           # the quadratic's root: above the cubic's
            v = (-c1 + math.sqrt(c1 * c1 + 4 * c2 * J)) / (2 * c2)
        elif c1 > 0:
            v = J / c1
        elif c3 > 0:
            v = (J / c3) ** (1.0 / 3.0)
        else:
            continue
        for _ in range(30):                  # Newton from above (the sum is convex in v ≥ 0)
            f = ((c3 * v + c2) * v + c1) * v - J
            if f <= 1e-12 * J:
                break
            v -= f / ((3 * c3 * v + 2 * c2) * v + c1)
        out = min(out, v)
    return out


def join_accel(a: Geo, b: Geo, v: float, alim, jlim, ix: int, iy: int, *,
               t1: float, t2: float, period: float, ramp: float, dkappa: float | None = None,
               kink: bool = True) -> float:
    """The path acceleration [m/s²] about the join a → b passed at ``v``: what the kink's
    acceleration v·|Δt_i|/T2 and the larger curvature's v²κ·|n_i| leave of each a_max_i along
    the tangent, and what the join's jerk at v (:func:`join_speed`'s terms, its step ``dkappa``
    as there) leaves of j_max_i to the ramps (ramp·s̈/T1·|t_i|) and 3·s̈·v·κ·|n_i|."""
    c, n, t, kappa, _ = _step_terms(a, b, ix, iy, t2, period, dkappa, kink)
    dt = join_frame(a, b, ix, iy)[1]
    t = [max(p, q) for p, q in zip(extent(a, ix, iy)[0], extent(b, ix, iy)[0])]
    if not math.isfinite(v):
        v = 0.0
    acc = _min_ratio([al - v * d / t2 - v * v * kappa * ni for al, d, ni in zip(alim, dt, n)], t)
    left = [j - ((c3 * v + c2) * v + c1) * v for j, (c1, c2, c3) in zip(jlim, c)]
    return max(0.0, min(acc, _min_ratio(left, [ramp / t1 * ti + 3.0 * v * kappa * ni for ti, ni in zip(t, n)])))
