"""Stage *select*, in the final model: effects doubted beside an unexplained structure, replaced
by a simpler case, polished, and the look-ahead between look-alike candidates.

Functions of a :class:`~motorctl.ident.checks.Judge` and the records of the selection under way:
the terms (list of :class:`~motorctl.ident.records.Term`), their ``accepted`` pairs
((:class:`~motorctl.ident.records.Evaluated`, held-out RMS before), ...) and the model's fit;
each returns new lists and records.
"""

from __future__ import annotations

from dataclasses import replace

from motorctl.effects import family as effect_family
from motorctl.ident.records import Evaluated, force_text, found_in_measurement, without
from motorctl.ident.rules import LOOK_AHEAD, LOOK_AHEAD_DEPTH, LOOK_ALIKE_SHARE, MIN_HELDOUT_GAIN, STRICT_HELDOUT_GAIN


def doubt(judge, base: list, accepted: list, current: Evaluated, last_step):
    """When the final residual keeps a structure no family explains
    (:meth:`~motorctl.ident.checks.Judge.unexplained`), each selected effect must keep a
    held-out gain of :data:`STRICT_HELDOUT_GAIN` against the final model without it; the
    weakest that does not is dropped (and the rest judged again): beside an unmodelled effect,
    a family the record shows only weakly may be fitting a part of it. An error found in the
    measurement itself (the encoder's, in y − x) is exempt: the reading shows it, whatever its
    share of the force. Returns (terms, accepted, final, [(family, why)])."""
    fits = judge.fits
    dropped = []
    while base and judge.unexplained(current, base, last_step):
        gains = []
        for i in range(len(base)):
            if found_in_measurement(base[i]):
                continue            # shown in the reading, not weakly in the force
            gains.append((1.0 - current.heldout_rms / fits.evaluate(without(base, i)).heldout_rms, i))
        if not gains:
            break
        gain, i = min(gains)
        if gain >= STRICT_HELDOUT_GAIN:
            break
        dropped.append((base[i].family, f"the residual keeps a structure no family explains, and this effect's "
                                        f"held-out gain in the final model is {100 * gain:.1f} % < "
                                        f"{100 * STRICT_HELDOUT_GAIN:g} %: it may be fitting a part of that "
                                        "structure"))
        base = without(base, i)
        accepted = without(accepted, i)
        current = fits.evaluate(base)
    return base, accepted, current, dropped


def simpler_case(judge, family: str, others: list, before: Evaluated | None = None) -> Evaluated | None:
    """The candidate of ``family``'s simpler special case
    (:attr:`~motorctl.effects.base.EffectFamily.simpler`, e.g. the linear slope of a friction
    shape) searched in the model of ``others`` (``before``: that model evaluated, when the
    caller has it) and judged there; None when the family has none, it is not searched,
    ``others`` already hold it, or the record cannot show it."""
    alt = effect_family(family).simpler
    if alt is None or alt not in judge.fits.families or any(t.family == alt for t in others):
        return None
    before = judge.fits.evaluate(others) if before is None else before
    ev = judge.search(alt, others, before.fit.residual)
    return None if ev is None else judge.judge(ev, before, others)


def simplify(judge, base: list, accepted: list, current: Evaluated):
    """A selected effect whose family has a simpler special case
    (:attr:`~motorctl.effects.base.EffectFamily.simpler`, e.g. a friction shape whose
    special case is the linear slope) is replaced by it when, in the final model, the
    simpler one is plausible and leaves a held-out residual less than
    :data:`MIN_HELDOUT_GAIN` above (the shape was taken at a step where other effects were
    not yet modelled). Returns (terms, accepted, final, [(family, why)] replaced)."""
    replaced = []
    gain = judge.fits.rec.gain
    for i, t in enumerate(list(base)):
        others = without(base, i)
        ev = simpler_case(judge, t.family, others)
        if ev is None or not ev.ok or current.heldout_rms <= (1.0 - MIN_HELDOUT_GAIN) * ev.heldout_rms:
            continue                    # the shape beats the straight line: kept
        swapped = others[:i] + [ev.term] + others[i:]
        final = judge.fits.evaluate(swapped)
        replaced.append((t.family, f"replaced by its simpler case {ev.term.family}, which does as well in the "
                                   f"final model (held-out RMS {force_text(final.heldout_rms, gain)} against "
                                   f"{force_text(current.heldout_rms, gain)})"))
        base, current = swapped, final
        accepted = accepted[:i] + [(ev, accepted[i][1])] + accepted[i + 1:]
    return base, accepted, current, replaced


def polish_at_rest(judge, base: list, current: Evaluated, searched_with: dict):
    """After an effect is taken: the effects that act at rest (stiction's band,
    :attr:`~motorctl.effects.base.EffectFamily.acts_at_rest`) polished with it
    (:func:`polish`), and when one changed, the effect just taken polished beside it. A band
    searched before a low-speed friction was modelled takes up part of it (default plant,
    Stribeck 20 N / 0.05 m/s: 1.65 mm/s, 0.33 mm/s beside the hump); left so until the end,
    the next steps take a phantom for what it leaves (an asymmetric friction). Only with the
    declared current loop modelled. Returns (terms, final)."""
    rest = {t.family for t in base[:-1] if effect_family(t.family).acts_at_rest}
    if not rest or not judge.fits.current_loop:
        return base, current
    new, current = polish(judge, base, current, searched_with, rest)
    if new != base:
        new, current = polish(judge, new, current, searched_with, {base[-1].family})
    return new, current


