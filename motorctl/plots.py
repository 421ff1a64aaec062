"""PNG figures of a run log, like the paper's Figs. 3-12 (needs the ``plot`` extra: matplotlib).

Per axis: the desired trajectory (Fig. 3), the control input (Fig. 4), the tracking error over
the run and over one magnified trajectory period (Figs. 5-6, 9-10), and the θ̂ histories
against the simulated truth when the log carries it (Figs. 7-8, 11-12).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from motorctl.recorder.runlog import read_log

_MAX_POINTS = 20000


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

    log = read_log(log_path)
    out = Path(out_dir) if out_dir else Path(str(log_path).rsplit(".", 1)[0] + "_plots")
    out.mkdir(parents=True, exist_ok=True)
    t = log.col("t")
    sl = _thin(t.size)
    truth = log.header.get("driver", {}).get("simulated", {})
    ctrls = log.header.get("controllers", {})
    cfg_axes = log.header.get("config", {}).get("axes", {})
    files = []
    for ax in log.axes:
        a = log.axis(ax)
        kind = ctrls.get(ax, "?").upper()
        tag = f"{ax} axis, {kind}"

        fig, axs = plt.subplots(3, 1, sharex=True, figsize=(8, 6))
        for k, (key, label) in enumerate((("x_d", "x_d [m]"), ("xd_dot", "dx_d/dt [m/s]"), ("xd_ddot", "d2x_d/dt2 [m/s2]"))):
            axs[k].plot(t[sl], a[key][sl], lw=0.8)
            axs[k].set_ylabel(label)
        axs[0].set_title(f"Desired trajectory ({tag})")
        axs[-1].set_xlabel("t [s]")
        files.append(_save(fig, out / f"{ax}_trajectory.png"))

        fig, axp = plt.subplots(figsize=(8, 3.5))
        axp.plot(t[sl], a["u"][sl], lw=0.6)
        axp.set_xlabel("t [s]")
        axp.set_ylabel("u [V]")
        axp.set_title(f"Control input ({tag}), peak |u| = {np.max(np.abs(a['u'])):.2f} V")
        files.append(_save(fig, out / f"{ax}_input.png"))

        e_um = a["e"] * 1e6
        fig, axs = plt.subplots(2, 1, figsize=(8, 6))
        axs[0].plot(t[sl], e_um[sl], lw=0.6)
        axs[0].set_ylabel("e [um]")
        axs[0].set_title(f"Tracking error ({tag}): e_M = {np.max(np.abs(e_um)):.1f} um, "
                         f"L2[e] = {np.sqrt(np.mean(e_um ** 2)):.2f} um")
        period = float(cfg_axes.get(ax, {}).get("trajectory", {}).get("period_s", 0.0) or 0.0)
        if period <= 0 or t[-1] - t[0] < period:
            period = min(4.0, float(t[-1] - t[0]))
        win = t >= t[-1] - period
        axs[1].plot(t[win], e_um[win], lw=0.8)
        axs[1].set_ylabel("e [um]")
        axs[1].set_xlabel("t [s]")
        axs[1].set_title("One running period, magnified")
        files.append(_save(fig, out / f"{ax}_error.png"))

        n = 6 if kind == "C2" else 4
        fig, axs = plt.subplots(n, 1, sharex=True, figsize=(8, 1.6 * n + 1))
        th_true = truth.get(ax, {}).get("theta_true")
        for i in range(n):
            axs[i].plot(t[sl], a[f"theta_hat{i + 1}"][sl], lw=0.8, label="estimate")
            if th_true is not None:
                axs[i].axhline(th_true[i], ls="--", color="k", lw=0.8, label="simulated truth")
            axs[i].set_ylabel(f"theta{i + 1}")
        axs[0].set_title(f"Parameter estimates ({tag})")
        if th_true is not None:
            axs[0].legend(loc="best", fontsize=8)
        axs[-1].set_xlabel("t [s]")
        files.append(_save(fig, out / f"{ax}_theta.png"))
    return files


def _save(fig, path: Path) -> str:
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    import matplotlib.pyplot as plt
    plt.close(fig)
    return str(path)
