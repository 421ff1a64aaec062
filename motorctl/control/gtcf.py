"""GTCF: the global task coordinate frame ARC law for a pair of axes (Hu, Yao & Wang 2011),
built on C2 (the DCDIARC law of Chen, Yao & Wang 2013) per axis.

Hu, Yao & Wang, "Global Task Coordinate Frame-Based Contouring Control of Linear-Motor-Driven
Biaxial Systems With Accurate Parameter Estimations", IEEE Trans. Ind. Electron. 58(11), 2011,
express the two axes' tracking errors in a frame that moves with the desired point: the
tangential and the normal direction of the desired path, so that the normal component is the
contour error (to first order), and set the ARC law's robust feedback with a higher gain on the
normal (contour) direction than on the tangential one. Here (docs/control-law.md, "GTCF: the
contouring law of a pair of axes")::

    t = (ẋ_d, ẏ_d) / |(ẋ_d, ẏ_d)|,  n = t rotated by +90°       the task frame at the desired point
    T(θ) = [tᵀ; nᵀ]  (2×2, orthonormal),   ε = T e              (Hu 2011: the GTCF errors)
    p_i = ė_i + k1_i e_i                    per axis, as C2's eq. (11) (ė: backward difference)
    p̃_i = p_i + (λ_n,i − 1) k1_i n_i sat(ε_n)   the contour error's own gain in p, sat: ±lambda_band
    q = D^½ p,  D = diag(k_s,X, k_s,Y)      the axes' own C2 gains as the scale
    K = g_t t tᵀ + N^½ n nᵀ N^½,  N = diag(g_n,X, g_n,Y)
    v_s = −D^½ K D^½ p̃                      the robust feedback set in the task frame
    u_i = C2's law of axis i with v_s,i in place of −k_s,i p_i  (the 2013 paper's model
          compensation v_a1 eq. 13, d̂0 eq. 18-19, the projection-type LS estimator eq. 25-28,
          the inversion eq. 9: per axis)

With one contour gain (g_n,X = g_n,Y = g_n), K = Tᵀ diag(g_t, g_n) T: the 2011 paper's
diagonal task-frame gain. Each axis's own ``gain_n`` is its stiffness when the contour
direction is its own (on a circle, at the other axis's reversal): the axes' loops bear
different gains (their margins, their rest noise), and the contour gain of each can be as high
as its own loop allows. K is symmetric and positive definite for positive gains, so the robust
feedback keeps the ARC law's −pᵀ D^½ K D^½ p ≤ 0. With g_t = g_n = 1 this is C2 on each axis.
Below ``v_min`` of desired speed (at rest, no contour direction) the gains blend linearly to 1
(C2): g(s) = 1 + min(1, s/v_min)(g − 1), λ_n alike. λ_n is the contour entry of the 2011 paper's
diagonal Λ in s = ε̇ + Λ ε (the tangential entry is k1): stiffness against a contour error
without the quantisation flicker a larger k_s carries. d̂0 and the estimator keep C2's p.

The feedback beyond C2's own, v_fb,i = v_s,i + k_s,i p_i, passes through a first-order low-pass
of corner ``lowpass_hz`` (none: unfiltered, the 2011 paper's law): v_fb[k] = v_fb[k−1] +
α (v_fb,raw − v_fb[k−1]), α = 1 − exp(−2π f_c Ts). The contour's errors (a reversal's
transient, 20-200 Hz) meet the task-frame gains; the encoder's quantisation through the
backward difference (0.5 µm a count at 5 kHz is 2.5 mm/s: most of an axis's u at rest lies
above 1 kHz) meets C2's gain alone.

The pair runs in the compiled servo cycle (:mod:`motorctl.loop.cycle`): each axis of the pair
has this law (``LAW_GTCF``); the cycle hands each one's step its partner's measured position and
desired sample of the same cycle (:func:`gtcf_step`), and the partner's C2 gains and g_n come
from the partner's own rows. When the partner does not run GTCF, is not running, or its sample
is not a number (IDLE), the step is C2 alone (v_fb = 0) for that cycle.

Settings: a ``gtcf:`` mapping in both axes' ``controller:`` sections (the C2 keys of the section
are the per-axis law's, its compensation C2's; theory mode is refused)::

    gtcf: {partner: Y, gain_t: 1.0, gain_n: 2.0, v_min: 0.002, lowpass_hz: 500, lambda_n: 1.5}

The pair's two sections name each other and give the same ``gain_t``; each its own ``gain_n``
and ``lambda_n``.
"""

