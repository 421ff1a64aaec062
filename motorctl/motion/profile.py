"""The path-speed profile: the look-ahead of the planner over a window of the program
(docs/motion.md, "The planner", step 2).

The path is cut into intervals of constant limits (the speed zones' elementary intervals:
:func:`speed_zones`) and rests; a backward and a forward pass over all of them give the speed at
each join (an acceleration-limited, trapezoidal profile: the speed reachable over an interval of
length L from v₀ at acceleration A is √(v₀² + 2·A·L)); each interval then accelerates, cruises and
decelerates (:class:`Phases`). Where the first moving average is T1 = max(a_max/j_max) long (its
jerk |s̈(t) − s̈(t − T1)|/T1), the profile's accelerations of opposite signs are kept at least T1
apart: a peak of the speed is lowered until it is flat for T1 (:func:`flat_peaks`); a valley is
a speed zone, at least 2·T1 long by its widening, or a rest.

The result is a list of phases of constant path acceleration: start time t0 [s], path length s0
[m], speed v0 [m/s], acceleration [m/s²] (shape (n,) each), which :meth:`Phases.at` evaluates at
any times with one search.
"""

from __future__ import annotations

import heapq
import math

import numpy as np


def speed_zones(starts: np.ndarray, ends: np.ndarray, vs: np.ndarray, accs: np.ndarray,
                breaks: np.ndarray, total: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The smallest speed and acceleration over zones [starts, ends] (arrays, shape (z,)) on each
    elementary interval between the sorted points ``breaks`` and the zones' ends within
    [0, total] [m]: (lo, hi, v, acc), each shape (k,)."""
    pts = np.unique(np.clip(np.concatenate([breaks, starts, ends]), 0.0, total))
    order = np.argsort(starts, kind="stable")
    hv: list = []
    ha: list = []
    out_v = np.empty(len(pts) - 1)
    out_a = np.empty(len(pts) - 1)
    j = 0
    nz = len(order)
    st, en, vv, aa = starts.tolist(), ends.tolist(), vs.tolist(), accs.tolist()
    plist = pts.tolist()
    for i in range(len(pts) - 1):
        lo, hi = plist[i], plist[i + 1]
        while j < nz and st[order[j]] <= lo:
            z = order[j]
            heapq.heappush(hv, (vv[z], en[z]))
            heapq.heappush(ha, (aa[z], en[z]))
            j += 1
        while hv and hv[0][1] < hi:
            heapq.heappop(hv)
        while ha and ha[0][1] < hi:
            heapq.heappop(ha)
        out_v[i] = hv[0][0] if hv else math.inf
        out_a[i] = ha[0][0] if ha else math.inf
    return pts[:-1], pts[1:], out_v, out_a


def junction_speeds(length: np.ndarray, v: np.ndarray, acc: np.ndarray) -> np.ndarray:
    """The speed [m/s] after each interval (shape (n,)): 0 after a rest (length 0) and at the end,
    else within both neighbours' speeds and what each side can reach or brake from over its
    length at its acceleration (the look-ahead's backward and forward passes)."""
    n = len(length)
    L, V, A = length.tolist(), v.tolist(), acc.tolist()
    vj = [0.0] * n
    for k in range(n - 1):
        if L[k] > 0 and L[k + 1] > 0:
            vj[k] = min(V[k], V[k + 1])
    for k in range(n - 2, -1, -1):
        if L[k + 1] > 0:
            vj[k] = min(vj[k], math.sqrt(vj[k + 1] ** 2 + 2 * A[k + 1] * L[k + 1]))
    vin = 0.0
    for k in range(n):
        if L[k] > 0:
            vj[k] = min(vj[k], math.sqrt(vin * vin + 2 * A[k] * L[k]))
        vin = vj[k] if L[k] > 0 else 0.0
    return np.array(vj)


class Phases:
    """A path-speed profile as phases of constant path acceleration (module docstring): t0, s0,
    v0, acc (shape (n,)), ``rest`` (bool, shape (n,): a phase at rest), ``line`` (the source
    line of each, int), ``duration`` [s]; a phase past the last holds the end at rest. Built from
    the lists of :func:`trapezoids`; with ``period`` [s] each rest is lengthened to end on the
    grid of that period."""

    def __init__(self, s0, ds, v0, v1, acc, rest_s, line, *, period: float = 0.0):
        s0, ds, v0, v1, acc = (np.asarray(x, dtype=float) for x in (s0, ds, v0, v1, acc))
        rest_s = np.asarray(rest_s, dtype=float)
        with np.errstate(divide="ignore", invalid="ignore"):
            dur = np.where(acc != 0.0, (v1 - v0) / np.where(acc != 0.0, acc, 1.0),
                           np.where(v0 > 0, ds / np.where(v0 > 0, v0, 1.0), rest_s))
        dur = np.maximum(dur, 0.0)
        if period > 0:                   # a rest ends on the grid: a pause's time is a grid point
            t, prev = 0.0, 0
            for k in np.flatnonzero((ds == 0.0) & (v0 == 0.0)).tolist():
                t += float(dur[prev:k].sum())
                dur[k] = max(math.ceil((t + rest_s[k]) / period - 1e-9) * period - t, 0.0)
                t += dur[k]
                prev = k + 1
        self.dur = dur
        self.t0 = np.concatenate([[0.0], np.cumsum(dur)])
        self.duration = float(self.t0[-1])
        end_s = float(s0[-1] + ds[-1]) if len(s0) else 0.0
        self.s0 = np.concatenate([s0, [end_s]])
        self.v0 = np.concatenate([v0, [0.0]])
        self.acc = np.concatenate([acc, [0.0]])
        self.rest = np.concatenate([(ds == 0.0) & (v0 == 0.0), [True]])
        self.line = np.concatenate([np.asarray(line, dtype=np.int64), [line[-1] if len(line) else 0]])
        self.end_s = end_s

    def at(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(s [m], ṡ [m/s]) at times t [s] (any shape); before 0 at 0, after the end at rest."""
        k = np.searchsorted(self.t0, t, side="right") - 1
        np.clip(k, 0, len(self.t0) - 1, out=k)
        tau = t - self.t0[k]
        np.clip(tau, 0.0, None, out=tau)
        last = k == len(self.t0) - 1
        tau[last] = 0.0
        a = self.acc[k]
        sd = self.v0[k] + a * tau
        s = self.s0[k] + (self.v0[k] + 0.5 * a * tau) * tau
        return s, sd

    def time_at(self, s: float) -> float:
        """The first time [s] the profile reaches path length s [m]."""
        moving = np.flatnonzero(~self.rest[:-1])
        if not moving.size:
            return 0.0
        i = max(int(np.searchsorted(self.s0[moving], s, side="left")) - 1, 0)
        k = int(moving[i])
        ds = s - self.s0[k]
        v0, a = float(self.v0[k]), float(self.acc[k])
        if ds <= 0:
            return float(self.t0[k])
        if a == 0.0:
            tau = ds / v0
        else:
            tau = (math.sqrt(max(v0 * v0 + 2 * a * ds, 0.0)) - v0) / a
        return float(self.t0[k] + min(max(tau, 0.0), self.dur[k]))


def trapezoids(length, v, acc, vj, rest_s, lines):
    """Each interval's phases between its junction speeds (v0 from the junction before it, v1
    = vj at its end): accelerate at acc to min(v, what its length allows), cruise, decelerate;
    a rest (length 0) one phase of ``rest_s`` seconds. Returns lists (s0, ds, v0, v1, acc,
    rest_s, line) of phases, and the index of each interval's last phase."""
    P = ([], [], [], [], [], [], [])
    last = []
    s = 0.0
    vin = 0.0
    for k in range(len(length)):
        L, V, A, v1 = float(length[k]), float(v[k]), float(acc[k]), float(vj[k])
        if L == 0.0:
            for lst, x in zip(P, (s, 0.0, 0.0, 0.0, 0.0, float(rest_s[k]), int(lines[k]))):
                lst.append(x)
            last.append(len(P[0]) - 1)
            vin = 0.0
            continue
        v0 = vin
        vp = min(V, math.sqrt(max((2 * A * L + v0 * v0 + v1 * v1) / 2, 0.0)))
        vp = max(vp, v0, v1)
        la = (vp * vp - v0 * v0) / (2 * A) if vp > v0 else 0.0
        ld = (vp * vp - v1 * v1) / (2 * A) if vp > v1 else 0.0
        lc = max(L - la - ld, 0.0)
        for ds_, va, vb, a_ in ((la, v0, vp, A), (lc, vp, vp, 0.0), (ld, vp, v1, -A)):
            if ds_ > 0.0 and (a_ != 0.0 or va > 0.0):
                for lst, x in zip(P, (s, ds_, va, vb, a_, 0.0, int(lines[k]))):
                    lst.append(x)
                s += ds_
        s = float(s)
        last.append(len(P[0]) - 1)
        vin = v1
    return P, last


def flat_peaks(P, t_flat: float) -> None:
    """Lower every peak of the phases' speed (an accelerating phase, cruises shorter than
    ``t_flat`` [s], a decelerating phase) until it is flat for ``t_flat``, in place on the lists
    of :func:`trapezoids`: the speed is clipped at the level v_c at which the path where the
    profile was above v_c, run at v_c, lasts t_flat (bisection). It only lowers the speed, so
    every limit still holds; phases stay continuous in speed."""
    s0, ds, v0, v1, acc, rest, line = P
    i = 0
    while i < len(s0):
        if acc[i] <= 0.0:
            i += 1
            continue
        j, flat = i + 1, 0.0
        while j < len(s0) and acc[j] == 0.0 and v0[j] > 0.0:
            flat += ds[j] / v0[j]
            j += 1
        if j >= len(s0) or acc[j] >= 0.0 or flat >= t_flat * (1.0 - 1e-9):
            i = j
            continue

        def span(vc, i=i, j=j):
            # where the speed crosses vc: on an accelerating phase before the peak, on a
            # decelerating one after it (the speed is continuous and starts and ends at rest)
            k = i
            while v0[k] > vc:
                k -= 1
            m = j
            while v1[m] > vc:
                m += 1
            up = s0[k] + (vc * vc - v0[k] ** 2) / (2.0 * acc[k])
            down = s0[m] + (v0[m] ** 2 - vc * vc) / (-2.0 * acc[m])
            return k, min(max(up, s0[k]), s0[k] + ds[k]), m, min(max(down, s0[m]), s0[m] + ds[m])

        lo, hi = 0.0, v1[i]
        while hi - lo > 1e-9 * v1[i]:
            mid = 0.5 * (lo + hi)
            _, up, _, down = span(mid)
            lo, hi = (mid, hi) if down - up >= mid * t_flat else (lo, mid)
        vc = lo
        if not vc > 0.0:
            i = j
            continue
        k, up, m, down = span(vc)
        new = []
        if up > s0[k]:
            new.append((s0[k], up - s0[k], v0[k], vc, acc[k], 0.0, line[k]))
        new.append((up, down - up, vc, vc, 0.0, 0.0, line[i]))
        if s0[m] + ds[m] > down:
            new.append((down, s0[m] + ds[m] - down, vc, v1[m], acc[m], 0.0, line[m]))
        for lst, col in zip(P, zip(*new)):
            lst[k:m + 1] = list(col)
        i = k + len(new) - 1
