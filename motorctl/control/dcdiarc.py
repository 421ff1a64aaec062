"""The DCDIARC law of Chen, Yao & Wang (2013): C2 (cubic model) and C1 (linear model).

Per sample k (docs/control-law.md, Order of operations)::

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

C1 is the same class with four parameters (θ5 = θ6 ≡ 0, no inversion), docs/control-law.md, The DCDIARC law.

Identified-effect compensation d̂_eff (motorctl.effects.compensation; 0 when none) is part of
the model both places use: v_a1 subtracts it (eq. 13) and the estimator sees the input
u + d̂_eff (eq. 4 with d_eff ≈ d̂_eff moved next to u), aligned with the u it was held with
(the d̂_eff of sample k−1 goes with u[k−1]). Feeding the estimator u alone would make θ̂4, θ̂3,
... absorb the effect's mean while v_a1 subtracts the whole effect: counted twice.

An **adapted** entry (``adapt: true``) is not in d̂_eff: its basis columns c(x, ẋ, t) extend φ
(estimator, on the measured mean position and velocity of the interval and its mid time) and
β̂ extends θ̂; v_a1 subtracts β̂ᵀc(x_d, ẋ_d, t). A **force ripple** entry divides v by
1 + r̂(x_d) before the inversion (F = F_m(u)(1 + r(x))) and scales the estimator's thrust
channels by 1 + r̂(x). An **input delay** τ entry evaluates v_a1 (and d̂_eff, c, r̂) on the
desired trajectory at t + τ (:meth:`DCDIARC.preview`, from the loop; else extrapolated with
the last jerk) and feeds the estimator the input applied over the interval, u[k − 1 − n],
n = round(τ/Ts). Without any of them the arithmetic is the paper's (bit-identical).
"""

from __future__ import annotations

import math
from typing import Annotated, Literal

import numpy as np
from numpy.lib.stride_tricks import as_strided
from pydantic import Field

