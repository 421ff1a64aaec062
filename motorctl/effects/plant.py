"""The effects' plant terms compiled: the simulated plant's hooks evaluated in one numba kernel.

A family whose :meth:`~motorctl.effects.base.EffectFamily.plant_term` is built by
:meth:`PlantTerm.compiled <motorctl.effects.base.PlantTerm.compiled>` gives a compiled kernel
(its formula, in its own module) and a parameter row. :func:`rows` turns the terms of one axis
into a code per term (the kernel's index in :data:`PLANT_KERNELS`) and a padded table of rows;
:func:`thrust`, :func:`force` and :func:`mass` apply every term of their kind, in the terms'
(registry) order, with the same operations as the Python hooks, so that
``motorctl_drivers.sim.AxisPlant`` runs a whole period compiled.

Adding a family with a compiled thrust, force or mass term: one row ``(hook, kernel)`` at the
end of :data:`PLANT_KERNELS` (the compiled dispatch is built from it, :func:`motorctl.jit.dispatch`).
A family left out keeps Python hooks: the plant then takes its Python path (the same equations,
slower). A code outside the table is refused by :func:`check_plant_code` when :func:`rows` builds
an axis's table; inside the compiled kernels it would give NaN (the supervisor faults the axis),
never another term.

numba caches the kernels here and in ``motorctl_drivers.sim`` beside their sources; its cache
is keyed on the calling module's file, so after editing a family's kernel, delete the
``__pycache__/*.nbi`` of this module and of ``motorctl_drivers/sim.py`` (or touch them).
"""

from __future__ import annotations

from functools import partial

import numpy as np

from motorctl.effects import (
    asymmetric_friction,
    cogging,
    force_constant_drift,
    force_ripple,
    payload_change,
    periodic,
    periodic_disturbance,
    position_dependent_friction,
    position_friction_shape,
    spring,
    stribeck,
)
from motorctl.jit import check_code, dispatch, njit

#: code -> (hook, compiled kernel) of every compiled plant term: a term's code is its row's index
PLANT_KERNELS: tuple[tuple[str, object], ...] = (
    ("force", cogging.plant_force),
    ("thrust", force_ripple.plant_thrust),
    ("force", stribeck.plant_force),
    ("force", asymmetric_friction.plant_force),
    ("force", position_dependent_friction.line_force),
    ("force", spring.plant_force),
    ("mass", payload_change.plant_mass),
    ("force", periodic_disturbance.plant_force),
    ("force", position_friction_shape.plant_force),
    ("thrust", force_constant_drift.plant_thrust),
    ("force", periodic.friction_force),
)
#: the compiled kernels by code (:data:`PLANT_KERNELS` without the hooks)
KERNELS = tuple(kernel for _, kernel in PLANT_KERNELS)
HOOKS = ("thrust", "force", "mass")
_N_KERNELS = len(PLANT_KERNELS)


#: ``check_plant_code(code, hook)``: ``code`` when it is a ``hook`` kernel's in :data:`PLANT_KERNELS`; else
#: ValueError naming the known codes (:func:`motorctl.jit.check_code`)
check_plant_code = partial(check_code, PLANT_KERNELS, what="plant term")


def _of(hook: str):
    return [(i, kernel) for i, (h, kernel) in enumerate(PLANT_KERNELS) if h == hook]


@njit
def _other_thrust(c, fm, x, t, p):
    return fm if 0 <= c < _N_KERNELS else np.nan


@njit
def _other_force(c, f, x, v, t, sf, p):
    return f if 0 <= c < _N_KERNELS else np.nan


@njit
def _other_mass(c, m, t, p):
    return m if 0 <= c < _N_KERNELS else np.nan


# the compiled dispatch by code, built from the table: a code of another hook leaves the value
# as it is (each of thrust, force, mass applies its own terms), a code outside the table is NaN
_thrust_of = dispatch(_of("thrust"), _other_thrust)
_force_of = dispatch(_of("force"), _other_force)
_mass_of = dispatch(_of("mass"), _other_mass)


def rows(terms: list) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """The compiled form of ``terms`` (:class:`~motorctl.effects.base.PlantTerm`, registry
    order; those without a thrust, force or mass hook are skipped).

    Returns:
        (codes (n,) int64, rows (n, w) float64 zero-padded, lengths (n,) int64), or None when a
        term with such a hook has no kernel listed in :data:`PLANT_KERNELS` (the plant then runs
        its Python hooks).
    Raises:
        ValueError: a term's kernel is listed for another hook than the term's
            (:func:`check_plant_code`).
    """
    hooked = [t for t in terms if (t.thrust, t.force, t.mass) != (None, None, None)]
    codes = []
    for t in hooked:
        k = next((i for i, fn in enumerate(KERNELS) if fn is t.kernel), None)
        if k is None:
            return None
        hook = next(h for h in HOOKS if getattr(t, h) is not None)
        codes.append(check_plant_code(k, hook))
    width = max([t.params.shape[0] for t in hooked] + [1])
    table = np.zeros((len(hooked), width))
    for i, t in enumerate(hooked):
        table[i, :t.params.shape[0]] = t.params
    return (np.array(codes, dtype=np.int64), table,
            np.array([t.params.shape[0] for t in hooked], dtype=np.int64))


@njit
def thrust(fm, x, t, codes, table, lengths):
    """The motor force [N] after every thrust term of ``codes`` (:func:`rows`) at position x [m]
    and plant time t [s]."""
    for i in range(codes.shape[0]):
        fm = _thrust_of(codes[i], fm, x, t, table[i, :lengths[i]])
    return fm


@njit
def force(f, x, v, t, sf, codes, table, lengths):
    """f [N] plus every force term of ``codes`` (:func:`rows`) at position x [m], velocity
    v [m/s], plant time t [s]; sf = S_f(v)."""
    for i in range(codes.shape[0]):
        f = _force_of(codes[i], f, x, v, t, sf, table[i, :lengths[i]])
    return f


@njit
def mass(m, t, codes, table, lengths):
    """The moving mass [kg] after every mass term of ``codes`` (:func:`rows`) at plant time t [s]."""
    for i in range(codes.shape[0]):
        m = _mass_of(codes[i], m, t, table[i, :lengths[i]])
    return m
