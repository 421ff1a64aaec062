"""``motorctl circle-test``: the ISO 230-4 circular test of the simulated gantry on the
daemon's motion path (:mod:`motorctl.app.circle_test`), C1, C2, PID+FF (and the GTCF pair when
configured on X and Y) at the given feeds; with
``--log`` each run's log, with ``--plot`` each run's polar plot; each run's figures by the
encoders and by the simulated ballbar (the driver's true carriage positions; none on a real
drive, and the output says so); ``--json``: one JSON list on stdout and nothing else (the log and
plot paths in it).
Exit codes: 0 done; 1 a fault or an underrun during a run; 2 bad input."""

from __future__ import annotations

import json
import sys
from pathlib import Path

from motorctl.cli import DEFAULT_CONFIG, UsageError, print_table


def log_paths(base: str, runs: list[tuple[str, float]]) -> list[str]:
    """The run-log path of each (controller, feed [m/s]) run: ``base`` itself for one run, else
    ``base`` with ``_<controller>_<feed mm/s>`` before its suffix (``c.log`` → ``c_c1_50.log``)."""
    if len(runs) == 1:
        return [base]
    p = Path(base)
    return [str(p.with_name(f"{p.stem}_{c}_{f * 1e3:g}{p.suffix}")) for c, f in runs]


def cmd_circle_test(args) -> int:
    from motorctl.app.circle_test import INSTRUMENTS, run_circle_test, summary, table
    from motorctl.config import load_config
    from motorctl.inputs import writable_file
    args.feed = args.feed or [0.05, 0.1]
    if not args.radius > 0 or any(not f > 0 for f in args.feed):
        raise UsageError("circle-test: --radius and --feed must be > 0 (m, m/s)")
    loaded = load_config(args.config)
    controllers = args.controller or ("c1", "c2", "pid") + (("gtcf",) if "gtcf" in _configured(loaded) else ())
    for c in controllers:
        if c not in _configured(loaded):
            raise UsageError(f"circle-test: controller {c!r} is not configured for X and Y in {args.config}")
    plan = [(c, f) for c in controllers for f in args.feed]
    logs = log_paths(args.log, plan) if args.log else [None] * len(plan)
    for lp in logs:
        if lp:
            writable_file(lp, "run log")          # before anything runs
    runs, bad = [], 0
    for (c, f), lp in zip(plan, logs):
        try:
            r = run_circle_test(loaded, args.radius, f, c, log_path=lp)
        except ValueError as exc:
            sys.stderr.write(f"motorctl: error: {exc}\n")
            bad += 1
            continue
        bad += r.underruns > 0
        runs.append(r)
    plots = [None] * len(runs)
    if args.plot and runs:
        from motorctl.plots import plot_circle_tests
        plots = plot_circle_tests(runs, args.plot)
    if args.json:
        sys.stdout.write(json.dumps([summary(r) | {"plot": pl} for r, pl in zip(runs, plots)]) + "\n")
    else:
        sys.stdout.write(f"ISO 230-4 circular test, R {args.radius * 1e3:g} mm about the middle of the soft "
                         f"limits, CCW then CW ({args.config}, simulated, virtual clock)\n")
        print_table(table(runs), sys.stdout)
        for k, what in INSTRUMENTS.items():
            sys.stdout.write(f"{k}: {what}\n")
        for why in dict.fromkeys(r.no_ballbar for r in runs if r.no_ballbar):
            sys.stdout.write(f"{why}\n")
        for r, pl in zip(runs, plots):
            for what, path in (("log", r.log_path), ("plot", pl)):
                if path:
                    sys.stdout.write(f"{what}: {path}\n")
    return 1 if bad else 0


def _configured(loaded) -> list[str]:
    """The controllers configured for both X and Y."""
    from motorctl.control import configured_controllers
    return [k for k in configured_controllers(loaded.axes["X"].controller)
            if k in configured_controllers(loaded.axes["Y"].controller)]


def register(parser, sub) -> None:
    p = sub.add_parser("circle-test", help="the ISO 230-4 circular test (G, H, F, the largest contour error) of "
                                           "the simulated gantry on the daemon's motion path, per controller and "
                                           "feed, by the encoders and by a simulated ballbar")
    p.add_argument("config", nargs="?", default=DEFAULT_CONFIG, help="the config YAML (default: %(default)s)")
    p.add_argument("--radius", type=float, default=0.05, help="circle radius [m] (default 0.05)")
    p.add_argument("--feed", type=float, action="append", help="feed [m/s], repeatable (default 0.05 and 0.1)")
    p.add_argument("--controller", action="append", choices=("c1", "c2", "pid", "gtcf"),
                   help="repeatable (default: c1, c2, pid, and gtcf when the config configures it on X and Y)")
    p.add_argument("--json", action="store_true",
                   help="one JSON list and nothing else (each run's figures, its log and plot paths)")
    p.add_argument("--log", metavar="PATH", default=None,
                   help="write each run's log (as motorctl run --log: motorctl plot/export read it); "
                        "several runs: PATH_<controller>_<feed mm/s> with PATH's suffix")
    p.add_argument("--plot", metavar="DIR", default=None,
                   help="also write DIR/circle_<controller>_<feed>.png: the radial deviation, polar")
    p.set_defaults(func=cmd_circle_test)
