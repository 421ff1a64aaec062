"""The daemon's OPC UA server (docs/opcua.md), after OPC 40502 (OPC UA for CNC Systems), in a
process of its own.

Address space (OPC 10000-3 objects and variables) on OPC 40502's own types, made here with the
NodeIds, BrowseNames, DataTypes and hierarchy of the OPC Foundation's published NodeSet
(Opc.Ua.CNC.NodeSet.xml 1.0.0: :data:`CNC_OBJECT_TYPES`, :data:`CNC_ENUMS`,
CncPositionVariableType) in its namespace :data:`CNC_NS`; the NodeSet file is not loaded::

    Objects/CncInterface                      (CncInterfaceType i=1007)
        CncChannelList/CncChannel             (CncChannelType i=1002): program, line, status,
                                              override, work offset; the methods
        CncAxisList/<axis>                    (CncAxisType i=1004), one per configured axis:
                                              PosDirect, PosIndirect (CncPositionVariableType
                                              i=2001: ActPos, CmdPos, RemDist [m]), ActStatus
                                              (CncAxisStatus i=3004), IsReferenced, ...
        CncSpindleList                        (CncSpindleListType i=1009), empty

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

Commands (the channel's methods, OPC 10000-4 5.11 Call) go the other way through the
daemon's Unix control socket (:mod:`motorctl.client`), as the operator's command line does:
the same checks by the I/O process and the loop, the same answers. A method is callable only
by a session of a user with the ``operator`` role (:mod:`motorctl.app.users`, checked at
ActivateSession, OPC 10000-4 5.6.3); an anonymous session (``daemon.opcua.anonymous: read``)
or a ``viewer`` may browse, read and subscribe, and a Call is answered BadUserAccessDenied.

Security (OPC 10000-4 6, OPC 10000-7): the policies of ``daemon.opcua.security``: None and
Basic256Sha256 with Sign and with SignAndEncrypt; without a configured certificate a
self-signed one (RSA 2048, asyncua's helpers over ``cryptography``) is made in
``LOG_DIR/opcua/`` at the first start and kept. A user name token must carry its password
encrypted with the server's certificate (OPC 10000-4 7.36.3; every endpoint's user token
policy says Basic256Sha256): a password in clear is refused (BadIdentityTokenRejected) before
it is looked at, whatever the channel. A channel's client certificate (Sign, SignAndEncrypt)
must be in the trust list (:class:`TrustList`, ``PKI_DIR/trusted``; ``motorctl opcua trust``):
an untrusted one is refused at ActivateSession (BadCertificateUntrusted), kept in
``PKI_DIR/rejected`` for the operator to accept, and journaled. Logins go through
:class:`motorctl.app.login.LoginGuard` (the operator page's check: constant time whatever the
name, back-off per name and address, lockout, journal).

Timestamps: a value's SourceTimestamp is the loop's own time of the row it comes from (the
master's clock, mapped onto UTC at the first snapshot), its ServerTimestamp the server's wall
clock.

The process runs at nice :data:`OPCUA_NICE` (0), follows the I/O process off the loop's CPU,
and ends with the I/O process (EOF on the link, ``PR_SET_PDEATHSIG``).
"""

from __future__ import annotations

import asyncio
import datetime as _dt
import logging
import math
import os
import pickle
import socket
import sys
import time

import numpy as np

from motorctl.app.daemon.forked import SnapshotLink, fork_helper, helper_started

#: the namespace of the CNC types and objects (OPC 40502's namespace URI, as its NodeSet has it)
CNC_NS = "http://opcfoundation.org/UA/CNC"
#: OPC 40502's ObjectTypes: (numeric NodeId in CNC_NS, BrowseName, supertype: a NodeId number
#: in CNC_NS, or "base" for BaseObjectType i=58, abstract), as the OPC Foundation's published
#: NodeSet (Opc.Ua.CNC.NodeSet.xml, 1.0.0 of 2017-06-19) defines them, supertypes first
CNC_OBJECT_TYPES = ((1001, "CncComponentType", "base", True), (1003, "CncDriveType", 1001, True),
                    (1004, "CncAxisType", 1003, False), (1005, "CncSpindleType", 1003, False),
                    (1002, "CncChannelType", 1001, False), (1007, "CncInterfaceType", "base", False),
                    (1008, "CncAxisListType", "base", False), (1009, "CncSpindleListType", "base", False),
                    (1010, "CncChannelListType", "base", False))
#: CncPositionVariableType (a BaseDataVariableType of DataType CncPositionDataType, a Structure)
CNC_POSITION_VARIABLE_TYPE, CNC_POSITION_DATA_TYPE = 2001, 3007
#: OPC 40502's enumeration DataTypes (NodeId number in CNC_NS, BrowseName, the values 0, 1, ...)
CNC_ENUMS = ((3001, "CncSpindleTurnDirection", ("None", "CW", "CCW")),
             (3002, "CncChannelProgramStatus", ("Stopped", "Running", "Waiting", "Interrupted", "Canceled")),
             (3003, "CncChannelStatus", ("Active", "Interrupted", "Reset")),
             (3004, "CncAxisStatus", ("InPosition", "Moving", "Parked")),
             (3005, "CncSpindleStatus", ("Stopped", "InTargetArea", "Accelerating", "Decelerating", "Parked")),
             (3006, "CncOperationMode", ("Manual", "MDA", "Automatic")))
#: EngineeringUnits (OPC 10000-8 5.6.3: UNECE Recommendation 20 common codes as UnitId):
#: (UnitId, DisplayName, Description)
EU_METRE = (5067858, "m", "metre")                 # MTR
EU_METRE_PER_SECOND = (5067859, "m/s", "metre per second")   # MTS
EU_PERCENT = (20529, "%", "percent")               # P1
EU_SECOND = (5457219, "s", "second")               # SEC
#: the I/O process sends a snapshot at most this often [s] (it wakes every 20 ms: 25-50 Hz)
SNAPSHOT_EVERY_S = 0.02
#: the slow figures (turnaround percentiles, work offsets) this often [s]
SLOW_EVERY_S = 1.0
#: the OPC UA process's niceness (the I/O process's own)
OPCUA_NICE = 0
#: snapshots the server reads per wake at most (the newest wins; the rest is skipped)
LINK_MESSAGES_PER_WAKE = 64
#: programs LoadProgram keeps at once (the oldest goes)
MAX_LOADED_PROGRAMS = 16
#: the files Start takes by path (nothing else on the daemon's host is read)
PROGRAM_SUFFIXES = (".ngc", ".nc", ".gcode", ".tap")
#: a command through the control socket is given up after this long [s]
COMMAND_TIMEOUT_S = 10.0

