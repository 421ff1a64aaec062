"""Projection-type filtered least-squares estimator of DCDIARC (paper eq. 7, 8, 25-28).

Per sample (Ts), with time-aligned inputs (spec §5.2):

1. Filter the pair describing the interval just ended, (x2[k], S_f(x2[k]), 1, u[k−1],
   u|u|[k−1], u³[k−1]), through H_f(s) = ω_f²/(s + ω_f)² discretised by exact ZOH (spec §5.3).
   Each channel has the two states (•_f, d•_f/dt), so ẋ2f needs no differentiation.
2. φ_f = [−ẋ2f, −x2f, −S_ff, 1_f, (u|u|)_f, (u³)_f] (eq. 25), ε = −φ_fᵀθ̂ − u_f (eq. 26).
3. Γ by the information-form (matrix-inversion lemma) update of eq. (27) with forgetting μ,
   normalisation ν and the freeze branch λ_max(Γ) > ρ_M (spec §5.4). Only the upper triangle is
   computed and mirrored, so Γ is exactly symmetric; the update keeps it positive definite.
4. τ = φ_f ε / (1 + ν φ_fᵀΓφ_f) (eq. 28) and θ̂ ← clip(θ̂ + Ts·Proj(Γτ)) with the Γ-weighted
   box projection (eq. 7-8) coded as the active-set rule of spec §2.2.

The linear model (C1) uses the first four channels and parameters only.
State is held in preallocated Python lists of floats: a step builds no containers.
"""

from __future__ import annotations

import numpy as np
from scipy.linalg import expm

from motorctl.model import s_f_scalar


def zoh_filter_matrices(omega_f: float, ts: float) -> tuple[np.ndarray, np.ndarray]:
    """Exact ZOH discretisation of H_f(s) = ω_f²/(s + ω_f)² with states (x_f, ẋ_f) (spec §5.3).

    Returns:
        (A_d shape (2, 2), B_d shape (2,)).
    """
    a = np.array([[0.0, 1.0], [-omega_f**2, -2.0 * omega_f]])
    b = np.array([0.0, omega_f**2])
    m = np.zeros((3, 3))
    m[:2, :2] = a
    m[:2, 2] = b
    e = expm(m * ts)
    return e[:2, :2], e[:2, 2]


