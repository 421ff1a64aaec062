"""The main job (``motorctl run``, ``motorctl compare``): build the loop from a config
(:func:`motorctl.app.build.build`), run it, write the run log, return the indexes.

The loop records into a ring of :data:`RING_S` seconds of rows; the rows leave it while the run
goes, for the run log (when asked) and for the indexes and timing statistics, which are
accumulated batch by batch (:class:`motorctl.metrics.TrackingAccumulator`,
:class:`motorctl.recorder.flight.TimingStats`): the loop process's memory does not grow with
the run's length. On the wall clock a child process drains the ring (a shared mapping with the
loop's heartbeat, as the daemon's flight recorder), so the loop process never writes a file; on
the virtual clock the loop takes the rows itself between cycles, every half ring. The log's
header is written before the first cycle, with room for what is known only at the end (the
real-time report, the stop the device confirmed, the signal), which is added last.

A run starts as the daemon's ``start`` does: idle cycles (0 V, amplifier off) read where the
axes stand, until two readings agree (a carriage still coasting is waited for, up to
:data:`motorctl.app.build.START_STILL_WAIT_S`); a position outside the soft limits refuses the run
(:class:`motorctl.app.build.StartRefused`, nothing driven), else every axis approaches its
program's first point (:func:`motorctl.app.build.approach_all`), then the programs run for the
run's duration. The rows carry each axis's mode; the indexes take the program's rows only
(``mode`` = program), in program time, and the log's header gives ``program_start_s`` and the
approaches.

The end of the run's duration, SIGTERM and SIGINT are a stop of category 1 (IEC 60204-1
§9.2.2): every driven axis comes to rest under power along its jerk-limited profile (the
daemon's ``stop``: a move in progress runs on to its end, within the axis's a_max and j_max,
and holds there ``daemon.stop_settle_s``), then 0 V and the amplifier off; the rows of that stop are in the log (mode program, then hold),
not in the indexes (the program's first ``duration`` of rows). A second signal during that stop
ends it at once (category 0: 0 V where the axes are). A fault is category 0 on its axis (0 V
with the amplifier off in the cycle it is seen), the other axes stop in category 1. Every exit
path leaves the axes at 0 V with the amplifiers disabled, confirmed by the device, and the rows
recorded so far are in the log; :attr:`JobResult.rest` says where each axis came to rest.
"""

from __future__ import annotations

import json
import os
import select
import signal
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from motorctl.app.build import (START_STILL_WAIT_S, StartRefused, approach_all, build, log_header, moving_axes,
                                record_layout, shutdown, start, stop_bound_s)
from motorctl.app.lifetime import parent_gone
from motorctl.config import LoadedConfig
from motorctl.driver import drive_fault_refusal
from motorctl.inputs import InputError
from motorctl.loop.records import MODE_PROGRAM, RecordLayout
from motorctl.loop.rt import keep_off, loop_cpu
from motorctl.loop.safety import with_drive_reason
from motorctl.loop.servo import IDLE
from motorctl.metrics import TrackingAccumulator
from motorctl.recorder.flight import CTL_STATE, SharedRing, TimingStats, take_rows
from motorctl.ordering import load_acquire, store_release
from motorctl.recorder.runlog import LogWriter


#: the record ring of a run [s]: rows leave it for the log and the indexes while the run goes,
#: so the loop process's memory does not grow with the run's length
RING_S = 4.0
#: the drain process's wake on the wall clock [s] (on the virtual clock the loop takes the rows
#: itself between cycles, every half ring)
DRAIN_S = 0.02
#: rows per block of the indexes' sums (:meth:`_Sink._account`)
BLOCK_ROWS = 1000
#: header bytes kept free for the facts known at the end (real-time report, stop, signal)
HEADER_RESERVE = 64 << 10
#: the drain process gets this long to hand over its figures after the loop ended [s]
DRAIN_END_S = 60.0
_ENDED = 3          # ring.ctl[CTL_STATE] when the loop has ended (flight.CTL_STATE's codes)
#: the longest approach a run makes room for [s] (a 1 m stroke at 0.5 m/s takes 2 s or so)
MAX_APPROACH_S = 60.0


