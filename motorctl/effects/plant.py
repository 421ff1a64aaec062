"""The effects' plant terms compiled: the simulated plant's hooks evaluated in one numba kernel.

A family whose :meth:`~motorctl.effects.base.EffectFamily.plant_term` is built by
:meth:`PlantTerm.compiled <motorctl.effects.base.PlantTerm.compiled>` gives a compiled kernel
(its formula, in its own module) and a parameter row. :func:`rows` turns the terms of one axis
into a code per term (the kernel's index in :data:`PLANT_KERNELS`) and a padded table of rows;
:func:`thrust`, :func:`force` and :func:`mass` apply every term of their kind, in the terms'
(registry) order, with the same operations as the Python hooks, so that
``motorctl_drivers.sim.AxisPlant`` runs a whole period compiled.

Adding a family with a compiled thrust, force or mass term: declare the kernel in the family's
:attr:`~motorctl.effects.base.EffectFamily.kernels`; :data:`PLANT_KERNELS` is built from the
registry, the compiled dispatch from it (:func:`motorctl.jit.dispatch`). A family whose terms
are Python hooks only keeps them: the plant then takes its Python path (the same equations,
slower). A term whose kernel is not in the table, or a code outside it, is refused when
:func:`rows` builds an axis's table (no fall-through to another term); inside the compiled
kernels an unknown code would give NaN (the supervisor faults the axis), never another term.

numba keys a cached kernel on its own module's file only; motorctl's cache folder is keyed by
all of its sources (:mod:`motorctl.jitcache`), so after an edit of a family's kernel this
module and ``motorctl_drivers.sim`` compile afresh.
"""

from __future__ import annotations

from functools import partial

import numpy as np

from motorctl.effects import FAMILIES
from motorctl.effects.registry import kernel_code, kernel_table
from motorctl.jit import check_code, dispatch, njit

HOOKS = ("thrust", "force", "mass")
#: code -> (hook, compiled kernel) of every compiled plant term: a term's code is its row's index.
#: Built from the registry (each family's :attr:`~motorctl.effects.base.EffectFamily.kernels`
#: of a plant hook, in registry order), so this package's codes do not depend on what else is
#: installed and a family from another package is compiled into the plant too.
PLANT_KERNELS: tuple[tuple[str, object], ...] = kernel_table(FAMILIES.values(), HOOKS)
#: the compiled kernels by code (:data:`PLANT_KERNELS` without the hooks)
KERNELS = tuple(kernel for _, kernel in PLANT_KERNELS)
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
        term with such a hook is Python hooks only (no kernel: the plant then runs its Python
        hooks).
    Raises:
        ValueError: a term's kernel is not in :data:`PLANT_KERNELS` (not declared in its
            family's :attr:`~motorctl.effects.base.EffectFamily.kernels`) or is listed for
            another hook than the term's (:func:`check_plant_code`).
    """
    hooked = [t for t in terms if (t.thrust, t.force, t.mass) != (None, None, None)]
    if any(t.kernel is None for t in hooked):
        return None
    codes = []
    for t in hooked:
        hook = next(h for h in HOOKS if getattr(t, h) is not None)
        codes.append(check_plant_code(kernel_code(PLANT_KERNELS, t.kernel, "plant term"), hook))
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
