"""Projection-type filtered least-squares estimator of DCDIARC (paper eq. 7, 8, 25-28).

Per sample (Ts), with time-aligned inputs (docs/control-law.md, Order of operations):

1. Filter the pair describing the interval just ended, (x2[k], S_f(x2[k]), 1, u[k−1] + d̂_eff[k−1],
   u|u|[k−1], u³[k−1]), through H_f(s) = ω_f²/(s + ω_f)² discretised by exact ZOH (docs/control-law.md, Filter discretisation).
   Each channel has the two states (•_f, d•_f/dt), so ẋ2f needs no differentiation.
   d̂_eff [V] is the identified-effect compensation term (motorctl.effects) in force of the
   interval: with it compensated, the model the law and the estimator share is eq. (4) with
   d̃ = d_eff + d̃', θ1 ẋ2 = (u + d_eff) − θ2 x2 − ..., so the input the model sees is u + d̂_eff
   (0 when nothing is compensated: the paper's estimator). Without it θ̂ would absorb the
   effect's mean while v_a1 subtracts the whole effect again (double counting).
2. φ_f = [−ẋ2f, −x2f, −S_ff, 1_f, (u|u|)_f, (u³)_f] (eq. 25), ε = −φ_fᵀθ̂ − u_f (eq. 26).
3. Γ by the information-form (matrix-inversion lemma) update of eq. (27) with forgetting μ,
   normalisation ν and the freeze branch λ_max(Γ) > ρ_M (docs/control-law.md, Adaptation laws): with g = Γφ,
   Γ⁺ = sΓ − c g gᵀ, s = 1/(1 − μTs), c = (Ts/n) s² / (1 + (Ts/n) s φᵀΓφ). Only the upper
   triangle is computed and mirrored, so Γ is exactly symmetric; the update keeps it positive
   definite (a rank-1 downdate that can never cross zero, unlike explicit Euler).
4. τ = φ_f ε / (1 + ν φ_fᵀΓφ_f) (eq. 28); ζ = Γ⁺τ = g (s − c φᵀΓφ) ε/n (no second product);
   θ̂ ← clip(θ̂ + Ts·Proj(ζ)) with the Γ-weighted box projection (eq. 7-8) coded as the
   active-set rule of docs/control-law.md, Box projection.

Adapted compensation (motorctl.effects.compensation): k basis columns c_j(x, ẋ, t) of the
interval are extra channels, filtered by the same H_f, and φ_f gets their filtered values
(u_f = −φ_fᵀθ with d_eff = βᵀc next to u); θ̂ is then (θ̂, β̂), Γ (n + k)². A force ripple scales
the thrust channels (u, u|u|, u³) by 1 + r̂(x).

The linear model (C1) uses the first four channels and parameters only. The per-sample work is
a numba-compiled kernel on preallocated arrays, the freeze check of eq. (27) included: it is
decided only when tr(Γ⁺) > ρ_M (λ_max ≤ tr for SPD), then without computing λ_max, by the
Cholesky factorisation of ρ_M I − Γ⁺ in scratch (:func:`lambda_max_exceeds`), so a loop with
forgetting that sits frozen at rest allocates nothing either. ``NUMBA_DISABLE_JIT=1`` runs the
same code as Python.
"""

from __future__ import annotations

import math

import numpy as np

from motorctl.jit import njit
from motorctl.model import s_f_scalar

# indices into the option vector passed to the kernel
_O_TS, _O_MU, _O_NU, _O_RHO = 0, 1, 2, 3
# indices into the result vector
_R_EPS, _R_FROZEN = 0, 1

s_f_jit = njit(s_f_scalar)