from __future__ import annotations

import math

import numpy as np

from motorctl.control.base import LAW_GTCF, LAW_PY
from motorctl.control.dcdiarc import (
    B_N,
    B_PRM,
    B_SPAN,
    B_ST,
    DCDIARC,
    P_K1,
    P_KS,
    P_TS,
    S_Y_PREV,
    dcdiarc_block_reset,
    dcdiarc_block_step,
    dcdiarc_comp_step,
)
from motorctl.control.params import ControllerConfig
from motorctl.jit import njit
from motorctl.schema import StrictModel, quantity

__all__ = ["GTCF", "GtcfConfig", "gtcf_feedback", "gtcf_partner", "gtcf_reset", "gtcf_step"]

# GTCF's numbers, in the C2 block after its span of θ_max − θ_min (B_SPAN, n entries; read by
# the theory mode only, which GTCF refuses): partner axis index, g_t, g_n (this axis's), v_min,
# the partner's y[k−1] (NaN: none yet), the last v_fb (the low-pass's state), the last ε_n (the
# task-frame normal error from this axis's view), 1.0 when the block has a compiled compensation
# (dcdiarc_comp_step) else 0.0, the low-pass's α (1: none), λ_n, its band [m]
G_PARTNER, G_GT, G_GN, G_VMIN, G_YJ, G_VFB, G_EN, G_COMP, G_ALPHA, G_LN, G_LB = range(11)
N_G = 11


class GtcfConfig(StrictModel):
    """The ``gtcf:`` mapping of an axis's ``controller:`` section.

    Attributes:
        partner: the other axis of the pair (its section must configure ``gtcf`` naming this one).
        gain_t: the task-frame gain on the tangential direction, as a multiple of the axes' own
            C2 k_s (the pair's: the partner's section gives the same).
        gain_n: this axis's gain when the contour (normal) direction is its own, as a multiple of
            its C2 k_s (1, 1: C2).
        v_min [m/s]: below this desired speed the gains blend to 1 (no contour direction at rest).
        lambda_n: this axis's gain on the contour error in its sliding variable, as a multiple of
            its C2 k1 (1: C2's p; the contour entry of the 2011 paper's Λ).
        lambda_band [m]: the contour error beyond which λ_n adds no more (ε_n clipped to ±it):
            a reversal's stick is a few µm; a fast move's transient error of tens of µm meets
            C2's stiffness, and λ_n's extra force is at most k_s g_n (λ_n − 1) k1 lambda_band.
        lowpass_hz [Hz]: the corner of the first-order low-pass on the feedback beyond C2's
            (None: unfiltered); below the Nyquist frequency 1/(2 Ts).
    """

    partner: str
    gain_t: quantity(1e-2, 100.0, "") = 1.0
    gain_n: quantity(1e-2, 100.0, "") = 2.0
    v_min: quantity(1e-6, 10.0, "m/s") = 0.002
    lowpass_hz: quantity(0.0, 1e6, "Hz", open_lo=True) | None = None
    lambda_n: quantity(1.0, 100.0, "") = 1.0
    lambda_band: quantity(0.0, 1.0, "m", open_lo=True) = 5e-6