#: refused client certificates kept in PKI_DIR/rejected at most (the oldest go)
MAX_REJECTED = 64

#: CncChannelProgramStatus (OPC 40502): Stopped, Running, Waiting, Interrupted, Canceled
PROG_STOPPED, PROG_RUNNING, PROG_WAITING, PROG_INTERRUPTED, PROG_CANCELED = range(5)
#: CncChannelStatus (OPC 40502): Active, Interrupted, Reset
CH_ACTIVE, CH_INTERRUPTED, CH_RESET = range(3)
#: CncAxisStatus (OPC 40502): InPosition, Moving, Parked
AX_IN_POSITION, AX_MOVING, AX_PARKED = range(3)


class OpcuaConfigError(ValueError):
    """daemon.opcua or daemon.users_file cannot be served: one line naming the key."""


def pki_dir(cfg, log_dir: str | None = None) -> str:
    """The trust list's folder: ``daemon.opcua.pki_dir``, else ``LOG_DIR/opcua`` (``log_dir``:
    the daemon's, when it was given on its command line)."""
    oc = cfg.daemon.opcua
    if oc is not None and oc.pki_dir:
        return oc.pki_dir
    return os.path.join(log_dir or cfg.daemon.log_dir, "opcua")


class TrustList:
    """The client certificates the server accepts (OPC 10000-4 6.1.3, 10000-12 7.3 "trust
    list"): ``PKI_DIR/trusted/`` holds them (DER or PEM, one per file; a certificate is trusted
    itself, not through an issuer), ``PKI_DIR/rejected/`` the ones refused, kept (at most
    :data:`MAX_REJECTED`, as ``<thumbprint>.der``) for the operator to accept. Thumbprints are
    the SHA-1 of the DER bytes in hex (OPC 10000-6 6.2.3, as UaExpert shows them). The folder is
    read again when ``trusted/`` changes: no restart."""

    def __init__(self, pki: str):
        self.pki = pki
        self.trusted_dir = os.path.join(pki, "trusted")
        self.rejected_dir = os.path.join(pki, "rejected")
        self._mtime = None
        self._thumbs: set[str] = set()

    @staticmethod
    def thumbprint(der: bytes) -> str:
        import hashlib
        return hashlib.sha1(der).hexdigest()

    @staticmethod
    def load(data: bytes):
        """An X.509 certificate from DER or PEM bytes. Raises ValueError."""
        from cryptography import x509
        if data.lstrip().startswith(b"-----BEGIN"):
            return x509.load_pem_x509_certificate(data)
        return x509.load_der_x509_certificate(data)

    def _files(self, folder: str):
        try:
            names = sorted(os.listdir(folder))
        except OSError:
            return
        for n in names:
            path = os.path.join(folder, n)
            try:
                with open(path, "rb") as f:
                    cert = self.load(f.read())
            except (OSError, ValueError):
                continue
            yield path, cert

    def trusted(self) -> set[str]:
        """The thumbprints of the trusted certificates (read again when the folder changed)."""
        from cryptography.hazmat.primitives.serialization import Encoding
        try:
            m = os.stat(self.trusted_dir).st_mtime_ns
        except OSError:
            m = None
        if m != self._mtime:
            self._mtime = m
            self._thumbs = {self.thumbprint(c.public_bytes(Encoding.DER)) for _, c in self._files(self.trusted_dir)}
        return self._thumbs

    def refusal(self, der: bytes) -> str:
        """Why a client certificate (DER) is refused: "" when it is trusted and within its
        validity, else "untrusted", "expired" or "not yet valid"."""
        import datetime as dt
        if self.thumbprint(der) not in self.trusted():
            return "untrusted"
        cert = self.load(der)
        now = dt.datetime.now(dt.timezone.utc)
        if now > cert.not_valid_after_utc:
            return "expired"
        if now < cert.not_valid_before_utc:
            return "not yet valid"
        return ""

    def reject(self, der: bytes) -> str:
        """Keep a refused certificate in ``rejected/`` (the oldest beyond MAX_REJECTED go).
        Returns its path ("" when it cannot be written)."""
        try:
            os.makedirs(self.rejected_dir, mode=0o700, exist_ok=True)
            path = os.path.join(self.rejected_dir, self.thumbprint(der) + ".der")
            if not os.path.exists(path):
                with open(path, "wb") as f:
                    f.write(der)
            else:
                os.utime(path)
            old = sorted(os.listdir(self.rejected_dir),
                         key=lambda n: os.stat(os.path.join(self.rejected_dir, n)).st_mtime_ns)
            for n in old[:max(0, len(old) - MAX_REJECTED)]:
                os.unlink(os.path.join(self.rejected_dir, n))
            return path
        except OSError:
            return ""

    def listing(self) -> list[dict]:
        """Every certificate of ``trusted/`` and ``rejected/``: {state, thumbprint, subject,
        uri (the application URI of its subjectAltName), not_after, path}."""
        from cryptography import x509
        from cryptography.hazmat.primitives.serialization import Encoding
        out = []
        for state, folder in (("trusted", self.trusted_dir), ("rejected", self.rejected_dir)):
            for path, c in self._files(folder):
                try:
                    uris = c.extensions.get_extension_for_class(x509.SubjectAlternativeName).value \
                        .get_values_for_type(x509.UniformResourceIdentifier)
                except x509.ExtensionNotFound:
                    uris = []
                out.append({"state": state, "thumbprint": self.thumbprint(c.public_bytes(Encoding.DER)),
                            "subject": c.subject.rfc4514_string(), "uri": uris[0] if uris else "",
                            "not_after": c.not_valid_after_utc.strftime("%Y-%m-%d"), "path": path})
        return out

    def trust(self, what: str) -> dict:
        """Trust a certificate: ``what`` is a file (DER or PEM) or the thumbprint (or its first
        8+ hex digits) of a rejected one. It is written to ``trusted/<thumbprint>.der`` and
        leaves ``rejected/``. Returns its :meth:`listing` entry. Raises ValueError (one line)."""
        der = self._resolve(what, self.rejected_dir, "rejected")
        os.makedirs(self.trusted_dir, mode=0o700, exist_ok=True)
        t = self.thumbprint(der)
        path = os.path.join(self.trusted_dir, t + ".der")
        with open(path, "wb") as f:
            f.write(der)
        try:
            os.unlink(os.path.join(self.rejected_dir, t + ".der"))
        except OSError:
            pass
        return next(e for e in self.listing() if e["thumbprint"] == t and e["state"] == "trusted")

    def untrust(self, what: str) -> int:
        """Remove a certificate (file or thumbprint) from ``trusted/``: the files removed.
        Raises ValueError (one line)."""
        t = self.thumbprint(self._resolve(what, self.trusted_dir, "trusted"))
        gone = [e["path"] for e in self.listing() if e["state"] == "trusted" and e["thumbprint"] == t]
        for p in gone:
            os.unlink(p)
        return len(gone)

    def _resolve(self, what: str, folder: str, state: str) -> bytes:
        from cryptography.hazmat.primitives.serialization import Encoding
        if os.path.isfile(what):
            try:
                with open(what, "rb") as f:
                    return self.load(f.read()).public_bytes(Encoding.DER)
            except (OSError, ValueError) as exc:
                raise ValueError(f"{what}: not an X.509 certificate (DER or PEM): {exc}") from None
        w = what.lower().replace(":", "")
        if len(w) < 8 or any(c not in "0123456789abcdef" for c in w):
            raise ValueError(f"{what}: neither a certificate file nor a thumbprint (8 or more hex digits) "
                             f"of a {state} certificate")
        hits = {e["thumbprint"]: e["path"] for e in self.listing()
                if e["state"] == state and e["thumbprint"].startswith(w)}
        if len(hits) != 1:
            raise ValueError(f"{what}: {'no' if not hits else 'more than one'} {state} certificate with that "
                             f"thumbprint in {folder}; `motorctl opcua list` shows them")
        with open(next(iter(hits.values())), "rb") as f:
            return self.load(f.read()).public_bytes(Encoding.DER)


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


