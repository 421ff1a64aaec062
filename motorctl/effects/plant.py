"""The effects' plant terms compiled: the simulated plant's hooks evaluated in one numba kernel.

A family whose :meth:`~motorctl.effects.base.EffectFamily.plant_term` is built by
:meth:`PlantTerm.compiled <motorctl.effects.base.PlantTerm.compiled>` gives a compiled kernel
(its formula, in its own module) and a parameter row. :func:`rows` turns the terms of one axis
into a code per term (the kernel's index in :data:`KERNELS`) and a padded table of rows;
:func:`thrust`, :func:`force` and :func:`mass` apply every term of their kind, in the terms'
(registry) order, with the same operations as the Python hooks, so that
``motorctl_drivers.sim.AxisPlant`` runs a whole period compiled.

Adding a family with a thrust, force or mass term: its kernel in :data:`KERNELS` and one branch
in the function of its kind below (a family left out keeps Python hooks: the plant then takes
its Python path, the same equations, slower).

numba caches the kernels here and in ``motorctl_drivers.sim`` beside their sources; its cache
is keyed on the calling module's file, so after editing a family's kernel, delete the
``__pycache__/*.nbi`` of this module and of ``motorctl_drivers/sim.py`` (or touch them).
"""

from __future__ import annotations

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
from motorctl.jit import njit

_cogging = cogging.plant_force
_ripple = force_ripple.plant_thrust
_stribeck = stribeck.plant_force
_asymmetric = asymmetric_friction.plant_force
_line = position_dependent_friction.line_force
_spring = spring.plant_force
_payload = payload_change.plant_mass
_disturbance = periodic_disturbance.plant_force
_bumps = position_friction_shape.plant_force
_drift = force_constant_drift.plant_thrust
_harmonic_friction = periodic.friction_force

#: the compiled kernels, a term's code is the index of its kernel here
KERNELS = (_cogging, _ripple, _stribeck, _asymmetric, _line, _spring, _payload, _disturbance, _bumps,
           _drift, _harmonic_friction)
(K_COGGING, K_RIPPLE, K_STRIBECK, K_ASYMMETRIC, K_LINE, K_SPRING, K_PAYLOAD, K_DISTURBANCE, K_BUMPS,
 K_DRIFT, K_HARMONIC_FRICTION) = range(len(KERNELS))


def rows(terms: list) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """The compiled form of ``terms`` (:class:`~motorctl.effects.base.PlantTerm`, registry
    order; those without a thrust, force or mass hook are skipped).

    Returns:
        (codes (n,) int64, rows (n, w) float64 zero-padded, lengths (n,) int64), or None when a
        term with such a hook has no kernel listed in :data:`KERNELS` (the plant then runs its
        Python hooks).
    """
    hooked = [t for t in terms if (t.thrust, t.force, t.mass) != (None, None, None)]
    codes = []
    for t in hooked:
        k = next((i for i, fn in enumerate(KERNELS) if fn is t.kernel), None)
        if k is None:
            return None
        codes.append(k)
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
        c = codes[i]
        if c == K_RIPPLE:
            fm = _ripple(fm, x, t, table[i, :lengths[i]])
        elif c == K_DRIFT:
            fm = _drift(fm, x, t, table[i, :lengths[i]])
    return fm


@njit
def force(f, x, v, t, sf, codes, table, lengths):
    """f [N] plus every force term of ``codes`` (:func:`rows`) at position x [m], velocity
    v [m/s], plant time t [s]; sf = S_f(v)."""
    for i in range(codes.shape[0]):
        c = codes[i]
        p = table[i, :lengths[i]]
        if c == K_COGGING:
            f = _cogging(f, x, v, t, sf, p)
        elif c == K_STRIBECK:
            f = _stribeck(f, x, v, t, sf, p)
        elif c == K_ASYMMETRIC:
            f = _asymmetric(f, x, v, t, sf, p)
        elif c == K_LINE:
            f = _line(f, x, v, t, sf, p)
        elif c == K_SPRING:
            f = _spring(f, x, v, t, sf, p)
        elif c == K_DISTURBANCE:
            f = _disturbance(f, x, v, t, sf, p)
        elif c == K_BUMPS:
            f = _bumps(f, x, v, t, sf, p)
        elif c == K_HARMONIC_FRICTION:
            f = _harmonic_friction(f, x, v, t, sf, p)
    return f


@njit
def mass(m, t, codes, table, lengths):
    """The moving mass [kg] after every mass term of ``codes`` (:func:`rows`) at plant time t [s]."""
    for i in range(codes.shape[0]):
        if codes[i] == K_PAYLOAD:
            m = _payload(m, t, table[i, :lengths[i]])
    return m
