"""The daemon's I/O process: serves the control socket, forwards commands to the loop process,
drains the shared ring to the run log's segments (:class:`motorctl.recorder.flight.Drainer`,
:class:`motorctl.recorder.segments.SegmentWriter`), keeps ``log_dir`` within its budget
(:class:`~motorctl.recorder.segments.Retention`), cuts event logs, reports fault onsets to the
journal and speaks systemd's notify protocol (``READY=1`` once the loop runs, ``STATUS=``,
``WATCHDOG=1`` only while the loop's heartbeat advances, ``STOPPING=1``). It never touches the
driver; the loop process checks and applies every command (:mod:`motorctl.app.daemon.loop_side`).

It bumps ``ctl[CTL_REC_BEAT]`` at every wake (the loop latches every axis when that stops for
longer than the stall bound). A run log it cannot write (a full disk) never ends it: the
drainer sets the recorder fault, the loop latches the axes, and ``status`` keeps answering
with the reason; the end record goes into the header (reserved space) at the exit.
"""

from __future__ import annotations

import math
import os
import queue
import secrets
import selectors
import shutil
import signal
import sys
import threading
import time

from motorctl.app.build import approach_move
from motorctl.app.daemon.forked import own_session
from motorctl.app.daemon.journal import Journal, install as install_journal
from motorctl.app.daemon.machine import MachineState, Observed, axis_state, machine_state, refusal
from motorctl.app.daemon.motion_side import AxisLimits, MotionError, MotionSide
from motorctl.app.daemon.notify import sd_notify, watchdog_ping_interval_s
from motorctl.app.program_planner import AHEAD_WINDOWS, PLAN_NICE, PlannerLink
from motorctl.app.daemon.protocol import (
    LineBuffer,
    Mailbox,
    Request,
    RequestError,
    encode_answer,
    parse_request,
)
from motorctl.app.daemon.status import ST, axis_status, fault_text
from motorctl.loop.rt import keep_off, loop_cpu
from motorctl.loop.safety import with_drive_reason
from motorctl.loop.servo import JOG, MODE_NAMES
from motorctl.loop.trajectory import Move
from motorctl.recorder.flight import (
    CTL_CMD_SEQ,
    CTL_REC_BEAT,
    CTL_REC_LATCHED,
    CTL_STATE,
    REC_REASONS,
    Drainer,
)
from motorctl.recorder.runlog import LogError
from motorctl.recorder.segments import SegmentWriter

#: the motion filler thread runs SCHED_FIFO this many priority levels below the loop (with
#: loop.realtime.policy not off), so that a busy host does not starve the setpoint stream
FILLER_PRIORITY_BELOW = 40
#: the I/O process's nice value with the real-time set-up on: its threads share one interpreter
#: lock, and the SCHED_FIFO filler waits for it while the main thread (socket, recorder drain)
#: holds it; at nice 0 beside CPU-bound work the main thread was preempted holding it long enough
#: for the 0.125 s of setpoints a feed-override rewrite leaves ahead to run dry (an underrun with
#: the override flipped 0.5/1.5 beside 4 CPU-bound processes). The planner process (nice -8) and
#: the views (nice 0) come after it
IO_NICE = -10
#: a command the loop has not answered within this time is answered with an error [s]
LOOP_ANSWER_S = 2.0
#: at the I/O process's end, how long the journal's queued lines may take to be written [s]
JOURNAL_DRAIN_S = 2.0
#: how often the I/O process wakes when nothing happens [s]
IDLE_WAKE_S = 0.02
#: STATUS= line to systemd at most this often [s]
STATUS_LINE_S = 2.0
#: most client connections open at once; the oldest idle one is closed to admit a new one
MAX_CLIENTS = 64
#: a connection without a complete request after this time is closed [s]
CLIENT_IDLE_S = 5.0
#: the scope's copy of the axes' states is refreshed this often [s]
SCOPE_STATUS_S = 0.2
#: after running out of file descriptors, accept nothing for this long [s]
EMFILE_PAUSE_S = 0.1
#: the planner process is started again when it ends, this many times in all
MAX_PLANNER_STARTS = 20
#: a program's check (read whole against LinuxCNC's subset and the soft limits) taking longer than
#: this is cancelled and the program refused [s]
CHECK_LIMIT_S = 600.0
#: a helper process (views, metrics, OPC UA) that ends is started again after HELPER_RETRY_S [s],
#: HELPER_STARTS times in all (the first start included)
HELPER_STARTS, HELPER_RETRY_S = 6, 1.0
#: programs being sent (or sent and not yet run) at once; one idle for UPLOAD_IDLE_S is dropped [s]
MAX_UPLOADS, UPLOAD_IDLE_S = 4, 120.0


