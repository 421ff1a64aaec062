"""Model compensation of effects found by ``motorctl identify``, added to the DCDIARC law.

The paper's model (eq. 4) lumps every unmodelled force into d̃. When identification traces
part of d̃ to a named physical effect, its term is compensated like the other model terms
(eq. 13): evaluated on the desired position x_d, the reference velocity ẋ_r and time t, in
input units (V, i.e. force / A1), and subtracted in v_a1:

    θ1 ẍ = u − θ2 ẋ − θ3 S_f(ẋ) + θ4 + θ5 u|u| + θ6 u³ + d_eff(x, ẋ, t) + d̃
    v_a1 = θ̂1 ẍ_d + θ̂2 ẋ_d + θ̂3 S_f(ẋ_d) − θ̂4 − d̂_eff(x_d, ẋ_r, t),   ẋ_r = ẋ_d − k1 e

ẋ_r is the velocity the sliding variable asks for (p = ẋ − ẋ_r, eq. 11; the reference
velocity of Slotine and Li's adaptive robot control, Int. J. Robotics Research 6(3), 1987). In
motion it is ẋ_d within k1 |e| (10 mm/s at 20 µm and k1 = 500 /s, against m/s); where ẋ_d is
0, a friction-like term (Stribeck, asymmetric, position-dependent, periodic friction, a
friction shape) then still pushes toward the target, in proportion to the error through S_f,
instead of vanishing while the carriage creeps in: with ẋ_d alone its value at rest is a
constant that d̂0 absorbs, and where the friction exceeds the breakaway the carriage sticks a
count or more short and C2 hunts (docs/identification.md §6). It uses the measured position
only (no differentiated velocity): a count's flicker moves ẋ_r by k1 · 0.5 µm. The paper's
own terms in θ̂ keep ẋ_d (desired compensation, eq. 13).

**Fixed** (default): the amplitudes come from the fit (the fast d̂0 term still absorbs what is
left); the estimator sees the input u + d̂_eff. **Adapted** (``adapt: true`` on an entry whose
family can adapt, :class:`motorctl.effects.base.Adaptable`): d_eff = Σ_j β_j c_j(x, ẋ, t), the
basis columns c_j join the regressor (φ extended, filtered by the same H_f, evaluated on the
measured x, ẋ in the estimator) and β̂ joins θ̂ (same LS, eq. 27-28, and box projection, eq. 7-8);
v_a1 subtracts Σ β̂_j c_j(x_d, ẋ_r, t).

Two families compensate without an additive term (:class:`motorctl.effects.base.CompHook`):
force ripple (v divided by 1 + r̂(x_d) before the inversion, eq. 9) and input delay (v_a1 on
the desired trajectory at t + τ).

YAML: ``axes.NAME.controller.compensation.<family>``. The keys and each family's term come from
the registry (:func:`motorctl.effects.compensable`, the family modules): this module composes
them. ``CompensationConfig`` has one key per additive family (the registry's
:func:`~motorctl.effects.compensable`); :data:`CompensationSection`, the schema of the
controller's section, adds one per family with :attr:`~motorctl.effects.base.EffectFamily.hook_options`.

Compiled: each family's term is a numba kernel with a parameter row
(:class:`~motorctl.effects.base.CompTerm`, its formula in its own module). An axis's terms are
one table (:attr:`Compensation.table`) that :func:`comp_value`, :func:`comp_fill` and
:func:`comp_thrust` evaluate; the table lives in the law's state block, so the compiled servo
cycle runs a compensated C1/C2 whole (``motorctl.control.dcdiarc.dcdiarc_comp_step``). Adding
a family with a compensation: declare its kernels in the family's
:attr:`~motorctl.effects.base.EffectFamily.kernels` (:data:`COMP_KERNELS` is built from the
registry, the compiled dispatch from it, :func:`motorctl.jit.dispatch`); a family whose term is
a Python callable (no :class:`~motorctl.effects.base.CompTerm`) keeps it, and the law then runs
from Python (the same arithmetic, slower). A term whose kernel is not in the table, or a code
outside it, is refused when :attr:`Compensation.table` is built; inside the compiled kernels an
unknown code would give NaN (the supervisor faults the axis), never another family's term.
numba caches these kernels beside their sources, keyed on this module's file: after editing a
family's kernel, touch this module.
"""

from __future__ import annotations

from functools import partial

import numpy as np
from pydantic import create_model

from motorctl.effects import FAMILIES, compensable, compensation_model
from motorctl.effects.registry import kernel_code, kernel_table
from motorctl.jit import check_code, dispatch, njit
from motorctl.model import s_f_scalar

