"""The emulated Modbus device (``motorctl emulate --transport modbus``).

Register map, framing and codecs are the driver's (:mod:`motorctl_drivers.modbus`); function
codes as in the Modbus Application Protocol v1.1b3 (§6.3 FC03, §6.4 FC04, §6.6 FC06, §6.12
FC16, §6.17 FC23; exception codes §7).
"""

from __future__ import annotations

import time

from motorctl_drivers.modbus import ModbusOptions, RegisterPlan, decode_frames, split_counts
from motorctl_drivers.split_phase import counts_to_volts, to_signed
from motorctl_emulators.device import Device
from motorctl_emulators.plant_bank import PlantBank
from motorctl_emulators.stream import StreamEndpoint


class ModbusDevice(Device):
    """Holding registers as in the map. FC03/FC04 read; FC06, FC16 and FC23 write (FC23 then
    reads). A write that covers an axis's voltage register is a command for that axis: the
    plant steps one period and the feedback registers are updated before any read. Faults:
    drop, late, corrupt (bad CRC on RTU, a broken MBAP length on TCP), stale (the previous
    answer again), exception (exception code 0x04, device failure; the command is not applied),
    disconnect (TCP: close the connection), bus_off (as drop).

    Raises:
        ValueError: the register map needs more than one FC23 request (the driver's check).
        OSError: the endpoint cannot be opened.
    """

    def __init__(self, options: ModbusOptions, axis_options: dict, bank: PlantBank):
        from pymodbus.framer import FramerRTU, FramerSocket
        from pymodbus.pdu import DecodePDU
        super().__init__(options, axis_options, bank)
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
        b, r, o = self.bank, self.regs, self.options
        for i, a in enumerate(self.ax):
            r0, r1 = split_counts(b.counts(i, a.encoder_m_per_count), a.word_order)
            r[a.counts_register], r[a.counts_register + 1] = r0, r1
            st = r[a.status_register] & ~(1 << a.fault_bit)
            r[a.status_register] = st | ((1 << a.fault_bit) if b.amp_fault[i] else 0)
        if o.sequence_echo_register is not None and o.sequence_register is not None:
            r[o.sequence_echo_register] = r[o.sequence_register]

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
        o = self.options
        self.buf += data
        for req in decode_frames(self.framer, self.buf):
            if req is None:
                continue
            if o.transport == "rtu" and req.dev_id not in (0, o.unit_id):
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
                if o.transport == "rtu":
                    bad[-1] ^= 0xFF
                else:
                    bad[8] = 0xFF        # byte count beyond the frame: the PDU does not decode
                self.ep.send(bytes(bad))
            else:
                if fault == "late":
                    time.sleep(self.bank.late_s)
                self.ep.send(frame)
            if req.function_code in (6, 16, 23):
                self.last = frame

    def close(self) -> None:
        self.ep.close()
