"""LinuxCNC's ``pid`` HAL component (P, I, D with FF0, FF1, FF2, bias and limits) as a controller.

Source of the semantics: LinuxCNC ``src/hal/components/pid.c`` and its manual page pid(9)
(the code is not copied; the per-period calculation is restated here in this project's units
and names). Per sample k, with Ts the sample period::

    ε    = x_d − y                        LinuxCNC ``error`` = command − feedback   [m]
    ε    ← clip(ε, ±maxerror)             (maxerror > 0)
    ε    ← 0            if |ε| ≤ deadband
           ε ∓ deadband otherwise         (the error is reduced by the deadband)
    εI  += ε Ts         only if ε·s ≤ 0, s = +1/−1 when the last output was clamped high/low,
                        else 0 (anti-windup: no integration further into the limit)
    εI   ← clip(εI, ±maxerror_i)          (maxerror_i > 0)
    x2   = (y[k] − y[k−1]) / Ts           feedback derivative (LinuxCNC feedback-deriv)
    εD   = ẋ_d − x2                       command-deriv − feedback-deriv (LinuxCNC ≥ 2.7)
    v    = bias + P ε + I εI + D εD + FF0 x_d + FF1 ẋ_d + FF2 ẍ_d
    u    = clip(v, ±u_max),  u_max = min(maxoutput, u_lim) (maxoutput = 0: u_lim)

Published signals (:data:`motorctl.control.signals.CONTROLLER_SIGNALS`): ``v`` [V] (before the
clamp), ``e = y − x_d = −error`` [m] (raw, before maxerror and deadband), ``p = ė = x2 − ẋ_d``
[m/s] (the error derivative in this project's sign, = −εD), ``x2`` [m/s]; θ̂1..θ̂6 and d̂0 are
NaN (a fixed-gain law, n_theta = 0).

Deviations from LinuxCNC, all deliberate:

* FF1 and FF2 use the trajectory's analytic velocity ẋ_d and acceleration ẍ_d instead of
  differencing the command (LinuxCNC's ``command-deriv`` pin wired to the planner's velocity;
  LinuxCNC differences command-deriv for FF2, we use ẍ_d). The D term uses ẋ_d the same way.
* the error is ``command − feedback`` of the same sample (``error-previous-target`` = 0): the
  loop reads y[k] and samples x_d(k Ts) at the same instant.
* the output is always clamped (to u_lim when maxoutput = 0, where LinuxCNC has no limit), so
  the anti-windup acts on that clamp too. maxerrorD, maxcmdD, maxcmdDD and index-enable are
  not offered (no field in :class:`PidConfig`).
"""

from __future__ import annotations

import numpy as np

from motorctl.control.base import LAW_PID, SIG_E, SIG_P, SIG_V, SIG_X2, Controller
from motorctl.control.params import ControllerConfig
from motorctl.jit import njit
from motorctl.schema import StrictModel, quantity

__all__ = ["PID", "PidConfig", "pid_reset", "pid_step"]


