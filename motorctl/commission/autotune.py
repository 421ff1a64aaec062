"""``motorctl autotune``: measure an axis's frequency response through its driver, fit a physical
model, choose every controller's gains by one rule, verify them on the machine, write them.

Steps (any driver; the simulated one by default):

1. **measure** (:func:`measure_frf`): the axis is held by a conservative PID+FF (catalogue θ̂1(0),
   ω_n = 2π·20 Hz, ζ = 0.7, integral corner ω_n/5), rests at one end of its stroke (the rest
   noise of the encoder is recorded there), then makes one slow constant-velocity pass across
   the stroke (so Coulomb friction is a constant force and stiction never grips) while a
   periodic multisine r is added at the plant input: amplitude ramped up over its first period,
   every 1 Hz line from 10 Hz to 1 kHz and every 4th line up to 0.48 fs, line amplitudes
   ∝ f² below 60 Hz (the displacement stays a small share of the following-error limit) and
   scaled so that |r| ≤ 80 % of u_lim (32 periods: the heavy Y axis's response above 700 Hz, where
   the current loop shows, is a few nm per line). The pass stays 10 % of the stroke inside the soft limits,
   the supervisor's following-error limit is armed, and the excitation switches itself off
   (latched) if |e| reaches half the smallest following-error limit.
   The plant FRF is the indirect closed-loop estimate P = S_re/S_ru (scipy.signal.csd, one
   multisine period per segment, boxcar window, linear detrend; e = y − x_d), with the
   coherence r → e; the feedback does not bias it because r is independent of the noise.
2. **fit** (:func:`fit_plant`): θ1 = M/A1, θ2 = B/A1, one structural mode (frequency, damping,
   load share), the current-loop bandwidth and a transport delay, by scipy.optimize.least_squares
   on log(P_model/P_measured) weighted by the coherence, with the ZOH and its aliases
   (:func:`motorctl.commission.loopshape.plant_model_frf`); a rigid model is kept when the mode does not
   lower the cost by 30 %. The friction is not taken from the multisine (above 10 Hz θ2 ẋ is a
   few per cent of θ1 ẍ): :func:`~motorctl.commission.measure.measure_friction` runs constant-velocity
   passes at three speeds both ways inside the stroke (holding PID on the fitted θ1; X of
   configs/gantry.yaml 9.5 s, Y 17.3 s on the machine) and fits θ2 (viscous), θ3 (Coulomb) and θ4
   (offset) to the steady-state u against speed by linear least squares, each with its σ. θ2..θ4
   replace the configured θ̂(0) in the model a law takes settings from (PID+FF: FF1 = θ2,
   FF2 = θ1, bias = −θ4), stated in the written config's comments.
3. **choose** (:func:`~motorctl.commission.choose.choose_gains`), ONE rule for every law, on the *measured* FRF:
   among each law's family (PID: P = θ1 ω², D = 2ζωθ1, I = P ω/r; C1/C2: k_s = 2ζωθ1,
   k1 = ω/(2ζ), γ_d of the config; ω on a log grid of 49 points from 30 to 3000 rad/s,
   ζ ∈ {0.3, 0.4, 0.5, 0.7, 1}, r ∈ {3, 5, 7, 10, 15, 20, 30, 50}; θ1 the fitted one; the rule
   reads the plant: when the fit keeps no structural mode, ζ ∈ :data:`ZETA_RIGID` too,
   :func:`~motorctl.commission.choose.family_zetas`), the *admissible* gains
   are those with gain margin ≥ 6 dB, phase margin ≥ 10° and peak sensitivity ≤ 16 dB at 100,
   75 and 50 % of their loop gain (the verification ladder; a lighter loop gain is also what
   a heavier load does; the back-off steps 35 and 25 % are tried only where they hold too).
   The floor is wide on purpose: the least L2[e] the machine accepts (no fault, saturation,
   rest noise; ``benchmarks/compare_laws.py --search``) lies at 10-20° of phase margin and
   11-16 dB of peak sensitivity on the default plant, and step 4 runs every candidate on the
   machine, which stops on oscillation. The first candidate is the admissible one of highest
   loop gain |L| at :data:`F_TRACK_HZ` = 5 Hz (the least sensitivity where the tracking error
   of a point-to-point program lives). The u noise at rest is predicted (the measured rest
   spectrum of y through |C|) and reported, but judged on the machine in step 4 (with
   stiction and quantisation the prediction is only a bound). The measured FRF the rule runs
   on is the fitted model times the measurement's departure from it where that departure is
   beyond the line's random error (:func:`~motorctl.commission.choose.loop_frf`). C1 and C2 have the same
   linearisation at rest (u0 = 0), so they share the admissible set and the first candidate;
   each is verified with its own runs and written in its own mapping.
4. **verify** (:mod:`motorctl.commission.verify`). Every run is ``motorctl run``'s own job
   (:func:`motorctl.commission.evaluate.evaluate`: the same counts as ``motorctl run --json``)
   of the axis's program, judged by :func:`~motorctl.commission.verify.admissible` against
   the configured controller's run of the same length: a fault (following error, limits),
   more saturated samples than :data:`SAT_FACTOR` times the configured controller's (or than
   that factor times :data:`SAT_FLOOR_SHARE` of the samples), u RMS at rest above
   :data:`REST_FACTOR` times the configured controller's, or oscillation (a spectral line in
   u at rest ≥ :data:`OSC_RATIO` times the median of its spectrum, or the error spectrum ≥
   :data:`OSC_RATIO` times the configured controller's at some frequency, beyond the ratio
   of the two loops' |S|² on the measured response) fails a run.
   Steps a.-c. screen on short runs (``verify_s``, two program periods); e. and f. decide on
   full ones. A short run is judged as the full run it stands for
   (:func:`~motorctl.commission.verify.limits`, :func:`~motorctl.commission.verify.rest_judged`):
   its saturated samples against the full run's allowed rate (it fails only above the 95 %
   quantile of a quasi-Poisson count at that rate, with the run's own dispersion of
   saturation episodes), its rest noise as the full run's it predicts (its first program
   period for the full run's first, the other for the remaining ones) against the full
   run's limit.

   a. *ladder* on the first candidate: 50 %, 75 %, 100 % of its loop gain (PID: P, I, D;
      C1/C2: k_s), a rung between two on a failure (when 50 % fails: 35 %, then 25 %).
   b. *search*: per shape (ζ, r), the highest admissible ω that passes. A failed run bounds ω
      from above (noise, saturation, oscillation, a fault of a ringing loop), or from below
      when it faults on its following error with u quiet at rest and no line in u or e
      (:func:`too_soft`: the loop is too soft for the program) or saturates more than a run
      of the shape at a higher ω did (its larger error drives u into the limit). The
      candidates are the admissible ω whose rest noise, read off the prediction of step 3
      through the shape's own runs (a power law through the nearest, of exponent
      :data:`NOISE_EXPONENT` or the one its runs fit: the prediction grows faster with ω
      than the machine's noise; a shape not yet run: in proportion to the latest run of
      any), is at most :data:`NOISE_SLACK` times the level (the run judges; the best often
      sits at the level). From where the previous shape's passed (the first shape: its
      highest candidate), down 1, 2, 4 ... grid points while runs fail high, up so while
      they pass or fail soft, then halving the bracket. Shapes
      in the order of their reach, the |L| at 5 Hz of their highest candidate (re-ranked
      after each shape); a shape whose reach is below :data:`PRUNE_SHARE` of that of the
      best run so far is probed with :data:`PROBE_RUNS` runs (searched in full once one
      passes below the best's L2[e]: on a resonant axis the reach misranks). At most
      :data:`SEARCH_RUNS` runs per shape and :data:`SEARCH_BUDGET` in all.
   c. *refinement* around the best run that passed at 100 %: its admissible neighbours on
      the family's grid (one step in ω, ζ or r, or in two of them at once), the highest |L|
      at 5 Hz first; the first that passes with a lower L2[e] becomes the centre; it stops
      when no neighbour improves, after :data:`REFINE_RUNS` runs.
   d. *the margin edge* (:meth:`~motorctl.commission.verify._Verification.ridge`): from the
      best run, per damping gain (C1/C2: k_s, PID: D) the stiffest gains the margins allow
      (off the family's grid, :func:`~motorctl.commission.choose.edge_member`), walked up to
      :data:`RIDGE_SPAN` times the damping gain while the runs pass and track better, at most
      :data:`RIDGE_RUNS` runs.
   e. *confirmation* on full runs of :data:`FULL_PERIODS` program periods (saturation is
      rare and bursty: X's C2 saturated 7, 13, 15, 13, 15 times in successive 8 s windows
      of one 40 s run): the :data:`FULL_TRIES` best candidates of the short runs at 100 %,
      then those that passed, by their full L2[e], at 75 % and 50 %; the first that passes
      all three is written. Candidates whose full run tracked better but failed are
      bracketed on full runs (:meth:`~motorctl.commission.verify._Verification.bracket`: the
      saturated samples follow the damping gain ζω, L2[e] the error corner ω/ζ; the family
      one notch of ζ below its lowest too). When none passes, the best candidate stepped down
      (:data:`STEP_DOWN`), each with its three rungs; nothing that failed is ever written.
   f. *step up* from the confirmed gains: × :data:`STEP_UP` in turn where the margins hold at
      100, 75 and 50 % of the raised gains, each screened on a short run and confirmed as in
      e.; the first step that fails or does not lower L2[e] ends it.

5. **a GTCF pair** (:func:`autotune_pairs`): when two tuned axes configure the contouring pair
   law (``gtcf`` blocks naming each other) and C2 was tuned on both, its task-frame gains
   ``gain_t``, ``gain_n`` by the same rule on those C2 gains
   (:func:`motorctl.commission.gtcf_tune.tune_pair`).

6. **write** (:func:`write_config`, :func:`plot_bode`): ``DIR/autotuned.yaml`` (the gains,
   commented with the margins that chose them) and ``DIR/bode_<A>.png``.
"""

