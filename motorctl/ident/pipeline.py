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

from motorctl.ident.explain import (SATURATION_NOTE_SHARE, add_refused, fig,  # noqa: F401
                                    saturation_note, text_report)
from motorctl.ident.judge import unsupported
from motorctl.ident.select import MAX_EFFECTS, Identifier
from motorctl.ident.tuned import (BOX_MARGIN, compensation_from_fit, set_theta0, tuned_config,  # noqa: F401
                                  values_and_parameters, values_from, write_tuned_config)
from motorctl.ident.uncertainty import fit_uncertainty
from motorctl.model import THETA_NAMES
from motorctl.recorder.runlog import LogError


#: Horizon of the simulated-position fit % (motorctl.ident.simfit) [s].
SIM_WINDOW_S = 0.2


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
