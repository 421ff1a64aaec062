"""``motorctl daemon CONFIG``: the long-running service that runs the 5 kHz loop.

Two processes, so that nothing can block the loop (docs/daemon.md):

* the **loop process** (the main PID; SCHED_FIFO, mlockall, gc frozen and disabled, pinned to a
  CPU): one thread, the :class:`~motorctl.servo.ServoLoop` on the driver. Its records go into a
  shared-memory ring (:class:`~motorctl.recorder.SharedRing`), its heartbeat is a shared
  counter. Between cycles (the ``on_slack`` hook) it looks at a shared command sequence number
  and only then reads the command pipe (non-blocking), applies commands at the cycle boundary
  and answers on a reply pipe (small pickled messages, atomic below PIPE_BUF). No file or
  socket I/O, no other Python thread.
* the **I/O process** (forked before the real-time set-up; SCHED_OTHER, on the other CPUs):
  serves the Unix control socket, prepares commands (approach moves, controller choice),
  drains the ring to the append-only run log and ``fdatasync``\\ s it at least every
  ``daemon.flush_s``, cuts event logs around faults and overruns, keeps the turnaround and
  lateness histograms for ``status``, and speaks systemd's notify protocol: ``READY=1`` once
  the loop runs, ``STATUS=``, ``WATCHDOG=1`` only while the loop's heartbeat advances (a stalled
  loop lets systemd's watchdog fire), ``STOPPING=1``.

Every axis starts disabled (0 V, amplifier off) and only an operator's ``start`` enables it,
so a restart by systemd never re-enables an axis. SIGTERM/SIGINT: every driven axis latches
FAULT_SHUTDOWN and goes to 0 V with the amplifier off at the next cycle, a few more cycles are
recorded, the I/O process drains, flushes and closes the log, then the daemon exits 0.
``kill -9`` of the loop process: the I/O process sees the reply pipe close, drains what the
loop published and closes the log. If the I/O process dies, the loop faults every axis and
exits non-zero (no motion without a recorder).

Protocol on the socket: one JSON object per line each way, e.g. ``{"cmd": "start",
"axis": "X", "controller": "c2"}`` → ``{"ok": true, ...}`` or ``{"ok": false, "error": "...",
"usage": false}``.
"""

from __future__ import annotations

import datetime as _dt
import grp
import json
import os
import pickle
import selectors
import signal
import socket
import struct
import sys
import threading
import time
from pathlib import Path

from motorctl.config import LoadedConfig, load_config
from motorctl.recorder import (CTL_CMD_SEQ, CTL_STATE, ST_FAULT, ST_FE_PEAK, ST_IO_ERRORS,
                               ST_KIND, ST_LIMIT, ST_MODE, ST_SIZE, ST_STARTED_K, ST_VALUE,
                               Drainer, SharedRing)
from motorctl.runlog import LogWriter, columns_for
from motorctl.safety import FAULT_SHUTDOWN, Supervisor, describe_faults
from motorctl.servo import IDLE, MODE_NAMES, ServoLoop
from motorctl.trajectory import Move

KINDS = {"c1": 1.0, "c2": 2.0}
KIND_NAMES = {1: "c1", 2: "c2"}
_HDR = struct.Struct("<I")


class DaemonError(RuntimeError):
    """The daemon cannot start (one line, e.g. the socket cannot be created)."""


# --------------------------------------------------------------------------- sd_notify
def sd_notify(message: str) -> bool:
    """Send one datagram to ``$NOTIFY_SOCKET`` (sd_notify(3)); False when not under systemd.

    ``message`` is e.g. "READY=1", "STATUS=...", "WATCHDOG=1", "STOPPING=1". An address
    starting with '@' is in the abstract namespace.
    """
    addr = os.environ.get("NOTIFY_SOCKET")
    if not addr:
        return False
    if addr[0] == "@":
        addr = "\0" + addr[1:]
    try:
        with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC) as s:
            s.connect(addr)
            s.sendall(message.encode())
        return True
    except OSError:
        return False