def zoh_filter_matrices(omega_f: float, ts: float) -> tuple[np.ndarray, np.ndarray]:
    """Exact ZOH discretisation of H_f(s) = ω_f²/(s + ω_f)² with states (x_f, ẋ_f) (docs/control-law.md, Filter discretisation).

    Returns:
        (A_d shape (2, 2), B_d shape (2,)).
    """
    a = np.array([[0.0, 1.0], [-omega_f**2, -2.0 * omega_f]])
    b = np.array([0.0, omega_f**2])
    from scipy.linalg import expm     # at build time (the loop process loads scipy.linalg only)
    m = np.zeros((3, 3))
    m[:2, :2] = a
    m[:2, 2] = b
    e = expm(m * ts)
    return e[:2, :2], e[:2, 2]


@njit
def project_box(z, th, tmin, tmax, gam, piv, coef, vec, pividx, active):
    """Γ-weighted box projection (eq. 8) in place on ζ = Γτ, exact at edges and corners.

    On a box the outward normals are ±e_i, so Proj(ζ) = ζ − Γ[:, A] λ with λ = Γ[A, A]⁻¹ ζ[A]
    for the set A of closed faces. A face is closed when the step would leave the box through it
    and its multiplier has the outward sign (λ_i ≥ 0 on an upper face, ≤ 0 on a lower face): the
    KKT conditions of the projection onto the tangent cone in the Γ⁻¹ metric. This is what makes
    P2, θ̃ᵀ(Γ⁻¹Proj(Γτ) − τ) ≤ 0, hold at corners too; an add-only rule can close
    a face whose multiplier has the wrong sign when Γ couples two bounded parameters.

    Primal active set: start empty; eliminate the closed faces one at a time on (Γ, ζ) (block
    Gaussian elimination: only the Schur-updated columns of the closed indices are formed,
    O(n·|A|) each); recover λ by back substitution; open the face with the worst wrong-sign
    multiplier, else close the worst violated face, else stop. Bounded by 4n rounds.

    Args:
        z: ζ, shape (n,), replaced by Proj(ζ). th, tmin, tmax: θ̂ and the box, (n,).
        gam: Γ, (n, n) SPD. Scratch: piv (n, n), coef (n, n), vec (3, n), pividx (n,) int64,
        active (n,) bool or int64 (0/1).
    Returns:
        The number of closed faces.
    """
    n = th.shape[0]
    zeta = vec[0]
    mu = vec[1]
    lam = vec[2]
    for i in range(n):
        zeta[i] = z[i]
        active[i] = False
    m = 0
    for _round in range(4 * n):
        # eliminate the closed faces (in index order) on a fresh copy of ζ
        for i in range(n):
            z[i] = zeta[i]
        m = 0
        for j in range(n):
            if not active[j]:
                continue
            for a in range(n):
                piv[m, a] = gam[j, a]
            for q in range(m):
                iq = pividx[q]
                r = piv[m, iq] / piv[q, iq]
                coef[m, q] = r
                if r != 0.0:
                    for a in range(n):
                        piv[m, a] -= r * piv[q, a]
            pividx[m] = j
            f = z[j] / piv[m, j]
            mu[m] = f
            for a in range(n):
                z[a] -= piv[m, a] * f
            z[j] = 0.0
            m += 1
        # multipliers λ of Γ[:, A] λ = Σ μ_m P_m, P_m = Γ e_{i_m} − Σ_{q<m} coef[m, q] P_q
        for mm in range(m - 1, -1, -1):
            lam[mm] = mu[mm]
            for q in range(mm):
                mu[q] -= lam[mm] * coef[mm, q]
        worst = -1
        worst_val = 0.0
        for mm in range(m):
            j = pividx[mm]
            bad = -lam[mm] if th[j] >= tmax[j] else lam[mm]  # > 0 means wrong sign
            if bad > worst_val:
                worst_val = bad
                worst = j
        if worst >= 0:
            active[worst] = False
            continue
        worst_val = 0.0
        for j in range(n):
            if active[j]:
                continue
            if th[j] >= tmax[j] and z[j] > worst_val:
                worst_val = z[j]
                worst = j
            elif th[j] <= tmin[j] and -z[j] > worst_val:
                worst_val = -z[j]
                worst = j
        if worst < 0:
            break
        active[worst] = True
    return m


