"""Simpler accounts of a residual: what an effect must explain more of than before it is named.

The decision rule (docs/identification.md, "Decision rule"): an effect is named only when it is
significant on its own *and* no simpler account of the same residual explains as much. The
accounts are forces that need no physics of the axis, each fitted jointly with the nominal θ and
the effects already in the model (IDIM-LS, the same regressor and held-out folds as a candidate):

* **step**: a constant force from a time t_s on, −[t ≥ t_s] (a load hung on, a cable caught, a
  collision), t_s the decimated instant that lowers the SSE most (:func:`best_step`) over the
  record less :data:`EDGE_S` at each end;
* **drift**: a force changing slowly over the record, τ and τ² with τ = (t − t_0)/L (a warming
  axis: friction or an offset drifting);
* **line**: the residual's strongest spectral line, sin and cos at its frequency (a vibration from
  outside, a loop's oscillation): the periodogram's highest peak (:func:`scipy.signal.find_peaks`
  on :func:`scipy.signal.periodogram` of the decimated residual, Hann window) between
  :data:`LINE_LOW_HZ` and 0.35 of the decimated rate.

A candidate whose held-out RMS (the selection's measure, :meth:`motorctl.ident.fit.Fits.heldout_with`) is not
below an account's is refused with the account named ("a force step of ... explains as much").
The time-periodic family is not judged against the line (the line is its own account), nor a
family against an account it contains. Data in and out are plain records (:class:`Account`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from motorctl.effects.periodic import spectral_lines

#: no step account within this time of the record's ends [s] (the decimation's edges are gone)
EDGE_S = 0.5
#: lowest frequency of a line account [Hz] (below: the program's own moves)
LINE_LOW_HZ = 0.5
#: highest frequency of a line account as a share of the decimated sample rate
LINE_HIGH_SHARE = 0.35
#: the families not judged against an account of a kind: its own physics is that account
EXEMPT = {"line": ("periodic_disturbance",), "step": (), "drift": ()}


@dataclass(frozen=True)
class Account:
    """One simpler account of a residual, fitted beside the nominal model and ``base``.

    Attributes:
        kind: 'step', 'drift' or 'line'. text: what it is, for a reason ("a force step at
            t = 3.90 s"). at: its time [s] (step) or frequency [Hz] (line), None (drift).
        heldout_rms: the held-out RMS [V] of the model with it (the selection's measure).
    """

    kind: str
    text: str
    at: float | None
    heldout_rms: float


def step_columns(t_d: np.ndarray, t_s: float) -> np.ndarray:
    """−[t ≥ t_s] at the decimated instants ``t_d`` (M,) [s]: (M, 1)."""
    return -(t_d >= t_s).astype(float)[:, None]


def drift_columns(t_d: np.ndarray) -> np.ndarray:
    """τ and τ² − mean, τ = (t − t_0)/L ∈ [0, 1] at ``t_d`` (M,) [s]: (M, 2)."""
    tau = (t_d - t_d[0]) / max(float(t_d[-1] - t_d[0]), 1e-12)
    return np.column_stack([tau - tau.mean(), tau * tau - (tau * tau).mean()])


def strongest_line(t_d: np.ndarray, r: np.ndarray) -> float | None:
    """The frequency [Hz] of the strongest line of ``r`` (M,) at the decimated instants ``t_d``
    (M,) [s] between :data:`LINE_LOW_HZ` and :data:`LINE_HIGH_SHARE` of the rate
    (:func:`motorctl.effects.periodic.spectral_lines`); None when there is none."""
    m = len(r)
    fs = (m - 1) / max(float(t_d[-1] - t_d[0]), 1e-12)
    found = spectral_lines(t_d, r, 1, LINE_LOW_HZ, LINE_HIGH_SHARE * fs)
    return found[0] if found else None


def line_columns(p, f_hz: float) -> np.ndarray:
    """sin, cos(2π f t) at the decimated instants, times the decimation's gain at f
    (``p.dec_gain``): (M, 2). ``p``: the prepared record (t_d [s])."""
    w = 2.0 * math.pi * f_hz * p.t_d
    return float(p.dec_gain(f_hz)) * np.column_stack([np.sin(w), np.cos(w)])


def best_step(phi: np.ndarray, residual: np.ndarray, weight: np.ndarray | None, t_d: np.ndarray,
              lo: float, hi: float) -> float | None:
    """The time t_s [s] in [lo, hi] whose step column −w·[t ≥ t_s] lowers the SSE of the LS fit
    on ``phi`` (M, p) most, ``residual`` (M,) that fit's residual, ``weight`` (M,) a holding
    family's weight on added columns (None: 1), at every decimated instant ``t_d`` (M,) at once:
    the SSE falls by (cᵀr)² / (cᵀc − cᵀΦ(ΦᵀΦ)⁻¹Φᵀc) (the added column's partial regression), whose
    sums over t ≥ t_s are reversed cumulative sums. None when no instant is inside."""
    w = np.ones(len(residual)) if weight is None else np.asarray(weight, dtype=float)
    rev = slice(None, None, -1)
    cr = np.cumsum((w * residual)[rev])[rev]
    cc = np.cumsum((w * w)[rev])[rev]
    ca = np.cumsum((w[:, None] * phi)[rev], axis=0)[rev]
    try:
        g_inv = np.linalg.pinv(phi.T @ phi)
    except np.linalg.LinAlgError:
        return None
    inside = np.flatnonzero((t_d >= lo) & (t_d <= hi))
    if inside.size == 0:
        return None
    den = cc[inside] - np.einsum("ij,jk,ik->i", ca[inside], g_inv, ca[inside])
    fall = np.where(den > 1e-12 * np.maximum(cc[inside], 1e-300), cr[inside] ** 2 / np.maximum(den, 1e-300), 0.0)
    return float(t_d[inside[int(np.argmax(fall))]])


def accounts(ctx, base: list, residual: np.ndarray) -> list[Account]:
    """The simpler accounts (:class:`Account`: step, drift, line) of ``residual`` (M,), the
    residual of the nominal model plus ``base``, each fitted beside them. ``ctx``: the
    identifier (``design``, ``hold_weight``, :meth:`~motorctl.ident.fit.Fits.heldout_with`,
    ``p``)."""
    p = ctx.p
    t_d = p.t_d
    out = []
    phi, _ = ctx.design(base)
    ts = best_step(phi, residual, ctx.hold_weight(base), t_d, float(t_d[0]) + EDGE_S, float(t_d[-1]) - EDGE_S)
    if ts is not None:
        out.append(Account("step", f"a force step at t = {ts:.2f} s", ts,
                           ctx.heldout_with(base, step_columns(t_d, ts))))
    out.append(Account("drift", "a force drifting over the record (a parabola in time)", None,
                       ctx.heldout_with(base, drift_columns(t_d))))
    f = strongest_line(t_d, residual)
    if f is not None:
        out.append(Account("line", f"the residual's strongest spectral line, {f:.4g} Hz", f,
                           ctx.heldout_with(base, line_columns(p, f))))
    return out


def explained_as_much(family: str, heldout_rms: float, found: list[Account]) -> list[str]:
    """The reasons a candidate of ``family`` with the held-out RMS ``heldout_rms`` [V] is not
    named: each account of ``found`` (not exempt for the family, :data:`EXEMPT`) whose held-out
    RMS is not above the candidate's. Empty: none explains as much."""
    return [f"a simpler account explains as much: {a.text} (held-out RMS {a.heldout_rms:.4g} against "
            f"{heldout_rms:.4g} V)"
            for a in found if family not in EXEMPT[a.kind] and a.heldout_rms <= heldout_rms]
