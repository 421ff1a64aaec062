"""The effect-family interface: one physical effect in every place the project meets it.

The paper's model (eq. 4) lumps every unmodelled force into d̃. An *effect family* is one named
physical cause of part of d̃ (cogging, Stribeck friction, a spring, ...). Its module
(``motorctl/effects/<name>.py``) holds, together:

* **simulator** (``motorctl_drivers.sim``): :attr:`EffectFamily.sim_options`, the options model
  of ``axes.NAME.driver.effects.<name>``, and :meth:`EffectFamily.plant_term`, what the effect
  does to the simulated plant (a force, a factor on the thrust, a mass change, a transform of
  the input; see :class:`PlantTerm`);
* **identification** (``motorctl identify``, ``motorctl.ident``): :meth:`EffectFamily.columns`
  (regressor columns C(h)), :meth:`EffectFamily.search` (the searched parameter h and its grid),
  :meth:`EffectFamily.plausible` (physical checks), :meth:`EffectFamily.parameters` (names with
  units);
* **compensation** (the controller, eq. 13): :attr:`EffectFamily.comp_options`, the options model
  of ``axes.NAME.controller.compensation.<name>``, and :meth:`EffectFamily.compensator`, its term
  d̂_eff [V] evaluated inside the 5 kHz cycle; :meth:`EffectFamily.compensation` turns a fit into
  such an entry. An additive entry can be **adapted** (``adapt: true``): its linear
  coefficients β join θ̂ in the estimator (:class:`Adaptable`, :meth:`EffectFamily.adapt_basis`;
  default: the family cannot adapt and keeps fixed amplitudes). A family whose compensation is
  not an additive term (force ripple: a factor on the thrust; input delay: a preview of the
  desired trajectory) declares :attr:`EffectFamily.hook_options` and
  :meth:`EffectFamily.comp_hook` instead (:class:`CompHook`);
* **report**: :meth:`EffectFamily.shape`, the fitted term against its natural variable.

Sign conventions, the same for every family (F_eff: the force the effect adds to the plant):

    plant (motorctl_drivers.sim):   M ẍ = F_m(u)(1 + ripple) − B ẋ − A_f S_f(ẋ) + F_0 + F_eff      [N]
    identification (u = Φθ + Cβ):   F_eff = −A1·Cβ                                                [N]
    compensation:                   d̂_eff = F_eff / A1 = −Cβ, v_a1 = … − d̂_eff (eq. 13)          [V]

so the controller's input gains −d̂_eff = −F_eff/A1, which cancels the effect's force.
The families are found through the registry :data:`motorctl.effects.FAMILIES`; this module
imports nothing of the simulator, the identification or the application.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any, ClassVar, Protocol

import numpy as np
from pydantic import model_validator

from motorctl.schema import Pos, StrictModel

#: default half-width of the projection box of an adapted coefficient, as a fraction of the
#: entry's largest |β| (``beta_min``/``beta_max`` not given): β_j ± ADAPT_MARGIN·max|β|
ADAPT_MARGIN = 0.5
#: default Γ(0) entry of an adapted coefficient (``gamma0`` not given) [β-unit²/(V² s)]; a basis
#: column of size ~1 V per unit β (sin/cos, S_f) then adapts like θ̂4 (Γ0 = 500) but slower
ADAPT_GAMMA0 = 100.0
#: number of standard deviations of a fitted β in the box :meth:`EffectFamily.adapt_entry` emits
ADAPT_SIGMAS = 3.0


class PlantTerm:
    """What one effect does to one simulated axis, built once from its options (pure floats).

    A hook is None when the effect has no such part. :class:`motorctl_drivers.sim.AxisPlant`
    calls the hooks of all active effects in registry order, inside every RK4 stage:

    * ``thrust(fm, x, t) -> fm'``: the motor force F_m(u) [N] at position x [m] and plant time
      t [s], modified (ripple, a drifting force constant);
    * ``force(f, x, v, t, sf) -> f + F_eff``: adds the effect's force [N] at position x [m],
      velocity v [m/s], plant time t [s]; ``sf`` = S_f(v) (already computed by the plant);
    * ``mass(m, t) -> m'``: the moving mass [kg] at plant time t [s];
    * ``input(u) -> u'``: the input [V] that reaches the amplifier this period (called once per
      period, before integrating; may keep state, e.g. a delay line).

    A term built by :meth:`compiled` also carries its hook as a compiled kernel and a parameter
    row (``kernel``, ``params``): the plant then runs the whole period compiled
    (:mod:`motorctl.effects.plant`); a term of Python hooks only is run by the plant's Python
    path (the same equations).
    """

    __slots__ = ("force", "input", "kernel", "mass", "params", "thrust")

    def __init__(self, thrust: Callable | None = None, force: Callable | None = None,
                 mass: Callable | None = None, input: Callable | None = None):
        self.thrust, self.force, self.mass, self.input = thrust, force, mass, input
        self.kernel, self.params = None, None

    @classmethod
    def compiled(cls, hook: str, kernel: Callable, params) -> PlantTerm:
        """A term whose ``hook`` ('thrust', 'force' or 'mass') is a compiled kernel (numba,
        :data:`motorctl.jit.njit`) with its parameter row bound.

        Args:
            hook: which hook the kernel is. kernel: ``kernel(fm, x, t, p)`` (thrust),
                ``kernel(f, x, v, t, sf, p)`` (force) or ``kernel(m, t, p)`` (mass), the hook's
                arguments followed by the row p; declared in its family's
                :attr:`EffectFamily.kernels` (the plant refuses a kernel that is not).
            params: the row p (k,) of floats, in the kernel's documented order.
        Raises:
            ValueError: unknown hook.
        """
        p = np.ascontiguousarray(params, dtype=np.float64)
        if hook == "thrust":
            term = cls(thrust=lambda fm, x, t: kernel(fm, x, t, p))
        elif hook == "force":
            term = cls(force=lambda f, x, v, t, sf: kernel(f, x, v, t, sf, p))
        elif hook == "mass":
            term = cls(mass=lambda m, t: kernel(m, t, p))
        else:
            raise ValueError(f"hook {hook!r}: must be 'thrust', 'force' or 'mass'")
        term.kernel, term.params = kernel, p
        return term


class CompTerm:
    """One effect's compensation, compiled: a numba kernel (:data:`motorctl.jit.njit`) and its
    parameter row, built once from the entry's options. The servo cycle evaluates every term of
    an axis in compiled code (:mod:`motorctl.effects.compensation`); from Python a term is
    called like its kernel without the row.

    * ``add``: ``kernel(d, x_d, xd_dot, t, sf, p) -> d + d̂_eff(x_d, ẋ_d, t)`` [V], x_d [m],
      ẋ_d [m/s], t [s], sf = S_f(ẋ_d);
    * ``fill``: ``kernel(out, j, x, xdot, t, sf, p)`` writes the k basis columns c_i(x, ẋ, t)
      [V per β-unit] of an adapted entry into out[j:j + k], d̂_eff = Σ_i β_i c_i.

    Every kernel is declared in its family's :attr:`EffectFamily.kernels` (the compensation
    refuses one that is not). Floats only, no allocation: it runs inside the 5 kHz cycle.
    """

    __slots__ = ("kernel", "kind", "params")

    def __init__(self, kind: str, kernel: Callable, params):
        if kind not in ("add", "fill"):
            raise ValueError(f"compensation term kind {kind!r}: must be 'add' or 'fill'")
        self.kind, self.kernel = kind, kernel
        self.params = np.ascontiguousarray(params, dtype=np.float64)

    def __call__(self, *args):
        return self.kernel(*args, self.params)


class CompHook:
    """A compensation that is not an additive term d̂_eff (built once from its options, floats).

    * ``thrust``: the ripple fraction r̂(x) [-] at position x [m] as a :class:`CompTerm` of kind
      'add' (r̂ = kernel(0.0, x, 0.0, 0.0, 0.0, p)); the plant's thrust is F_m(u)(1 + r(x)), so
      the law divides v by 1 + r̂(x_d) before the inversion (eq. 9) and the estimator's thrust
      channels (u, u|u|, u³) are scaled by 1 + r̂(x) at the measured x;
    * ``preview_s``: the input delay τ [s] the law predicts over: the desired-compensation part
      v_a1 (eq. 13) is evaluated on the desired trajectory at t + τ, and the estimator pairs
      x2[k] with the input applied over that interval, u[k − 1 − round(τ/Ts)].
    """

    __slots__ = ("preview_s", "thrust")

    def __init__(self, thrust: CompTerm | None = None, preview_s: float = 0.0):
        self.thrust, self.preview_s = thrust, float(preview_s)


class Adaptable(StrictModel):
    """Keys every adaptable compensation entry has (mixed into a family's :attr:`comp_options`).

    With ``adapt: true`` the entry's linear coefficients β (:meth:`beta`, in the order of its
    coefficient keys) are adapted with θ̂ (eq. 7-8, 25-28 with φ extended by the basis columns);
    its searched parameter (period, frequency, v_s) and references stay fixed. False (default):
    the amplitudes are fixed, the behaviour of an entry without these keys.

    Attributes:
        adapt: adapt β (default False).
        beta_min, beta_max: the projection box of β (β-units, one entry per coefficient, in
            :meth:`beta` order); default β_j ∓ ADAPT_MARGIN·max|β| (``motorctl identify``
            writes them from the fit). Must contain β.
        gamma0: Γ(0) of β, one value for all or one per coefficient (> 0, ≤ rho_M);
            default ADAPT_GAMMA0.
    """

    adapt: bool = False
    beta_min: list[float] | None = None
    beta_max: list[float] | None = None
    gamma0: Pos | list[Pos] | None = None

    def beta(self) -> list[float]:
        """The entry's linear coefficients β (k,), in the order of its coefficient keys."""
        raise NotImplementedError

    def beta_names(self) -> list[str]:
        """Names of the β entries (k,), e.g. ``sin_V[0]`` (messages, reports)."""
        raise NotImplementedError

    def adapt_box(self) -> tuple[list[float], list[float]]:
        """(β_min, β_max) (k,) each: the given keys, else β ∓ ADAPT_MARGIN·max|β|."""
        b = self.beta()
        w = ADAPT_MARGIN * max((abs(v) for v in b), default=0.0)
        lo = list(self.beta_min) if self.beta_min is not None else [v - w for v in b]
        hi = list(self.beta_max) if self.beta_max is not None else [v + w for v in b]
        return lo, hi

    def adapt_gamma0(self) -> list[float]:
        """Γ(0) diagonal of β (k,)."""
        k = len(self.beta())
        g = self.gamma0
        if g is None:
            return [ADAPT_GAMMA0] * k
        return [float(g)] * k if isinstance(g, (int, float)) else list(g)

    @model_validator(mode="after")
    def _check_adapt(self):
        b = self.beta()
        k = len(b)
        names = ", ".join(self.beta_names())
        for key in ("beta_min", "beta_max"):
            v = getattr(self, key)
            if v is not None and len(v) != k:
                raise ValueError(f"{key}: needs {k} entries ({names}), got {len(v)}")
        if isinstance(self.gamma0, list) and len(self.gamma0) != k:
            raise ValueError(f"gamma0: needs one value or {k} ({names}), got {len(self.gamma0)}")
        if self.beta_min is not None or self.beta_max is not None or self.adapt:
            lo, hi = self.adapt_box()
            if self.adapt and self.beta_min is None and self.beta_max is None and all(v == 0.0 for v in b):
                raise ValueError("adapt: all coefficients are 0, so beta_min and beta_max must be given")
            for j in range(k):
                if not lo[j] <= b[j] <= hi[j]:
                    raise ValueError(f"beta_min/beta_max: {self.beta_names()[j]} = {b[j]:g} outside "
                                     f"[{lo[j]:g}, {hi[j]:g}]")
        return self


