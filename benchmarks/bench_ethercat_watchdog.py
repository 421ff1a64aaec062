"""Benchmark: does the SM watchdog trip on this host's stalls? ``motorctl run`` of
configs/gantry-ethercat.yaml on the wall clock at 5 kHz against the emulated segment (a veth pair
in a network namespace this script makes; root), RUNS runs of SECONDS each per watchdog setting;
per run: whether a slave's SM watchdog tripped (the emulator's ``SM watchdog`` line), the exit
code, the loop's turnaround maximum and its overruns (periods missed: the stalls), from the loop line.

    sudo .venv/bin/python benchmarks/bench_ethercat_watchdog.py                 # 10 and 50 ms, 5 x 3 s
    sudo .venv/bin/python benchmarks/bench_ethercat_watchdog.py 10 50 200 --runs 3 --seconds 5

The figures behind the SM watchdog table of docs/drivers.md.
"""

from __future__ import annotations

import argparse
import re
import sys
import tempfile
from pathlib import Path

import yaml

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))
from harness import Emulator, NetNamespace, run_cli  # noqa: E402

VETH = ("ecb0", "ecb0-slave")


def one_run(tmp: Path, watchdog_ms: float, seconds: float) -> dict:
    d = yaml.safe_load((REPO / "configs" / "gantry-ethercat.yaml").read_text())
    d["driver"].update(ifname=VETH[0], watchdog_ms=watchdog_ms)
    cfg = tmp / f"wd{watchdog_ms:g}.yaml"
    cfg.write_text(yaml.safe_dump(d, sort_keys=False))
    with NetNamespace(veth=VETH) as ns, Emulator("ethercat", cfg, plant=REPO / "configs" / "gantry.yaml",
                                                 prefix=ns.prefix) as emu:
        r = run_cli(["run", str(cfg), "--duration", f"{seconds:g}", "--log", str(tmp / "run.mlog")],
                    prefix=ns.prefix, timeout_s=120 + seconds)
        err = emu.stderr()
    turn = re.search(r"max ([\d.]+) us; lateness", r.stdout)
    over = re.search(r"overruns (\d+)", r.stdout)
    return {"trips": len(re.findall(r"SM watchdog", err)), "exit": r.returncode,
            "turnaround_max_ms": round(float(turn.group(1)) / 1e3, 1) if turn else None,
            "overruns": int(over.group(1)) if over else None}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("watchdog_ms", nargs="*", type=float, default=[10.0, 50.0])
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--seconds", type=float, default=3.0)
    a = ap.parse_args()
    with tempfile.TemporaryDirectory() as t:
        for wd in a.watchdog_ms:
            rows = [one_run(Path(t), wd, a.seconds) for _ in range(a.runs)]
            tripped = sum(1 for r in rows if r["trips"])
            print(f"watchdog {wd:g} ms: {tripped} of {a.runs} runs tripped it; exit codes "
                  f"{[r['exit'] for r in rows]}; turnaround max {[r['turnaround_max_ms'] for r in rows]} ms; "
                  f"overruns {[r['overruns'] for r in rows]}",
                  flush=True)


if __name__ == "__main__":
    main()
