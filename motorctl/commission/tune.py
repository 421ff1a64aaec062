"""``motorctl tune``'s runs (:func:`tune`: run → identify → tuned config → run again → compare,
keeping only the compensation the closed loop is better with), its effect-free floor on the
simulated driver and the damage removed, and the synthetic logs of the identification's tests
(:func:`make_log`).
The CLI (arguments, text) is :mod:`motorctl.cli.tune`; the steps are described there.

The floor and the damage removed:

On the sim driver the plant's unmodelled effects are known: the floor is the same config and
seed with every effect family switched off, the best a compensation can do. The families are
found through the registry :data:`motorctl.effects.FAMILIES` (no list here): a family with an
``effects:`` entry (``sim_options``) is switched off by removing that entry; one whose simulator
option is an axis-level driver key (e.g. ``input_delay_s``) by removing the keys of its
``example`` (the fragment of ``axes.NAME.driver`` that switches it on), which restores the
option's default (off). :func:`effect_free` then checks through each family's ``sim_config``
that nothing is left on.

    damage removed = (L2_before − L2_after) / (L2_before − L2_floor)

1 means the tuned run tracks like the effect-free plant; 0 means nothing was gained.
"""

from __future__ import annotations

import copy
from pathlib import Path

from motorctl.config import LoadedConfig, config_from_dict
from motorctl.effects import FAMILIES
from motorctl.ident.ambiguity import SPEED_SCALE, SPRING_FAMILY as SPRING
from motorctl.inputs import InputError

#: e_M may grow by this much and still count as not worse [µm]: one count of the 0.5 µm encoder
E_M_SLACK_UM = 0.5
#: u's RMS at rest may grow by this share and still count as not worse: on the default plant
#: it is 60-130 mV, mostly one encoder count's flicker through k_s, and a tuned run's is up to
#: 25 % above its before run's with where the carriage sticks after each move
#: (benchmarks/tune_families.py, 2026-11-23); a compensation that makes the amplifier chatter
#: at rest shows as a multiple
U_REST_SLACK = 0.5

#: file names written in the output directory
FILES = {"before": "before.mclog", "tuned": "tuned.yaml", "after": "after.mclog",
         "floor_config": "floor.yaml", "floor": "floor.mclog", "rejected": "tuned-rejected.yaml"}

#: ``driver.type`` of the simulated driver (its plant and effects are in the config)
SIM_DRIVER = "sim"


def is_simulated(loaded: LoadedConfig) -> bool:
    """True when the config runs the simulated driver (whose plant is in the config)."""
    return loaded.cfg.driver.type == SIM_DRIVER


def effects_on(loaded: LoadedConfig, axis: str) -> list[str]:
    """Names of the effect families switched on in the simulated plant of ``axis``, in registry
    order (each family's ``sim_config`` is not None). Empty for a driver other than sim."""
    if not is_simulated(loaded):
        return []
    opts = loaded.axis_driver_options[axis]
    return [name for name, fam in FAMILIES.items() if fam.sim_config(opts) is not None]


def removable() -> list:
    """The families a compensation can remove (:attr:`~motorctl.effects.base.EffectFamily.has_compensation`),
    in registry order: those :func:`effect_free` switches off. A family that is identified and
    reported only (a mass step, stiction, a dead-zone, a gain drift) stays on in the floor: the
    floor is the best a compensation can do on that plant."""
    return [f for f in FAMILIES.values() if f.has_compensation]


def effect_free(cfg: dict, source: str = "<effect-free config>") -> dict:
    """A copy of the sim-driver config dict ``cfg`` with every effect family a compensation can
    remove (:func:`removable`) switched off on every axis; everything else (plant, force noise,
    seed, controllers, programs, the effects no compensation removes) unchanged.

    Args:
        cfg: a config dict (parsed YAML) of the sim driver. source: its name in errors.
    Returns:
        The new config dict (``cfg`` is not modified).
    Raises:
        ConfigError: ``cfg`` is not a valid config.
        ValueError: the driver is not sim, or a family is still on after its entry and keys
            were removed (a family whose switch this rule does not find).
    """
    d = copy.deepcopy(cfg)
    for ax in d.get("axes", {}).values():
        drv = ax.get("driver")
        if not isinstance(drv, dict):
            continue
        effects = drv.get("effects")
        for fam in removable():
            if fam.sim_options is not None:
                if isinstance(effects, dict):
                    effects.pop(fam.name, None)
            else:
                for key in fam.example:
                    drv.pop(key, None)
        if isinstance(effects, dict) and not effects:
            drv.pop("effects")
    loaded = config_from_dict(d, source, check_budget=False)
    if not is_simulated(loaded):
        raise ValueError(f"{source}: driver {loaded.cfg.driver.type!r} has no simulated plant to switch "
                         f"effects off in (driver type {SIM_DRIVER!r} only)")
    for a in loaded.axes:
        left = [n for n in effects_on(loaded, a) if FAMILIES[n].has_compensation]
        if left:
            raise ValueError(f"{source}: axes.{a}.driver: {', '.join(left)} still on after removing "
                             f"its effects entry and the keys of its example")
    return d