class Signals:
    """Signals regressor columns are built from (identification, report), each shape (N,).

    Attributes:
        x: position [m]. v: velocity [m/s]. a: acceleration [m/s²]. u: input [V]. t: time [s].
        fu: thrust shape f_u(u) = u + θ5 u|u| + θ6 u³ [V] (paper eq. 9) when the nominal θ5, θ6
            are fitted, else None (then the thrust is taken proportional to u).
        columns_single: False: columns on these signals are used as they are, in double
            precision (a prepared record's full-rate columns may be float32: it says True).
    """

    __slots__ = ("a", "fu", "t", "u", "v", "x")
    columns_single = False

    def __init__(self, x, v, a, u, t, fu=None):
        self.x, self.v, self.a, self.u, self.t, self.fu = x, v, a, u, t, fu

    @classmethod
    def decimated(cls, p) -> Signals:
        """The decimated signals of a prepared record ``p`` (x_d, v_d, a_d, u_d, t_d; fu None):
        cheap approximate columns for grid searches."""
        return cls(p.x_d, p.v_d, p.a_d, p.u_d, p.t_d)


class SearchContext(Protocol):
    """What a family's search, plausibility check and report shape may use of the identifier
    (:class:`motorctl.ident.fit.Fits`, the fit stage, provides it; families never import it).

    Attributes:
        p: the prepared record: full rate x, v, a, u, t (N,) and fu; decimated x_d, v_d, a_d,
            u_d, t_d (M,); fs [Hz] sample rate, nd decimation factor.
        stroke: position range of the record [m]. moving: bool (M,), the axis is moving.
        zoh: input-to-acceleration delay of the logged input [samples].
    """

    p: Any
    stroke: float
    moving: np.ndarray
    zoh: float

    def term(self, family: str, h) -> Any:
        """A model term of ``family`` at h with its exact decimated columns (and input shift)."""

    def best_over(self, family: str, grid, base: list, cols_fn=None) -> tuple[Any, np.ndarray]:
        """The term minimising the joint-LS SSE over ``grid`` (K,), and the SSE per value (K,).
        ``cols_fn(h)`` may give cheap approximate decimated columns (M, k) for the scan."""

    def best_between(self, family: str, lo: float, hi: float, base: list, xatol: float) -> Any:
        """The term minimising the joint-LS SSE for h in [lo, hi], found to within ``xatol``
        (bounded Brent search): for an SSE with one minimum in the interval."""

    def sse(self, terms: list) -> float:
        """SSE of the joint LS fit of the nominal model plus ``terms``."""

    def heldout_with(self, terms: list, cols: np.ndarray) -> float:
        """Held-out residual RMS [V] of the nominal model plus ``terms`` plus the decimated
        columns ``cols`` (M, k) that are no family's term (a simpler account to compare with)."""

    def heldout_rms(self, terms: list) -> float:
        """Held-out residual RMS [V] of the nominal model plus ``terms`` (the identifier's
        folds: what the decision rule compares)."""

    def evaluate(self, terms: list) -> Any:
        """The joint LS fit of the nominal model plus ``terms``: ``.fit.coef``, ``.fit.std``
        (nominal θ first, then each term's β), ``.heldout_rms``."""

    n_theta: int

    def delay_sses(self, base: list, grid, band=None, rows=None) -> np.ndarray:
        """Joint-LS SSE (K,) with the input shifted by ``grid`` (K,) extra samples; ``band``
        (lo, hi) [Hz]: fitted on that frequency band of the columns and target only; ``rows``
        (M,) bool: fitted on those decimated samples only."""

    def direction_agreement(self, term, base: list) -> float:
        """1 − ‖β₊ − β₋‖/(‖β₊‖ + ‖β₋‖) of the term fitted on forward / backward motion."""

    def speed_growth(self, term, base: list, period: float) -> float:
        """‖β_fast‖/‖β_slow‖ of the term fitted on the faster / slower half of the moving
        samples at which a spatial period [m] passes the position filter (NaN: too few)."""

    def speed_growth_interval(self, term, base: list, period: float) -> tuple[float, float, float]:
        """(r, lo, hi): :meth:`speed_growth` and its ±2 standard errors (NaN: too few)."""

    def target(self, delay: float) -> np.ndarray:
        """The decimated input u(t − delay·Ts) (M,)."""

    def design(self, terms: list) -> tuple[np.ndarray, np.ndarray]:
        """Regressor (M, p) of the nominal model plus ``terms`` (nominal θ first, then each
        term's columns) and its target (M,); after the run, ``terms`` holds the final model's."""


