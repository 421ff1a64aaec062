"""Modbus driver: an open register map, Modbus TCP or RTU, from the YAML.

Function codes (MODBUS Application Protocol Specification V1.1b3): reads with FC03 (holding
registers, §6.3), FC04 (input registers, §6.4), FC01 (coils, §6.1), FC02 (discrete inputs,
§6.2); writes with FC06 (one register, §6.6), FC16 (several, §6.12), FC05 (one coil, §6.5),
FC15 (several coils, §6.11); FC23 (read/write multiple registers, §6.17: the write is applied
first, then the read) only where the device has it: ``fc23: auto`` probes it in ``configure()``
(an exception 01, illegal function, means no), ``yes`` uses it, ``no`` never does.

Every axis names its fields; axes may sit on different devices (per-axis ``unit_id``, and for
TCP ``host``/``port``). Per device and cycle the driver builds the fewest requests that carry the
map: contiguous written registers form one FC16 (FC06 when a block is one register), coils one
FC15 (FC05), read registers blocks of at most 125 (FC03/FC04), bits FC01/FC02; with FC23 the
written block and the first read block of the holding registers go in one request. Writes come
first, then reads, so the answer is the position one period after the command.

Split phase, non-blocking: ``write()`` sends the first request of the cycle on every connection,
``read()`` sends each next one as soon as the answer to the one before has arrived (one
transaction in flight per connection: Modbus TCP servers need not queue more, and pymodbus's
does not; RTU cannot) and collects the answers until ``timeout_s``. Framing is this module's own, from the specifications (Modbus Messaging on TCP/IP
Implementation Guide V1.0b: MBAP header; Modbus over Serial Line V1.02 §2.5.1: RTU with the
CRC-16 of §6.2.2, polynomial 0xA001 reflected, initial 0xFFFF, low byte first), on preallocated
frames: no pymodbus client (it would block for the answer) and no library logging inside the
cycle. A reply that does not parse is counted (``bad_frames``) and the stream resynchronises: on
TCP the parser drops bytes until a plausible MBAP header (protocol 0, a length of 2-254, a unit
and transaction id it sent) starts a frame that checks; on RTU until a frame with a good CRC. An
exception response (§7) is a read error for the axes of the request; its code and meaning are
counted and named in ``describe()`` and :meth:`ModbusDriver.fault_reason`.

Values (per field): ``type`` int16 | uint16 | int32 | uint32 | float32 (IEEE 754), ``byte_order``
of the two bytes in a register (Modbus: big), ``word_order`` of a 32-bit value (big: high word
first), ``scale`` and ``offset``: SI value = raw × scale + offset (voltage [V], position [m]).
Integer positions are signed counters (int16, int32: a drive's position is signed, CiA 402
0x6064 INTEGER32) that wrap and are unwrapped; an unsigned position type is refused at the
config check, by name (a carriage one count below 0 would read as the type's largest count);
float32 positions are taken as they are. Bits: a coil, a discrete input, or ``bit`` of a holding/input register, with polarity
``active: high | low``. The driver owns every bit of the registers it writes (bits it does not
set are written 0).

YAML (``driver:``)::

    type: modbus
    transport: tcp | rtu
    host: 127.0.0.1   port: 502          # tcp: the default device
    serial_port: /dev/ttyUSB0 | socket://127.0.0.1:5021   baudrate: 115200   # rtu
    parity: E | N | O   stopbits: 1 | 2   bytesize: 8      # rtu line settings (default 8E1)
    gap_chars: 3.5   device_latency_s: 0.0005              # rtu budget
    unit_id: 1                  # the default unit (per axis: unit_id)
    fc23: auto | yes | no
    sequence_register / sequence_echo_register: optional (RTU: recognises stale answers)
    watchdog: {address: 0x1120, value: 100}   # optional: a device register written with FC06
                                              # in configure() and read back (its command
                                              # timeout; units as the device defines them)
    timeout_s, wait, round_trip_s (tcp: request/answer time; default 400 us assumed until
    configure() measures it), max_bus_load: see split_phase.CommonOptions

per axis (``axes.NAME.driver``)::

    unit_id: 2                  # optional; host/port too (TCP: another device)
    voltage:  {address: 0, type: int16}                 # holding; scale default: full scale / 32767
    enable:   {table: holding, address: 1, bit: 0}      # or {table: coil, address: 0}
    fault_reset: {table: holding, address: 1, bit: 7}   # optional: pulsed on the operator's fault-reset
    position: {table: input, address: 100, type: int32, word_order: big, scale: 0.5e-6}
    fault:    {table: discrete, address: 0, active: high}   # optional
    voltage_full_scale_V: 10.0  # the limit of voltage_out

Device watchdog: where the device has a command timeout register, ``watchdog:`` sets it; where
it has none, set the device's own communication-loss action (docs/drivers.md).
"""

from __future__ import annotations

import math
import socket
import struct
import time
from typing import Annotated, Literal

import numpy as np
from pydantic import Field, model_validator

from motorctl.driver import BusBudget, StopCheck
from motorctl.schema import StrictModel
from motorctl_drivers.split_phase import (
    CommonOptions,
    EncoderUnwrap,
    ResetPulses,
    SplitPhaseDriver,
    make_budget,
    open_error,
)

Reg = Annotated[int, Field(ge=0, le=0xFFFF)]
MAX_READ_REGS, MAX_WRITE_REGS, MAX_READ_BITS, MAX_WRITE_BITS = 125, 123, 2000, 1968
FC23_MAX_READ, FC23_MAX_WRITE = 125, 121

#: exception codes (Modbus Application Protocol V1.1b3 §7)
EXCEPTION_CODES = {1: "illegal function", 2: "illegal data address", 3: "illegal data value",
                   4: "server device failure", 5: "acknowledge", 6: "server device busy",
                   8: "memory parity error", 10: "gateway path unavailable",
                   11: "gateway target device failed to respond"}
TYPE_REGS = {"int16": 1, "uint16": 1, "int32": 2, "uint32": 2, "float32": 2}
TYPE_MAX = {"int16": 32767, "uint16": 65535, "int32": 2**31 - 1, "uint32": 2**32 - 1}
TYPE_MIN = {"int16": -32768, "uint16": 0, "int32": -2**31, "uint32": 0}


def exception_text(code: int) -> str:
    """'0x02 illegal data address' for a Modbus exception code."""
    return f"0x{code:02X} {EXCEPTION_CODES.get(code, 'unknown exception')}"


