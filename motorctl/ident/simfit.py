"""Fit % of a simulation of an identified model against the measured position.

The logged records are closed loop and the axis is a double integrator, so an open-loop
simulation over the whole record drifts for any model. As in MATLAB's ``compare`` with a finite
horizon, the model is simulated from the measured (filtered) state at the start of consecutive
windows of ``window_s`` seconds, driven by the measured input, and

    fit % = 100 (1 − ‖Δy − Δŷ‖ / ‖Δy − mean(Δy)‖),   Δ = position minus the window's start

over all windows. The model is u = Φθ + Cβ (idim.py, effects.py) solved for the acceleration
(it is affine in ẍ: θ1 plus a payload step), integrated by semi-implicit Euler at the sample rate.
An error of the reading (an encoder's interpolation error: a family's ``measurement``) is no
force: its columns, which stand for what it puts into the measured acceleration, are left out,
and the simulated position is read through it, ŷ = x + e(x).
"""

from __future__ import annotations

import numpy as np

from motorctl.effects import family as effect_family
from motorctl.effects.base import Signals
from motorctl.model import idim_regressor


def simulation_fit(fits, terms: list, ev, window_s: float = 0.2) -> float | None:
    """Fit % (see the module docstring) of the model (nominal + ``terms``, fit ``ev``).

    Args:
        fits: the fit stage of the model (:class:`~motorctl.ident.fit.Fits`). terms: its terms (or []).
        ev: the matching fit (the selection's final or nominal). window_s: horizon [s].
    Returns:
        The fit in %, or None when the record is shorter than two windows.
    """
    p = fits.p
    nt = fits.n_theta
    th, betas = fits.coef_split(ev, terms)
    delay = fits.zoh + sum(t.delay for t in terms)
    # u, u|u|, u³ as the fit saw them: the force curve of the held input, then the delay
    # (motorctl.ident.columns.Columns.input_columns), not the curve of an interpolated input
    uc = fits.input_columns(delay)
    n = len(p.t)
    length = int(round(window_s * p.fs))
    edge = int(round(0.1 * p.fs))
    starts = np.arange(edge, n - edge - length, length)
    if len(starts) < 2:
        return None
    ts = 1.0 / p.fs
    x = p.x[starts].copy()
    v = p.v[starts].copy()
    y0 = p.y[starts]
    err2 = []
    dy_all = []
    fu_coef = (th[4], th[5]) if nt == 6 else None
    families = [effect_family(t.family) for t in terms]
    # an error of the reading is no force (the module docstring): read through, not simulated
    fitted = list(zip(families, terms, betas))
    read = [(fam, t, b) for fam, t, b in fitted if fam.measurement]
    forces = [(fam, t, b) for fam, t, b in fitted if not fam.measurement and t.cols is not None]
    for k in range(length):
        idx = starts + k
        uk, uk_curve = uc[idx, 0], uc[idx, 1:]
        dy_all.append(p.y[idx] - y0)
        y_hat = x + sum(fam.reading_error(t.h, b, th[0], x) for fam, t, b in read) if read else x
        err2.append(p.y[idx] - y_hat)      # Δy − Δŷ with Δ from the measured start y0
        zero = np.zeros_like(x)
        phi = idim_regressor(zero, v, uk, nt)      # at ẍ = 0; the row at ẍ = 1 differs in column 0
        if fits.friction == "sign":
            phi[:, 2] = np.sign(v)
        fu = None
        if fu_coef:
            phi[:, 4:6] = -uk_curve
            fu = uk + uk_curve @ np.asarray(fu_coef)       # f_u (paper eq. 9) of the held input
        rest_cols = []
        for a_val in (zero, np.ones_like(x)):
            if a_val is not zero:
                phi[:, 0] = a_val
            val = phi @ th
            q = Signals(x, v, a_val, uk, p.t[idx], fu)
            for fam, t, b in forces:
                val = val + fam.fitted(t.h, q, b)      # harmonics cut: select._prune_harmonics
            rest_cols.append(val)
        m_eff = rest_cols[1] - rest_cols[0]
        acc = (uk - rest_cols[0]) / np.where(np.abs(m_eff) > 1e-12, m_eff, 1e-12)
        v = v + acc * ts
        x = x + v * ts
    dy = np.concatenate(dy_all)
    e = np.concatenate(err2)
    den = np.linalg.norm(dy - dy.mean())
    return float(100.0 * (1.0 - np.linalg.norm(e) / den)) if den > 0 else None
