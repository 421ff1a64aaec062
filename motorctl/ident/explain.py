"""Stage *explain*: what ``motorctl identify`` says of a fit. The summary of an identification
(:func:`summarise`, the JSON of ``identify``): the nominal and augmented models with their
intervals, each named effect (by what stands of it, :func:`motorctl.ident.judge.claims`), the
candidates of every step, the residual verdict completed with the last step's candidates
refused on their physics (:func:`add_refused`) and the ambiguities; and the text report of a
summary (:func:`text_report`)."""

from __future__ import annotations

import math
from dataclasses import replace

from motorctl.ident import effects as fx
from motorctl.ident.idim import RAIL_MIN_S
from motorctl.ident.rules import MAX_EFFECTS, REFUSED_GAIN, outcome
from motorctl.ident.verdict import Verdict
from motorctl.model import THETA_NAMES

#: Horizon of the simulated-position fit % (motorctl.ident.simfit) [s].
SIM_WINDOW_S = 0.2
#: the share of the samples at the input's limit (:func:`motorctl.ident.idim.input_saturation`)
#: from which the report says the values may be off. Default plant, X, 20 s, the program's
#: a_max raised from 40 to 41-47 m/s²: up to 1.3 % at the limit cogging came within 2.4 % and
#: nothing else was named; from 1.8 % a phantom force ripple (seeds 1-2), from 3 % phantom
#: springs and warnings, at 4.5 % cogging and the encoder's error missed
#: (docs/identification.md, "Input saturation")
SATURATION_NOTE_SHARE = 0.01
#: the uncertainty's method, as the summary states it
UNCERTAINTY_METHOD = ("sigma = sqrt(s^2 + b^2): s the Newey-West HAC standard deviation (Bartlett kernel, Andrews' "
                      "AR(1) bandwidth), b the model error the record shows (the fit on the low band and on the "
                      "samples in motion against the fit on all, beyond its sampling variance, where significant "
                      "at 5 %); 95 % interval = value -+ 1.96 sigma")


def _r(x):
    return float(x) if x is not None and math.isfinite(float(x)) else None


