"""Soak: the daemon for N minutes at 5 kHz on the simulated gantry with a small log budget.

Both axes run their programs; every ``--fault-every`` seconds X gets a NaN injected (a fault
and its event log), is reset and started again. The default cadence (90 s: six faults in ten
minutes) is chosen so that every event window fits: a fault window is 3 s of rows (5.2 MB),
an overrun window 0.2 s (0.34 MB, at most ``max_event_logs`` / 2 of them), and event logs may
hold the budget less two segments (40 MB of 50): at most seven fault windows and ten overrun
windows. A faster cadence shows the other half of the policy: the oldest overrun, then fault
event logs go once event logs alone would break the budget. Every ``--poll`` seconds the script prints the
bytes per second, the bytes kept in ``log_dir`` against the budget (the status figure and a
scan of the directory), the segments and event logs kept, and the daemon's memory (loop and
I/O process RSS). At the end it stops the daemon (SIGTERM) and exports the rotated set
(``motorctl export RUN --mat``/``--csv``) in a child process, printing its peak RSS.

Not part of the test suite. Rerun::

    python benchmarks/soak_daemon.py                  # 10 minutes, 50 MB budget
    python benchmarks/soak_daemon.py --minutes 3 --budget-mb 50 --segment-mb 5
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import yaml

from bench_export import run_child  # (benchmarks/, the script's own folder: on sys.path)

from motorctl.cli.operator import DaemonUnreachable, call

REPO = Path(__file__).resolve().parents[1]
MOTORCTL = [sys.executable, "-m", "motorctl"]


def _status(sock: str) -> dict:
    ans = call(sock, {"cmd": "status"})
    if not ans.get("ok"):
        raise SystemExit(f"status refused: {ans}")
    return ans["status"]


def _ctl(sock: str, *args) -> subprocess.CompletedProcess:
    return subprocess.run([*MOTORCTL, "--socket", sock, *args], capture_output=True, text=True,
                          timeout=60)


def _rss_mb(pid) -> float:
    try:
        with open(f"/proc/{pid}/status") as fh:
            for line in fh:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) / 1024.0
    except (OSError, TypeError):
        pass
    return float("nan")


def _dir_bytes(d: Path) -> int:
    total = 0
    for e in os.scandir(d):
        try:                       # retention may delete a file between the scan and the stat
            total += e.stat().st_size if e.is_file() else 0
        except FileNotFoundError:
            pass
    return total


def _wait(pred, timeout: float, what: str):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        try:
            v = pred()
        except DaemonUnreachable:
            v = None
        if v:
            return v
        time.sleep(0.05)
    raise SystemExit(f"timed out waiting for {what}")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--minutes", type=float, default=10.0)
    ap.add_argument("--budget-mb", type=float, default=50.0)
    ap.add_argument("--segment-mb", type=float, default=5.0)
    ap.add_argument("--poll", type=float, default=10.0, help="seconds between status lines")
    ap.add_argument("--fault-every", type=float, default=90.0, help="seconds between injected faults")
    ap.add_argument("--keep", action="store_true", help="keep the temporary directory")
    a = ap.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="motorctl-soak-"))
    sock, logs = str(tmp / "motorctl.sock"), tmp / "logs"
    budget = int(a.budget_mb * 1e6)
    d = yaml.safe_load((REPO / "configs" / "gantry.yaml").read_text())
    d["loop"]["realtime"]["policy"] = "best_effort"
    d["daemon"].update(socket=sock, log_dir=str(logs), allow_fault_injection=True,
                       log_segment_bytes=int(a.segment_mb * 1e6), log_budget_bytes=budget)
    cfg = tmp / "soak.yaml"
    cfg.write_text(yaml.safe_dump(d))
    proc = subprocess.Popen([*MOTORCTL, "daemon", str(cfg)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    io_pid = None
    peak_dir = peak_loop_rss = peak_io_rss = 0.0
    faults = recoveries = 0
    try:
        st = _wait(lambda: os.path.exists(sock) and (s := _status(sock))["loop"]["cycles"] > 0 and s,
                   120, "the daemon")
        io_pid, loop_pid = st["process"]["io_pid"], st["process"]["loop_pid"]
        print(f"soak: {a.minutes:g} min at {st['loop']['rate_hz']:.0f} Hz, budget {budget / 1e6:g} MB, "
              f"segments {a.segment_mb:g} MB, a NaN fault on X every {a.fault_every:g} s; "
              f"realtime: {st['realtime_summary']}")
        for ax in ("X", "Y"):
            r = _ctl(sock, "start", ax)
            if r.returncode:
                raise SystemExit(r.stderr)
        t0 = time.monotonic()
        next_poll = t0 + a.poll
        next_fault = t0 + a.fault_every
        print(f"{'t_s':>6} {'cycles':>9} {'MB/s':>6} {'kept_MB':>8} {'dir_MB':>7} {'segs':>5} "
              f"{'events':>6} {'dropped':>7} {'lost':>5} {'loop_MB':>7} {'io_MB':>6}  axes")
        while time.monotonic() - t0 < a.minutes * 60:
            now = time.monotonic()
            peak_dir = max(peak_dir, _dir_bytes(logs))
            if now >= next_fault:
                next_fault += a.fault_every
                _ctl(sock, "inject", "X", "nan")
                _wait(lambda: _status(sock)["axes"]["X"]["state"] == "fault", 20, "X fault")
                r = _ctl(sock, "fault-reset", "X")
                if r.returncode and "outside the soft limits" in r.stderr:
                    # stopped at speed, X coasted out (0 V, amplifier off): the documented
                    # recovery, a slow jog back inside (docs/daemon.md), then start
                    lim = d["axes"]["X"]["limits"]
                    back = 0.5 * (lim["soft_min_m"] + lim["soft_max_m"])
                    r = _ctl(sock, "jog", "X", f"{back:.4f}", "--speed", "0.2")
                    recoveries += r.returncode == 0
                if r.returncode:
                    print(f"  (recovery of X refused: {r.stderr.strip()})")
                r = _ctl(sock, "start", "X")
                if r.returncode:
                    print(f"  (start X refused: {r.stderr.strip()})")
                faults += 1
            if now >= next_poll:
                next_poll += a.poll
                st = _status(sock)
                ret = st["log"]["retention"]
                lr, ir = _rss_mb(loop_pid), _rss_mb(io_pid)
                peak_loop_rss, peak_io_rss = max(peak_loop_rss, lr), max(peak_io_rss, ir)
                axes = ", ".join(f"{n} {s['state']}" for n, s in st["axes"].items())
                print(f"{now - t0:6.0f} {st['loop']['cycles']:9d} {ret['bytes_per_s'] / 1e6:6.2f} "
                      f"{ret['kept_bytes'] / 1e6:8.1f} {_dir_bytes(logs) / 1e6:7.1f} "
                      f"{ret['kept_segments']:5d} {ret['kept_events']:6d} {ret['dropped_segments']:7d} "
                      f"{st['log']['lost_rows']:5d} {lr:7.0f} {ir:6.0f}  {axes}", flush=True)
            time.sleep(0.05)
        st = _status(sock)
        run = st["log"]["run"]
        proc.send_signal(signal.SIGTERM)
        proc.communicate(timeout=60)
        ret = st["log"]["retention"]
        events = [e for e in st["log"]["events"]]
        kept_ev = [e for e in events if os.path.exists(e["path"])]
        print(f"\nstopped (exit {proc.returncode}) after {st['loop']['cycles']} cycles; "
              f"{faults} faults injected, {recoveries} of them recovered by a jog from outside the soft limits")
        print(f"bytes/s: {ret['bytes_per_s'] / 1e6:.3f} MB/s measured, {ret['row_bytes_per_s'] / 1e6:.3f} "
              f"MB/s of records; at the budget: {ret['days_at_budget'] * 86400:.0f} s of routine rows "
              f"({ret['days_at_budget']:.6f} days)")
        print(f"kept: {_dir_bytes(logs) / 1e6:.1f} MB of {budget / 1e6:g} MB (peak {peak_dir / 1e6:.1f} MB); "
              f"{ret['kept_segments']} segments, {ret['dropped_segments']} dropped; event logs of this "
              f"run kept {len(kept_ev)}/{len(events)} ({ret['dropped_events']} dropped by the budget), "
              f"{st['log']['events_dropped']} events over max_event_logs")
        print("event logs kept: " + ", ".join(sorted(Path(e["path"]).name.split(".", 1)[1]
                                                      for e in kept_ev)))
        print(f"lost rows: {st['log']['lost_rows']}; daemon peak RSS: loop {peak_loop_rss:.0f} MB, "
              f"I/O {peak_io_rss:.0f} MB")
        for fmt in ("mat", "csv"):
            out = str(tmp / f"soak.{fmt}")
            rss, dt, line = run_child(["export", run, f"--{fmt}", out])
            print(f"export --{fmt} of the rotated set: peak RSS {rss:.0f} MB, {dt:.1f} s: {line}")
            os.unlink(out)
        print(json.dumps({"minutes": a.minutes, "bytes_per_s": ret["bytes_per_s"],
                          "kept_bytes": _dir_bytes(logs), "budget_bytes": budget,
                          "peak_dir_bytes": peak_dir, "events_kept": len(kept_ev),
                          "events": len(events), "lost_rows": st["log"]["lost_rows"]}))
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(30)
            except subprocess.TimeoutExpired:
                proc.kill()
        if io_pid and proc.returncode != 0:      # the I/O process must not outlive a failed run
            try:
                os.kill(io_pid, signal.SIGKILL)
            except OSError:
                pass
        if a.keep:
            print(f"kept {tmp}")
        else:
            shutil.rmtree(tmp, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
