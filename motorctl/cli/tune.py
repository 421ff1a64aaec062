"""``motorctl tune``: run → identify → tuned config → run again → compare, on the config's driver.

    motorctl tune CONFIG --axis A [--duration S] [--out DIR] [--virtual-clock] [--json]

1. **before**: the axis's program on CONFIG (:func:`motorctl.app.job.run_job`, the config's
   clock), log ``DIR/before.mclog``;
2. **identify** that log for axis A (:func:`motorctl.ident.pipeline.identify_record`); when no
   effect is found, or none the controller can compensate, it says so and stops here (exit 0,
   nothing written but the log);
3. **tuned config**: ``DIR/tuned.yaml``, what ``motorctl identify LOG --config CONFIG
   --write-config`` writes (:func:`motorctl.ident.pipeline.write_tuned_config`);
4. **after**: the same program on the tuned config, log ``DIR/after.mclog``. tune never hands
   over a worse config: where more than one effect is compensated, each is run once without
   (``DIR/without_<family>.yaml`` / ``.mclog``) and dropped when the loop is better without it
   (:func:`better`: a lower L2[e] and an e_M no worse than one encoder count); then the kept
   set must beat the before run the same way, else no effect is kept and ``tuned.yaml`` is
   CONFIG unchanged (the report says which were dropped and why);
5. on the simulated driver, **floor**: CONFIG with the plant's effects switched off
   (:func:`motorctl.app.tune.effect_free`, same seed), ``DIR/floor.yaml`` and ``DIR/floor.mclog``;
6. **compare** (:func:`motorctl.cli.runs.compare_logs`, what ``motorctl compare-runs`` computes):
   e_M, e_F, L2[e] [µm] and u_peak [V] before, after, their ratio and the floor over the same
   program periods, the damage removed (L2_before − L2_after)/(L2_before − L2_floor) and
   whether e_M got worse; ``DIR/compare_runs_<A>.png`` when matplotlib is installed.

Exit codes: 0 done (with or without an effect found), 1 a run faulted, 2 bad input (one line on
stderr, nothing started).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from motorctl.inputs import InputError
from motorctl.inputs import seconds_arg as seconds

#: e_M may grow by this much and still count as not worse [µm]: one count of the 0.5 µm encoder
E_M_SLACK_UM = 0.5

#: file names written in the output directory
FILES = {"before": "before.mclog", "tuned": "tuned.yaml", "after": "after.mclog",
         "floor_config": "floor.yaml", "floor": "floor.mclog"}


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
    p.set_defaults(func=cmd_tune)


def better(a: dict, b: dict) -> bool:
    """Run ``a`` tracks better than run ``b`` (their indexes over the same program periods,
    :func:`motorctl.metrics.tracking_indexes` [µm]): a lower L2[e], and an e_M no more than
    :data:`E_M_SLACK_UM` above."""
    return a["L2_um"] < b["L2_um"] and a["e_M_um"] <= b["e_M_um"] + E_M_SLACK_UM


def default_out(config: str, axis: str) -> Path:
    """The default output directory: runs/tune-<config file stem>-<axis>."""
    return Path("runs") / f"tune-{Path(config).stem}-{axis}"


def tune(config: str, axis: str, out_dir: str | Path, duration_s: float | None = None,
         clock: str | None = None, progress=None) -> dict:
    """The whole tune of one axis (module docstring, steps 1-6).

    Args:
        config: path of the config to tune. axis: its axis name. out_dir: where the logs,
            ``tuned.yaml``, ``floor.yaml`` and the figure go (created).
        duration_s: length of each run [s] (None: loop.duration_s); at least one program period.
        clock: 'wall' | 'virtual' (None: the config's ``loop.clock``).
        progress: called with one line of text before each step (None: silent).
    Returns:
        {"config", "axis", "driver", "clock", "duration_s", "out", "files": {step: path written},
        "faults": {run: reason or ""}, "effects" (identify's summary), "compensation",
        "not_compensable", "kept" (the compensated families kept in tuned.yaml), "dropped"
        ({family: why}), "verdict" (None, or that no effect was kept), "stopped" (None, or why it
        stopped early), "compare": None or
        {window_s, period_s, settle_periods, before, after, ratio, floor (sim only)} with the
        indexes of :func:`motorctl.metrics.tracking_indexes` [µm, V], "floor_effects_off"
        (sim: the families the floor switches off; else None), "damage_removed" [-] (sim),
        "e_M_not_worse", "figures"}.
    Raises:
        ConfigError: CONFIG is not a valid config. InputError: no such axis, a duration shorter
        than one program period, an output that cannot be written, a sim plant whose effects
        cannot be switched off (all before anything runs). LogError: the before log cannot be
        identified. RealtimeError: ``realtime: required`` refused. OSError: a driver cannot
        reach its device.
    """
    from motorctl.app.tune import effect_free, effects_on, is_simulated
    from motorctl.ident.pipeline import compensation_from_fit, write_tuned_config
    from motorctl.config import load_config, load_yaml
    from motorctl.inputs import writable_dir, writable_file

    note = progress or (lambda _line: None)
    loaded = load_config(config)
    if axis not in loaded.axes:
        raise InputError(f"{config}: no axis {axis!r}; axes: {', '.join(loaded.axes)}")
    duration = float(duration_s if duration_s is not None else loaded.cfg.loop.duration_s)
    period = loaded.axes[axis].trajectory.period_s
    if period > 0 and duration < period:
        raise InputError(f"duration {duration:g} s: shorter than one program period of axis {axis} "
                         f"({period:g} s); before and after are compared over whole periods")
    clock = clock or loaded.cfg.loop.clock
    base = load_yaml(config)
    floor_cfg = None
    if is_simulated(loaded):
        try:
            floor_cfg = effect_free(base, str(config))
        except ValueError as exc:
            raise InputError(str(exc)) from None
    out = writable_dir(out_dir, "tune output")
    files = {k: out / v for k, v in FILES.items() if floor_cfg is not None or not k.startswith("floor")}
    for k, f in files.items():
        writable_file(f, f"tune {k} output")
    res = {"config": str(config), "axis": axis, "driver": loaded.cfg.driver.type, "clock": clock,
           "duration_s": duration, "out": str(out), "files": {}, "faults": {}, "effects": [],
           "compensation": {}, "not_compensable": [], "kept": [], "dropped": {}, "verdict": None,
           "stopped": None, "compare": None,
           "floor_effects_off": effects_on(loaded, axis) if floor_cfg is not None else None,
           "damage_removed": None, "e_M_not_worse": None, "figures": []}

    def run(step: str, cfg) -> bool:
        note(f"{step}: axis {axis} of {cfg.path}, {duration:g} s, {clock} clock -> {files[step]}")
        fault = _run_axis(cfg, axis, duration, clock, files[step])["fault"]
        res["files"][step] = str(files[step])
        res["faults"][step] = fault
        if fault:
            res["stopped"] = f"the {step} run faulted: {fault}"
        return not fault

    if not run("before", loaded):
        return res
    note(f"identify: {files['before']}, axis {axis}")
    idf, s = _identify(files["before"], axis)
    comp, _theta, skipped = compensation_from_fit(idf)
    res.update(effects=s["effects"], compensation=comp, not_compensable=skipped)
    if not s["effects"]:
        res["stopped"] = "no effect found (no candidate passed held-out gain, BIC and plausibility)"
        return res
    if not comp:
        res["stopped"] = f"no compensable effect found ({', '.join(skipped)}: no compensation term)"
        return res
    tuned = write_tuned_config(idf, s, base, axis, str(config), files["tuned"])
    res["files"]["tuned"] = str(files["tuned"])
    if not run("after", load_config(files["tuned"])):
        return res
    if not _keep_what_helps(res, files, tuned, base, axis, duration, clock, note):
        return res
    if floor_cfg is not None:
        res["files"]["floor_config"] = str(_write_floor(floor_cfg, config, files["floor_config"]))
        if not run("floor", load_config(files["floor_config"])):
            return res
    _compare(res, files)
    return res


def _indexes(files: dict, log: Path, axis: str) -> dict:
    """The indexes of run ``log`` over the program periods it shares with the before run."""
    from motorctl.cli.runs import compare_logs
    try:
        return compare_logs(str(files["before"]), str(log), [axis])["axes"][axis]["after"]
    except ValueError as exc:      # no common program period (a run cut short)
        raise InputError(str(exc)) from None


def _keep_what_helps(res: dict, files: dict, tuned: dict, base: dict, axis: str, duration: float,
                     clock: str, note) -> bool:
    """Keep in ``tuned.yaml`` only the compensated effects the closed loop is better with
    (module docstring, step 4); rewrite ``tuned.yaml`` and ``after.mclog`` when some go.
    Returns False when a run faulted (``res['stopped']`` says which)."""
    import copy
    import shutil

    import yaml

    from motorctl.config import config_from_dict
    comp = dict(tuned["axes"][axis]["controller"].get("compensation") or {})
    kept = list(comp)
    best, best_cfg, best_log = _indexes(files, files["after"], axis), tuned, files["after"]
    out = files["tuned"].parent
    for fam in list(kept) if len(kept) > 1 else []:
        trial = copy.deepcopy(best_cfg)
        ctl = trial["axes"][axis]["controller"]
        ctl["compensation"] = {k: v for k, v in ctl["compensation"].items() if k != fam}
        path, log = out / f"without_{fam}.yaml", out / f"without_{fam}.mclog"
        path.write_text(yaml.safe_dump(trial, sort_keys=False, default_flow_style=False, allow_unicode=True),
                        encoding="utf-8")
        note(f"without {fam}: axis {axis} of {path}, {duration:g} s, {clock} clock -> {log}")
        fault = _run_axis(config_from_dict(trial, str(path)), axis, duration, clock, log)["fault"]
        res["files"][f"without_{fam}"] = str(log)
        if fault:
            res["faults"][f"without_{fam}"] = fault
            res["stopped"] = f"the run without {fam} faulted: {fault}"
            return False
        m = _indexes(files, log, axis)
        if better(m, best):
            kept.remove(fam)
            res["dropped"][fam] = (f"the loop is better without it (L2[e] {best['L2_um']:.3f} -> {m['L2_um']:.3f} um, "
                                   f"e_M {best['e_M_um']:.2f} -> {m['e_M_um']:.2f} um)")
            best, best_cfg, best_log = m, trial, log
    before = _indexes(files, files["before"], axis)
    if not better(best, before):
        for fam in kept:
            res["dropped"][fam] = (f"with it the loop is not better than before (L2[e] {before['L2_um']:.3f} -> "
                                   f"{best['L2_um']:.3f} um, e_M {before['e_M_um']:.2f} -> {best['e_M_um']:.2f} um)")
        kept, best_cfg, best_log = [], base, files["before"]
        res["verdict"] = "no effect kept: the closed loop was not better with the compensation; tuned.yaml is CONFIG unchanged"
    res["kept"] = kept
    if best_log != files["after"]:
        head = (f"# motorctl tune: {res['config']} with the compensation of {', '.join(kept)}\n" if kept else
                f"# motorctl tune: {res['config']} unchanged (no compensation made the closed loop better)\n")
        files["tuned"].write_text(head + yaml.safe_dump(best_cfg, sort_keys=False, default_flow_style=False,
                                                        allow_unicode=True), encoding="utf-8")
        shutil.copyfile(best_log, files["after"])
    return True


def _run_axis(loaded, axis: str, duration_s: float, clock: str, log_path: Path) -> dict:
    """One run of ``axis`` with its log; returns run_job's entry of the axis."""
    from motorctl.app.job import run_job
    return run_job(loaded, axes=[axis], duration_s=duration_s, clock=clock, log_path=str(log_path)).axes[axis]


def _identify(log_path: Path, axis: str):
    """identify's fit of a run log with its default options; returns (Identifier, summary)."""
    from motorctl.ident.pipeline import identify_record
    from motorctl.ident.data import load_record
    return identify_record(load_record(str(log_path), None, None, axis))


def _write_floor(floor_cfg: dict, config: str, path: Path) -> Path:
    """Write the effect-free config (:func:`motorctl.app.tune.effect_free`) with a comment."""
    import yaml
    head = (f"# the effect-free floor of `motorctl tune`: {config} with every simulated effect switched "
            f"off (motorctl.app.tune.effect_free); the same plant otherwise, the same seed\n")
    path.write_text(head + yaml.safe_dump(floor_cfg, sort_keys=False, default_flow_style=False,
                                          allow_unicode=True), encoding="utf-8")
    return path


def _compare(res: dict, files: dict) -> None:
    """Fill ``res['compare']`` (before/after/ratio, the floor on sim), the damage removed,
    e_M not worse and the figure, with compare-runs' code over the same program periods."""
    from motorctl.app.tune import damage_removed
    from motorctl.cli.runs import compare_logs, figures, public
    axis = res["axis"]

    def compare(after: str) -> dict:
        try:
            return compare_logs(str(files["before"]), str(files[after]), [axis])
        except ValueError as exc:      # no common program period (a run cut short)
            raise InputError(str(exc)) from None

    cmp = compare("after")
    r = cmp["axes"][axis]
    if "floor" in res["files"]:
        fl = compare("floor")["axes"][axis]
        r["floor"] = fl["after"]          # same duration and program: the same window
        res["damage_removed"] = damage_removed(r["before"]["L2_um"], r["after"]["L2_um"], r["floor"]["L2_um"])
    res["e_M_not_worse"] = bool(r["after"]["e_M_um"] <= r["before"]["e_M_um"])
    try:
        res["figures"] = figures(cmp, res["out"])
    except ImportError:                   # the figure needs the `plot` extra; the table does not
        res["figures"] = []
    res["compare"] = public(cmp)["axes"][axis]


def text_report(res: dict) -> str:
    """The text output of ``motorctl tune`` (its result :func:`tune`): what was found, then one
    table (compare-runs') with the floor on sim, the damage removed and whether e_M got worse."""
    from motorctl.ident.pipeline import fig as _fig
    from motorctl.cli.runs import text_report as table
    lines = []
    for e in res["effects"]:
        pars = ", ".join(f"{k} {_fig(v)}" for k, v in e["parameters"].items())
        tag = ("not compensable" if e["name"] not in res["compensation"] else
               f"dropped: {res['dropped'][e['name']]}" if e["name"] in res["dropped"] else "compensated")
        lines.append(f"effect found: {e['name']}: {pars}; {tag}")
    if "tuned" in res["files"]:
        lines.append(f"tuned config: {res['files']['tuned']}")
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
    return "\n".join(lines) + "\n"


def cmd_tune(args) -> int:
    out = args.out or default_out(args.config, args.axis)

    def progress(line: str) -> None:
        sys.stdout.write(line + "\n")
        sys.stdout.flush()

    res = tune(args.config, args.axis, out, args.duration, "virtual" if args.virtual_clock else None,
               None if args.json else progress)
    if args.json:
        from motorctl.ident.pipeline import json_default
        sys.stdout.write(json.dumps(res, default=json_default) + "\n")
    else:
        sys.stdout.write(text_report(res))
    return 1 if any(res["faults"].values()) else 0


__all__ = ["FILES", "cmd_tune", "default_out", "register", "text_report", "tune"]
