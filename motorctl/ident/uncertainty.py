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

What no resampling and no sandwich covers is a *bias*: an error of the model the residual's
variance does not show (the same on every record, e.g. a current loop's lag the model
represents as a delay) shifts θ̂ without widening its spread. Part of it the record shows as a
disagreement between fits the correct model would make agree (a specification test in the
manner of Hausman 1978): the same model fitted on the low band of the decimated record (below
:data:`LOW_BAND_SHARE` of the band kept; dynamics the model lacks, a lag or a structural mode,
act more the higher the frequency) and on the samples in motion (the identifier's
``moving``, |ẋ| above 2 % of its largest: what the model gets wrong near zero velocity, the
steep Coulomb column S_f of a quantised velocity, weighs at rest), each against the fit on all. For a split P the difference
d = θ̂_P − θ̂ is exact from the full fit's residual and its covariance V_d under a correct model
is the Newey-West covariance of its scores (:func:`split_difference`); the model error of a
value is b = sqrt(d² − V_d) where the difference is significant at 5 % (|d| > 1.96 sqrt(V_d)),
else 0, the largest over the splits (:func:`model_error`; named parameters through the same
delta method). When the values' model holds columns for a structure the record cannot resolve
(the identifier's ``nuisance``: a structural mode above the record's band, its antiresonance
assumed), the values' shift against the model without them is a third such difference
(:func:`omitted_difference`). A searched parameter (a frequency, a period, a Stribeck velocity:
the value of a Gauss-Newton column, never a size whose interval decides whether an effect is
named) takes the positive part sqrt(max(d² − V_d, 0)) without the significance test: a split
of few samples has little power, and the pre-test then sets a bias it cannot prove to 0. (On
the default plant a 7.3 Hz disturbance's frequency, fitted over records at rest 87 % of the
time, where stiction holds the carriage and the line does not reach the input, came out 1-8e-4
Hz off against a sampling σ of 1-4e-5 Hz; the fit on the samples in motion is within 3e-5 Hz
of the truth, but its difference was significant on 6 of 10 records. The price: under a correct
model d² > V_d in about a third of records, P(|z| > 1), and the searched parameter's interval
is wider there than its sampling σ asks.) The stated standard deviation is sqrt(σ² + b²), σ the sandwich's, and the
interval value ± 1.96 of it (a normal approximation: asymptotically exact for the sandwich,
Newey & West 1987, Thm. 2). Its assumption: the low band's fit, or the fit in motion, is the
less biased, so that the full fit's bias is about its difference from it. A bias both share
(an error of the model at every frequency and speed, the same in every subset) is not
covered; docs/identification.md, "Uncertainty", gives the coverage measured on the simulated
plants and where that is the case.

References: J. A. Hausman, "Specification tests in econometrics", Econometrica 46(6),
1251-1271, 1978. W. K. Newey, K. D. West, "A simple, positive semi-definite, heteroskedasticity and
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
    lag = bandwidth(z, fs_d)
    cov = bread @ _hac_sum(z, lag) @ bread * (m / max(m - p, 1))
    return cov / np.outer(sc, sc), lag


def bandwidth(z: np.ndarray, fs_d: float) -> int:
    """The Bartlett bandwidth [samples] of the score series ``z`` (M, p) at the decimated rate
    ``fs_d`` [Hz]: :func:`andrews_bandwidth`, at least :data:`MIN_LAG_S`, at most
    :data:`MAX_LAG_SHARE` of M."""
    m = z.shape[0]
    lag = andrews_bandwidth(z)
    return int(min(max(math.ceil(lag), math.ceil(MIN_LAG_S * fs_d)), max(1, int(MAX_LAG_SHARE * m))))


def _hac_sum(z: np.ndarray, lag: int) -> np.ndarray:
    """Ŝ = Γ₀ + Σ_{l=1..L} (1 − l/(L+1)) (Γ_l + Γ_lᵀ) of the scores ``z`` (M, p) (Newey & West
    1987, the Bartlett kernel)."""
    s = z.T @ z
    for l in range(1, lag + 1):
        g = z[l:].T @ z[:-l]
        s += (1.0 - l / (lag + 1.0)) * (g + g.T)
    return s


