"""What the selected model leaves unexplained: the residual after selection tested for structure.

A residual that is noise has no mean that depends on where the axis is, how fast it moves,
what the input is or when in the record, and no spectral line. For each of velocity v,
position x, input u and time t (decimated signals, :class:`motorctl.ident.idim.Prepared`) the
residual r is averaged in :data:`N_BINS` quantile bins of that variable; the variable
*explains* the share Σ n_b m_b² / Σ r² of the residual's power (m_b, n_b: a bin's mean and
count). It is structured when

* that share is at least :data:`MIN_SHARE`, and
* at least :data:`NOISE_FACTOR` times what noise alone gives it: (bins − 1)/n_eff, n_eff =
  n (1 − ρ)/(1 + ρ) counting the residual's lag-1 autocorrelation ρ, and
* its size, the 99th percentile of the bin means over the samples, is one an effect would be
  named at (``min_size``: the selection's least force of an effect, 1 % of the RMS input and
  0.5 N; :mod:`motorctl.ident.select`). A share is relative: once a plant's residual is only
  its noise (the rigid plant: no stiction, no mode, an ideal amplifier) a 0.3 N difference
  between the friction the model computes from the filtered velocity and the one the carriage
  felt at the slowest speeds held 53-56 % of it, a structure no family would be named for.

The most deviating bin (its mean in standard errors, z) is where the structure is said to live.

The spectrum (Welch, scipy.signal) is structured when a line stands :data:`MIN_PEAK_RATIO`
times above the median of the spectrum above 0.5 Hz, holds at least :data:`MIN_LINE_SHARE` of
the power and its amplitude √(2·power) is at least ``min_size``. Each finding says where the structure lives ("near zero velocity (|v| < 3.2 mm/s)",
"at |u| < 0.21 V", "periodic at 4.10 Hz"), in the residual's unit.
"""

from __future__ import annotations

import math

import numpy as np
from scipy import signal

N_BINS = 16
MIN_SHARE = 0.12       #: share of the residual's power a 1-D function of one variable explains
#: "near zero velocity": below this share of the record's peak speed (a structure there is a
#: selected holding effect's, the stick and slip at rest its model leaves)
REST_SPEED_SHARE = 0.05
NOISE_FACTOR = 4.0     #: the share must be this many times what noise alone would give
MIN_PEAK_RATIO = 30.0  #: a spectral line this far above the spectrum's median
MIN_LINE_SHARE = 0.08  #: and holding this share of the residual's power (clean logs: 2.5-3.4 %)


def _binned(r: np.ndarray, x: np.ndarray, n_eff_ratio: float):
    """Quantile bins of x: the share of r's power their means explain, the noise level of that
    share, and the most deviating bin (its z, edges and mean)."""
    edges = np.unique(np.quantile(x, np.linspace(0.0, 1.0, N_BINS + 1)))
    if edges.size < 3:
        return None
    idx = np.clip(np.searchsorted(edges, x, side="right") - 1, 0, edges.size - 2)
    n = np.bincount(idx, minlength=edges.size - 1).astype(float)
    s = np.bincount(idx, weights=r, minlength=edges.size - 1)
    ok = n > 0
    m = np.where(ok, s / np.maximum(n, 1.0), 0.0)
    size = float(np.percentile(np.abs(m[idx]), 99))
    share = float(np.sum(n * m * m) / max(float(r @ r), 1e-300))
    sd = float(np.std(r))
    se = sd / np.sqrt(np.maximum(n * n_eff_ratio, 1.0))
    z = np.where(ok, np.abs(m) / np.maximum(se, 1e-300), 0.0)
    j = int(np.argmax(z))
    noise = (float(ok.sum()) - 1.0) / max(r.size * n_eff_ratio, 1.0)
    return {"share": share, "noise": noise, "size": size, "z": float(z[j]), "lo": float(edges[j]),
            "hi": float(edges[j + 1]), "mean": float(m[j])}


def _where(name: str, b: dict, span: float) -> str:
    lo, hi = b["lo"], b["hi"]
    if name == "velocity":
        if lo <= 0.0 <= hi or max(abs(lo), abs(hi)) < REST_SPEED_SHARE * span:
            return f"near zero velocity (|v| < {1e3 * max(abs(lo), abs(hi)):.3g} mm/s)"
        return f"at v in [{1e3 * lo:.3g}, {1e3 * hi:.3g}] mm/s"
    if name == "input":
        if lo <= 0.0 <= hi:
            return f"at |u| < {max(abs(lo), abs(hi)):.3g} V"
        if max(abs(lo), abs(hi)) < 0.1 * span:
            return f"at small inputs (u in [{lo:.3g}, {hi:.3g}] V)"
        return f"at u in [{lo:.3g}, {hi:.3g}] V"
    if name == "position":
        return f"at x in [{1e3 * lo:.4g}, {1e3 * hi:.4g}] mm"
    return f"from t = {lo:.3g} s to {hi:.3g} s (it drifts over the record)"


