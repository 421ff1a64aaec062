"""Step 4 of ``motorctl autotune``: closed-loop runs of the axis's program judged by the
rule's verdicts (:func:`admissible`), the search over the admissible gains, and the final
verification on full runs."""

from __future__ import annotations

import copy
import math

import numpy as np
from scipy import stats

from motorctl.commission.choose import OMEGA, design_of, neighbours, shape_of
from motorctl.commission.evaluate import evaluate
from motorctl.commission.rule import (BRACKET_EXPONENT, BRACKET_EXPONENT_RANGE, BRACKET_RUNS, BRACKET_T_SLACK,
                                      CONFIRM_ROUNDS, FULL_TRIES, NOISE_EXPONENT, NOISE_SLACK, OSC_RATIO, PROBE_RUNS,
                                      PRUNE_SHARE, REFINE_RUNS, REST_FACTOR, REST_SCREEN_SLACK, RIDGE_POINTS,
                                      RIDGE_RUNS, RIDGE_SPAN, SAT_ALPHA, SAT_FACTOR, SAT_FLOOR_SHARE,
                                      SATURATED, SCALES, SEARCH_BUDGET, SEARCH_RUNS, STEP_DOWN, STEP_UP,
                                      STEP_UP_MIN, STEP_UP_TRIES, U_REST_FRACTION, WINNER_TRIES, ZETA_BELOW)
from motorctl.config import config_from_dict
from motorctl.control import controller_class


def scaled(law: str, g: dict, s: float) -> dict:
    """Gains ``g`` at share ``s`` of the loop gain (the law's own knob:
    :meth:`motorctl.control.base.Controller.scaled`)."""
    return controller_class(law).scaled(g, s)


def apply_gains(raw: dict, axis: str, law: str, g: dict, extra: dict | None = None) -> dict:
    """A copy of the config dict with ``law``'s tuned keys of ``g`` (and the settings in
    ``extra``, e.g. the PID's feedforward) in the law's own mapping of ``axis``'s
    ``controller:`` section (over the shared keys, which stay as they are)."""
    raw = copy.deepcopy(raw)
    sec = raw["axes"][axis]["controller"]
    own = dict(sec.get(law) or {})
    if extra:
        own.update(extra)
    own.update({k: float(g[k]) for k in controller_class(law).tuned_keys if k in g})
    sec[law] = own
    return raw






def e_line_ratio(res: dict, ref: dict, expect=None) -> tuple[float, float]:
    """(largest ratio of a run's error spectrum to the reference run's above 20 Hz, where
    [Hz]). A loop near its stability limit rings at its crossover or a mode while the axis
    moves (at rest stiction can hold the carriage and hide it): e.g. X with PM −0.3° on the
    measured response: 724x at 444 Hz against ≤ 24x for loops with PM ≥ 15°. ``expect``:
    f (M,) [Hz] -> the ratio the two loops' sensitivities on the measured response predict,
    |S_run|²/|S_ref|² (:func:`motorctl.commission.choose.choose_gains`' "sensitivity"); the
    ratio is taken beyond it where it exceeds 1 (a lightly damped loop's error peaks where its
    |S| does, without ringing: rigid Y's C1 at k_s 132.5, k1 1630, PM 13° at 50 %, 136x the
    configured C2's at 93 Hz, 0.563 µm over 40 s)."""
    f, p = res["e_psd"]
    fr, pr = ref["e_psd"]
    if f.shape != fr.shape:
        return math.nan, math.nan
    band = f > 20.0
    ratio = np.where(band, p / np.maximum(pr, 1e-300), -np.inf)
    if expect is not None:
        ratio = ratio / np.maximum(expect(f), 1.0)
    j = int(np.argmax(ratio))
    return float(ratio[j]), float(f[j])


def limits(ref: dict | None, u_lim: float, samples: int, full_ref: dict | None = None,
           dispersion: float = 1.0) -> tuple[int, float]:
    """(saturated samples allowed, u RMS at rest allowed [V]) of a run of ``samples`` samples.

    Saturation is judged as the constraint on a full run is: A = :data:`SAT_FACTOR` × max(the
    configured controller's saturated samples on its run ``full_ref`` of N samples (without
    it: on ``ref``), :data:`SAT_FLOOR_SHARE` × N) in N samples, i.e. a rate A/N. A run of N
    samples or more may have its share of A. A shorter run (the search's screen) holds a
    small, bursty count, so it is judged by a one-sided test: it fails only when its count
    exceeds the (1 − :data:`SAT_ALPHA`) quantile of a count at the allowed rate over its
    samples, the count / ``dispersion`` (:func:`motorctl.commission.evaluate.sat_dispersion`,
    the run's own) taken as Poisson of mean A·samples/N / dispersion (a run exactly at the
    limit rate fails the screen in :data:`SAT_ALPHA` of its windows; the full run decides),
    and never below :data:`SAT_FACTOR` × the configured controller's count on ``ref`` (the same
    program periods, the same start). u RMS at rest: :data:`REST_FACTOR` × ``ref``'s (without
    a reference run: :data:`U_REST_FRACTION` of u_lim)."""
    base = full_ref or ref
    n_ref = base["samples"] if base else samples
    allowed = SAT_FACTOR * max(base["saturated"] if base else 0, SAT_FLOOR_SHARE * n_ref)
    if samples >= n_ref:
        sat = int(allowed * samples / n_ref) if n_ref > 0 else 0
    else:
        d = max(1.0, dispersion)
        sat = int(d * stats.poisson.ppf(1.0 - SAT_ALPHA, allowed * samples / n_ref / d))
        if ref:
            sat = max(sat, int(SAT_FACTOR * max(ref["saturated"], SAT_FLOOR_SHARE * samples)))
    rest_ref = ref["u_rest_rms_V"] if ref else math.nan
    rest = REST_FACTOR * rest_ref if rest_ref == rest_ref and rest_ref > 0 else U_REST_FRACTION * u_lim
    return sat, rest


