"""Periodic friction along the stroke: a Coulomb level that repeats with position (a ball screw's
or a rail's waviness, rollers recirculating in a linear guide carriage at the ball pitch).

Physical model (the paper's smooth sign S_f(ẋ) = (2/π) atan(900 ẋ), eq. 1):

    F_eff(x, ẋ) = −Σ_k A_k sin(2π k x / P + φ_k) S_f(ẋ)                                    [N]

Unlike cogging it changes sign with the direction of motion. Identification: columns
sin, cos(2π k x / P)·S_f(ẋ), k ≤ :data:`~motorctl.effects.periodic.N_HARMONICS`; P from the
spatial periodogram of the residual times sign(ẋ) (moving samples), refined by the joint fit
(:class:`~motorctl.effects.periodic.PositionPeriodic`); plausible only when fitted alike on each
direction of motion (the columns carry S_f, so a friction gives the same β both ways, a cogging
force opposite ones) and when the friction level θ3 + g(x) stays positive. Compensation (eq. 13): d̂_eff(x_d, ẋ_d) = Σ_k (a_k sin + b_k cos)(2π k x_d
/ P)·S_f(ẋ_d) [V]; adaptable (β = sin_V then cos_V, P fixed).
"""

from __future__ import annotations

import math
from typing import ClassVar

import numpy as np
from pydantic import Field

from motorctl.effects.base import CompTerm, PlantTerm
from motorctl.effects.periodic import (
    N_HARMONICS,
    FourierAdaptable,
    PositionPeriodic,
    amplitudes_phases,
    fourier,
    fourier_add,
    fourier_basis,
    fourier_fill,
    friction_force,
    fourier_term,
    harmonics,
    sin_cos_of,
)
from motorctl.jit import njit
from motorctl.model import s_f
from motorctl.schema import Pos, StrictModel

@njit
def comp_add(d, x, v, t, sf, p):
    """d + g(x_d) S_f(ẋ_d) [V], g the Fourier sum of :func:`~motorctl.effects.periodic.fourier_add`
    on x_d with its row p."""
    return d + fourier_add(0.0, x, v, t, sf, p) * sf


@njit
def comp_fill(out, j, x, v, t, sf, p):
    """The adapted columns of :func:`~motorctl.effects.periodic.fourier_fill` (its row p) times
    S_f(ẋ)."""
    fourier_fill(out, j, x, v, t, sf, p)
    for i in range(j, j + 2 * int(p[1])):
        out[i] *= sf

class PeriodicFriction(StrictModel):
    """Simulated periodic friction, ``axes.NAME.driver.effects.periodic_friction``:
    −Σ_k A_k sin(2π k x / P + φ_k) S_f(ẋ) [N]. amplitudes_N: A_k [N] (k = 1.., at least one).
    period_m: P [m]. phases_rad: φ_k [rad] (missing ones are 0)."""

    amplitudes_N: list[float] = Field(min_length=1)
    period_m: Pos
    phases_rad: list[float] = []


class PeriodicFrictionComp(FourierAdaptable):
    """Periodic friction compensation, ``axes.NAME.controller.compensation.periodic_friction``:
    Σ_k (a_k sin + b_k cos)(2π k x / P)·S_f(ẋ) [V] (force / A1); the shorter list is padded with
    zeros. Adaptable (:class:`~motorctl.effects.base.Adaptable`): β = sin_V then cos_V, P fixed."""

    period_m: Pos
    sin_V: list[float] = []
    cos_V: list[float] = []


class PeriodicFrictionFamily(PositionPeriodic):
    name = "periodic_friction"
    size_parameters = ("amplitudes_",)
    search_cost = 0.009
    kernels = (("force", friction_force), ("add", comp_add), ("fill", comp_fill))
    plant_force = "−Σ A_k sin(2πkx/P + φ_k) S_f(ẋ)"
    sim_options = PeriodicFriction
    example: ClassVar[dict] = {"periodic_friction": {"amplitudes_N": [8.0], "period_m": 0.05, "phases_rad": [0.5]}}
    comp_options = PeriodicFrictionComp
    comp_needs_sf = True

    # simulator
    def plant_term(self, o: PeriodicFriction, period_s):
        ph = list(o.phases_rad) + [0.0] * len(o.amplitudes_N)
        row = []
        for k, a in enumerate(o.amplitudes_N):
            row += [a, 2 * math.pi * (k + 1) / o.period_m, ph[k]]
        return PlantTerm.compiled("force", friction_force, row)

    # identification
    def columns(self, h, p):
        """sin, cos(2π k x / h)·S_f(ẋ) interleaved, (N, 2·N_HARMONICS); h: period P [m]."""
        return fourier(p.x, h, N_HARMONICS, scale=s_f(p.v), single=p.columns_single)

    def peak_data(self, ctx, residual):
        mv = ctx.moving
        return ctx.p.x_d[mv], residual[mv] * np.sign(ctx.p.v_d[mv])

    def plausible(self, ctx, term, beta, theta, base):
        out = super().plausible(ctx, term, beta, theta, base)
        # the friction level θ3 + g(x) stays positive (g's peak bounded by the sum of amplitudes)
        peak = float(np.sum(np.hypot(beta[0::2], beta[1::2])))
        if peak >= theta[2]:
            out.append(f"friction level would turn negative along the stroke (variation {peak:.3g} V >= "
                       f"Coulomb level theta3 {theta[2]:.3g} V)")
        return out

    def parameters(self, h, beta, gain, fs):
        g, unit = (gain, "N") if gain else (1.0, "V")
        amp, ph = amplitudes_phases(-np.asarray(beta), g)   # of g(x), F_eff = −g(x) S_f(ẋ)
        return {"period_m": float(h), f"amplitudes_{unit}": [float(a) for a in amp],
                "phases_rad": [float(p) for p in ph]}

    # compensation
    def compensation(self, h, beta, signals=None, beta_std=None):
        std = None if beta_std is None else list(beta_std[0::2]) + list(beta_std[1::2])
        return self.adapt_entry({"period_m": float(h), "sin_V": [float(-b) for b in beta[0::2]],
                                 "cos_V": [float(-b) for b in beta[1::2]]}, std)

    def compensation_for(self, o: PeriodicFriction, a1):
        ph = list(o.phases_rad) + [0.0] * len(o.amplitudes_N)
        sc = [sin_cos_of(-a / a1, ph[k]) for k, a in enumerate(o.amplitudes_N)]
        return {"period_m": o.period_m, "sin_V": [s for s, _ in sc], "cos_V": [c for _, c in sc]}

    def compensator(self, o: PeriodicFrictionComp):
        g = fourier_term(harmonics(2.0 * math.pi / o.period_m, o.sin_V, o.cos_V), on_time=False)
        return CompTerm("add", comp_add, g.params)

    def adapt_basis(self, o: PeriodicFrictionComp):
        g = fourier_basis(2.0 * math.pi / o.period_m, len(o.beta()) // 2, on_time=False)
        return CompTerm("fill", comp_fill, g.params)

    # report
    def shape(self, ctx, h, beta, gain):
        xs = self.position_grid(ctx, h)
        # the Coulomb-level change g(x) in forward motion (S_f = 1)
        y = -(gain or 1.0) * (fourier(xs, h, N_HARMONICS) @ beta)
        return xs, y, "position [m]", "friction level change [UNIT]"


FAMILY = PeriodicFrictionFamily()
