"""The look-ahead path planner: a :class:`~motorctl.motion.gcode.Program` → a jerk-limited
:class:`Trajectory` of every axis, and Ruckig's point-to-point moves (docs/motion.md).

Path programs are planned in three steps (docs/motion.md, "The planner"):

1. the *blended path* (:mod:`motorctl.motion.blend`): LinuxCNC's naive-CAM merge within G64 Q and
   a tangent arc at every line-line corner within G64 P; its lines and arcs are within P of the
   programmed moves by construction;
2. a *look-ahead* over the whole program: each piece limits the path speed and acceleration
   (the feed, each axis's v_max and a_max along the tangent, on an arc the normal acceleration
   v²κ, the jerk of moving on a curve 3·s̈·ṡ·κ + ṡ³κ², the second filter's chord), each join the
   speed through it (its curvature step and kink spread over T2 within JERK_STEP of j_max);
   each limit holds on a zone widened by v·(T1 + T2 + h) of path up to the nearest stop, and a
   backward then a forward pass give an acceleration-limited (trapezoidal) path-speed profile;
3. two moving averages (the scheme of FIR-filter interpolators: L. Biagiotti, C. Melchiorri,
   "FIR filters for online trajectory planning with time- and frequency-domain
   specifications", Control Engineering Practice 20 (2012) 1385-1399): the path length and
   speed through one of T1 = 2·max(a_max/j_max) (the path acceleration's ramps within j_max),
   the blended path at that length, the setpoints through one of T2 = SMOOTH_S (the joins'
   curvature steps spread over T2; an arc long enough is planned on the radius the average
   shrinks back onto its own). The motion is delayed by (T1 + T2)/2 and ends at the program's
   end point exactly.

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

from motorctl.motion import blend as _bl
from motorctl.motion.blend import Geo
from motorctl.motion.gcode import AXES, Arc, Dwell, Event, Line, Pause, Program

#: the loop's period [s] (5 kHz): the default grid of the filters
PERIOD_S = 2e-4
#: share of each axis's a_max (along the tangent) the path-speed profile uses on a curve and
#: around a join (the rest: the normal acceleration v²/R); a line's own zone uses all of it
ACCEL_SHARE = 0.5
#: share of each axis's j_max a join's curvature step and kink take (spread over T2 by the second
#: moving average); the rest is the path acceleration's ramps and, on a curve, the jerk of moving
#: on it (3·s̈·ṡ·κ + ṡ³κ²). A line alone takes all of it for its ramps
JERK_STEP = 0.5
#: the second moving average's length T2 [s]: it spreads a join's curvature step over T2
SMOOTH_S = 2e-3
#: a join or a blend the path could pass only below this share of its neighbours' speed is an
#: exact stop instead (stopping costs less than crawling through the widened speed zone)
STOP_SHARE = 0.35
#: a line shorter than this between two blends [m] is passed within one period at any speed
#: where its curvature steps would matter (docs/motion.md, "The planner")
REMNANT_M = 5e-7
#: the arc tolerance used where G61 (exact stop) asks for none [m]
EXACT_ARC_TOL_M = 1e-6
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
def _curve_speed(kappa: float, a_n: float, j_curve: float, tol_left: float, smooth_s: float) -> float:
    """The highest path speed [m/s] on a piece of curvature ``kappa`` [1/m] (> 0): the normal
    acceleration v²κ within ``a_n``; the short filter's deviation from the curve (the chord of
    a window of path v·T_c: κ(v·T_c)²/8) within ``tol_left`` [m]; of the jerk of moving on a
    curve, s⃛·t + 3·s̈·ṡ·κ·n − ṡ³κ²·t (the derivative of s̈·t + ṡ²κ·n), the term v³κ² within
    half of ``j_curve`` (the path acceleration a is then lowered so that 3·a·v·κ + v³κ² stays
    within it)."""
    v = math.sqrt(a_n / kappa)
    if math.isfinite(tol_left):
        v = min(v, math.sqrt(8.0 * max(tol_left, 0.0) / kappa) / smooth_s)
    return min(v, (0.5 * j_curve / (kappa * kappa)) ** (1.0 / 3.0))


def _join_speed(dkappa: float, kink: float, j_step: float, smooth_s: float, period: float) -> float:
    """The highest speed [m/s] through a join of two pieces whose curvature steps by ``dkappa``
    [1/m] and whose tangent turns by ``kink`` [rad]: the short filter of length T_c spreads the
    normal acceleration's step v²Δκ over T_c (jerk v²Δκ/T_c) and the velocity's step v·α over
    T_c (an acceleration step v·α/T_c in one period h: jerk v·α/(T_c·h)); their sum within
    ``j_step``."""
    a = dkappa / smooth_s
    b = kink / (smooth_s * period)
    if a <= 0 and b <= 0:
        return math.inf
    if a <= 0:
        return j_step / b
    return (-b + math.sqrt(b * b + 4 * a * j_step)) / (2 * a)


def _same_circle(a: Geo, b: Geo, tol_m: float = 1e-9) -> bool:
    """Whether arc ``b`` continues arc ``a`` on the same circle: both arcs, the same centre and
    radius within ``tol_m`` [m] (a's end radius, b's start radius), the same turning direction,
    b starting where a ends, no other axis moving."""
    if a.kind != 1 or b.kind != 1:
        return False
    ca, cb = a.arc, b.arc
    if abs(ca[0] - cb[0]) > tol_m or abs(ca[1] - cb[1]) > tol_m or abs(ca[3] - cb[2]) > tol_m:
        return False
    if ca[5] * cb[5] <= 0 or np.any(a.u != 0.0) or np.any(b.u != 0.0):
        return False
    return bool(np.all(np.abs(a.p1 - b.p0) <= tol_m))


class PathTrajectory(Trajectory):
    """A planned program: the blended path, the path-speed profile and its two moving averages
    (module docstring)."""

    def __init__(self, axes, prof, geo, ix, iy, n1, n2, period, start, end, events, stops):
        self.axes = tuple(axes)
        (self._t0, self._ta, self._tc, self._td, self._v0, self._vp, self._acc, self._la, self._lc,
         self._len, self._s0, self._lines) = prof
        (self._gs0, self._glen, self._kind, self._p0, self._p1, self._u, self._arc) = geo
        self._ix, self._iy = ix, iy
        self.n1, self.n2, self.period = n1, n2, period
        self._m = n1 + n2 - 2
        self.delay = 0.5 * self._m * period
        self.t_profile = float(self._t0[-1] + self._ta[-1] + self._tc[-1] + self._td[-1]) if len(self._t0) else 0.0
        self.duration = self.t_profile + (n1 + n2 + 1) * period
        self.start, self.end = start, end
        self.events, self.stops = events, stops

    def _shrink(self, om: np.ndarray) -> np.ndarray:
        """1/S(ω) − 1: the relative radius the short moving average of n2 samples shrinks back
        to 0 on a circle run at angular rate ω [rad/s], S its gain sin(n ω h/2)/(n sin(ω h/2))
        (a moving average's frequency response)."""
        x = 0.5 * np.asarray(om, dtype=float) * self.period
        small = np.abs(x) < 1e-9
        xs = np.where(small, 1.0, x)
        s = np.where(small, 1.0, np.sin(self.n2 * xs) / (self.n2 * np.sin(xs)))
        return 1.0 / s - 1.0

    def _profile(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The unfiltered path-speed profile: (s [m], ṡ [m/s]) at times t (any shape)."""
        k = np.clip(np.searchsorted(self._t0, t, side="right") - 1, 0, len(self._t0) - 1)
        tau = np.clip(t - self._t0[k], 0.0, None)
        ta, tc, td = self._ta[k], self._tc[k], self._td[k]
        v0, vp, acc = self._v0[k], self._vp[k], self._acc[k]
        t1 = np.minimum(tau, ta)
        s = v0 * t1 + 0.5 * acc * t1 * t1
        sd = np.where(tau < ta, v0 + acc * t1, vp)
        s = s + vp * np.clip(tau - ta, 0.0, tc)
        t3 = np.clip(tau - ta - tc, 0.0, td)
        dec = tau > ta + tc
        s = s + np.where(dec, vp * t3 - 0.5 * acc * t3 * t3, 0.0)
        sd = np.where(dec, np.maximum(vp - acc * t3, 0.0), sd)
        done = tau >= ta + tc + td
        sd = np.where(done, 0.0, sd)
        length = self._len[k]
        s = np.where(done, length, np.minimum(s, length))
        return self._s0[k] + s, sd

    def _path(self, s: np.ndarray, sd: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The blended path's point and velocity at path length s moving at ṡ (shapes s.shape +
        (n_axes,)); arcs on the radius the short filter shrinks back onto theirs."""
        k = np.clip(np.searchsorted(self._gs0, s, side="right") - 1, 0, len(self._gs0) - 1)
        length = self._glen[k]
        sig = np.clip(s - self._gs0[k], 0.0, length)
        u = self._u[k]
        x = self._p0[k] + sig[..., None] * u
        v = sd[..., None] * u
        arc = self._kind[k] == 1
        if np.any(arc):                                    # the arcs' points only
            sel = np.nonzero(arc)
            ka, sg, sda, la = k[sel], sig[sel], sd[sel], length[sel]
            cx, cy, r0, r1, phi0, sweep, fi, fo = (self._arc[ka, i] for i in range(8))
            safe = np.where(la > 0, la, 1.0)
            f = sg / safe
            phi = phi0 + sweep * f
            r = r0 + (r1 - r0) * f
            dphi = sweep / safe
            dr = (r1 - r0) / safe
            rs = np.where(r > 0, r, 1.0)
            g = self._shrink(sda * np.abs(dphi))
            # the compensation faded in over fi of path at the arc's start and out over fo at
            # its end (0: none there, the same circle goes on; < 0: not compensated), by a
            # smoothstep of the path (the radial velocity it adds starts and ends at 0)
            wi = np.where(fi > 0, sg / np.where(fi > 0, fi, 1.0), np.inf)
            wo = np.where(fo > 0, (la - sg) / np.where(fo > 0, fo, 1.0), np.inf)
            u_ = np.clip(np.minimum(wi, wo), 0.0, 1.0)
            du = np.where((u_ > 0) & (u_ < 1), np.where(wi < wo, 1.0 / np.where(fi > 0, fi, 1.0),
                                                       -1.0 / np.where(fo > 0, fo, 1.0)), 0.0)
            w = u_ * u_ * (3.0 - 2.0 * u_)
            dw = 6.0 * u_ * (1.0 - u_) * du
            g = np.where((fi < 0) | (fo < 0), 0.0, g)
            rr = r + rs * g * w
            c, sn = np.cos(phi), np.sin(phi)
            radial = sda * (dr + rs * g * dw)
            ax, ay = self._ix, self._iy
            x[sel + (ax,)] = cx + rr * c
            x[sel + (ay,)] = cy + rr * sn
            v[sel + (ax,)] = radial * c - sda * rr * dphi * sn
            v[sel + (ay,)] = radial * sn + sda * rr * dphi * c
        return x, v

    def _filtered(self, t: np.ndarray, n_out: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """x, v, a (each (rows, n_out, n_axes)) at the last n_out of each row of grid times t
        (shape (rows, n_out + n1 + n2), spaced by the period): s and ṡ through the moving
        average of n1, the path at s, then x and v through the moving average of n2, a the
        backward difference of v."""
        n1, n2, h = self.n1, self.n2, self.period
        s, sd = self._profile(t)
        ref = s[:, :1]
        z = np.zeros((s.shape[0], 1))
        c = np.cumsum(np.concatenate([z, s - ref], axis=1), axis=1)
        sf = (c[:, n1:] - c[:, :-n1]) / n1 + ref
        c = np.cumsum(np.concatenate([z, sd], axis=1), axis=1)
        sdf = (c[:, n1:] - c[:, :-n1]) / n1
        xr, vr = self._path(sf, sdf)                              # (rows, n_out + n2 + 1, na)
        xref = xr[:, :1]
        z = np.zeros((xr.shape[0], 1, xr.shape[2]))
        c = np.cumsum(np.concatenate([z, xr - xref], axis=1), axis=1)
        x = (c[:, n2:] - c[:, :-n2]) / n2 + xref
        c = np.cumsum(np.concatenate([z, vr], axis=1), axis=1)
        v = (c[:, n2:] - c[:, :-n2]) / n2
        a = (vr[:, n2:] - vr[:, :-n2]) / (n2 * h)
        return x[:, -n_out:], v[:, -n_out:], a[:, -n_out:]

    def sample_into(self, t0: float, dt: float, out: np.ndarray) -> None:
        n = out.shape[0]
        h, n1, n2 = self.period, self.n1, self.n2
        if abs(dt - h) <= 1e-12 * h:
            g = t0 + np.arange(-(n1 + n2), n) * h
            x, v, a = self._filtered(g[None, :], n)
            out[:, 0], out[:, 1], out[:, 2] = x[0], v[0], a[0]
        else:
            t = t0 + np.arange(n) * dt
            for lo in range(0, n, 256):                      # the filters anchored at each t
                tt = t[lo:lo + 256]
                g = tt[:, None] + np.arange(-(n1 + n2), 1) * h
                x, v, a = self._filtered(g, 1)
                out[lo:lo + len(tt), 0], out[lo:lo + len(tt), 1], out[lo:lo + len(tt), 2] = x[:, 0], v[:, 0], a[:, 0]
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
    """(N1, N2) samples of the two moving averages: T1 (of the path speed) = 2·max(a_max/j_max),
    so that a line's path acceleration ramps between ±a_max within each axis's j_max (the
    moving average of a velocity whose slope steps by 2a has the jerk 2a/T1); T2 (of the
    setpoints) = SMOOTH_S."""
    ratio = max(lim.a_max / lim.j_max for lim in limits)
    n1 = max(2, math.ceil(2.0 * ratio / period - 1e-9))
    n2 = max(2, int(round(SMOOTH_S / period)))
    return n1, n2


def _speed_zones(starts, ends, vs, accs, breaks, total):
    """The smallest speed and acceleration over zones [starts, ends] (arrays) on each elementary
    interval between the sorted points ``breaks`` (the zones' ends and the pieces' joins within
    [0, total]): (lo, hi, v, acc) per interval."""
    import heapq
    pts = np.unique(np.clip(np.concatenate([breaks, starts, ends]), 0.0, total))
    order = np.argsort(starts, kind="stable")
    hv: list = []
    ha: list = []
    out_v = np.empty(len(pts) - 1)
    out_a = np.empty(len(pts) - 1)
    j = 0
    nz = len(order)
    for i in range(len(pts) - 1):
        lo, hi = pts[i], pts[i + 1]
        while j < nz and starts[order[j]] <= lo:
            z = order[j]
            heapq.heappush(hv, (vs[z], ends[z]))
            heapq.heappush(ha, (accs[z], ends[z]))
            j += 1
        while hv and hv[0][1] < hi:
            heapq.heappop(hv)
        while ha and ha[0][1] < hi:
            heapq.heappop(ha)
        out_v[i] = hv[0][0] if hv else math.inf
        out_a[i] = ha[0][0] if ha else math.inf
    return pts[:-1], pts[1:], out_v, out_a


def plan(program: Program, axes: Sequence[str], limits: Sequence[AxisLimits], *,
         feed_scale: float = 1.0, start: Sequence[float] | None = None,
         period: float = PERIOD_S) -> Trajectory:
    """Plan a parsed program for the machine's ``axes`` (letters among X Y Z, in the order of the
    arrays) with each axis's ``limits`` (module docstring: the blended path, the look-ahead, the
    two moving averages).

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
    na = len(axes)
    n1, n2 = _filter_lengths(limits, period)
    t_c = n2 * period
    t_s = n1 * period
    tw = (n1 + n2 + 1) * period                         # a rest: both windows held in it
    vlim = np.array([lim.v_max for lim in limits])
    alim = np.array([lim.a_max for lim in limits])
    jlim = np.array([lim.j_max for lim in limits])
    a_min, j_min = float(alim.min()), float(jlim.min())
    a_n = (1.0 - ACCEL_SHARE) * a_min
    a_curve = ACCEL_SHARE * a_min
    t_s0 = _filter_lengths(limits, period)[0] * period
    a_join = min(a_curve, 0.5 * (1.0 - JERK_STEP) * j_min * t_s0)   # ramps 2a/T1 beside a join's step

    def proj(p):
        return np.asarray(p, dtype=float)[idx].copy()

    pos0 = proj(program.start) if start is None else np.asarray(start, dtype=float).copy()
    # ---- the programmed moves, and what follows each: (kind, seconds, segment)
    moves: list[Geo] = []
    after: dict[int, list] = {}
    cur = pos0.copy()

    def act(kind, seconds, seg):
        after.setdefault(len(moves) - 1, []).append((kind, seconds, seg))

    def add(g):
        nonlocal cur
        if g is not None:
            moves.append(g)
            cur = g.p1.copy()

    for seg in program.segments:
        if isinstance(seg, (Line, Arc)):
            for i in other:
                if seg.end[i] != seg.start[i]:
                    raise ValueError(f"{program.filename}:{seg.line}: the program moves {AXES[i]}, "
                                     f"not an axis of this machine ({' '.join(axes)})")
            if not moves and np.any(proj(seg.start) != cur):
                add(_bl.line_geo(cur, proj(seg.start), seg.line, None, 0.0, -1))
        if isinstance(seg, Line):
            feed = None if seg.feed is None else seg.feed * feed_scale
            add(_bl.line_geo(cur, proj(seg.end), seg.line, feed, seg.tolerance, len(moves),
                             getattr(seg, "naive_cam", 0.0)))
        elif isinstance(seg, Arc):
            if ix < 0 or iy < 0:
                raise ValueError(f"{program.filename}:{seg.line}: an arc needs axes X and Y "
                                 f"(this machine: {' '.join(axes)})")
            p0, p1 = proj(seg.start), proj(seg.end)
            dz = p1 - p0
            dz[ix] = dz[iy] = 0.0
            r1 = float(math.hypot(seg.end[0] - seg.center[0], seg.end[1] - seg.center[1]))
            phi0 = math.atan2(seg.start[1] - seg.center[1], seg.start[0] - seg.center[0])
            add(Geo(1, p0, p1, dz / seg.length, seg.length, seg.line, seg.feed * feed_scale, seg.tolerance,
                    len(moves), arc=(float(seg.center[0]), float(seg.center[1]), seg.radius, r1, phi0, seg.sweep)))
        elif isinstance(seg, Dwell):
            act("rest", seg.seconds, seg)
        elif isinstance(seg, Pause):
            act("pause", 0.0, seg)
        elif isinstance(seg, Event):
            act("event" if seg.synchronized else "word", 0.0, seg)
    for k, g in enumerate(moves):
        g.src = k
    stop_after = [g.tol == 0.0 or any(a[0] != "event" for a in after.get(k, ())) for k, g in enumerate(moves)]
    barrier = [stop_after[k] or k in after for k in range(len(moves))]
    geos = _bl.merge_collinear(moves, barrier)

    # ---- each piece's own limits
    def base(g: Geo) -> tuple[float, float]:
        """(speed, path acceleration) of one piece."""
        v = math.inf if g.feed is None else g.feed
        au = np.abs(g.u)
        if g.kind == 0:
            nz = au > 0
            v = min(v, float(np.min(vlim[nz] / au[nz])))
            return v, float(np.min(alim[nz] / au[nz]))        # no normal acceleration on a line
        v = min(v, float(min(vlim[ix], vlim[iy])))
        for i in range(na):
            if au[i] > 0:
                v = min(v, vlim[i] / au[i])
        kappa = 1.0 / max(min(g.arc[2], g.arc[3]), 1e-12)
        tol = g.tol if g.tol > 0 else EXACT_ARC_TOL_M
        j_c = (1.0 - JERK_STEP) * j_min
        v = min(v, _curve_speed(kappa, a_n, j_c, tol - g.dev, t_c))
        # the path acceleration's ramps 2·a/T1 and the curve's 3·a·v·κ + v³κ² share j_c
        return v, min(a_curve, (j_c - v ** 3 * kappa * kappa) / (2.0 / t_s + 3.0 * v * kappa))

    # ---- corners: a blend arc between two lines within the tolerance, a join where the tangent
    # goes on (a curvature step, a kink small enough for the short filter), else an exact stop
    path: list[Geo] = []
    join_v: list[float] = []              # join_v[k]: the speed through the join after path[k]; 0: stop
    room = {}
    for g in geos:
        if g.kind == 0:
            room[id(g)] = 0.5 * g.length
    for g in geos:
        if not path:
            path.append(g)
            continue
        a = path[-1]
        stop = a.tol == 0.0 or stop_after[a.src] or (a.blend and stop_after[path[-2].src])
        if stop:
            join_v.append(0.0)
            path.append(g)
            continue
        ta, tb = a.tangents(ix, iy)[1], g.tangents(ix, iy)[0]
        kink = 2.0 * math.asin(min(1.0, 0.5 * float(np.linalg.norm(tb - ta))))
        va, vb = base(a)[0], base(g)[0]
        v_near = min(va, vb)
        if kink <= _bl.TANGENT_RAD:
            vj = _join_speed(abs(g.curvature() - a.curvature()), 0.0, JERK_STEP * j_min, t_c, period)
            join_v.append(vj if vj >= STOP_SHARE * v_near else 0.0)
            path.append(g)
            continue
        vk = _join_speed(abs(g.curvature() - a.curvature()), kink, JERK_STEP * j_min, t_c, period)
        if vk >= STOP_SHARE * v_near:     # a kink the short filter rounds at that speed
            join_v.append(vk)
            path.append(g)
            continue
        done = False
        if a.kind == 0 and g.kind == 0 and a.tol > 0:
            tol = _bl.BLEND_SHARE * (a.tol - max(a.dev, g.dev)) if math.isfinite(a.tol) else math.inf
            bl = _bl.corner_blend(a, g, tol, room[id(a)], room[id(g)], ix, iy) if tol > 0 else None
            if bl is not None:
                arc, dev, lt = bl
                arc.tol = a.tol                   # the program's P (the blend used a share of it)
                kappa = 1.0 / arc.arc[2]
                v_arc = min(base(arc)[0], _join_speed(kappa, 0.0, JERK_STEP * j_min, t_c, period))
                if v_arc >= STOP_SHARE * v_near:
                    a.p1 = arc.p0.copy()
                    a.length = float(np.linalg.norm(a.p1 - a.p0))
                    g.p0 = arc.p1.copy()
                    g.length = float(np.linalg.norm(g.p1 - g.p0))
                    join_v.append(_join_speed(kappa, 0.0, JERK_STEP * j_min, t_c, period))
                    path.append(arc)
                    join_v.append(_join_speed(kappa, 0.0, JERK_STEP * j_min, t_c, period))
                    path.append(g)
                    done = True
        if not done:
            join_v.append(0.0)
            path.append(g)
    # a line left shorter than REMNANT_M between two pieces (two blends' ends nearly meeting) lies
    # between two samples at any speed where it matters: its joins are one step, from the piece
    # before it to the piece after
    for k in range(1, len(path) - 1):
        g = path[k]
        if g.kind == 0 and g.length < REMNANT_M and join_v[k - 1] > 0 and join_v[k] > 0:
            vj = _join_speed(abs(path[k + 1].curvature() - path[k - 1].curvature()), 0.0, JERK_STEP * j_min,
                             t_c, period)
            join_v[k - 1] = join_v[k] = max(min(join_v[k - 1], join_v[k]), vj)

    # drop pieces a blend left without length (their joins merge: the smaller speed)
    keep_p, keep_j = [], []
    last_of: dict[int, int] = {}          # programmed move -> the path piece it ends with
    for k, g in enumerate(path):
        drop = (g.length <= 1e-12 and g.kind == 0 and 0 < k < len(path) - 1 and join_v[k - 1] > 0
                and join_v[k] > 0)
        if drop:
            keep_j[-1] = min(keep_j[-1], join_v[k])
        else:
            keep_p.append(g)
            if k < len(join_v):
                keep_j.append(join_v[k])
        if not g.blend:
            for src in (g.merged or [g.src]):
                last_of[src] = len(keep_p) - 1
    path, join_v = keep_p, keep_j
    # ---- the speed zones: each piece's limits on its length, each join's at its point, each
    # widened by v·(T1 + T2) on both sides: the moving averages then never carry a faster part
    # of the profile into it (the path length their windows span at speed v)
    npth = len(path)
    gs0 = np.zeros(npth)
    for k in range(1, npth):
        gs0[k] = gs0[k - 1] + path[k - 1].length
    total = float(gs0[-1] + path[-1].length) if npth else 0.0
    zs, ze, zv, za = [], [], [], []
    for k, g in enumerate(path):
        v, acc = base(g)
        d = v * tw if math.isfinite(v) else total
        zs.append(gs0[k] - d)
        ze.append(gs0[k] + g.length + d)
        zv.append(v)
        za.append(acc)
    for k, vj in enumerate(join_v):
        if vj > 0 and math.isfinite(vj):
            s = gs0[k + 1]
            zs.append(s - vj * tw)
            ze.append(s + vj * tw)
            zv.append(vj)
            za.append(a_join)                 # the join's step takes JERK_STEP: the path's ramps the rest
    # a stop's rest holds both windows: nothing is carried across it, the zones end there
    stops_s = np.array([0.0] + [gs0[k + 1] for k in range(npth - 1) if join_v[k] == 0.0] + [total])
    if zs:
        za_s, ze_s = np.array(zs), np.array(ze)
        home = np.array([gs0[k] for k in range(npth)] + [gs0[k + 1] for k, vj in enumerate(join_v)
                                                          if vj > 0 and math.isfinite(vj)])
        i_lo = np.searchsorted(stops_s, home, side="right") - 1
        i_hi = np.searchsorted(stops_s, home + np.array([g.length for g in path] + [0.0] * (len(home) - npth)),
                               side="left")
        zs = list(np.maximum(za_s, stops_s[np.clip(i_lo, 0, len(stops_s) - 1)]))
        ze = list(np.minimum(ze_s, stops_s[np.clip(i_hi, 0, len(stops_s) - 1)]))
    if npth:
        lo, hi, iv, ia = _speed_zones(np.array(zs), np.array(ze), np.array(zv), np.array(za),
                                      np.concatenate([gs0, [total]]), total)
    else:
        lo = hi = iv = ia = np.zeros(0)
    # ---- the profile's pieces: the intervals, and rests where the path stops
    stop_at = {}                            # path index k -> rest actions after it
    for k in range(npth - 1):
        if join_v[k] == 0.0:
            stop_at[k] = []
    events_after: dict[int, list] = {}
    for src, acts in after.items():
        k = last_of.get(src, -1) if src >= 0 else -1
        for kind, sec, seg in acts:
            if kind == "event":
                events_after.setdefault(k, []).append(seg)
            else:
                stop_at.setdefault(k, []).append((kind, sec, seg))
    P_len, P_v, P_acc, P_rest, P_s0, P_line = [], [], [], [], [], []
    marks: list[tuple[int, object]] = []
    synced: list[tuple[int, object]] = []

    def rest(seconds, line, s):
        P_len.append(0.0); P_v.append(0.0); P_acc.append(0.0); P_rest.append(seconds)
        P_s0.append(s); P_line.append(line)

    def rests_at(k, s, line):
        prev_word = False
        for kind, sec, seg in stop_at.get(k, []):
            if kind == "word":
                if not prev_word:
                    rest(tw, seg.line, s)
                prev_word = True
            else:
                rest(tw + sec, seg.line, s)
                prev_word = False
            if kind != "rest":
                marks.append((len(P_len) - 1, seg))
        if not stop_at.get(k) and k in stop_at:
            rest(tw, line, s)

    rests_at(-1, 0.0, path[0].line if npth else 0)
    for seg in events_after.get(-1, []):
        synced.append((len(P_len) - 1, seg))
    gi = 0
    for i in range(len(lo)):
        while gi + 1 < npth and gs0[gi + 1] <= lo[i]:
            gi += 1
        P_len.append(float(hi[i] - lo[i])); P_v.append(float(iv[i])); P_acc.append(float(ia[i]))
        P_rest.append(0.0); P_s0.append(float(lo[i])); P_line.append(path[gi].line)
        at_end = gi + 1 < npth and abs(gs0[gi + 1] - hi[i]) <= 0.0 or (gi == npth - 1 and i == len(lo) - 1)
        if at_end:
            for seg in events_after.get(gi, []):
                synced.append((len(P_len) - 1, seg))
            if gi in stop_at:
                rests_at(gi, float(hi[i]), path[gi].line)
    if not P_len:
        rest(0.0, 0, 0.0)
    npc = len(P_len)
    L = np.array(P_len)
    V = np.array(P_v)
    A = np.array(P_acc)
    # junction speeds: vj[k] after piece k: 0 at rests and the end; else the smaller side
    vj = np.zeros(npc)
    for k in range(npc - 1):
        if L[k] > 0 and L[k + 1] > 0:
            vj[k] = min(V[k], V[k + 1])
    # backward and forward passes (look-ahead over the whole program)
    for k in range(npc - 2, -1, -1):
        if L[k + 1] > 0:
            vj[k] = min(vj[k], math.sqrt(vj[k + 1] ** 2 + 2 * A[k + 1] * L[k + 1]))
    vin = 0.0
    for k in range(npc):
        if L[k] > 0:
            vj[k] = min(vj[k], math.sqrt(vin * vin + 2 * A[k] * L[k]))
        vin = vj[k] if L[k] > 0 else 0.0
    # ---- per-piece trapezoids
    t0s, tas, tcs, tds, v0s, vps = (np.zeros(npc) for _ in range(6))
    las, lcs = np.zeros(npc), np.zeros(npc)
    t = 0.0
    v0 = 0.0
    t_end = np.zeros(npc)
    for k in range(npc):
        v1 = vj[k]
        if L[k] == 0.0:
            ta = td = vp = la = lc = 0.0
            v0 = 0.0
            # a rest ends on the grid: a pause's stop time is then a grid point (exact setpoints)
            tc = max(math.ceil((t + P_rest[k]) / period - 1e-9) * period - t, 0.0)
        else:
            a = A[k]
            vp = min(V[k], math.sqrt(max((2 * a * L[k] + v0 * v0 + v1 * v1) / 2, 0.0)))
            vp = max(vp, v0, v1)
            ta = (vp - v0) / a
            td = (vp - v1) / a
            la = (vp * vp - v0 * v0) / (2 * a)
            ld = (vp * vp - v1 * v1) / (2 * a)
            lc = max(L[k] - la - ld, 0.0)
            tc = lc / vp if vp > 0 else 0.0
        t0s[k], tas[k], tcs[k], tds[k], v0s[k], vps[k], las[k], lcs[k] = t, ta, tc, td, v0, vp, la, lc
        t += ta + tc + td
        t_end[k] = t
        v0 = v1
    # ---- the geometry table; arcs' compensation faded over 2·v·T2 of path where the circle changes
    G = np.zeros((npth, 8))
    kinds = np.zeros(npth, dtype=int)
    p0s, p1s, us = np.zeros((npth, na)), np.zeros((npth, na)), np.zeros((npth, na))
    for k, g in enumerate(path):
        kinds[k], p0s[k], p1s[k], us[k] = g.kind, g.p0, g.p1, g.u
        if g.kind == 1:
            fade = 2.0 * min(base(g)[0], 1e3) * t_c
            fi = 0.0 if k > 0 and join_v[k - 1] > 0 and _same_circle(path[k - 1], g) else fade
            fo = 0.0 if k < npth - 1 and join_v[k] > 0 and _same_circle(g, path[k + 1]) else fade
            if fi + fo > g.length:        # too short to fade in and out: not compensated (its
                fi = fo = -1.0            # shrink is within the speed rule's chord, _curve_speed)
            G[k] = (*g.arc, fi, fo)
    m = n1 + n2 - 2
    events: list[tuple[float, Event]] = []
    stops: list[tuple[float, Pause]] = []
    for k, seg in marks:
        te = t_end[k] if k >= 0 else 0.0
        if isinstance(seg, Pause):
            stops.append((te, seg))       # the windows hold only the rest: at rest exactly
        else:
            events.append((te, seg))
    for k, seg in synced:
        events.append(((t_end[k] if k >= 0 else 0.0) + 0.5 * m * period, seg))
    events.sort(key=lambda e: e[0])
    prof = (t0s, tas, tcs, tds, v0s, vps, A, las, lcs, L, np.array(P_s0), np.array(P_line))
    if not npth:
        G, kinds = np.zeros((1, 8)), np.zeros(1, dtype=int)
        p0s = p1s = pos0[None, :].copy()
        us = np.zeros((1, na))
        gs0 = np.zeros(1)
        glen = np.zeros(1)
    else:
        glen = np.array([g.length for g in path])
    geo = (gs0, glen, kinds, p0s, p1s, us, G)
    end = path[-1].p1.copy() if npth else pos0.copy()
    return PathTrajectory(axes, prof, geo, ix, iy, n1, n2, period, pos0, end, events, stops)


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
