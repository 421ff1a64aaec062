"""Force ripple: a position-periodic fraction of the thrust (the force constant varies with the
magnet pitch), same in both directions of motion.

Physical model:

    F_eff(x, u) = F_m(u) · Σ_k r_k sin(2π k x / P + φ_k)                            [N]

with F_m(u) = A1 u + A2 u|u| + A3 u³ (paper eq. 3); the plant applies it as the factor
(1 + Σ r_k sin(·)) on F_m. Identification: columns f_u(u)·sin, f_u(u)·cos(2π k x / P) (f_u: the
nominal thrust shape of eq. 9 once θ5, θ6 are fitted, else u). Compensation (not an additive
d̂_eff, a :class:`~motorctl.effects.base.CompHook`): the law divides its virtual input v by
1 + r̂(x_d) before the inversion (eq. 9), r̂(x) = Σ_k a_k sin(2π k x / P) + b_k cos(2π k x / P),
and the estimator's thrust channels are scaled by 1 + r̂(x) at the measured position.
"""

from __future__ import annotations

import math
from typing import ClassVar

import numpy as np
from pydantic import Field, model_validator

from motorctl.effects.base import CompHook, PlantTerm, Signals
from motorctl.effects.periodic import N_HARMONICS, PositionPeriodic, fourier, fourier_add, fourier_term, harmonics, sin_cos_of
from motorctl.jit import njit
from motorctl.schema import Pos, StrictModel

#: Largest plausible ripple fraction r_k.
MAX_FRACTION = 0.3


@njit
def plant_thrust(fm, x, t, p):
    """The thrust [N] at position x [m] (t unused): fm (1 + Σ_k r_k sin(w_k x + φ_k)); the row
    p = (r_1 [-], w_1 [rad/m], φ_1 [rad], r_2, w_2, φ_2, ...) of :meth:`ForceRippleFamily.plant_term`."""
    r = 0.0
    for j in range(0, p.shape[0], 3):
        r += p[j] * math.sin(p[j + 1] * x + p[j + 2])
    return fm * (1.0 + r)


class ForceRipple(StrictModel):
    """Simulated ripple, ``axes.NAME.driver.effects.force_ripple``: the thrust times
    (1 + Σ_k r_k sin(2π k x / P + φ_k)).

    fractions: r_k [-] (at least one). period_m: P [m]. phases_rad: φ_k [rad] (missing: 0).
    """

    fractions: list[float] = Field(min_length=1)
    period_m: Pos
    phases_rad: list[float] = []


class RippleComp(StrictModel):
    """Ripple compensation, ``axes.NAME.controller.compensation.force_ripple``: the thrust
    fraction r̂(x) = Σ_k a_k sin(2π k x / P) + b_k cos(2π k x / P) [-]; v is divided by
    1 + r̂(x_d) before the inversion (eq. 9). period_m: P [m]. sin, cos: a_k, b_k [-] (the
    shorter list padded with zeros; |Σ| < 0.5 checked by the family's plausibility, not here)."""

    period_m: Pos
    sin: list[float] = []
    cos: list[float] = []

    @model_validator(mode="after")
    def _bounded(self):
        if sum(abs(v) for v in self.sin) + sum(abs(v) for v in self.cos) >= 0.5:
            raise ValueError("sin, cos: the ripple fractions must add up to less than 0.5 "
                             "(1 + r(x) must stay well above 0)")
        return self


class ForceRippleFamily(PositionPeriodic):
    name = "force_ripple"
    size_parameters = ("fractions",)
    search_cost = 0.072
    kernels = (("thrust", plant_thrust), ("add", fourier_add))
    plant_force = "F_m(u)·Σ r_k sin(2πkx/P + φ_k)"
    columns_on_thrust_shape = True
    sim_options = ForceRipple
    example: ClassVar[dict] = {"force_ripple": {"fractions": [0.06], "period_m": 0.045, "phases_rad": [0.5]}}
    #: an encoder's interpolation error at the same period, seen only where the moves end
    look_alike: ClassVar[tuple[str, ...]] = ("encoder_interpolation",)
    size_options: ClassVar[tuple[str, ...]] = ("fractions",)
    hook_options = RippleComp

    # simulator
    def plant_term(self, o: ForceRipple, period_s):
        ph = list(o.phases_rad) + [0.0] * len(o.fractions)
        row = []
        for k, r in enumerate(o.fractions):
            row += [r, 2 * math.pi * (k + 1) / o.period_m, ph[k]]
        return PlantTerm.compiled("thrust", plant_thrust, row)

    # identification
    def columns(self, h, p):
        """f_u(u)·sin, f_u(u)·cos(2π k x / h) interleaved, (N, 2·N_HARMONICS); h: period P [m]."""
        fu = getattr(p, "fu", None)
        return fourier(p.x, h, N_HARMONICS, scale=fu if fu is not None else p.u, single=p.columns_single)

    def peak_data(self, ctx, residual):
        p, mv = ctx.p, ctx.moving
        big = mv & (np.abs(p.u_d) > 0.3 * np.max(np.abs(p.u_d)))
        if big.sum() < 50:
            return None
        return p.x_d[big], residual[big] / p.u_d[big]

    def plausible(self, ctx, term, beta, theta, base):
        reasons = super().plausible(ctx, term, beta, theta, base)
        if np.max(np.hypot(beta[0::2], beta[1::2])) > MAX_FRACTION:
            reasons.append(f"ripple fraction above {MAX_FRACTION:g}")
        return reasons

    def parameters(self, h, beta, gain, fs):
        s, c = beta[0::2], beta[1::2]
        return {"period_m": float(h), "fractions": [float(a) for a in np.hypot(s, c)],
                "phases_rad": [float(p) for p in np.arctan2(-c, -s)]}

    # compensation (a factor on the thrust, not an additive d̂_eff)
    def compensation(self, h, beta, signals=None):
        """r̂ = −Σ (β_s sin + β_c cos): the fit's thrust is f_u(u)(1 − Cβ/f_u(u))."""
        return {"period_m": float(h), "sin": [float(-b) for b in beta[0::2]],
                "cos": [float(-b) for b in beta[1::2]]}

    def compensation_for(self, o: ForceRipple, a1):
        ph = list(o.phases_rad) + [0.0] * len(o.fractions)
        sc = [sin_cos_of(r, ph[k]) for k, r in enumerate(o.fractions)]
        return {"period_m": o.period_m, "sin": [s for s, _ in sc], "cos": [c for _, c in sc]}

    def comp_hook(self, o: RippleComp) -> CompHook:
        # r̂(x) = Σ_k a_k sin(w_k x) + b_k cos(w_k x), summed from 0
        return CompHook(thrust=fourier_term(harmonics(2.0 * math.pi / o.period_m, o.sin, o.cos), on_time=False))

    # report
    def shape(self, ctx, h, beta, gain):
        xs = self.position_grid(ctx, h)
        zero = np.zeros_like(xs)
        y = -(self.columns(h, Signals(xs, zero, zero, np.ones_like(xs), zero)) @ beta)
        return xs, y, "position [m]", "ripple fraction of the thrust [-]"


FAMILY = ForceRippleFamily()
