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
from motorctl.motion import profile as _prof
from motorctl.motion import rules as _rules
from motorctl.motion import ruckig_profile
from motorctl.motion.blend import Geo
from motorctl.motion.gcode import AXES, Arc, Dwell, Event, Line, Pause, Program
from motorctl.motion.path_trajectory import PathTrajectory
from motorctl.motion.rules import CURVE_SHARE, JERK_STEP, NORMAL_SHARE  # noqa: F401  (the rules' shares)
from motorctl.motion.trajectory import Trajectory

#: the loop's period [s] (5 kHz): the default grid of the filters
PERIOD_S = 2e-4
#: the second moving average's length T2 [s]: it spreads a join's curvature step over T2
SMOOTH_S = 2e-3
#: the first moving average's length over max(a_max/j_max): 1 with the profile's accelerations of
#: opposite signs T1 apart (profile.flat_peaks), 2 without (any acceleration step 2·a_max)
RAMP = 1.0
#: the arc tolerance used where G61 or G64 without P (exact path) asks for none [m]
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
        if ruckig_profile.evaluable(self._t):       # all samples at once from the profiles
            t = t0 + np.arange(out.shape[0]) * dt
            p, v, a = ruckig_profile.states(self._t, t)
            if self._u is None:
                out[:, 0], out[:, 1], out[:, 2] = p, v, a
            else:
                out[:, 0] = self.start + p[:, :1] * self._u
                out[:, 1] = v[:, :1] * self._u
                out[:, 2] = a[:, :1] * self._u
            late = t >= self.duration
            out[late, 0] = self.end
            out[late, 1:3] = 0.0
            return
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


def _filter_lengths(limits: Sequence[AxisLimits], period: float) -> tuple[int, int]:
    """(N1, N2) samples of the two moving averages: T1 (of the path speed) = max(a_max/j_max)
    (the path acceleration steps by at most a_max within T1: accelerations of opposite signs
    are T1 apart, profile.flat_peaks, so its ramps keep j_max); T2 (of the setpoints) =
    SMOOTH_S."""
    ratio = max(lim.a_max / lim.j_max for lim in limits)
    n1 = max(2, math.ceil(RAMP * ratio / period - 1e-9))
    n2 = max(2, int(round(SMOOTH_S / period)))
    return n1, n2


def _curvature_range(kappa: np.ndarray, lengths: np.ndarray, turns: np.ndarray, w: float) -> float:
    """max − min [1/m] of the curvature averaged over every stretch of path ``w`` [m] long within
    consecutive pieces of curvature ``kappa`` [1/m] and ``lengths`` [m] (shape (n,) each) whose
    joins turn by ``turns`` [rad] (shape (n − 1,), signed as the curvature: a kink is a turn
    within no length, its averaged curvature α/w); the pieces' own range when w is 0."""
    b = np.concatenate([[0.0], np.cumsum(lengths)])
    if not w > 0.0:
        return float(kappa.max() - kappa.min())
    if w >= b[-1]:
        return 0.0
    F = np.concatenate([[0.0], np.cumsum(kappa * lengths)])
    eps = 1e-9 * w
    x = np.clip(np.concatenate([b - eps, b + eps, b - w - eps, b - w + eps]), 0.0, b[-1] - w)
    cj = np.concatenate([[0.0], np.cumsum(turns)])

    def integral(y):
        return np.interp(y, b, F) + cj[np.searchsorted(b[1:-1], y, side="right")]

    avg = (integral(x + w) - integral(x)) / w
    return float(avg.max() - avg.min())


def _stop_speed(v: float, acc: float, rest_s: float) -> float:
    """Below this speed [m/s] a join costs more passed than stopped at: passing at v_j loses
    (v − v_j)²/(A·v) braking to it and speeding up again and 2·rest·(1 − v_j/v) in its zone
    (widened by v_j·rest on each side), a stop loses v/A and the rest; equal at the smaller root
    of v_j² − 2·(v + A·rest)·v_j + A·v·rest (about A·rest/2). v: the neighbours' speed [m/s], acc
    their path acceleration [m/s²], rest_s the rest at a stop [s]."""
    if not (math.isfinite(v) and v > 0 and acc > 0):
        return 0.0
    b = v + acc * rest_s
    return b - math.sqrt(max(b * b - acc * v * rest_s, 0.0))


