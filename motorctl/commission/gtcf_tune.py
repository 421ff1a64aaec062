"""``motorctl autotune`` for the contouring pair law GTCF (:mod:`motorctl.control.gtcf`): each
axis's contour gain ``gain_n`` chosen by the rule per-axis C2 is chosen by
(:mod:`motorctl.commission.autotune`), after both axes' C2 gains are chosen.

GTCF is C2 on each axis with the robust feedback −k_s p set in the task frame of the desired
path (Hu, Yao & Wang, IEEE TIE 58(11), 2011; docs/control-law.md, "GTCF"): an error normal to
the path meets √(g_n,X g_n,Y)-weighted gains, one along it g_t k_s, on each axis's own k_s and
k1 (the autotuned C2 gains of the pair). Axis i's own term of that feedback is
−k_s,i (g_t t_i² + g_n,i n_i²) p_i: as the path turns, each axis's loop is C2's with its k_s
scaled by every factor between g_t and its own g_n,i, the part beyond C2's unfiltered or
through the law's low-pass (``lowpass_hz``: :data:`LOWPASS_HZ`, less of the encoder's noise,
less phase margin: each axis's own choice). The pair's two loops are coupled
through the cross term, and the margins here are per axis (SISO), with the task-frame gain as
the loop-gain scale: what the rule can read off one axis's measured response. g_t is 1 (the
tangential stiffness the per-axis autotune chose); each axis's g_n and low-pass are searched.

The rule (the same lines as per-axis C2's, :mod:`motorctl.commission.rule`; nothing judged by
the contour error):

1. *margins* on each axis's measured FRF (:func:`motorctl.commission.choose.loop_frf`): GTCF's
   linearisation (:meth:`motorctl.control.gtcf.GTCF.linearise`) at every g on
   :data:`SPAN_POINTS` points from 1 to the axis's g_n, every one at 100, 75 and 50 % of its
   loop gain (:func:`motorctl.commission.choose.margins_hold`): GM ≥ 6 dB, PM ≥ 10°,
   |S| ≤ 16 dB (the rule's :class:`~motorctl.commission.rule.Rule`). Each axis's admissible
   options follow from its own response: for each g_n of :data:`GAIN_N`, highest first, the
   unfiltered feedback, then the low-pass, where the margins hold. The rest noise such a loop would have at
   standstill (the measured rest spectrum of y through |C| at its g_n) is predicted and
   reported, judged on the machine (2.): an axis whose command stands still while its partner
   moves is the contour direction and has its g_n (GTCF blends to C2 only when both stand).
2. *on the machine*: the *test contour* (:func:`contour_program`: ``motorctl circle-test``'s
   ISO 230-4 circle, R :data:`CONTOUR_RADIUS` at :data:`CONTOUR_FEED`, then a rectangle with
   R 3 mm corners at the same feed, its G0 moves at the axes' limits, dwells of 0.5 s: the
   standstill; on the rectangle's edges one axis stands still while the other moves, the
   contour direction its own), at 100, 75 and 50 % of the loop gain (both axes' k_s scaled, as
   C2's ladder), each run judged per axis by
   :func:`motorctl.commission.verify.admissible` against per-axis C2 with the autotuned gains
   on the same contour at the same rung (the law GTCF replaces, on the heavier load or weaker
   amplifier the rung stands for; C2's u at rest itself grows as X's loop softens): no fault,
   saturated samples ≤ 1.5 × max(C2's, 5e-5 of the samples) (at 100 %; at 75 and 50 %
   reported, not judged, as C2's confirmation), u RMS at rest ≤ 1.5 × C2's, no line in u at
   rest, no error spectrum 100 × C2's beyond what the sensitivities predict.
   The axes' own point-to-point programs (``motorctl run --controller gtcf``, both axes,
   ``full_periods`` periods: C2's confirmation runs, the 40 s constraints) are judged the same
   way against per-axis C2 on them, at each rung after the contour's: a contour gain that the
   contour takes can still saturate an axis that stands while its partner makes its 40 m/s²
   moves (``judge_programs`` False: run once with the chosen gains and reported, not judged).
3. *choice*: both axes start at their first admissible option; a run that fails names the axis
   whose figures failed, and that axis steps to its next option: the same g_n with the
   low-pass when the run failed on that axis's u at rest alone (what the low-pass is for),
   else the next lower g_n (a fault, saturation or a line: the filter's phase would not cure
   them); when it is at 1 already, the partner steps (the coupling is the partner's gain).
   The first pair that passes 2. is taken. Then, on it, each axis in turn its contour error's
   gain λ_n (:data:`LAMBDA_N`, highest first; the law's ``lambda_n``): where the margins hold
   with it over the span (:func:`span_lambda`) and its runs pass 2., it is kept; else the axis
   keeps λ_n 1. Reaching 1, 1: GTCF is C2, written so. At most ``max_runs`` machine runs.
"""