# --------------------------------------------------------------------------- pipes
class Mailbox:
    """Length-prefixed pickled messages over a pipe; the read side is non-blocking."""

    def __init__(self, rfd: int | None = None, wfd: int | None = None):
        self.rfd, self.wfd = rfd, wfd
        self._buf = b""
        if rfd is not None:
            os.set_blocking(rfd, False)

    def send(self, obj) -> None:
        data = pickle.dumps(obj, protocol=pickle.HIGHEST_PROTOCOL)
        os.write(self.wfd, _HDR.pack(len(data)) + data)

    def recv(self) -> list | None:
        """Messages available now ([] if none); None when the writer has closed the pipe."""
        eof = False
        while True:
            try:
                chunk = os.read(self.rfd, 65536)
            except BlockingIOError:
                break
            if not chunk:
                eof = True
                break
            self._buf += chunk
        out = []
        while len(self._buf) >= 4:
            (n,) = _HDR.unpack_from(self._buf)
            if len(self._buf) < 4 + n:
                break
            out.append(pickle.loads(self._buf[4:4 + n]))
            self._buf = self._buf[4 + n:]
        if eof and not out:
            return None
        return out


# --------------------------------------------------------------------------- socket
def _resolve_group(group) -> int | None:
    if group is None:
        return None
    if isinstance(group, int):
        return group
    try:
        return grp.getgrnam(group).gr_gid
    except KeyError:
        raise DaemonError(f"daemon.group: no group named {group!r}") from None


def bind_control_socket(path: str, group=None) -> socket.socket:
    """Create the listening Unix socket at ``path`` with mode 0660 and the given group.

    A stale socket file is replaced; a live one (another daemon answers) is an error.
    Raises:
        DaemonError: one line naming the path and the reason (permission, missing directory,
        another daemon running, unknown group).
    """
    gid = _resolve_group(group)
    p = Path(path)
    if not p.parent.exists() and str(p.parent).startswith("/run/motorctl"):
        try:
            os.makedirs(p.parent, mode=0o750, exist_ok=True)
        except OSError as exc:
            raise DaemonError(f"cannot create {p.parent}: {exc.strerror}") from None
    if p.exists() or p.is_socket():
        probe = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            probe.connect(str(p))
            probe.close()
            raise DaemonError(f"another daemon is already serving {p}")
        except (ConnectionRefusedError, FileNotFoundError):
            pass
        except PermissionError:
            raise DaemonError(f"cannot use the control socket {p}: permission denied") from None
        finally:
            probe.close()
        try:
            p.unlink()
        except OSError as exc:
            raise DaemonError(f"cannot replace the stale socket {p}: {exc.strerror}") from None
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM | socket.SOCK_CLOEXEC)
    old = os.umask(0o117)
    try:
        s.bind(str(p))
    except OSError as exc:
        s.close()
        raise DaemonError(f"cannot create the control socket {p}: {exc.strerror}") from None
    finally:
        os.umask(old)
    try:
        os.chmod(p, 0o660)
        if gid is not None:
            os.chown(p, -1, gid)
    except OSError as exc:
        s.close()
        p.unlink(missing_ok=True)
        raise DaemonError(f"cannot set the group/mode of {p}: {exc.strerror}") from None
    s.listen(16)
    return s


# --------------------------------------------------------------------------- the daemon
class _Shared:
    """What both processes know after the fork (built before it)."""

    def __init__(self, loaded: LoadedConfig, socket_path: str, log_path: str):
        cfg = loaded.cfg
        self.loaded = loaded
        self.names = list(loaded.axes)
        self.period_s = loaded.period_s
        self.socket_path = socket_path
        self.log_path = log_path
        d = cfg.daemon
        ring_s = d.event_before_s + d.event_after_s + 3.0
        self.columns = columns_for(self.names)
        self.ring = SharedRing(int(ring_s / self.period_s), len(self.columns), len(self.names))
        self.programs = [loaded.axes[a].trajectory.program() for a in self.names]
        self.stop_bound_s = []
        for a, prog in zip(self.names, self.programs):
            longest = max((m.duration for m in prog.moves), default=0.0)
            self.stop_bound_s.append(longest + d.stop_settle_s + 0.05)


def _header(sh: _Shared, extra: dict) -> dict:
    from motorctl.job import software_version
    cfg = sh.loaded.cfg
    h = {
        "format": 1,
        "software": f"motorctl {software_version()}",
        "kind": "daemon run log",
        "started": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        "config_file": str(sh.loaded.path),
        "config": cfg.model_dump(mode="json"),
        "driver_type": cfg.driver.type,
        "axes": sh.names,
        "controllers": {a: cfg.axes[a].controller.type for a in sh.names},
        "period_s": sh.period_s,
        "clock": "wall",
        "columns": sh.columns,
    }
    h.update(extra)
    return h


