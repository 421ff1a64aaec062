"""Read-outs of the fit stage that the families' searches and checks use (through
:class:`motorctl.ident.fit.Fits`, their :class:`~motorctl.effects.base.SearchContext`): the
input delay's SSE over a grid, the share a term explains on sets of samples, its force forward
against backward, and its size at slow against fast speeds. Each takes the fits and plain
terms and returns numbers; none keeps anything."""

from __future__ import annotations

import math

import numpy as np
from scipy.fft import irfft

from motorctl.ident.idim import ls_coef as _coef, ls_cov as _cov, ls_sse as _sse_of, unit_columns

#: elements of the shifted input columns :func:`delay_sses` holds at once (delays x samples x 3;
#: 2 M: 16 MB, a 20 s record's whole grid)
DELAY_CHUNK_ELEMENTS = 2_000_000


def delay_sses(fits, base: list, grid, band: tuple[float, float] | None = None,
               rows: np.ndarray | None = None) -> np.ndarray:
    """Joint-LS SSE for extra input delays ``grid`` [samples]: the decimated u, u|u|, u³ are
    shifted by a fractional number of decimated samples (FFT phase shift of band-limited
    signals) instead of being re-filtered for every candidate. ``band`` (lo, hi) [Hz]: the
    fit on that band of every column and of the target only (their FFT outside it zeroed),
    the delay one band's phase says; None: all of the record's band. ``rows`` (M,) bool: the
    fit and its SSE on those decimated samples only (e.g. ``moving``); None: all."""
    p = fits.p
    ud = fits.columns.held_input()
    spec = np.fft.rfft(ud, axis=0)
    w = 2 * np.pi * np.fft.rfftfreq(ud.shape[0])
    phi0, _ = fits.design(base)
    if band is not None:
        f = np.fft.rfftfreq(ud.shape[0], p.nd / p.fs)
        keep = ((f >= band[0]) & (f < band[1])).astype(float)[:, None]
        spec = spec * keep
        phi0 = np.fft.irfft(np.fft.rfft(phi0, axis=0) * keep, n=ud.shape[0], axis=0)
    if rows is None:
        fit, scored = slice(None), slice(4, -4)
    else:
        fit = rows.copy()
        fit[:4] = fit[-4:] = False
        scored = slice(None)
    # the columns that do not move with the delay (all but θ5, θ6's) scaled and their Gram
    # matrix formed once; every delay of a chunk of the grid shifted and fitted at once,
    # its Gram matrix bordered with the moving columns (as in Fits.sse)
    moving = [4, 5] if fits.n_theta == 6 else []
    a_f = phi0[fit][:, [j for j in range(phi0.shape[1]) if j not in moving]]
    a_f = unit_columns(a_f)[0]
    g_ff = a_f.T @ a_f
    grid = np.asarray(grid, dtype=float)
    chunk = max(1, DELAY_CHUNK_ELEMENTS // (3 * ud.shape[0]))
    return np.concatenate([_delay_chunk(p.nd, spec, w, ud.shape[0], grid[i:i + chunk], a_f, g_ff, len(moving),
                                        fit, scored) for i in range(0, len(grid), chunk)])


def _delay_chunk(nd, spec, w, m, delays, a_f, g_ff, k, fit, scored) -> np.ndarray:
    """SSEs (G,) of :func:`delay_sses` for ``delays`` (G,) [samples]: nd the decimation factor;
    spec (F, 3) the spectrum of the decimated u, u|u|, u³ (m samples); w (F,) its bins
    [rad/sample]; a_f (m', q) the scaled columns that do not move with the delay on the fitted
    rows ``fit``, g_ff their Gram matrix; k the moving columns (0, or 2: θ5, θ6's −u|u|, −u³);
    the SSE on the rows ``scored`` of the fitted ones."""
    shift = np.exp(np.multiply.outer(delays / nd, -1j * w))                       # (G, F)
    used = spec.T[:1 + k]                                          # u, and u|u|, u³ when they move
    sh = irfft(used[None, :, :] * shift[:, None, :], n=m, axis=-1)[:, :, fit]     # (G, 1 + k, m')
    y = sh[:, 0, :]
    n_g, q = len(delays), a_f.shape[1]
    gram = np.empty((n_g, q + k, q + k))
    gram[:, :q, :q] = g_ff
    rhs = np.empty((n_g, q + k))
    rhs[:, :q] = y @ a_f
    if k:
        a_s = -sh[:, 1:3, :]                                                      # (G, 2, m')
        sc_s = np.sqrt(np.einsum("gji,gji->gj", a_s, a_s))
        sc_s[sc_s == 0] = 1.0
        a_s /= sc_s[:, :, None]
        cross = a_s @ a_f                                                         # (G, 2, q)
        gram[:, q:, :q] = cross
        gram[:, :q, q:] = cross.transpose(0, 2, 1)
        gram[:, q:, q:] = a_s @ a_s.transpose(0, 2, 1)
        rhs[:, q:] = (a_s @ y[:, :, None])[:, :, 0]
    try:
        coef = np.linalg.solve(gram, rhs[:, :, None])[:, :, 0]
    except np.linalg.LinAlgError:        # a singular fit: its least-norm coefficients
        coef = (np.linalg.pinv(gram) @ rhs[:, :, None])[:, :, 0]
    r = y - coef[:, :q] @ a_f.T
    if k:
        r -= (coef[:, None, q:] @ a_s)[:, 0, :]
    r = r[:, scored]
    return np.einsum("gi,gi->g", r, r)


def explained_shares(fits, term, base: list, *rows: np.ndarray) -> tuple[float, ...]:
    """For each set of decimated samples in ``rows`` ((M,) bool each), the share [-] of the
    residual SSE of the model of ``base`` that adding ``term`` explains, both fitted jointly
    with the nominal θ on those samples only; 0 where they are too few for the fit or leave
    no residual. The two models' regressors are built once for all the sets."""
    phi0, y0 = fits.design(base)
    phi1, y1 = fits.design(base + [term])
    out = []
    for sel in rows:
        if sel.sum() < 4 * phi1.shape[1]:
            out.append(0.0)
            continue
        r0 = y0[sel] - phi0[sel] @ _coef(phi0[sel], y0[sel])
        r1 = y1[sel] - phi1[sel] @ _coef(phi1[sel], y1[sel])
        s0 = float(r0 @ r0)
        out.append((s0 - float(r1 @ r1)) / s0 if s0 > 0 else 0.0)
    return tuple(out)


def direction_agreement(fits, term, base: list) -> float:
    """1 − ‖β₊ − β₋‖/(‖β₊‖ + ‖β₋‖) for the effect's coefficients fitted jointly with the
    nominal θ on the samples moving forward (β₊) and backward (β₋) separately (1: the same
    force both ways, as cogging and ripple must be; ≤ 0: unrelated)."""
    phi, y = fits.design(base + [term])
    k = term.cols.shape[1]
    betas = []
    for sel in (fits.p.v_d > 0, fits.p.v_d < 0):
        sel = sel & fits.moving
        if sel.sum() < 4 * phi.shape[1]:
            return 0.0
        betas.append(_coef(phi[sel], y[sel])[-k:])
    bp, bm = betas
    den = np.linalg.norm(bp) + np.linalg.norm(bm)
    return float(1.0 - np.linalg.norm(bp - bm) / den) if den > 0 else 0.0


def direction_split_gain(fits, term, base: list) -> float:
    """What the effect's columns explain beyond their joint fit when fitted on each direction
    of motion with their own coefficients (the columns × [ẋ > 0] and × [ẋ < 0] in place of
    them, jointly with the nominal θ), as a share of what they explain: (SSE(base + term) −
    SSE(split)) / (SSE(base) − SSE(base + term)). About 0 for a force that is one function
    of the state whichever way the carriage moves (a friction of position: its columns carry
    S_f(ẋ)); large for a force that differs with the direction (a play taken up at other
    positions going out and back). NaN when the term explains nothing."""
    phi, y = fits.design(base + [term])
    k = term.cols.shape[1]
    s_with, s0 = fits.sse(base + [term]), fits.sse(base)
    fwd = (fits.p.v_d > 0)[:, None]
    split = np.hstack([phi[:, :-k], phi[:, -k:] * fwd, phi[:, -k:] * ~fwd])
    gain = s0 - s_with
    return float((s_with - _sse_of(split, y)) / gain) if gain > 0 else math.nan


def speed_growth_interval(fits, term, base: list, period: float) -> tuple[float, float, float]:
    """(r, lo, hi): ‖β_fast‖/‖β_slow‖ for the effect's coefficients fitted jointly with the
    nominal θ (θ1 taken from the whole record, the other columns fitted on each half) on the
    slower and the faster half of the moving samples at which a spatial period ``period`` [m]
    passes the position filter (|ẋ| < fq·period): about 1 for a force of position (cogging,
    ripple) and for a reading's error in its own columns; a reading's error fitted as a force
    grows with ẋ² (ë = −w²ẋ² e). lo, hi: r ∓ 2 standard errors (each half's amplitude ‖β‖ with
    its standard error from the fit's covariance σ̂²(ΦᵀΦ)⁻¹ projected on β/‖β‖; the ratio's by
    the first-order propagation of the two). NaN (all three) when too few samples."""
    phi, y = fits.design(base + [term])
    # θ1 from the whole record, not from each half: in the faster half (the cruise) the
    # carriage accelerates only as the effect itself makes it, at the effect's frequency, so
    # the mass is not measured there and trades with the effect's columns (half-mode plant,
    # 6 N cogging: θ1 0.124 there for the record's 0.156, the amplitude x2.9 the slower half's)
    y = y - _coef(phi, y)[0] * phi[:, 0]
    phi = phi[:, 1:]
    k = term.cols.shape[1]
    sp = np.abs(fits.p.v_d)
    seen = fits.moving & (sp < fits.p.fq * period)
    nan = (math.nan, math.nan, math.nan)
    if seen.sum() < 8 * phi.shape[1]:
        return nan
    med = float(np.median(sp[seen]))
    norms, rel = [], []
    for sel in (seen & (sp <= med), seen & (sp > med)):
        if sel.sum() < 4 * phi.shape[1]:
            return nan
        coef = _coef(phi[sel], y[sel])
        b = coef[-k:]
        n = float(np.linalg.norm(b))
        norms.append(n)
        if n > 0:
            g = b / n
            cov = _cov(phi[sel], y[sel] - phi[sel] @ coef)[-k:, -k:]
            rel.append(math.sqrt(max(float(g @ cov @ g), 0.0)) / n)
    r = norms[1] / norms[0] if norms[0] > 0 else math.inf
    if len(rel) < 2:            # a zero amplitude on a half: the ratio 0 or inf, no interval
        return r, r, r
    se = r * math.hypot(rel[0], rel[1])
    return r, r - 2.0 * se, r + 2.0 * se



def rows_std(fits, phi: np.ndarray, y: np.ndarray, rows: np.ndarray, combos: np.ndarray) -> tuple[np.ndarray,
                                                                                                    np.ndarray]:
    """The least-squares fit of ``y`` (M,) on ``phi`` (M, p) on the decimated samples ``rows``
    ((M,) bool) only, columns that vanish there left out (minimum norm), and the standard
    deviations of the linear combinations ``combos`` (q, p) of its coefficients: the Newey-West
    σ of the fit on those samples (the others' scores zero, the kept ones in their places in
    time; :func:`motorctl.ident.uncertainty.hac_covariance`) and, in quadrature, the model
    error the record shows between that fit and the fit on all samples
    (:func:`~motorctl.ident.uncertainty.split_difference` of the same projection,
    :func:`~motorctl.ident.uncertainty.model_error`): the stated σ of a value fitted on part of
    the record, as :func:`~motorctl.ident.uncertainty.fit_uncertainty` states the others.

    Returns:
        (the coefficients (p,), their combinations' σ (q,); NaN where a combination takes a
        column left out).
    """
    from motorctl.ident.uncertainty import hac_covariance, model_error, split_difference
    w = np.asarray(rows, dtype=float)
    a, b = phi[rows], y[rows]
    norms = np.sqrt(np.einsum("ij,ij->j", a, a))
    live = norms > 1e-9 * norms.max()
    coef = np.zeros(phi.shape[1])
    coef[live] = np.linalg.lstsq(a[:, live] / norms[live], b, rcond=None)[0] / norms[live]
    m, n, k = len(w), float(w.sum()), int(live.sum())
    fs_d = fits.p.fs / fits.p.nd
    cov_l, lag = hac_covariance(phi[:, live] * w[:, None], (y - phi @ coef) * w, fs_d)
    # the degrees of freedom of the samples fitted, not of the whole record
    cov = np.full((phi.shape[1],) * 2, np.nan)
    cov[np.ix_(live, live)] = cov_l * (n / max(n - k, 1.0)) / (m / max(m - k, 1.0))
    full = np.linalg.lstsq(phi, y, rcond=None)[0]
    split = split_difference(phi, y - phi @ full, lambda c: c * (w[:, None] if c.ndim > 1 else w), lag, full)
    out = np.full(len(combos), np.nan)
    for i, c in enumerate(np.atleast_2d(combos)):
        if np.any(c[~live] != 0.0):
            continue
        s2 = float(c[live] @ cov[np.ix_(live, live)] @ c[live])
        bias = 0.0 if split is None else model_error(float(c @ split[0]), float(c @ split[1] @ c))
        out[i] = math.sqrt(s2 + bias * bias) if s2 >= 0.0 else math.nan
    return coef, out