from __future__ import annotations

from pathlib import Path
import copy
import math

import numpy as np
import yaml

from motorctl.commission.choose import choose_gains, family_zetas, loop_frf, tunable_laws
from motorctl.commission.evaluate import evaluate
from motorctl.commission.fit import fit_plant, input_gain_range
from motorctl.commission.loopshape import c_frf, loop_margins
from motorctl.commission.measure import measure_friction, measure_frf
from motorctl.commission.rule import (COH_USED, FULL_PERIODS, PERIODS, REST_FACTOR, RULE, SAT_FACTOR, SAT_FLOOR_SHARE,
                                      SEARCH_BUDGET, AutotuneError, Rule)
from motorctl.commission.verify import apply_gains, verify
from motorctl.config import LoadedConfig, config_from_dict
from motorctl.control import controller_class


# ================================================================ the whole procedure
def autotune(loaded: LoadedConfig, raw: dict, axis: str, clock: str = "virtual",
             verify_s: float | None = None, progress=None, periods: int = PERIODS,
             rule: Rule = RULE, laws=None, measure_only: bool = False,
             search_runs: int = SEARCH_BUDGET, full_periods: int = FULL_PERIODS) -> dict:
    """Steps 1-4 for one axis and the laws ``laws`` (None: every law of :func:`tunable_laws`;
    ``measure_only``: steps 1-2, no law; ``search_runs``: :func:`verify`'s; ``full_periods``:
    program periods of a confirmation run). Returns
    {"measure", "model", "theta_hat0", "w", "G_fit", "G_w", "choice": {law: ...}, "verify":
    {law: ...}, "reference" (None when measure_only), "gains": {law: gains written}, "extra":
    {law: settings written with them}}.

    Raises:
        AutotuneError: the measurement faulted or tripped its guard, or no law could be tuned.
    """
    sec = loaded.axes[axis].controller
    ts = loaded.period_s
    meas = measure_frf(loaded, raw, axis, clock, progress, periods)
    if meas["fault"] or meas["tripped"] or "G" not in meas:
        why = meas["fault"] or ("the excitation guard fired (|e| reached "
                                f"{meas['guard_m'] * 1e6:.0f} um)" if meas["tripped"] else "too short")
        raise AutotuneError(f"axis {axis}: the measurement stopped: {why}")
    model = fit_plant(meas["f_hz"], meas["G"], meas["coherence"], ts, sec.theta_hat0, meas.get("u_cov"))
    fric = measure_friction(loaded, raw, axis, model["theta1"], clock, progress)
    if fric["fault"] or "theta2" not in fric:
        raise AutotuneError(f"axis {axis}: the friction passes stopped: {fric['fault'] or 'too short'}")
    meas["friction"] = fric
    # friction from the passes (steady state); the multisine's θ2 (above 10 Hz, where θ2 ẋ is
    # a few per cent of θ1 ẍ) is kept for comparison only
    model["theta2_frf"] = model["theta2"]
    model.update(theta2=fric["theta2"], theta3=fric["theta3"], theta4=fric["theta4"])
    model["sigma"] = dict(model["sigma"], theta2_frf=model["sigma"]["theta2"], **fric["sigma"])
    k_range = input_gain_range(sec.theta_min, sec.theta_max, meas.get("u_cov"))
    model["ci95"] = model_intervals(model, fric, k_range)
    if model["input_gain"] == 1.0 and meas.get("u_cov"):
        # θ̂(0) declares no input nonlinearity: θ1 is M/(A1 κ) at the multisine's amplitude,
        # κ unknown; M/A1 is known only within κ's range over the bounds of θ5, θ6
        model["input_gain_range"] = list(k_range)
        model["theta1_small_signal_range"] = model["ci95"]["theta1"]
    if progress:
        sg = model["sigma"]
        progress(f"fit {axis}: friction theta2 {fric['theta2']:.4g} +- {sg['theta2']:.2g} V s/m, theta3 "
                 f"{fric['theta3']:.4g} +- {sg['theta3']:.2g} V, theta4 {fric['theta4']:.4g} +- "
                 f"{sg['theta4']:.2g} V from {len(fric['passes'])} constant-velocity passes "
                 f"({fric['duration_s']:.1f} s)")
        rng = theta1_meaning(model)[1]
        kappa = (f"input nonlinearity's gain {model['input_gain']:.3f} taken out" if model["input_gain"] != 1.0
                 else "no input nonlinearity declared in theta_hat0: its gain at this amplitude is in it"
                 + (f"; {rng}, one amplitude cannot tell them" if rng else ""))
        progress(f"fit {axis}: theta1 {model['theta1']:.4g} +- {sg['theta1']:.2g} V s^2/m ({kappa}; theta_hat1(0) "
                 f"{sec.theta_hat0[0]:.4g}), theta2 (multisine) {model['theta2_frf']:.3g} +- "
                 f"{sg['theta2_frf']:.2g} V s/m, mode "
                 f"{model['mode_hz']:.1f} +- {sg.get('mode_hz', 0.0):.2g} Hz zeta {model['mode_damping']:.3f} load "
                 f"{model['load_fraction']:.2f}, current loop {model['current_loop_hz']:.0f} +- "
                 f"{sg['current_loop_hz']:.2g} Hz, delay {model['delay_s'] * 1e6:.1f} +- {sg['delay_s'] * 1e6:.2g} us "
                 f"(+- one standard deviation: the fit's spread and the model error its band's halves show)")
    w, G_fit, G_w = loop_frf(meas, model, ts, periods)
    th = np.asarray(sec.theta_hat0, dtype=float)
    fitted = th.copy()              # θ1 from the FRF, θ2..θ4 (viscous, Coulomb, offset) from the
    fitted[0] = model["theta1"]     # passes, θ5, θ6 (force curve) as configured
    fitted[1:4] = model["theta2"], model["theta3"], model["theta4"]
    done = {"axis": axis, "measure": meas, "model": model, "theta_hat0": th.tolist(), "w": w,
            "G_fit": G_fit, "G_w": G_w, "choice": {}, "verify": {}, "reference": None,
            "gains": {}, "extra": {}, "ts": ts, "section": sec, "rule": rule}
    if measure_only:
        return done
    period = loaded.axes[axis].trajectory.period_s
    vs = verify_s if verify_s is not None else max(2.0 * period, 1.0)
    ref = evaluate(raw, str(loaded.path), axis, sec.type, vs, clock)
    full_s = full_periods * period if period > 0 else None
    full_ref = evaluate(raw, str(loaded.path), axis, sec.type, full_s, clock) if full_s else None
    if progress:
        for r_, s_ in ((ref, vs), (full_ref, full_s)):
            if r_ is not None:
                progress(f"verify {axis}: as configured ({sec.type}), {s_:g} s: L2 {r_['L2_um']:.3f} um, "
                         f"{r_['saturated']} saturated samples, u at rest {r_['u_rest_rms_V'] * 1e3:.0f} mV")
    choice, ver, gains, extra = {}, {}, {}, {}
    for law in (laws or tunable_laws(sec)):
        ch_ = choose_gains(law, G_w, w, ts, model["theta1"], sec, meas["rest_psd"], th, rule,
                           family_zetas(law, model))
        choice[law] = ch_
        if ch_ is None:
            continue
        if progress:
            m = ch_["margins"]
            progress(f"rule {axis} {law}: {_fmt_gains(law, ch_['gains'])}: GM {m.gm_db:.1f} dB, PM "
                     f"{m.pm_deg:.1f} deg, |S| {m.ms_db:.1f} dB, crossover {m.wc_hz:.0f} Hz, rest "
                     f"{ch_['u_rest_pred_V'] * 1e3:.0f} mV predicted ({ch_['candidates']} passed "
                     f"in {len(ch_['admissible'])} shapes)")
        extra[law] = controller_class(law).model_settings(fitted) or None
        ver[law] = verify(raw, str(loaded.path), axis, law, ch_, vs, clock, ref, extra[law], progress,
                          search_runs, full_s, full_ref)
        if ver[law]["gains"] is not None:
            gains[law] = ver[law]["gains"]
    if not choice or all(c is None for c in choice.values()):
        raise AutotuneError(f"axis {axis}: no gains of any law meet the rule on the measured response")
    return done | {"choice": choice, "verify": ver, "reference": ref, "gains": gains, "extra": extra}


