"""Force ripple: a position-periodic fraction of the thrust (the force constant varies with the
magnet pitch), same in both directions of motion.

Physical model:

    F_eff(x, u) = F_m(u) · Σ_k r_k sin(2π k x / P + φ_k)                            [N]

with F_m(u) = A1 u + A2 u|u| + A3 u³ (paper eq. 3); the plant applies it as the factor
(1 + Σ r_k sin(·)) on F_m. Identification: columns f_u(u)·sin, f_u(u)·cos(2π k x / P) (f_u: the
nominal thrust shape of eq. 9 once θ5, θ6 are fitted, else u). Not compensable: the term needs
u, and d̂_eff is a function of (x_d, ẋ_d, t) only.
"""

from __future__ import annotations

import math
from typing import ClassVar

import numpy as np
from pydantic import Field

from motorctl.effects.base import PlantTerm, Signals
from motorctl.effects.periodic import N_HARMONICS, PositionPeriodic, fourier
from motorctl.schema import Pos, StrictModel

#: Largest plausible ripple fraction r_k.
MAX_FRACTION = 0.3


class ForceRipple(StrictModel):
    """Simulated ripple, ``axes.NAME.driver.effects.force_ripple``: the thrust times
    (1 + Σ_k r_k sin(2π k x / P + φ_k)).

    fractions: r_k [-] (at least one). period_m: P [m]. phases_rad: φ_k [rad] (missing: 0).
    """

    fractions: list[float] = Field(min_length=1)
    period_m: Pos
    phases_rad: list[float] = []


class ForceRippleFamily(PositionPeriodic):
    name = "force_ripple"
    plant_force = "F_m(u)·Σ r_k sin(2πkx/P + φ_k)"
    sim_options = ForceRipple
    example: ClassVar[dict] = {"force_ripple": {"fractions": [0.06], "period_m": 0.045, "phases_rad": [0.5]}}

    # simulator
    def plant_term(self, o: ForceRipple, period_s):
        ph = list(o.phases_rad) + [0.0] * len(o.fractions)
        harm = tuple((r, 2 * math.pi * (k + 1) / o.period_m, ph[k]) for k, r in enumerate(o.fractions))
        sin = math.sin

        def thrust(fm, x):
            r = 0.0
            for amp, w, phi in harm:
                r += amp * sin(w * x + phi)
            return fm * (1.0 + r)
        return PlantTerm(thrust=thrust)

    # identification
    def columns(self, h, p):
        """f_u(u)·sin, f_u(u)·cos(2π k x / h) interleaved, (N, 2·N_HARMONICS); h: period P [m]."""
        fu = getattr(p, "fu", None)
        return fourier(p.x, h, N_HARMONICS, scale=fu if fu is not None else p.u)

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

    # report
    def shape(self, ctx, h, beta, gain):
        xs = self.position_grid(ctx, h)
        zero = np.zeros_like(xs)
        y = -(self.columns(h, Signals(xs, zero, zero, np.ones_like(xs), zero)) @ beta)
        return xs, y, "position [m]", "ripple fraction of the thrust [-]"


FAMILY = ForceRippleFamily()
