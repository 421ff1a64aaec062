"""The driver interface: one bus exchange per cycle for every axis of a group.

Lifecycle (ros2_control's hardware lifecycle; python-can's ``BusABC`` rule: a public method
around a private hook, the hook is what a driver writes)::

    Driver(options, axis_options, period_s)   parse only; no I/O                 unconfigured
    configure()  -> _configure()              reach the device, check it answers, read and
                                              set its parameters, measure round trips
                                              (may block)                         inactive
    activate()   -> _activate()               start cyclic exchange (e.g. CiA 402: NMT
                                              operational, SYNC); every amplifier still
                                              disabled (may block)                active
    read() / write(u_V, enable)               cyclic, inside the 5 kHz loop: never block past
                                              the deadline, never raise, never allocate arrays
    deactivate() -> _stop(), _deactivate()    0 V with every amplifier disabled as a
                                              transaction of its own, answered and read
                                              back (a :class:`StopCheck` per axis), then
                                              stop cyclic exchange (may block)    inactive
    close()      -> _close()                  release the transport (deactivates first if
                                              needed; idempotent)                 finalized

An amplifier is enabled per axis, cycle by cycle, through the ``enable`` argument of
:meth:`Driver.write` (a drive's own power state machine, where it has one, is stepped by
the driver from that request without blocking).

Named interfaces per axis (ros2_control's command/state interfaces, LinuxCNC's canonical
channels), with limits: command ``voltage_out`` [V] within ±:meth:`Driver.voltage_limit_V`
and ``enable``; state ``position`` [m] (:attr:`position_m`), ``amp_fault``. Per-axis health
flags are set by read/write instead of raising: :attr:`read_error`, :attr:`write_error` (this
cycle's exchange failed) and :attr:`amp_fault` (the amplifier reports a fault). The supervisor
turns them into faults.

Drivers register under the entry-point group ``motorctl.drivers`` (as python-can interfaces do
under ``can.interface``); :func:`load_driver_class` finds them. The core never imports a
concrete driver.
"""

from __future__ import annotations

import abc
from dataclasses import dataclass
from importlib.metadata import entry_points
from typing import ClassVar

import numpy as np
from pydantic import BaseModel

from motorctl.schema import StrictModel

ENTRY_POINT_GROUP = "motorctl.drivers"


class NoOptions(StrictModel):
    """A driver or axis section with no settings."""


@dataclass(frozen=True)
class BusBudget:
    """What one cycle costs on the bus, computed from the driver's settings.

    Attributes:
        cycle_time_s: bus time one cycle needs for the configured axes [s].
        max_rate_hz: the highest loop rate the bus can carry [Hz].
        detail: the arithmetic behind the figures, one line, for error messages.
        suggestion: which setting would fit a rate the bus cannot carry ('' when none needed).
    """

    cycle_time_s: float
    max_rate_hz: float
    detail: str
    suggestion: str = ""


@dataclass(frozen=True)
class StopCheck:
    """What one axis's device holds after :meth:`Driver.deactivate`, as read back from it.

    Attributes:
        axis: the axis name.
        confirmed: the device answered the 0 V, amplifier-off command and what was read back
            afterwards says it holds 0 V with the amplifier off.
        held: what was read back, one line (e.g. "HR 100 = 0 (0.000 V), HR 101 bit 0 = 0
            (amplifier off)"), or why nothing could be (e.g. "no answer within 1 s").
    """

    axis: str
    confirmed: bool
    held: str


@dataclass(frozen=True)
class Interface:
    """A named command or state interface of one axis, with its unit and limits."""

    name: str
    unit: str
    min: float
    max: float


class LifecycleError(RuntimeError):
    """A lifecycle method was called in a state that does not allow it."""


