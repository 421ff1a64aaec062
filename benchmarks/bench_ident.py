"""Benchmark of ``motorctl identify`` on a 20 s run log at 5 kHz: wall and CPU time with
start-up, without the closed-loop check (budget 2 s wall) and with it (budget 4 s wall), on an
idle 2-core machine.

Rerun:
    python benchmarks/bench_ident.py              # generates the log once into /tmp, times identify
    python benchmarks/bench_ident.py --repeat 5 --effect stribeck --keep-log /tmp/x.log
    git archive main | tar -x -C /tmp/motorctl-main
    python benchmarks/bench_ident.py --ref-src /tmp/motorctl-main    # and main's, in the same run

What is timed: ``motorctl identify LOG --json`` as a new process, end to end (Python start-up,
imports from compiled bytecode and numba's kernels from its cache, as an installed package has
them: an untimed run fills each tree's cache first; reading, IDIM-LS, the effect search over
every family with forward selection and backward elimination, simulation fit %, residual
verdict, JSON), once with the closed-loop before/after (two simulated C2 runs of 8 s
in one worker forked at start: *before* with the nominal fit while the effect search goes on,
*after* once it is done) and once with ``--no-closed-loop``; the median of ``--repeat`` runs.
CPU is user + system of the process and its children (both search threads, and the closed
loop's worker when it runs). Wall-clock seconds on this machine: other
processes inflate them, so the load average is printed, and with ``--ref-src`` the same runs of
another source tree (e.g. main) alternate with this tree's, and the ratios of the medians are
printed: on a loaded machine those and the CPU seconds are what compare.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

#: wall time with start-up [s] that identify must stay within on the 20 s, 5 kHz log, without
#: and with the closed-loop check
BUDGET_S = {"--no-closed-loop": 2.0, "with the closed loop": 4.0}
#: the source tree this script belongs to
HERE = Path(__file__).resolve().parents[1]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--duration", type=float, default=20.0, help="log length [s] (default 20)")
    ap.add_argument("--effect", default="cogging", help="undeclared effect on the plant (synth.EXAMPLES key)")
    ap.add_argument("--config", default=str(HERE / "configs" / "gantry.yaml"),
                    help="the plant (default configs/gantry.yaml: the default plant, with its structural mode, "
                         "current loop, encoder noise and stiction)")
    ap.add_argument("--repeat", type=int, default=3, help="runs of each mode (median; default 3)")
    ap.add_argument("--keep-log", default=None,
                    help="log path (reused when it exists with the same effect and length; default "
                         "/tmp/motorctl_bench_ident_<duration>s_<config>_<effect>.log)")
    ap.add_argument("--closed-loop", action="store_true",
                    help="accepted for old command lines: both modes are always timed")
    ap.add_argument("--ref-src", default=None,
                    help="also time this source tree (e.g. an export of main), alternating with this one")
    args = ap.parse_args(argv)
    if args.ref_src and not (Path(args.ref_src) / "motorctl").is_dir():
        ap.error(f"--ref-src {args.ref_src}: no motorctl package there")

    from motorctl.commission.tune import make_log
    from motorctl.ident.synth import EXAMPLES
    from motorctl.recorder.runlog import read_log

    path = args.keep_log or f"/tmp/motorctl_bench_ident_{args.duration:g}s_{Path(args.config).stem}_{args.effect}.log"
    regenerate = True
    if os.path.exists(path):
        log = read_log(path)
        truth = log.header.get("driver", {}).get("simulated", {}).get("X", {})
        want = EXAMPLES[args.effect]
        same = (truth.get("input_delay_s") == want["input_delay_s"]) if "input_delay_s" in want \
            else all(truth.get("effects", {}).get(k) == v for k, v in want.items())
        # a log of D s holds a few samples more than D/period (the run's first and last cycles)
        regenerate = abs(log.data.shape[0] * log.header["period_s"] - args.duration) > 5 * log.header["period_s"] \
            or not same
    if regenerate:
        t0 = time.perf_counter()
        make_log(path, EXAMPLES[args.effect], duration_s=args.duration, seed=1, noise_N=None, base=args.config)
        print(f"generated {path}: {args.duration:g} s at 5 kHz of {args.config} with {args.effect} in "
              f"{time.perf_counter() - t0:.1f} s")
    log = read_log(path)
    n = log.data.shape[0]
    print(f"log: {path}, {n} samples ({n * log.header['period_s']:.1f} s at {1 / log.header['period_s']:.0f} Hz), "
          f"effect {args.effect}; load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} CPUs")

    import resource
    import statistics
    import subprocess

    def timed(src, extra):
        """(exit code, wall [s], CPU [s], summary) of one identify run on the source tree src."""
        env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(src)] + [v for v in [os.environ.get("PYTHONPATH")] if v]))
        cmd = [sys.executable, "-c", "import sys; from motorctl.cli import main; sys.exit(main())", "identify",
               str(Path(path).resolve()), "--json"] + extra
        r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
        t0 = time.perf_counter()
        out = subprocess.run(cmd, capture_output=True, text=True, check=False, cwd=str(src), env=env)
        dt = time.perf_counter() - t0
        r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
        cpu = (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime)
        return out.returncode, dt, cpu, (json.loads(out.stdout) if out.returncode == 0 else {"error": out.stderr})

    trees = [("this tree", HERE)] + ([("reference", Path(args.ref_src).resolve())] if args.ref_src else [])
    # the modules' bytecode, as an installed motorctl has it (pip compiles at install, and an
    # editable install writes it at its first run): with PYTHONDONTWRITEBYTECODE set and no
    # __pycache__, every run would compile motorctl's modules again (0.1-0.2 s)
    import compileall
    for _, src in trees:
        for pkg in ("motorctl", "motorctl_drivers", "motorctl_emulators"):
            if (src / pkg).is_dir():
                compileall.compile_dir(str(src / pkg), quiet=1)
    print(f"bytecode of motorctl compiled ahead in {', '.join(str(s) for _, s in trees)} "
          f"(PYTHONDONTWRITEBYTECODE={os.environ.get('PYTHONDONTWRITEBYTECODE', 'unset')} in this shell)")
    # numba's kernel cache, as after ``motorctl warmup``: the cache folder is keyed by the sources,
    # so a tree's first closed-loop run after an edit compiles the loop (30-50 s), not timed
    for _, src in trees:
        timed(src, ["--closed-loop-duration", "0.01"])
    print("numba's kernel cache of each tree filled by an untimed closed-loop run")
    over = False
    for label, extra in (("--no-closed-loop", ["--no-closed-loop"]), ("with the closed loop", [])):
        runs = {name: [] for name, _ in trees}
        for _ in range(args.repeat):               # alternate the trees: the same load on both
            for name, src in trees:
                runs[name].append(timed(src, extra))
        med = {}
        for name, _ in trees:
            rr = runs[name]
            rc, _, _, s = rr[-1]
            wall = statistics.median(r[1] for r in rr)
            cpu = statistics.median(r[2] for r in rr)
            med[name] = (wall, cpu)
            budget = BUDGET_S[label]
            if name == "this tree":
                over |= wall > budget
            eff = ", ".join(f"{e['name']} {json.dumps(e['parameters'])}" for e in s.get("effects", [])) or "none"
            print(f"identify {label} ({name}): median {wall:.2f} s wall with start-up "
                  f"({min(r[1] for r in rr):.2f} .. {max(r[1] for r in rr):.2f} over {args.repeat}), "
                  f"{cpu:.2f} s CPU (user + sys, all threads and children); budget {budget:g} s wall -> "
                  f"{'OK' if wall <= budget else 'OVER BUDGET'}; exit {rc}; effects: {eff}")
            cl = s.get("closed_loop") or {}
            if cl:
                b, a = cl.get("before", {}), cl.get("after", {})
                print(f"  closed loop (2 x {cl.get('duration_s', 0):g} s simulated): e_M "
                      f"{b.get('e_M_um', float('nan')):.2f} -> {a.get('e_M_um', float('nan')):.2f} um")
        if args.ref_src:
            (w1, c1), (w0, c0) = med["this tree"], med["reference"]
            print(f"  ratio this tree / reference: wall {w1 / w0:.2f}, CPU {c1 / c0:.2f}")
    print(f"load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} CPUs")
    print("rerun: python benchmarks/bench_ident.py [--repeat N] [--effect NAME] [--ref-src DIR]")
    return 1 if over else 0


if __name__ == "__main__":
    sys.exit(main())
