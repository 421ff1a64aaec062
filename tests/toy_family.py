"""A toy effect family for the registry's tests (not installed): quadratic aerodynamic drag.

It imports only the family interface and the kernel decorator, so an interpreter can load it
while ``motorctl.effects`` is being built: ``tests/test_effect_entry_points.py`` registers
:data:`FAMILY` (its plant term and compensation compiled kernels, declared in ``kernels``) as an
entry point of a package outside motorctl, ``tests/test_effect_registry.py`` puts the Python
one (:class:`QuadraticDrag`) into the registry directly, after the tables are built.
"""

from __future__ import annotations

from typing import ClassVar

import numpy as np

from motorctl.effects.base import CompTerm, EffectFamily, PlantTerm, Signals
from motorctl.jit import njit
from motorctl.schema import StrictModel


class DragOptions(StrictModel):
    drag_N_s2_per_m2: float


class DragComp(StrictModel):
    drag_V_s2_per_m2: float


class QuadraticDrag(EffectFamily):
    """Aerodynamic drag F_eff = −c ẋ|ẋ| [N]; column ẋ|ẋ|; d̂_eff = −c_V ẋ|ẋ| [V]."""

    name = "quadratic_drag"
    plant_force = "−c ẋ|ẋ|"
    sim_options = DragOptions
    example: ClassVar[dict] = {"quadratic_drag": {"drag_N_s2_per_m2": 20.0}}
    comp_options = DragComp

    def plant_term(self, o, period_s):
        c = o.drag_N_s2_per_m2
        return PlantTerm(force=lambda f, x, v, t, sf: f - c * v * abs(v))

    def columns(self, h, p):
        return (p.v * np.abs(p.v))[:, None]

    def parameters(self, h, beta, gain, fs):
        g, unit = (gain, "N") if gain else (1.0, "V")
        return {f"drag_{unit}_s2_per_m2": float(g * beta[0])}

    def compensation(self, h, beta):
        return {"drag_V_s2_per_m2": float(beta[0])}

    def compensation_for(self, o, a1):
        return {"drag_V_s2_per_m2": o.drag_N_s2_per_m2 / a1}

    def compensator(self, o):
        c = o.drag_V_s2_per_m2
        return lambda d, x, v, t, sf: d - c * v * abs(v)

    def shape(self, ctx, h, beta, gain):
        vs = np.linspace(-1.0, 1.0, 101)
        zero = np.zeros_like(vs)
        return vs, -(gain or 1.0) * (self.columns(h, Signals(zero, vs, zero, zero, zero)) @ beta), \
            "velocity [m/s]", "effect force [UNIT]"


@njit
def drag_force(f, x, v, t, sf, p):
    """f − c v|v| [N], p = (c [N s²/m²],)."""
    return f - p[0] * v * abs(v)


@njit
def drag_add(d, x, v, t, sf, p):
    """d − c_V v|v| [V], p = (c_V [V s²/m²],)."""
    return d - p[0] * v * abs(v)


class CompiledDrag(QuadraticDrag):
    """:class:`QuadraticDrag` with its plant term and compensation compiled (as an installed
    family's would be): the kernels are declared, the tables built from the registry take them."""

    kernels = (("force", drag_force), ("add", drag_add))

    def plant_term(self, o, period_s):
        return PlantTerm.compiled("force", drag_force, [o.drag_N_s2_per_m2])

    def compensator(self, o):
        return CompTerm("add", drag_add, [o.drag_V_s2_per_m2])


FAMILY = CompiledDrag()
