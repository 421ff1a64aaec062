"""EtherCAT driver on pysoem (SOEM, the open EtherCAT master): a CiA 402 drive in cyclic
synchronous torque, or the paper's amplifier behind I/O terminals, per axis, at the loop rate.

Sources: ETG.1000.4 (datagrams, working counter), ETG.1000.6 (AL states, AL status codes,
CoE), ETG.6010 (CiA 402 over EtherCAT: PDO assignment 0x1C12/0x1C13), CiA 402-2 (power state
machine, objects), the Beckhoff EL5101/EL4132/EL2008 documentation (terminal process data).

YAML (``driver:``)::

    type: ethercat
    ifname: enp3s0           # the NIC the segment hangs on (a dedicated port; raw frames)
    sync0: false             # true: distributed clocks, SYNC0 at the loop period on every DC
                             # slave; false (default): SM-synchronous, each slave acts on the
                             # frame. The loop is paced by CLOCK_MONOTONIC, not by the DC
                             # clock, and its phase to SYNC0 is not aligned: a frame that
                             # reaches a slave near its SYNC0 edge is applied a period early
                             # or late. Use false with loop.clock virtual.
    watchdog_ms: 10          # SM watchdog (ESC 0x0400/0x0420): no outputs for this long ->
                             # the slaves' outputs to 0 / safe state; above the host's longest
                             # stall (docs/drivers.md: 10 ms RT kernel, 50 stock, 200 a VM)
    timeout_s, round_trip_s, max_bus_load   # as every bus driver (split_phase.CommonOptions)
    state_timeout_s: 2.0     # how long configure()/activate() wait for an AL state

per axis (``axes.NAME.driver``), ``profile: cia402``::

    profile: cia402
    slave: 1                 # position on the segment (1 = first after the master)
    voltage_full_scale_V: 10.0   full_scale_permille: 1000   # u [V] <-> target torque 0x6071
    rated_torque: 100000     # optional: checked against 0x6076
    encoder_m_per_count: 0.5e-6  # position actual 0x6064 [counts] -> m

``profile: io``::

    profile: io
    encoder:    {slave: 2}               # EL5101-type incremental encoder terminal
    analog_out: {slave: 3, channel: 1}   # EL4132-type ±10 V output, channel 1 or 2
    enable:     {slave: 4, channel: 1}   # EL2008-type digital output, channel 1-8
    voltage_full_scale_V: 10.0   encoder_m_per_count: 0.5e-6

The cycle: ``write()`` packs every axis's outputs into the process image and sends it in one
LRW (plus SOEM's DC datagram); ``read()`` of the next cycle receives it (waiting at most
``timeout_s``) and compares the working counter with the one the slaves' AL states give
(ETG.1000.4 §5.4: 2 per slave with outputs in OP, 1 per slave with inputs in SAFE-OP or OP; an
ESC takes no outputs below OP). A short working counter means a slave did not take part: every
axis gets ``read_error`` (the supervisor's error bucket counts it), the position is held, and
``service()`` (after the cycle's write, outside its timing) reads the AL status and AL status
code (0x0130, 0x0134) of every slave the axes use, one FPRD each. From the next read on, an
axis with a slave out of OP (the SM watchdog took it to SAFE-OP, error 0x001B; a slave reset)
is an amplifier fault, not an I/O error: the supervisor latches it within that cycle, and
:meth:`EthercatDriver.fault_reason` names the slave, its state and its AL status code. A short
working counter with every slave in OP (a lost or damaged frame) stays in the error bucket
and reads "EtherCAT working counter 3 of 6". A CiA 402 drive's power state machine is stepped
from the enable request by :class:`motorctl_drivers.cia402.PowerStateMachine` (the same as the
CANopen driver's); its statusword fault bit is ``amp_fault``, its error code 0x603F (mapped)
names the fault; its emergencies arrive through pysoem's emergency callback (read from the
mailbox at the stop).

The stop receives the loop's last frame first (SOEM's receive adds up the working counters of
every frame sent since the previous receive), reads the AL states and judges the stop's frames
against them; an output terminal below OP holds its safe state (0 V, off) whatever its SM
buffer kept. At close the drives go to PRE-OP and get back, by SDO, the PDO mapping and
assignment (0x1600, 0x1A00, 0x1C12, 0x1C13) and modes of operation (0x6060) the set-up found,
then INIT.

Set-up (``configure``): the segment is scanned (``config_init``), every slave's identity is
checked against its role, the drives' PDOs are mapped by SDO in PRE-OP (0x1C12/0x1C13 cleared,
0x1600 = controlword, target torque, modes of operation; 0x1A00 = statusword, position actual,
torque actual, error code; assigned; modes of operation 10) and read back, the image is mapped,
the SM watchdog is written and read back, DC is configured with SYNC0 where the slaves have it
(before SAFE-OP, where a slave checks its sync configuration), and the segment goes to SAFE-OP; ``activate`` goes to OP with every amplifier disabled.

Inside the cycle the driver packs into preallocated buffers; pysoem's ``output`` setter and
``input`` getter copy one small ``bytes`` per slave and cycle (its API has no in-place view).
"""

from __future__ import annotations

import struct
import time
from typing import Annotated, Literal

import numpy as np
from pydantic import Field, model_validator

from motorctl.driver import BusBudget, Driver, StopCheck
from motorctl.inputs import InputError
from motorctl.schema import StrictModel
from motorctl_drivers import cia402
from motorctl_drivers.split_phase import (
    CommonOptions,
    EncoderUnwrap,
    make_budget,
    one_line,
    round_trip_stats,
    volts_to_counts,
)

#: identities (ETG vendor ID list: 0x00000002 Beckhoff Automation)
VENDOR_BECKHOFF = 0x00000002
#: Beckhoff product codes (terminal number << 16 | 0x3052; the coupler 0x2C52)
EK1100, EL5101, EL4132, EL2008 = 0x044C2C52, 0x13ED3052, 0x10243052, 0x07D83052
PRODUCT_NAMES = {EK1100: "EK1100", EL5101: "EL5101", EL4132: "EL4132", EL2008: "EL2008", 0: "CiA 402 drive"}