class _Columns:
    """Column indices of the fields a snapshot takes from a ring row."""

    def __init__(self, layout, names):
        ix = layout.index
        self.y = np.asarray([ix(f"{a}.y") for a in names])
        self.xd = np.asarray([ix(f"{a}.x_d") for a in names])
        self.v = np.asarray([ix(f"{a}.x2") for a in names])
        self.vd = np.asarray([ix(f"{a}.xd_dot") for a in names])
        self.e = np.asarray([ix(f"{a}.e") for a in names])
        self.en = np.asarray([ix(f"{a}.enabled") for a in names])
        self.t = layout.cycle("t")


def snapshot(io, cols: _Columns, slow: bool) -> dict:
    """The figures the server shows, from the I/O process's own state (``io``: its
    :class:`~motorctl.app.daemon.io_side.IOSide`); nothing is read from the loop but the status
    block and the newest row. Units: metres, m/s, seconds, µs; ``slow``: also the turnaround
    percentiles and the work offsets. Raises nothing the caller does not catch."""
    from motorctl.app.daemon.status import ST, fault_text
    from motorctl.loop.safety import with_drive_reason
    from motorctl.recorder.flight import CTL_REC_LATCHED, REC_REASONS

    ring, mo = io.plan.ring, io.motion
    row = ring.latest()
    st = ring.status
    n = len(io.names)
    bits = [int(b) for b in st[:, ST["fault"]]]
    modes = [int(m) for m in st[:, ST["mode"]]]
    nan = [math.nan] * n
    if row is None:
        t, y, xd, v, vd, e, en = 0.0, nan, nan, nan, nan, nan, [False] * n
    else:
        t = float(row[cols.t])
        y, xd, v = row[cols.y].tolist(), row[cols.xd].tolist(), row[cols.v].tolist()
        vd, e = row[cols.vd].tolist(), row[cols.e].tolist()
        en = [bool(x > 0) for x in row[cols.en]]
    faults = []
    rec = REC_REASONS.get(int(ring.ctl[CTL_REC_LATCHED]), "")
    for i in range(n):
        if bits[i]:
            text = fault_text(bits[i], st[i, ST["value"]], st[i, ST["limit"]], rec)
            faults.append(with_drive_reason(text, io.drive_reasons[i]))
        else:
            faults.append("")
    line, done, left = mo.progress()
    job = io.job
    snap = {"t": t, "cycles": int(ring.published()), "y": y, "x_d": xd, "v": v, "xd_dot": vd,
            "e": e, "enabled": en, "modes": modes, "fault_bits": bits, "faults": faults,
            "homed": [bool(h) for h in mo.homed], "line": int(line), "done": float(done),
            "left_s": float(left), "override": float(mo.override), "hold": bool(mo.holding),
            "aborting": bool(mo.aborting), "idle": bool(mo.idle()), "feed_m_s": float(mo.feed_m_s),
            "stopped_because": str(mo.reason),
            "program": job["job"].filename if job is not None else None}
    if slow:
        snap["turnaround"] = [{k: float(v) for k, v in io.drainer.axis_stats[i].summary().items()
                               if k.startswith("turnaround")} for i in range(n)]
        g54 = mo.work_offsets.get("G54")
        snap["zero_offset"] = [0.0] * n if g54 is None else [
            float(g54["XYZ".index(a)]) if a in "XYZ" and len(a) == 1 else 0.0 for a in io.names]
    return snap


class OpcuaLink(SnapshotLink):
    """The I/O process's end of the OPC UA process (:class:`.forked.SnapshotLink`: pid, sent,
    dropped, alive, build_s); the slow figures ride on one snapshot every :data:`SLOW_EVERY_S`."""

    def __init__(self, sock: socket.socket, pid: int, endpoint: str, cols: _Columns):
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
    axes = [{"name": a, "rotational": False} for a in io.names]
    d = loaded.cfg.daemon
    forked = fork_helper("OPC UA", lambda sock, parent: opcua_main(
        sock, oc, users, cert, key, cert_dir, io.plan.socket_path, axes, d.max_program_bytes,
        parent, pki, d.login_lockout_s))
    if forked is None:
        return None
    return OpcuaLink(*forked, oc.endpoint, _Columns(io.layout, io.names))


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


