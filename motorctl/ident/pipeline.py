"""The identification pipeline of ``motorctl identify`` and ``motorctl tune``, on a loaded
record: fit and trace the residual (:func:`identify_record`), summarise it (:func:`summarise`,
the JSON of ``identify``), validate on a second record, turn the found effects into a
controller's compensation and θ̂(0) (:func:`compensation_from_fit`), write the tuned config
(:func:`tuned_config`, :func:`write_tuned_config`) and the text report (:func:`text_report`).

No run happens here (the closed-loop before/after is :class:`motorctl.commission.closed_loop.ClosedLoop`),
and nothing here parses arguments (the CLI is :mod:`motorctl.cli.identify`).
"""

from __future__ import annotations

import contextlib
import math

import numpy as np
from threadpoolctl import threadpool_limits

from motorctl.ident import effects as fx
from motorctl.ident.idim import RAIL_MIN_S
from motorctl.ident.judge import unsupported
from motorctl.ident.select import MAX_EFFECTS, REFUSED_GAIN, Identifier, refused_on_physics
from motorctl.ident.uncertainty import fit_uncertainty
from motorctl.model import THETA_NAMES
from motorctl.recorder.runlog import LogError

#: the share of the samples at the input's limit (:func:`motorctl.ident.idim.input_saturation`)
#: from which the report says the values may be off. Default plant, X, 20 s, the program's
#: a_max raised from 40 to 41-47 m/s²: up to 1.3 % at the limit cogging came within 2.4 % and
#: nothing else was named; from 1.8 % a phantom force ripple (seeds 1-2), from 3 % phantom
#: springs and warnings, at 4.5 % cogging and the encoder's error missed
#: (docs/identification.md, "Input saturation")
SATURATION_NOTE_SHARE = 0.01
#: Horizon of the simulated-position fit % (motorctl.ident.simfit) [s].
SIM_WINDOW_S = 0.2


# ---------------------------------------------------------------------------- summary
def _r(x):
    return float(x) if x is not None and math.isfinite(float(x)) else None


