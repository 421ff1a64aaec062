"""The daemon's OPC UA server (docs/opcua.md), after OPC 40502 (OPC UA for CNC Systems), in a
process of its own: its life from the I/O process's fork to its end. The other jobs are in
modules of their own:

* :mod:`~motorctl.app.daemon.opcua_nodeset`: OPC 40502's facts (types, DataTypes, the Mandatory
  children with their DataTypes and EngineeringUnits, from the OPC Foundation's NodeSet);
* :mod:`~motorctl.app.daemon.opcua_space`: the address space built from them;
* :mod:`~motorctl.app.daemon.opcua_values`: the snapshot the I/O process sends, and what each
  variable shows of it;
* :mod:`~motorctl.app.daemon.opcua_methods`: the channel's methods (the control socket);
* :mod:`~motorctl.app.daemon.opcua_security` and :mod:`~motorctl.app.daemon.opcua_trust`: users,
  passwords, certificates, permissions, the transport's bounds.

How the values get here. The I/O process (:mod:`motorctl.app.daemon.io_side`) hands this
process a *snapshot* of figures it already holds (the newest row of the shared ring, the
status block, the motion filler's progress) every :data:`SNAPSHOT_EVERY_S` over a
non-blocking socket pair (:class:`OpcuaLink`, as :mod:`motorctl.app.daemon.metrics` does). A
send that would wait is dropped and counted, so a slow server or a slow client costs the I/O
process nothing; the server, not the I/O process, answers every OPC UA request. The
alternative, polling the control socket's ``status`` at 20 Hz and more, was not taken: a
``status`` builds the whole status (timing percentiles over 40 000-bin histograms per axis,
the log's figures, JSON) and costs a connection per poll in the process that drains the
recorder; the snapshot is a few dozen numbers (a pickle of 0.4 kB for two axes: 26 µs to
pickle on a 2-core host at load 12, that is 1.3 ms of CPU per second at 50 Hz; the I/O
process's CPU with and without the server: benchmarks/bench_opcua.py, docs/opcua.md), the
slower figures (turnaround percentiles, work offsets) only every :data:`SLOW_EVERY_S`.

Timestamps: a value's SourceTimestamp is the loop's own time of the row it comes from (the
master's clock, mapped onto UTC at the first snapshot), its ServerTimestamp the server's wall
clock. The process runs at nice :data:`OPCUA_NICE` (0), follows the I/O process off the loop's
CPU, and ends with the I/O process (EOF on the link, ``PR_SET_PDEATHSIG``).
"""

from __future__ import annotations

import asyncio
import logging
import os
import pickle
import socket
import sys

from motorctl.app.daemon.forked import SnapshotLink, fork_helper, helper_started
from motorctl.app.daemon.opcua_nodeset import CNC_NS
from motorctl.app.daemon.opcua_trust import TrustList, pki_dir  # noqa: F401 - motorctl.cli.opcua's
from motorctl.app.daemon.opcua_values import Columns, axes_info, snapshot

#: the I/O process sends a snapshot at most this often [s] (it wakes every 20 ms: 25-50 Hz)
SNAPSHOT_EVERY_S = 0.02
#: the slow figures (turnaround percentiles, work offsets) this often [s]
SLOW_EVERY_S = 1.0
#: the OPC UA process's niceness (the I/O process's own)
OPCUA_NICE = 0
#: snapshots the server reads per wake at most (the newest wins; the rest is skipped)
LINK_MESSAGES_PER_WAKE = 64


class OpcuaConfigError(ValueError):
    """daemon.opcua or daemon.users_file cannot be served: one line naming the key."""


# ---------------------------------------------------------------------------- I/O process side
def check_config(cfg) -> tuple:
    """Check what the server needs beyond the schema: the users file (loaded and checked), the
    certificate pair (both or neither, readable). Paths as given (a relative one from the
    daemon's working directory, as the operator page reads ``daemon.users_file``). Returns
    ``(users or None, cert, key)``. Raises OpcuaConfigError (one line)."""
    from motorctl.app.users import UsersError, load_users
    d = cfg.daemon
    oc = d.opcua
    users = None
    if d.users_file is not None:
        try:
            users = load_users(d.users_file)
        except UsersError as exc:
            raise OpcuaConfigError(f"daemon.users_file: {exc}") from None
    cert, key = oc.certificate, oc.private_key
    if (cert is None) != (key is None):
        raise OpcuaConfigError("daemon.opcua: certificate and private_key go together; allowed: both "
                               "(PEM or DER files) or neither (a self-signed pair is made)")
    out = []
    for name, p in (("certificate", cert), ("private_key", key)):
        if p is None:
            out.append(None)
            continue
        if not os.access(p, os.R_OK):
            raise OpcuaConfigError(f"daemon.opcua.{name}: {p}: not a readable file")
        out.append(p)
    if oc.anonymous == "off" and users is None:
        raise OpcuaConfigError("daemon.opcua.anonymous: off without daemon.users_file lets nobody in; "
                               "allowed: a users_file, or anonymous: read")
    return users, out[0], out[1]