def _role_user(users, anonymous: bool, guard=None, trust: TrustList | None = None):
    """asyncua's user manager over :class:`motorctl.app.users.Users` (OPC 10000-4 5.6.3):
    operator -> UserRole.User (may Call), viewer -> UserRole.Anonymous with its name (reads),
    no name -> anonymous when allowed; None (BadUserAccessDenied / BadIdentityTokenRejected)
    otherwise. Names and passwords go through ``guard`` (:class:`motorctl.app.login.LoginGuard`:
    back-off, lockout, journal) with the client's address that :func:`_guard_tokens` noted; a
    channel's client certificate not in ``trust`` is refused (BadCertificateUntrusted), kept in
    its ``rejected/`` and journaled."""
    from asyncua import ua
    from asyncua.common.utils import ServiceError
    from asyncua.crypto.permission_rules import User, UserRole
    from asyncua.server.user_managers import UserManager

    from motorctl.app.login import JOURNAL
    from motorctl.app.users import UsersError, load_users

    class Users(UserManager):
        def __init__(self):
            self.users = users
            self.path = users.path if users is not None else None
            self.mtime = _mtime(self.path)
            self.peer = "?"                  # the address of the session being activated

        def check_certificate(self, der: bytes) -> None:
            """Raise ServiceError unless the channel's client certificate is trusted."""
            why = trust.refusal(der) if trust is not None else ""
            if not why:
                return
            try:
                c = TrustList.load(der)
                subject = c.subject.rfc4514_string()
            except ValueError:
                subject = "?"
            kept = trust.reject(der) if why == "untrusted" else ""
            JOURNAL.warning("OPC UA: client certificate refused (%s) from %s: %s, thumbprint %s%s", why,
                            self.peer, subject, TrustList.thumbprint(der),
                            f"; kept as {kept}: `motorctl opcua trust {TrustList.thumbprint(der)[:16]}` "
                            "accepts it" if kept else "")
            raise ServiceError(ua.StatusCodes.BadCertificateUntrusted if why == "untrusted"
                               else ua.StatusCodes.BadCertificateTimeInvalid)

        def current(self):
            """The users file, read again when its modification time changed (a file that has
            become wrong: no logins, one line on stderr)."""
            if self.path is None:
                return None
            m = _mtime(self.path)
            if m != self.mtime:
                self.mtime = m
                try:
                    self.users = load_users(self.path)
                except UsersError as exc:
                    self.users = None
                    sys.stderr.write(f"motorctl: warning: OPC UA logins off: {exc}\n")
            return self.users

        def get_user(self, iserver, username=None, password=None, certificate=None):
            peer, self.peer = self.peer, "?"
            if certificate:
                # the channel's client certificate (None on a None channel: _Factory), not an
                # X509 identity token (not offered)
                self.peer = peer
                self.check_certificate(certificate)
            if username is None:
                return User(role=UserRole.Anonymous) if anonymous else None
            now = self.current()
            if now is None or guard is None:
                JOURNAL.warning("login refused: %r from %s (OPC UA): logins are off", str(username)[:64], peer)
                return None
            try:
                v = guard.attempt(now, username, password, peer)
            except OSError as exc:
                JOURNAL.warning("login refused: %r from %s (OPC UA): the login state %s: %s", str(username)[:64],
                                peer, guard.path, exc.strerror or exc)
                return None
            if not v.ok:
                return None
            return User(role=UserRole.User if "operator" in v.roles else UserRole.Anonymous, name=username)

    return Users()


def _guard_tokens(iserver, um) -> None:
    """Refuse a user name token whose password is not encrypted (OPC 10000-4 7.36.3: the token
    policy says Basic256Sha256, so a conforming client encrypts it with the server's
    certificate; a password in clear has crossed the network readable): BadIdentityTokenRejected
    before the name or the password is looked at, journaled. Notes the client's address for the
    user manager ``um`` (ActivateSession runs the two one after the other, without a wait)."""
    from asyncua import ua
    from asyncua.common.utils import ServiceError

    from motorctl.app.login import JOURNAL
    decrypt = iserver.decrypt_user_token

    def checked(isession, token):
        peer = isession.name[0] if isinstance(isession.name, tuple) and isession.name else str(isession.name)
        um.peer = str(peer)
        if not token.EncryptionAlgorithm:
            JOURNAL.warning("login refused: %r from %s (OPC UA): the password was sent in clear (not encrypted "
                            "with the server's certificate, as the user token policy asks)",
                            str(token.UserName)[:64], um.peer)
            raise ServiceError(ua.StatusCodes.BadIdentityTokenRejected)
        return decrypt(isession, token)

    iserver.decrypt_user_token = checked


def _server_class():
    """asyncua's Server with two changes to its endpoints, made where it builds them: every
    user name token policy asks for the password encrypted with the server's certificate
    (Basic256Sha256; asyncua offers it in clear on a SignAndEncrypt channel), and a None
    channel carries no client certificate (OPC 10000-4 7.1: ignored with SecurityPolicy None),
    so the user manager sees one only on Sign and SignAndEncrypt channels."""
    from asyncua import Server, ua
    from asyncua.crypto import security_policies as sp

    class _Factory(sp.SecurityPolicyFactory):
        def create(self, peer_certificate):
            return super().create(None if self.mode == ua.MessageSecurityMode.None_ else peer_certificate)

    class CncUaServer(Server):
        async def _setup_server_nodes(self):
            await super()._setup_server_nodes()
            self._policies[:] = [_Factory(f.cls, f.mode, f.certificate, f.private_key, f.permission_ruleset)
                                 for f in self._policies]
            for edp in self.iserver.endpoints:
                for tok in edp.UserIdentityTokens:
                    if tok.TokenType == ua.UserTokenType.UserName:
                        tok.SecurityPolicyUri = sp.SecurityPolicyBasic256Sha256.URI

    return CncUaServer


def _mtime(path: str | None) -> int | None:
    try:
        return os.stat(path).st_mtime_ns if path else None
    except OSError:
        return None


def _ruleset():
    """Anonymous and viewer sessions: sessions, browse, read, subscriptions; an operator's also
    Call; nobody writes or changes the address space (OPC 10000-4 5.10.4, 5.7)."""
    from asyncua import ua
    from asyncua.crypto.permission_rules import USER_TYPES, PermissionRuleset, UserRole

    call = ua.NodeId(ua.ObjectIds.CallRequest_Encoding_DefaultBinary)
    write = ua.NodeId(ua.ObjectIds.WriteRequest_Encoding_DefaultBinary)
    read = {ua.NodeId(t) for t in USER_TYPES} - {call, write}

    class Rules(PermissionRuleset):
        def check_validity(self, user, action_type_id, body):
            if action_type_id in read:
                return True
            if action_type_id == call:
                return user is not None and user.role == UserRole.User
            return False

    return Rules()