class _Sink:
    """Takes the rows the loop published out of its ring buffer: appends them to the run log
    (when there is one) and accumulates the indexes and the timing statistics, batch by batch.

    Args:
        rows: the ring (capacity, width) float64. layout: its :class:`RecordLayout`.
        windows: the e_F window per axis [s]. period_s: the loop period [s]. writer: an open
        :class:`LogWriter` or None.
    Rows overwritten before they were taken are counted in ``lost`` (never read torn: the
    publisher's count is read again after the copy).
    """

    def __init__(self, rows, layout: RecordLayout, names, windows, period_s: float, writer=None,
                 program_rows: int | None = None):
        self.rows, self.cap, self.writer = rows, rows.shape[0], writer
        self._left = [program_rows if program_rows is not None else -1] * len(names)  # rows still indexed
        self.k = 0
        self.lost = 0
        self.write_error = ""
        self._t = layout.cycle("t")
        self._turn, self._late = layout.cycle("turnaround_ns"), layout.cycle("lateness_ns")
        self._e = [layout.index(f"{a}.e") for a in names]
        self._u = [layout.index(f"{a}.u") for a in names]
        self._mode = [layout.index(f"{a}.mode") for a in names]
        self._t0 = [None] * len(names)        # each axis's program start [s], from its first row
        self.acc = [TrackingAccumulator(w, period_s) for w in windows]
        self.timing = TimingStats()
        self._pending: list = []
        self._n_pending = 0

    def take(self, published: int, recheck=None) -> None:
        """The rows of cycles [k, published) (``recheck``: the loop's count, when it runs on)."""
        if published <= self.k:
            return
        rows, start = take_rows(self.rows, self.k, published, recheck)
        self.lost += start - self.k
        self.k = published
        if self.writer is not None and not self.write_error:
            try:
                self.writer.append(rows)
            except OSError as exc:
                self.write_error = exc.strerror or str(exc)
        self._pending.append(rows)
        self._n_pending += rows.shape[0]
        if self._n_pending >= BLOCK_ROWS:
            self._account(final=False)

    def _account(self, final: bool) -> None:
        """The indexes and statistics take the pending rows in blocks of :data:`BLOCK_ROWS`
        (the rest waits, unless ``final``): the sums are then the same whatever the batches
        the ring was drained in (the wall and the virtual clock give identical figures)."""
        rows = np.concatenate(self._pending) if len(self._pending) > 1 else self._pending[0]
        n = rows.shape[0] if final else rows.shape[0] // BLOCK_ROWS * BLOCK_ROWS
        for j in range(0, n, BLOCK_ROWS):
            b = rows[j:min(j + BLOCK_ROWS, n)]
            t = b[:, self._t]
            for a, (acc, ce, cu, cm) in enumerate(zip(self.acc, self._e, self._u, self._mode)):
                m = b[:, cm] == MODE_PROGRAM          # the program's rows, in program time
                if self._left[a] >= 0:                # the run's duration, not its stop's rows
                    m &= np.cumsum(m) <= self._left[a]
                    self._left[a] -= int(m.sum())
                if m.any():
                    if self._t0[a] is None:
                        self._t0[a] = float(t[m][0])
                    acc.add(t[m] - self._t0[a], b[m, ce], b[m, cu])
            self.timing.add(b[:, self._turn], b[:, self._late])
        self._pending = [rows[n:]]
        self._n_pending = rows.shape[0] - n

    def close(self) -> None:
        """Close the log (fsync); a failure is kept in ``write_error``."""
        if self.writer is not None:
            try:
                self.writer.close()
            except OSError as exc:
                self.write_error = self.write_error or exc.strerror or str(exc)

    def summary(self) -> dict:
        if self._n_pending:
            self._account(final=True)
        return {"indexes": [acc.indexes() if acc.n else None for acc in self.acc],
                "timing": self.timing.summary(), "lost": self.lost,
                "write_error": self.write_error}


