"""Modbus driver (pymodbus framers and PDUs): Modbus TCP or RTU, register map from the YAML.

The command registers of every axis (voltage, control word) and the optional sequence
register must form one contiguous block and the feedback registers (counts, status, sequence
echo) lie within 125 registers, so that one **Read/Write Multiple Registers (FC23)** request per
cycle carries the whole group: the write is applied first, then the read (Modbus Application
Protocol v1.1b3 §6.17), so its answer is the position one period after the command. It is sent
in ``write()`` and collected in the next ``read()`` (split phase, non-blocking sockets: the
pymodbus client would block for the answer). ``configure()`` reads the feedback block with
FC03 (no step). An exception response counts as an error answer.

Encoding (pymodbus ``FramerSocket`` / ``FramerRTU``, whose CRC is the Modbus CRC-16,
polynomial 0xA001 reflected, initial 0xFFFF): the voltage register is a signed 16-bit value,
±32767 = ±``voltage_full_scale_V``; the encoder count is a 32-bit counter in two registers,
``word_order: big`` (high word first, the Modbus convention) or ``little``; it wraps and is
unwrapped here. Stale answers are recognised by the MBAP transaction id (TCP) or, where the map
has them, by ``sequence_register`` / ``sequence_echo_register`` (RTU).

YAML (``driver:``)::

    type: modbus
    transport: tcp | rtu
    host: 127.0.0.1          # tcp
    port: 502                # tcp
    serial_port: /dev/ttyUSB0 | socket://127.0.0.1:5021 | /tmp/pty-link   # rtu
    baudrate: 115200         # rtu
    bits_per_char: 11        # rtu: 8E1 = start + 8 + parity + stop
    gap_chars: 3.5           # rtu: silent interval between frames (spec: 1.75 ms above 19200 Bd)
    device_latency_s: 0.0005 # rtu: the device's answer time
    unit_id: 1
    sequence_register: 4         # optional: written with the cycle counter
    sequence_echo_register: 106  # optional: the device's echo of it
    timeout_s, wait, round_trip_s (tcp: the measured request/answer time, default 400 us),
    max_bus_load: see split_phase.CommonOptions

per axis (``axes.NAME.driver``): voltage_register, control_register + enable_bit,
counts_register (+1), word_order, status_register + fault_bit, voltage_full_scale_V,
encoder_m_per_count. The voltage limit of an axis (its ``voltage_out`` interface) is its
``voltage_full_scale_V``.
"""

from __future__ import annotations

import math
import socket
from typing import Annotated, Literal

import numpy as np
from pydantic import Field

from motorctl.driver import BusBudget
from motorctl.schema import StrictModel
from motorctl_drivers.split_phase import (CommonOptions, EncoderUnwrap, SplitPhaseDriver, make_budget,
                                          to_unsigned, volts_to_counts)

Reg = Annotated[int, Field(ge=0, le=0xFFFF)]
FC23_MAX_READ, FC23_MAX_WRITE = 125, 121


class ModbusOptions(CommonOptions):
    """YAML ``driver:`` of the Modbus driver (see the module docstring)."""

    transport: Literal["tcp", "rtu"] = "tcp"
    host: str = "127.0.0.1"
    port: Annotated[int, Field(ge=1, le=65535)] = 502
    serial_port: str = ""
    baudrate: Annotated[int, Field(gt=0)] = 115200
    bits_per_char: Annotated[int, Field(ge=10, le=12)] = 11
    gap_chars: Annotated[float, Field(ge=0)] = 3.5
    device_latency_s: Annotated[float, Field(ge=0)] = 0.0005
    unit_id: Annotated[int, Field(ge=0, le=247)] = 1
    sequence_register: Reg | None = None
    sequence_echo_register: Reg | None = None
    round_trip_s: Annotated[float, Field(ge=0)] = 400e-6


