"""The emulated Modbus device (``motorctl emulate --transport modbus``).

Register map and value codecs are the driver's (:mod:`motorctl_drivers.modbus`); function codes
as in the Modbus Application Protocol V1.1b3 (§6.1 FC01, §6.2 FC02, §6.3 FC03, §6.4 FC04, §6.5
FC05, §6.6 FC06, §6.11 FC15, §6.12 FC16, §6.17 FC23; exception codes §7); framing: MBAP
(Modbus Messaging on TCP/IP V1.0b) or RTU with the CRC of Modbus over Serial Line V1.02.
"""

from __future__ import annotations

import struct

from motorctl_drivers.modbus import (
    ModbusOptions,
    RegisterPlan,
    crc16,
    registers_to_value,
    value_to_registers,
)
from motorctl_emulators.device import Device, LateAnswers
from motorctl_emulators.plant_bank import PlantBank
from motorctl_emulators.stream import StreamEndpoint

_MBAP = struct.Struct(">HHHB")


class ModbusDevice(Device):
    """Holding and input registers, coils and discrete inputs as in the map (every unit of the
    map answers). FC01-06, 15, 16 and 23; others get exception 01. A write to an axis's voltage
    register is that axis's command; it is applied (the plant steps one period, the position
    and fault fields are updated) when the axis's position is next read, so the answer carries
    the position one period after the command, as with FC23 (write, then read). Faults, counted
    per command: drop, late (the answer after ``late_s`` and never before the next request to
    that unit: :class:`~motorctl_emulators.device.LateAnswers`), corrupt (bad CRC on RTU, a
    broken MBAP length on TCP), stale (the
    previous answer again), exception (exception 0x04, server device failure; the command is not
    applied), disconnect (TCP: close the connection), bus_off (as drop). With ``fc23: no`` in
    the driver config the device has no FC23 (exception 01). An axis whose map has a
    ``fault_reset`` bit keeps a latched fault (its watchdog's, an injected one) until that bit's
    rising edge with the amplifier disabled (:class:`PlantBank`'s reset input), across hosts;
    one without clears it on a command with the amplifier disabled.

    Raises:
        ValueError: the register map cannot be served (the driver's checks).
        OSError: the endpoint cannot be opened.
    """

    def __init__(self, options: ModbusOptions, axis_options: dict, bank: PlantBank):
        super().__init__(options, axis_options, bank)
        names = bank.names
        self.ax = [axis_options[a] for a in names]
        self.plan = RegisterPlan(names, axis_options, options)        # the same checks as the driver
        self.units = {u for _h, _p, u in self.plan.devices}
        self.tables = {"holding": [0] * 0x10000, "input": [0] * 0x10000, "coil": [False] * 0x10000,
                       "discrete": [False] * 0x10000}
        self.has_fc23 = options.fc23 != "no"
        self.by_voltage = {}
        for i, a in enumerate(self.ax):
            for k in range(a.voltage.nregs):
                self.by_voltage[(self.plan.devices[self.plan.dev_of[i]][2], a.voltage.address + k)] = i
        self.pending = [None] * len(self.ax)      # the fault drawn for an axis's unapplied command
        for i, a in enumerate(self.ax):
            bank.reset_input[i] = a.fault_reset is not None
        self.late = LateAnswers(bank)             # keyed by the unit
        self.tcp = options.transport == "tcp"
        self.ep = StreamEndpoint(f"tcp://{options.host}:{options.port}" if self.tcp else options.serial_port)
        self.buf = bytearray()
        self.last = None
        # the master's time: the sequence register (where the map has one) numbers the cycles
        self.clock = bank.master_time(1 << 16 if self.tcp else 1 << 8)
        self._periods = 1
        for i in range(len(self.ax)):
            self._feedback(i)

    # ------------------------------------------------------------------ the axes
    def _bit(self, b, value: bool | None = None):
        t = self.tables[b.table]
        if b.table in ("coil", "discrete"):
            if value is None:
                return t[b.address] == (b.active == "high")
            t[b.address] = value == (b.active == "high")
            return None
        if value is None:
            return bool(t[b.address] >> b.bit & 1) == (b.active == "high")
        on = value == (b.active == "high")
        t[b.address] = (t[b.address] & ~(1 << b.bit) & 0xFFFF) | ((1 << b.bit) if on else 0)
        return None

    def _feedback(self, i: int) -> None:
        a, b = self.ax[i], self.bank
        pos = b.plants[i].measured()
        raw = (pos - a.position.offset) / a.position.scale
        raw = raw if a.position.type == "float32" else int(round(raw))
        t = self.tables[a.position.table]
        for k, w in enumerate(value_to_registers(a.position, raw)):
            t[a.position.address + k] = w
        if a.fault is not None:
            self._bit(a.fault, b.amp_fault[i])

    def _apply(self, i: int) -> None:
        a = self.ax[i]
        t = self.tables["holding"]
        raw = registers_to_value(a.voltage, [t[a.voltage.address + k] for k in range(a.voltage.nregs)])
        if a.voltage.type in ("int16", "int32"):
            bits = 16 * a.voltage.nregs
            raw = raw - (1 << bits) if raw >= 1 << (bits - 1) else raw
        u = raw * a.voltage_scale() + a.voltage.offset
        self.bank.command(i, u, self._bit(a.enable), self._periods,
                          reset=a.fault_reset is not None and bool(self._bit(a.fault_reset)))
        self._feedback(i)

    def _step_if_read(self, unit: int, table: str, address: int, count: int) -> None:
        """Apply the pending command of every axis whose position lies in what is read."""
        for i, a in enumerate(self.ax):
            if self.pending[i] is not None and a.position.table == table and \
                    self.plan.devices[self.plan.dev_of[i]][2] == unit and \
                    address <= a.position.address < address + count:
                self.pending[i] = None
                self._apply(i)

    # ------------------------------------------------------------------ requests
    def _request_len(self, buf) -> int:
        """RTU: the length of the request at the start of ``buf`` (0: not complete yet)."""
        if len(buf) < 2:
            return 0
        fc = buf[1]
        if fc in (1, 2, 3, 4, 5, 6):
            return 8
        if fc in (15, 16):
            return 9 + buf[6] if len(buf) >= 7 else 0
        if fc == 23:
            return 13 + buf[10] if len(buf) >= 11 else 0
        return 4

    def _handle(self, unit: int, pdu: bytes):
        """(answer PDU, fault) for request ``pdu`` of ``unit``."""
        fc = pdu[0]
        b = self.bank
        t = self.tables
        try:
            if fc in (1, 2, 3, 4):
                addr, count = struct.unpack_from(">HH", pdu, 1)
                table = {1: "coil", 2: "discrete", 3: "holding", 4: "input"}[fc]
                self._step_if_read(unit, table, addr, count)
                for i in range(len(self.ax)):     # faults (e.g. the watchdog) show in every answer
                    self._feedback(i)
                if fc in (1, 2):
                    bits = t[table][addr:addr + count]
                    data = bytearray((count + 7) // 8)
                    for k, v in enumerate(bits):
                        if v:
                            data[k // 8] |= 1 << (k % 8)
                    return bytes((fc, len(data))) + bytes(data), None
                regs = t[table][addr:addr + count]
                return bytes((fc, 2 * count)) + b"".join(struct.pack(">H", r) for r in regs), None
            if fc in (5, 6, 15, 16, 23):
                if fc == 23 and not self.has_fc23:
                    return bytes((0x80 | fc, 1)), None
                if fc == 5:
                    addr, val = struct.unpack_from(">HH", pdu, 1)
                    writes = [("coil", addr, val == 0xFF00)]
                elif fc == 6:
                    addr, val = struct.unpack_from(">HH", pdu, 1)
                    writes = [("holding", addr, val)]
                elif fc == 15:
                    addr, count = struct.unpack_from(">HH", pdu, 1)
                    writes = [("coil", addr + k, bool(pdu[6 + k // 8] >> (k % 8) & 1)) for k in range(count)]
                elif fc == 16:
                    addr, count = struct.unpack_from(">HH", pdu, 1)
                    writes = [("holding", addr + k, struct.unpack_from(">H", pdu, 6 + 2 * k)[0]) for k in range(count)]
                else:
                    raddr, rcount, addr, count = struct.unpack_from(">HHHH", pdu, 1)
                    writes = [("holding", addr + k, struct.unpack_from(">H", pdu, 10 + 2 * k)[0]) for k in range(count)]
                axes = sorted({self.by_voltage[(unit, a)] for tb, a, _ in writes
                               if tb == "holding" and (unit, a) in self.by_voltage})
                fault = b.next_fault(axes) if axes else None
                if fault == "exception":
                    return bytes((0x80 | fc, 4)), None
                if fault == "disconnect":
                    return None, "disconnect"
                o = self.options
                for tb, a, v in writes:
                    t[tb][a] = v
                    if tb == "holding" and a == o.sequence_register:
                        self._periods = self.clock.periods(v)
                if o.sequence_register is not None and o.sequence_echo_register is not None:
                    t["holding"][o.sequence_echo_register] = t["holding"][o.sequence_register]
                for i in axes:
                    self.pending[i] = fault or "ok"
                if fc == 23:
                    self._step_if_read(unit, "holding", raddr, rcount)
                    for i in range(len(self.ax)):
                        self._feedback(i)
                    regs = t["holding"][raddr:raddr + rcount]
                    rsp = bytes((fc, 2 * rcount)) + b"".join(struct.pack(">H", r) for r in regs)
                elif fc in (5, 6):
                    rsp = pdu[:5]
                else:
                    rsp = pdu[:5]
                return rsp, fault
            return bytes((0x80 | fc, 1)), None
        except (struct.error, IndexError):
            return bytes((0x80 | fc, 3)), None

    def _frame(self, tid: int, unit: int, pdu: bytes) -> bytes:
        if self.tcp:
            return _MBAP.pack(tid, 0, len(pdu) + 1, unit) + pdu
        body = bytes((unit,)) + pdu
        c = crc16(body)
        return body + bytes((c & 0xFF, c >> 8))

    def _requests(self):
        buf = self.buf
        while buf:
            if self.tcp:
                if len(buf) < 8:
                    return
                tid, proto, length, unit = _MBAP.unpack_from(buf, 0)
                if len(buf) < 6 + length:
                    return
                pdu = bytes(buf[7:6 + length])
                del buf[:6 + length]
                yield tid, unit, pdu
            else:
                n = self._request_len(buf)
                if n == 0 or len(buf) < n:
                    return
                frame = bytes(buf[:n])
                if crc16(frame[:-2]) != frame[-2] | frame[-1] << 8:
                    del buf[0]               # resync: not a frame that starts here
                    continue
                del buf[:n]
                yield 0, frame[0], frame[1:-2]

    def poll(self, timeout_s: float) -> None:
        data = self.ep.wait(timeout_s)
        if not data:
            return
        self.buf += data
        for tid, unit, pdu in self._requests():
            if unit not in self.units and not (self.tcp and unit == 0):
                continue
            self.late.release(unit)             # a late answer goes out before this request's
            rsp, fault = self._handle(unit, pdu)
            # a dropped, late or stale answer still applied its command when read; the drawn
            # fault of a write decides the answer to the position read that applies it
            if fault is None and pdu[0] in (1, 2, 3, 4):
                fault = self._read_fault
                self._read_fault = None
            elif pdu[0] in (5, 6, 15, 16) and fault not in (None, "disconnect"):
                self._read_fault, fault = fault, None
            if fault == "disconnect":
                self.ep.disconnect()
                self.buf.clear()
                return
            frame = self._frame(tid, unit, rsp)
            if fault in ("drop", "bus_off"):
                pass
            elif fault == "stale" and self.last is not None:
                self.ep.send(self.last)
            elif fault == "corrupt":
                bad = bytearray(frame)
                if self.tcp:
                    bad[4:6] = (len(bad) + 40).to_bytes(2, "big")[:2]   # a length beyond the frame
                    bad[7] = 0x63
                else:
                    bad[-1] ^= 0xFF
                self.ep.send(bytes(bad))
            elif fault == "late":
                self.late.hold(self.ep.send, frame, key=unit)
            else:
                self.ep.send(frame)
            self.last = frame

    _read_fault = None

    def close(self) -> None:
        self.ep.close()
