"""``motorctl run``, ``compare``, ``check-config`` and ``plot``: the job on a config."""

from __future__ import annotations

import json
import os
import sys
import tempfile

from motorctl.cli import DEFAULT_CONFIG, UsageError, print_table
from motorctl.control import CONTROLLER_NAMES
from motorctl.inputs import seconds_arg as seconds
from motorctl.inputs import writable_dir, writable_file


def _load(path: str, check_budget: bool = True):
    from motorctl.config import load_config
    return load_config(path, check_budget=check_budget)


# --------------------------------------------------------------------------- run
#: exit code of a run whose end the device did not confirm (0 V, amplifier off not read back)
EXIT_STOP_UNCONFIRMED = 3


def cmd_run(args) -> int:
    """``motorctl run``: a SIGTERM/SIGINT during start-up, before the device is opened, ends it
    with one line (nothing was driven; :func:`motorctl.cli.main` catches it); from the device's
    opening on, the run's own stop (:func:`motorctl.app.job.run_job`: 0 V confirmed by the
    device, the stop line)."""
    return _cmd_run(args)


def _cmd_run(args) -> int:
    from motorctl.app.warmup import say_if_cold
    say_if_cold()                                 # within a second, before numba is imported
    from motorctl.app.build import StartRefused, rest_words, stop_lines
    from motorctl.app.job import run_job
    loaded = _load(args.config)
    axes = _select_axes(loaded, args.axis)
    if args.log:
        writable_file(args.log, "run log")        # before anything runs
    out = sys.stdout

    def announce(names, n_cycles, clock):
        out.write(f"running {', '.join(names)} at {1 / loaded.period_s:.0f} Hz for "
                  f"{n_cycles * loaded.period_s:g} s ({clock} clock); SIGINT/SIGTERM stops at 0 V\n")
        out.flush()

    if args.json:
        return _run_json(args, loaded, axes)
    try:
        res = run_job(loaded, axes=axes, controller=args.controller, duration_s=args.duration,
                      clock="virtual" if args.virtual_clock else None, log_path=args.log,
                      realtime_policy=args.realtime, on_start=announce,
                      on_notice=lambda line: (sys.stderr.write(f"motorctl: {line}\n"), sys.stderr.flush()))
    except StartRefused as exc:            # where the axes stand: 0 V, amplifiers off, nothing driven
        out.flush()
        sys.stderr.write(f"motorctl: error: the run is refused: {exc}\n")
        return 1
    rows = [["axis", "ctrl", "e_M um", "e_F um", "L2[e] um", "u_peak V", "io errors", "fault"]]
    for a, r in res.axes.items():
        rows.append([a, r["controller"], f"{r.get('e_M_um', float('nan')):.2f}",
                     f"{r.get('e_F_um', float('nan')):.2f}", f"{r.get('L2_um', float('nan')):.3f}",
                     f"{r.get('u_peak_V', float('nan')):.2f}", str(r["io_errors"]), r["fault"] or "-"])
    print_table(rows, out)
    tm = res.timing
    if tm.get("cycles"):
        out.write(f"loop: {tm['cycles']} cycles at {1 / loaded.period_s:.0f} Hz "
                  f"({'virtual' if args.virtual_clock or loaded.cfg.loop.clock == 'virtual' else 'wall'} clock); "
                  f"turnaround p50 {tm['turnaround_p50_us']:.1f} / p99 {tm['turnaround_p99_us']:.1f} / "
                  f"p99.9 {tm['turnaround_p999_us']:.1f} / max {tm['turnaround_max_us']:.1f} us; "
                  f"lateness p99 {tm['lateness_p99_us']:.1f} us; overruns {tm['overruns']}; "
                  f"page faults {tm['page_faults']}\n")
    rt = res.realtime
    out.write("realtime: " + ", ".join(f"{k} {'yes' if v['obtained'] else 'no'} ({v['detail']})"
                                       for k, v in rt.items()) + "\n")
    if res.log_path:
        out.write(f"log: {res.log_path}\n")
    if res.lost_rows:
        sys.stderr.write(f"motorctl: warning: {res.lost_rows} rows were overwritten in the record "
                         f"ring before they reached the log and the indexes\n")
    confirmed, lines = stop_lines(res.stop)
    if confirmed:
        how = f"stopped by {res.stopped_by_signal}" if res.stopped_by_signal else "stop"
        rest = rest_words(res.rest)
        out.write(f"{how}: {lines[0]}{'; ' + rest if rest else ''}\n")
    else:
        out.flush()
        for line in lines:
            sys.stderr.write(f"motorctl: error: {line}\n")
        return EXIT_STOP_UNCONFIRMED
    return 1 if any(r["fault"] for r in res.axes.values()) else 0


