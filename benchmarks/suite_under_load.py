"""The README's test command N times in a row, some of them beside CPU-spinning processes, with the
verdict and the wall time of each run: does the suite give the same verdict whatever the load?

    python benchmarks/suite_under_load.py --runs 10 --loaded 5 --spinners 2 --fresh-clone --keep-output /tmp/sul
    python benchmarks/suite_under_load.py --runs 1 -- tests/test_config.py      # a quick try

Each run is the README's test command: with ``--fresh-clone`` in a new clone of this repository's
HEAD (committed work only; made in a new folder beside this checkout, with a link to this
checkout's ``../shared`` beside the clone, as CI has it), ``python3 -m venv .venv && .venv/bin/pip
install -q -e ".[test]" && .venv/bin/python -m pytest -q``; without it, ``.venv/bin/python -m
pytest -q`` in this checkout (its venv must exist). Arguments after ``--`` go to pytest. The last
``--loaded`` runs have ``--spinners`` processes beside them that spin on the CPU (two on a 2-core
machine keep both cores busy); they are started before the run and killed after it. Every run is
bounded by ``--timeout-s``. Prints one line per run (pytest's closing line, the exit code, the wall
time) and a summary; exits 0 when every run was green.
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def _spin() -> None:  # pragma: no cover  (a background load; killed by the parent)
    x = 0
    while True:
        x += 1


def _closing_line(out: str) -> str:
    """pytest's closing line ('627 passed in 380.20s', with failures and errors), or ''."""
    for line in reversed(out.splitlines()):
        s = line.strip().strip("=").strip()
        if " in " in s and any(w in s for w in ("passed", "failed", "error", "no tests ran")):
            return s
    return ""


def _failures(out: str) -> list[str]:
    """pytest's short summary lines of failed and erroring tests (``-ra`` prints them)."""
    return [ln.strip() for ln in out.splitlines() if ln.startswith(("FAILED ", "ERROR "))]


def one_run(pytest_args: list[str], fresh_clone: bool, timeout_s: float) -> tuple[int, str, float, list[str], str]:
    """One run of the test command: (exit code, pytest's closing line, wall time [s], the
    failed tests' summary lines, the whole output)."""
    t0 = time.monotonic()
    clone = None
    try:
        if fresh_clone:
            clone = Path(tempfile.mkdtemp(prefix=".suite-clone-", dir=REPO.parent))
            clone.chmod(0o755)          # mkdtemp's 0700 would keep the tests' 'nobody' out of the venv
            subprocess.run(["git", "clone", "-q", str(REPO), str(clone / "motorctl")], check=True, timeout=300)
            if (REPO.parent / "shared").is_dir():          # ../shared of the clone, as CI has it
                (clone / "shared").symlink_to(REPO.parent / "shared")
            where = clone / "motorctl"
            cmd = (f'python3 -m venv .venv && .venv/bin/pip install -q -e ".[test]" && '
                   f'.venv/bin/python -m pytest -q {" ".join(pytest_args)}')
        else:
            where = REPO
            cmd = f'.venv/bin/python -m pytest -q {" ".join(pytest_args)}'
        env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
        try:
            r = subprocess.run(["bash", "-c", cmd], cwd=where, env=env, capture_output=True, text=True,
                               timeout=timeout_s)
            code, out = r.returncode, r.stdout + r.stderr
        except subprocess.TimeoutExpired as exc:
            code, out = -1, f"timed out after {timeout_s:g} s\n{exc.stdout or ''}"
        lines = out.strip().splitlines()
        verdict = _closing_line(out) or (lines[-1] if lines else "")
        return code, verdict, time.monotonic() - t0, _failures(out), out
    finally:
        if clone is not None:
            shutil.rmtree(clone, ignore_errors=True)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=1, help="runs in a row (default 1)")
    ap.add_argument("--loaded", type=int, default=0, help="how many of them (the last) run beside the spinners")
    ap.add_argument("--spinners", type=int, default=2, help="CPU-spinning processes beside a loaded run (default 2)")
    ap.add_argument("--fresh-clone", action="store_true", help="each run in a new clone of HEAD, venv included")
    ap.add_argument("--timeout-s", type=float, default=1800.0, help="bound of one run [s] (default 1800)")
    ap.add_argument("--keep-output", metavar="DIR", default=None,
                    help="write the whole output of each failed run to DIR/suite-run-N.txt")
    ap.add_argument("pytest_args", nargs="*", help="after --: arguments for pytest")
    a = ap.parse_args(argv)
    if a.runs < 1 or not 0 <= a.loaded <= a.runs or a.spinners < 0:
        ap.error("need --runs >= 1, 0 <= --loaded <= --runs, --spinners >= 0")
    print(f"{a.runs} run(s) of the README's test command{' (fresh clone each)' if a.fresh_clone else ''}, "
          f"the last {a.loaded} beside {a.spinners} spinning process(es); {os.cpu_count()} CPU(s)", flush=True)
    results = []
    for k in range(a.runs):
        loaded = k >= a.runs - a.loaded
        spinners = [mp.Process(target=_spin, daemon=True) for _ in range(a.spinners if loaded else 0)]
        for p in spinners:
            p.start()
        try:
            code, verdict, wall, failed, out = one_run(a.pytest_args, a.fresh_clone, a.timeout_s)
        finally:
            for p in spinners:
                p.kill()
                p.join(timeout=5)
        results.append((loaded, code, wall))
        print(f"run {k + 1}/{a.runs} ({'loaded' if loaded else 'idle'}): exit {code}: {verdict} | wall {wall:.1f} s",
              flush=True)
        for line in failed:
            print(f"    {line}", flush=True)
        if code != 0 and a.keep_output:
            path = Path(a.keep_output) / f"suite-run-{k + 1}.txt"
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(out)
            print(f"    pytest's whole output: {path}", flush=True)
    green = sum(1 for _, c, _ in results if c == 0)
    for what, sel in (("idle", False), ("loaded", True)):
        walls = [w for ld, _, w in results if ld == sel]
        if walls:
            print(f"{what}: median wall {statistics.median(walls):.1f} s over {len(walls)} run(s)")
    print(f"{green} of {len(results)} runs green")
    return 0 if green == len(results) else 1


if __name__ == "__main__":
    sys.exit(main())
