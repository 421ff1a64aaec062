"""The DCDIARC law of Chen, Yao & Wang (2013): C2 (cubic model) and C1 (linear model).

Per sample k (spec §5.2)::

    x2   = (y[k] − y[k−1]) / Ts                                   backward difference
    estimator.update(x2, u[k−1] + d̂_eff[k−1])                     eq. (25)-(28), (7)-(8)
    e    = y − x_d,  p = ė + k1 e                                 eq. (11)
    d̂0  ← clip(d̂0 + Ts γ_d p, ±d̂_max)                            eq. (19)
    v_a1 = θ̂1 ẍ_d + θ̂2 ẋ_d + θ̂3 S_f(ẋ_d) − θ̂4                   eq. (13), desired compensation
    v_a2 = −d̂0                                                   eq. (18)
    v_s  = −k_s p              (experiment mode, k_s = 95)
         = −(k_s1 + k_s2) p    (theory mode, eq. 22)
    v    = v_a1 + v_a2 + v_s
    u    = f_u⁻¹(v; θ̂5, θ̂6, u_M), clipped to ±u_lim                eq. (9), C2 only; C1: u = v

C1 is the same class with four parameters (θ5 = θ6 ≡ 0, no inversion), spec §3.5.

Identified-effect compensation d̂_eff (motorctl.effects.compensation; 0 when none) is part of
the model both places use: v_a1 subtracts it (eq. 13) and the estimator sees the input
u + d̂_eff (eq. 4 with d_eff ≈ d̂_eff moved next to u), aligned with the u it was held with
(the d̂_eff of sample k−1 goes with u[k−1]). Feeding the estimator u alone would make θ̂4, θ̂3,
... absorb the effect's mean while v_a1 subtracts the whole effect: counted twice.
"""

from __future__ import annotations

import numpy as np

from motorctl.jit import njit
from motorctl.control.base import (
    SIG_D0,
    SIG_E,
    SIG_P,
    SIG_THETA,
    SIG_V,
    SIG_X2,
    Controller,
)
from motorctl.control.estimator import LeastSquaresEstimator, ls_update, s_f_jit
from motorctl.control.inversion import invert_cubic
from motorctl.control.params import ControllerConfig, theory_k_s1
from motorctl.effects.compensation import Compensation

__all__ = ["DCDIARC", "dcdiarc_step", "theory_k_s1"]


# state vector of the law (outputs of the last sample)
S_Y_PREV, S_U, S_V, S_E, S_P, S_X2, S_D0, S_KS, S_DC = range(9)
N_STATE = 9
# parameter vector of the law
P_TS, P_K1, P_KS, P_GD, P_DMAX, P_ULIM, P_THEORY, P_KS1, P_ETA4, P_DELTA = range(10)


@njit
def dcdiarc_step(y, x_d, xd_dot, xd_ddot, v_comp, sig, st, prm, span, th, gam, tmin, tmax, zf, zd,
                 inp, flt, phi, g, z, piv, coef, vec, pividx, active, opts, res):
    """One sample of the DCDIARC law (spec §5.2); returns u [V]. State arrays updated in place.

    Args:
        y [m], x_d [m], xd_dot [m/s], xd_ddot [m/s²]: measurement and desired trajectory.
        v_comp [V]: identified-effect compensation d̂_eff(x_d, ẋ_d, t) (0 when none).
        sig (N_SIGNALS,): the published signals (motorctl.loop.records.CONTROLLER_SIGNALS),
            written at the end of the sample; θ̂ entries beyond n stay as they are (NaN).
        st (N_STATE,): law state (S_* indices; S_DC: the d̂_eff held with S_U).
        prm (10,): law parameters (P_* indices).
        span (n,): θ_max − θ_min (theory-mode k_s2). The rest: the estimator's arrays.
    """
    ts = prm[P_TS]
    x2 = (y - st[S_Y_PREV]) / ts
    st[S_Y_PREV] = y
    st[S_X2] = x2
    ls_update(x2, st[S_U], st[S_DC], th, gam, tmin, tmax, zf, zd, inp, flt, phi, g, z, piv, coef, vec,
              pividx, active, opts, res)
    n = th.shape[0]
    e = y - x_d
    p = (x2 - xd_dot) + prm[P_K1] * e
    dmax = prm[P_DMAX]
    d0 = st[S_D0] + ts * prm[P_GD] * p                                   # eq. (19)
    if d0 > dmax:
        d0 = dmax
    elif d0 < -dmax:
        d0 = -dmax
    st[S_D0] = d0
    sfd = s_f_jit(xd_dot)
    va1 = th[0] * xd_ddot + th[1] * xd_dot + th[2] * sfd - th[3] - v_comp  # eq. (13)
    if prm[P_THEORY] > 0.0:
        # k_s2 = (d̂_max + Σ θ_Mi |φ_di| + δ_d)² / (4η), eq. (22), componentwise bound, with the
        # previous u in φ_d to break the algebraic loop (spec §3.3).
        hb = span[0] * abs(xd_ddot) + span[1] * abs(xd_dot) + span[2] * abs(sfd) + span[3]
        if n == 6:
            up = st[S_U]
            hb += span[4] * up * up + span[5] * abs(up * up * up)
        hb += dmax + prm[P_DELTA]
        ks = prm[P_KS1] + hb * hb / prm[P_ETA4]
    else:
        ks = prm[P_KS]
    st[S_KS] = ks
    v = va1 - d0 - ks * p
    ulim = prm[P_ULIM]
    if n == 6:
        u = invert_cubic(v, th[4], th[5], ulim)                            # eq. (9)
    else:
        u = v
    if u > ulim:
        u = ulim
    elif u < -ulim:
        u = -ulim
    st[S_E] = e
    st[S_P] = p
    st[S_V] = v
    st[S_U] = u
    st[S_DC] = v_comp
    sig[SIG_V] = v
    sig[SIG_E] = e
    sig[SIG_P] = p
    sig[SIG_X2] = x2
    for j in range(n):
        sig[SIG_THETA + j] = th[j]
    sig[SIG_D0] = d0
    return u


