"""The emulated device of a bus driver: base class, registry, and assembly from the configs.

A device is the other end of one driver's protocol: it decodes the driver's commands, applies
them to a :class:`~motorctl_emulators.plant_bank.PlantBank` and answers as a drive would, with
the bank's fault schedule. Devices register under the entry-point group ``motorctl.emulators``
with the name of the driver they answer (its ``motorctl.drivers`` name, the YAML
``driver.type``), as the drivers register under ``motorctl.drivers``.
"""

from __future__ import annotations

import abc
import math
import time
from importlib.metadata import entry_points
from pathlib import Path

from motorctl_emulators.plant_bank import DEFAULT_LATE_S, PlantBank, load_plant

ENTRY_POINT_GROUP = "motorctl.emulators"


class Device(abc.ABC):
    """Base of the emulated devices.

    Args:
        options: the driver's parsed ``Options`` (the YAML ``driver:`` section).
        axis_options: axis name → the driver's ``AxisOptions`` (``axes.NAME.driver``).
        bank: the emulated axes, in the driver config's order.
    Raises (subclasses):
        OSError: the device's endpoint cannot be opened (port taken, bus missing).
        ValueError: the layout in the options cannot be served.
    """

    def __init__(self, options, axis_options: dict, bank: PlantBank):
        self.options = options
        self.axis_options = axis_options
        self.bank = bank

    @abc.abstractmethod
    def poll(self, timeout_s: float) -> None:
        """Wait up to ``timeout_s`` [s] for a request and handle whatever arrived."""

    @abc.abstractmethod
    def close(self) -> None:
        """Release the endpoint."""

    def serve(self, stop=None, duration_s: float | None = None) -> None:
        """Answer requests until ``stop()`` is true or ``duration_s`` [s] has passed, running the
        bank's watchdog between requests; the endpoint is closed at the end."""
        end = time.monotonic() + duration_s if duration_s else math.inf
        try:
            while (stop is None or not stop()) and time.monotonic() < end:
                due = self.bank.check_watchdog()
                self.poll(min(due, 0.01))
        finally:
            self.close()


class LateAnswers:
    """Answers held back by the 'late' fault. Each goes out ``late_s`` [s] after it was made
    and never before the master's next command with the same ``key`` (:meth:`release`, called
    before that command is handled), ahead of that command's answer: so it misses the read
    that waited for it whatever the scheduling of master and device (a master in lockstep
    sends its next command only once that read has timed out), and comes in a burst with the
    next answer. ``late_s`` is read from the bank when an answer is held."""

    def __init__(self, bank: PlantBank):
        self.bank = bank
        self.held: list = []                   # (key, monotonic time due, send, payload)

    def hold(self, send, payload, key=None) -> None:
        self.held.append((key, time.monotonic() + self.bank.late_s, send, payload))

    def release(self, key=None) -> None:
        if not self.held:
            return
        keep = []
        for k, due, send, payload in self.held:
            if k != key:
                keep.append((k, due, send, payload))
                continue
            wait = due - time.monotonic()
            if wait > 0.0:
                time.sleep(wait)
            send(payload)
        self.held = keep


def available_devices() -> dict[str, object]:
    """Transport names → entry points of the installed emulated devices."""
    return {ep.name: ep for ep in entry_points(group=ENTRY_POINT_GROUP)}


def load_device_class(name: str) -> type[Device]:
    """The device class registered as ``name`` in ``motorctl.emulators``.

    Raises:
        KeyError: no device of that name is installed (the message lists the installed ones),
            or the entry point does not name a :class:`Device` subclass.
    """
    eps = available_devices()
    if name not in eps:
        raise KeyError(f"no emulated device for driver type {name!r}; installed: "
                       f"{', '.join(sorted(eps)) or 'none'}")
    cls = eps[name].load()
    if not (isinstance(cls, type) and issubclass(cls, Device)):
        raise KeyError(f"entry point {name!r} of {ENTRY_POINT_GROUP} does not name a Device subclass")
    return cls


def build_device(loaded, plant: str | Path, *, watchdog_s: float | None = None,
                 late_s: float = DEFAULT_LATE_S, faults=()) -> Device:
    """The device answering the driver of ``loaded`` (a checked bus-driver config), its plant
    from the simulated-gantry config ``plant`` (see :func:`~motorctl_emulators.plant_bank.load_plant`
    for ``watchdog_s``); one plant period = the driver config's loop period.

    Raises:
        KeyError: no device for the driver type. motorctl.config.ConfigError: the plant config
        (see ``load_plant``). ValueError: a fault on an unknown axis, a layout the device
        cannot serve. OSError: the endpoint cannot be opened.
    """
    cls = load_device_class(loaded.cfg.driver.type)
    names = list(loaded.axes)
    bank = load_plant(plant, names, loaded.period_s, watchdog_s=watchdog_s, late_s=late_s, faults=faults)
    return cls(loaded.driver_options, {a: loaded.axis_driver_options[a] for a in names}, bank)
