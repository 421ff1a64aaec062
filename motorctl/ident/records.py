"""The plain records passed between the identification's stages: a model term (:class:`Term`),
a candidate judged (:class:`Evaluated`), and the small functions on lists of terms."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from motorctl.effects import family as effect_family


@dataclass
class Term:
    """One effect in the model: family, searched value h, decimated columns (M, k), input delay."""

    family: str
    h: float | None
    cols: np.ndarray | None
    delay: float = 0.0


@dataclass
class Evaluated:
    term: Term
    heldout_rms: float
    fit: object            # LSFit on all data
    bic: float
    ok: bool = False
    reasons: list = field(default_factory=list)
    #: (family, held-out gain) of look-alike candidates nearly as good (the record cannot tell)
    rivals: list = field(default_factory=list)


def _same_width(term: Term, like: Term) -> Term:
    """``term`` with no more columns than ``like`` (a term whose harmonics were cut,
    :meth:`Identifier._prune_harmonics`, keeps its first columns wherever it is built again)."""
    c, k = term.cols, None if like.cols is None or like.cols.ndim != 2 else like.cols.shape[1]
    if c is None or k is None or c.ndim != 2 or c.shape[1] <= k:
        return term
    return Term(term.family, term.h, np.ascontiguousarray(c[:, :k]), term.delay)


def _plain(h) -> bool:
    """h is a plain number (a period, a frequency), not None nor a float subclass carrying more."""
    return h is not None and type(h) in (float, int, np.float64)


def _r_h(h):
    return None if h is None else float(h)


def _found_in_measurement(term: Term) -> bool:
    """The term is an error of the measurement found in the measurement itself (its family's
    ``sized_in_reading``: the encoder's error fitted on y − x), not inferred from the force."""
    found = getattr(effect_family(term.family), "sized_in_reading", None)
    return found is not None and bool(found(term))


def _h_key(h):
    """A hashable key of a searched value h: a float, None, or a float subclass carrying the
    basis in its attributes (position_friction_shape's knot grid)."""
    if h is None:
        return None
    extra = tuple(sorted(vars(h).items())) if hasattr(h, "__dict__") else ()
    return (type(h).__name__, float(h), extra)


def _hold(terms: list) -> tuple[np.ndarray | None, str | None]:
    """(the product (M,) of the ``other_weight`` of the terms whose family holds the carriage at
    rest, the first such family); (None, None) when none does."""
    weight, holder = None, None
    for t in terms:
        w = effect_family(t.family).other_weight(t)
        if w is not None:
            weight = w if weight is None else weight * w
            holder = holder or t.family
    return weight, holder


def _searchable(family: str, base: list) -> bool:
    """``family`` can be a candidate beside the terms ``base``: not among them, and not a
    second shift of the input where one is modelled (a found delay)."""
    return (not any(t.family == family for t in base)
            and not (effect_family(family).shifts_input and any(t.delay for t in base)))


def _force(v: float, gain: float | None) -> str:
    """An input-unit size v [V] as text: in N when the gain [N/V] is known."""
    return f"{v * gain:.3g} N" if gain else f"{v:.3g} V"
