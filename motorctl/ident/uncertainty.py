"""Standard deviations and 95 % intervals of ``motorctl identify``'s fitted values that hold when
the residual is coloured.

The least-squares formula σ̂²(ΦᵀΦ)⁻¹ (:func:`motorctl.ident.idim.ls`, EMPS eq. 10) assumes a white
residual. A logged run's residual is not white: the program repeats, the plant has dynamics the
model lacks (a structural mode, the current loop), and in closed loop the controller turns the
noise into the next samples' input. Where the residual of neighbouring decimated samples is
correlated, the white formula understates the spread of θ̂ (on the simulated plants by factors
of 2-8, docs/identification.md, "Uncertainty").

The covariance here is the heteroscedasticity- and autocorrelation-consistent (HAC) sandwich of
Newey & West (1987) with the Bartlett kernel and the bandwidth of Andrews (1991):

    Cov(θ̂) = (ΦᵀΦ)⁻¹ Ŝ (ΦᵀΦ)⁻¹,   Ŝ = Γ₀ + Σ_{l=1..L} (1 − l/(L+1)) (Γ_l + Γ_lᵀ),
    Γ_l = Σ_t (φ_t r_t)(φ_{t−l} r_{t−l})ᵀ,

scaled by M/(M − p) (the small-sample factor of the white formula). The bandwidth L comes from
Andrews' AR(1) plug-in on the scores φ_t r_t, at least :data:`MIN_LAG_S` of decimated samples.
It is deterministic (no random draw: nothing to seed), and its cost is a few products of the
(M, p) regressor: on a 20 s log at 5 kHz about 10 ms.

Effects' searched parameters (a period, a frequency, a Stribeck velocity) enter the model
nonlinearly: the regressor is extended by the Gauss-Newton column ∂(C(h)β)/∂h at the fitted h
(the linearisation of the separable problem, Golub & Pereyra 1973), so that h gets a variance
and the others the share of it they carry. The named parameters of an effect (amplitudes,
phases, forces in N) are functions of (β, h) (:func:`motorctl.ident.effects.parameters`); their
covariance is J Cov Jᵀ with J the numerical Jacobian of that function (the delta method).

The interval is value ± 1.96 σ (a normal approximation: asymptotically exact for the sandwich,
Newey & West 1987, Thm. 2). What no resampling and no sandwich covers is a *bias*: an error of
the model the residual does not show (the same on every seed, e.g. a lag the model represents
as a delay) shifts θ̂ without widening its spread; docs/identification.md, "Uncertainty", gives
the coverage measured on the simulated plants and where that is the case.

References: W. K. Newey, K. D. West, "A simple, positive semi-definite, heteroskedasticity and
autocorrelation consistent covariance matrix", Econometrica 55(3), 703-708, 1987. D. W. K.
Andrews, "Heteroskedasticity and autocorrelation consistent covariance matrix estimation",
Econometrica 59(3), 817-858, 1991 (§6, the AR(1) plug-in). G. H. Golub, V. Pereyra, "The
differentiation of pseudo-inverses and nonlinear least squares problems whose variables
separate", SIAM J. Numer. Anal. 10(2), 413-432, 1973.
"""

from __future__ import annotations

import math

import numpy as np

#: the two-sided 95 % normal quantile
Z95 = 1.959963984540054
#: least bandwidth of the HAC sum [s of decimated samples]: the residual of a closed loop is
#: correlated over the loop's settling (a few ms to tens of ms) whatever the AR(1) fit says
MIN_LAG_S = 0.02
#: largest bandwidth as a share of the record's decimated samples (Andrews' rule grows without
#: bound as the scores' lag-1 correlation nears 1)
MAX_LAG_SHARE = 0.1
#: relative step of the numerical derivatives in h and β (central differences)
REL_STEP = 1e-4


def andrews_bandwidth(scores: np.ndarray) -> float:
    """Andrews' (1991, eq. 6.4) AR(1) plug-in bandwidth [samples] of the Bartlett kernel for the
    score series ``scores`` (M, p): each column's lag-1 correlation ρ_a and innovation variance
    σ_a², α(1) = Σ 4ρ²σ⁴/((1−ρ)⁶(1+ρ)²) / Σ σ⁴/(1−ρ)⁴, L = 1.1447 (α(1) M)^{1/3}."""
    m = scores.shape[0]
    num = den = 0.0
    for a in range(scores.shape[1]):
        z = scores[:, a]
        z0, z1 = z[:-1], z[1:]
        d = float(z0 @ z0)
        if not d > 0.0:
            continue
        rho = min(max(float(z0 @ z1) / d, -0.97), 0.97)
        s2 = float(np.mean((z1 - rho * z0) ** 2))
        num += 4.0 * rho * rho * s2 * s2 / ((1 - rho) ** 6 * (1 + rho) ** 2)
        den += s2 * s2 / (1 - rho) ** 4
    if not den > 0.0:
        return 0.0
    return 1.1447 * (num / den * m) ** (1.0 / 3.0)


