"""Benchmark: the loop process's peak memory and its start, for runs of different lengths.

Rerun:  python benchmarks/bench_memory.py [--config configs/gantry.yaml] [--seconds 40 60 600]

Each run is ``motorctl run CONFIG --duration S --log TMP`` as a new process on the wall clock
(the config's real-time policy: SCHED_FIFO and mlockall where the machine grants them). Printed
per run: the process's peak RSS (``ru_maxrss`` of the loop process from wait4; the child that
drains the record ring to the log is not counted, it is not locked), the time from the start
of the process to its "running" line (imports, build, the compiled kernels from numba's cache,
the real-time set-up and the driver's activation), the rows in the log and the overruns. Memory
is flat with run length when the peaks agree (the record ring holds
:data:`motorctl.app.job.RING_S` seconds; rows leave it for the log while the run goes).
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import tempfile
import time


def one(config: str, seconds: float) -> dict:
    with tempfile.TemporaryDirectory(prefix="motorctl-bench-memory-") as tmp:
        log = os.path.join(tmp, "run.mclog")
        t0 = time.monotonic()
        p = subprocess.Popen([sys.executable, "-m", "motorctl", "run", config, "--duration", str(seconds),
                              "--log", log], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        first = p.stdout.readline()
        t_start = time.monotonic() - t0
        rest = p.stdout.read()
        err = p.stderr.read()
        _, status, usage = os.wait4(p.pid, 0)
        p.returncode = os.waitstatus_to_exitcode(status)
        from motorctl.recorder.runlog import open_log
        rows = open_log(log).n_rows if os.path.exists(log) else 0
    m = re.search(r"overruns (\d+)", rest)
    return {"seconds": seconds, "rss_mb": usage.ru_maxrss / 1024.0, "start_s": t_start,
            "rows": rows, "overruns": int(m.group(1)) if m else -1, "exit": p.returncode,
            "first_line": first.strip(), "stderr": err.strip()[-300:]}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--config", default="configs/gantry.yaml")
    ap.add_argument("--seconds", type=float, nargs="+", default=[40.0, 60.0])
    args = ap.parse_args(argv)
    print(f"load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} CPUs; {args.config}")
    res = [one(args.config, s) for s in args.seconds]
    for r in res:
        print(f"run {r['seconds']:g} s: loop process peak RSS {r['rss_mb']:.1f} MB, 'running' after "
              f"{r['start_s']:.2f} s, {r['rows']} rows logged, overruns {r['overruns']}, exit {r['exit']}"
              + (f" ({r['stderr']})" if r["exit"] not in (0, 1) else ""))
    if len(res) > 1:
        lo, hi = min(r["rss_mb"] for r in res), max(r["rss_mb"] for r in res)
        print(f"peak RSS spread over the run lengths: {100.0 * (hi - lo) / lo:.1f} %")
    print("rerun: python benchmarks/bench_memory.py [--config C] [--seconds S ...]")
    return 0


if __name__ == "__main__":
    sys.exit(main())