@njit
def lambda_max_exceeds(gam, g, scale, c, rho, w):
    """λ_max(sΓ − c g gᵀ) > ρ for Γ (n, n) symmetric, g (n,), s = ``scale``, c, ρ = ``rho``:
    the freeze test of eq. (27), decided as "ρI − (sΓ − c g gᵀ) is not positive definite", i.e.
    its Cholesky factorisation (row by row into the scratch ``w`` (n, n), lower triangle) meets
    a pivot ≤ 0. Exact up to rounding (it differs from comparing an eigenvalue only where
    λ_max = ρ to the last bits); O(n³/6) flops, no allocation."""
    n = gam.shape[0]
    for i in range(n):
        for j in range(i + 1):
            a = c * g[i] * g[j] - scale * gam[i, j]
            if i == j:
                a += rho
            for k in range(j):
                a -= w[i, k] * w[j, k]
            if i == j:
                if not a > 0.0:
                    return True
                w[i, i] = math.sqrt(a)
            else:
                w[i, j] = a / w[j, j]
    return False


@njit
def ls_update(x2, u_prev, d_prev, g_prev, cols, th, gam, tmin, tmax, zf, zd, inp, flt, phi, g, z,
              piv, coef, vec, pividx, active, opts, res):
    """One estimator sample (docs/control-law.md, Order of operations step 2); see the module docstring. All arrays preallocated.

    Args:
        x2: measured velocity over the interval just ended [m/s]; u_prev: input held over it [V].
        d_prev: the compensated effect d̂_eff [V] (paper input units, eq. 4: acts like +u) the
            law assumed over that interval, 0 when none; the linear input channel is
            u_prev + d_prev, the thrust-shape channels u|u|, u³ stay on u_prev.
        g_prev: thrust factor 1 + r̂(x) [-] over that interval (force ripple, 1.0: none): the
            thrust channels become u·g, u|u|·g, u³·g (F = F_m(u)(1 + r(x))).
        cols (k,): adapted compensation basis c(x, ẋ, t) over that interval [V per β-unit]
            (k = 0: none); they are filtered like the other channels and appended to φ_f, the
            last k entries of θ̂ being β̂ (u_f = −φ_fᵀθ holds with d_eff = βᵀc next to u).
        th (n,), gam (n, n), tmin/tmax (n,): θ̂ (then β̂), Γ, box — updated in place;
            n = n_θ + k, n_θ ∈ {4, 6}.
        zf, zd, inp (nch,): filter states and inputs, nch = n_θ + k. flt (6,): a11 a12 a21 a22 b1 b2.
        phi, g, z (n,), piv, coef (n, n), vec (3, n), pividx (n,), active (n,): outputs/scratch.
        opts (4,): Ts, μ, ν, ρ_M. res (2,): out ε, frozen (0/1).
    """
    n = th.shape[0]
    nch = zf.shape[0]
    nb = cols.shape[0]
    nn = n - nb                      # nominal parameters (4 or 6) = nominal channels
    inp[0] = x2
    inp[1] = s_f_jit(x2)
    inp[2] = 1.0
    if g_prev != 1.0:
        ug = u_prev * g_prev
        inp[3] = ug + d_prev
        if nn == 6:
            inp[4] = ug * abs(u_prev)
            inp[5] = ug * u_prev * u_prev
    else:
        inp[3] = u_prev + d_prev
        if nn == 6:
            inp[4] = u_prev * abs(u_prev)
            inp[5] = u_prev * u_prev * u_prev
    for j in range(nb):
        inp[nn + j] = cols[j]
    a11, a12, a21, a22, b1, b2 = flt[0], flt[1], flt[2], flt[3], flt[4], flt[5]
    for c in range(nch):
        f = zf[c]
        d = zd[c]
        zf[c] = a11 * f + a12 * d + b1 * inp[c]
        zd[c] = a21 * f + a22 * d + b2 * inp[c]
    phi[0] = -zd[0]
    phi[1] = -zf[0]
    phi[2] = -zf[1]
    phi[3] = zf[2]
    if nn == 6:
        phi[4] = zf[4]
        phi[5] = zf[5]
    for j in range(nb):
        phi[nn + j] = zf[nn + j]
    u_f = zf[3]
    pred = 0.0
    for i in range(n):
        pred -= phi[i] * th[i]
    eps = pred - u_f
    res[_R_EPS] = eps

    ts, mu, nu, rho = opts[_O_TS], opts[_O_MU], opts[_O_NU], opts[_O_RHO]
    quad = 0.0
    trace = 0.0
    g2 = 0.0
    for i in range(n):
        acc = 0.0
        for j in range(n):
            acc += gam[i, j] * phi[j]
        g[i] = acc
        quad += phi[i] * acc
        g2 += acc * acc
        trace += gam[i, i]
    nk = 1.0 + nu * quad
    scale = 1.0 / (1.0 - mu * ts) if mu > 0.0 else 1.0
    h = ts / nk
    c = h * scale * scale / (1.0 + h * scale * quad)
    frozen = False
    if scale * trace - c * g2 > rho:  # λ_max ≤ tr for SPD: decided only when it may bite
        frozen = lambda_max_exceeds(gam, g, scale, c, rho, piv)      # piv: scratch until the projection
    res[_R_FROZEN] = 1.0 if frozen else 0.0
    k = eps / nk
    if not frozen:
        for i in range(n):
            cgi = c * g[i]
            for j in range(i, n):
                val = scale * gam[i, j] - cgi * g[j]
                gam[i, j] = val
                gam[j, i] = val
        f = (scale - c * quad) * k
    else:
        f = k
    for i in range(n):
        z[i] = g[i] * f
    project_box(z, th, tmin, tmax, gam, piv, coef, vec, pividx, active)
    for i in range(n):
        val = th[i] + ts * z[i]
        if val > tmax[i]:
            val = tmax[i]
        elif val < tmin[i]:
            val = tmin[i]
        th[i] = val


