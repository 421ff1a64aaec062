"""The first start against later ones: ``motorctl run CONFIG --virtual-clock --duration 0.01``
with an empty numba cache (``NUMBA_CACHE_DIR`` in a temporary directory: a fresh install),
then again on the cache that run left, and ``motorctl warmup`` on a cold and on the warm
cache. Prints the time to the first line on stderr (the compile notice on a cold cache) and to
the end, per run. ``--breakdown``: then where a cold compile's time goes, kernel by kernel
(``compile_breakdown.py`` on another empty cache: overloads compiled, own and inclusive time).

Rerun:
    python benchmarks/bench_start.py [--config configs/gantry-rigid.yaml] [--breakdown]
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def _timed(argv, env) -> tuple[float, float, str]:
    t0 = time.monotonic()
    p = subprocess.Popen([sys.executable, "-m", "motorctl", *argv], cwd=REPO, env=env,
                         stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    first = p.stderr.readline()
    t_first = time.monotonic() - t0
    p.communicate(timeout=1800)
    return t_first if first else float("nan"), time.monotonic() - t0, first.strip()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default="configs/gantry-rigid.yaml")
    ap.add_argument("--breakdown", action="store_true", help="also the cold compile kernel by kernel")
    args = ap.parse_args()
    print(f"# rerun: python benchmarks/bench_start.py --config {args.config}; load average "
          f"{os.getloadavg()[0]:.1f} at the start")
    run = ["run", args.config, "--virtual-clock", "--duration", "0.01"]
    rows = []
    with tempfile.TemporaryDirectory() as a, tempfile.TemporaryDirectory() as b:
        env_a = {**os.environ, "NUMBA_CACHE_DIR": a}
        env_b = {**os.environ, "NUMBA_CACHE_DIR": b}
        rows.append(("run, cold cache", *_timed(run, env_a)))
        rows.append(("run, warm cache", *_timed(run, env_a)))
        rows.append(("warmup, cold cache", *_timed(["warmup", args.config], env_b)))
        rows.append(("warmup, warm cache", *_timed(["warmup", args.config], env_b)))
        rows.append(("run after warmup", *_timed(run, env_b)))
    print(f"# load average {os.getloadavg()[0]:.1f} at the end")
    print("| start | first stderr line after [s] | done after [s] | first stderr line |")
    print("|---|---|---|---|")
    for name, t1, t2, line in rows:
        print(f"| {name} | {t1:.2f} | {t2:.1f} | {line or '-'} |")
    if args.breakdown:
        with tempfile.TemporaryDirectory() as c:
            sys.stdout.flush()
            subprocess.run([sys.executable, str(REPO / "benchmarks" / "compile_breakdown.py"), args.config],
                           cwd=REPO, env={**os.environ, "NUMBA_CACHE_DIR": c}, timeout=1800, check=True)


if __name__ == "__main__":
    main()
