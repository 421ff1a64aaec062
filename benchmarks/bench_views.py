"""Views on a busy PC: do the scope page and Prometheus ``/metrics`` answer beside CPU-bound
processes, and what do they cost the loop?

The daemon on configs/gantry.yaml (simulated gantry, wall clock, the config's real-time policy;
socket and log_dir in a temporary folder), ``--hogs`` CPU-bound processes at normal priority
(multiprocessing spinners, started before the daemon), Y running its program. Two daemons in turn:

1. without views: ``--seconds`` of the loop beside the hogs;
2. with ``daemon.scope`` and ``daemon.metrics`` on loopback ports: the time from the daemon's
   start to the first answer of the page and of ``/metrics``, then ``--clients`` threads each
   GET ``/`` and ``/metrics`` in turn for ``--seconds`` (at most ``--max-requests`` each).

Prints the answer times (median, p99, max, failures) per path; per daemon the loop's turnaround
p99.9 and max over the measured window (the run log's ``turnaround_ns``, cycles from the
``status`` before to the one after), missed periods in it, rows lost, and the view and metrics
processes' CPU seconds.

    python benchmarks/bench_views.py                    # 4 hogs, 4 clients, 30 s
    python benchmarks/bench_views.py --hogs 0 --seconds 10
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
import urllib.request
from pathlib import Path

import numpy as np
import yaml

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from motorctl.client import Client, DaemonUnreachable  # noqa: E402

TICK = os.sysconf("SC_CLK_TCK")


def _spin() -> None:  # pragma: no cover  (a background load; killed by the parent)
    os.setpriority(os.PRIO_PROCESS, 0, 0)
    x = 0
    while True:
        x += 1


def _port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Daemon:
    """``motorctl daemon`` on configs/gantry.yaml in ``tmp`` (``views``: the scope and /metrics on
    free loopback ports; ``extra``: further keys of its ``daemon`` section; ``loop_cpu``: its
    ``loop.realtime.cpu``), ready, Y started."""

    def __init__(self, tmp: Path, views: bool, extra: dict | None = None, loop_cpu: int | None = None):
        d = yaml.safe_load((REPO / "configs" / "gantry.yaml").read_text())
        d["daemon"].update(socket=str(tmp / "motorctl.sock"), log_dir=str(tmp / "logs"))
        if loop_cpu is not None:                    # loop.realtime.cpu: the loop pinned there
            d["loop"].setdefault("realtime", {})["cpu"] = loop_cpu
        self.scope_port = self.metrics_port = None
        if views:
            self.scope_port, self.metrics_port = _port(), _port()
            d["daemon"]["scope"] = {"listen": f"127.0.0.1:{self.scope_port}"}
            d["daemon"]["metrics"] = {"listen": f"127.0.0.1:{self.metrics_port}"}
        d["daemon"].update(extra or {})
        self.cfg = tmp / "gantry.yaml"
        self.cfg.write_text(yaml.safe_dump(d))
        self.sock = str(tmp / "motorctl.sock")
        self.err_path = tmp / "daemon.err"
        self.err = open(self.err_path, "w")
        self.t0 = time.monotonic()
        self.proc = subprocess.Popen([sys.executable, "-m", "motorctl", "daemon", str(self.cfg)],
                                     stdout=self.err, stderr=self.err, cwd=REPO)
        self.c = Client(self.sock, timeout_s=30.0)
        try:
            self.c.wait_started(300, alive=lambda: self.proc.poll() is None)
        except DaemonUnreachable as exc:
            self.proc.kill()
            raise SystemExit(f"{exc}: {self.err_path.read_text()[-2000:]}") from None
        self.ready_s = time.monotonic() - self.t0
        self.c.start("Y")

    def child_cpu_s(self) -> dict:
        """CPU seconds of the I/O process's children (view, metrics, planner) by command line."""
        st = self.c.status()
        out = {}
        io = st["process"]["io_pid"]
        kids = subprocess.run(["pgrep", "-P", str(io)], capture_output=True, text=True).stdout.split()
        views = (st.get("views") or {}).get("pid")
        for p in kids:
            try:
                f = open(f"/proc/{p}/stat").read().rsplit(")", 1)[1].split()
            except OSError:
                continue
            name = "view" if int(p) == views else ("planner" if int(p) == st["process"]["planner_pid"]
                                                   else "metrics")
            out[name] = (int(f[11]) + int(f[12])) / TICK
        return out

    def stop(self) -> None:
        self.proc.terminate()
        try:
            self.proc.wait(30)
        except subprocess.TimeoutExpired:
            self.proc.kill()


def first_answer(url: str, t0: float, bound_s: float = 300.0) -> float:
    """Seconds from t0 to the first 200 from url (NaN: none within bound_s)."""
    while time.monotonic() - t0 < bound_s:
        try:
            urllib.request.urlopen(url, timeout=bound_s).read()
            return time.monotonic() - t0
        except OSError:
            time.sleep(0.05)
    return float("nan")