class IOSide:
    """The I/O process after the fork. ``plan`` is the daemon's :class:`DaemonPlan`."""

    def __init__(self, plan, lsock, writer: SegmentWriter, cmds: Mailbox, replies: Mailbox, journal: Journal):
        self.plan, self.lsock, self.cmds, self.replies = plan, lsock, cmds, replies
        self.journal = journal             # the stderr Journal (its dropped lines in status)
        asm = plan.asm
        self.names = asm.names
        self.layout = asm.loop.layout
        self.controllers = [list(b) for b in asm.bank]
        d = asm.loaded.cfg.daemon
        self.header = plan.header
        self.writer = writer
        self.retention = writer.retention
        self.drainer = Drainer(plan.ring, writer, self.header, self.names, asm.loaded.timebase,
                               d.flush_s, d.event_before_s, d.event_after_s, d.max_event_logs,
                               d.overrun_event_before_s, d.overrun_event_after_s)
        self.ready: dict | None = None
        self.fatal = ""
        self.pending: dict[int, tuple] = {}
        self.buffers: dict = {}
        self.clients: dict = {}          # conn -> time it connected (waiting for its request)
        self.accept_paused_until = 0.0
        self.clients_refused = 0
        self.next_id = 1
        self.sel = selectors.DefaultSelector()
        self.started = time.monotonic()
        self.notified_ready = False
        self.watchdog_s = watchdog_ping_interval_s(os.getppid())
        self.last_ping = time.monotonic()
        self.last_hb = 0
        self.last_status = 0.0
        self.exit_reason = ""
        self.drive_reasons = [""] * len(self.names)   # the drive's words per faulted axis
        self.link: dict = {"connected": True, "attempts": 0, "reconnects": 0, "last_error": "",
                           "last_pause_s": 0.0}
        self.audit: list[dict] = []      # commands applied by the loop, with their cycle
        self._reported = 0
        self._rec_reported = ""
        self.scope = self.views = None
        self.scope_d, self.foxglove_d = d.scope, d.foxglove
        if d.scope is not None or d.foxglove is not None:
            from motorctl.app.daemon.scope import Scope
            self.scope = Scope(d.scope.listen if d.scope else None, self.layout, self.names,
                               asm.loaded.period_s,
                               {a: asm.loaded.axes[a].trajectory.period_s for a in self.names})
        self.last_scope_status = 0.0
        ring = plan.ring
        lims = []
        for a in self.names:
            ac = asm.loaded.axes[a]
            tc, lc = ac.trajectory, ac.limits
            lims.append(AxisLimits(tc.v_max, tc.a_max, tc.j_max, lc.soft_min_m, lc.soft_max_m))
        has_inputs = getattr(asm.driver, "has_homing_inputs", False)
        self.internal: queue.Queue = queue.Queue()     # the homing thread's commands to the loop
        # a command of the homing thread wakes this process's select at once (not at IDLE_WAKE_S)
        self._wake_r, self._wake_w = os.pipe()
        os.set_blocking(self._wake_r, False)
        os.set_blocking(self._wake_w, False)
        self.motion = MotionSide(asm.loop.stream, ring.latest, self.layout, self.names, lims,
                                 lambda: ring.status[:, ST["mode"]], asm.loaded.period_s,
                                 [asm.loaded.axes[a].homing for a in self.names],
                                 (lambda i: (bool(ring.status[i, ST["home_switch"]]),
                                             float(ring.status[i, ST["index_latch"]])))
                                 if has_inputs else None,
                                 self.internal_request if has_inputs else None,
                                 gcode_settings=asm.loaded.cfg.gcode, lead_s=d.motion_lead_s)
        rt = asm.loaded.cfg.loop.realtime
        if rt.policy != "off":
            self.motion.fifo_priority = max(1, rt.priority - FILLER_PRIORITY_BELOW)
        #: programs: the planner process, the spool of programs sent in chunks, the job planned
        self.planner = PlannerLink()
        self.max_program_bytes = d.max_program_bytes
        self.spool = spool_beside(self.plan.socket_path)
        self.uploads: dict[str, dict] = {}
        self.raw: dict = {}                  # connection -> the upload whose bytes it sends
        self.job: dict | None = None
        #: each axis's latched fault bits at the last wake (a new fault: :meth:`react_to_faults`)
        self.fault_seen = [0] * len(self.names)
        self.helpers: dict = {}              # the watched helper processes (run(), supervise())
        self.planner_ended = ""

    # ------------------------------------------------------------------ requests
    def to_loop(self, conn, msg: dict, post=None) -> None:
        msg["id"] = self.next_id
        self.next_id += 1
        self.pending[msg["id"]] = (conn, time.monotonic() + LOOP_ANSWER_S, post, msg)
        self.cmds.send(msg)
        ctl = self.plan.ring.ctl
        ctl[CTL_CMD_SEQ] = int(ctl[CTL_CMD_SEQ]) + 1

    def request(self, conn, req: Request) -> dict | None:
        """Answer now (a dict) or forward to the loop (None: the answer comes later)."""
        if self.fatal:
            return {"ok": False, "error": self.fatal}
        # a fault latched since the last wake acts first, for a status too: one that said the
        # fault beside the motion it ends (still queued) let the state machine test see
        # "aborted" with a queue when a loaded host delayed the I/O process's wake
        self.react_to_faults()
        i = req.axis
        if req.cmd == "status":
            st = self.status()
            if i is not None:
                st["axes"] = {self.names[i]: st["axes"][self.names[i]]}
            return {"ok": True, "status": st}
        if self.ready is None:
            return {"ok": False, "error": "the loop is not running yet; retry in a moment"}
        ob = self.observed()
        state = machine_state(ob)
        why = refusal(state, self.rule_of(req), ob, self.names)
        if why:
            return {"ok": False, "error": why, "usage": False, "state": state.value}
        if req.cmd == "abort":
            self.abort_all()
        if req.cmd == "upload":
            return self.upload(conn, req.motion, self.buffers[conn].take_rest())
        if req.cmd == "gcode":
            return self.start_program(conn, req.motion)
        if req.cmd in ("move", "hold", "resume", "abort", "override", "optional-stop"):
            return self.motion_request(req)
        if req.cmd == "jog" and (req.jog["kind"] != "to" or self.axis_status(i)["phase"] == "command"):
            try:                             # an axis in command mode: a move of the stream
                j = req.jog
                if j["kind"] == "to":
                    v_max = self.plan.asm.loaded.axes[self.names[i]].trajectory.v_max
                    return {"ok": True, **self.motion.jog(i, "to", j["to_m"], feed=j["speed"] * v_max)}
                return {"ok": True, **self.motion.jog(i, j["kind"], j.get(j["kind"], 0.0))}
            except MotionError as exc:
                return {"ok": False, "error": str(exc), "usage": exc.usage}
        if req.cmd == "home":
            try:
                return {"ok": True, **self.motion.home(i)}
            except MotionError as exc:
                return {"ok": False, "error": str(exc), "usage": exc.usage}
        if req.cmd == "start" and req.mode == "command":
            tc = self.plan.asm.loaded.axes[self.names[i]].trajectory
            self.to_loop(conn, {"op": "start", "axis": i, "controller": req.controller,
                                "mode": "command", "a_max": tc.a_max, "j_max": tc.j_max},
                         post={"mode": "command"})
        elif req.cmd == "start":
            # the approach from where the axis stands to the program's start; the loop checks
            # the axis's state and that it has not moved since
            ax = self.axis_status(i)
            mv = approach_move(self.plan.asm, i, ax["y_m"])
            self.to_loop(conn, {"op": "start", "axis": i, "controller": req.controller, "move": mv},
                         post={"approach_s": mv.duration, "approach_m": mv.end - ax["y_m"]})
        elif req.cmd == "stop":
            self.to_loop(conn, {"op": "stop", "axis": i}, post={"bound_s": self.plan.stop_bound_s[i]})
        elif req.cmd == "switch":
            self.to_loop(conn, {"op": "switch", "axis": i, "controller": req.controller})
        elif req.cmd == "fault-reset":
            self.to_loop(conn, {"op": "fault_reset", "axis": i})
        elif req.cmd == "inject":
            self.to_loop(conn, {"op": "inject", "axis": i, "inject": req.inject})
        elif req.cmd == "jog":
            # a jerk-limited move at a fraction of the axis's limits from where it stands; the
            # loop checks the state (idle, or a soft-limit fault it may recover from)
            ax = self.axis_status(i)
            tc = self.plan.asm.loaded.axes[self.names[i]].trajectory
            f = req.jog["speed"]
            y0 = float(ax["y_m"])
            mv = Move(y0, req.jog["to_m"], f * tc.v_max, f * tc.a_max, tc.j_max, 0.0)
            self.to_loop(conn, {"op": "jog", "axis": i, "move": mv},
                         post={"from_m": y0, "move_s": mv.duration,
                               "bound_s": self.plan.stop_bound_s[i]})
        return None

    # ------------------------------------------------------------------ the machine state
    def rule_of(self, req: Request) -> str:
        """The name :mod:`.machine`'s table rules ``req`` by (a jog of a disabled axis is the
        loop's own jog; a jog's ``stop`` is an abort)."""
        if req.cmd != "jog":
            return req.cmd
        if req.jog["kind"] == "stop":
            return "abort"
        streamed = req.jog["kind"] != "to" or self.axis_status(req.axis)["phase"] == "command"
        return "jog" if streamed else "jog-disabled"

    def observed(self, st=None, motion: dict | None = None) -> Observed:
        """What the machine state is computed from now (:class:`.machine.Observed`); ``st``: the
        status block (n, len(ST_FIELDS)) to read (default: the live one the loop writes);
        ``motion``: the motion block of the same ``status`` (:meth:`MotionSide.status`; default:
        read now)."""
        st = self.plan.ring.status if st is None else st
        motion = self.motion.status() if motion is None else motion
        modes = tuple(MODE_NAMES.get(int(st[i, ST["mode"]]), "?") for i in range(len(self.names)))
        faults = tuple(self.fault_line(i, st) for i in range(len(self.names)))
        busy = not motion["idle"] or motion["homing_runs"] or self.job is not None
        return Observed(modes, faults, busy, motion["held"], bool(motion["aborting"]), motion["ring_depth"],
                        motion["braking"])

    def fault_line(self, i: int, st=None) -> str:
        """Axis i's latched fault in one line from the status block ``st`` (default: the live
        one; '' when none)."""
        st = (self.plan.ring.status if st is None else st)[i]
        return fault_text(int(st[ST["fault"]]), st[ST["value"]], st[ST["limit"]],
                          REC_REASONS.get(int(self.plan.ring.ctl[CTL_REC_LATCHED]), ""))

    def machine_status(self, st, motion: dict) -> dict:
        """``status``' ``machine`` block: the PackML state and each axis's CiA 402 state, from
        the status block ``st`` and the motion block ``motion`` of the same ``status``."""
        ob = self.observed(st, motion)
        return {"state": machine_state(ob).value,
                "axes": {a: axis_state(m, f) for a, m, f in zip(self.names, ob.modes, ob.faults)}}

    def react_to_faults(self) -> None:
        """At every wake and before every request: a fault newly latched on any axis ends the
        commanded motion at once (:meth:`MotionSide.fault_stop`: the queue, the program being
        planned or checked and homing dropped; the loop has drained the ring in the cycle it saw
        the fault), its cause is ``stopped_because``, the client waiting for a program's start
        is answered with it, and the machine is then ``aborted`` until ``fault-reset``."""
        st = self.plan.ring.status
        bits = [int(st[i, ST["fault"]]) for i in range(len(self.names))]
        new = [i for i, b in enumerate(bits) if b & ~self.fault_seen[i]]
        self.fault_seen = bits
        if not new:
            return
        i = new[0]
        cause = f"fault: axis {self.names[i]}: {self.fault_line(i)}"
        self.motion.fault_stop(cause)
        if self.job is not None:
            if self.job["info"] is None:
                self.cancel_check(cause)
            else:
                self._end_job(cause)

    def abort_all(self) -> None:
        """``abort`` beyond the commanded motion (which :meth:`MotionSide.abort` stops): a program
        still being checked is dropped (its client answered), and every axis on a jog of the
        loop's own is stopped (its jerk-limited stop, then 0 V)."""
        if self.job is not None:
            if self.job["info"] is None:
                self.cancel_check("gcode: aborted before it started")
            else:
                self._end_job("gcode: aborted before it started")
        for i in range(len(self.names)):
            if int(self.plan.ring.status[i, ST["mode"]]) == JOG:
                self.to_loop(None, {"op": "stop", "axis": i}, post=(threading.Event(), {}))

    def internal_request(self, msg: dict, timeout_s: float = LOOP_ANSWER_S) -> dict:
        """From another thread (homing): a command to the loop through the I/O process's own
        loop (which alone writes the pipe); its answer."""
        done, box = threading.Event(), {}
        self.internal.put((msg, done, box))
        try:
            os.write(self._wake_w, b"!")     # this process's select wakes at once
        except BlockingIOError:
            pass                             # a wake-up is pending already
        if not done.wait(timeout_s + 1.0):
            return {"ok": False, "error": "the loop did not answer"}
        return box

    def motion_request(self, req: Request) -> dict:
        """move, hold, resume, abort, override: answered here (the loop only follows the
        stream)."""
        mo, a = self.motion, req.motion
        try:
            if req.cmd == "move":
                return {"ok": True, **mo.move(a["targets"], a["feed"])}
            if req.cmd == "override":
                mo.set_override(a["value"])
            elif req.cmd == "optional-stop":
                mo.set_optional_stop(a["value"])
            else:
                getattr(mo, req.cmd)()
        except MotionError as exc:
            return {"ok": False, "error": str(exc), "usage": exc.usage}
        # the loop's count when it was taken: where its effect is found in the run log
        return {"ok": True, "motion": mo.status(), "cycle": self.plan.ring.published()}

    # ------------------------------------------------------------------ programs
    def upload(self, conn, a: dict, rest: bytes) -> dict | None:
        """``upload`` (:mod:`motorctl.app.daemon.protocol`): a program's ``bytes`` follow on this
        connection, into a spool file. Answers ``continue`` at once (the client then sends them),
        the token once they are all in (:meth:`_upload_in`). A program beyond
        ``daemon.max_program_bytes`` is refused by name before a byte of it is taken. None:
        the answer comes later."""
        now = time.monotonic()
        for tok in [t for t, u in self.uploads.items() if now - u["t"] > UPLOAD_IDLE_S]:
            self._drop_upload(tok)
        n = a["bytes"]
        if n > self.max_program_bytes:
            return {"ok": False, "error": f"upload: the program ({n} bytes) is larger than "
                                          f"daemon.max_program_bytes = {self.max_program_bytes} bytes; refused",
                    "usage": True}
        if len(self.uploads) >= MAX_UPLOADS:
            return {"ok": False, "error": f"upload: {MAX_UPLOADS} programs are being sent already; retry "
                                          f"when one is done", "usage": False}
        tok = secrets.token_hex(8)
        path = os.path.join(self.spool, tok + ".ngc")
        try:
            fh = open(path, "wb")
        except OSError as exc:
            return {"ok": False, "error": f"upload: cannot spool the program ({exc.strerror})", "usage": False}
        self.uploads[tok] = {"path": path, "bytes": 0, "size": n, "t": now, "fh": fh, "conn": conn}
        self.raw[conn] = tok
        self.clients.pop(conn, None)         # not idle: UPLOAD_IDLE_S applies
        try:
            conn.send(encode_answer({"ok": True, "upload": tok, "continue": True}))
        except OSError:
            self._drop_upload(tok)
            return None
        if rest or n == 0:
            self._upload_in(conn, rest)
        return None

    def _upload_in(self, conn, data: bytes | None = None) -> None:
        """The bytes of an upload that arrived (None: read them from ``conn``)."""
        tok = self.raw.get(conn)
        u = self.uploads.get(tok)
        if u is None:
            self.raw.pop(conn, None)
            self.drop(conn)
            return
        if data is None:
            try:
                data = conn.recv(1 << 20)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                data = b""
            if not data:                     # the client went away before the end
                self._drop_upload(tok)
                return
        u["t"] = time.monotonic()
        if u["bytes"] + len(data) > u["size"]:
            self._drop_upload(tok, keep_conn=True)
            self.respond(conn, {"ok": False, "error": f"upload: more than the {u['size']} bytes announced",
                                "usage": True})
            return
        try:
            u["fh"].write(data)
        except OSError as exc:
            self._drop_upload(tok, keep_conn=True)
            self.respond(conn, {"ok": False, "error": f"upload: cannot spool the program ({exc.strerror})",
                                "usage": False})
            return
        u["bytes"] += len(data)
        if u["bytes"] == u["size"]:
            u["fh"].close()
            u["fh"] = u["conn"] = None
            self.raw.pop(conn, None)
            self.respond(conn, {"ok": True, "upload": tok, "bytes": u["bytes"]})

    def _drop_upload(self, tok: str, keep_conn: bool = False) -> None:
        """Forget an upload: its spool file, and its connection while it was still sending."""
        u = self.uploads.pop(tok, None)
        if u is None:
            return
        if u["fh"] is not None:
            u["fh"].close()
        if u["conn"] is not None:
            self.raw.pop(u["conn"], None)
            if not keep_conn:
                self.drop(u["conn"])
        try:
            os.unlink(u["path"])
        except OSError:
            pass

    def start_program(self, conn, a: dict) -> dict | None:
        """``gcode``: hand the program to the planner process; answered when its first window
        is planned (or it is refused). None: the answer comes later."""
        mo = self.motion
        if a["upload"] is not None:
            u = self.uploads.get(a["upload"])
            if u is None or u["fh"] is not None:
                return {"ok": False, "error": f"gcode: no program sent whole as {a['upload']!r}", "usage": True}
            self.uploads.pop(a["upload"])
            path = u["path"]
        else:
            if len(a["text"].encode("utf-8", "surrogatepass")) > self.max_program_bytes:
                return {"ok": False, "error": f"gcode: the program is larger than daemon.max_program_bytes "
                                              f"= {self.max_program_bytes} bytes; refused", "usage": True}
            path = os.path.join(self.spool, secrets.token_hex(8) + ".ngc")
            try:
                with open(path, "w", encoding="utf-8", errors="surrogatepass") as fh:
                    fh.write(a["text"])
            except OSError as exc:
                return {"ok": False, "error": f"gcode: cannot spool the program ({exc.strerror})", "usage": False}
        if self.job is not None and self.job["info"] is None:
            # the program still being checked (nothing of it runs) gives way to the new one: its
            # client is answered, the planner process, which may be deep in its check, restarted
            self.cancel_check("gcode: superseded by a newer program before its check ended")
        if self.job is not None:
            os.unlink(path)
            return {"ok": False, "error": "gcode: a program is still being planned; wait for it or abort",
                    "usage": False}
        try:
            job = mo.program_job(a["filename"], path=path, from_line=a["from_line"],
                                 single_block=a["single_block"])
        except MotionError as exc:
            os.unlink(path)
            return {"ok": False, "error": str(exc), "usage": exc.usage}
        if not self.planner.pid:
            os.unlink(path)
            return {"ok": False, "error": "gcode: the planner process is not running", "usage": False}
        self.job = {"job": job, "conn": conn, "info": None, "axes": [], "clears": mo.clears,
                    "asked": 0, "got": 0, "path": path, "t0": time.monotonic()}
        self.planner.send({"op": "plan", "job": job})
        return None

    def cancel_check(self, why: str) -> None:
        """The program being checked is dropped (its client answered ``why``) and the planner
        process restarted: a check deep in a large program is not waited for (the next program's
        check never queues behind it)."""
        self._end_job(why)
        try:
            self.sel.unregister(self.planner.rfd)
        except (KeyError, ValueError, OSError):
            pass
        self.planner.stop()
        self.start_planner()

    def start_planner(self) -> None:
        """Start the planner process (again), at most :data:`MAX_PLANNER_STARTS` times: a
        program is then refused with one line while it is not running."""
        if self.planner.starts >= MAX_PLANNER_STARTS:
            return
        try:
            rt_on = self.plan.asm.loaded.cfg.loop.realtime.policy != "off"
            self.planner.start(PLAN_NICE if rt_on else 0)
            self.sel.register(self.planner.rfd, selectors.EVENT_READ, "planner")
        except OSError as exc:
            sys.stderr.write(f"motorctl daemon: warning: no planner process ({exc}); G-code refused\n")

    def on_planner(self) -> None:
        """The planner process's answers (:mod:`motorctl.app.program_planner`)."""
        msgs = self.planner.from_plan.recv()
        if msgs is None:                     # the planner process ended: a new one
            try:
                self.sel.unregister(self.planner.rfd)
            except (KeyError, ValueError):
                pass
            self.planner.stop()
            self._end_job("the planner process ended; retry")
            self.planner_ended = "its pipe closed"
            sys.stderr.write("motorctl daemon: the planner process ended; starting it again\n")
            self.start_planner()
            return
        for m in msgs:
            jb = self.job
            if jb is None or m.get("id") != jb["job"].id:
                continue                     # a cancelled job's late answers
            op = m["op"]
            if op == "refused":
                self._end_job(m["error"], usage=True)
            elif op == "failed":
                self._end_job(f"planner error: {m['error']}")
            elif op == "checked":
                try:
                    jb["axes"] = self.motion.accept_checked(jb["job"], m)
                except MotionError as exc:
                    self._end_job(str(exc), usage=exc.usage)
                    continue
                jb["info"] = m
                jb["asked"] = 1
            elif op == "window":
                jb["got"] += 1
                traj, last = m["traj"], m["last"]
                if m["k"] == 0:
                    info = jb["info"]
                    self.motion.begin_program(jb["job"], jb["axes"], traj, last, info["offsets"])
                    jb["clears"] = self.motion.clears
                    if jb["conn"] is not None:
                        self.respond(jb["conn"], {"ok": True, "segments": info["segments"],
                                                  "lines": info["lines"], "end_m": info["end"],
                                                  "warnings": info["warnings"],
                                                  "duration_s": float(traj.duration) if traj is not None else 0.0,
                                                  "planning": not last})
                        jb["conn"] = None
                elif not self.motion.add_window(jb["job"].id, traj, last):
                    self._end_job("")
                    continue
                if last:
                    self._end_job("")

    def _end_job(self, error: str, usage: bool = False) -> None:
        """The program's job is over (planned whole, refused, failed or dropped): the client
        still waiting gets ``error``; the planner process is told to stop planning it."""
        jb, self.job = self.job, None
        if jb is None:
            return
        if error and self.planner.pid:
            try:
                self.planner.send({"op": "cancel", "id": jb["job"].id})
            except OSError:
                pass
        try:
            os.unlink(jb["path"])
        except OSError:
            pass
        if jb["conn"] is not None:
            self.respond(jb["conn"], {"ok": False, "error": error or "gcode: dropped", "usage": usage})
        elif error:
            with self.motion.lock:
                if self.motion.planning == jb["job"].id:
                    self.motion._clear(error)

    def plan_poll(self) -> None:
        """Each wake: a program dropped meanwhile (abort, stop, fault) is cancelled in the
        planner; else one more window is asked for while fewer than AHEAD_WINDOWS wait."""
        jb = self.job
        if jb is not None and jb["info"] is None and time.monotonic() - jb["t0"] > CHECK_LIMIT_S:
            self.cancel_check(f"gcode: the program's check took longer than {CHECK_LIMIT_S:g} s; refused "
                              f"(split the program, or send it from a faster disk)")
            return
        if jb is None or jb["info"] is None:
            return
        mo = self.motion
        if jb["got"] and (mo.clears != jb["clears"] or mo.planning != jb["job"].id):
            self._end_job("dropped")
            return
        if mo.windows_ahead(jb["job"].id) + jb["asked"] - jb["got"] < AHEAD_WINDOWS:
            jb["asked"] += 1
            self.planner.send({"op": "more", "id": jb["job"].id})

    # ------------------------------------------------------------------ status
    def axis_status(self, i: int, st=None) -> dict:
        """Axis i's block of ``status`` from the status block ``st`` (default: the live one)."""
        ring = self.plan.ring
        st = ring.status if st is None else st
        out = axis_status(i, self.names[i], st[i], ring.latest(), self.layout,
                          REC_REASONS.get(int(ring.ctl[CTL_REC_LATCHED]), ""))
        out["fault"] = with_drive_reason(out["fault"], self.drive_reasons[i])
        out["drive_fault"] = self.drive_reasons[i] if out["fault_bits"] else ""
        out["timing_since_start"] = self.drainer.axis_stats[i].summary()
        out["stop_bound_s"] = self.plan.stop_bound_s[i]
        window = self.plan.asm.loaded.axes[self.names[i]].limits.in_position_m
        out["in_position"] = bool(abs(out.get("x_d_m", math.nan) - out["y_m"]) <= window)
        return out

    def status(self) -> dict:
        dr = self.drainer
        ring = self.plan.ring
        ready = self.ready or {}
        # one copy of the status block and one read of the motion side for the axes, the motion
        # and the machine state: the loop may latch a fault, and the motion side end a motion,
        # between two reads
        st = ring.status.copy()
        motion = self.motion.status()
        return {
            "axes": {a: self.axis_status(i, st) for i, a in enumerate(self.names)},
            "loop": {**{("cycles_timed" if k == "cycles" else k): v
                        for k, v in dr.loop_stats.summary().items()},
                     "rate_hz": 1.0 / self.plan.asm.loaded.period_s, "cycles": ring.published(),
                     "overruns": dr.overruns, "state": int(ring.ctl[CTL_STATE]),
                     "phase_max_us": {k: v / 1000.0 for k, v in zip(("read", "control", "write"),
                                                                    dr.phase_max_ns)}},
            "machine": self.machine_status(st, motion),
            "realtime": ready.get("realtime", {}),
            "realtime_summary": ready.get("realtime_summary", "pending"),
            "process": {k: ready.get(k) for k in ("loop_pid", "python_threads", "native_threads",
                                                  "cpu_affinity", "switch_interval_s")}
                       | {"io_pid": os.getpid(), "planner_pid": self.planner.pid or None,
                          "opcua_pid": getattr(getattr(self, "opcua", None), "pid", None),
                          "uptime_s": time.monotonic() - self.started},
            "log": {"path": self.writer.path, "run": self.plan.log_path,
                    "segment": self.writer.index, "rows": self.writer.rows_written,
                    "rows_flushed": dr.flushed_rows, "lost_rows": dr.lost_rows,
                    "flush_s": dr.flush_s, "flushes": dr.flushes,
                    "max_flush_gap_s": dr.max_flush_gap_s, "events": dr.events,
                    "events_pending": len(dr.pending), "events_dropped": dr.events_dropped,
                    "recorder_fault": REC_REASONS.get(dr.fault, ""), "error": dr.error,
                    "write_errors": dr.write_errors, "rows_unwritten": dr.drained - dr.written,
                    "journal_dropped": self.journal.dropped,
                    "retention": self.retention.figures() if self.retention else {}},
            "link": dict(self.link),
            "motion": motion,
            "socket": self.plan.socket_path,
            "clients": {"open": len(self.clients), "refused": self.clients_refused,
                        "max": MAX_CLIENTS},
            "views": ({"pid": self.views.pid, "frames_sent": self.views.sent,
                       "frames_dropped": self.views.dropped} if self.views is not None else None),
            "helpers": self.helpers_status(),
        }

    def summary_line(self) -> str:
        parts = []
        for i, a in enumerate(self.names):
            s = self.axis_status(i)
            parts.append(f"{a} {s['state']}" + (f" ({s['fault']})" if s["fault"] else ""))
        return "; ".join(parts) + f"; overruns {self.drainer.overruns}"

    # ------------------------------------------------------------------ replies from the loop
    def on_reply(self, m: dict) -> None:
        op = m.get("op")
        if op == "ready":
            self.ready = m
            self.header["realtime"] = m["realtime"]
            self.header["process"] = {k: m[k] for k in ("loop_pid", "python_threads",
                                                       "native_threads", "cpu_affinity")}
            try:
                self.writer.update_header(self.header)
            except (OSError, LogError):
                pass                         # later segments carry it; the drainer reports the disk
            loop_cpus = set(m.get("cpu_affinity") or [])
            others = set(os.sched_getaffinity(0)) - loop_cpus
            if loop_cpus and others and len(loop_cpus) == 1:
                for pid in (0, self.views.pid if self.views is not None else None):
                    try:
                        if pid is not None:
                            os.sched_setaffinity(pid, others)
                    except OSError:
                        pass
            return
        if op == "fatal":
            self.fatal = m["error"]
            return
        if op == "exit":
            self.exit_reason = m.get("reason", "")
            return
        if op == "drive_fault":
            self.drive_reasons[m["axis"]] = m["text"]
            if m["text"]:
                sys.stderr.write(f"motorctl daemon: axis {self.names[m['axis']]}: drive says: "
                                 f"{m['text']}\n")
            return
        if op == "link":
            m.pop("op")
            was = self.link["connected"]
            self.link = m
            if was and not m["connected"]:
                sys.stderr.write("motorctl daemon: the link to the drives is lost; reconnecting "
                                 "while every axis is idle (faults stay latched)\n")
            elif m["connected"] and not was:
                sys.stderr.write(f"motorctl daemon: the link to the drives is back (attempt "
                                 f"{m['attempts']}); the axes stay faulted until fault-reset\n")
            return
        entry = self.pending.pop(m.get("id"), None)
        if entry is None:
            return
        conn, _, post, req = entry
        m.pop("id", None)
        if conn is None:                     # a command of the homing thread
            done, box = post
            box.update(m)
            done.set()
            return
        if m.get("ok"):
            self.audit.append({"cycle": m.get("cycle"), "op": req.get("op"),
                               "axis": self.names[req["axis"]],
                               **({"controller": req["controller"]} if req.get("controller") else {}),
                               **({"kind": req["inject"]["kind"]} if req.get("inject") else {})})
        if post and m.get("ok"):
            m.update(post)
        self.respond(conn, m)

    # ------------------------------------------------------------------ clients
    def forget(self, conn) -> None:
        try:
            self.sel.unregister(conn)
        except (KeyError, ValueError):
            pass
        self.buffers.pop(conn, None)
        self.clients.pop(conn, None)

    def drop(self, conn) -> None:
        """Close a client connection that will get no answer."""
        self.forget(conn)
        try:
            conn.close()
        except OSError:
            pass

    def accept(self, now: float) -> None:
        """Accept the waiting clients (at most :data:`MAX_CLIENTS` per wake). At the connection
        cap the oldest waiting client is dropped; out of descriptors (EMFILE/ENFILE), idle
        clients are dropped and accepting pauses briefly, so no client can take the I/O
        process (and with it every axis) down."""
        if now < self.accept_paused_until:
            return
        for _ in range(MAX_CLIENTS):
            if len(self.clients) >= MAX_CLIENTS:
                oldest = min(self.clients, key=self.clients.get)
                self.drop(oldest)
                self.clients_refused += 1
            try:
                conn, _ = self.lsock.accept()
            except (BlockingIOError, InterruptedError):
                return
            except OSError:                  # EMFILE, ENFILE, ENOBUFS ...
                for c in [c for c, t in self.clients.items() if now - t > 0.5]:
                    self.drop(c)
                self.clients_refused += 1
                self.accept_paused_until = now + EMFILE_PAUSE_S
                return
            conn.setblocking(False)
            self.sel.register(conn, selectors.EVENT_READ, "client")
            self.clients[conn] = now

    def expire_clients(self, now: float) -> None:
        for c in [c for c, t in self.clients.items() if now - t > CLIENT_IDLE_S]:
            self.drop(c)
        for tok in [t for t, u in self.uploads.items() if now - u["t"] > UPLOAD_IDLE_S]:
            self._drop_upload(tok)

    def respond(self, conn, obj: dict) -> None:
        try:
            conn.setblocking(True)
            conn.settimeout(0.5)         # a client that does not read cannot stall us long
            conn.sendall(encode_answer(obj))
        except OSError:
            pass
        finally:
            self.forget(conn)
            conn.close()

    def on_client(self, conn) -> None:
        if conn in self.raw:
            self._upload_in(conn)
            return
        try:
            data = conn.recv(65536)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            data = b""
        if not data:
            self.forget(conn)
            conn.close()
            return
        try:
            line = self.buffers.setdefault(conn, LineBuffer()).feed(data)
            if line is None:
                return
            ans = self.request(conn, parse_request(line, self.names, self.controllers))
        except RequestError as exc:
            ans = {"ok": False, "error": str(exc), "usage": True}
        except Exception as exc:           # noqa: BLE001 - no request may end the daemon
            sys.stderr.write(f"motorctl daemon: internal error on a request: {type(exc).__name__}: {exc}\n")
            ans = {"ok": False, "error": f"internal error ({type(exc).__name__}: {exc}); nothing was "
                                         f"carried out", "usage": False}
        if ans is not None:
            self.respond(conn, ans)
        elif conn not in self.raw:         # the answer comes later (the loop, the planner)
            self.forget(conn)

    # ------------------------------------------------------------------ the run
    def run(self) -> int:
        self.lsock.setblocking(False)
        self.sel.register(self.lsock, selectors.EVENT_READ, "listen")
        self.sel.register(self.replies.rfd, selectors.EVENT_READ, "loop")
        self.sel.register(self._wake_r, selectors.EVENT_READ, "wake")
        loop_gone = False
        ctl = self.plan.ring.ctl
        d = self.plan.asm.loaded.cfg.daemon
        self.metrics = self.opcua = None
        # the helpers the I/O process watches (started again when they end, HELPER_STARTS in all)
        self.helpers = {name: {"pid": None, "starts": 0, "ended": "", "retry_at": 0.0}
                        for name, on in (("views", self.scope is not None),
                                         ("metrics", d.metrics is not None),
                                         ("opcua", d.opcua is not None)) if on}
        for name in self.helpers:
            self.start_helper(name)
            ctl[CTL_REC_BEAT] = int(ctl[CTL_REC_BEAT]) + 1   # awake between two starts
            self.drainer.poll()
        self.start_planner()
        self.motion.start()
        while not loop_gone:
            ctl[CTL_REC_BEAT] = int(ctl[CTL_REC_BEAT]) + 1     # "the recorder is awake"
            for key, _ in self.sel.select(timeout=IDLE_WAKE_S):
                if key.data == "listen":
                    self.accept(time.monotonic())
                elif key.data == "views":
                    self.on_views()
                elif key.data == "planner":
                    self.on_planner()
                elif key.data == "loop":
                    msgs = self.replies.recv()
                    if msgs is None:
                        loop_gone = True
                        break
                    for m in msgs:
                        self.on_reply(m)
                elif key.data == "wake":
                    try:
                        os.read(self._wake_r, 4096)
                    except BlockingIOError:
                        pass
                else:
                    self.on_client(key.fileobj)
            while not self.internal.empty():
                msg, done, box = self.internal.get_nowait()
                self.to_loop(None, msg, post=(done, box))
            self.plan_poll()
            now = time.monotonic()
            self.expire_clients(now)
            for rid, (conn, deadline, _, _) in list(self.pending.items()):
                if now > deadline:
                    self.pending.pop(rid)
                    if conn is None:
                        continue                 # the homing thread's own wait times out
                    self.respond(conn, {"ok": False, "error": f"the loop did not answer within "
                                                              f"{LOOP_ANSWER_S:g} s"})
            self.drainer.poll()
            self.react_to_faults()
            self.motion.settle_abort()
            self.report_faults()
            self.drainer.cut_events()
            self.drainer.maybe_flush()
            if self.retention is not None:
                self.retention.maybe_prune(now)
            self.report_recorder()
            self.notify(now)
            if self.metrics is not None:
                self.metrics.poll(self, now)
            if self.opcua is not None:
                self.opcua.poll(self, now)
            self.supervise(now)
            if self.scope is not None and now - self.last_scope_status >= SCOPE_STATUS_S:
                self.last_scope_status = now
                st = {"axes": {a: {k: v for k, v in self.axis_status(i).items()
                                   if k in ("state", "phase", "fault", "controller")}
                               for i, a in enumerate(self.names)}}
                self.scope.set_status(st)
                if self.views is not None:
                    self.views.set_status(st, self.scope.last_t)
        self.motion.stop()
        self.planner.stop()
        shutil.rmtree(self.spool, ignore_errors=True)
        if self.views is not None:
            self.views.stop()
        if self.metrics is not None:
            self.metrics.stop()
        if self.opcua is not None:
            self.opcua.stop()
        # the loop process ended (normally, or killed): keep everything it published
        try:
            dr = self.drainer
            dr.finish()
            self.report_faults()
            self.report_recorder()
            self.header["commands"] = self.audit
            self.header["events"] = dr.events
            self.header["ended"] = {"reason": self.exit_reason or "loop process killed",
                                    "cycles": self.plan.ring.published(),
                                    "lost_rows": dr.lost_rows,
                                    **({"recorder": dr.error} if dr.write_errors else {})}
            self.write_end_record()
            dr.close()
        finally:
            self.lsock.close()
            try:
                os.unlink(self.plan.socket_path)
            except OSError:
                pass
        return 0

    # ------------------------------------------------------------------ helper processes
    def start_helper(self, name: str) -> None:
        """Start the helper process ``name`` ("views", "metrics", "opcua"); its pid is noted for
        ``status`` (a start that fails is said in one line and tried again later)."""
        h = self.helpers[name]
        h["starts"] += 1
        if name == "views":
            self.start_scope()
        elif name == "metrics":
            from motorctl.app.daemon.metrics import start_metrics
            self.metrics = start_metrics(self.plan.asm.loaded.cfg.daemon.metrics.listen, self.layout,
                                         self.names, self.drainer)
        else:
            from motorctl.app.daemon.opcua_server import start_opcua
            self.opcua = start_opcua(self)
        link = getattr(self, name)
        h["pid"] = link.pid if link is not None else None

    def supervise(self, now: float) -> None:
        """Each wake: a helper process that ended (killed, crashed, exited) is reaped (no zombie),
        named in the journal and in ``status``' ``helpers``, and started again after
        :data:`HELPER_RETRY_S`, :data:`HELPER_STARTS` times in all. The loop and the recorder
        never wait for it."""
        for name, h in self.helpers.items():
            link = getattr(self, name)
            if link is None:
                if h["starts"] < HELPER_STARTS and h["retry_at"] and now >= h["retry_at"]:
                    h["retry_at"] = 0.0
                    self.start_helper(name)
                continue
            st = None
            if link.alive:
                try:
                    got, st = os.waitpid(link.pid, os.WNOHANG)
                except ChildProcessError:
                    got = link.pid
                if not got:
                    continue
            if name == "views":
                # what it reported before it ended is read first: reaped in the same wake as its
                # report came, the report would go with the link (a broken view's line lost)
                self.report_views()
            st2 = self.drop_views() if name == "views" else link.stop(0.5)
            st = st if st is not None else st2
            if name != "views":
                setattr(self, name, None)
            h["ended"] = exit_text(st) if st is not None else "its link closed"
            h["pid"] = None
            # exit code 0: it ended by itself (nothing it could serve, each said in a line): not again
            clean = st is not None and os.WIFEXITED(st) and os.WEXITSTATUS(st) == 0
            if clean:
                h["retry_at"] = 0.0
                sys.stderr.write(f"motorctl daemon: the {name} process (pid {link.pid}) ended by itself "
                                 f"(exit code 0); not started again\n")
                continue
            more = h["starts"] < HELPER_STARTS
            h["retry_at"] = now + HELPER_RETRY_S if more else 0.0
            sys.stderr.write(f"motorctl daemon: the {name} process (pid {link.pid}) ended ({h['ended']}); "
                             + (f"starting it again in {HELPER_RETRY_S:g} s (start {h['starts'] + 1} of "
                                f"{HELPER_STARTS})\n" if more else
                                f"not started again ({HELPER_STARTS} starts)\n"))

    def helpers_status(self) -> dict:
        """``status``' ``helpers``: per helper process its pid (None while it is not running),
        starts, how it last ended; the planner process's too."""
        out = {name: {"pid": h["pid"], "running": getattr(self, name) is not None,
                      "starts": h["starts"], "last_end": h["ended"]}
               for name, h in self.helpers.items()}
        out["planner"] = {"pid": self.planner.pid or None, "running": bool(self.planner.pid),
                          "starts": self.planner.starts, "last_end": self.planner_ended}
        return out

    def start_scope(self) -> None:
        """Fork the view process for the scope page and the Foxglove channels (where
        configured and installed; a missing extra is one warning line). Nothing is awaited:
        the view process reports what it serves through :meth:`on_views`."""
        if self.scope is None:
            return
        from motorctl.app.daemon.views import exposure_warning, missing_extra, start_views
        serve_scope = self.scope_d is not None
        fox = self.foxglove_d.listen if self.foxglove_d is not None else None
        for on, key, listen, module, extra, what in (
                (serve_scope, "daemon.scope.listen", self.scope_d and self.scope_d.listen,
                 "aiohttp", "scope", "scope"),
                (fox, "daemon.foxglove.listen", fox, "foxglove", "foxglove", "foxglove")):
            if not on:
                continue
            line = missing_extra(module, extra, what)
            if line:
                sys.stderr.write(line + "\n")
                serve_scope = serve_scope and what != "scope"
                fox = None if what == "foxglove" else fox
                continue
            from motorctl.config import parse_listen
            if line := exposure_warning(key, parse_listen(listen)[0]):
                sys.stderr.write(line + "\n")
        if not serve_scope and not fox:
            return
        try:
            self.views = start_views(self.scope, serve_scope, fox, {   # + the operator page
                "socket": self.plan.socket_path, "users_file": self.plan.asm.loaded.cfg.daemon.users_file,
                "lockout_s": self.plan.asm.loaded.cfg.daemon.login_lockout_s})
        except Exception as exc:               # noqa: BLE001 - no view is worth the drain
            sys.stderr.write(f"motorctl: warning: views not served ({type(exc).__name__}: {exc})\n")
            return
        if self.views is None:                 # the fork failed (said in one line)
            return
        self.fox_listen = fox
        self.sel.register(self.views.sock, selectors.EVENT_READ, "views")
        self.scope.listeners.append(self.views.on_frame)
        self.drainer.taps.append(self.scope.tap)

    def on_views(self) -> None:
        """The view process's reports (:meth:`report_views`); its end."""
        self.report_views()
        if not self.views.alive:
            self.supervise(time.monotonic())

    def report_views(self) -> None:
        """The view process's reports waiting on its link: one line per view served or not."""
        v = self.views
        for kind, rep in v.receive():
            if kind != "started":
                continue
            for what, err in rep.items():
                if err is None:
                    continue
                if what == "scope":
                    where, url = self.scope_d.listen, f"http://{self.scope.host}:{self.scope.port}/"
                else:
                    where, url = self.fox_listen, "ws://" + self.fox_listen + "/"
                if err:
                    sys.stderr.write(f"motorctl: warning: daemon.{what}.listen {where}: not served ({err})\n")
                else:
                    sys.stderr.write(f"motorctl: {what} on {url}\n")

    def drop_views(self) -> int | None:
        """The view process has ended: its link out of the selector, the scope and the drain;
        reaped (its wait status, None when reaped already)."""
        v = self.views
        try:
            self.sel.unregister(v.sock)
        except (KeyError, ValueError):
            pass
        if v.on_frame in self.scope.listeners:
            self.scope.listeners.remove(v.on_frame)
        if self.scope.tap in self.drainer.taps:
            self.drainer.taps.remove(self.scope.tap)
        self.views = None
        return v.stop(0.5)

    def write_end_record(self) -> None:
        """The header with ``ended`` into the segment being written (in place, reserved
        space: it needs no new blocks on a full disk); commands trimmed if they do not fit."""
        try:
            if not self.writer.update_header(self.header):
                self.header["commands"] = self.audit[-50:]
                self.writer.update_header(self.header)
        except (OSError, LogError) as exc:
            sys.stderr.write(f"motorctl daemon: cannot write the end record into "
                             f"{self.writer.path}: {getattr(exc, 'strerror', None) or exc}\n")

    def report_recorder(self) -> None:
        """One line on stderr when the run log stops being written and when it recovers."""
        dr = self.drainer
        now = dr.error if dr.fault else ""
        if now != self._rec_reported:
            if now:
                sys.stderr.write(f"motorctl daemon: cannot write the run log {self.writer.path}: "
                                 f"{now}; every axis latched (recorder), retrying\n")
            else:
                sys.stderr.write(f"motorctl daemon: the run log is written again "
                                 f"({dr.lost_rows} rows lost); axes stay latched until "
                                 f"fault-reset\n")
            self._rec_reported = now

    def report_faults(self) -> None:
        """One line on stderr (the journal) per fault onset: reported once, not per cycle."""
        onsets = self.drainer.fault_onsets
        for e in onsets[self._reported:]:
            i = self.names.index(e["axis"])
            st = self.plan.ring.status[i]
            why = fault_text(e["bits"], st[ST["value"]], st[ST["limit"]],
                             REC_REASONS.get(int(self.plan.ring.ctl[CTL_REC_LATCHED]), ""))
            sys.stderr.write(f"motorctl daemon: axis {e['axis']} fault at t = "
                             f"{e['k'] * self.plan.asm.loaded.period_s:.4f} s: "
                             f"{why}; 0 V, amplifier off, latched\n")
        self._reported = len(onsets)

    def notify(self, now: float) -> None:
        hb = self.plan.ring.published()
        if self.ready is not None and not self.notified_ready and hb > 0:
            sd_notify("READY=1\nSTATUS=" + self.summary_line())
            self.notified_ready = True
            self.last_status = now
        if self.watchdog_s and now - self.last_ping >= self.watchdog_s:
            if hb != self.last_hb:           # only while the loop's heartbeat advances
                sd_notify("WATCHDOG=1")
                self.last_hb = hb
                self.last_ping = now
        if self.notified_ready and now - self.last_status >= STATUS_LINE_S:
            sd_notify("STATUS=" + self.summary_line())
            self.last_status = now