_s_f = njit(s_f_scalar)

#: code -> (kind, compiled kernel) of every compensation term (:class:`~motorctl.effects.base.CompTerm`):
#: a term's code in the table is its row's index here. Built from the registry (each family's
#: :attr:`~motorctl.effects.base.EffectFamily.kernels` of kind 'add' or 'fill', in registry
#: order), so a family from another package is compensated in compiled code too.
COMP_KERNELS: tuple[tuple[str, object], ...] = kernel_table(FAMILIES.values(), ("add", "fill"))
#: the compiled kernels by code (:data:`COMP_KERNELS` without the kinds)
KERNELS = tuple(kernel for _, kernel in COMP_KERNELS)


#: ``check_comp_code(code, kind)``: ``code`` when it is a ``kind`` kernel's in :data:`COMP_KERNELS`; else
#: ValueError naming the known codes (:func:`motorctl.jit.check_code`)
check_comp_code = partial(check_code, COMP_KERNELS, what="compensation term")


@njit
def _unknown_add(c, d, x, v, t, sf, p):
    return np.nan


@njit
def _unknown_fill(c, out, j, x, v, t, sf, p):
    out[j] = np.nan


# the compiled dispatch by code, built from the table (a code outside it: NaN)
_add = dispatch([(i, k) for i, (kind, k) in enumerate(COMP_KERNELS) if kind == "add"], _unknown_add)
_fill = dispatch([(i, k) for i, (kind, k) in enumerate(COMP_KERNELS) if kind == "fill"], _unknown_fill)

# the table's head (:meth:`Compensation.table`): preview τ [s], S_f wanted by the additive terms,
# by the basis, the additive and the basis terms' counts, where the basis records start, where
# the thrust record starts (0: none)
T_PREVIEW, T_ADD_SF, T_FILL_SF, T_N_ADD, T_N_FILL, T_FILL_AT, T_THRUST_AT = range(7)
#: the table's head size; a record is (code, row length m, column offset j, the row's m floats)
T_HEAD = 7


@njit
def comp_value(tab, x, v, t):
    """d̂_eff [V] of the fixed terms of the table ``tab`` (:meth:`Compensation.table`) at the
    desired position x [m], velocity v [m/s] (the law passes the reference velocity ẋ_r) and
    time t [s]: the terms added to 0.0 in order."""
    sf = _s_f(v) if tab[T_ADD_SF] != 0.0 else 0.0
    d = 0.0
    at = T_HEAD
    for _ in range(int(tab[T_N_ADD])):
        m = int(tab[at + 1])
        d = _add(int(tab[at]), d, x, v, t, sf, tab[at + 3:at + 3 + m])
        at += 3 + m
    return d


@njit
def comp_fill(tab, out, x, v, t):
    """The adapted basis columns of ``tab`` at x [m], ẋ = v [m/s], t [s] into ``out`` (n_beta,)."""
    sf = _s_f(v) if tab[T_FILL_SF] != 0.0 else 0.0
    at = int(tab[T_FILL_AT])
    for _ in range(int(tab[T_N_FILL])):
        m = int(tab[at + 1])
        _fill(int(tab[at]), out, int(tab[at + 2]), x, v, t, sf, tab[at + 3:at + 3 + m])
        at += 3 + m