@njit
def gtcf_feedback(p_i, p_j, v_i, v_j, ks_i, ks_j, g_t, g_ni, g_nj, v_min):
    """The task-frame robust feedback of axis i minus C2's own −k_s,i p_i [V], unfiltered (module
    docstring): −√k_s,i (g_t' t_i (tᵀq) + √g_ni' n_i (nᵀ N'^½ q)) + k_s,i p_i, q = √k_s p, t = v/|v|,
    n = t rotated +90° in (i, j) order, g' = 1 + min(1, |v|/v_min)(g − 1); g_ni, g_nj the two
    axes' contour gains. p [m/s], v (ẋ_d) [m/s], k_s [V s/m]. Symmetric in the two axes (axis j's
    is this with i and j swapped). Hu, Yao & Wang 2011: the task frame T and the robust feedback
    set in it, with a contour gain per axis (docs/control-law.md, "GTCF"); per axis the 2013
    paper's eq. (11), (13)."""
    s = math.sqrt(v_i * v_i + v_j * v_j)
    w = s / v_min
    if w > 1.0:
        w = 1.0
    gt = 1.0 + w * (g_t - 1.0)
    gni = 1.0 + w * (g_ni - 1.0)
    gnj = 1.0 + w * (g_nj - 1.0)
    ti = 0.0
    tj = 0.0
    if s > 0.0:
        ti = v_i / s
        tj = v_j / s
    ri = math.sqrt(ks_i)
    qi = ri * p_i
    qj = math.sqrt(ks_j) * p_j
    # with t tᵀ + n nᵀ = I, −k_s,i p_i = −√k_s,i (t_i tᵀq + n_i nᵀq), so the difference is written
    # without the cancellation of the two k_s,i p_i terms: exactly 0 when every gain is 1 (at
    # rest, or gains of 1: C2); n_i = −t_j, n_j = t_i
    ni = -tj
    return -ri * ((gt - 1.0) * ti * (ti * qi + tj * qj)
                  + ni * (ni * (gni - 1.0) * qi + ti * (math.sqrt(gni * gnj) - 1.0) * qj))


def lowpass_alpha(lowpass_hz: float | None, ts: float) -> float:
    """α = 1 − exp(−2π f_c Ts) of the first-order low-pass of corner ``lowpass_hz`` [Hz] sampled
    at ``ts`` [s] (the pole of the continuous filter mapped by z = e^{sTs}); 1.0 for None (no
    filter). Raises ValueError: a corner at or above the Nyquist frequency 1/(2 Ts)."""
    if lowpass_hz is None:
        return 1.0
    if not 0.0 < lowpass_hz < 0.5 / ts:
        raise ValueError(f"{lowpass_hz:g} Hz must be above 0 and below the Nyquist frequency "
                         f"{0.5 / ts:g} Hz of the {ts * 1e3:g} ms period")
    return 1.0 - math.exp(-2.0 * math.pi * lowpass_hz * ts)


@njit
def _contour_dp(lambda_n, band, k1, n_i, w, e_n):
    """The term the contour error's gain adds to axis i's p [m/s]: (λ' − 1) k1 n_i sat(ε_n),
    λ' = 1 + w (λ_n − 1), sat clipping ε_n [m] to ±``band`` [m] (module docstring)."""
    return (lambda_n - 1.0) * w * k1 * n_i * min(max(e_n, -band), band)


@njit
def gtcf_partner(F, L):
    """The partner axis's index (into the cycle's rows) of a GTCF block."""
    return int(F[L[B_SPAN] + L[B_N] + G_PARTNER])