from __future__ import annotations

import copy
import math
import tempfile
from pathlib import Path

import numpy as np

from motorctl.commission.choose import _sensitivity2, margins_hold, rest_noise
from motorctl.commission.loopshape import c_frf, loop_margins
from motorctl.commission.rule import RULE, SCALES, Rule
from motorctl.commission.verify import admissible, apply_gains
from motorctl.config import LoadedConfig, config_from_dict

#: the contour-direction gains g_n searched per axis (multiples of its C2 k_s; 1: C2)
GAIN_N = (1.0, 1.25, 1.5, 1.75, 2.0, 2.5, 3.0, 4.0, 5.0, 6.0, 8.0)
#: the contour error's gain in the sliding variable tried per axis on its chosen g_n (multiples of
#: its C2 k1; 1: C2's p), highest first (motorctl.control.gtcf: p̃ = p + (λ_n − 1) k1 n sat(ε_n))
LAMBDA_N = (1.5, 1.25, 1.0)
#: the tangential gain written: C2's stiffness along the path (the per-axis autotune's)
GAIN_T = 1.0
#: the low-pass corner written on the feedback beyond C2's [Hz] (motorctl.control.gtcf): above the
#: contour's errors (a reversal's transient, 20-200 Hz), below the band of the encoder's
#: quantisation through the backward difference (most of an axis's u at rest, above 1 kHz)
LOWPASS_HZ = 500.0
#: points of the gain range [min(g_t, g_n), max(g_t, g_n)] whose margins must hold (log-spaced)
SPAN_POINTS = 5
#: the test contour: circle-test's circle [m], [m/s]
CONTOUR_RADIUS = 0.05
CONTOUR_FEED = 0.1
#: ... then a rectangle: its side lasts at least this long at the feed [s], its corners' radius [m]
SIDE_S = 0.6
CORNER_M = 0.003
#: machine runs of the search, at most (a candidate: up to 3 contour runs and 3 program runs, its ladder)
MAX_RUNS = 24


def pairs(loaded: LoadedConfig, axes) -> list[tuple[str, str]]:
    """The GTCF pairs among ``axes`` (both configure ``gtcf`` and name each other), each once,
    in the order of ``axes``."""
    out = []
    for a in axes:
        sec = loaded.axes[a].controller
        if not sec.configures("gtcf"):
            continue
        b = sec.settings("gtcf").partner
        if b in axes and b != a and loaded.axes[b].controller.configures("gtcf") \
                and loaded.axes[b].controller.settings("gtcf").partner == a \
                and (b, a) not in out:
            out.append((a, b))
    return out


def c2_gains(res: dict) -> dict:
    """Axis result ``res``'s C2 gains {k_s [V s/m], k1 [1/s], γ_d}: the autotuned ones, else its
    configured ones."""
    g = res["gains"].get("c2")
    if g is None:
        s = res["section"].settings("c2")
        g = {"k_s": float(s.k_s), "k1": float(s.k1), "gamma_d": float(s.gamma_d)}
    return {k: float(g[k]) for k in ("k_s", "k1", "gamma_d")}


def span(g_t: float, g_n: float) -> np.ndarray:
    """The loop-gain scales an axis's loop passes through as the path turns: :data:`SPAN_POINTS`
    log-spaced from min(g_t, g_n) to max(g_t, g_n) (one when equal)."""
    lo, hi = min(g_t, g_n), max(g_t, g_n)
    return np.array([lo]) if hi == lo else np.geomspace(lo, hi, SPAN_POINTS)


def gtcf_gains(g_c2: dict, g: float, lowpass_hz: float | None = None, lambda_n: float = 1.0) -> dict:
    """The gains of :meth:`motorctl.control.gtcf.GTCF.linearise` for one axis: its C2 gains
    ``g_c2`` at task-frame gain ``g`` and contour-error gain ``lambda_n`` through the low-pass of
    ``lowpass_hz`` [Hz]."""
    return dict(g_c2, g=float(g), lowpass_hz=lowpass_hz, lambda_n=float(lambda_n))