def _drain_process(ring: SharedRing, sink: _Sink, wfd: int, cpu: int | None, parent: int) -> None:
    """The child that drains the ring of a wall-clock run (never returns): off the loop's
    ``cpu`` (:func:`motorctl.loop.rt.keep_off`), takes the published rows every
    :data:`DRAIN_S` until the loop has ended, or its ``parent`` (the loop process) has died
    (``kill -9``: it keeps the rows published so far), closes the log (fsync) and writes its
    summary (JSON) to ``wfd``."""
    code = 1
    try:
        keep_off(cpu)
        signal.signal(signal.SIGINT, signal.SIG_IGN)     # the loop decides when the run ends
        while True:
            ended = load_acquire(ring.ctl, CTL_STATE) == _ENDED or parent_gone(parent)
            sink.take(ring.published(), ring.published)
            if ended:
                break
            time.sleep(DRAIN_S)
        sink.close()
        data = json.dumps(sink.summary()).encode()
        while data:
            data = data[os.write(wfd, data):]
        code = 0
    finally:
        os._exit(code)


def _collect(rfd: int, pid: int) -> dict:
    """The drain process's summary (after the loop ended); {} when it died or hung."""
    chunks, end = [], time.monotonic() + DRAIN_END_S
    try:
        while time.monotonic() < end:
            ready, _, _ = select.select([rfd], [], [], max(0.0, end - time.monotonic()))
            if not ready:
                break
            chunk = os.read(rfd, 1 << 20)
            if not chunk:
                break
            chunks.append(chunk)
    finally:
        os.close(rfd)
        try:
            if os.waitpid(pid, os.WNOHANG) == (0, 0):
                os.kill(pid, signal.SIGKILL)
                os.waitpid(pid, 0)
        except ChildProcessError:
            pass
    try:
        return json.loads(b"".join(chunks))
    except ValueError:
        return {}


@dataclass
class JobResult:
    """Outcome of one run: per-axis indexes and faults, loop timing, real-time report, log path."""

    axes: dict = field(default_factory=dict)      # name -> {"controller", indexes..., "fault",
    #                                                 the protection's peaks and limits}
    timing: dict = field(default_factory=dict)
    realtime: dict = field(default_factory=dict)
    cycles: int = 0
    stopped_by_signal: str = ""
    log_path: str | None = None
    stop: list = field(default_factory=list)      # StopCheck per axis: what the device confirmed
    notices: list = field(default_factory=list)   # the driver's set-up notices
    lost_rows: int = 0                            # rows the ring overwrote before the drain took them
    program_start_s: float | None = None          # when the programs started (after the approaches)
    program_end_s: float | None = None            # when the run's duration ended (its stop began)
    approach: dict = field(default_factory=dict)  # name -> {"from_m", "to_m", "duration_s"}
    rest: dict = field(default_factory=dict)      # name -> {"at_m": last reading [m], "category": 0 | 1}

    @property
    def stop_confirmed(self) -> bool:
        """Every axis's device confirmed 0 V with the amplifier off at the end of the run."""
        return bool(self.stop) and all(c.confirmed for c in self.stop)