class EffectFamily:
    """Base of every effect family (see the module docstring). Subclasses set the class
    attributes and override the methods of the parts they have; one instance is registered in
    :data:`motorctl.effects.FAMILIES`.

    Attributes:
        name: registry name, also the YAML key under ``effects:`` and ``compensation:``.
        plant_force: the force F_eff the effect adds to the plant, as a formula (docs, report).
        searched: the searched parameter h and its unit (None: none; the columns are linear).
        sim_options: options model of ``axes.NAME.driver.effects.<name>`` (None: the family has
            no entry there, its simulator option lives elsewhere; see :meth:`sim_config`).
        example: a fragment of ``axes.NAME.driver`` switching the effect on, sized for the X axis
            of configs/gantry.yaml (M = 12.8 kg, A1 = 80 N/V, stroke 0.4 m); synthetic logs,
            tests and benchmarks use it.
        force_bounded_by_input: identification rejects a fitted term Cβ larger than half the
            input range (False for a term that is part of the inertial force, a mass step).
        shifts_input: the family delays the input instead of adding columns (at most one such
            term in a model).
        comp_options: options model of ``axes.NAME.controller.compensation.<name>`` (None: the
            effect is not an additive force in (x_d, ẋ_d, t) and cannot be compensated).
        comp_needs_sf: the compensation term uses S_f(ẋ_d) (computed once per cycle for all).
        compensation_rank: position of the term in ``CompensationConfig`` and in the sum d̂_eff
            (increasing; ties in registry order). Float addition is not associative: the ranks
            of the first six compensable families keep the sum bit-identical to the code before
            the registry; a new family keeps the default and comes after them.
        hook_options: options model of ``axes.NAME.controller.compensation.<name>`` for a
            compensation that is not an additive term (None: none); see :meth:`comp_hook`.
            Such a family is not :attr:`compensable` (not in ``CompensationConfig``); its key is
            added by :data:`motorctl.effects.compensation.CompensationSection`.
        kernels: the family's compiled kernels, ``(kind, kernel)`` rows: kind a plant hook
            ('thrust', 'force', 'mass', :meth:`PlantTerm.compiled`) or a compensation kind
            ('add', 'fill', :class:`CompTerm`). The code -> kernel tables of the plant
            (:data:`motorctl.effects.plant.PLANT_KERNELS`) and of the compensation
            (:data:`motorctl.effects.compensation.COMP_KERNELS`) are built from these, in registry
            order, so a family from another package runs compiled with no edit to motorctl; a
            term whose kernel is not declared here is refused when an axis is built. Empty
            (default): the family's terms, if any, are Python hooks (the plant's and the law's
            Python paths: the same equations, slower).
    """

    name: ClassVar[str] = ""
    plant_force: ClassVar[str] = ""
    searched: ClassVar[str | None] = None
    sim_options: ClassVar[type[StrictModel] | None] = None
    example: ClassVar[dict] = {}
    force_bounded_by_input: ClassVar[bool] = True
    shifts_input: ClassVar[bool] = False
    comp_options: ClassVar[type[StrictModel] | None] = None
    comp_needs_sf: ClassVar[bool] = False
    compensation_rank: ClassVar[int] = 100
    hook_options: ClassVar[type[StrictModel] | None] = None
    kernels: ClassVar[tuple[tuple[str, Callable], ...]] = ()
    #: CPU seconds of the family's search at a selection's first step, before any of its
    #: searches has been timed (the median over 14 logs of the default plant, one per family,
    #: 20 s at 5 kHz, one thread): only the order in which the identifier hands that step's
    #: searches to its threads, longest first (:data:`motorctl.ident.select.SEARCH_THREADS`).
    #: Unknown (default): first
    search_cost: ClassVar[float] = math.inf
    #: options of :attr:`example` that set the effect's size besides those in force units
    #: (what ``benchmarks/tune_families.py`` scales; e.g. a delay)
    size_options: ClassVar[tuple[str, ...]] = ()
    #: the names (prefixes) of :meth:`parameters`' keys that give the effect's size (a force, a
    #: stiffness, a mass, a rate; not where or when it acts): the effect is named only when the
    #: 95 % interval of at least one of them excludes 0 (:func:`motorctl.ident.judge.holds_zero`;
    #: those whose interval holds 0 are then not claimed, :meth:`named_by`).
    #: Empty (default): no such check
    size_parameters: ClassVar[tuple[str, ...]] = ()
    #: families whose force looks alike in tracking data (stiction and an amplifier dead-zone
    #: both hold the carriage at small input): when one of them is selected and the other
    #: explains nearly as much, the report says the record cannot tell them apart
    look_alike: ClassVar[tuple[str, ...]] = ()
    #: the effect acts where the axis is at rest or its input small (a holding force, a
    #: dead-zone): the residual verdict counts what is left near zero velocity and at small
    #: inputs as this effect's, not as an unexplained structure, once it is selected
    acts_at_rest: ClassVar[bool] = False
    #: the effect is a lost motion of the input at each reversal (a dead-zone's band): a play in
    #: the drive, which no family models, shows the same lost motion and, beside it, a force of
    #: the travel since the reversal; where the residual verdict reports that force beside the
    #: effect, the effect is not named (:func:`motorctl.ident.judge.travel_shared`)
    lost_motion: ClassVar[bool] = False
    #: the family's columns carry the drive's input before the amplifier's current loop (a
    #: dead-zone's lost band, the input stiction holds at rest): where identify models a
    #: declared current loop (:meth:`motorctl.ident.columns.Columns.input_columns`) they go
    #: through the loop as the input does
    before_current_loop: ClassVar[bool] = False
    #: a family whose model is this one's special case (a straight line is a friction shape
    #: with one segment): after the selection, a selected effect of this family is replaced by
    #: the simpler one when that leaves a held-out residual less than the identifier's
    #: held-out gain above (None: no such family)
    simpler: ClassVar[str | None] = None
    #: selected, the effects' values are fitted again on the declared current loop's model
    #: (:func:`motorctl.ident.values.refit`): this family's values depend on the
    #: few ms after each start, where the loop's first-order lag fitted as a pure delay leaves
    #: a difference it takes up (Stribeck's hump); the selection and the verdict stay as found
    values_on_current_loop: ClassVar[bool] = False
    #: searched again in that refit beside such a family: its value moves with what the loop's
    #: lag leaves at each start (stiction's band, the input delay beyond the loop)
    searched_on_current_loop: ClassVar[bool] = False
    #: this family's columns carry the identifier's thrust shape f_u(u) = u + θ5 u|u| + θ6 u³
    #: (``Prepared.fu``): the nominal fit's θ5, θ6 during the selection, the final model's after
    #: it (:func:`motorctl.ident.stepwise.refit_thrust_shape`)
    columns_on_thrust_shape: ClassVar[bool] = False
    #: selected beside a family that holds the carriage and whose hold the encoder's reading
    #: shows (:meth:`stick_state`), this family's values are taken again with the stick state
    #: measured: they are seen on the samples at each stop and breakaway (a dead-zone's offset)
    values_on_stick_state: ClassVar[bool] = False
    #: the effect is an error of the measurement, not a force (an encoder's interpolation
    #: error): the carriage moves as without it, and its columns stand for what it puts into
    #: the measured acceleration; a model simulated from the input leaves them out and reads
    #: its position through :meth:`reading_error`
    measurement: ClassVar[bool] = False
    #: the searched parameter is a line read off the current residual's spectrum (a frequency):
    #: where a strong effect is not modelled yet, its residual can hide the line, so when the
    #: step's candidate is a partner of the selection's look-ahead, the family is searched again
    #: beside each look-alike contender (:attr:`look_alike`), on that contender's residual
    line_from_residual: ClassVar[bool] = False

    def above_band(self, p) -> float | None:
        """The searched value h [the family's unit] at which this family's columns stand for a
        force above the band of the prepared record ``p``, whatever the effect's own h there (a
        structural mode's antiresonance at the top of its grid: its columns are then the load's
        inertia rising with frequency, m_l s²ẍ/ω_a²), for the values' model
        (:func:`motorctl.ident.values.mode_above_band`); None (default): the family
        has no such columns, or the record's band is too narrow for them."""
        return None

    def beyond_band(self, p, h) -> bool:
        """True when this family's searched value ``h`` in the prepared record ``p`` stands for
        a force above the record's band (:meth:`above_band`'s columns: the top of the grid),
        not an effect the band can locate; False (default) for a family without such columns."""
        return False

    def __repr__(self) -> str:
        return f"<effect family {self.name}>"

    @property
    def compensable(self) -> bool:
        """True when the family has a compensation term (:attr:`comp_options` set)."""
        return self.comp_options is not None

    @property
    def has_compensation(self) -> bool:
        """True when the controller can compensate the effect at all: an additive term
        (:attr:`compensable`) or a hook (:attr:`hook_options`: force ripple, input delay)."""
        return self.comp_options is not None or self.hook_options is not None

    # ------------------------------------------------------------------ simulator
    def sim_config(self, axis_options):
        """This family's options in a checked ``axes.NAME.driver`` section (a
        ``SimAxisOptions``), or None when the effect is off. Default: ``effects.<name>``."""
        return getattr(axis_options.effects, self.name, None)

    def plant_term(self, options, period_s: float) -> PlantTerm | None:
        """The effect's hooks into one simulated axis (see :class:`PlantTerm`), built once.

        Args:
            options: what :meth:`sim_config` returned (not None). period_s: control period [s].
        Returns:
            The hooks, or None when the options make the effect vanish.
        """
        raise NotImplementedError(f"effect family {self.name!r} has no simulator part")

    # ------------------------------------------------------------------ identification
    def columns(self, h, p) -> np.ndarray | None:
        """Regressor columns C(h), shape (N, k), input units (u = Φθ + Cβ), on the signals of
        ``p`` (:class:`Signals` or a prepared record); None when the family adds no columns."""
        raise NotImplementedError(f"effect family {self.name!r} has no regressor columns")

    def fitted(self, h, p, beta) -> np.ndarray | None:
        """The term's value C(h) β (N,) [input units] on the signals of ``p`` with a fit's
        coefficients ``beta`` (k',); the columns cut to the first k' (a selection that keeps
        fewer harmonics than :meth:`columns` gives holds the first ones' coefficients only).
        None when the family adds no columns."""
        cols = self.columns(h, p)
        if cols is None:
            return None
        b = np.asarray(beta, dtype=float)
        c = np.asarray(cols, dtype=float).reshape(len(cols), -1)
        return c[:, :len(b)] @ b

    def search(self, ctx: SearchContext, base: list, residual: np.ndarray):
        """The best term of this family given the already selected ``base`` terms.

        Args:
            ctx: the identifier (:class:`SearchContext`). base: selected terms.
            residual: decimated residual of the current model (M,) [V].
        Returns:
            (term, note): the term (from ``ctx.term`` / ``ctx.best_over``) and a reason that
            makes it implausible (e.g. the searched parameter at the edge of its grid) or None;
            or None when the record cannot show this effect. Default (no searched parameter):
            the term with its columns, no note.
        """
        return ctx.term(self.name, None), None

    def joint_values(self, h) -> np.ndarray | None:
        """Values of this family's searched parameter to try in the current loop's refit
        (:func:`motorctl.ident.values.refit`) instead of the selected ``h``, the
        ``values_on_current_loop`` families searched beside each, before the refit's sweeps:
        where two effects act at low speed their SSE can have two valleys, and the sweeps stay
        in the one the selection started in. Default: None (none tried)."""
        return None

    def polish(self, ctx: SearchContext, term, others: list):
        """The searched parameter of a selected ``term`` taken again in the final model, with
        the ``others`` selected effects (found after it, they may have biased its search), or
        None to keep it. Default: None (kept as searched).

        Returns:
            A term of this family (``ctx.best_between`` / ``ctx.term``) or None.
        """
        return None

    def recheck(self, ctx: SearchContext, term, base: list) -> str | None:
        """A check of :meth:`search` that depends on the other effects, made again on the final
        model by backward elimination (``base``: the final model's other terms): the reason the
        selected ``term`` fails it there, or None (default: nothing to check again). A term
        searched beside an effect that elimination later drops must still pass it without that
        effect."""
        return None

    def unnamed_evidence(self, ctx: SearchContext) -> str | None:
        """What the record shows of this effect on its own, outside the force model (a
        reading's error in y − x), when the selection did not name the family: the text the
        residual verdict reports as an unexplained structure, or None (default: nothing)."""
        return None

    def reading_error(self, h, beta: np.ndarray, theta1: float, x: np.ndarray) -> np.ndarray:
        """The error [m] (N,) a :attr:`measurement` effect adds to the reading at the carriage's
        positions ``x`` [m] (N,), from its fitted term (searched value h, coefficients beta (k,),
        θ1 [V·s²/m] of the same fit): the reading is x + this.

        Raises:
            NotImplementedError: the family is not a :attr:`measurement`.
        """
        raise NotImplementedError(f"{self.name} is a force, not an error of the reading")

    def searched_again(self, ctx: SearchContext, others: list):
        """:meth:`search` run again with ``others`` as the base (for a :meth:`polish`): its term,
        or None when the search finds none or notes its value (e.g. at its grid's edge)."""
        found = self.search(ctx, others, None)
        return None if found is None or found[1] else found[0]

    def plausible(self, ctx: SearchContext, term, beta: np.ndarray, theta: np.ndarray,
                  base: list) -> list[str]:
        """Reasons why a fitted term is not physically plausible (empty: plausible).

        Args:
            term: the candidate term (term.h the searched value). beta: its coefficients (k,).
            theta: the nominal θ̂ of the same joint fit (n_theta,) [θ1 V·s²/m, θ2 V·s/m, θ3 V,
                θ4 V, θ5 1/V, θ6 1/V²]. base: the terms selected before.
        """
        return []

    def parameters(self, h, beta: np.ndarray, gain: float | None, fs: float) -> dict:
        """Physical parameters of a fitted term, names ending in their unit: forces in N when
        the gain A1 [N/V] is known, else in V (force / A1). fs: sample rate [Hz]."""
        raise NotImplementedError

    def refitted_std(self, h, beta: np.ndarray, gain: float | None, theta=None, p=None, fitted=None) -> dict:
        """{name: σ} of the :meth:`parameters` this family fits again on part of the record
        (with ``fitted``, the identification's values' model: its ``terms``, ``final`` and
        ``fits``), in their units: the fitted β and h do not move them, so their interval comes
        from that fit. Default: none."""
        return {}

    def named_by(self, standing: list) -> str:
        """The name the effect is reported by when only some of its size parameters stand on
        their own (``standing``: the names of :attr:`size_parameters`' entries whose 95 %
        interval excludes 0; the others are not claimed). Default: the family's name."""
        return self.name

    def decimated_columns(self, h, p) -> np.ndarray | None:
        """The decimated columns (M, k) at h computed without filtering the full-rate ones, when
        the family knows them in closed form (a sine in time: the decimation's gain times the
        sine at the decimated instants); None (default): the identification decimates
        :meth:`columns` of the prepared record ``p``."""
        return None

    def input_shift(self, h) -> float:
        """Extra delay of the input [samples] this term applies (0 for additive columns)."""
        return 0.0

    def stick_state(self, p, h, check: bool = True):
        """For a family that holds the carriage at rest: its searched parameter h with the stick
        state measured from the record's raw reading (stiction's
        :class:`~motorctl.effects.stiction.StickState`), for
        :attr:`values_on_stick_state`'s refit; ``check``: only when the reading of the prepared
        record ``p`` shows the hold (a quantized reading, still within a count at rest). None
        (default): the family holds nothing, or the reading does not show it."""
        return None

    def other_weight(self, term) -> np.ndarray | None:
        """A weight (M,) in [0, 1] on the other terms' decimated columns while this term is in
        the model (a holding force at rest: the carriage feels no other force while held), or
        None (default: the term does not weigh the others)."""
        return None

    # ------------------------------------------------------------------ compensation
    def compensation(self, h, beta: np.ndarray, signals: Signals | None = None) -> dict | None:
        """The ``controller.compensation.<name>`` options (V units) of a fitted term, i.e.
        d̂_eff = −C(h)β, or None when the family cannot be compensated.

        Args:
            signals: the record's signals (:class:`Signals`, (N,) each), for a family whose
                columns leave a reference unidentifiable (θ3 or θ4 absorb it): the emitted
                reference is then the record's own (see :meth:`theta_shift`). None: 0.
        """
        return None

    def theta_shift(self, entry: dict, n_theta: int) -> np.ndarray:
        """Δθ (n_theta,) that re-expresses the jointly fitted nominal θ for the compensation
        ``entry`` (from :meth:`compensation`): the fit gives θ_fit and the term Cβ; writing the
        term about a reference r moves the constant part β·r between the term and θ3 or θ4, so
        the θ̂(0) that goes with ``entry`` is θ_fit + Δθ. Default: zeros (no reference)."""
        return np.zeros(n_theta)

    def compensation_for(self, options, a1: float) -> dict:
        """The ``controller.compensation.<name>`` options that cancel a known simulated effect
        ``options`` (a :attr:`sim_options` instance) on a plant with force gain a1 [N/V]:
        d̂_eff = F_eff / a1.

        Raises:
            NotImplementedError: the family is not compensable.
        """
        raise NotImplementedError(f"effect family {self.name!r} cannot be compensated")

    def compensator(self, options) -> CompTerm:
        """The compensation term, built once from ``options`` (a :attr:`comp_options` instance):
        a :class:`CompTerm` of kind 'add', ``term(d, x_d, xd_dot, t, sf) -> d + d̂_eff(x_d, ẋ_d,
        t)`` [V], with x_d [m], ẋ_d [m/s], t [s] and sf = S_f(ẋ_d).

        Raises:
            NotImplementedError: the family is not compensable.
        """
        raise NotImplementedError(f"effect family {self.name!r} cannot be compensated")

    def adapt_basis(self, options) -> CompTerm | None:
        """The basis of an adapted entry, built once from ``options`` (a :attr:`comp_options`
        instance, :class:`Adaptable`): a :class:`CompTerm` of kind 'fill', ``term(out, j, x,
        xdot, t, sf)`` writes the k = len(options.beta()) columns c_i(x, ẋ, t) [V per β-unit]
        into out[j:j + k], so that d̂_eff = Σ_i β_i c_i (the term :meth:`compensator` adds with
        β = options.beta()); sf = S_f(ẋ).

        Default: None, the family cannot adapt (its entries keep fixed amplitudes; a
        :attr:`comp_options` without :class:`Adaptable` has no ``adapt`` key at all).
        """
        return None

    def adapt_entry(self, entry: dict, beta_std: list | None = None) -> dict:
        """``entry`` (a :meth:`compensation` result) with ``adapt: false`` and the projection
        box of its β written out, so that a user only flips ``adapt``: β ∓ max(ADAPT_SIGMAS·σ_j,
        ADAPT_MARGIN·max|β|), σ (k,) in :meth:`Adaptable.beta` order (None: margin only).
        Returns ``entry`` unchanged when the family cannot adapt."""
        opts = self.comp_options
        if opts is None or not issubclass(opts, Adaptable) or type(self).adapt_basis is EffectFamily.adapt_basis:
            return entry
        b = opts.model_validate(entry).beta()
        w = ADAPT_MARGIN * max((abs(v) for v in b), default=0.0)
        half = [max(w, ADAPT_SIGMAS * float(beta_std[j])) if beta_std is not None else w
                for j in range(len(b))]
        if not any(h > 0 for h in half) or not all(math.isfinite(h) for h in half):
            return entry
        return {**entry, "adapt": False, "beta_min": [v - h for v, h in zip(b, half)],
                "beta_max": [v + h for v, h in zip(b, half)]}

    def comp_hook(self, options) -> CompHook:
        """The non-additive compensation (:class:`CompHook`), built once from ``options`` (a
        :attr:`hook_options` instance).

        Raises:
            NotImplementedError: the family has no such compensation.
        """
        raise NotImplementedError(f"effect family {self.name!r} has no non-additive compensation")

    # ------------------------------------------------------------------ report
    def shape(self, ctx: SearchContext, h, beta: np.ndarray, gain: float | None):
        """The fitted term against its natural variable, unfiltered, for the report figure.

        Returns:
            (x (K,), y (K,), x label, y label with UNIT standing for N or V), or None.
        """
        return
