"""The plain records passed between the identification's stages (docs/identification.md, "The
stages in the code"): the record as the stages see it (:class:`Setup`), the nominal model's
structure (:class:`Structure`), a model term (:class:`Term`), a candidate fitted and judged
(:class:`Evaluated`), a selection's outcome (:class:`Selection`) and what came after it
(:class:`Refined`), and the small functions on lists of terms.

All are frozen dataclasses: a stage reads what it is handed and returns new records, never
changes one it was given. They compare by identity (``eq=False``: they hold arrays), which the
selection relies on (a term is the same term when it is the same object).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from motorctl.effects import family as effect_family


@dataclass(frozen=True, eq=False)
class Setup:
    """One record prepared for the stages, whatever the model fitted on it.

    Attributes:
        rec: the checked :class:`~motorctl.ident.data.Record`. p: its prepared signals
            (:class:`~motorctl.ident.idim.Prepared`, without a thrust shape: ``p.fu`` None).
        friction: 'sf' or 'sign' (the Coulomb column's shape). families: the effect families
            searched (registry names, tuple). current_loop: the declared current loop is
            modelled in the input columns. loop_filter: its filter (b, a) or None.
            modelled_lag: its lag [samples] (0: none).
        fold: (M,) 0/1 the held-out fold of each decimated sample (blocks of
            :data:`~motorctl.ident.rules.BLOCK_S`). moving: (M,) bool the axis moves there.
        stroke: the position range [m]. u_reach: the largest input |u|max [V]. m: M, the
            decimated samples. hold_estimated: the zero-order hold is looked for in the data
            (a CSV/MAT record without ``--zoh-delay``).
        memo: what a family keeps of this record between its searches (the encoder's reading),
            by the family's own keys; the only mutable part, and only the families write it.
    """

    rec: object
    p: object
    friction: str
    families: tuple
    current_loop: bool
    loop_filter: object
    modelled_lag: float
    fold: np.ndarray
    moving: np.ndarray
    stroke: float
    u_reach: float
    m: int
    hold_estimated: bool
    memo: dict = field(default_factory=dict, repr=False)


@dataclass(frozen=True, eq=False)
class Structure:
    """The nominal model a selection fits its candidates beside.

    Attributes:
        n_theta: 4 or 6 (θ1..θ4, or with θ5, θ6 of the force curve). n_theta_reason: why.
        n_theta_forced: the user chose it (``--n-theta``): not decided on the way.
        zoh: the input's delay to the acceleration [samples] (the zero-order hold). zoh_source:
            how it was found.
        fu: the thrust shape f_u(u) [V] (N,) the ripple's and the drift's columns are built on
            (None: u). nuisance: decimated columns (M, k) appended to every regressor after the
            effects' (a structural mode's force above the band in the values' model), or None.
    """

    n_theta: int
    n_theta_reason: str
    zoh: float
    zoh_source: str
    n_theta_forced: bool = False
    fu: np.ndarray | None = None
    nuisance: np.ndarray | None = None


@dataclass(frozen=True, eq=False)
class Term:
    """One effect in the model: family, searched value h, decimated columns (M, k), input delay."""

    family: str
    h: float | None
    cols: np.ndarray | None
    delay: float = 0.0


@dataclass(frozen=True, eq=False)
class Evaluated:
    """A model fitted on the record (the nominal model plus terms) and, once judged, the verdict
    on its last term.

    Attributes:
        term: the candidate (the last of the model's terms; None: the nominal model).
        heldout_rms: the 2-fold held-out residual RMS [V]. fit: the LS fit on all samples
            (:class:`~motorctl.ident.idim.LSFit`). bic: its BIC.
        ok: the candidate passed the decision rule. reasons: why not (tuple of text).
        rivals: ((family, held-out gain), ...) of look-alike candidates nearly as good (the
            record cannot tell). gain: its held-out gain against the model without it [-].
        size: its force's 99th percentile [V] (None: not judged).
    """

    term: Term | None
    heldout_rms: float
    fit: object
    bic: float
    ok: bool = False
    reasons: tuple = ()
    rivals: tuple = ()
    gain: float = 0.0
    size: float | None = None


@dataclass(frozen=True, eq=False)
class Selection:
    """What the stepwise selection chose on one record.

    Attributes:
        structure: the nominal model it ran at. nominal: the nominal model's fit. final: the
            fit of the nominal model plus ``terms``.
        terms: the selected terms (tuple). accepted: ((Evaluated, held-out RMS before), ...)
            per term, in the same order. steps: the candidates of each forward step.
        eliminated: ((family, why), ...) selected and then dropped. researched: ((family, why,
            h before, h after), ...) failed in the final model, searched again and kept.
        ambiguous: the :class:`~motorctl.ident.ambiguity.Ambiguity` pairs taken out.
        verdict_step: the last step's candidates as the final model sees them (the residual
            verdict reads them).
    """

    structure: Structure
    nominal: Evaluated
    final: Evaluated
    terms: tuple
    accepted: tuple
    steps: tuple
    eliminated: tuple = ()
    researched: tuple = ()
    ambiguous: tuple = ()
    verdict_step: tuple = ()


@dataclass(frozen=True, eq=False)
class Refined:
    """What the joint refit after the selection changed: ``moved`` ((family, h before, h after),
    ...) and ``harmonics_cut`` ((family, harmonics kept, held-out gain of the rest), ...)."""

    moved: tuple = ()
    harmonics_cut: tuple = ()


def same_width(term: Term, like: Term) -> Term:
    """``term`` with no more columns than ``like`` (a term whose harmonics were cut,
    :func:`motorctl.ident.refine.prune_harmonics`, keeps its first columns wherever it is built
    again)."""
    c, k = term.cols, None if like.cols is None or like.cols.ndim != 2 else like.cols.shape[1]
    if c is None or k is None or c.ndim != 2 or c.shape[1] <= k:
        return term
    return Term(term.family, term.h, np.ascontiguousarray(c[:, :k]), term.delay)


def plain(h) -> bool:
    """h is a plain number (a period, a frequency), not None nor a float subclass carrying more."""
    return h is not None and type(h) in (float, int, np.float64)


def r_h(h):
    return None if h is None else float(h)


def found_in_measurement(term: Term) -> bool:
    """The term is an error of the measurement found in the measurement itself (its family's
    ``sized_in_reading``: the encoder's error fitted on y − x), not inferred from the force."""
    found = getattr(effect_family(term.family), "sized_in_reading", None)
    return found is not None and bool(found(term))


def h_key(h):
    """A hashable key of a searched value h: a float, None, or a float subclass carrying the
    basis in its attributes (position_friction_shape's knot grid)."""
    if h is None:
        return None
    extra = tuple(sorted(vars(h).items())) if hasattr(h, "__dict__") else ()
    return (type(h).__name__, float(h), extra)


def hold(terms) -> tuple[np.ndarray | None, str | None]:
    """(the product (M,) of the ``other_weight`` of the terms whose family holds the carriage at
    rest, the first such family); (None, None) when none does."""
    weight, holder = None, None
    for t in terms:
        w = effect_family(t.family).other_weight(t)
        if w is not None:
            weight = w if weight is None else weight * w
            holder = holder or t.family
    return weight, holder


def searchable(family: str, base) -> bool:
    """``family`` can be a candidate beside the terms ``base``: not among them, and not a
    second shift of the input where one is modelled (a found delay)."""
    return (not any(t.family == family for t in base)
            and not (effect_family(family).shifts_input and any(t.delay for t in base)))


def force_text(v: float, gain: float | None) -> str:
    """An input-unit size v [V] as text: in N when the gain [N/V] is known."""
    return f"{v * gain:.3g} N" if gain else f"{v:.3g} V"


def without(seq, i: int) -> list:
    """``seq`` as a list without its element ``i``."""
    return list(seq[:i]) + list(seq[i + 1:])