def autotune_pairs(loaded: LoadedConfig, raw: dict, results: list, clock: str = "virtual", progress=None,
                   rule: Rule = RULE, full_periods: int = FULL_PERIODS) -> list:
    """Step 5: GTCF's ``gain_t``, ``gain_n`` for every pair of ``results``' axes that configures
    it (each ``gtcf.partner`` the other) and had C2 tuned here on both
    (:func:`motorctl.commission.gtcf_tune.tune_pair`; ``full_periods``: program periods of its
    program runs). Returns [tune_pair's result, ...] (empty: no such pair)."""
    from motorctl.commission.gtcf_tune import pairs, tune_pair
    by = {r["axis"]: r for r in results}
    out = []
    for a, b in pairs(loaded, list(by)):
        if not all("c2" in by[x]["choice"] for x in (a, b)):
            if progress:
                progress(f"rule gtcf {a}-{b}: not tuned (c2 was not tuned on both axes)")
            continue
        out.append(tune_pair(loaded, raw, by[a], by[b], clock, progress, rule, full_periods))
    return out


#: the dynamic parameters of the multisine's fit whose 95 % interval is its own ± 1.96 σ
FRF_KEYS = ("current_loop_hz", "delay_s", "mode_hz", "mode_damping", "load_fraction")


def model_intervals(model: dict, fric: dict, k_range: tuple[float, float]) -> dict:
    """The 95 % interval of each fitted parameter of ``model`` (:func:`autotune`'s), over what
    the measurement cannot tell: {name: [lo, hi]} in the parameter's unit.

    * θ1 = M/A1: the multisine sees M/(A1 κ), κ the input nonlinearity's gain at its amplitude
      (:func:`motorctl.commission.fit.input_gain`); with θ5, θ6 anywhere in the bounds' box
      (Ω_θ, eq. 5) κ lies in :func:`~motorctl.commission.fit.input_gain_range`, so M/A1 lies in
      (θ1/κ ∓ 1.96 σ/κ)·[κ_lo, κ_hi], θ1/κ the fit before the correction;
    * θ2, θ3, θ4: the passes' "ci95" (:func:`motorctl.commission.measure.measure_friction`: the
      friction's shape and θ5, θ6 in the box);
    * the dynamic parameters (:data:`FRF_KEYS`, those the fit holds: a mode only when kept):
      ± 1.96 σ of the fit (the sandwich σ of :func:`motorctl.commission.fit.fit_plant`: the
      sampling spread; a bias of the linear model against a nonlinear axis at the multisine's
      amplitude is not in it: ``benchmarks/autotune_coverage.py`` measures how often these
      intervals hold the plant's values).

    Args: model: :func:`autotune`'s model (fitted values, "sigma", "input_gain", "mode"); fric:
    measure_friction's result; k_range: (κ_lo, κ_hi) of input_gain_range."""
    z = 1.959964
    out = {}
    k_lo, k_hi = k_range
    t1, s1 = model["theta1"] / model["input_gain"], model["sigma"]["theta1"] / model["input_gain"]
    out["theta1"] = [(t1 - z * s1) * k_lo, (t1 + z * s1) * k_hi]
    out.update({k: list(v) for k, v in fric["ci95"].items()})
    for k in FRF_KEYS:
        if k in model["sigma"] and (model["mode"] or k not in ("mode_hz", "mode_damping", "load_fraction")):
            out[k] = [model[k] - z * model["sigma"][k], model[k] + z * model["sigma"][k]]
    return out