# --------------------------------------------------------------------------- CRC, framing
def _crc_table() -> list[int]:
    table = []
    for n in range(256):
        c = n
        for _ in range(8):
            c = (c >> 1) ^ 0xA001 if c & 1 else c >> 1
        table.append(c)
    return table


_CRC_TABLE = _crc_table()


def crc16(data) -> int:
    """Modbus RTU CRC-16 (Modbus over Serial Line V1.02 §6.2.2: polynomial 0xA001 reflected,
    initial value 0xFFFF) of ``data``; sent low byte first."""
    crc = 0xFFFF
    t = _CRC_TABLE
    for b in data:
        crc = (crc >> 8) ^ t[(crc ^ b) & 0xFF]
    return crc


# --------------------------------------------------------------------------- settings
class Value(StrictModel):
    """A number in one or two registers (see the module docstring)."""

    table: Literal["holding", "input"] = "holding"
    address: Reg
    type: Literal["int16", "uint16", "int32", "uint32", "float32"] = "int16"
    byte_order: Literal["big", "little"] = "big"
    word_order: Literal["big", "little"] = "big"
    scale: float | None = None
    offset: float = 0.0

    @property
    def nregs(self) -> int:
        return TYPE_REGS[self.type]


class Bit(StrictModel):
    """One bit: a coil, a discrete input, or ``bit`` of a holding/input register; ``active``
    high (1 = true) or low (0 = true)."""

    table: Literal["holding", "input", "coil", "discrete"] = "holding"
    address: Reg
    bit: Annotated[int, Field(ge=0, le=15)] = 0
    active: Literal["high", "low"] = "high"


class Watchdog(StrictModel):
    """A device command-timeout register written with FC06 in ``configure()`` and read back."""

    address: Reg
    value: Annotated[int, Field(ge=0, le=0xFFFF)]


class ModbusOptions(CommonOptions):
    """YAML ``driver:`` of the Modbus driver (see the module docstring)."""

    transport: Literal["tcp", "rtu"] = "tcp"
    host: str = "127.0.0.1"
    port: Annotated[int, Field(ge=1, le=65535)] = 502
    serial_port: str = ""
    baudrate: Annotated[int, Field(gt=0)] = 115200
    parity: Literal["N", "E", "O"] = "E"
    stopbits: Literal[1, 2] = 1
    bytesize: Literal[7, 8] = 8
    gap_chars: Annotated[float, Field(ge=0)] = 3.5
    device_latency_s: Annotated[float, Field(ge=0)] = 0.0005
    unit_id: Annotated[int, Field(ge=0, le=247)] = 1
    fc23: Literal["auto", "yes", "no"] = "auto"
    sequence_register: Reg | None = None
    sequence_echo_register: Reg | None = None
    watchdog: Watchdog | None = None

    @property
    def bits_per_char(self) -> int:
        """Start + data + parity + stop bits of one character on the RTU line."""
        return 1 + self.bytesize + (0 if self.parity == "N" else 1) + self.stopbits


class ModbusAxisOptions(StrictModel):
    """YAML ``axes.NAME.driver`` of the Modbus driver: where this axis lives in the map."""

    unit_id: Annotated[int, Field(ge=0, le=247)] | None = None
    host: str | None = None
    port: Annotated[int, Field(ge=1, le=65535)] | None = None
    voltage: Value
    enable: Bit
    fault_reset: Bit | None = None
    position: Value
    fault: Bit | None = None
    voltage_full_scale_V: Annotated[float, Field(gt=0)] = 10.0

    @model_validator(mode="after")
    def _check(self):
        if self.voltage.table != "holding":
            raise ValueError("voltage must be a holding register (it is written)")
        for name in ("enable", "fault_reset"):
            b = getattr(self, name)
            if b is not None and b.table not in ("holding", "coil"):
                raise ValueError(f"{name} must be a holding register bit or a coil (it is written)")
        if self.position.scale is None:
            raise ValueError("position.scale (metres per count) is required")
        if self.position.type in ("uint16", "uint32"):
            # a drive's position counter is signed (CiA 402 0x6064 is INTEGER32): taken unsigned,
            # a carriage one count below 0 reads as 2**32 - 1 counts (2147.48 m at 0.5 um)
            signed = "int16" if self.position.type == "uint16" else "int32"
            raise ValueError(f"position.type {self.position.type}: a position counter is signed; declare "
                             f"the same register {signed} (a carriage one count below 0 would read as "
                             f"{(TYPE_MAX[self.position.type]) * self.position.scale:.6g} m; a counter that "
                             f"wraps is unwrapped either way)")
        if self.voltage.scale is None and self.voltage.type in ("uint16", "uint32"):
            raise ValueError("voltage of an unsigned type needs scale and offset (volts per count, volts at 0)")
        return self

    def voltage_scale(self) -> float:
        """Volts per raw count of the voltage field (default: full scale / the type's largest)."""
        v = self.voltage
        if v.scale is not None:
            return v.scale
        return 1.0 if v.type == "float32" else self.voltage_full_scale_V / TYPE_MAX[v.type]


# --------------------------------------------------------------------------- value codec
def value_to_registers(v: Value, raw) -> tuple[int, ...]:
    """Raw value (int, or float for float32) → the registers of ``v`` (1 or 2 words) in its
    byte and word order."""
    if v.type == "float32":
        b = struct.pack(">f", float(raw))
    else:
        b = (int(raw) & ((1 << (16 * v.nregs)) - 1)).to_bytes(2 * v.nregs, "big")
    words = [b[k:k + 2] for k in range(0, len(b), 2)]
    if v.word_order == "little":
        words.reverse()
    if v.byte_order == "little":
        words = [w[::-1] for w in words]
    return tuple(int.from_bytes(w, "big") for w in words)


def registers_to_value(v: Value, regs) -> int | float:
    """Registers of ``v`` (in its byte and word order) → the raw value: an unsigned integer of
    16 or 32 bits (two's complement as it stands; the unwrap takes the sign), or a float."""
    words = [int(r) & 0xFFFF for r in regs[:v.nregs]]
    if v.byte_order == "little":
        words = [((w & 0xFF) << 8) | (w >> 8) for w in words]
    if v.word_order == "little":
        words.reverse()
    raw = 0
    for w in words:
        raw = raw << 16 | w
    if v.type == "float32":
        return struct.unpack(">f", raw.to_bytes(4, "big"))[0]
    return raw


