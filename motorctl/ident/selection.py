"""Stage *select*: the stepwise selection of effects on one record, the nominal structure and
the hold decided on the way (:func:`run`), as a :class:`~motorctl.ident.records.Selection`.

Decision rule (docs/identification.md, "Decision rule"): a candidate effect, re-fitted *jointly*
with the nominal θ, is accepted only when all three agree:

1. held-out gain: the RMS of the 2-fold cross-validated residual over interleaved blocks
   (blocks of :data:`BLOCK_S`, assigned to the two folds by a fixed pseudo-random draw so that no
   periodic trajectory lands in one fold) drops by at least :data:`MIN_HELDOUT_GAIN`;
2. information criterion: BIC = M ln(SSE/M) + k ln M drops by at least :data:`MIN_BIC_DROP`
   (k counts the columns and the searched parameter);
3. plausibility: the effect's coefficients are significant (Wald statistic per column ≥
   :data:`MIN_WALD`), its force is of a physical size worth naming (the 99th percentile of
   |A1·Cβ| at least :data:`MIN_SIZE_SHARE` of the RMS input force and, when the gain A1 is known,
   :data:`MIN_SIZE_N`), its parameters are inside their physical range (searched parameter not at
   the edge of its grid, amplitudes below half the input range, a position-periodic force the
   same in both directions of motion, ...), the nominal θ stay physical (θ1 > 0, θ2, θ3
   not significantly negative), and no simpler account (a step, a drift, the residual's
   strongest line: :mod:`motorctl.ident.accounts`) explains as much.

Accepted effects are added one at a time (the best held-out gain first) and everything is
re-fitted, until no candidate passes (at most :data:`MAX_EFFECTS`). Then each selected effect is
judged again in the final model (backward elimination, :func:`motorctl.ident.stepwise.eliminate`);
the weakest that fails is dropped, and the forward selection resumes without it
(:data:`STEPWISE_ROUNDS` rounds at most). When a passing candidate of a family that looks alike
(:attr:`~motorctl.effects.base.EffectFamily.look_alike`) gains at least :data:`LOOK_ALIKE_SHARE`
of the selected one's held-out gain, the one kept is the one that leaves the lower held-out RMS
with the step's other candidates taken beside it (:func:`motorctl.ident.prune.look_ahead`), and
it carries the other in ``rivals``: the report says the record cannot tell them apart.

The candidate families come from the registry :data:`motorctl.effects.FAMILIES`; each family's
columns, search over its parameter and its own plausibility checks are in its module
(``motorctl/effects/<name>.py``), handed the fit stage (:class:`motorctl.ident.fit.Fits`) as
their :class:`~motorctl.effects.base.SearchContext`.

The driver of all the stages is :class:`motorctl.ident.select.Identifier`.
"""

from __future__ import annotations

import math
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace

import numpy as np

from motorctl.effects import family as effect_family
from motorctl.effects.input_delay import is_hold
from motorctl.ident import prune, stepwise
from motorctl.ident.checks import Judge
from motorctl.ident.idim import ls_cov
from motorctl.ident.records import Selection, searchable
from motorctl.ident.rules import (BLOCK_S, HOLD_GRID, LOOK_ALIKE_SHARE, MAX_EFFECTS, MIN_BIC_DROP,  # noqa: F401
                                  MIN_HELDOUT_GAIN, MIN_SIZE_N, MIN_SIZE_SHARE, MIN_WALD, STEPWISE_ROUNDS)


