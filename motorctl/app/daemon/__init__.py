"""``motorctl daemon CONFIG``: the long-running service that runs the 5 kHz loop.

Two processes (three with a live view), so that nothing can block the loop (docs/daemon.md):

* the **loop process** (the main PID; SCHED_FIFO, mlockall, gc frozen and disabled, pinned to a
  CPU): one thread, the servo loop on the driver, recording into a shared-memory ring
  (:class:`~motorctl.recorder.flight.SharedRing`) with a shared heartbeat; commands are applied
  between cycles (:mod:`.loop_side`);
* the **I/O process** (forked before the real-time set-up; SCHED_OTHER, on the other CPUs):
  the control socket, the run log and event logs, ``status``, systemd's notify protocol
  (:mod:`.io_side`). Wire formats: :mod:`.protocol`; the status block: :mod:`.status`.
* with a scope or Foxglove configured, the **view process** (forked by the I/O process,
  nice 0 with bounded work per wake, ending with it): the scope page and Foxglove server, fed
  frames without waiting (:mod:`.views`).
* with ``daemon.metrics`` configured, the **metrics process** (forked by the I/O process, nice
  0, ending with it): Prometheus ``/metrics`` from a snapshot the I/O process sends every second
  (:mod:`.metrics`).

Every axis starts disabled (0 V, amplifier off) and only an operator's ``start`` enables it,
so a restart by systemd never re-enables an axis. SIGTERM/SIGINT: a stop of category 1
(IEC 60204-1 §9.2.2): every driven axis comes to rest on its jerk-limited profile (the
``stop`` command's; a command-mode axis brakes), bounded, then 0 V with the amplifier off; a
second signal, or the bound passed, cuts the power at once (FAULT_SHUTDOWN latched). A few
more cycles are recorded, the I/O process drains, flushes and closes the log, then the daemon
exits 0. A signal during start-up: one line, no cycle run, 0 V confirmed when the device was
opened.
``kill -9`` of the loop process: the I/O process sees the reply pipe close, drains what the
loop published and closes the log. If the I/O process dies, the loop latches every axis with
FAULT_RECORDER, ends, writes the end record into the run log itself, removes the socket and
exits non-zero (no motion without a recorder). A recorder that cannot write (a full disk) or
stalls latches every axis the same way while the daemon keeps serving ``status``.

The run log is a numbered set of segments kept within ``daemon.log_budget_bytes`` and
``log_max_age_s`` (:mod:`motorctl.recorder.segments`).
"""

from __future__ import annotations

import datetime as _dt
import os
import signal
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from motorctl.app.build import Assembly, build, log_header, record_layout, stop_bound_s
from motorctl.app.daemon.io_side import io_main
from motorctl.app.daemon.motion_side import warm_up as motion_warm_up
from motorctl.app.daemon.loop_side import LoopSide
from motorctl.app.daemon.notify import sd_notify
from motorctl.app.daemon.protocol import DaemonError, Mailbox, bind_control_socket
from motorctl.app.daemon.status import ST_SIZE
from motorctl.config import ConfigError, load_config
from motorctl.loop.stream import SetpointRing
from motorctl.motion.gcode import output_names
from motorctl.recorder.flight import SharedRing, stall_bound_s
from motorctl.recorder.segments import Retention, SegmentWriter

#: seconds of records the shared ring holds beyond the event window and the recorder's stall
#: bound (2·flush_s + 1 s): an I/O process stalled for that bound and this spare loses no row
#: (the loop latches every axis at the bound; the default flush_s 0.5 s gives 3 s in all)
RING_SPARE_S = 1.0
#: extra time a stop may take beyond the longest move and the settle time [s]
STOP_MARGIN_S = 0.05
#: seconds of setpoints the stream of commanded motion holds (motorctl.loop.stream); the I/O
#: side keeps about motion_side.LEAD_S of it filled
STREAM_RING_S = 1.0
#: header bytes reserved for what is known only later (real-time report, commands, end)
HEADER_RESERVE = 16384


@dataclass
class DaemonPlan:
    """What both processes know after the fork (built before it)."""

    asm: Assembly
    ring: SharedRing
    socket_path: str
    log_path: str          # the run's name (DIR/motorctl-STAMP-PID.mlog); segments .0001.mlog ...
    header: dict
    stop_bound_s: list