def _status_of(fn):
    """A method whose refusal (a raised UaStatusCodeError) is the call's StatusCode (asyncua
    answers any exception BadUnexpectedError); wrong arguments are BadInvalidArgument."""
    from asyncua import ua

    async def method(parent, *args):
        try:
            return await fn(parent, *args)
        except ua.UaStatusCodeError as exc:
            return ua.StatusCode(exc.code)
        except (TypeError, ValueError, AttributeError):
            return ua.StatusCode(ua.StatusCodes.BadInvalidArgument)

    return method


class CncServer:
    """The asyncua server and the CNC objects (module docstring). ``axes``: [{name,
    rotational}] in loop order; ``control``: the daemon's control socket."""

    def __init__(self, oc, users, cert, key, cert_dir, control, axes, max_program_bytes, pki=None,
                 lockout_s=None):
        from motorctl.app.login import LOCKOUT_S, LoginGuard, state_path
        self.oc, self.users, self.cert, self.key, self.cert_dir = oc, users, cert, key, cert_dir
        self.trust = TrustList(pki or cert_dir)
        self.guard = LoginGuard(state_path(control), LOCKOUT_S if lockout_s is None else lockout_s, "OPC UA")
        self.control, self.axes, self.max_program_bytes = control, axes, max_program_bytes
        self.names = [a["name"] for a in axes]
        self.vars: dict = {}                 # key -> (node id, variant type)
        self.last: dict = {}                 # key -> the value written last
        self.programs: dict[str, str] = {}   # LoadProgram's programs by name
        self.program = ""                    # the program run last (name)
        self.base: float | None = None       # UTC [s] of loop time 0
        self.snapshots = 0

    # ------------------------------------------------------------------ set-up
    async def _certificate(self):
        """The (certificate, key) files: the configured pair, or the self-signed one in
        cert_dir (made at the first start)."""
        if self.cert is not None:
            return self.cert, self.key
        from pathlib import Path

        from asyncua.crypto.cert_gen import setup_self_signed_certificate
        from cryptography.x509.oid import ExtendedKeyUsageOID
        os.makedirs(self.cert_dir, mode=0o700, exist_ok=True)
        key, cert = Path(self.cert_dir, "server_key.pem"), Path(self.cert_dir, "server_cert.der")
        host = socket.gethostname()
        await setup_self_signed_certificate(key, cert, self.app_uri, host,
                                            [ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH],
                                            {"commonName": "motorctl", "organizationName": "motorctl"})
        return str(cert), str(key)

    async def setup(self):
        from asyncua import ua
        self.app_uri = f"urn:{socket.gethostname()}:motorctl"
        anon = self.oc.anonymous == "read"
        um = _role_user(self.users, anon, self.guard, self.trust)
        s = self.server = _server_class()(user_manager=um)
        await s.init()
        _guard_tokens(s.iserver, um)
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
        cert, key = await self._certificate()      # on None too: passwords are encrypted with it
        await s.load_certificate(cert)
        await s.load_private_key(key)
        s.set_security_policy(policies, permission_ruleset=_ruleset())
        s.set_identity_tokens(([ua.AnonymousIdentityToken] if anon else []) + [ua.UserNameIdentityToken])
        self.ns = await s.register_namespace(CNC_NS)
        await self._build()

    async def _types(self) -> dict:
        """OPC 40502's types with the NodeSet's NodeIds, BrowseNames and hierarchy
        (:data:`CNC_OBJECT_TYPES`, :data:`CNC_ENUMS`, CncPositionVariableType). Returns
        BrowseName -> NodeId."""
        from asyncua import ua
        from asyncua.common.structures104 import new_enum, new_enum_field, new_struct, new_struct_field
        s, ns = self.server, self.ns
        ids = {}
        for num, name, sup, abstract in CNC_OBJECT_TYPES:
            base = s.nodes.base_object_type if sup == "base" else s.get_node(ua.NodeId(sup, ns))
            t = await base.add_object_type(ua.NodeId(num, ns), ua.QualifiedName(name, ns))
            if abstract:
                await t.write_attribute(ua.AttributeIds.IsAbstract, ua.DataValue(ua.Variant(True, ua.VariantType.Boolean)))
            ids[name] = t.nodeid
        for num, name, values in CNC_ENUMS:
            dt = await new_enum(s, ua.NodeId(num, ns), ua.QualifiedName(name, ns), [new_enum_field(v) for v in values])
            evs = [ua.EnumValueType(Value=i, DisplayName=ua.LocalizedText(v)) for i, v in enumerate(values)]
            await dt.add_property(0, "EnumValues", ua.Variant(evs, ua.VariantType.ExtensionObject))
            ids[name] = dt.nodeid
        d = ua.VariantType.Double
        pos, _ = await new_struct(s, ua.NodeId(CNC_POSITION_DATA_TYPE, ns), ua.QualifiedName("CncPositionDataType", ns),
                                  [new_struct_field(f, d) for f in ("ActPos", "CmdPos", "RemDist")])
        ids["CncPositionDataType"] = pos.nodeid
        vt = await s.get_node(ua.NodeId(ua.ObjectIds.BaseDataVariableType)).add_variable_type(
            ua.NodeId(CNC_POSITION_VARIABLE_TYPE, ns), ua.QualifiedName("CncPositionVariableType", ns), pos.nodeid)
        ids["CncPositionVariableType"] = vt.nodeid
        return ids

    async def _eu(self, node, unit: tuple) -> None:
        """The EngineeringUnits property of ``node`` (OPC 10000-8 5.6.3 EUInformation)."""
        from asyncua import ua
        eu = ua.EUInformation(NamespaceUri="http://www.opcfoundation.org/UA/units/un/cefact", UnitId=unit[0],
                              DisplayName=ua.LocalizedText(unit[1]), Description=ua.LocalizedText(unit[2]))
        await node.add_property(0, "EngineeringUnits", ua.Variant(eu, ua.VariantType.ExtensionObject))

    async def _position(self, axis, p: str, name: str, desc: str):
        """A CncPositionVariable (PosDirect, PosIndirect) with its ActPos, CmdPos, RemDist [m]
        and EngineeringUnits (metre)."""
        from asyncua import ua
        ns = self.ns
        var = await axis.add_variable(ua.NodeId(f"{p}.{name}", ns), ua.QualifiedName(name, ns), None,
                                      varianttype=ua.VariantType.ExtensionObject, datatype=self.types["CncPositionDataType"])
        await var.add_reference(self.types["CncPositionVariableType"], ua.ObjectIds.HasTypeDefinition, True, False)
        await var.delete_reference(ua.NodeId(ua.ObjectIds.BaseDataVariableType), ua.ObjectIds.HasTypeDefinition,
                                   forward=True, bidirectional=False)
        await var.write_attribute(ua.AttributeIds.Description,
                                  ua.DataValue(ua.Variant(ua.LocalizedText(desc), ua.VariantType.LocalizedText)))
        for child, value, d in (("ActPos", math.nan, "measured position [m]"),
                                ("CmdPos", math.nan, "commanded position [m]"),
                                ("RemDist", 0.0, "distance left to the commanded position [m]")):
            await self._var(var, f"{p}.{name}", child, value, ua.VariantType.Double, d)
        await self._eu(var, EU_METRE)

    #: the EngineeringUnits of the variables by BrowseName
    UNITS = {"ActPos": EU_METRE, "CmdPos": EU_METRE, "FollowingError": EU_METRE, "ZeroOffset": EU_METRE,
             "ActSpeed": EU_METRE_PER_SECOND, "CmdSpeed": EU_METRE_PER_SECOND, "ActFeedrate": EU_METRE_PER_SECOND,
             "FeedOverride": EU_PERCENT, "LoopTime": EU_SECOND, "TimeLeft": EU_SECOND}
    #: the enumeration DataType of the variables by BrowseName (within their parent's type)
    ENUM_OF = {"CncAxisList": {"ActStatus": "CncAxisStatus"},
               "CncChannelList": {"ActStatus": "CncChannelStatus", "ActProgramStatus": "CncChannelProgramStatus"}}

    async def _var(self, parent, path: str, name: str, value, vtype, desc: str = ""):
        from asyncua import ua
        nid = ua.NodeId(f"{path}.{name}", self.ns)
        enum = next((e.get(name) for k, e in self.ENUM_OF.items() if f".{k}." in f".{path}."), None)
        node = await parent.add_variable(nid, ua.QualifiedName(name, self.ns), ua.Variant(value, vtype),
                                         datatype=self.types[enum] if enum else None)
        if name in self.UNITS and path.rsplit(".", 1)[-1] not in ("PosDirect", "PosIndirect"):
            await self._eu(node, self.UNITS[name])
        if desc:
            await node.write_attribute(ua.AttributeIds.Description,
                                       ua.DataValue(ua.Variant(ua.LocalizedText(desc), ua.VariantType.LocalizedText)))
        self.vars[f"{path}.{name}"] = (nid, vtype)
        self.last[f"{path}.{name}"] = value
        return node

    async def _build(self):
        from asyncua import ua
        s, ns = self.server, self.ns
        self.types = ty = await self._types()
        t_iface, t_list, t_clist, t_slist = (ty[n] for n in ("CncInterfaceType", "CncAxisListType",
                                                               "CncChannelListType", "CncSpindleListType"))
        t_axis, t_chan = ty["CncAxisType"], ty["CncChannelType"]
        D, B, S, I32, U32, U64 = (ua.VariantType.Double, ua.VariantType.Boolean, ua.VariantType.String,
                                  ua.VariantType.Int32, ua.VariantType.UInt32, ua.VariantType.UInt64)
        iface = await s.nodes.objects.add_object(ua.NodeId("CncInterface", ns), ua.QualifiedName("CncInterface", ns),
                                                 objecttype=t_iface)
        await self._var(iface, "CncInterface", "CncTypeName", "motorctl", S)
        await self._var(iface, "CncInterface", "LoopTime", 0.0, D,
                        "the loop's time of the newest snapshot [s] (motorctl)")
        await self._var(iface, "CncInterface", "LoopCycles", 0, U64, "cycles the loop has published (motorctl)")
        for name, value in (("VendorName", "motorctl"), ("VendorRevision", ""), ("Version", "1.0.0")):
            await iface.add_property(ua.NodeId(f"CncInterface.{name}", ns), ua.QualifiedName(name, ns),
                                     ua.Variant(value, S))
        alist = await iface.add_object(ua.NodeId("CncInterface.CncAxisList", ns),
                                       ua.QualifiedName("CncAxisList", ns), objecttype=t_list)
        clist = await iface.add_object(ua.NodeId("CncInterface.CncChannelList", ns),
                                       ua.QualifiedName("CncChannelList", ns), objecttype=t_clist)
        await iface.add_object(ua.NodeId("CncInterface.CncSpindleList", ns),     # no spindles: empty
                               ua.QualifiedName("CncSpindleList", ns), objecttype=t_slist)
        for j, ax in enumerate(self.axes):
            a = ax["name"]
            p = f"CncInterface.CncAxisList.{a}"
            node = await alist.add_object(ua.NodeId(p, ns), ua.QualifiedName(a, ns), objecttype=t_axis)
            await self._position(node, p, "PosDirect", "the axis's position from its own (linear) encoder")
            await self._position(node, p, "PosIndirect", "as PosDirect: the drive has no second measuring system")
            for name, value, vt, desc in (
                    ("Id", j + 1, U32, ""),
                    ("ActPos", math.nan, D, "measured position [m]"),
                    ("CmdPos", math.nan, D, "commanded (setpoint) position [m]"),
                    ("ActSpeed", math.nan, D, "velocity estimate [m/s]"),
                    ("CmdSpeed", math.nan, D, "commanded velocity [m/s]"),
                    ("FollowingError", math.nan, D, "measured - commanded position [m] (motorctl)"),
                    ("ActStatus", AX_PARKED, I32, "CncAxisStatus: 0 InPosition, 1 Moving, 2 Parked"),
                    ("IsReferenced", False, B, "homed"),
                    ("IsRotational", bool(ax["rotational"]), B, ""),
                    ("ZeroOffset", 0.0, D, "G54 work offset of this axis [m]"),
                    ("Enabled", False, B, "amplifier enabled (motorctl)"),
                    ("Phase", "", S, "the sequencer's mode (motorctl)"),
                    ("IsFaulted", False, B, "a fault is latched (motorctl)"),
                    ("FaultReason", "", S, "the latched fault in words (motorctl)"),
                    ("FaultBits", 0, U32, "latched fault bits (motorctl)"),
                    ("TurnaroundP50", math.nan, D, "loop turnaround median [us] (motorctl)"),
                    ("TurnaroundP99", math.nan, D, "loop turnaround 99th percentile [us] (motorctl)"),
                    ("TurnaroundMax", math.nan, D, "loop turnaround maximum [us] (motorctl)")):
                await self._var(node, p, name, value, vt, desc)
        p = "CncInterface.CncChannelList.CncChannel"
        ch = await clist.add_object(ua.NodeId(p, ns), ua.QualifiedName("CncChannel", ns), objecttype=t_chan)
        for name, value, vt, desc in (
                ("Id", 1, U32, ""),
                ("ActProgramName", "", S, "the program running or run last"),
                ("ActMainProgramName", "", S, "as ActProgramName (no subprograms)"),
                ("ActProgramLine", 0, U32, "source line of the motion the loop runs (0: none)"),
                ("ActProgramStatus", PROG_STOPPED, I32,
                 "CncChannelProgramStatus: 0 Stopped, 1 Running, 2 Waiting, 3 Interrupted, 4 Canceled"),
                ("ActStatus", CH_RESET, I32, "CncChannelStatus: 0 Active, 1 Interrupted, 2 Reset"),
                ("FeedOverride", 100.0, D, "feed override [%]"),
                ("FeedHold", False, B, "feed hold"),
                ("ActFeedrate", 0.0, D, "programmed path feed [m/s]"),
                ("ActModalOffsetFunction", 54, U32, "work offset system programs start in (G54)"),
                ("ProgramDone", 1.0, D, "share of the program done 0..1 (motorctl)"),
                ("TimeLeft", 0.0, D, "time left at the current override [s] (motorctl)"),
                ("StoppedBecause", "", S, "why the last program ended early (motorctl)"),
                ("LastCommandError", "", S, "the daemon's answer to the last refused method (motorctl)")):
            await self._var(ch, p, name, value, vt, desc)
        await self._methods(ch, p)

    async def _methods(self, ch, p):
        from asyncua import ua
        S, D = ua.VariantType.String, ua.VariantType.Double

        def arg(name, vt, desc):
            a = ua.Argument()
            a.Name, a.DataType, a.ValueRank = name, ua.NodeId(vt.value), -1
            a.Description = ua.LocalizedText(desc)
            return a

        out = [arg("Result", S, "the daemon's answer (JSON)")]
        axis = arg("Axis", S, f"axis name ({', '.join(self.names)}); empty: every axis (Enable), "
                              "every faulted axis (FaultReset)")
        for name, fn, ins in (
                ("Start", self.m_start, [arg("Program", S, "a name given to LoadProgram, or a file path on "
                                                           "the daemon's host")]),
                ("LoadProgram", self.m_load, [arg("Name", S, "the program's name"),
                                              arg("Text", S, "G-code")]),
                ("Stop", self.m_stop, []), ("Hold", self.m_simple("hold"), []),
                ("Resume", self.m_simple("resume"), []), ("Abort", self.m_simple("abort"), []),
                ("Home", self.m_axis("home", False), [axis]),
                ("FaultReset", self.m_axis("fault-reset", True), [axis]),
                ("Enable", self.m_enable, [axis]),
                ("SetFeedOverride", self.m_override, [arg("Percent", D, "0 .. 150")])):
            await ch.add_method(ua.NodeId(f"{p}.{name}", self.ns), ua.QualifiedName(name, self.ns),
                                _status_of(fn), ins, out)

    # ------------------------------------------------------------------ methods
    async def _cmd(self, req: dict, timeout_s: float = COMMAND_TIMEOUT_S, program: tuple | None = None) -> dict:
        """One request through the control socket (a thread: the server goes on meanwhile)."""
        from motorctl.client import DaemonUnreachable, call, send_program
        try:
            if program is not None:
                ans = await asyncio.to_thread(send_program, self.control, program[1], program[0], timeout_s)
            else:
                ans = await asyncio.to_thread(call, self.control, req, timeout_s)
        except DaemonUnreachable as exc:
            ans = {"ok": False, "error": str(exc), "usage": False}
        return ans

    async def _answer(self, ans: dict):
        """The method's output, or its refusal as a status code (the reason in LastCommandError)."""
        import json

        from asyncua import ua
        if not ans.get("ok"):
            await self._write("CncInterface.CncChannelList.CncChannel.LastCommandError", ans.get("error", "refused"))
            raise ua.UaStatusCodeError(ua.StatusCodes.BadInvalidArgument if ans.get("usage")
                                       else ua.StatusCodes.BadInvalidState)
        ans.pop("status", None)
        return [ua.Variant(json.dumps(ans, default=str), ua.VariantType.String)]

    async def m_load(self, parent, name, text):
        from asyncua import ua
        name, text = str(name.Value or ""), str(text.Value or "")
        if not name or len(text.encode("utf-8", "surrogatepass")) > self.max_program_bytes:
            raise ua.UaStatusCodeError(ua.StatusCodes.BadInvalidArgument)
        self.programs.pop(name, None)
        self.programs[name] = text
        while len(self.programs) > MAX_LOADED_PROGRAMS:
            self.programs.pop(next(iter(self.programs)))
        return [ua.Variant(f'{{"ok": true, "loaded": {len(text)}}}', ua.VariantType.String)]

    async def m_start(self, parent, prog):
        from asyncua import ua
        name = str(prog.Value or "")
        if name in self.programs:
            text = self.programs[name]
        else:
            if not name.lower().endswith(PROGRAM_SUFFIXES):
                await self._write("CncInterface.CncChannelList.CncChannel.LastCommandError",
                                  f"Start: {name!r}: no program loaded by that name, and not a G-code "
                                  f"file ({', '.join(PROGRAM_SUFFIXES)})")
                raise ua.UaStatusCodeError(ua.StatusCodes.BadNotFound)
            try:
                if os.path.getsize(name) > self.max_program_bytes:
                    raise ua.UaStatusCodeError(ua.StatusCodes.BadInvalidArgument)
                with open(name, encoding="utf-8", errors="surrogateescape") as fh:
                    text = fh.read()
            except OSError as exc:
                await self._write("CncInterface.CncChannelList.CncChannel.LastCommandError",
                                  f"Start: {name!r}: no program loaded by that name, and not a readable "
                                  f"file ({exc.strerror})")
                raise ua.UaStatusCodeError(ua.StatusCodes.BadNotFound) from None
            name = os.path.basename(name)
        ans = await self._cmd({}, 30.0, program=(name, text))
        if ans.get("ok"):
            self.program = name
        return await self._answer(ans)

    def m_simple(self, cmd: str):
        async def m(parent):
            return await self._answer(await self._cmd({"cmd": cmd}))
        return m

    def _axes_of(self, v) -> list[str]:
        from asyncua import ua
        name = str(v.Value or "")
        if not name:
            return list(self.names)
        if name not in self.names:
            raise ua.UaStatusCodeError(ua.StatusCodes.BadInvalidArgument)
        return [name]

    def m_axis(self, cmd: str, faulted_only: bool):
        """Home (one axis: homing one runs at a time) or FaultReset ("" = every faulted axis)."""
        from asyncua import ua

        async def m(parent, axis):
            names = self._axes_of(axis)
            if len(names) > 1:
                if not faulted_only:
                    raise ua.UaStatusCodeError(ua.StatusCodes.BadInvalidArgument)
                names = [a for a in names if self.last.get(f"CncInterface.CncAxisList.{a}.IsFaulted")]
            ans = {"ok": True}
            for a in names:
                ans = await self._cmd({"cmd": cmd, "axis": a})
                if not ans.get("ok"):
                    break
            return await self._answer(ans)
        return m

    async def m_enable(self, parent, axis):
        ans = {"ok": True}
        for a in self._axes_of(axis):
            if self.last.get(f"CncInterface.CncAxisList.{a}.Phase") == "command":
                continue
            ans = await self._cmd({"cmd": "start", "axis": a, "mode": "command"})
            if not ans.get("ok"):
                break
        return await self._answer(ans)

    async def m_stop(self, parent):
        ans = {"ok": True}
        for a in self.names:
            if self.last.get(f"CncInterface.CncAxisList.{a}.Enabled") or \
                    self.last.get(f"CncInterface.CncAxisList.{a}.Phase") not in ("disabled", ""):
                ans = await self._cmd({"cmd": "stop", "axis": a})
                if not ans.get("ok"):
                    break
        return await self._answer(ans)

    async def m_override(self, parent, pct):
        return await self._answer(await self._cmd({"cmd": "override", "value": float(pct.Value) / 100.0}))

    # ------------------------------------------------------------------ values
    async def _write(self, key: str, value, ts=None, always: bool = False) -> None:
        from asyncua import ua
        if not always and self.last.get(key) == value and not (isinstance(value, float) and math.isnan(value)):
            return
        self.last[key] = value
        nid, vt = self.vars[key]
        dv = ua.DataValue(ua.Variant(value, vt), SourceTimestamp=ts,
                          ServerTimestamp=_dt.datetime.now(_dt.timezone.utc))
        await self.server.write_attribute_value(nid, dv)

    async def apply(self, snap: dict) -> None:
        """Write one snapshot's values: the live figures every time (their SourceTimestamp is
        the row's loop time), the others when they changed."""
        from motorctl.loop.servo import MODE_NAMES
        if self.base is None:
            self.base = time.time() - snap["t"]
        ts = _dt.datetime.fromtimestamp(self.base + snap["t"], _dt.timezone.utc)
        w = self._write
        await w("CncInterface.LoopTime", snap["t"], ts, True)
        await w("CncInterface.LoopCycles", snap["cycles"], ts)
        for i, a in enumerate(self.names):
            p = f"CncInterface.CncAxisList.{a}."
            for key, field in (("ActPos", "y"), ("CmdPos", "x_d"), ("ActSpeed", "v"),
                               ("CmdSpeed", "xd_dot"), ("FollowingError", "e")):
                await w(p + key, float(snap[field][i]), ts, True)
            for pos in ("PosDirect.", "PosIndirect."):
                await w(p + pos + "ActPos", float(snap["y"][i]), ts, True)
                await w(p + pos + "CmdPos", float(snap["x_d"][i]), ts, True)
                await w(p + pos + "RemDist", -float(snap["e"][i]), ts)
            mode, en = snap["modes"][i], snap["enabled"][i]
            moving = abs(snap["xd_dot"][i]) > 0.0
            await w(p + "ActStatus", AX_PARKED if not en else (AX_MOVING if moving else AX_IN_POSITION), ts)
            await w(p + "IsReferenced", snap["homed"][i], ts)
            await w(p + "Enabled", en, ts)
            await w(p + "Phase", MODE_NAMES.get(mode, "?"), ts)
            await w(p + "IsFaulted", bool(snap["fault_bits"][i]), ts)
            await w(p + "FaultBits", snap["fault_bits"][i], ts)
            await w(p + "FaultReason", snap["faults"][i], ts)
            if "turnaround" in snap:
                tr = snap["turnaround"][i]
                await w(p + "TurnaroundP50", tr["turnaround_p50_us"], ts)
                await w(p + "TurnaroundP99", tr["turnaround_p99_us"], ts)
                await w(p + "TurnaroundMax", tr["turnaround_max_us"], ts)
                await w(p + "ZeroOffset", snap["zero_offset"][i], ts)
        c = "CncInterface.CncChannelList.CncChannel."
        if snap["program"]:
            self.program = snap["program"]
        running = not snap["idle"]
        if snap["hold"] and running:
            prog, chan = PROG_INTERRUPTED, CH_INTERRUPTED
        elif running:
            prog, chan = (PROG_CANCELED if snap["aborting"] else PROG_RUNNING), CH_ACTIVE
        else:
            prog, chan = (PROG_CANCELED if snap["stopped_because"] else PROG_STOPPED), CH_RESET
        await w(c + "ActProgramName", self.program, ts)
        await w(c + "ActMainProgramName", self.program, ts)
        await w(c + "ActProgramLine", snap["line"], ts)
        await w(c + "ActProgramStatus", prog, ts)
        await w(c + "ActStatus", chan, ts)
        await w(c + "FeedOverride", snap["override"] * 100.0, ts)
        await w(c + "FeedHold", snap["hold"], ts)
        await w(c + "ActFeedrate", snap["feed_m_s"], ts)
        await w(c + "ProgramDone", snap["done"], ts)
        await w(c + "TimeLeft", snap["left_s"], ts)
        await w(c + "StoppedBecause", snap["stopped_because"], ts)
        self.snapshots += 1

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


def ua_nodeid(ns: int, name: str):
    from asyncua import ua
    return ua.NodeId(name, ns)


def ua_qn(ns: int, name: str):
    from asyncua import ua
    return ua.QualifiedName(name, ns)


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
           "CNC_NS", "SNAPSHOT_EVERY_S"]
