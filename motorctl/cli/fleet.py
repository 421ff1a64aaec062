"""``motorctl fleet``: a fleet's health from its run logs (the library: :mod:`motorctl.fleet`).

    motorctl fleet identify SOURCES... --out DIR [--scheduler tcp://HOST:8786] [--workers N]
                            [--window-s S] [--memory-limit M]
    motorctl fleet report DIR [--out REPORT_DIR] [--no-plots]
    motorctl fleet simulate OUT [--machines N] [--days D] [--logs-per-day K] [--duration S]
                            [--seed SEED] [--workers N]

Exit codes: 0 done; 1 ``identify`` ran but some logs failed (each named on stderr, the others
written); 2 bad input (a missing source, an output folder that cannot be written, a bad or
unreachable scheduler, no dataset to report on): one line on stderr, nothing started. Needs the
``fleet`` extra (dask[distributed], pyarrow, fsspec).
"""

from __future__ import annotations

import sys
import time


def _positive_int(text: str) -> int:
    import argparse
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
    if v < 1:
        raise argparse.ArgumentTypeError(f"{v}: at least 1")
    return v


def _positive_float(text: str) -> float:
    import argparse
    import math
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not (math.isfinite(v) and v > 0):
        raise argparse.ArgumentTypeError(f"{text}: a positive number")
    return v


def register(parser, subparsers) -> None:
    """Add ``fleet identify``, ``fleet report`` and ``fleet simulate`` (called by
    :func:`motorctl.cli.build_parser`)."""
    p = subparsers.add_parser("fleet", help="identification over many machines' run logs on Dask, "
                                            "and the fleet's report (the 'fleet' extra)")
    sub = p.add_subparsers(dest="fleet_command", metavar="{identify,report,simulate}")
    sub.required = True
    pi = sub.add_parser("identify", help="identify every new log's windows into a Parquet dataset")
    pi.add_argument("sources", nargs="+", metavar="SOURCE",
                    help="run logs or folders of them (*.mclog, *.log), local paths or fsspec URLs")
    pi.add_argument("--out", required=True, metavar="DIR", help="the dataset's folder (created; logs already "
                                                                 "in it, by content hash, are skipped)")
    pi.add_argument("--scheduler", default=None, metavar="tcp://HOST:PORT",
                    help="a running Dask scheduler (default: a local cluster)")
    pi.add_argument("--workers", type=_positive_int, default=None,
                    help="local cluster: worker processes of one thread each (default: the cores)")
    pi.add_argument("--window-s", type=_positive_float, default=None, metavar="S",
                    help="split each log into windows of at least S seconds (default: one window per log)")
    pi.add_argument("--memory-limit", default="auto", metavar="M",
                    help="local cluster: each worker's memory bound, e.g. 2GiB (default auto: the "
                         "memory over the workers)")
    pi.set_defaults(func=cmd_identify)
    pr = sub.add_parser("report", help="trends, change points and outliers of a fleet dataset")
    pr.add_argument("dir", metavar="DIR", help="the --out of `motorctl fleet identify`")
    pr.add_argument("--out", default=None, metavar="REPORT_DIR", help="where summary.md, findings.json and "
                                                                      "the PNGs go (default DIR/_report)")
    pr.add_argument("--no-plots", action="store_true", help="no PNG per machine")
    pr.set_defaults(func=cmd_report)
    ps = sub.add_parser("simulate", help="write a simulated fleet's run logs with injected wear")
    ps.add_argument("out", metavar="OUT", help="folder for the logs and fleet_truth.json")
    ps.add_argument("--machines", type=_positive_int, default=5,
                    help="machines (default 5; the first three worn, the next three one bad day each)")
    ps.add_argument("--days", type=_positive_int, default=10, help="days (default 10; wear from a third on)")
    ps.add_argument("--logs-per-day", type=_positive_int, default=1, help="logs per machine and day (default 1)")
    ps.add_argument("--duration", type=_positive_float, default=3.0,
                    help="program seconds per log (default 3; 2 s is too short to tell cogging)")
    ps.add_argument("--seed", type=int, default=0, help="the fleet's seed (each machine's plant and each log's noise)")
    ps.add_argument("--workers", type=_positive_int, default=1, help="processes")
    ps.set_defaults(func=cmd_simulate)


class _Progress:
    """One progress line on stderr: rewritten in place on a terminal, else a line every 2 s and
    the last."""

    def __init__(self, out=None):
        self.out = out or sys.stderr
        self.tty = self.out.isatty()
        self.last = 0.0

    def __call__(self, d: dict) -> None:
        line = (f"fleet: {d['done']}/{d['total']} logs ({d['identified']} identified, {d['skipped']} skipped, "
                f"{d['failed']} failed), {d['rate']:.2f} logs/s")
        now = time.monotonic()
        if self.tty:
            self.out.write("\r" + line + ("\n" if d["done"] == d["total"] else ""))
        elif now - self.last >= 2.0 or d["done"] == d["total"]:
            self.out.write(line + "\n")
            self.last = now
        else:
            return
        self.out.flush()


def cmd_identify(args) -> int:
    from motorctl.fleet.jobs import run_fleet
    s = run_fleet(args.sources, args.out, scheduler=args.scheduler, workers=args.workers,
                  window_s=args.window_s, memory_limit=args.memory_limit, progress=_Progress())
    for url, msg in s["failed"]:
        sys.stderr.write(f"motorctl fleet: skipped {url}: {msg}\n")
    for url, whole, n, n_whole in s["cut"]:
        sys.stdout.write(f"cut log {url}: {n} of the {n_whole} records of the run in {whole}; not counted again\n")
    for old, new, n, n_new in s["superseded"]:
        sys.stdout.write(f"superseded {old} ({n} records): the same run, longer, in {new} ({n_new} records)\n")
    c = s["compaction"]
    sys.stdout.write(f"{s['logs']} logs: {s['identified']} identified, {s['skipped']} skipped (already in "
                     f"{args.out}, or cut), {len(s['failed'])} failed; {s['rows']} rows; {c['files_after']} part "
                     f"files ({c['partitions']} partitions compacted); {s['seconds']:.1f} s\n")
    return 1 if s["failed"] else 0


def cmd_report(args) -> int:
    from motorctl.fleet.report import write_report
    r = write_report(args.dir, args.out, plots=not args.no_plots)
    for f in r["alarms"]:
        c = f["change"]
        sys.stdout.write(f"ALARM {f['machine']} {f['axis']} {f['parameter']}: {c['shape']} of {c['delta']:+.4g} "
                         f"from {f['when'][:10]} (z {c['z']:.1f})\n")
    sys.stdout.write(f"{len(r['alarms'])} alarms; {r['summary']}\n")
    return 0


def cmd_simulate(args) -> int:
    from motorctl.fleet.simulate import simulate_fleet
    from motorctl.inputs import writable_dir
    writable_dir(args.out, "fleet simulation output")
    t = simulate_fleet(args.out, machines=args.machines, days=args.days, logs_per_day=args.logs_per_day,
                       duration_s=args.duration, seed=args.seed, workers=args.workers)
    sys.stdout.write(f"{len(t['logs'])} logs in {args.out}; wear: "
                     + (", ".join(f"{w['machine']} {w['kind']} from day {w['onset_day']}" for w in t["wear"]) or "none")
                     + "; bad days: "
                     + (", ".join(f"{b['machine']} {b['parameter']} x{b['factor']:g} on day {b['day']}"
                                  for b in t["bad_days"]) or "none")
                     + "\n")
    return 0


__all__ = ["cmd_identify", "cmd_report", "cmd_simulate", "register"]