def theta1_meaning(model: dict) -> tuple[str, str]:
    """(what the fitted θ1 of ``model`` (:func:`autotune`'s) is, the text of its M/A1 range or
    ""), for the reports: "M/A1" where the input nonlinearity's gain is taken out or none is
    declared and measured; where θ̂(0) declares none, θ1 at the multisine's amplitude and the
    range of M/A1 over the bounds of θ5, θ6 ("theta1_small_signal_range")."""
    rng = model.get("theta1_small_signal_range")
    if not rng:
        return "M/A1", ""
    return ("M/(A1 kappa) at the multisine's amplitude",
            f"M/A1 within [{rng[0]:.4g}, {rng[1]:.4g}] for theta5, theta6 within the bounds")


def _fmt_gains(law: str, g: dict) -> str:
    return " ".join(f"{k} {g[k]:.4g}" for k in controller_class(law).tuned_keys if k in g)


def final_margins(res: dict) -> dict:
    """Margins of the written gains on the measured FRF: {law: Margins}."""
    return {law: loop_margins(c_frf(law, g, res["ts"], res["w"], res["theta_hat0"]) * res["G_w"],
                              res["w"] / (2.0 * math.pi))
            for law, g in res["gains"].items()}


def write_config(raw: dict, results: list, source: str, path, pairs: list = ()) -> dict:
    """Step 6: ``raw`` with every autotuned axis's gains (each law in its own mapping of the
    ``controller:`` section) and each GTCF pair's ``gain_t``, ``gain_n`` (``pairs``:
    :func:`autotune_pairs`' results, in both axes' ``gtcf`` blocks), checked as check-config
    does, written to ``path`` with a comment block per axis (model, rule, margins,
    verification) and per pair.

    Raises:
        ConfigError: the result does not pass the checks (nothing written). OSError.
    """
    new = copy.deepcopy(raw)
    lines = [f"# motorctl autotune of {source}: per law, among the gains whose margins on the measured",
             f"# frequency response hold ({(results[0]['rule'] if results else RULE).text()} at 100/75/50 %), "
             f"the least L2[e] of a run",
             f"# of the axis's program ({FULL_PERIODS} periods, as motorctl run) that passes at 100/75/50 % of its "
             f"loop gain: no fault,",
             f"# saturated samples <= {SAT_FACTOR:g} x max(as configured, {SAT_FLOOR_SHARE:.0e} of the samples), "
             f"u RMS at rest <= {REST_FACTOR:g} x as configured, no oscillation."]
    for res in results:
        a, mdl = res["axis"], res["model"]
        sg = mdl["sigma"]
        what, rng = theta1_meaning(mdl)
        lines.append(f"# axis {a}: fitted theta1 = {what} {mdl['theta1']:.4g} +- {sg['theta1']:.2g} V s^2/m "
                     + (f"({rng}) " if rng else "") +
                     f"(config theta_hat1(0) {res['theta_hat0'][0]:.4g}; multisine), mode "
                     f"{mdl['mode_hz']:.1f} Hz (zeta {mdl['mode_damping']:.3f}, load "
                     f"{mdl['load_fraction']:.2f}), current loop {mdl['current_loop_hz']:.0f} Hz, delay "
                     f"{mdl['delay_s'] * 1e6:.1f} us")
        lines.append(f"#   friction (constant-velocity passes): theta2 = B/A1 {mdl['theta2']:.4g} +- "
                     f"{sg['theta2']:.2g} V s/m, theta3 = A_f/A1 {mdl['theta3']:.4g} +- {sg['theta3']:.2g} V, "
                     f"theta4 = F_dis0/A1 {mdl['theta4']:.4g} +- {sg['theta4']:.2g} V")
        mg = final_margins(res)
        for law in res["choice"]:
            if law not in res["gains"]:
                lines.append(f"#   {law}: not tuned (kept as configured)")
                continue
            g, v, m = res["gains"][law], res["verify"][law], mg[law]
            new = apply_gains(new, a, law, g, res["extra"].get(law))
            how = ("the rule's first candidate" if v["from"] == "rule" else "the search's best")
            lines.append(f"#   {law}: {_fmt_gains(law, g)} ({v['scale']:.0%} of {how}, L2 {v['L2_um']:.3f} um): "
                         f"GM {m.gm_db:.1f} dB at {m.gm_hz:.0f} Hz, PM {m.pm_deg:.1f} deg, |S|max "
                         f"{m.ms_db:.1f} dB, crossover {m.wc_hz:.0f} Hz")
            ex = res["extra"].get(law) or {}
            if ex:                      # a law's settings from the fitted model (PID: its feedforward)
                lines.append(f"#     from the fitted theta1 {mdl['theta1']:.4g}, theta2 {mdl['theta2']:.4g}, theta4 "
                             f"{mdl['theta4']:.4g}: " + ", ".join(f"{k} {float(x):.4g}" for k, x in ex.items()))
    from motorctl.commission.gtcf_tune import apply_pair, comment_lines
    for tp in pairs:
        new = apply_pair(new, tp)
        lines += comment_lines(tp)
    config_from_dict(new, str(path), check_budget=False)
    text = "\n".join(lines) + "\n" + yaml.safe_dump(new, sort_keys=False, default_flow_style=None)
    Path(path).write_text(text, encoding="utf-8")
    return new