def volts_to_raw(v: Value, u_V: float, scale: float) -> int | float:
    """Voltage [V] → the raw value of field ``v``: (u − offset) / scale, rounded and saturated
    to the type's range; NaN → the raw value of 0 V."""
    if not (u_V == u_V):
        u_V = 0.0
    x = (u_V - v.offset) / scale
    if v.type == "float32":
        return x
    c = round(x)
    lo, hi = TYPE_MIN[v.type], TYPE_MAX[v.type]
    return hi if c > hi else (lo if c < lo else int(c))


class _Float:
    """The 'unwrap' of a float position: the value as it is."""

    def update(self, raw):
        return raw


class _Unwrap(EncoderUnwrap):
    """An unsigned counter's first reading is taken unsigned (EncoderUnwrap takes it signed)."""

    def __init__(self, bits: int, signed: bool):
        super().__init__(bits)
        self.signed = signed

    def update(self, raw: int) -> int:
        if self.last < 0 and not self.signed:
            self.last = raw
            self.total = raw
            return raw
        return super().update(raw)


# --------------------------------------------------------------------------- the plan
class Request:
    """One Modbus request of a cycle, with its preallocated frame.

    Attributes: fc, unit, device (index into the driver's links), address/count (read part;
    FC23: read block), waddress/wcount (write part), slots_w: what fills the written
    registers/coils, slots_r: what the answer carries, axes: the axes it serves, rsp_len: the
    length of a normal answer's PDU [bytes].
    """

    def __init__(self, fc: int, unit: int, device: int, address: int = 0, count: int = 0,
                 waddress: int = 0, wcount: int = 0):
        self.fc, self.unit, self.device = fc, unit, device
        self.address, self.count, self.waddress, self.wcount = address, count, waddress, wcount
        self.slots_w: list = []
        self.slots_r: list = []
        self.axes: set[int] = set()
        self.tid = 0
        self.frame = bytearray()
        self.pdu_off = 0
        self.data_off = 0

    @property
    def rsp_len(self) -> int:
        """Length of the normal answer's PDU (function code included) [bytes]."""
        if self.fc in (3, 4, 23):
            return 2 + 2 * self.count
        if self.fc in (1, 2):
            return 2 + (self.count + 7) // 8
        return 5                                   # 5, 6, 15, 16: echo of address and value/count

    def describe(self) -> str:
        if self.fc == 23:
            return (f"FC23 unit {self.unit} write {self.waddress}+{self.wcount} read "
                    f"{self.address}+{self.count}")
        if self.fc in (5, 6, 15, 16):
            return f"FC{self.fc:02d} unit {self.unit} write {self.waddress}+{self.wcount}"
        return f"FC{self.fc:02d} unit {self.unit} read {self.address}+{self.count}"

    def build(self, tcp: bool) -> None:
        """Preallocate the frame (MBAP header or RTU address + CRC around the PDU)."""
        fc = self.fc
        if fc in (1, 2, 3, 4):
            pdu = struct.pack(">BHH", fc, self.address, self.count)
        elif fc == 5:
            pdu = struct.pack(">BHH", fc, self.waddress, 0)
        elif fc == 6:
            pdu = struct.pack(">BHH", fc, self.waddress, 0)
        elif fc == 15:
            nb = (self.wcount + 7) // 8
            pdu = struct.pack(">BHHB", fc, self.waddress, self.wcount, nb) + bytes(nb)
        elif fc == 16:
            pdu = struct.pack(">BHHB", fc, self.waddress, self.wcount, 2 * self.wcount) + bytes(2 * self.wcount)
        else:   # 23
            pdu = struct.pack(">BHHHHB", fc, self.address, self.count, self.waddress, self.wcount,
                              2 * self.wcount) + bytes(2 * self.wcount)
        self.data_off = {5: 3, 6: 3, 15: 6, 16: 6, 23: 10}.get(fc, 0)
        if tcp:
            self.frame = bytearray(struct.pack(">HHHB", 0, 0, len(pdu) + 1, self.unit) + pdu)
            self.pdu_off = 7
        else:
            self.frame = bytearray(bytes((self.unit,)) + pdu + b"\0\0")
            self.pdu_off = 1


def _blocks(addresses, limit: int) -> list[tuple[int, int]]:
    """Sorted addresses → (start, count) blocks; contiguous=False allows gaps within ``limit``."""
    out = []
    for a in sorted(set(addresses)):
        if out and a - out[-1][0] < limit:
            out[-1] = (out[-1][0], a - out[-1][0] + 1)
        else:
            out.append((a, 1))
    return out


def _runs(addresses) -> list[tuple[int, int]]:
    """Sorted addresses → contiguous (start, count) runs."""
    out = []
    for a in sorted(set(addresses)):
        if out and a == out[-1][0] + out[-1][1]:
            out[-1] = (out[-1][0], out[-1][1] + 1)
        else:
            out.append((a, 1))
    return out