class OpcuaLink(SnapshotLink):
    """The I/O process's end of the OPC UA process (:class:`.forked.SnapshotLink`: pid, sent,
    dropped, alive, build_s); the slow figures ride on one snapshot every :data:`SLOW_EVERY_S`."""

    def __init__(self, sock: socket.socket, pid: int, endpoint: str, cols: Columns):
        super().__init__(sock, pid, SNAPSHOT_EVERY_S)
        self.endpoint, self.cols = endpoint, cols
        self.last_slow = 0.0

    def snapshot(self, io, now: float) -> dict:
        slow = now - self.last_slow >= SLOW_EVERY_S
        if slow:
            self.last_slow = now
        self._slow = slow
        return snapshot(io, self.cols, slow)

    def dropped_one(self) -> None:
        if self._slow:
            self.last_slow = 0.0             # the next one carries them

    def report_line(self, text: str) -> str:
        if text == "ok":
            return f"motorctl: OPC UA on {self.endpoint}"
        return f"motorctl: warning: daemon.opcua {self.endpoint}: {text}"


def start_opcua(io) -> OpcuaLink | None:
    """Fork the OPC UA process (I/O process ``io``, before its threads start); None with one
    line on stderr when the ``opcua`` extra is missing, the users file or the certificate is
    wrong, or the fork fails. The line saying it serves comes later (:meth:`OpcuaLink.poll`)."""
    from motorctl.app.daemon.views import missing_extra
    loaded = io.plan.asm.loaded
    oc = loaded.cfg.daemon.opcua
    line = missing_extra("asyncua", "opcua", "OPC UA server")
    if line:
        sys.stderr.write(line + "\n")
        return None
    try:
        users, cert, key = check_config(loaded.cfg)
    except OpcuaConfigError as exc:
        sys.stderr.write(f"motorctl: error: {loaded.path}: {exc}; OPC UA not served\n")
        return None
    cert_dir = os.path.join(os.path.dirname(os.path.abspath(io.plan.log_path)), "opcua")
    pki = oc.pki_dir or cert_dir
    axes = axes_info(loaded, io.names)
    d = loaded.cfg.daemon
    forked = fork_helper("OPC UA", lambda sock, parent: opcua_main(
        sock, oc, users, cert, key, cert_dir, io.plan.socket_path, axes, d.max_program_bytes,
        parent, pki, d.login_lockout_s))
    if forked is None:
        return None
    return OpcuaLink(*forked, oc.endpoint, Columns(io.layout, io.names))




# ---------------------------------------------------------------------------- the OPC UA process
def opcua_main(sock: socket.socket, oc, users, cert, key, cert_dir: str, control: str, axes: list,
               max_program_bytes: int, parent_pid: int, pki: str | None = None,
               lockout_s: float | None = None) -> int:
    """The OPC UA process: serve ``oc.endpoint`` until the link closes. Returns 0."""
    helper_started(parent_pid, OPCUA_NICE)
    import gc
    gc.enable()              # the I/O process runs with it off; asyncio and asyncua make cycles
    logging.basicConfig(level=logging.CRITICAL)
    logging.getLogger("asyncua").setLevel(logging.CRITICAL)
    from motorctl.app.login import journal_to_stderr
    journal_to_stderr()
    srv = CncServer(oc, users, cert, key, cert_dir, control, axes, max_program_bytes, pki, lockout_s)
    return asyncio.run(srv.run(sock))



