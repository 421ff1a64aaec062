"""The main job (``motorctl run``, ``motorctl compare``): build the loop from a config
(:func:`motorctl.app.build.build`), run it, write the run log, return the indexes.

SIGTERM and SIGINT end the run at a cycle boundary; every exit path leaves the axes at 0 V with
the amplifiers disabled, and the rows recorded so far are written to the log.
"""

from __future__ import annotations

import signal
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from motorctl.app.build import build, log_header, shutdown, start
from motorctl.config import LoadedConfig
from motorctl.inputs import InputError
from motorctl.loop.records import RecordLayout
from motorctl.loop.safety import with_drive_reason
from motorctl.metrics import timing_stats, tracking_indexes
from motorctl.recorder.runlog import LogWriter


#: largest in-memory record of one run [bytes] (the daemon records into a ring instead)
MAX_RECORD_BYTES = 2 << 30


def _check_record_size(loaded: LoadedConfig, axes, duration: float, n_cycles: int) -> None:
    """A run keeps every row in memory: refuse, before anything starts, a duration whose
    record does not fit in :data:`MAX_RECORD_BYTES` (or that is shorter than one period)."""
    names = list(axes) if axes else list(loaded.axes)
    width = RecordLayout(names).width
    if n_cycles < 1:
        raise InputError(f"duration {duration:g} s is shorter than one period "
                         f"({loaded.period_s:g} s)")
    if n_cycles * width * 8 > MAX_RECORD_BYTES:
        fit_s = MAX_RECORD_BYTES // (width * 8) * loaded.period_s
        raise InputError(f"duration {duration:g} s: {n_cycles} cycles of {width} columns need "
                         f"{n_cycles * width * 8 / 2**30:.1f} GiB of records; at most "
                         f"{fit_s:.0f} s fit in {MAX_RECORD_BYTES / 2**30:.0f} GiB at "
                         f"{1 / loaded.period_s:g} Hz with {len(names)} axes (the daemon "
                         f"records without a limit)")


@dataclass
class JobResult:
    """Outcome of one run: per-axis indexes and faults, loop timing, real-time report, log path."""

    axes: dict = field(default_factory=dict)      # name -> {"controller", indexes..., "fault"}
    timing: dict = field(default_factory=dict)
    realtime: dict = field(default_factory=dict)
    cycles: int = 0
    stopped_by_signal: str = ""
    log_path: str | None = None
    stop: list = field(default_factory=list)      # StopCheck per axis: what the device confirmed
    notices: list = field(default_factory=list)   # the driver's set-up notices

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
        log_path: where to write the run log (None: no file).
        realtime_policy: override of loop.realtime.policy ('off' with the virtual clock).
        on_start: called with (axes, n_cycles, clock) once the driver is active, just before
            the first cycle (e.g. to tell the operator the loop runs).
        on_notice: called with each of the driver's set-up notices (one line each) before
            ``on_start``.
    Raises:
        RealtimeError: ``realtime: required`` refused (before the driver is opened).
        ConfigError: ``controller`` is not configured for an axis.
        OSError: the driver cannot reach its device.
    """
    cfg = loaded.cfg
    duration = float(duration_s if duration_s is not None else cfg.loop.duration_s)
    clock = clock or cfg.loop.clock
    n_cycles = loaded.timebase.cycles(duration)
    _check_record_size(loaded, axes, duration, n_cycles)
    policy = realtime_policy or ("off" if clock == "virtual" else cfg.loop.realtime.policy)
    asm = build(loaded, axes, controller, clock=clock, capacity=max(n_cycles, 1))
    loop, names = asm.loop, asm.names
    result = JobResult()
    stopped = []

    def on_signal(signum, _frame):
        stopped.append(signal.Signals(signum).name)
        loop.request_stop()

    old = {s: signal.signal(s, on_signal) for s in (signal.SIGTERM, signal.SIGINT)}
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
            result.cycles = loop.run(n_cycles)
        finally:
            if stopped:
                loop.shutdown_faults()
            result.stop = shutdown(asm)
    finally:
        for s, h in old.items():
            signal.signal(s, h)
        result.stopped_by_signal = stopped[0] if stopped else ""
        # what was recorded reaches the log on every exit path, an exception included
        if log_path and loop.k > 0:
            header = log_header(asm, realtime=result.realtime,
                                stopped_by_signal=result.stopped_by_signal,
                                stop=[{"axis": c.axis, "confirmed": c.confirmed, "held": c.held}
                                      for c in result.stop],
                                notices=result.notices)
            Path(log_path).parent.mkdir(parents=True, exist_ok=True)
            with LogWriter(log_path, header) as w:
                w.append(np.ascontiguousarray(loop.rows()))
            result.log_path = str(log_path)

    rows = loop.rows()
    lay = loop.layout
    t = rows[:, lay.cycle("t")]
    for i, a in enumerate(names):
        e = rows[:, lay.index(f"{a}.e")]
        u = rows[:, lay.index(f"{a}.u")]
        period = loaded.axes[a].trajectory.period_s
        ctrl = loop.controllers[i]
        entry = {"controller": ctrl.name}
        if rows.shape[0]:
            entry.update(tracking_indexes(t, e, u, period if period > 0 else 4.0))
        entry["fault"] = with_drive_reason(asm.supervisor.reason(i), asm.driver.fault_reason(i))
        entry["io_errors"] = int(asm.supervisor.io_errors[i])
        entry["theta_hat"] = ctrl.theta_hat.tolist()
        result.axes[a] = entry
    result.timing = timing_stats(rows[:, lay.cycle("turnaround_ns")],
                                 rows[:, lay.cycle("lateness_ns")], loop.overruns)
    return result
