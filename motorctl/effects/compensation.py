"""Model compensation of effects found by ``motorctl identify``, added to the DCDIARC law.

The paper's model (eq. 4) lumps every unmodelled force into d̃. When identification traces
part of d̃ to a named physical effect, its term is compensated like the other model terms
(desired compensation, eq. 13): evaluated on the desired trajectory (x_d, ẋ_d) and time t,
in input units (V, i.e. force / A1), and subtracted in v_a1:

    θ1 ẍ = u − θ2 ẋ − θ3 S_f(ẋ) + θ4 + θ5 u|u| + θ6 u³ + d_eff(x, ẋ, t) + d̃
    v_a1 = θ̂1 ẍ_d + θ̂2 ẋ_d + θ̂3 S_f(ẋ_d) − θ̂4 − d̂_eff(x_d, ẋ_d, t)

**Fixed** (default): the amplitudes come from the fit (the fast d̂0 term still absorbs what is
left); the estimator sees the input u + d̂_eff. **Adapted** (``adapt: true`` on an entry whose
family can adapt, :class:`motorctl.effects.base.Adaptable`): d_eff = Σ_j β_j c_j(x, ẋ, t), the
basis columns c_j join the regressor (φ extended, filtered by the same H_f, evaluated on the
measured x, ẋ in the estimator) and β̂ joins θ̂ (same LS, eq. 27-28, and box projection, eq. 7-8);
v_a1 subtracts Σ β̂_j c_j(x_d, ẋ_d, t).

Two families compensate without an additive term (:class:`motorctl.effects.base.CompHook`):
force ripple (v divided by 1 + r̂(x_d) before the inversion, eq. 9) and input delay (v_a1 on
the desired trajectory at t + τ).

YAML: ``axes.NAME.controller.compensation.<family>``. The keys and each family's term come from
the registry (:func:`motorctl.effects.compensable`, the family modules): this module only
composes them. ``CompensationConfig`` has one key per additive family (the registry's
:func:`~motorctl.effects.compensable`); :data:`CompensationSection`, the schema of the
controller's section, adds one per family with :attr:`~motorctl.effects.base.EffectFamily.hook_options`.
"""

from __future__ import annotations

import numpy as np
from pydantic import create_model

from motorctl.effects import FAMILIES, compensable, compensation_model
from motorctl.model import s_f_scalar

#: The additive terms of the ``compensation:`` section: one optional key per compensable family
#: (built from the registry).
CompensationConfig = compensation_model(__name__)


def hooked() -> list:
    """Families with a non-additive compensation (:attr:`hook_options`), in registry order."""
    return [f for f in FAMILIES.values() if f.hook_options is not None]


#: The controller's ``compensation:`` section: :data:`CompensationConfig` plus one optional key
#: per :func:`hooked` family (force_ripple, input_delay).
CompensationSection = create_model(
    "CompensationSection", __base__=CompensationConfig, __module__=__name__,
    __doc__="Identified effects compensated by the controller (eq. 13, 9), one key per family "
            "with a compensation (motorctl.effects); V units for additive terms.",
    **{f.name: (f.hook_options | None, None) for f in hooked()})


class Compensation:
    """Evaluates the compensation of one axis (runs inside the 5 kHz cycle).

    The terms of the configured families are built once here (in :func:`compensable` order);
    the per-sample methods only add floats or write into preallocated arrays.

    Args:
        cfg: a ``CompensationConfig`` or ``CompensationSection`` (any model with one attribute
            per family, None when off).
    Attributes:
        n_beta: number of adapted coefficients k (0: none).
        beta0, beta_min, beta_max, gamma0: (k,) arrays, β̂(0), the box and the Γ(0) diagonal of
            the adapted coefficients, entries in :func:`compensable` order, each entry's β in
            :meth:`~motorctl.effects.base.Adaptable.beta` order.
        beta_names: (k,) "family.name" of each adapted coefficient.
        thrust: r̂(x) of the force ripple (None: none). preview_s: input delay τ [s] (0: none).
    Raises:
        ValueError: ``adapt: true`` on a family that has no basis (:meth:`adapt_basis` None).
    """

    def __init__(self, cfg):
        self.cfg = cfg
        terms, fills = [], []
        need_sf = False
        fill_sf = False
        b0, lo, hi, g0, names = [], [], [], [], []
        for fam in compensable():
            opts = getattr(cfg, fam.name, None)
            if opts is None:
                continue
            if getattr(opts, "adapt", False):
                fill = fam.adapt_basis(opts)
                if fill is None:
                    raise ValueError(f"compensation.{fam.name}: adapt: the family cannot adapt")
                fills.append((fill, len(b0)))
                b = opts.beta()
                bl, bh = opts.adapt_box()
                b0 += b
                lo += bl
                hi += bh
                g0 += opts.adapt_gamma0()
                names += [f"{fam.name}.{n}" for n in opts.beta_names()]
                fill_sf = fill_sf or fam.comp_needs_sf
            else:
                terms.append(fam.compensator(opts))
                need_sf = need_sf or fam.comp_needs_sf
        self._terms = tuple(terms)
        self._need_sf = need_sf
        self._fills = tuple(fills)
        self._fill_sf = fill_sf
        self.n_beta = len(b0)
        self.beta0 = np.array(b0, dtype=float)
        self.beta_min = np.array(lo, dtype=float)
        self.beta_max = np.array(hi, dtype=float)
        self.gamma0 = np.array(g0, dtype=float)
        self.beta_names = names
        self.thrust = None
        self.preview_s = 0.0
        for fam in hooked():
            opts = getattr(cfg, fam.name, None)
            if opts is None:
                continue
            hook = fam.comp_hook(opts)
            if hook.thrust is not None:
                if self.thrust is not None:
                    raise ValueError(f"compensation.{fam.name}: a second thrust factor")
                self.thrust = hook.thrust
            if hook.preview_s:
                self.preview_s += hook.preview_s

    @property
    def additive(self) -> bool:
        """True when there is a fixed additive term (:meth:`value` can be nonzero)."""
        return bool(self._terms)

    def value(self, x_d: float, xd_dot: float, t: float) -> float:
        """d̂_eff [V] of the fixed (not adapted) terms at the desired position x_d [m], velocity
        ẋ_d [m/s] and time t [s]."""
        sf = s_f_scalar(xd_dot) if self._need_sf else 0.0
        d = 0.0
        for add in self._terms:
            d = add(d, x_d, xd_dot, t, sf)
        return d

    def fill(self, out: np.ndarray, x: float, xdot: float, t: float) -> None:
        """The adapted basis columns c(x, ẋ, t) into ``out`` (n_beta,) [V per β-unit]: d̂_eff of
        the adapted terms is β·c. x [m], ẋ [m/s], t [s]."""
        sf = s_f_scalar(xdot) if self._fill_sf else 0.0
        for fill, j in self._fills:
            fill(out, j, x, xdot, t, sf)


__all__ = ["Compensation", "CompensationConfig", "CompensationSection", "hooked"]