def span_lambda(g: float, g_t: float, g_n: float, lambda_n: float) -> float:
    """The contour-error gain λ' at the point of the span where the axis's own task-frame gain is
    ``g``: with s = n_i² the share of the contour direction that is the axis's own, its own
    term is k_s g (p + (λ_n − 1) s k1 e), g = g_t (1 − s) + g_n s (the task-frame feedback on
    p̃_i = p_i + (λ_n − 1) k1 n_i ε_n, ε_n's own part n_i e_i), so λ' = 1 + (λ_n − 1) s."""
    if lambda_n == 1.0 or g_n == g_t:
        return lambda_n
    return 1.0 + (lambda_n - 1.0) * (g - g_t) / (g_n - g_t)


def axis_margins(res: dict, g_c2: dict, g_t: float, g_n: float, lowpass_hz: float | None = None,
                 lambda_n: float = 1.0, rule: Rule = RULE) -> tuple[dict, bool]:
    """The margins of one axis's loop under GTCF on its measured FRF (``res``: the axis's autotune
    result, :func:`motorctl.commission.autotune.autotune`; g_c2: its C2 gains; g_n: its own
    contour gain; lowpass_hz: the law's low-pass [Hz], None: unfiltered; lambda_n: its
    contour-error gain, taken along the span by :func:`span_lambda`).

    Returns:
        ({"gm_db", "pm_deg", "ms_db": the worst over :func:`span` at 100 % [dB, deg, dB], "gm_at",
        "pm_at", "ms_at": the scale g where each is taken, "wc_hz": crossover at g_n [Hz],
        "rest_pred_V": predicted u RMS at standstill at g_n [V]}, whether the rule holds at
        every scale of the span, each at 100, 75 and 50 % of its loop gain).
    """
    ts, w, G_w, th = res["ts"], res["w"], res["G_w"], res["theta_hat0"]
    f = w / (2.0 * math.pi)
    out = {"gm_db": math.inf, "pm_deg": math.inf, "ms_db": -math.inf, "gm_at": g_n, "pm_at": g_n, "ms_at": g_n}
    ok = True
    for g in span(g_t, g_n):
        mg, holds = margins_hold("gtcf", gtcf_gains(g_c2, g, lowpass_hz, span_lambda(g, g_t, g_n, lambda_n)),
                                 ts, w, G_w, th, rule)
        ok &= holds
        if mg.gm_db < out["gm_db"]:
            out["gm_db"], out["gm_at"] = mg.gm_db, float(g)
        if mg.pm_deg < out["pm_deg"]:
            out["pm_deg"], out["pm_at"] = mg.pm_deg, float(g)
        if mg.ms_db > out["ms_db"]:
            out["ms_db"], out["ms_at"] = mg.ms_db, float(g)
    gn = gtcf_gains(g_c2, g_n, lowpass_hz, lambda_n)
    out["wc_hz"] = loop_margins(c_frf("gtcf", gn, ts, w, th) * G_w, f).wc_hz
    rp = res["measure"]["rest_psd"]
    out["rest_pred_V"] = rest_noise(c_frf("gtcf", gn, ts, np.maximum(2.0 * math.pi * rp[0], 1e-9), th), rp)
    return out, bool(ok)


def contour_metrics(log_path: str, loaded: LoadedConfig, axis: str) -> dict:
    """The commissioning's figures of one axis from a circle-test log, over its every enabled
    row (the hold, the G0 approach, the circles and the dwells):
    :func:`motorctl.commission.evaluate.run_metrics` with ``program_only`` False ("saturated",
    "sat_dispersion", "samples", "u_rest_rms_V", "osc_ratio", "osc_hz", "e_psd", "u_peak_V" [V],
    ...). Raises LogError, KeyError as run_metrics."""
    from motorctl.commission.evaluate import run_metrics
    return run_metrics(log_path, loaded, axis, program_only=False)


def with_gains(raw: dict, pair, g_c2: dict, g_t: float, opt: dict, scale: float = 1.0) -> dict:
    """A copy of the config dict with each axis's C2 gains ``g_c2[axis]`` (k_s × ``scale``), the
    pair's ``gain_t`` and each axis's option ``opt[axis]`` = (gain_n, lowpass_hz or None,
    lambda_n) in its ``gtcf`` block (partner and v_min as configured)."""
    new = copy.deepcopy(raw)
    for a in pair:
        new = apply_gains(new, a, "c2", dict(g_c2[a], k_s=g_c2[a]["k_s"] * scale))
        ctl = new["axes"][a]["controller"]
        ctl["gtcf"] = _block(ctl["gtcf"], g_t, opt[a])
    return new