def summarise(idf) -> dict:
    """The JSON object of ``identify`` for an identification (the driver
    :class:`~motorctl.ident.pipeline.Identifier` after its stages: its ``fits``, ``judge``,
    ``selection``, ``refined`` and values' model, :func:`~motorctl.ident.values.values_from`);
    residuals in N when a gain is known."""
    from motorctl.ident.ambiguity import summaries
    from motorctl.ident.judge import claims, parameters_of
    from motorctl.ident.simfit import simulation_fit
    from motorctl.ident.values import values_from
    from motorctl.ident.uncertainty import stated_uncertainty
    rec, fits, sel, judge = idf.rec, idf.fits, idf.selection, idf.judge
    values = values_from(idf)
    g = rec.gain or 1.0
    unit = "N" if rec.gain else "V"
    nt = fits.n_theta
    nom = sel.nominal
    # the σ of every value from the residual's own correlation (Newey-West; the white formula's
    # σ̂²(ΦᵀΦ)⁻¹ kept beside it as theta_std_white): motorctl.ident.uncertainty
    nom_unc = stated_uncertainty(fits, nom, [], None)
    st = fits.structure
    out = {
        "source": rec.source,
        "axis": rec.axis or None,
        "samples": int(rec.n),
        "period_s": rec.period_s,
        "filters": {"position_lowpass_Hz": fits.p.fq, "decimation": fits.p.nd, "zoh_delay_samples": st.zoh,
                    "zoh_source": st.zoh_source, "block_s": 0.25, "friction_shape": fits.friction},
        "residual_unit": unit,
        "gain_N_per_V": rec.gain,
        "nominal": {
            "theta": [float(v) for v in nom.fit.coef[:nt]],
            "theta_std": [float(v) for v in nom_unc["theta_std"]],
            "theta_ci95": nom_unc["theta_ci95"],
            "theta_std_sampling": nom_unc["theta_std_sampling"],
            "theta_model_error": nom_unc["theta_model_error"],
            "theta_std_white": nom_unc["theta_std_white"],
            "theta_names": list(THETA_NAMES[:nt]),
            "n_theta": nt,
            "n_theta_reason": st.n_theta_reason,
            "condition_number": nom.fit.cond,
            "residual_rms": g * nom.fit.rms,
            "heldout_rms": g * nom.heldout_rms,
        },
    }
    out["input_saturation"] = idf.saturation
    if rec.gain:
        th = nom.fit.coef
        # the offset in both conventions: F_offset_N as published for EMPS (Janot, Gautier & Brunot
        # 2019: M ÿ + Fv ẏ + Fc sign(ẏ) + F_offset = A1 u, the force the motor holds against), and
        # offset_N = θ4·A1 as the plant's driver.offset_N (a force on the carriage, model.py's
        # θ1 ẍ = u − … + θ4): the same number with the opposite sign
        out["nominal"]["physical"] = {"mass_kg": g * th[0], "viscous_N_s_per_m": g * th[1],
                                      "coulomb_N": g * th[2], "F_offset_N": -g * th[3],
                                      "offset_N": g * th[3]}
    th, _ = fits.coef_split(sel.final, sel.terms)
    params_of = parameters_of(values, rec.gain)
    th_v, betas = values.coef_split(values.final, values.terms)
    unc = stated_uncertainty(values.fits, values.final, values.terms, params_of)
    effects = []
    for (ev, before), term, beta, eu in zip(sel.accepted, values.terms, betas, unc["effects"]):
        named_as, unclaimed = claims(term.family, eu["ci95"])
        effects.append({
            "name": term.family,
            # the name by what stands of it, and the size parameters it does not claim (their
            # 95 % interval holds 0): motorctl.ident.judge.claims
            "named_as": named_as,
            "not_claimed": [{"parameter": n, "ci95": [lo, hi]} for n, lo, hi in unclaimed],
            "parameters": params_of(term, term.h, beta),
            # σ and 95 % interval of each named parameter (those a number; delta method on the
            # Newey-West covariance of β and the searched h: motorctl.ident.uncertainty)
            "parameters_std": eu["std"],
            "parameters_ci95": eu["ci95"],
            "parameters_std_sampling": eu.get("std_sampling", {}),
            "parameters_model_error": eu.get("model_error", {}),
            "heldout_rms_before": g * before,
            "heldout_rms_after": g * ev.heldout_rms,
            "heldout_gain_percent": 100 * ev.gain,
            "cannot_be_told_from": [{"name": n, "heldout_gain_percent": 100 * gn} for n, gn in ev.rivals],
        })
    out["effects"] = effects
    # theta_std / theta_ci95: of the values the effects' parameters come from (the values' model)
    out["augmented"] = {"theta": [float(v) for v in th], "residual_rms": g * sel.final.fit.rms,
                        "heldout_rms": g * sel.final.heldout_rms,
                        "theta_values": [float(v) for v in th_v],
                        "theta_std": unc["theta_std"], "theta_ci95": unc["theta_ci95"],
                        "theta_std_sampling": unc["theta_std_sampling"],
                        "theta_model_error": unc["theta_model_error"],
                        "theta_std_white": unc["theta_std_white"]}
    out["uncertainty"] = {"method": UNCERTAINTY_METHOD,
                          "lag_samples": unc["lag_samples"], "nominal_lag_samples": nom_unc["lag_samples"],
                          "splits": unc.get("splits", []), "nominal_splits": nom_unc.get("splits", [])}
    # the effects' values (and the compensation's) taken again on the declared current loop's
    # model, with the stick state measured, and/or with a structural mode's force above the band
    out["refit"] = None if not values.refitted else {
        "families": list(values.families),
        "on_current_loop": values.on_current_loop,
        "current_loop_modelled": values.fits.loop_filter is not None,
        "stick_state_measured": values.stick_measured,
        "mode_above_band": None if values.band_mode is None else {
            "columns_at_Hz": values.band_mode["columns_at_Hz"],
            "heldout_gain_percent": 100.0 * values.band_mode["heldout_gain"],
            "load_fraction_at_columns": values.band_mode["load_fraction"]},
        "theta": [float(v) for v in th_v], "residual_rms": g * values.final.fit.rms,
        "heldout_rms": g * values.final.heldout_rms}
    out["nominal"]["simulation_fit_percent"] = simulation_fit(fits, [], nom, SIM_WINDOW_S)
    out["augmented"]["simulation_fit_percent"] = simulation_fit(fits, list(sel.terms), sel.final, SIM_WINDOW_S)
    out["simulation_window_s"] = SIM_WINDOW_S
    chosen = [ev for ev, _ in sel.accepted]
    out["candidates"] = [
        [{"name": c.term.family, "searched": _r(c.term.h), "heldout_gain_percent": 100 * c.gain,
          "accepted": c.ok, "selected": any(c is e for e in chosen), "reasons": list(c.reasons)} for c in step]
        for step in sel.steps]
    out["eliminated"] = [{"name": n, "reason": why} for n, why in sel.eliminated]
    # searched parameters the joint refit after the selection moved (motorctl.ident.refine)
    out["joint_refit"] = [{"name": n, "searched_before": _r(h0), "searched_after": _r(h1)}
                          for n, h0, h1 in idf.refined.moved]
    out["harmonics_cut"] = [{"name": n, "harmonics_kept": k, "heldout_gain_percent": 100 * gn}
                            for n, k, gn in idf.refined.harmonics_cut]
    # failed in the final model, searched again there and kept with another searched parameter
    out["researched"] = [{"name": n, "reason": why, "searched_before": _r(h0), "searched_after": _r(h1)}
                         for n, why, h0, h1 in sel.researched]
    # passed in the last step but not taken, when the effect limit ended the selection
    out["cut_by_limit"] = ([c.term.family for c in sel.steps[-1] if c.ok and not any(c is e for e in chosen)]
                           if sel.steps and len(sel.terms) >= MAX_EFFECTS else [])
    verdict = add_refused(judge.verdict(sel.final, sel.terms, g, unit), sel.verdict_step, chosen, judge, sel)
    out["residual"] = verdict.as_dict()
    # effects the record cannot tell from a structure the selection refused: named neither,
    # compensated neither (motorctl.ident.ambiguity)
    out["ambiguous"] = summaries(fits, sel.ambiguous, rec.gain, unit)
    return out


