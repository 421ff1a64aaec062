"""Cogging (detent) force: position-periodic, independent of the thrust and of the direction.

Physical model (permanent-magnet linear motor, detent between magnets and iron core):

    F_eff(x) = Σ_k A_k sin(2π k x / P + φ_k)                                       [N]

Identification: columns sin, cos(2π k x / P), k ≤ :data:`~motorctl.effects.periodic.N_HARMONICS`
(u = Φθ + Cβ, so F_eff = −A1 Cβ); P searched on the spatial periodogram of the residual
(:class:`~motorctl.effects.periodic.PositionPeriodic`). Compensation (eq. 13, desired
compensation): d̂_eff(x_d) = Σ_k a_k sin(2π k x_d / P) + b_k cos(2π k x_d / P) [V].
"""

from __future__ import annotations

import math
from typing import ClassVar

import numpy as np
from pydantic import Field

from motorctl.effects.base import PlantTerm, Signals
from motorctl.effects.periodic import (
    N_HARMONICS,
    AmplitudeStep,
    FourierAdaptable,
    PositionPeriodic,
    amplitudes_phases,
    fourier,
    fourier_add,
    fourier_fill,
    fourier_basis,
    fourier_term,
    harmonics,
    sin_cos_of,
)
from motorctl.jit import njit
from motorctl.schema import Pos


@njit
def plant_force(f, x, v, t, sf, p):
    """f + F_eff [N] at position x [m], plant time t [s] (v, sf unused): f + Σ_k g A_k
    sin(w_k x + φ_k), g = s after plant time t_s, else 1; the row p = (t_s [s] (inf: no step),
    s [-], A_1 [N], w_1 [rad/m], φ_1 [rad], A_2, w_2, φ_2, ...) of :meth:`CoggingFamily.plant_term`."""
    g = p[1] if t >= p[0] else 1.0
    for j in range(2, p.shape[0], 3):
        f += g * p[j] * math.sin(p[j + 1] * x + p[j + 2])
    return f


class Cogging(AmplitudeStep):
    """Simulated cogging, ``axes.NAME.driver.effects.cogging``: Σ_k A_k sin(2π k x / P + φ_k) [N].

    amplitudes_N: A_k [N] (k = 1.., at least one). period_m: P [m]. phases_rad: φ_k [rad]
    (missing ones are 0). step_at_s, scale_after: a drifting amplitude (tests of adapted
    compensation): from plant time step_at_s [s] on, every A_k is multiplied by scale_after
    (both or neither; default: no step).
    """

    amplitudes_N: list[float] = Field(min_length=1)
    period_m: Pos
    phases_rad: list[float] = []


class FourierPosition(FourierAdaptable):
    """Cogging compensation, ``axes.NAME.controller.compensation.cogging``:
    Σ_k a_k sin(2π k x / P) + b_k cos(2π k x / P) [V] (force / A1); the shorter list is padded
    with zeros. Adaptable (``adapt``, ``beta_min``, ``beta_max``, ``gamma0``;
    :class:`~motorctl.effects.base.Adaptable`): β = sin_V then cos_V (padded), P fixed."""

    period_m: Pos
    sin_V: list[float] = []
    cos_V: list[float] = []


class CoggingFamily(PositionPeriodic):
    name = "cogging"
    size_parameters = ("amplitudes_",)
    search_cost = 0.076
    kernels = (("force", plant_force), ("add", fourier_add), ("fill", fourier_fill))
    plant_force = "Σ A_k sin(2πkx/P + φ_k)"
    sim_options = Cogging
    example: ClassVar[dict] = {"cogging": {"amplitudes_N": [12.0, 4.0], "period_m": 0.032, "phases_rad": [0.3, 1.0]}}
    comp_options = FourierPosition
    compensation_rank = 1
    #: an encoder's interpolation error at the same period, seen only where the moves end
    look_alike: ClassVar[tuple[str, ...]] = ("encoder_interpolation",)

    # simulator
    def plant_term(self, o: Cogging, period_s):
        ph = list(o.phases_rad) + [0.0] * len(o.amplitudes_N)
        row = [math.inf, 1.0] if o.step_at_s is None else [o.step_at_s, o.scale_after]
        for k, a in enumerate(o.amplitudes_N):
            row += [a, 2 * math.pi * (k + 1) / o.period_m, ph[k]]
        return PlantTerm.compiled("force", plant_force, row)

    # identification
    def columns(self, h, p):
        """sin, cos(2π k x / h) interleaved, (N, 2·N_HARMONICS); h: period P [m]."""
        return fourier(p.x, h, N_HARMONICS, single=p.columns_single)

    def peak_data(self, ctx, residual):
        mv = ctx.moving
        return ctx.p.x_d[mv], residual[mv]

    def parameters(self, h, beta, gain, fs):
        g, unit = (gain, "N") if gain else (1.0, "V")
        amp, ph = amplitudes_phases(beta, g)
        return {"period_m": float(h), f"amplitudes_{unit}": [float(a) for a in amp],
                "phases_rad": [float(p) for p in ph]}

    # compensation
    def compensation(self, h, beta, signals=None, beta_std=None):
        """β_std: standard deviations of the fitted β (interleaved as ``beta``), or None."""
        std = None if beta_std is None else list(beta_std[0::2]) + list(beta_std[1::2])
        return self.adapt_entry({"period_m": float(h), "sin_V": [float(-b) for b in beta[0::2]],
                                 "cos_V": [float(-b) for b in beta[1::2]]}, std)

    def compensation_for(self, o: Cogging, a1):
        ph = list(o.phases_rad) + [0.0] * len(o.amplitudes_N)
        sc = [sin_cos_of(a / a1, ph[k]) for k, a in enumerate(o.amplitudes_N)]
        return {"period_m": o.period_m, "sin_V": [s for s, _ in sc], "cos_V": [c for _, c in sc]}

    def compensator(self, o: FourierPosition):
        return fourier_term(harmonics(2.0 * math.pi / o.period_m, o.sin_V, o.cos_V), on_time=False)

    def adapt_basis(self, o: FourierPosition):
        return fourier_basis(2.0 * math.pi / o.period_m, len(o.beta()) // 2, on_time=False)

    # report
    def shape(self, ctx, h, beta, gain):
        xs = self.position_grid(ctx, h)
        zero = np.zeros_like(xs)
        y = -(gain or 1.0) * (self.columns(h, Signals(xs, zero, zero, zero, zero)) @ beta)
        return xs, y, "position [m]", "effect force [UNIT]"


FAMILY = CoggingFamily()