def _block(blk: dict | None, g_t: float, opt_a: tuple) -> dict:
    """A copy of an axis's ``gtcf`` block (None: none yet) with the pair's ``gain_t`` and the
    axis's option ``opt_a`` = (gain_n, lowpass_hz or None, lambda_n); its other keys kept."""
    return dict(blk or {}, gain_t=float(g_t), gain_n=float(opt_a[0]), lowpass_hz=opt_a[1],
                lambda_n=float(opt_a[2]))


def _chosen(tp: dict) -> dict:
    """{axis: (gain_n, lowpass_hz, lambda_n)} of :func:`tune_pair`'s choice ``tp``."""
    g = tp["gains"]
    return {a: (g["gain_n"][a], g["lowpass_hz"][a], g["lambda_n"][a]) for a in tp["pair"]}


def contour_program(radius: float, feed: float, center) -> tuple[str, dict]:
    """The test contour's G-code and {"cw", "ccw": the line of its full circle} (the form of
    :func:`motorctl.motion.circle.circle_program`): circle-test's ISO 230-4 circle (CCW then CW,
    tangential lead-in and lead-out arcs, a dwell of 0.5 s after each), then a rectangle about
    the same centre, of side max(2 R, :data:`SIDE_S` × feed) with corners of radius
    :data:`CORNER_M` (cut-path corners), and a dwell of 0.5 s. On the rectangle's edges one axis
    stands still for more than 0.3 s (its "rest" by :func:`motorctl.metrics.rest_mask`) while
    the other moves at feed: the still axis is the contour direction, under g_n k_s; on the
    circle both axes always move. radius [m], feed [m/s], center (x, y) [m]."""
    from motorctl.motion.circle import circle_program
    text, where = circle_program(radius, feed, center)
    lines = text.rstrip("\n").split("\n")
    end = lines.index("M2")
    mm = 1e3
    cx, cy = center[0] * mm, center[1] * mm
    h = 0.5 * max(2.0 * radius, SIDE_S * feed) * mm
    r = CORNER_M * mm
    rect = [f"G0 X{cx - h + r:.4f} Y{cy - h:.4f}", f"F{feed * 60 * mm:.1f}",
            f"G1 X{cx + h - r:.4f} Y{cy - h:.4f}", f"G3 X{cx + h:.4f} Y{cy - h + r:.4f} I0 J{r:.4f}",
            f"G1 X{cx + h:.4f} Y{cy + h - r:.4f}", f"G3 X{cx + h - r:.4f} Y{cy + h:.4f} I{-r:.4f} J0",
            f"G1 X{cx - h + r:.4f} Y{cy + h:.4f}", f"G3 X{cx - h:.4f} Y{cy + h - r:.4f} I0 J{-r:.4f}",
            f"G1 X{cx - h:.4f} Y{cy - h + r:.4f}", f"G3 X{cx - h + r:.4f} Y{cy - h:.4f} I{r:.4f} J0",
            "G4 P0.5"]
    return "\n".join(lines[:end] + rect + lines[end:]) + "\n", where


def contour_run(raw: dict, source: str, pair, law: str | None, radius: float, feed: float) -> dict:
    """The test contour (:func:`contour_program`) run as ``motorctl circle-test`` runs its circle
    (:func:`motorctl.app.circle_test.run_circle_test`: the daemon's motion path, virtual clock)
    with ``law`` on the pair, and each axis's :func:`contour_metrics` ({axis: {..., "fault"}}; a
    fault: every axis's "fault" the supervisor's reason, the figures from the rows before it)."""
    import motorctl.app.circle_test as ct
    loaded = config_from_dict(copy.deepcopy(raw), source)
    with tempfile.TemporaryDirectory(prefix="motorctl-gtcf-") as tmp:
        path = str(Path(tmp) / "contour.mclog")
        fault = ""
        # circle-test's runner with its program swapped for the test contour (one run, this thread)
        orig = ct.circle_program
        ct.circle_program = contour_program
        try:
            ct.run_circle_test(loaded, radius, feed, law, axes=tuple(pair), log_path=path)
        except ValueError as exc:
            fault = str(exc)
        finally:
            ct.circle_program = orig
        out = {}
        for a in pair:
            try:
                out[a] = contour_metrics(path, loaded, a) | {"fault": fault}
            except Exception:                             # no log row written before the fault
                out[a] = {"fault": fault or "no run", "saturated": 0, "samples": 0, "u_rest_rms_V": math.nan,
                          "osc_ratio": math.nan, "osc_hz": math.nan, "u_peak_V": math.nan}
    return out