def add_refused(verdict, last_step, chosen, judge=None, sel=None) -> Verdict:
    """The residual verdict (:class:`~motorctl.ident.verdict.Verdict`, or its dict) with the
    candidates of the last selection step that explain a share of the held-out residual
    (≥ :data:`~motorctl.ident.rules.REFUSED_GAIN`) with significant coefficients and were
    refused only because their physics does not fit (a line the loop itself oscillates at, a
    periodic force not the same both ways): the residual has a structure there that no family
    models. Each goes to ``findings`` (against "family", the family's columns, the reasons),
    ``structured`` becomes true and the text names them. Returns the new verdict.

    With the selection's ``judge`` and ``sel`` (its :class:`~motorctl.ident.records.Selection`)
    and stiction selected: a candidate that explains mostly samples near zero velocity
    (:meth:`~motorctl.ident.checks.Judge.rest_share` above one half) is counted as stiction's,
    the stick and slip beyond its band that its model leaves (a Stribeck hump at the search's
    2 mm/s edge with a negative force, 11-27 % on clean logs of the default config's Y axis).
    Not for a dead-zone holding the carriage: beside a play named a dead-zone, such a candidate
    was the play's only warning (docs/benchmarks.md, 2026-11-27).

    With them: a family the selection did not name that the record shows on its own, outside
    the force model (:meth:`~motorctl.effects.base.EffectFamily.unnamed_evidence`: the
    encoder's error in the raw minus the filtered position, too fast for its force to show),
    is reported the same way, with its last-step reasons; its candidate is not reported
    twice.

    With them: a candidate that stands for a mode above the record's band and leaves no
    structure beside it (:func:`_band_limit`) is the plant's own bandwidth limit: added to
    ``tested``, explained by its family, not a warning; and every other refused candidate that
    takes less than REFUSED_GAIN of the held-out residual beside that mode's force shared its
    evidence and is counted as the mode's (on clean 20 s logs of the Y axis with a mode at
    150-200 Hz, a force ripple "not the same both ways" at 5-7 % fell to -4 to 0 % beside it)."""
    if not isinstance(verdict, Verdict):
        verdict = Verdict(structured=bool(verdict["structured"]), findings=tuple(verdict["findings"]),
                          tested=tuple(verdict.get("tested", ())), text=verdict["text"])
    known = judge is not None and sel is not None
    terms = list(sel.terms) if known else []
    held = known and any(t.family == "stiction" for t in terms)
    extra, counted = [], []
    named = {t.family for t in terms}
    for name in (judge.fits.families if known else []):
        seen = None if name in named else fx.family(name).unnamed_evidence(judge.fits)
        if seen:
            why = next((c.reasons for c in last_step if c.term.family == name and c.reasons), [])
            extra.append(_finding(name, math.nan, seen + (f" ({'; '.join(why)})" if why else "")))
    refused = [c for c in last_step if not any(c is e for e in chosen)
               and outcome(passed=False, refused=c) == "unexplained"
               and not any(e["against"] == c.term.family for e in extra)]
    band, with_band = _band_limit(judge, terms, refused) if known else (None, None)

    def where(c):
        return (f"what {c.term.family} would explain ({100 * c.gain:.0f} % of the held-out residual), "
                f"refused: {'; '.join(c.reasons)}")
    for c in refused:
        if c is band:
            continue
        if held and judge.rest_share(sel.final, c) > 0.5:
            counted.append(_finding(c.term.family, float(c.gain), where(c) + ", near zero velocity", "stiction"))
            continue
        if band is not None:
            beside = 1.0 - judge.fits.evaluate(terms + [band.term, c.term]).heldout_rms / with_band.heldout_rms
            if beside < REFUSED_GAIN:
                counted.append(_finding(c.term.family, float(c.gain), where(c) + f"; {100 * beside:.0f} % beside "
                                        "the force of the mode above the band", band.term.family))
                continue
        extra.append(_finding(c.term.family, float(c.gain), where(c)))
    tested, text = verdict.tested, verdict.text
    if counted:
        tested = tested + tuple(counted)
        text += "".join(f"; {e['where']}, counted as {e['explained_by']}'s" for e in counted)
    if band is not None:
        tested = tested + (_finding(band.term.family, float(band.gain), where(band), band.term.family),)
        text += (f"; {where(band)}: with its force in the model the residual shows no structure, the "
                 "plant's own mode above the record's band")
    verdict = replace(verdict, tested=tested, text=text)
    if not extra:
        return verdict
    lead = "unexplained structured residual remains: "
    body = "; ".join(e["where"] for e in extra)
    if verdict.structured:
        text = verdict.text + "; " + body
    else:
        text = lead + body + verdict.text[verdict.text.find(")") + 1:]
    return replace(verdict, text=text, findings=verdict.findings + tuple(extra), structured=True)