@njit
def gtcf_step(y, x_d, xd_dot, xd_ddot, xf, vf, af, t, y_j, x_dj, xd_dot_j, coupled, sig, F, I, L, Fj, Lj):
    """One sample of GTCF on axis i's block (F, I, L; the C2 block of
    :func:`motorctl.control.dcdiarc.dcdiarc_block_step` with GTCF's numbers after it); returns
    u [V], |u| ≤ u_lim.

    Args:
        y [m], x_d [m], xd_dot [m/s], xd_ddot [m/s²]: axis i's measurement and desired sample.
        xf, vf, af, t: the desired sample at t + τ and the time [s], for a compensation
            (:func:`motorctl.control.dcdiarc.dcdiarc_comp_step`; unused without one).
        y_j [m], x_dj [m], xd_dot_j [m/s]: the partner's of the same cycle.
        coupled: the partner runs GTCF (its block Fj, Lj holds its k1, k_s, Ts); False: C2 alone.
        sig (N_SIGNALS,): axis i's published signals.
    The partner's p_j = (y_j − y_j[k−1])/Ts − ẋ_dj + k1_j (y_j − x_dj), with y_j[k−1] kept in
    this block (so neither axis depends on which of the two the cycle runs first); a NaN p_j (the
    first sample, an IDLE partner) gives v_fb = 0. Axis i's own p is computed with the same
    operations as the C2 step's (the 2013 paper's eq. 11).
    """
    g = L[B_SPAN] + L[B_N]
    st = L[B_ST]
    prm = L[B_PRM]
    y_jp = F[g + G_YJ]
    F[g + G_YJ] = y_j
    v_fb = 0.0
    e_n = np.nan
    if coupled:
        pj_ = Lj[B_PRM]
        p_j = ((y_j - y_jp) / Fj[pj_ + P_TS] - xd_dot_j) + Fj[pj_ + P_K1] * (y_j - x_dj)
        if p_j == p_j and abs(p_j) < math.inf:
            p_i = ((y - F[st + S_Y_PREV]) / F[prm + P_TS] - xd_dot) + F[prm + P_K1] * (y - x_d)
            gj = Lj[B_SPAN] + Lj[B_N]
            s = math.sqrt(xd_dot * xd_dot + xd_dot_j * xd_dot_j)
            dp_i = 0.0
            if s > 0.0:   # ε_n = n·e with n = t rotated +90° in (i, j) order
                e_n = (xd_dot * (y_j - x_dj) - xd_dot_j * (y - x_d)) / s
                w = min(1.0, s / F[g + G_VMIN])
                # the contour error's own gain, each axis's λ_n and band (n_i = −t_j, n_j = t_i)
                dp_i = _contour_dp(F[g + G_LN], F[g + G_LB], F[prm + P_K1], -xd_dot_j / s, w, e_n)
                p_j += _contour_dp(Fj[gj + G_LN], Fj[gj + G_LB], Fj[pj_ + P_K1], xd_dot / s, w, e_n)
            v_fb = gtcf_feedback(p_i + dp_i, p_j, xd_dot, xd_dot_j, F[prm + P_KS], Fj[pj_ + P_KS], F[g + G_GT],
                                 F[g + G_GN], Fj[gj + G_GN], F[g + G_VMIN]) - F[prm + P_KS] * dp_i
            if F[g + G_ALPHA] < 1.0:                     # the low-pass (module docstring)
                v_fb = F[g + G_VFB] + F[g + G_ALPHA] * (v_fb - F[g + G_VFB])
    F[g + G_VFB] = v_fb
    F[g + G_EN] = e_n
    if F[g + G_COMP] != 0.0:
        return dcdiarc_comp_step(y, x_d, xd_dot, xd_ddot, xf, vf, af, t, sig, F, I, L, v_fb)
    return dcdiarc_block_step(y, x_d, xd_dot, xd_ddot, x_d, xd_dot, xd_ddot, 0.0, 1.0, 1.0, sig, F, I, L, v_fb)


@njit
def gtcf_reset(y0, F, L):
    """Restart the block from y0 [m] as C2 does (:func:`dcdiarc_block_reset`); the partner's
    y[k−1] forgotten (the first sample after is C2 alone)."""
    dcdiarc_block_reset(y0, F, L)
    g = L[B_SPAN] + L[B_N]
    F[g + G_YJ] = np.nan
    F[g + G_VFB] = 0.0