def program_run(raw: dict, source: str, pair, law: str | None, seconds: float, clock: str = "virtual") -> dict:
    """``motorctl run --controller LAW`` of both axes of the pair for ``seconds`` and each axis's
    :func:`motorctl.commission.evaluate.run_metrics` with the job's indexes ({axis: {...}})."""
    from motorctl.app.job import run_job
    from motorctl.commission.evaluate import JOB_KEYS, run_metrics
    loaded = config_from_dict(copy.deepcopy(raw), source)
    with tempfile.TemporaryDirectory(prefix="motorctl-gtcf-") as tmp:
        path = str(Path(tmp) / "run.mclog")
        res = run_job(loaded, axes=list(pair), controller=law, duration_s=seconds, clock=clock, log_path=path)
        out = {}
        for a in pair:
            r = {k: res.axes[a].get(k, math.nan) for k in JOB_KEYS}
            r["fault"] = r["fault"] or ""
            out[a] = r | run_metrics(path, loaded, a)
    return out


def tune_pair(loaded: LoadedConfig, raw: dict, res_a: dict, res_b: dict, clock: str = "virtual",
              progress=None, rule: Rule = RULE, full_periods: int = 10, radius: float = CONTOUR_RADIUS,
              feed: float = CONTOUR_FEED, max_runs: int = MAX_RUNS, judge_programs: bool = True) -> dict:
    """Choose each axis's GTCF ``gain_n`` and ``lowpass_hz`` for the pair of ``res_a``, ``res_b``
    (the two axes' :func:`motorctl.commission.autotune.autotune` results, measured FRF and chosen
    C2 gains) by the rule of the module docstring; ``gain_t`` :data:`GAIN_T`.

    Args:
        loaded, raw: the config (checked, and its dict). clock: the program runs' clock (the
            contour runs: virtual, as circle-test). full_periods: program periods of the
            program runs (0: none). judge_programs: the program runs are part of the rule
            (each candidate's ladder on them too, each rung after the contour's); False: run
            once with the chosen gains and reported with the verdict they would get, not judged. radius [m], feed [m/s]: the test
            contour. max_runs: machine runs at most.
    Returns:
        {"pair": (A, B), "gains": {"gain_t", "gain_n": {axis: g_n} (1 each when nothing above
        passes), "lowpass_hz": {axis: [Hz] or None}}, "c2": {axis: C2 gains used}, "margins":
        {axis: :func:`axis_margins` of the chosen}, "admissible": {axis: [(g_n, lowpass_hz) whose
        margins hold, in the order tried]}, "grid": GAIN_N, "reference": {"contour": {axis:
        figures}, "program": {...} or None}, "chosen": {"contour", "program": {axis: figures},
        "program_verdict"} (the chosen's runs at 100 %; empty for 1, 1), "runs": [({axis: (g_n,
        lowpass_hz)}, "contour" | "program", scale, {axis: figures}, verdict '' or why)], "rule",
        "contour": (radius, feed), "program_s"}.
    Raises:
        ValueError: the two results are not a GTCF pair of ``loaded``. OSError, ConfigError:
            as :func:`motorctl.app.job.run_job` (a run that cannot start).
    """
    pair = (res_a["axis"], res_b["axis"])
    if pair not in pairs(loaded, pair) and pair[::-1] not in pairs(loaded, pair):
        raise ValueError(f"axes {pair[0]} and {pair[1]} are not a gtcf pair (each gtcf.partner the other)")
    say = progress or (lambda s: None)
    by = {res_a["axis"]: res_a, res_b["axis"]: res_b}
    g_c2 = {a: c2_gains(by[a]) for a in pair}
    source = str(loaded.path)
    g_t = GAIN_T
    # each axis's admissible options (g_n, low-pass, λ_n 1), highest g_n first, unfiltered before
    # the low-pass, from its own measured response; (1, none, 1), C2 on its own term, closes the
    # list. λ_n is raised after (below), on the chosen g_n
    adm = {a: [(g, fc, 1.0) for g in sorted(GAIN_N, reverse=True) if g > 1.0 for fc in (None, LOWPASS_HZ)
               if axis_margins(by[a], g_c2[a], g_t, g, fc, 1.0, rule)[1]] + [(1.0, None, 1.0)] for a in pair}
    say(f"rule gtcf {pair[0]}-{pair[1]}: margins hold up to gain_n "
        + ", ".join(f"{a} {adm[a][0][0]:g}" for a in pair) + f" (gain_t {g_t:g})")
    seconds = full_periods * max(loaded.axes[a].trajectory.period_s for a in pair) if full_periods else 0.0
    # the reference of each rung: per-axis C2 with the pair's (autotuned) C2 gains on the same
    # run at the same scale (the law GTCF replaces, on the same heavier load or weaker amplifier
    # the rung stands for): like for like. One reference at 100 % for every rung asked GTCF at
    # 50 % to be quieter at rest than C2 itself is there (X's u at rest on the programs grows as
    # its loop softens: C2's 80 mV at 100 %, 126 mV at 50 %, over the 119 mV that bound allows)
    refs: dict = {}

    def ref(what: str, s: float = 1.0) -> dict:
        if (what, s) not in refs:
            cfg = with_gains(raw, pair, g_c2, 1.0, {a: (1.0, None, 1.0) for a in pair}, s)
            refs[what, s] = r = (contour_run(cfg, source, pair, "c2", radius, feed) if what == "contour" else
                                 program_run(cfg, source, pair, "c2", seconds, clock))
            say(f"verify gtcf: per-axis c2 (the pair's c2 gains) at {s:.0%} on {_where(what, seconds)}: "
                + "; ".join(f"{a} {r[a]['saturated']} saturated, u at rest {r[a]['u_rest_rms_V'] * 1e3:.0f} mV"
                            + (f", L2 {r[a]['L2_um']:.3f} um" if what == "program" else "") for a in pair))
        return refs[what, s]

    def trial(what: str, opt: dict, s: float) -> tuple[dict, str | None, str]:
        cfg = with_gains(raw, pair, g_c2, g_t, opt, s)
        r = (contour_run(cfg, source, pair, "gtcf", radius, feed) if what == "contour" else
             program_run(cfg, source, pair, "gtcf", seconds, clock))
        failed, why, noise = _judge(r, ref(what, s), by, g_c2, g_t, opt, s, loaded)
        runs.append((dict(opt), what, s, r, why))
        l2 = ", ".join(f"{a} {r[a]['L2_um']:.3f}" for a in pair) if what == "program" else ""
        say(f"verify gtcf gain_n {_opts(opt)} at {s:.0%} on {_where(what, seconds)}: {why or 'ok'}"
            + (f" (L2 {l2} um)" if l2 else ""))
        return r, (failed, noise), why

    runs, n_runs, chosen = [], 0, None
    steps = [(what, s) for s in sorted(SCALES, reverse=True)
             for what in (("contour", "program") if seconds and judge_programs else ("contour",))]

    def ladder(opt: dict) -> tuple[str, dict, tuple]:
        """The runs of one candidate, 100 % to 50 %, to the first that fails: (why or '', the
        runs at 100 %, the failed axis and whether on its rest noise alone)."""
        nonlocal n_runs
        why, got, failed = "", {}, (None, False)
        for what, s in steps:
            r, failed, why = trial(what, opt, s)
            n_runs += 1
            if s == 1.0:
                got[what] = r
            if why:
                break
        return why, got, failed

    at = {a: 0 for a in pair}
    while True:
        opt = {a: adm[a][at[a]] for a in pair}
        if all(o[0] == 1.0 for o in opt.values()):
            break
        if n_runs >= max_runs:
            say(f"verify gtcf: {max_runs} runs made; the search stops")
            break
        why, got, failed = ladder(opt)
        if not why:
            chosen = (opt, got)
            break
        # the axis the verdict names takes its next option; at 1 already, its partner (the
        # coupling). The low-pass is for the encoder's noise at rest: the same g_n low-passed
        # only after a run that failed on its rest noise alone; any other failure (a fault,
        # saturation, a line) goes to the next lower g_n
        a, noise = failed
        if opt[a][0] <= 1.0:
            a, noise = next(b for b in pair if opt[b][0] > 1.0), False
        at[a] += 1
        while not noise and adm[a][at[a]][0] == opt[a][0]:
            at[a] += 1
    # on the chosen g_n, each axis in turn (the pair's first first) its highest λ_n whose margins
    # hold and whose ladder passes; one that fails leaves the axis at λ_n 1
    for a in (pair if chosen is not None else ()):
        opt = chosen[0]
        for lam in (v for v in LAMBDA_N if v > 1.0):
            if opt[a][0] <= 1.0 or n_runs >= max_runs:
                break
            cand = dict(opt, **{a: (opt[a][0], opt[a][1], lam)})
            if not axis_margins(by[a], g_c2[a], g_t, *cand[a], rule)[1]:
                say(f"rule gtcf {a}: margins do not hold with lambda_n {lam:g} at gain_n {opt[a][0]:g}")
                continue
            why, got, _ = ladder(cand)
            if not why:
                chosen = (cand, got)
                break
    if chosen is None:
        chosen = ({a: (1.0, None, 1.0) for a in pair}, {})
    elif seconds and not judge_programs:
        # reported, not judged: the axes' own point-to-point programs with the chosen gains
        chosen[1]["program"], _, why = trial("program", chosen[0], 1.0)
        chosen[1]["program_verdict"] = why
    opt, got = chosen
    mg = {a: axis_margins(by[a], g_c2[a], g_t, *opt[a], rule)[0] for a in pair}
    return {"pair": pair, "gains": {"gain_t": g_t, "gain_n": {a: opt[a][0] for a in pair},
                                    "lowpass_hz": {a: opt[a][1] for a in pair},
                                    "lambda_n": {a: opt[a][2] for a in pair}}, "c2": g_c2,
            "margins": mg, "admissible": adm, "grid": GAIN_N,
            "reference": {what: refs.get((what, 1.0)) for what in ("contour", "program")}, "chosen": got,
            "runs": runs, "rule": rule, "contour": (radius, feed), "program_s": seconds}


