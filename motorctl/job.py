"""The main job: build driver, controllers and loop from a config, run, write the run log.

Used by ``motorctl run`` and ``motorctl compare``. SIGTERM and SIGINT end the run at a cycle
boundary; every exit path leaves the axes at 0 V with the amplifiers disabled, and the rows
recorded so far are written to the log.
"""

from __future__ import annotations

import datetime as _dt
import signal
from dataclasses import dataclass, field
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

import numpy as np

from motorctl.config import LoadedConfig
from motorctl.metrics import timing_stats, tracking_indexes
from motorctl.rt import restore, setup_realtime
from motorctl.runlog import LogWriter
from motorctl.safety import Supervisor
from motorctl.servo import ServoLoop


def software_version() -> str:
    try:
        return version("motorctl")
    except PackageNotFoundError:
        return "unknown"


@dataclass
class JobResult:
    """Outcome of one run: per-axis indexes and faults, loop timing, real-time report, log path."""

    axes: dict = field(default_factory=dict)      # name -> {"controller", indexes..., "fault"}
    timing: dict = field(default_factory=dict)
    realtime: dict = field(default_factory=dict)
    cycles: int = 0
    stopped_by_signal: str = ""
    log_path: str | None = None


def run_job(loaded: LoadedConfig, axes: list | None = None, controller: str | None = None,
            duration_s: float | None = None, clock: str | None = None,
            log_path: str | None = None, realtime_policy: str | None = None,
            on_start=None) -> JobResult:
    """Run the loop on the configured driver and return the indexes (see :class:`JobResult`).

    Args:
        loaded: a checked config. axes: subset of axis names (default: all).
        controller: 'c1' or 'c2' to override every axis's controller type.
        duration_s: run length [s] (default: loop.duration_s). clock: 'wall' | 'virtual'.
        log_path: where to write the run log (None: no file).
        realtime_policy: override of loop.realtime.policy ('off' with the virtual clock).
        on_start: called with (axes, n_cycles, clock) once the driver is open, just before
            the first cycle (e.g. to tell the operator the loop runs).
    Raises:
        RealtimeError: ``realtime: required`` refused (before the driver is opened).
        OSError: the driver cannot reach its device.
    """
    cfg = loaded.cfg
    names = list(axes) if axes else list(loaded.axes)
    duration = float(duration_s if duration_s is not None else cfg.loop.duration_s)
    clock = clock or cfg.loop.clock
    n_cycles = int(round(duration / loaded.period_s))
    rt_cfg = cfg.loop.realtime
    policy = realtime_policy or ("off" if clock == "virtual" else rt_cfg.policy)

    driver = loaded.make_driver(names)
    ctrls = loaded.make_controllers(names, controller)
    programs = [loaded.axes[a].trajectory.program() for a in names]
    sup = Supervisor([loaded.axes[a].limits for a in names], loaded.period_s)
    loop = ServoLoop(driver, ctrls, programs, sup, loaded.period_s, capacity=max(n_cycles, 1),
                     clock=clock, spin_us=rt_cfg.spin_us)
    result = JobResult()
    stopped = []

    def on_signal(signum, _frame):
        stopped.append(signal.Signals(signum).name)
        loop.request_stop()

    started = _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")
    old = {s: signal.signal(s, on_signal) for s in (signal.SIGTERM, signal.SIGINT)}
    try:
        # real-time set-up first: with `realtime: required` a refusal raises before the driver
        # is opened, so nothing starts
        result.realtime = setup_realtime(policy, rt_cfg.priority, rt_cfg.cpu, rt_cfg.lock_memory).as_dict()
        driver.open()
        try:
            if on_start is not None:
                on_start(names, n_cycles, clock)
            result.cycles = loop.run(n_cycles)
        finally:
            if stopped:
                loop.shutdown_faults()
            try:
                loop.safe_output()
            finally:
                driver.close()
    finally:
        restore()
        for s, h in old.items():
            signal.signal(s, h)
        result.stopped_by_signal = stopped[0] if stopped else ""
        # what was recorded reaches the log on every exit path, an exception included
        if log_path and loop.k > 0:
            _write_log(log_path, loaded, loop, driver, ctrls, names, clock, started, result)

    rows = loop.rows()
    t = rows[:, 0]
    for i, a in enumerate(names):
        e = rows[:, loop.columns.index(f"{a}.e")]
        u = rows[:, loop.columns.index(f"{a}.u")]
        period = loaded.axes[a].trajectory.period_s
        entry = {"controller": ctrls[i].kind}
        if rows.shape[0]:
            entry.update(tracking_indexes(t, e, u, period if period > 0 else 4.0))
        entry["fault"] = sup.reason(i)
        entry["io_errors"] = sup.io_errors[i]
        entry["theta_hat"] = ctrls[i].theta_vector().tolist()
        result.axes[a] = entry
    result.timing = timing_stats(rows[:, 2], rows[:, 1], loop.overruns)
    return result


def _write_log(log_path, loaded, loop, driver, ctrls, names, clock, started, result) -> None:
    header = {
        "format": 1,
        "software": f"motorctl {software_version()}",
        "started": started,
        "config_file": str(loaded.path),
        "config": loaded.cfg.model_dump(mode="json"),
        "driver_type": loaded.cfg.driver.type,
        "axes": names,
        "controllers": {a: ctrls[i].kind for i, a in enumerate(names)},
        "period_s": loaded.period_s,
        "clock": clock,
        "realtime": result.realtime,
        "columns": loop.columns,
        "driver": driver.describe(),
        "stopped_by_signal": result.stopped_by_signal,
    }
    Path(log_path).parent.mkdir(parents=True, exist_ok=True)
    with LogWriter(log_path, header) as w:
        w.append(np.ascontiguousarray(loop.rows()))
    result.log_path = str(log_path)
