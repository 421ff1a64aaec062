"""The driver interface: one bus exchange per cycle for every axis of a group.

Lifecycle (ros2_control's, with LinuxCNC's canonical analog-out semantics)::

    Driver(options, axis_options, period_s)   parse only; no I/O
    open()                                    talk to the device, check it answers (may block)
    read() / write(u_V, enable)               cyclic, inside the 5 kHz loop: never block past
                                              the deadline, never raise, never allocate arrays
    close()                                   0 V, amplifier off, release (may block)

Channels per axis (the same for every transport): ``encoder_in`` → :attr:`position_m` [m]
(counts × scale), ``voltage_out`` → ``write(u_V, enable)`` [V]; ``enable = False`` means 0 V
at the hardware. Per-axis health flags are set by read/write instead of raising:
:attr:`read_error`, :attr:`write_error` (this cycle's exchange failed) and :attr:`amp_fault`
(the amplifier reports a fault). The supervisor turns them into faults.

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
from pydantic import BaseModel, ConfigDict

ENTRY_POINT_GROUP = "motorctl.drivers"


class StrictModel(BaseModel):
    """Base of every YAML-facing options model: unknown keys are errors, numbers stay numbers."""

    model_config = ConfigDict(extra="forbid", strict=True, frozen=True)


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


class Driver(abc.ABC):
    """Base class of every I/O driver (sim, CAN, serial, Modbus, ...).

    Subclasses set ``Options`` and ``AxisOptions`` (pydantic models, strict) and implement
    :meth:`read` and :meth:`write`.

    Args:
        options: an ``Options`` instance (the YAML ``driver:`` section without ``type``).
        axis_options: axis name → ``AxisOptions`` instance (``axes.NAME.driver``), in loop order.
        period_s: loop period [s].
    """

    Options: ClassVar[type[BaseModel]] = NoOptions
    AxisOptions: ClassVar[type[BaseModel]] = NoOptions

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

    def open(self) -> None:
        """Connect and check the device answers. May block; never called inside the cycle."""

    def close(self) -> None:
        """Command 0 V with the amplifier disabled and release the transport. May block."""

    @abc.abstractmethod
    def read(self) -> None:
        """Fill :attr:`position_m` (and the health flags) for every axis. One exchange."""

    @abc.abstractmethod
    def write(self, u_V: np.ndarray, enable: np.ndarray) -> None:
        """Command voltage u_V [V], shape (n_axes,), and amplifier enable, bool (n_axes,).

        Where ``enable[i]`` is False the hardware must see 0 V and the amplifier off.
        """

    def budget(self, rate_hz: float) -> BusBudget:
        """Bus time per cycle and the highest sustainable rate; default: not bus-limited."""
        return BusBudget(cycle_time_s=0.0, max_rate_hz=float("inf"), detail="no bus")

    def describe(self) -> dict:
        """JSON-able facts for the run-log header (e.g. the simulated truth)."""
        return {}


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