def _opts(opt: dict) -> str:
    """'X 2 (lambda_n 1.5), Y 1.5 (low-pass 500 Hz)' of {axis: (g_n, lowpass_hz, lambda_n)}."""
    return ", ".join(f"{a} {g:g}" + "".join(f" ({x})" for x in ((f"lambda_n {lam:g}" if lam != 1.0 else ""),
                                                                  (f"low-pass {fc:g} Hz" if fc else "")) if x)
                     for a, (g, fc, lam) in opt.items())


def _where(what: str, seconds: float) -> str:
    return "the test contour" if what == "contour" else f"the programs ({seconds:g} s)"


def _judge(run: dict, ref: dict, by: dict, g_c2: dict, g_t: float, opt: dict, scale: float,
           loaded: LoadedConfig) -> tuple[str | None, str, bool]:
    """(None, '', False) when every axis's figures of ``run`` meet
    :func:`motorctl.commission.verify.admissible` against the reference run ``ref`` (per-axis C2
    with gains ``g_c2``, k_s × ``scale`` as the run's), else (the first axis that failed,
    'AXIS: why', whether it failed on its u at rest alone: it would pass with a quiet rest).
    The error-spectrum ratio is taken beyond the one the sensitivities predict at the extreme
    gains of the axis's span (|S|² of GTCF's linearisation at k_s × scale, g_t and its g_n
    with its low-pass and λ_n, ``opt[axis]`` = (g_n, lowpass_hz, lambda_n), against C2's at the
    same k_s)."""
    for a, r in run.items():
        res = by[a]

        def expect(f_hz, a=a, res=res):
            scaled = dict(g_c2[a], k_s=g_c2[a]["k_s"] * scale)
            base = _sensitivity2("c2", scaled, res["ts"], res["w"], res["G_w"], res["theta_hat0"], f_hz)
            return np.max([_sensitivity2("gtcf", gtcf_gains(scaled, g, opt[a][1], lam), res["ts"], res["w"],
                                         res["G_w"], res["theta_hat0"], f_hz)
                           for g, lam in ((g_t, 1.0), (opt[a][0], opt[a][2]))], axis=0) / base
        # at 75 and 50 % the saturation is reported, not judged, as C2's confirmation does (a
        # softer loop's larger error drives u into its limit more often)
        judged = r if scale >= 1.0 else {**r, "saturated": 0}
        u_lim = loaded.axes[a].controller.u_lim
        why = admissible(judged, u_lim, ref[a], expect=expect)
        if why:
            noise = not admissible({**judged, "u_rest_rms_V": 0.0}, u_lim, ref[a], expect=expect)
            return a, f"{a}: {why}", noise
    return None, "", False


