"""The daemon's state machine soaked: tests/test_daemon_stateful.py's random requests and injected
faults (drive faults, following-error trips, underruns and recorder stalls by SIGSTOP of the I/O
process, a killed helper) against the shipped daemon, for as many steps as asked, with the same
invariants checked after every step. The suite runs a few hundred steps; this runs many more.
Prints the steps, the examples, the wall time and the verdict (any invariant violation fails the
run with hypothesis's shrunk example).

Rerun:
    python benchmarks/soak_stateful.py --steps 50000 [--per-example 100] [--hogs 4]
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
HOG = "import time\nend = time.monotonic() + {s}\nwhile time.monotonic() < end: pass\n"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--steps", type=int, default=50000, help="steps in all (default 50000)")
    ap.add_argument("--per-example", type=int, default=100, help="steps per example (default 100)")
    ap.add_argument("--hogs", type=int, default=0, help="CPU-bound processes beside it (default 0)")
    a = ap.parse_args()
    examples = max(1, a.steps // a.per_example)
    # hypothesis draws each example's length up to --per-example: the floor is a third of --steps
    env = dict(os.environ, MOTORCTL_STATEFUL_EXAMPLES=str(examples),
               MOTORCTL_STATEFUL_STEPS=str(a.per_example),
               MOTORCTL_STATEFUL_MIN_STEPS=str(a.steps // 3))
    hogs = [subprocess.Popen([sys.executable, "-c", HOG.format(s=24 * 3600)]) for _ in range(a.hogs)]
    t0 = time.monotonic()
    try:
        p = subprocess.run([sys.executable, "-m", "pytest", "-q", "-s", "-n", "0", "-p", "no:randomly",
                            "tests/test_daemon_stateful.py::test_random_requests_and_faults_keep_the_machine_in_its_table"],
                           cwd=REPO, env=env, capture_output=True, text=True)
    finally:
        for h in hogs:
            h.kill()
    wall = time.monotonic() - t0
    tail = "\n".join(p.stdout.strip().splitlines()[-3:])
    taken = next((int(ln.split()[2]) for ln in p.stdout.splitlines() if ln.startswith("state machine: ")), 0)
    print(f"state machine soak: {examples} examples of at most {a.per_example} steps: {taken} steps taken, "
          f"{a.hogs} CPU hogs beside, {wall:.0f} s ({taken / wall:.1f} steps/s); "
          f"verdict: {'0 invariant violations' if p.returncode == 0 else 'FAILED'}")
    if p.returncode:
        print(p.stdout[-6000:])
    else:
        print(tail)
    return p.returncode


if __name__ == "__main__":
    sys.exit(main())
