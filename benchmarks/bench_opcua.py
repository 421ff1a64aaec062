"""The OPC UA server on a busy PC: how long does a read of a position take beside CPU-bound
processes, and what does the server cost the I/O process and the loop?

The daemon on configs/gantry.yaml (simulated gantry, wall clock, the config's real-time policy;
socket and log_dir in a temporary folder), ``--hogs`` CPU-bound processes at nice 0
(multiprocessing spinners, started before the daemon), Y running its program. Two daemons in
turn:

1. without ``daemon.opcua``: ``--seconds`` of the loop beside the hogs;
2. with ``daemon.opcua`` (anonymous read, security None and Basic256Sha256) on a loopback
   port: the time from the daemon's start to the first answer, then one asyncua client reads
   X's ActPos back to back for ``--seconds`` (at most ``--reads`` reads) on a None session, and
   the same on a Basic256Sha256 SignAndEncrypt session (a client certificate made for the run).

Prints the read latency (median, p99, max) per session; per daemon the CPU seconds per second
of the I/O process and of the OPC UA process over the measured window, the loop's turnaround
p99.9 and max (the run log's ``turnaround_ns``), missed periods and rows lost.

``--logins N``: instead, the time of a refused login for a known name (a wrong password) and
for an unknown one, N of each, interleaved, on both surfaces served by one process of their own
(the OPC UA server, :class:`~motorctl.app.daemon.opcua_server.CncServer`, and the operator
page, :class:`~motorctl.app.daemon.operator_page.OperatorPage`; no daemon: a login does not ask
it), ``--hogs`` CPU-bound processes beside them: OPC UA's ActivateSession on a None channel
(asyncua's client, the password encrypted with the server's certificate; the channel and the
session opened before the clock starts), the page's ``POST /login`` (its 0.5 s delay of a
refusal included). The login state is cleared before each attempt (as ``motorctl users
unlock`` does), so every attempt is checked rather than backed off. Prints the medians, their
ratio and the spread.

    python benchmarks/bench_opcua.py                    # 4 hogs, 20 s per daemon
    python benchmarks/bench_opcua.py --hogs 0 --seconds 5
    python benchmarks/bench_opcua.py --logins 20 --hogs 0
"""

from __future__ import annotations

import argparse
import asyncio
import multiprocessing as mp
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "benchmarks"))

from bench_views import Daemon as ViewsDaemon  # noqa: E402
from bench_views import _port, _spin, turnaround  # noqa: E402


TICK = os.sysconf("SC_CLK_TCK")
NODE = "ns=2;s=CncInterface.CncAxisList.X.ActPos"


def cpu_s(pid: int | None) -> float:
    """User + system CPU seconds of a process (NaN: gone)."""
    try:
        f = open(f"/proc/{pid}/stat").read().rsplit(")", 1)[1].split()
    except (OSError, TypeError):
        return float("nan")
    return (int(f[11]) + int(f[12])) / TICK


class Daemon(ViewsDaemon):
    """bench_views's daemon, with (``opcua``) the OPC UA server on a free loopback port."""

    def __init__(self, tmp: Path, opcua: bool):
        self.url = f"opc.tcp://127.0.0.1:{_port()}/motorctl" if opcua else None
        super().__init__(tmp, False, {"opcua": {"endpoint": self.url, "anonymous": "read",
                                                "security": ["None", "Basic256Sha256"]}} if opcua else None)


async def first_answer(url: str, t0: float, bound_s: float = 300.0) -> float:
    """Seconds from t0 to the first value of NODE (NaN: none within bound_s)."""
    from asyncua import Client as UaClient
    while time.monotonic() - t0 < bound_s:
        try:
            async with UaClient(url, timeout=30) as c:
                await c.get_node(NODE).read_value()
                return time.monotonic() - t0
        except Exception:                    # noqa: BLE001 - not up yet
            await asyncio.sleep(0.1)
    return float("nan")


async def client_cert(tmp: Path) -> tuple[str, str]:
    """A client certificate and key for the run (asyncua's helper)."""
    from asyncua.crypto.cert_gen import setup_self_signed_certificate
    from cryptography.x509.oid import ExtendedKeyUsageOID
    key, cert = tmp / "client_key.pem", tmp / "client_cert.der"
    await setup_self_signed_certificate(key, cert, "urn:bench:client", "localhost",
                                        [ExtendedKeyUsageOID.CLIENT_AUTH], {"commonName": "bench"})
    return str(cert), str(key)


async def reads(url: str, seconds: float, max_reads: int, security: str | None) -> list[float]:
    """Back-to-back reads of NODE for ``seconds`` (at most max_reads): their latencies [s]."""
    from asyncua import Client as UaClient
    c = UaClient(url, timeout=30)
    if security:
        await c.set_security_string(security)
    out = []
    async with c:
        node = c.get_node(NODE)
        end = time.monotonic() + seconds
        while len(out) < max_reads and time.monotonic() < end:
            t = time.perf_counter()
            await node.read_value()
            out.append(time.perf_counter() - t)
    return out