def comment_lines(tp: dict) -> list[str]:
    """The autotuned config's comment lines of a pair's choice (:func:`tune_pair`)."""
    a, b = tp["pair"]
    g = tp["gains"]
    rule = tp["rule"]
    r_, f_ = tp["contour"]
    opt = _chosen(tp)
    lines = [f"#   gtcf {a}-{b}: gain_t {g['gain_t']:g}, gain_n {_opts(opt)}: "
             f"each axis's contour gain of {{{', '.join(f'{x:g}' for x in tp['grid'])}}} with lambda_n "
             f"{{{', '.join(f'{x:g}' for x in LAMBDA_N)}}}, unfiltered or low-passed,",
             f"#     whose margins hold on its measured response at k_s x every gain in [gain_t, gain_n] "
             f"({rule.text()} at 100/75/50 %), highest first, the axis a run failed on stepped down,",
             f"#     the first whose runs on the test contour (circle R {r_ * 1e3:g} mm, then a rectangle, at "
             f"{f_ * 1e3:g} mm/s)" + (f" and on the axes' programs ({tp['program_s']:g} s)"
                                      if tp["chosen"].get("program") is not None and "program_verdict" not in tp["chosen"]
                                      else "") + " pass at 100/75/50 % against per-axis c2",
             "#     with the gains above at the same % (no fault, saturation, rest noise, oscillation as above)"]
    for ax in tp["pair"]:
        m = tp["margins"][ax]
        gn = g["gain_n"][ax]
        fc = g["lowpass_hz"][ax]
        lam = g["lambda_n"][ax]
        lines.append(f"#     {ax} (c2 k_s {tp['c2'][ax]['k_s']:.4g} x [{min(g['gain_t'], gn):g}, "
                     f"{max(g['gain_t'], gn):g}]{f', lambda_n {lam:g}' if lam != 1.0 else ''}"
                     f"{f', low-pass {fc:g} Hz' if fc else ''}; margins hold up to "
                     f"{tp['admissible'][ax][0][0]:g}): GM "
                     f"{m['gm_db']:.1f} dB (at x{m['gm_at']:g}), PM "
                     f"{m['pm_deg']:.1f} deg (x{m['pm_at']:g}), |S|max {m['ms_db']:.1f} dB (x{m['ms_at']:g}), "
                     f"crossover {m['wc_hz']:.0f} Hz at gain_n, u at rest {m['rest_pred_V'] * 1e3:.0f} mV "
                     f"predicted at gain_n")
    ch, ref = tp["chosen"], tp["reference"]
    for what in ("contour", "program"):
        if ch.get(what) is None or ref.get(what) is None:
            continue
        label = ("test contour" if what == "contour" else
                 f"the axes' programs, {tp['program_s']:g} s" + ("" if "program_verdict" not in ch else
                 " (reported, not judged" + (f": {ch['program_verdict']}" if ch["program_verdict"] else ": would pass")
                 + ")"))
        lines.append(f"#     {label}, gtcf / c2: " + "; ".join(
            f"{ax} {ch[what][ax]['saturated']} / {ref[what][ax]['saturated']} saturated, u at rest "
            f"{ch[what][ax]['u_rest_rms_V'] * 1e3:.0f} / {ref[what][ax]['u_rest_rms_V'] * 1e3:.0f} mV"
            for ax in tp["pair"]))
    return lines