class PidConfig(StrictModel):
    """LinuxCNC ``pid`` gains and limits (hal/components/pid.c, manual page pid(9)), in SI
    units: the ``pid:`` mapping of an axis's ``controller:`` section.

    LinuxCNC's error = command − feedback = x_d − y (the opposite sign of the published
    tracking error e = y − x_d); the output u [V] pushes +x. A gain of 0 (or a limit of 0)
    switches that term (or that limit) off, as in LinuxCNC. Unlike LinuxCNC, FF1 and FF2 (and
    the command part of the D term) use the trajectory's analytic ẋ_d and ẍ_d.

    Attributes:
        P [V/m], I [V/(m s)], D [V s/m]: feedback gains on the error, its integral and its
            derivative (ẋ_d − ẏ); ≥ 0.
        FF0 [V/m], FF1 [V s/m], FF2 [V s²/m]: feedforward of the command x_d, its velocity ẋ_d
            and its acceleration ẍ_d (for this plant FF1 ≈ θ2, FF2 ≈ θ1 of the model, eq. 4).
        bias [V]: constant output offset (≈ −θ4).
        deadband [m]: |error| ≤ deadband counts as 0; above it the error is reduced by it. ≥ 0.
        maxerror [m]: the error is clipped to ±maxerror before the deadband (0 = none).
        maxerror_i [m s]: the integral of the error is clipped to ±maxerror_i (0 = none).
        maxoutput [V]: output limit; the output is clipped to ±min(maxoutput, u_lim)
            (0 = u_lim of the section).
    """

    P: quantity(0.0, 1e10, "V/m") = 0.0
    I: quantity(0.0, 1e12, "V/(m s)") = 0.0
    D: quantity(0.0, 1e8, "V s/m") = 0.0
    FF0: quantity(-1e10, 1e10, "V/m") = 0.0
    FF1: quantity(-1e8, 1e8, "V s/m") = 0.0
    FF2: quantity(-1e6, 1e6, "V s^2/m") = 0.0
    bias: quantity(-1e3, 1e3, "V") = 0.0
    deadband: quantity(0.0, 1.0, "m") = 0.0
    maxerror: quantity(0.0, 100.0, "m") = 0.0
    maxerror_i: quantity(0.0, 1e4, "m s") = 0.0
    maxoutput: quantity(0.0, 1e3, "V") = 0.0

# state vector (what the next sample needs, and the last sample's values)
S_Y_PREV, S_EI, S_LIMIT, S_U, S_V, S_ERR, S_ED, S_X2 = range(8)
# parameter vector
(P_TS, P_P, P_I, P_D, P_FF0, P_FF1, P_FF2, P_BIAS, P_DB, P_MAXE, P_MAXEI, P_UMAX) = range(12)
N_STATE, N_PRM = 8, 12


@njit
def pid_step(y, x_d, xd_dot, xd_ddot, sig, st, prm):
    """One period of LinuxCNC's pid calculation (module docstring); returns u [V].

    Args:
        y [m], x_d [m], xd_dot [m/s], xd_ddot [m/s²]: feedback and command with its analytic
            derivatives.
        sig (N_SIGNALS,) float64: the published signals; v, e, p, x2 written here.
        st (8,) float64: state (S_* indices), updated in place.
        prm (12,) float64: Ts [s], P, I, D, FF0, FF1, FF2, bias, deadband, maxerror,
            maxerror_i, u_max (P_* indices); a limit of 0 means none (u_max > 0 always).
    """
    ts = prm[P_TS]
    err = x_d - y                          # LinuxCNC error = command − feedback
    t = err
    maxe = prm[P_MAXE]
    if maxe > 0.0:
        if t > maxe:
            t = maxe
        elif t < -maxe:
            t = -maxe
    db = prm[P_DB]
    if t > db:
        t -= db
    elif t < -db:
        t += db
    else:
        t = 0.0
    ei = st[S_EI]
    if t * st[S_LIMIT] <= 0.0:             # not integrating further into the output limit
        ei += t * ts
    maxei = prm[P_MAXEI]
    if maxei > 0.0:
        if ei > maxei:
            ei = maxei
        elif ei < -maxei:
            ei = -maxei
    x2 = (y - st[S_Y_PREV]) / ts
    ed = xd_dot - x2                       # command-deriv − feedback-deriv
    v = (prm[P_BIAS] + prm[P_P] * t + prm[P_I] * ei + prm[P_D] * ed
         + prm[P_FF0] * x_d + prm[P_FF1] * xd_dot + prm[P_FF2] * xd_ddot)
    umax = prm[P_UMAX]
    if v > umax:
        u = umax
        lim = 1.0
    elif v < -umax:
        u = -umax
        lim = -1.0
    else:
        u = v
        lim = 0.0
    st[S_Y_PREV] = y
    st[S_EI] = ei
    st[S_LIMIT] = lim
    st[S_U] = u
    st[S_V] = v
    st[S_ERR] = err
    st[S_ED] = ed
    st[S_X2] = x2
    sig[SIG_V] = v
    sig[SIG_E] = -err
    sig[SIG_P] = -ed
    sig[SIG_X2] = x2
    return u