class LeastSquaresEstimator:
    """Filtered LS estimator with Γ-weighted box projection, for 4 (C1) or 6 (C2) parameters,
    plus k adapted compensation coefficients β (appended to θ̂, their basis columns to φ_f).

    Args:
        theta_hat0: θ̂(0) then β̂(0), length n = n_θ + n_beta, n_θ ∈ {4, 6}; must lie in
            [theta_min, theta_max].
        theta_min, theta_max: the box Ω_θ (eq. 5) (and the β box), length n.
        gamma0: Γ(0), n×n symmetric positive definite (array-like), ‖Γ(0)‖ ≤ rho_M.
        omega_f: H_f corner [rad/s]. ts: sample period [s].
        mu: forgetting factor [1/s] ≥ 0. nu: normalisation ≥ 0. rho_M: bound on λ_max(Γ).
        n_beta: number k ≥ 0 of adapted coefficients (the last k entries).
    Attributes (numpy arrays, updated in place every sample):
        theta_hat (n,), gamma (n, n), phi (n,) = φ_f of the last sample; ``epsilon`` and
        ``frozen`` describe the last sample. cols (k,): the basis columns of the interval the
        next :meth:`update` processes (the caller writes them).
    Raises:
        ValueError: inconsistent sizes or θ̂(0) outside the box.
    """

    def __init__(self, theta_hat0, theta_min, theta_max, gamma0, omega_f: float, ts: float,
                 mu: float = 0.0, nu: float = 0.0, rho_M: float = 1000.0, n_beta: int = 0):
        n = len(theta_hat0)
        n_beta = int(n_beta)
        if n_beta < 0 or n - n_beta not in (4, 6) or len(theta_min) != n or len(theta_max) != n:
            raise ValueError("theta_hat0, theta_min and theta_max must all have 4 or 6 entries "
                             "(plus n_beta)")
        g0 = np.array(gamma0, dtype=float)
        if g0.shape != (n, n):
            raise ValueError(f"gamma0 must be {n}x{n}, got {g0.shape}")
        for i in range(n):
            if not theta_min[i] <= theta_hat0[i] <= theta_max[i]:
                raise ValueError(f"theta_hat0[{i}] = {theta_hat0[i]} outside [{theta_min[i]}, {theta_max[i]}]")
        self.n = n
        self.ts = float(ts)
        self.theta_min = np.array(theta_min, dtype=float)
        self.theta_max = np.array(theta_max, dtype=float)
        self.theta_hat = np.array(theta_hat0, dtype=float)
        self.gamma = g0
        ad, bd = zoh_filter_matrices(omega_f, ts)
        self.flt = np.array([ad[0, 0], ad[0, 1], ad[1, 0], ad[1, 1], bd[0], bd[1]])
        self.n_beta = n_beta
        self.cols = np.zeros(n_beta)
        nch = n
        self.zf = np.zeros(nch)
        self.zd = np.zeros(nch)
        self._inp = np.zeros(nch)
        self.phi = np.zeros(n)
        self._g = np.zeros(n)
        self._z = np.zeros(n)
        self._piv = np.zeros((n, n))
        self._coef = np.zeros((n, n))
        self._vec = np.zeros((3, n))
        self._pividx = np.zeros(n, dtype=np.int64)
        self._active = np.zeros(n, dtype=np.int64)      # 0/1: the closed faces of the box
        self.opts = np.array([ts, mu, nu, rho_M], dtype=float)
        self.res = np.zeros(2)

    @property
    def epsilon(self) -> float:
        """Prediction error ε of the last sample (eq. 26) [V]."""
        return float(self.res[_R_EPS])

    @property
    def frozen(self) -> bool:
        """True when the last Γ update was frozen (λ_max(Γ⁺) > ρ_M, eq. 27)."""
        return bool(self.res[_R_FROZEN])

    #: the float64 arrays of :meth:`kernel_args`, in order (:meth:`motorctl.control.dcdiarc.DCDIARC`
    #: packs them into one state block and rebinds these attributes to views of it)
    FLOAT_ARRAYS = ("theta_hat", "gamma", "theta_min", "theta_max", "zf", "zd", "_inp", "flt", "phi",
                    "_g", "_z", "_piv", "_coef", "_vec", "opts", "res")
    #: the int64 arrays of :meth:`kernel_args`, in order
    INT_ARRAYS = ("_pividx", "_active")

    def kernel_args(self) -> tuple:
        """The preallocated arrays the kernel works on, in ``ls_update`` order after
        (x2, u_prev, d_prev, g_prev, cols)."""
        return (self.theta_hat, self.gamma, self.theta_min, self.theta_max, self.zf, self.zd,
                self._inp, self.flt, self.phi, self._g, self._z, self._piv, self._coef, self._vec,
                self._pividx, self._active, self.opts, self.res)

    def update(self, x2: float, u_prev: float, d_prev: float = 0.0, g_prev: float = 1.0) -> None:
        """One estimator sample (docs/control-law.md, Order of operations step 2).

        Args:
            x2: measured velocity over the interval just ended [m/s] (backward difference).
            u_prev: the input held over that interval [V].
            d_prev: the compensated effect d̂_eff over that interval [V] (0: none); the model's
                input is u_prev + d_prev (see the module docstring).
            g_prev: thrust factor 1 + r̂(x) over that interval (force ripple; 1: none).
            The adapted basis columns are taken from :attr:`cols`.
        """
        ls_update(x2, u_prev, d_prev, g_prev, self.cols, *self.kernel_args())

    def reset_filters(self) -> None:
        """Zero the H_f states (used when an axis is (re)started)."""
        self.zf[:] = 0.0
        self.zd[:] = 0.0