class CncServer:
    """The asyncua server and the CNC objects. ``axes``: :func:`~.opcua_values.axes_info`'s
    dicts in loop order (``name`` at least; the rest defaults to a real linear axis of unknown
    limits); ``control``: the daemon's control socket."""

    def __init__(self, oc, users, cert, key, cert_dir, control, axes, max_program_bytes, pki=None,
                 lockout_s=None):
        from motorctl.app.login import LOCKOUT_S, LoginGuard, state_path
        self.oc, self.users, self.cert, self.key, self.cert_dir = oc, users, cert, key, cert_dir
        self.trust = TrustList(pki or cert_dir)
        self.guard = LoginGuard(state_path(control), LOCKOUT_S if lockout_s is None else lockout_s, "OPC UA")
        nan = float("nan")
        self.axes = [{"rotational": False, "virtual": False, "u_lim": nan, "soft_m": (nan, nan), "v_max": nan,
                      **a} for a in axes]
        self.control, self.max_program_bytes = control, max_program_bytes
        self.names = [a["name"] for a in self.axes]

    async def setup(self):
        from asyncua import ua

        from motorctl.app.daemon.opcua_methods import program_limit
        from motorctl.app.daemon.opcua_security import (MESSAGE_OVERHEAD, certificate_files, refuse_clear_passwords,
                                                        ruleset, server_class, user_manager)
        self.app_uri = f"urn:{socket.gethostname()}:motorctl"
        anon = self.oc.anonymous == "read"
        um = user_manager(self.users, anon, self.guard, self.trust)
        s = self.server = server_class(program_limit(self.max_program_bytes) + MESSAGE_OVERHEAD)(user_manager=um)
        await s.init()
        refuse_clear_passwords(s.iserver, um)
        s.set_endpoint(self.oc.endpoint)
        s.set_server_name("motorctl")
        await s.set_application_uri(self.app_uri)
        s.product_uri = "urn:motorctl"
        s.manufacturer_name = "motorctl"
        policies = []
        if "None" in self.oc.security:
            policies.append(ua.SecurityPolicyType.NoSecurity)
        if "Basic256Sha256" in self.oc.security:
            policies += [ua.SecurityPolicyType.Basic256Sha256_Sign,
                         ua.SecurityPolicyType.Basic256Sha256_SignAndEncrypt]
        # on None too: passwords are encrypted with it
        cert, key = await certificate_files(self.cert, self.key, self.cert_dir, self.app_uri)
        await s.load_certificate(cert)
        await s.load_private_key(key)
        s.set_security_policy(policies, permission_ruleset=ruleset())
        s.set_identity_tokens(([ua.AnonymousIdentityToken] if anon else []) + [ua.UserNameIdentityToken])
        self.ns = await s.register_namespace(CNC_NS)
        await self._build()

    async def _build(self):
        """The CNC objects from OPC 40502's types, motorctl's own figures beside them, the
        methods, the constants."""
        from asyncua import ua

        from motorctl.app.daemon.opcua_methods import Methods
        from motorctl.app.daemon.opcua_space import AXES, CHANNEL, IFACE, Space
        from motorctl.app.daemon.opcua_values import Figures
        s, ns = self.server, self.ns
        D, B, S, U32, U64 = (ua.VariantType.Double, ua.VariantType.Boolean, ua.VariantType.String,
                             ua.VariantType.UInt32, ua.VariantType.UInt64)
        sp = self.space = Space(s, ns)
        await sp.build_types()
        iface = await sp.instantiate(s.nodes.objects, IFACE, "CncInterface", "CncInterfaceType")
        await sp.extra(iface, IFACE, "LoopTime", 0.0, D, "the loop's time of the newest snapshot [s] (motorctl)")
        await sp.extra(iface, IFACE, "LoopCycles", 0, U64, "cycles the loop has published (motorctl)")
        alist = s.get_node(ua.NodeId(AXES.rstrip("."), ns))
        nan = float("nan")
        for ax in self.axes:
            p = AXES + ax["name"]
            node = await sp.instantiate(alist, p, ax["name"], "CncAxisType")
            for name, value, vt, desc in (
                    ("Id", 0, U32, "1, 2, ... in loop order (motorctl)"),
                    ("ActPos", nan, D, "measured position [m] (motorctl; as PosDirect.ActPos)"),
                    ("CmdPos", nan, D, "commanded (setpoint) position [m] (motorctl; as PosDirect.CmdPos)"),
                    ("ActSpeed", nan, D, "velocity estimate [m/s] (motorctl)"),
                    ("CmdSpeed", nan, D, "commanded velocity [m/s] (motorctl)"),
                    ("FollowingError", nan, D, "measured - commanded position [m] (motorctl)"),
                    ("Enabled", False, B, "amplifier enabled (motorctl)"),
                    ("Phase", "", S, "the sequencer's mode (motorctl)"),
                    ("IsFaulted", False, B, "a fault is latched (motorctl)"),
                    ("FaultReason", "", S, "the latched fault in words (motorctl)"),
                    ("FaultBits", 0, U32, "latched fault bits (motorctl)"),
                    ("TurnaroundP50", nan, D, "loop turnaround median [us] (motorctl)"),
                    ("TurnaroundP99", nan, D, "loop turnaround 99th percentile [us] (motorctl)"),
                    ("TurnaroundMax", nan, D, "loop turnaround maximum [us] (motorctl)")):
                await sp.extra(node, p, name, value, vt, desc)
        clist = s.get_node(ua.NodeId("CncInterface.CncChannelList", ns))
        ch = await sp.instantiate(clist, CHANNEL, "CncChannel", "CncChannelType")
        for name, value, vt, desc in (
                ("FeedOverride", 100.0, D, "feed override [%] (motorctl; as ActOverride)"),
                ("ProgramDone", 1.0, D, "share of the program done 0..1 (motorctl)"),
                ("TimeLeft", 0.0, D, "time left at the current override [s] (motorctl)"),
                ("StoppedBecause", "", S, "why the last program ended early (motorctl)"),
                ("LastCommandError", "", S, "the daemon's answer to the last refused method (motorctl)")):
            await sp.extra(ch, CHANNEL, name, value, vt, desc)
        self.figures = Figures(sp, self.axes)
        self.methods = Methods(sp, self.figures, self.control, self.names, self.max_program_bytes)
        await self.methods.add(ch)
        await self.figures.constants()

    async def apply(self, snap: dict) -> None:
        """One snapshot's values (:meth:`.opcua_values.Figures.apply`)."""
        await self.figures.apply(snap)

    # ------------------------------------------------------------------ the run
    async def run(self, sock: socket.socket) -> int:
        loop = asyncio.get_running_loop()
        try:
            await self.setup()
            await self.server.start()
        except BaseException as exc:          # noqa: BLE001 - one line, no server
            sock.send((f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__).encode()[:4000])
            return 0
        sock.send(b"ok")
        sock.setblocking(False)
        done = loop.create_future()
        pending: list = []
        wake = asyncio.Event()

        def readable():
            for _ in range(LINK_MESSAGES_PER_WAKE):
                try:
                    data = sock.recv(1 << 20)
                except (BlockingIOError, InterruptedError):
                    break
                except OSError:
                    data = b""
                if not data:
                    if not done.done():
                        done.set_result(None)
                    break
                pending[:] = [data]          # the newest wins
            wake.set()

        loop.add_reader(sock.fileno(), readable)
        try:
            while not done.done():
                try:
                    await asyncio.wait_for(wake.wait(), 1.0)
                except asyncio.TimeoutError:
                    continue
                wake.clear()
                if pending:
                    data = pending.pop()
                    try:
                        await self.apply(pickle.loads(data))
                    except Exception as exc:  # noqa: BLE001 - a bad snapshot is skipped
                        logging.getLogger(__name__).debug("snapshot skipped: %r", exc)
        finally:
            loop.remove_reader(sock.fileno())
            try:
                await asyncio.wait_for(self.server.stop(), 2.0)
            except BaseException:             # noqa: BLE001
                pass
        return 0