def sat_later(res: dict, ref: dict | None, full_ref: dict | None) -> tuple[int, int] | None:
    """(saturated samples after the first program period, allowed there) of a short run of two
    program periods or more, judged as the full run ``full_ref`` it stands for; None for a run
    as long as that, without one, or of one period.

    An adaptive law saturates less in its first period than later (θ̂ and d̂ still move: the
    gantry X axis's C2 6, then 16, 15, 16, 17, 14, 18, 18, 22, 22 in the ten periods of 40 s),
    so the first period stands for the full run's first and the others for the rest: of the
    full run's allowance A (:func:`limits`), A − (first period's count) is left for its N − 1
    other periods, and the short run's k − 1 later periods fail when their count exceeds the
    (1 − :data:`SAT_ALPHA`) quantile of a quasi-Poisson count (the run's own dispersion) of
    mean (A − first)·(k − 1)/(N − 1); a run saturating no more than :data:`SAT_FACTOR` × the
    configured controller's on its run ``ref`` of the same length passes."""
    n1 = res.get("period_samples", 0)
    if not (full_ref and n1 > 0 and "sat_first" in res and 2 * n1 <= res["samples"] < full_ref["samples"]):
        return None
    allowed = limits(full_ref, 0.0, full_ref["samples"])[0]
    k, n = res["samples"] / n1, full_ref["samples"] / n1
    later = res["saturated"] - res["sat_first"]
    d = max(1.0, res.get("sat_dispersion", 1.0))
    room = int(d * stats.poisson.ppf(1.0 - SAT_ALPHA, max(allowed - res["sat_first"], 0) * (k - 1) / (n - 1) / d))
    if ref and res["saturated"] <= SAT_FACTOR * max(ref["saturated"], SAT_FLOOR_SHARE * res["samples"]):
        room = max(room, later)
    return later, room


def gain_axes(g: dict, scale: float = 1.0) -> tuple[float, float] | None:
    """(damping gain d = ζ·ω·scale [rad/s], error corner t = ω/ζ [rad/s]) of a family member
    ``g`` run at ``scale`` of its loop gain; None when ``g`` has no design pole pair (no "_w",
    "_zeta"). In the family's own terms: C1/C2 k_s = 2 θ1 d·scale and k1 = t/2 (the loop-gain
    knob scales k_s only); PID D = 2 θ1 d and P/D = t/2 (its knob scales P, I and D alike, so
    d only, t kept)."""
    if "_w" not in g or "_zeta" not in g:
        return None
    return g["_zeta"] * g["_w"] * scale, g["_w"] / g["_zeta"]


def sat_bound(full: list, allowed: float) -> float:
    """The damping gain d [rad/s] (:func:`gain_axes`) at which a full run's saturated samples
    reach ``allowed``, on ln(sat) = a + b ln d least-squares fitted to the full runs ``full``
    [(d, t, result, verdict, ...)] that saturated at all and did not fault (b: the fit's slope
    clipped to :data:`BRACKET_EXPONENT_RANGE`, or :data:`BRACKET_EXPONENT` with fewer than two
    runs or a spread of d under 5 %); inf with no such run."""
    pts = [(math.log(d), math.log(res["saturated"])) for d, _, res, *_ in full
           if not res["fault"] and res["saturated"] > 0 and d > 0]
    if not pts:
        return math.inf
    x, y = np.array(pts).T
    b = BRACKET_EXPONENT
    if np.ptp(x) > 0.05:
        b = float(np.clip(np.polyfit(x, y, 1)[0], *BRACKET_EXPONENT_RANGE))
    a = float(np.mean(y - b * x))
    return math.exp((math.log(max(allowed, 1.0)) - a) / b)


def rest_judged(res: dict, full_ref: dict | None = None) -> tuple[float, bool]:
    """(the u RMS at rest [V] a run is judged by, whether it is a prediction): its own; for a
    run shorter than the configured controller's full run ``full_ref``, the full run's it predicts: the first program period as
    the full run's first (an adaptive law's θ̂ still moves there, and its rest is noisier:
    rigid Y's C2 61 mV RMS over 8 s, 37 mV over 40 s), the others for the rest of the full
    run's periods, in mean square (then judged against :data:`REST_SCREEN_SLACK` × the full
    run's limit: the prediction is a screen, the full run judges). Its own when it has one
    period only."""
    n1, n = res.get("period_samples", 0), full_ref["samples"] if full_ref else 0
    a, b = res.get("u_rest_first_V", math.nan), res.get("u_rest_later_V", math.nan)
    if not (n1 > 0 and res["samples"] < n and a == a and b == b):
        return res["u_rest_rms_V"], False
    periods = n / n1
    return math.sqrt((a * a + (periods - 1.0) * b * b) / periods), True