class DCDIARC(Controller):
    """One axis of C1 or C2. Call :meth:`update` once per sample; it returns u [V].

    Args:
        config: the axis's ``controller:`` section (:class:`ControllerConfig`).
        ts: sample period [s].
        kind: "c1" (linear force model, θ1..θ4, no inversion) or "c2" (cubic, θ1..θ6).
    Attributes (of the last sample): u, v [V], e [m], p [m/s], x2 [m/s], d_hat0 [V],
        k_s_eff [V s/m]; theta_hat (n,) and estimator.gamma (n, n) are live arrays;
        signals (see :class:`motorctl.control.base.Controller`).
    Raises:
        ValueError: unknown kind or mode.
    """

    def __init__(self, config: ControllerConfig, ts: float, kind: str = "c2"):
        if kind not in ("c1", "c2"):
            raise ValueError(f"DCDIARC kind must be 'c1' or 'c2', got {kind!r}")
        if config.mode not in ("experiment", "theory"):
            raise ValueError(f"controller mode must be 'experiment' or 'theory', got {config.mode!r}")
        n = 6 if kind == "c2" else 4
        super().__init__(ts, config.u_lim, n)
        self.name = kind
        self.kind = kind
        self.config = config
        params = config
        self.estimator = self._new_estimator()
        self.theory = params.mode == "theory"
        th = params.theory
        if self.theory:
            k_s1 = (theory_k_s1(params.theta_min, params.theta_max, params.k1, th.k2)
                    if th.k_s1 is None else float(th.k_s1))
        else:
            k_s1 = float(params.k_s)
        self.k_s1 = k_s1
        self._prm = np.array([ts, params.k1, params.k_s, params.gamma_d, params.d_hat_max,
                              params.u_lim, 1.0 if self.theory else 0.0, k_s1, 4.0 * th.eta,
                              th.delta_d], dtype=float)
        self._span = np.array([params.theta_max[i] - params.theta_min[i] for i in range(n)])
        self._st = np.zeros(N_STATE)
        self._st[S_KS] = k_s1
        self.compensation = (None if params.compensation.is_empty()
                             else Compensation(params.compensation))
        self._started = False
        self._bind()
        # compile (or load the cached machine code) now, on copies of the state, so that the
        # first servo cycle never pays for it
        dcdiarc_step(0.0, 0.0, 0.0, 0.0, 0.0, *(a.copy() for a in self._args))

    @classmethod
    def from_config(cls, section: ControllerConfig, ts: float, name: str) -> "DCDIARC":
        """C1 or C2 (``name``) from an axis's ``controller:`` section."""
        return cls(section, ts, name)

    def _new_estimator(self) -> LeastSquaresEstimator:
        p, n = self.config, self.n_theta
        return LeastSquaresEstimator(p.theta_hat0[:n], p.theta_min[:n], p.theta_max[:n],
                                     np.diag(p.gamma0[:n]), p.filter.omega_f, self.ts, p.mu, p.nu,
                                     p.rho_M)

    def _bind(self) -> None:
        self.theta_hat = self.estimator.theta_hat
        self.signals[SIG_THETA:SIG_THETA + self.n_theta] = self.theta_hat
        self._args = (self.signals, self._st, self._prm, self._span) + self.estimator.kernel_args()

    def reset(self, y0: float, keep_theta: bool = True) -> None:
        """Start (or restart) from the measured position y0 [m] with u = 0 and d̂0 = 0.

        θ̂ and Γ are kept unless keep_theta is False (then θ̂(0), Γ(0) are restored).
        """
        if not keep_theta:
            self.estimator = self._new_estimator()
            self._bind()
        self.estimator.reset_filters()
        st = self._st
        st[S_Y_PREV] = y0
        st[S_U] = 0.0
        st[S_DC] = 0.0
        st[S_V] = 0.0
        st[S_D0] = 0.0
        self._started = True

    def update(self, y: float, x_d: float, xd_dot: float, xd_ddot: float, t: float = 0.0) -> float:
        """One control sample (spec §5.2). Returns u [V], |u| ≤ u_lim.

        Args:
            y: measured position [m]. x_d, xd_dot, xd_ddot: desired position [m],
            velocity [m/s] and acceleration [m/s²] at this sample. t: time [s] (used only by
            a time-periodic compensation term).
        """
        if not self._started:
            self.reset(y)
        comp = self.compensation
        v_comp = comp.value(x_d, xd_dot, t) if comp is not None else 0.0
        return dcdiarc_step(y, x_d, xd_dot, xd_ddot, v_comp, *self._args)

    # outputs of the last sample (float reads of the state vector)
    u = property(lambda self: float(self._st[S_U]))
    v = property(lambda self: float(self._st[S_V]))
    p = property(lambda self: float(self._st[S_P]))
    x2 = property(lambda self: float(self._st[S_X2]))
    d_hat0 = property(lambda self: float(self._st[S_D0]))
    k_s_eff = property(lambda self: float(self._st[S_KS]))