def main(argv: list[str] | None = None) -> int:
    """``python -m motorctl.app.daemon.opcua_server CONFIG``: check daemon.opcua and the users
    file of CONFIG as the daemon will (exit 0), or one line and exit 2."""
    from motorctl.config import ConfigError, load_config
    argv = sys.argv[1:] if argv is None else argv
    if len(argv) != 1:
        sys.stderr.write("usage: python -m motorctl.app.daemon.opcua_server CONFIG\n")
        return 2
    try:
        loaded = load_config(argv[0])
    except ConfigError as exc:
        sys.stderr.write(f"motorctl: error: {exc}\n")
        return 2
    if loaded.cfg.daemon.opcua is None:
        sys.stdout.write(f"{argv[0]}: daemon.opcua is off\n")
        return 0
    try:
        check_config(loaded.cfg)
    except OpcuaConfigError as exc:
        sys.stderr.write(f"motorctl: error: {argv[0]}: {exc}\n")
        return 2
    sys.stdout.write(f"{argv[0]}: daemon.opcua ok ({loaded.cfg.daemon.opcua.endpoint})\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())


__all__ = ["OpcuaLink", "CncServer", "snapshot", "start_opcua", "check_config", "OpcuaConfigError",
           "CNC_NS", "SNAPSHOT_EVERY_S", "TrustList", "pki_dir"]
