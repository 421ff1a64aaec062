"""``motorctl compare-runs``: the tracking indexes of two run logs over the same program periods.

    motorctl compare-runs BEFORE.mclog AFTER.mclog [--axis A] [--period S] [--settle-periods N]
                          [--json] [--out DIR]

Per axis present in both logs: e_M, e_F, L2[e] [µm] and u_peak [V] (docs/control-law.md, Performance indexes,
:func:`motorctl.metrics.tracking_indexes`) of each log and the ratio after/before, and L2[e]'s
parts in motion and at standstill (L2[e]² = motion² + standstill²; the desired velocity not
zero / zero) and u's noise at rest (RMS of u about its mean where the command has not moved
for 0.3 s, :func:`motorctl.metrics.u_rest_rms`) where both logs record the desired velocity
and acceleration. The two logs
are aligned by program time (the record's ``t`` = k·Ts): both are evaluated over the same whole
program periods, from the end of the settling (the first ``--settle-periods`` periods, default
1, excluded the same way for both, :func:`motorctl.metrics.settled_mask`) to the end of the
last period both logs complete; e_F is the last of those periods. Only cycles with the
amplifier enabled count. The program period comes from each log's header (the config's
``axes.A.trajectory.period_s``) or ``--period``; without one the whole common span is used.
Works on any run log (simulated or real driver). With ``--out DIR`` it writes
``compare_runs_<axis>.png``, the error of the last common period of both logs overlaid.

Exit codes: 0 done, 2 bad input (one line on stderr).
"""

from __future__ import annotations

import json
import math
import sys


def register(parser, subparsers) -> None:
    """Add the ``compare-runs`` subcommand (called by :func:`motorctl.cli.build_parser`)."""
    p = subparsers.add_parser("compare-runs", help="e_M, e_F, L2[e], u_peak of two run logs over the same "
                                                   "program periods, and their ratio")
    p.add_argument("before", help="run log (the reference)")
    p.add_argument("after", help="run log compared with it")
    p.add_argument("--axis", action="append", default=None, help="axis (repeatable; default: all in both)")
    p.add_argument("--period", type=float, default=None,
                   help="program period [s] (default: from the logs' headers)")
    p.add_argument("--settle-periods", type=int, default=1,
                   help="whole program periods excluded at the start of both (default 1)")
    p.add_argument("--json", action="store_true", help="one JSON object on stdout")
    p.add_argument("--out", default=None, metavar="DIR", help="write compare_runs_<axis>.png here")
    p.set_defaults(func=cmd_compare_runs)


def text_report(res: dict, extra_rows: tuple[str, ...] = ()) -> str:
    """The text report of ``res`` (:func:`compare_logs`); ``extra_rows``: more index rows of
    each axis entry (e.g. ``motorctl tune``'s "floor"), printed after the ratio."""
    from motorctl.commission.compare import INDEXES, SPLIT   # numpy: not at the parser's import
    from motorctl.metrics import REST_AFTER_S
    lines = [f"compare-runs: before {res['before']}", f"              after  {res['after']}"]
    for a, r in res["axes"].items():
        t0, t1 = r["window_s"]
        per = f", period {r['period_s']:g} s, first {r['settle_periods']} excluded" if r["period_s"] else ""
        lines.append(f"axis {a}: program time {t0:g}..{t1:g} s{per}")
        keys = INDEXES + tuple(k for k in SPLIT if k in r["ratio"])
        heads = {"e_M_um": "e_M um", "e_F_um": "e_F um", "L2_um": "L2[e] um", "u_peak_V": "u_peak V",
                 "L2_motion_um": "in motion", "L2_standstill_um": "standstill", "u_rest_rms_V": "u rest V"}
        lines.append(f"  {'':8s} " + " ".join(f"{heads[k]:>10s}" for k in keys))
        rows = [n for n in ("before", "after", "ratio", *extra_rows) if r.get(n)]
        for name in rows:
            fmt = "10.3f" if name == "ratio" else "10.4g"
            lines.append(f"  {name:8s} " + " ".join(
                f"{r[name][k]:{fmt}}" if r[name].get(k) is not None else f"{'-':>10s}" for k in keys))
        if len(keys) > len(INDEXES):
            lines.append("  (in motion / standstill: L2[e]'s parts where the desired velocity is not / is zero, "
                         "L2[e]² = motion² + standstill², um; u rest: RMS of u about its mean where the "
                         f"command has not moved for {REST_AFTER_S:g} s, V)")
    return "\n".join(lines) + "\n"


def cmd_compare_runs(args) -> int:
    from motorctl.cli import UsageError
    from motorctl.commission.compare import compare_logs, figures, public
    from motorctl.recorder.runlog import LogError
    if args.period is not None and not (math.isfinite(args.period) and args.period > 0):
        raise UsageError(f"--period {args.period}: must be a finite number > 0 s")
    if args.settle_periods < 0:
        raise UsageError(f"--settle-periods {args.settle_periods}: must be >= 0")
    if args.out:
        from motorctl.inputs import writable_dir
        writable_dir(args.out, "out")
    try:
        res = compare_logs(args.before, args.after, args.axis, args.period, args.settle_periods)
    except (LogError, ValueError, OSError) as exc:
        raise UsageError(str(exc)) from None
    if args.out:
        try:
            res["figures"] = figures(res, args.out)
        except ImportError:
            raise UsageError("--out needs matplotlib (the `plot` extra)") from None
    public(res)
    if args.json:
        sys.stdout.write(json.dumps(res) + "\n")
    else:
        sys.stdout.write(text_report(res))
    return 0


__all__ = ["cmd_compare_runs", "register", "text_report"]
