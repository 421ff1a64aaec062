"""Effect families: one module per identified physical effect, found through :data:`FAMILIES`
(the ``motorctl.effects`` entry points, :mod:`motorctl.effects.registry`).

Each module ``motorctl/effects/<name>.py`` holds everything about one family (the interface is
:class:`motorctl.effects.base.EffectFamily`): the simulator's options and plant term, the
identification's regressor columns, searched parameter, plausibility checks and parameter
names, the compensation's options and term, and the report figure. The simulator
(``motorctl_drivers.sim``), ``motorctl identify`` (``motorctl.ident``), the compensation
(:mod:`motorctl.effects.compensation`) and the report iterate this registry and name no family.

==============================  ===================================  ======================
family                          plant force F_eff [N]                columns C (u = Φθ + Cβ)
==============================  ===================================  ======================
cogging                         Σ A_k sin(2πkx/P + φ_k)              sin, cos(2πkx/P), k ≤ 2
force_ripple                    F_m Σ r_k sin(2πkx/P + φ_k)          f_u(u)·sin, ·cos(2πkx/P)
stribeck                        −F_s exp(−(ẋ/v_s)²) S_f(ẋ)           exp(−(ẋ/v_s)²) S_f(ẋ)
asymmetric_friction             −(ΔF_c S_f(ẋ) + ΔB ẋ), ẋ > 0 only    S_f(ẋ)·[ẋ>0], ẋ·[ẋ>0]
position_dependent_friction     −c (x − x_ref) S_f(ẋ)                x·S_f(ẋ)
spring                          −k (x − x_0)                         x
payload_change                  Δm ẍ from t_c on (mass step)         ẍ·[t ≥ t_c]
input_delay                     u acts τ later                       target u(t − τ) instead of u
periodic_disturbance            A sin(2πft + φ)                      sin, cos(2πft)
position_friction_shape         −g(x) S_f(ẋ), g a cubic spline       B_j(x)·S_f(ẋ)
stiction                        holds A1 u + F_0 at rest (Karnopp)   u·w(ẋ), w(ẋ) = exp(−(ẋ/h)²)
amplifier_dead_zone             −A1 (f_u(u) − f_u(dz(u + o)))        f_u(u) − f_u(dz(u + o))
force_constant_drift            κ t A1 f_u(u)                        f_u(u)·(t − t̄)
periodic_friction               −Σ A_k sin(2πkx/P + φ_k) S_f(ẋ)      sin, cos(2πkx/P)·S_f(ẋ)
encoder_interpolation           none (reading y = x + Σ a_k sin(..))  d²/dt² sin, cos(2πky/P)
structural_mode                 −m_l δ̈, load on a spring (two-mass)  −G(s)ẍ, G = s²/(s²+..ω_a²)
==============================  ===================================  ======================

F_eff = −A1·Cβ; x_ref, x_0 are absorbed by θ3, θ4 (only the slope/stiffness is identifiable).
Compensable (additive in (x_d, ẋ_d, t)): cogging, stribeck, asymmetric_friction,
position_dependent_friction, spring, periodic_disturbance, position_friction_shape,
periodic_friction; through a hook: force_ripple, input_delay. Identified and reported only:
payload_change, stiction, amplifier_dead_zone, force_constant_drift, encoder_interpolation,
structural_mode (a mass, a holding force, a static input nonlinearity, a gain drift, an error of
the reading and a resonance of the feedback path: no additive term in (x_d, ẋ_d, t) cancels
them).

The order of :data:`FAMILIES` is fixed: it is the order of the identification's candidates and
of the plant's force terms (float sums: do not reorder existing entries). This package's families
come first in :data:`motorctl.effects.registry.BUILTIN_ORDER`, then any other, by name.

Adding a family: a module with an :class:`~motorctl.effects.base.EffectFamily` subclass and a
``FAMILY`` instance, its tests, and one entry point in the ``motorctl.effects`` group (in this
package or any installed one: ``name = "module:FAMILY"``); a
thrust, force or mass plant term or a compensation written as a compiled kernel
(:meth:`~motorctl.effects.base.PlantTerm.compiled`, :class:`~motorctl.effects.base.CompTerm`) is
also declared in the family's :attr:`~motorctl.effects.base.EffectFamily.kernels`: the tables
:data:`motorctl.effects.plant.PLANT_KERNELS` and :data:`motorctl.effects.compensation.COMP_KERNELS`
are built from the registry (a family of Python hooks instead runs from Python: the same
equations, slower). The YAML schemas
(``axes.NAME.driver.effects``, ``axes.NAME.controller.compensation``) are built from the
registry when their modules are imported (:func:`effects_model`, :func:`compensation_model`).
"""