def polish(judge, base: list, current: Evaluated, searched_with: dict, families=None):
    """Each selected effect searched in a model other than the final one (effects were
    taken, dropped or replaced since) has its searched parameter taken again with the
    final model's other effects (:meth:`~motorctl.effects.base.EffectFamily.polish`), kept
    when it lowers the SSE: a period found before stiction was modelled sits where the
    unmodelled stiction pulled it. ``families``: only the effects of these families (None:
    all). ``searched_with`` ({id(term): the terms beside it when searched}) gets the new
    terms. Returns (terms, final)."""
    fits = judge.fits
    changed, sse = False, None
    for i, t in enumerate(list(base)):
        others = without(base, i)
        if families is not None and t.family not in families:
            continue
        if [id(o) for o in searched_with.get(id(t), [None])] == [id(o) for o in others]:
            continue                        # searched in this very model
        new = effect_family(t.family).polish(fits, t, others)
        if new is None:
            continue
        trial = base[:i] + [new] + base[i + 1:]
        sse = fits.sse(base) if sse is None else sse
        trial_sse = fits.sse(trial)
        if trial_sse < sse:
            searched_with[id(new)] = others
            base, sse, changed = trial, trial_sse, True
    return (base, fits.evaluate(base)) if changed else (base, current)


def look_ahead(judge, best: Evaluated, good: list, cands: list, base: list) -> Evaluated:
    """``best``, or a look-alike rival that explains nearly as much (within
    :data:`LOOK_ALIKE_SHARE` of its held-out gain) and leaves the lower held-out RMS on its
    way through the step's other candidates (the :data:`LOOK_AHEAD` best, and as many passing
    ones beyond them; one whose family reads its line off the residual,
    :attr:`~motorctl.effects.base.EffectFamily.line_from_residual`, searched again on each
    contender's residual): beside each contender the partner that lowers the held-out RMS
    most is taken, :data:`LOOK_AHEAD_DEPTH` times, and the lowest RMS on the way counts. A greedy
    step cannot tell stiction from a dead-zone while the current loop's lag is unmodelled;
    the pair can, and beside a small ripple only the three together (default plant, a 1.8 %
    ripple, held-out RMS in mV of input: a dead-zone 22.3 alone, 16.5 with the ripple, 17.3
    with the ripple and the lag; stiction 25.3, 16.9 and 4.5). A contender found in the
    measurement itself (:func:`~motorctl.ident.records.found_in_measurement`) is chosen over
    force look-alikes. Returns the chosen one with the others in ``rivals``."""
    fits = judge.fits
    alike = effect_family(best.term.family).look_alike
    contenders = [best] + [c for c in good if c.term.family in alike and c.gain >= LOOK_ALIKE_SHARE * best.gain]
    measured = [c for c in contenders if found_in_measurement(c.term)]
    if len(contenders) > 1 and measured:
        # an error found in the reading itself (y − x) is measured, not inferred from the
        # force: a force of position cannot put it there, while the reading's error puts its
        # ë into ÿ, which cogging or a ripple then fit (a ±1.5 µm error at 4 mm: cogging,
        # a ripple at 7.3 mm). The force families are judged again with it modelled.
        best = max(measured, key=lambda c: c.gain)
    elif len(contenders) > 1:
        names = {c.term.family for c in contenders}
        others = sorted((c for c in cands if c.term.family not in names
                         and not any(c.term.family in effect_family(n).look_alike for n in names)),
                        key=lambda c: -c.gain)
        partners = others[:LOOK_AHEAD] + [c for c in others[LOOK_AHEAD:] if c.ok][:LOOK_AHEAD]

        def chain_rms(c):
            # the contender and, LOOK_AHEAD_DEPTH times, the partner that lowers the held-out
            # RMS most beside what is taken: the lowest held-out RMS on the way. A partner
            # whose line is read off the residual is searched again on the contender's residual
            left = [judge.search(q.term.family, base + [c.term], c.fit.residual)
                    if effect_family(q.term.family).line_from_residual else q for q in partners]
            left = [q for q in left if q is not None]
            terms, rms = base + [c.term], c.heldout_rms
            for _ in range(LOOK_AHEAD_DEPTH):
                if not left:
                    break
                r, q = min(((fits.evaluate(terms + [q.term]).heldout_rms, q) for q in left),
                           key=lambda p: p[0])
                if r >= rms:
                    break
                terms, rms = terms + [q.term], r
                left.remove(q)
            return rms
        best = min(contenders, key=chain_rms)
    return replace(best, rivals=tuple((c.term.family, c.gain) for c in contenders if c is not best))