def run_daemon(config_path: str, socket_path: str | None = None, log_dir: str | None = None,
               out=sys.stderr) -> int:
    """Run the service until SIGTERM/SIGINT. Returns the exit code (0 after a signal).

    Raises:
        ConfigError: the config is wrong (exit 2 in the CLI).
        DaemonError: the socket or the log cannot be created (exit 1).
    """
    loaded = load_config(config_path)
    cfg = loaded.cfg
    d = cfg.daemon
    if cfg.loop.clock != "wall":
        from motorctl.config import ConfigError
        raise ConfigError(loaded.path, "loop.clock", "the daemon runs on the wall clock; set clock: wall")
    sock_path = socket_path or d.socket
    ldir = Path(log_dir or d.log_dir)
    try:
        ldir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise DaemonError(f"cannot create the log directory {ldir}: {exc.strerror}") from None
    stamp = _dt.datetime.now().strftime("%Y%m%dT%H%M%S")
    log_path = str(ldir / f"motorctl-{stamp}-{os.getpid()}.mlog")
    sh = _Shared(loaded, sock_path, log_path)
    names = sh.names
    # controllers for both kinds, built (and compiled) before anything runs: a switch is a swap
    ctrls = {k: loaded.make_controllers(names, k) for k in KINDS}
    driver = loaded.make_driver(names)
    sup = Supervisor([loaded.axes[a].limits for a in names], loaded.period_s)

    lsock = bind_control_socket(sock_path, d.group)
    try:
        writer = LogWriter(log_path, _header(sh, {"realtime": "pending"}), reserve=16384)
    except OSError as exc:
        lsock.close()
        Path(sock_path).unlink(missing_ok=True)
        raise DaemonError(f"cannot create the run log {log_path}: {exc.strerror}") from None
    cmd_r, cmd_w = os.pipe()
    rep_r, rep_w = os.pipe()
    sys.stdout.flush()
    sys.stderr.flush()
    pid = os.fork()
    if pid == 0:                                   # ---- the I/O process
        code = 1
        try:
            os.close(cmd_r)
            os.close(rep_w)
            code = _io_main(sh, lsock, writer, Mailbox(wfd=cmd_w), Mailbox(rfd=rep_r))
        except BaseException as exc:               # noqa: BLE001 - last resort, one line
            try:
                sys.stderr.write(f"motorctl daemon (I/O process): {type(exc).__name__}: {exc}\n")
            except Exception:
                pass
        finally:
            os._exit(code)
    # ---- the loop process
    os.close(cmd_w)
    os.close(rep_r)
    os.set_blocking(rep_w, False)   # a stalled I/O process must never block the loop
    lsock.close()
    writer.release()
    return _loop_main(sh, driver, ctrls, sup, pid, Mailbox(rfd=cmd_r), Mailbox(wfd=rep_w), out)


