"""After the selection: the selected effects' searched parameters refitted jointly and a
position-periodic term's higher harmonics pruned (:func:`joint_refit`: a
:class:`~motorctl.ident.records.Selection` in, a new one and a
:class:`~motorctl.ident.records.Refined` out)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from motorctl.effects import family as effect_family
from motorctl.effects.periodic import REFINE_SPAN, REFINE_TOL, PositionPeriodic
from motorctl.ident.records import Refined, Selection, Term, h_key, plain, r_h, without
from motorctl.ident.rules import JOINT_LOBES, JOINT_LOBE_POINTS, JOINT_MIN_DROP, JOINT_SWEEPS, MIN_HARMONIC_GAIN


def joint_refit(judge, sel: Selection) -> tuple[Selection, Refined]:
    """The selected effects refitted jointly after the selection: each effect's searched
    parameter taken again with every other selected effect in the model, Gauss-Seidel, for
    :data:`JOINT_SWEEPS` sweeps (or until nothing moves). A position period is searched over
    :data:`JOINT_LOBES` side lobes either way of the selected one (the SSE's lobes lie
    P²/L apart on a record whose moves span L, :func:`period_window`), a grid of
    :data:`JOINT_LOBE_POINTS` per lobe then Brent's method; the others by their family's
    :meth:`~motorctl.effects.base.EffectFamily.polish`. A change is kept when it leaves the
    effect plausible in the joint fit (:meth:`~motorctl.ident.checks.Judge.implausible_in`) and
    lowers the held-out RMS, or lowers the SSE without raising the held-out RMS (a polish may be
    a fixed point, not an SSE minimum: the drift's thrust shape θ5, θ6 taken again from the
    joint fit, default plant beside cogging: κ 10.4 % → 1.7 % off). Why: the selection
    searches each effect's parameter with the effects taken before it; the first one's was
    searched with the later ones unmodelled, and a periodogram peak can sit on a side lobe
    (default plant, cogging of one harmonic at a 17 mm period: 17.80 mm, its amplitude −12 %
    and a phantom second harmonic; on the true period the SSE is 42 % lower). One effect alone:
    only a period's tolerance narrowed (:func:`period_fine`; rigid plant, cogging alone: the
    period's 95 % interval held the truth on 3-4 of 10 fits at the selection's tolerance, 9-10
    after). Returns (the selection with the refitted terms and final model, what moved)."""
    fits = judge.fits
    terms = list(sel.terms)
    if not terms:
        return sel, Refined()
    sse = fits.sse(terms)
    held = sel.final.heldout_rms
    moved = []
    alone = len(terms) == 1
    for _ in range(1 if alone else JOINT_SWEEPS):
        changed = False
        for i, t in enumerate(list(terms)):
            others = without(terms, i)
            fam = effect_family(t.family)
            if isinstance(fam, PositionPeriodic) and plain(t.h):
                new = period_fine(fits, t, others) if alone else period_window(fits, t, others)
            elif alone:
                # searched with nothing else beside it: only its period's tolerance to narrow
                continue
            else:
                try:
                    new = fam.polish(fits, t, others)
                except (ValueError, ArithmeticError, np.linalg.LinAlgError):
                    new = None
            if new is None or new.cols is None and t.cols is not None:
                continue
            if h_key(new.h) == h_key(t.h) and new.delay == t.delay:
                continue
            trial = terms[:i] + [new] + terms[i + 1:]
            trial_sse = fits.sse(trial)
            ev = fits.evaluate(trial)
            # a lower held-out RMS, or a lower SSE without a higher held-out RMS (a family's
            # polish may be a fixed point rather than an SSE minimum: the drift's thrust shape)
            better = ev.heldout_rms < held or (trial_sse < sse * (1.0 - JOINT_MIN_DROP) and ev.heldout_rms <= held)
            if not better or judge.implausible_in(trial, i):
                continue
            moved.append((t.family, r_h(t.h), r_h(new.h)))
            terms, sse, held, changed = trial, trial_sse, ev.heldout_rms, True
        if not changed:
            break
    terms, cut = prune_harmonics(judge, terms, held)
    if moved or cut:
        sel = replace(sel, terms=tuple(terms), final=fits.evaluate(terms))
    return sel, Refined(moved=tuple(moved), harmonics_cut=tuple(cut))


def prune_harmonics(judge, terms: list, held: float) -> tuple[list, list]:
    """Each position-periodic effect's harmonics above the first kept only where the
    held-out data supports them: left out when keeping them lowers the held-out RMS by less
    than :data:`MIN_HARMONIC_GAIN` of it. The term then holds the first harmonic's columns (its
    β one sin/cos pair; the family's parameters and compensation take the shorter β).
    ``held``: the held-out RMS of ``terms``. Returns (terms, [(family, 1, gain)])."""
    cut = []
    for i, t in enumerate(list(terms)):
        fam = effect_family(t.family)
        if not isinstance(fam, PositionPeriodic) or t.cols is None or t.cols.ndim != 2 or t.cols.shape[1] <= 2:
            continue
        trial = terms[:i] + [Term(t.family, t.h, np.ascontiguousarray(t.cols[:, :2]), t.delay)] + terms[i + 1:]
        ev = judge.fits.evaluate(trial)
        gain = 1.0 - held / ev.heldout_rms
        if gain < MIN_HARMONIC_GAIN and not judge.implausible_in(trial, i):
            terms, held = trial, ev.heldout_rms
            cut.append((t.family, 1, float(gain)))
    return terms, cut


def period_fine(fits, term: Term, others: list) -> Term:
    """The position period minimising the joint SSE within twice the selection's tolerance
    of ``term.h`` (:meth:`~motorctl.effects.periodic.PositionPeriodic._refine`: 1/30 of its
    half-span, 0.1 % of P, some 25σ of a cogging period on a 20 s log), to a thousandth of
    that: one effect alone, whose lobe the selection found."""
    period = float(term.h)
    tol = REFINE_TOL * min(REFINE_SPAN, period / max(fits.stroke, 1e-9)) * period
    return fits.best_between(term.family, period - 2.0 * tol, period + 2.0 * tol, others, 1e-3 * tol)


def period_window(fits, term: Term, others: list) -> Term:
    """The position period minimising the joint SSE within :data:`JOINT_LOBES` side lobes of
    ``term.h`` (lobe width P²/L, L the stroke), with ``others`` in the model: a grid, then
    Brent's method around its best point."""
    period = float(term.h)
    lobe = period * period / max(fits.stroke, 1e-9)
    lo = max(period - JOINT_LOBES * lobe, 0.5 * period)
    hi = min(period + JOINT_LOBES * lobe, 1.5 * period)
    n = int(2 * JOINT_LOBES * JOINT_LOBE_POINTS) + 1
    grid = np.linspace(lo, hi, n)
    best, _ = fits.best_over(term.family, grid, others)
    step = (hi - lo) / (n - 1)
    return fits.best_between(term.family, float(best.h) - step, float(best.h) + step, others, 1e-3 * step)
