"""The daemon's loop process: the servo loop, and between cycles the commands from the I/O
process, the status block, signals and the recorder's health.

One thread; no file or socket I/O inside a cycle. Commands arrive in the ``on_slack`` hook
(after a cycle, outside its timed part): the loop looks at a shared command sequence number
and only then reads the command pipe (non-blocking), applies each command at the cycle
boundary and answers on the reply pipe (non-blocking: a stalled I/O process never blocks the
loop). Every command's checks are made here, against the live state (the one place).

A lost link to the drives (``Driver.link_down``: the transport failed, or no axis answered for
a while) is reconnected from here too, every :data:`RECONNECT_EVERY_S`, but only while every
axis is idle (the lost link has faulted them: 0 V, amplifier off): the loop pauses for one
blocking attempt of at most :data:`RECONNECT_TIMEOUT_S` (the device's first answer), then
resynchronises its clock (the pause is not counted as overruns). Nothing is re-enabled: the
faults stay latched until ``fault-reset``. The drive's own words about a fault
(``Driver.fault_reason``: an EMCY code, a Modbus exception) go to the I/O process when a fault
latches, for ``status`` and the journal.

The recorder check (every :data:`RECORDER_CHECK_S`, a few integer compares and a ``waitpid``)
latches FAULT_RECORDER on every axis when the I/O process reports that it cannot write the run
log (``ctl[CTL_REC_FAULT]``: "log disk full"), when its wake counter (``ctl[CTL_REC_BEAT]``)
has not moved for the stall bound (``2·flush_s + 1 s`` of loop periods: "recorder stalled"),
or when it died ("recorder died"; the loop then ends, writes the end record into the run log
itself and removes the socket). ``fault-reset`` is refused while the cause persists.
"""

from __future__ import annotations

import math
import os
import signal
import sys
import threading
import time

from motorctl.app.build import Assembly, rest_words, shutdown, start, stop_bound_s, stop_lines
from motorctl.app.daemon.notify import sd_notify
from motorctl.app.daemon.protocol import Mailbox
from motorctl.app.daemon.status import StatusPublisher
from motorctl.loop.rt import RealtimeError
from motorctl.loop.safety import FAULT_RECORDER, FAULT_SHUTDOWN, with_drive_reason
from motorctl.loop.servo import IDLE, MODE_NAMES, STREAM
from motorctl.loop.trajectory import Move
from motorctl.recorder.flight import (
    CTL_CMD_SEQ,
    CTL_REC_BEAT,
    CTL_REC_FAULT,
    CTL_REC_LATCHED,
    CTL_SEGMENT,
    CTL_STATE,
    REC_DIED,
    REC_REASONS,
    REC_STALLED,
    SharedRing,
    stall_bound_s,
)
from motorctl.recorder.runlog import LogError
from motorctl.recorder.segments import close_orphaned, segment_path

#: how often the loop checks the I/O process (the recorder) [s] (a waitpid and the shared
#: recorder words between cycles, every few cycles: a dead recorder is noticed within a
#: millisecond or two)
RECORDER_CHECK_S = 0.002
#: how often a lost link is tried again while every axis is idle [s]
RECONNECT_EVERY_S = 1.0
#: the longest pause of the loop for one reconnection attempt (the device's first answer) [s]:
#: well inside systemd's WatchdogSec (2 s), which the I/O process pings while the loop moves
RECONNECT_TIMEOUT_S = 0.25
#: how often the link is looked at (a flag and a few compares) [s]
LINK_CHECK_S = 0.05
#: how often the status block is refreshed besides every fault change [s]
STATUS_PUBLISH_S = 0.005
#: cycles recorded after a SIGTERM before the loop ends (the 0 V rows reach the log)
SHUTDOWN_TAIL_CYCLES = 10
#: how far inside its soft limits the jog a refused fault reset names takes the axis [m]
WAY_OUT_INSIDE_M = 0.001
#: a signal's category-1 stop may take this much beyond its bound (the longest move of a
#: program or a stream's brake from v_max, plus daemon.stop_settle_s) before the power is cut [s]
SIGNAL_STOP_MARGIN_S = 0.05
#: a start is refused when the axis moved more than this since the approach was planned [m]
START_MOVED_M = 1e-3