def _run_json(args, loaded, axes) -> int:
    """``motorctl run --json``: the run's indexes and the commissioning's figures per axis
    (:func:`motorctl.commission.evaluate.job_evaluation`, the path autotune verifies by)."""
    from motorctl.app.job import run_job
    from motorctl.commission.evaluate import run_metrics
    with tempfile.TemporaryDirectory(prefix="motorctl-run-") as tmp:
        log = args.log or os.path.join(tmp, "run.log")
        res = run_job(loaded, axes=axes, controller=args.controller, duration_s=args.duration,
                      clock="virtual" if args.virtual_clock else None, log_path=log,
                      realtime_policy=args.realtime)
        out = {}
        for a, r in res.axes.items():
            m = run_metrics(log, loaded, a)
            m.pop("e_psd")
            out[a] = {**{k: (None if isinstance(v, float) and v != v else v) for k, v in r.items()},
                      **{k: (None if isinstance(v, float) and v != v else v) for k, v in m.items()}}
    json.dump({"axes": out, "stop_confirmed": res.stop_confirmed}, sys.stdout)
    sys.stdout.write("\n")
    return 1 if any(r["fault"] for r in res.axes.values()) else 0


def _select_axes(loaded, axis):
    if axis is None:
        return None
    if axis not in loaded.axes:
        raise UsageError(f"{loaded.path}: no axis {axis!r}; axes: {', '.join(loaded.axes)}")
    return [axis]


# --------------------------------------------------------------------------- compare
def compared_controllers(loaded) -> list[str]:
    """The controllers ``compare`` runs: those configured on every axis, in registry order
    (C1 and C2 always; a PID when every axis names its gains)."""
    from motorctl.control import configured_controllers
    sets = [set(configured_controllers(ax.controller)) for ax in loaded.axes.values()]
    return [n for n in CONTROLLER_NAMES if all(n in s for s in sets)]


def cmd_compare(args) -> int:
    from motorctl.app.job import run_job
    from motorctl.metrics import PAPER_TABLES
    loaded = _load(args.config)
    kinds = compared_controllers(loaded)
    if args.plot:
        writable_dir(args.plot, "plot")           # before anything runs
    results = {}
    errors, t = {}, None
    with tempfile.TemporaryDirectory(prefix="motorctl-compare-") as tmp:
        for kind in kinds:
            log = os.path.join(tmp, f"{kind}.log") if args.plot else None
            res = run_job(loaded, controller=kind, duration_s=args.duration,
                          clock="wall" if args.wall_clock else "virtual", log_path=log)
            for a, r in res.axes.items():
                results.setdefault(a, {})[kind] = {k: r[k] for k in ("e_M_um", "e_F_um", "L2_um", "u_peak_V")}
            if log:
                from motorctl.recorder.runlog import read_log
                rl = read_log(log)
                t = rl.col("t")
                for a in rl.axes:
                    errors.setdefault(a, {})[kind] = rl.axis(a)["e"].copy()
    if args.plot and t is not None:
        from motorctl.plots import plot_compare_errors
        periods = {a: loaded.axes[a].trajectory.period_s for a in errors}
        files = plot_compare_errors(t, errors, periods, args.plot, title=os.path.basename(str(args.config)))
        if not args.json:
            for f in files:
                sys.stdout.write(f"{f}\n")
    if args.json:
        sys.stdout.write(json.dumps(results) + "\n")
        return 0
    out = sys.stdout
    keys = (("e_M_um", "e_M um"), ("e_F_um", "e_F um"), ("L2_um", "L2[e] um"), ("u_peak_V", "u_peak V"))
    for a, r in results.items():
        out.write(f"\naxis {a} ({args.duration or loaded.cfg.loop.duration_s:g} s, same seeded plant)\n")
        paper = PAPER_TABLES.get(a)
        rows = [["index"] + [k.upper() for k in kinds] + ["C2/C1"]
                + (["paper C1", "paper C2", "paper C2/C1"] if paper else [])]
        for k, label in keys:
            row = [label] + [f"{r[kind][k]:.2f}" for kind in kinds] + [f"{r['c2'][k] / r['c1'][k]:.2f}"]
            if paper:
                row += [f"{paper['c1'][k]:.2f}", f"{paper['c2'][k]:.2f}", f"{paper['c2'][k] / paper['c1'][k]:.2f}"]
            rows.append(row)
        print_table(rows, out)
    return 0