def clients(urls: list[str], n: int, seconds: float, max_requests: int) -> dict:
    times: dict[str, list[float]] = {u: [] for u in urls}
    fails: dict[str, int] = {u: 0 for u in urls}
    lock = threading.Lock()
    end = time.monotonic() + seconds

    def one():
        for i in range(max_requests):
            if time.monotonic() > end:
                return
            u = urls[i % len(urls)]
            t = time.monotonic()
            try:
                urllib.request.urlopen(u, timeout=60).read()
                ok = True
            except OSError:
                ok = False
            dt = time.monotonic() - t
            with lock:
                if ok:
                    times[u].append(dt)
                else:
                    fails[u] += 1

    th = [threading.Thread(target=one) for _ in range(n)]
    for t in th:
        t.start()
    for t in th:
        t.join()
    return {u: (times[u], fails[u]) for u in urls}


def turnaround(run_path: str, k0: int, k1: int) -> tuple[float, float, int]:
    """p99.9 and max of the turnaround [us] over cycles k0..k1, and the missed periods in them."""
    from motorctl.recorder.segments import read_run
    log = read_run(run_path)
    t = log.col("t")
    period = 1.0 / 5000
    sel = (t >= k0 * period) & (t < k1 * period)
    ta = log.col("turnaround_ns")[sel] / 1e3
    ovr = log.col("overruns")[sel]
    return float(np.percentile(ta, 99.9)), float(ta.max()), int(ovr[-1] - ovr[0])


def measure(tmp: Path, views: bool, a) -> dict:
    dm = Daemon(tmp, views)
    out = {"ready_s": dm.ready_s}
    try:
        if views:
            base = f"http://127.0.0.1:{dm.scope_port}/"
            murl = f"http://127.0.0.1:{dm.metrics_port}/metrics"
            got = {}
            th = [threading.Thread(target=lambda k=k, u=u: got.__setitem__(k, first_answer(u, dm.t0)))
                  for k, u in (("first_page_s", base), ("first_metrics_s", murl))]
            for t in th:
                t.start()
            for t in th:
                t.join()
            out.update(got)
        st0 = dm.c.status()
        if views:
            out["answers"] = clients([base, murl], a.clients, a.seconds, a.max_requests)
        else:
            time.sleep(a.seconds)
        st1 = dm.c.status()
        out["cpu"] = dm.child_cpu_s()
        out["views"] = st1.get("views")
        out["lost_rows"] = st1["log"]["lost_rows"]
        out["faults"] = {ax: s["fault"] for ax, s in st1["axes"].items() if s["fault"]}
        k0, k1 = st0["loop"]["cycles"], st1["loop"]["cycles"]
        run = st1["log"]["run"]
    finally:
        dm.stop()
    out["p999_us"], out["max_us"], out["missed"] = turnaround(run, k0, k1)
    out["cycles"] = k1 - k0
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--hogs", type=int, default=4, help="CPU-bound processes at nice 0")
    ap.add_argument("--clients", type=int, default=4, help="HTTP client threads")
    ap.add_argument("--seconds", type=float, default=30.0, help="measured time per daemon [s]")
    ap.add_argument("--max-requests", type=int, default=2000, help="GETs per client at most")
    a = ap.parse_args()
    hogs = [mp.Process(target=_spin, daemon=True) for _ in range(a.hogs)]
    for h in hogs:
        h.start()
    try:
        res = {}
        for views in (False, True):
            with tempfile.TemporaryDirectory(prefix="bench-views-") as tmp:
                res[views] = measure(Path(tmp), views, a)
    finally:
        for h in hogs:
            h.kill()
    print(f"host: {os.cpu_count()} CPUs, {a.hogs} hogs at nice 0, {a.clients} clients, "
          f"{a.seconds:g} s per daemon; load average {os.getloadavg()[0]:.1f}")
    w = res[True]
    print(f"with views: daemon ready {w['ready_s']:.1f} s; first answer: page {w['first_page_s']:.2f} s, "
          f"/metrics {w['first_metrics_s']:.2f} s after the daemon's start")
    for url, (times, fails) in w["answers"].items():
        path = "/metrics" if url.endswith("/metrics") else "/"
        if times:
            ms = np.asarray(times) * 1e3
            print(f"  GET {path:9s} {len(times):5d} answers, {fails} failed: median "
                  f"{statistics.median(ms):.1f} ms, p99 {np.percentile(ms, 99):.1f} ms, "
                  f"max {ms.max():.1f} ms")
        else:
            print(f"  GET {path:9s} no answer, {fails} failed")
    for views in (False, True):
        r = res[views]
        print(f"{'with' if views else 'without':7s} views: turnaround p99.9 {r['p999_us']:.1f} us, "
              f"max {r['max_us']:.1f} us over {r['cycles']} cycles; missed periods {r['missed']}; "
              f"rows lost {r['lost_rows']}; faults {r['faults'] or 'none'}; "
              f"CPU s {r['cpu']}; views {r['views']}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