class ModbusAxisOptions(StrictModel):
    """YAML ``axes.NAME.driver`` of the Modbus driver: where this axis lives in the map."""

    voltage_register: Reg
    control_register: Reg
    enable_bit: Annotated[int, Field(ge=0, le=15)] = 0
    counts_register: Reg
    word_order: Literal["big", "little"] = "big"
    status_register: Reg
    fault_bit: Annotated[int, Field(ge=0, le=15)] = 0
    voltage_full_scale_V: Annotated[float, Field(gt=0)] = 10.0
    encoder_m_per_count: Annotated[float, Field(gt=0)] = 0.5e-6


def split_counts(counts: int, word_order: str) -> tuple[int, int]:
    """32-bit encoder count (wrapped) → two registers in ``word_order``."""
    c = to_unsigned(counts, 32)
    hi, lo = c >> 16, c & 0xFFFF
    return (hi, lo) if word_order == "big" else (lo, hi)


def join_counts(r0: int, r1: int, word_order: str) -> int:
    """Two registers in ``word_order`` → the unsigned 32-bit counter."""
    return (r0 << 16 | r1) if word_order == "big" else (r1 << 16 | r0)


def decode_frames(framer, buf: bytearray):
    """Cut the complete ADUs out of ``buf`` (consumed in place) with the pymodbus framer's
    ``decode`` (MBAP or RTU with CRC check) and decode each PDU. Yields the PDU (with
    ``dev_id`` and ``transaction_id`` set from the ADU), or None for a frame that failed its
    CRC or does not decode. Used by the driver and by its emulated device."""
    while buf:
        used, dev_id, tid, frame = framer.decode(bytes(buf))
        if used == 0:
            return
        del buf[:used]
        pdu = framer.decoder.decode(frame) if frame else None
        if pdu is not None:
            pdu.dev_id, pdu.transaction_id = dev_id, tid
        yield pdu


class RegisterPlan:
    """The FC23 request a cycle needs: write block (address, per-register source) and read
    block (address, count) over the whole group.

    Raises:
        ValueError: the command registers are not one contiguous block, overlap, or a block
            exceeds FC23's limits (121 written, 125 read registers).
    """

    def __init__(self, names, axis_options, options: ModbusOptions):
        writes: dict[int, tuple[str, int]] = {}
        for i, a in enumerate(names):
            o = axis_options[a]
            for reg, what in ((o.voltage_register, "voltage"), (o.control_register, "control")):
                if reg in writes:
                    raise ValueError(f"register {reg} is used twice ({names[writes[reg][1]]} and {a})")
                writes[reg] = (what, i)
        if options.sequence_register is not None:
            if options.sequence_register in writes:
                raise ValueError(f"sequence_register {options.sequence_register} is also an axis register")
            writes[options.sequence_register] = ("sequence", -1)
        lo, hi = min(writes), max(writes)
        if hi - lo + 1 != len(writes):
            gaps = sorted(set(range(lo, hi + 1)) - set(writes))
            raise ValueError(f"command registers {sorted(writes)} are not contiguous (gaps at {gaps}): "
                             f"make them one block so one FC23 request carries the cycle")
        if len(writes) > FC23_MAX_WRITE:
            raise ValueError(f"{len(writes)} command registers exceed FC23's {FC23_MAX_WRITE}")
        self.write_address = lo
        self.write_slots = [writes[r] for r in range(lo, hi + 1)]
        reads = []
        for a in names:
            o = axis_options[a]
            reads += [o.counts_register, o.counts_register + 1, o.status_register]
        if options.sequence_echo_register is not None:
            reads.append(options.sequence_echo_register)
        self.read_address = min(reads)
        self.read_count = max(reads) - self.read_address + 1
        if self.read_count > FC23_MAX_READ:
            raise ValueError(f"feedback registers span {self.read_count} registers, more than FC23's {FC23_MAX_READ}")


