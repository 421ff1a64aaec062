"""Stage *explain*: what ``motorctl identify`` says of a fit. The residual verdict's findings
completed with the last step's candidates refused on their physics (:func:`add_refused`), and the
text report of a summary (:func:`text_report`, the JSON of
:func:`motorctl.ident.pipeline.summarise`)."""

from __future__ import annotations

import math

from motorctl.ident import effects as fx
from motorctl.ident.idim import RAIL_MIN_S
from motorctl.ident.select import MAX_EFFECTS, REFUSED_GAIN, refused_on_physics


#: the share of the samples at the input's limit (:func:`motorctl.ident.idim.input_saturation`)
#: from which the report says the values may be off. Default plant, X, 20 s, the program's
#: a_max raised from 40 to 41-47 m/s²: up to 1.3 % at the limit cogging came within 2.4 % and
#: nothing else was named; from 1.8 % a phantom force ripple (seeds 1-2), from 3 % phantom
#: springs and warnings, at 4.5 % cogging and the encoder's error missed
#: (docs/identification.md, "Input saturation")
SATURATION_NOTE_SHARE = 0.01


def add_refused(verdict: dict, last_step: list, chosen: list, idf: Identifier | None = None) -> None:
    """Add to the residual verdict (:func:`motorctl.ident.verdict.residual_verdict`) the
    candidates of the last selection step that explain a share of the held-out residual
    (≥ :data:`~motorctl.ident.select.REFUSED_GAIN`) with significant coefficients and were
    refused only because their physics does not fit (a line the loop itself oscillates at, a
    periodic force not the same both ways): the residual has a structure there that no family
    models. Each goes to
    ``findings`` (against "family", the family's columns, the reasons), ``structured`` becomes
    true and the text names them.

    With ``idf`` (the identifier, after its run) and stiction selected: a candidate that
    explains mostly samples near zero velocity (:meth:`~motorctl.ident.select.Identifier.
    rest_share` above one half) is counted as stiction's, the stick and slip beyond its band
    that its model leaves (a Stribeck hump at the search's 2 mm/s edge with a negative force,
    11-27 % on clean logs of the default config's Y axis). Not for a dead-zone holding the
    carriage: beside a play named a dead-zone, such a candidate was the play's only warning
    (docs/benchmarks.md, 2026-11-27).

    With ``idf``: a family the selection did not name that the record shows on its own, outside
    the force model (:meth:`~motorctl.effects.base.EffectFamily.unnamed_evidence`: the
    encoder's error in the raw minus the filtered position, too fast for its force to show),
    is reported the same way, with its last-step reasons; its candidate is not reported
    twice.

    With ``idf``: a candidate that stands for a mode above the record's band and leaves no
    structure beside it (:func:`_band_limit`) is the plant's own bandwidth limit: added to
    ``tested``, explained by its family, not a warning; and every other refused candidate that
    takes less than REFUSED_GAIN of the held-out residual beside that mode's force shared its
    evidence and is counted as the mode's (on clean 20 s logs of the Y axis with a mode at
    150-200 Hz, a force ripple "not the same both ways" at 5-7 % fell to -4 to 0 % beside it)."""
    held = idf is not None and any(t.family == "stiction" for t in idf.terms)
    extra, counted = [], []
    named = set() if idf is None else {t.family for t in idf.terms}
    for name in ([] if idf is None else idf.families):
        seen = None if name in named else fx.family(name).unnamed_evidence(idf)
        if seen:
            why = next((c.reasons for c in last_step if c.term.family == name and c.reasons), [])
            extra.append(_finding(name, math.nan, seen + (f" ({'; '.join(why)})" if why else "")))
    refused = [c for c in last_step if not any(c is e for e in chosen) and refused_on_physics(c)
               and not any(e["against"] == c.term.family for e in extra)]
    band, with_band = _band_limit(idf, refused)

    def where(c):
        return (f"what {c.term.family} would explain ({100 * c.gain:.0f} % of the held-out residual), "
                f"refused: {'; '.join(c.reasons)}")
    for c in refused:
        if c is band:
            continue
        if held and idf.rest_share(c) > 0.5:
            counted.append(_finding(c.term.family, float(c.gain), where(c) + ", near zero velocity", "stiction"))
            continue
        if band is not None:
            beside = 1.0 - idf.evaluate(list(idf.terms) + [band.term, c.term]).heldout_rms / with_band.heldout_rms
            if beside < REFUSED_GAIN:
                counted.append(_finding(c.term.family, float(c.gain), where(c) + f"; {100 * beside:.0f} % beside "
                                        "the force of the mode above the band", band.term.family))
                continue
        extra.append(_finding(c.term.family, float(c.gain), where(c)))
    if counted:
        verdict["tested"] = verdict["tested"] + counted
        verdict["text"] += "".join(f"; {e['where']}, counted as {e['explained_by']}'s" for e in counted)
    if band is not None:
        verdict["tested"] = verdict["tested"] + [_finding(band.term.family, float(band.gain), where(band),
                                                          band.term.family)]
        verdict["text"] += (f"; {where(band)}: with its force in the model the residual shows no structure, the "
                            "plant's own mode above the record's band")
    if not extra:
        return
    lead = "unexplained structured residual remains: "
    body = "; ".join(e["where"] for e in extra)
    if verdict["structured"]:
        verdict["text"] = verdict["text"] + "; " + body
    else:
        verdict["text"] = lead + body + verdict["text"][verdict["text"].find(")") + 1:]
    verdict["findings"] = verdict["findings"] + extra
    verdict["structured"] = True


def _band_limit(idf: Identifier | None, refused: list):
    """The first refused candidate that stands for a force above the record's band
    (:meth:`~motorctl.effects.base.EffectFamily.beyond_band`: a structural mode whose
    antiresonance the band cannot locate) with which the final model leaves a residual without
    structure (:meth:`~motorctl.ident.select.Identifier.verdict`), and that model evaluated:
    what remains is the plant's own mode, told as its bandwidth limit, not a structure no family
    models; (None, None) when there is none. A play, a hysteresis or another unmodelled force
    that the mode's columns explain in part keeps its structure beside them, and its warning.
    Beside that model each other refused candidate is judged again (:func:`add_refused`): what
    it takes of the held-out residual there, below REFUSED_GAIN, was the mode's evidence."""
    for c in ([] if idf is None else refused):
        if fx.family(c.term.family).beyond_band(idf.p, c.term.h):
            terms = list(idf.terms) + [c.term]
            ev = idf.evaluate(terms)
            if not idf.verdict(ev, terms)["structured"]:
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
        lines.append(f"effect found: {e['name']}: " + ", ".join(f"{k} {v}" for k, v in e["parameters"].items()))
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
