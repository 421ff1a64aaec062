"""Modbus driver (pymodbus framers and PDUs): Modbus TCP or RTU, register map from the YAML.

The command registers of every axis (voltage, control word) and the optional sequence
register must form one contiguous block and the feedback registers (counts, status, sequence
echo) lie within 125 registers, so that one **Read/Write Multiple Registers (FC23)** request per
cycle carries the whole group: the write is applied first, then the read (Modbus Application
Protocol v1.1b3 §6.17), so its answer is the position one period after the command. It is sent
in ``write()`` and collected in the next ``read()`` (split phase, non-blocking sockets: the
pymodbus client would block for the answer). ``open()`` reads the feedback block with FC03
(no step).

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
    timeout_s, round_trip_s (tcp: the measured request/answer time, default 400 us),
    max_bus_load, emulator: see proto_common.CommonOptions

per axis (``axes.NAME.driver``): voltage_register, control_register + enable_bit,
counts_register (+1), word_order, status_register + fault_bit, voltage_full_scale_V,
encoder_m_per_count, plant (emulator only).
"""

from __future__ import annotations

import math
import socket
import time
from typing import Annotated, Literal

import numpy as np
from pydantic import Field

from motorctl.driver import BusBudget
from motorctl.schema import StrictModel
from motorctl_drivers.proto_common import (CommonOptions, EncoderUnwrap, PlantBank, SplitPhaseDriver,
                                           StreamEndpoint, counts_to_volts, make_budget, serve_forever,
                                           to_signed, to_unsigned, volts_to_counts)
from motorctl_drivers.sim import SimAxisOptions

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
    plant: SimAxisOptions | None = None


def split_counts(counts: int, word_order: str) -> tuple[int, int]:
    """32-bit encoder count (wrapped) → two registers in ``word_order``."""
    c = to_unsigned(counts, 32)
    hi, lo = c >> 16, c & 0xFFFF
    return (hi, lo) if word_order == "big" else (lo, hi)


def join_counts(r0: int, r1: int, word_order: str) -> int:
    """Two registers in ``word_order`` → the unsigned 32-bit counter."""
    return (r0 << 16 | r1) if word_order == "big" else (r1 << 16 | r0)


def _frames(framer, buf: bytearray):
    """Cut the complete ADUs out of ``buf`` (consumed in place) with the pymodbus framer's
    ``decode`` (MBAP or RTU with CRC check) and decode each PDU. Yields the PDU, or None for a
    frame that failed its CRC or does not decode."""
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
    def _configure(self) -> None:
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
        self.connected = True
        self._first_reading()

    def _close(self) -> None:
        if self.sock is None and self.port is None:
            return
        try:
            n = len(self.axis_names)
            self._transmit((self.seq + 1) & self.SEQ_MASK, np.zeros(n), np.zeros(n, dtype=bool))
            time.sleep(0.002)
        except Exception:  # noqa: BLE001  (closing anyway)
            pass
        if self.sock is not None:
            self.sock.close()
        if self.port is not None:
            self.port.close()
        self.sock = self.port = None
        self.connected = False

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
        for pdu in _frames(self.framer, buf):
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
            if seq == self.seq:
                self.counters["exceptions"] += 1
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