#: the CoE process data of a drive in cyclic synchronous torque: (index, subindex, bits)
COE_RX_MAP = ((cia402.CONTROLWORD, 0, 16), (cia402.TARGET_TORQUE, 0, 16), (cia402.MODES_OF_OPERATION, 0, 8))
COE_TX_MAP = ((cia402.STATUSWORD, 0, 16), (cia402.POSITION_ACTUAL, 0, 32), (cia402.TORQUE_ACTUAL, 0, 16),
              (cia402.ERROR_CODE, 0, 16))
RXPDO, TXPDO, RX_ASSIGN, TX_ASSIGN = 0x1600, 0x1A00, 0x1C12, 0x1C13
#: process image sizes [bytes] of each role: (outputs, inputs)
IMAGE = {0: (5, 10), EL5101: (6, 10), EL4132: (4, 0), EL2008: (1, 0), EK1100: (0, 0)}

#: ESC registers (ET1100 datasheet section II)
REG_FEATURES, REG_WD_DIVIDER, REG_WD_PD = 0x0008, 0x0400, 0x0420
WD_DIVIDER = 2498                     # 40 ns × (2498 + 2) = 100 us per watchdog unit
#: one byte at 100 Mbit/s [s]; an ESC's forwarding delay per slave [s] (ET1100: < 1 us)
BYTE_TIME_S, SLAVE_DELAY_S = 80e-9, 1e-6


class Channel(StrictModel):
    """A terminal at ``slave`` (position, 1 = first), channel ``channel`` (1-based)."""

    slave: Annotated[int, Field(ge=1, le=1000)]
    channel: Annotated[int, Field(ge=1, le=8)] = 1


class EthercatOptions(CommonOptions):
    """YAML ``driver:`` of the EtherCAT driver (see the module docstring)."""

    ifname: Annotated[str, Field(min_length=1, max_length=15)]
    sync0: bool = False
    watchdog_ms: Annotated[float, Field(ge=0.1, le=6000)] = 10.0
    state_timeout_s: Annotated[float, Field(gt=0, le=30)] = 2.0


class EthercatAxisOptions(StrictModel):
    """YAML ``axes.NAME.driver`` of the EtherCAT driver: ``profile`` cia402 or io."""

    profile: Literal["cia402", "io"]
    slave: Annotated[int, Field(ge=1, le=1000)] | None = None
    encoder: Channel | None = None
    analog_out: Channel | None = None
    enable: Channel | None = None
    voltage_full_scale_V: Annotated[float, Field(gt=0)] = 10.0
    full_scale_permille: Annotated[int, Field(ge=1, le=32767)] = 1000
    rated_torque: Annotated[int, Field(ge=0)] | None = None
    encoder_m_per_count: Annotated[float, Field(gt=0)] = 0.5e-6

    @model_validator(mode="after")
    def _profile_keys(self):
        if self.profile == "cia402":
            if self.slave is None:
                raise ValueError("profile cia402 needs slave (the drive's position on the segment)")
            if self.encoder or self.analog_out or self.enable:
                raise ValueError("profile cia402 takes slave, not encoder/analog_out/enable")
        else:
            missing = [k for k in ("encoder", "analog_out", "enable") if getattr(self, k) is None]
            if missing:
                raise ValueError(f"profile io needs {', '.join(missing)} ({{slave: N, channel: K}})")
            if self.slave is not None:
                raise ValueError("profile io takes encoder, analog_out and enable, not slave")
            if self.analog_out.channel > 2:
                raise ValueError(f"analog_out channel {self.analog_out.channel}: an EL4132 has channels 1 and 2")
        return self

    def slave_roles(self) -> list[tuple[int, int]]:
        """(position, product code; 0 for a CiA 402 drive) of every slave this axis uses."""
        if self.profile == "cia402":
            return [(self.slave, 0)]
        return [(self.encoder.slave, EL5101), (self.analog_out.slave, EL4132), (self.enable.slave, EL2008)]


def segment_roles(axis_options: dict) -> dict[int, int]:
    """Position → role (product code; 0 a CiA 402 drive) of every slave the axes use.

    Raises:
        ValueError: a position has two roles, or a drive or encoder serves two axes.
    """
    roles: dict[int, int] = {}
    for a, o in axis_options.items():
        for pos, product in o.slave_roles():
            if roles.get(pos, product) != product:
                raise ValueError(f"axes.{a}.driver: slave {pos} is already a {PRODUCT_NAMES[roles[pos]]}, "
                                 f"not a {PRODUCT_NAMES[product]}")
            if product in (0, EL5101) and any(p == pos and pr == product for b, ob in axis_options.items()
                                               if b != a for p, pr in ob.slave_roles()):
                raise ValueError(f"axes.{a}.driver: slave {pos} ({PRODUCT_NAMES[product]}) serves another axis too")
            roles[pos] = product
    return roles


