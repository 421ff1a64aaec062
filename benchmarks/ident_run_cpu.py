"""CPU time of the identification itself, single-threaded: ``Identifier.run()`` (nominal fit,
effect search, selection, verdict), ``refit()`` and ``summarise()`` (the JSON, with its
simulation fits) on run logs, for this source tree and, alternating with it, another one.

Rerun:
    python benchmarks/bench_ident.py --keep-log /tmp/cog.log      # a 20 s cogging log, once
    git archive main | tar -x -C /tmp/motorctl-main                 # the reference tree, once
    python benchmarks/ident_run_cpu.py /tmp/cog.log --ref-src /tmp/motorctl-main --repeat 3
    python benchmarks/ident_run_cpu.py /tmp/motorctl-ident-equivalence/stribeck_20s.mclog

Each tree runs in a new process (PYTHONPATH: that tree first) that reads the log (axis X),
identifies it once to warm up (imports, compiled kernels, FFT plans) and then ``--runs`` times
more, with ``motorctl.ident.select.SEARCH_THREADS = 1`` and BLAS on one thread (as
``identify`` runs it: :func:`motorctl.ident.pipeline.identify_record`) so that the process time
is the work itself, not a second thread's share or its waiting; the figure is the median over
``--repeat`` processes per tree, the trees alternating. Process CPU time (``time.process_time``)
moves less with the machine's load than wall time, but not nothing: compare the trees in one
run (the ratio), on an idle machine if you can (the load average is printed).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

#: the source tree this script belongs to
HERE = Path(__file__).resolve().parents[1]

CHILD = r"""
import json, sys, time
import numpy as np
from threadpoolctl import threadpool_limits
import motorctl.ident.select as select
from motorctl.ident.data import load_record
from motorctl.ident.pipeline import summarise
select.SEARCH_THREADS = 1
rec = load_record(sys.argv[1], None, None, "X")
out = []
with np.errstate(all="ignore"), threadpool_limits(limits=1, user_api="blas"):
    for i in range(1 + int(sys.argv[2])):
        t0 = time.process_time()
        idf = select.Identifier(rec).run()
        t1 = time.process_time()
        idf.refitted = idf.refit()
        t2 = time.process_time()
        summarise(idf)
        t3 = time.process_time()
        if i:
            out.append([t1 - t0, t2 - t1, t3 - t2])
print(json.dumps({"cpu": out, "effects": [t.family for t in idf.terms]}))
"""


def measure(src: Path, log: str, runs: int) -> dict:
    """{'cpu': [[run, refit, summarise] s per run], 'effects': [...]} of one process on ``src``."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(src)] + [p for p in [env.get("PYTHONPATH")] if p])
    out = subprocess.run([sys.executable, "-c", CHILD, log, str(runs)], capture_output=True, text=True,
                         env=env, cwd=str(src), check=False)
    if out.returncode != 0:
        raise SystemExit(f"{src}: identification of {log} failed: {out.stderr.strip()[-300:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("logs", nargs="+", help="run logs (axis X)")
    ap.add_argument("--ref-src", default=None, help="also this source tree (e.g. an export of main), alternating")
    ap.add_argument("--repeat", type=int, default=3, help="processes per tree and log (default 3)")
    ap.add_argument("--runs", type=int, default=2, help="timed identifications per process after the warm-up")
    args = ap.parse_args(argv)
    if args.ref_src and not (Path(args.ref_src) / "motorctl").is_dir():
        ap.error(f"--ref-src {args.ref_src}: no motorctl package there")
    for log in args.logs:
        if not Path(log).is_file():
            ap.error(f"{log}: no such file")
    trees = [("this tree", HERE)] + ([("reference", Path(args.ref_src).resolve())] if args.ref_src else [])
    print(f"single-thread CPU (SEARCH_THREADS = 1), median over {args.repeat} processes x {args.runs} runs; "
          f"load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} CPUs")
    for log in args.logs:
        got = {name: [] for name, _ in trees}
        named = {}
        for _ in range(args.repeat):
            for name, src in trees:
                m = measure(src, log, args.runs)
                got[name] += m["cpu"]
                named[name] = m["effects"]
        med = {name: [statistics.median(r[j] for r in rows) for j in range(3)] for name, rows in got.items()}
        print(f"{log}:")
        for name, _ in trees:
            run, refit, summ = med[name]
            print(f"  {name:9s}: run() {run:.3f} s, refit() {refit:.3f} s, summarise() {summ:.3f} s; "
                  f"effects {', '.join(named[name]) or 'none'}")
        if args.ref_src:
            a, b = med["this tree"], med["reference"]
            print("  ratio this tree / reference: run() " + f"{a[0] / b[0]:.3f}"
                  + (f", refit() {a[1] / b[1]:.3f}" if b[1] > 1e-3 else "") + f", summarise() {a[2] / b[2]:.3f}"
                  + f", total {sum(a) / sum(b):.3f}")
    print("rerun: python benchmarks/ident_run_cpu.py LOG [LOG ...] --ref-src DIR [--repeat N]")
    return 0


if __name__ == "__main__":
    sys.exit(main())
