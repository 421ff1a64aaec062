"""Benchmark: the daemon at 5 kHz with X and Y on C2 for 10^6 cycles (200 s), with SCHED_FIFO
and without. Reports turnaround and lateness p50/p99/p99.9/max and the cycles that overran,
from the run log the daemon wrote. It drives the real daemon through the CLI with the test
suite's daemon helpers, so it runs under pytest (not part of the test suite):

    python -m pytest benchmarks/bench_daemon.py -s                                  # both, ~7 min
    MOTORCTL_BENCH_CYCLES=100000 MOTORCTL_BENCH_CPU=0 python -m pytest benchmarks/bench_daemon.py -s

Figures go to stdout and to ``bench-daemon-<policy>.json`` in the pytest tmp dir; the last
measured ones are quoted in docs/daemon.md."""

from __future__ import annotations

import json
import os
import struct
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from test_daemon_helpers import Daemon, ctl, make_config, status, wait_for  # noqa: E402

from motorctl.recorder.runlog import MAGIC

CYCLES = int(os.environ.get("MOTORCTL_BENCH_CYCLES", "1000000"))
CPU = int(os.environ.get("MOTORCTL_BENCH_CPU", "1"))


def _columns(path, names):
    """Columns of a (large) run log through a memory map, without loading every column."""
    with open(path, "rb") as fh:
        fh.seek(len(MAGIC))
        (hlen,) = struct.unpack("<Q", fh.read(8))
        header = json.loads(fh.read(hlen).decode())
    cols = header["columns"]
    off = len(MAGIC) + 8 + hlen
    w = len(cols)
    n = (os.path.getsize(path) - off) // (8 * w)
    mm = np.memmap(path, dtype="<f8", mode="r", offset=off, shape=(n, w))
    return {c: np.array(mm[:, cols.index(c)]) for c in names}, header


def _figures(x_ns):
    return {f"p{q:g}_us": float(np.percentile(x_ns, q)) / 1000 for q in (50, 99, 99.9)} | {
        "max_us": float(x_ns.max()) / 1000}


@pytest.mark.parametrize("policy", ["required", "off"])
def test_bench_two_axes_c2_5khz(tmp_path, policy):
    cfg = make_config(tmp_path, policy=policy)
    d = yaml.safe_load(cfg.read_text())
    d["loop"]["realtime"]["cpu"] = CPU
    d["daemon"]["event_before_s"] = 0.5
    cfg.write_text(yaml.safe_dump(d))
    dm = Daemon(cfg, tmp_path / "motorctl.sock")
    try:
        dm.wait_ready()
        assert ctl(dm.sock, "start", "X", "--controller", "c2").returncode == 0
        assert ctl(dm.sock, "start", "Y", "--controller", "c2").returncode == 0
        c0 = status(dm.sock)["loop"]["cycles"]
        wait_for(lambda: status(dm.sock)["loop"]["cycles"] >= c0 + CYCLES, CYCLES / 5000 * 3 + 60,
                 f"{CYCLES} cycles", interval=1.0)
        st = status(dm.sock)
        code, _, err = dm.terminate(timeout=60)
        assert code == 0, err
    finally:
        dm.kill()
    cols, header = _columns(st["log"]["path"], ["turnaround_ns", "lateness_ns", "overruns", "read_ns",
                                                "control_ns", "write_ns", "X.enabled", "Y.enabled",
                                                "X.fault_bits", "Y.fault_bits"])
    both = (cols["X.enabled"] > 0) & (cols["Y.enabled"] > 0)
    sel = np.flatnonzero(both)
    a, b = sel[0], sel[0] + CYCLES
    turn, late = cols["turnaround_ns"][a:b], cols["lateness_ns"][a:b]
    ovr = cols["overruns"][a:b]
    period_ns = 1e9 / 5000
    res = {
        "policy": policy, "cpu": CPU, "realtime": header.get("realtime"),
        "cycles": int(b - a),
        "turnaround": _figures(turn), "lateness": _figures(late),
        "read_us_p99.9": float(np.percentile(cols["read_ns"][a:b], 99.9)) / 1000,
        "control_us_p99.9": float(np.percentile(cols["control_ns"][a:b], 99.9)) / 1000,
        "write_us_p99.9": float(np.percentile(cols["write_ns"][a:b], 99.9)) / 1000,
        "missed_periods": int(ovr[-1] - ovr[0]),
        "cycles_that_overran": int(np.count_nonzero(np.diff(ovr) > 0)),
        "cycles_turnaround_over_period": int(np.count_nonzero(turn > period_ns)),
        "faults": int(np.count_nonzero(cols["X.fault_bits"][a:b]) + np.count_nonzero(cols["Y.fault_bits"][a:b])),
        "log_max_flush_gap_s": st["log"]["max_flush_gap_s"], "lost_rows": st["log"]["lost_rows"],
    }
    out = json.dumps(res, indent=1)
    print(out)
    (tmp_path.parent / f"bench-daemon-{policy}.json").write_text(out)
    with open("/tmp/motorctl-bench-daemon.jsonl", "a") as fh:
        fh.write(json.dumps(res) + "\n")
    assert res["cycles"] == CYCLES and res["lost_rows"] == 0