def admissible(res: dict, u_lim: float, ref: dict | None = None, osc_ref: dict | None = None,
               full_ref: dict | None = None, expect=None) -> str:
    """'' when a run meets the rule's closed-loop lines, else why not (one phrase). ref: the
    configured controller's run on the same program and of the same length
    (:func:`motorctl.commission.evaluate.evaluate`): the saturation and the u noise at rest are
    judged against it and against its full run ``full_ref`` (:func:`limits`), and an error
    spectrum :data:`OSC_RATIO` times its own at some frequency is an oscillation (``osc_ref``:
    another run's spectrum instead; ``expect``: beyond the ratio the sensitivities predict,
    :func:`e_line_ratio`)."""
    if res["fault"]:
        return f"fault: {res['fault']}"
    sat_max, rest_max = limits(ref, u_lim, res["samples"], full_ref, res.get("sat_dispersion", 1.0))
    later = sat_later(res, ref, full_ref)
    if later is not None:
        if later[0] > later[1]:
            return (f"{res['saturated']} {SATURATED} ({later[0]} after the first program period > "
                    f"{later[1]}, of {res['samples']})")
    elif res["saturated"] > sat_max:
        return f"{res['saturated']} {SATURATED} (> {sat_max} of {res['samples']})"
    rest, predicted = rest_judged(res, full_ref)
    over = ""
    if predicted:
        rest_max = REST_SCREEN_SLACK * limits(full_ref, u_lim, full_ref["samples"])[1]
        over = f" predicted over {full_ref['samples']} samples"
    if not rest <= rest_max:
        return f"u at rest {rest * 1e3:.0f} mV RMS{over} (> {rest_max * 1e3:.0f} mV)"
    if res["osc_ratio"] >= OSC_RATIO:
        return f"oscillation at {res['osc_hz']:.0f} Hz (line {res['osc_ratio']:.0f}x the median)"
    if osc_ref or ref:
        ratio, f = e_line_ratio(res, osc_ref or ref, expect)
        if ratio >= OSC_RATIO:
            whose = "the same gains' at 100 %" if osc_ref else "the configured controller's"
            return f"oscillation at {f:.0f} Hz (e {ratio:.0f}x {whose})"
    return ""


def too_soft(res: dict, u_lim: float, ref: dict | None = None) -> bool:
    """Whether a failed run (:func:`admissible`) failed because its loop is too soft for the
    program: a following-error fault while u was quiet at rest and showed no line, in u at
    rest nor in e against ``ref`` (a loop that rings until it faults shows one). A higher
    loop gain of the same shape is then the way out, not a lower one."""
    if "following error" not in res["fault"]:
        return False
    if not res["u_rest_rms_V"] <= limits(ref, u_lim, res["samples"])[1] or res["osc_ratio"] >= OSC_RATIO:
        return False
    return not (ref and e_line_ratio(res, ref)[0] >= OSC_RATIO)