def _phase_deg(H: np.ndarray) -> np.ndarray:
    """The phase of H (K,) unwrapped along the frequency and brought to (−360°, 0°] at its first
    point (a plant with a double integrator starts near −180°) [deg]."""
    ph = np.degrees(np.unwrap(np.angle(H)))
    return ph - 360.0 * math.ceil(ph[0] / 360.0)


def plot_bode(res: dict, path) -> str:
    """Step 6: the Bode plot as PNG, over the measured band only (the first to the last line of
    the multisine), five panels sharing the frequency axis: |G| (the measured lines, those of
    coherence < :data:`COH_USED` drawn light: the rule takes the model there, and the fitted
    model), G's phase, the coherence r → e with that threshold, |L| of each law's written
    gains with the crossover and the gain margin marked (a bar from |L| at the −180° crossing
    up to 1), L's phase with −180° and the phase margin marked (a bar from −180° up to the
    phase at the crossover); the last two only when gains were chosen (three panels after
    ``--measure-only``). Every phase is unwrapped the same way (:func:`_phase_deg`, along the
    whole grid from 1 Hz) and each measured line is put on the model's branch (within ±180°
    of the model at its frequency). Needs matplotlib (the ``plot`` extra)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    w, ts = res["w"], res["ts"]
    f = w / (2.0 * math.pi)
    meas = res["measure"]
    fm, Gm, coh = meas["f_hz"], meas["G"], meas["coherence"]
    ph_fit = _phase_deg(res["G_fit"])
    ph_m = np.degrees(np.angle(Gm))
    ph_m += 360.0 * np.round((np.interp(fm, f, ph_fit) - ph_m) / 360.0)     # on the model's branch
    used = coh >= COH_USED
    band = (f >= fm[0]) & (f <= fm[-1])
    # where the FRF the rule runs on (loop_frf) is the measured one: between the first and the
    # last line of coherence >= COH_USED; the fitted model elsewhere
    on_meas = (f >= fm[used][0]) & (f <= fm[used][-1]) if used.sum() > 10 else np.zeros(f.shape, bool)
    n_panels = 5 if res["gains"] else 3        # --measure-only: no loop to draw
    fig, ax = plt.subplots(n_panels, 1, figsize=(10, 13 if res["gains"] else 8), sharex=True,
                           gridspec_kw={"height_ratios": [3, 2, 1, 3, 2][:n_panels]})
    ax = list(ax) + [None] * (5 - n_panels)
    for sel, c, lab in ((used, "0.35", "measured"), (~used, "0.8", f"measured, coherence < {COH_USED:g} (not used)")):
        if sel.any():
            ax[0].loglog(fm[sel], np.abs(Gm[sel]), ".", ms=2, color=c, label=f"plant G, {lab}")
            ax[1].semilogx(fm[sel], ph_m[sel], ".", ms=2, color=c)
            ax[2].semilogx(fm[sel], coh[sel], ".", ms=2, color=c)
    ax[0].loglog(f[band], np.abs(res["G_fit"][band]), "k-", lw=1, label="plant G, fitted model")
    ax[1].semilogx(f[band], ph_fit[band], "k-", lw=1)
    ax[2].axhline(COH_USED, color="0.6", lw=0.8, ls="--")
    mg = final_margins(res)
    colors = ("tab:green", "tab:blue", "tab:red", "tab:purple", "tab:orange")
    for j, law in enumerate(res["gains"]):
        color = colors[j % len(colors)]
        L = c_frf(law, res["gains"][law], ts, w, res["theta_hat0"]) * res["G_w"]
        m = mg[law]
        ph = _phase_deg(L)
        for k, y in ((3, np.abs(L)), (4, ph)):         # dashed: where the rule's FRF is the model
            ax[k].plot(f[band], np.where(on_meas, np.nan, y)[band], color=color, lw=1, ls="--")
            ax[k].plot(f[on_meas], y[on_meas], color=color, lw=1, label=(
                f"L {law}: GM {m.gm_db:.1f} dB, PM {m.pm_deg:.0f} deg, |S| {m.ms_db:.1f} dB" if k == 3 else None))
        if math.isfinite(m.wc_hz):                      # phase margin: −180° up to the phase at crossover
            p_c = float(np.interp(m.wc_hz, f, ph))
            ax[3].axvline(m.wc_hz, color=color, ls=":", lw=0.8)
            ax[4].plot([m.wc_hz, m.wc_hz], [-180.0, p_c], color=color, lw=2.5, alpha=0.6)
            ax[4].plot([m.wc_hz], [p_c], "o", color=color, ms=4)
        if math.isfinite(m.gm_hz):                      # gain margin: |L| at −180° up to 1
            ax[3].plot([m.gm_hz, m.gm_hz], [10 ** (-m.gm_db / 20), 1.0], color=color, lw=2.5, alpha=0.6)
            ax[3].plot([m.gm_hz], [10 ** (-m.gm_db / 20)], "v", color=color)
            ax[4].axvline(m.gm_hz, color=color, ls=":", lw=0.8)
    if res["gains"]:
        ax[3].set_yscale("log")
        ax[3].axhline(1.0, color="0.6", lw=0.8)
        ax[4].axhline(-180.0, color="0.6", lw=0.8)
        ax[3].set_ylabel("|L| [-]")
        ax[4].set_ylabel("phase L [deg]")
        ax[3].legend(fontsize=8)
        ax[3].set_title(f"loop gain L = C G of the written gains (dashed: G is the model, coherence < {COH_USED:g}); "
                        "bars: the margins", fontsize=9)
    for k in (1, 4)[:1 + bool(res["gains"])]:
        ys = np.concatenate([line.get_ydata() for line in ax[k].get_lines() if len(line.get_ydata()) > 2])
        lo_, hi_ = float(np.nanmin(ys)), float(np.nanmax(ys))
        ax[k].set_ylim(45.0 * math.floor(min(lo_, -180.0) / 45.0) - 5.0, 45.0 * math.ceil(hi_ / 45.0) + 5.0)
        ax[k].set_yticks(np.arange(90.0 * math.floor(min(lo_, -180.0) / 90.0), 90.0 * math.ceil(hi_ / 90.0) + 1, 90.0))
    ax[0].set_ylabel("|G| [m/V]")
    ax[1].set_ylabel("phase G [deg]")
    ax[2].set_ylabel("coherence")
    ax[2].set_ylim(0.0, 1.05)
    ax[0].set_xlim(fm[0], fm[-1])
    ax[n_panels - 1].set_xlabel("frequency [Hz] (the measured band)")
    ax[0].legend(fontsize=8)
    ax[0].set_title(f"axis {res['axis']}: measured plant G (indirect closed-loop estimate) and fitted model")
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return str(path)
