"""``motorctl tune``: run → identify → tuned config → run again → compare, on the config's driver.

    motorctl tune CONFIG --axis A [--duration S] [--out DIR] [--virtual-clock] [--json]
                  [--no-speed-experiment] [--no-pass-experiment]

1. **before**: the axis's program on CONFIG (:func:`motorctl.app.job.run_job`, the config's
   clock), log ``DIR/before.mclog``;
2. **identify** that log for axis A (:func:`motorctl.ident.pipeline.identify_record`); when no
   effect is found, or none the controller can compensate, it says so and stops here (exit 0,
   nothing written but the log);
3. **tuned config**: ``DIR/tuned.yaml``, what ``motorctl identify LOG --config CONFIG
   --write-config`` writes (:func:`motorctl.ident.pipeline.write_tuned_config`);
4. **after**: the same program on the tuned config, log ``DIR/after.mclog``. When it faults
   (following error, or the cycle's I²t or oscillation-at-rest protection) tune stops and the
   config is not handed over: ``tuned.yaml`` is moved to ``DIR/tuned-rejected.yaml``. tune never hands
   over a worse config: the changes of ``tuned.yaml`` (the fitted θ̂(0) with its box, each
   compensated effect) go by backward elimination: each change still kept is undone in turn
   (``DIR/without_<changes>.yaml`` / ``.mclog``), the undo that leaves the loop best among
   those it is better with (:func:`motorctl.commission.tune.better`: a lower L2[e], an e_M no more
   than one encoder count above the before run's, and u's noise at rest no more than
   :data:`~motorctl.commission.tune.U_REST_SLACK` above it) is taken, and again until no undo helps;
   then what is kept must
   beat the before run the same way, else no effect is kept and ``tuned.yaml`` is CONFIG
   unchanged (the report says which were dropped and why);
5. on the simulated driver, **floor**: CONFIG with the plant's effects switched off
   (:func:`motorctl.commission.tune.effect_free`, same seed), ``DIR/floor.yaml`` and ``DIR/floor.mclog``;
6. **compare** (:func:`motorctl.commission.compare.compare_logs`, what ``motorctl compare-runs`` computes):
   e_M, e_F, L2[e] [µm] and u_peak [V] before, after, their ratio and the floor over the same
   program periods (with L2[e] in motion / at standstill and u's noise at rest), the damage
   removed (L2_before − L2_after)/(L2_before − L2_floor) and whether e_M got worse;
   ``DIR/compare_runs_<A>.png`` when matplotlib is installed.

7. on the simulated driver, when the before log's identification reports a time-periodic line
   at a harmonic of the program's period ambiguous with a force of position
   (:mod:`motorctl.ident.ambiguity`: named neither, compensated neither), **other speed**: the
   same program at 0.7 x the speed (:func:`motorctl.commission.tune.speed_experiment`),
   ``DIR/other_speed_<k>.mclog``, identified: a line that keeps its frequency in Hz is named the
   time-periodic disturbance, one whose frequency scales with the speed the force of position
   (``speed_experiments`` in the JSON; skipped with ``--no-speed-experiment``). Nothing of it
   goes into ``tuned.yaml``: it names, it does not compensate.
8. on the simulated driver, when the before log's identification reports a spring ambiguous
   with another family (a hold at rest: stiction, a dead-zone, a coarse or noisy encoder's flat
   reading), **slow passes**: the axis back and forth over 80 % of its stroke at a slow constant
   speed (:func:`motorctl.commission.tune.pass_experiment`), ``DIR/slow_passes_<k>.mclog``; the
   input's slope over the position names the spring when it is the fitted stiffness, the other
   family when it is not there (``pass_experiments`` in the JSON; skipped with
   ``--no-pass-experiment``). It names, it does not compensate.

The runs are :func:`motorctl.commission.tune.tune`'s; this module parses the arguments and prints.

Exit codes: 0 done (with or without an effect found), 1 a run faulted, 2 bad input (one line on
stderr, nothing started).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from motorctl.inputs import seconds_arg as seconds


def register(parser, subparsers) -> None:
    """Add the ``tune`` subcommand (called by :func:`motorctl.cli.build_parser`)."""
    p = subparsers.add_parser("tune", help="run, identify the log, write the tuned config, run it, "
                                           "compare before/after (and the effect-free floor on sim)")
    p.add_argument("config", help="config to tune (any driver)")
    p.add_argument("--axis", required=True, help="the axis to run, identify and tune")
    p.add_argument("--duration", type=seconds, default=None,
                   help="length of each run in s (default: loop.duration_s); at least one program period")
    p.add_argument("--out", default=None, metavar="DIR",
                   help="logs, tuned.yaml and the figure (default: runs/tune-<config name>-<axis>)")
    p.add_argument("--virtual-clock", action="store_true",
                   help="run as fast as possible (as `run --virtual-clock`; default: the config's clock)")
    p.add_argument("--json", action="store_true", help="one JSON object on stdout and nothing else")
    p.add_argument("--no-speed-experiment", action="store_true",
                   help="on a simulated plant, do not run the program again at another speed to tell a "
                        "time-periodic line at a program harmonic from a force of position")
    p.add_argument("--no-pass-experiment", action="store_true",
                   help="on a simulated plant, do not run slow constant-velocity passes to tell a spring "
                        "from a hold at rest")
    p.set_defaults(func=cmd_tune)


def default_out(config: str, axis: str) -> Path:
    """The default output directory: runs/tune-<config file stem>-<axis>."""
    return Path("runs") / f"tune-{Path(config).stem}-{axis}"


def text_report(res: dict) -> str:
    """The text output of ``motorctl tune`` (its result :func:`tune`): what was found, then one
    table (compare-runs') with the floor on sim, the damage removed and whether e_M got worse."""
    from motorctl.ident.pipeline import fig as _fig, saturation_note
    from motorctl.cli.runs import text_report as table
    note = saturation_note(res.get("input_saturation"))
    lines = [note] if note else []
    for e in res["effects"]:
        pars = ", ".join(f"{k} {_fig(v)}" for k, v in e["parameters"].items())
        tag = ("not compensable" if e["name"] not in res["compensation"] else
               f"dropped: {res['dropped'][e['name']]}" if e["name"] in res["dropped"] else "compensated")
        lines.append(f"effect found: {e['name']}: {pars}; {tag}")
    if "tuned" in res["files"]:
        lines.append(f"tuned config: {res['files']['tuned']}")
    if res.get("theta_hat0") and res["kept"]:
        lines.append(f"theta_hat0: {res['theta_hat0']}")
    if res["stopped"]:
        lines.append(f"stopped: {res['stopped']}")
    if res["verdict"]:
        lines.append(res["verdict"])
    r = res["compare"]
    if r:
        f = res["files"]
        lines.append(table({"before": f["before"], "after": f["after"], "axes": {res["axis"]: r}},
                           extra_rows=("floor",)).rstrip("\n"))
        if res["floor_effects_off"] is not None:
            off = ", ".join(res["floor_effects_off"]) or "none was on"
            d = res["damage_removed"]
            lines.append(f"floor: {f['floor_config']} (the same plant and seed, effects off: {off})")
            lines.append("damage removed (L2_before - L2_after)/(L2_before - L2_floor): "
                         + (f"{d:.3f}" if d is not None else "- (L2 before is not above the floor)"))
        lines.append(f"e_M not worse: {'yes' if res['e_M_not_worse'] else 'no'}; L2[e] not worse: "
                     f"{'yes' if r['after']['L2_um'] <= r['before']['L2_um'] else 'no'}")
        lines.extend(f"figure: {p}" for p in res["figures"])
    for key, run in (("speed_experiments", lambda e: f"the program at {e['scale']:g} x the speed"),
                     ("pass_experiments", lambda e: "slow passes")):
        for e in res.get(key) or []:
            lines.append(f"{e['ambiguous']}: {run(e)} ({e['log']}): "
                         + (f"named {e['named']}: " if e.get("named") else "") + e["why"])
    return "\n".join(lines) + "\n"


def cmd_tune(args) -> int:
    out = args.out or default_out(args.config, args.axis)

    def progress(line: str) -> None:
        sys.stdout.write(line + "\n")
        sys.stdout.flush()

    from motorctl.commission.tune import pass_experiments, speed_experiments, tune
    res = tune(args.config, args.axis, out, args.duration, "virtual" if args.virtual_clock else None,
               None if args.json else progress)
    res["speed_experiments"] = ([] if args.no_speed_experiment else
                                speed_experiments(res, None if args.json else progress))
    res["pass_experiments"] = ([] if args.no_pass_experiment else
                               pass_experiments(res, None if args.json else progress))
    if args.json:
        from motorctl.ident.pipeline import json_default
        sys.stdout.write(json.dumps(res, default=json_default) + "\n")
    else:
        sys.stdout.write(text_report(res))
    return 1 if any(res["faults"].values()) else 0


__all__ = ["cmd_tune", "default_out", "register", "text_report"]