@njit
def pid_reset(y0, st):
    """Bumpless (re)start of the state st (N_STATE,) from the measured position y0 [m]:
    integrator 0, not in the limit, previous feedback y0, u = 0 (:meth:`PID.reset`)."""
    for j in range(N_STATE):
        st[j] = 0.0
    st[S_Y_PREV] = y0


class PID(Controller):
    """LinuxCNC's ``pid`` for one axis, with feedforward. Call :meth:`update` once per sample.

    Args:
        gains: the axis's :class:`PidConfig` (SI units; 0 switches a term or limit off).
        ts: sample period Ts [s] (> 0).
        u_lim: the section's output limit [V] (> 0); |u| ≤ min(maxoutput or u_lim, u_lim).
    Attributes (of the last sample): u, v [V], e [m] (y − x_d), p [m/s] (ė), x2 [m/s],
        error_i [m s] (the integrator εI), saturated (bool); signals (N_SIGNALS,) as in
        :class:`motorctl.control.base.Controller`, θ̂ and d̂0 entries NaN; theta_hat shape (0,).
    Raises:
        ValueError: ts or u_lim not > 0.
    """

    name = "pid"
    Settings = PidConfig
    tuned_keys = ("P", "I", "D", "maxerror_i")
    #: autotune's family: damping ζ and integral corner ratio r (I = P ω / r) of the
    #: pole-placement design P = θ1 ω², D = 2 ζ ω θ1
    ZETA = (0.3, 0.4, 0.5, 0.7, 1.0)
    R_INT = (3.0, 5.0, 7.0, 10.0, 15.0, 20.0, 30.0, 50.0)   # 30, 50: with the friction in the
    # feedforward the integrator has little left to do (the floor-constrained search's best Y PID: r ≈ 46)

    def __init__(self, gains: PidConfig, ts: float, u_lim: float):
        if not ts > 0.0 or not u_lim > 0.0:
            raise ValueError(f"PID needs ts > 0 and u_lim > 0, got ts={ts!r}, u_lim={u_lim!r}")
        super().__init__(ts, u_lim, 0)
        self.gains = gains
        g = gains
        self.u_max = min(g.maxoutput, float(u_lim)) if g.maxoutput > 0.0 else float(u_lim)
        self._prm = np.array([ts, g.P, g.I, g.D, g.FF0, g.FF1, g.FF2, g.bias, g.deadband,
                              g.maxerror, g.maxerror_i, self.u_max], dtype=float)
        self._st = np.zeros(N_STATE)
        self._started = False
        # compile (or load the cached machine code) now, on copies, so the first cycle does not
        pid_step(0.0, 0.0, 0.0, 0.0, self.signals.copy(), self._st.copy(), self._prm)
        pid_reset(0.0, self._st.copy())
        self._attached = False

    @classmethod
    def from_config(cls, section: ControllerConfig, ts: float) -> PID:
        """From an axis's ``controller:`` section: its ``pid`` gains and ``u_lim``.

        Raises:
            ValueError: the section has no ``pid:`` key.
        """
        return cls(section.settings("pid"), ts, section.u_lim)

    @classmethod
    def linearise(cls, gains, ts, w, theta_hat=None, u0=0.0):
        """C(z) = P + I Ts/(1 − z⁻¹) + D (1 − z⁻¹)/Ts at z = e^{jωTs} (the feedforward acts on
        x_d only and the limits are inactive at small signals). w (K,) [rad/s] -> complex (K,)."""
        z1 = np.exp(-1j * np.asarray(w) * ts)
        return gains["P"] + gains["I"] * ts / (1.0 - z1) + gains["D"] * (1.0 - z1) / ts

    @classmethod
    def gain_family(cls, theta1, settings, omegas, zetas=None):
        """P = θ1 ω², D = 2 ζ ω θ1, I = P ω / r for ω in ``omegas`` [rad/s], ζ in ``zetas``
        (None: :attr:`ZETA`), r in :attr:`R_INT`; the integral clamp maxerror_i = 1 V / I."""
        out = []
        for w in omegas:
            for z in (zetas or cls.ZETA):
                for r in cls.R_INT:
                    p = theta1 * w * w
                    out.append({"P": p, "I": p * w / r, "D": 2.0 * z * w * theta1,
                                "maxerror_i": r / (p * w), "_w": w, "_zeta": z, "_r": r})
        return out

    @classmethod
    def model_settings(cls, theta):
        """The feedforward from θ (6,) (eq. 4): FF1 = θ2, FF2 = θ1, bias = −θ4, FF0 = 0."""
        return {"FF0": 0.0, "FF1": float(theta[1]), "FF2": float(theta[0]), "bias": -float(theta[3])}

    @classmethod
    def scaled(cls, gains, s):
        """P, I, D × s (the integral clamp keeps 1 V of I·ε_I)."""
        g = dict(gains)
        for k in ("P", "I", "D"):
            g[k] = g[k] * s
        if g.get("I", 0.0) > 0.0:
            g["maxerror_i"] = 1.0 / g["I"]
        return g

    def reset(self, y0: float) -> None:
        """Bumpless (re)start from the measured position y0 [m]: integrator 0, not in the
        limit, previous feedback y0 (so the first feedback derivative is 0), u = 0."""
        pid_reset(y0, self._st)
        self._started = True

    @property
    def law_code(self) -> int:
        """LAW_PID: the cycle runs :func:`pid_step` on the rows it keeps (:meth:`attach`)."""
        return LAW_PID

    def state_size(self) -> tuple[int, int]:
        return N_STATE + N_PRM, 0

    def attach(self, sig, f, ii, lay) -> None:
        """State and parameters into the cycle's float row (f[:N_STATE], then N_PRM), the
        signals into its row (:meth:`Controller.attach`)."""
        sig[:] = self.signals
        f[:N_STATE] = self._st
        f[N_STATE:N_STATE + N_PRM] = self._prm
        lay[:] = 0
        self.signals, self._st, self._prm = sig, f[:N_STATE], f[N_STATE:N_STATE + N_PRM]
        self._attached = True

    def detach(self) -> None:
        if self._attached:
            self._attached = False
            self.signals, self._st, self._prm = self.signals.copy(), self._st.copy(), self._prm.copy()

    def update(self, y: float, x_d: float, xd_dot: float, xd_ddot: float, t: float = 0.0) -> float:
        """One sample. Returns u [V], |u| ≤ u_max; fills :attr:`signals` (v, e, p, x2).

        Args:
            y: measured position [m]. x_d, xd_dot, xd_ddot: desired position [m], velocity
            [m/s], acceleration [m/s²] (analytic, used for FF1, FF2 and the D term).
            t: time [s] (unused; the law is time-invariant).
        """
        if not self._started:
            self.reset(y)
        return pid_step(y, x_d, xd_dot, xd_ddot, self.signals, self._st, self._prm)

    # outputs of the last sample (float reads of the state vector)
    u = property(lambda self: float(self._st[S_U]))
    v = property(lambda self: float(self._st[S_V]))
    p = property(lambda self: -float(self._st[S_ED]))
    x2 = property(lambda self: float(self._st[S_X2]))
    error_i = property(lambda self: float(self._st[S_EI]))
    saturated = property(lambda self: self._st[S_LIMIT] != 0.0)
