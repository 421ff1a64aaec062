"""Stage *judge*, after the selection: a name only where the effect's own values stand on their
own, on the values' model (:class:`~motorctl.ident.values.ValuesModel`).

* :func:`confirm_values`: an effect whose values the more exact model (the refit's) finds
  implausible or too small is taken out;
* :func:`travel_shared`: a lost motion beside a force of the travel since a reversal (a play,
  which no family models) is taken out;
* :func:`drop_unsupported`: an effect whose size is not told from zero is taken out. At least
  one of its family's size parameters
  (:attr:`~motorctl.effects.base.EffectFamily.size_parameters`: a force, a stiffness, a mass, a
  rate) must have a 95 % interval (:func:`motorctl.ident.uncertainty.fit_uncertainty`, the
  intervals the report states) that excludes 0 (:func:`motorctl.ident.rules.stands`). An
  interval that holds 0 never carries a name: when every size interval holds 0 the effect is
  taken out and reported with the reason (:func:`holds_zero`), as the selection's own refusals
  are, and the residual verdict then says what it leaves; when some stand and others do not,
  the effect is named by what stands (its family's
  :meth:`~motorctl.effects.base.EffectFamily.named_by`, e.g. "asymmetric viscous friction")
  and the others are not claimed (:func:`claims`).

Each takes the judge, the :class:`~motorctl.ident.records.Selection` and the values' model, and
returns new ones (:func:`drop_after`: the final model, the verdict's candidates and the values'
model made again without the effects taken out).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from motorctl.effects import family as effect_family
from motorctl.ident import rules
from motorctl.ident.records import Selection, found_in_measurement
from motorctl.ident.stepwise import on_final
from motorctl.ident.values import ValuesModel, of_selection, refit


def size_intervals(family: str, ci95: dict) -> list[tuple[str, float, float]]:
    """(name, lo, hi) of each finite 95 % interval in ``ci95`` ({name: [lo, hi] or [[lo, hi],
    ...]}, the summary's ``parameters_ci95``) of the family's size parameters."""
    return rules.intervals(ci95, tuple(effect_family(family).size_parameters))


def holds_zero(family: str, ci95: dict) -> str | None:
    """The reason an effect of ``family`` with the 95 % intervals ``ci95`` (the summary's
    ``parameters_ci95``) is not named: every interval of its size parameters holds 0; None when
    one excludes 0 (:func:`motorctl.ident.rules.stands`), or the family declares no size or the
    fit gives no interval of one."""
    found = size_intervals(family, ci95)
    if rules.outcome(passed=True, size_intervals=found) != "not named":
        return None
    said = ", ".join(f"{name} [{lo:.3g}, {hi:.3g}]" for name, lo, hi in found)
    return f"its size is not told from zero: the 95 % interval holds 0 ({said})"


def claims(family: str, ci95: dict) -> tuple[str, list[tuple[str, float, float]]]:
    """(the name the effect is reported by, [(parameter, lo, hi)] of its size parameters whose
    95 % interval holds 0 and which it does not claim) for a named effect of ``family``: the
    family's name when every size interval stands (or none is known), else its
    :meth:`~motorctl.effects.base.EffectFamily.named_by` the standing ones."""
    found = size_intervals(family, ci95)
    standing, not_standing = rules.stands(found)
    if not standing or not not_standing:
        return family, []
    return effect_family(family).named_by([name for name, _, _ in standing]), not_standing


def unsupported(terms, effect_intervals: list) -> list[tuple[str, str]]:
    """[(family, reason)] of the ``terms`` whose size is not told from zero (:func:`holds_zero`);
    ``effect_intervals``: per term, {"ci95": {...}} as :func:`~motorctl.ident.uncertainty.
    fit_uncertainty` gives them ("effects")."""
    out = []
    for term, eu in zip(terms, effect_intervals):
        why = holds_zero(term.family, eu.get("ci95", {}))
        if why:
            out.append((term.family, why))
    return out


def values_of(judge, sel: Selection) -> ValuesModel:
    """The values' model of ``sel``: the refit's (:func:`motorctl.ident.values.refit`) when one
    is needed, else the selection's own."""
    return refit(judge, sel) or of_selection(judge, sel)


def drop_after(judge, sel: Selection, dropped: list) -> tuple[Selection, ValuesModel]:
    """Take the selected effects of ``dropped`` ([(family, reason)]) out after the selection:
    the final model made again without them, the verdict's candidates as it sees them, each in
    ``eliminated`` with its reason, and the values' model made again. Returns (selection,
    values' model)."""
    names = {n for n, _ in dropped}
    keep = [i for i, t in enumerate(sel.terms) if t.family not in names]
    terms = [sel.terms[i] for i in keep]
    final = judge.fits.evaluate(terms)
    # the verdict's candidates as the new final model sees them
    step = on_final(judge, list(sel.verdict_step), list(sel.terms), terms, final)
    sel = replace(sel, terms=tuple(terms), accepted=tuple(sel.accepted[i] for i in keep), final=final,
                  verdict_step=tuple(step), eliminated=sel.eliminated + tuple(dropped))
    return sel, values_of(judge, sel)


def confirm_values(judge, sel: Selection, values: ValuesModel) -> tuple[Selection, ValuesModel]:
    """Each selected effect whose values are taken on the refit's model (``values.refitted``:
    the families with :attr:`~motorctl.effects.base.EffectFamily.values_on_current_loop` or
    ``values_on_stick_state``) must be plausible there too, by its family's
    :meth:`~motorctl.effects.base.EffectFamily.plausible` on the refit's coefficients. One
    that is not, the more exact model does not confirm: it is dropped (``eliminated``, with
    the refit's reason), and the final model and the refit are made again without it. A
    log recorded under C1 with a 50 µm play (default plant, seeds 1 and 4): a 3 % Stribeck
    hump at 0.28 m/s on the delay's model, −0.24 and −0.45 N on the current loop's, was named
    with that negative force. Every effect (the refit gives all their values) must also keep
    the size an effect is named at (:meth:`~motorctl.ident.checks.Judge.too_small`) there: on a
    clean plant with a 269 Hz mode (antiresonance 208 Hz, above the record's band) a 3.8 N/m
    spring taken on the rigid model was 0.27 N/m (0.1 N over the stroke) with the mode's force
    above the band in the values' model: the mode's inertia, not a spring."""
    if not values.refitted:
        return sel, values
    from motorctl.ident.checks import Judge
    ref = Judge(values.fits)
    bad = {}
    betas = values.fits.coef_split(values.final, values.terms)[1]
    for i, t in enumerate(values.terms):
        fam = effect_family(t.family)
        why = ref.implausible_in(values.terms, i) if fam.values_on_current_loop or fam.values_on_stick_state else []
        if t.cols is not None and not found_in_measurement(t):
            # every effect's values are the refit's: one whose force there is below the
            # size an effect is named at, the more exact model does not confirm either
            why = why + ref.too_small(float(np.percentile(np.abs(t.cols @ betas[i]), 99)))
        if why:
            bad[t.family] = why
    if not bad:
        return sel, values
    model = " and ".join(m for m, on in (("the current loop's lag modelled", values.on_current_loop),
                                          ("the stick state measured", values.stick_measured),
                                          ("a structural mode's force above the band in the model",
                                           values.band_mode is not None)) if on)
    return drop_after(judge, sel, [(name, f"not confirmed by the refit's model ({model}): " + "; ".join(why))
                                   for name, why in bad.items()])


def travel_shared(judge, sel: Selection, values: ValuesModel) -> tuple[Selection, ValuesModel]:
    """A name and a warning never share evidence: when the residual verdict of the final
    model reports a force of the travel since a reversal (less force against the motion over
    the first millimetres after each reversal) beside a selected effect of a
    :attr:`~motorctl.effects.base.EffectFamily.lost_motion` family, the two are a play in
    the drive, which no family models: its lost motion at the reversal is what the effect
    fitted, the travel's force what it left. A dead-zone of the input leaves no such force
    (the default plant's dead-zones at two sizes: no warning). The effect is dropped
    (``eliminated``, with the verdict's finding) and the final model and the refit are made
    again without it (:func:`drop_after`); the verdict then reports what it had taken. Plays
    of 50-200 µm on the load's coupling were named an amplifier dead-zone beside that warning
    (plants with their mode at 226 and 241 Hz; the default plant's 100 and 150 µm plays on a
    10 kg load)."""
    travel = next((f for f in judge.verdict(sel.final, sel.terms).findings if f["against"] == "travel"), None)
    bad = [t.family for t in sel.terms if effect_family(t.family).lost_motion] if travel else []
    if not bad:
        return sel, values
    return drop_after(judge, sel, [(name, f"a lost motion beside a force of the travel since a reversal "
                                         f"({travel['where']}): a play in the drive, which no family models, "
                                         "shows both") for name in bad])


def drop_unsupported(judge, sel: Selection, values: ValuesModel, gain: float | None) -> tuple[Selection, ValuesModel]:
    """Take out each selected effect whose size is not told from zero on the values' fit
    (:func:`unsupported` on the stated intervals,
    :func:`motorctl.ident.uncertainty.stated_uncertainty`), until none is left (``eliminated``
    gets the reason). Returns (selection, values' model)."""
    from motorctl.ident.uncertainty import stated_uncertainty
    for _ in range(len(sel.terms)):
        if not values.terms:
            break
        unc = stated_uncertainty(values.fits, values.final, values.terms, parameters_of(values, gain))
        bad = unsupported(values.terms, unc["effects"])
        if not bad:
            break
        sel, values = drop_after(judge, sel, bad)
    return sel, values


def parameters_of(values: ValuesModel, gain: float | None):
    """``params_of(term, h, beta)``: an effect's named parameters in physical units
    (:func:`motorctl.ident.effects.parameters` on the values' fit ``values``, with the record's
    ``gain`` [N/V]), and, as ``params_of.std(term, h, beta)``, the standard deviations a family
    gives of the parameters it fits again on part of the record
    (:meth:`~motorctl.effects.base.EffectFamily.refitted_std`): what
    :func:`~motorctl.ident.uncertainty.fit_uncertainty` takes."""
    from motorctl.ident import effects as fx
    th_v = values.fits.coef_split(values.final, values.terms)[0]

    def params_of(term, h, beta):
        return fx.parameters(term.family, h, beta, gain, values.p.fs, theta=th_v, p=values.p, fitted=values)

    def std(term, h, beta):
        return effect_family(term.family).refitted_std(h, beta, gain, theta=th_v, p=values.p, fitted=values)
    params_of.std = std
    return params_of