def _loop_main(sh: _Shared, driver, ctrls, sup, io_pid: int, cmds: Mailbox, replies: Mailbox, out) -> int:
    from motorctl.rt import RealtimeError, setup_realtime
    cfg = sh.loaded.cfg
    d = cfg.daemon
    rtc = cfg.loop.realtime
    names = sh.names
    n = len(names)
    ring = sh.ring
    kinds = [cfg.axes[a].controller.type for a in names]
    loop = ServoLoop(driver, [ctrls[kinds[i]][i] for i in range(n)], sh.programs, sup, sh.period_s,
                     capacity=ring.capacity, clock="wall", spin_us=rtc.spin_us, buffer=ring.rows,
                     heartbeat=memoryview(ring.ctl), overrun_policy=cfg.loop.overrun_policy,
                     overrun_hold=cfg.loop.overrun_hold_cycles,
                     overrun_ramp=int(round(cfg.loop.overrun_ramp_s / sh.period_s)))
    loop.idle_all()
    loop.disable_on_fault = True
    loop.stop_settle = int(round(d.stop_settle_s / sh.period_s))
    ctl = memoryview(ring.ctl)
    smv = memoryview(ring.status.reshape(-1))
    state = {"seen": 0, "term": "", "tail": -1, "io_dead": False, "started_k": [0] * n,
             "replies_dropped": 0}
    allow_inject = d.allow_fault_injection and hasattr(driver, "inject")

    published_fault = [0] * n

    def publish() -> None:
        for i in range(n):
            published_fault[i] = sup.fault[i]
            b = i * ST_SIZE
            smv[b + ST_MODE] = float(loop.mode[i])
            smv[b + ST_KIND] = KINDS[kinds[i]]
            smv[b + ST_FAULT] = float(sup.fault[i])
            smv[b + ST_VALUE] = sup.value_at_fault[i]
            smv[b + ST_LIMIT] = sup.limit_at_fault[i]
            smv[b + ST_IO_ERRORS] = float(sup.io_errors[i])
            smv[b + ST_FE_PEAK] = sup.fe_peak[i]
            smv[b + ST_STARTED_K] = float(state["started_k"][i])

    def handle(m: dict) -> dict:
        op, i = m.get("op"), m.get("axis", -1)
        r = {"id": m.get("id"), "ok": True, "cycle": loop.k}
        try:
            if op == "start":
                if sup.fault[i]:
                    return {**r, "ok": False, "error": f"axis {names[i]} is in fault: {sup.reason(i)}; "
                                                      f"run 'motorctl fault-reset {names[i]}' first"}
                if loop.mode[i] != IDLE:
                    return {**r, "ok": False, "error": f"axis {names[i]} is already enabled "
                                                      f"({MODE_NAMES[loop.mode[i]]})"}
                mv = m["move"]
                y = float(driver.position_m[i])
                if abs(mv.start - y) > 1e-3:
                    return {**r, "ok": False, "error": f"axis {names[i]} moved while the start was "
                                                      f"prepared ({mv.start:.6f} -> {y:.6f} m); retry"}
                k = m.get("controller") or kinds[i]
                loop.switch_axis(i, ctrls[k][i])
                kinds[i] = k
                loop.start_axis(i, mv)
                state["started_k"][i] = loop.k
                r["controller"] = k
            elif op == "stop":
                r["was"] = MODE_NAMES[loop.mode[i]]
                loop.stop_axis(i)
            elif op == "switch":
                k = m["controller"]
                r["from"] = kinds[i]
                loop.switch_axis(i, ctrls[k][i])
                kinds[i] = k
                r["cycle"] = loop.k
            elif op == "fault_reset":
                was = sup.reason(i)
                ok, why = loop.fault_reset(i)
                r.update(ok=ok, error=why, was=was)
            elif op == "inject":
                if not allow_inject:
                    return {**r, "ok": False, "error": "fault injection is off (daemon.allow_fault_"
                                                      "injection: true, simulated driver only)"}
                driver.inject(m["kind"], names[i], m.get("cycles", 1), jump_m=m.get("jump_m", 0.0),
                              force_N=m.get("force_N", 0.0))
                r["cycle"] = loop.k
            else:
                return {**r, "ok": False, "error": f"unknown operation {op!r}"}
        except Exception as exc:  # noqa: BLE001 - a bad command never stops the loop
            return {**r, "ok": False, "error": f"{type(exc).__name__}: {exc}"}
        finally:
            publish()
        return r

    def on_slack(lp) -> None:
        k = lp.k
        seq = ctl[CTL_CMD_SEQ]
        if seq != state["seen"]:
            state["seen"] = seq
            msgs = cmds.recv()
            if msgs:
                for m in msgs:
                    try:
                        replies.send(handle(m))
                    except BlockingIOError:
                        state["replies_dropped"] += 1     # pipe full: the client times out
                    except OSError:
                        state["io_dead"] = True
        if state["term"] and state["tail"] < 0:
            for i in range(n):
                if lp.mode[i] != IDLE:
                    sup.trip(i, FAULT_SHUTDOWN)
            lp.idle_all()
            state["tail"] = 10
            ctl[CTL_STATE] = 2
        elif state["tail"] > 0:
            state["tail"] -= 1
            if state["tail"] == 0:
                lp.request_stop()
        if k % 25 == 0:
            publish()
        else:
            for i in range(n):                  # a new fault is published at once
                if sup.fault[i] != published_fault[i]:
                    publish()
                    break
        if k % 5000 == 2500:                     # about once a second: is the recorder alive?
            try:
                if os.waitpid(io_pid, os.WNOHANG)[0] != 0:
                    state["io_dead"] = True
            except ChildProcessError:
                state["io_dead"] = True
            if state["io_dead"] and not state["term"]:
                state["term"] = "recorder process died"

    loop.on_slack = on_slack

    def on_signal(signum, _frame):
        if not state["term"]:
            state["term"] = signal.Signals(signum).name

    old = {s: signal.signal(s, on_signal) for s in (signal.SIGTERM, signal.SIGINT)}
    publish()
    code = 0
    try:
        driver.open()
        try:
            rep = setup_realtime(rtc.policy, rtc.priority, rtc.cpu, rtc.lock_memory)
        except RealtimeError as exc:
            replies.send({"op": "fatal", "error": str(exc)})
            out.write(f"motorctl: error: {exc}\n")
            return 1
        info = {"op": "ready", "realtime": rep.as_dict(), "realtime_summary": rep.summary(),
                "loop_pid": os.getpid(), "python_threads": threading.active_count(),
                "native_threads": len(os.listdir("/proc/self/task")),
                "cpu_affinity": sorted(os.sched_getaffinity(0)),
                "switch_interval_s": sys.getswitchinterval()}
        replies.send(info)
        out.write(f"motorctl daemon: {len(names)} axes ({', '.join(names)}) at "
                  f"{1 / sh.period_s:.0f} Hz, all disabled; socket {sh.socket_path}; log {sh.log_path}; "
                  f"realtime: {rep.summary()}\n")
        out.flush()
        ctl[CTL_STATE] = 1
        loop.run(1 << 62)
    finally:
        try:
            loop.safe_output()
        finally:
            try:
                driver.close()
            finally:
                ctl[CTL_STATE] = 3
                for s_, h in old.items():
                    signal.signal(s_, h)
                from motorctl.rt import restore
                restore()
                sd_notify("STOPPING=1")
                try:
                    os.set_blocking(replies.wfd, True)   # the loop has ended: waiting is fine
                    replies.send({"op": "exit", "reason": state["term"] or "loop ended"})
                except OSError:
                    pass
                os.close(replies.wfd)
                _reap(io_pid, 15.0)
    if state["io_dead"]:
        out.write("motorctl: error: the recorder process died; all axes at 0 V, amplifiers off\n")
        return 1
    out.write(f"motorctl daemon: stopped by {state['term'] or 'loop end'}: all axes at 0 V, "
              f"amplifiers off; log {sh.log_path}\n")
    return code


