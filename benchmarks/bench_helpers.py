"""The daemon's helper processes at start and when killed: ``motorctl daemon`` on configs/gantry.yaml
with the scope, /metrics and OPC UA configured (loopback ports), started N times beside CPU-bound
processes. Per start: the rows lost at start (``status`` ``log.lost_rows`` once the loop has run
``--settle`` s), a recorder fault, and, with ``--kill``, each helper killed with SIGKILL in turn:
the time until ``status`` names it back (a new pid) and whether the loop went on untouched (no
fault latched, no row lost). Prints one line per start and the totals.

Rerun:
    python benchmarks/bench_helpers.py [--starts 10] [--hogs 4] [--settle 5] [--kill]
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import yaml

REPO = Path(__file__).resolve().parents[1]
HOG = "import time\nend = time.monotonic() + {s}\nwhile time.monotonic() < end: pass\n"


def port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def status(sock: str) -> dict | None:
    from motorctl.cli.operator import call
    try:
        ans = call(sock, {"cmd": "status"}, timeout_s=10.0)
    except Exception:  # noqa: BLE001 - not up yet
        return None
    return ans["status"] if ans.get("ok") else None


def one_start(tmp: Path, settle_s: float, kill: bool) -> dict:
    d = yaml.safe_load((REPO / "configs" / "gantry.yaml").read_text())
    d["daemon"].update(socket=str(tmp / "m.sock"), log_dir=str(tmp / "logs"),
                       scope={"listen": f"127.0.0.1:{port()}"}, metrics={"listen": f"127.0.0.1:{port()}"},
                       opcua={"endpoint": f"opc.tcp://127.0.0.1:{port()}/motorctl"})
    cfg = tmp / "cfg.yaml"
    cfg.write_text(yaml.safe_dump(d))
    sock = str(tmp / "m.sock")
    p = subprocess.Popen([sys.executable, "-m", "motorctl", "daemon", str(cfg)], cwd=REPO,
                         stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    out: dict = {}
    try:
        t0 = time.monotonic()
        while time.monotonic() - t0 < 300:
            st = status(sock)
            if st and st["loop"]["cycles"] > 0:
                break
            time.sleep(0.1)
        c0 = st["loop"]["cycles"]
        while (st := status(sock))["loop"]["cycles"] < c0 + settle_s * st["loop"]["rate_hz"]:
            time.sleep(0.1)
        out["lost_at_start"] = st["log"]["lost_rows"]
        out["recorder_fault"] = st["log"]["recorder_fault"]
        out["faults"] = [a for a, x in st["axes"].items() if x["fault"]]
        if kill:
            back = {}
            for name in ("views", "metrics", "opcua"):
                h = st["helpers"].get(name)
                if not h or not h["pid"]:
                    back[name] = None
                    continue
                os.kill(h["pid"], signal.SIGKILL)
                t1 = time.monotonic()
                while time.monotonic() - t1 < 30:
                    s2 = status(sock)
                    n = s2["helpers"][name]
                    if n["pid"] and n["pid"] != h["pid"]:
                        break
                    time.sleep(0.02)
                back[name] = time.monotonic() - t1
                st = s2
            out["back_s"] = back
            st = status(sock)
            out["lost_after_kills"] = st["log"]["lost_rows"]
            out["faults_after_kills"] = [a for a, x in st["axes"].items() if x["fault"]]
    finally:
        p.send_signal(signal.SIGTERM)
        try:
            p.communicate(timeout=30)
        except subprocess.TimeoutExpired:
            p.kill()
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--starts", type=int, default=10)
    ap.add_argument("--hogs", type=int, default=4)
    ap.add_argument("--settle", type=float, default=5.0, help="loop time after the first cycle [s]")
    ap.add_argument("--kill", action="store_true", help="kill each helper once per start")
    a = ap.parse_args()
    hogs = [subprocess.Popen([sys.executable, "-c", HOG.format(s=24 * 3600)]) for _ in range(a.hogs)]
    results = []
    try:
        for k in range(a.starts):
            with tempfile.TemporaryDirectory() as t:
                r = one_start(Path(t), a.settle, a.kill)
            results.append(r)
            print(f"start {k + 1}: {json.dumps(r)}", flush=True)
    finally:
        for h in hogs:
            h.kill()
    lost = sum(r["lost_at_start"] for r in results)
    stalls = sum(1 for r in results if r["recorder_fault"])
    print(f"{a.starts} starts beside {a.hogs} CPU hogs: rows lost at start {lost} in all, recorder faults "
          f"{stalls}", end="")
    if a.kill:
        backs = [v for r in results for v in r["back_s"].values() if v is not None]
        print(f"; killed helpers back in at most {max(backs):.2f} s (median {sorted(backs)[len(backs) // 2]:.2f}), "
              f"rows lost after the kills {sum(r['lost_after_kills'] for r in results)}, faults "
              f"{sum(len(r['faults_after_kills']) for r in results)}", end="")
    print()
    return 0


if __name__ == "__main__":
    sys.exit(main())
