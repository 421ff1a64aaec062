"""The driver of the identification's stages on one record, :class:`Identifier` (docs/
identification.md, "The stages in the code"): it holds the records each stage returns and hands
them to the next; the stages are the modules' (:mod:`motorctl.ident.fit` opens the record,
:mod:`motorctl.ident.selection` selects, :mod:`motorctl.ident.refine`, :mod:`motorctl.ident.values`
and :mod:`motorctl.ident.judge` come after the selection, :mod:`motorctl.ident.explain` says what
it found). The decision rule's thresholds (:mod:`motorctl.ident.rules`) are re-exported here, as
they were when this module held the whole identification.
"""

from __future__ import annotations

import functools
import os

import numpy as np

from motorctl.effects.input_delay import HOLD_TOLERANCE, is_hold  # noqa: F401  (re-exported)
from motorctl.ident import judge as after
from motorctl.ident import probes, prune, refine
from motorctl.ident.checks import Judge
from motorctl.ident.columns import thrust_shape
from motorctl.ident.fit import start
from motorctl.ident.records import Evaluated, Refined, Selection, Term  # noqa: F401  (re-exported)
from motorctl.ident.rules import *  # noqa: F401,F403  (the decision rule's thresholds, re-exported)
from motorctl.ident.rules import MAX_EFFECTS
from motorctl.ident.selection import run as select_effects

#: threads searching the families of one selection step (:func:`motorctl.ident.selection.select`;
#: the result does not depend on it): read at each :meth:`Identifier.run`
SEARCH_THREADS = min(2, os.cpu_count() or 1)


def _read(*path: str) -> property:
    """A read-only attribute of the driver: the record at ``path`` (attribute names) from it."""
    def get(self):
        out = self
        for name in path:
            out = getattr(out, name)
        return out
    return property(get)