def apply_pair(raw: dict, tp: dict) -> dict:
    """A copy of the config dict with the pair's chosen ``gain_t``, each axis's ``gain_n``,
    ``lowpass_hz`` and ``lambda_n`` in both axes' ``gtcf`` blocks (partner and v_min kept)."""
    new = copy.deepcopy(raw)
    for a, opt_a in _chosen(tp).items():
        ctl = new["axes"][a]["controller"]
        ctl["gtcf"] = _block(ctl.get("gtcf"), tp["gains"]["gain_t"], opt_a)
    return new


def summary(tp: dict) -> dict:
    """JSON-ready figures of a pair's choice: gains, margins per axis, the runs' verdicts."""
    def fin(v):
        return v if isinstance(v, (int, str)) or (isinstance(v, float) and math.isfinite(v)) else None
    return {"pair": list(tp["pair"]), "gains": tp["gains"],
            "margins": {a: {k: fin(v) for k, v in m.items()} for a, m in tp["margins"].items()},
            "admissible": {a: [list(o) for o in v] for a, v in tp["admissible"].items()},
            "runs": [{"gain_n": {a: o[0] for a, o in n.items()}, "lowpass_hz": {a: o[1] for a, o in n.items()},
                      "lambda_n": {a: o[2] for a, o in n.items()},
                      "run": what, "scale": s, "verdict": why or "ok",
                      **{a: {k: fin(r[a][k]) for k in ("saturated", "u_rest_rms_V", "u_peak_V", "fault")
                             if k in r[a]} for a in tp["pair"]}}
                     for n, what, s, r, why in tp["runs"]]}


__all__ = ["GAIN_N", "GAIN_T", "LAMBDA_N", "LOWPASS_HZ", "apply_pair", "axis_margins", "comment_lines", "contour_metrics",
           "gtcf_gains", "pairs", "summary", "tune_pair"]