class GTCF(DCDIARC):
    """One axis of the GTCF pair (module docstring): C2 of the axis's section with the robust
    feedback set in the task frame of the axis and its ``partner``.

    Args:
        config: the axis's ``controller:`` section; it configures C2 (the per-axis law: k_s, k1,
            γ_d, θ box, Γ(0), ...) and ``gtcf:`` (:class:`GtcfConfig`).
        ts: sample period [s].
    Raises:
        ValueError: the section does not configure C2 or gtcf, C2 in theory mode.
    The partner's index is set by the servo loop (:meth:`link_axes`) before the law is attached;
    :meth:`update` from Python (no partner there) is C2 alone. The section's compensation is C2's
    (compiled: :func:`dcdiarc_comp_step` under the task-frame feedback); one with a term that has
    no compiled kernel makes the law run from Python (LAW_PY) as C2 alone, uncoupled.
    """

    name = "gtcf"
    Settings = GtcfConfig
    shared_keys = False
    records = ("v", "e", "p", "x2", "theta_hat1", "theta_hat2", "theta_hat3", "theta_hat4",
               "theta_hat5", "theta_hat6", "d_hat0")
    tuned_keys = ()

    def __init__(self, config: ControllerConfig, ts: float, kind: str = "c2"):
        problems = self.check(config.settings("gtcf"), config)
        if problems:
            raise ValueError("gtcf: " + "; ".join(f"{k}: {why}" for k, why in problems))
        super().__init__(config, ts, "c2")
        self.name = "gtcf"
        self.gtcf = config.settings("gtcf")
        self.partner_name = self.gtcf.partner
        g = np.zeros(N_G)
        g[G_PARTNER] = -1.0
        g[G_GT], g[G_GN], g[G_VMIN] = self.gtcf.gain_t, self.gtcf.gain_n, self.gtcf.v_min
        g[G_YJ] = np.nan
        g[G_LN] = self.gtcf.lambda_n
        g[G_LB] = self.gtcf.lambda_band
        g[G_COMP] = 1.0 if self._compiled_comp else 0.0
        try:
            g[G_ALPHA] = lowpass_alpha(self.gtcf.lowpass_hz, ts)
        except ValueError as exc:
            raise ValueError(f"gtcf: lowpass_hz: {exc}") from None
        self._span = np.concatenate([self._span, g])        # GTCF's numbers after the span (module comment)
        self._bind()
        # compile (or load) the step now, on copies, so that the first cycle never pays for it
        gtcf_step(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, True, self.signals.copy(), self._F.copy(),
                  self._I.copy(), self._L, self._F.copy(), self._L)
        gtcf_reset(0.0, self._F.copy(), self._L)

    @classmethod
    def from_config(cls, section: ControllerConfig, ts: float) -> "GTCF":
        return cls(section, ts)

    @classmethod
    def check(cls, settings: GtcfConfig, section: ControllerConfig) -> list[tuple[str, str]]:
        """C2 configured in experiment mode (the task-frame gains scale its constant k_s), C2's own
        checks (Γ(0), Assumption 2)."""
        if not section.configures("c2"):
            return [("gtcf", "gtcf runs C2 per axis: configure C2's keys (k_s, k1, gamma0, ...) in the section")]
        c2 = section.settings("c2")
        out = list(DCDIARC.check(c2, section))
        if c2.mode != "experiment":
            out.append(("mode", "gtcf needs C2's experiment mode (constant k_s scaled by gain_t, gain_n)"))
        return out

    @classmethod
    def gain_family(cls, theta1, settings, omegas, zetas=None):
        """None: autotune tunes C2 per axis (whose k_s, k1, γ_d GTCF uses); the pair's gain_t, gain_n
        are chosen after both axes by :mod:`motorctl.commission.gtcf_tune` (C2's rule)."""
        return []

    @classmethod
    def scaled(cls, gains, s):
        raise NotImplementedError("controller 'gtcf' has no loop-gain knob (tune c2)")

    @classmethod
    def linearise(cls, gains, ts, w, theta_hat=None, u0=0.0):
        """One axis's loop at a task-frame gain g on its own term (a point of the span the axis
        passes through as the path turns, g_t to its g_n; the partner's cross term left out):
        C2's linearisation (:meth:`motorctl.control.dcdiarc.DCDIARC.linearise`) with k_s replaced
        by k_s (1 + (g − 1) F(z)), F(z) = α / (1 − (1 − α) z⁻¹) the low-pass of ``lowpass_hz``
        (F = 1 without), plus the contour error's own term F(z) k_s g (λ_n − 1) k1 / f_u'(u0).
        ``gains``: C2's {"k_s", "k1", "gamma_d"} and "g", "lowpass_hz" (None: none), "lambda_n"
        (default 1). w (K,) [rad/s] -> complex (K,). Raises ValueError as :func:`lowpass_alpha`."""
        from motorctl.control.dcdiarc import C2
        a = lowpass_alpha(gains.get("lowpass_hz"), ts)
        z1 = np.exp(-1j * np.asarray(w) * ts)
        F = a / (1.0 - (1.0 - a) * z1)
        g = float(gains.get("g", 1.0))
        k_s = gains["k_s"] * (1.0 + (g - 1.0) * F)
        extra = gains["k_s"] * g * (float(gains.get("lambda_n", 1.0)) - 1.0) * gains["k1"] * F
        return C2.linearise(dict(gains, k_s=k_s), ts, w, theta_hat, u0) + extra / C2.inversion_slope(theta_hat, u0)

    @classmethod
    def check_axes(cls, axis, settings: GtcfConfig, sections, period_s: float) -> list[tuple[str, str]]:
        """A partner that configures GTCF naming this axis gives the same ``gain_t`` (the pair's
        tangential gain; each axis its own ``gain_n``); ``lowpass_hz`` below the Nyquist
        frequency of ``period_s``. (A partner that is not an axis of the run is refused when the
        loop is built; one on another law makes this axis's step C2 alone.)"""
        out = []
        other = sections.get(settings.partner)
        if other is not None and other.configures("gtcf"):
            o = other.settings("gtcf")
            if o.partner == axis and o.gain_t != settings.gain_t:
                out.append(("gtcf.gain_t", f"{settings.gain_t:g} differs from axis {settings.partner}'s "
                            f"{o.gain_t:g} (the tangential gain is the pair's: give both the same)"))
        try:
            lowpass_alpha(settings.lowpass_hz, period_s)
        except ValueError as exc:
            out.append(("gtcf.lowpass_hz", str(exc)))
        return out

    @property
    def law_code(self) -> int:
        """LAW_GTCF: the cycle runs :func:`gtcf_step` with the partner's sample; LAW_PY (C2 alone,
        from Python) with a compensation term that has no compiled kernel."""
        if self.compensation is not None and not self._compiled_comp:
            return LAW_PY
        return LAW_GTCF

    def link_axes(self, axis_names, i: int) -> None:
        """Set the partner's index from the loop's axis names (called by the servo loop before
        :meth:`attach`, between cycles). Raises ValueError: the partner is not one of the loop's
        axes or is this axis ``axis_names[i]``."""
        names = list(axis_names)
        if self.partner_name not in names or names.index(self.partner_name) == i:
            raise ValueError(f"gtcf on axis {names[i]!r}: partner {self.partner_name!r} must be another axis of "
                             f"this loop ({', '.join(names)})")
        j = names.index(self.partner_name)
        self._F[self._g0() + G_PARTNER] = float(j)

    def _g0(self) -> int:
        """Where GTCF's numbers start in the block (module comment)."""
        return int(self._L[B_SPAN] + self._L[B_N])

    def reset(self, y0: float, keep_theta: bool = True) -> None:
        super().reset(y0, keep_theta)
        self._F[self._g0() + G_YJ] = np.nan

    @property
    def v_fb(self) -> float:
        """The last sample's task-frame feedback beyond C2's −k_s p [V]."""
        return float(self._F[self._g0() + G_VFB])

    @property
    def e_n(self) -> float:
        """The last sample's normal (contour) error ε_n [m] (NaN: uncoupled)."""
        return float(self._F[self._g0() + G_EN])