class LeastSquaresEstimator:
    """Filtered LS estimator with Γ-weighted box projection, for 4 (C1) or 6 (C2) parameters.

    Args:
        theta_hat0: θ̂(0), length n ∈ {4, 6}; must lie in [theta_min, theta_max].
        theta_min, theta_max: the box Ω_θ (eq. 5), length n.
        gamma0: Γ(0), n×n symmetric positive definite (array-like), ‖Γ(0)‖ ≤ rho_M.
        omega_f: H_f corner [rad/s]. ts: sample period [s].
        mu: forgetting factor [1/s] ≥ 0. nu: normalisation ≥ 0. rho_M: bound on λ_max(Γ).
    Raises:
        ValueError: on inconsistent sizes or θ̂(0) outside the box.
    """

    def __init__(self, theta_hat0, theta_min, theta_max, gamma0, omega_f: float, ts: float,
                 mu: float = 0.0, nu: float = 0.0, rho_M: float = 1000.0):
        n = len(theta_hat0)
        if n not in (4, 6) or len(theta_min) != n or len(theta_max) != n:
            raise ValueError("theta_hat0, theta_min and theta_max must all have 4 or 6 entries")
        g0 = np.asarray(gamma0, dtype=float)
        if g0.shape != (n, n):
            raise ValueError(f"gamma0 must be {n}x{n}, got {g0.shape}")
        for i in range(n):
            if not theta_min[i] <= theta_hat0[i] <= theta_max[i]:
                raise ValueError(f"theta_hat0[{i}] = {theta_hat0[i]} outside [{theta_min[i]}, {theta_max[i]}]")
        self.n = n
        self.ts = float(ts)
        self.mu = float(mu)
        self.nu = float(nu)
        self.rho_M = float(rho_M)
        self.theta_min = [float(x) for x in theta_min]
        self.theta_max = [float(x) for x in theta_max]
        self.theta_hat = [float(x) for x in theta_hat0]
        self.gamma = [[float(g0[i, j]) for j in range(n)] for i in range(n)]
        ad, bd = zoh_filter_matrices(omega_f, ts)
        self._a11, self._a12, self._a21, self._a22 = (float(ad[0, 0]), float(ad[0, 1]),
                                                      float(ad[1, 0]), float(ad[1, 1]))
        self._b1, self._b2 = float(bd[0]), float(bd[1])
        # Channels: 0 x2, 1 S_f(x2), 2 one, 3 u, 4 u|u|, 5 u³ (4 and 5 only for n = 6).
        self._nch = 4 if n == 4 else 6
        self._zf = [0.0] * self._nch   # filtered signal
        self._zd = [0.0] * self._nch   # its derivative
        self._in = [0.0] * self._nch
        self.phi = [0.0] * n           # φ_f of the last step (eq. 25)
        self.epsilon = 0.0             # prediction error ε (eq. 26)
        self.frozen = False            # True when the last Γ update was frozen (λ_max > ρ_M)
        # scratch
        self._g = [0.0] * n
        self._z = [0.0] * n
        self._active = [False] * n
        self._pivcols = [[0.0] * n for _ in range(n)]
        self._pividx = [0] * n

    # ------------------------------------------------------------------ filters
    def _filter(self, x2: float, u_prev: float) -> None:
        inp = self._in
        inp[0] = x2
        inp[1] = s_f_scalar(x2)
        inp[2] = 1.0
        inp[3] = u_prev
        if self._nch == 6:
            inp[4] = u_prev * abs(u_prev)
            inp[5] = u_prev * u_prev * u_prev
        a11, a12, a21, a22, b1, b2 = self._a11, self._a12, self._a21, self._a22, self._b1, self._b2
        zf, zd = self._zf, self._zd
        for c in range(self._nch):
            f = zf[c]
            d = zd[c]
            zf[c] = a11 * f + a12 * d + b1 * inp[c]
            zd[c] = a21 * f + a22 * d + b2 * inp[c]

    # ------------------------------------------------------------------ step
    def update(self, x2: float, u_prev: float) -> None:
        """One estimator sample (spec §5.2 step 2).

        Args:
            x2: measured velocity over the interval just ended [m/s] (backward difference).
            u_prev: the input held over that interval [V].
        """
        n = self.n
        zf, zd = self._zf, self._zd
        phi = self.phi
        # Filter first: φ_f and u_f must describe the same instant.
        self._filter(x2, u_prev)
        phi[0] = -zd[0]
        phi[1] = -zf[0]
        phi[2] = -zf[1]
        phi[3] = zf[2]
        if n == 6:
            phi[4] = zf[4]
            phi[5] = zf[5]
        u_f = zf[3]
        th = self.theta_hat
        pred = 0.0
        for i in range(n):
            pred -= phi[i] * th[i]
        eps = pred - u_f
        self.epsilon = eps

        gam = self.gamma
        g = self._g
        # φᵀΓφ with the current Γ (for ν-normalisation, eq. 27/28)
        for i in range(n):
            row = gam[i]
            acc = 0.0
            for j in range(n):
                acc += row[j] * phi[j]
            g[i] = acc
        quad = 0.0
        for i in range(n):
            quad += phi[i] * g[i]
        nk = 1.0 + self.nu * quad
        # Information-form update (spec §5.4): Γ' = Γ/(1 − μTs);
        # Γ⁺ = Γ' − (Ts/n) Γ'φφᵀΓ' / (1 + (Ts/n) φᵀΓ'φ).
        scale = 1.0 / (1.0 - self.mu * self.ts) if self.mu > 0.0 else 1.0
        h = self.ts / nk
        c = h * scale * scale / (1.0 + h * scale * quad)
        # tr(Γ⁺) = s·tr(Γ) − c·Σ g_i² bounds λ_max(Γ⁺) for SPD Γ⁺; the eigenvalue is computed
        # only when that bound exceeds ρ_M (the freeze branch of eq. 27).
        trace = 0.0
        g2 = 0.0
        for i in range(n):
            trace += gam[i][i]
            g2 += g[i] * g[i]
        frozen = False
        if scale * trace - c * g2 > self.rho_M:
            cand = scale * np.array(gam) - c * np.outer(g, g)
            frozen = bool(np.linalg.eigvalsh(cand)[-1] > self.rho_M)
        self.frozen = frozen
        z = self._z
        k = eps / nk
        if not frozen:
            for i in range(n):
                gam_i = gam[i]
                cgi = c * g[i]
                for j in range(i, n):
                    val = scale * gam_i[j] - cgi * g[j]
                    gam_i[j] = val
                    gam[j][i] = val
            # τ = φ ε / n (eq. 28); ζ = Γ⁺τ = (s·g − c·g·(gᵀφ))·ε/n, since Γ⁺φ = g (s − c φᵀΓφ)
            f = (scale - c * quad) * k
            for i in range(n):
                z[i] = g[i] * f
        else:
            for i in range(n):
                z[i] = g[i] * k
        self._project(z)
        tmin, tmax, ts = self.theta_min, self.theta_max, self.ts
        for i in range(n):
            val = th[i] + ts * z[i]
            if val > tmax[i]:
                val = tmax[i]
            elif val < tmin[i]:
                val = tmin[i]
            th[i] = val

    def _project(self, z: list) -> None:
        """Γ-weighted box projection (eq. 8) in place on ζ = Γτ (spec §2.2 active-set rule).

        Faces are eliminated one at a time on (Γ, ζ): block Gaussian elimination, so the result
        equals ζ − Γ[:, A] Γ[A, A]⁻¹ ζ[A] for the final active set A. Only the Schur-updated
        columns of the active indices are formed (O(n·|A|) each), in preallocated lists.
        """
        n = self.n
        th, tmin, tmax = self.theta_hat, self.theta_min, self.theta_max
        gam = self.gamma
        active = self._active
        piv_cols = self._pivcols
        piv_idx = self._pividx
        for i in range(n):
            active[i] = False
        m = 0
        added = True
        while added:
            added = False
            for j in range(n):
                if active[j]:
                    continue
                zj = z[j]
                if not ((zj > 0.0 and th[j] >= tmax[j]) or (zj < 0.0 and th[j] <= tmin[j])):
                    continue
                active[j] = True
                added = True
                col = piv_cols[m]
                gj = gam[j]
                for a in range(n):
                    col[a] = gj[a]
                for q in range(m):
                    prev = piv_cols[q]
                    r = col[piv_idx[q]] / prev[piv_idx[q]]
                    if r != 0.0:
                        for a in range(n):
                            col[a] -= r * prev[a]
                piv_idx[m] = j
                m += 1
                cjj = col[j]
                if cjj <= 0.0:  # cannot happen for SPD Γ; keep the face closed regardless
                    z[j] = 0.0
                    continue
                f = z[j] / cjj
                for a in range(n):
                    z[a] -= col[a] * f
                z[j] = 0.0

    # ------------------------------------------------------------------ views
    def gamma_array(self) -> np.ndarray:
        """Γ as a new (n, n) array (for tests and logs; allocates, not for the cycle)."""
        return np.array(self.gamma)

    def reset_filters(self) -> None:
        """Zero the H_f states (used when an axis is (re)started)."""
        for c in range(self._nch):
            self._zf[c] = 0.0
            self._zd[c] = 0.0


def lambda_bounds(gamma: np.ndarray) -> tuple[float, float]:
    """(λ_min, λ_max) of a symmetric matrix; helper for checks and tests."""
    ev = np.linalg.eigvalsh(np.asarray(gamma, dtype=float))
    return float(ev[0]), float(ev[-1])