def measure(tmp: Path, opcua: bool, a) -> dict:
    dm = Daemon(tmp, opcua)
    out = {"ready_s": dm.ready_s}
    try:
        st0 = dm.c.status()
        io_pid, ua_pid = st0["process"]["io_pid"], st0["process"].get("opcua_pid")
        if opcua:
            out["first_s"] = asyncio.run(first_answer(dm.url, dm.t0))
            cert, key = asyncio.run(client_cert(tmp))
            st0 = dm.c.status()
        c0, u0, t0 = cpu_s(io_pid), cpu_s(ua_pid), time.monotonic()
        if opcua:
            half = a.seconds / 2
            out["reads"] = {
                "None": asyncio.run(reads(dm.url, half, a.reads, None)),
                "Basic256Sha256 SignAndEncrypt": asyncio.run(
                    reads(dm.url, half, a.reads, f"Basic256Sha256,SignAndEncrypt,{cert},{key}"))}
        else:
            time.sleep(a.seconds)
        wall = time.monotonic() - t0
        out["io_cpu"] = (cpu_s(io_pid) - c0) / wall
        out["ua_cpu"] = (cpu_s(ua_pid) - u0) / wall if opcua else float("nan")
        st1 = dm.c.status()
        out["lost_rows"] = st1["log"]["lost_rows"]
        out["faults"] = {ax: s["fault"] for ax, s in st1["axes"].items() if s["fault"]}
        k0, k1 = st0["loop"]["cycles"], st1["loop"]["cycles"]
        run = st1["log"]["run"]
    except BaseException:
        dm.stop()
        sys.stderr.write(f"the daemon's output:\n{dm.err_path.read_text()[-3000:]}\n")
        raise
    finally:
        dm.stop()
    out["p999_us"], out["max_us"], out["missed"] = turnaround(run, k0, k1)
    out["cycles"] = k1 - k0
    return out


KNOWN, PASSWORD, UNKNOWN = "olga", "op-secret-4711", "nobody"


def _serve_logins(tmp: str, ua_url: str, http_port: int, ready) -> None:
    """The child: the OPC UA server and the operator page on loopback, one users file."""
    import logging

    from aiohttp import web

    from motorctl.app.daemon.opcua_server import CncServer
    from motorctl.app.daemon.operator_page import OperatorPage
    from motorctl.config import OpcuaConfig
    from motorctl.app.users import load_users
    logging.basicConfig(level=logging.CRITICAL)
    logging.getLogger("motorctl.login").disabled = True       # the journal: not measured here

    async def go():
        srv = CncServer(OpcuaConfig(endpoint=ua_url), load_users(f"{tmp}/users.yaml"), None, None,
                        f"{tmp}/opcua", f"{tmp}/m.sock", [{"name": "X", "rotational": False}], 1 << 20)
        await srv.setup()
        await srv.server.start()
        app = web.Application()
        OperatorPage(f"{tmp}/m.sock", f"{tmp}/users.yaml", ["X"], lambda n: b"").add_routes(app)
        runner = web.AppRunner(app, access_log=None)
        await runner.setup()
        await web.TCPSite(runner, "127.0.0.1", http_port).start()
        ready.set()
        await asyncio.sleep(3600)
    asyncio.run(go())


async def _ua_refusal(url: str, name: str) -> float:
    """The time of one refused ActivateSession [s] (channel and session opened before)."""
    from asyncua import Client as UaClient
    c = UaClient(url, timeout=30)
    await c.connect_socket()
    try:
        await c.send_hello()
        await c.open_secure_channel()
        await c.create_session()
        t = time.perf_counter()
        try:
            await c.activate_session(name, "not-the-password")
            raise AssertionError(f"{name}: logged in with a wrong password")
        except Exception as exc:                    # noqa: BLE001 - BadUserAccessDenied expected
            if "BadUserAccessDenied" not in type(exc).__name__ + str(exc):
                raise
        return time.perf_counter() - t
    finally:
        c.disconnect_socket()


async def _page_refusal(base: str, name: str) -> float:
    import aiohttp
    async with aiohttp.ClientSession() as s:
        t = time.perf_counter()
        async with s.post(base + "/login", json={"name": name, "password": "not-the-password"}) as r:
            await r.read()
            assert r.status == 403, (name, r.status)
        return time.perf_counter() - t