def summarise(idf: Identifier) -> dict:
    """The JSON object of ``identify``; residuals in N when a gain is known."""
    rec = idf.rec
    g = rec.gain or 1.0
    unit = "N" if rec.gain else "V"
    nt = idf.n_theta
    nom = idf.nominal
    # the σ of every value from the residual's own correlation (Newey-West; the white formula's
    # σ̂²(ΦᵀΦ)⁻¹ kept beside it as theta_std_white): motorctl.ident.uncertainty
    nom_unc = _uncertainty(idf, nom, [], None)
    out = {
        "source": rec.source,
        "axis": rec.axis or None,
        "samples": int(rec.n),
        "period_s": rec.period_s,
        "filters": {"position_lowpass_Hz": idf.p.fq, "decimation": idf.p.nd, "zoh_delay_samples": idf.zoh,
                    "zoh_source": idf.zoh_source,
                    "block_s": 0.25, "friction_shape": idf.friction},
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
            "n_theta_reason": idf.n_theta_reason,
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
    th, _ = idf.coef_split(idf.final, idf.terms)
    src, params_of = values_and_parameters(idf, rec.gain)
    th_v, betas = src.coef_split(src.final, src.terms)
    unc = _uncertainty(src, src.final, src.terms, params_of)
    effects = []
    for (ev, before), term, beta, eu in zip(idf.accepted, src.terms, betas, unc["effects"]):
        effects.append({
            "name": term.family,
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
    # theta_std / theta_ci95: of the values the effects' parameters come from (values_from)
    out["augmented"] = {"theta": [float(v) for v in th], "residual_rms": g * idf.final.fit.rms,
                        "heldout_rms": g * idf.final.heldout_rms,
                        "theta_values": [float(v) for v in th_v],
                        "theta_std": unc["theta_std"], "theta_ci95": unc["theta_ci95"],
                        "theta_std_sampling": unc["theta_std_sampling"],
                        "theta_model_error": unc["theta_model_error"],
                        "theta_std_white": unc["theta_std_white"]}
    out["uncertainty"] = {"method": "sigma = sqrt(s^2 + b^2): s the Newey-West HAC standard deviation (Bartlett "
                                    "kernel, Andrews' AR(1) bandwidth), b the model error the record shows (the fit "
                                    "on the low band and on the samples in motion against the fit on all, beyond "
                                    "its sampling variance, where significant at 5 %); 95 % interval = value -+ "
                                    "1.96 sigma",
                          "lag_samples": unc["lag_samples"], "nominal_lag_samples": nom_unc["lag_samples"],
                          "splits": unc.get("splits", []), "nominal_splits": nom_unc.get("splits", [])}
    # the effects' values (and the compensation's) taken again on the declared current loop's
    # model, with the stick state measured, and/or with a structural mode's force above the band
    out["refit"] = None if src is idf else {
        "families": src.refit_families,
        "on_current_loop": src.loop_refit,
        "current_loop_modelled": src.loop_filter is not None,
        "stick_state_measured": src.stick_measured,
        "mode_above_band": None if src.band_mode is None else {
            "columns_at_Hz": src.band_mode["columns_at_Hz"],
            "heldout_gain_percent": 100.0 * src.band_mode["heldout_gain"],
            "load_fraction_at_columns": src.band_mode["load_fraction"]},
        "theta": [float(v) for v in th_v], "residual_rms": g * src.final.fit.rms,
        "heldout_rms": g * src.final.heldout_rms}
    from motorctl.ident.simfit import simulation_fit
    out["nominal"]["simulation_fit_percent"] = simulation_fit(idf, [], idf.nominal, SIM_WINDOW_S)
    out["augmented"]["simulation_fit_percent"] = simulation_fit(idf, idf.terms, idf.final, SIM_WINDOW_S)
    out["simulation_window_s"] = SIM_WINDOW_S
    chosen = [ev for ev, _ in idf.accepted]
    out["candidates"] = [
        [{"name": c.term.family, "searched": _r(c.term.h), "heldout_gain_percent": 100 * c.gain,
          "accepted": c.ok, "selected": any(c is e for e in chosen), "reasons": c.reasons} for c in step]
        for step in idf.steps]
    out["eliminated"] = [{"name": n, "reason": why} for n, why in getattr(idf, "eliminated", [])]
    # searched parameters the joint refit after the selection moved (select.Identifier.joint_refit)
    out["joint_refit"] = [{"name": n, "searched_before": _r(h0), "searched_after": _r(h1)}
                          for n, h0, h1 in getattr(idf, "joint_moved", [])]
    out["harmonics_cut"] = [{"name": n, "harmonics_kept": k, "heldout_gain_percent": 100 * gn}
                            for n, k, gn in getattr(idf, "harmonics_cut", [])]
    # failed in the final model, searched again there and kept with another searched parameter
    out["researched"] = [{"name": n, "reason": why, "searched_before": _r(h0), "searched_after": _r(h1)}
                         for n, why, h0, h1 in getattr(idf, "researched", [])]
    # passed in the last step but not taken, when the effect limit ended the selection
    out["cut_by_limit"] = ([c.term.family for c in idf.steps[-1] if c.ok and not any(c is e for e in chosen)]
                           if idf.steps and len(idf.terms) >= MAX_EFFECTS else [])
    out["residual"] = idf.verdict(idf.final, idf.terms, g, unit)
    add_refused(out["residual"], idf.verdict_step, chosen, idf)
    # effects the record cannot tell from a structure the selection refused: named neither,
    # compensated neither (motorctl.ident.ambiguity)
    from motorctl.ident.ambiguity import summaries
    out["ambiguous"] = summaries(idf, getattr(idf, "ambiguous", []), rec.gain, unit)
    return out


def _uncertainty(idf: Identifier, ev, terms: list, params_of) -> dict:
    """:func:`~motorctl.ident.uncertainty.fit_uncertainty` of a fit; a regressor it cannot take
    (degenerate) gives the white formula's σ for θ and no effect intervals, lag_samples None."""
    try:
        return fit_uncertainty(idf, ev, terms, params_of)
    except (ValueError, np.linalg.LinAlgError):
        from motorctl.ident.uncertainty import ci95
        nt = idf.n_theta
        sd = [float(v) for v in ev.fit.std[:nt]]
        return {"theta_std": sd, "theta_std_white": sd, "lag_samples": None, "theta_std_sampling": sd,
                "theta_model_error": [0.0] * nt, "splits": [],
                "theta_ci95": [ci95(float(v), s) for v, s in zip(ev.fit.coef[:nt], sd)],
                "effects": [{"std": {}, "ci95": {}} for _ in terms]}


def drop_unsupported(idf: Identifier, gain: float | None) -> Identifier:
    """Take out of ``idf``'s model each selected effect whose size is not told from zero on the
    values' fit (:func:`motorctl.ident.judge.unsupported` on the intervals of
    :func:`_uncertainty`), until none is left (``eliminated`` gets the reason). Returns ``idf``."""
    for _ in range(len(idf.terms)):
        src, params_of = values_and_parameters(idf, gain)
        if not src.terms:
            break
        bad = unsupported(src.terms, _uncertainty(src, src.final, src.terms, params_of)["effects"])
        if not bad:
            break
        idf.drop_after(bad)
    return idf


def values_from(idf: Identifier) -> Identifier:
    """The identifier whose joint fit gives the found effects' values and compensation: the
    refit on the declared current loop's model when :meth:`~motorctl.ident.select.Identifier.
    refit` ran (``idf.refitted``), else ``idf`` itself. Selection, held-out gains and the
    residual verdict are always ``idf``'s."""
    return idf if idf.refitted is None else idf.refitted


def values_and_parameters(idf: Identifier, gain: float):
    """(:func:`values_from` of ``idf``, its ``params_of(term, h, beta)``: an effect's named
    parameters in physical units, :func:`motorctl.effects.parameters` on the values' fit, with
    the record's ``gain`` [N/V])); what :func:`~motorctl.ident.uncertainty.fit_uncertainty`
    takes as ``params_of``."""
    src = values_from(idf)
    th_v = src.coef_split(src.final, src.terms)[0]

    def params_of(term, h, beta):
        return fx.parameters(term.family, h, beta, gain, src.p.fs, theta=th_v, p=src.p, ctx=src)
    return src, params_of


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


def validation(idf: Identifier, rec2) -> dict:
    """The models fitted on DATA judged on a second record ``rec2`` (a record of
    :func:`motorctl.ident.data.load_record`, e.g. EMPS's ``DATA_EMPS_PULSES.mat``), nothing
    fitted again there: the nominal model and the augmented one (the found effects).

    Returns:
        ``{"source", "residual_rms_before", "residual_rms_after"}`` (N with a gain, else V: the
        residual of the force equation on rec2's decimated samples) and
        ``relative_error_percent_before`` / ``_after``: 100·‖residual‖/‖A1 u‖ on the same
        samples, the cross-test validation's "relative error" of the EMPS description
        (Script_IDIM_LS_CTV.m: 100·norm(error)/norm(force), decimated).
    Raises:
        ValueError, numpy.linalg.LinAlgError: rec2 too short or degenerate for the filters.
    """
    other = Identifier(rec2, n_theta=idf.n_theta, friction=idf.friction, zoh_delay=idf.zoh,
                       current_loop=idf.current_loop)
    g = idf.rec.gain or 1.0
    r0 = idf.predict_on(other, [], idf.nominal)
    r1 = idf.predict_on(other, idf.terms, idf.final)
    _, target = other.design([])
    ref = float(np.linalg.norm(target)) or math.nan
    return {"source": rec2.source, "residual_rms_before": g * float(np.sqrt(np.mean(r0 ** 2))),
            "residual_rms_after": g * float(np.sqrt(np.mean(r1 ** 2))),
            "relative_error_percent_before": 100 * float(np.linalg.norm(r0)) / ref,
            "relative_error_percent_after": 100 * float(np.linalg.norm(r1)) / ref}


# ---------------------------------------------------------------------------- fit -> controller
def _split_std(idf: Identifier, ev, terms) -> list:
    """The fit's standard deviations of each term's β (the layout of ``coef_split``)."""
    i, out = idf.n_theta, []
    for t in terms:
        k = 0 if t.cols is None else t.cols.shape[1]
        out.append(np.asarray(ev.fit.std[i:i + k], dtype=float))
        i += k
    return out


def compensation_from_fit(idf: Identifier, final=None, terms=None) -> tuple[dict, np.ndarray, list]:
    """The ``controller.compensation`` of the found effects and the θ̂(0) that goes with it.

    ``final`` and ``terms``: the evaluated model and its effect terms (default: the
    identifier's final ones, ``idf.final`` and ``idf.terms``, or its refit's on the declared
    current loop's model when one ran: :func:`values_from`).

    An adaptable family's entry carries ``adapt: false`` and its projection box from the fit's
    confidence interval (β ∓ 3σ, at least the default margin): a user only flips ``adapt``.

    A found effect the record cannot tell from a look-alike family (``cannot_be_told_from`` in
    the summary: cogging or an encoder's interpolation error, stiction or a dead-zone) is not
    compensated: a compensation is only written for an effect the identification names.

    Returns:
        (compensation {family: options} (V units, d̂_eff = −Cβ), θ (n_theta,) = the jointly
        fitted nominal θ re-expressed about each term's reference
        (:meth:`motorctl.effects.base.EffectFamily.theta_shift`), names of found families that
        have no compensation term or are not told from a look-alike).
    """
    unnamed = {ev.term.family for ev, _ in getattr(idf, "accepted", []) if ev.rivals}
    if final is None and terms is None:
        idf = values_from(idf)
    final = idf.final if final is None else final
    terms = idf.terms if terms is None else terms
    th, betas = idf.coef_split(final, terms)
    stds = _split_std(idf, final, terms)
    theta = np.array(th, dtype=float)
    comp, skipped = {}, []
    for t, b, sd in zip(terms, betas, stds):
        c = None if t.family in unnamed else fx.compensation(t.family, t.h, b, idf.p, beta_std=sd)
        if c:
            comp.update(c)
            theta = theta + fx.family(t.family).theta_shift(c[t.family], idf.n_theta)
        else:
            skipped.append(t.family)
    return comp, theta, skipped


#: margin added beyond a fitted θ that lies outside the configured box (fraction of |θ|, and
#: at least this fraction of the box's width)
BOX_MARGIN = 0.2


def tuned_config(idf: Identifier, s: dict, base: dict, axis: str, base_name: str) -> tuple[dict, str]:
    """The config ``base`` with axis ``axis`` tuned from the identification, and its YAML text.

    Changes, each commented in the text with its figure: ``controller.compensation`` = the found
    effects (:func:`compensation_from_fit`); ``theta_hat0`` = the fitted θ (θ1..θ4 only when the
    fit has four parameters; θ5, θ6 clipped into the box, which Assumption 2 checks); where a
    fitted θ_i (i ≤ 4) lies outside [theta_min, theta_max] the bound moves past it by
    :data:`BOX_MARGIN`. Nothing else changes.

    Args:
        s: the summary (:func:`summarise`). base: a config dict (parsed YAML). axis: its axis.
        base_name: where ``base`` came from (named in the header comment).
    Returns:
        (the new config dict, its YAML text with comments).
    """
    import copy

    import yaml

    cfg = copy.deepcopy(base)
    ctl = cfg["axes"][axis]["controller"]
    comp, theta, skipped = compensation_from_fit(idf)
    nt = idf.n_theta
    unit = s["residual_unit"]
    notes = set_theta0(ctl, theta[:nt])
    t0, lo, hi = ctl["theta_hat0"], ctl["theta_min"], ctl["theta_max"]
    if comp:
        ctl["compensation"] = copy.deepcopy(comp)
    else:
        ctl.pop("compensation", None)
    # YAML text: dump with placeholders, then put the commented sections in their place
    marks = {"theta_hat0": "@@T0@@", "theta_min": "@@TMIN@@", "theta_max": "@@TMAX@@", "compensation": "@@COMP@@"}
    draft = copy.deepcopy(cfg)
    dctl = draft["axes"][axis]["controller"]
    for k, m in marks.items():
        dctl[k] = m
    text = yaml.safe_dump(draft, sort_keys=False, default_flow_style=False, allow_unicode=True, width=100)
    std = s["nominal"]["theta_std"]
    fit_line = ", ".join(f"theta{i + 1} {theta[i]:.5g} +- {std[i]:.2g}" for i in range(nt))
    out = []
    for line in text.splitlines():
        stripped = line.strip()
        key = stripped.split(":", 1)[0]
        if key in marks and marks[key] in stripped:
            ind = line[: len(line) - len(line.lstrip())]
            if key == "theta_hat0":
                out.append(f"{ind}# motorctl identify: theta_hat0 from the joint fit ({fit_line}); "
                           f"{nt} parameters fitted")
                for i, n in sorted(notes.items()):
                    out.append(f"{ind}#   theta{i + 1}: {n}")
                out.append(f"{ind}theta_hat0: {_flow(t0)}")
            elif key == "theta_min":
                out.append(f"{ind}theta_min: {_flow(lo)}" + _changed(base, axis, "theta_min", lo))
            elif key == "theta_max":
                out.append(f"{ind}theta_max: {_flow(hi)}" + _changed(base, axis, "theta_max", hi))
            else:
                if not comp:
                    out.append(f"{ind}# motorctl identify: no compensable effect found"
                               + (f" ({', '.join(skipped)} has no compensation term)" if skipped else ""))
                    continue
                out.append(f"{ind}# motorctl identify: the found effects, compensated (an additive term in "
                           f"v_a1, eq. 13, told to the estimator; ripple: v / (1 + r(x)) before eq. 9; "
                           f"delay: v_a1 on the trajectory ahead)")
                for e in s["effects"]:
                    pars = ", ".join(f"{k} {fig(v)}" for k, v in e["parameters"].items())
                    tag = ("compensated" if e["name"] in comp else
                           "NOT compensated: the record cannot tell it from "
                           + ", ".join(r["name"] for r in e["cannot_be_told_from"])
                           if e.get("cannot_be_told_from") else "NOT compensable (no compensation term)")
                    out.append(f"{ind}#   {e['name']}: {pars}; held-out RMS {e['heldout_rms_before']:.4g} -> "
                               f"{e['heldout_rms_after']:.4g} {unit}; {tag}")
                body = yaml.safe_dump({"compensation": comp}, sort_keys=False, default_flow_style=False, width=100)
                out.extend(ind + b for b in body.splitlines())
        else:
            out.append(line)
    head = [f"# tuned by `motorctl identify {s['source']} --write-config` from {base_name}, axis {axis}",
            f"# nominal held-out residual RMS {s['nominal']['heldout_rms']:.4g} {unit}, augmented "
            f"{s['augmented']['heldout_rms']:.4g} {unit}"]
    if not s["effects"]:
        head.append("# no effect found: only theta_hat0 (and the box where needed) changed")
    note = saturation_note(s.get("input_saturation"))
    if note:
        head.append(f"# {note}")
    return cfg, "\n".join(head + out) + "\n"


def set_theta0(ctl: dict, theta) -> dict:
    """Set ``theta_hat0`` of a controller section (dict) to the fitted ``theta`` (4 or 6), with
    the rules of :func:`tuned_config` (θ5, θ6 clipped into the box, the box widened past a
    θ1..θ4 outside it). Returns {index: note}."""
    t0 = [float(v) for v in ctl["theta_hat0"]]
    lo = [float(v) for v in ctl["theta_min"]]
    hi = [float(v) for v in ctl["theta_max"]]
    notes = {}
    for i in range(min(len(theta), len(t0))):
        v = float(theta[i])
        if i >= 4:
            c = min(max(v, lo[i]), hi[i])
            notes[i] = f"fit {v:.5g}" + ("" if c == v else f", clipped into the box [{lo[i]:g}, {hi[i]:g}]")
            v = c
        else:
            w = BOX_MARGIN * max(abs(v), hi[i] - lo[i])
            if v < lo[i]:
                notes[i] = f"fit {v:.5g} < theta_min {lo[i]:g}: theta_min widened"
                lo[i] = max(v - w, 0.5 * v) if i == 0 else v - w
            elif v > hi[i]:
                notes[i] = f"fit {v:.5g} > theta_max {hi[i]:g}: theta_max widened"
                hi[i] = v + w
            else:
                notes[i] = f"fit {v:.5g}"
        t0[i] = round(v, 6)
    ctl["theta_hat0"] = t0
    ctl["theta_min"] = [round(v, 6) for v in lo]
    ctl["theta_max"] = [round(v, 6) for v in hi]
    return notes


def fig(v) -> str:
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(fig(x) for x in v) + "]"
    return f"{v:.5g}" if isinstance(v, (int, float)) else str(v)


def _flow(v: list) -> str:
    return "[" + ", ".join(f"{x:.6g}" for x in v) + "]"


def _changed(base: dict, axis: str, key: str, new: list) -> str:
    old = [float(v) for v in base["axes"][axis]["controller"][key]]
    if old == [float(v) for v in new]:
        return ""
    return f"  # motorctl identify: was {_flow(old)} (the fit lies outside)"


# ---------------------------------------------------------------------------- text
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


# ---------------------------------------------------------------------------- fit and write
def identify_record(rec, n_theta: int | None = None, friction: str = "sf",
                    zoh_delay: float | None = None, after_fit=None,
                    on_nominal=None, current_loop: bool = False) -> tuple[Identifier, dict]:
    """Fit the model to a loaded record, trace the residual to effects, and summarise.

    Args:
        rec: a record of :func:`motorctl.ident.data.load_record`. n_theta: 4, 6 or None (chosen
            from the input range). friction: 'sf' or 'sign'. zoh_delay: input delay of the
            logged input [samples] (None: 0.5 for run logs, detected for CSV/MAT).
        after_fit: called with the identifier once the fit is checked, before the summary
            (e.g. to start the closed-loop runs meanwhile); None: nothing.
        on_nominal: called with the nominal θ̂ (n_theta,) each time the nominal model is fitted,
            before the effect search (:class:`~motorctl.ident.select.Identifier`); None: nothing.
        current_loop: model the current loop the run log's config declares in the nominal
            fit (:class:`~motorctl.ident.select.Identifier`; off: fitted as an input delay).
    Returns:
        (the identifier after its run, the summary of :func:`summarise`; no validation or
        closed loop yet).
    Raises:
        LogError: the fit fails on the record or is physically meaningless (θ1 ≤ 0, simulated
        position fit below 0 %), with the likely cause.
    """
    # numpy's overflow/invalid warnings would add lines to stderr on a degenerate record; the
    # results are checked for finiteness and physical meaning instead (_check_physical). BLAS on
    # one thread: the effect search runs its own threads (select.SEARCH_THREADS), and OpenBLAS's
    # threads inside their many small (M, k) products only contend with them for the cores
    # (benchmarks/bench_ident.py: run() 1.81 -> 1.69 s wall, 3.04 -> 2.74 s CPU)
    @contextlib.contextmanager
    def quiet():
        with np.errstate(all="ignore"), threadpool_limits(limits=1, user_api="blas"):
            yield

    try:
        with quiet():
            idf = Identifier(rec, n_theta=n_theta, friction=friction, zoh_delay=zoh_delay,
                             on_nominal=on_nominal, current_loop=current_loop).run()
            # the selected effects' searched parameters taken again jointly, each with all the
            # others in the model (select.Identifier.joint_refit)
            idf.joint_refit()
            # the selected effects' values on the declared current loop's model (None: not needed),
            # and those the more exact model does not confirm dropped
            idf.refitted = idf.refit()
            idf.confirm_values()
            # a lost motion beside the travel's force of a play the verdict reports: not named
            idf.travel_shared()
            # an effect whose size's 95 % interval holds 0: not named (motorctl.ident.judge)
            drop_unsupported(idf, rec.gain)
    except (np.linalg.LinAlgError, FloatingPointError, ValueError) as exc:
        if isinstance(exc, LogError):
            raise
        msg = " ".join(str(exc).split())[:120]
        raise LogError(f"{rec.source}: the fit failed on this record ({type(exc).__name__}: {msg}); "
                       "check the units (t s, y m, u V) and that the axis moves with a varying input") from None
    # θ1 is judged on the model the user gets: with the found effects (a strong spring makes the
    # nominal fit's θ1 negative while the augmented one is right)
    check_physical(rec, max(idf.nominal.fit.coef[0], idf.final.fit.coef[0]), None)
    if after_fit is not None:
        after_fit(idf)
    with quiet():
        s = summarise(idf)
    check_physical(rec, max(s["nominal"]["theta"][0], s["augmented"]["theta"][0]),
                    (s["nominal"].get("simulation_fit_percent"), s["augmented"].get("simulation_fit_percent")))
    return idf, s


def write_tuned_config(idf: Identifier, s: dict, base: dict, axis: str, base_name: str, path) -> dict:
    """Write the tuned config of :func:`tuned_config` to ``path`` after checking it as
    ``motorctl check-config`` does (the bus budget aside), and note it in ``s``
    (``written_config``).

    Returns:
        The new config dict.
    Raises:
        ConfigError: the tuned config does not pass the checks (nothing is written).
        OSError: ``path`` cannot be written.
    """
    from motorctl.config import config_from_dict
    new_cfg, text = tuned_config(idf, s, base, axis, base_name)
    config_from_dict(new_cfg, path, check_budget=False)   # what check-config checks
    with open(path, "w", encoding="utf-8") as fh:
        fh.write(text)
    s["written_config"] = str(path)
    return new_cfg


_CAUSES = ("check the sign of u (a positive u must push y positive), the units of y (m) and u "
           "(V, or N without --gain) and the time base (t in s)")


def check_physical(rec, theta1, sim_fits) -> None:
    """Refuse (LogError, exit 2) a fit without physical meaning: θ1 = M/A1 <= 0 (a negative or
    zero mass; the caller passes the larger of the nominal and the augmented fit's), or a simulated position fit below 0 % for both the nominal and the augmented
    model (worse than a constant). ``sim_fits``: (nominal %, augmented %) or None (not yet)."""
    th1 = float(theta1)
    if not (math.isfinite(th1) and th1 > 0):
        raise LogError(f"{rec.source}: the fit gives theta1 = {th1:.4g} <= 0 (a mass that is not positive), "
                       f"so the record does not follow the model; {_CAUSES}")
    if sim_fits is None:
        return
    fits = [float(f) for f in sim_fits if f is not None]
    if fits and not any(math.isfinite(f) for f in fits):
        raise LogError(f"{rec.source}: the fitted model's simulated position diverges (fit % not finite), "
                       f"so the record does not follow the model; {_CAUSES}")
    fits = [f for f in fits if math.isfinite(f)]
    if fits and max(fits) < 0:
        raise LogError(f"{rec.source}: the fitted model simulates the position worse than a constant "
                       f"(simulated position fit {max(fits):.4g} % < 0 %); {_CAUSES}")


def json_default(o):
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(type(o).__name__)


__all__ = ["BOX_MARGIN", "SATURATION_NOTE_SHARE", "SIM_WINDOW_S", "check_physical", "compensation_from_fit", "fig",
           "identify_record", "json_default", "saturation_note", "set_theta0", "summarise", "text_report",
           "tuned_config", "validation", "values_and_parameters", "values_from", "write_tuned_config"]