class RegisterPlan:
    """The requests of one cycle for the whole group, and those of a position query.

    Args:
        names, axis_options, options: the driver's axes and settings.
        fc23: per device key, whether FC23 may be used.
    Attributes:
        devices: [(host, port, unit)] (RTU: host/port of the link, one link for all).
        cycle: the requests of a cycle in send order (writes before reads, per device).
        query: the read-only requests (configure's first reading).
    Raises:
        ValueError: two fields overlap, a value cannot be carried.
    """

    def __init__(self, names, axis_options, options: ModbusOptions, fc23: dict | None = None):
        tcp = options.transport == "tcp"
        self.devices: list[tuple] = []
        dev_of = []
        for a in names:
            o = axis_options[a]
            key = ((o.host or options.host) if tcp else "", (o.port or options.port) if tcp else 0,
                   o.unit_id if o.unit_id is not None else options.unit_id)
            if key not in self.devices:
                self.devices.append(key)
            dev_of.append(self.devices.index(key))
        self.dev_of = dev_of
        fc23 = fc23 or {}
        self.cycle: list[Request] = []
        self.query: list[Request] = []
        for dv, key in enumerate(self.devices):
            axes = [i for i in range(len(names)) if dev_of[i] == dv]
            hold_w: dict[int, tuple] = {}      # address -> ("voltage", i, k) | ("bits", [(i, name)]) | ("sequence", -1, 0)
            coil_w: dict[int, tuple] = {}      # address -> ("coil", i, name)
            reads = {"holding": {}, "input": {}, "coil": {}, "discrete": {}}

            def taken(table: dict, addr: int, what: str):
                if addr in table:
                    raise ValueError(f"unit {key[2]}: address {addr} is used twice (by {what} and another field)")

            for i in axes:
                o = axis_options[names[i]]
                v = o.voltage
                for k in range(v.nregs):
                    taken(hold_w, v.address + k, f"{names[i]} voltage")
                    hold_w[v.address + k] = ("voltage", i, k)
                for bname in ("enable", "fault_reset"):
                    b = getattr(o, bname)
                    if b is None:
                        continue
                    if b.table == "coil":
                        taken(coil_w, b.address, f"{names[i]} {bname}")
                        coil_w[b.address] = ("coil", i, bname)
                    else:
                        slot = hold_w.setdefault(b.address, ("bits", []))
                        if slot[0] != "bits":
                            raise ValueError(f"unit {key[2]}: register {b.address} holds a value and {names[i]} {bname}")
                        slot[1].append((i, bname))
                p = o.position
                for k in range(p.nregs):
                    taken(reads[p.table], p.address + k, f"{names[i]} position")
                    reads[p.table][p.address + k] = ("position", i, k)
                if o.fault is not None:
                    slot = reads[o.fault.table].setdefault(o.fault.address, ("fault", []))
                    if slot[0] != "fault":
                        raise ValueError(f"unit {key[2]}: {o.fault.table} {o.fault.address} holds a position and "
                                         f"{names[i]} fault")
                    slot[1].append(i)
            if dv == 0 and options.sequence_register is not None:
                taken(hold_w, options.sequence_register, "sequence_register")
                hold_w[options.sequence_register] = ("sequence", -1, 0)
            if dv == 0 and options.sequence_echo_register is not None:
                taken(reads["holding"], options.sequence_echo_register, "sequence_echo_register")
                reads["holding"][options.sequence_echo_register] = ("echo", -1, 0)
            clash = set(hold_w) & set(reads["holding"])
            if clash:
                raise ValueError(f"unit {key[2]}: holding registers {sorted(clash)} are both written and read")
            unit = key[2]
            writes = []
            for start, count in _runs(hold_w):
                fc = 6 if count == 1 else 16
                if count > MAX_WRITE_REGS:
                    raise ValueError(f"unit {unit}: {count} written registers exceed FC16's {MAX_WRITE_REGS}")
                r = Request(fc, unit, dv, waddress=start, wcount=count)
                r.slots_w = [(a - start, hold_w[a]) for a in range(start, start + count)]
                writes.append(r)
            for start, count in _runs(coil_w):
                r = Request(5 if count == 1 else 15, unit, dv, waddress=start, wcount=count)
                r.slots_w = [(a - start, coil_w[a]) for a in range(start, start + count)]
                writes.append(r)
            read_reqs = []
            for table, fc, limit in (("holding", 3, MAX_READ_REGS), ("input", 4, MAX_READ_REGS),
                                     ("coil", 1, MAX_READ_BITS), ("discrete", 2, MAX_READ_BITS)):
                for start, count in _blocks(reads[table], limit):
                    r = Request(fc, unit, dv, address=start, count=count)
                    r.slots_r = [(a - start, reads[table][a]) for a in sorted(reads[table])
                                 if start <= a < start + count]
                    read_reqs.append(r)
            hw = [r for r in writes if r.fc in (6, 16)]
            hr = [r for r in read_reqs if r.fc == 3]
            if fc23.get(dv) and len(hw) == 1 and hr and hw[0].wcount <= FC23_MAX_WRITE:
                w, rd = hw[0], hr[0]
                m = Request(23, unit, dv, address=rd.address, count=rd.count, waddress=w.waddress, wcount=w.wcount)
                m.slots_w, m.slots_r = w.slots_w, rd.slots_r
                writes = [m] + [r for r in writes if r is not w]
                read_reqs = [r for r in read_reqs if r is not rd]
            for r in writes + read_reqs:
                for _, s in r.slots_w:
                    if s[0] == "bits":
                        r.axes.update(ax for ax, _ in s[1])
                    elif s[1] >= 0:
                        r.axes.add(s[1])
                for _, s in r.slots_r:
                    if s[0] == "fault":
                        r.axes.update(s[1])
                    elif s[1] >= 0:
                        r.axes.add(s[1])
                r.build(tcp)
            self.cycle += writes + read_reqs
            q = []
            for r in writes + read_reqs:
                if r.fc == 23:            # the query reads the same block without writing
                    qr = Request(3, unit, dv, address=r.address, count=r.count)
                    qr.slots_r, qr.axes = r.slots_r, r.axes
                    qr.build(tcp)
                    q.append(qr)
                elif r.fc in (1, 2, 3, 4):
                    q.append(r)
            self.query += q
        self.needs = [[k for k, r in enumerate(self.cycle) if i in r.axes] for i in range(len(names))]
        self.query_needs = [[k for k, r in enumerate(self.query) if i in r.axes] for i in range(len(names))]

    def summary(self) -> list[str]:
        return [r.describe() for r in self.cycle]


