"""Model compensation of effects found by ``motorctl identify``, added to the DCDIARC law.

The paper's model (eq. 4) lumps every unmodelled force into d̃. When identification traces
part of d̃ to a named physical effect, its term is compensated like the other model terms
(desired compensation, eq. 13): evaluated on the desired trajectory (x_d, ẋ_d) and time t,
in input units (V, i.e. force / A1), and subtracted in v_a1:

    θ1 ẍ = u − θ2 ẋ − θ3 S_f(ẋ) + θ4 + θ5 u|u| + θ6 u³ + d_eff(x, ẋ, t) + d̃
    v_a1 = θ̂1 ẍ_d + θ̂2 ẋ_d + θ̂3 S_f(ẋ_d) − θ̂4 − d̂_eff(x_d, ẋ_d, t)

Amplitudes are fixed from the fit (the fast d̂0 term still absorbs what is left).
YAML: ``axes.NAME.controller.compensation``.
"""

from __future__ import annotations

import math
from typing import Annotated

from pydantic import Field

from motorctl.driver import StrictModel

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


class CompensationConfig(StrictModel):
    cogging: FourierPosition | None = None
    spring: SpringComp | None = None
    periodic_disturbance: FourierTime | None = None

    def is_empty(self) -> bool:
        return self.cogging is None and self.spring is None and self.periodic_disturbance is None


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
        return d
