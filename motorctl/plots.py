"""PNG figures of a run log, like the paper's Figs. 3-12 (needs the ``plot`` extra: matplotlib).

Per axis: the desired trajectory (Fig. 3), the control input (Fig. 4), the tracking error over
the run and over one magnified trajectory period (Figs. 5-6, 9-10), and the θ̂ histories
against the simulated truth when the log carries it (Figs. 7-8, 11-12).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from motorctl.model import THETA_UNITS
from motorctl.recorder.runlog import LogError, RunLog
from motorctl.recorder.segments import read_run

_MAX_POINTS = 20000
#: the columns the figures of an axis need (besides t)
_AXIS_NEEDS = ("x_d", "xd_dot", "xd_ddot", "u", "e") + tuple(f"theta_hat{i}" for i in range(1, 7))


def _get(d, *keys, default=None):
    """``d[k1][k2]...`` of a header, or ``default`` when a level is missing or not a mapping."""
    for k in keys:
        if not isinstance(d, dict) or k not in d:
            return default
        d = d[k]
    return d


def _read(log_path: str) -> RunLog:
    """The run (a run log, or a daemon's segments as one run) with the columns the figures
    need. Raises LogError (one line) when it has no records or lacks a column."""
    log = read_run(log_path)
    need = ["t"] + [f"{a}.{f}" for a in log.axes for f in _AXIS_NEEDS]
    missing = [c for c in need if c not in log.columns]
    if missing:
        raise LogError(f"{log_path}: no column {missing[0]!r} for the figures "
                       f"({len(missing)} missing)")
    if log.data.shape[0] == 0:
        raise LogError(f"{log_path}: the run log has no records")
    return log


def _thin(n: int) -> slice:
    return slice(None, None, max(1, n // _MAX_POINTS))


def plot_log(log_path: str, out_dir: str | None = None) -> list[str]:
    """Write the figures of ``log_path`` as PNG files; returns their paths.

    Raises:
        motorctl.recorder.runlog.LogError: not a run log. OSError: cannot write ``out_dir``.
    """
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    log = _read(log_path)
    out = Path(out_dir) if out_dir else Path(str(log_path).rsplit(".", 1)[0] + "_plots")
    out.mkdir(parents=True, exist_ok=True)
    t_all = log.col("t")
    files = []
    for ax in log.axes:
        a = log.axis(ax)
        keep = log.program_rows(ax)              # the rows ``motorctl run``'s indexes cover
        if keep is not None and keep.any():
            a = {k: v[keep] for k, v in a.items()}
            t = t_all[keep]
        else:
            t = t_all
        sl = _thin(t.size)
        kind = str(_get(log.header, "controllers", ax, default="?")).upper()
        tag = f"{ax} axis, {kind}"

        fig, axs = plt.subplots(3, 1, sharex=True, figsize=(8, 6))
        for k, (key, label) in enumerate((("x_d", r"$x_d$ [m]"), ("xd_dot", r"$\dot x_d$ [m/s]"),
                                          ("xd_ddot", r"$\ddot x_d$ [m/s²]"))):
            axs[k].plot(t[sl], a[key][sl], lw=0.8)
            axs[k].set_ylabel(label)
        axs[0].set_title(f"Desired trajectory ({tag})")
        axs[-1].set_xlabel("t [s]")
        files.append(_save(fig, out / f"{ax}_trajectory.png", log_path))

        ctl = _get(log.header, "config", "axes", ax, "controller", default={})
        fig, axp = plt.subplots(figsize=(8, 3.5))
        axp.plot(t[sl], a["u"][sl], lw=0.6)
        u_lim = _get(ctl, "u_lim")
        if isinstance(u_lim, (int, float)) and np.isfinite(u_lim):
            for sgn in (1.0, -1.0):
                axp.axhline(sgn * u_lim, ls="--", color="r", lw=0.8, label="±u_lim" if sgn > 0 else None)
            axp.legend(loc="upper right", fontsize=8)
        axp.set_xlabel("t [s]")
        axp.set_ylabel("u [V]")
        axp.set_title(f"Control input ({tag}), peak |u| = {np.max(np.abs(a['u'])):.2f} V")
        files.append(_save(fig, out / f"{ax}_input.png", log_path))

        e_um = a["e"] * 1e6
        fig, axs = plt.subplots(2, 1, figsize=(8, 6))
        axs[0].plot(t[sl], e_um[sl], lw=0.6)
        axs[0].set_ylabel("e [um]")
        axs[0].set_title(f"Tracking error ({tag}): e_M = {np.max(np.abs(e_um)):.1f} um, "
                         f"L2[e] = {np.sqrt(np.mean(e_um ** 2)):.2f} um")
        period = _get(log.header, "config", "axes", ax, "trajectory", "period_s", default=0.0)
        period = float(period) if isinstance(period, (int, float)) and np.isfinite(period) else 0.0
        if period <= 0 or t[-1] - t[0] < period:
            period = min(4.0, float(t[-1] - t[0]))
        win = t >= t[-1] - period
        axs[1].plot(t[win], e_um[win], lw=0.8)
        axs[1].set_ylabel("e [um]")
        axs[1].set_xlabel("t [s]")
        axs[1].set_title("One running period, magnified")
        files.append(_save(fig, out / f"{ax}_error.png", log_path))

        n = 6 if kind == "C2" else 4
        fig, axs = plt.subplots(n, 1, sharex=True, figsize=(8, 1.6 * n + 1))
        th_true = _get(log.header, "driver", "simulated", ax, "theta_true")
        if not (isinstance(th_true, list) and len(th_true) >= n
                and all(isinstance(x, (int, float)) for x in th_true[:n])):
            th_true = None
        lo, hi = _get(ctl, "theta_min"), _get(ctl, "theta_max")
        box = (isinstance(lo, list) and isinstance(hi, list) and len(lo) >= n and len(hi) >= n
               and all(isinstance(x, (int, float)) for x in lo[:n] + hi[:n]))
        for i in range(n):
            axs[i].plot(t[sl], a[f"theta_hat{i + 1}"][sl], lw=0.8, label=r"$\hat\theta$")
            if th_true is not None:
                axs[i].axhline(th_true[i], ls="--", color="k", lw=0.8, label="simulated truth")
            if box:
                for k, b in enumerate((lo[i], hi[i])):
                    axs[i].axhline(b, ls=":", color="r", lw=0.8, label="projection bounds" if k == 0 else None)
            axs[i].set_ylabel(rf"$\hat\theta_{i + 1}$ [{THETA_UNITS[i].replace('*', ' ').replace('^2', '²')}]", fontsize=8)
        axs[0].set_title(rf"Parameter estimates $\hat\theta$ ({tag})")
        if th_true is not None or box:
            axs[0].legend(loc="best", fontsize=7, ncol=3)
        axs[-1].set_xlabel("t [s]")
        files.append(_save(fig, out / f"{ax}_theta.png", log_path))
    return files


def _save(fig, path: Path, source: str | None = None) -> str:
    """Write ``fig`` as PNG at ``path``: refused over the run log ``source`` or any run log,
    written to a temporary name and renamed (never a partial PNG). Raises InputError."""
    import matplotlib.pyplot as plt

    from motorctl.recorder.outfile import atomic_output, check_output
    try:
        check_output(path, [source] if source else [], "plot")
        fig.tight_layout()
        with atomic_output(path, "plot") as tmp:
            fig.savefig(tmp, dpi=110, format="png")
    finally:
        plt.close(fig)
    return str(path)


def plot_compare_errors(t: np.ndarray, errors: dict, periods: dict, out_dir: str,
                        title: str = "") -> list[str]:
    """The tracking error of the last trajectory period of each controller, overlaid (like the
    paper's Figs. 5 and 9), one PNG per axis: ``<out_dir>/<axis>_compare_error.png``.

    Args:
        t: time [s], shape (N,), shared by the runs (same config, same duration).
        errors: {axis: {controller name: e [m], shape (N,)}}.
        periods: {axis: trajectory period [s]} (≤ 0 or longer than the run: the last 4 s).
        out_dir: created if missing. title: appended to each figure's title.
    Returns: the paths written.
    Raises: OSError: cannot write ``out_dir``.
    """
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    files = []
    for ax, per_ctrl in errors.items():
        period = float(periods.get(ax, 0.0) or 0.0)
        if period <= 0 or t[-1] - t[0] < period:
            period = min(4.0, float(t[-1] - t[0]))
        win = t >= t[-1] - period
        fig, axp = plt.subplots(figsize=(8, 4))
        for kind, e in per_ctrl.items():
            e_um = np.asarray(e)[win] * 1e6
            axp.plot(t[win], e_um, lw=0.8, label=f"{kind.upper()}: e_M {np.max(np.abs(e_um)):.1f} um, "
                                                 f"L2 {np.sqrt(np.mean(e_um ** 2)):.2f} um")
        axp.set_xlabel("t [s]")
        axp.set_ylabel("e [um]")
        axp.set_title(f"Tracking error over one period, {ax} axis{(', ' + title) if title else ''}")
        axp.legend(loc="best", fontsize=8)
        files.append(_save(fig, out / f"{ax}_compare_error.png"))
    return files


def plot_circle_tests(runs: list, out_dir: str) -> list[str]:
    """The radial deviation of each circular test (ISO 230-4, as a ballbar report shows it):
    the CW and CCW paths' radius about their least-squares centre minus the least-squares
    radius [um], on a polar plot around a reference circle, G and H in the title; one PNG per
    run: ``<out_dir>/circle_<controller>_<feed mm/s>.png``.

    Args:
        runs: :class:`motorctl.app.circle_test.CircleRun` list. out_dir: created if missing.
    Returns: the paths written. Raises: OSError: cannot write ``out_dir``.
    """
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from motorctl.motion.circle import radial

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    files = []
    for r in runs:
        g = r.result
        fig = plt.figure(figsize=(5.5, 5.5))
        axp = fig.add_subplot(projection="polar")
        ref = max(5.0 * g.G_b * 1e6, 10.0)        # the reference circle [um of the plot's radius]
        for d, style in (("ccw", "-"), ("cw", "--")):
            ang, rad = radial(*r.paths[d], g.center_lsc)
            dev = (rad - g.radius_lsc) * 1e6
            axp.plot(ang, ref + dev, style, lw=0.8, label=d.upper())
        axp.plot(np.linspace(0, 2 * np.pi, 361), np.full(361, ref), ":", color="grey", lw=0.6)
        axp.set_rlim(0, ref + 2.0 * max(g.G_b * 1e6, 1.0))
        axp.set_yticklabels([])
        axp.set_title(f"{r.controller.upper()}, R {r.radius * 1e3:g} mm, F {r.feed * 1e3:.0f} mm/s: "
                      f"G(b) {g.G_b * 1e6:.2f} um, H {g.H * 1e6:.2f} um\n(radial deviation, reference "
                      f"circle = {ref:.0f} um of the scale)", fontsize=9)
        axp.legend(loc="lower right", fontsize=8)
        files.append(_save(fig, out / f"circle_{r.controller}_{r.feed * 1e3:.0f}.png"))
    return files
