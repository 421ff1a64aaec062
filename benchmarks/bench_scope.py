"""What live views cost the daemon, and whether they can hurt it: the daemon on the simulated
gantry (wall clock, both axes running their programs, the config's real-time policy), with
``--spinners`` CPU-bound processes loading the host, and in turn 0, 5, 20 and 50 scope pages
(WebSocket clients of ``/ws`` reading every message, as the page does) plus one Foxglove client
subscribed to every channel. Per step (``--seconds`` each): faults latched, rows lost, the
recorder's state, overruns, CPU seconds of the I/O process and of the view process, the frames
a page received and the frames it was told it missed.

Rerun:
    python benchmarks/bench_scope.py [--seconds 20] [--spinners 2] [--pages 0 5 20 50]

Needs the test extra (aiohttp, foxglove-sdk).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import yaml

REPO = Path(__file__).resolve().parents[1]
TICK = os.sysconf("SC_CLK_TCK")


def _port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _call(sock: str, msg: dict) -> dict:
    from motorctl.cli.operator import call
    return call(sock, msg)


def _cpu_s(pid: int | None) -> float:
    if not pid:
        return 0.0
    try:
        f = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(f[11]) + int(f[12])) / TICK
    except OSError:
        return 0.0


def _children(pid: int) -> list[int]:
    try:
        return [int(x) for x in Path(f"/proc/{pid}/task/{pid}/children").read_text().split()]
    except OSError:
        return []


def _daemon(tmp: Path, scope_port: int, fox_port: int):
    d = yaml.safe_load((REPO / "configs" / "gantry.yaml").read_text())
    d["daemon"].update(socket=str(tmp / "m.sock"), log_dir=str(tmp / "logs"),
                       scope={"listen": f"127.0.0.1:{scope_port}"},
                       foxglove={"listen": f"127.0.0.1:{fox_port}"})
    cfg = tmp / "cfg.yaml"
    cfg.write_text(yaml.safe_dump(d))
    proc = subprocess.Popen([sys.executable, "-m", "motorctl", "daemon", str(cfg)], cwd=REPO,
                            stdout=subprocess.DEVNULL, stderr=open(tmp / "daemon.err", "w"),
                            start_new_session=True)
    sock = str(tmp / "m.sock")
    from motorctl.cli.operator import DaemonUnreachable
    for _ in range(3000):
        try:
            st = _call(sock, {"cmd": "status"})
            if st["ok"] and st["status"]["loop"]["cycles"] > 0:
                break
        except (OSError, DaemonUnreachable, KeyError):
            pass
        time.sleep(0.1)
    for a in ("X", "Y"):
        for _ in range(50):
            if _call(sock, {"cmd": "start", "axis": a}).get("ok"):
                break
            time.sleep(0.2)
    return proc, sock


class Clients:
    """``n`` scope pages and one Foxglove client on a thread's event loop."""

    def __init__(self, scope_port: int, fox_port: int, n: int):
        self.sp, self.fp, self.n = scope_port, fox_port, n
        self.frames = [0] * n
        self.dropped = [0] * n
        self.fox_msgs = [0]
        self.stop = threading.Event()
        self.thread = threading.Thread(target=lambda: asyncio.run(self._run()), daemon=True)

    async def _page(self, s, i):
        import aiohttp
        async with s.ws_connect(f"ws://127.0.0.1:{self.sp}/ws", max_msg_size=0) as ws:
            while not self.stop.is_set():
                try:
                    m = await ws.receive(timeout=0.5)
                except asyncio.TimeoutError:
                    continue
                if m.type != aiohttp.WSMsgType.TEXT:
                    break
                msg = json.loads(m.data)
                self.frames[i] += len(msg.get("frames", ()))
                self.dropped[i] = msg.get("dropped", self.dropped[i])

    async def _fox(self, s):
        import aiohttp
        async with s.ws_connect(f"ws://127.0.0.1:{self.fp}/",
                                protocols=["foxglove.sdk.v1", "foxglove.websocket.v1"]) as ws:
            while not self.stop.is_set():
                try:
                    m = await ws.receive(timeout=0.5)
                except asyncio.TimeoutError:
                    continue
                if m.type == aiohttp.WSMsgType.TEXT:
                    op = json.loads(m.data)
                    if op["op"] == "advertise":
                        await ws.send_str(json.dumps({"op": "subscribe", "subscriptions": [
                            {"id": c["id"], "channelId": c["id"]} for c in op["channels"]]}))
                elif m.type == aiohttp.WSMsgType.BINARY:
                    self.fox_msgs[0] += 1
                else:
                    break

    async def _run(self):
        import aiohttp
        async with aiohttp.ClientSession() as s:
            jobs = [self._page(s, i) for i in range(self.n)] + [self._fox(s)]
            await asyncio.gather(*jobs, return_exceptions=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--spinners", type=int, default=2)
    ap.add_argument("--pages", type=int, nargs="+", default=[0, 5, 20, 50])
    ap.add_argument("--keep-stderr", default=None, metavar="FILE", help="copy the daemon's stderr here")
    args = ap.parse_args()
    print(f"# rerun: python benchmarks/bench_scope.py --seconds {args.seconds:g} --spinners "
          f"{args.spinners} --pages {' '.join(map(str, args.pages))}")
    spinners = [subprocess.Popen([sys.executable, "-c", "while True: pass"])
                for _ in range(args.spinners)]
    rows = []
    try:
        with tempfile.TemporaryDirectory() as tmp:
            sp, fp = _port(), _port()
            proc, sock = _daemon(Path(tmp), sp, fp)
            try:
                st = _call(sock, {"cmd": "status"})["status"]
                io_pid = st["process"]["io_pid"]
                time.sleep(2.0)
                view_pid = (_children(io_pid) or [None])[0]
                for n in args.pages:
                    a = _call(sock, {"cmd": "status"})["status"]
                    cpu_io, cpu_view = _cpu_s(io_pid), _cpu_s(view_pid)
                    cl = Clients(sp, fp, n)
                    cl.thread.start()
                    time.sleep(args.seconds)
                    b = _call(sock, {"cmd": "status"})["status"]
                    d_io, d_view = _cpu_s(io_pid) - cpu_io, _cpu_s(view_pid) - cpu_view
                    cl.stop.set()
                    cl.thread.join(5.0)
                    faults = [f"{ax}: {s['fault']}" for ax, s in b["axes"].items() if s["fault"]]
                    rows.append({
                        "pages": n, "faults": "; ".join(faults) or "0",
                        "lost": b["log"]["lost_rows"] - a["log"]["lost_rows"],
                        "recorder": b["log"]["recorder_fault"] or "ok",
                        "overruns": b["loop"]["overruns"] - a["loop"]["overruns"],
                        "io_cpu": d_io / args.seconds, "view_cpu": d_view / args.seconds,
                        "frames": min(cl.frames) if n else 0, "dropped": max(cl.dropped) if n else 0,
                        "fox": cl.fox_msgs[0],
                    })
                    if faults:            # the next step starts from a clean machine
                        for ax in b["axes"]:
                            _call(sock, {"cmd": "fault-reset", "axis": ax})
                            _call(sock, {"cmd": "start", "axis": ax})
            finally:
                os.killpg(proc.pid, signal.SIGTERM)
                proc.wait(20)
                err = (Path(tmp) / "daemon.err").read_text()
                if args.keep_stderr:
                    Path(args.keep_stderr).write_text(err)
    finally:
        for s in spinners:
            s.kill()
            s.wait()
    load = os.getloadavg()
    print(f"# {args.spinners} spinning processes, {args.seconds:g} s per step, load average "
          f"{load[0]:.1f}; the daemon's stderr had {err.count(chr(10))} lines"
          f"{', a traceback' if 'Traceback' in err else ''}")
    print("| scope pages (+1 Foxglove) | faults | rows lost | recorder | overruns | I/O process CPU | "
          "view process CPU | frames per page (least) | frames dropped (most) | Foxglove messages |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['pages']} | {r['faults']} | {r['lost']} | {r['recorder']} | {r['overruns']} | "
              f"{100 * r['io_cpu']:.1f} % | {100 * r['view_cpu']:.1f} % | {r['frames']} | "
              f"{r['dropped']} | {r['fox']} |")


if __name__ == "__main__":
    main()
