"""Performance indexes of the paper's Tables I-II (docs/control-law.md, Performance indexes).

* e_M = max |e| over the evaluated run [0, T_f] (transient performance);
* e_F = max |e| over the last ``final_window_s`` (final tracking accuracy; one trajectory
  period by default);
* L2[e] = sqrt(mean(e²)) over the run;
* u_peak = max |u| over the run (Tables I/II call it u_M; it is not the actuator limit u_lim).

Given the desired velocity ẋ_d, L2[e] is also split into its parts in motion and at standstill
(ẋ_d = 0, the program dwelling): L2_motion = sqrt(Σ_motion e² / N) and L2_standstill =
sqrt(Σ_standstill e² / N) over all N samples, so that L2[e]² = L2_motion² + L2_standstill². The
tracking in motion is what a model compensation acts on; the error at standstill is where a
servo hunts against stiction (a limit cycle of integral action against the breakaway force).

u noise at rest (:func:`u_rest_rms`): the RMS of u about its mean over each stretch where the
command has not moved (ẋ_d = ẍ_d = 0) for :data:`REST_AFTER_S`: what the loop does to the
amplifier when it should be holding still (encoder noise through the gains, hunting).
"""

from __future__ import annotations

import numpy as np

#: Tables I and II of the paper (µm, µm, µm, V).
PAPER_TABLES = {
    "X": {"c1": {"e_M_um": 65.5, "e_F_um": 44.4, "L2_um": 4.54, "u_peak_V": 9.55},
          "c2": {"e_M_um": 37.6, "e_F_um": 28.1, "L2_um": 3.40, "u_peak_V": 9.85}},
    "Y": {"c1": {"e_M_um": 75.4, "e_F_um": 66.1, "L2_um": 9.14, "u_peak_V": 9.32},
          "c2": {"e_M_um": 39.1, "e_F_um": 35.0, "L2_um": 5.90, "u_peak_V": 9.60}},
}


#: |ẋ_d| at or below this is standstill (the program dwelling) [m/s]
STANDSTILL_M_PER_S = 1e-6
#: "at rest" for the u noise: the command has not moved for this long [s]
REST_AFTER_S = 0.3


def rest_mask(xd_dot: np.ndarray, xd_ddot: np.ndarray, ts: float, after_s: float = REST_AFTER_S) -> np.ndarray:
    """Samples where the command has not moved (ẋ_d = ẍ_d = 0) for ``after_s`` [s].

    Args:
        xd_dot [m/s], xd_ddot [m/s²]: the desired velocity and acceleration, (N,) each, one
            sample per period ``ts`` [s].
    Returns:
        bool (N,).
    """
    moving = (np.asarray(xd_dot) != 0.0) | (np.asarray(xd_ddot) != 0.0)
    k = np.arange(moving.size)
    last = np.maximum.accumulate(np.where(moving, k, -(10 ** 9)))
    return (k - last) * ts >= after_s


def runs(mask) -> tuple[np.ndarray, np.ndarray]:
    """(starts, ends): the runs of True in a boolean array (N,), each the half-open sample range
    [start, end); two empty arrays when there is none."""
    d = np.diff(np.concatenate(([0], np.asarray(mask, dtype=bool).astype(np.int8), [0])))
    return np.flatnonzero(d == 1), np.flatnonzero(d == -1)


def u_rest_rms(u: np.ndarray, rest: np.ndarray) -> float:
    """RMS of u about its mean over each stretch of ``rest`` (:func:`rest_mask`) [V]; NaN when
    there is none. u [V] and rest: (N,)."""
    u = np.asarray(u, dtype=float)
    segs = [u[a:b] - u[a:b].mean() for a, b in zip(*runs(rest))]
    return float(np.sqrt(np.mean(np.concatenate(segs) ** 2))) if segs else float("nan")


