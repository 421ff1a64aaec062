"""The effect families, found through the ``motorctl.effects`` entry-point group (as the drivers
and the laws are: ``motorctl.drivers``, ``motorctl.controllers``).

Each entry point names one :class:`~motorctl.effects.base.EffectFamily` instance, e.g. in a
package's ``pyproject.toml``::

    [project.entry-points."motorctl.effects"]
    quadratic_drag = "mypkg.drag:FAMILY"

so a family from another installed package is found with no edit to motorctl. Order: the
families that ship with motorctl keep their fixed order (:data:`BUILTIN_ORDER`: the order of the
identification's candidates and of the simulated plant's force terms, i.e. of float sums), every
other family follows by name. The installed metadata lists entry points sorted by name, so the
order cannot come from there.
"""

from __future__ import annotations

from collections.abc import Iterable
from importlib.metadata import entry_points

from motorctl.effects.base import EffectFamily
from motorctl.jitcache import KERNEL_ENTRY_POINTS

#: the families' entry-point group (numba caches the kernels of a process where another package
#: registers one apart: :func:`motorctl.jitcache.numba_folder`)
ENTRY_POINT_GROUP = KERNEL_ENTRY_POINTS

#: the families of this package in their fixed order (do not reorder; a new one goes after them)
BUILTIN_ORDER = ("cogging", "force_ripple", "stribeck", "asymmetric_friction", "position_dependent_friction",
                 "spring", "payload_change", "input_delay", "periodic_disturbance", "position_friction_shape",
                 "stiction", "amplifier_dead_zone", "force_constant_drift", "periodic_friction",
                 "encoder_interpolation", "structural_mode")


class RegistryError(ImportError):
    """The installed entry points do not give a consistent set of families (stale metadata, a
    name registered twice, an entry point that is not a family of that name)."""


def load_families() -> dict[str, EffectFamily]:
    """Every family registered in the ``motorctl.effects`` entry-point group, loaded, by name:
    :data:`BUILTIN_ORDER` first, then the others sorted by name.

    Raises:
        RegistryError: a family of this package is missing from the installed metadata (installed
            before the group existed: reinstall), one name is registered by two packages with
            different targets, or an entry point loads something that is not an
            :class:`EffectFamily` whose ``name`` is the entry point's name.
    """
    eps = {}
    for ep in entry_points(group=ENTRY_POINT_GROUP):
        if ep.name in eps and eps[ep.name].value != ep.value:
            raise RegistryError(f"effect family {ep.name!r} registered twice ({eps[ep.name].value}, {ep.value})")
        eps[ep.name] = ep
    missing = [n for n in BUILTIN_ORDER if n not in eps]
    if missing:
        raise RegistryError(f"entry points {ENTRY_POINT_GROUP}: {', '.join(missing)} missing: the installed "
                            "metadata of motorctl is older than its pyproject.toml; reinstall (pip install -e .)")
    families = {}
    for name in (*BUILTIN_ORDER, *sorted(set(eps) - set(BUILTIN_ORDER))):
        fam = eps[name].load()
        if not isinstance(fam, EffectFamily) or fam.name != name:
            raise RegistryError(f"entry point {ENTRY_POINT_GROUP} {name} = {eps[name].value}: not an "
                                f"EffectFamily named {name!r} ({fam!r})")
        families[name] = fam
    return families


def kernel_table(families: Iterable[EffectFamily], kinds: tuple[str, ...]) -> tuple[tuple[str, object], ...]:
    """The code -> compiled kernel table of ``kinds``: every ``(kind, kernel)`` row of the
    families' :attr:`~motorctl.effects.base.EffectFamily.kernels` whose kind is one of ``kinds``,
    in the families' (registry) order, each kernel once (a kernel two families share keeps its
    first row). A row's index is its code (:func:`motorctl.jit.dispatch`, :func:`motorctl.jit.check_code`).

    Raises:
        RegistryError: a family declares a kernel under two kinds.
    """
    rows: dict[object, str] = {}
    for fam in families:
        for kind, kernel in fam.kernels:
            if kind not in kinds:
                continue
            if rows.setdefault(kernel, kind) != kind:
                raise RegistryError(f"effect family {fam.name!r}: kernel {getattr(kernel, '__name__', kernel)} "
                                    f"declared as {rows[kernel]!r} and {kind!r}")
    return tuple((kind, kernel) for kernel, kind in rows.items())


def kernel_code(table: tuple[tuple[str, object], ...], kernel, what: str) -> int:
    """The code of ``kernel`` in ``table`` (a :func:`kernel_table`: its row's index).

    Raises:
        ValueError: ``kernel`` is in no row: "``what`` kernel NAME is not declared in its effect
            family's kernels (EffectFamily.kernels); known: KIND NAME, ..."
    """
    for code, (_, fn) in enumerate(table):
        if fn is kernel:
            return code
    raise ValueError(f"{what} kernel {getattr(kernel, '__name__', kernel)!r} is not declared in its effect "
                     "family's kernels (EffectFamily.kernels); known: "
                     + ", ".join(f"{kind} {fn.__name__}" for kind, fn in table))