def run(fits, max_effects: int = MAX_EFFECTS, on_nominal=None, threads: int = 1) -> tuple[Selection, Judge]:
    """The selection on the record of ``fits`` (:class:`~motorctl.ident.fit.Fits` at the
    structure the record starts with), with the nominal structure and the hold decided on the
    way. ``threads``: threads searching the families of one step (the result does not depend on
    it). Returns (the :class:`~motorctl.ident.records.Selection`, the judge at its structure).

    θ5, θ6 are kept only when, with the selected effects, they lower the held-out residual
    by at least :data:`MIN_HELDOUT_GAIN` and are not significantly positive (the paper's force
    curve has A2, A3 ≤ 0; a positive cubic term absorbs something else); otherwise the
    selection is redone with θ1..θ4, and the reason says so.

    The hold of a CSV/MAT record (``setup.hold_estimated``) is estimated jointly with the
    effects: after the selection the best input delay of the final model (its effects, no found
    delay) is taken again on :data:`HOLD_GRID`; when it says otherwise than the nominal model
    did (hold or none), the whole selection is redone with that hold and kept if its held-out
    residual is lower.
    """
    start = fits.structure
    sel, judge = _with_structure(fits, max_effects, on_nominal, threads)
    if not fits.setup.hold_estimated:
        return sel, judge
    base = [t for t in sel.terms if not t.delay]
    best = float(HOLD_GRID[int(np.argmin(judge.fits.delay_sses(base, HOLD_GRID - judge.fits.zoh)))])
    hold = 0.5 if is_hold(best) else 0.0
    if hold == judge.fits.zoh:
        return sel, judge
    again, judge2 = _with_structure(judge.fits.at(replace(start, zoh=hold)), max_effects, on_nominal, threads)
    if again.final.heldout_rms < sel.final.heldout_rms:
        source = (f"estimated with the effects: the best input delay of the model with "
                  f"{', '.join(t.family for t in base) or 'no effect'} is {best:.2f} sample, "
                  + ("the zero-order hold of a sampled-data loop" if hold else "no hold")
                  + f" (the nominal model alone said: {sel.structure.zoh_source})")
        structure = replace(judge2.fits.structure, zoh_source=source)
        return replace(again, structure=structure), judge2.at(judge2.fits.at(structure))
    return sel, judge


def _with_structure(fits, max_effects: int, on_nominal, threads: int) -> tuple[Selection, Judge]:
    """The selection at the structure of ``fits``, θ5, θ6 kept or left out on the way (:func:`run`)."""
    sel, judge = select(fits, max_effects, on_nominal, threads)
    st = judge.fits.structure
    if st.n_theta != 6 or st.n_theta_forced:
        return sel, judge
    th = sel.final.fit.coef
    six = sel.final.heldout_rms
    # f_u(u)/u − 1 = θ5 r + θ6 r² at r = |u|max/2 and |u|max, with its standard deviation
    phi, _ = judge.fits.design(list(sel.terms))
    cov = ls_cov(phi, sel.final.fit.residual)[4:6, 4:6]
    r_max = fits.setup.u_reach
    rising = []
    for r in (0.5 * r_max, r_max):
        g = np.array([r, r * r])
        rising.append(float(g @ th[4:6]) > 3.0 * math.sqrt(max(float(g @ cov @ g), 0.0)))
    four = judge.fits.at(replace(st, n_theta=4)).evaluate(list(sel.terms)).heldout_rms
    gain = 1.0 - six / four
    if any(rising):
        reason = (f"; but with the effects modelled the fit gives theta5 = {th[4]:.3g} 1/V, "
                  f"theta6 = {th[5]:.3g} 1/V^2, a force constant that rises significantly with "
                  "|u| (the paper's force curve saturates, A2, A3 <= 0): the cubic terms absorb "
                  "something else, so theta1..theta4 are kept")
    elif gain < MIN_HELDOUT_GAIN:
        reason = (f"; but theta5, theta6 lower the held-out residual by only {100 * gain:.1f} % "
                  f"(< {100 * MIN_HELDOUT_GAIN:g} %), so theta1..theta4 are kept")
    else:
        return sel, judge
    return select(judge.fits.at(replace(st, n_theta=4, n_theta_reason=st.n_theta_reason + reason, fu=None)),
                  max_effects, on_nominal, threads)