def hac_covariance(phi: np.ndarray, residual: np.ndarray, fs_d: float) -> tuple[np.ndarray, int]:
    """The Newey-West covariance (p, p) of the LS coefficients of ``phi`` (M, p) with the
    residual ``residual`` (M,) sampled at ``fs_d`` [Hz] (the decimated rate), and the bandwidth
    L [samples] used (module docstring). Columns of any scale (each is scaled to unit norm
    inside). A singular regressor gives its pseudo-inverse.

    Raises:
        ValueError: ``phi`` and ``residual`` of different lengths.
    """
    phi = np.asarray(phi, dtype=float)
    r = np.asarray(residual, dtype=float)
    if phi.shape[0] != r.shape[0]:
        raise ValueError(f"regressor of {phi.shape[0]} rows against a residual of {r.shape[0]}")
    m, p = phi.shape
    sc = np.sqrt(np.einsum("ij,ij->j", phi, phi))
    sc[sc == 0] = 1.0
    a = phi / sc
    bread = np.linalg.pinv(a.T @ a)
    z = a * r[:, None]
    lag = andrews_bandwidth(z)
    lag = int(min(max(math.ceil(lag), math.ceil(MIN_LAG_S * fs_d)), max(1, int(MAX_LAG_SHARE * m))))
    s = z.T @ z
    for l in range(1, lag + 1):
        g = z[l:].T @ z[:-l]
        s += (1.0 - l / (lag + 1.0)) * (g + g.T)
    cov = bread @ s @ bread * (m / max(m - p, 1))
    return cov / np.outer(sc, sc), lag


def ci95(value: float, std: float) -> list:
    """[lo, hi] = value ∓ :data:`Z95`·std (None for both when either is not finite)."""
    if not (math.isfinite(value) and math.isfinite(std)):
        return [None, None]
    return [float(value - Z95 * std), float(value + Z95 * std)]


def _searched_float(h) -> bool:
    """h is a plain number the columns are a smooth function of (not None, not a float subclass
    carrying a basis or a stick state)."""
    return type(h) in (float, int, np.float64) and math.isfinite(float(h)) and float(h) != 0.0


def _flat(params: dict) -> list[tuple[str, int | None, float]]:
    """(name, index or None, value) of every finite number among ``params``' values (lists
    element-wise)."""
    out = []
    for k, v in params.items():
        if isinstance(v, (list, tuple)):
            out += [(k, i, float(x)) for i, x in enumerate(v)
                    if isinstance(x, (int, float, np.floating)) and not isinstance(x, bool)]
        elif isinstance(v, (int, float, np.floating)) and not isinstance(v, bool):
            out.append((k, None, float(v)))
    return out


def white_covariance(phi: np.ndarray, residual: np.ndarray) -> np.ndarray:
    """The white least-squares covariance σ̂²(ΦᵀΦ)⁻¹ (p, p) of ``phi`` (M, p) with its
    residual (M,) (EMPS eq. 10): what ``fit.std`` holds, for comparison."""
    m, p = phi.shape
    sc = np.sqrt(np.einsum("ij,ij->j", phi, phi))
    sc[sc == 0] = 1.0
    a = phi / sc
    s2 = float(residual @ residual) / max(m - p, 1)
    return s2 * np.linalg.pinv(a.T @ a) / np.outer(sc, sc)