def plan_daemon(config_path: str, socket_path: str | None, log_dir: str | None) -> DaemonPlan:
    """Load the config, build the loop on a shared ring, choose the log path.

    Raises:
        ConfigError: the config is wrong. DaemonError: the log directory cannot be created.
    """
    loaded = load_config(config_path)
    cfg = loaded.cfg
    d = cfg.daemon
    if cfg.loop.clock != "wall":
        raise ConfigError(loaded.path, "loop.clock", "the daemon runs on the wall clock; set clock: wall")
    ldir = Path(log_dir or d.log_dir)
    try:
        ldir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise DaemonError(f"cannot create the log directory {ldir}: {exc.strerror}") from None
    stamp = _dt.datetime.now().strftime("%Y%m%dT%H%M%S")
    log_path = str(ldir / f"motorctl-{stamp}-{os.getpid()}.mlog")
    names = list(loaded.axes)
    tb = loaded.timebase
    outputs, stop_outputs = output_names(cfg.gcode)
    width = record_layout(loaded, names, outputs).width
    window_s = max(d.event_before_s + d.event_after_s,
                   d.overrun_event_before_s + d.overrun_event_after_s)
    ring = SharedRing(tb.cycles(window_s + stall_bound_s(d.flush_s) + RING_SPARE_S), width,
                      len(names), ST_SIZE)
    # every configured controller of every axis is built (and compiled) before anything runs:
    # a switch is a swap
    stream = SetpointRing(tb.cycles(max(STREAM_RING_S, 2.0 * d.motion_lead_s)), len(names),
                          outputs=outputs, stop_outputs=stop_outputs)
    asm = build(loaded, names, clock="wall", capacity=ring.capacity, buffer=ring.rows,
                heartbeat=ring, operated=True, all_controllers=True, stream=stream)
    motion_warm_up()                 # the I/O side's compiled steps too, before the fork
    stop_bound = [stop_bound_s(prog, d.stop_settle_s) + STOP_MARGIN_S for prog in asm.programs]
    header = log_header(asm, kind="daemon run log", realtime="pending")
    return DaemonPlan(asm, ring, socket_path or d.socket, log_path, header, stop_bound)


def run_daemon(config_path: str, socket_path: str | None = None, log_dir: str | None = None,
               out=sys.stderr) -> int:
    """Run the service until SIGTERM/SIGINT. Returns the exit code (0 after a signal).

    A signal while the daemon is built (the config read, the loop's compile) ends it with one
    line and nothing opened; from then on the loop process's own stop (:mod:`.loop_side`: a
    signal before its first cycle runs none, 0 V confirmed by the device when it was opened).

    Raises:
        ConfigError: the config is wrong (exit 2 in the CLI).
        DaemonError: the socket or the log cannot be created (exit 1).
    """
    term: list = []

    def start_up_signal(signum, _frame):
        raise _StartUpSignal(signal.Signals(signum).name)

    def note_signal(signum, _frame):
        term.append(signal.Signals(signum).name)

    old = {s: signal.signal(s, start_up_signal) for s in (signal.SIGTERM, signal.SIGINT)}
    try:
        plan = plan_daemon(config_path, socket_path, log_dir)
    except _StartUpSignal as exc:
        for s, h in old.items():
            signal.signal(s, h)
        sys.stdout.flush()
        out.write(f"motorctl daemon: stopped by {exc} during start-up, before the device was opened: "
                  f"nothing was driven\n")
        return 0
    except BaseException:
        for s, h in old.items():
            signal.signal(s, h)
        raise
    # from here to the loop process's own handlers a signal is noted (the loop process then
    # opens no device); the I/O process ignores the signals
    for s in old:
        signal.signal(s, note_signal)
    try:
        return _serve(plan, term, out)
    finally:
        for s, h in old.items():
            signal.signal(s, h)


class _StartUpSignal(Exception):
    """SIGTERM or SIGINT while the daemon is planned and built (config, compile): nothing is
    opened yet."""


def _serve(plan: DaemonPlan, term: list, out) -> int:
    d = plan.asm.loaded.cfg.daemon
    lsock = bind_control_socket(plan.socket_path, d.group)
    retention = Retention(str(Path(plan.log_path).parent), d.log_budget_bytes,
                          d.log_segment_bytes, d.log_max_age_s,
                          row_bytes_per_s=8.0 * plan.ring.width / plan.asm.loaded.period_s)
    try:
        writer = SegmentWriter(plan.log_path, plan.header, reserve=HEADER_RESERVE,
                               segment_bytes=d.log_segment_bytes, segment_s=d.log_segment_s,
                               retention=retention)
    except OSError as exc:
        lsock.close()
        Path(plan.socket_path).unlink(missing_ok=True)
        raise DaemonError(f"cannot create the run log {plan.log_path}: {exc.strerror}") from None
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
            code = io_main(plan, lsock, writer, Mailbox(wfd=cmd_w), Mailbox(rfd=rep_r))
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
    side = LoopSide(plan.asm, plan.ring, pid, Mailbox(rfd=cmd_r), Mailbox(wfd=rep_w),
                    plan.socket_path, plan.log_path, out, early=term)
    return side.run(_reap)


def _reap(pid: int, timeout_s: float) -> int | None:
    """Wait up to ``timeout_s`` for the I/O process, then SIGKILL it. Returns its wait
    status, or None when it had been reaped already."""
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        try:
            got, st = os.waitpid(pid, os.WNOHANG)
        except ChildProcessError:
            return None
        if got != 0:
            return st
        time.sleep(0.01)
    try:
        os.kill(pid, signal.SIGKILL)
        return os.waitpid(pid, 0)[1]
    except (ProcessLookupError, ChildProcessError):
        return None


__all__ = ["run_daemon", "plan_daemon", "sd_notify", "bind_control_socket", "DaemonError", "Mailbox"]
