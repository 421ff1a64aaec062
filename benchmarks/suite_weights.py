"""The test files' own time in a full run, from pytest's ``--durations=0`` report: the table
``FILE_SECONDS`` of tests/conftest.py (xdist hands the files out longest first), and with ``-v``
output the time each xdist worker spent (how evenly the two ended).

    .venv/bin/python -m pytest -q -v --durations=0 2>&1 | tee /tmp/durations.txt
    python benchmarks/suite_weights.py /tmp/durations.txt [--top 30] [--write tests/file_seconds.json]

Prints the files' sums (set-up + call + tear-down of their tests) [s], longest first (with
``--write``: into that JSON file, the table tests/conftest.py orders the files by), the slowest
single entries, and per worker (``[gwN] ... PASSED`` lines of
``-v``) its files and busy time. ``--simulate COMPILE_S``: two workers taking whole files in
xdist's default order (most tests first) with both waiting COMPILE_S for the session's compile,
against the order of tests/file_seconds.json with the plugin file not waiting (a model: no
prefetch, no contention; the files' times as reported, the first set-ups' waits left out). The set-up of a worker's first module also holds the wait for the
session's compile (tests/conftest.py ``warm_numba_cache``): printed apart, not counted to the file.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from collections import defaultdict
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

DURATION = re.compile(r"^([0-9.]+)s (setup|call|teardown)\s+(\S+)")
WORKER = re.compile(r"^\[(gw\d+)\].*?(?:PASSED|FAILED|ERROR|SKIPPED|XFAIL|XPASS)\s+(\S+)")


def parse(text: str):
    """(entries [(seconds, phase, nodeid)], nodeid -> worker)."""
    entries, worker = [], {}
    for line in text.splitlines():
        m = DURATION.match(line)
        if m:
            entries.append((float(m[1]), m[2], m[3]))
            continue
        m = WORKER.match(line)
        if m:
            worker[m[2]] = m[1]
    return entries, worker


def _model(order, seconds, compile_s, own=()) -> list[float]:
    """Two workers, each taking the next whole file when free; a file not in ``own`` starts no
    earlier than ``compile_s``. Returns the workers' end times [s]."""
    free = [0.0, 0.0]
    for f in order:
        w = free.index(min(free))
        start = free[w] if f in own else max(free[w], compile_s)
        free[w] = start + seconds.get(f, 0.0)
    return free


def simulate(per_file, worker, compile_s) -> None:
    """Print the model's end times for xdist's default order and the longest-first one."""
    count = defaultdict(int)
    for nodeid in worker:
        count[nodeid.split("::", 1)[0]] += 1
    files = sorted(count)
    table = json.loads((REPO / "tests" / "file_seconds.json").read_text())
    default = sorted(files, key=lambda f: -count[f])
    longest = sorted(files, key=lambda f: -table.get(f, 100.0))
    before = _model(default, per_file, compile_s)
    after = _model(longest, per_file, compile_s, own={"tests/test_effect_entry_points.py"})
    print(f"\nmodel, session compile {compile_s:.0f} s: most tests first, all wait: workers end at "
          f"{before[0]:.0f} / {before[1]:.0f} s; longest first, the plugin file not waiting: "
          f"{after[0]:.0f} / {after[1]:.0f} s (sum of the files {sum(per_file.values()):.0f} s)")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("report", help="pytest's output with --durations=0 (and -v for the workers)")
    ap.add_argument("--top", type=int, default=30, help="the slowest entries to list")
    ap.add_argument("--simulate", type=float, metavar="COMPILE_S",
                    help="model the two orders with a session compile of this many seconds")
    ap.add_argument("--write", metavar="JSON", help="write the files' sums into this file (tests/file_seconds.json)")
    args = ap.parse_args(argv)
    entries, worker = parse(open(args.report).read())
    if not entries:
        print(f"{args.report}: no --durations lines", file=sys.stderr)
        return 2
    per_file = defaultdict(float)
    wait = {}
    firsts = {}
    for nodeid in worker:                      # the worker's first module: its set-up waited
        firsts.setdefault(worker[nodeid], nodeid)
    first_nodes = set(firsts.values())
    for s, phase, nodeid in entries:
        f = nodeid.split("::", 1)[0]
        if phase == "setup" and nodeid in first_nodes:
            wait[nodeid] = s
            continue
        per_file[f] += s
    total = sum(s for s, _, _ in entries)
    print(f"sum of the durations: {total:.1f} s over {len(per_file)} files")
    for nodeid, s in wait.items():
        print(f"first set-up of {worker[nodeid]} ({nodeid}): {s:.1f} s (the session's compile, not counted)")
    print(f"\nslowest {args.top}:")
    for s, phase, nodeid in sorted(entries, reverse=True)[:args.top]:
        print(f"  {s:7.2f} s {phase:8s} {nodeid}")
    if worker:
        busy, files = defaultdict(float), defaultdict(list)
        for s, _, nodeid in entries:
            if nodeid in worker:
                busy[worker[nodeid]] += s
        for f in per_file:
            ws = {worker[n] for n in worker if n.startswith(f + "::")}
            for w in ws:
                files[w].append(f)
        print("\nper worker (busy time, incl. the waits):")
        for w in sorted(busy):
            print(f"  {w}: {busy[w]:.1f} s, {len(files[w])} files")
    for path in sorted((REPO / "tests").glob("test_*.py")):     # all its durations hidden (< 5 ms)
        per_file.setdefault(f"tests/{path.name}", 0.0)
    if args.simulate is not None:
        if not worker:
            print(f"{args.report}: --simulate needs the -v lines (the tests of each file)", file=sys.stderr)
            return 2
        simulate(per_file, worker, args.simulate)
    table = {f: round(s, 1) for f, s in sorted(per_file.items(), key=lambda kv: -kv[1])}
    print("\nfiles, longest first [s]:")
    for f, s in table.items():
        print(f"  {s:7.1f} {f}")
    if args.write:
        with open(args.write, "w") as fh:
            json.dump(table, fh, indent=0)
            fh.write("\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