def tracking_indexes(t: np.ndarray, e: np.ndarray, u: np.ndarray, final_window_s: float,
                     xd_dot: np.ndarray | None = None) -> dict:
    """e_M, e_F, L2[e] in µm and u_peak in V (docs/control-law.md, Performance indexes).

    Args:
        t: sample times [s], shape (N,). e: tracking error [m], (N,). u: input [V], (N,).
        final_window_s: length of the e_F window at the end of the run [s].
        xd_dot: desired velocity [m/s], (N,), or None: with it, L2[e]'s parts in motion and at
            standstill (module docstring).
    Returns:
        {"e_M_um", "e_F_um", "L2_um", "u_peak_V"}, with ``xd_dot`` also "L2_motion_um" and
        "L2_standstill_um".
    Raises:
        ValueError: empty or mismatched arrays.
    """
    t, e, u = (np.asarray(a, dtype=float) for a in (t, e, u))
    if e.size == 0 or not (t.shape == e.shape == u.shape):
        raise ValueError("t, e and u must be non-empty arrays of the same shape")
    final = e[t >= t[-1] - final_window_s] if final_window_s > 0 else e[-1:]
    out = {
        "e_M_um": float(np.max(np.abs(e)) * 1e6),
        "e_F_um": float(np.max(np.abs(final)) * 1e6),
        "L2_um": float(np.sqrt(np.mean(e**2)) * 1e6),
        "u_peak_V": float(np.max(np.abs(u))),
    }
    if xd_dot is not None:
        xd_dot = np.asarray(xd_dot, dtype=float)
        if xd_dot.shape != e.shape:
            raise ValueError("xd_dot must have the shape of e")
        rest = np.abs(xd_dot) <= STANDSTILL_M_PER_S
        out["L2_motion_um"] = float(np.sqrt(np.sum(e[~rest] ** 2) / e.size) * 1e6)
        out["L2_standstill_um"] = float(np.sqrt(np.sum(e[rest] ** 2) / e.size) * 1e6)
    return out


class TrackingAccumulator:
    """:func:`tracking_indexes` of a run fed in batches, in memory that does not grow with it:
    running max |e|, Σe² and max |u|, and the samples of the last ``final_window_s`` for e_F.

    Args:
        final_window_s: the e_F window [s] (≤ 0: the last sample). period_s: sample period [s].
    :meth:`add` takes t [s], e [m], u [V], each (N,); :meth:`indexes` gives the dict of
    :func:`tracking_indexes` (the same e_M, e_F and u_peak; L2[e] equal up to rounding).
    Raises ValueError (``indexes``) when nothing was added.
    """

    def __init__(self, final_window_s: float, period_s: float):
        self.window = float(final_window_s)
        keep = int(np.ceil(self.window / period_s)) + 2 if self.window > 0 else 1
        self._t = np.empty(0)
        self._e = np.empty(0)
        self._keep = keep
        self.n = 0
        self.e_max = 0.0
        self.sum_e2 = 0.0
        self.u_max = 0.0

    def add(self, t: np.ndarray, e: np.ndarray, u: np.ndarray) -> None:
        if e.size == 0:
            return
        self.n += int(e.size)
        self.e_max = max(self.e_max, float(np.max(np.abs(e))))
        self.sum_e2 += float(np.dot(e, e))
        self.u_max = max(self.u_max, float(np.max(np.abs(u))))
        self._t = np.concatenate([self._t, t])[-self._keep:]
        self._e = np.concatenate([self._e, e])[-self._keep:]

    def indexes(self) -> dict:
        if self.n == 0:
            raise ValueError("no samples")
        t, e = self._t, self._e
        final = e[t >= t[-1] - self.window] if self.window > 0 else e[-1:]
        return {"e_M_um": self.e_max * 1e6, "e_F_um": float(np.max(np.abs(final)) * 1e6),
                "L2_um": float(np.sqrt(self.sum_e2 / self.n) * 1e6), "u_peak_V": self.u_max}


def settled_mask(t: np.ndarray, period_s: float, settle_periods: int = 1) -> np.ndarray:
    """Samples past the settling of a periodic program: t − t[0] ≥ settle_periods·period_s.

    Used by :func:`settled_indexes` so that two runs (before/after, ``compare-runs``) exclude
    the adaptation transient the same way.

    Args:
        t: program time of each sample [s], shape (N,). period_s: program period [s] (≤ 0: no
            period known, nothing is excluded). settle_periods: whole periods to exclude.
    Returns:
        bool (N,); all True when excluding would leave less than one period.
    """
    t = np.asarray(t, dtype=float)
    if period_s <= 0 or t.size == 0:
        return np.ones(t.shape, dtype=bool)
    m = (t - t[0]) >= settle_periods * period_s
    if t[-1] - t[0] < (settle_periods + 1) * period_s:
        return np.ones(t.shape, dtype=bool)
    return m


def settled_indexes(t: np.ndarray, e: np.ndarray, u: np.ndarray, period_s: float,
                    settle_periods: int = 1) -> dict:
    """:func:`tracking_indexes` over the settled part (:func:`settled_mask`), e_F over the last
    period; plus ``settled_from_s``, the program time the evaluation starts at [s]."""
    t, e, u = (np.asarray(a, dtype=float) for a in (t, e, u))
    m = settled_mask(t, period_s, settle_periods)
    out = tracking_indexes(t[m], e[m], u[m], period_s if period_s > 0 else 0.0)
    out["settled_from_s"] = float(t[m][0] - t[0]) if m.any() else 0.0
    return out
