"""Report of ``motorctl identify --report DIR``: report.txt, summary.json and PNG figures.

Figures (matplotlib, Agg backend):
  * residual_position.png, residual_velocity.png, residual_time.png: the decimated residual of
    the nominal and of the augmented model against position, velocity and time;
  * spatial_periodogram.png: least-squares periodogram of the nominal residual with position as
    the abscissa (moving samples), periods on the x axis;
  * effect_shape.png: each found effect's fitted term (force or input units) against its
    natural variable (the family's :meth:`~motorctl.effects.base.EffectFamily.shape`).
"""

from __future__ import annotations

import json
import os

import numpy as np

from motorctl.effects import family as effect_family
from motorctl.effects.periodic import period_grid, spatial_periodogram


def write_report(idf, summary: dict, out_dir: str, text: str) -> list:
    """Write the report files into ``out_dir`` (created). Returns the paths written.

    Raises:
        OSError: the directory cannot be created or written.
    """
    os.makedirs(out_dir, exist_ok=True)
    paths = []
    p = os.path.join(out_dir, "report.txt")
    with open(p, "w") as fh:
        fh.write(text)
    paths.append(p)
    p = os.path.join(out_dir, "summary.json")
    with open(p, "w") as fh:
        json.dump(summary, fh, indent=1, default=float)
    paths.append(p)
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:  # pragma: no cover - matplotlib is in the plot/test extras
        return paths
    g = idf.rec.gain or 1.0
    unit = summary["residual_unit"]
    pr = idf.p
    r0 = g * idf.nominal.fit.residual
    r1 = g * idf.final.fit.residual
    for name, xv, xl in (("position", pr.x_d, "position [m]"), ("velocity", pr.v_d, "velocity [m/s]"),
                         ("time", pr.t_d, "time [s]")):
        fig, ax = plt.subplots(figsize=(8, 4.5))
        ax.plot(xv, r0, ".", ms=2, alpha=0.5, label=f"nominal (RMS {np.sqrt(np.mean(r0**2)):.3g} {unit})")
        ax.plot(xv, r1, ".", ms=2, alpha=0.5, label=f"augmented (RMS {np.sqrt(np.mean(r1**2)):.3g} {unit})")
        ax.set_xlabel(xl)
        ax.set_ylabel(f"residual [{unit}]")
        ax.set_title(f"IDIM residual against {name}")
        ax.legend(loc="upper right")
        ax.grid(alpha=0.3)
        fig.tight_layout()
        p = os.path.join(out_dir, f"residual_{name}.png")
        fig.savefig(p, dpi=110)
        plt.close(fig)
        paths.append(p)
    grid = period_grid(idf.stroke)
    if grid.size and idf.moving.sum() > 50:
        mv = idf.moving
        pw = spatial_periodogram(pr.x_d[mv], idf.nominal.fit.residual[mv], grid)
        fig, ax = plt.subplots(figsize=(8, 4.5))
        ax.semilogx(grid * 1e3, pw)
        for e in summary["effects"]:
            if "period_m" in e["parameters"]:
                ax.axvline(e["parameters"]["period_m"] * 1e3, color="r", ls="--", label=f"{e['name']}")
        ax.set_xlabel("period [mm]")
        ax.set_ylabel("normalised LS power")
        ax.set_title("spatial periodogram of the nominal residual (moving samples)")
        if any("period_m" in e["parameters"] for e in summary["effects"]):
            ax.legend()
        ax.grid(alpha=0.3, which="both")
        fig.tight_layout()
        p = os.path.join(out_dir, "spatial_periodogram.png")
        fig.savefig(p, dpi=110)
        plt.close(fig)
        paths.append(p)
    if idf.terms:
        # the values the report prints (a refit's, when one ran)
        src = idf.refitted or idf
        _, betas = src.coef_split(src.final, src.terms)
        n = len(src.terms)
        fig, axes = plt.subplots(n, 1, figsize=(8, 3.2 * n), squeeze=False)
        for ax, t, b in zip(axes[:, 0], src.terms, betas):
            fam = effect_family(t.family)
            shape = effect_shape(src, t, b)
            if shape is not None:
                xv, yv, xl, yl = shape
                ax.plot(xv, yv, "-", lw=1)
                ax.set_xlabel(xl)
                ax.set_ylabel(yl.replace("UNIT", unit))
            ax.set_title(f"{t.family}: " + _fmt(fam.parameters(t.h, b, idf.rec.gain, pr.fs)), fontsize=9)
            ax.grid(alpha=0.3)
        fig.tight_layout()
        p = os.path.join(out_dir, "effect_shape.png")
        fig.savefig(p, dpi=110)
        plt.close(fig)
        paths.append(p)
    return paths


def _fmt(params: dict) -> str:
    out = []
    for k, v in params.items():
        if isinstance(v, list):
            out.append(f"{k} [" + ", ".join(f"{x:.3g}" for x in v) + "]")
        else:
            out.append(f"{k} {v:.4g}")
    return ", ".join(out)


def effect_shape(idf, term, beta):
    """The found effect's term on a grid of its natural variable, unfiltered (the family's
    :meth:`~motorctl.effects.base.EffectFamily.shape`).

    Args:
        idf: the run identifier. term: a selected term. beta: its coefficients (k,).
    Returns:
        (x (K,), y (K,), x label, y label with UNIT for N or V), or None when the family has no
        figure.
    """
    return effect_family(term.family).shape(idf, term.h, beta, idf.rec.gain)
