"""Benchmark of ``motorctl identify`` on a 20 s run log at 5 kHz (it must finish within 30 s).

Rerun:
    python benchmarks/bench_ident.py              # generates the log once into /tmp, times identify
    python benchmarks/bench_ident.py --repeat 3 --effect stribeck --keep-log /tmp/x.log

What is timed: ``motorctl identify LOG --json --no-closed-loop`` end to end through
``motorctl.cli.main`` (reading, IDIM-LS, the effect search over all nine families with forward
selection, simulation fit %, JSON), and separately the same with the closed-loop before/after
(two simulated C2 runs of --closed-loop-duration seconds, 8 s by default), whose cost is the
simulator's, not the identification's. Wall-clock seconds on this machine; other processes on
the machine inflate them (the load average is printed).
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import os
import sys
import time


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--duration", type=float, default=20.0, help="log length [s] (default 20)")
    ap.add_argument("--effect", default="cogging", help="undeclared effect on the plant (synth.EXAMPLES key)")
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--keep-log", default="/tmp/motorctl_bench_ident_20s.log",
                    help="log path (reused when it exists)")
    ap.add_argument("--closed-loop", action="store_true", help="also time the run with the closed-loop check")
    args = ap.parse_args(argv)

    from motorctl.app.tune import make_log
    from motorctl.cli import main as cli_main
    from motorctl.ident.synth import EXAMPLES
    from motorctl.recorder.runlog import read_log

    path = args.keep_log
    regenerate = True
    if os.path.exists(path):
        log = read_log(path)
        truth = log.header.get("driver", {}).get("simulated", {}).get("X", {})
        want = EXAMPLES[args.effect]
        same = (truth.get("input_delay_s") == want["input_delay_s"]) if "input_delay_s" in want \
            else truth.get("effects") == want
        regenerate = abs(log.data.shape[0] * log.header["period_s"] - args.duration) > 1e-6 or not same
    if regenerate:
        t0 = time.perf_counter()
        make_log(path, EXAMPLES[args.effect], duration_s=args.duration, seed=1)
        print(f"generated {path}: {args.duration:g} s at 5 kHz with {args.effect} in "
              f"{time.perf_counter() - t0:.1f} s")
    log = read_log(path)
    n = log.data.shape[0]
    print(f"log: {path}, {n} samples ({n * log.header['period_s']:.1f} s at {1 / log.header['period_s']:.0f} Hz), "
          f"effect {args.effect}; load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} CPUs")

    def timed(extra):
        buf = io.StringIO()
        t0 = time.perf_counter()
        with contextlib.redirect_stdout(buf):
            rc = cli_main(["identify", path, "--json"] + extra)
        dt = time.perf_counter() - t0
        return rc, dt, json.loads(buf.getvalue())

    times = []
    for _ in range(args.repeat):
        rc, dt, s = timed(["--no-closed-loop"])
        times.append(dt)
    eff = ", ".join(f"{e['name']} {json.dumps(e['parameters'])}" for e in s["effects"]) or "none"
    print(f"identify (no closed loop): {min(times):.2f} s best, {max(times):.2f} s worst of {args.repeat} "
          f"(budget 30 s) -> {'OK' if max(times) < 30 else 'OVER BUDGET'}; exit {rc}; effects: {eff}")
    if args.closed_loop:
        rc, dt, s = timed([])
        cl = s.get("closed_loop") or {}
        b, a = cl.get("before", {}), cl.get("after", {})
        print(f"identify with closed-loop before/after (2 x {cl.get('duration_s', 0):g} s simulated): {dt:.2f} s; "
              f"e_M {b.get('e_M_um', float('nan')):.2f} -> {a.get('e_M_um', float('nan')):.2f} um")
    print("rerun: python benchmarks/bench_ident.py [--repeat N] [--closed-loop] [--effect NAME]")
    return 0 if max(times) < 30 else 1


if __name__ == "__main__":
    sys.exit(main())