def _band_limit(judge, terms: list, refused: list):
    """The first refused candidate that stands for a force above the record's band
    (:meth:`~motorctl.effects.base.EffectFamily.beyond_band`: a structural mode whose
    antiresonance the band cannot locate) with which the final model (of ``terms``) leaves a
    residual without structure (:meth:`~motorctl.ident.checks.Judge.verdict`), and that model
    evaluated: what remains is the plant's own mode, told as its bandwidth limit, not a
    structure no family models; (None, None) when there is none. A play, a hysteresis or
    another unmodelled force that the mode's columns explain in part keeps its structure beside
    them, and its warning. Beside that model each other refused candidate is judged again
    (:func:`add_refused`): what it takes of the held-out residual there, below REFUSED_GAIN,
    was the mode's evidence."""
    for c in refused:
        if fx.family(c.term.family).beyond_band(judge.fits.p, c.term.h):
            model = terms + [c.term]
            ev = judge.fits.evaluate(model)
            if not judge.verdict(ev, model).structured:
                return c, ev
    return None, None


def _finding(against: str, share: float, where: str, explained_by: str | None = None) -> dict:
    """One entry of the residual verdict's ``findings`` or ``tested`` (the keys of
    :func:`motorctl.ident.verdict.residual_verdict`'s) for a candidate or an effect seen outside
    the force model: structured unless a selected family (``explained_by``) explains it; no noise
    share, z or mean (not a binned function of one variable)."""
    return {"against": against, "share": share, "noise_share": math.nan, "z": math.nan, "where": where,
            "mean": math.nan, "structured": explained_by is None, "explained_by": explained_by}


