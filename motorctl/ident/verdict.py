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

The travel since the motion last reversed (:func:`travel_since_reversal`, from the raw reading)
is a fifth variable, for a force of that travel rather than of the speed: presliding
(hysteretic) friction, whose bristles deflect elastically over a distance δ = F_c/σ₀ after each
reversal before the friction reaches its sliding level (dF/dx = σ₀ (1 − sgn(ẋ) F/F_c), P. R.
Dahl, "A solid friction model", The Aerospace Corporation, TOR-0158(3107-18)-1, 1968; the LuGre
model of C. Canudas de Wit, H. Olsson, K. J. Åström, P. Lischinsky, "A new model for control of
systems with friction", IEEE Trans. Automatic Control 40(3), 1995), or a play the motor crosses
before it takes up its load. The model's friction reaches its level within a few mm/s of speed,
so such a force is left right after each reversal; averaged over velocity bins it falls in the
slowest bins with the samples at rest (a selected stiction's, by the rule above) and the
accelerating and decelerating branches partly cancel. The residual, signed by the direction of
motion, is averaged in log-spaced bins of the travel (:data:`N_TRAVEL_BINS` from the reversal's
detection threshold to the longest travel, merged until each holds :data:`MIN_TRAVEL_COUNT`
samples); it is structured with the share and noise rules above and when, within the first
:data:`MAX_TRAVEL_SHARE` of the longest travel, a bin's mean is a deficit (less force against
the motion than the model's) of at least :data:`MIN_TRAVEL_COULOMB` of the Coulomb level θ3
(and ``min_size``). The sign is the physics: while the bristles deflect the friction is below
its sliding level (|F| ≤ F_c in Dahl's model) and across a play the motor moves without its
load, so both leave less force than the model, whose friction reaches θ3 within a few mm/s; a
sign-shaped (Karnopp) Coulomb friction against the model's smooth S_f leaves more (or a few per
cent of θ3 less where a fitted Stribeck hump overshoots it).

The spectrum (Welch, scipy.signal) is structured when a line stands :data:`MIN_PEAK_RATIO`
times above the median of the spectrum above 0.5 Hz, holds at least :data:`MIN_LINE_SHARE` of
the power and its amplitude √(2·power) is at least ``min_size``. Each finding says where the structure lives ("near zero velocity (|v| < 3.2 mm/s)",
"at |u| < 0.21 V", "periodic at 4.10 Hz"), in the residual's unit.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

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
#: bins of the travel since the last reversal (log-spaced, :func:`_travel_binned`)
N_TRAVEL_BINS = 12
#: least samples (decimated) in a bin of the travel; smaller bins are merged into the next
#: (a 12 s record of 7.5 back-and-forth periods has one sample per reversal in the first bins)
MIN_TRAVEL_COUNT = 5
#: the deficit after a reversal must reach this share of the Coulomb level θ3. Measured (deficit /
#: θ3): clean records 0.02-0.06 (benchmarks/ident_unmodelled.py clean and encoder5um seeds 1-6:
#: a fitted Stribeck hump overshooting the sign-shaped Coulomb friction), 0.00-0.04 on
#: benchmarks/ident_verdict.py's clean, encoder and mode logs of the default, rigid and
#: half-mode plants (0.05-0.06 with a 400 Hz current loop); Dahl/LuGre friction with a
#: presliding distance of 40 and 120 µm 0.74 and 1.06 (seeds 1-6); EMPS (a real axis)
#: 0.41-0.45, 8.2-8.4 N in its first 46 µm
MIN_TRAVEL_COULOMB = 0.3
#: the deficit is looked for within this share of the longest travel: presliding lasts tens to
#: hundreds of µm, a play its width; beyond, on a back-and-forth program the travel since the
#: reversal is the distance from the stroke's end, a function of position (tested as such: a
#: force constant falling 20 % towards the stroke's ends left a deficit of 0.26 θ3 at 41-111 mm
#: of a 300 mm travel, and an excess of up to 0.29 θ3 at 3-10 mm)
MAX_TRAVEL_SHARE = 0.1


def _binned(r: np.ndarray, x: np.ndarray, n_eff_ratio: float):
    """Quantile bins of x: the share of r's power their means explain, the noise level of that
    share, and the most deviating bin (its z, edges and mean)."""
    edges = np.unique(np.quantile(x, np.linspace(0.0, 1.0, N_BINS + 1)))
    if edges.size < 3:
        return None
    idx = np.clip(np.searchsorted(edges, x, side="right") - 1, 0, edges.size - 2)
    m, share, noise, z = _bin_means(r, r, idx, edges.size - 1, n_eff_ratio)
    size = float(np.percentile(np.abs(m[idx]), 99))
    j = int(np.argmax(z))
    return {"share": share, "noise": noise, "size": size, "z": float(z[j]), "lo": float(edges[j]),
            "hi": float(edges[j + 1]), "mean": float(m[j])}


def _bin_means(r: np.ndarray, w: np.ndarray, idx: np.ndarray, bins: int, n_eff_ratio: float):
    """The means m (bins,) of ``w`` (K,) over its bins ``idx`` (K,) (0 in an empty bin), the
    share of the residual r's (M,) power they explain Σ n_b m_b² / Σ r², that share's level for
    noise alone ((bins holding samples − 1)/n_eff, n_eff = M · ``n_eff_ratio``) and each mean in
    standard errors of r (z, (bins,)). ``w`` is r or a part of it (signed, e.g. by the direction
    of motion)."""
    n = np.bincount(idx, minlength=bins).astype(float)
    m = np.bincount(idx, weights=w, minlength=bins) / np.maximum(n, 1.0)
    share = float(np.sum(n * m * m) / max(float(r @ r), 1e-300))
    noise = (float((n > 0).sum()) - 1.0) / max(r.size * n_eff_ratio, 1.0)
    se = float(np.std(r)) / np.sqrt(np.maximum(n * n_eff_ratio, 1.0))
    return m, share, noise, np.abs(m) / np.maximum(se, 1e-300)


def reversal_threshold(p) -> float:
    """The travel [m] that tells a reversal of the motion from the reading's noise: two counts
    of a quantized reading (:func:`motorctl.effects.stiction.encoder_count`; a reading at rest
    flickers by one), else four robust standard deviations (1.4826 MAD) of the raw reading
    about the filtered position, y − x. p: prepared signals with ``y``, ``x`` (N,) [m]."""
    from motorctl.effects.stiction import encoder_count

    q = encoder_count(p.y)
    if q > 0.0:
        return 2.0 * q
    e = np.asarray(p.y, dtype=float) - np.asarray(p.x, dtype=float)
    return 4.0 * 1.4826 * float(np.median(np.abs(e - np.median(e))))


def travel_since_reversal(y: np.ndarray, threshold: float) -> tuple[np.ndarray, np.ndarray]:
    """The travel since the motion last reversed, from the raw reading y (N,) [m]: the distance
    [m] (N,) from the last turning point (the reading's extreme before it moved back by more
    than ``threshold`` [m]), and the direction of motion since then (N,) in {−1, +1}; 0 (both)
    before the reading first moved by ``threshold``. A start from rest in the same direction
    is not a reversal: Dahl's bristles keep their deflection at rest (dz/dt = 0 when ẋ = 0)."""
    y = np.asarray(y, dtype=float)
    s = np.zeros(y.size)
    d = np.zeros(y.size)
    lo = hi = ext = turn = float(y[0]) if y.size else 0.0
    sgn = 0
    for i, yi in enumerate(y.tolist()):
        if sgn == 0:
            lo, hi = min(lo, yi), max(hi, yi)
            if hi - lo > threshold:
                sgn = 1 if yi == hi else -1
                turn, ext = (lo if sgn > 0 else hi), yi
        elif sgn * (yi - ext) > 0.0:
            ext = yi
        elif sgn * (ext - yi) > threshold:
            sgn, turn, ext = -sgn, ext, yi
        if sgn:
            s[i], d[i] = abs(yi - turn), sgn
    return s, d


def _travel_binned(r: np.ndarray, p, n_eff_ratio: float):
    """The residual r (M,) signed by the direction of motion, in log-spaced bins of the travel
    since the last reversal at the decimated instants (:data:`N_TRAVEL_BINS` from the reversal
    threshold to the longest travel, each merged into the next until it holds
    :data:`MIN_TRAVEL_COUNT` samples): the share of r's power their means explain, its noise
    level, the deficit (``size``: minus the most negative bin mean among the bins within
    :data:`MAX_TRAVEL_SHARE` of the longest travel, 0 when none is negative) and its bin (else
    the most deviating bin); None without a reversal. p: the record's
    :class:`~motorctl.ident.idim.Prepared` (the travel is kept in its ``derived``)."""
    got = p.derived.get("travel_since_reversal")
    if got is None:                         # the verdict runs several times on one record
        thr = reversal_threshold(p)
        got = (thr, None, None)
        if thr > 0.0:
            s_full, d_full = travel_since_reversal(p.y, thr)
            k = np.clip(np.searchsorted(p.t, p.t_d), 0, len(p.t) - 1)
            got = (thr, s_full[k], d_full[k])
        p.derived["travel_since_reversal"] = got
    thr, s, d = got
    if s is None or s.size != r.size:
        return None
    use = d != 0
    if use.sum() < 2 * MIN_TRAVEL_COUNT or not s[use].max() > thr:
        return None
    rs, s = (r * d)[use], s[use]
    edges = np.geomspace(thr, s.max() * (1.0 + 1e-9), N_TRAVEL_BINS + 1)
    edges[0] = 0.0
    idx = np.clip(np.searchsorted(edges, s, side="right") - 1, 0, N_TRAVEL_BINS - 1)
    n = np.bincount(idx, minlength=N_TRAVEL_BINS)
    keep, acc = [0], 0                      # merge each bin short of MIN_TRAVEL_COUNT into the next
    for b in range(N_TRAVEL_BINS - 1):
        acc += n[b]
        if acc >= MIN_TRAVEL_COUNT:
            keep.append(b + 1)
            acc = 0
    if acc + n[-1] < MIN_TRAVEL_COUNT and len(keep) > 1:
        keep.pop()                          # the last bin is too small: into the one before
    edges = np.append(edges[keep], edges[-1])
    if edges.size < 3:
        return None
    idx = np.clip(np.searchsorted(edges, s, side="right") - 1, 0, edges.size - 2)
    m, share, noise, z = _bin_means(r, rs, idx, edges.size - 1, n_eff_ratio)
    short = edges[1:] <= MAX_TRAVEL_SHARE * s.max()
    # the deficit: the most negative mean in the first tenth of the travel (else the most deviating bin)
    j = int(np.argmin(np.where(short, m, np.inf))) if short.any() else int(np.argmax(z))
    if not (short[j] and m[j] < 0.0):
        j = int(np.argmax(z))
    deficit = float(-m[j]) if short[j] and m[j] < 0.0 else 0.0
    return {"share": share, "noise": noise, "size": deficit, "z": float(z[j]), "lo": float(edges[j]),
            "hi": float(edges[j + 1]), "mean": float(m[j]), "from": thr}


def _where_travel(b: dict) -> str:
    """Where a structure against the travel lives (:func:`_travel_binned`'s bin), in µm or mm."""
    lo, hi = max(b["lo"], b["from"]), b["hi"]
    unit, k = ("µm", 1e6) if hi < 1e-3 else ("mm", 1e3)
    if b["size"] > 0.0:
        return (f"at {k * lo:.3g}-{k * hi:.3g} {unit} of travel since the motion reversed, less force "
                f"against the motion than the model's friction: a force of the travel, not of the speed "
                f"(presliding friction, a play)")
    return f"at {k * lo:.3g}-{k * hi:.3g} {unit} of travel since the motion reversed"


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


@dataclass(frozen=True, eq=False)
class Verdict:
    """The structure left in a residual (:func:`residual_verdict`), a plain record.

    Attributes:
        structured: the residual keeps a structure no selected effect explains.
        findings: the structured entries (dicts: ``against``, ``share``, ``noise_share``, ``z``,
            ``where``, ``mean``, ``size``, ``structured``, ``explained_by``), the largest share first.
        tested: every entry tested, structured or not. text: the report's sentence.

    Read like the summary's ``residual`` dict too (``v["structured"]``); :meth:`as_dict` is it.
    """

    structured: bool
    findings: tuple
    tested: tuple
    text: str

    def __getitem__(self, key: str):
        if key not in ("structured", "findings", "tested", "text"):
            raise KeyError(key)
        return getattr(self, key)

    def get(self, key: str, default=None):
        try:
            return self[key]
        except KeyError:
            return default

    def as_dict(self) -> dict:
        """{"structured", "findings", "tested", "text"}: the summary's ``residual``."""
        return {"structured": self.structured, "findings": list(self.findings), "tested": list(self.tested),
                "text": self.text}


def residual_verdict(r: np.ndarray, p, gain: float = 1.0, unit: str = "V", at_rest_by: str | None = None,
                     min_size: float = 0.0, coulomb: float | None = None) -> Verdict:
    """The structure left in a residual.

    Args:
        r: the final model's residual on the decimated samples (M,) [V of input].
        p: the :class:`~motorctl.ident.idim.Prepared` signals of the record (t_d, x_d, v_d, u_d (M,)).
        gain: N per V (1 when unknown); unit: the unit the report uses ('N' or 'V').
        at_rest_by: the name of a selected effect that acts at rest or at small inputs (a
            structure there is counted as its, ``explained_by``), or None.
        min_size: least size of a structure [V]: its bin means' 99th percentile over the
            samples, or a line's amplitude (0: any size).
        coulomb: the model's Coulomb level θ3 [V]; with it and the full-rate reading (``p.y``,
            ``p.x``, ``p.t`` (N,)) the residual is also tested against the travel since the last
            reversal (size: its deficit, at least :data:`MIN_TRAVEL_COULOMB` |θ3|).
    Returns:
        A :class:`Verdict`: ``structured``, ``findings`` ({"against", "share", "z", "where",
        "mean", "size"}, the structured ones first), ``tested`` (every variable with its share,
        z, size (in the report's unit) and, when a selected effect accounts for it,
        ``explained_by``), ``text``.
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
    b = _travel_binned(r, p, ratio) if coulomb is not None else None
    if b is not None:
        big = (b["share"] >= max(MIN_SHARE, NOISE_FACTOR * b["noise"])
               and b["size"] >= max(min_size, MIN_TRAVEL_COULOMB * abs(float(coulomb))))
        tested.append({"against": "travel", "share": b["share"], "noise_share": b["noise"], "z": b["z"],
                       "where": _where_travel(b), "mean": gain * b["mean"], "size": gain * b["size"],
                       "structured": big, "explained_by": None})
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
        if found else "the residual shows no structure (against velocity, input, position, time, "
        + ("travel since a reversal, " if any(t["against"] == "travel" for t in tested) else "") + "spectrum)")
    text += "".join(f"; {t['where']} ({100 * t['share']:.0f} % of the residual's power) counted as "
                    f"{t['explained_by']}'s" for t in tested if t.get("explained_by"))
    return Verdict(structured=bool(found), findings=tuple(found), tested=tuple(tested), text=text)