class Driver(abc.ABC):
    """Base class of every I/O driver (sim, CAN, serial, Modbus, ...).

    Subclasses set ``Options`` and ``AxisOptions`` (pydantic models, strict), implement
    :meth:`read` and :meth:`write`, and override the lifecycle hooks they need
    (:meth:`_configure`, :meth:`_activate`, :meth:`_deactivate`, :meth:`_close`) and
    :meth:`_full_scale_V`.

    Args:
        options: an ``Options`` instance (the YAML ``driver:`` section without ``type``).
        axis_options: axis name → ``AxisOptions`` instance (``axes.NAME.driver``), in loop order.
        period_s: loop period [s].
    Attributes:
        state (str): "unconfigured", "inactive", "active" or "finalized".
        position_m (np.ndarray): (n_axes,) positions of the last read [m].
        read_error, write_error, amp_fault (np.ndarray): (n_axes,) bool health flags.
    """

    Options: ClassVar[type[BaseModel]] = NoOptions
    AxisOptions: ClassVar[type[BaseModel]] = NoOptions
    #: longest wait of :meth:`deactivate` for the device to answer and confirm the stop [s]
    STOP_TIMEOUT_S: ClassVar[float] = 1.0

    def __init__(self, options: BaseModel, axis_options: dict[str, BaseModel], period_s: float):
        self.options = options
        self.axis_options = dict(axis_options)
        self.axis_names = list(axis_options)
        self.period_s = float(period_s)
        n = len(self.axis_names)
        self.position_m = np.zeros(n)
        self.read_error = np.zeros(n, dtype=bool)
        self.write_error = np.zeros(n, dtype=bool)
        self.amp_fault = np.zeros(n, dtype=bool)
        self.state = "unconfigured"
        self.stop_checks: list[StopCheck] = []
        #: set-up notices, one line each, prefixed "notice: " or "warning: " (what configure
        #: cleared on the device, optional objects it does not have, a missing watchdog); the
        #: CLI prints them, the daemon journals them, the run-log header keeps them
        self.notices: list[str] = []
        #: the machine outputs as :meth:`apply_outputs` last set them (name → value)
        self.outputs: dict[str, float] = {}

    # ------------------------------------------------------------------ lifecycle
    def apply_outputs(self, names: tuple[str, ...], values: np.ndarray) -> None:
        """The machine outputs ``names`` of the setpoint stream take ``values`` ((len(names),): 0/1
        for a digital output, the S value for a power output) in this cycle's exchange. Called by
        the loop inside the cycle, before :meth:`write`, only in a cycle where the stream changed
        them (:mod:`motorctl.loop.stream`: LinuxCNC's motion-synchronised outputs); it must not
        block nor allocate a buffer. The base class records them in :attr:`outputs` (a driver with
        outputs on its bus overrides this and puts them into the process image its write sends)."""
        for name, v in zip(names, values):
            self.outputs[name] = float(v)

    def configure(self) -> None:
        """Reach the device and set it up (may block; never inside the cycle). What the set-up
        found and changed on the way is in :attr:`notices`.

        Raises:
            LifecycleError: not unconfigured. OSError: the device cannot be reached.
        """
        self._require("configure", "unconfigured")
        self.notices = []
        self._configure()
        self.state = "inactive"

    def activate(self) -> None:
        """Start cyclic exchange with every amplifier disabled (may block).

        Raises:
            LifecycleError: not inactive. OSError: the device refused.
        """
        self._require("activate", "inactive")
        self._activate()
        self.state = "active"

    def deactivate(self) -> list[StopCheck]:
        """0 V with every amplifier disabled, confirmed by the device, then stop cyclic exchange.

        The stop is a transaction of its own (:meth:`_stop`): what is still in flight is
        settled first (a device that serves one request at a time drops one queued behind a
        late one), the 0 V, amplifier-off command is sent until the device answers it (at most
        ``STOP_TIMEOUT_S``), and what the device holds is read back. Never raises for a device
        that does not confirm: that is in the returned checks (also kept in
        :attr:`stop_checks`). No-op unless active (returns the checks of the last stop).

        Returns:
            one :class:`StopCheck` per axis, in loop order.
        """
        if self.state != "active":
            return list(self.stop_checks)
        checks = None
        try:
            checks = self._stop(self.STOP_TIMEOUT_S)
        except Exception as exc:  # noqa: BLE001  (stopping anyway; the reason is reported)
            text = str(exc).strip().splitlines()
            why = text[0] if text else type(exc).__name__
            checks = [StopCheck(a, False, f"the stop failed: {why}") for a in self.axis_names]
        finally:
            if checks is None:
                checks = [StopCheck(a, False, "the stop was interrupted") for a in self.axis_names]
            checks = [StopCheck(str(c.axis), bool(c.confirmed), str(c.held)) for c in checks]
            self.stop_checks = checks
            try:
                self._deactivate()
            finally:
                self.state = "inactive"
        return list(checks)

    @property
    def stop_confirmed(self) -> bool:
        """True when the last :meth:`deactivate` was confirmed on every axis."""
        return bool(self.stop_checks) and all(c.confirmed for c in self.stop_checks)

    def close(self) -> None:
        """Deactivate if needed and release the transport. Idempotent; may block."""
        if self.state == "finalized":
            return
        try:
            self.deactivate()
        finally:
            try:
                self._close()
            finally:
                self.state = "finalized"

    def open(self) -> None:
        """:meth:`configure` then :meth:`activate` (for tools and tests)."""
        self.configure()
        self.activate()

    def _notice(self, text: str, warning: bool = False) -> None:
        """Add a set-up notice (outside the cycle only)."""
        self.notices.append(("warning: " if warning else "notice: ") + text)

    def _require(self, what: str, state: str) -> None:
        if self.state != state:
            raise LifecycleError(f"{type(self).__name__}.{what}() needs state {state!r}, "
                                 f"the driver is {self.state!r}")

    def _configure(self) -> None:
        """Hook: connect and check the device answers."""

    def _activate(self) -> None:
        """Hook: start cyclic exchange."""

    def _stop(self, timeout_s: float) -> list[StopCheck]:
        """Hook: command 0 V with every amplifier off, wait (at most ``timeout_s`` [s]) for the
        device to answer, read back what it holds. The default writes the command once and
        confirms nothing (a driver that cannot read back must say so)."""
        n = len(self.axis_names)
        self.write(np.zeros(n), np.zeros(n, dtype=bool))
        return [StopCheck(a, False, f"{type(self).__name__} cannot read back what the device holds")
                for a in self.axis_names]

    def _deactivate(self) -> None:
        """Hook: stop cyclic exchange (0 V and amplifiers off were already sent by :meth:`_stop`)."""

    def _close(self) -> None:
        """Hook: release the transport."""

    # ------------------------------------------------------------------ link
    @property
    def link_down(self) -> bool:
        """True when the link to the device is lost (the transport failed, or no axis has
        answered for a while): what the daemon reconnects between cycles. Cheap; never
        blocks. The simulated driver has no link: always False."""
        return self._link_down()

    def _link_down(self) -> bool:
        """Hook: see :attr:`link_down`."""
        return False

    def reconnect(self, timeout_s: float | None = None) -> None:
        """Release and re-open a lost link and check the device answers, as ``configure()``
        does (blocking: call outside the cycle, only while no axis is enabled). Sends no
        enable: what is enabled is decided by the next ``write()``, and the supervisor keeps
        its faults latched until an operator resets them.

        Args:
            timeout_s: longest wait for the device's first answer [s] (None: the driver's
                own configure timeout).
        Raises:
            LifecycleError: the driver is not configured (unconfigured or closed).
            NotImplementedError: the driver has no link to reconnect.
            OSError, ConnectionError: the device is not back (the link stays down).
        """
        if self.state not in ("inactive", "active"):
            raise LifecycleError(f"{type(self).__name__}.reconnect() needs a configured driver, "
                                 f"the driver is {self.state!r}")
        self._reconnect(timeout_s)

    def _reconnect(self, timeout_s: float | None) -> None:
        """Hook: see :meth:`reconnect`."""
        raise NotImplementedError(f"{type(self).__name__} has no link to reconnect")

    # ------------------------------------------------------------------ cyclic
    @abc.abstractmethod
    def read(self) -> None:
        """Fill :attr:`position_m` (and the health flags) for every axis. One exchange."""

    @abc.abstractmethod
    def write(self, u_V: np.ndarray, enable: np.ndarray) -> None:
        """Command voltage u_V [V], shape (n_axes,), and amplifier enable, bool (n_axes,).

        Where ``enable[i]`` is False the hardware must see 0 V and the amplifier off.
        """

    def rehearse(self, u_V: np.ndarray, enable: np.ndarray) -> None:
        """Run the exchange ahead on copies, changing nothing: the loop calls it while it waits
        for its deadline, so that the code and data of the next :meth:`read` and :meth:`write`
        are in the CPU's caches (after a sleep they are cold). ``u_V`` [V], ``enable`` (n_axes,):
        the last command. Never blocks, sends nothing. Default: nothing (a transport's exchange
        cannot be rehearsed)."""
        self._rehearse(u_V, enable)

    def _rehearse(self, u_V: np.ndarray, enable: np.ndarray) -> None:
        """Hook: see :meth:`rehearse`."""

    def service(self) -> None:
        """Work the driver has to do between exchanges, outside the timed cycle: the loop calls
        it once per cycle after :meth:`write` and its timing record (before it sleeps), so its
        time is not in the turnaround. Never blocks. A driver must stay correct when it is not
        called (a write that finds the work still pending does it first). Default: nothing."""
        self._service()

    def _service(self) -> None:
        """Hook: see :meth:`service`."""

    # ------------------------------------------------------------------ interfaces
    def _full_scale_V(self, axis: str) -> float:
        """Hook: the largest |voltage| the drive of ``axis`` can be commanded [V]."""
        return float("inf")

    def voltage_limit_V(self, axis: str) -> float:
        """Full scale of ``axis``'s ``voltage_out`` [V] (inf where nothing limits it)."""
        return self._full_scale_V(axis)

    def command_interfaces(self, axis: str) -> tuple[Interface, ...]:
        """``voltage_out`` [V] and ``enable`` of one axis, with their limits."""
        fs = self.voltage_limit_V(axis)
        return (Interface("voltage_out", "V", -fs, fs), Interface("enable", "bool", 0.0, 1.0))

    def state_interfaces(self, axis: str) -> tuple[Interface, ...]:
        """``position`` [m] and ``amp_fault`` of one axis."""
        inf = float("inf")
        return (Interface("position", "m", -inf, inf), Interface("amp_fault", "bool", 0.0, 1.0))

    def budget(self, rate_hz: float) -> BusBudget:
        """Bus time per cycle and the highest sustainable rate; default: not bus-limited."""
        return BusBudget(cycle_time_s=0.0, max_rate_hz=float("inf"), detail="no bus")

    def describe(self) -> dict:
        """JSON-able facts for the run-log header (e.g. the simulated truth)."""
        return {}

    def reset_fault(self, i: int) -> bool:
        """The operator's fault reset of axis ``i``'s drive (``motorctl fault-reset``, between
        cycles, the axis disabled): ask the device to clear the fault it latched (CiA 402: the
        rising edge of controlword bit 7, transition 15, sent with the next writes until the
        drive leaves Fault). A driver never resets a drive's fault on its own. Returns True
        when a reset was asked of the device, False when the device has no fault reset of its
        own (the default)."""
        return False

    def other_master(self) -> str:
        """Before :meth:`configure` (the driver unconfigured): another master driving this bus
        now, one line naming what was seen (e.g. a CANopen SYNC on the channel), '' when none is
        seen or the driver cannot tell (the default). ``motorctl fault-reset --config`` asks it
        before it opens a bus a daemon or a run may hold. May block for a few heartbeat times."""
        return ""

    def drive_state(self, i: int) -> str:
        """The state of axis ``i``'s drive as last read, whatever it is, one line for the
        operator (e.g. "canopen node 1 (axis X) is in Switch on disabled (statusword 0x0250)"):
        what ``motorctl fault-reset`` reports after the drive's reset. The default: the
        :meth:`fault_state` while the drive reports a fault, '' otherwise (a device with no
        state of its own beyond the fault bit). Called outside the cycle; may build strings."""
        return self.fault_state(i) if self.amp_fault[i] else ""

    def _notice_drive_fault(self, i: int, state: str) -> None:
        """Set-up found axis ``i``'s drive in a fault it latched (an earlier run's fault, its
        own watchdog when an earlier host went away): a warning notice naming ``state`` (the
        drive's words, e.g. its CiA 402 state, statusword and error code) and how the operator
        clears it. A driver never resets it on its own: the first cycle faults the axis and
        ``motorctl run`` is refused (:func:`drive_fault_refusal`)."""
        self._notice(f"axis {self.axis_names[i]}: set-up found the drive in its fault ({state}); it stays "
                     f"there until the operator's 'motorctl fault-reset'", warning=True)

    def fault_state(self, i: int) -> str:
        """The state of axis ``i``'s drive while it reports a fault, one line for the operator
        (e.g. a CiA 402 drive's power state and statusword, a Modbus fault input), '' when the
        driver has nothing to say beyond :meth:`fault_reason`'s words (the default gives them).
        Called outside the cycle (the answer to a fault reset the drive did not take); may build
        strings."""
        return self.fault_reason(i)

    def fault_reason(self, i: int) -> str:
        """What the drive of axis ``i`` says about its fault, one line (e.g. a CiA 402 EMCY
        code and its meaning, a Modbus exception), '' when it says nothing. Called outside the
        cycle (the run table, the daemon's status); may build strings."""
        return ""