def fig(v) -> str:
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(fig(x) for x in v) + "]"
    return f"{v:.5g}" if isinstance(v, (int, float)) else str(v)


def _flow(v: list) -> str:
    return "[" + ", ".join(f"{x:.6g}" for x in v) + "]"


def saturation_note(sat: dict | None) -> str | None:
    """The report's line on an input that sits at its limit (``sat``: :func:`motorctl.ident.
    idim.input_saturation`'s dict), or None when it does so on less than
    :data:`SATURATION_NOTE_SHARE` of the samples (or not at all)."""
    if not sat or sat["share"] < SATURATION_NOTE_SHARE:
        return None
    limits = " / ".join(f"{v:+.4g} V" for v in sat["limits_V"])
    what = ("its limit, the controller's u_lim" if sat.get("known_limit") else
            "its extremes, held the way a clipped input is logged (not a limit if the input was flat "
            "there on purpose, e.g. a step)")
    return (f"NOTE: the input sits at {what} ({limits}) on {100 * sat['share']:.1f} % of the samples, "
            f"{sat['stretches']} stretches of {1e3 * RAIL_MIN_S:g} ms or more (the longest "
            f"{1e3 * sat['longest_s']:.1f} ms). There the loop is open and catches up afterwards, often from "
            "rail to rail, which the model does not describe: the values and the verdict may be off. Record "
            "moves the amplifier can follow (a lower trajectory a_max or j_max).")


def _interval(ci) -> str:
    """A [lo, hi] pair, or a list of them, as text."""
    if ci and isinstance(ci[0], (list, tuple)):
        return "[" + ", ".join(_interval(c) for c in ci) + "]"
    if not ci or ci[0] is None:
        return "-"
    return f"[{ci[0]:.5g}, {ci[1]:.5g}]"