class Identifier:
    """The driver of the identification's stages on one record: it holds the records each stage
    returns and hands them to the next; all the work is the stages'.

    Args:
        rec, n_theta, friction, fq, nd, families, seed, zoh_delay, current_loop: the record and
            how it is opened and fitted, as :func:`motorctl.ident.fit.start` takes them.
        on_nominal: called with the nominal θ̂ (n_theta,) each time the nominal model is
            fitted, before the effect search starts (e.g. to start a closed-loop run with it
            meanwhile); None: nothing.

    Raises:
        ValueError: unknown friction shape or effect family.

    Attributes:
        fits: the fit stage at the current structure (:class:`~motorctl.ident.fit.Fits`).
        judge: the judge on it (:class:`~motorctl.ident.checks.Judge`). selection: the
            :class:`~motorctl.ident.records.Selection` (None before :meth:`run`). refined: the
            joint refit's :class:`~motorctl.ident.records.Refined`. values: the values' model
            (:class:`~motorctl.ident.values.ValuesModel`, None before :meth:`find_values`).

    The fit stage's methods (``evaluate``, ``coef_split``, ``term``, ``design``, ...) and the
    judge's (``verdict``, ``implausible_in``, ...) are reached through it as before.
    """

    def __init__(self, rec, n_theta: int | None = None, friction: str = "sf", fq: float | None = None,
                 nd: int | None = None, families=None, seed: int = 0, zoh_delay: float | None = None,
                 on_nominal=None, current_loop: bool = False):
        self.fits = start(rec, n_theta=n_theta, friction=friction, fq=fq, nd=nd, families=families, seed=seed,
                          zoh_delay=zoh_delay, current_loop=current_loop)
        self.judge = Judge(self.fits)
        self.on_nominal = on_nominal
        self.selection = None
        self.refined = Refined()
        self.values = None

    # the stages, in order
    def run(self, max_effects: int = MAX_EFFECTS) -> "Identifier":
        """Stage *select* (:func:`motorctl.ident.selection.run`, :data:`SEARCH_THREADS` threads).
        Returns self."""
        self.selection, self.judge = select_effects(self.fits, max_effects, self.on_nominal, SEARCH_THREADS)
        self.fits = self.judge.fits
        return self

    def joint_refit(self) -> "Identifier":
        """The searched parameters refitted jointly (:func:`motorctl.ident.refine.joint_refit`)."""
        self.selection, self.refined = refine.joint_refit(self.judge, self.selection)
        return self

    def refit(self):
        """The values' model a refit gives (:func:`motorctl.ident.values.refit`), or None."""
        from motorctl.ident.values import refit
        return refit(self.judge, self.selection)

    def find_values(self) -> "Identifier":
        """The values' model (:func:`motorctl.ident.judge.values_of`)."""
        self.values = after.values_of(self.judge, self.selection)
        return self

    def confirm_values(self) -> "Identifier":
        """:func:`motorctl.ident.judge.confirm_values`."""
        self.selection, self.values = after.confirm_values(self.judge, self.selection, self._values())
        return self

    def travel_shared(self) -> "Identifier":
        """:func:`motorctl.ident.judge.travel_shared`."""
        self.selection, self.values = after.travel_shared(self.judge, self.selection, self._values())
        return self

    def drop_unsupported(self) -> "Identifier":
        """:func:`motorctl.ident.judge.drop_unsupported`."""
        self.selection, self.values = after.drop_unsupported(self.judge, self.selection, self._values(),
                                                             self.rec.gain)
        return self

    def drop_after(self, dropped: list) -> "Identifier":
        """:func:`motorctl.ident.judge.drop_after` of ``dropped`` ([(family, reason)])."""
        self.selection, self.values = after.drop_after(self.judge, self.selection, dropped)
        return self

    def _values(self):
        """The values' model: the one :meth:`find_values` set, else the selection's own."""
        from motorctl.ident.values import of_selection
        return self.values if self.values is not None else of_selection(self.judge, self.selection)

    # what the records hold, read through the driver (the fit stage's own, rec, setup,
    # structure, p, n_theta, zoh, ..., through __getattr__)
    n_theta_reason, zoh_source = (_read("fits", "structure", n) for n in ("n_theta_reason", "zoh_source"))
    u_reach = _read("fits", "setup", "u_reach")
    nominal, steps, accepted, eliminated, researched, ambiguous, verdict_step = (
        _read("selection", n) for n in ("nominal", "steps", "accepted", "eliminated", "researched", "ambiguous",
                                        "verdict_step"))
    joint_moved, harmonics_cut = _read("refined", "moved"), _read("refined", "harmonics_cut")

    @property
    def families(self) -> list:
        return list(self.fits.families)

    @property
    def terms(self) -> list:
        return list(self.selection.terms)

    @terms.setter
    def terms(self, terms) -> None:
        from dataclasses import replace
        self.selection = replace(self.selection, terms=tuple(terms))

    @property
    def final(self):
        return self.selection.final

    @final.setter
    def final(self, ev) -> None:
        from dataclasses import replace
        self.selection = replace(self.selection, final=ev)

    @property
    def refitted(self):
        """The values' model when it is a refit's (else None)."""
        return self.values if self.values is not None and self.values.refitted else None

    @refitted.setter
    def refitted(self, values) -> None:
        self.values = values

    @functools.cached_property
    def saturation(self) -> dict | None:
        """Where the input sits at its limit (:func:`~motorctl.ident.idim.input_saturation`;
        None: nowhere): reported, the fit unchanged."""
        from motorctl.ident.idim import input_saturation
        return input_saturation(self.p.u, self.p.fs, self.rec.u_limit)

    def thrust_shape(self, u: np.ndarray, theta: np.ndarray) -> np.ndarray | None:
        """:func:`motorctl.ident.columns.thrust_shape` at this record's structure."""
        return thrust_shape(self.n_theta, self.u_reach, u, theta)

    explained_shares = probes.explained_shares

    def _doubt(self, base, accepted, current, last_step):
        """:func:`motorctl.ident.prune.doubt` with this identifier's judge."""
        return prune.doubt(self.judge, list(base), list(accepted), current, last_step)

    def _simplify(self, base, accepted, current):
        """:func:`motorctl.ident.prune.simplify` with this identifier's judge."""
        return prune.simplify(self.judge, list(base), list(accepted), current)

    def __getattr__(self, name: str):
        # the fit stage's read-outs and the judge's, as the identifier offered them before
        if name.startswith("__") or name in ("fits", "judge"):
            raise AttributeError(name)
        for part in (self.fits, self.judge):
            try:
                return getattr(part, name)
            except AttributeError:
                pass
        raise AttributeError(f"{type(self).__name__!s} has no attribute {name!r}")