def logins(a) -> int:
    """``--logins N``: the refusal times of a known and an unknown name on both surfaces."""
    import yaml

    import logging

    from motorctl.app.login import state_path
    from motorctl.app.users import hash_password
    logging.getLogger("asyncua").setLevel(logging.CRITICAL)     # each refusal is a ServiceFault
    with tempfile.TemporaryDirectory(prefix="bench-logins-") as tmp:
        Path(tmp, "users.yaml").write_text(yaml.safe_dump({"users": {
            KNOWN: {"password": hash_password(PASSWORD), "roles": ["operator"]}}}))
        state = state_path(f"{tmp}/m.sock")
        ua_url, port = f"opc.tcp://127.0.0.1:{_port()}/motorctl", _port()
        ready = mp.Event()
        child = mp.Process(target=_serve_logins, args=(tmp, ua_url, port, ready), daemon=True)
        child.start()
        try:
            if not ready.wait(300):
                raise SystemExit("the servers did not start within 300 s")
            times = {}
            for surface, one in (("OPC UA", lambda n: asyncio.run(_ua_refusal(ua_url, n))),
                                 ("operator page", lambda n: asyncio.run(_page_refusal(f"http://127.0.0.1:{port}", n)))):
                got = {KNOWN: [], UNKNOWN: []}
                for i in range(a.logins + 2):                 # 2 of each to warm up, not counted
                    for name in ((KNOWN, UNKNOWN) if i % 2 else (UNKNOWN, KNOWN)):
                        if os.path.exists(state):
                            os.unlink(state)
                        t = one(name)
                        if i >= 2:
                            got[name].append(t)
                times[surface] = got
        finally:
            child.kill()
    print(f"host: {os.cpu_count()} CPUs, {a.hogs} hogs at nice 0; load average {os.getloadavg()[0]:.1f}; "
          f"{a.logins} refusals per name and surface, interleaved")
    for surface, got in times.items():
        k, u = (np.asarray(got[n]) * 1e3 for n in (KNOWN, UNKNOWN))
        mk, mu = statistics.median(k), statistics.median(u)
        print(f"  {surface:13s} known name (wrong password): median {mk:7.1f} ms (p10 {np.percentile(k, 10):.1f}, "
              f"p90 {np.percentile(k, 90):.1f}); unknown name: median {mu:7.1f} ms (p10 {np.percentile(u, 10):.1f}, "
              f"p90 {np.percentile(u, 90):.1f}); unknown / known {mu / mk:.3f}")
    print(f"rerun: python benchmarks/bench_opcua.py --logins {a.logins} --hogs {a.hogs}")
    return 0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--hogs", type=int, default=4, help="CPU-bound processes at nice 0")
    ap.add_argument("--seconds", type=float, default=20.0, help="measured time per daemon [s]")
    ap.add_argument("--reads", type=int, default=2000, help="reads per session at most")
    ap.add_argument("--logins", type=int, default=0, metavar="N",
                    help="instead: N refused logins of a known and of an unknown name on each surface")
    a = ap.parse_args()
    hogs = [mp.Process(target=_spin, daemon=True) for _ in range(a.hogs)]
    for h in hogs:
        h.start()
    if a.logins:
        try:
            return logins(a)
        finally:
            for h in hogs:
                h.kill()
    try:
        res = {}
        for opcua in (False, True):
            with tempfile.TemporaryDirectory(prefix="bench-opcua-") as tmp:
                res[opcua] = measure(Path(tmp), opcua, a)
    finally:
        for h in hogs:
            h.kill()
    print(f"host: {os.cpu_count()} CPUs, {a.hogs} hogs at nice 0, {a.seconds:g} s per daemon; "
          f"load average {os.getloadavg()[0]:.1f}")
    w = res[True]
    print(f"with OPC UA: daemon ready {w['ready_s']:.1f} s; first read answered {w['first_s']:.1f} s "
          f"after the daemon's start")
    for name, lat in w["reads"].items():
        if lat:
            ms = np.asarray(lat) * 1e3
            print(f"  read ActPos, {name:30s} {len(ms):5d} reads: median {statistics.median(ms):.2f} ms, "
                  f"p99 {np.percentile(ms, 99):.2f} ms, max {ms.max():.1f} ms")
        else:
            print(f"  read ActPos, {name}: no read")
    for opcua in (False, True):
        r = res[opcua]
        print(f"{'with' if opcua else 'without':7s} OPC UA: I/O process {r['io_cpu']:.3f} CPU s/s, "
              f"OPC UA process {r['ua_cpu']:.3f} CPU s/s; turnaround p99.9 {r['p999_us']:.1f} us, "
              f"max {r['max_us']:.1f} us over {r['cycles']} cycles; missed periods {r['missed']}; "
              f"rows lost {r['lost_rows']}; faults {r['faults'] or 'none'}")
    print("rerun: python benchmarks/bench_opcua.py [--hogs N] [--seconds S] [--reads N]")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
