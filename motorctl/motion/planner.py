"""The look-ahead path planner: a :class:`~motorctl.motion.gcode.Program` → a jerk-limited
:class:`Trajectory` of every axis, and Ruckig's point-to-point moves (docs/motion.md).

Path programs are planned in two stages, the scheme of FIR-filter interpolators (L. Biagiotti,
C. Melchiorri, "FIR filters for online trajectory planning with time- and frequency-domain
specifications", Control Engineering Practice 20 (2012) 1385-1399):

1. a *look-ahead* over the whole program: each line or arc gets its top path speed (the feed, each
   axis's v_max over its share of the tangent, the arc's centripetal budget), each corner its
   junction speed (0 at an exact stop G61, a dwell, a pause or a machine word; else bounded by the
   G64 tolerance and by the velocity step each axis can absorb), and a backward then a forward
   pass give an acceleration-limited (trapezoidal) path-speed profile through the corners;
2. every axis of that profile is passed through two moving averages of lengths T1 and T2
   (T2 = max over axes of 2 a_max/j_max): the result has |a| ≤ a_max because any T1 window of the
   profile changes the velocity by at most a_max·T1, and |j| ≤ 2 a_max/T2 ≤ j_max. The filter
   rounds each corner inside the convex hull of the path within (T1 + T2)·v of it, which is how
   the G64 tolerance bounds the junction speed; it delays the motion by (T1 + T2)/2 and ends at the
   program's end point exactly.

The filters act on the planner's grid (period ``period``, the loop's by default): setpoints on that
grid are the filtered profile exactly; :meth:`Trajectory.sample_into` at that period takes a fast
path (cumulative sums). Point-to-point moves use Ruckig (time-optimal, jerk-limited, Berscheid &
Kröger, "Jerk-limited real-time trajectory generation with arbitrary target states", RSS 2021).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from motorctl.motion.gcode import AXES, Arc, Dwell, Event, Line, Pause, Program

#: the loop's period [s] (5 kHz): the default grid of the filters
PERIOD_S = 2e-4
#: share of each axis's a_max the path-speed profile uses; the rest absorbs the corners'
#: velocity steps. On an arc, half of the share is the path acceleration and half the centripetal
#: v²/R, so a corner step next to an arc still finds the other half free
ACCEL_SHARE = 0.5
#: the arc tolerance used where G61 (exact stop) asks for none: the filters always round an arc
#: a little (its radius shrinks by v²(T1² + T2²)/(24 R))
EXACT_ARC_TOL_M = 1e-6
#: the filters' radial shrink of an arc is compensated: the arc is planned on the radius the
#: two moving averages shrink back onto the programmed one (PathTrajectory._shrink), the
#: enlargement faded in and out at the arc's ends over ARC_FADE of a filter window's path
#: (vp·(T1 + T2)), at most half the arc. Measured (benchmarks/bench_contour.py): 0.1 keeps the
#: cut path's lead-ins within P 0.01 mm at ARC_RESIDUAL 0.25 (8.8 µm), 0.3 does not (12.4 µm)
ARC_COMPENSATE = True
ARC_FADE = 0.1
#: the part of the uncompensated shrink v²(T1² + T2²)/(24 R) left once compensated (the fades,
#: speed changes on the arc) that the arc speed rule plans for: v ≤ √(12·R·P/((T1² + T2²)·0.25)),
#: twice the uncompensated rule's speed (measured, docs/motion.md "The planner")
ARC_RESIDUAL = 0.25
#: the rounding of program arithmetic (mm → m, centre + radius) a soft limit forgives [m]
ROUND_M = 1e-12


class LimitError(ValueError):
    """A program or move outside the soft limits: ``str()`` is one line naming the file:line, the
    axis, and how far outside [m]. Attributes: line (source line, 0 for a move), axis, excess_m."""

    def __init__(self, msg: str, line: int, axis: str, excess_m: float):
        self.line, self.axis, self.excess_m = line, axis, excess_m
        super().__init__(msg)


@dataclass(frozen=True)
class AxisLimits:
    """One axis's limits: v_max [m/s], a_max [m/s²], j_max [m/s³] (all > 0)."""

    v_max: float
    a_max: float
    j_max: float


