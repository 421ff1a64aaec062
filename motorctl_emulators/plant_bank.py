"""The emulated axes behind every device: plants, command watchdog, amplifier state, faults.

The plant of each axis is the sim driver's (:class:`motorctl_drivers.sim.AxisPlant`, built and
seeded by :class:`~motorctl_drivers.sim.SimDriver` itself), taken from a simulated-gantry config
(``driver: {type: sim, seed, substeps, watchdog_s}``, ``axes.NAME.driver`` = the plant of NAME,
e.g. ``configs/gantry.yaml``): with the same config a run through the emulator meets the same
plant and noise as a run on the sim driver.

The master's time: a device is paced by its master (time-compressed: a run on the virtual clock
goes as fast as the exchanges do), so its plant time is the master's period count, not the
device's clock. The device learns it from what the master numbers (:class:`MasterTime`: the
serial frame's seq, the CAN sequence byte, the Modbus sequence register, the CANopen SYNC
counter): a command that comes ``g`` periods after the last one steps the plant ``g`` periods,
the ``g - 1`` periods without a command coasting on what the amplifier held (a drive's output
holds until its watchdog), so a command the master sent and the device never received costs
no plant time. A repeated number steps nothing.

Watchdog (a drive's command timeout: LinuxCNC hm2 ``timeout_ns``, CiA 402 0x6007): no valid
command for ``watchdog_s`` → 0 V and an amplifier fault, latched until the device's fault reset.

The fault reset: where the protocol has none of its own (serial and CAN revision 1:
docs/serial-protocol.md, "Revisions"), a command with the amplifier disabled clears a latched
fault. A device with a reset input of its own (``reset_input[i]``: serial flags bit 1 and a CAN
layout's ``fault_reset`` bit, revision 2; a Modbus map's ``fault_reset`` bit) clears it only on
that input's rising edge with the amplifier disabled, as a drive with a fault-reset input does: its fault
stays latched across hosts until an operator resets it; its watchdog latches a fault only on
an amplifier that was enabled when the commands stopped (a disabled one holds 0 V, off already:
nothing was lost, so a host that ended its run cleanly leaves no fault behind).
"""

from __future__ import annotations

import math
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Literal

from pydantic import Field

from motorctl.schema import StrictModel

if TYPE_CHECKING:                          # annotations only: the sim driver loads numba kernels
    from motorctl_drivers.sim import SimAxisOptions, SimOptions

class MasterTime:
    """The master's period count from a wrapping number it sends with every command.

    Args:
        modulo: the number wraps at this (256 for a byte, 65536 for a register, 240 for a
            CiA 301 SYNC counter of overflow value 240).
        max_gap: the most periods one command may stand for (the watchdog time in periods: a
            device whose watchdog ran out has stopped; a larger jump is a new master): beyond
            it a command counts as one period.
    """

    def __init__(self, modulo: int, max_gap: int):
        self.modulo = int(modulo)
        self.max_gap = max(1, int(max_gap))
        self.last: int | None = None
        self.coasted = 0                # periods stepped without a command (missing commands)

    def seen(self, number: int) -> None:
        """A frame that numbers the master's time but commands nothing (a query, a config)."""
        self.last = int(number) % self.modulo

    def periods(self, number: int) -> int:
        """Periods the command numbered ``number`` stands for: 1 after a frame numbered one
        less (or for the first), ``g`` after a gap of ``g``, 0 for a repeat."""
        number = int(number) % self.modulo
        g = 1 if self.last is None else (number - self.last) % self.modulo
        self.last = number
        if g > self.max_gap:
            g = 1
        self.coasted += max(0, g - 1)
        return g


FAULT_KINDS = ("drop", "late", "corrupt", "stale", "exception", "disconnect", "bus_off", "emcy")
#: the error code of an ``emcy`` fault without ``=CODE`` (CiA 402: continuous over-current)
DEFAULT_EMCY_CODE = 0x2310
#: the watchdog when neither ``--watchdog`` nor the plant config's ``driver.watchdog_s`` sets one [s]
DEFAULT_WATCHDOG_S = 0.05
#: delay of a 'late' answer [s]
DEFAULT_LATE_S = 0.002