def fit_uncertainty(idf, ev, terms, params_of, white: bool = False) -> dict:
    """The HAC standard deviations and 95 % intervals of a fit's nominal θ and of each effect's
    named parameters.

    Args:
        idf: the identifier whose model was fitted (:class:`~motorctl.ident.select.Identifier`:
            ``design``, ``term``, ``coef_split``, ``n_theta``, ``p``).
        ev: the evaluated model (``ev.fit``: coef, std, residual). terms: its effect terms.
        params_of: ``params_of(term, h, beta) -> dict`` (the effect's named parameters, as
            :func:`motorctl.ident.effects.parameters` gives them for the summary, in N with a
            gain); None when ``terms`` is empty.
    Returns:
        {"theta_std": (n_theta,) HAC σ, "theta_ci95": [[lo, hi], ...], "theta_std_white": the
        white formula's σ, "lag_samples": L, "effects": [{"std": {name: σ or [σ, ...]},
        "ci95": {name: [lo, hi] or [[lo, hi], ...]}} per term]}; σ in the units of the values.
        ``white``: the same with the white covariance (:func:`white_covariance`) in place of
        the HAC one (lag_samples 0), for comparison.
    Raises:
        ValueError: ``ev`` is not the fit of ``terms`` on ``idf`` (its coefficients and the
        regressor differ in number).
    """
    nt = idf.n_theta
    phi, y = idf.design(terms)
    coef = np.asarray(ev.fit.coef, dtype=float)
    # the Gauss-Newton columns of the searched parameters (those the columns depend on smoothly)
    extra = []
    th, betas = idf.coef_split(ev, terms)
    for i, (t, b) in enumerate(zip(terms, betas)):
        if t.cols is None or t.delay or not _searched_float(t.h) or not len(b):
            continue
        dh = REL_STEP * abs(float(t.h))
        try:
            cp = idf.term(t.family, float(t.h) + dh).cols
            cm = idf.term(t.family, float(t.h) - dh).cols
        except (ValueError, ArithmeticError):
            continue
        if cp is not None and cm is not None and cp.ndim == 2 and cp.shape[1] > t.cols.shape[1]:
            cp, cm = cp[:, :t.cols.shape[1]], cm[:, :t.cols.shape[1]]     # harmonics cut
        if cp is None or cm is None or cp.shape != t.cols.shape:
            continue
        col = ((cp - cm) @ b) / (2.0 * dh)
        if float(col @ col) > 0.0:
            extra.append((i, col))
    full = np.column_stack([phi] + [c for _, c in extra]) if extra else phi
    if phi.shape[1] != len(coef) or phi.shape[0] != len(ev.fit.residual):
        raise ValueError(f"the fit has {len(coef)} coefficients, its model's regressor {phi.shape}")
    fs_d = idf.p.fs / idf.p.nd
    if white:
        cov, lag = white_covariance(full, ev.fit.residual), 0
    else:
        cov, lag = hac_covariance(full, ev.fit.residual, fs_d)
    sd = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    out = {"theta_std": [float(v) for v in sd[:nt]],
           "theta_ci95": [ci95(float(coef[j]), float(sd[j])) for j in range(nt)],
           "theta_std_white": [float(v) for v in ev.fit.std[:nt]],
           "lag_samples": int(lag), "effects": []}
    hcol = {i: phi.shape[1] + k for k, (i, _) in enumerate(extra)}
    j0 = nt
    for i, (t, b) in enumerate(zip(terms, betas)):
        k = len(b)
        idx = list(range(j0, j0 + k)) + ([hcol[i]] if i in hcol else [])
        j0 += k
        out["effects"].append(_effect_interval(t, np.asarray(b, float), idx, cov, i in hcol, params_of))
    return out


def _effect_interval(t, b, idx, cov, with_h, params_of) -> dict:
    """σ and [lo, hi] of each named parameter of one effect by the delta method (module
    docstring): J (numerical, central differences in β and h) times the covariance block of
    (β, h) ``idx`` of ``cov``."""
    base = _flat(params_of(t, t.h, b))
    if not base or not idx:
        return {"std": {}, "ci95": {}}
    n = len(idx)
    jac = np.zeros((len(base), n))
    for c in range(n):
        is_h = with_h and c == n - 1
        x0 = float(t.h) if is_h else float(b[c])
        step = REL_STEP * max(abs(x0), math.sqrt(max(cov[idx[c], idx[c]], 0.0)), 1e-12)
        vals = []
        for s in (+1.0, -1.0):
            bb, hh = b.copy(), t.h
            if is_h:
                hh = float(t.h) + s * step
            else:
                bb[c] += s * step
            try:
                f = _flat(params_of(t, hh, bb))
            except (ValueError, ArithmeticError):
                f = []
            vals.append(f)
        if len(vals[0]) != len(base) or len(vals[1]) != len(base):
            jac[:, c] = np.nan
            continue
        for r in range(len(base)):
            d = vals[0][r][2] - vals[1][r][2]
            if base[r][0].startswith("phase"):            # an angle: the short way round
                d = (d + math.pi) % (2.0 * math.pi) - math.pi
            jac[r, c] = d / (2.0 * step)
    block = cov[np.ix_(idx, idx)]
    var = np.einsum("ij,jk,ik->i", jac, block, jac)
    # a parameter the fitted (β, h) do not move is computed from more of the record than this
    # fit (asymmetric friction's, fitted again on the samples in motion): no σ from here
    var[~np.any(jac != 0.0, axis=1)] = np.nan
    std, ci = {}, {}
    for (name, pos, v), s2 in zip(base, var):
        s = math.sqrt(s2) if math.isfinite(s2) and s2 >= 0 else math.nan
        if pos is None:
            std[name], ci[name] = _num(s), ci95(v, s)
        else:
            std.setdefault(name, []).append(_num(s))
            ci.setdefault(name, []).append(ci95(v, s))
    return {"std": std, "ci95": ci}


def _num(x: float):
    return float(x) if math.isfinite(x) else None


__all__ = ["MAX_LAG_SHARE", "MIN_LAG_S", "REL_STEP", "Z95", "andrews_bandwidth", "ci95", "fit_uncertainty",
           "hac_covariance", "white_covariance"]
