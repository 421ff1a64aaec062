"""Model compensation of effects found by ``motorctl identify``, added to the DCDIARC law.

The paper's model (eq. 4) lumps every unmodelled force into d̃. When identification traces
part of d̃ to a named physical effect, its term is compensated like the other model terms
(desired compensation, eq. 13): evaluated on the desired trajectory (x_d, ẋ_d) and time t,
in input units (V, i.e. force / A1), and subtracted in v_a1:

    θ1 ẍ = u − θ2 ẋ − θ3 S_f(ẋ) + θ4 + θ5 u|u| + θ6 u³ + d_eff(x, ẋ, t) + d̃
    v_a1 = θ̂1 ẍ_d + θ̂2 ẋ_d + θ̂3 S_f(ẋ_d) − θ̂4 − d̂_eff(x_d, ẋ_d, t)

Amplitudes are fixed from the fit (the fast d̂0 term still absorbs what is left).
YAML: ``axes.NAME.controller.compensation``. Families: cogging, spring, periodic_disturbance,
stribeck, asymmetric_friction, position_dependent_friction (the additive forces of
``motorctl_drivers.sim``; force ripple, payload change and input delay are not additive in
(x_d, ẋ_d, t) and have no term here).
"""

from __future__ import annotations

import math
from typing import Annotated

from pydantic import Field

from motorctl.schema import StrictModel
from motorctl.model import s_f_scalar

Pos = Annotated[float, Field(gt=0)]


class FourierPosition(StrictModel):
    """Σ_k a_k sin(2π k x / P) + b_k cos(2π k x / P) [V] (cogging / detent force)."""

    period_m: Pos
    sin_V: list[float] = []
    cos_V: list[float] = []


class SpringComp(StrictModel):
    """−k (x − x0) [V]: stiffness in V/m (force / A1)."""

    stiffness_V_per_m: float
    rest_position_m: float = 0.0


class FourierTime(StrictModel):
    """Σ_k a_k sin(2π k f t) + b_k cos(2π k f t) [V] (time-periodic disturbance)."""

    frequency_Hz: Pos
    sin_V: list[float] = []
    cos_V: list[float] = []


class StribeckComp(StrictModel):
    """−F_s exp(−(ẋ/v_s)²) S_f(ẋ) [V]: friction hump at low speed (force / A1)."""

    force_V: float
    velocity_m_per_s: Pos


class AsymmetricFrictionComp(StrictModel):
    """−(ΔF_c S_f(ẋ) + ΔB ẋ) for ẋ > 0 only [V]: direction-dependent friction (force / A1)."""

    coulomb_V: float = 0.0
    viscous_V_s_per_m: float = 0.0


class PositionFrictionComp(StrictModel):
    """−c (x − x_ref) S_f(ẋ) [V]: Coulomb level varying with position (force / A1)."""

    coulomb_slope_V_per_m: float
    reference_m: float = 0.0


class CompensationConfig(StrictModel):
    cogging: FourierPosition | None = None
    spring: SpringComp | None = None
    periodic_disturbance: FourierTime | None = None
    stribeck: StribeckComp | None = None
    asymmetric_friction: AsymmetricFrictionComp | None = None
    position_dependent_friction: PositionFrictionComp | None = None

    def is_empty(self) -> bool:
        return all(getattr(self, k) is None for k in type(self).model_fields)


class Compensation:
    """Evaluates d̂_eff(x_d, ẋ_d, t) [V] for one axis; pure floats (runs inside the cycle)."""

    def __init__(self, cfg: CompensationConfig):
        self.cfg = cfg
        self._cog = None
        if cfg.cogging is not None:
            w = 2.0 * math.pi / cfg.cogging.period_m
            n = max(len(cfg.cogging.sin_V), len(cfg.cogging.cos_V))
            a = list(cfg.cogging.sin_V) + [0.0] * (n - len(cfg.cogging.sin_V))
            b = list(cfg.cogging.cos_V) + [0.0] * (n - len(cfg.cogging.cos_V))
            self._cog = [(w * (k + 1), a[k], b[k]) for k in range(n)]
        self._pd = None
        if cfg.periodic_disturbance is not None:
            w = 2.0 * math.pi * cfg.periodic_disturbance.frequency_Hz
            d = cfg.periodic_disturbance
            n = max(len(d.sin_V), len(d.cos_V))
            a = list(d.sin_V) + [0.0] * (n - len(d.sin_V))
            b = list(d.cos_V) + [0.0] * (n - len(d.cos_V))
            self._pd = [(w * (k + 1), a[k], b[k]) for k in range(n)]
        self._spring = cfg.spring
        self._strib = cfg.stribeck
        self._asym = cfg.asymmetric_friction
        self._pdf = cfg.position_dependent_friction

    def value(self, x_d: float, xd_dot: float, t: float) -> float:
        """d̂_eff [V] at the desired position x_d [m], velocity ẋ_d [m/s] and time t [s]."""
        d = 0.0
        if self._cog is not None:
            for w, a, b in self._cog:
                d += a * math.sin(w * x_d) + b * math.cos(w * x_d)
        if self._spring is not None:
            d -= self._spring.stiffness_V_per_m * (x_d - self._spring.rest_position_m)
        if self._pd is not None:
            for w, a, b in self._pd:
                d += a * math.sin(w * t) + b * math.cos(w * t)
        if self._strib is not None or self._asym is not None or self._pdf is not None:
            sf = s_f_scalar(xd_dot)
            if self._strib is not None:
                z = xd_dot / self._strib.velocity_m_per_s
                d -= self._strib.force_V * math.exp(-z * z) * sf
            if self._asym is not None and xd_dot > 0.0:
                d -= self._asym.coulomb_V * sf + self._asym.viscous_V_s_per_m * xd_dot
            if self._pdf is not None:
                d -= self._pdf.coulomb_slope_V_per_m * (x_d - self._pdf.reference_m) * sf
        return d