STATE_STARTING, STATE_RUNNING, STATE_STOPPING, STATE_ENDED = 0, 1, 2, 3


class LoopSide:
    """The loop process after the fork.

    Args:
        asm: the built loop (every configured controller per axis in ``asm.bank``).
        ring: the shared ring the loop records into. io_pid: the I/O process.
        cmds: mailbox of commands (read side). replies: mailbox of answers (write side,
        non-blocking). out: where the one-line start and stop messages go. early: the list the
        start-up's handler appends the names of signals to until :meth:`run` installs its own
        (a signal there: no device is opened).
    """

    def __init__(self, asm: Assembly, ring: SharedRing, io_pid: int, cmds: Mailbox,
                 replies: Mailbox, socket_path: str, log_path: str, out=sys.stderr, early=None):
        self.asm, self.ring, self.io_pid = asm, ring, io_pid
        self.cmds, self.replies, self.out = cmds, replies, out
        self.socket_path, self.log_path = socket_path, log_path
        self.loop = asm.loop
        self.names = asm.names
        self.ctl = memoryview(ring.ctl)
        self.status = StatusPublisher(ring.status, self.loop, asm.active)
        tb = asm.loaded.timebase
        self.check_every = tb.cycles(RECORDER_CHECK_S, minimum=1)
        self.publish_every = tb.cycles(STATUS_PUBLISH_S, minimum=1)
        d = asm.loaded.cfg.daemon
        self.stall_cycles = tb.cycles_ceil(stall_bound_s(d.flush_s))
        self.io_beat = -1               # the I/O process's wake counter last seen ...
        self.io_beat_n = 0              # ... and the loop period (k + missed) it was seen at
        self.io_status = None           # the I/O process's wait status once it is gone
        self.allow_inject = d.allow_fault_injection and hasattr(asm.driver, "inject")
        self.seen = 0
        self.term = ""                   # the signal that ends the daemon ('' until one came)
        self.early = early if early is not None else []
        self.stop_checks: list = []      # what the drives confirmed at shutdown (StopCheck)
        self.tail = -1
        self.io_dead = False
        self.replies_dropped = 0
        self.link_every = tb.cycles(LINK_CHECK_S, minimum=1)
        self.link = {"connected": True, "attempts": 0, "reconnects": 0, "last_error": "",
                     "last_pause_s": 0.0}
        self.next_attempt = 0.0
        self.can_reconnect = True
        self.drive_text = [""] * len(self.names)
        self.resets: list = []           # fault resets waiting for a drive: (axis, answer, was)
        self.n_stream = 0                # axes in command mode at the last check_stream
        # SIGTERM/SIGINT: a category-1 stop of the driven axes, bounded; a second signal cuts
        self.signals = 0
        self.stop_end = -1               # the cycle by which the signal's stop must be done
        self.signal_driven: list = []    # the axes driven when the signal came
        self.cut: list = []              # of those, the axes whose power was removed at once
        self.rest: dict = {}             # where each driven axis ended (build.rest_words)
        self.signal_stop_cycles = tb.cycles_ceil(self.signal_stop_bound_s())
        self.loop.on_slack = self.on_slack

    def signal_stop_bound_s(self) -> float:
        """The longest a signal's category-1 stop may take [s]: per axis the longest move of its
        program (a move in progress runs on to its end) and a stream's brake from v_max
        (v_max/a_max + a_max/j_max), whichever is longer, plus ``daemon.stop_settle_s`` and
        :data:`SIGNAL_STOP_MARGIN_S`. Beyond it the power is cut (category 0)."""
        loaded, settle = self.asm.loaded, self.asm.loaded.cfg.daemon.stop_settle_s
        bound = 0.0
        for name, prog in zip(self.names, self.asm.programs):
            tc = loaded.axes[name].trajectory
            brake = tc.v_max / tc.a_max + tc.a_max / tc.j_max
            bound = max(bound, stop_bound_s(prog, settle), brake + settle)
        return bound + SIGNAL_STOP_MARGIN_S

    # ------------------------------------------------------------------ commands
    def apply(self, m: dict) -> dict | None:
        """Apply one command at the cycle boundary; the answer to send back, or None when it
        comes later (a fault reset waiting for the drive to leave its fault: :meth:`poll_resets`)."""
        loop, sup, names = self.loop, self.loop.supervisor, self.names
        op, i = m.get("op"), m.get("axis", -1)
        r = {"id": m.get("id"), "ok": True, "cycle": loop.k}
        if self.term and op in ("start", "jog", "switch", "fault_reset", "set_position", "inject"):
            return {**r, "ok": False, "error": f"the daemon is stopping ({self.term})"}
        try:
            if op == "start":
                if sup.fault[i]:
                    drv = self.asm.driver
                    why = with_drive_reason(sup.reason(i), drv.fault_state(i) if drv.amp_fault[i]
                                            else drv.fault_reason(i))
                    return {**r, "ok": False, "error": f"axis {names[i]} is in fault: {why}; "
                                                      f"run 'motorctl fault-reset {names[i]}' first"}
                if loop.mode[i] != IDLE:
                    return {**r, "ok": False, "error": f"axis {names[i]} is already enabled "
                                                      f"({MODE_NAMES[loop.mode[i]]})"}
                if m.get("mode") == "command":   # hold where it stands, follow the stream
                    k = m.get("controller") or self.asm.active[i]
                    self._switch(i, k)
                    if not any(loop.mode[j] == STREAM for j in range(len(names))):
                        loop.stream.drain(False)   # nothing left from before is followed
                    loop.command_axis(i, m["a_max"], m["j_max"])
                    self.status.started_k[i] = loop.k
                    r["controller"] = k
                    return r
                mv = m["move"]
                y = float(self.asm.driver.position_m[i])
                if abs(mv.start - y) > START_MOVED_M:
                    return {**r, "ok": False, "error": f"axis {names[i]} moved while the start was "
                                                      f"prepared ({mv.start:.6f} -> {y:.6f} m); retry"}
                if mv.start != y:
                    # the plan was made on a record row some ms old (the I/O side's newest): the
                    # approach starts where the axis stands now (a disabled carriage may creep)
                    mv = Move(y, mv.end, mv.v_max, mv.a_max, mv.j_max, mv.t0)
                k = m.get("controller") or self.asm.active[i]
                self._switch(i, k)
                loop.start_axis(i, mv)
                self.status.started_k[i] = loop.k
                r["controller"] = k
            elif op == "stop":
                r["was"] = MODE_NAMES[loop.mode[i]]
                loop.stop_axis(i)
                r["cycle"] = loop.k          # the stop's start on the loop's clock (the CLI's wait)
            elif op == "switch":
                r["from"] = self.asm.active[i]
                self._switch(i, m["controller"])
                r["cycle"] = loop.k
            elif op == "fault_reset":
                trouble = self.recorder_trouble(loop)
                if trouble:
                    return {**r, "ok": False, "error": f"the recorder is still faulted "
                                                      f"({REC_REASONS[trouble]})"}
                was = sup.reason(i)
                pending, ok, why = loop.begin_fault_reset(i)
                if pending:              # the drive's reset is sent: answered once it left its fault
                    self.resets.append((i, {**r, "was": was}))
                    return None
                r.update(ok=ok, error=self.way_out(i, why), was=was)
            elif op == "jog":
                mv = m["move"]
                y = float(self.asm.driver.position_m[i])
                if abs(mv.start - y) > START_MOVED_M:
                    return {**r, "ok": False, "error": f"axis {names[i]} moved while the jog was "
                                                      f"prepared ({mv.start:.6f} -> {y:.6f} m); retry"}
                if loop.mode[i] != IDLE:
                    return {**r, "ok": False, "error": f"axis {names[i]} is enabled "
                                                      f"({MODE_NAMES[loop.mode[i]]}); stop it first"}
                if sup.fault[i]:
                    trouble = self.recorder_trouble(loop)
                    if trouble:
                        return {**r, "ok": False, "error": f"the recorder is still faulted "
                                                          f"({REC_REASONS[trouble]})"}
                    ok, why = sup.begin_recovery(i, y, mv.end, bool(self.asm.driver.amp_fault[i]))
                    if not ok:
                        return {**r, "ok": False, "error": f"jog {names[i]} refused: {why}"}
                    r["recovery"] = True
                elif not sup.inside(i, mv.end):
                    return {**r, "ok": False, "error": f"jog {names[i]} refused: target "
                                                      f"{mv.end:.6f} m is outside the soft limits"}
                loop.jog_axis(i, mv)
                r["cycle"] = loop.k
            elif op == "arm_index":
                self.asm.driver.arm_index(i)
            elif op == "set_position":
                # homing: the reading shifted by delta from the next cycle; the setpoint, the
                # encoder-jump check's last reading and the law (reset from the new reading)
                # shifted with it, so nothing sees a jump
                if loop.mode[i] != STREAM:
                    return {**r, "ok": False, "error": f"axis {names[i]} is not in command mode"}
                d_m = float(m["delta_m"])
                self.asm.driver.set_position_offset(i, d_m)
                loop.shift_axis(i, d_m)
            elif op == "inject":
                if not self.allow_inject:
                    return {**r, "ok": False, "error": "fault injection is off (daemon.allow_fault_"
                                                      "injection: true, simulated driver only)"}
                inj = m["inject"]
                self.asm.driver.inject(inj["kind"], names[i], inj["cycles"], jump_m=inj["jump_m"],
                                       force_N=inj["force_N"])
                r["cycle"] = loop.k
            else:
                return {**r, "ok": False, "error": f"unknown operation {op!r}"}
        except Exception as exc:  # noqa: BLE001 - a bad command never stops the loop
            return {**r, "ok": False, "error": f"{type(exc).__name__}: {exc}"}
        finally:
            self.status.publish()
        return r

    def _switch(self, i: int, name: str) -> None:
        self.loop.switch_axis(i, self.asm.controller(i, name))
        self.asm.active[i] = name

    # ------------------------------------------------------------------ between cycles
    def on_slack(self, lp) -> None:
        k = lp.k
        ctl = self.ctl
        seq = ctl[CTL_CMD_SEQ]
        if seq != self.seen:
            self.seen = seq
            msgs = self.cmds.recv()
            for m in msgs or ():
                self._answer(self.apply(m))
        if self.resets:
            self.poll_resets(lp)
        if self.term and self.tail < 0:
            self.stop_on_signal(lp, k)
        elif self.tail > 0:
            self.tail -= 1
            if self.tail == 0:
                lp.request_stop()
        if self.status.fault_changed():
            self.check_stream(lp)             # the setpoints of a faulted axis dropped at once ...
            self.status.publish()             # ... a new fault is published at once ...
            self.send_drive_reasons(lp)       # ... with what the drive says about it
        elif k % self.publish_every == 0:
            self.status.publish()
        if k % self.check_every == self.check_every // 2:
            self.check_recorder(lp)
            self.check_stream(lp)
        if k % self.link_every == 0 and self.can_reconnect and not self.term:
            self.check_link(lp)

    def check_stream(self, lp) -> None:
        """Between cycles (at a fault change and every :data:`RECORDER_CHECK_S`): when an axis
        has left command mode (a fault, a stop) the setpoint ring is drained
        (:meth:`SetpointRing.drain`: the rows not taken dropped, the stop outputs off), the axes
        still in command mode braking to rest on their own a_max/j_max (category 1); when no axis
        is in command mode, rows the I/O side still wrote are dropped likewise. So no stale
        setpoint is left to follow at the next start, and the commanded motion's ``idle`` comes
        true within a few cycles of the fault."""
        n = 0
        for i in range(len(self.names)):
            if lp.mode[i] == STREAM:
                n += 1
        stream = lp.stream
        if n < self.n_stream or (n == 0 and stream.depth() > 0):
            stream.drain(n > 0)
        self.n_stream = n

    def _answer(self, ans: dict | None) -> None:
        """Send one command's answer (non-blocking; None: it comes later)."""
        if ans is None:
            return
        try:
            self.replies.send(ans)
        except BlockingIOError:
            self.replies_dropped += 1     # pipe full: the client times out
        except OSError:
            self.io_dead = True

    def poll_resets(self, lp) -> None:
        """Between cycles: the fault resets that wait for a drive to leave its fault
        (:meth:`ServoLoop.poll_fault_reset`), each answered once it is done (cleared, refused by
        another cause, or the drive still in its fault after the bound, named by its state)."""
        left = []
        for i, r in self.resets:
            done, ok, why = lp.poll_fault_reset(i)
            if not done:
                left.append((i, r))
                continue
            self._answer({**r, "ok": ok, "error": self.way_out(i, why), "cycle": lp.k})
            self.status.publish()
        self.resets = left

    def way_out(self, i: int, why: str) -> str:
        """A fault reset's refusal ``why`` ("" when none) with the way out when axis i stands
        outside its soft limits (a drive fault at speed lets the carriage coast on, past them):
        the jog of the disabled axis back inside, which the loop takes in a fault too
        (:meth:`Supervisor.begin_recovery`), to the nearest point 1 mm inside."""
        y = float(self.asm.driver.position_m[i])
        if not why or not math.isfinite(y) or self.loop.supervisor.stands_inside(i, y):
            return why
        lim = self.asm.loaded.axes[self.names[i]].limits
        to = min(max(y, lim.soft_min_m + WAY_OUT_INSIDE_M), lim.soft_max_m - WAY_OUT_INSIDE_M)
        return f"{why}; jog it back inside first: motorctl jog {self.names[i]} {to:.4f}"

    def stop_on_signal(self, lp, k: int) -> None:
        """Between cycles after SIGTERM/SIGINT: a stop of category 1 (IEC 60204-1 §9.2.2) of every
        driven axis (:meth:`ServoLoop.stop_all`: a program or an approach runs on to its next
        rest point within the axis's a_max/j_max, a stream brakes jerk-limited), then 0 V and
        amplifier off; then :data:`SHUTDOWN_TAIL_CYCLES` more cycles are recorded and the loop
        ends. Category 0 (FAULT_SHUTDOWN latched, 0 V at the next cycle) for the axes still
        driven at a second signal or after :meth:`signal_stop_bound_s`."""
        n = len(self.names)
        if self.stop_end < 0:
            self.signal_driven = [i for i in range(n) if lp.mode[i] != IDLE]
            lp.stop_all()
            self.stop_end = k + self.signal_stop_cycles
            self.ctl[CTL_STATE] = STATE_STOPPING
            for i, r in self.resets:       # resets under way are not finished: the daemon ends
                self._answer({**r, "ok": False, "error": f"the daemon is stopping ({self.term})"})
            self.resets = []
        if not (lp.at_rest() or self.signals > 1 or k >= self.stop_end):
            return
        sup = lp.supervisor
        for i in range(n):
            if lp.mode[i] != IDLE:
                self.cut.append(i)
                sup.trip(i, FAULT_SHUTDOWN)
        self.rest = {self.names[i]: {"at_m": float(self.asm.driver.position_m[i]),
                                     "category": 0 if (i in self.cut or sup.fault[i]) else 1}
                     for i in self.signal_driven}
        lp.idle_all()
        self.tail = SHUTDOWN_TAIL_CYCLES

    def _tell_io(self, m: dict) -> None:
        """A message to the I/O process (non-blocking; dropped and counted when the pipe is full)."""
        try:
            self.replies.send(m)
        except BlockingIOError:
            self.replies_dropped += 1
        except OSError:
            self.io_dead = True

    def send_drive_reasons(self, lp) -> None:
        """Between cycles, after a fault latched or cleared: the drive's own words about each
        faulted axis (``Driver.fault_reason``), sent when they change."""
        drv, fault = self.asm.driver, lp.supervisor.fault
        for i in range(len(self.names)):
            text = drv.fault_reason(i) if fault[i] else ""
            if text != self.drive_text[i]:
                self.drive_text[i] = text
                self._tell_io({"op": "drive_fault", "axis": i, "text": text})

    def check_link(self, lp) -> None:
        """Between cycles: is the link to the drives down? Then, while every axis is idle, one
        blocking reconnection attempt every :data:`RECONNECT_EVERY_S` (the loop pauses for at
        most :data:`RECONNECT_TIMEOUT_S` and resynchronises). Nothing is re-enabled."""
        drv, link = self.asm.driver, self.link
        down = drv.link_down
        if not down:
            if not link["connected"]:           # came back by itself (the transport recovered)
                link["connected"] = True
                self._tell_io({"op": "link", **link})
            return
        now = time.monotonic()
        if link["connected"]:
            link["connected"] = False
            self.next_attempt = now + RECONNECT_EVERY_S
            self._tell_io({"op": "link", **link})
            return
        if now < self.next_attempt or any(lp.mode[i] != IDLE for i in range(len(self.names))):
            return
        link["attempts"] += 1
        try:
            drv.reconnect(RECONNECT_TIMEOUT_S)
            link["last_error"] = ""
        except NotImplementedError:
            self.can_reconnect = False         # a driver without a link: nothing to do
            return
        except Exception as exc:  # noqa: BLE001 - the device is not back: try again later
            link["last_error"] = f"{type(exc).__name__}: {exc}"
        lp.resync()
        end = time.monotonic()
        link["last_pause_s"] = end - now
        self.next_attempt = end + RECONNECT_EVERY_S
        if not drv.link_down:
            link["connected"] = True
            link["reconnects"] += 1
        self._tell_io({"op": "link", **link})

    def recorder_trouble(self, lp) -> int:
        """The REC_* code of what is wrong with the recorder now (0: nothing). Cheap: a few
        integer compares on the shared control words."""
        if self.io_dead:
            return REC_DIED
        ctl = self.ctl
        code = ctl[CTL_REC_FAULT]
        if code:
            return code
        n = lp.k + lp.overruns           # loop periods elapsed, missed ones included
        beat = ctl[CTL_REC_BEAT]
        if beat != self.io_beat:
            self.io_beat = beat
            self.io_beat_n = n
        elif n - self.io_beat_n > self.stall_cycles:
            return REC_STALLED
        return 0

    def check_recorder(self, lp) -> None:
        """Between cycles: is the I/O process alive, writing and awake? If not, latch
        FAULT_RECORDER on every axis (0 V, amplifier off from the next cycle)."""
        if not self.io_dead:
            try:
                pid, st = os.waitpid(self.io_pid, os.WNOHANG)
                if pid != 0:
                    self.io_dead, self.io_status = True, st
            except ChildProcessError:
                self.io_dead = True
        code = self.recorder_trouble(lp)
        if code:
            sup = lp.supervisor
            for i in range(len(self.names)):
                if not sup.fault[i] & FAULT_RECORDER:
                    sup.trip(i, FAULT_RECORDER)
                    self.ctl[CTL_REC_LATCHED] = code
        if self.io_dead and not self.term:
            self.term = "recorder process died"

    def finish_for_recorder(self) -> None:
        """After the loop has ended, when the I/O process did not finish the run log: append
        what the ring still holds, write the end record (reopening the segment being
        written), and remove the control socket."""
        index = int(self.ctl[CTL_SEGMENT]) or 1
        try:
            why = "recorder died" if self.io_dead else "recorder did not finish (killed)"
            ended = close_orphaned(self.log_path, index, self.ring,
                                   {"reason": self.term or "loop ended", "recorder": why})
            self.out.write(f"motorctl daemon: end record written by the loop process into "
                           f"{segment_path(self.log_path, index)} ({ended['lost_rows']} rows lost)\n")
        except (LogError, OSError) as exc:
            self.out.write(f"motorctl daemon: cannot write the end record: {exc}\n")
        try:
            os.unlink(self.socket_path)
        except OSError:
            pass

    def on_signal(self, signum, _frame) -> None:
        """SIGTERM/SIGINT: the first asks for the category-1 stop (:meth:`stop_on_signal`, at the
        next cycle boundary), a second cuts the power at once (category 0)."""
        self.signals += 1
        if not self.term:
            self.term = signal.Signals(signum).name

    # ------------------------------------------------------------------ the run
    def _serve(self, rep) -> None:
        """The device is set up: say the loop is ready and run it until it is asked to end."""
        asm, loop, ctl = self.asm, self.loop, self.ctl
        self.replies.send({"op": "ready", "realtime": rep.as_dict(),
                           "realtime_summary": rep.summary(), "loop_pid": os.getpid(),
                           "python_threads": threading.active_count(),
                           "native_threads": len(os.listdir("/proc/self/task")),
                           "cpu_affinity": sorted(os.sched_getaffinity(0)),
                           "switch_interval_s": sys.getswitchinterval()})
        for line in asm.driver.notices:
            self.out.write(f"motorctl daemon: {line}\n")
        self.out.write(f"motorctl daemon: {len(self.names)} axes ({', '.join(self.names)}) at "
                       f"{1 / asm.loaded.period_s:.0f} Hz, all disabled; socket "
                       f"{self.socket_path}; log {self.log_path}; realtime: {rep.summary()}\n")
        self.out.flush()
        ctl[CTL_STATE] = STATE_RUNNING
        loop.run(1 << 62)

    def run(self, reap) -> int:
        """Start the driver and the real-time set-up, run until a signal, shut down.
        ``reap(pid, timeout_s)`` waits for the I/O process. Returns the exit code.

        A signal before the loop's first cycle (``early``: one after the build, or while the
        device is set up) runs no cycle: the device, when it was
        opened, is brought to 0 V with its amplifiers off and that is confirmed by it
        (:func:`motorctl.app.build.shutdown`); one line says so, exit 0."""
        asm, loop, ctl = self.asm, self.loop, self.ctl
        rtc = asm.loaded.cfg.loop.realtime
        rep = None
        old = {s: signal.signal(s, self.on_signal) for s in (signal.SIGTERM, signal.SIGINT)}
        if self.early and not self.term:
            self.term = self.early[0]
        self.status.publish()
        opened = tried = False
        try:
            if not self.term:             # else a signal during the build: no device opened
                try:
                    tried = True
                    rep = start(asm, rtc.policy)
                    opened = True
                except RealtimeError as exc:
                    self.replies.send({"op": "fatal", "error": str(exc)})
                    self.out.write(f"motorctl: error: {exc}\n")
                    return 1
            if not self.term:             # else a signal while the device was set up: no cycle
                self._serve(rep)
        finally:
            try:
                if tried:
                    self.stop_checks = shutdown(asm)
            finally:
                ctl[CTL_STATE] = STATE_ENDED
                for s_, h in old.items():
                    signal.signal(s_, h)
                sd_notify("STOPPING=1")
                try:
                    os.set_blocking(self.replies.wfd, True)   # the loop has ended: waiting is fine
                    self.replies.send({"op": "exit", "reason": self.term or "loop ended",
                                       "stop": [{"axis": c.axis, "confirmed": c.confirmed, "held": c.held}
                                                for c in self.stop_checks]})
                except OSError:
                    pass
                os.close(self.replies.wfd)
                st = reap(self.io_pid, 15.0)
                if self.io_status is None:
                    self.io_status = st
        if not opened and self.term:
            self.out.write(f"motorctl daemon: stopped by {self.term} during start-up, before the device "
                           f"was opened: nothing was driven; log {self.log_path}\n")
            return 0
        confirmed, lines = stop_lines(self.stop_checks)
        if not confirmed:
            for line in lines:
                self.out.write(f"motorctl: error: {line}\n")
        if not (self.io_status is not None and os.WIFEXITED(self.io_status)
                and os.WEXITSTATUS(self.io_status) == 0):
            self.finish_for_recorder()
            what = "died" if self.io_dead else "did not finish"
            self.out.write(f"motorctl: error: the recorder process {what}; "
                           f"{lines[0] if confirmed else 'the stop is not confirmed'}; log {self.log_path}\n")
            return 1
        if not confirmed:
            return 3
        when = " during start-up, before the loop ran" if loop.k == 0 and self.term else ""
        rest = rest_words(self.rest)
        self.out.write(f"motorctl daemon: stopped by {self.term or 'loop end'}{when}: {lines[0]}"
                       f"{'; ' + rest if rest else ''}; log {self.log_path}\n")
        return 0