@njit
def comp_thrust(tab, x):
    """The ripple fraction r̂(x) [-] of ``tab`` at x [m] (0.0 without a thrust term)."""
    at = int(tab[T_THRUST_AT])
    if at == 0:
        return 0.0
    m = int(tab[at + 1])
    return _add(int(tab[at]), 0.0, x, 0.0, 0.0, 0.0, tab[at + 3:at + 3 + m])


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

    The terms of the configured families are built once here (in :func:`compensable` order)
    into :attr:`table`, their compiled form, which the servo cycle evaluates in compiled code
    (:func:`comp_value`, :func:`comp_fill`, :func:`comp_thrust`); the per-sample methods here
    evaluate the same table from Python (or, for a family whose term is a Python callable, not
    a :class:`~motorctl.effects.base.CompTerm`, its Python terms).

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
        table: the compiled form (float64, 1-D: :data:`T_HEAD`, then per term its kernel's code
            in :data:`COMP_KERNELS`, its row's length m, its first column, its row), or None.
    Raises:
        ValueError: ``adapt: true`` on a family that has no basis (:meth:`adapt_basis` None);
            a term whose kernel is not declared in its family's ``kernels`` (:data:`COMP_KERNELS`).
    """

    def __init__(self, cfg):
        self.cfg = cfg
        adds, fills = [], []
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
                adds.append(fam.compensator(opts))
                need_sf = need_sf or fam.comp_needs_sf
        self.n_beta = len(b0)
        self.beta0 = np.array(b0, dtype=float)
        self.beta_min = np.array(lo, dtype=float)
        self.beta_max = np.array(hi, dtype=float)
        self.gamma0 = np.array(g0, dtype=float)
        self.beta_names = names
        thrust = None
        self.preview_s = 0.0
        for fam in hooked():
            opts = getattr(cfg, fam.name, None)
            if opts is None:
                continue
            hook = fam.comp_hook(opts)
            if hook.thrust is not None:
                if thrust is not None:
                    raise ValueError(f"compensation.{fam.name}: a second thrust factor")
                thrust = hook.thrust
            if hook.preview_s:
                self.preview_s += hook.preview_s
        self._adds = tuple(adds)
        self._fills = tuple(fills)
        self._need_sf, self._fill_sf = need_sf, fill_sf
        self._thrust_term = thrust
        self.thrust = self._thrust if thrust is not None else None
        #: the compiled form (T_HEAD, then a record per term), read by :func:`comp_value`,
        #: :func:`comp_fill` and :func:`comp_thrust` (float64, 1-D); None when a term is a
        #: Python callable (no kernel): then the terms run from Python
        self.table = self._table()

    def _table(self) -> np.ndarray | None:
        adds, fills, thrust = self._adds, self._fills, self._thrust_term
        rows = [(term, 0) for term in adds] + list(fills) + ([(thrust, 0)] if thrust is not None else [])
        codes = [_code(term) for term, _ in rows]
        if None in codes:
            return None
        codes = [check_comp_code(code, term.kind) for (term, _), code in zip(rows, codes)]
        head = [0.0] * T_HEAD
        head[T_PREVIEW] = self.preview_s
        head[T_ADD_SF] = float(self._need_sf)
        head[T_FILL_SF] = float(self._fill_sf)
        head[T_N_ADD] = float(len(adds))
        head[T_N_FILL] = float(len(fills))
        sizes = [3 + term.params.size for term, _ in rows]
        head[T_FILL_AT] = float(T_HEAD + sum(sizes[:len(adds)]))
        if thrust is not None:
            head[T_THRUST_AT] = float(T_HEAD + sum(sizes[:-1]))
        tab = list(head)
        for (term, j), code in zip(rows, codes):
            tab += [float(code), float(term.params.size), float(j), *term.params]
        return np.array(tab, dtype=np.float64)

    @property
    def additive(self) -> bool:
        """True when there is a fixed additive term (:meth:`value` can be nonzero)."""
        return bool(self._adds)

    def value(self, x_d: float, xd_dot: float, t: float) -> float:
        """d̂_eff [V] of the fixed (not adapted) terms at the desired position x_d [m], velocity
        xd_dot [m/s] (the law passes the reference velocity ẋ_r) and time t [s]."""
        if self.table is not None:
            return comp_value(self.table, x_d, xd_dot, t)
        sf = s_f_scalar(xd_dot) if self._need_sf else 0.0
        d = 0.0
        for add in self._adds:
            d = add(d, x_d, xd_dot, t, sf)
        return d

    def fill(self, out: np.ndarray, x: float, xdot: float, t: float) -> None:
        """The adapted basis columns c(x, ẋ, t) into ``out`` (n_beta,) [V per β-unit]: d̂_eff of
        the adapted terms is β·c. x [m], ẋ [m/s], t [s]."""
        if self.table is not None:
            comp_fill(self.table, out, x, xdot, t)
            return
        sf = s_f_scalar(xdot) if self._fill_sf else 0.0
        for fill, j in self._fills:
            fill(out, j, x, xdot, t, sf)

    def _thrust(self, x: float) -> float:
        """r̂(x) [-] of the force ripple at position x [m]."""
        if self.table is not None:
            return comp_thrust(self.table, x)
        return self._thrust_term(0.0, x, 0.0, 0.0, 0.0)


def _code(term) -> int | None:
    """The code of ``term``'s kernel in :data:`COMP_KERNELS` (None: a Python callable, no kernel).

    Raises:
        ValueError: a kernel not declared in its family's ``kernels`` (not in the table)."""
    kernel = getattr(term, "kernel", None)
    return None if kernel is None else kernel_code(COMP_KERNELS, kernel, "compensation term")


__all__ = ["Compensation", "CompensationConfig", "CompensationSection", "comp_fill", "comp_thrust", "comp_value",
           "hooked"]