class ModbusDriver(SplitPhaseDriver):
    """The Modbus driver (TCP or RTU). See the module docstring."""

    Options = ModbusOptions
    AxisOptions = ModbusAxisOptions

    def __init__(self, options: ModbusOptions, axis_options: dict, period_s: float):
        super().__init__(options, axis_options, period_s)
        from pymodbus.framer import FramerRTU, FramerSocket
        from pymodbus.pdu import DecodePDU
        self.SEQ_MASK = 0xFFFF if options.transport == "tcp" else 0xFF
        self.plan_error = ""
        try:
            self.plan = RegisterPlan(self.axis_names, axis_options, options)
        except ValueError as exc:
            self.plan = None
            self.plan_error = str(exc)
        self._ax = [axis_options[a] for a in self.axis_names]
        self._unwrap = [EncoderUnwrap(32) for _ in self._ax]
        self._m_per_count = [o.encoder_m_per_count for o in self._ax]
        from pymodbus.pdu.register_message import ReadHoldingRegistersRequest, ReadWriteMultipleRegistersRequest
        self._fc03, self._fc23 = ReadHoldingRegistersRequest, ReadWriteMultipleRegistersRequest
        framer = FramerSocket if options.transport == "tcp" else FramerRTU
        self.framer = framer(DecodePDU(is_server=False))
        self.sock = None
        self.port = None
        self.buf = bytearray()
        self._regs = [0] * (len(self.plan.write_slots) if self.plan else 0)

    # --- link
    def _open_transport(self) -> None:
        """Open the TCP connection or the RTU serial port.

        Raises:
            ValueError: the register map needs more than one FC23 request (found at parse time).
            OSError: the link cannot be opened.
        """
        if self.plan is None:
            raise ValueError(f"modbus register map: {self.plan_error}")
        import logging   # a frame that does not decode is counted, not logged from inside the cycle
        logging.getLogger("pymodbus").setLevel(logging.ERROR)
        o = self.options
        if o.transport == "tcp":
            self.sock = socket.create_connection((o.host, o.port), timeout=2.0)
            self.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            self.sock.setblocking(False)
        else:
            import serial
            if "://" in o.serial_port:
                self.port = serial.serial_for_url(o.serial_port, baudrate=o.baudrate, timeout=0, write_timeout=0)
            else:
                self.port = serial.Serial(o.serial_port, baudrate=o.baudrate, parity="E", timeout=0,
                                          write_timeout=0)
        self.buf = bytearray()
        self._set_wait_fd(self.sock.fileno() if self.sock is not None else self.port.fileno())

    def _release_transport(self) -> None:
        sock, port = self.sock, self.port
        self.sock = self.port = None
        if sock is not None:
            sock.close()
        if port is not None:
            port.close()

    def _full_scale_V(self, axis: str) -> float:
        """``axes.NAME.driver.voltage_full_scale_V`` [V]: the voltage register's ±32767."""
        return float(self.axis_options[axis].voltage_full_scale_V)

    def _send(self, frame: bytes) -> None:
        if self.sock is not None:
            if self.sock.send(frame) != len(frame):
                raise OSError("short send")
        else:
            self.port.write(frame)

    def _recv(self) -> bytes:
        if self.sock is not None:
            try:
                data = self.sock.recv(4096)
            except BlockingIOError:
                return b""
            if not data:
                raise ConnectionError("modbus peer closed the connection")
            return data
        return self.port.read(4096)

    # --- cycle
    def _transmit_query(self, seq: int) -> None:
        p = self.plan
        req = self._fc03(address=p.read_address, count=p.read_count, dev_id=self.options.unit_id,
                         transaction_id=seq)
        self._send(self.framer.buildFrame(req))

    def _transmit(self, seq: int, u_V: np.ndarray, enable: np.ndarray) -> None:
        p = self.plan
        regs = self._regs
        ax = self._ax
        for k, (what, i) in enumerate(p.write_slots):
            if what == "voltage":
                regs[k] = to_unsigned(volts_to_counts(float(u_V[i]), ax[i].voltage_full_scale_V, 16)
                                      if enable[i] else 0, 16)
            elif what == "control":
                regs[k] = (1 << ax[i].enable_bit) if enable[i] else 0
            else:
                regs[k] = seq & 0xFFFF
        req = self._fc23(read_address=p.read_address, read_count=p.read_count, write_address=p.write_address,
                         write_registers=regs, dev_id=self.options.unit_id, transaction_id=seq)
        self._send(self.framer.buildFrame(req))

    def _receive(self) -> None:
        data = self._recv()
        if not data:
            return
        buf = self.buf
        buf += data
        for pdu in decode_frames(self.framer, buf):
            if pdu is None:
                self.counters["bad_frames"] += 1
            else:
                self._handle(pdu)

    def _handle(self, pdu) -> None:
        o = self.options
        if o.transport == "tcp":
            seq = pdu.transaction_id
        elif o.sequence_echo_register is not None and not pdu.isError():
            seq = pdu.registers[o.sequence_echo_register - self.plan.read_address] & self.SEQ_MASK
        else:
            seq = self.seq
        if pdu.isError():
            self._accept_error(seq)
            return
        regs = pdu.registers
        base = self.plan.read_address
        if len(regs) < self.plan.read_count:
            self.counters["bad_frames"] += 1
            return
        for i, a in enumerate(self._ax):
            c = a.counts_register - base
            raw = join_counts(regs[c], regs[c + 1], a.word_order)
            fault = bool(regs[a.status_register - base] >> a.fault_bit & 1)
            self._accept(i, seq, raw, fault)

    # --- budget
    def budget(self, rate_hz: float) -> BusBudget:
        """TCP: the measured request/answer time (``round_trip_s``; the wire, a few minimum-size
        Ethernet frames, is negligible). RTU: characters and gaps of the FC23 request and answer
        at ``baudrate`` (``bits_per_char`` per byte, ``gap_chars`` silent interval per frame)
        plus ``device_latency_s``."""
        o = self.options
        if self.plan is None:
            return BusBudget(0.0, 0.0, f"the register map needs more than one request: {self.plan_error}",
                             "fix the register map")
        p = self.plan
        if o.transport == "tcp":
            what = (f"Modbus TCP, 1 FC23 request per cycle ({len(p.write_slots)} registers written, "
                    f"{p.read_count} read) to {o.host}:{o.port}")
            fits = "use the CAN or serial driver for a faster loop (a Modbus TCP device answers in 0.2-5 ms)"
            return make_budget(rate_hz, 0.0, o.round_trip_s, o.max_bus_load, what, fits)
        req = 1 + 1 + 9 + 2 * len(p.write_slots) + 2        # unit, fc, header, data, CRC
        rsp = 1 + 1 + 1 + 2 * p.read_count + 2
        char_s = o.bits_per_char / o.baudrate
        wire = (req + rsp + 2 * o.gap_chars) * char_s + o.device_latency_s
        what = (f"Modbus RTU {o.baudrate} Bd, FC23 {req} B request + {rsp} B answer, "
                f"{o.gap_chars:g}-char gaps at {o.bits_per_char} bits/char + "
                f"{o.device_latency_s * 1e6:.0f} us device latency")
        room = o.max_bus_load / rate_hz - o.device_latency_s - o.round_trip_s
        need = (req + rsp + 2 * o.gap_chars) * o.bits_per_char / room if room > 0 else math.inf
        fits = (f"raise driver.baudrate to {math.ceil(need)} Bd" if need < 1e6 else
                "use Modbus TCP, CAN or serial (no RTU baud rate carries it)")
        return make_budget(rate_hz, wire, o.round_trip_s, o.max_bus_load, what, fits)

    def describe(self) -> dict:
        d = super().describe()
        o = self.options
        d.update(transport=f"modbus-{o.transport}",
                 endpoint=f"{o.host}:{o.port}" if o.transport == "tcp" else o.serial_port,
                 fc23=None if self.plan is None else {
                     "write": [self.plan.write_address, len(self.plan.write_slots)],
                     "read": [self.plan.read_address, self.plan.read_count]})
        return d