from __future__ import annotations

from pydantic import create_model

from motorctl.effects.base import EffectFamily, PlantTerm, Signals
from motorctl.effects.registry import load_families
from motorctl.schema import StrictModel

#: name -> family, from the ``motorctl.effects`` entry points (:mod:`motorctl.effects.registry`):
#: this package's families in the fixed order described in the module docstring, then any other
#: installed package's, by name.
FAMILIES: dict[str, EffectFamily] = load_families()


def family(name: str) -> EffectFamily:
    """The registered family ``name``.

    Raises:
        ValueError: unknown name (the message lists the families).
    """
    try:
        return FAMILIES[name]
    except KeyError:
        raise ValueError(f"unknown effect family {name!r}; families: {', '.join(FAMILIES)}") from None


def simulated() -> list[EffectFamily]:
    """Families with an ``axes.NAME.driver.effects`` entry, in registry order."""
    return [f for f in FAMILIES.values() if f.sim_options is not None]


def compensable() -> list[EffectFamily]:
    """Families with a compensation term, by :attr:`~EffectFamily.compensation_rank` (ties in
    registry order): the order of ``CompensationConfig``'s keys and of the sum d̂_eff."""
    fams = list(FAMILIES.values())
    return sorted((f for f in fams if f.comp_options is not None),
                  key=lambda f: (f.compensation_rank, fams.index(f)))


def effects_model(module: str | None = None) -> type[StrictModel]:
    """The options model of ``axes.NAME.driver.effects`` (``Effects``): one optional key per
    :func:`simulated` family, each validated by its ``sim_options``; all off by default.

    Args:
        module: the ``__module__`` the model is published in (so that it pickles by reference).
    """
    fields = {f.name: (f.sim_options | None, None) for f in simulated()}
    return create_model("Effects", __base__=StrictModel, __module__=module or __name__,
                        __doc__="Simulated effects (all off by default), one key per effect family "
                                "(motorctl.effects).", **fields)


class CompensationBase(StrictModel):
    """Base of ``CompensationConfig`` (see :func:`compensation_model`)."""

    def is_empty(self) -> bool:
        """True when no family is compensated."""
        return all(getattr(self, k) is None for k in type(self).model_fields)


def compensation_model(module: str | None = None) -> type[CompensationBase]:
    """The options model of ``axes.NAME.controller.compensation`` (``CompensationConfig``): one
    optional key per :func:`compensable` family, each validated by its ``comp_options``.

    Args:
        module: the ``__module__`` the model is published in (so that it pickles by reference).
    """
    fields = {f.name: (f.comp_options | None, None) for f in compensable()}
    return create_model("CompensationConfig", __base__=CompensationBase, __module__=module or __name__,
                        __doc__="Identified effects compensated in v_a1 (eq. 13), one key per "
                                "compensable effect family (motorctl.effects); V units.", **fields)


__all__ = [
    "FAMILIES",
    "CompensationBase",
    "EffectFamily",
    "PlantTerm",
    "Signals",
    "compensable",
    "compensation_model",
    "effects_model",
    "family",
    "simulated",
]
