"""Model compensation of effects found by ``motorctl identify``, added to the DCDIARC law.

The paper's model (eq. 4) lumps every unmodelled force into d̃. When identification traces
part of d̃ to a named physical effect, its term is compensated like the other model terms
(desired compensation, eq. 13): evaluated on the desired trajectory (x_d, ẋ_d) and time t,
in input units (V, i.e. force / A1), and subtracted in v_a1:

    θ1 ẍ = u − θ2 ẋ − θ3 S_f(ẋ) + θ4 + θ5 u|u| + θ6 u³ + d_eff(x, ẋ, t) + d̃
    v_a1 = θ̂1 ẍ_d + θ̂2 ẋ_d + θ̂3 S_f(ẋ_d) − θ̂4 − d̂_eff(x_d, ẋ_d, t)

Amplitudes are fixed from the fit (the fast d̂0 term still absorbs what is left).
YAML: ``axes.NAME.controller.compensation.<family>``; the keys and each family's term come from
the registry (:func:`motorctl.effects.compensable`, the family modules): this module only
composes them. Families without a term (force ripple needs u; a payload change and an input
delay are not additive forces in (x_d, ẋ_d, t)) have no key here.
"""

from __future__ import annotations

from motorctl.effects import compensable, compensation_model
from motorctl.model import s_f_scalar

#: The ``compensation:`` section: one optional key per compensable family (built from the registry).
CompensationConfig = compensation_model(__name__)


class Compensation:
    """Evaluates d̂_eff(x_d, ẋ_d, t) [V] for one axis (runs inside the 5 kHz cycle).

    The terms of the configured families are built once here (in :func:`compensable` order);
    :meth:`value` only adds floats: no container is built per call.

    Args:
        cfg: a ``CompensationConfig`` (or any model with one attribute per compensable family,
            None when off).
    """

    def __init__(self, cfg):
        self.cfg = cfg
        terms = []
        need_sf = False
        for fam in compensable():
            opts = getattr(cfg, fam.name, None)
            if opts is not None:
                terms.append(fam.compensator(opts))
                need_sf = need_sf or fam.comp_needs_sf
        self._terms = tuple(terms)
        self._need_sf = need_sf

    def value(self, x_d: float, xd_dot: float, t: float) -> float:
        """d̂_eff [V] at the desired position x_d [m], velocity ẋ_d [m/s] and time t [s]."""
        sf = s_f_scalar(xd_dot) if self._need_sf else 0.0
        d = 0.0
        for add in self._terms:
            d = add(d, x_d, xd_dot, t, sf)
        return d


__all__ = ["Compensation", "CompensationConfig"]