def _blend_tol(g: Geo) -> float:
    """The G64 P a piece may use [m]: 0 under G61, and under G64 without P (no tolerance given:
    the path is followed exactly, corners stop)."""
    return g.tol if 0.0 < g.tol < math.inf else 0.0


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
    t1, t2 = n1 * period, n2 * period
    tw = (n1 + n2 + 1) * period                         # a rest: both windows held in it
    vlim = [float(lim.v_max) for lim in limits]
    alim = [float(lim.a_max) for lim in limits]
    jlim = [float(lim.j_max) for lim in limits]

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
            sweep = seg.sweep
            # the length along the turn and the radius's change (radii that differ: a spiral)
            length = math.hypot(math.hypot(abs(sweep) * 0.5 * (seg.radius + r1), r1 - seg.radius),
                                float(np.linalg.norm(dz)))
            add(Geo(1, p0, p1, dz / length, length, seg.line, seg.feed * feed_scale, seg.tolerance,
                    len(moves), arc=(float(seg.center[0]), float(seg.center[1]), seg.radius, r1, phi0, sweep)))
        elif isinstance(seg, Dwell):
            act("rest", seg.seconds, seg)
        elif isinstance(seg, Pause):
            act("pause", 0.0, seg)
        elif isinstance(seg, Event):
            act("event" if seg.synchronized else "word", 0.0, seg)
    for k, g in enumerate(moves):
        g.src = k
        if not _blend_tol(g) > 0.0:
            g.q = 0.0                    # no tolerance: nothing merged either
    stop_after = [g.tol == 0.0 or any(a[0] != "event" for a in after.get(k, ())) for k, g in enumerate(moves)]
    barrier = [stop_after[k] or k in after for k in range(len(moves))]
    geos = _bl.merge_collinear(moves, barrier)
    room = {id(g): 0.5 * g.length for g in geos if g.kind == 0}
    # ---- a short arc between two lines rounding their corner (a kerf arc): the corner's blend
    for k in range(1, len(geos) - 1):
        a, g, b = geos[k - 1], geos[k], geos[k + 1]
        if g.kind != 1 or a.kind != 0 or b.kind != 0 or barrier[a.src] or barrier[g.src]:
            continue
        tol = min(_blend_tol(a), _blend_tol(g))
        if tol > 0.0:
            new = _bl.reblend_arc(a, g, b, _bl.BLEND_SHARE * (tol - max(a.dev, b.dev)), ix, iy)
            if new is not None:
                a.p1 = new.p0.copy()
                a.length = float(np.linalg.norm(a.p1 - a.p0))
                b.p0 = new.p1.copy()
                b.length = float(np.linalg.norm(b.p1 - b.p0))
                new.tol = g.tol
                geos[k] = new

    # ---- each piece's own limits (rules.py), once per piece
    limits_of: dict[int, tuple[Geo, tuple[float, float]]] = {}     # id -> (the piece, kept alive; its limits)

    def base(g: Geo) -> tuple[float, float]:
        got = limits_of.get(id(g))
        if got is None:
            tol = _blend_tol(g) if _blend_tol(g) > 0 else EXACT_ARC_TOL_M
            got = limits_of[id(g)] = (g, _rules.piece_limits(g, vlim, alim, jlim, ix, iy, tol_left=tol - g.dev,
                                                             t1=t1, t2=t2, ramp=RAMP))
        return got[1]

    def through(a: Geo, b: Geo, dkappa=None, kink=True) -> float:
        dev_left = min((_blend_tol(g) if _blend_tol(g) > 0 else EXACT_ARC_TOL_M) - g.dev for g in (a, b))
        return _rules.join_speed(a, b, jlim, ix, iy, t2=t2, period=period, dev_left=dev_left, dkappa=dkappa,
                                 kink=kink)

    # ---- corners: a blend arc between two lines within the tolerance, a join where the tangent
    # goes on (a curvature step, a kink small enough for the short filter), else an exact stop
    path: list[Geo] = []
    join_v: list[float] = []              # join_v[k]: the speed through the join after path[k]; 0: stop
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
        v_near = min(base(a)[0], base(g)[0])
        v_stop = _stop_speed(v_near, min(base(a)[1], base(g)[1]), tw)
        vk = through(a, g)                # tangent, or a kink the short filter rounds at that speed
        blend = None
        tol_a = _blend_tol(a)
        if (vk < v_near and a.kind == 0 and g.kind == 0 and tol_a > 0
                and _rules.join_frame(a, g, ix, iy)[2] > _bl.TANGENT_RAD):
            tol = _bl.BLEND_SHARE * (tol_a - max(a.dev, g.dev))
            bl = _bl.corner_blend(a, g, tol, room[id(a)], room[id(g)], ix, iy) if tol > 0 else None
            if bl is not None:
                arc = bl[0]
                arc.tol = a.tol                   # the program's P (the blend used a share of it)
                kappa = 1.0 / arc.arc[2]
                v_in, v_out = through(a, arc, kappa), through(arc, g, kappa)
                blend = (min(base(arc)[0], v_in, v_out), arc, v_in, v_out)
        if blend is not None and blend[0] > vk and blend[0] >= v_stop:
            _, arc, v_in, v_out = blend
            a.p1 = arc.p0.copy()
            a.length = float(np.linalg.norm(a.p1 - a.p0))
            g.p0 = arc.p1.copy()
            g.length = float(np.linalg.norm(g.p1 - g.p0))
            join_v += [v_in, v_out]
            path += [arc, g]
        elif vk >= v_stop:
            join_v.append(vk)
            path.append(g)
        else:                             # slower: a stop costs less (_stop_speed)
            join_v.append(0.0)
            path.append(g)
    # drop pieces a blend left without length (their joins become one)
    keep_p, keep_j = [], []
    last_of: dict[int, int] = {}          # programmed move -> the path piece it ends with
    for k, g in enumerate(path):
        drop = (g.length <= 1e-12 and g.kind == 0 and 0 < k < len(path) - 1 and join_v[k - 1] > 0
                and join_v[k] > 0)
        if drop:                          # the pieces about it now meet: their own step and kink
            keep_j[-1] = through(keep_p[-1], path[k + 1])
        else:
            keep_p.append(g)
            if k < len(join_v):
                keep_j.append(join_v[k])
        if not g.blend:
            for src in (g.merged or [g.src]):
                last_of[src] = len(keep_p) - 1
    path, join_v = keep_p, keep_j
    # a join's curvature step as the second average sees it: each sample's direction turns by the
    # curvature averaged over the path between two samples (v·h; a kink α there: α/(v·h)), the
    # average over T2 spreads the changes of that; where pieces shorter than v·(T2 + h) follow, the
    # range of the averaged curvature, kinks included, over the window about the join (a short
    # piece between two joins puts both into one window: blends of alternating turn, chords
    # zigzagging; a line shorter than v·h between two arcs of one circle hardly shows), the speed
    # the largest v whose range at v·h keeps the join's jerk
    kap = np.array([g.curvature() for g in path])
    lens = np.array([g.length for g in path])
    turn = np.array([_rules.join_turn(path[k], path[k + 1], ix, iy) for k in range(len(join_v))])
    join_dk = [abs(kap[k + 1] - kap[k]) for k in range(len(join_v))]    # the step each join is judged by
    join_kinks = [False] * len(join_v)          # True: its step holds the window's kinks too
    for k, vj in enumerate(join_v):
        if not vj > 0.0:
            continue
        v_hi = min(base(path[k])[0], base(path[k + 1])[0])
        d = v_hi * (t2 + period)
        lo_k, hi_k, left, right = k, k + 1, lens[k], lens[k + 1]
        while left < d and lo_k > 0 and join_v[lo_k - 1] > 0.0:
            lo_k -= 1
            left += lens[lo_k]
        while right < d and hi_k < len(path) - 1 and join_v[hi_k] > 0.0:
            hi_k += 1
            right += lens[hi_k]
        if hi_k - lo_k < 2:
            continue
        kk, ll, tt = kap[lo_k:hi_k + 1], lens[lo_k:hi_k + 1], turn[lo_k:hi_k]
        join_kinks[k] = True
        dk = _curvature_range(kk, ll, tt, v_hi * period)
        v_top = through(path[k], path[k + 1], dk, kink=False)
        if v_top >= v_hi:
            join_v[k], join_dk[k] = v_top, dk
            continue
        lo_v, hi_v = 0.0, v_hi
        while hi_v - lo_v > 1e-3 * hi_v:
            mid = 0.5 * (lo_v + hi_v)
            ok = through(path[k], path[k + 1], _curvature_range(kk, ll, tt, mid * period), kink=False) >= mid
            lo_v, hi_v = (mid, hi_v) if ok else (lo_v, mid)
        join_v[k] = lo_v if lo_v >= _stop_speed(v_hi, min(base(path[k])[1], base(path[k + 1])[1]), tw) else 0.0
        join_dk[k] = _curvature_range(kk, ll, tt, lo_v * period)

    # ---- the speed zones: each piece's limits on its length, each join's at its point, each
    # widened by v·(T1 + T2 + h) on both sides: the moving averages then never carry a faster part
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
    join_k = [k for k, vj in enumerate(join_v) if vj > 0 and math.isfinite(vj)]
    for k in join_k:
        # the speed about a join is within its pieces' (their zones reach over it): its zone's
        # acceleration is that of the slower of the join and the pieces
        vj, s = min(join_v[k], base(path[k])[0], base(path[k + 1])[0]), gs0[k + 1]
        zs.append(s - vj * tw)
        ze.append(s + vj * tw)
        zv.append(vj)
        za.append(_rules.join_accel(path[k], path[k + 1], vj, alim, jlim, ix, iy, t1=t1, t2=t2, period=period,
                                    ramp=RAMP, dkappa=join_dk[k], kink=not join_kinks[k]))
    # a stop's rest holds both windows: nothing is carried across it, the zones end there
    stops_s = np.array([0.0] + [gs0[k + 1] for k in range(npth - 1) if join_v[k] == 0.0] + [total])
    if zs:
        home = np.concatenate([gs0, gs0[np.array(join_k, dtype=int) + 1]])
        home_end = np.concatenate([gs0 + np.array([g.length for g in path]), gs0[np.array(join_k, dtype=int) + 1]])
        i_lo = np.clip(np.searchsorted(stops_s, home, side="right") - 1, 0, len(stops_s) - 1)
        i_hi = np.clip(np.searchsorted(stops_s, home_end, side="left"), 0, len(stops_s) - 1)
        zs = np.maximum(np.array(zs), stops_s[i_lo])
        ze = np.minimum(np.array(ze), stops_s[i_hi])
    if npth:
        lo, hi, iv, ia = _prof.speed_zones(np.asarray(zs, dtype=float), np.asarray(ze, dtype=float), np.array(zv),
                                           np.array(za), np.concatenate([gs0, [total]]), total)
    else:
        lo = hi = iv = ia = np.zeros(0)
    # ---- the intervals and the rests where the path stops: at a stop the first rest holds both
    # windows (tw); what follows at rest there adds only its own time (a dwell's seconds)
    stop_at: dict[int, list] = {k: [] for k in range(npth - 1) if join_v[k] == 0.0}
    events_after: dict[int, list] = {}
    for src, acts in after.items():
        k = last_of.get(src, -1) if src >= 0 else -1
        for kind, sec, seg in acts:
            if kind == "event":
                events_after.setdefault(k, []).append(seg)
            else:
                stop_at.setdefault(k, []).append((kind, sec, seg))
    I_len, I_v, I_acc, I_rest, I_line = [], [], [], [], []
    marks: list[tuple[int, object]] = []              # (interval index of a rest, Pause or Event)
    synced: list[tuple[float, object]] = []           # (path length, Event)

    def rest(seconds, line):
        I_len.append(0.0); I_v.append(0.0); I_acc.append(0.0); I_rest.append(seconds); I_line.append(line)

    def rests_at(k, line, held):
        for kind, sec, seg in stop_at.get(k, []):
            rest((0.0 if held else tw) + (sec if kind == "rest" else 0.0), seg.line)
            held = True
            if kind != "rest":
                marks.append((len(I_len) - 1, seg))
        if not held:
            rest(tw, line)

    rests_at(-1, path[0].line if npth else 0, True)  # before the first move: at rest already
    for seg in events_after.get(-1, []):
        synced.append((0.0, seg))
    gi = 0
    for i in range(len(lo)):
        while gi + 1 < npth and gs0[gi + 1] <= lo[i]:
            gi += 1
        I_len.append(float(hi[i] - lo[i])); I_v.append(float(iv[i])); I_acc.append(float(ia[i]))
        I_rest.append(0.0); I_line.append(path[gi].line)
        at_end = (gi + 1 < npth and gs0[gi + 1] == hi[i]) or (gi == npth - 1 and i == len(lo) - 1)
        if at_end:
            for seg in events_after.get(gi, []):
                synced.append((float(hi[i]), seg))
            if gi in stop_at:
                rests_at(gi, path[gi].line, False)
    if not I_len:
        rest(0.0, 0)
    L, V, A = np.array(I_len), np.array(I_v), np.array(I_acc)
    vj = _prof.junction_speeds(L, V, A)
    phases, _ = _prof.trapezoids(L, V, A, vj, I_rest, I_line)
    if RAMP < 2.0:
        _prof.flat_peaks(phases, t1)
    # the rests, in order, are the phases at rest (flat_peaks moves the others)
    rest_phase = dict(zip((k for k in range(len(I_len)) if I_len[k] == 0.0),
                          (k for k, (d, v0) in enumerate(zip(phases[1], phases[2])) if d == 0.0 and v0 == 0.0)))
    prof = _prof.Phases(*phases, period=period)
    # ---- the geometry table; arcs' compensation faded over 2·v·T2 of path where the circle changes
    G = np.zeros((max(npth, 1), 8))
    kinds = np.zeros(max(npth, 1), dtype=int)
    p0s, p1s, us = (np.zeros((max(npth, 1), na)) for _ in range(3))
    for k, g in enumerate(path):
        kinds[k], p0s[k], p1s[k], us[k] = g.kind, g.p0, g.p1, g.u
        if g.kind == 1:
            fade = 2.0 * min(base(g)[0], 1e3) * t2
            fi = 0.0 if k > 0 and join_v[k - 1] > 0 and _same_circle(path[k - 1], g) else fade
            fo = 0.0 if k < npth - 1 and join_v[k] > 0 and _same_circle(g, path[k + 1]) else fade
            if fi + fo > g.length:        # too short to fade in and out: not compensated (its
                fi = fo = -1.0            # shrink is within the speed rule's chord, rules.piece_limits)
            G[k] = (*g.arc, fi, fo)
    if not npth:
        p0s[0] = p1s[0] = pos0
    delay = 0.5 * (n1 + n2 - 2) * period
    events: list[tuple[float, Event]] = []
    stops: list[tuple[float, Pause]] = []
    for k, seg in marks:
        te = float(prof.t0[rest_phase[k] + 1])
        if isinstance(seg, Pause):
            stops.append((te, seg))       # the windows hold only the rest: at rest exactly
        else:
            events.append((te, seg))
    for s, seg in synced:
        events.append((prof.time_at(s) + delay, seg))
    events.sort(key=lambda e: e[0])
    glen = np.array([g.length for g in path]) if npth else np.zeros(1)
    geo = (gs0 if npth else np.zeros(1), glen, kinds, p0s, p1s, us, G)
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