def damage_removed(l2_before: float, l2_after: float, l2_floor: float) -> float | None:
    """(L2_before − L2_after) / (L2_before − L2_floor) [-], or None when the effect does no
    damage (L2_before ≤ L2_floor: nothing to remove). L2 in any one unit (e.g. µm)."""
    damage = l2_before - l2_floor
    if not damage > 0:
        return None
    return (l2_before - l2_after) / damage


def make_log(path: str, effect: dict | None = None, duration_s: float = 8.0, seed: int = 1,
             axis: str = "X", noise_N: float | None = 1.0, compensation: dict | None = None,
             trajectory: dict | None = None, base=None):
    """Run the simulated axis of :func:`motorctl.ident.synth.gantry_dict` (C2, virtual clock)
    and write the run log to ``path`` (arguments as ``gantry_dict``): the synthetic logs of the
    identification's tests and benchmarks.

    Returns:
        The :class:`motorctl.app.job.JobResult`.
    """
    from motorctl.app.job import run_job
    from motorctl.ident.synth import gantry_dict
    loaded = config_from_dict(gantry_dict(axis, effect, seed, noise_N, compensation, trajectory, base),
                              f"<synthetic {axis}>")
    return run_job(loaded, duration_s=duration_s, clock="virtual", log_path=str(path))