# --------------------------------------------------------------------------- check-config
def cmd_check_config(args) -> int:
    loaded = _load(args.config)
    drv = loaded.make_driver()
    b = drv.budget(loaded.cfg.loop.rate_hz)
    sys.stdout.write(f"{loaded.path}: ok: {len(loaded.axes)} axes ({', '.join(loaded.axes)}), "
                     f"driver {loaded.cfg.driver.type}, {loaded.cfg.loop.rate_hz:g} Hz")
    if b.max_rate_hz != float("inf"):
        sys.stdout.write(f"; bus {b.cycle_time_s * 1e6:.1f} us per cycle, max {b.max_rate_hz:.0f} Hz ({b.detail})")
    sys.stdout.write("\n")
    return 0


# --------------------------------------------------------------------------- warmup
def cmd_warmup(args) -> int:
    from motorctl.app.warmup import say_if_cold, warmup
    cold = say_if_cold()
    try:                 # systemd's ExecStartPre inherits the unit's SCHED_FIFO: compile as a guest
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    except OSError:
        pass
    loaded = _load(args.config)
    res = warmup(loaded)
    what = "the controllers and the servo cycle" if res["cycle"] else \
        f"the controllers (driver {loaded.cfg.driver.type!r} not opened: its servo cycle compiles at the first start)"
    sys.stdout.write(f"warmup: {what} {'compiled' if cold else 'loaded from the cache'} in "
                     f"{res['seconds']:.1f} s\n")
    return 0


# --------------------------------------------------------------------------- plot
def cmd_plot(args) -> int:
    from motorctl.plots import plot_log
    if args.out:
        writable_dir(args.out, "plot")
    files = plot_log(args.log, args.out)
    for f in files:
        sys.stdout.write(f"{f}\n")
    return 0



def register(parser, sub) -> None:
    r = sub.add_parser("run", help="run the servo loop on a config (the main job)")
    r.add_argument("config", nargs="?", default=DEFAULT_CONFIG, help="the config YAML (default: %(default)s)")
    r.add_argument("--axis", help="run only this axis")
    r.add_argument("--controller", choices=CONTROLLER_NAMES, help="override every axis's controller")
    r.add_argument("--duration", type=seconds, help="run length in s (default: loop.duration_s)")
    r.add_argument("--log", help="write the run log here")
    r.add_argument("--json", action="store_true",
                   help="print one JSON object (per axis: the indexes, saturated samples, u RMS at rest) "
                        "and nothing else")
    r.add_argument("--virtual-clock", action="store_true", help="run as fast as possible (same results)")
    r.add_argument("--realtime", choices=("off", "best_effort", "required"),
                   help="override loop.realtime.policy")
    r.set_defaults(func=cmd_run)

    c = sub.add_parser("compare", help="C1, C2 (and a PID where configured) on the same seeded plant, beside the paper's tables")
    c.add_argument("config", nargs="?", default=DEFAULT_CONFIG, help="the config YAML (default: %(default)s)")
    c.add_argument("--duration", type=seconds, help="run length in s (default: loop.duration_s = 40)")
    c.add_argument("--json", action="store_true", help="print one JSON object and nothing else")
    c.add_argument("--wall-clock", action="store_true", help="pace by the wall clock (default: virtual)")
    c.add_argument("--plot", metavar="DIR", default=None,
                   help="also write DIR/<axis>_compare_error.png: one period's error of each controller overlaid")
    c.set_defaults(func=cmd_compare)

    k = sub.add_parser("check-config", help="check a config; exit 0 if it is valid")
    k.add_argument("config", nargs="?", default=DEFAULT_CONFIG, help="the config YAML (default: %(default)s)")
    k.set_defaults(func=cmd_check_config)

    w = sub.add_parser("warmup", help="compile the servo cycle and the controllers for this CPU "
                                      "ahead of the first run (no device opened)")
    w.add_argument("config", nargs="?", default=DEFAULT_CONFIG, help="the config YAML (default: %(default)s)")
    w.set_defaults(func=cmd_warmup)

    pl = sub.add_parser("plot", help="PNG figures of a run log (like the paper's Figs. 4-12)")
    pl.add_argument("log", help="a run log (motorctl run --log, or a daemon's segment)")
    pl.add_argument("--out", default=None, help="output directory (default: LOG without suffix + '_plots')")
    pl.set_defaults(func=cmd_plot)