def fault_reset_command(axis: str, config: str | None = None) -> str:
    """How the operator clears the fault axis ``axis``'s drive latched, for a refusal or a
    set-up notice: the daemon client's ``motorctl fault-reset AXIS`` and, with no daemon holding
    the bus, ``motorctl fault-reset --config CONFIG AXIS`` (``config`` None: the word CONFIG)."""
    return (f"'motorctl fault-reset --config {config or 'CONFIG'} {axis}' (no daemon running) or "
            f"'motorctl fault-reset {axis}' (through the daemon)")


def drive_fault_refusal(driver: Driver, names: list[str] | None = None, config: str | None = None) -> str:
    """One line naming every axis whose drive reports a fault it latched now (``amp_fault``),
    with the drive's state (:meth:`Driver.fault_state`: e.g. its CiA 402 state, statusword,
    error code, AL status code) and the command that clears it (:func:`fault_reset_command`);
    '' when none does. ``names``: the axes to look at (default: every axis of the driver)."""
    lines = []
    for i, a in enumerate(driver.axis_names):
        if (names is None or a in names) and driver.amp_fault[i]:
            state = driver.fault_state(i) or "the device reports an amplifier fault"
            lines.append(f"axis {a}'s drive is in its fault ({state}); it stays there until the operator "
                         f"resets it: {fault_reset_command(a, config)}")
    return "; ".join(lines)


def available_drivers() -> dict[str, object]:
    """Names of the installed drivers → their entry points."""
    return {ep.name: ep for ep in entry_points(group=ENTRY_POINT_GROUP)}


def load_driver_class(name: str) -> type[Driver]:
    """Load the driver registered as ``name`` in the ``motorctl.drivers`` entry-point group.

    Raises:
        KeyError: no driver of that name is installed (the message lists the installed ones).
    """
    eps = available_drivers()
    if name not in eps:
        raise KeyError(f"no driver named {name!r}; installed: {', '.join(sorted(eps)) or 'none'}")
    cls = eps[name].load()
    if not (isinstance(cls, type) and issubclass(cls, Driver)):
        raise KeyError(f"entry point {name!r} does not name a motorctl Driver subclass")
    return cls