class EthercatDriver(Driver):
    """EtherCAT master for the axes of one segment (see the module docstring).

    Counters (``describe()``): exchanges, wkc_errors, no_frame, al_reads.
    """

    Options = EthercatOptions
    AxisOptions = EthercatAxisOptions
    #: the link counts as down after this long without a complete working counter [s]
    LINK_DOWN_S = 0.2
    WARMUP_EXCHANGES = 50

    def __init__(self, options: EthercatOptions, axis_options: dict, period_s: float):
        super().__init__(options, axis_options, period_s)
        self.roles = segment_roles(self.axis_options)
        n = len(self.axis_names)
        self._ax = [self.axis_options[a] for a in self.axis_names]
        self.timeout_s = options.timeout_s if options.timeout_s is not None else 0.5 * period_s
        self._timeout_us = max(1, int(self.timeout_s * 1e6))
        self.master = None
        self.slaves: list = []
        self.expected_wkc = 0               # every slave in OP (SOEM's expectedWKC)
        self._expect = 0                    # what this exchange is judged against (its AL states)
        self._wkc_parts: dict[int, tuple[int, int]] = {}   # position -> (outputs 2 / 0, inputs 1 / 0)
        self._al: dict[int, tuple[int, int]] = {}          # position -> (AL status, AL status code) read last
        self._al_due = False
        self._al_fault = np.zeros(n, dtype=bool)           # axis i: one of its slaves left OP
        self._found: dict[int, list[tuple[int, int, bytes]]] = {}   # drive -> objects as found
        self.last_wkc = 0
        self._bad_wkc_since = None          # exchange count when the working counter went short
        self.exchanges = 0
        self._outstanding = False
        self._sm = [cia402.PowerStateMachine() if o.profile == "cia402" else None for o in self._ax]
        self._statusword = [0] * n
        self._error_code = [0] * n
        self._named_code = [0] * n          # the error code of the last fault, until enabled again
        self._torque = [0] * n
        self._unwrap = [EncoderUnwrap(32) for _ in range(n)]
        self._m_per_count = [o.encoder_m_per_count for o in self._ax]
        self._out: dict[int, bytearray] = {p: bytearray(IMAGE[r][0]) for p, r in self.roles.items() if IMAGE[r][0]}
        self._down_cycles = max(1, round(self.LINK_DOWN_S / period_s))
        # a working counter short for longer than the SM watchdog: the slaves have dropped their
        # outputs to the safe state and left OP (SAFE-OP + error 0x001B), where a full working
        # counter no longer means the outputs are applied; the segment stays "down" until
        # reconnect() has set it up and brought it to OP again
        self._wd_cycles = min(self._down_cycles, max(1, round(options.watchdog_ms * 1e-3 / period_s)))
        self._needs_setup = False
        self._short = 0
        self.round_trip = round_trip_stats(())
        self.dc_slaves: list[int] = []
        self.slave_info: list[dict] = []
        self.emergencies: list[tuple[int, int, int]] = []     # (position, error code, error register)
        self.counters = {"exchanges": 0, "wkc_errors": 0, "no_frame": 0, "al_reads": 0, "al_read_misses": 0}
        # the first slave-state trip of the run on the master's clock (exchanges): the frame that
        # first came back short, and per axis the frame whose read faulted it from the AL status
        self._trip_first = -1
        self._trip_named = [-1] * n
        self.connected = False

    # ------------------------------------------------------------------ set-up helpers
    def _where(self, pos: int) -> str:
        axes = [a for a, o in zip(self.axis_names, self._ax) if pos in [p for p, _ in o.slave_roles()]]
        return f"EtherCAT slave {pos} ({PRODUCT_NAMES.get(self.roles.get(pos, -1), '?')}, axis {', '.join(axes)})"

    def _sdo_write(self, pos: int, index: int, sub: int, data: bytes) -> None:
        import pysoem
        try:
            self.slaves[pos - 1].sdo_write(index, sub, data)
        except pysoem.SdoError as exc:
            raise OSError(f"{self._where(pos)}: SDO download 0x{index:04X}:{sub:02X} refused: abort "
                          f"0x{exc.abort_code:08X} ({exc.desc})") from None

    def _sdo_read(self, pos: int, index: int, sub: int = 0, signed: bool = False) -> int:
        import pysoem
        try:
            raw = self.slaves[pos - 1].sdo_read(index, sub)
        except pysoem.SdoError as exc:
            raise OSError(f"{self._where(pos)}: SDO upload 0x{index:04X}:{sub:02X} refused: abort "
                          f"0x{exc.abort_code:08X} ({exc.desc})") from None
        return int.from_bytes(raw, "little", signed=signed)

    def _sdo_read_optional(self, pos: int, index: int, what: str) -> int | None:
        """An object a drive may not have: None (and a notice saying what goes unchecked) when
        the drive answers "object does not exist" (abort 0x06020000)."""
        import pysoem
        try:
            return int.from_bytes(self.slaves[pos - 1].sdo_read(index, 0), "little")
        except pysoem.SdoError as exc:
            if exc.abort_code != 0x06020000:
                raise OSError(f"{self._where(pos)}: SDO upload 0x{index:04X}:00 refused: abort "
                              f"0x{exc.abort_code:08X} ({exc.desc})") from None
            self._notice(f"{self._where(pos)} has no 0x{index:04X}: {what}")
            return None

    def _map_drive(self, pos: int) -> None:
        """PRE-OP → SAFE-OP hook of a drive (called by SOEM's config_map): write the PDO
        mapping and assignment by SDO, modes of operation 10, and read them back."""
        dtype = self._sdo_read(pos, cia402.DEVICE_TYPE)
        if dtype & 0xFFFF != cia402.PROFILE_402:
            raise OSError(f"{self._where(pos)}: device type 0x1000 = 0x{dtype:08X}, profile {dtype & 0xFFFF}, "
                          f"not a CiA 402 drive")
        modes = self._sdo_read_optional(pos, cia402.SUPPORTED_MODES, "cyclic synchronous torque is taken as "
                                        "supported (modes of operation is read back below)")
        if modes is not None and not modes & cia402.SUPPORTED_CST_BIT:
            raise OSError(f"{self._where(pos)}: supported drive modes 0x6502 = 0x{modes:08X} has no cyclic "
                          f"synchronous torque (bit 9)")
        if pos not in self._found:          # a reconnect finds the mapping it wrote itself
            self._found[pos] = self._as_found(pos)
        for assign, pdo, entries in ((RX_ASSIGN, RXPDO, COE_RX_MAP), (TX_ASSIGN, TXPDO, COE_TX_MAP)):
            self._sdo_write(pos, assign, 0, b"\x00")
            self._sdo_write(pos, pdo, 0, b"\x00")
            for k, (index, sub, bits) in enumerate(entries, 1):
                self._sdo_write(pos, pdo, k, struct.pack("<I", index << 16 | sub << 8 | bits))
            self._sdo_write(pos, pdo, 0, bytes((len(entries),)))
            self._sdo_write(pos, assign, 1, struct.pack("<H", pdo))
            self._sdo_write(pos, assign, 0, b"\x01")
            got = [self._sdo_read(pos, pdo, k) for k in range(1, self._sdo_read(pos, pdo, 0) + 1)]
            want = [index << 16 | sub << 8 | bits for index, sub, bits in entries]
            if got != want or self._sdo_read(pos, assign, 1) != pdo:
                raise OSError(f"{self._where(pos)}: PDO 0x{pdo:04X} reads back "
                              f"{', '.join(f'0x{v:08X}' for v in got)}, not the mapping written")
        self._sdo_write(pos, cia402.MODES_OF_OPERATION, 0, bytes((cia402.MODE_CST,)))
        mode = self._sdo_read(pos, cia402.MODES_OF_OPERATION, signed=True)
        if mode != cia402.MODE_CST:
            raise OSError(f"{self._where(pos)}: modes of operation 0x6060 reads {mode}, not 10 (CST)")
        i = next(k for k, o in enumerate(self._ax) if o.profile == "cia402" and o.slave == pos)
        a = self._ax[i]
        rated = self._sdo_read_optional(pos, cia402.RATED_TORQUE, "the V -> per mille scale is taken as configured")
        max_t = self._sdo_read_optional(pos, cia402.MAX_TORQUE, "full_scale_permille is not checked against the "
                                        "drive's clip")
        if a.rated_torque is not None and rated is not None and rated != a.rated_torque:
            raise OSError(f"{self._where(pos)}: rated torque 0x6076 is {rated}, the config says {a.rated_torque}")
        if max_t is not None and a.full_scale_permille > max_t:
            raise OSError(f"{self._where(pos)}: full_scale_permille {a.full_scale_permille} is above the drive's "
                          f"max torque 0x6072 = {max_t} per mille (the drive would clip)")
        self.slave_info[pos - 1].update(device_type=f"0x{dtype:08X}", rated_torque=rated,
                                        max_torque_permille=max_t, mapping="written and read back")

    def _as_found(self, pos: int) -> list[tuple[int, int, bytes]]:
        """The objects :meth:`_map_drive` changes, as the drive holds them before: (index,
        subindex, raw value) in the order that writes them back (ETG.6010 §5.3: an assignment
        cleared, the PDO's count cleared, its entries, its count, then the assignment)."""
        out = []
        for assign, pdo in ((RX_ASSIGN, RXPDO), (TX_ASSIGN, TXPDO)):
            pdos = [self._sdo_read(pos, assign, k) for k in range(1, self._sdo_read(pos, assign, 0) + 1)]
            n = self._sdo_read(pos, pdo, 0)
            out += [(assign, 0, b"\x00"), (pdo, 0, b"\x00")]
            out += [(pdo, k, struct.pack("<I", self._sdo_read(pos, pdo, k))) for k in range(1, n + 1)]
            out.append((pdo, 0, bytes((n,))))
            out += [(assign, k, struct.pack("<H", v)) for k, v in enumerate(pdos, 1)]
            out.append((assign, 0, bytes((len(pdos),))))
        out.append((cia402.MODES_OF_OPERATION, 0, self.slaves[pos - 1].sdo_read(cia402.MODES_OF_OPERATION, 0)))
        return out

    def _restore(self) -> None:
        """PRE-OP, and every object the set-up changed written back as found (outside the
        cycle, at close); a drive that refuses is named in a notice."""
        import pysoem
        m = self.master
        if not self._found or m is None:
            return
        m.state = pysoem.PREOP_STATE
        m.write_state()
        if m.state_check(pysoem.PREOP_STATE, int(self.options.state_timeout_s * 1e6)) != pysoem.PREOP_STATE:
            self._notice(f"EtherCAT: PRE-OP refused at close, the drives' PDO mapping and mode stay as set: "
                         f"{self._fail_states(pysoem.PREOP_STATE)}", warning=True)
            return
        for pos, objects in self._found.items():
            try:
                for index, sub, raw in objects:
                    self._sdo_write(pos, index, sub, raw)
            except OSError as exc:
                self._notice(f"{one_line(exc)}: the mapping is not restored", warning=True)
        self._found = {}

    def _on_emergency(self, pos: int, emcy) -> None:
        """pysoem's emergency callback (CoE emergency, ETG.1000.6 §5.6.4): kept for the report."""
        self.emergencies.append((pos, emcy.error_code, emcy.error_reg))

    def _expected_for(self, states: dict[int, int]) -> int:
        """The working counter of the process-data LRW with the slaves in AL ``states``
        (position -> state): a slave's outputs count 2 in OP only, its inputs 1 in SAFE-OP and
        OP (ETG.1000.4 §5.4; an ESC enables its output SM in OP)."""
        return sum((out if states.get(p, 8) & 0x0F == 8 else 0) + (inp if states.get(p, 8) & 0x0F in (4, 8) else 0)
                   for p, (out, inp) in self._wkc_parts.items())

    def _read_al(self) -> None:
        """AL status and AL status code (0x0130, 0x0134) of every slave the axes use, one FPRD
        each, and which axes have a slave out of OP. Outside the cycle (service, stop). A slave
        that did not answer is read again at the next service, not at the next read-out of
        the bucket's period: its axis is named from its AL status in the cycle after."""
        self.counters["al_reads"] += 1
        timeout = max(self._timeout_us, 2000)
        for pos in self.roles:
            try:
                raw = self.slaves[pos - 1]._fprd(0x0130, 6, timeout)
                status, _r, code = struct.unpack("<HHH", raw[:6])
            except Exception:  # noqa: BLE001  (no answer: judged from the working counter alone)
                self._al_due = True          # asked again after the next cycle's write
                self.counters["al_read_misses"] += 1
                continue
            self._al[pos] = (status, code)
        for i, o in enumerate(self._ax):
            self._al_fault[i] = any(self._al.get(p, (8, 0))[0] & 0x1F != 8 for p, _ in o.slave_roles())

    def _service(self) -> None:
        """After a short working counter: read the slaves' AL status (outside the timed cycle),
        so that the next read faults the axis whose slave left OP."""
        if self._al_due and self.connected and self.master is not None:
            self._al_due = False
            self._read_al()

    def _al_text(self, i: int) -> str:
        """The slaves of axis ``i`` out of OP, with their AL status codes (ETG.1000.6 Table 11)."""
        import pysoem
        bad = []
        for p, _ in self._ax[i].slave_roles():
            status, code = self._al.get(p, (8, 0))
            if status & 0x1F != 8:
                bad.append(f"{self._where(p)} left OP: {_state_name(status)}, AL status code 0x{code:04X} "
                           f"({pysoem.al_status_code_to_string(code)})")
        return "; ".join(bad)

    def _fail_states(self, want: int) -> str:
        """One line per slave not in AL state ``want``: its state and AL status code."""
        import pysoem
        self.master.read_state()
        self.counters["al_reads"] += 1
        bad = []
        for k, s in enumerate(self.slaves, 1):
            if s.state != want:
                code = s.al_status
                bad.append(f"{self._where(k) if k in self.roles else f'EtherCAT slave {k}'} is in "
                           f"{_state_name(s.state)}, AL status code 0x{code:04X} "
                           f"({pysoem.al_status_code_to_string(code)})")
        return "; ".join(bad)

    def _configure(self) -> None:
        """Scan, check, map, watchdog, DC, SAFE-OP (see the module docstring).

        Raises:
            InputError: this machine has no interface ``ifname``.
            OSError: pysoem is missing, the interface cannot be opened (needs CAP_NET_RAW and
            CAP_NET_ADMIN), no
            or too few slaves answer, a slave is not what its role needs, a drive refused its
            mapping, a slave refused SAFE-OP (with its AL status code).
        """
        _check_interface(self.options.ifname)
        try:
            import pysoem
        except ImportError:
            raise OSError("the ethercat driver needs pysoem: pip install 'motorctl[ethercat]'") from None
        o = self.options
        m = pysoem.Master()
        try:
            m.open(o.ifname)
        except Exception as exc:  # noqa: BLE001  (pysoem raises ConnectionError without errno)
            raise OSError(f"EtherCAT interface {o.ifname}: cannot open it for raw frames ({one_line(exc)}); "
                          f"it must exist, be up, and the process needs CAP_NET_RAW and CAP_NET_ADMIN "
                          f"(SOEM sets it promiscuous; systemd/ethercat.conf grants both)") from None
        self.master = m
        self.connected = True
        try:
            self._bring_up(pysoem)
        except BaseException:
            self._close()
            raise

    def _bring_up(self, pysoem) -> None:
        o, m = self.options, self.master
        m.manual_state_change = 1          # PRE-OP, SAFE-OP asked for here, after DC is set up
        n = m.config_init()
        if n <= 0:
            raise OSError(f"EtherCAT interface {o.ifname}: no slave answers (is the segment plugged in and powered?)")
        self.slaves = list(m.slaves)
        need = max(self.roles)
        if n < need:
            raise OSError(f"EtherCAT: {n} slave(s) on {o.ifname}, the axes need {need}")
        self.slave_info = [{"position": k, "name": s.name, "vendor_id": f"0x{s.man:08X}",
                            "product_code": f"0x{s.id:08X}"} for k, s in enumerate(self.slaves, 1)]
        for pos, role in self.roles.items():
            s = self.slaves[pos - 1]
            if role == 0:
                s.setup_func = lambda _slave, pos=pos: self._map_drive(pos)
                s.add_emergency_callback(lambda emcy, pos=pos: self._on_emergency(pos, emcy))
            elif s.man != VENDOR_BECKHOFF or s.id != role:
                raise OSError(f"{self._where(pos)}: the segment has {s.name!r} (vendor 0x{s.man:08X}, product "
                              f"0x{s.id:08X}) there, not an {PRODUCT_NAMES[role]} (0x{role:08X})")
        m.state = pysoem.PREOP_STATE
        m.write_state()
        if m.state_check(pysoem.PREOP_STATE, int(o.state_timeout_s * 1e6)) != pysoem.PREOP_STATE:
            raise OSError(f"EtherCAT: PRE-OP refused: {self._fail_states(pysoem.PREOP_STATE)}")
        try:
            m.config_map()
        except pysoem.ConfigMapError as exc:
            raise OSError(f"EtherCAT: mapping the process data failed: "
                          f"{'; '.join(one_line(e) for e in exc.error_list)}") from None
        for pos, role in self.roles.items():
            s = self.slaves[pos - 1]
            want = IMAGE[role]
            if (len(s.output), len(s.input)) != want:
                raise OSError(f"{self._where(pos)}: process image {len(s.output)} bytes out, {len(s.input)} in; "
                              f"its role needs {want[0]} out, {want[1]} in")
        wd = max(1, round(o.watchdog_ms * 10))
        for pos in sorted(self._out):
            s = self.slaves[pos - 1]
            s._fpwr(REG_WD_DIVIDER, struct.pack("<H", WD_DIVIDER))
            s._fpwr(REG_WD_PD, struct.pack("<H", wd))
            back = struct.unpack("<HH", s._fprd(REG_WD_DIVIDER, 2) + s._fprd(REG_WD_PD, 2))
            if back != (WD_DIVIDER, wd):
                raise OSError(f"{self._where(pos)}: SM watchdog reads back divider {back[0]}, time {back[1]}; "
                              f"written {WD_DIVIDER}, {wd}")
            self.slave_info[pos - 1]["watchdog_ms"] = wd * 40 * (WD_DIVIDER + 2) / 1e6
        self.dc_slaves = []
        if o.sync0 and m.config_dc():
            for k, s in enumerate(self.slaves, 1):
                if struct.unpack("<H", s._fprd(REG_FEATURES, 2))[0] & 0x0004 and k in self.roles:
                    s.dc_sync(True, round(self.period_s * 1e9))
                    self.dc_slaves.append(k)
        m.state = pysoem.SAFEOP_STATE
        m.write_state()
        if m.state_check(pysoem.SAFEOP_STATE, int(o.state_timeout_s * 1e6)) != pysoem.SAFEOP_STATE:
            raise OSError(f"EtherCAT: SAFE-OP refused: {self._fail_states(pysoem.SAFEOP_STATE)}")
        self.expected_wkc = m.expected_wkc
        self._wkc_parts = {k: (2 if len(s.output) else 0, 1 if len(s.input) else 0)
                           for k, s in enumerate(self.slaves, 1)}
        self._al = {}
        self._al_fault[:] = False
        self._expect = self._expected_for({k: 4 for k in self._wkc_parts})     # SAFE-OP: inputs only
        times = []
        zeros, off = np.zeros(len(self.axis_names)), np.zeros(len(self.axis_names), dtype=bool)
        for _ in range(self.WARMUP_EXCHANGES):
            t0 = time.perf_counter()
            self.write(zeros, off)
            self._receive(100_000)
            times.append(time.perf_counter() - t0)
        self.round_trip = round_trip_stats(times)
        if self.last_wkc <= 0:
            raise ConnectionError(f"EtherCAT: no process data came back on {o.ifname}")

    def _activate(self) -> None:
        """OP with every amplifier disabled: process data flows while the slaves change state.

        Raises:
            OSError: a slave refused OP (with its AL status code).
        """
        import pysoem
        m = self.master
        n = len(self.axis_names)
        zeros, off = np.zeros(n), np.zeros(n, dtype=bool)
        m.state = pysoem.OP_STATE
        m.write_state()
        deadline = time.perf_counter() + self.options.state_timeout_s
        self._expect = None                 # slaves change state between these frames: not judged
        while True:
            self.write(zeros, off)
            self._receive(100_000)
            if m.state_check(pysoem.OP_STATE, 1000) == pysoem.OP_STATE:
                break
            if time.perf_counter() > deadline:
                raise OSError(f"EtherCAT: OP refused: {self._fail_states(pysoem.OP_STATE)}")
        self._expect = self.expected_wkc
        self._al = {}
        self._al_fault[:] = False
        self.write(zeros, off)
        self._receive(100_000)
        self.read_error[:] = False
        self._bad_wkc_since = None
        self._short = 0
        self._needs_setup = False

    # ------------------------------------------------------------------ cycle
    def write(self, u_V: np.ndarray, enable: np.ndarray) -> None:
        if not self.connected:
            self.write_error[:] = True
            return
        if self._outstanding:
            # a write with the last frame not yet received is one outside the cycle (the loop's
            # safe output after its last cycle, the stop; inside, read() always comes first):
            # receive that frame now, since SOEM's receive adds up the working counters of every
            # frame sent since the last receive (two frames would read 20 of 10)
            self._receive(self._timeout_us)
        out = self._out
        for i, o in enumerate(self._ax):
            if o.profile == "cia402":
                cw = self._sm[i].step(self._statusword[i], bool(enable[i]))
                t = cia402.volts_to_permille(float(u_V[i]), o.voltage_full_scale_V, o.full_scale_permille) \
                    if self._sm[i].enabled and enable[i] else 0
                struct.pack_into("<HhB", out[o.slave], 0, cw, t, cia402.MODE_CST)
            else:
                on = bool(enable[i])
                c = volts_to_counts(float(u_V[i]), o.voltage_full_scale_V, 16) if on else 0
                struct.pack_into("<h", out[o.analog_out.slave], 2 * (o.analog_out.channel - 1), c)
                buf = out[o.enable.slave]
                bit = 1 << (o.enable.channel - 1)
                buf[0] = (buf[0] | bit) if on else (buf[0] & ~bit & 0xFF)
        slaves = self.slaves
        for pos, buf in out.items():
            slaves[pos - 1].output = bytes(buf)
        try:
            self.master.send_processdata()
        except Exception:  # noqa: BLE001  (a dead socket inside the cycle is a write error)
            self.write_error[:] = True
            self.connected = False
            return
        self.write_error[:] = False
        self._outstanding = True

    def _receive(self, timeout_us: int) -> None:
        """Receive the outstanding process-data frame (at most ``timeout_us``) and decode it."""
        if not self._outstanding:
            return
        self._outstanding = False
        wkc = self.master.receive_processdata(timeout_us)
        self.last_wkc = wkc
        self.exchanges += 1
        self.counters["exchanges"] += 1
        expect = self._expect
        if wkc <= 0 or (expect is not None and wkc != expect):
            if wkc <= 0:
                self.counters["no_frame"] += 1
            else:
                self.counters["wkc_errors"] += 1
            if self._bad_wkc_since is None:
                self._bad_wkc_since = self.exchanges
            self._short += 1
            if self._trip_first < 0:
                self._trip_first = self.exchanges
            if self._short == 1 or self._short % self._down_cycles == 0:
                self._al_due = True         # service() reads the AL status before the next read
            if self._short > self._wd_cycles and self.state == "active":
                self._needs_setup = True
            # an axis whose slave has left OP (AL status read after the first short frame) is an
            # amplifier fault now; the others wait in the error bucket (a frame may be lost)
            al = self._al_fault
            named = self._trip_named
            for i in range(len(al)):
                self.read_error[i] = not al[i]
                if al[i]:
                    self.amp_fault[i] = True
                    if named[i] < 0:
                        named[i] = self.exchanges
            return
        self._bad_wkc_since = None
        self._short = 0
        self.read_error[:] = False
        slaves = self.slaves
        for i, o in enumerate(self._ax):
            if o.profile == "cia402":
                sw, pos, torque, err = struct.unpack_from("<HiHH", slaves[o.slave - 1].input, 0)
                self._statusword[i] = sw
                self._torque[i] = torque - 0x10000 if torque & 0x8000 else torque
                self._error_code[i] = err
                self.amp_fault[i] = bool(sw & cia402.SW_FAULT) or self._al_fault[i]
                if err and sw & cia402.SW_FAULT:
                    self._named_code[i] = err
                elif sw & 0x6F == 0x27:                   # Operation enabled: a new start
                    self._named_code[i] = 0
                raw = pos & 0xFFFFFFFF
            else:
                _status, raw, _latch = struct.unpack_from("<HII", slaves[o.encoder.slave - 1].input, 0)
                self.amp_fault[i] = self._al_fault[i]
            self.position_m[i] = self._unwrap[i].update(raw) * self._m_per_count[i]

    def read(self) -> None:
        if not self._outstanding:
            self.read_error[:] = False
            return
        try:
            self._receive(self._timeout_us)
        except Exception:  # noqa: BLE001  (a transport error inside the cycle is a read error)
            self.read_error[:] = True
            self.connected = False

    # ------------------------------------------------------------------ stop, lifecycle
    def _stop(self, timeout_s: float) -> list[StopCheck]:
        """0 V / zero torque with every amplifier off, exchanged until every drive has left the
        powered states (or ``timeout_s``), then read back: a drive's statusword and torque
        actual from the process data; a terminal's output buffer (SM2 in the ESC's RAM, read
        with FPRD) holding 0 V and the enable bit clear."""
        names = self.axis_names
        n = len(names)
        if not self.connected or self.master is None:
            return [StopCheck(a, False, "the link is down: the stop could not be sent") for a in names]
        deadline = time.perf_counter() + timeout_s
        zeros, off = np.zeros(n), np.zeros(n, dtype=bool)
        powered = (cia402.OPERATION_ENABLED, cia402.QUICK_STOP_ACTIVE, cia402.FAULT_REACTION_ACTIVE)
        answered = np.zeros(n, dtype=bool)
        self._receive(self._timeout_us)     # the loop's last frame, still on the wire
        # judged against the slaves' AL states as they are now (a slave the SM watchdog took to
        # SAFE-OP no longer counts its outputs)
        self._read_al()
        self._expect = self._expected_for({p: st for p, (st, _c) in self._al.items()})
        while time.perf_counter() < deadline:
            self.write(zeros, off)
            self._receive(max(1, int(min(0.05, deadline - time.perf_counter()) * 1e6)))
            if self.last_wkc == self._expect:
                answered[:] = True
            if answered.all() and not any(self._sm[i] is not None and cia402.decode_state(self._statusword[i])
                                          in powered for i in range(n)):
                break
        self._poll_mailboxes()
        out = []
        for i, (a, o) in enumerate(zip(names, self._ax)):
            if not answered[i]:
                out.append(StopCheck(a, False, f"no complete working counter after the stop "
                                               f"(last {max(self.last_wkc, 0)} of {self._expect})"))
                continue
            if o.profile == "cia402":
                state = cia402.decode_state(self._statusword[i])
                ok = state not in powered and self._torque[i] == 0
                out.append(StopCheck(a, ok, f"statusword 0x{self._statusword[i]:04X} ({cia402.STATE_NAMES[state]}), "
                                            f"torque actual 0x6077 = {self._torque[i]} per mille"))
                continue
            try:
                ao = self._sm2(o.analog_out.slave)
                do = self._sm2(o.enable.slave)
            except Exception as exc:  # noqa: BLE001  (reported per axis)
                out.append(StopCheck(a, False, f"the outputs could not be read back ({one_line(exc)})"))
                continue
            k = 2 * (o.analog_out.channel - 1)
            c = int.from_bytes(ao[k:k + 2], "little", signed=True)
            bit = do[0] >> (o.enable.channel - 1) & 1
            # below OP an output terminal holds its safe state (0 V, off), whatever its SM buffer
            # kept (ESC: the buffer keeps the last data); in OP the buffer is what it drives
            safe = [(p, self._al.get(p, (8, 0))) for p in (o.analog_out.slave, o.enable.slave)]
            safe = {p: f" ({_state_name(st)}, AL status code 0x{code:04X}: its safe state, 0 V and off)"
                    for p, (st, code) in safe if st & 0x0F != 8}
            held0 = c == 0 or o.analog_out.slave in safe
            held1 = bit == 0 or o.enable.slave in safe
            out.append(StopCheck(a, held0 and held1,
                                 f"slave {o.analog_out.slave} channel {o.analog_out.channel} holds {c} "
                                 f"({c * o.voltage_full_scale_V / 32767:.3f} V){safe.get(o.analog_out.slave, '')}, "
                                 f"slave {o.enable.slave} channel {o.enable.channel} = {bit} "
                                 f"({'amplifier on' if bit else 'amplifier off'}){safe.get(o.enable.slave, '')}"))
        return out

    def _sm2(self, pos: int) -> bytes:
        """The output buffer of slave ``pos`` as its ESC holds it (SM2 start and length read from
        the SM registers, then the buffer, both with FPRD)."""
        s = self.slaves[pos - 1]
        for n in range(4):
            start, length, control = struct.unpack("<HHB", s._fprd(0x0800 + 8 * n, 5))
            if length and control & 0x0C == 0x04 and control & 0x03 == 0x00:   # buffered, master writes
                return s._fprd(start, length)
        raise OSError(f"EtherCAT slave {pos}: no output sync manager")

    def _poll_mailboxes(self) -> None:
        """Collect the drives' emergency messages (outside the cycle)."""
        import pysoem
        for pos, role in self.roles.items():
            if role != 0:
                continue
            s = self.slaves[pos - 1]
            for _ in range(8):
                try:
                    if s.mbx_receive() <= 0:
                        break
                except pysoem.Emergency as e:
                    self.emergencies.append((pos, e.error_code, e.error_reg))
                except Exception:  # noqa: BLE001  (a mailbox that does not answer: nothing to collect)
                    break

    def _deactivate(self) -> None:
        """SAFE-OP: the slaves keep their outputs in the safe state and stop acting on frames."""
        import pysoem
        if not self.connected or self.master is None:
            return
        try:
            self.master.state = pysoem.SAFEOP_STATE
            self.master.write_state()
        except Exception:  # noqa: BLE001  (stopping anyway)
            self.connected = False

    def _close(self, restore: bool = True) -> None:
        """The drives' objects restored as found (:meth:`_restore`), INIT, and the interface
        released."""
        if restore and self.connected and self.master is not None:
            try:
                self._restore()
            except Exception as exc:  # noqa: BLE001  (closing anyway; said)
                self._notice(f"EtherCAT: restoring the drives' objects failed ({one_line(exc)})", warning=True)
        m, self.master = self.master, None
        self.connected = False
        if m is None:
            return
        try:
            import pysoem
            m.state = pysoem.INIT_STATE
            m.write_state()
        except Exception:  # noqa: BLE001
            pass
        try:
            m.close()
        except Exception:  # noqa: BLE001
            pass

    def _wkc_text(self) -> str:
        """The last working counter against the expected one (ETG.1000.4: each slave that
        reads or writes its part of the frame adds to it); a frame that did not come back at
        all (SOEM returns a negative code, EC_NOFRAME / EC_TIMEOUT) counts 0."""
        if self.last_wkc <= 0:
            return (f"EtherCAT working counter 0 of {self.expected_wkc} (no frame came back on "
                    f"{self.options.ifname}: cable, port or segment power)")
        return f"EtherCAT working counter {self.last_wkc} of {self.expected_wkc if self._expect is None else self._expect}"

    def _link_down(self) -> bool:
        return not self.connected or (self.state == "active" and (self._short >= self._down_cycles
                                                                   or self._needs_setup))

    def _reconnect(self, timeout_s: float | None) -> None:
        """Release the interface, scan and set the segment up again (configure), back to OP if active."""
        was_active = self.state == "active"
        self._close(restore=False)
        self._configure()
        if was_active:
            self._activate()

    # ------------------------------------------------------------------ reports
    def _full_scale_V(self, axis: str) -> float:
        return float(self.axis_options[axis].voltage_full_scale_V)

    def reset_fault(self, i: int) -> bool:
        """The operator's fault reset of axis i: a CiA 402 drive gets transition 15 (the rising
        edge of controlword bit 7) in the next frames while the axis is disabled, until it leaves
        Fault (:meth:`PowerStateMachine.request_reset`); never sent otherwise. The I/O profile's
        terminals have no fault of their own to reset (False)."""
        if self._sm[i] is None:
            return False
        self._sm[i].request_reset()
        return True

    def fault_state(self, i: int) -> str:
        """Axis i's drive's CiA 402 power state and statusword (0x6041) as last read, with what
        its slaves said (:meth:`fault_reason`); the I/O profile's terminals: :meth:`fault_reason`
        alone. Outside the cycle."""
        said = self.fault_reason(i)
        if self._sm[i] is None:
            return said
        said = said.rsplit("; now ", 1)[0]             # the state comes first here
        return self.drive_state(i) + (f"; {said}" if said else "")

    def drive_state(self, i: int) -> str:
        """Axis i's drive's CiA 402 power state and statusword (0x6041) as last read, whatever
        it is ("EtherCAT slave 1 (CiA 402 drive, axis X) is in Switch on disabled (statusword
        0x0250)"); the I/O profile: its slaves out of OP with their AL status codes, '' in OP."""
        if self._sm[i] is None:
            return self._al_text(i) if self._al_fault[i] else ""
        sw = self._statusword[i]
        return (f"{self._where(self._ax[i].slave)} is in {cia402.STATE_NAMES[cia402.decode_state(sw)]} "
                f"(statusword 0x{sw:04X})")

    def fault_reason(self, i: int) -> str:
        """Why axis ``i`` faults, one line: its slaves that left OP with their AL status codes
        (read after a short working counter), or the working counter while it is short (and the
        slaves not in OP with their AL status codes), or the drive's error code 0x603F of its
        last fault (kept until the drive is in Operation enabled again, so the report after the
        fault reset still names it) with the emergency it sent and its state now."""
        if self._al_fault[i]:
            return self._al_text(i)
        if self._bad_wkc_since is not None:
            why = self._wkc_text()
            try:
                import pysoem
                states = self._fail_states(pysoem.OP_STATE)
            except Exception:  # noqa: BLE001  (the report must not fail)
                states = ""
            return why + (f" ({states})" if states else "")
        o = self._ax[i]
        if o.profile != "cia402":
            return ""
        code = self._named_code[i] or self._error_code[i]
        if not (code or self.amp_fault[i] or self._sm[i].fault):
            return ""
        emcy = [c for p, c, _r in self.emergencies if p == o.slave and c]
        return (f"{self._where(o.slave)}: error code 0x603F = {cia402.describe_error(code)}"
                + (f", emergency 0x{emcy[-1]:04X} received" if emcy else "")
                + f"; now {cia402.STATE_NAMES[cia402.decode_state(self._statusword[i])]} "
                  f"(statusword 0x{self._statusword[i]:04X})")

    def budget(self, rate_hz: float) -> BusBudget:
        """One frame per cycle: preamble, Ethernet header, EtherCAT header, the LRW datagram
        over the whole image (outputs and inputs), SOEM's DC datagram when SYNC0 is on, FCS and
        the inter-frame gap at 100 Mbit/s, plus ``SLAVE_DELAY_S`` per slave, plus the host's
        round trip (``round_trip_s``, or measured by ``configure()``)."""
        o = self.options
        image = sum(sum(IMAGE[r]) for r in self.roles.values())
        dc = 10 + 8 + 2 if o.sync0 else 0
        frame = max(64, 14 + 2 + 10 + image + 2 + dc + 4)
        wire_bytes = 8 + frame + 12
        n_slaves = max(self.roles)
        wire = wire_bytes * BYTE_TIME_S + n_slaves * SLAVE_DELAY_S
        if o.round_trip_s is not None:
            rt, source = float(o.round_trip_s), "configured"
        elif self.round_trip.get("median_s") is not None:
            rt, source = float(self.round_trip["median_s"]), "measured"
        else:
            rt, source = 50e-6, "assumed"
        what = (f"EtherCAT, 1 frame of {frame} bytes (image {image} bytes{', DC datagram' if dc else ''}) through "
                f"{n_slaves} slave(s) at 100 Mbit/s")
        return make_budget(rate_hz, wire, rt, o.max_bus_load, what,
                           "a faster host NIC path (a dedicated port, an RT kernel)", source)

    def describe(self) -> dict:
        rt = self.round_trip
        d = {"ifname": self.options.ifname, "slaves": self.slave_info, "expected_wkc": self.expected_wkc,
             "sync0_slaves": self.dc_slaves, "counters": dict(self.counters),
             "emergencies": [{"slave": p, "code": f"0x{c:04X}", "meaning": cia402.error_meaning(c),
                              "register": f"0x{r:02X}"} for p, c, r in self.emergencies],
             "al_trip": ({"first_short_frame": self._trip_first,
                          "named_after_frames": {a: (x - self._trip_first if x >= 0 else None)
                                                 for a, x in zip(self.axis_names, self._trip_named)}}
                         if self._trip_first >= 0 else None),
             "round_trip": {"n": rt["n"],
                            "median_us": None if rt["median_s"] is None else round(rt["median_s"] * 1e6, 1),
                            "max_us": None if rt["max_s"] is None else round(rt["max_s"] * 1e6, 1)}}
        try:
            b = self.budget(1.0 / self.period_s)
            d["budget"] = {"cycle_us": round(b.cycle_time_s * 1e6, 1), "max_rate_hz": round(b.max_rate_hz, 1),
                           "fits": bool(1.0 / self.period_s <= b.max_rate_hz), "detail": b.detail}
        except Exception as exc:  # noqa: BLE001
            d["budget"] = {"error": one_line(exc)}
        return d


def _check_interface(ifname: str) -> None:
    """Refuse an interface this machine does not have, naming the ones it has.

    Raises:
        InputError: no network interface ``ifname`` (a setting to correct: exit code 2 in the
            CLI, nothing started); an interface that exists but cannot be opened is the
            caller's OSError.
    """
    import socket
    try:
        socket.if_nametoindex(ifname)
    except OSError:
        have = ", ".join(sorted(name for _, name in socket.if_nameindex())) or "none"
        raise InputError(f"driver.ifname: this machine has no network interface {ifname!r} "
                         f"(it has: {have}); set the NIC port the EtherCAT segment is plugged into") from None


def _state_name(state: int) -> str:
    base = {1: "INIT", 2: "PRE-OP", 3: "BOOT", 4: "SAFE-OP", 8: "OP"}.get(state & 0x0F, f"state {state & 0x0F}")
    return base + (" + error" if state & 0x10 else "")