def verify(raw: dict, source: str, axis: str, law: str, choice: dict, seconds: float,
           clock: str = "virtual", ref: dict | None = None, extra: dict | None = None,
           progress=None, search_runs: int = SEARCH_BUDGET, full_seconds: float | None = None,
           full_ref: dict | None = None) -> dict:
    """Step 4 for one law (module docstring): on runs of ``seconds``, the ladder on the rule's
    first candidate, the search over the admissible shapes and the local refinement around its
    best; then the confirmation on full runs of ``full_seconds`` (:meth:`_Verification.confirm`).

    Args:
        choice: :func:`motorctl.commission.choose.choose_gains`'s result. ref, full_ref: the
        configured controller's runs of ``seconds`` and ``full_seconds``
        (:func:`motorctl.commission.evaluate.evaluate`). extra: settings written with the gains
        (the PID's feedforward). search_runs: the search's budget (b.); the refinement's is the
        lesser of it and :data:`REFINE_RUNS`. full_seconds: None: no confirmation (the short
        runs' ladder decides).
    Returns:
        {"gains" (None when nothing passed), "scale" (of the winner's own gains), "from" ('rule'
        or 'search'), "L2_um" (of its full run at 100 %, else of its short run), "runs":
        [(label, scale, result, verdict)]}.
    """
    v = _Verification(raw, source, axis, law, choice, seconds, clock, ref, extra, progress, full_ref)
    g0 = choice["gains"]
    s0, r0 = v.ladder(g0, choice["backoff"], "rule")
    rule_best = (r0["L2_um"], scaled(law, g0, s0), s0, "rule") if s0 > 0 else None
    if rule_best:
        v.short[(design_of(g0), s0)] = r0
    v.calibrate_on_rule()
    v.tried[design_of(g0)] = (r0, "") if s0 == 1.0 else (None, "failed in the ladder")
    if s0 == 1.0:
        v.found.append((r0["L2_um"], g0, 1.0, "rule"))
    v.search(search_runs)
    if not v.found and rule_best is None:    # nothing passed yet: a second budget (runs made are not repeated)
        v.search(search_runs)
    v.refine(min(REFINE_RUNS, search_runs))
    v.ridge(min(RIDGE_RUNS, search_runs // 3))
    if full_seconds:
        best = v.confirm(rule_best, full_seconds, full_ref)
    else:
        best = v.winner(rule_best)
    if best is None:
        return {"gains": None, "scale": 0.0, "from": "", "L2_um": math.nan, "runs": v.runs}
    return {"gains": best[1], "scale": best[2], "from": best[3], "L2_um": best[0], "runs": v.runs}


class _Verification:
    """What the steps of :func:`verify` share for one law: the runs made, the designs tried and
    their verdicts, the family members that passed at 100 %, and the calibration of the rest
    noise on the machine against the prediction.

    The calibration: the prediction (the open loop of a carriage held by stiction) is a bound
    that grows faster with ω than the noise does; so a member's noise is read off its
    prediction as a power law through the nearest run of its shape, with the shape's own
    exponent once it has two runs (NOISE_EXPONENT until then); a shape not yet run: in
    proportion to the latest run of any (a run that faulted says nothing of the noise).
    """

    def __init__(self, raw, source, axis, law, choice, seconds, clock, ref, extra, progress, full_ref=None):
        self.raw, self.source, self.axis, self.law, self.choice = raw, source, axis, law, choice
        self.full_ref = full_ref
        self.seconds, self.clock, self.ref, self.extra, self.progress = seconds, clock, ref, extra, progress
        sec = self.section = config_from_dict(raw, source).axes[axis].controller   # the configured law's
        self.u_lim = sec.u_lim
        self.rest_max = limits(full_ref or ref, self.u_lim, 0)[1]    # the level rest_judged is held to
        self.runs: list = []      # (label, scale, result, verdict)
        self.tried: dict = {}     # {design: (result or None, verdict)}
        self.found: list = []     # (L2, gains, 1.0, 'rule' | 'search') passed at 100 %
        self.obs: dict = {}       # {shape: [(predicted, measured) rest noise [V]]}
        self.last: list = []      # the latest (predicted, measured) of any shape
        self.short: dict = {}     # {(design, scale): the short run's result} of what passed it
        self.full: list = []      # (damping gain, error corner, result, verdict, other design numbers) of the
                                  # full runs (:func:`gain_axes`, :func:`_others`)
        sens = choice.get("sensitivity")
        try:
            own = {k: float(getattr(sec.settings(sec.type), k)) for k in controller_class(sec.type).tuned_keys}
            sens and sens(sec.type, own, np.array([100.0]))
        except (AttributeError, KeyError, TypeError, NotImplementedError):
            sens = None                           # the configured law has no linearisation: none predicted
        self._sens = (lambda g: lambda f: sens(law, g, f) / sens(sec.type, own, f)) if sens else None

    def expect(self, g):
        """f [Hz] -> |S|² of ``g``'s loop over the configured controller's on the measured
        response (:func:`e_line_ratio`), or None."""
        return self._sens(g) if self._sens else None

    def run(self, g, label, scale, seconds=None, ref=None):
        """One run of gains ``g`` (already scaled by ``scale``, which only labels it) of
        ``seconds`` (default: the short runs') judged against ``ref`` (default: the short
        reference); recorded. Returns (result, verdict: '' when it passed)."""
        seconds = seconds or self.seconds
        ref = ref if ref is not None else self.ref
        res = evaluate(apply_gains(self.raw, self.axis, self.law, g, self.extra), self.source, self.axis,
                       self.law, seconds, self.clock)
        why = admissible(res, self.u_lim, ref, full_ref=self.full_ref, expect=self.expect(g))
        self.record(f"{label} {seconds:g} s", scale, res, why)
        axes = gain_axes(g, scale)
        if seconds > self.seconds and axes is not None:
            self.full.append((*axes, res, why, _others(g)))
        return res, why

    def record(self, label, scale, res, why) -> None:
        self.runs.append((label, scale, res, why))
        if self.progress:
            self.progress(f"verify {self.axis} {self.law} {label} at {scale:.0%}: L2 "
                          f"{res['L2_um']:.3f} um, e_M {res['e_M_um']:.2f} um, rest "
                          f"{res['u_rest_rms_V'] * 1e3:.0f} mV, sat {res['saturated']}: {why or 'ok'}")

    def ladder(self, g, backoff, label, done=None) -> tuple[float, dict | None]:
        """Short runs of ``g`` climbing :data:`SCALES`. A rung that saturates more than allowed
        is not passed, but the climb goes on (a lower loop gain can saturate more: its error
        is larger), after one run at the geometric mean of it and the last passed scale; a
        fault, u noise at rest or an oscillation stops it, and then one more run at the
        geometric mean of the last passed and the stopping scale; when 50 % stops it with
        nothing passed, the ``backoff`` scales in turn. ``done``: {scale: result} already run
        (and passed). Returns (the highest scale that passed, 0 when none; its result)."""
        passed, best, steps = 0.0, None, list(SCALES)
        done = done or {}
        while steps:
            sc = steps.pop(0)
            if sc in done:
                res, why = done[sc], ""
            else:
                res, why = self.run(scaled(self.law, g, sc), label, sc)
            if why and SATURATED in why:
                if passed > 0 and sc / passed > 1.2:       # one rung between, then climb on
                    steps.insert(0, round(math.sqrt(passed * sc), 3))
                continue
            if why:
                lower = [b for b in backoff if b < sc]
                if sc <= SCALES[0] and lower and passed == 0:
                    steps = lower[:1]
                    continue
                if passed > 0 and sc / passed > 1.2:       # one rung between the last two
                    steps = [round(math.sqrt(passed * sc), 3)]
                    continue
                break
            if sc > passed:
                passed, best = sc, res
            if sc < SCALES[0]:
                break
        return passed, best

    def confirm(self, rule_best, seconds: float, ref: dict | None):
        """The verification on full runs of ``seconds`` (the program's periods, judged against
        the configured controller's run ``ref`` of the same length): the candidates that passed
        their short run (the search's and the rule's) whose margins hold at 100, 75 and 50 % of
        the gains themselves (a candidate the ladder stopped below 100 %: of its scaled gains),
        by their short L2[e], the first
        :data:`FULL_TRIES` run at 100 % (when nothing of them is written, the next :data:`FULL_TRIES`, up to
        :data:`CONFIRM_ROUNDS` rounds: on half-mode X the PID+FF's only candidate that passed at
        100 % rang at rest at 50 %, its steps down failed the margins, and nothing was written
        while candidates were left); those that pass, by their full L2[e], each run at
        75 % and 50 % (:data:`SCALES`, highest first); the first that passes all three rungs
        wins. Candidates that tracked better on their full run but failed it (a law whose
        saturation grows through the run: gantry X's C2 at ω 711, ζ 0.3 saturated 6 times in
        8 s and 49 in 40 s, limit 15) are then bracketed on full runs (:meth:`bracket`), and
        the best climbs (:meth:`climb`). A candidate whose full run fails on
        its rest noise bars those whose short run was as noisy at rest or more
        (:func:`rest_judged`). (Not so on saturation: a short run's few
        saturated samples do not rank the full runs': rigid X's C2 at ω 1149, ζ 0.2 saturated
        3 times in 8 s and 91 in 40 s, at ω 1044, ζ 0.2 6 and 60.) When none passes, the best
        candidate's gains stepped down (:data:`STEP_DOWN`), each with its own three rungs.
        Returns (L2 of the full run at 100 %, gains, scale, from) or
        None (nothing is written)."""
        return self._confirm(self._pool(rule_best), seconds, ref, 1)

    def _pool(self, rule_best) -> list:
        """The candidates of :meth:`confirm`, by their short L2[e], each design and scale once."""
        pool, seen = [], set()
        cands = sorted(self.found + ([rule_best] if rule_best else []), key=lambda b: b[0])
        for c in cands:
            key = (design_of(c[1]), c[2])
            if key not in seen:
                seen.add(key)
                pool.append(c)
        holds = self.choice.get("holds", lambda g: True)
        return [c for c in pool if holds(c[1])]      # the margins at 100/75/50 % of the gains written

    def _confirm(self, pool: list, seconds: float, ref: dict | None, round_: int):
        """:meth:`confirm` on ``pool`` (:meth:`_pool`); when nothing of its first FULL_TRIES is
        written, the rest of the pool in another round, up to :data:`CONFIRM_ROUNDS`."""
        full, bars, tries, done = [], [], 0, len(pool)
        holds = self.choice.get("holds", lambda g: True)
        for i, (l2, g, sc, frm) in enumerate(pool):
            if tries == FULL_TRIES:
                done = i
                break
            short = self.short.get((design_of(g), sc))
            if short is not None and any(_as_bad(short, bar, self.full_ref) for bar in bars):
                continue
            tries += 1
            res, why = self.run(g, "confirm", sc, seconds, ref)
            if not why:
                full.append((res["L2_um"], g, sc, frm, res))
            elif short is not None and "u at rest" in why:
                bars.append(short)
        won = None
        for cand in sorted(full, key=lambda b: b[0]):
            if self._rungs(cand[1], cand[2], seconds, ref, cand[4]):
                won = cand[:4]
                break
        if won is not None:
            return self.climb(self.bracket(won, seconds, ref), seconds, ref)
        if not pool:
            return None
        l2, g, sc, frm = pool[0]
        for step in STEP_DOWN:
            gs = scaled(self.law, g, step)
            if not holds(gs):
                continue
            res, why = self.run(gs, "step down", sc * step, seconds, ref)
            if not why and self._rungs(gs, sc * step, seconds, ref, res):
                return (res["L2_um"], gs, sc * step, frm)
        if round_ < CONFIRM_ROUNDS and done < len(pool):
            return self._confirm(pool[done:], seconds, ref, round_ + 1)
        return None

    def bracket(self, best, seconds: float, ref: dict | None):
        """Full runs between the confirmed ``best`` (L2, gains, scale, from) and the candidates
        whose full runs tracked better but failed, in the two directions that matter
        (:func:`gain_axes`): the saturated samples follow the damping gain d = ζω (k_s, D), the
        tracking error the error corner t = ω/ζ (k1, P/D). Measured on configs/gantry.yaml X
        with C2 over 40 s: at ζ 0.3, ω 500 .. 700 (d 150 .. 210) 11, 18, 30, 27, 49 saturated
        samples while L2[e] fell 1.54 .. 0.97 µm; at the same k1 1167, k_s 46.7 and 53.9
        saturated 21 and 26 times; ζ 0.4 saturated 25 times at d 176 with L2 2.2 µm, ζ 0.25
        13 times at d 138 with 1.27 µm. So the next run is the member (the family's, and one
        notch of ζ below it: :meth:`below`) of the highest t, up to the best failed
        candidate's, whose d stays under the d where the saturated samples reach the full
        run's allowance, on a power law ln(sat) = a + b ln d fitted to every full run so far
        (b from :data:`BRACKET_EXPONENT` and its range), and that no failed full run dominates
        (at least its d and its t); t up to :data:`BRACKET_T_SLACK` times the best failed one's
        (less than one ω step of the grid, 1.1007: the family's ζ fall on nearly the same t,
        rigid X's ζ 0.15 at ω 862 on 5747 rad/s against ζ 0.2 at ω 1149 on 5745), and the failed
        candidates' other design numbers (the PID's r: its tracking is its integral's too). A run that passes with a lower L2[e] and whose rungs
        pass becomes the best; each run refits the law. At most :data:`BRACKET_RUNS` runs at
        100 %. Returns the best."""
        holds = self.choice.get("holds", lambda g: True)
        if self.full_ref is None or gain_axes(best[1], best[2]) is None:
            return best
        allowed = limits(self.full_ref, self.u_lim, self.full_ref["samples"])[0]
        pool = list(self.choice.get("members", {}).values()) + self.below()
        for _ in range(BRACKET_RUNS):
            d0, t0 = gain_axes(best[1], best[2])
            failed = [(d, t, res) for d, t, res, why, _ in self.full if why and not res["fault"]]
            better = [(t, rest) for d, t, res, why, rest in self.full
                      if why and not res["fault"] and res["L2_um"] < best[0]]
            if not better:
                break
            t_cap = BRACKET_T_SLACK * max(t for t, _ in better)
            kinds = {rest for _, rest in better}      # their other design numbers (the PID's r)
            d_max = sat_bound(self.full, allowed)
            done = {(round(d, 6), round(t, 6)) for d, t, _, _, _ in self.full}
            cands = []
            for g in pool:
                d, t = gain_axes(g, 1.0)
                if (round(d, 6), round(t, 6)) in done or not (t0 < t <= t_cap) or d > d_max:
                    continue
                if _others(g) not in kinds:
                    continue
                if any(d >= fd and t >= ft for fd, ft, _ in failed) or not holds(g):
                    continue
                cands.append((t, d, g))
            if not cands:
                break
            _, _, g = max(cands, key=lambda c: (c[0], c[1]))
            res, why = self.run(g, "bracket " + _fmt_shape(g), 1.0, seconds, ref)
            if not why and res["L2_um"] < best[0] and self._rungs(g, 1.0, seconds, ref, res):
                best = (res["L2_um"], g, 1.0, "search")
        return best

    def below(self) -> list[dict]:
        """The family one notch of ζ below its lowest (× :data:`ZETA_BELOW`), with the
        margins holding at 100, 75 and 50 % (``choice["holds"]``): the independent search's
        best C2 gains on configs/gantry.yaml X sit at ζ ≈ 0.25, below the law's own 0.3
        (1.27 µm with 13 saturated samples in 40 s where ζ 0.3 reached 1.54 µm with 11).
        Empty when the choice does not state its θ1 and settings."""
        grid, holds = self.choice.get("grid", {}), self.choice.get("holds")
        if "_zeta" not in grid or "theta1" not in self.choice or holds is None:
            return []
        z = round(min(grid["_zeta"]) * ZETA_BELOW, 4)
        fam = controller_class(self.law).gain_family(self.choice["theta1"], self.section.settings(self.law), OMEGA,
                                                    zetas=(z,))
        return [g for g in fam if holds(g)]

    def climb(self, best, seconds: float, ref: dict | None):
        """Up from the confirmed ``best`` (L2, gains, scale, from): its gains at :data:`STEP_UP`
        times their loop gain, where the margins hold at 100, 75 and 50 % of the raised gains;
        each screened on a short run, then confirmed as :meth:`confirm` does (a full run and
        its rungs). A step that passes with a lower L2[e] becomes the best and the next goes
        on from it with the same factor; one that fails halves the factor (in log) down to
        :data:`STEP_UP_MIN`; at most :data:`STEP_UP_TRIES` steps. The search's grid stops
        where its short runs stop it; this goes where the full runs allow (a rigid plant's
        margins leave room above the grid's point). Returns the best."""
        holds = self.choice.get("holds", lambda g: True)
        step = STEP_UP
        for _ in range(STEP_UP_TRIES):
            if step < STEP_UP_MIN:
                break
            l2, g, sc, frm = best
            gu = scaled(self.law, g, step)
            if holds(gu):
                why = self.run(gu, "step up", sc * step)[1] if seconds > self.seconds else ""
                if not why:
                    res, why = self.run(gu, "step up", sc * step, seconds, ref)
                    if not why and res["L2_um"] < l2 and self._rungs(gu, sc * step, seconds, ref, res):
                        best = (res["L2_um"], gu, sc * step, frm)
                        continue
            step = math.sqrt(step)
        return best

    def _rungs(self, g, sc, seconds, ref, top: dict) -> bool:
        """Full runs of ``g`` at the ladder's rungs below 100 % (:data:`SCALES`, highest first);
        whether every one passed. A lower rung stands for a heavier load or a weaker amplifier:
        it must not fault, ring or be noisy at rest (the limits of ``ref``). Its error spectrum
        is compared with the gains' own run at 100 % ``top`` (a softer loop rejects less, and
        its error at tens of Hz is a few times the stiff configured controller's without any
        ringing: Y's PID at 50 % 130-380x the configured C2's, never 100x its own), and its
        saturation is reported, not judged (a softer loop's larger error drives u into its
        limit more often: X's C2 at 50 % saturates 3-5x what it does at 100 %)."""
        for rung in sorted(SCALES[:-1], reverse=True):
            gr = scaled(self.law, g, rung)
            res = evaluate(apply_gains(self.raw, self.axis, self.law, gr, self.extra), self.source, self.axis,
                           self.law, seconds, self.clock)
            why = admissible({**res, "saturated": 0}, self.u_lim, ref, osc_ref=top)
            self.record(f"confirm {seconds:g} s", sc * rung, res, why)
            if why:
                return False
        return True

    def calibrate_on_rule(self) -> None:
        """The first calibration point: the ladder's run whose noise most exceeds its prediction."""
        pred = self.choice["u_rest_pred_V"]
        pts = [(sc * pred, rest) for sc, rest in ((sc, rest_judged(res, self.full_ref)[0])
                                                  for _, sc, res, _ in self.runs if not res["fault"])
               if rest > 0 and pred > 0]
        self.last = [max(pts, key=lambda x: x[1] / x[0])] if pts else []

    def noise_of(self, g) -> float:
        """The rest noise [V] expected of the design ``g`` (class docstring)."""
        own = self.obs.get(shape_of(g), [])
        if not (own or self.last) or g["_rest_V"] <= 0:
            return 0.0
        if not own:                             # another shape's run: in proportion
            return self.last[0][1] * g["_rest_V"] / self.last[0][0]
        beta = NOISE_EXPONENT
        lp = np.log([x[0] for x in own])
        if np.ptp(lp) > 0.05:
            beta = float(np.clip(np.polyfit(lp, np.log([x[1] for x in own]), 1)[0], 0.25, 1.0))
        p0, a0 = min(own, key=lambda x: abs(math.log(g["_rest_V"] / x[0])))
        return a0 * (g["_rest_V"] / p0) ** beta

    def noisy(self, g) -> bool:
        return self.noise_of(g) > NOISE_SLACK * self.rest_max

    def trial(self, g, label):
        """A run of ``g`` at 100 % (once per design); recorded, calibrated on. Returns
        (result, verdict: '' when it passed)."""
        key = design_of(g)
        if key in self.tried:
            return self.tried[key]
        res, why = self.run(g, label, 1.0)
        self.tried[key] = (res, why)
        if not why:
            self.found.append((res["L2_um"], g, 1.0, "search"))
            self.short[(key, 1.0)] = res
        rest = rest_judged(res, self.full_ref)[0]
        if not res["fault"] and rest > 0 and g["_rest_V"] > 0:   # nan: False
            self.obs.setdefault(shape_of(g), []).append((g["_rest_V"], rest))
            self.last[:] = [(g["_rest_V"], rest)]
        return res, why

    def reach(self, members) -> float:
        """|L| at F_TRACK_HZ of the shape's highest admissible ω whose noise is quiet."""
        g = next((g for g in members if not self.noisy(g)), members[-1])
        return self.choice["l_track"][design_of(g)]

    def search(self, budget: int) -> None:
        """Per shape, the highest ω that passes, bracketed on the shape's admissible ω (those
        whose rest noise, so calibrated, stays below the level). A run that fails by noise,
        saturation, oscillation or a fault of a ringing loop bounds ω from above; one that
        faults on its following error while quiet, or saturates more than at a higher ω (too
        soft for the program), bounds it from below. Shapes in the order of the |L| at
        F_TRACK_HZ of their highest quiet admissible ω (re-ranked after each shape, the
        calibration moving on), at most SEARCH_RUNS runs per shape and ``budget`` in all."""
        choice, u_lim = self.choice, self.u_lim
        w_hint, left, spent = None, dict(choice["admissible"]), 0
        while left and spent < budget:
            members = left.pop(max(left, key=lambda k: self.reach(left[k])))
            lead = min(self.found, key=lambda b: b[0], default=None)
            # a shape that reaches less than PRUNE_SHARE of the best run's is probed: PROBE_RUNS
            # runs, all of them only once one passes below the best's L2[e] (on a resonant axis
            # the reach at F_TRACK_HZ misranks: half-mode Y's C1 best is ω 330, ζ 1)
            probe = lead is not None and design_of(lead[1]) in choice["l_track"] and \
                self.reach(members) < PRUNE_SHARE * choice["l_track"][design_of(lead[1])]
            n = len(members)
            top = next((j for j, g in enumerate(members) if not self.noisy(g)), n - 1)
            p = top if w_hint is None else max(top, min(range(n),
                                                       key=lambda j: abs(members[j]["_w"] - w_hint)))
            # positions: ω falls with j; hi < boundary ≤ ok < lo (hi: failed high, lo: failed soft)
            hi, lo, ok, down, up, sat = -1, n, None, 1, 1, {}
            for k in range(SEARCH_RUNS):
                if spent >= budget or (probe and k >= PROBE_RUNS):
                    break
                n_before = len(self.runs)
                res, why = self.trial(members[p], _fmt_shape(members[p]))
                spent += len(self.runs) - n_before
                if probe and not why and res["L2_um"] < lead[0]:
                    probe = False                   # it beats the best: a shape like the others
                if res is not None and why and SATURATED in why:
                    sat[p] = res["saturated"]
                if not why:
                    ok = p if ok is None else min(ok, p)
                elif res is not None and (too_soft(res, u_lim, self.ref) or (
                        p in sat and any(j < p and sat[j] < sat[p] for j in sat))):
                    lo = min(lo, p)                 # (saturating more than at a higher ω: its error)
                else:
                    hi = max(hi, p)
                # the highest ω whose noise, calibrated anew on this run, stays below the level
                # (a shape with no noise of its own yet, all its runs faulted: no ceiling)
                top = (next((j for j, g in enumerate(members) if j > hi and not self.noisy(g)), n - 1)
                       if shape_of(members[0]) in self.obs else hi + 1)
                floor_ = max(hi, top - 1)           # every position ≤ this fails or is noisy
                if ok is not None:
                    if ok - floor_ <= 1:
                        break
                    if hi < 0:                      # nothing above has failed yet: climb
                        p, up = max(top, ok - up), up * 2
                    else:
                        p = (floor_ + ok) // 2
                elif lo - floor_ <= 1:              # no ω left between the two kinds of failure
                    break
                elif lo < n and hi < 0:             # only too soft so far: climb
                    p, up = max(floor_ + 1, p - up), up * 2
                elif lo < n:                        # failed on both sides: halve the window
                    p = (floor_ + lo) // 2
                else:                               # only too high so far: descend
                    p, down = min(n - 1, max(top, p + down)), down * 2
            if ok is not None:
                w_hint = members[ok]["_w"]

    def refine(self, budget: int) -> None:
        """From the best family member that passed, one grid step at a time (ω, ζ, r, and two of
        them at once) to an admissible neighbour not yet run, the highest |L| at F_TRACK_HZ
        first; move to the first that passes with a lower L2[e], stop when none does or after
        ``budget`` runs."""
        choice = self.choice
        center = min(self.found, key=lambda b: b[0], default=None)
        while center is not None and budget > 0:
            near = [g for g in neighbours(center[1], choice["grid"], choice["members"])
                    if design_of(g) not in self.tried and not self.noisy(g)]
            near.sort(key=lambda g: -choice["l_track"][design_of(g)])
            moved = None
            for g in near[:budget]:
                budget -= 1
                res, why = self.trial(g, "near " + _fmt_shape(g))
                if not why and res["L2_um"] < center[0]:
                    moved = (res["L2_um"], g, 1.0, "search")
                    break
            center = moved

    def ridge(self, budget: int) -> None:
        """From the best family member that passed at 100 %, along the margin edge
        (:func:`motorctl.commission.choose.edge_member`: per damping gain, the stiffest gains
        the margins allow): of the edge's members at 1 to :data:`RIDGE_SPAN` times the centre's
        damping gain (:data:`RIDGE_POINTS` of them), not yet run, whose rest noise (calibrated
        through the prediction from the centre's own run, as :meth:`noise_of` does within a
        shape) stays below the level and whose |L| at F_TRACK_HZ
        is above the centre's, the one of highest |L|; one that passes with a lower L2[e]
        becomes the centre, the first that does not ends the walk. At most ``budget`` runs. The margins bind between the family's damping ratios, and the grid's ζ steps
        stop the search short of the edge (rigid Y's C1: ω 330, ζ 0.2 passed, 1.539 µm on
        the full run; the edge ζ 0.21 at ω 400: 1.095 µm)."""
        edge = self.choice.get("edge")
        center = min(self.found, key=lambda b: b[0], default=None)
        if edge is None or center is None:
            return
        l_track = self.choice["l_track"]
        while budget > 0:
            reach = l_track[design_of(center[1])]
            c_rest = rest_judged(self.tried[design_of(center[1])][0], self.full_ref)[0]

            def quiet(g):       # the centre's own noise through the prediction (as noise_of on a shape)
                return c_rest * (g["_rest_V"] / center[1]["_rest_V"]) ** NOISE_EXPONENT <= NOISE_SLACK * self.rest_max

            near = [g for g in (edge(center[1], u) for u in np.geomspace(1.0, RIDGE_SPAN, RIDGE_POINTS))
                    if g is not None and design_of(g) not in self.tried and quiet(g)
                    and reach < l_track[design_of(g)]]
            if not near:
                return
            g = max(near, key=lambda m: l_track[design_of(m)])
            budget -= 1
            res, why = self.trial(g, "edge " + _fmt_shape(g))
            if why or res["L2_um"] >= center[0]:
                return                  # the edge's neighbours differ little (gantry X C2: four runs at ω 960)
            center = (res["L2_um"], g)

    def winner(self, rule_best):
        """The least L2[e] of every run that passed: (L2, gains, scale, from) or None. A search
        winner climbs the ladder too (its 100 % run is already done); when a rung below stops
        it, it stands at the highest scale that passed (as the rule's gains do) and the next
        best climbs, at most WINNER_TRIES of them, one per shape; the least L2[e] of what stood
        is kept."""
        accepted = [rule_best] if rule_best is not None else []
        climbs, stopped = 0, set()
        for cand in sorted((b for b in self.found if b[3] == "search"), key=lambda b: b[0]):
            if climbs == WINNER_TRIES or (accepted and min(a[0] for a in accepted) <= cand[0]):
                break
            if shape_of(cand[1]) in stopped:        # its shape stopped on a lower rung already
                continue
            climbs += 1
            sc, res_sc = self.ladder(cand[1], (), "winner", done={1.0: self.tried[design_of(cand[1])][0]})
            if sc == 1.0:
                accepted.append(cand)
                break
            stopped.add(shape_of(cand[1]))
            if sc > 0.0:
                accepted.append((res_sc["L2_um"], scaled(self.law, cand[1], sc), sc, "search"))
        return min(accepted, key=lambda b: b[0], default=None)


def _others(g: dict) -> tuple:
    """A candidate's design numbers other than ω and ζ (the PID's integral ratio r)."""
    return tuple((k, v) for k, v in shape_of(g) if k != "_zeta")


def _as_bad(short: dict, bar: dict, full_ref: dict | None) -> bool:
    """Whether a short run ``short`` was as noisy at rest (:func:`rest_judged`) as the short run
    ``bar`` of a candidate whose full run failed on its rest noise, or more."""
    return rest_judged(short, full_ref)[0] >= rest_judged(bar, full_ref)[0]


def _fmt_shape(g: dict) -> str:
    return "w {:.0f}".format(g["_w"]) + "".join(f" {k[1:]} {v:g}" for k, v in shape_of(g))
