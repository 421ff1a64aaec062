"""The operator's reset of a drive's own fault with no daemon running
(``motorctl fault-reset --config CONFIG AXIS...``).

A drive's fault (a CiA 402 drive in Fault, a Modbus device's fault bit, an EtherCAT drive's
statusword) stays latched in the drive across runs and daemon restarts: no driver resets it on
its own, and ``motorctl run`` is refused while one is there, naming the drive's state and this
command (:func:`motorctl.driver.drive_fault_refusal`). With a daemon running, its
``fault-reset AXIS`` sends the reset; without one, :func:`reset_drive_faults` opens the driver
from the config, runs idle cycles (0 V, every amplifier disabled, at the loop's period) to read
each drive's state, asks each named drive that reports a fault for its own reset
(:meth:`motorctl.driver.Driver.reset_fault`: the rising edge of CiA 402 controlword bit 7,
transition 15, in the process data; a Modbus map's ``fault_reset`` bit), runs cycles until the
drive has left its fault (at most :data:`RESET_WAIT_S`), reads the state after, and closes the
driver with its confirmed stop. It never enables an amplifier.

A daemon holds the bus while it runs: where its control socket answers (the config's
``daemon.socket``, ``--socket``, ``$MOTORCTL_SOCKET``), or the driver hears another master on
the bus (:meth:`motorctl.driver.Driver.other_master`: a CANopen SYNC or host heartbeat), the
reset is refused (:class:`BusHeld`) and names the daemon's command instead.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, field

import numpy as np

#: longest wait for a drive to leave its fault after its reset [s] (CiA 402 drives take a few
#: cycles; the PowerStateMachine sends up to 3 rising edges of bit 7, 8 cycles apart)
RESET_WAIT_S = 1.0
#: idle cycles before the drives' states are judged: the first answers of the process data [s]
SETTLE_S = 0.05


class BusHeld(OSError):
    """A daemon answers on its control socket: it holds the bus. One line; exit code 1."""


@dataclass(frozen=True)
class DriveReset:
    """What the reset did to one axis's drive.

    Attributes:
        axis: the axis name. was: the drive's state before (its :meth:`Driver.fault_state`),
            '' when it reported no fault. now: its state after (:meth:`Driver.fault_state`
            while it still reports a fault, else :meth:`Driver.drive_state`).
        sent: the drive's own reset was sent. cleared: the drive reports no fault now.
    """

    axis: str
    was: str
    now: str
    sent: bool
    cleared: bool


@dataclass
class ResetReport:
    """:func:`reset_drive_faults`'s answer: per named axis a :class:`DriveReset`, the driver's
    set-up notices, and the stop lines (:func:`motorctl.app.build.stop_lines`)."""

    axes: list = field(default_factory=list)
    notices: list = field(default_factory=list)
    stop_confirmed: bool = False
    stop: list = field(default_factory=list)


def daemon_answering(paths) -> str | None:
    """The first of the control socket ``paths`` a daemon answers on (a ``status`` request),
    None when none does (a socket file left by a dead daemon does not count)."""
    from motorctl.client import DaemonUnreachable, call
    for p in paths:
        if not p or not os.path.exists(p):
            continue
        try:
            call(p, {"cmd": "status"}, 2.0)
        except DaemonUnreachable:
            continue
        return p
    return None


def reset_drive_faults(loaded, axes: list[str], socket_paths=()) -> ResetReport:
    """The operator's reset of the drives of ``axes`` with no daemon (module docstring).

    Args:
        loaded: the checked config (:func:`motorctl.config.load_config`). axes: axis names of it.
        socket_paths: control sockets to look for a running daemon on, besides the config's
            ``daemon.socket``.
    Returns:
        a :class:`ResetReport`.
    Raises:
        InputError: an axis is not in the config (the message lists its axes).
        BusHeld: a daemon answers on one of the sockets, or the driver hears another master on
            the bus (nothing was opened).
        OSError, ConnectionError: the driver cannot reach its device.
    """
    from motorctl.inputs import InputError
    names = list(loaded.axes)
    unknown = [a for a in axes if a not in names]
    if unknown:
        raise InputError(f"{loaded.path}: no axis {', '.join(unknown)}; the config's axes: {', '.join(names)}")
    held = daemon_answering([*socket_paths, loaded.cfg.daemon.socket])
    if held is not None:
        raise BusHeld(f"a daemon answers on {held}: it holds the bus, nothing was opened; reset through it: "
                      f"'motorctl --socket {held} fault-reset {' '.join(axes)}'")
    drv = loaded.make_driver()
    seen = drv.other_master()
    if seen:
        raise BusHeld(f"{seen} (a daemon or a run holds it): nothing was opened; reset through the daemon "
                      f"('motorctl --socket SOCKET fault-reset {' '.join(axes)}') or once it has stopped")
    report = ResetReport()
    try:
        drv.open()
        report.notices = list(drv.notices)
        n = len(names)
        period = loaded.period_s
        cycle = _Cycles(drv, n, period)
        cycle.run(max(3, round(SETTLE_S / period)))
        idx = [names.index(a) for a in axes]
        was = {i: (drv.fault_state(i) or "the device reports an amplifier fault") if drv.amp_fault[i] else ""
               for i in idx}
        sent = {i: bool(drv.amp_fault[i]) and drv.reset_fault(i) for i in idx}
        cycle.run(max(1, round(RESET_WAIT_S / period)), until=lambda: not any(drv.amp_fault[i] for i in idx))
        cycle.run(max(3, round(SETTLE_S / period)))      # the state the drive settles in after leaving Fault
        for i in idx:
            now = drv.fault_state(i) if drv.amp_fault[i] else drv.drive_state(i)
            report.axes.append(DriveReset(names[i], was[i], now or "", sent[i], not drv.amp_fault[i]))
    finally:
        checks = drv.deactivate()
        drv.close()
    from motorctl.app.build import stop_lines
    report.stop_confirmed, report.stop = stop_lines(checks)
    return report


class _Cycles:
    """Idle cycles (0 V, every amplifier disabled) at the loop's period: read, write, service."""

    def __init__(self, drv, n: int, period_s: float):
        self.drv, self.period = drv, period_s
        self.zeros, self.off = np.zeros(n), np.zeros(n, dtype=bool)
        self.t = time.perf_counter()

    def run(self, k: int, until=None) -> None:
        d = self.drv
        for _ in range(k):
            d.read()
            d.write(self.zeros, self.off)
            d.service()
            self.t = max(self.t + self.period, time.perf_counter() - self.period)
            left = self.t - time.perf_counter()
            if left > 0:
                time.sleep(left)
            if until is not None and until():
                return
