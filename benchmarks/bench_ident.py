"""Benchmark of ``motorctl identify`` on a 20 s run log at 5 kHz: wall time with start-up
(budget 4 s).

Rerun:
    python benchmarks/bench_ident.py              # generates the log once into /tmp, times identify
    python benchmarks/bench_ident.py --repeat 5 --effect stribeck --keep-log /tmp/x.log

What is timed: ``motorctl identify LOG --json`` as a new process, end to end (Python start-up,
imports, reading, IDIM-LS, the effect search over every family with forward selection and
backward elimination, simulation fit %, residual verdict, JSON), once with the closed-loop
before/after (two simulated C2 runs of 8 s in one worker forked at start, fed the nominal fit and
the model found so far while the effect search goes on)
and once with ``--no-closed-loop``; the median of ``--repeat`` runs. Wall-clock seconds on this
machine: other processes inflate them, so the load average and the CPU time are printed too.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

#: wall time with start-up [s] that identify must stay within on the 20 s, 5 kHz log
BUDGET_S = 4.0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--duration", type=float, default=20.0, help="log length [s] (default 20)")
    ap.add_argument("--effect", default="cogging", help="undeclared effect on the plant (synth.EXAMPLES key)")
    ap.add_argument("--repeat", type=int, default=3, help="runs of each mode (median; default 3)")
    ap.add_argument("--keep-log", default="/tmp/motorctl_bench_ident_20s.log",
                    help="log path (reused when it exists)")
    ap.add_argument("--closed-loop", action="store_true",
                    help="accepted for old command lines: both modes are always timed")
    args = ap.parse_args(argv)

    from motorctl.commission.tune import make_log
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

    import resource
    import statistics
    import subprocess

    cmd = [sys.executable, "-c", "import sys; from motorctl.cli import main; sys.exit(main())", "identify", path,
           "--json"]

    def timed(extra):
        r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
        t0 = time.perf_counter()
        out = subprocess.run(cmd + extra, capture_output=True, text=True, check=False)
        dt = time.perf_counter() - t0
        r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
        cpu = (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime)
        return out.returncode, dt, cpu, (json.loads(out.stdout) if out.returncode == 0 else {"error": out.stderr})

    worst = 0.0
    for label, extra in (("with the closed loop", []), ("--no-closed-loop", ["--no-closed-loop"])):
        runs = [timed(extra) for _ in range(args.repeat)]
        rc, _, _, s = runs[-1]
        wall = statistics.median(r[1] for r in runs)
        cpu = statistics.median(r[2] for r in runs)
        worst = max(worst, wall)
        eff = ", ".join(f"{e['name']} {json.dumps(e['parameters'])}" for e in s.get("effects", [])) or "none"
        print(f"identify {label}: median {wall:.2f} s wall with start-up ({min(r[1] for r in runs):.2f} .. "
              f"{max(r[1] for r in runs):.2f} over {args.repeat}), {cpu:.2f} s CPU; budget {BUDGET_S:g} s -> "
              f"{'OK' if wall <= BUDGET_S else 'OVER BUDGET'}; exit {rc}; effects: {eff}")
        cl = s.get("closed_loop") or {}
        if cl:
            b, a = cl.get("before", {}), cl.get("after", {})
            print(f"  closed loop (2 x {cl.get('duration_s', 0):g} s simulated): e_M {b.get('e_M_um', float('nan')):.2f} "
                  f"-> {a.get('e_M_um', float('nan')):.2f} um")
    print(f"load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} CPUs")
    print("rerun: python benchmarks/bench_ident.py [--repeat N] [--effect NAME]")
    return 0 if worst <= BUDGET_S else 1


if __name__ == "__main__":
    sys.exit(main())
