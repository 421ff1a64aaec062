"""Two run logs over the same program periods: the tracking indexes of each and their ratio
(``motorctl compare-runs``, and ``motorctl tune``'s before/after), and the figure of the last
common period. The text and the command are :mod:`motorctl.cli.runs`.

Per axis present in both logs: e_M, e_F, L2[e] [µm] and u_peak [V] (docs/control-law.md, Performance indexes,
:func:`motorctl.metrics.tracking_indexes`) of each log and the ratio after/before, with L2[e]'s
parts in motion and at standstill and u's noise at rest (:data:`SPLIT`) where both logs record
the desired velocity and acceleration. The two logs
are aligned by program time (the program's rows, ``mode`` = program, their ``t`` = k·Ts counted
from the program's start): both are evaluated over the same whole
program periods, from the end of the settling (the first ``settle_periods`` periods excluded the
same way for both, :func:`motorctl.metrics.settled_mask`) to the end of the last period both
logs complete; e_F is the last of those periods. Only cycles with the amplifier enabled count.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from motorctl.metrics import rest_mask, tracking_indexes, u_rest_rms

INDEXES = ("e_M_um", "e_F_um", "L2_um", "u_peak_V")
#: L2[e]'s parts in motion and at standstill (L2² = motion² + standstill²,
#: :func:`motorctl.metrics.tracking_indexes`) and u's RMS at rest [V]
#: (:func:`motorctl.metrics.u_rest_rms`), when both records carry ẋ_d and ẍ_d
SPLIT = ("L2_motion_um", "L2_standstill_um", "u_rest_rms_V")


def _period(header: dict, axis: str) -> float | None:
    try:
        v = header["config"]["axes"][axis]["trajectory"].get("period_s")
    except (KeyError, TypeError, AttributeError):
        return None
    return float(v) if v else None


def _axis_data(log, axis: str) -> tuple:
    """(t, e, u, ẋ_d, ẍ_d) of the enabled program cycles of ``axis`` in program time (each
    (N,); ẋ_d and ẍ_d None when the log lacks them). A log whose rows carry the sequencer's
    ``mode`` (a run starts with idle cycles and an approach) keeps the rows of mode program,
    t counted from the program's start (the header's ``program_start_s``, else the axis's
    first program row); an older log without it: every enabled row, t as recorded."""
    a = log.axis(axis)
    t = log.col("t")
    on = a["enabled"] > 0.5
    prog = log.program_rows(axis)
    if prog is not None:
        on &= prog
        t0 = log.header.get("program_start_s") if isinstance(log.header, dict) else None
        if t0 is None and prog.any():
            t0 = float(t[np.argmax(prog)])
        t = t - float(t0 or 0.0)
    if "xd_dot" not in a or "xd_ddot" not in a:
        return t[on], a["e"][on], a["u"][on], None, None
    return t[on], a["e"][on], a["u"][on], a["xd_dot"][on], a["xd_ddot"][on]


def window(t_b: np.ndarray, t_a: np.ndarray, period_s: float | None, settle_periods: int) -> tuple[float, float]:
    """The common evaluation window [t0, t1) in program time [s]: whole periods after the
    settling, up to the last period both logs complete (without a period: the common span).

    Raises:
        ValueError: the logs share no program time, or less than one period after settling.
    """
    lo, hi = max(t_b[0], t_a[0]), min(t_b[-1], t_a[-1])
    if t_b.size > 1:
        hi += float(np.median(np.diff(t_b[-64:])))      # the last sample covers one more period
    if not hi > lo:
        raise ValueError(f"the logs share no program time (before {t_b[0]:g}..{t_b[-1]:g} s, "
                         f"after {t_a[0]:g}..{t_a[-1]:g} s)")
    if not period_s:
        return lo, hi + 1e-12
    k0 = math.ceil(lo / period_s - 1e-9) + settle_periods
    n = math.floor((hi + 1e-9) / period_s) - k0
    if n < 1:
        # too short to exclude the settling and keep a whole period: no exclusion
        k0 = math.ceil(lo / period_s - 1e-9)
        n = math.floor((hi + 1e-9) / period_s) - k0
        if n < 1:
            raise ValueError(f"the logs share less than one program period ({period_s:g} s): "
                             f"{lo:g}..{hi:g} s")
    return k0 * period_s, (k0 + n) * period_s


def compare_axis(before: tuple, after: tuple, period_s: float | None, settle_periods: int = 1) -> dict:
    """Indexes of two (t, e, u) records of one axis over the same window, and the ratios.

    Args:
        before, after: (t [s], e [m], u [V]) or (t, e, u, ẋ_d [m/s], ẍ_d [m/s²]) each (N,),
            program time t (ẋ_d and ẍ_d may be None).
        period_s: program period [s] or None. settle_periods: periods excluded at the start.
    Returns:
        {"window_s": [t0, t1], "period_s", "before": {...}, "after": {...}, "ratio": {...}}
        with the keys of :func:`motorctl.metrics.tracking_indexes` (:data:`SPLIT` too when both
        records carry ẋ_d and ẍ_d; "u_rest_rms_V" None when the window has no rest); ratio =
        after / before (None where before's is 0 or None).
    Raises:
        ValueError: see :func:`window`.
    """
    t0, t1 = window(before[0], after[0], period_s, settle_periods)
    out = {"window_s": [t0, t1], "period_s": period_s, "settle_periods": settle_periods}
    split = all(len(r) > 4 and r[3] is not None and r[4] is not None for r in (before, after))
    for name, rec in (("before", before), ("after", after)):
        t, e, u = rec[:3]
        m = (t >= t0 - 1e-9) & (t < t1 - 1e-9)
        if m.sum() < 2:
            raise ValueError(f"{name}: no enabled cycles in {t0:g}..{t1:g} s")
        out[name] = tracking_indexes(t[m], e[m], u[m], period_s or 0.0, rec[3][m] if split else None)
        if split:
            ts = float(np.median(np.diff(t[m])))
            ur = u_rest_rms(u[m], rest_mask(rec[3][m], rec[4][m], ts))
            out[name]["u_rest_rms_V"] = ur if ur == ur else None      # None: no rest in the window
        out[name]["cycles"] = int(m.sum())
    keys = INDEXES + (SPLIT if split else ())
    out["ratio"] = {k: (out["after"][k] / out["before"][k] if out["before"][k] and out["after"][k] is not None
                        else None) for k in keys}
    return out


def compare_logs(before_path: str, after_path: str, axes=None, period_s: float | None = None,
                 settle_periods: int = 1) -> dict:
    """:func:`compare_axis` for every axis of both run logs (or ``axes``).

    Raises:
        LogError: a log cannot be read. ValueError: an axis missing, or no common window.
    """
    from motorctl.recorder.runlog import read_log
    lb, la = read_log(before_path), read_log(after_path)
    names = axes or [a for a in lb.axes if a in la.axes]
    if not names:
        raise ValueError(f"{before_path} and {after_path} have no axis in common "
                         f"({', '.join(lb.axes)} / {', '.join(la.axes)})")
    res = {"before": str(before_path), "after": str(after_path), "axes": {}}
    for a in names:
        for path, log in ((before_path, lb), (after_path, la)):
            if a not in log.axes:
                raise ValueError(f"{path}: no axis {a!r}; axes: {', '.join(log.axes)}")
        p = period_s or _period(lb.header, a) or _period(la.header, a)
        db, da = _axis_data(lb, a), _axis_data(la, a)
        if db[0].size < 2 or da[0].size < 2:
            raise ValueError(f"axis {a!r}: fewer than 2 enabled cycles in a log")
        res["axes"][a] = compare_axis(db, da, p, settle_periods)
        res["axes"][a]["_data"] = (db, da)
    return res


def figure(res: dict, axis: str, path: Path) -> None:
    """The error [µm] of the last common period of both logs, against time in the period."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    r = res["axes"][axis]
    t0, t1 = r["window_s"]
    p = r["period_s"] or (t1 - t0)
    s0 = t1 - p
    fig, ax = plt.subplots(figsize=(8, 3.5))
    for name, (t, e, *_rest) in zip(("before", "after"), r["_data"]):
        m = (t >= s0 - 1e-9) & (t < t1 - 1e-9)
        ax.plot(t[m] - s0, e[m] * 1e6, lw=0.8,
                label=f"{name}: L2 {r[name]['L2_um']:.3g} um, e_M {r[name]['e_M_um']:.3g} um")
    ax.set_xlabel(f"time in the period from {s0:g} s [s]")
    ax.set_ylabel(f"{axis} tracking error [um]")
    ax.legend(loc="upper right", fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def figures(res: dict, out_dir) -> list[str]:
    """Write :func:`figure` of every axis of ``res`` to ``out_dir/compare_runs_<axis>.png``.

    Returns:
        The paths written.
    Raises:
        ImportError: matplotlib (the ``plot`` extra) is not installed.
    """
    paths = [Path(out_dir) / f"compare_runs_{a}.png" for a in res["axes"]]
    for a, path in zip(res["axes"], paths):
        figure(res, a, path)
    return [str(p) for p in paths]


def public(res: dict) -> dict:
    """``res`` of :func:`compare_logs` without the records it carries (what --json prints)."""
    for r in res["axes"].values():
        r.pop("_data", None)
    return res


__all__ = ["INDEXES", "SPLIT", "compare_axis", "compare_logs", "figure", "figures", "public", "window"]