def exit_text(status: int) -> str:
    """A wait status in words: "exit code N" or "killed by SIGNAME"."""
    if os.WIFSIGNALED(status):
        try:
            return f"killed by {signal.Signals(os.WTERMSIG(status)).name}"
        except ValueError:
            return f"killed by signal {os.WTERMSIG(status)}"
    return f"exit code {os.WEXITSTATUS(status)}" if os.WIFEXITED(status) else f"wait status {status}"


def spool_beside(socket_path: str) -> str:
    """The folder that programs sent in chunks are spooled to: ``<socket_path>.programs``,
    mode 0700, beside the control socket this daemon has just bound (so under systemd in its
    RuntimeDirectory, removed with it). A folder left there by a daemon that was killed on the
    same socket is removed first: the socket is this daemon's now, so is the folder.

    Raises:
        OSError: the folder cannot be made (the socket's directory was writable a moment ago).
    """
    path = socket_path + ".programs"
    shutil.rmtree(path, ignore_errors=True)
    os.mkdir(path, 0o700)
    return path


def io_main(plan, lsock, writer: SegmentWriter, cmds: Mailbox, replies: Mailbox) -> int:
    """Entry of the I/O process: ignore the signals (the loop process says when to go),
    SCHED_OTHER (at nice :data:`IO_NICE` with the real-time set-up on), off the loop's CPU
    when the loop is pinned to one (:func:`motorctl.loop.rt.keep_off`: the planner and the
    views it forks inherit it, so their work and their sockets' interrupts stay off the
    loop's CPU), in a session of its own (:func:`motorctl.app.daemon.forked.own_session`: with
    the kernel's autogroup, not in one CPU share with what else its starter's session runs),
    its stderr a :class:`~motorctl.app.daemon.journal.Journal` (a line never blocks the main
    thread, which drains the run log), serve until the loop process ends."""
    for s in (signal.SIGTERM, signal.SIGINT, signal.SIGHUP):
        signal.signal(s, signal.SIG_IGN)
    own_session()
    rt = plan.asm.loaded.cfg.loop.realtime
    try:
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
        if rt.policy != "off":
            os.setpriority(os.PRIO_PROCESS, 0, IO_NICE)     # before its threads: they inherit it
    except OSError:
        pass
    if rt.policy != "off":
        keep_off(loop_cpu(rt.cpu))
    journal = install_journal()          # no line on stderr ever waits for its reader here
    try:
        return IOSide(plan, lsock, writer, cmds, replies, journal).run()
    finally:
        journal.drain(JOURNAL_DRAIN_S)
