"""Performance indexes of the paper's Tables I-II (docs/control-law.md, Performance indexes) and loop timing statistics.

* e_M = max |e| over the evaluated run [0, T_f] (transient performance);
* e_F = max |e| over the last ``final_window_s`` (final tracking accuracy; one trajectory
  period by default);
* L2[e] = sqrt(mean(e²)) over the run;
* u_peak = max |u| over the run (Tables I/II call it u_M; it is not the actuator limit u_lim).
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


def tracking_indexes(t: np.ndarray, e: np.ndarray, u: np.ndarray, final_window_s: float) -> dict:
    """e_M, e_F, L2[e] in µm and u_peak in V (docs/control-law.md, Performance indexes).

    Args:
        t: sample times [s], shape (N,). e: tracking error [m], (N,). u: input [V], (N,).
        final_window_s: length of the e_F window at the end of the run [s].
    Returns:
        {"e_M_um", "e_F_um", "L2_um", "u_peak_V"}.
    Raises:
        ValueError: empty or mismatched arrays.
    """
    t, e, u = (np.asarray(a, dtype=float) for a in (t, e, u))
    if e.size == 0 or not (t.shape == e.shape == u.shape):
        raise ValueError("t, e and u must be non-empty arrays of the same shape")
    final = e[t >= t[-1] - final_window_s] if final_window_s > 0 else e[-1:]
    return {
        "e_M_um": float(np.max(np.abs(e)) * 1e6),
        "e_F_um": float(np.max(np.abs(final)) * 1e6),
        "L2_um": float(np.sqrt(np.mean(e**2)) * 1e6),
        "u_peak_V": float(np.max(np.abs(u))),
    }


def timing_stats(turnaround_ns: np.ndarray, lateness_ns: np.ndarray, overruns: int) -> dict:
    """Turnaround p50/p99/p99.9/max and lateness p50/p99/max in µs, plus the overrun count."""
    ta = np.asarray(turnaround_ns, dtype=float) / 1e3
    la = np.asarray(lateness_ns, dtype=float) / 1e3
    if ta.size == 0:
        return {"cycles": 0, "overruns": int(overruns)}
    return {
        "cycles": int(ta.size),
        "turnaround_p50_us": float(np.percentile(ta, 50)),
        "turnaround_p99_us": float(np.percentile(ta, 99)),
        "turnaround_p999_us": float(np.percentile(ta, 99.9)),
        "turnaround_max_us": float(ta.max()),
        "lateness_p50_us": float(np.percentile(la, 50)),
        "lateness_p99_us": float(np.percentile(la, 99)),
        "lateness_max_us": float(la.max()),
        "overruns": int(overruns),
    }


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