def select(fits, max_effects: int = MAX_EFFECTS, on_nominal=None, threads: int = 1) -> tuple[Selection, Judge]:
    """One stepwise selection at the structure of ``fits``: forward steps (the families of a
    step searched in ``threads`` threads, handed out longest first: by the CPU time of each
    family's last search or, at the first step, by its
    :attr:`~motorctl.effects.base.EffectFamily.search_cost`; each family's search is independent
    of the others' and its numpy/scipy work releases the GIL, so the result does not depend on
    it), backward elimination, simplification,
    polish, doubt beside an unexplained structure, ambiguities and the thrust shape on the
    final model. ``on_nominal``: called with the nominal θ̂ (n_theta,) before the search
    starts (None: nothing). Returns (the Selection, the judge at its final structure)."""
    nominal = fits.evaluate([])
    # thrust shape f_u(u) = u + θ5 u|u| + θ6 u³ for the ripple family (the families' columns anew)
    fits = fits.at(replace(fits.structure, fu=fits.columns.thrust_shape(fits.p.u, nominal.fit.coef)), fresh=True)
    judge = Judge(fits)
    if on_nominal is not None:
        on_nominal(nominal.fit.coef[:fits.n_theta])
    base: list = []
    current = nominal
    researched: list = []
    steps = []
    accepted = []
    pool = ThreadPoolExecutor(max_workers=threads) if threads > 1 else None
    eliminated: list = []
    searched_with: dict = {}     # id(term) -> the terms selected when it was searched
    families = list(fits.families)
    # family -> CPU seconds of its last search and judgement (at first: its search_cost)
    cost = {name: effect_family(name).search_cost for name in families}
    step_base: list = []         # the terms in the model when the last step was searched
    for _ in range(STEPWISE_ROUNDS):
        out = {n for n, _ in eliminated}        # never taken again once dropped
        while len(base) < max_effects:
            residual = current.fit.residual
            step_base = list(base)
            todo = [fam for fam in families if fam not in out and searchable(fam, base)]

            def one(fam, base=base, residual=residual, current=current):
                t0 = time.thread_time()
                ev = judge.search(fam, base, residual)
                ev = None if ev is None else judge.judge(ev, current, base)
                cost[fam] = time.thread_time() - t0
                return ev
            if pool:
                # longest first (the CPU time of the family's last search; its search_cost at
                # the first step), so that the threads end together; the results keep todo's order
                order = sorted(range(len(todo)), key=lambda i: -cost[todo[i]])
                futures = {i: pool.submit(one, todo[i]) for i in order}
                found = [futures[i].result() for i in range(len(todo))]
            else:
                found = [one(f) for f in todo]
            cands = [c for c in found if c is not None]
            good = [c for c in cands if c.ok]
            if not good:
                steps.append(cands)
                break
            chosen = max(good, key=lambda c: c.gain)
            best = prune.look_ahead(judge, chosen, good, cands, base)
            # the chosen candidate carries its rivals in the step's list too
            picked = next(c for c in cands if c.term is best.term)
            steps.append([best if c is picked else c for c in cands])
            accepted.append((best, current.heldout_rms))
            searched_with[id(best.term)] = list(base)
            base = base + [best.term]
            current = best
            base, current = prune.polish_at_rest(judge, base, current, searched_with)
        base, accepted, current, dropped, again = stepwise.eliminate(judge, base, accepted, current, searched_with)
        researched += again
        if not dropped:
            break
        eliminated += dropped
    base, accepted, current, replaced = prune.simplify(judge, base, accepted, current)
    eliminated += replaced
    base, current = prune.polish(judge, base, current, searched_with)
    last = steps[-1] if steps else []
    fresh = stepwise.on_final(judge, last, step_base, base, current)
    # the strong-effects rule reads the step as searched too: a structure refused on its
    # physics that the model's last change took away may be what that change is fitting
    base, accepted, current, doubted = prune.doubt(judge, base, accepted, current,
                                                   last if fresh is last else last + fresh)
    if doubted:
        fresh = stepwise.on_final(judge, last, step_base, base, current)
    eliminated += doubted
    base, accepted, current, fresh, ambiguous = stepwise.ambiguities(judge, base, accepted, current, fresh, last,
                                                                      step_base)
    judge, base, current = stepwise.refit_thrust_shape(judge, base, current)
    if pool:
        pool.shutdown()
    sel = Selection(structure=judge.fits.structure, nominal=nominal, final=current, terms=tuple(base),
                    accepted=tuple(accepted), steps=tuple(tuple(s) for s in steps), eliminated=tuple(eliminated),
                    researched=tuple(researched), ambiguous=tuple(ambiguous), verdict_step=tuple(fresh))
    return sel, judge