class FaultSpec(StrictModel):
    """One injected fault: ``kind`` on ``axis`` ('*' = every axis / the whole frame) for
    ``count`` commands, starting at the ``start``-th command the device receives (0-based).

    Kinds: drop (no reply), late (reply after ``late_s``; a CANopen drive's TPDO
    also waits for the next SYNC), corrupt (bad CRC / bad frame),
    stale (the previous reply again, old sequence number), exception (an error reply:
    Modbus exception 0x04, or the frame's error flag), disconnect (close the link / stop
    answering), bus_off (CAN: the node leaves the bus, nothing sent or answered), emcy (a
    CiA 402 drive faults and sends an EMCY with error code ``code``; ``emcy=0x4310`` in the CLI
    form, default :data:`DEFAULT_EMCY_CODE`).
    """

    kind: Literal["drop", "late", "corrupt", "stale", "exception", "disconnect", "bus_off", "emcy"]
    axis: str = "*"
    start: Annotated[int, Field(ge=0)] = 0
    count: Annotated[int, Field(ge=1)] = 1
    code: Annotated[int, Field(ge=1, le=0xFFFF)] = DEFAULT_EMCY_CODE

    @classmethod
    def parse(cls, text: str) -> "FaultSpec":
        """``KIND[=CODE][:AXIS[:START[:COUNT]]]`` (CLI form), e.g. ``drop:X:2000:5``,
        ``emcy=0x2310:X:500``. Raises ValueError."""
        parts = text.split(":")
        if not parts[0] or len(parts) > 4:
            raise ValueError(f"fault {text!r}: expected KIND[:AXIS[:START[:COUNT]]]")
        kind, _, code = parts[0].partition("=")
        if kind not in FAULT_KINDS:
            raise ValueError(f"fault {text!r}: unknown kind {kind!r}; allowed: {', '.join(FAULT_KINDS)}")
        kw = {"kind": kind}
        if code:
            if kind != "emcy":
                raise ValueError(f"fault {text!r}: only emcy takes =CODE")
            try:
                kw["code"] = int(code, 0)
            except ValueError:
                raise ValueError(f"fault {text!r}: CODE is an integer (e.g. 0x2310)") from None
        try:
            if len(parts) > 1 and parts[1]:
                kw["axis"] = parts[1]
            if len(parts) > 2:
                kw["start"] = int(parts[2])
            if len(parts) > 3:
                kw["count"] = int(parts[3])
        except ValueError:
            raise ValueError(f"fault {text!r}: START and COUNT are integers") from None
        return cls(**kw)