# --------------------------------------------------------------------------- driver
class ModbusDriver(SplitPhaseDriver):
    """The Modbus driver (TCP or RTU). See the module docstring."""

    Options = ModbusOptions
    AxisOptions = ModbusAxisOptions
    DEFAULT_ROUND_TRIP_S = 400e-6

    def __init__(self, options: ModbusOptions, axis_options: dict, period_s: float):
        super().__init__(options, axis_options, period_s)
        self.SEQ_MASK = 0xFFFF if options.transport == "tcp" else 0xFF
        self._ax = [axis_options[a] for a in self.axis_names]
        n = len(self._ax)
        self.fc23_probe: dict = {}
        self.plan = RegisterPlan(self.axis_names, axis_options, options,
                                 fc23={d: options.fc23 != "no" for d in range(64)})
        self._unwrap = [_Float() if o.position.type == "float32" else
                        _Unwrap(16 * o.position.nregs, o.position.type.startswith("int")) for o in self._ax]
        self._m_per_count = [float(o.position.scale) for o in self._ax]
        self._offset_m = [o.position.offset for o in self._ax]
        self._vscale = [o.voltage_scale() for o in self._ax]
        self._pos_words = [[0] * o.position.nregs for o in self._ax]
        self._fault_raw = [False] * n
        self._pulses = ResetPulses(n)       # the operator's fault reset, pulsed on fault_reset
        self._enable_now = [False] * n
        self._reset_now = [False] * n
        self.exception_counts: dict[int, int] = {}
        self.last_exception = [""] * n
        self.links: list = []          # per device: socket (tcp) or the serial port (rtu, one)
        self.bufs: list[bytearray] = []
        self._reqs: list[Request] = self.plan.cycle
        self._needs = self.plan.needs
        self._done = [False] * max(len(self.plan.cycle), len(self.plan.query), 1)
        self._chain: list[int] = []
        self._due = [None]
        self._conn_of: list[int] = []
        self._conn_reqs: list = []
        self._tid = 0

    # --- link
    def _open_transport(self) -> None:
        """Open one TCP connection per host:port (units behind one gateway share it), or the RTU
        serial port with its line settings.

        Raises:
            OSError: a connection or the port cannot be opened, or the port refuses a line
            setting (one line naming the endpoint and why).
        """
        o = self.options
        self.links = []
        self._conn_of = []
        if o.transport == "tcp":
            keys = []
            for host, port, _unit in self.plan.devices:
                if (host, port) not in keys:
                    keys.append((host, port))
                    try:
                        sock = socket.create_connection((host, port), timeout=2.0)
                    except OSError as exc:
                        self._release_transport()
                        raise open_error("Modbus TCP device", f"{host}:{port}", exc) from None
                    sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                    sock.setblocking(False)
                    self.links.append(_Sock(sock))
                self._conn_of.append(keys.index((host, port)))
        else:
            self.links = [_open_serial(o)]
            self._conn_of = [0] * len(self.plan.devices)
        self.bufs = [bytearray() for _ in self.links]
        self._set_requests(self.plan.cycle, self.plan.needs)
        fds = [link.fileno() for link in self.links]
        self._wait_fds = fds if o.wait == "select" else []

    def _set_requests(self, reqs, needs) -> None:
        """Make ``reqs`` the requests in flight (per connection lists for the answer lookup)."""
        self._reqs, self._needs = reqs, needs
        self._conn_reqs = [[r for r in reqs if self._conn_of[r.device] == c] for c in range(len(self.links))]
        self._chain = [0] * len(self.links)

    def _release_transport(self) -> None:
        for link in self.links:
            try:
                link.close()
            except Exception:  # noqa: BLE001
                pass
        self.links = []

    def _full_scale_V(self, axis: str) -> float:
        """``axes.NAME.driver.voltage_full_scale_V`` [V]."""
        return float(self.axis_options[axis].voltage_full_scale_V)

    # --- configure: watchdog, FC23 probe, first reading with timed exchanges
    def _configure(self) -> None:
        """Open the links, write and read back the device watchdog (``watchdog``), read every
        axis (:meth:`_first_reading`, timed: the round trip), then probe FC23 (``fc23: auto``).

        Raises:
            OSError: a link cannot be opened; the device answers the watchdog write with an
            exception or holds another value. ConnectionError: a device does not answer.
        """
        self._open_transport()
        self.connected = True
        try:
            if self.options.watchdog is not None:
                self._set_watchdog()
            self._first_reading(self.CONFIGURE_TIMEOUT_S)
            if self.options.fc23 == "auto":   # its write (0 V, disabled) arms the device's watchdog
                self._probe_fc23()
            self._found_latched()
        except BaseException:
            self._close()
            raise

    def _found_latched(self) -> None:
        """A fault the device reports at set-up (the ``fault`` bit, e.g. an earlier run's fault
        or its own communication watchdog when an earlier host stopped) stays: the host never
        pulses ``fault_reset`` on its own. A set-up warning names it and the command that
        clears it; the first cycle faults the axis; only the operator's ``motorctl
        fault-reset`` pulses the reset bit (:meth:`reset_fault`)."""
        for i in range(len(self.axis_names)):
            if self.amp_fault[i]:
                how = "" if self._ax[i].fault_reset is not None else \
                    "; the map has no fault_reset bit: the device's own reset clears it"
                self._notice_drive_fault(i, (self.fault_state(i) or "the device's fault bit is active") + how)

    def _read_back_stop(self, answered: np.ndarray, deadline: float) -> list[StopCheck]:
        """Read back every register and coil the cycle writes (FC03 / FC01, one request at a
        time): each axis's voltage must hold the raw value of 0 V and its enable bit must be
        inactive."""
        tcp = self.options.transport == "tcp"
        n = len(self._ax)
        ok = [bool(answered[i]) for i in range(n)]
        held: list[list[str]] = [[] if answered[i] else ["no answer to the stop command"] for i in range(n)]
        vwords = [[0] * o.voltage.nregs for o in self._ax]
        vread = [False] * n
        for r in self.plan.cycle:
            if not r.wcount:
                continue
            coil = r.fc in (5, 15)
            rd = Request(1 if coil else 3, r.unit, r.device, address=r.waddress, count=r.wcount)
            rd.build(tcp)
            where = f"{'coil' if coil else 'HR'} {r.waddress}" + (f"-{r.waddress + r.wcount - 1}" if r.wcount > 1 else "")
            try:
                pdu = self._blocking(rd, max(0.01, deadline - time.perf_counter()))
            except ConnectionError:
                pdu = None
            if pdu is None or pdu[0] & 0x80:
                why = "no answer" if pdu is None else f"exception {exception_text(pdu[1])}"
                for i in r.axes:
                    ok[i] = False
                    held[i].append(f"reading back unit {r.unit} {where}: {why}")
                continue
            for off, slot in r.slots_w:
                if coil:
                    _, i, bname = slot
                    bit = pdu[2 + off // 8] >> (off % 8) & 1
                    self._held_bit(i, bname, bit, f"coil {r.waddress + off}", ok, held)
                    continue
                word = pdu[2 + 2 * off] << 8 | pdu[3 + 2 * off]
                if slot[0] == "voltage":
                    vwords[slot[1]][slot[2]] = word
                    vread[slot[1]] = True
                elif slot[0] == "bits":
                    for i, bname in slot[1]:
                        b = getattr(self._ax[i], bname)
                        self._held_bit(i, bname, word >> b.bit & 1, f"HR {r.waddress + off} bit {b.bit}", ok, held)
        for i, o in enumerate(self._ax):
            if not vread[i]:
                continue
            v = o.voltage
            zero = value_to_registers(v, volts_to_raw(v, 0.0, self._vscale[i]))
            raw = registers_to_value(v, vwords[i])
            if v.type.startswith("int") and raw >= 1 << (16 * v.nregs - 1):
                raw -= 1 << (16 * v.nregs)
            volts = raw * self._vscale[i] + v.offset
            if tuple(vwords[i]) != zero:
                ok[i] = False
            held[i].insert(0, f"HR {v.address} = {raw:g} ({volts:.3f} V)")
        return [StopCheck(a, ok[i], ", ".join(held[i])) for i, a in enumerate(self.axis_names)]

    def _held_bit(self, i: int, bname: str, bit: int, where: str, ok: list, held: list) -> None:
        """A read-back bit of axis i: the enable must be inactive (the reset bit is reported only)."""
        if bname != "enable":
            return
        on = bit == (self._ax[i].enable.active == "high")
        if on:
            ok[i] = False
        held[i].append(f"{where} = {bit} (amplifier {'ON' if on else 'off'})")

    def _blocking(self, req: Request, timeout_s: float):
        """Send one request and wait for its answer (outside the loop): the PDU bytes, or raise."""
        c = self._conn_of[req.device]
        self._stamp(req)
        self._send(req)
        deadline = time.perf_counter() + timeout_s
        while time.perf_counter() < deadline:
            self._fill(c)
            for r, pdu in self._frames(c, [req]):
                if r is req:
                    return pdu
            time.sleep(0.0002)
        raise ConnectionError(f"modbus unit {req.unit}: no answer to {req.describe()} within {timeout_s:g} s")

    def _set_watchdog(self) -> None:
        w = self.options.watchdog
        for dv, (_h, _p, unit) in enumerate(self.plan.devices):
            wr = Request(6, unit, dv, waddress=w.address, wcount=1)
            wr.build(self.options.transport == "tcp")
            struct.pack_into(">H", wr.frame, wr.pdu_off + 3, w.value)
            pdu = self._blocking(wr, self.CONFIGURE_TIMEOUT_S)
            if pdu[0] & 0x80:
                raise OSError(f"modbus unit {unit}: watchdog register {w.address} refused: exception "
                              f"{exception_text(pdu[1])}")
            rd = Request(3, unit, dv, address=w.address, count=1)
            rd.build(self.options.transport == "tcp")
            pdu = self._blocking(rd, self.CONFIGURE_TIMEOUT_S)
            got = struct.unpack_from(">H", pdu, 2)[0] if not pdu[0] & 0x80 else None
            if got != w.value:
                raise OSError(f"modbus unit {unit}: watchdog register {w.address} reads back {got} after writing {w.value}")

    def _probe_fc23(self) -> None:
        """Send each FC23 of the plan once with every axis disabled and 0 V: an exception 01
        (illegal function) means the device has no FC23, and the plan is rebuilt without it."""
        without = set()
        for r in [r for r in self.plan.cycle if r.fc == 23]:
            self._fill_writes(r, self.seq, np.zeros(len(self._ax)), np.zeros(len(self._ax), dtype=bool))
            pdu = self._blocking(r, self.CONFIGURE_TIMEOUT_S)
            self.fc23_probe[r.unit] = "yes"
            if pdu[0] == 0x97 and pdu[1] == 1:
                without.add(r.device)
                self.fc23_probe[r.unit] = "no (exception 0x01 illegal function)"
            elif pdu[0] & 0x80:
                raise OSError(f"modbus unit {r.unit}: {r.describe()} answered exception {exception_text(pdu[1])}")
        if without:
            self.plan = RegisterPlan(self.axis_names, self.axis_options, self.options,
                                     fc23={d: d not in without for d in range(len(self.plan.devices))})
            self._set_requests(self.plan.cycle, self.plan.needs)
            self._done = [False] * max(len(self.plan.cycle), len(self.plan.query), 1)

    # --- io
    def _send(self, r: Request) -> None:
        self.links[self._conn_of[r.device]].send(r.frame)

    def _fill(self, c: int) -> None:
        data = self.links[c].recv()
        if data:
            self.bufs[c] += data

    def _stamp(self, r: Request) -> None:
        """Give ``r`` the next transaction id (TCP) / its CRC (RTU)."""
        if self.options.transport == "tcp":
            self._tid = (self._tid + 1) & 0xFFFF
            r.tid = self._tid
            struct.pack_into(">H", r.frame, 0, r.tid)
        else:
            r.tid = 0
            f = r.frame
            c = crc16(memoryview(f)[:-2])
            f[-2] = c & 0xFF
            f[-1] = c >> 8

    def _fill_writes(self, r: Request, seq: int, u_V, enable) -> None:
        """Put this cycle's values into the written part of request ``r``'s frame."""
        f = r.frame
        base = r.pdu_off + r.data_off
        ax = self._ax
        if r.fc in (5, 15):
            if r.fc == 15:
                for k in range((r.wcount + 7) // 8):
                    f[base + k] = 0
            for off, s in r.slots_w:
                _, i, bname = s
                b = getattr(ax[i], bname)
                on = (self._enable_now[i] if bname == "enable" else self._reset_now[i]) == (b.active == "high")
                if r.fc == 5:
                    struct.pack_into(">H", f, r.pdu_off + 3, 0xFF00 if on else 0)
                elif on:
                    f[base + off // 8] |= 1 << (off % 8)
            return
        dst = base if r.fc != 6 else r.pdu_off + 3
        for off, s in r.slots_w:
            kind = s[0]
            if kind == "voltage":
                i, k = s[1], s[2]
                o = ax[i]
                raw = volts_to_raw(o.voltage, float(u_V[i]), self._vscale[i]) if enable[i] \
                    else volts_to_raw(o.voltage, 0.0, self._vscale[i])
                val = value_to_registers(o.voltage, raw)[k]
            elif kind == "bits":
                val = 0
                for i, bname in s[1]:
                    b = getattr(ax[i], bname)
                    on = self._enable_now[i] if bname == "enable" else self._reset_now[i]
                    if on == (b.active == "high"):
                        val |= 1 << b.bit
            else:
                val = seq & 0xFFFF
            struct.pack_into(">H", f, dst + 2 * off, val)

    def _transmit(self, seq: int, u_V: np.ndarray, enable: np.ndarray) -> None:
        en, rs, amp = self._enable_now, self._reset_now, self.amp_fault
        for i in range(len(en)):
            e = bool(enable[i])
            en[i] = e
            rs[i] = self._pulses.bit(i, e, bool(amp[i]))       # only on the operator's reset
        done = self._done
        for k in range(len(done)):
            done[k] = False
        for buf in self.bufs:        # a partial frame left from the previous cycle will not complete
            if buf and self.options.transport == "rtu":
                self.counters["stale"] += 1
                buf.clear()
        reqs = self._reqs
        for r in reqs:
            if r.wcount:
                self._fill_writes(r, seq, u_V, enable)
        self._start(reqs)

    def _start(self, reqs) -> None:
        """Send the first request of every connection; each next one goes out when the answer
        to the one before has come (:meth:`_receive`): one transaction in flight per connection
        (Modbus TCP devices need not queue more; RTU cannot)."""
        chain = self._chain
        for c, creqs in enumerate(self._conn_reqs):
            chain[c] = 0
            if creqs:
                self._stamp(creqs[0])
                self._send(creqs[0])
                chain[c] = 1

    def _transmit_query(self, seq: int) -> None:
        done = self._done
        for k in range(len(done)):
            done[k] = False
        self._set_requests(self.plan.query, self.plan.query_needs)
        self._start(self._reqs)

    def _query_once(self, timeout_s: float) -> None:
        try:
            super()._query_once(timeout_s)
        finally:
            self._set_requests(self.plan.cycle, self.plan.needs)

    # --- answers
    def _frames(self, c: int, candidates):
        """Complete frames in connection ``c``'s buffer: yields (request, pdu) for those that
        check against one of ``candidates`` (the requests in flight; RTU: the one whose answer is
        due), (None, pdu) for a well-formed late answer to an earlier request. Junk is dropped
        byte by byte (one ``bad_frames`` per resync) until a frame checks."""
        buf = self.bufs[c]
        tcp = self.options.transport == "tcp"
        junk = False
        while buf:
            if tcp:
                if len(buf) < 8:
                    break
                tid, proto, length, unit = _MBAP.unpack_from(buf, 0)
                r = None
                for q in candidates:
                    if q.tid == tid:
                        r = q
                        break
                plausible = proto == 0 and 3 <= length <= 254 and self._length_fits(buf, length)
                if plausible and r is not None:   # the length an answer to r can have
                    plausible = unit == r.unit and (length - 1 == r.rsp_len or length == 3)
                elif plausible:                   # not in flight: a late answer, or junk
                    plausible = self._known_tid(tid) and (buf[7] & 0x7F) in (1, 2, 3, 4, 5, 6, 15, 16, 23)
                if not plausible:
                    del buf[0]
                    junk = True
                    continue
                if len(buf) < 6 + length:
                    break
                pdu = bytes(buf[7:6 + length])
                if r is not None and not self._pdu_fits(r, pdu):
                    del buf[0]
                    junk = True
                    continue
                del buf[:6 + length]
            else:
                r = candidates[0] if candidates else None
                if r is None:
                    self.counters["stale"] += 1
                    buf.clear()
                    break
                if buf[0] != r.unit or (buf[1] & 0x7F) != r.fc:
                    del buf[0]
                    junk = True
                    continue
                n = 5 if buf[1] & 0x80 else 1 + r.rsp_len + 2
                if len(buf) < n:
                    break
                if crc16(memoryview(buf)[:n - 2]) != buf[n - 2] | buf[n - 1] << 8 or \
                        not self._pdu_fits(r, bytes(buf[1:n - 2])):
                    del buf[0]
                    junk = True
                    continue
                pdu = bytes(buf[1:n - 2])
                del buf[:n]
            if junk:
                self.counters["bad_frames"] += 1
                junk = False
            yield r, pdu
        if junk:
            self.counters["bad_frames"] += 1

    @staticmethod
    def _length_fits(buf, length: int) -> bool:
        """The MBAP length agrees with the PDU it announces (exception: 3; FC05/06/15/16: 6;
        reads and FC23: 3 + the byte count)."""
        fc = buf[7]
        if fc & 0x80:
            return length == 3
        if fc in (5, 6, 15, 16):
            return length == 6
        if fc in (1, 2, 3, 4, 23):
            return len(buf) < 9 or length == 3 + buf[8]
        return False

    def _known_tid(self, tid: int) -> bool:
        """A transaction id this driver sent recently (a late answer, not junk)."""
        return 0 < ((self._tid - tid) & 0xFFFF) < 4 * max(len(self.plan.cycle), 1) + 64

    @staticmethod
    def _pdu_fits(r: Request, pdu: bytes) -> bool:
        if not pdu:
            return False
        if pdu[0] == r.fc | 0x80:
            return len(pdu) == 2
        if pdu[0] != r.fc or len(pdu) != r.rsp_len:
            return False
        if r.fc in (1, 2, 3, 4, 23):
            return pdu[1] == r.rsp_len - 2
        return struct.unpack_from(">H", pdu, 1)[0] == r.waddress

    def _receive(self) -> None:
        reqs = self._reqs
        done = self._done
        chain = self._chain
        due = self._due
        for c in range(len(self.links)):
            self._fill(c)
            if not self.bufs[c]:
                continue
            creqs = self._conn_reqs[c]
            k = chain[c] - 1
            due[0] = creqs[k] if 0 <= k < len(creqs) else None
            for r, pdu in self._frames(c, due if due[0] is not None else ()):
                if r is None:
                    self.counters["stale"] += 1
                    continue
                k = reqs.index(r)
                if done[k]:
                    self.counters["stale"] += 1
                    continue
                self._answer(k, r, pdu)
                if done[k] and chain[c] < len(creqs):     # the next request of this connection
                    nxt = creqs[chain[c]]
                    chain[c] += 1
                    self._stamp(nxt)
                    self._send(nxt)
                    due[0] = nxt
        got = self._got
        needs = self._needs
        for i in range(len(got)):
            if got[i]:
                continue
            ok = True
            for k in needs[i]:
                if done[k] != 1:
                    ok = False
                    break
            if ok:
                raw = registers_to_value(self._ax[i].position, self._pos_words[i])
                self._accept(i, self.seq, raw, self._fault_raw[i])

    def _answer(self, k: int, r: Request, pdu: bytes) -> None:
        """Decode request k's answer into the axes' slots (``done[k]``: 1 ok, 2 exception)."""
        if pdu[0] & 0x80:
            self._done[k] = 2
            code = pdu[1]
            self.exception_counts[code] = self.exception_counts.get(code, 0) + 1
            self._accept_error(self.seq if self.options.transport == "tcp" else None,
                               f"exception {exception_text(code)} to {r.describe()}")
            for i in r.axes:
                self.last_exception[i] = f"exception {exception_text(code)} to {r.describe()}"
            return
        if not r.slots_r:
            self._done[k] = 1
            return
        if r.fc in (3, 4, 23) and self.options.transport == "rtu":
            for off, s in r.slots_r:     # RTU: a sequence echo that is not this cycle's: a late answer
                if s[0] == "echo" and not self._query and (pdu[2 + 2 * off] << 8 | pdu[3 + 2 * off]) != \
                        self.seq & 0xFFFF:
                    self.counters["stale"] += 1
                    return
        self._done[k] = 1
        if r.fc in (3, 4, 23):
            for off, s in r.slots_r:
                word = pdu[2 + 2 * off] << 8 | pdu[3 + 2 * off]
                kind = s[0]
                if kind == "position":
                    self._pos_words[s[1]][s[2]] = word
                elif kind == "fault":
                    for i in s[1]:
                        b = self._ax[i].fault
                        self._fault_raw[i] = bool(word >> b.bit & 1) == (b.active == "high")
        else:
            for off, s in r.slots_r:
                bit = bool(pdu[2 + off // 8] >> (off % 8) & 1)
                if s[0] == "fault":
                    for i in s[1]:
                        self._fault_raw[i] = bit == (self._ax[i].fault.active == "high")

    # --- reports
    def reset_fault(self, i: int) -> bool:
        """The operator's fault reset of axis i: a pulse of its ``fault_reset`` bit
        (:class:`~motorctl_drivers.split_phase.ResetPulses`: one cycle in EVERY, at most TRIES)
        while the axis is disabled and the device's fault bit is active; never pulsed otherwise.
        False when the map has no ``fault_reset``."""
        if self._ax[i].fault_reset is None:
            return False
        self._pulses.request(i)
        return True

    def fault_reason(self, i: int) -> str:
        """The last exception that hit axis i's requests (code and meaning) while its exchange
        is still failing (``read_error``), '' otherwise: an exception minutes before a fault of
        another kind is not its reason (the history is in ``describe()["fault_reasons"]``)."""
        if self.read_error[i] and self.last_exception[i]:
            return self.last_exception[i]
        f = self._ax[i].fault
        if self.amp_fault[i] and f is not None:
            return f"the device's fault bit ({f.table} {f.address} bit {f.bit}) is active"
        return ""

    def budget(self, rate_hz: float) -> BusBudget:
        """TCP: one round trip per request of the cycle (``round_trip_s``, or measured: the
        requests of a connection go one after another). RTU: characters and gaps of every
        request and answer at ``baudrate`` (``bits_per_char`` from bytesize, parity, stop bits;
        ``gap_chars`` silent interval per frame) plus ``device_latency_s`` per request."""
        o = self.options
        reqs = self.plan.cycle
        rt, source = self.budget_round_trip()
        names = ", ".join(r.describe() for r in reqs)
        if o.transport == "tcp":
            what = f"Modbus TCP, {len(reqs)} request(s) per cycle ({names})"
            fits = ("fewer requests per cycle (one contiguous block per device, a device with FC23), "
                    "or CAN / serial for a faster loop")
            return make_budget(rate_hz, (len(reqs) - 1) * rt, rt, o.max_bus_load, what, fits, source)
        chars = 0
        for r in reqs:
            req = 1 + len(r.frame) - r.pdu_off       # address + PDU + CRC (the frame holds them)
            chars += req + 1 + r.rsp_len + 2 + 2 * o.gap_chars
        char_s = o.bits_per_char / o.baudrate
        wire = chars * char_s + len(reqs) * o.device_latency_s
        what = (f"Modbus RTU {o.baudrate} Bd {o.bytesize}{o.parity}{o.stopbits}, {len(reqs)} request(s) "
                f"({names}), {chars:g} chars with {o.gap_chars:g}-char gaps at {o.bits_per_char} bits/char + "
                f"{o.device_latency_s * 1e6:.0f} us device latency per request")
        room = o.max_bus_load / rate_hz - len(reqs) * o.device_latency_s - rt
        need = chars * o.bits_per_char / room if room > 0 else math.inf
        fits = (f"raise driver.baudrate to {math.ceil(need)} Bd" if need < 1e6 else
                "use Modbus TCP, CAN or serial (no RTU baud rate carries it)")
        return make_budget(rate_hz, wire, rt, o.max_bus_load, what, fits, source)

    def describe(self) -> dict:
        d = super().describe()
        o = self.options
        d.update(transport=f"modbus-{o.transport}",
                 endpoint=(", ".join(f"{h}:{p} unit {u}" for h, p, u in self.plan.devices) if o.transport == "tcp"
                           else f"{o.serial_port} {o.baudrate} {o.bytesize}{o.parity}{o.stopbits}"),
                 requests=self.plan.summary(), fc23=dict(self.fc23_probe) or o.fc23,
                 watchdog=None if o.watchdog is None else o.watchdog.model_dump(),
                 exceptions={exception_text(c): n for c, n in sorted(self.exception_counts.items())},
                 fault_reasons={a: self.last_exception[i] for i, a in enumerate(self.axis_names)
                                if self.last_exception[i]})
        return d


# --------------------------------------------------------------------------- links
_MBAP = struct.Struct(">HHHB")


class _Sock:
    """A non-blocking TCP connection to one device (``recv`` returns b'' when nothing is there;
    a closed connection raises ConnectionError)."""

    def __init__(self, sock):
        self.sock = sock

    def fileno(self) -> int:
        return self.sock.fileno()

    def send(self, frame) -> None:
        if self.sock.send(frame) != len(frame):
            raise OSError("short send")

    def recv(self) -> bytes:
        try:
            data = self.sock.recv(4096)
        except BlockingIOError:
            return b""
        if not data:
            raise ConnectionError("modbus peer closed the connection")
        return data

    def close(self) -> None:
        self.sock.close()


class _Serial:
    """The RTU serial port (pyserial), non-blocking."""

    def __init__(self, port):
        self.port = port

    def fileno(self) -> int:
        return self.port.fileno()

    def send(self, frame) -> None:
        self.port.write(frame)

    def recv(self) -> bytes:
        return self.port.read(4096)

    def close(self) -> None:
        self.port.close()


def _open_serial(o: ModbusOptions) -> _Serial:
    """The RTU port with ``o``'s line settings.

    Raises:
        OSError: the port is missing, not permitted, or refuses a setting (one line)."""
    import serial
    kw = dict(baudrate=o.baudrate, parity={"N": serial.PARITY_NONE, "E": serial.PARITY_EVEN,
                                           "O": serial.PARITY_ODD}[o.parity],
              stopbits={1: serial.STOPBITS_ONE, 2: serial.STOPBITS_TWO}[o.stopbits],
              bytesize={7: serial.SEVENBITS, 8: serial.EIGHTBITS}[o.bytesize], timeout=0, write_timeout=0)
    try:
        if "://" in o.serial_port:
            port = serial.serial_for_url(o.serial_port, **kw)
        else:
            port = serial.Serial(o.serial_port, **kw)
    except (serial.SerialException, OSError, ValueError) as exc:
        raise open_error("Modbus RTU port", f"{o.serial_port} ({o.baudrate} {o.bytesize}{o.parity}{o.stopbits})",
                         exc) from None
    return _Serial(port)
