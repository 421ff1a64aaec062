"""``motorctl autotune``: measured frequency response → fitted model → gains by one rule →
verified on the machine → ``DIR/autotuned.yaml`` and ``DIR/bode_<A>.png`` (a GTCF pair's
gain_t, gain_n too when both its axes are tuned with C2)
(:mod:`motorctl.commission.autotune` has the procedure and the rule).

    motorctl autotune CONFIG --axis A [--axis B] [--out DIR] [--virtual-clock] [--verify-seconds S]
                     [--periods N] [--gm-min-db G] [--pm-min-deg P] [--ms-max-db M]
                     [--law L ...] [--search-runs N] [--measure-only] [--json]

Exit codes: 0 gains written; 1 the measurement stopped (fault, guard: nothing written) or an
axis had no gains pass the verification (the config is written with that axis as configured);
2 bad input (one line on stderr, nothing started).
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

from motorctl.inputs import seconds_arg as seconds

#: the shortest verification run [s] (2500 cycles at 5 kHz: the indexes need a stretch of tracking)
VERIFY_MIN_S = 0.5


def register(parser, subparsers) -> None:
    """Add the ``autotune`` subcommand (called by :func:`motorctl.cli.build_parser`)."""
    p = subparsers.add_parser("autotune", help="measure the axis's frequency response, fit a model, "
                                               "choose and verify every controller's gains")
    p.add_argument("config", help="config of the axis (any driver)")
    p.add_argument("--axis", action="append", required=True, help="axis to tune (repeatable)")
    p.add_argument("--out", default=None, metavar="DIR",
                   help="autotuned.yaml and the Bode plots (default: runs/autotune-<config name>)")
    p.add_argument("--virtual-clock", action="store_true",
                   help="run as fast as possible (default: the config's clock)")
    p.add_argument("--verify-seconds", type=seconds, default=None,
                   help=f"length of each screening run in s, at least {VERIFY_MIN_S:g} "
                        f"(default: two program periods)")
    p.add_argument("--full-periods", type=int, default=None,
                   help="program periods of each confirmation run, 1..100 (default 10: the gains "
                        "written passed runs of this length at 100, 75 and 50 %% of their loop gain)")
    p.add_argument("--periods", type=int, default=None,
                   help="measured multisine periods of 1 s, even, 2..200 (default 32)")
    p.add_argument("--gm-min-db", type=float, default=None, help="the rule's gain margin floor [dB] (default 6)")
    p.add_argument("--pm-min-deg", type=float, default=None, help="the rule's phase margin floor [deg] (default 10)")
    p.add_argument("--ms-max-db", type=float, default=None,
                   help="the rule's peak sensitivity ceiling [dB] (default 16)")
    p.add_argument("--search-runs", type=int, default=None,
                   help="verification runs of the search per law, at most (default 14; the "
                        "refinement's: the lesser of this and 6)")
    p.add_argument("--law", action="append", default=None,
                   help="tune only this law (repeatable; default: every law the axis configures)")
    p.add_argument("--measure-only", action="store_true",
                   help="measure the frequency response and fit the model only: the Bode plot, no gains")
    p.add_argument("--json", action="store_true", help="one JSON object on stdout and nothing else")
    p.set_defaults(func=cmd_autotune)


def _summary(res: dict) -> dict:
    from motorctl.commission.autotune import final_margins
    meas, mdl = res["measure"], res["model"]
    mg = final_margins(res)
    return {
        "model": mdl, "theta_hat0": res["theta_hat0"],
        "measurement": {k: meas[k] for k in ("excitation_rms_V", "excitation_peak_V", "e_max_m",
                                             "guard_m", "stroke_m", "soft_limits_m", "pass")}
        | {"friction": meas.get("friction")},
        "gains": {law: {k: v for k, v in g.items() if not k.startswith("_")}
                  for law, g in res["gains"].items()},
        "design": {law: {k[1:]: v for k, v in g.items() if k.startswith("_")}
                   for law, g in res["gains"].items()},
        "chosen_by": {law: {"from": v["from"], "scale": v["scale"], "L2_um": v["L2_um"]}
                      for law, v in res["verify"].items()},
        "margins": {law: {k: (None if not math.isfinite(v) else v) for k, v in vars(m).items()}
                    for law, m in mg.items()},
        "verify": [{"law": law, "run": label, "scale": s, "verdict": why or "ok",
                    **{k: res_[k] for k in ("e_M_um", "e_F_um", "L2_um", "u_peak_V", "u_rest_rms_V",
                                            "saturated", "fault")}}
                   for law, v in res["verify"].items() for label, s, res_, why in v["runs"]],
    }


def cmd_autotune(args) -> int:
    from motorctl.commission.autotune import autotune, plot_bode, theta1_meaning, write_config
    from motorctl.commission.rule import FULL_PERIODS, PERIODS, RULE, SEARCH_BUDGET, AutotuneError, Rule
    from motorctl.cli import UsageError
    from motorctl.config import config_from_dict, load_yaml
    from motorctl.inputs import writable_dir
    if args.verify_seconds is not None and args.verify_seconds < VERIFY_MIN_S:
        raise UsageError(f"--verify-seconds {args.verify_seconds:g}: allowed {VERIFY_MIN_S:g}..1e+06 s "
                         f"(a verification run tracks the program at least this long)")
    periods = PERIODS if args.periods is None else args.periods
    if not (2 <= periods <= 200 and periods % 2 == 0):
        raise UsageError(f"--periods {args.periods}: must be an even number within 2..200")
    given = {k: getattr(args, k) for k in ("gm_min_db", "pm_min_deg", "ms_max_db")}
    for k, lo, hi in (("gm_min_db", 0.0, 30.0), ("pm_min_deg", 0.0, 90.0), ("ms_max_db", 0.0, 30.0)):
        v = given[k]
        if v is not None and not lo <= v <= hi:
            raise UsageError(f"--{k.replace('_', '-')} {v:g}: allowed {lo:g}..{hi:g}")
    rule = Rule(**{k: (getattr(RULE, k) if v is None else v) for k, v in given.items()})
    search_runs = SEARCH_BUDGET if args.search_runs is None else args.search_runs
    if not 0 <= search_runs <= 200:
        raise UsageError(f"--search-runs {args.search_runs}: allowed 0..200")
    full_periods = FULL_PERIODS if args.full_periods is None else args.full_periods
    if not 1 <= full_periods <= 100:
        raise UsageError(f"--full-periods {args.full_periods}: allowed 1..100")
    raw = load_yaml(args.config)
    loaded = config_from_dict(raw, args.config)
    from motorctl.commission.choose import tunable_laws
    for a in args.axis:
        if a not in loaded.axes:
            raise UsageError(f"--axis {a}: no such axis in {args.config}; axes: {', '.join(loaded.axes)}")
        for law in args.law or ():
            if law not in tunable_laws(loaded.axes[a].controller):
                raise UsageError(f"--law {law}: not a law axis {a} configures with a linearisation; "
                                 f"allowed: {', '.join(tunable_laws(loaded.axes[a].controller))}")
    out = Path(args.out) if args.out else Path("runs") / f"autotune-{Path(args.config).stem}"
    writable_dir(str(out), "out")
    clock = "virtual" if args.virtual_clock else loaded.cfg.loop.clock
    say = (lambda s: None) if args.json else (lambda s: print(s, flush=True))
    results, summary, failed = [], {}, False
    for a in args.axis:
        try:
            res = autotune(loaded, raw, a, clock, args.verify_seconds, progress=say, periods=periods,
                           rule=rule, laws=args.law, measure_only=args.measure_only,
                           search_runs=search_runs, full_periods=full_periods)
        except AutotuneError as exc:
            sys.stderr.write(f"motorctl: autotune: {exc}\n")
            return 1
        results.append(res)
        summary[a] = _summary(res)
        try:
            summary[a]["bode"] = plot_bode(res, out / f"bode_{a}.png")
        except ImportError:
            summary[a]["bode"] = None
        if not res["gains"] and not args.measure_only:
            sys.stderr.write(f"motorctl: autotune: axis {a}: no gains passed the verification "
                             f"(kept as configured)\n")
            failed = True
    path = out / "autotuned.yaml"
    pairs = []
    if not args.measure_only:
        from motorctl.commission.autotune import autotune_pairs
        pairs = autotune_pairs(loaded, raw, results, clock, say, rule, full_periods)
        write_config(raw, results, args.config, path, pairs)
    if args.json:
        from motorctl.commission.gtcf_tune import summary as gtcf_summary
        print(json.dumps({"config": None if args.measure_only else str(path), "axes": summary,
                          "gtcf": [gtcf_summary(tp) for tp in pairs]}, default=float))
    else:
        for a, s in summary.items():
            m = s["model"]
            what, rng = theta1_meaning(m)
            print(f"{a}: fitted theta1 = {what} {m['theta1']:.4g} V s^2/m " + (f"({rng}) " if rng else "")
                  + f"(theta_hat1(0) {s['theta_hat0'][0]:.4g}), "
                  f"mode {m['mode_hz']:.1f} Hz, current loop {m['current_loop_hz']:.0f} Hz, delay "
                  f"{m['delay_s'] * 1e6:.1f} us")
            for law, mg in s["margins"].items():
                print(f"  {law}: GM {mg['gm_db'] or math.inf:.1f} dB, PM {mg['pm_deg']:.1f} deg, |S| {mg['ms_db']:.1f} dB, "
                      f"crossover {mg['wc_hz']:.0f} Hz")
        for tp in pairs:
            g = tp["gains"]
            print(f"gtcf {'-'.join(tp['pair'])}: gain_t {g['gain_t']:g}; " + "; ".join(
                f"{a} gain_n {g['gain_n'][a]:g} (contour direction its own: k_s x {g['gain_n'][a]:g}"
                + (f", contour error x {g['lambda_n'][a]:g} in p" if g["lambda_n"][a] != 1.0 else "")
                + (f", low-pass {g['lowpass_hz'][a]:g} Hz" if g["lowpass_hz"][a] else "") + f"): GM "
                f"{m['gm_db']:.1f} dB, PM {m['pm_deg']:.1f} deg, |S| {m['ms_db']:.1f} dB"
                for a, m in tp["margins"].items()) + " (the worst over [gain_t, gain_n])")
        written = ([] if args.measure_only else [str(path)]) + [s["bode"] for s in summary.values() if s.get("bode")]
        print("wrote " + ", ".join(written))
    return 1 if failed else 0