def _reap(pid: int, timeout_s: float) -> None:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        try:
            if os.waitpid(pid, os.WNOHANG)[0] != 0:
                return
        except ChildProcessError:
            return
        time.sleep(0.01)
    try:
        os.kill(pid, signal.SIGKILL)
        os.waitpid(pid, 0)
    except (ProcessLookupError, ChildProcessError):
        pass


# --------------------------------------------------------------------------- I/O process
class _IO:
    def __init__(self, sh: _Shared, lsock, writer: LogWriter, cmds: Mailbox, replies: Mailbox):
        self.sh, self.lsock, self.cmds, self.replies = sh, lsock, cmds, replies
        d = sh.loaded.cfg.daemon
        self.header = _header(sh, {"realtime": "pending"})
        self.writer = writer
        self.drainer = Drainer(sh.ring, writer, self.header, sh.names, sh.period_s, d.flush_s,
                               d.event_before_s, d.event_after_s, d.max_event_logs)
        self.ready: dict | None = None
        self.fatal = ""
        self.pending: dict[int, tuple] = {}
        self.next_id = 1
        self.sel = selectors.DefaultSelector()
        self.started = time.monotonic()
        self.notified_ready = False
        wd = int(os.environ.get("WATCHDOG_USEC", "0") or 0)
        wpid = os.environ.get("WATCHDOG_PID")
        if wpid and wpid.isdigit() and int(wpid) != os.getppid():
            wd = 0
        self.watchdog_s = wd / 2e6 if wd else 0.0
        self.last_ping = time.monotonic()
        self.last_hb = 0
        self.last_status = 0.0
        self.exit_reason = ""
        self.audit: list[dict] = []      # commands applied by the loop, with their cycle
        self._reported = 0

    # ---- commands from clients
    def axis_index(self, req) -> int:
        a = req.get("axis")
        if a not in self.sh.names:
            raise _Usage(f"unknown axis {a!r}; axes: {', '.join(self.sh.names)}")
        return self.sh.names.index(a)

    def to_loop(self, conn, msg: dict, post=None) -> None:
        msg["id"] = self.next_id
        self.next_id += 1
        self.pending[msg["id"]] = (conn, time.monotonic() + 2.0, post, msg)
        self.cmds.send(msg)
        ctl = self.sh.ring.ctl
        ctl[CTL_CMD_SEQ] = int(ctl[CTL_CMD_SEQ]) + 1

    def request(self, conn, req: dict) -> dict | None:
        """Answer now (a dict) or forward to the loop (None: the answer comes later)."""
        cmd = req.get("cmd")
        if self.fatal:
            return {"ok": False, "error": self.fatal}
        if cmd == "status":
            st = self.status()
            if req.get("axis") is not None:
                i = self.axis_index(req)
                st["axes"] = {self.sh.names[i]: st["axes"][self.sh.names[i]]}
            return {"ok": True, "status": st}
        if self.ready is None:
            return {"ok": False, "error": "the loop is not running yet; retry in a moment"}
        if cmd == "start":
            i = self.axis_index(req)
            kind = req.get("controller")
            if kind not in (None, "c1", "c2"):
                raise _Usage(f"unknown controller {kind!r}; allowed: c1, c2")
            ax = self.axis_status(i)
            if ax["fault_bits"]:
                return {"ok": False, "error": f"axis {ax['axis']} is in fault: {ax['fault']}; "
                                              f"run 'motorctl fault-reset {ax['axis']}' first"}
            if ax["state"] != "disabled":
                return {"ok": False, "error": f"axis {ax['axis']} is already enabled ({ax['phase']})"}
            tc = self.sh.loaded.axes[self.sh.names[i]].trajectory
            x0 = self.sh.programs[i].sample(0.0)[0]
            mv = Move(float(ax["y_m"]), float(x0), tc.v_max, tc.a_max, tc.j_max, 0.0)
            self.to_loop(conn, {"op": "start", "axis": i, "controller": kind, "move": mv},
                         post={"approach_s": mv.duration, "approach_m": x0 - ax["y_m"]})
            return None
        if cmd == "stop":
            i = self.axis_index(req)
            self.to_loop(conn, {"op": "stop", "axis": i}, post={"bound_s": self.sh.stop_bound_s[i]})
            return None
        if cmd == "switch":
            i = self.axis_index(req)
            kind = req.get("controller")
            if kind not in ("c1", "c2"):
                raise _Usage(f"unknown controller {kind!r}; allowed: c1, c2")
            self.to_loop(conn, {"op": "switch", "axis": i, "controller": kind})
            return None
        if cmd == "fault-reset":
            i = self.axis_index(req)
            self.to_loop(conn, {"op": "fault_reset", "axis": i})
            return None
        if cmd == "inject":
            i = self.axis_index(req)
            self.to_loop(conn, {"op": "inject", "axis": i, "kind": req.get("kind"),
                                "cycles": int(req.get("cycles", 1)),
                                "jump_m": float(req.get("jump_m", 0.0)),
                                "force_N": float(req.get("force_N", 0.0))})
            return None
        raise _Usage(f"unknown command {cmd!r}")

    # ---- status
    def axis_status(self, i: int) -> dict:
        from motorctl.runlog import AXIS_FIELDS, CYCLE_FIELDS
        sh = self.sh
        a = sh.names[i]
        row = sh.ring.latest()
        st = sh.ring.status[i]
        bits = int(st[ST_FAULT])
        mode = int(st[ST_MODE])
        out = {"axis": a}
        if bits:
            out["state"] = "fault"
        else:
            out["state"] = "disabled" if mode == IDLE else "enabled"
        out["phase"] = MODE_NAMES.get(mode, "?")
        out["fault_bits"] = bits
        out["fault"] = (f"{describe_faults(bits)} (value {st[ST_VALUE]:.6g}, limit {st[ST_LIMIT]:.6g})"
                        if bits else "")
        out["controller"] = KIND_NAMES.get(int(st[ST_KIND]), "?")
        if row is not None:
            base = len(CYCLE_FIELDS) + i * len(AXIS_FIELDS)
            f = {name: float(row[base + j]) for j, name in enumerate(AXIS_FIELDS)}
            out.update(y_m=f["y"], x_d_m=f["x_d"], following_error_m=f["e"], u_V=f["u"],
                       theta_hat=[f[f"theta_hat{j}"] for j in range(1, 7)], d_hat0_V=f["d_hat0"],
                       amplifier_enabled=bool(f["enabled"]))
            out["theta_hat"] = out["theta_hat"][:4] if out["controller"] == "c1" else out["theta_hat"]
        else:
            out.update(y_m=float("nan"), following_error_m=float("nan"))
        out["following_error_peak_m"] = float(st[ST_FE_PEAK])
        out["io_errors"] = int(st[ST_IO_ERRORS])
        out["timing_since_start"] = self.drainer.axis_stats[i].summary()
        out["stop_bound_s"] = sh.stop_bound_s[i]
        return out

    def status(self) -> dict:
        dr = self.drainer
        ring = self.sh.ring
        return {
            "axes": {a: self.axis_status(i) for i, a in enumerate(self.sh.names)},
            "loop": {"rate_hz": 1.0 / self.sh.period_s, "cycles": ring.published(),
                     "overruns": dr.overruns, "state": int(ring.ctl[CTL_STATE]),
                     "phase_max_us": {k: v / 1000.0 for k, v in zip(("read", "control", "write"), dr.phase_max_ns)},
                     **dr.loop_stats.summary()},
            "realtime": (self.ready or {}).get("realtime", {}),
            "realtime_summary": (self.ready or {}).get("realtime_summary", "pending"),
            "process": {k: (self.ready or {}).get(k) for k in ("loop_pid", "python_threads",
                                                               "native_threads", "cpu_affinity",
                                                               "switch_interval_s")}
                       | {"io_pid": os.getpid(), "uptime_s": time.monotonic() - self.started},
            "log": {"path": self.sh.log_path, "rows": self.writer.rows_written,
                    "rows_flushed": dr.flushed_rows, "lost_rows": dr.lost_rows,
                    "flush_s": self.sh.loaded.cfg.daemon.flush_s, "flushes": dr.flushes,
                    "max_flush_gap_s": dr.max_flush_gap_s, "events": dr.events,
                    "events_pending": len(dr.pending), "events_dropped": dr.events_dropped},
            "socket": self.sh.socket_path,
        }

    def summary_line(self) -> str:
        parts = []
        for i, a in enumerate(self.sh.names):
            s = self.axis_status(i)
            parts.append(f"{a} {s['state']}" + (f" ({s['fault']})" if s["fault"] else ""))
        return "; ".join(parts) + f"; overruns {self.drainer.overruns}"

    # ---- replies from the loop
    def on_reply(self, m: dict) -> None:
        op = m.get("op")
        if op == "ready":
            self.ready = m
            self.header["realtime"] = m["realtime"]
            self.header["process"] = {k: m[k] for k in ("loop_pid", "python_threads", "native_threads",
                                                       "cpu_affinity")}
            self.writer.update_header(self.header)
            loop_cpus = set(m.get("cpu_affinity") or [])
            others = set(os.sched_getaffinity(0)) - loop_cpus
            if loop_cpus and others and len(loop_cpus) == 1:
                try:
                    os.sched_setaffinity(0, others)
                except OSError:
                    pass
            return
        if op == "fatal":
            self.fatal = m["error"]
            return
        if op == "exit":
            self.exit_reason = m.get("reason", "")
            return
        entry = self.pending.pop(m.get("id"), None)
        if entry is None:
            return
        conn, _, post, req = entry
        m.pop("id", None)
        if m.get("ok"):
            self.audit.append({"cycle": m.get("cycle"), "op": req.get("op"),
                               "axis": self.sh.names[req["axis"]],
                               **({"controller": req["controller"]} if req.get("controller") else {}),
                               **({"kind": req["kind"]} if req.get("kind") else {})})
        if post and m.get("ok"):
            m.update(post)
        self.respond(conn, m)

    def respond(self, conn, obj: dict) -> None:
        try:
            conn.setblocking(True)
            conn.settimeout(1.0)
            conn.sendall((json.dumps(obj) + "\n").encode())
        except OSError:
            pass
        finally:
            try:
                self.sel.unregister(conn)
            except (KeyError, ValueError):
                pass
            conn.close()

    def on_client(self, conn) -> None:
        try:
            data = conn.recv(65536)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            data = b""
        if not data:
            self.sel.unregister(conn)
            conn.close()
            return
        buf = getattr(conn, "_mc_buf", b"") + data
        if b"\n" not in buf:
            conn._mc_buf = buf  # type: ignore[attr-defined]
            return
        try:
            req = json.loads(buf.split(b"\n", 1)[0].decode())
            if not isinstance(req, dict):
                raise ValueError("not an object")
            ans = self.request(conn, req)
        except _Usage as exc:
            ans = {"ok": False, "error": str(exc), "usage": True}
        except (ValueError, UnicodeDecodeError) as exc:
            ans = {"ok": False, "error": f"bad request: {exc}", "usage": True}
        if ans is not None:
            self.respond(conn, ans)
        else:
            try:
                self.sel.unregister(conn)
            except (KeyError, ValueError):
                pass

    def run(self) -> int:
        self.lsock.setblocking(False)
        self.sel.register(self.lsock, selectors.EVENT_READ, "listen")
        self.sel.register(self.replies.rfd, selectors.EVENT_READ, "loop")
        loop_gone = False
        while not loop_gone:
            for key, _ in self.sel.select(timeout=0.02):
                if key.data == "listen":
                    try:
                        conn, _ = self.lsock.accept()
                    except (BlockingIOError, InterruptedError):
                        continue
                    conn.setblocking(False)
                    self.sel.register(conn, selectors.EVENT_READ, "client")
                elif key.data == "loop":
                    msgs = self.replies.recv()
                    if msgs is None:
                        loop_gone = True
                        break
                    for m in msgs:
                        self.on_reply(m)
                else:
                    self.on_client(key.fileobj)
            now = time.monotonic()
            for rid, (conn, deadline, _, _) in list(self.pending.items()):
                if now > deadline:
                    self.pending.pop(rid)
                    self.respond(conn, {"ok": False, "error": "the loop did not answer within 2 s"})
            self.drainer.poll()
            self.report_faults()
            self.drainer.cut_events()
            self.drainer.maybe_flush()
            self.notify(now)
        # the loop process ended (normally, or killed): keep everything it published
        try:
            self.drainer.poll()
            self.report_faults()
            self.header["commands"] = self.audit
            self.header["events"] = self.drainer.events
            self.header["ended"] = {"reason": self.exit_reason or "loop process killed",
                                    "cycles": self.sh.ring.published(),
                                    "lost_rows": self.drainer.lost_rows}
            if not self.writer.update_header(self.header):
                self.header["commands"] = self.audit[-50:]
                self.writer.update_header(self.header)
            self.drainer.finish()
        finally:
            self.lsock.close()
            try:
                os.unlink(self.sh.socket_path)
            except OSError:
                pass
        return 0

    def report_faults(self) -> None:
        """One line on stderr (the journal) per fault onset: reported once, not per cycle."""
        onsets = self.drainer.fault_onsets
        for e in onsets[self._reported:]:
            i = self.sh.names.index(e["axis"])
            st = self.sh.ring.status[i]
            sys.stderr.write(f"motorctl daemon: axis {e['axis']} fault at t = "
                             f"{e['k'] * self.sh.period_s:.4f} s: {describe_faults(e['bits'])} "
                             f"(value {st[ST_VALUE]:.6g}, limit {st[ST_LIMIT]:.6g}); 0 V, "
                             f"amplifier off, latched\n")
        self._reported = len(onsets)

    def notify(self, now: float) -> None:
        hb = self.sh.ring.published()
        if self.ready is not None and not self.notified_ready and hb > 0:
            sd_notify("READY=1\nSTATUS=" + self.summary_line())
            self.notified_ready = True
            self.last_status = now
        if self.watchdog_s and now - self.last_ping >= self.watchdog_s:
            if hb != self.last_hb:           # only while the loop's heartbeat advances
                sd_notify("WATCHDOG=1")
                self.last_hb = hb
                self.last_ping = now
        if self.notified_ready and now - self.last_status >= 2.0:
            sd_notify("STATUS=" + self.summary_line())
            self.last_status = now


class _Usage(Exception):
    pass


def _io_main(sh: _Shared, lsock, writer: LogWriter, cmds: Mailbox, replies: Mailbox) -> int:
    for s in (signal.SIGTERM, signal.SIGINT, signal.SIGHUP):
        signal.signal(s, signal.SIG_IGN)        # the loop process tells us when to go
    try:
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    except OSError:
        pass
    return _IO(sh, lsock, writer, cmds, replies).run()


__all__ = ["run_daemon", "sd_notify", "bind_control_socket", "DaemonError", "Mailbox"]