class PlantBank:
    """The emulated axes.

    Args:
        sim_options: the plant config's ``driver:`` section (seed, substeps).
        plants: axis name → its plant (``SimAxisOptions``), in the driver config's axis order
            (the order decides each axis's noise seed, as in the sim driver).
        period_s: loop period [s]: one valid command = one period of plant time.
        watchdog_s: command watchdog [s] (> 0). late_s: delay of a 'late' answer [s].
        faults: the fault schedule (:class:`FaultSpec`). log: one-line messages (default stderr).
    Raises:
        ValueError: a fault names an axis that is not in ``plants``; watchdog_s ≤ 0.
    """

    def __init__(self, sim_options: SimOptions, plants: dict[str, SimAxisOptions], period_s: float, *,
                 watchdog_s: float = DEFAULT_WATCHDOG_S, late_s: float = DEFAULT_LATE_S,
                 faults=(), log=None):
        if not watchdog_s > 0:
            raise ValueError(f"watchdog {watchdog_s!r} s: must be > 0")
        self.names = list(plants)
        self.period_s = float(period_s)
        from motorctl_drivers.sim import SimDriver     # here, not at import: `motorctl --help` stays light
        self.plants = SimDriver(sim_options, dict(plants), period_s).plants   # the sim driver's seeding
        self.watchdog_s = float(watchdog_s)
        self.late_s = float(late_s)
        n = len(self.names)
        self.amp_fault = [False] * n
        #: per axis: the device has a fault-reset input of its own (module docstring)
        self.reset_input = [False] * n
        self._reset_prev = [False] * n
        self.applied_V = [0.0] * n
        self.enabled = [False] * n
        self.commands = [0] * n          # valid commands applied per axis
        self.received = [0] * n          # command frames received per axis (the fault schedule's clock)
        self.last_cmd = [math.nan] * n   # monotonic time of the last valid command
        self.watchdog_trips = 0
        self.faults = list(faults)
        for f in self.faults:
            if f.axis != "*" and f.axis not in self.names:
                raise ValueError(f"fault on unknown axis {f.axis!r}; axes: {', '.join(self.names)}")
        self.log = log or (lambda msg: print(msg, file=sys.stderr, flush=True))

    def next_fault(self, axes) -> str | None:
        """Count one received command frame for ``axes`` (indexes) and return the fault
        scheduled for it (None: answer normally). A frame-level fault hits every axis it carries."""
        spec = self.next_fault_spec(axes)
        return spec.kind if spec is not None else None

    def next_fault_spec(self, axes) -> FaultSpec | None:
        """As :meth:`next_fault`, returning the whole :class:`FaultSpec` (e.g. an EMCY's code)."""
        found = None
        for f in self.faults:
            for k in axes:
                if f.axis in ("*", self.names[k]) and f.start <= self.received[k] < f.start + f.count:
                    found = f
                    break
            if found:
                break
        for k in axes:
            self.received[k] += 1
        return found

    def master_time(self, modulo: int) -> MasterTime:
        """A :class:`MasterTime` for a number wrapping at ``modulo``, its largest gap the
        watchdog time in loop periods."""
        return MasterTime(modulo, round(self.watchdog_s / self.period_s))

    def command(self, i: int, u_V: float, enable: bool, periods: int = 1, reset: bool = False) -> None:
        """Apply one valid command to axis i that comes ``periods`` periods of the master's time
        after the last (:class:`MasterTime`): the plant first coasts ``periods - 1`` periods on
        what the amplifier held, then holds u_V [V] for one period (0 V when disabled or
        faulted). ``periods`` 0 (a repeated command) steps nothing. ``reset``: the state of the
        axis's fault-reset input in this command (where ``reset_input[i]``; module docstring)."""
        if self.reset_input[i]:
            rising = reset and not self._reset_prev[i]
            self._reset_prev[i] = bool(reset)
            if rising and not enable and self.amp_fault[i]:
                self.amp_fault[i] = False
                self.log(f"fault reset {self.names[i]}: the reset input's rising edge, amplifier disabled")
        if periods <= 0:
            return
        for _ in range(periods - 1):
            self.plants[i].step(self.applied_V[i])
        self.last_cmd[i] = time.monotonic()
        if self.commands[i] == 0:
            self.log(f"first command {self.names[i]}")
        self.commands[i] += 1
        if not enable and not self.reset_input[i]:
            self.amp_fault[i] = False   # a disabled command resets a latched fault: the protocol's reset
        on = enable and not self.amp_fault[i]
        u = u_V if on and u_V == u_V else 0.0
        self.enabled[i] = on
        self.applied_V[i] = u
        self.plants[i].step(u)

    def counts(self, i: int, m_per_count: float) -> int:
        """Axis i's encoder count: the plant's quantised position [m] in counts of ``m_per_count`` [m]."""
        return int(round(self.plants[i].measured() / m_per_count))

    def check_watchdog(self) -> float:
        """Trip the watchdog of every axis whose last command is older than ``watchdog_s``.

        Returns the seconds until the next check is due (for the server's select timeout).
        """
        now = time.monotonic()
        wd = self.watchdog_s
        due = wd
        for i, t in enumerate(self.last_cmd):
            if t != t:
                continue
            left = t + wd - now
            if left <= 0:
                if self.reset_input[i] and not self.enabled[i] and self.applied_V[i] == 0.0:
                    pass                # disabled at 0 V already: nothing to stop, nothing latched
                elif not self.amp_fault[i] or self.applied_V[i] != 0.0:
                    self.amp_fault[i] = True
                    self.applied_V[i] = 0.0
                    self.enabled[i] = False
                    self.watchdog_trips += 1
                    self.log(f"watchdog {self.names[i]}: no command for {wd * 1e3:.1f} ms: "
                             f"0 V, amplifier fault")
                self.last_cmd[i] = math.nan
            else:
                due = min(due, left)
        return due


def load_plant(plant_config: str | Path, names: list[str], period_s: float, *,
               watchdog_s: float | None = None, late_s: float = DEFAULT_LATE_S, faults=(),
               log=None) -> PlantBank:
    """The :class:`PlantBank` of axes ``names`` from a simulated-gantry config.

    ``watchdog_s`` None: the plant config's ``driver.watchdog_s`` when it is > 0, else
    :data:`DEFAULT_WATCHDOG_S` (an emulated drive always has a watchdog).

    Raises:
        motorctl.config.ConfigError: the file is not a valid config, its driver is not ``sim``,
            or it has no plant for one of ``names``.
        ValueError: as :class:`PlantBank`.
    """
    from motorctl.config import ConfigError, load_config
    loaded = load_config(plant_config, check_budget=False)
    sim = loaded.driver_options
    from motorctl_drivers.sim import SimOptions
    if not isinstance(sim, SimOptions):
        raise ConfigError(plant_config, "driver.type",
                          f"{loaded.cfg.driver.type!r}: the emulator's plant comes from a simulated-gantry "
                          f"config (driver.type: sim, the plant of each axis under axes.NAME.driver)")
    missing = [a for a in names if a not in loaded.axes]
    if missing:
        raise ConfigError(plant_config, "axes",
                          f"no plant for axis {', '.join(missing)} of the driver config; "
                          f"axes here: {', '.join(loaded.axes)}")
    if watchdog_s is None:
        watchdog_s = sim.watchdog_s if sim.watchdog_s > 0 else DEFAULT_WATCHDOG_S
    return PlantBank(sim, {a: loaded.axis_driver_options[a] for a in names}, period_s,
                     watchdog_s=watchdog_s, late_s=late_s, faults=faults, log=log)