class Trajectory:
    """Setpoints of n_axes axes over [0, duration].

    duration [s]; axes: the axis names (len n_axes); events: [(t [s], Event)] in time order (the
    time its output is set); stops: [(t [s], Pause)] (the trajectory is at rest at t: the caller
    holds its clock there until resume); start, end: the first and final positions, shape
    (n_axes,) [m].
    """

    axes: tuple[str, ...]
    duration: float
    start: np.ndarray
    end: np.ndarray
    events: list[tuple[float, Event]]
    stops: list[tuple[float, Pause]]

    def sample(self, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(x [m], v [m/s], a [m/s²]) at time t [s], each shape (n_axes,); before 0 the start at
        rest, after ``duration`` the end at rest."""
        out = np.empty((1, 3, len(self.axes)))
        self.sample_into(t, 1.0, out)
        return out[0, 0].copy(), out[0, 1].copy(), out[0, 2].copy()

    def sample_into(self, t0: float, dt: float, out: np.ndarray) -> None:
        """Fill out[k, 0:3, i] = (x, v, a) of axis i at t0 + k·dt for k < out.shape[0]
        (out shape (n, 3, n_axes), float64); the work is proportional to the block, not to the
        program."""
        raise NotImplementedError

    def line_at(self, t: float) -> int:
        """The source line of the segment being run at time t [s] (0 before the first)."""
        return 0


# ------------------------------------------------------------------------------ point to point
class RuckigTrajectory(Trajectory):
    """A Ruckig trajectory (offline, computed once) behind the :class:`Trajectory` interface;
    with ``direction`` (shape (n_axes,)) a one-axis trajectory of the path length s along it:
    x = start + s·direction."""

    def __init__(self, traj, axes: tuple[str, ...], start: np.ndarray, end: np.ndarray,
                 direction: np.ndarray | None = None):
        self._t = traj
        self._u = direction
        self.axes = axes
        self.duration = float(traj.duration)
        self.start, self.end = start, end
        self.events, self.stops = [], []

    def sample_into(self, t0: float, dt: float, out: np.ndarray) -> None:
        for k in range(out.shape[0]):
            t = t0 + k * dt
            if t >= self.duration:
                out[k, 0] = self.end
                out[k, 1:3] = 0.0
                continue
            p, v, a = self._t.at_time(max(t, 0.0))      # before 0: the state it starts from
            if self._u is None:
                out[k, 0], out[k, 1], out[k, 2] = p, v, a
            else:
                out[k, 0] = self.start + p[0] * self._u
                out[k, 1] = v[0] * self._u
                out[k, 2] = a[0] * self._u


def headroom(limits: Sequence[AxisLimits], speedup: float) -> list[AxisLimits]:
    """The limits to plan with so that the trajectory, run up to ``speedup`` (≥ 1) times faster
    (a time scaling by a feed override: v × r, a × r², j × r³), keeps ``limits``. Raises
    ValueError on speedup < 1."""
    if not speedup >= 1.0:
        raise ValueError(f"speedup {speedup}: must be >= 1")
    r = float(speedup)
    return [AxisLimits(lim.v_max / r, lim.a_max / r**2, lim.j_max / r**3) for lim in limits]


def override_cap(traj: Trajectory, limits: Sequence[AxisLimits], *, share: float = 0.0,
                 period: float = PERIOD_S, bin_s: float = 0.01, ahead_s: float = 0.0) -> np.ndarray:
    """The highest feed override (time scaling by r: v × r, a × r², j × r³) each stretch of a
    trajectory planned at the full ``limits`` can take and keep them: LinuxCNC's rule (the planner
    plans at the machine's limits, the override is capped where they would be passed).

    The trajectory is sampled on ``period``; per sample r = min over axes of v_max/|v|,
    √((1 − share)·a_max/|a|), ∛((1 − share)·j_max/|j|) (``share``: the part of a_max and j_max
    left to the override's own ramp, the terms p'·ḟ and 3p''·f·ḟ + p'·f̈ of the time scaling);
    the minimum over each bin of ``bin_s`` of path time, then over the bins from one before to
    ``ahead_s`` after (so that a ramp of the override started ``ahead_s`` early has come down
    in time). Returns shape (ceil(duration / bin_s) + 1,), values ≥ 0 (inf where nothing moves).
    Raises ValueError on share outside [0, 1)."""
    if not 0.0 <= share < 1.0:
        raise ValueError(f"share {share}: must be within [0, 1)")
    n = max(int(math.ceil(traj.duration / period)) + 2, 2)
    out = np.empty((n, 3, len(traj.axes)))
    traj.sample_into(0.0, period, out)
    v = np.abs(out[:, 1])
    a = np.abs(out[:, 2])
    j = np.zeros_like(a)
    j[1:] = np.abs(np.diff(out[:, 2], axis=0)) / period
    j[:-1] = np.maximum(j[:-1], j[1:])              # a jerk step belongs to both of its samples
    vm = np.array([lim.v_max for lim in limits])
    am = np.array([lim.a_max for lim in limits]) * (1.0 - share)
    jm = np.array([lim.j_max for lim in limits]) * (1.0 - share)
    with np.errstate(divide="ignore"):
        r = np.minimum(np.minimum(vm / v, np.sqrt(am / a)), np.cbrt(jm / j)).min(axis=1)
    per_bin = max(1, int(round(bin_s / period)))
    nb = int(math.ceil(n / per_bin))
    pad = np.full(nb * per_bin, np.inf)
    pad[:n] = r
    bins = pad.reshape(nb, per_bin).min(axis=1)
    k_ahead = int(math.ceil(ahead_s / (per_bin * period)))
    ext = np.concatenate([bins[:1], bins, np.full(k_ahead, bins[-1])])
    win = np.lib.stride_tricks.sliding_window_view(ext, k_ahead + 2)
    return win.min(axis=1)[:nb]


def point_to_point(start: Sequence[float], goal: Sequence[float], limits: Sequence[AxisLimits], *,
                   feed: float | None = None, axes: Sequence[str] | None = None,
                   velocity: Sequence[float] | None = None,
                   acceleration: Sequence[float] | None = None) -> Trajectory:
    """A coordinated move to rest at ``goal`` (shape (n_axes,) [m]) with synchronised arrival,
    each axis within its own limits (Ruckig). From rest: the straight line, as Ruckig's
    time-optimal jerk-limited profile of the path length s with the path's limits
    min over axes of (limit / |u_i|) (u the unit direction), so every axis arrives together on the
    line. From a moving state (``velocity``/``acceleration`` given and not 0: a new target in
    mid-move): Ruckig over all axes with time synchronisation (the path bends from the current
    motion into the goal). The path speed is ≤ ``feed`` [m/s] when given. Raises ValueError on a
    bad input (Ruckig's message)."""
    from ruckig import InputParameter, Result, Ruckig, Synchronization
    from ruckig import Trajectory as RTraj

    x0 = np.asarray(start, dtype=float)
    x1 = np.asarray(goal, dtype=float)
    n = x0.size
    if x1.size != n or len(limits) != n:
        raise ValueError(f"start, goal and limits must name the same {n} axes")
    d = x1 - x0
    dist = float(np.linalg.norm(d))
    names = tuple(axes) if axes is not None else tuple(AXES[:n])
    if feed is not None and not feed > 0:
        raise ValueError(f"feed {feed} m/s: must be > 0")
    at_rest = (velocity is None or not np.any(velocity)) and (acceleration is None or not np.any(acceleration))
    if at_rest and dist > 0.0:
        u = d / dist
        au = np.abs(u)
        nz = au > 0

        def path(attr):
            return float(np.min(np.array([getattr(lim, attr) for lim in limits])[nz] / au[nz]))

        inp = InputParameter(1)
        inp.current_position, inp.current_velocity, inp.current_acceleration = [0.0], [0.0], [0.0]
        inp.target_position, inp.target_velocity, inp.target_acceleration = [dist], [0.0], [0.0]
        inp.max_velocity = [min(path("v_max"), feed) if feed is not None else path("v_max")]
        inp.max_acceleration = [path("a_max")]
        inp.max_jerk = [path("j_max")]
        traj = RTraj(1)
        try:
            res = Ruckig(1).calculate(inp, traj)
        except RuntimeError as e:
            raise ValueError(f"move refused by the planner: {e}") from None
        if res not in (Result.Working, Result.Finished):
            raise ValueError(f"move refused by the planner: {res}")
        return RuckigTrajectory(traj, names, x0.copy(), x1.copy(), direction=u)
    vmax = np.array([lim.v_max for lim in limits])
    if feed is not None:
        if dist > 0:
            # each axis's share of the straight line: near it, this caps the path speed
            vmax = np.minimum(vmax, np.maximum(feed * np.abs(d) / dist, 1e-9))
    inp = InputParameter(n)
    inp.current_position = x0.tolist()
    inp.current_velocity = [0.0] * n if velocity is None else list(map(float, velocity))
    inp.current_acceleration = [0.0] * n if acceleration is None else list(map(float, acceleration))
    inp.target_position = x1.tolist()
    inp.target_velocity = [0.0] * n
    inp.target_acceleration = [0.0] * n
    inp.max_velocity = vmax.tolist()
    inp.max_acceleration = [lim.a_max for lim in limits]
    inp.max_jerk = [lim.j_max for lim in limits]
    inp.synchronization = Synchronization.Time
    traj = RTraj(n)
    try:
        res = Ruckig(n).calculate(inp, traj)
    except RuntimeError as e:   # ruckig raises on invalid input
        raise ValueError(f"move refused by the planner: {e}") from None
    if res not in (Result.Working, Result.Finished):
        raise ValueError(f"move refused by the planner: {res}")
    return RuckigTrajectory(traj, names, x0.copy(), x1.copy())


# ------------------------------------------------------------------------------ path programs
@dataclass
class _Piece:
    """One stretch of the unfiltered profile: a line, an arc, or a rest (length 0)."""

    kind: int                 # 0 line / rest, 1 arc
    line: int
    p0: np.ndarray            # start (n_axes,)
    p1: np.ndarray            # end
    u: np.ndarray             # line: unit tangent; arc: the non-XY axes' displacement per metre
    length: float
    vmax: float
    acc: float
    tol: float
    rest: float = 0.0         # a rest's duration [s]
    acc_alone: float = 0.0    # a line's path acceleration between two rests (no corner step near)
    arc: tuple[float, ...] = (0.0,) * 8   # an arc's cx, cy, r0, r1, phi0, sweep [m, rad], fades in, out [1]


def _tangents(p: _Piece, ix: int, iy: int) -> tuple[np.ndarray, np.ndarray]:
    """Unit tangents at the start and the end of a piece."""
    if p.kind == 0:
        return p.u, p.u
    out = []
    _, _, r0, r1, phi0, sweep = p.arc[:6]
    sgn = 1.0 if sweep > 0 else -1.0
    for phi in (phi0, phi0 + sweep):
        t = p.u * p.length                     # non-XY axes: their displacement
        planar = abs(sweep) * 0.5 * (r0 + r1)
        t[ix] = -math.sin(phi) * sgn * planar
        t[iy] = math.cos(phi) * sgn * planar
        out.append(t / np.linalg.norm(t))
    return out[0], out[1]


def _same_circle(a: _Piece, b: _Piece, tol_m: float = 1e-9) -> bool:
    """Whether arc piece ``b`` continues arc piece ``a`` on the same circle: both arcs, the same
    centre and radius within ``tol_m`` [m] (a's end radius, b's start radius), the same turning
    direction, b starting where a ends, no non-XY axis moving (a helix's pitch may change)."""
    if a.kind != 1 or b.kind != 1 or a.length == 0.0 or b.length == 0.0:
        return False
    ca, cb = a.arc, b.arc
    if abs(ca[0] - cb[0]) > tol_m or abs(ca[1] - cb[1]) > tol_m or abs(ca[3] - cb[2]) > tol_m:
        return False
    if ca[5] * cb[5] <= 0 or np.any(a.u != 0.0) or np.any(b.u != 0.0):
        return False
    return bool(np.all(np.abs(a.p1 - b.p0) <= tol_m))


class PathTrajectory(Trajectory):
    """A planned program: the unfiltered pieces and the two moving averages (module docstring)."""

    def __init__(self, axes, pieces_table, lines, ix, iy, n1, n2, period, start, end, events, stops):
        self.axes = tuple(axes)
        (self._t0, self._ta, self._tc, self._td, self._v0, self._vp, self._acc, self._la, self._lc,
         self._len, self._kind, self._p0, self._p1, self._u, self._arc) = pieces_table
        self._lines = lines
        self._ix, self._iy = ix, iy
        self.n1, self.n2, self.period = n1, n2, period
        self._m = n1 + n2 - 2
        self.delay = 0.5 * self._m * period
        w = np.convolve(np.ones(n1), np.ones(n2)) / (n1 * n2)
        self._w = w
        self.t_profile = float(self._t0[-1] + self._ta[-1] + self._tc[-1] + self._td[-1]) if len(self._t0) else 0.0
        self.duration = self.t_profile + (self._m + 1) * period
        self.start, self.end = start, end
        self.events, self.stops = events, stops

    def _shrink(self, om: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(g, dg/dω): the relative radius 1/S(ω) − 1 that the two moving averages of n1 and n2
        grid samples shrink back to 0 on a circle run at angular rate ω [rad/s], S the product
        of their gains sin(n ω h/2) / (n sin(ω h/2)) (Biagiotti & Melchiorri 2012: a moving
        average's frequency response); its derivative by central difference."""
        def g(w):
            s = np.ones_like(w)
            for n in (self.n1, self.n2):
                x = 0.5 * w * self.period
                small = np.abs(x) < 1e-9
                xs = np.where(small, 1.0, x)
                s = s * np.where(small, 1.0, np.sin(n * xs) / (n * np.sin(xs)))
            return 1.0 / s - 1.0
        om = np.asarray(om, dtype=float)
        e = 1e-3 + 1e-6 * np.abs(om)
        return g(om), (g(om + e) - g(om - e)) / (2 * e)

    # the unfiltered profile at times t (any shape) -> x, v of shape t.shape + (n_axes,)
    def _raw(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        t = np.asarray(t, dtype=float)
        k = np.clip(np.searchsorted(self._t0, t, side="right") - 1, 0, len(self._t0) - 1)
        tau = np.clip(t - self._t0[k], 0.0, None)
        ta, tc, td = self._ta[k], self._tc[k], self._td[k]
        v0, vp, acc, la, lc = self._v0[k], self._vp[k], self._acc[k], self._la[k], self._lc[k]
        t1 = np.minimum(tau, ta)
        s = v0 * t1 + 0.5 * acc * t1 * t1
        sd = np.where(tau < ta, v0 + acc * t1, vp)
        t2 = np.clip(tau - ta, 0.0, tc)
        s = s + vp * t2
        t3 = np.clip(tau - ta - tc, 0.0, td)
        s = s + np.where(tau > ta + tc, vp * t3 - 0.5 * acc * t3 * t3, 0.0)
        sd = np.where(tau > ta + tc, np.maximum(vp - acc * t3, 0.0), sd)
        done = tau >= ta + tc + td
        sd = np.where(done, 0.0, sd)
        length = self._len[k]
        s = np.where(done, length, np.minimum(s, length))
        p0, u = self._p0[k], self._u[k]
        x = p0 + s[..., None] * u
        v = sd[..., None] * u
        arc = self._kind[k] == 1
        if np.any(arc):
            cx, cy, r0, r1, phi0, sweep, fi, fo = (self._arc[k, i] for i in range(8))
            safe = np.where(length > 0, length, 1.0)
            f = s / safe
            phi = phi0 + sweep * f
            r = r0 + (r1 - r0) * f
            dphi = sweep / safe
            dr = (r1 - r0) / safe
            # the filters' radial shrink compensated (docs/motion.md, "The planner"): the arc is
            # planned on the radius r + delta that the two moving averages shrink back onto r at
            # the path speed sd, delta faded in over a fraction fi of the arc at its start and out
            # over fo at its end (0: no fade there, the next arc is the same circle; inf: none)
            sdd = np.where(tau < ta, acc, np.where((tau > ta + tc) & ~done, -acc, 0.0))
            fi1, fo1 = np.where(fi > 0, fi, 1.0), np.where(fo > 0, fo, 1.0)
            ri = np.where(fi > 0, f / fi1, np.inf)
            ro = np.where(fo > 0, (1.0 - f) / fo1, np.inf)
            wr = np.clip(np.minimum(ri, ro), 0.0, 1.0)
            dw = np.where((wr > 0) & (wr < 1), np.where(ri < ro, 1.0 / fi1, -1.0 / fo1), 0.0)
            rs = np.where(r > 0, r, 1.0)
            g, dg = self._shrink(sd / rs)
            delta = np.where(arc, r * g * wr, 0.0)
            ddelta = np.where(arc, g * r * dw * sd / safe + r * wr * dg * sdd / rs, 0.0)
            r = r + delta
            c, sn = np.cos(phi), np.sin(phi)
            ax, ay = self._ix, self._iy
            x[..., ax] = np.where(arc, cx + r * c, x[..., ax])
            x[..., ay] = np.where(arc, cy + r * sn, x[..., ay])
            v[..., ax] = np.where(arc, sd * (dr * c - r * dphi * sn) + ddelta * c, v[..., ax])
            v[..., ay] = np.where(arc, sd * (dr * sn + r * dphi * c) + ddelta * sn, v[..., ay])
        x = np.where(done[..., None], self._p1[k], x)
        return x, v

    def sample_into(self, t0: float, dt: float, out: np.ndarray) -> None:
        n = out.shape[0]
        h, m, n1, n2 = self.period, self._m, self.n1, self.n2
        if abs(dt - h) <= 1e-12 * h:
            g = t0 + (np.arange(-(m + 1), n)) * h                 # n + m + 1 grid points
            xg, vg = self._raw(g)
            c = np.cumsum(np.concatenate([np.zeros((1, xg.shape[1])), xg[1:]]), axis=0)
            x1 = (c[n1:] - c[:-n1]) / n1
            c = np.cumsum(np.concatenate([np.zeros((1, xg.shape[1])), x1]), axis=0)
            out[:, 0] = ((c[n2:] - c[:-n2]) / n2)[-n:]
            c = np.cumsum(np.concatenate([np.zeros((1, vg.shape[1])), vg[1:]]), axis=0)
            v1 = (c[n1:] - c[:-n1]) / n1
            c = np.cumsum(np.concatenate([np.zeros((1, vg.shape[1])), v1]), axis=0)
            out[:, 1] = ((c[n2:] - c[:-n2]) / n2)[-n:]
            a1 = (vg[n1:] - vg[:-n1]) / (n1 * h)
            c = np.cumsum(np.concatenate([np.zeros((1, vg.shape[1])), a1]), axis=0)
            out[:, 2] = ((c[n2:] - c[:-n2]) / n2)[-n:]
        else:
            t = t0 + np.arange(n) * dt
            g = t[:, None] - np.arange(m + 1) * h                     # (n, m + 1)
            xg, vg = self._raw(g)
            out[:, 0] = np.einsum("m,nma->na", self._w, xg)
            out[:, 1] = np.einsum("m,nma->na", self._w, vg)
            gb = t[:, None] - (np.arange(n2) + n1) * h
            _, vb = self._raw(gb)
            out[:, 2] = (vg[:, :n2].sum(axis=1) - vb.sum(axis=1)) / (n1 * n2 * h)
        t = t0 + np.arange(n) * dt
        late = t >= self.duration
        if np.any(late):
            out[late, 0] = self.end
            out[late, 1:3] = 0.0

    #: grid points computed at once by :meth:`sample` (the cache a streaming caller walks through)
    CACHE = 256

    def sample(self, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(x, v, a) at t [s] (each shape (n_axes,)): on the planner's grid (within 1e-6 of a
        period) the grid's setpoints exactly; between two grid points x and v interpolated by
        cubic Hermite polynomials (from x, v and v, a at both ends) and a linearly. Grid points
        are computed a block of :data:`CACHE` at a time (the fast path of :meth:`sample_into`),
        so a caller walking forward pays about 1 µs a call."""
        if t >= self.duration:
            z = np.zeros(len(self.axes))
            return self.end.copy(), z, z.copy()
        h = self.period
        q = t / h
        k = math.floor(q)
        frac = q - k
        if frac > 1.0 - 1e-6:
            k, frac = k + 1, 0.0
        elif frac < 1e-6:
            frac = 0.0
        c = getattr(self, "_cache", None)
        need_hi = k + (1 if frac else 0)
        if c is None or not (self._c0 <= k and need_hi < self._c0 + self.CACHE):
            if c is None:
                c = self._cache = np.empty((self.CACHE, 3, len(self.axes)))
            self._c0 = k
            self.sample_into(k * h, h, c)
        i = k - self._c0
        if frac == 0.0:
            return c[i, 0].copy(), c[i, 1].copy(), c[i, 2].copy()
        x0, v0, a0 = c[i]
        x1, v1, a1 = c[i + 1]
        s = frac
        h00, h10, h01, h11 = (2 * s**3 - 3 * s**2 + 1, s**3 - 2 * s**2 + s, -2 * s**3 + 3 * s**2, s**3 - s**2)
        x = h00 * x0 + h10 * h * v0 + h01 * x1 + h11 * h * v1
        v = h00 * v0 + h10 * h * a0 + h01 * v1 + h11 * h * a1
        return x, v, a0 + (a1 - a0) * s

    def line_at(self, t: float) -> int:
        tu = t - self.delay
        if tu < 0 or not len(self._t0):
            return 0
        k = int(np.searchsorted(self._t0, tu, side="right") - 1)
        return int(self._lines[min(k, len(self._lines) - 1)])


def _filter_lengths(limits: Sequence[AxisLimits], period: float) -> tuple[int, int]:
    """(N1, N2) samples of the two moving averages: T2 = max 2 a_max/j_max, T1 = T2."""
    t2 = max(2.0 * lim.a_max / lim.j_max for lim in limits)
    n2 = max(2, math.ceil(t2 / period - 1e-9))
    return n2, n2


def plan(program: Program, axes: Sequence[str], limits: Sequence[AxisLimits], *,
         feed_scale: float = 1.0, start: Sequence[float] | None = None,
         period: float = PERIOD_S) -> Trajectory:
    """Plan a parsed program for the machine's ``axes`` (letters among X Y Z, in the order of the
    arrays) with each axis's ``limits`` (module docstring: look-ahead, then two moving averages).

    feed_scale: multiplies every programmed feed (feed override; the axis limits still hold).
    start: the axes' positions [m] before the program (None: the program's start; a difference
    is closed by a first straight rapid). period: the grid of the filters [s] (the loop's).
    Raises ValueError on an axis the program moves that is not in ``axes``, or an arc whose plane
    (X and Y) is not among them.
    """
    axes = tuple(axes)
    if len(limits) != len(axes):
        raise ValueError(f"{len(axes)} axes and {len(limits)} limits")
    idx = [AXES.index(a) for a in axes]
    other = [i for i in range(3) if i not in idx]
    ix = axes.index("X") if "X" in axes else -1
    iy = axes.index("Y") if "Y" in axes else -1
    n1, n2 = _filter_lengths(limits, period)
    t1, t2 = n1 * period, n2 * period
    tw = t1 + t2
    vlim = np.array([lim.v_max for lim in limits])
    alim = np.array([lim.a_max for lim in limits])

    def proj(p):
        return np.asarray(p, dtype=float)[idx].copy()

    pos0 = proj(program.start) if start is None else np.asarray(start, dtype=float).copy()
    # ---- pieces, and "stops" (forced v = 0) between them
    pieces: list[_Piece] = []
    stop_after: list[bool] = []
    pending: list[tuple[str, object]] = []        # events/pauses after the piece index
    marks: list[tuple[int, object]] = []          # (piece index it follows, segment)
    cur = pos0.copy()

    def add_rest(seconds: float, line: int):
        pieces.append(_Piece(0, line, cur.copy(), cur.copy(), np.zeros(len(axes)), 0.0, 0.0, 0.0, 0.0,
                             rest=seconds))
        stop_after.append(True)

    def add_line(p1, feed, tol, line):
        nonlocal cur
        d = p1 - cur
        length = float(np.linalg.norm(d))
        if length <= 0.0:
            return
        u = d / length
        au = np.abs(u)
        with np.errstate(divide="ignore"):
            vmax = float(np.min(np.where(au > 0, vlim / np.where(au > 0, au, 1), np.inf)))
            amax = float(np.min(np.where(au > 0, alim / np.where(au > 0, au, 1), np.inf)))
        if feed is not None:
            vmax = min(vmax, feed * feed_scale)
        pieces.append(_Piece(0, line, cur.copy(), p1.copy(), u, length, vmax, ACCEL_SHARE * amax, tol,
                             acc_alone=amax))
        stop_after.append(tol == 0.0)
        cur = p1.copy()

    for seg in program.segments:
        if isinstance(seg, (Line, Arc)):
            for i in other:
                if seg.end[i] != seg.start[i]:
                    raise ValueError(f"{program.filename}:{seg.line}: the program moves {AXES[i]}, "
                                     f"not an axis of this machine ({' '.join(axes)})")
        if isinstance(seg, Line):
            p1 = proj(seg.end)
            if not pieces and np.any(proj(seg.start) != cur):
                add_line(proj(seg.start), None, 0.0, seg.line)
            add_line(p1, seg.feed, seg.tolerance, seg.line)
        elif isinstance(seg, Arc):
            if ix < 0 or iy < 0:
                raise ValueError(f"{program.filename}:{seg.line}: an arc needs axes X and Y "
                                 f"(this machine: {' '.join(axes)})")
            if not pieces and np.any(proj(seg.start) != cur):
                add_line(proj(seg.start), None, 0.0, seg.line)
            p0, p1 = proj(seg.start), proj(seg.end)
            length = seg.length
            r0 = seg.radius
            r1 = float(math.hypot(seg.end[0] - seg.center[0], seg.end[1] - seg.center[1]))
            dz = p1 - p0
            dz[ix] = dz[iy] = 0.0
            u = dz / length
            a_min = float(min(alim[ix], alim[iy]))
            vmax = min(seg.feed * feed_scale, float(min(vlim[ix], vlim[iy])))
            for i in range(len(axes)):
                if u[i] != 0.0:
                    vmax = min(vmax, vlim[i] / abs(u[i]))
            r = min(r0, r1)
            tol = seg.tolerance if seg.tolerance > 0 else EXACT_ARC_TOL_M
            # centripetal v²/R within half the share (ACCEL_SHARE); the filters' radial shrink v²(T1² + T2²)/(24 R) within half the tolerance
            vmax = min(vmax, math.sqrt(0.5 * ACCEL_SHARE * a_min * r))
            if math.isfinite(tol):
                vmax = min(vmax, math.sqrt(12.0 * r * tol / ((t1 * t1 + t2 * t2) * ARC_RESIDUAL)))
            phi0 = math.atan2(seg.start[1] - seg.center[1], seg.start[0] - seg.center[0])
            pc = _Piece(1, seg.line, p0, p1, u, length, vmax, 0.5 * ACCEL_SHARE * a_min, seg.tolerance,
                        arc=(float(seg.center[0]), float(seg.center[1]), r0, r1, phi0, seg.sweep, math.inf, math.inf))
            pieces.append(pc)
            stop_after.append(seg.tolerance == 0.0)
            cur = p1.copy()
        elif isinstance(seg, Dwell):
            add_rest(tw + seg.seconds, seg.line)
        elif isinstance(seg, Pause):
            add_rest(tw, seg.line)
            marks.append((len(pieces) - 1, seg))
        elif isinstance(seg, Event):
            if seg.synchronized:
                marks.append((len(pieces) - 1, seg))
            else:
                if not (pieces and pieces[-1].length == 0.0 and marks and marks[-1][0] == len(pieces) - 1
                        and isinstance(marks[-1][1], Event) and not marks[-1][1].synchronized):
                    add_rest(tw, seg.line)
                marks.append((len(pieces) - 1, seg))
    if not pieces:
        add_rest(0.0, 0)
    # ---- junction speeds: vj[k] between piece k and k+1; the end at rest. A corner the filters
    # cannot round within its tolerance becomes an exact stop with a rest of the filters' length
    # (their window then never holds both legs: the corner is kept exactly).
    npc = len(pieces)
    vj = np.zeros(npc)
    rest_after = [False] * npc
    for k in range(npc - 1):
        a, b = pieces[k], pieces[k + 1]
        if a.length == 0.0 or b.length == 0.0:
            continue
        if stop_after[k]:
            rest_after[k] = True
            continue
        ua = _tangents(a, ix, iy)[1]
        ub = _tangents(b, ix, iy)[0]
        du = ub - ua
        dn = float(np.linalg.norm(du))
        v = min(a.vmax, b.vmax)
        if dn > 1e-12:
            theta = 2.0 * math.asin(min(1.0, dn / 2.0))          # |du| = 2 sin(theta/2)
            g = math.sin(theta) if theta < math.pi / 2 else 1.0
            if math.isfinite(a.tol):
                # the filtered corner stays within g·(v_j·tw/2 + a·tw²/8) of the path (the legs'
                # points in the window, weighted): half the tolerance to each term
                a_corner = 0.5 * a.tol * 8.0 / (g * tw * tw)
                if a_corner < 0.5 * min(a.acc, b.acc):   # slower than stopping: stop
                    rest_after[k] = True
                    continue
                a.acc = min(a.acc, a_corner)
                b.acc = min(b.acc, a_corner)
                v = min(v, 0.5 * a.tol * 2.0 / (g * tw))
            # each axis's velocity step, with the corners of short neighbours in the same window,
            # within the acceleration share left by the path profile: v|du|(1 + v T1/l) <= (1-s) a T1
            ell = max(min(a.length, b.length), 1e-12)
            for i in range(len(axes)):
                di = abs(du[i])
                if di > 0:
                    cap = (1 - ACCEL_SHARE) * alim[i] * t1
                    qa, qb = di * t1 / ell, di
                    v = min(v, (-qb + math.sqrt(qb * qb + 4 * qa * cap)) / (2 * qa))
        vj[k] = v
    if any(rest_after):
        new_pieces: list[_Piece] = []
        where = []
        for k, p in enumerate(pieces):
            new_pieces.append(p)
            where.append(len(new_pieces) - 1)
            if rest_after[k]:
                new_pieces.append(_Piece(0, p.line, p.p1.copy(), p.p1.copy(), np.zeros(len(axes)), 0.0, 0.0,
                                         0.0, 0.0, rest=tw))
        vj_new = np.zeros(len(new_pieces))
        for k in range(npc):
            if not rest_after[k]:
                vj_new[where[k]] = vj[k]
        marks = [(where[k] if k >= 0 else k, seg) for k, seg in marks]
        pieces, vj, npc = new_pieces, vj_new, len(new_pieces)
    # a line between rests (or the ends) has no velocity step within a filter window of it: the
    # whole of each axis's a_max is its own
    for k, p in enumerate(pieces):
        if p.acc_alone > 0 and (k == 0 or pieces[k - 1].length == 0.0) and (
                k == npc - 1 or pieces[k + 1].length == 0.0):
            p.acc = p.acc_alone
    # backward and forward passes (look-ahead over the whole program)
    for k in range(npc - 2, -1, -1):
        b = pieces[k + 1]
        vj[k] = min(vj[k], math.sqrt(vj[k + 1] ** 2 + 2 * b.acc * b.length))
    vin = 0.0
    for k in range(npc):
        p = pieces[k]
        vj[k] = min(vj[k], math.sqrt(vin * vin + 2 * p.acc * p.length))
        vin = vj[k]
    # ---- per-piece trapezoids
    tab = {key: np.zeros(npc) for key in ("t0", "ta", "tc", "td", "v0", "vp", "acc", "la", "lc", "len", "kind")}
    na = len(axes)
    p0s, p1s, us = np.zeros((npc, na)), np.zeros((npc, na)), np.zeros((npc, na))
    arcs = np.zeros((npc, 8))
    t = 0.0
    v0 = 0.0
    t_end = np.zeros(npc)
    for k, p in enumerate(pieces):
        v1 = vj[k]
        if p.length == 0.0:
            ta = td = 0.0
            vp = la = lc = 0.0
            # a rest ends on the grid: a pause's stop time is then a grid point (exact setpoints)
            tc = max(math.ceil((t + p.rest) / period - 1e-9) * period - t, 0.0)
        else:
            a = p.acc
            vp = min(p.vmax, math.sqrt(max((2 * a * p.length + v0 * v0 + v1 * v1) / 2, 0.0)))
            vp = max(vp, v0, v1)
            ta = (vp - v0) / a
            td = (vp - v1) / a
            la = (vp * vp - v0 * v0) / (2 * a)
            ld = (vp * vp - v1 * v1) / (2 * a)
            lc = max(p.length - la - ld, 0.0)
            tc = lc / vp if vp > 0 else 0.0
        for key, val in (("t0", t), ("ta", ta), ("tc", tc), ("td", td), ("v0", v0), ("vp", vp),
                         ("acc", p.acc), ("la", la), ("lc", lc), ("len", p.length), ("kind", p.kind)):
            tab[key][k] = val
        p0s[k], p1s[k], us[k] = p.p0, p.p1, p.u
        if p.kind == 1:
            arcs[k] = p.arc
            if ARC_COMPENSATE and p.length > 0:        # the fade of the compensation: a filter window's path
                arcs[k, 6] = arcs[k, 7] = min(0.5, ARC_FADE * vp * tw / p.length)
        t += ta + tc + td
        t_end[k] = t
        v0 = v1
    # an arc that goes on as the same circle (the same centre and radius, turning the same way,
    # no stop between: a ballbar test's overshoot arcs, a circle programmed in parts) keeps its
    # compensation across the join: no fade out and in again, which would dip the setpoint inside
    # the circle there by the shrink itself
    for k in range(npc - 1):
        if _same_circle(pieces[k], pieces[k + 1]) and vj[k] > 0:        # (a stop: a rest piece between)
            arcs[k, 7] = arcs[k + 1, 6] = 0.0
    table = (tab["t0"], tab["ta"], tab["tc"], tab["td"], tab["v0"], tab["vp"], tab["acc"], tab["la"],
             tab["lc"], tab["len"], tab["kind"].astype(int), p0s, p1s, us, arcs)
    m = n1 + n2 - 2
    events: list[tuple[float, Event]] = []
    stops: list[tuple[float, Pause]] = []
    for k, seg in marks:
        te = t_end[k] if k >= 0 else 0.0
        if isinstance(seg, Pause):
            stops.append((te, seg))       # the window holds only the rest: at rest exactly
        elif seg.synchronized:
            events.append((te + 0.5 * m * period, seg))
        else:
            events.append((te, seg))
    events.sort(key=lambda e: e[0])
    return PathTrajectory(axes, table, np.array([p.line for p in pieces]), ix, iy, n1, n2, period,
                          pos0, pieces[-1].p1.copy(), events, stops)


def _arc_extremes(seg: Arc) -> list[tuple[int, float]]:
    """(axis index, value) of the arc's extreme points in X and Y (start, end, and the quadrant
    points it passes)."""
    out = [(0, float(seg.start[0])), (1, float(seg.start[1])), (0, float(seg.end[0])), (1, float(seg.end[1]))]
    phi0 = math.atan2(seg.start[1] - seg.center[1], seg.start[0] - seg.center[0])
    sw = seg.sweep
    r = max(seg.radius, float(math.hypot(seg.end[0] - seg.center[0], seg.end[1] - seg.center[1])))
    for q in range(4):
        ang = q * math.pi / 2
        rel = (ang - phi0) % (2 * math.pi) if sw > 0 else (phi0 - ang) % (2 * math.pi)
        if rel <= abs(sw):
            out.append((0, float(seg.center[0] + r * math.cos(ang))))
            out.append((1, float(seg.center[1] + r * math.sin(ang))))
    return out


def check_limits(program: Program, soft_limits: Mapping[str, tuple[float, float]],
                 offsets: Mapping[str, float] | None = None) -> None:
    """Refuse a program that leaves the soft limits anywhere on its path (arcs with their extreme
    points, the start of the first move included). The filters of :func:`plan` keep the path
    within the convex hull of the programmed one, so a program that passes here stays inside.

    soft_limits: axis letter → (soft_min, soft_max) [m] (axes not named: not checked); offsets:
    axis letter → shift [m] added to the program's machine coordinates (None: 0). Raises
    :class:`LimitError` naming the first offending line, the axis and how far outside [m]."""
    check_segments(program.segments, program.filename, soft_limits, offsets)


def check_segments(segments, filename: str, soft_limits: Mapping[str, tuple[float, float]],
                   offsets: Mapping[str, float] | None = None) -> None:
    """:func:`check_limits` of a program's segments (any iterable: a batch at a time, so that a
    program of any length is checked whole before anything moves, LinuxCNC's preview).
    ``filename`` is named in the error. Raises :class:`LimitError`."""
    shift = np.array([(offsets or {}).get(a, 0.0) for a in AXES])
    lo = np.array([soft_limits[a][0] if a in soft_limits else -np.inf for a in AXES]) - shift - ROUND_M
    hi = np.array([soft_limits[a][1] if a in soft_limits else np.inf for a in AXES]) - shift + ROUND_M

    def refuse(line: int, i: int, value: float) -> None:
        a = AXES[i]
        lo_a, hi_a = soft_limits[a]
        x = value + shift[i]
        excess = lo_a - x if x < lo_a else x - hi_a
        side = "soft_min" if x < lo_a else "soft_max"
        raise LimitError(f"{filename}:{line}: {a} reaches {x * 1e3:.4f} mm, "
                         f"{excess * 1e3:.4f} mm beyond {side} {(lo_a if x < lo_a else hi_a) * 1e3:.4f} mm "
                         f"(soft limits [{lo_a * 1e3:.4f}, {hi_a * 1e3:.4f}] mm)", line, a, float(excess))

    def check_one(seg) -> None:
        for p in (seg.start, seg.end):
            bad = (p < lo) | (p > hi)
            if bad.any():
                i = int(np.flatnonzero(bad)[0])
                refuse(seg.line, i, float(p[i]))
        if isinstance(seg, Arc):
            for i, v in _arc_extremes(seg):
                if not lo[i] <= v <= hi[i]:
                    refuse(seg.line, i, v)

    moves = [seg for seg in segments if isinstance(seg, (Line, Arc))]
    if not moves:
        return
    pts = np.array([seg.start for seg in moves] + [seg.end for seg in moves]).reshape(2, len(moves), 3)
    bad = ((pts < lo) | (pts > hi)).any(axis=2).any(axis=0)
    first = int(np.argmax(bad)) if bad.any() else len(moves)
    for seg in moves[:first + 1]:        # in program order: an arc's extreme may come first
        if isinstance(seg, Arc) or seg is moves[min(first, len(moves) - 1)]:
            check_one(seg)


def _at_rest_after(seg) -> bool:
    """True when the planned profile is at rest after ``seg`` whatever follows: a dwell, a
    pause, a machine word that is not synchronised with the motion (:func:`plan` puts a rest
    before it), a move in exact stop (G61: tolerance 0)."""
    if isinstance(seg, (Dwell, Pause)):
        return True
    if isinstance(seg, Event):
        return not seg.synchronized
    return seg.tolerance == 0.0


def windows(batches, *, soft: int = 1000, hard: int = 5000):
    """The segments of ``batches`` (iterables of segments in program order) regrouped into
    windows that each end where the path is at rest: the first point at rest after ``soft``
    moves (:func:`_at_rest_after`), or after ``hard`` moves when the program has none (the
    path then comes to rest there: an exact stop every ``hard`` moves). Each window planned
    alone with :func:`plan` from the previous one's end is the same motion as the whole program
    planned at once, up to those forced stops; memory is bounded by ``hard`` moves. Yields
    (segments, last): ``last`` True for the program's final window (known from the segment
    after it, read before the window is given). Raises ValueError on soft < 1 or hard < soft."""
    if not 1 <= soft <= hard:
        raise ValueError(f"windows: need 1 <= soft ({soft}) <= hard ({hard})")
    cur: list = []
    done = None                          # a full window, given once a segment follows it
    moves = 0
    for batch in batches:
        for seg in batch:
            if done is not None:
                yield done, False
                done = None
            cur.append(seg)
            if isinstance(seg, (Line, Arc)):
                moves += 1
            if moves >= hard or (moves >= soft and _at_rest_after(seg)):
                done, cur, moves = cur, [], 0
    if done is not None:
        yield done, not cur
    if cur:
        yield cur, True
