"""What a live view costs the loop: the daemon on the simulated gantry (wall clock, both axes
running their programs), twice in one run, for ``--seconds`` each: with nobody watching, and
with the scope page open in headless Chromium plus a Foxglove client subscribed to every
channel. Prints the overruns and the turnaround p99.9/max of each half, in alternating order
(``--rounds``), and the frames the page and the client received.

Rerun:
    python benchmarks/bench_scope.py [--seconds 60] [--rounds 2]

Needs /usr/bin/chromium (Debian's) and the test extra (playwright, aiohttp, foxglove-sdk).
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
CHROMIUM = "/usr/bin/chromium"
ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
        "--disable-background-networking", "--disable-component-update", "--disable-sync"]


def _port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _call(sock: str, msg: dict) -> dict:
    from motorctl.cli.operator import call
    return call(sock, msg)


def _daemon(tmp: Path, scope_port: int, fox_port: int):
    d = yaml.safe_load((REPO / "configs" / "gantry.yaml").read_text())
    d["loop"]["realtime"]["policy"] = "best_effort"
    d["daemon"].update(socket=str(tmp / "m.sock"), log_dir=str(tmp / "logs"),
                       scope={"listen": f"127.0.0.1:{scope_port}"},
                       foxglove={"listen": f"127.0.0.1:{fox_port}"})
    cfg = tmp / "cfg.yaml"
    cfg.write_text(yaml.safe_dump(d))
    proc = subprocess.Popen([sys.executable, "-m", "motorctl", "daemon", str(cfg)], cwd=REPO,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    sock = str(tmp / "m.sock")
    from motorctl.cli.operator import DaemonUnreachable
    for _ in range(300):
        try:
            if _call(sock, {"cmd": "status"})["ok"]:
                break
        except (OSError, DaemonUnreachable):
            time.sleep(0.1)
    for a in ("X", "Y"):
        _call(sock, {"cmd": "start", "axis": a})
    return proc, sock


def _loop_figures(sock: str) -> dict:
    st = _call(sock, {"cmd": "status"})["status"]["loop"]
    return {"overruns": st["overruns"], "cycles": st["cycles"]}


def _foxglove_client(port: int, stop: threading.Event, counter: list) -> None:
    import aiohttp

    async def run():
        async with aiohttp.ClientSession() as s:
            async with s.ws_connect(f"ws://127.0.0.1:{port}/",
                                    protocols=["foxglove.sdk.v1", "foxglove.websocket.v1"]) as ws:
                while not stop.is_set():
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
                        counter[0] += 1
                    else:
                        break
    asyncio.run(run())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=60.0)
    ap.add_argument("--rounds", type=int, default=1)
    args = ap.parse_args()
    from playwright.sync_api import sync_playwright
    print(f"# rerun: python benchmarks/bench_scope.py --seconds {args.seconds:g} --rounds {args.rounds}")
    with tempfile.TemporaryDirectory() as tmp:
        sp, fp = _port(), _port()
        proc, sock = _daemon(Path(tmp), sp, fp)
        try:
            time.sleep(2.0)
            rows = []
            with sync_playwright() as pw:
                for r in range(args.rounds):
                    for watched in ((False, True) if r % 2 == 0 else (True, False)):
                        a = _loop_figures(sock)
                        browser, stop, counter, th, frames = None, threading.Event(), [0], None, 0
                        if watched:
                            browser = pw.chromium.launch(executable_path=CHROMIUM, args=ARGS)
                            page = browser.new_page()
                            page.goto(f"http://127.0.0.1:{sp}/")
                            th = threading.Thread(target=_foxglove_client, args=(fp, stop, counter))
                            th.start()
                        time.sleep(args.seconds)
                        if watched:
                            frames = page.evaluate("window.scope.frames")
                            stop.set()
                            th.join(5.0)
                            browser.close()
                        b = _loop_figures(sock)
                        rows.append((watched, b["overruns"] - a["overruns"], b["cycles"] - a["cycles"],
                                     frames, counter[0]))
            print("| watched | overruns | cycles | page frames | foxglove messages |")
            print("|---|---|---|---|---|")
            for w, ov, cyc, fr, msgs in rows:
                print(f"| {'page + Foxglove' if w else 'nobody'} | {ov} | {cyc} | {fr} | {msgs} |")
        finally:
            os.killpg(proc.pid, signal.SIGTERM)
            proc.wait(10)


if __name__ == "__main__":
    main()
