"""Stage *select*, in the final model: effects doubted beside an unexplained structure, replaced
by a simpler case, polished, and the look-ahead between look-alike candidates."""

from __future__ import annotations

from motorctl.effects import family as effect_family
from motorctl.ident.records import _force, _found_in_measurement
from motorctl.ident.rules import LOOK_AHEAD, LOOK_AHEAD_DEPTH, LOOK_ALIKE_SHARE, MIN_HELDOUT_GAIN, STRICT_HELDOUT_GAIN


class Prune:
    """The final model's doubts, simplifications and polish (a part of
    :class:`~motorctl.ident.select.Identifier`)."""

    def _doubt(self, base: list, accepted: list, current: Evaluated, last_step: list):
        """When the final residual keeps a structure no family explains (:meth:`unexplained`),
        each selected effect must keep a held-out gain of :data:`STRICT_HELDOUT_GAIN` against
        the final model without it; the weakest that does not is dropped (and the rest judged
        again): beside an unmodelled effect, a family the record shows only weakly may be
        fitting a part of it. An error found in the measurement itself (the encoder's, in y − x)
        is exempt: the reading shows it, whatever its share of the force. Returns (terms,
        accepted, final, [(family, why)])."""
        dropped = []
        while base and self.unexplained(current, base, last_step):
            gains = []
            for i in range(len(base)):
                if _found_in_measurement(base[i]):
                    continue            # shown in the reading, not weakly in the force
                others = base[:i] + base[i + 1:]
                gains.append((1.0 - current.heldout_rms / self.evaluate(others).heldout_rms, i))
            if not gains:
                break
            gain, i = min(gains)
            if gain >= STRICT_HELDOUT_GAIN:
                break
            dropped.append((base[i].family, f"the residual keeps a structure no family explains, and this effect's "
                                            f"held-out gain in the final model is {100 * gain:.1f} % < "
                                            f"{100 * STRICT_HELDOUT_GAIN:g} %: it may be fitting a part of that "
                                            "structure"))
            base = base[:i] + base[i + 1:]
            accepted = accepted[:i] + accepted[i + 1:]
            current = self.evaluate(base)
        return base, accepted, current, dropped

    def _simpler_case(self, family: str, others: list, without: Evaluated | None = None) -> Evaluated | None:
        """The candidate of ``family``'s simpler special case
        (:attr:`~motorctl.effects.base.EffectFamily.simpler`, e.g. the linear slope of a friction
        shape) searched in the model of ``others`` (``without``: that model evaluated, when the
        caller has it) and judged there (:meth:`judge`); None when the family has none, it is
        not searched, ``others`` already hold it, or the record cannot show it."""
        alt = effect_family(family).simpler
        if alt is None or alt not in self.families or any(t.family == alt for t in others):
            return None
        without = self.evaluate(others) if without is None else without
        ev = self.search(alt, others, without.fit.residual)
        return None if ev is None else self.judge(ev, without, others)

    def _simplify(self, base: list, accepted: list, current: Evaluated):
        """A selected effect whose family has a simpler special case
        (:attr:`~motorctl.effects.base.EffectFamily.simpler`, e.g. a friction shape whose
        special case is the linear slope) is replaced by it when, in the final model, the
        simpler one is plausible and leaves a held-out residual less than
        :data:`MIN_HELDOUT_GAIN` above (the shape was taken at a step where other effects were
        not yet modelled). Returns (terms, accepted, final, [(family, why)] replaced)."""
        replaced = []
        for i, t in enumerate(list(base)):
            others = base[:i] + base[i + 1:]
            ev = self._simpler_case(t.family, others)
            if ev is None or not ev.ok or current.heldout_rms <= (1.0 - MIN_HELDOUT_GAIN) * ev.heldout_rms:
                continue                    # the shape beats the straight line: kept
            swapped = others[:i] + [ev.term] + others[i:]
            final = self.evaluate(swapped)
            replaced.append((t.family, f"replaced by its simpler case {ev.term.family}, which does as well in the "
                                       f"final model (held-out RMS {_force(final.heldout_rms, self.rec.gain)} against "
                                       f"{_force(current.heldout_rms, self.rec.gain)})"))
            base, current = swapped, final
            accepted = accepted[:i] + [(ev, accepted[i][1])] + accepted[i + 1:]
        return base, accepted, current, replaced

    def _polish_at_rest(self, base: list, current: Evaluated, searched_with: dict):
        """After an effect is taken: the effects that act at rest (stiction's band,
        :attr:`~motorctl.effects.base.EffectFamily.acts_at_rest`) polished with it
        (:meth:`_polish`), and when one changed, the effect just taken polished beside it. A band
        searched before a low-speed friction was modelled takes up part of it (default plant,
        Stribeck 20 N / 0.05 m/s: 1.65 mm/s, 0.33 mm/s beside the hump); left so until the end,
        the next steps take a phantom for what it leaves (an asymmetric friction). Returns
        (terms, final)."""
        rest = {t.family for t in base[:-1] if effect_family(t.family).acts_at_rest}
        if not rest or not self.current_loop:
            return base, current
        new, current = self._polish(base, current, searched_with, rest)
        if new != base:
            new, current = self._polish(new, current, searched_with, {base[-1].family})
        return new, current

    def _polish(self, base: list, current: Evaluated, searched_with: dict, families=None):
        """Each selected effect searched in a model other than the final one (effects were
        taken, dropped or replaced since) has its searched parameter taken again with the
        final model's other effects (:meth:`~motorctl.effects.base.EffectFamily.polish`), kept
        when it lowers the SSE: a period found before stiction was modelled sits where the
        unmodelled stiction pulled it. ``families``: only the effects of these families (None:
        all). Returns (terms, final)."""
        changed, sse = False, None
        for i, t in enumerate(list(base)):
            others = base[:i] + base[i + 1:]
            if families is not None and t.family not in families:
                continue
            if [id(o) for o in searched_with.get(id(t), [None])] == [id(o) for o in others]:
                continue                        # searched in this very model
            new = effect_family(t.family).polish(self, t, others)
            if new is None:
                continue
            trial = base[:i] + [new] + base[i + 1:]
            sse = self.sse(base) if sse is None else sse
            trial_sse = self.sse(trial)
            if trial_sse < sse:
                searched_with[id(new)] = others
                base, sse, changed = trial, trial_sse, True
        return (base, self.evaluate(base)) if changed else (base, current)

    def _look_ahead(self, best: Evaluated, good: list, cands: list, base: list) -> Evaluated:
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
        measurement itself (:func:`_found_in_measurement`) is chosen over force look-alikes.
        The chosen one carries the others in ``rivals``."""
        alike = effect_family(best.term.family).look_alike
        contenders = [best] + [c for c in good if c.term.family in alike and c.gain >= LOOK_ALIKE_SHARE * best.gain]
        measured = [c for c in contenders if _found_in_measurement(c.term)]
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
                left = [self.search(q.term.family, base + [c.term], c.fit.residual)
                        if effect_family(q.term.family).line_from_residual else q for q in partners]
                left = [q for q in left if q is not None]
                terms, rms = base + [c.term], c.heldout_rms
                for _ in range(LOOK_AHEAD_DEPTH):
                    if not left:
                        break
                    r, q = min(((self.evaluate(terms + [q.term]).heldout_rms, q) for q in left),
                               key=lambda p: p[0])
                    if r >= rms:
                        break
                    terms, rms = terms + [q.term], r
                    left.remove(q)
                return rms
            best = min(contenders, key=chain_rms)
        best.rivals = [(c.term.family, c.gain) for c in contenders if c is not best]
        return best