def text_report(s: dict) -> str:
    u = s["residual_unit"]
    n = s["nominal"]
    lines = [f"motorctl identify: {s['source']}" + (f" (axis {s['axis']})" if s.get("axis") else ""),
             f"  {s['samples']} samples at {1 / s['period_s']:.0f} Hz; position low-pass "
             f"{s['filters']['position_lowpass_Hz']:g} Hz, decimation {s['filters']['decimation']}, "
             f"friction shape {s['filters']['friction_shape']}",
             f"  zero-order hold: input shifted by {s['filters']['zoh_delay_samples']:g} sample "
             f"({s['filters'].get('zoh_source', '')})",
             f"nominal model: {n['n_theta_reason']}",
             f"  condition number {n['condition_number']:.1f}"]
    errs = n.get("theta_model_error") or [0.0] * len(n["theta"])
    for name, v, sd, ci, b in zip(n["theta_names"], n["theta"], n["theta_std"], n["theta_ci95"], errs):
        part = f", of it model error {b:.2g}" if b else ""
        lines.append(f"  {name} = {v:.6g} +- {sd:.2g} (95 %: {_interval(ci)}{part})")
    if "physical" in n:
        ph = n["physical"]
        lines.append("  physical: " + ", ".join(f"{k} {v:.4g}" for k, v in ph.items() if "offset" not in k))
        if "F_offset_N" in ph:
            lines.append(f"  offset: F_offset {ph['F_offset_N']:+.4g} N as published (M y'' + Fv y' + Fc S(y') "
                         f"+ F_offset = A1 u); a force {ph['offset_N']:+.4g} N on the carriage "
                         f"(theta4 * A1, the plant's driver.offset_N)")
    lines.append(f"  residual RMS {n['residual_rms']:.4g} {u}; held-out RMS {n['heldout_rms']:.4g} {u}")
    note = saturation_note(s.get("input_saturation"))
    if note:
        lines.append(note)
    if not s["effects"]:
        lines.append("effects: no effect found (no candidate passed held-out gain, BIC and plausibility)")
    for e in s.get("eliminated", []):
        lines.append(f"  selected, then dropped with the later effects in the model: {e['name']} ({e['reason']})")
    for e in s.get("researched", []):
        moved = ("" if e["searched_before"] is None or e["searched_after"] is None else
                 f"; searched parameter {e['searched_before']:.4g} -> {e['searched_after']:.4g}")
        lines.append(f"  selected, then searched again with the later effects in the model and kept: {e['name']} "
                     f"({e['reason']}{moved})")
    for e in s.get("joint_refit", []):
        h0, h1 = e["searched_before"], e["searched_after"]
        how = ("its column's shape taken again" if h0 is None or h1 is None or h0 == h1
               else f"searched parameter {h0:.5g} -> {h1:.5g}")
        lines.append(f"  refitted jointly with the other effects: {e['name']} ({how})")
    for e in s.get("harmonics_cut", []):
        lines.append(f"  {e['name']}: harmonics above the first left out (they lower the held-out RMS by "
                     f"{e['heldout_gain_percent']:.2f} %, under 1 %)")
    if s.get("cut_by_limit"):
        lines.append(f"  not taken, the limit of {MAX_EFFECTS} effects reached: " + ", ".join(s["cut_by_limit"]))
    for e in s["effects"]:
        named = e.get("named_as", e["name"])
        lines.append(f"effect found: {e['name']}" + (f" ({named})" if named != e["name"] else "") + ": "
                     + ", ".join(f"{k} {v}" for k, v in e["parameters"].items()))
        for nc in e.get("not_claimed", []):
            lines.append(f"  not claimed: {nc['parameter']} (its 95 % interval {_interval(nc['ci95'])} holds 0)")
        if e.get("parameters_ci95"):
            lines.append("  95 % intervals: " + ", ".join(f"{k} {_interval(v)}" for k, v in e["parameters_ci95"].items()))
        lines.append(f"  held-out RMS {e['heldout_rms_before']:.4g} -> {e['heldout_rms_after']:.4g} {u}")
        for r in e.get("cannot_be_told_from", []):
            lines.append(f"  NOTE: this record cannot tell it from {r['name']} (held-out gain "
                         f"{e['heldout_gain_percent']:.1f} % against {r['heldout_gain_percent']:.1f} %): "
                         f"both are named as possible; a slow constant-speed move or a breakaway test separates them")
    if s.get("ambiguous"):
        from motorctl.ident.ambiguity import text_lines
        lines.extend(text_lines(s["ambiguous"]))
    a = s["augmented"]
    lines.append(f"augmented model: residual RMS {a['residual_rms']:.4g} {u}, held-out RMS {a['heldout_rms']:.4g} {u}")
    if a.get("theta_ci95"):
        lines.append("  " + ", ".join(f"{name} {v:.6g} +- {sd:.2g} (95 %: {_interval(ci)})" for name, v, sd, ci in
                                      zip(n["theta_names"], a["theta_values"], a["theta_std"], a["theta_ci95"])))
        lines.append("  (sigma: the residual's own correlation, Newey-West, and the model's error the record shows, "
                     "the fits on the low band and in motion against the fit on all; a bias neither shows is not "
                     "in it: docs/identification.md, \"Uncertainty\")")
    if s.get("refit"):
        r = s["refit"]
        how = []
        if r.get("on_current_loop"):
            how.append("the declared current loop modelled as its lag, not a delay"
                       if r["current_loop_modelled"] else "no current loop declared")
        if r.get("stick_state_measured"):
            how.append("stiction's stick state measured from the encoder's reading")
        if r.get("mode_above_band"):
            m = r["mode_above_band"]
            how.append(f"a structural mode above the record's band in the model, its force m_l s^2 a / w_a^2 "
                       f"(columns at f_a {m['columns_at_Hz']:.4g} Hz, not named: f_a is not identifiable there; "
                       f"held-out RMS -{m['heldout_gain_percent']:.1f} %)")
        again = f"; searched again: {', '.join(r['families'])}" if r["families"] else ""
        lines.append(f"  the effects' values and compensation fitted again on a more exact model ({'; '.join(how)}"
                     f"{again}): held-out RMS {r['heldout_rms']:.4g} {u}")
    if s.get("residual"):
        lines.append(("WARNING: " if s["residual"]["structured"] else "residual: ") + s["residual"]["text"])
    if n.get("simulation_fit_percent") is not None:
        lines.append(f"simulated position fit ({s['simulation_window_s']:g} s windows from the measured state): "
                     f"nominal {n['simulation_fit_percent']:.3f} %, augmented {a['simulation_fit_percent']:.3f} %")
    lines.append("candidates per forward-selection step:")
    for i, step in enumerate(s["candidates"]):
        for c in sorted(step, key=lambda c: -c["heldout_gain_percent"]):
            verdict = ("SELECTED" if c.get("selected") else "passes (a better one was selected)") if c["accepted"] \
                else "rejected: " + "; ".join(c["reasons"])
            lines.append(f"  step {i + 1}: {c['name']:28s} held-out gain {c['heldout_gain_percent']:7.2f} % {verdict}")
    if s.get("validation"):
        v = s["validation"]
        lines.append(f"validation on {v['source']} (the models fitted here, not fitted again): residual RMS "
                     f"{v['residual_rms_before']:.4g} -> {v['residual_rms_after']:.4g} {u}"
                     + (f"; relative error {v['relative_error_percent_before']:.2f} % -> "
                        f"{v['relative_error_percent_after']:.2f} % (100 |residual| / |force|)"
                        if v.get("relative_error_percent_before") is not None else ""))
    cl = s.get("closed_loop")
    if cl:
        b, f = cl["before"], cl["after"]
        lines.append(f"closed loop ({cl['duration_s']:g} s, simulated plant with the effect):")
        lines.append(f"  C2 alone:            e_M {b['e_M_um']:.2f} um, e_F {b['e_F_um']:.2f} um, L2 {b['L2_um']:.3f} um")
        lines.append(f"  C2 + compensation:   e_M {f['e_M_um']:.2f} um, e_F {f['e_F_um']:.2f} um, L2 {f['L2_um']:.3f} um")
    elif s.get("closed_loop_note"):
        lines.append(f"closed loop: {s['closed_loop_note']}")
    return "\n".join(lines) + "\n"