# --------------------------------------------------------------------------- device side
class ModbusDevice:
    """The emulated Modbus device (``motorctl emulate --transport modbus``).

    Holding registers as in the map. FC03/FC04 read; FC06, FC16 and FC23 write (FC23 then
    reads). A write that covers an axis's voltage register is a command for that axis: the
    plant steps one period and the feedback registers are updated before any read. Faults:
    drop, late, corrupt (bad CRC on RTU, a broken MBAP length on TCP), stale (the previous
    answer again), exception (exception code 0x04, device failure; the command is not applied),
    disconnect (TCP: close the connection), bus_off (as drop).
    """

    def __init__(self, options: ModbusOptions, axis_options: dict, bank: PlantBank):
        from pymodbus.framer import FramerRTU, FramerSocket
        from pymodbus.pdu import DecodePDU
        self.o = options
        self.bank = bank
        self.ax = [axis_options[a] for a in bank.names]
        RegisterPlan(bank.names, axis_options, options)   # the same checks as the driver
        self.regs = [0] * 0x10000
        self.by_voltage = {a.voltage_register: i for i, a in enumerate(self.ax)}
        if options.transport == "tcp":
            self.framer = FramerSocket(DecodePDU(is_server=True))
            url = f"tcp://{options.host}:{options.port}"
        else:
            self.framer = FramerRTU(DecodePDU(is_server=True))
            url = options.serial_port
        self.ep = StreamEndpoint(url)
        self.buf = bytearray()
        self.last = None
        self._update_feedback()

    def _update_feedback(self) -> None:
        b, r = self.bank, self.regs
        for i, a in enumerate(self.ax):
            r0, r1 = split_counts(b.counts(i, a.encoder_m_per_count), a.word_order)
            r[a.counts_register], r[a.counts_register + 1] = r0, r1
            st = r[a.status_register] & ~(1 << a.fault_bit)
            r[a.status_register] = st | ((1 << a.fault_bit) if b.amp_fault[i] else 0)
        if self.o.sequence_echo_register is not None and self.o.sequence_register is not None:
            r[self.o.sequence_echo_register] = r[self.o.sequence_register]

    def _write(self, address: int, values) -> list[int]:
        """Store registers; return the axes whose voltage register was written."""
        hit = []
        for k, v in enumerate(values):
            self.regs[address + k] = v & 0xFFFF
            i = self.by_voltage.get(address + k)
            if i is not None:
                hit.append(i)
        return hit

    def _apply(self, axes) -> None:
        b = self.bank
        for i in axes:
            a = self.ax[i]
            u = counts_to_volts(to_signed(self.regs[a.voltage_register], 16), a.voltage_full_scale_V, 16)
            b.command(i, u, bool(self.regs[a.control_register] >> a.enable_bit & 1))

    def _respond(self, req):
        from pymodbus.pdu import ExceptionResponse
        from pymodbus.pdu.register_message import (ReadHoldingRegistersResponse, ReadInputRegistersResponse,
                                                   ReadWriteMultipleRegistersResponse,
                                                   WriteMultipleRegistersResponse, WriteSingleRegisterResponse)
        fc = req.function_code
        kw = dict(dev_id=req.dev_id, transaction_id=req.transaction_id)
        if fc in (3, 4):
            self._update_feedback()
            cls = ReadHoldingRegistersResponse if fc == 3 else ReadInputRegistersResponse
            return cls(registers=self.regs[req.address:req.address + req.count], **kw), None
        if fc in (6, 16, 23):
            if fc == 23:
                addr, values = req.write_address, req.write_registers
            elif fc == 16:
                addr, values = req.address, req.registers
            else:
                addr, values = req.address, req.registers[:1]
            axes = [self.by_voltage[r] for r in range(addr, addr + len(values)) if r in self.by_voltage]
            fault = self.bank.next_fault(axes) if axes else None
            if fault == "exception":
                return ExceptionResponse(fc, 0x04, device_id=req.dev_id, transaction=req.transaction_id), None
            if fault == "disconnect":
                return None, "disconnect"
            self._apply(self._write(addr, values))
            self._update_feedback()
            if fc == 23:
                rsp = ReadWriteMultipleRegistersResponse(
                    registers=self.regs[req.read_address:req.read_address + req.read_count], **kw)
            elif fc == 16:
                rsp = WriteMultipleRegistersResponse(address=addr, count=len(values), **kw)
            else:
                rsp = WriteSingleRegisterResponse(address=addr, registers=list(values), **kw)
            return rsp, fault
        return ExceptionResponse(fc, 0x01, device_id=req.dev_id, transaction=req.transaction_id), None

    def poll(self, timeout_s: float) -> None:
        data = self.ep.wait(timeout_s)
        if not data:
            return
        self.buf += data
        for req in _frames(self.framer, self.buf):
            if req is None:
                continue
            if self.o.transport == "rtu" and req.dev_id not in (0, self.o.unit_id):
                continue
            rsp, fault = self._respond(req)
            if fault == "disconnect":
                self.ep.disconnect()
                self.buf.clear()
                return
            frame = self.framer.buildFrame(rsp)
            if fault in ("drop", "bus_off"):
                pass
            elif fault == "stale" and self.last is not None:
                self.ep.send(self.last)
            elif fault == "corrupt":
                bad = bytearray(frame)
                if self.o.transport == "rtu":
                    bad[-1] ^= 0xFF
                else:
                    bad[8] = 0xFF        # byte count beyond the frame: the PDU does not decode
                self.ep.send(bytes(bad))
            else:
                if fault == "late":
                    time.sleep(self.bank.opts.late_s)
                self.ep.send(frame)
            if req.function_code in (6, 16, 23):
                self.last = frame

    def serve(self, stop=None, duration_s=None) -> None:
        try:
            serve_forever(self.poll, self.bank, stop, duration_s)
        finally:
            self.ep.close()