from motorctl.jit import borrow, entry, njit
from motorctl.control.base import (
    LAW_DCDIARC,
    LAW_DCDIARC_COMP,
    LAW_PY,
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
from motorctl.control.params import ControllerConfig
from motorctl.effects.compensation import (
    T_HEAD,
    T_PREVIEW,
    T_THRUST_AT,
    Compensation,
    comp_fill,
    comp_thrust,
    comp_value,
)
from motorctl.model import S_F_GAIN, assumption2_margin
from motorctl.schema import NonNeg, Pos, StrictModel, quantity

__all__ = ["DCDIARC", "dcdiarc_block_reset", "dcdiarc_block_step", "theory_k_s1"]


# state vector of the law (outputs of the last sample)
S_Y_PREV, S_U, S_V, S_E, S_P, S_X2, S_D0, S_KS, S_DC, S_RI = range(10)
N_STATE = 10
# parameter vector of the law
P_TS, P_K1, P_KS, P_GD, P_DMAX, P_ULIM, P_THEORY, P_KS1, P_ETA4, P_DELTA = range(10)
N_PRM = 10


class FilterConfig(StrictModel):
    """H_f = ω_f²/(s + ω_f)² of the estimator's regressor (docs/control-law.md, Order of operations) [S]."""

    omega_f: quantity(1e-2, 1e6, "rad/s") = 200.0


class TheoryConfig(StrictModel):
    """Theory-mode design numbers (eq. 14-15, 22): k2 [V s/m], eta, delta_d [V], optional k_s1."""

    k2: Pos = 10.0
    eta: Pos = 0.05
    delta_d: NonNeg = 0.3
    k_s1: Pos | None = None


class DcdiarcConfig(StrictModel):
    """C1's and C2's settings (the paper's Section VI; values: docs/control-law.md): the
    top-level keys of an axis's ``controller:`` section, which the two laws share, with a
    ``c1:`` or ``c2:`` mapping over them for one law alone.

    Attributes:
        mode: "experiment" (constant k_s) or "theory" (k_s1 + k_s2, eq. 22).
        k_s [V s/m], k1 [1/s], gamma_d [V/m], d_hat_max [V]: the robust feedback (eq. 11,
            18-19, 22). gamma0: diagonal of Γ(0). filter.omega_f [rad/s]. mu [1/s], nu, rho_M:
            LS settings (eq. 27). theory: theory-mode numbers.
    """

    mode: Literal["experiment", "theory"] = "experiment"
    k_s: quantity(1e-3, 1e7, "V s/m") = 95.0
    k1: quantity(1e-3, 1e6, "1/s") = 250.0
    gamma_d: quantity(0.0, 1e9, "V/m") = 500.0
    d_hat_max: quantity(0.0, 1e3, "V") = 1.0
    gamma0: Annotated[list[Pos], Field(min_length=6, max_length=6)]
    filter: FilterConfig = FilterConfig()
    mu: quantity(0.0, 1e4, "1/s") = 0.0
    nu: NonNeg = 0.0
    rho_M: Pos = 1000.0
    theory: TheoryConfig = TheoryConfig()


def theory_k_s1(theta_min, theta_max, k1: float, k2: float) -> float:
    """Smallest k_s1 meeting the PSD condition of paper eq. 13-15; docs/control-law.md, The DCDIARC law (paper eq. 14-15, as reconstructed).

    k_s1 ≥ k2 + θ1 k1 − θ2 − θ3 g + (θ2 + θ3 g)²/(2 θ1 k1) for all θ ∈ Ω_θ, 0 ≤ g ≤ 1800/π.
    The right side is convex in g and in (θ2, θ3), so the maximum over the box corners and the
    end points of g is exact; a grid in g guards the corner enumeration.
    """
    g_max = 2.0 * S_F_GAIN / math.pi
    worst = -math.inf
    for t1 in (theta_min[0], theta_max[0]):
        for t2 in (theta_min[1], theta_max[1]):
            for t3 in (theta_min[2], theta_max[2]):
                for g in np.linspace(0.0, g_max, 65):
                    val = k2 + t1 * k1 - t2 - t3 * g + (t2 + t3 * g) ** 2 / (2.0 * t1 * k1)
                    worst = max(worst, val)
    return float(worst)


# the state block of one axis's law: offsets into ``L`` (the block's layout vector); L[B_N],
# L[B_K], L[B_M] are sizes, the others offsets into F (float64) or I (int64)
B_N, B_K, B_M = 0, 1, 2            # n = n_θ + k, k adapted coefficients, ring width m
(B_ST, B_PRM, B_SPAN, B_RING, B_CM, B_CD, B_TH, B_GAM, B_TMIN, B_TMAX, B_ZF, B_ZD, B_INP, B_FLT,
 B_PHI, B_G, B_Z, B_PIV, B_COEF, B_VEC, B_OPTS, B_RES, B_CT) = range(3, 26)
B_PIVIDX, B_ACTIVE = 26, 27        # offsets into I
N_LAYOUT = 28


@njit
def _matrix(buf, at, rows, cols):
    """buf[at:at + rows·cols] (float64 or int64, 1-D) as a (rows, cols) row-major view, no
    copy. Written with ``as_strided`` because numba's ``reshape`` calls a C helper of about
    50 ns a view (the five views of a sample: a sixth of the C2 step, ``bench_loop.py``)."""
    return as_strided(buf[at:at + rows * cols], shape=(rows, cols), strides=(cols * buf.itemsize, buf.itemsize))


@njit
def dcdiarc_block_step(y, x_d, xd_dot, xd_ddot, xf, vf, af, v_comp, g_meas, g_des, sig, F, I, L, v_fb):
    """One sample of the DCDIARC law (docs/control-law.md, Order of operations) on one axis's
    state block; returns u [V]. State arrays updated in place.

    The law's and the estimator's arrays live in two preallocated buffers, F (float64) and I
    (int64), at the offsets of the layout vector L (int64, N_LAYOUT: the sizes n, k, m, then an
    offset per array, ``B_*``); sig (N_SIGNALS,) the published signals. One call passes four
    arrays instead of thirty, which is most of what a call from Python costs, and the
    compiled servo cycle keeps every axis's block in its rows. The views are taken here,
    without allocation and borrowed (:func:`motorctl.jit.borrow`: F and I are held by the
    caller), and the law runs on them in the same function (a call passing them on, 35
    arrays, cost as much as the law's arithmetic).

    Args:
        y [m], x_d [m], xd_dot [m/s], xd_ddot [m/s²]: measurement and desired trajectory (the
            error e, p of eq. 11).
        xf [m], vf [m/s], af [m/s²]: the desired trajectory the model compensation v_a1 (eq. 13)
            is evaluated on: (x_d, ẋ_d, ẍ_d) itself, or its sample at t + τ (input delay τ).
        v_comp [V]: fixed identified-effect compensation d̂_eff at that point (0 when none).
        g_meas, g_des: thrust factor 1 + r̂(x) (force ripple; 1.0 when none) at the measured
            position over the interval just ended (estimator) and at xf (v / g_des is inverted).
        sig (N_SIGNALS,): the published signals (motorctl.control.signals.CONTROLLER_SIGNALS),
            written at the end of the sample; θ̂ entries beyond n_θ stay as they are (NaN).
        v_fb [V]: a feedback term added to v beside −k_s p (0 for C1/C2; the coupled pair law
            GTCF, :mod:`motorctl.control.gtcf`, passes its task-frame feedback minus −k_s p).
    The block's views: st (N_STATE,): law state (S_* indices; S_DC: the d̂_eff held with S_U;
    S_RI: ring index); prm (10,): law parameters (P_* indices); span (n,): θ_max − θ_min (then
    β_max − β_min) (theory-mode k_s2); ring (2, m): the last m = 1 + round(τ/Ts) outputs (u,
    d̂_eff) when m > 1 (input delay): the estimator is fed the pair applied over the interval
    just ended; cm, cd (k,): adapted basis columns at the measured point (estimator input,
    filled by the caller) and at the desired point (v_a1: − Σ β̂_j cd_j), k = 0: nothing
    adapted; the rest: the estimator's arrays (θ̂ (n_θ + k,), ...).
    """
    n = L[B_N]
    k = L[B_K]
    m = L[B_M]
    st = borrow(F[L[B_ST]:L[B_ST] + N_STATE])
    prm = borrow(F[L[B_PRM]:L[B_PRM] + N_PRM])
    span = borrow(F[L[B_SPAN]:L[B_SPAN] + n])
    ring = borrow(_matrix(F, L[B_RING], 2, m))
    cm = borrow(F[L[B_CM]:L[B_CM] + k])
    cd = borrow(F[L[B_CD]:L[B_CD] + k])
    th = borrow(F[L[B_TH]:L[B_TH] + n])
    gam = borrow(_matrix(F, L[B_GAM], n, n))
    tmin = borrow(F[L[B_TMIN]:L[B_TMIN] + n])
    tmax = borrow(F[L[B_TMAX]:L[B_TMAX] + n])
    zf = borrow(F[L[B_ZF]:L[B_ZF] + n])
    zd = borrow(F[L[B_ZD]:L[B_ZD] + n])
    inp = borrow(F[L[B_INP]:L[B_INP] + n])
    flt = borrow(F[L[B_FLT]:L[B_FLT] + 6])
    phi = borrow(F[L[B_PHI]:L[B_PHI] + n])
    g = borrow(F[L[B_G]:L[B_G] + n])
    z = borrow(F[L[B_Z]:L[B_Z] + n])
    piv = borrow(_matrix(F, L[B_PIV], n, n))
    coef = borrow(_matrix(F, L[B_COEF], n, n))
    vec = borrow(_matrix(F, L[B_VEC], 3, n))
    opts = borrow(F[L[B_OPTS]:L[B_OPTS] + 4])
    res = borrow(F[L[B_RES]:L[B_RES] + 2])
    pividx = borrow(I[L[B_PIVIDX]:L[B_PIVIDX] + n])
    active = borrow(I[L[B_ACTIVE]:L[B_ACTIVE] + n])

    ts = prm[P_TS]
    x2 = (y - st[S_Y_PREV]) / ts
    st[S_Y_PREV] = y
    st[S_X2] = x2
    m = ring.shape[1]
    if m > 1:
        ri = int(st[S_RI])
        ls_update(x2, ring[0, ri], ring[1, ri], g_meas, cm, th, gam, tmin, tmax, zf, zd, inp, flt,
                  phi, g, z, piv, coef, vec, pividx, active, opts, res)
    else:
        ls_update(x2, st[S_U], st[S_DC], g_meas, cm, th, gam, tmin, tmax, zf, zd, inp, flt, phi,
                  g, z, piv, coef, vec, pividx, active, opts, res)
    nb = cd.shape[0]
    n = th.shape[0] - nb
    e = y - x_d
    p = (x2 - xd_dot) + prm[P_K1] * e
    dmax = prm[P_DMAX]
    d0 = st[S_D0] + ts * prm[P_GD] * p                                   # eq. (19)
    if d0 > dmax:
        d0 = dmax
    elif d0 < -dmax:
        d0 = -dmax
    st[S_D0] = d0
    sfd = s_f_jit(vf)
    va1 = th[0] * af + th[1] * vf + th[2] * sfd - th[3] - v_comp         # eq. (13)
    for j in range(nb):
        va1 -= th[n + j] * cd[j]                                         # adapted d̂_eff = β̂ᵀc
    if prm[P_THEORY] > 0.0:
        # k_s2 = (d̂_max + Σ θ_Mi |φ_di| + δ_d)² / (4η), eq. (22), componentwise bound, with the
        # previous u in φ_d to break the algebraic loop (paper eq. 13-15; docs/control-law.md, The DCDIARC law).
        hb = span[0] * abs(af) + span[1] * abs(vf) + span[2] * abs(sfd) + span[3]
        if n == 6:
            up = st[S_U]
            hb += span[4] * up * up + span[5] * abs(up * up * up)
        for j in range(nb):
            hb += span[n + j] * abs(cd[j])
        hb += dmax + prm[P_DELTA]
        ks = prm[P_KS1] + hb * hb / prm[P_ETA4]
    else:
        ks = prm[P_KS]
    st[S_KS] = ks
    v = va1 - d0 - ks * p + v_fb
    ulim = prm[P_ULIM]
    w = v / g_des if g_des != 1.0 else v                                 # F = F_m(u)(1 + r)
    if n == 6:
        u = invert_cubic(w, th[4], th[5], ulim)                            # eq. (9)
    else:
        u = w
    if u > ulim:
        u = ulim
    elif u < -ulim:
        u = -ulim
    st[S_E] = e
    st[S_P] = p
    st[S_V] = v
    st[S_U] = u
    st[S_DC] = v_comp
    if m > 1:
        ri = int(st[S_RI])
        ring[0, ri] = u
        ring[1, ri] = v_comp
        st[S_RI] = float((ri + 1) % m)
    sig[SIG_V] = v
    sig[SIG_E] = e
    sig[SIG_P] = p
    sig[SIG_X2] = x2
    for j in range(n):
        sig[SIG_THETA + j] = th[j]
    sig[SIG_D0] = d0
    return u


@njit
def dcdiarc_comp_step(y, x_d, xd_dot, xd_ddot, xf, vf, af, t, sig, F, I, L, v_fb):
    """One sample of C1/C2 with its compensation (module docstring), on its state block; returns
    u [V].

    The compensation is the block's table (B_CT, the last float field:
    :attr:`motorctl.effects.compensation.Compensation.table`, evaluated in compiled code).
    x_d, xd_dot, xd_ddot: the desired trajectory at this sample [m, m/s, m/s²]; xf, vf, af: at
    t + τ (τ the table's preview; the sample itself when τ = 0); t: time [s]. d̂_eff is evaluated
    on (xf, ẋ_r, t + τ) with the reference velocity ẋ_r = vf − k1 e (e = y − x_d, so that
    p = ẋ − ẋ_r, eq. 11; :mod:`motorctl.effects.compensation`); an adapted basis on the interval
    just ended (mean position, mean velocity, mid time) for the estimator and on (xf, ẋ_r, t + τ)
    for v_a1; the ripple factor at the mean and at the desired position. v_fb [V]: passed on to
    :func:`dcdiarc_block_step` (0 for C1/C2; GTCF's task-frame feedback).
    """
    tab = borrow(F[L[B_CT]:])
    tf = t + tab[T_PREVIEW]
    vr = vf - F[L[B_PRM] + P_K1] * (y - x_d)   # the reference velocity ẋ_r = ẋ_d − k1 e (p = ẋ − ẋ_r)
    v_comp = comp_value(tab, xf, vr, tf)
    g_meas = 1.0
    g_des = 1.0
    k = L[B_K]
    thrust = tab[T_THRUST_AT] != 0.0
    if k > 0 or thrust:
        ts = F[L[B_PRM] + P_TS]
        y_prev = F[L[B_ST] + S_Y_PREV]
        xm = 0.5 * (y + y_prev)              # the interval just ended: mean position,
        if k > 0:                            # mean velocity, mid time
            comp_fill(tab, borrow(F[L[B_CM]:L[B_CM] + k]), xm, (y - y_prev) / ts, t - 0.5 * ts)
            comp_fill(tab, borrow(F[L[B_CD]:L[B_CD] + k]), xf, vr, tf)
        if thrust:
            g_meas = 1.0 + comp_thrust(tab, xm)
            g_des = 1.0 + comp_thrust(tab, xf)
    return dcdiarc_block_step(y, x_d, xd_dot, xd_ddot, xf, vf, af, v_comp, g_meas, g_des, sig, F, I, L, v_fb)


@njit
def dcdiarc_block_reset(y0, F, L):
    """Restart the law of a state block from the measured position y0 [m] with u = 0, d̂0 = 0,
    the H_f states and the input ring zeroed; θ̂, β̂ and Γ kept (:meth:`DCDIARC.reset`)."""
    n = L[B_N]
    for j in range(n):
        F[L[B_ZF] + j] = 0.0
        F[L[B_ZD] + j] = 0.0
    st = L[B_ST]
    F[st + S_Y_PREV] = y0
    F[st + S_U] = 0.0
    F[st + S_DC] = 0.0
    F[st + S_V] = 0.0
    F[st + S_D0] = 0.0
    F[st + S_RI] = 0.0
    for j in range(2 * L[B_M]):
        F[L[B_RING] + j] = 0.0


def _pack(fields, dtype) -> tuple[np.ndarray, list[int]]:
    """Copy each ``(owner, attribute)`` array into one contiguous buffer of ``dtype``; returns
    (buffer, the offset of each)."""
    arrays = [getattr(o, a) for o, a in fields]
    buf = np.zeros(sum(a.size for a in arrays), dtype=dtype)
    offs = []
    at = 0
    for a in arrays:
        buf[at:at + a.size] = a.reshape(-1)
        offs.append(at)
        at += a.size
    return buf, offs


class DCDIARC(Controller):
    """One axis of C1 or C2. Call :meth:`update` once per sample; it returns u [V].

    Args:
        config: the axis's ``controller:`` section (:class:`ControllerConfig`).
        ts: sample period [s].
        kind: "c1" (linear force model, θ1..θ4, no inversion) or "c2" (cubic, θ1..θ6).
    Attributes (of the last sample): u, v [V], e [m], p [m/s], x2 [m/s], d_hat0 [V],
        k_s_eff [V s/m]; theta_hat (n,), beta_hat (k,) (adapted compensation coefficients,
        :attr:`beta_names`) and estimator.gamma (n + k, n + k) are live arrays;
        preview_s [s]: the input delay the law predicts over (0: none);
        signals (see :class:`motorctl.control.base.Controller`).
    Raises:
        ValueError: unknown kind or mode; an adapted entry whose family cannot adapt.
    """

    Settings = DcdiarcConfig
    shared_keys = True
    tuned_keys = ("k_s", "k1", "gamma_d")
    #: autotune's family: damping ζ of the design k_s = 2 ζ ω θ1, k1 = ω / (2 ζ)
    ZETA = (0.3, 0.4, 0.5, 0.7, 1.0)

    def __init__(self, config: ControllerConfig, ts: float, kind: str = "c2"):
        if kind not in ("c1", "c2"):
            raise ValueError(f"DCDIARC kind must be 'c1' or 'c2', got {kind!r}")
        law = config.settings(kind)
        n = 6 if kind == "c2" else 4
        super().__init__(ts, config.u_lim, n)
        self.name = kind
        self.kind = kind
        self.config = config
        self.law = law
        params = config
        comp = None if params.compensation.is_empty() else Compensation(params.compensation)
        self.compensation = comp
        # every term a compiled kernel: the cycle runs the whole law compiled (LAW_DCDIARC_COMP)
        self._compiled_comp = comp is not None and comp.table is not None
        self.n_beta = comp.n_beta if comp is not None else 0
        self.beta_names = list(comp.beta_names) if comp is not None else []
        self.preview_s = comp.preview_s if comp is not None else 0.0
        n_delay = int(round(self.preview_s / ts))
        self.estimator = self._new_estimator()
        self.theory = law.mode == "theory"
        th = law.theory
        if self.theory:
            k_s1 = (theory_k_s1(params.theta_min, params.theta_max, law.k1, th.k2)
                    if th.k_s1 is None else float(th.k_s1))
        else:
            k_s1 = float(law.k_s)
        self.k_s1 = k_s1
        self._prm = np.array([ts, law.k1, law.k_s, law.gamma_d, law.d_hat_max,
                              params.u_lim, 1.0 if self.theory else 0.0, k_s1, 4.0 * th.eta,
                              th.delta_d], dtype=float)
        span = [params.theta_max[i] - params.theta_min[i] for i in range(n)]
        if self.n_beta:
            span += list(comp.beta_max - comp.beta_min)
        self._span = np.array(span, dtype=float)
        self._st = np.zeros(N_STATE)
        self._st[S_KS] = k_s1
        self._ring = np.zeros((2, 1 + n_delay))
        self._cd = np.zeros(self.n_beta)
        # the compensation's compiled table (an empty head without one), copied into the block
        self._ctab = comp.table if self._compiled_comp else np.zeros(T_HEAD)
        # the desired trajectory at t + τ (set by the loop through preview(); else extrapolated)
        self._pv = np.zeros(3)
        self._pv_set = False
        self._ad_prev = 0.0
        self._started = False
        self._rows = None                 # the cycle's rows while attached (attach)
        self._bind()
        # compile (or load the cached machine code) now, on copies of the state, so that the
        # first servo cycle never pays for it
        dcdiarc_block_step(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0, 1.0, self.signals.copy(), self._F.copy(),
                           self._I.copy(), self._L, 0.0)
        if self._compiled_comp:
            dcdiarc_comp_step(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, self.signals.copy(), self._F.copy(),
                              self._I.copy(), self._L, 0.0)
        dcdiarc_block_reset(0.0, self._F.copy(), self._L)

    @classmethod
    def from_config(cls, section: ControllerConfig, ts: float) -> "DCDIARC":
        """C1 or C2 (the class's ``name``) from an axis's ``controller:`` section."""
        return cls(section, ts, cls.name)

    @classmethod
    def check(cls, settings: DcdiarcConfig, section: ControllerConfig) -> list[tuple[str, str]]:
        """Γ(0) within ρ_M (eq. 27) and Assumption 2 on the θ box: the cubic f_u(u) = u + θ5 u|u|
        + θ6 u³ must be monotonic on |u| ≤ u_lim for every θ5, θ6 of the box (eq. 3, 9)."""
        out = []
        if max(settings.gamma0) > settings.rho_M:
            out.append(("gamma0", f"largest entry {max(settings.gamma0)} exceeds rho_M = {settings.rho_M} "
                                  "(eq. 27 needs ||Gamma(0)|| <= rho_M)"))
        c = section
        margin = assumption2_margin((c.theta_min[4], c.theta_max[4]), (c.theta_min[5], c.theta_max[5]), c.u_lim)
        if margin <= 0:
            out.append(("theta_min", f"bounds break Assumption 2: f_u(u) = u + theta5 u|u| + theta6 u^3 is not "
                                     f"monotonic on |u| <= u_lim = {c.u_lim} V (min slope {margin:.3g}); "
                                     f"raise theta_min[4]/theta_min[5] or lower u_lim"))
        return out

    @classmethod
    def linearise(cls, gains, ts, w, theta_hat=None, u0=0.0):
        """Experiment mode at rest: v_s = −k_s p, p = Δy + k1 e, d̂0 += Ts γ_d p (eq. 11, 18-19);
        v_a1 depends on x_d only and the θ̂ adaptation is slow and left out, so
        C(z) = (k_s + γ_d Ts/(1 − z⁻¹)) (k1 + (1 − z⁻¹)/Ts) / f_u'(u0), where C2 divides by the
        slope of its inversion f_u(u) = u + θ̂5 u|u| + θ̂6 u³ (eq. 9) at u0 [V] (θ̂ (6,); default
        θ̂5 = θ̂6 = 0) and C1 by 1. w (K,) [rad/s] -> complex (K,)."""
        z1 = np.exp(-1j * np.asarray(w) * ts)
        return ((gains["k_s"] + gains["gamma_d"] * ts / (1.0 - z1)) * (gains["k1"] + (1.0 - z1) / ts)
                / cls.inversion_slope(theta_hat, u0))

    @classmethod
    def inversion_slope(cls, theta_hat=None, u0=0.0) -> float:
        """f_u'(u0) = 1 + 2 θ̂5 |u0| + 3 θ̂6 u0² of C2's inversion (eq. 9) at u0 [V] (θ̂ (6,); 1.0
        for C1 or without θ̂): what :meth:`linearise` divides the feedback by."""
        if cls.name == "c2" and theta_hat is not None:
            return 1.0 + 2.0 * float(theta_hat[4]) * abs(u0) + 3.0 * float(theta_hat[5]) * u0 * u0
        return 1.0

    @classmethod
    def gain_family(cls, theta1, settings, omegas, zetas=None):
        """k_s = 2 ζ ω θ1, k1 = ω / (2 ζ) for ω in ``omegas`` [rad/s], ζ in ``zetas`` (None:
        :attr:`ZETA`), γ_d of the settings (the robust part's pole pair at ω with damping ζ on
        the rigid model)."""
        return [{"k_s": 2.0 * z * w * theta1, "k1": w / (2.0 * z), "gamma_d": float(settings.gamma_d),
                 "_w": w, "_zeta": z} for w in omegas for z in (zetas or cls.ZETA)]

    @classmethod
    def scaled(cls, gains, s):
        """k_s × s (k1 and γ_d kept)."""
        g = dict(gains)
        g["k_s"] = g["k_s"] * s
        return g

    def _new_estimator(self) -> LeastSquaresEstimator:
        c, p, n, comp = self.config, self.law, self.n_theta, self.compensation
        th0, tmin, tmax = list(c.theta_hat0[:n]), list(c.theta_min[:n]), list(c.theta_max[:n])
        g0 = list(p.gamma0[:n])
        if self.n_beta:
            th0 += list(comp.beta0)
            tmin += list(comp.beta_min)
            tmax += list(comp.beta_max)
            g0 += list(comp.gamma0)
        return LeastSquaresEstimator(th0, tmin, tmax, np.diag(g0), p.filter.omega_f, self.ts, p.mu,
                                     p.nu, p.rho_M, n_beta=self.n_beta)

    def _fields(self):
        """The arrays of the state block, in layout order: (float fields, int fields), each a
        list of (owner, attribute)."""
        est = self.estimator
        floats = [(self, "_st"), (self, "_prm"), (self, "_span"), (self, "_ring"), (est, "cols"), (self, "_cd")]
        floats += [(est, a) for a in est.FLOAT_ARRAYS] + [(self, "_ctab")]   # the table last (B_CT)
        return floats, [(est, a) for a in est.INT_ARRAYS]

    def _bind(self) -> None:
        """Pack the law's and the estimator's arrays into this axis's state block (F, I, L;
        :func:`dcdiarc_block_step`) and rebind them, the estimator's included, to views of it
        (between cycles: at construction and when θ̂(0) is restored); an attached law moves
        the new block into the cycle's rows again."""
        est = self.estimator
        n = self.n_theta
        self.signals[SIG_THETA:SIG_THETA + n] = est.theta_hat[:n]
        floats, ints = self._fields()
        self._F, f_off = _pack(floats, np.float64)
        self._I, i_off = _pack(ints, np.int64)
        self._L = np.array([est.n, self.n_beta, self._ring.shape[1], *f_off, *i_off], dtype=np.int64)
        assert self._L.shape == (N_LAYOUT,)
        self._sizes = (self._F.size, self._I.size)
        self._views()
        if self._rows is not None:
            self.attach(*self._rows)

    def _views(self) -> None:
        """Rebind every array of the block to its view of the current F and I."""
        floats, ints = self._fields()
        for buf, fields in ((self._F, floats), (self._I, ints)):
            for j, (owner, attr) in enumerate(fields):
                a = getattr(owner, attr)
                at = self._L[3 + j if buf is self._F else 3 + len(floats) + j]
                setattr(owner, attr, buf[at:at + a.size].reshape(a.shape))
        n = self.n_theta
        est = self.estimator
        self.theta_hat = est.theta_hat[:n]
        self.beta_hat = est.theta_hat[n:]
        self._cm = est.cols
        # the compiled step for these arrays, called from update() without numba's type resolution
        if not self._compiled_comp:
            self._step = entry(dcdiarc_block_step, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0, 1.0,
                               self.signals, self._F, self._I, self._L, 0.0)
        else:
            self._step = entry(dcdiarc_comp_step, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, self.signals,
                               self._F, self._I, self._L, 0.0)

    @property
    def law_code(self) -> int:
        """LAW_DCDIARC without compensation (the cycle runs :func:`dcdiarc_block_step`),
        LAW_DCDIARC_COMP with one whose terms are all compiled (:func:`dcdiarc_comp_step`), else
        LAW_PY (a term that is a Python callable: :meth:`update` from Python)."""
        if self.compensation is None:
            return LAW_DCDIARC
        return LAW_DCDIARC_COMP if self._compiled_comp else LAW_PY

    def state_size(self) -> tuple[int, int]:
        return self._sizes

    def attach(self, sig, f, ii, lay) -> None:
        """The block and the signals into the cycle's rows (:meth:`Controller.attach`)."""
        nf, ni = self._sizes
        sig[:] = self.signals
        f[:nf] = self._F[:nf]
        ii[:ni] = self._I[:ni]
        lay[:] = self._L
        self.signals = sig
        self._F, self._I = f, ii
        self._rows = (sig, f, ii, lay)
        self._views()

    def detach(self) -> None:
        """The block back into arrays of this controller's own (:meth:`Controller.detach`)."""
        if self._rows is None:
            return
        self._rows = None
        self.signals = self.signals.copy()
        nf, ni = self._sizes
        self._F, self._I = self._F[:nf].copy(), self._I[:ni].copy()
        self._views()

    def reset(self, y0: float, keep_theta: bool = True) -> None:
        """Start (or restart) from the measured position y0 [m] with u = 0 and d̂0 = 0.

        θ̂, β̂ and Γ are kept unless keep_theta is False (then θ̂(0), β̂(0), Γ(0) are restored).
        """
        if not keep_theta:
            self.estimator = self._new_estimator()
            self._bind()
        dcdiarc_block_reset(y0, self._F, self._L)
        self._pv_set = False
        self._ad_prev = 0.0
        self._started = True

    def inherit(self, other: Controller) -> None:
        """θ̂ (common leading entries, :meth:`Controller.inherit`) and β̂ when ``other`` adapts
        the same coefficients."""
        super().inherit(other)
        if self.n_beta and getattr(other, "beta_names", None) == self.beta_names:
            self.beta_hat[:] = other.beta_hat

    def preview(self, x_d: float, xd_dot: float, xd_ddot: float) -> None:
        """The desired trajectory at t + :attr:`preview_s` [m, m/s, m/s²] for the next
        :meth:`update` (called by the servo loop when preview_s > 0)."""
        pv = self._pv
        pv[0] = x_d
        pv[1] = xd_dot
        pv[2] = xd_ddot
        self._pv_set = True

    def update(self, y: float, x_d: float, xd_dot: float, xd_ddot: float, t: float = 0.0) -> float:
        """One control sample (docs/control-law.md, Order of operations). Returns u [V], |u| ≤ u_lim.

        Args:
            y: measured position [m]. x_d, xd_dot, xd_ddot: desired position [m],
            velocity [m/s] and acceleration [m/s²] at this sample. t: time [s] (used only by
            a time-periodic compensation term).
        """
        if not self._started:
            self.reset(y)
        if self.compensation is None:
            return self._step(y, x_d, xd_dot, xd_ddot, x_d, xd_dot, xd_ddot, 0.0, 1.0, 1.0,
                              self.signals, self._F, self._I, self._L, 0.0)
        tau = self.preview_s
        if tau > 0.0:
            if self._pv_set:
                pv = self._pv
                xf, vf, af = float(pv[0]), float(pv[1]), float(pv[2])
                self._pv_set = False
            else:   # no preview given: extrapolate with the jerk of the last sample
                jk = (xd_ddot - self._ad_prev) / self.ts
                xf = x_d + tau * (xd_dot + tau * (0.5 * xd_ddot + tau * jk / 6.0))
                vf = xd_dot + tau * (xd_ddot + 0.5 * tau * jk)
                af = xd_ddot + tau * jk
            self._ad_prev = xd_ddot
        else:
            xf, vf, af = x_d, xd_dot, xd_ddot
        if self._compiled_comp:
            return self._step(y, x_d, xd_dot, xd_ddot, xf, vf, af, t, self.signals, self._F, self._I, self._L, 0.0)
        # a Python term (no kernel): the same evaluation as dcdiarc_comp_step, from Python
        comp = self.compensation
        tf = t + tau
        vr = vf - float(self._prm[P_K1]) * (y - x_d)    # the reference velocity, as dcdiarc_comp_step
        v_comp = comp.value(xf, vr, tf)
        g_meas = g_des = 1.0
        if self.n_beta or comp.thrust is not None:
            ts = self.ts
            y_prev = float(self._st[S_Y_PREV])
            xm = 0.5 * (y + y_prev)              # the interval just ended: mean position,
            if self.n_beta:                      # mean velocity, mid time
                comp.fill(self._cm, xm, (y - y_prev) / ts, t - 0.5 * ts)
                comp.fill(self._cd, xf, vr, tf)
            if comp.thrust is not None:
                g_meas = 1.0 + comp.thrust(xm)
                g_des = 1.0 + comp.thrust(xf)
        return self._step(y, x_d, xd_dot, xd_ddot, xf, vf, af, v_comp, g_meas, g_des, self.signals, self._F,
                          self._I, self._L, 0.0)

    # outputs of the last sample (float reads of the state vector)
    u = property(lambda self: float(self._st[S_U]))
    v = property(lambda self: float(self._st[S_V]))
    p = property(lambda self: float(self._st[S_P]))
    x2 = property(lambda self: float(self._st[S_X2]))
    d_hat0 = property(lambda self: float(self._st[S_D0]))
    k_s_eff = property(lambda self: float(self._st[S_KS]))


class C1(DCDIARC):
    """C1: the ARC law with the linear force model F = A1 u (θ1..θ4, no input inversion)."""

    name = "c1"
    records = ("v", "e", "p", "x2", "theta_hat1", "theta_hat2", "theta_hat3", "theta_hat4", "d_hat0")

    def __init__(self, config: ControllerConfig, ts: float, kind: str = "c1"):
        super().__init__(config, ts, kind)


class C2(DCDIARC):
    """C2: DCDIARC with the cubic force model F = A1 u + A2 u|u| + A3 u³ (θ1..θ6, eq. 3-9)."""

    name = "c2"
    records = ("v", "e", "p", "x2", "theta_hat1", "theta_hat2", "theta_hat3", "theta_hat4",
               "theta_hat5", "theta_hat6", "d_hat0")

    def __init__(self, config: ControllerConfig, ts: float, kind: str = "c2"):
        super().__init__(config, ts, kind)