def better(a: dict, b: dict, ref: dict | None = None) -> bool:
    """Run ``a`` tracks better than run ``b`` (their indexes over the same program periods,
    :func:`motorctl.commission.compare.compare_axis` [µm, V]): a lower L2[e], an e_M no more than
    :data:`E_M_SLACK_UM` above that of ``ref`` (default ``b``; tune passes the before run: L2[e]
    decides, e_M must not get worse than without tuning), and, where both have it, u's RMS at
    rest ("u_rest_rms_V") no more than :data:`U_REST_SLACK` above ``ref``'s: a compensation
    must not buy tracking with a noisier amplifier at rest."""
    ref = b if ref is None else ref
    ur_a, ur_ref = a.get("u_rest_rms_V"), ref.get("u_rest_rms_V")
    quiet = ur_a is None or ur_ref is None or ur_a <= ur_ref * (1.0 + U_REST_SLACK)
    return a["L2_um"] < b["L2_um"] and a["e_M_um"] <= ref["e_M_um"] + E_M_SLACK_UM and quiet


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
        "faults": {run: reason or ""}, "effects" (identify's summary), "ambiguous" (its ambiguities), "compensation",
        "not_compensable", "kept" (the compensated families kept in tuned.yaml), "dropped"
        ({family: why}), "theta_hat0" (which θ̂(0) tuned.yaml carries and why: the fitted one or
        the config's own; None when it stopped before), "verdict" (None, or that no effect was
        kept), "stopped" (None, or why it stopped early), "compare": None or
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
           "compensation": {}, "not_compensable": [], "input_saturation": None, "kept": [], "dropped": {},
           "theta_hat0": None,
           "verdict": None,
           "stopped": None, "compare": None,
           "floor_effects_off": ([n for n in effects_on(loaded, axis) if FAMILIES[n].has_compensation]
                                 if floor_cfg is not None else None),
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
    res.update(effects=s["effects"], compensation=comp, not_compensable=skipped,
               input_saturation=s["input_saturation"], ambiguous=s.get("ambiguous", []),
               gain_N_per_V=s.get("gain_N_per_V"))
    if not s["effects"]:
        res["stopped"] = "no effect found (no candidate passed held-out gain, BIC and plausibility)"
        return res
    if not comp:
        res["stopped"] = (f"no compensable effect found ({', '.join(skipped)}: no compensation term, or the "
                          f"record cannot tell it from a look-alike)")
        return res
    tuned = write_tuned_config(idf, s, base, axis, str(config), files["tuned"])
    res["files"]["tuned"] = str(files["tuned"])
    if not run("after", load_config(files["tuned"])):
        # a config whose own run faulted (a trip of the cycle's protections: following error,
        # I²t, oscillation at rest) is not handed over as tuned.yaml; kept aside for the reader
        files["tuned"].replace(files["rejected"])
        res["files"]["rejected"] = str(files["rejected"])
        del res["files"]["tuned"]
        res["stopped"] += f"; its config is not handed over (moved to {files['rejected'].name})"
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
    from motorctl.commission.compare import compare_logs
    try:
        return compare_logs(str(files["before"]), str(log), [axis])["axes"][axis]["after"]
    except ValueError as exc:      # no common program period (a run cut short)
        raise InputError(str(exc)) from None


#: the controller keys of the fitted model θ̂(0) that ``tuned.yaml`` changes (one change for
#: :func:`_keep_what_helps`: the fitted start, or the config's own)
THETA_KEYS = ("theta_hat0", "theta_min", "theta_max")
#: the name of that change (its ``without_<change>`` files; the outcome is ``res['theta_hat0']``)
THETA_CHANGE = "theta_hat0"


def _keep_what_helps(res: dict, files: dict, tuned: dict, base: dict, axis: str, duration: float,
                     clock: str, note) -> bool:
    """Keep in ``tuned.yaml`` only the changes the closed loop is better with (module
    docstring, step 4): the fitted θ̂(0) (with its box) and each compensated effect are the
    changes. Backward elimination: each change still kept is undone in turn from the best
    config so far (``DIR/without_<changes>.yaml``/``.mclog``, the changes undone joined by
    ``+``); of the undos the loop is better with (:func:`better` against the before run's
    e_M), the one with the lowest L2[e] is taken, and the round repeats until no undo helps.
    One harmful change (a phantom effect) therefore goes first instead of taking the good ones
    with it. Undoing the last effect is the before run and is not tried. Rewrites
    ``tuned.yaml`` and ``after.mclog`` when something goes. Returns False when a run faulted
    (``res['stopped']`` says which)."""
    import copy
    import shutil

    import yaml

    from motorctl.config import config_from_dict
    ctl0 = base["axes"][axis]["controller"]
    comp = dict(tuned["axes"][axis]["controller"].get("compensation") or {})
    kept = [THETA_CHANGE] + list(comp)
    undone: list = []
    best, best_cfg, best_log = _indexes(files, files["after"], axis), tuned, files["after"]
    before = _indexes(files, files["before"], axis)
    out = files["tuned"].parent
    while True:
        effects_kept = [c for c in kept if c != THETA_CHANGE]
        took = None                              # (L2, change, indexes, config, log) of the best undo
        for change in kept:
            if change != THETA_CHANGE and len(effects_kept) == 1:
                continue                         # undoing the last effect is the before run
            trial = copy.deepcopy(best_cfg)
            ctl = trial["axes"][axis]["controller"]
            if change == THETA_CHANGE:
                for k in THETA_KEYS:
                    if k in ctl0:
                        ctl[k] = copy.deepcopy(ctl0[k])
                    else:
                        ctl.pop(k, None)
            else:
                ctl["compensation"] = {k: v for k, v in ctl["compensation"].items() if k != change}
                if not ctl["compensation"]:
                    ctl.pop("compensation")
            name = "without_" + "+".join(undone + [change])
            path, log = out / f"{name}.yaml", out / f"{name}.mclog"
            path.write_text(yaml.safe_dump(trial, sort_keys=False, default_flow_style=False, allow_unicode=True),
                            encoding="utf-8")
            note(f"without {' and '.join(undone + [change])}: axis {axis} of {path}, {duration:g} s, "
                 f"{clock} clock -> {log}")
            fault = _run_axis(config_from_dict(trial, str(path)), axis, duration, clock, log)["fault"]
            res["files"][name] = str(log)
            if fault:
                res["faults"][name] = fault
                res["stopped"] = f"the run without {' and '.join(undone + [change])} faulted: {fault}"
                return False
            m = _indexes(files, log, axis)
            if better(m, best, before) and (took is None or m["L2_um"] < took[0]):
                took = (m["L2_um"], change, m, trial, log)
        if took is None:
            break
        _, change, m, trial, log = took
        kept.remove(change)
        undone.append(change)
        why = (f"the loop is better without it (L2[e] {best['L2_um']:.3f} -> {m['L2_um']:.3f} um, "
               f"e_M {best['e_M_um']:.2f} -> {m['e_M_um']:.2f} um)")
        if change == THETA_CHANGE:
            res["theta_hat0"] = "the config's own: " + why
        else:
            res["dropped"][change] = why
        best, best_cfg, best_log = m, trial, log
    effects = [c for c in kept if c != THETA_CHANGE]
    if not effects or not better(best, before):
        for c in effects:
            res["dropped"][c] = (f"with it the loop is not better than before (L2[e] {before['L2_um']:.3f} -> "
                                 f"{best['L2_um']:.3f} um, e_M {before['e_M_um']:.2f} -> {best['e_M_um']:.2f} um)")
        kept, best_cfg, best_log = [], base, files["before"]
        res["verdict"] = ("no effect kept: the closed loop was not better with any of the compensation; "
                          "tuned.yaml is CONFIG unchanged")
    res["kept"] = [c for c in kept if c != THETA_CHANGE]
    if res["kept"] and THETA_CHANGE in kept:
        res["theta_hat0"] = "the fitted one (the loop is not better with the config's own)"
    elif not res["kept"]:
        res["theta_hat0"] = "the config's own (tuned.yaml is CONFIG unchanged)"
    if best_log != files["after"]:
        head = (f"# motorctl tune: {res['config']} with the compensation of {', '.join(res['kept'])}"
                + ("" if THETA_CHANGE in kept else " (theta_hat0 and its box: the config's own)") + "\n"
                if res["kept"] else
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
    """Write the effect-free config (:func:`motorctl.commission.tune.effect_free`) with a comment."""
    import yaml
    head = (f"# the effect-free floor of `motorctl tune`: {config} with every simulated effect switched "
            f"off (motorctl.commission.tune.effect_free); the same plant otherwise, the same seed\n")
    path.write_text(head + yaml.safe_dump(floor_cfg, sort_keys=False, default_flow_style=False,
                                          allow_unicode=True), encoding="utf-8")
    return path


def _compare(res: dict, files: dict) -> None:
    """Fill ``res['compare']`` (before/after/ratio, the floor on sim), the damage removed,
    e_M not worse and the figure, with compare-runs' code over the same program periods."""
    from motorctl.commission.compare import compare_logs, figures, public
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



# ----------------------------------------------------------- the other-speed experiment
def other_speed(cfg: dict, axis: str, scale: float = SPEED_SCALE) -> dict:
    """A copy of config dict ``cfg`` whose axis ``axis`` runs the same program at ``scale``
    times the speed: the same points, the move times and the period divided by ``scale``, v_max
    times scale, a_max times scale², j_max times scale³ (the path as a function of scale·t).
    Raises KeyError: the axis has no ``trajectory`` with those keys."""
    import copy
    d = copy.deepcopy(cfg)
    tr = d["axes"][axis]["trajectory"]
    tr["move_times_s"] = [float(t) / scale for t in tr["move_times_s"]]
    tr["period_s"] = float(tr["period_s"]) / scale
    for key, k in (("v_max", 1), ("a_max", 2), ("j_max", 3)):
        if key in tr:
            tr[key] = float(tr[key]) * scale ** k
    return d


def speed_experiment(cfg: dict, axis: str, entry: dict, log_path, duration_s: float,
                     scale: float = SPEED_SCALE, source: str = "<config>") -> dict:
    """The experiment that separates a time-periodic line from a force of position (an entry of
    :func:`summaries` with a ``harmonic``), run on a simulated plant: the same program at
    ``scale`` times the speed (:func:`other_speed`) for ``duration_s / scale`` seconds on the
    virtual clock, logged to ``log_path``, identified with the default options.

    The time-periodic hypothesis predicts the line at the same f [Hz]; a force of position
    predicts it at scale·f (its period in metres kept). Named: ``periodic_disturbance`` when the
    record names it within its resolution 1/L of f, or reports a line (a fit of the family in
    an ambiguity) there; the position family when the record names it, or its line is at
    scale·f; else none ("not resolved").

    Returns:
        {"scale", "log", "named" (family or None), "why", "effects" (the second record's named
        families), "ambiguous" (its ambiguity texts)}.
    Raises:
        KeyError: the axis has no trajectory to scale. ConfigError: the scaled config is not
        valid. LogError: the second record cannot be identified.
    """
    from motorctl.app.job import run_job
    from motorctl.ident.ambiguity import TIME_FAMILY
    from motorctl.ident.data import load_record
    from motorctl.ident.pipeline import identify_record

    time_fam, pos_fam = entry["families"]
    f1 = float(entry["fits"][0]["parameters"]["frequency_Hz"])
    d = other_speed(cfg, axis, scale)
    run_job(config_from_dict(d, f"{source} at {scale:g} x the speed"), duration_s=duration_s / scale,
            clock="virtual", log_path=str(log_path))
    _, s = identify_record(load_record(str(log_path), None, None, axis))
    res = 1.0 / (duration_s / scale)
    lines = [float(e["parameters"]["frequency_Hz"]) for e in s["effects"] if e["name"] == TIME_FAMILY]
    lines += [float(f["parameters"]["frequency_Hz"]) for a in s["ambiguous"] for f in a["fits"]
              if f["name"] == TIME_FAMILY and "frequency_Hz" in f["parameters"]]
    named = {e["name"] for e in s["effects"]}
    out = {"scale": scale, "log": str(log_path), "effects": sorted(named),
           "ambiguous": [a["text"] for a in s["ambiguous"]]}
    if any(abs(f - f1) <= res for f in lines):
        out.update(named=TIME_FAMILY, why=f"at {scale:g} x the speed the line stays at {f1:.4g} Hz: a force in time")
    elif pos_fam in named or any(abs(f - scale * f1) <= res for f in lines):
        out.update(named=pos_fam, why=f"at {scale:g} x the speed the line moves to {scale * f1:.4g} Hz "
                                      f"({scale:g} x {f1:.4g} Hz), its period in metres kept: a force of position")
    else:
        out.update(named=None, why=f"not resolved: at {scale:g} x the speed neither a line at {f1:.4g} Hz "
                                   f"nor one at {scale * f1:.4g} Hz, nor {pos_fam} named")
    return out


def speed_experiments(res: dict, progress=None) -> list:
    """The other-speed runs of step 7 (module docstring) for ``res`` (:func:`motorctl.commission.
    tune.tune`'s result): on a simulated plant with a before log, each time-periodic line at a
    program harmonic that the before log's identification reports ambiguous
    (:func:`speed_experiment`). Returns [{"ambiguous" (its text), and
    speed_experiment's keys}], or [{"ambiguous", "error"}] for one that could not run; [] when
    none applies."""
    return _experiments(res, lambda a: a.get("harmonic"), "other_speed",
                        "other speed: {text}: the program at 0.7 x the speed -> {log}",
                        lambda cfg, e, log: speed_experiment(cfg, res["axis"], e, log, res["duration_s"],
                                                             source=res["config"]),
                        progress, {"scale": 0.7})


def _experiments(res: dict, applies, stem: str, say: str, run, progress=None, not_run: dict | None = None) -> list:
    """The second experiments of ``res`` (:func:`tune`'s result) on a simulated plant with a
    before log: for each of its ambiguities for which ``applies(entry)`` holds, ``run(config
    dict, entry, log path)`` with the log ``DIR/<stem>_<k>.mclog``, after ``progress(say)``
    (``say`` formatted with ``text``, ``log``). Returns [{"ambiguous" (its text), and run's
    keys}], or [{"ambiguous", "error", "log", "named": None, "why", and ``not_run``'s keys}] for
    one that could not run; [] when none applies."""
    before = res.get("files", {}).get("before")
    if res.get("floor_effects_off") is None or not before or res.get("faults", {}).get("before"):
        return []
    entries = [a for a in res.get("ambiguous", []) if applies(a)]     # the before log's identification
    if not entries:
        return []
    from motorctl.config import load_yaml
    out = []
    for k, e in enumerate(entries):
        log = Path(res["out"]) / f"{stem}_{k + 1}.mclog"
        if progress:
            progress(say.format(text=e["text"], log=log))
        try:
            r = run(load_yaml(res["config"]), e, log)
        except Exception as exc:        # noqa: BLE001 - reported, the tune's result stands
            out.append({"ambiguous": e["text"], "error": f"{type(exc).__name__}: {exc}"[:300],
                        **(not_run or {}), "log": str(log), "named": None, "why": "not run"})
            continue
        out.append({"ambiguous": e["text"], **r})
    return out


# ----------------------------------------------------------- the slow-pass experiment
#: the passes' stroke: this share of the program's stroke, centred on it
PASS_SPAN = 0.8
#: the passes' speed: this share of the program's v_max, at most PASS_SPEED_MAX [m/s]
PASS_SPEED_SHARE, PASS_SPEED_MAX = 0.05, 0.05
#: passes each way, and the position bins each pass is averaged in
PASS_COUNT, PASS_BINS = 2, 8
#: a cruise's first rows left out (the loop settling after the acceleration) [s]
PASS_SETTLE_S = 0.2


def pass_program(cfg: dict, axis: str) -> tuple[dict, float]:
    """A copy of config dict ``cfg`` whose axis ``axis`` moves back and forth over
    :data:`PASS_SPAN` of its program's stroke at a slow constant speed (:data:`PASS_SPEED_SHARE`
    of its v_max, at most :data:`PASS_SPEED_MAX`), its a_max and j_max as configured, 0.5 s at
    rest at each end. Returns (the config dict, the run's length [s]: :data:`PASS_COUNT` periods).
    Raises: KeyError: the axis has no ``trajectory``; ValueError: its program holds one position."""
    import copy
    from motorctl.loop.trajectory import Move
    d = copy.deepcopy(cfg)
    tr = d["axes"][axis]["trajectory"]
    lo, hi = min(tr["points"]), max(tr["points"])
    if not hi > lo:
        raise ValueError(f"axis {axis}: its program holds one position; no stroke to pass over")
    mid, half = 0.5 * (lo + hi), 0.5 * PASS_SPAN * (hi - lo)
    v = min(PASS_SPEED_SHARE * float(tr.get("v_max", 1.0)), PASS_SPEED_MAX)
    a_max, j_max = float(tr.get("a_max", 10.0)), float(tr.get("j_max", 1000.0))
    move = Move(mid - half, mid + half, v, a_max, j_max).duration
    tr.update(points=[mid - half, mid + half], move_times_s=[0.5, move + 1.0], period_s=2.0 * move + 1.0,
              v_max=v)
    return d, PASS_COUNT * tr["period_s"]


def pass_forces(log_path, axis: str, bins: int = PASS_BINS) -> list[dict]:
    """The input over each constant-velocity stretch of ``axis`` in a run log (ẋ_d at its
    largest magnitude, after :data:`PASS_SETTLE_S`), averaged in ``bins`` equal position bins
    of the stretch: [{"x" (the bin's mean position) [m], "direction" (±1), "u" (its mean) [V]}]."""
    import numpy as np
    from motorctl.recorder.runlog import read_log
    log = read_log(str(log_path))
    prog = log.program_rows(axis)
    y, v, u, t = log.col(f"{axis}.y"), log.col(f"{axis}.xd_dot"), log.col(f"{axis}.u"), log.col("t")
    vmax = float(np.max(np.abs(v))) if v.size else 0.0
    cruise = np.abs(np.abs(v) - vmax) <= 1e-9 * max(vmax, 1e-12)
    if prog is not None:
        cruise &= prog
    out, i, n = [], 0, len(v)
    while i < n:
        if not cruise[i]:
            i += 1
            continue
        j = i
        while j < n and cruise[j] and np.sign(v[j]) == np.sign(v[i]):
            j += 1
        k = int(np.searchsorted(t[i:j], t[i] + PASS_SETTLE_S)) + i
        if j - k >= 4 * bins:
            for part in np.array_split(np.arange(k, j), bins):
                out.append({"x": float(np.mean(y[part])), "direction": int(np.sign(v[i])),
                            "u": float(np.mean(u[part]))})
        i = j
    return out


def pass_experiment(cfg: dict, axis: str, entry: dict, log_path, gain_N_per_V: float | None,
                    source: str = "<config>") -> dict:
    """The experiment that tells a spring from a look-alike at rest (an ambiguity between
    ``spring`` and another family: stiction, a dead-zone, what a coarse or noisy encoder's flat
    reading at rest leaves), run on a simulated plant: slow constant-velocity passes both ways
    (:func:`pass_program`) on the virtual clock, logged to ``log_path``; the input averaged in
    position bins (:func:`pass_forces`) and fitted by least squares as u = c + a·direction +
    s·x. In motion at one speed the friction is a constant each way (a, with the viscous part in
    it) and nothing holds at a band's edge: what changes with the position is s.

    A spring of stiffness k needs u = k/A1·(x − x_0) + const: s near the fitted k/A1 (within 3σ
    or 30 %) and above 3σ names the spring. s below half of k/A1 and below it by 3σ: not a
    spring, the other family named. Anything else: not resolved.

    Args: entry: the ambiguity (``families`` holds "spring" and one other; its fits the
    spring's stiffness, in N/m with ``gain_N_per_V`` [N/V] or in V/m). Returns {"log",
    "speed_m_per_s", "bins" (pass_forces'), "slope_V_per_m", "slope_std", "direction_V",
    "spring_V_per_m" (the fit's), "named" (family or None), "why"}.
    Raises: KeyError: the axis has no trajectory, or the entry no spring fit. ValueError: no
    stroke, or no constant-velocity stretch each way in the run. ConfigError: the pass config
    is not valid.
    """
    import numpy as np
    from motorctl.app.job import run_job
    other = next(f for f in entry["families"] if f != SPRING)
    prm = next(f["parameters"] for f in entry["fits"] if f["name"] == SPRING)
    k_fit = (float(prm["stiffness_N_per_m"]) / float(gain_N_per_V) if "stiffness_N_per_m" in prm
             else float(prm["stiffness_V_per_m"]))
    d, duration = pass_program(cfg, axis)
    run_job(config_from_dict(d, f"{source} in slow passes"), axes=[axis], duration_s=duration,
            clock="virtual", log_path=str(log_path))
    rows = pass_forces(log_path, axis)
    if len({(r["direction"]) for r in rows}) < 2:
        raise ValueError("the slow passes gave no constant-velocity stretch both ways")
    A = np.array([[1.0, r["direction"], r["x"]] for r in rows])
    y = np.array([r["u"] for r in rows])
    coef, *_ = np.linalg.lstsq(A, y, rcond=None)
    s2 = float(np.sum((y - A @ coef) ** 2)) / max(1, len(y) - 3)
    std = np.sqrt(np.maximum(np.diag(np.linalg.pinv(A.T @ A)) * s2, 0.0))
    sl, ss = float(coef[2]), float(std[2])
    out = {"log": str(log_path), "speed_m_per_s": float(d["axes"][axis]["trajectory"]["v_max"]), "bins": rows,
           "slope_V_per_m": sl, "slope_std": ss, "direction_V": float(coef[1]), "spring_V_per_m": k_fit}
    span = f"the input's slope over the position {sl:.4g} +- {ss:.2g} V/m against the spring's {k_fit:.4g} V/m"
    if sl > 3.0 * ss and abs(sl - k_fit) <= max(3.0 * ss, 0.3 * abs(k_fit)):
        out.update(named=SPRING, why=f"a force of the position in slow passes: {span}")
    elif abs(sl) < 0.5 * abs(k_fit) and abs(sl) + 3.0 * ss < abs(k_fit):
        out.update(named=other, why=f"not a spring: {span}; {other} is left")
    else:
        out.update(named=None, why=f"not resolved: {span}")
    return out


def pass_experiments(res: dict, progress=None) -> list:
    """The slow-pass runs of step 8 (:mod:`motorctl.cli.tune`) for ``res`` (:func:`tune`'s
    result): on a simulated plant with a before log, each ambiguity between a spring and one
    other family that the before log's identification reports (:func:`pass_experiment`).
    Returns [{"ambiguous" (its text), and pass_experiment's keys}], or [{"ambiguous", "error",
    "log", "named": None, "why"}] for one that could not run; [] when none applies."""
    return _experiments(res, lambda a: not a.get("harmonic") and SPRING in a.get("families", [])
                        and len(set(a["families"])) == 2, "slow_passes",
                        "slow passes: {text}: both ways at a constant speed -> {log}",
                        lambda cfg, e, log: pass_experiment(cfg, res["axis"], e, log, res.get("gain_N_per_V"),
                                                            source=res["config"]),
                        progress)


__all__ = ["E_M_SLACK_UM", "FILES", "SIM_DRIVER", "U_REST_SLACK", "better", "damage_removed", "effect_free",
           "effects_on", "is_simulated", "make_log", "tune", "other_speed", "speed_experiment", "speed_experiments",
           "pass_program", "pass_forces", "pass_experiment", "pass_experiments"]
