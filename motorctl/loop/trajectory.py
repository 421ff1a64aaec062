"""Desired trajectories x_d(t), ẋ_d(t), ẍ_d(t): jerk-limited point-to-point moves, repeated programs, hold.

A move from rest to rest over a distance D uses the 7-segment jerk-limited profile (jerk ±j,
acceleration ≤ a_max, velocity ≤ v_max): jerk-up, constant acceleration, jerk-down, cruise,
and the mirror image. When D is too short to reach v_max (or a_max), the peak velocity is
lowered by bisection until the profile fits exactly. The X program of the paper's Fig. 3
(0 ↔ 0.4 m, 2 m/s, 40 m/s², 4000 m/s³) takes 0.26 s a move (configs/gantry.yaml).

Sampling is pure float arithmetic on precomputed segments, at and after the end of a move the
position is the end point exactly. Each Move and Program keeps its segments in a flat float64
table (:attr:`Program.table`, layout below), and one compiled function samples it
(:func:`sample_table`): :meth:`Move.sample` and :meth:`Program.sample` call it from Python, the
compiled servo cycle (:mod:`motorctl.loop.cycle`) calls it inside the cycle.

Table layout: [0] n_moves (−1: a single move sampled as such, 0: a hold), [1] period [s],
[2] t_start [s], [3] the first point (the hold position) [m], then per move j at
4 + MOVE_W·j: start, end, t0, duration, the 7 segment start times, the 7 segment start states
(x, v, a, jerk).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Annotated

import numpy as np
from pydantic import Field

from motorctl.jit import njit
from motorctl.schema import Position_m, StrictModel, Time_s, quantity

#: floats per move in a table: start, end, t0, duration, 7 segment starts, 7 × (x, v, a, j)
MOVE_W = 4 + 7 + 28
#: the header of a table: n_moves, period, t_start, first point
TABLE_HEAD = 4


@njit
def _move_sample(tab, b, t):
    """One move of a table at offset b, at time t [s] (see the module docstring)."""
    t0 = tab[b + 2]
    if t <= t0:
        return tab[b], 0.0, 0.0
    if t >= t0 + tab[b + 3]:
        return tab[b + 1], 0.0, 0.0
    i = 6
    while i > 0 and tab[b + 4 + i] > t:       # bisect_right(starts, t) − 1 on 7 entries
        i -= 1
    q = b + 11 + 4 * i
    p, v, a, j = tab[q], tab[q + 1], tab[q + 2], tab[q + 3]
    d = t - tab[b + 4 + i]
    return (p + v * d + a * d * d / 2 + j * d * d * d / 6, v + a * d + j * d * d / 2, a + j * d)


@njit
def sample_table(tab, t):
    """(x_d [m], ẋ_d [m/s], ẍ_d [m/s²]) of a Move's or Program's table (module docstring) at
    time t [s]: the arithmetic of the 7-segment profile, compiled, without allocation."""
    nm = int(tab[0])
    if nm < 0:
        return _move_sample(tab, TABLE_HEAD, t)
    if nm == 0:
        return tab[3], 0.0, 0.0
    tau = t - tab[2]
    if tau < 0.0:
        return tab[3], 0.0, 0.0
    period = tab[1]
    if period > 0.0:
        tau = np.fmod(tau, period)            # exact, as C fmod
    i = nm - 1
    while i >= 0 and tab[TABLE_HEAD + MOVE_W * i + 2] > tau:   # bisect_right(move t0s, tau) − 1
        i -= 1
    if i < 0:
        return tab[TABLE_HEAD], 0.0, 0.0
    return _move_sample(tab, TABLE_HEAD + MOVE_W * i, tau)


def _move_record(m: "Move") -> list[float]:
    rec = [m.start, m.end, m.t0, m.duration, *m._starts]
    for st in m._states:
        rec.extend(st)
    return rec


def _accel_phase(v: float, a_max: float, j_max: float) -> tuple[float, float]:
    """(T_j, T_a) to go from rest to velocity v with jerk j_max and acceleration ≤ a_max."""
    if v * j_max <= a_max * a_max:
        return math.sqrt(v / j_max), 0.0
    tj = a_max / j_max
    return tj, v / a_max - tj


@dataclass(frozen=True)
class Move:
    """One rest-to-rest jerk-limited move from ``start`` to ``end`` [m] beginning at ``t0`` [s].

    Raises:
        ValueError: a limit is not positive.
    """

    start: float
    end: float
    v_max: float
    a_max: float
    j_max: float
    t0: float = 0.0

    def __post_init__(self):
        for name in ("v_max", "a_max", "j_max"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        dist = abs(self.end - self.start)
        sgn = 1.0 if self.end >= self.start else -1.0
        v = self.v_max
        tj, ta = _accel_phase(v, self.a_max, self.j_max)
        if dist < v * (2 * tj + ta):
            lo, hi = 0.0, v
            for _ in range(200):
                mid = 0.5 * (lo + hi)
                tj, ta = _accel_phase(mid, self.a_max, self.j_max)
                if mid * (2 * tj + ta) > dist:
                    hi = mid
                else:
                    lo = mid
            v = lo
            tj, ta = _accel_phase(v, self.a_max, self.j_max)
        tv = (dist - v * (2 * tj + ta)) / v if v > 0 else 0.0
        tv = max(tv, 0.0)
        j = self.j_max * sgn
        durations = [tj, ta, tj, tv, tj, ta, tj]
        jerks = [j, 0.0, -j, 0.0, -j, 0.0, j]
        # integrate segment start states exactly
        starts, states = [], []
        t, p, vel, acc = self.t0, self.start, 0.0, 0.0
        for d, jj in zip(durations, jerks):
            starts.append(t)
            states.append((p, vel, acc, jj))
            p += vel * d + acc * d * d / 2 + jj * d**3 / 6
            vel += acc * d + jj * d * d / 2
            acc += jj * d
            t += d
        object.__setattr__(self, "_starts", starts)
        object.__setattr__(self, "_states", states)
        object.__setattr__(self, "duration", sum(durations))
        object.__setattr__(self, "peak_velocity", v)
        object.__setattr__(self, "table", np.array([-1.0, 0.0, 0.0, self.start, *_move_record(self)]))

    def sample(self, t: float) -> tuple[float, float, float]:
        """(x_d [m], ẋ_d [m/s], ẍ_d [m/s²]) at time t [s]; rest at start/end outside the move."""
        return sample_table(self.table, t)


class Program:
    """A repeated point-to-point program: moves at fixed times within a period, or a hold.

    Args:
        points: positions visited in turn [m] (≥ 1 entry; one entry = hold there).
        move_times: start time of each move within the period [s], one per point (the move
            at move_times[i] goes to points[(i+1) % len(points)]).
        period: repetition period [s]; 0 = play once and stay at the last point.
        v_max, a_max, j_max: limits [m/s, m/s², m/s³].
        t_start: program time zero [s].
    Raises:
        ValueError: moves overlap, do not fit in the period, or limits are not positive.
    """

    def __init__(self, points, move_times, period: float, v_max: float, a_max: float,
                 j_max: float, t_start: float = 0.0):
        self.points = [float(p) for p in points]
        if not self.points:
            raise ValueError("a program needs at least one point")
        self.period = float(period)
        self.t_start = float(t_start)
        self.moves: list[Move] = []
        if len(self.points) > 1:
            if len(move_times) != len(self.points):
                raise ValueError("move_times needs one start time per point")
            n = len(self.points)
            for i, t0 in enumerate(move_times):
                self.moves.append(Move(self.points[i], self.points[(i + 1) % n], v_max, a_max,
                                       j_max, float(t0)))
            for a, b in zip(self.moves, self.moves[1:]):
                if a.t0 + a.duration > b.t0 + 1e-12:
                    raise ValueError(f"move at {a.t0} s (duration {a.duration:.3f} s) overlaps the move at {b.t0} s")
            last = self.moves[-1]
            if self.period > 0 and last.t0 + last.duration > self.period + 1e-12:
                raise ValueError(f"moves do not fit in the period {self.period} s")
        tab = [float(len(self.moves)), self.period, self.t_start, self.points[0]]
        for m in self.moves:
            tab.extend(_move_record(m))
        #: the table the compiled sampler reads (module docstring), float64 (4 + MOVE_W·n_moves,)
        self.table = np.array(tab)

    @classmethod
    def hold(cls, position: float = 0.0) -> "Program":
        """Stay at ``position`` [m]."""
        return cls([position], [], 0.0, 1.0, 1.0, 1.0)

    def sample(self, t: float) -> tuple[float, float, float]:
        """(x_d [m], ẋ_d [m/s], ẍ_d [m/s²]) at absolute time t [s]."""
        return sample_table(self.table, t)


class TrajectoryConfig(StrictModel):
    """Repeated point-to-point program (one point = hold). Times in s, limits in SI."""

    points: Annotated[list[Position_m], Field(min_length=1)] = [0.0]
    move_times_s: list[Time_s] = []
    period_s: Time_s = 0.0
    v_max: quantity(1e-6, 20.0, "m/s") = 1.0
    a_max: quantity(1e-4, 1e4, "m/s^2") = 10.0
    j_max: quantity(1e-2, 1e8, "m/s^3") = 1000.0
    start_s: Time_s = 0.0

    def program(self, offset: float = 0.0) -> Program:
        return Program([p + offset for p in self.points], self.move_times_s, self.period_s,
                       self.v_max, self.a_max, self.j_max, self.start_s)
