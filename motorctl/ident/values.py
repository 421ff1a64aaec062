"""After the selection: the effects' values taken on a more exact model (the declared current
loop, the stick state, a structural mode above the band), and effects that model does not
confirm, or that share evidence with a play, taken out."""

from __future__ import annotations

import copy
import threading

import numpy as np

from motorctl.effects import family as effect_family
from motorctl.effects.input_delay import FoundDelay
from motorctl.ident.records import _found_in_measurement, _same_width
from motorctl.ident.rules import MIN_HELDOUT_GAIN, REFIT_SWEEPS


class Values:
    """The values' model and the confirmations on it (a part of
    :class:`~motorctl.ident.select.Identifier`)."""

    def confirm_values(self) -> "Identifier":
        """Each selected effect whose values are taken on the refit's model (:meth:`refit`,
        ``refitted``: the families with
        :attr:`~motorctl.effects.base.EffectFamily.values_on_current_loop` or
        ``values_on_stick_state``) must be plausible there too, by its family's
        :meth:`~motorctl.effects.base.EffectFamily.plausible` on the refit's coefficients. One
        that is not, the more exact model does not confirm: it is dropped (``eliminated``, with
        the refit's reason), and the final model and the refit are made again without it. A
        log recorded under C1 with a 50 µm play (default plant, seeds 1 and 4): a 3 % Stribeck
        hump at 0.28 m/s on the delay's model, −0.24 and −0.45 N on the current loop's, was named
        with that negative force. Every effect (the refit gives all their values) must also keep
        the size an effect is named at (:meth:`too_small`) there: on a clean plant with a 269 Hz
        mode (antiresonance 208 Hz, above the record's band) a 3.8 N/m spring taken on the rigid
        model was 0.27 N/m (0.1 N over the stroke) with the mode's force above the band in the
        values' model: the mode's inertia, not a spring. Returns self."""
        ref = self.refitted
        if ref is None:
            return self
        bad = {}
        betas = ref.coef_split(ref.final, ref.terms)[1]
        for i, t in enumerate(ref.terms):
            fam = effect_family(t.family)
            why = ref.implausible_in(ref.terms, i) if fam.values_on_current_loop or fam.values_on_stick_state else []
            if t.cols is not None and not _found_in_measurement(t):
                # every effect's values are the refit's: one whose force there is below the
                # size an effect is named at, the more exact model does not confirm either
                why = why + ref.too_small(float(np.percentile(np.abs(t.cols @ betas[i]), 99)))
            if why:
                bad[t.family] = why
        if not bad:
            return self
        model = " and ".join(m for m, on in (("the current loop's lag modelled", ref.loop_refit),
                                              ("the stick state measured", ref.stick_measured),
                                              ("a structural mode's force above the band in the model",
                                               getattr(ref, "band_mode", None) is not None)) if on)
        return self._drop_after([(name, f"not confirmed by the refit's model ({model}): " + "; ".join(why))
                                 for name, why in bad.items()])

    def drop_after(self, dropped: list) -> "Identifier":
        """Take the selected effects of ``dropped`` ([(family, reason)]) out after the selection
        (:meth:`_drop_after`: the final model, the verdict's candidates and the refit made again
        without them; ``eliminated`` gets each reason). Returns self."""
        return self._drop_after(dropped)

    def _drop_after(self, dropped: list) -> "Identifier":
        """Take the selected effects of ``dropped`` ([(family, reason)]) out after the selection:
        the final model made again without them, the verdict's candidates as it sees them, each
        in ``eliminated`` with its reason, and the refit made again (:meth:`refit`). Returns self."""
        names = {n for n, _ in dropped}
        keep = [i for i, t in enumerate(self.terms) if t.family not in names]
        before = self.terms
        self.terms = [self.terms[i] for i in keep]
        self.accepted = [self.accepted[i] for i in keep]
        self.final = self.evaluate(self.terms)
        # the verdict's candidates as the new final model sees them
        self.verdict_step = self._on_final(self.verdict_step, before, self.terms, self.final)
        self.eliminated = self.eliminated + list(dropped)
        self.refitted = self.refit()
        return self

    def travel_shared(self) -> "Identifier":
        """A name and a warning never share evidence: when the residual verdict of the final
        model reports a force of the travel since a reversal (less force against the motion over
        the first millimetres after each reversal) beside a selected effect of a
        :attr:`~motorctl.effects.base.EffectFamily.lost_motion` family, the two are a play in
        the drive, which no family models: its lost motion at the reversal is what the effect
        fitted, the travel's force what it left. A dead-zone of the input leaves no such force
        (the default plant's dead-zones at two sizes: no warning). The effect is dropped
        (``eliminated``, with the verdict's finding) and the final model and the refit are made
        again without it (:meth:`_drop_after`, as :meth:`confirm_values` does); the verdict then
        reports what it had taken. Plays of 50-200 µm on the load's coupling were named an
        amplifier dead-zone beside that warning (plants with their mode at 226 and 241 Hz; the
        default plant's 100 and 150 µm plays on a 10 kg load). Returns self."""
        travel = next((f for f in self.verdict(self.final, self.terms)["findings"] if f["against"] == "travel"), None)
        bad = [t.family for t in self.terms if effect_family(t.family).lost_motion] if travel else []
        if not bad:
            return self
        return self._drop_after([(name, f"a lost motion beside a force of the travel since a reversal "
                                       f"({travel['where']}): a play in the drive, which no family models, "
                                       "shows both") for name in bad])

    def refit(self) -> "Identifier | None":
        """The selected effects' values taken again on a more exact model (a new identifier, or
        a copy of this one; this one unchanged): the current loop the run log's config declares
        (``current_loop``) when a family with
        :attr:`~motorctl.effects.base.EffectFamily.values_on_current_loop` (Stribeck) was
        selected and the loop is not modelled already, and the stick state measured (the
        holding family's :meth:`~motorctl.effects.base.EffectFamily.stick_state`: stiction's
        :class:`~motorctl.effects.stiction.StickState`) when a family with
        :attr:`~motorctl.effects.base.EffectFamily.values_on_stick_state` (the dead-zone) was
        selected beside stiction on a reading that shows it (quantized, within a count at
        rest); else None.

        Without a declared loop (a CSV/MAT record, the rigid plant) the loop's model differs by
        Stribeck's S_f on the nominal Coulomb column's velocity and stiction's band searched
        beside the hump (``current_loop``'s other two changes): rigid plant, 20 N / 0.05 m/s,
        21.5 N / 0.0447 m/s → 20.0 N / 0.0493 m/s.
        The selection and the residual verdict stay this identifier's: they were calibrated
        on the model that fits the loop as an input delay (with the loop modelled the verdict
        warns on clean logs and misses a 50 µm backlash, a dead-zone is named stiction). The
        values are not: a pure delay is not the loop's first-order lag within the few ms after
        each start, where Stribeck's hump acts, and the hump took up the difference (default
        plant, F_s 20 N, v_s 0.05 m/s: 10.9 N, 0.070 m/s; on the loop's model 19.6 N,
        0.047 m/s; docs/identification.md, "Stribeck: the velocity of its column").

        The stick state: Karnopp stiction holds the carriage exactly still, so a sample is held
        only where the encoder's reading stands still too; the selection's weight w(ẋ) on the
        filtered velocity is a smooth stand-in for that switch, and a dead-zone's offset, seen
        on the samples crossing its band at each stop and breakaway, follows w's band (default
        plant, 20 mV: 23.9 mV at ×1; with the reading's stick state 18.3-19.8 mV, seeds 1-2,
        ×0.5 and ×1, and a lower SSE). Stiction's band is kept (its weight multiplies the
        measured state), the dead-zone searched again with it.

        The same effects (families and their other searched parameters) are built on the
        refit's model; the searched parameters of the families with ``values_on_current_loop``
        and ``searched_on_current_loop`` (stiction's band, which beside an unmodelled hump
        widens to take part of it; the input delay beyond the loop) on the loop's model, and
        those with ``values_on_stick_state`` with the stick state measured, are searched again
        there, each with the others in the model
        (:data:`REFIT_SWEEPS` sweeps when more than one; on the loop's model started from the
        least SSE of :meth:`_refit_jointly`), and everything is fitted jointly
        (IDIM-LS, as :meth:`evaluate`). A dead-zone's values are not taken on the loop's model
        alone: there its offset came out 33-45 % high (20 mV), stiction's band wider.

        A structural mode above the record's band (:meth:`mode_above_band`), when neither of the
        above asks for a refit: its broadband force is put into the values' model as
        :attr:`nuisance` columns (on a copy of this identifier), so that the effects' values are
        not what the rigid model makes of the load's inertia rising with frequency. Not beside
        the low-speed models: there the columns (s²ẍ, largest at each start and stop) took part
        of the forces those values are measured from (default plant, seed 1: the dead-zone's
        offset 19.8 → 8.9 mV for 20, Stribeck's F_s 19.6 → 19.0 N and v_s 0.048 → 0.053 m/s for
        20 N, 0.05 m/s). The default
        plant (350 Hz mode, its antiresonance 271 Hz, 40 % of the mass beyond it; X, 20 s, seed
        1): cogging beside a force-constant drift 11.87 / 4.44 N for 12 / 4 (+10.9 %, the
        input at ±10 V on 4.2 % of the samples, the rail-to-rail steps ringing the mode), with
        the term 12.02 / 4.08 N; cogging beside asymmetric friction 12.65 / 3.68 N and ΔF_c
        11.03 N for 10, with the term 12.08 / 3.71 N and 10.31 N; the held-out RMS 25-55 %
        lower.

        Returns:
            The refit identifier, its ``terms`` (list of :class:`Term`) and ``final``
            (:class:`Evaluated`) set, or None.
        """
        fams = [effect_family(t.family) for t in self.terms]
        loop = not self.current_loop and any(f.values_on_current_loop for f in fams)
        held = None             # the index of the term whose hold the reading shows
        if any(f.values_on_stick_state for f in fams):
            held = next((i for i, (f, t) in enumerate(zip(fams, self.terms))
                         if f.stick_state(self.p, t.h) is not None), None)
        stick = held is not None
        # the values taken on the low-speed models (the loop's lag, the stick state) stay on the
        # model they were measured on: beside them the mode's columns (s²ẍ, largest at each
        # start and stop) take part of the low-speed forces those values come from
        mode = None if loop or stick else self.mode_above_band()
        if not (loop or stick or mode):
            return None
        if loop:
            ctx = type(self)(self.rec, n_theta=self.n_theta, friction=self.friction, zoh_delay=self.zoh,
                             families=self.families, current_loop=True)
            ctx.p.fu = self.p.fu
        else:
            ctx = copy.copy(self)         # the same record and model: caches shared
            ctx._local = threading.local()
        if mode:
            ctx.nuisance = ctx.dec_cols(mode["family"], mode["columns_at_Hz"])
            ctx.band_mode = mode

        def built(i, h):
            fam = fams[i]
            if loop and fam.shifts_input:     # the lag beyond the modelled loop
                h = FoundDelay(max(float(h) - ctx.modelled_lag, 0.0), ctx.modelled_lag, True)
            if stick and i == held:
                h = fam.stick_state(ctx.p, h, check=False)
            return _same_width(ctx.term(fam.name, h), self.terms[i])

        terms = [built(i, t.h) for i, t in enumerate(self.terms)]
        again = [i for i, f in enumerate(fams)
                 if (loop and (f.values_on_current_loop or f.searched_on_current_loop))
                 or (stick and f.values_on_stick_state)]
        if loop:
            terms = self._refit_jointly(ctx, fams, terms, again, built)
        for _ in range(REFIT_SWEEPS if len(again) > 1 else 1):
            for i in again:
                fam = fams[i]
                found = fam.search(ctx, terms[:i] + terms[i + 1:], None)
                # a value at its grid's edge is not taken; a delay of 0 beyond the loop is; nor
                # one its family finds implausible in the refit's model (a search may return its
                # candidate for the selection's judge to refuse: a dead-zone whose band's input
                # is not lost whole, half-mode plant ×0.5: 0.226 V and a share of 0.46 for 75 mV)
                if found is not None and (not found[1] or fam.shifts_input):
                    trial = list(terms)
                    trial[i] = built(i, found[0].h) if stick and i == held else found[0]
                    if not ctx.implausible_in(trial, i):
                        terms = trial
        ctx.terms, ctx.final = terms, ctx.evaluate(terms)
        ctx.stick_measured = stick
        ctx.loop_refit = loop
        ctx.refit_families = sorted({terms[i].family for i in again} | ({terms[held].family} if stick else set()))
        return ctx

    def mode_above_band(self) -> dict | None:
        """The broadband force of a structural mode above the record's band, for the values'
        model (:meth:`refit`): the structural-mode family's term at the top of its grid
        (:func:`~motorctl.effects.structural_mode.f_max`, 1.5 × the decimated band's edge:
        above the band its columns are m_l s²ẍ/ω_a² whatever f_a, and the family's SSE barely
        moves over f_a there) fitted beside the final model's effects. Taken when it lowers the
        held-out RMS of the final model (:meth:`heldout`) by at least :data:`MIN_HELDOUT_GAIN`
        (the selection's own rule for a term to enter the model) with a positive load (β_G > 0,
        a mass); the family does not name it (f_a is not identifiable there, the residual verdict
        reports it as the band's limit), but the rigid model without it gives the load's
        inertia, which rises with frequency towards the antiresonance, to the effects whose
        columns carry the moves' high frequencies (cogging's harmonics at speed, the rail-to-rail
        steps of a saturated input): docs/identification.md, "Two effects at once".

        Returns:
            None (the family not searched or already selected, no final model, too few samples
            in motion, no gain, a load ≤ 0); else {"family": the family whose
            :meth:`~motorctl.effects.base.EffectFamily.above_band` columns these are (the
            structural mode's), "columns_at_Hz": f_a of the columns [Hz],
            "heldout_gain": the relative fall of the held-out RMS [-], "load_fraction": β_G/θ1
            at the columns' f_e [-] (m_l/M·(f_e/f_a)² with f_a the mode's own antiresonance,
            which the record does not tell)}.
        """
        fam, top = next(((f, h) for f in self.families if (h := effect_family(f).above_band(self.p)) is not None),
                        (None, None))
        final = getattr(self, "final", None)
        if fam is None or any(t.family == fam for t in self.terms) or final is None or self.moving.sum() < 50:
            return None
        term = self.term(fam, top)
        if term.cols is None:
            return None
        ev = self.evaluate(list(self.terms) + [term])
        gain = 1.0 - ev.heldout_rms / final.heldout_rms
        coef = ev.fit.coef
        if not gain >= MIN_HELDOUT_GAIN or not coef[-2] > 0.0 or not coef[0] > 0.0:
            return None
        return {"family": fam, "columns_at_Hz": float(top), "heldout_gain": float(gain),
                "load_fraction": float(coef[-2] / coef[0])}

    @staticmethod
    def _refit_jointly(ctx, fams: list, terms: list, again: list, built) -> list:
        """The refit's start: for a family among ``again`` with
        :meth:`~motorctl.effects.base.EffectFamily.joint_values` for its selected value, each of
        those with the ``values_on_current_loop`` families searched beside it; the least-SSE
        combination replaces ``terms`` when its SSE is lower (the sweeps then start there).
        Returns the terms."""
        for i in again:
            partners = [j for j in again if j != i and fams[j].values_on_current_loop]
            values = fams[i].joint_values(terms[i].h) if partners else None
            if values is None:
                continue
            best, best_sse = terms, ctx.sse(terms)
            for h in values:
                trial = list(terms)
                trial[i] = built(i, h)
                for j in partners:
                    found = fams[j].search(ctx, trial[:j] + trial[j + 1:], None)
                    if found is not None and not found[1]:
                        trial[j] = found[0]
                sse = ctx.sse(trial)
                if sse < best_sse:
                    best, best_sse = trial, sse
            terms = best
        return terms