def _at_rest(name: str, b: dict, span: float) -> bool:
    """The bin lies near zero velocity or at small inputs (where a holding force or a dead-zone acts)."""
    lo, hi = b["lo"], b["hi"]
    if name == "velocity":
        return lo <= 0.0 <= hi or max(abs(lo), abs(hi)) < REST_SPEED_SHARE * span
    if name == "input":
        return lo <= 0.0 <= hi or max(abs(lo), abs(hi)) < 0.1 * span
    return False


def residual_verdict(r: np.ndarray, p, gain: float = 1.0, unit: str = "V", at_rest_by: str | None = None,
                     min_size: float = 0.0) -> dict:
    """The structure left in a residual.

    Args:
        r: the final model's residual on the decimated samples (M,) [V of input].
        p: the :class:`~motorctl.ident.idim.Prepared` signals of the record (t_d, x_d, v_d, u_d (M,)).
        gain: N per V (1 when unknown); unit: the unit the report uses ('N' or 'V').
        at_rest_by: the name of a selected effect that acts at rest or at small inputs (a
            structure there is counted as its, ``explained_by``), or None.
        min_size: least size of a structure [V]: its bin means' 99th percentile over the
            samples, or a line's amplitude (0: any size).
    Returns:
        {"structured": bool, "findings": [{"against", "share", "z", "where", "mean", "size"}]
        (the structured ones first), "tested": [every variable with its share, z, size (in
        the report's unit) and, when a selected effect accounts for it, ``explained_by``],
        "text"}.
    """
    r = np.asarray(r, dtype=float)
    r = r - r.mean()
    rho = float(np.clip(np.corrcoef(r[:-1], r[1:])[0, 1], 0.0, 0.99)) if r.size > 3 else 0.0
    ratio = (1.0 - rho) / (1.0 + rho)
    tested = []
    for name, x in (("velocity", p.v_d), ("input", p.u_d), ("position", p.x_d), ("time", p.t_d)):
        b = _binned(r, np.asarray(x, dtype=float), ratio)
        if b is None:
            continue
        span = float(np.max(np.abs(x))) if name in ("velocity", "input") else 0.0
        big = b["share"] >= max(MIN_SHARE, NOISE_FACTOR * b["noise"]) and b["size"] >= min_size
        explained = at_rest_by if big and at_rest_by and _at_rest(name, b, span) else None
        tested.append({"against": name, "share": b["share"], "noise_share": b["noise"], "z": b["z"],
                       "where": _where(name, b, span), "mean": gain * b["mean"], "size": gain * b["size"],
                       "structured": big and explained is None, "explained_by": explained})
    fs = 1.0 / float(np.median(np.diff(p.t_d)))
    f, psd = signal.welch(r, fs=fs, nperseg=min(1024, r.size), detrend="constant")
    band = f > 0.5
    if band.sum() > 8:
        j = int(np.argmax(np.where(band, psd, -np.inf)))
        ratio_pk = float(psd[j] / np.median(psd[band]))
        near = band & (np.abs(f - f[j]) <= 2.0 * (f[1] - f[0]))
        share = float(psd[near].sum() / psd[band].sum())
        amp = math.sqrt(2.0 * share * float(np.mean(r * r)))
        tested.append({"against": "spectrum", "share": share, "noise_share": math.nan, "z": ratio_pk,
                       "where": f"periodic at {f[j]:.3g} Hz", "mean": math.nan, "size": gain * amp,
                       "structured": ratio_pk >= MIN_PEAK_RATIO and share >= MIN_LINE_SHARE and amp >= min_size,
                       "explained_by": None})
    found = sorted((t for t in tested if t["structured"]), key=lambda t: -t["share"])
    text = ("unexplained structured residual remains: " + "; ".join(
        f"{t['where']} ({100 * t['share']:.0f} % of the residual's power"
        + (f", mean {t['mean']:+.3g} {unit} there" if math.isfinite(t["mean"]) else "") + ")" for t in found)
        if found else "the residual shows no structure (against velocity, input, position, time, spectrum)")
    text += "".join(f"; {t['where']} ({100 * t['share']:.0f} % of the residual's power) counted as "
                    f"{t['explained_by']}'s" for t in tested if t.get("explained_by"))
    return {"structured": bool(found), "findings": found, "tested": tested, "text": text}