#: the low band of the band-split specification test: frequencies below this share of the
#: decimated band's kept part (the parallel decimation keeps up to 0.8 of the decimated
#: Nyquist frequency, :func:`motorctl.ident.idim.parallel_decimate`)
LOW_BAND_SHARE = 0.25
#: a column is compared in a split only when the split keeps at least this share of its
#: squared norm; else the split is not made (a stiction's hold columns, zero in motion)
MIN_SPLIT_SHARE = 1e-3
#: largest condition number of the split's normal equations (columns scaled to unit norm)
MAX_SPLIT_COND = 1e10


def low_band(m: int, share: float | None = None):
    """The orthogonal projection (a callable on (M,) or (M, k) arrays) onto the frequencies
    below ``share`` (default :data:`LOW_BAND_SHARE`) × 0.8 × the decimated Nyquist frequency of
    an M-sample decimated series (the DFT bins kept, the others zeroed: symmetric and
    idempotent on R^M)."""
    share = LOW_BAND_SHARE if share is None else share
    keep = max(2, int(round(share * 0.8 * (m // 2 + 1))))

    def proj(a):
        spec = np.fft.rfft(a, axis=0)
        spec[keep:] = 0.0
        return np.fft.irfft(spec, n=m, axis=0)
    return proj


def split_difference(a: np.ndarray, r: np.ndarray, proj, lag: int,
                     coef: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray] | None:
    """The difference d = θ̂_P − θ̂ (p,) between the least-squares fit of the regressor ``a``
    (M, p) restricted by the orthogonal projection ``proj`` (a subset of the samples, a band of
    frequencies) and the fit on all of it, and its covariance V_d (p, p) if the model were right.

    With y = aθ̂ + r (``r`` the full fit's residual), θ̂_P = (aᵀPa)⁻¹aᵀPy gives
    d = (aᵀPa)⁻¹ Σ_t (Pa)_t r_t exactly; under a correct model both estimate θ and
    d = Σ_t ψ_t e_t, ψ_t = (aᵀPa)⁻¹(Pa)_t − (aᵀa)⁻¹a_t, whose Newey-West covariance (the
    Bartlett bandwidth ``lag`` [samples], the residual for e) is V_d (Hausman 1978, the
    difference of two estimators consistent under the model; its HAC form as in
    :func:`hac_covariance`). Columns of any scale (scaled to unit norm inside; d and V_d in the
    columns' own units).

    A column the projection keeps less than :data:`MIN_SPLIT_SHARE` of (a stiction's columns,
    zero in motion) has no estimate in the split: with the full fit's coefficients ``coef``
    (p,) the split is fitted without it (its force a_D θ̂_D taken as known,
    d_R = (a_RᵀPa_R)⁻¹a_RᵀP(a_D θ̂_D + r)) and its d and V_d are 0; without ``coef``, None.
    None as well when the normal equations of the split are worse than :data:`MAX_SPLIT_COND`.
    """
    m, p = a.shape
    sc = np.sqrt(np.einsum("ij,ij->j", a, a))
    sc[sc == 0] = 1.0
    u = a / sc
    pu = proj(u)
    keep = np.einsum("ij,ij->j", pu, pu) >= MIN_SPLIT_SHARE
    if not keep.all() and (coef is None or not keep.any()):
        return None
    target = r if keep.all() else r + u[:, ~keep] @ (np.asarray(coef, dtype=float)[~keep] * sc[~keep])
    uk, puk = u[:, keep], pu[:, keep]
    gp = uk.T @ puk
    lam = np.linalg.eigvalsh(0.5 * (gp + gp.T))
    if not lam[0] > 0 or lam[-1] / lam[0] > MAX_SPLIT_COND:
        return None
    gpi = np.linalg.inv(gp)
    d, vd = np.zeros(p), np.zeros((p, p))
    d[keep] = gpi @ (puk.T @ target)
    psi = puk @ gpi.T - (u @ np.linalg.pinv(u.T @ u).T)[:, keep]
    vd[np.ix_(keep, keep)] = _hac_sum(psi * r[:, None], lag) * (m / max(m - p, 1))
    return d / sc, vd / np.outer(sc, sc)


def omitted_difference(a: np.ndarray, cov: np.ndarray, idx, coef: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The difference d (p,) between the fit of the regressor ``a`` (M, p) and the fit without
    its columns ``idx`` (a sequence of k indexes), and its covariance V_d (p, p) from the fit's
    covariance ``cov`` (p, p); ``coef`` (p,) the fit's coefficients.

    With y = a_K b_K + a_N γ̂ + r (K the other columns, r orthogonal to all), the fit without
    a_N gives b_K + A γ̂, A = (a_Kᵀa_K)⁻¹a_Kᵀa_N (k columns regressed on the others), so
    d_K = −A γ̂ exactly (a linear function of γ̂ alone: V_d = A Cov(γ̂) Aᵀ); d_N = γ̂ with
    Cov(γ̂). A value's shift between the two models beyond its sampling variance is a model
    error the record shows (:func:`model_error`): what the values owe to the columns ``idx``,
    which stand for a structure the record cannot resolve (a structural mode above its band,
    whose antiresonance the columns assume). Columns of any scale; d and V_d in their units.
    """
    p = a.shape[1]
    nidx = np.asarray(list(idx), dtype=int)
    keep = np.setdiff1d(np.arange(p), nidx)
    sc = np.sqrt(np.einsum("ij,ij->j", a, a))
    sc[sc == 0] = 1.0
    u = a / sc
    amat = np.linalg.lstsq(u[:, keep], u[:, nidx], rcond=None)[0] * sc[nidx][None, :] / sc[keep][:, None]
    g = np.asarray(coef, dtype=float)[nidx]
    cg = cov[np.ix_(nidx, nidx)]
    d, vd = np.zeros(p), np.zeros((p, p))
    d[keep] = -amat @ g
    vd[np.ix_(keep, keep)] = amat @ cg @ amat.T
    d[nidx] = g
    vd[np.ix_(nidx, nidx)] = cg
    return d, vd


def model_error(d: float, vd: float, gated: bool = True) -> float:
    """The bias a split's difference ``d`` shows beyond its sampling variance ``vd`` (both of
    one value): sqrt(d² − V_d) when |d| exceeds :data:`Z95`·sqrt(V_d) (the Hausman statistic
    d²/V_d beyond the 95 % point of χ²₁), else 0. ``gated`` False: the positive part
    sqrt(max(d² − V_d, 0)) whether significant or not (E[d²] = b² + V_d: the estimate of b²
    without the pre-test, which sets an insignificant bias to 0 and so covers less where the
    split has little power)."""
    if not (math.isfinite(d) and math.isfinite(vd)) or vd < 0:
        return 0.0
    if not gated:
        return math.sqrt(max(d * d - vd, 0.0))
    return math.sqrt(d * d - vd) if d * d > Z95 * Z95 * vd else 0.0


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


def fit_uncertainty(fits, ev, terms, params_of, white: bool = False, specification: bool = True) -> dict:
    """The HAC standard deviations and 95 % intervals of a fit's nominal θ and of each effect's
    named parameters.

    Args:
        fits: the fit stage the model was fitted by (:class:`~motorctl.ident.fit.Fits`:
            ``design``, ``term``, ``coef_split``, ``n_theta``, ``p``, ``moving``, ``nuisance``).
        ev: the evaluated model (``ev.fit``: coef, std, residual). terms: its effect terms.
        params_of: ``params_of(term, h, beta) -> dict`` (the effect's named parameters, as
            :func:`motorctl.ident.effects.parameters` gives them for the summary, in N with a
            gain); None when ``terms`` is empty. Its attribute ``std`` (optional),
            ``params_of.std(term, h, beta) -> {name: σ}``, gives the σ of the parameters a
            family fits again on part of the record (the fitted β and h do not move them):
            they get that σ (no model error) instead of none.
    Returns:
        {"theta_std": (n_theta,) the stated σ, sqrt(σ_HAC² + b²), "theta_ci95": [[lo, hi], ...]
        (value ∓ 1.96 of it), "theta_std_sampling": σ_HAC, "theta_model_error": b (0 where no
        split shows one), "theta_std_white": the white formula's σ, "lag_samples": L, "splits":
        the names of the splits made ("low_band", "moving"), "effects": [{"std", "ci95",
        "std_sampling", "model_error": {name: value or [value, ...]}} per term]}; σ, b in the
        units of the values. ``white``: the white covariance (:func:`white_covariance`) in
        place of the HAC one (lag_samples 0) and no model error, for comparison;
        ``specification`` False: no model error (b = 0).
    Raises:
        ValueError: ``ev`` is not the fit of ``terms`` on ``fits`` (its coefficients and the
        regressor differ in number).
    """
    nt = fits.n_theta
    phi, y = fits.design(terms)
    coef = np.asarray(ev.fit.coef, dtype=float)
    # the Gauss-Newton columns of the searched parameters (those the columns depend on smoothly)
    extra = []
    th, betas = fits.coef_split(ev, terms)
    for i, (t, b) in enumerate(zip(terms, betas)):
        if t.cols is None or t.delay or not _searched_float(t.h) or not len(b):
            continue
        dh = REL_STEP * abs(float(t.h))
        try:
            cp = fits.term(t.family, float(t.h) + dh).cols
            cm = fits.term(t.family, float(t.h) - dh).cols
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
    fs_d = fits.p.fs / fits.p.nd
    if white:
        cov, lag = white_covariance(full, ev.fit.residual), 0
    else:
        cov, lag = hac_covariance(full, ev.fit.residual, fs_d)
    sd = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    # the model's error the record shows: the fit on the low band and on the samples in motion
    # against the fit on all (split_difference); not for the white comparison
    splits = {}
    if not white and specification:
        r = np.asarray(ev.fit.residual, dtype=float)
        moving = getattr(fits, "moving", None)
        cands = [("low_band", low_band(len(r)))]
        if moving is not None and len(moving) == len(r) and 0 < int(np.sum(moving)) < len(r):
            mv = np.asarray(moving, dtype=float)
            cands.append(("moving", lambda a, mv=mv: a * (mv[:, None] if a.ndim > 1 else mv)))
        cf = np.concatenate([coef, np.zeros(full.shape[1] - len(coef))])
        for name, proj in cands:
            got = split_difference(full, r, proj, lag, cf)
            if got is not None:
                splits[name] = got
        # the values' shift against the model without the structure's nuisance columns (the
        # last of its regressor: a structural mode above the band, motorctl.ident.values.mode_above_band)
        nz = getattr(fits, "nuisance", None)
        if nz is not None:
            k_n = nz.shape[1] if nz.ndim == 2 else 1
            splits["nuisance"] = omitted_difference(full, cov, range(phi.shape[1] - k_n, phi.shape[1]), cf)
    bias = np.zeros(len(sd))
    for d, vd in splits.values():
        bias = np.maximum(bias, [model_error(float(d[j]), float(vd[j, j]), gated=j < phi.shape[1])
                                 for j in range(len(sd))])
    tot = np.sqrt(sd ** 2 + bias ** 2)
    out = {"theta_std": [float(v) for v in tot[:nt]],
           "theta_ci95": [ci95(float(coef[j]), float(tot[j])) for j in range(nt)],
           "theta_std_sampling": [float(v) for v in sd[:nt]],
           "theta_model_error": [float(v) for v in bias[:nt]],
           "theta_std_white": [float(v) for v in ev.fit.std[:nt]],
           "lag_samples": int(lag), "splits": sorted(splits), "effects": []}
    hcol = {i: phi.shape[1] + k for k, (i, _) in enumerate(extra)}
    j0 = nt
    for i, (t, b) in enumerate(zip(terms, betas)):
        k = len(b)
        idx = list(range(j0, j0 + k)) + ([hcol[i]] if i in hcol else [])
        j0 += k
        own = getattr(params_of, "std", None)
        out["effects"].append(_effect_interval(t, np.asarray(b, float), idx, cov, i in hcol, params_of,
                                               list(splits.values()), own(t, t.h, np.asarray(b, float)) if own else {}))
    return out


def stated_uncertainty(fits, ev, terms, params_of) -> dict:
    """:func:`fit_uncertainty` of a fit; a regressor it cannot take (degenerate) gives the white
    formula's σ for θ and no effect intervals, lag_samples None."""
    try:
        return fit_uncertainty(fits, ev, terms, params_of)
    except (ValueError, np.linalg.LinAlgError):
        nt = fits.n_theta
        sd = [float(v) for v in ev.fit.std[:nt]]
        return {"theta_std": sd, "theta_std_white": sd, "lag_samples": None, "theta_std_sampling": sd,
                "theta_model_error": [0.0] * nt, "splits": [],
                "theta_ci95": [ci95(float(v), s) for v, s in zip(ev.fit.coef[:nt], sd)],
                "effects": [{"std": {}, "ci95": {}} for _ in terms]}


def _effect_interval(t, b, idx, cov, with_h, params_of, splits=(), own=None) -> dict:
    """σ and [lo, hi] of each named parameter of one effect by the delta method (module
    docstring): J (numerical, central differences in β and h) times the covariance block of
    (β, h) ``idx`` of ``cov``; the model's error of each from the splits' (d, V_d) through the
    same J (:func:`model_error`, the largest over ``splits``). A parameter the fitted (β, h) do
    not move takes its σ from ``own`` ({name: σ}, the family's own fit of it) when given there."""
    base = _flat(params_of(t, t.h, b))
    if not base or not idx:
        return {"std": {}, "ci95": {}, "std_sampling": {}, "model_error": {}}
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
    # fit (asymmetric friction's, fitted again on the samples in motion): no σ from here, only
    # the one its family gives of its own fit (own)
    var[~np.any(jac != 0.0, axis=1)] = np.nan
    for r, (name, pos, _) in enumerate(base):
        s_own = (own or {}).get(name)
        if not math.isfinite(var[r]) and s_own is not None and pos is None and math.isfinite(float(s_own)):
            var[r] = float(s_own) ** 2
    bias = np.zeros(len(base))
    # a parameter of h alone (the frequency, the period: never a size whose interval decides a
    # name) takes the ungated model error (module docstring)
    h_only = (np.all(jac[:, :-1] == 0.0, axis=1) & (jac[:, -1] != 0.0)) if with_h else np.zeros(len(base), bool)
    for d, vd in splits:
        db = jac @ d[idx]
        vb = np.einsum("ij,jk,ik->i", jac, vd[np.ix_(idx, idx)], jac)
        bias = np.maximum(bias, [model_error(float(x), float(y), gated=not ho) for x, y, ho in zip(db, vb, h_only)])
    std, ci, samp, err = {}, {}, {}, {}
    for (name, pos, v), s2, b2 in zip(base, var, bias):
        s = math.sqrt(s2) if math.isfinite(s2) and s2 >= 0 else math.nan
        tot = math.sqrt(s * s + b2 * b2) if math.isfinite(s) else math.nan
        e = b2 if math.isfinite(s) else math.nan
        if pos is None:
            std[name], ci[name], samp[name], err[name] = _num(tot), ci95(v, tot), _num(s), _num(e)
        else:
            std.setdefault(name, []).append(_num(tot))
            ci.setdefault(name, []).append(ci95(v, tot))
            samp.setdefault(name, []).append(_num(s))
            err.setdefault(name, []).append(_num(e))
    return {"std": std, "ci95": ci, "std_sampling": samp, "model_error": err}


def _num(x: float):
    return float(x) if math.isfinite(x) else None


__all__ = ["LOW_BAND_SHARE", "MAX_LAG_SHARE", "MAX_SPLIT_COND", "MIN_LAG_S", "MIN_SPLIT_SHARE", "REL_STEP", "Z95",
           "andrews_bandwidth", "bandwidth", "ci95", "fit_uncertainty", "hac_covariance", "low_band", "model_error",
           "split_difference", "stated_uncertainty", "white_covariance"]