def run_job(loaded: LoadedConfig, axes: list | None = None, controller: str | None = None,
            duration_s: float | None = None, clock: str | None = None,
            log_path: str | None = None, realtime_policy: str | None = None,
            on_start=None, on_notice=None) -> JobResult:
    """Run the loop on the configured driver and return the indexes (see :class:`JobResult`).

    Args:
        loaded: a checked config. axes: subset of axis names (default: all).
        controller: a controller name (:data:`motorctl.control.CONTROLLER_NAMES`) overriding
            every axis's controller.
        duration_s: run length [s] (default: loop.duration_s). clock: 'wall' | 'virtual'.
        log_path: where to write the run log (None: no file; a run that never cycled leaves
            none).
        realtime_policy: override of loop.realtime.policy ('off' with the virtual clock).
        on_start: called with (axes, n_cycles, clock) once the driver is active, just before
            the first cycle (e.g. to tell the operator the loop runs).
        on_notice: called with each of the driver's set-up notices (one line each) before
            ``on_start``.
    The run is idle cycles until the axes stand still (two at least), the approaches, then
    ``duration_s`` of the programs (module docstring).
    Raises:
        StartRefused: an axis stands outside its soft limits (or faulted on its first
            reading; a drive in a fault it latched is named with its state and the command that
            resets it, :func:`motorctl.driver.drive_fault_refusal`): refused after the idle
            cycles, nothing driven (their rows are in the log).
        RealtimeError: ``realtime: required`` refused (before the driver is opened).
        ConfigError: ``controller`` is not configured for an axis.
        InputError: the duration is shorter than one period.
        OSError: the driver cannot reach its device; the run log cannot be created (before
            anything starts) or written (after the run, at 0 V: the rows before the failure
            stay in the file).
    """
    cfg = loaded.cfg
    duration = float(duration_s if duration_s is not None else cfg.loop.duration_s)
    clock = clock or cfg.loop.clock
    n_cycles = loaded.timebase.cycles(duration)
    if n_cycles < 1:
        raise InputError(f"duration {duration:g} s is shorter than one period ({loaded.period_s:g} s)")
    policy = realtime_policy or ("off" if clock == "virtual" else cfg.loop.realtime.policy)
    names = list(axes) if axes else list(loaded.axes)
    wall = clock == "wall"
    cap = loaded.timebase.cycles(RING_S)     # the approaches come on top of the program's cycles
    ring = SharedRing(cap, record_layout(loaded, names).width, len(names)) if wall else None
    asm = build(loaded, axes, controller, clock=clock, capacity=cap,
                buffer=ring.rows if wall else None, heartbeat=ring)
    loop, names = asm.loop, asm.names
    loop.idle_all()                          # cycle 0 reads where the axes stand
    writer = None
    if log_path:
        Path(log_path).parent.mkdir(parents=True, exist_ok=True)
        writer = LogWriter(str(log_path), log_header(asm, realtime="pending"), reserve=HEADER_RESERVE)
    windows = [p if (p := loaded.axes[a].trajectory.period_s) > 0 else 4.0 for a in names]
    sink = _Sink(loop.buf, loop.layout, names, windows, loaded.period_s, writer, program_rows=n_cycles)
    result = JobResult()
    stopped = []
    drain = None
    if wall:                   # a child drains the ring; the loop process never writes a file
        rfd, wfd = os.pipe()
        sys.stdout.flush()
        sys.stderr.flush()
        parent = os.getpid()
        pid = os.fork()
        if pid == 0:
            os.close(rfd)
            _drain_process(ring, sink, wfd, loop_cpu(loaded.cfg.loop.realtime.cpu), parent)
        os.close(wfd)
        if writer is not None:
            writer.release()
        drain = (rfd, pid)
    every = max(1, cap // 2)
    plan: dict = {}

    def on_slack(lp):
        # idle cycles until every axis stands still (two readings agree), then the approaches
        # (or the refusal); after the program (or a signal) the category-1 stop, then the end
        if stopped and "stop_k" not in plan:
            plan["end"] = lp.k                   # a signal: the stop now (before the approaches: none start)
        if plan.get("end") is None:
            y_before = plan.get("y")
            plan["y"] = [float(y) for y in asm.driver.position_m]
            moving = moving_axes(asm, y_before) if y_before is not None else names
            if moving and lp.k * loaded.period_s >= START_STILL_WAIT_S:
                plan["end"], plan["refused"] = 0, StartRefused(
                    f"{', '.join(moving)} still moving after {START_STILL_WAIT_S:g} s at 0 V; nothing was driven")
            elif not moving:
                # a drive in a fault it latched (found so at set-up, or since): refused naming the
                # drive's state and the operator's command that resets it; no driver resets it
                held = drive_fault_refusal(asm.driver, names, str(loaded.path))
                try:
                    if held:
                        raise StartRefused(f"{held}; nothing was driven")
                    k_prog, moves = approach_all(asm)
                except StartRefused as exc:
                    plan["end"], plan["refused"] = 0, exc
                else:
                    plan["end"], plan["k_prog"], plan["moves"] = k_prog + n_cycles, k_prog, moves
            else:
                plan["end"] = None
        if plan["end"] is not None and lp.k >= plan["end"]:
            if "stop_k" not in plan:
                plan["stop_k"] = lp.k
                lp.stop_all()
            if lp.at_rest():
                lp.request_stop()
        if not wall and lp.k % every == 0:   # the virtual clock: the rows, every half ring
            sink.take(lp.k)

    loop.on_slack = on_slack

    def on_signal(signum, _frame):
        stopped.append(signal.Signals(signum).name)
        if len(stopped) > 1 or loop.k == 0:   # a second signal, or no cycle yet: at once
            loop.request_stop()

    old = {s: signal.signal(s, on_signal) for s in (signal.SIGTERM, signal.SIGINT)}
    summary: dict = {}
    try:
        report = start(asm, policy)
        result.realtime = report.as_dict()
        result.notices = list(asm.driver.notices)
        try:
            if on_notice is not None:
                for line in result.notices:
                    on_notice(line)
            if on_start is not None:
                on_start(names, n_cycles, clock)
            stop_s = max(stop_bound_s(p, cfg.daemon.stop_settle_s) for p in asm.programs)
            result.cycles = loop.run(n_cycles + loaded.timebase.cycles(START_STILL_WAIT_S + MAX_APPROACH_S + stop_s)
                                     + 4)
        finally:
            result.rest = {a: {"at_m": float(asm.driver.position_m[i]),
                               "category": 1 if loop.mode[i] == IDLE and not asm.supervisor.fault[i] else 0}
                           for i, a in enumerate(names)}
            if stopped:
                loop.shutdown_faults()
            result.stop = shutdown(asm)
    finally:
        for s, h in old.items():
            signal.signal(s, h)
        result.stopped_by_signal = stopped[0] if stopped else ""
        if "k_prog" in plan:
            result.program_start_s = plan["k_prog"] * loaded.period_s
            result.program_end_s = plan["end"] * loaded.period_s
            result.approach = {a: {"from_m": mv.start, "to_m": mv.end, "duration_s": mv.duration}
                               for a, mv in zip(names, plan["moves"])}
        if drain is not None:
            store_release(ring.ctl, CTL_STATE, _ENDED)
            summary = _collect(*drain)
        else:
            sink.take(loop.k)
            sink.close()
            summary = sink.summary()
        # the facts known only now go into the header; a run that never cycled leaves no log
        if log_path:
            _finish_log(str(log_path), loop.k, asm, result)
            result.log_path = str(log_path) if loop.k > 0 else None

    if "refused" in plan:
        raise plan["refused"]
    if summary.get("write_error"):
        raise OSError(f"the run log {log_path}: {summary['write_error']}")
    if not summary:
        raise OSError("the run's drain process ended without its figures")
    for i, a in enumerate(names):
        ctrl = loop.controllers[i]
        entry = {"controller": ctrl.name}
        if summary["indexes"][i] is not None:
            entry.update(summary["indexes"][i])
        entry["fault"] = with_drive_reason(asm.supervisor.reason(i), asm.driver.fault_reason(i))
        entry["io_errors"] = int(asm.supervisor.io_errors[i])
        # the protection's margins (docs/protection.md): its high-water marks over the run
        entry["i2t_peak_V2s"] = float(asm.supervisor.i2t_peak[i])
        entry["i2t_limit_V2s"] = float(asm.supervisor.i2t_limit[i])
        entry["rest_rms_peak_V"] = float(asm.supervisor.oscillation_rms_peak[i])
        entry["rest_rms_limit_V"] = float(asm.supervisor.oscillation_rms_limit[i])
        entry["theta_hat"] = ctrl.theta_hat.tolist()
        result.axes[a] = entry
    tm = summary["timing"]
    result.timing = {**({"cycles": 0} if not tm["cycles"] else tm), "overruns": int(loop.overruns),
                     "page_faults": int(loop.page_faults)}
    result.lost_rows = int(summary["lost"])
    return result


def _finish_log(path: str, k: int, asm, result: JobResult) -> None:
    if k == 0:
        Path(path).unlink(missing_ok=True)
        return
    w, _ = LogWriter.reopen(path)
    try:
        fits = w.update_header(log_header(asm, realtime=result.realtime,
                                   stopped_by_signal=result.stopped_by_signal,
                                   stop=[{"axis": c.axis, "confirmed": c.confirmed, "held": c.held}
                                         for c in result.stop],
                                   notices=result.notices, program_start_s=result.program_start_s,
                                   program_end_s=result.program_end_s, approach=result.approach,
                                   rest=result.rest))
    finally:
        w.close()
    if not fits:
        raise OSError(f"the run log {path}: the final header does not fit in the "
                      f"{HEADER_RESERVE} bytes reserved; the rows are there, the header says "
                      f"realtime 'pending'")
