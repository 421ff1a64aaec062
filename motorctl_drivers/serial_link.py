"""Serial driver (pyserial): one compact binary exchange per cycle for the whole axis group.

Frames (our layout; multi-byte fields little-endian, CRC big-endian)::

    command  A5 | addr | seq | n | n × (node, flags, u int16) | CRC-16   flags bit0 = amplifier enable,
                                                                   bit1 = fault reset (rising edge, enable 0)
    query    A6 | addr | seq | n | n × (node)                 | CRC-16   (positions only, no plant step)
    reply    5A | addr | seq | n | n × (node, status, counts int32) | CRC-16   status bit0 = amp
                                       fault, bit1 = amplifier on, bit2 = revision 2 (keeps its fault)
    error    5B | addr | seq | n | code |                 CRC-16     (the device refused the command)
    config   A7 | addr | seq | 1 | watchdog uint16 |      CRC-16     watchdog in units of 100 us
    ack      5C | addr | seq | 1 | watchdog uint16 |      CRC-16     the watchdog the device applies

The protocol byte by byte, with line settings, RS-485 direction, when counts are latched, the
watchdog and the two revisions: docs/serial-protocol.md (firmware can be written from it alone).
Revision 2 keeps a latched amplifier fault until the host's fault-reset request (flags bit 1,
sent only on the operator's ``motorctl fault-reset``: :meth:`SerialDriver.reset_fault`) and
says so in every reply (status bit 2); a device whose replies leave bit 2 clear is of revision
1, whose command with enable 0 clears the fault: set-up says the fault cannot stay latched.

CRC-16/CCITT-FALSE (polynomial 0x1021, initial value 0xFFFF, no reflection) over every byte
before it, via :func:`binascii.crc_hqx`. ``seq`` is the cycle counter mod 256: the reply carries
the command's, so a stale or late reply is recognised. ``u`` is the voltage scaled so that
±32767 = ±``voltage_full_scale_V``; counts are the 32-bit encoder counter (wraps, unwrapped by
the driver). ``node`` is the axis's drive number on the link (``axes.NAME.driver.node``), so a
frame may carry any subset of the axes.

YAML (``driver:``)::

    type: serial
    port: /dev/ttyS4 | socket://127.0.0.1:5020 | /tmp/motorctl-pty   (pyserial URL or device)
    baudrate: 3000000
    address: 1
    low_latency: true            # ASYNC_LOW_LATENCY where the port supports it (reported)
    voltage_full_scale_V: 10.0
    bits_per_char: 10            # 8N1
    turnaround_chars: 1.0        # line turnaround per exchange, in characters (budget)
    device_latency_s: 10.0e-6    # the drive's answer time (budget)
    timeout_s, wait, round_trip_s, max_bus_load: see split_phase.CommonOptions

    watchdog_s: 0.05             # the device's command watchdog, set in configure() (config frame)
    rs485: false                 # RS-485 direction by the UART (TIOCSRS485) where it has it

per axis (``axes.NAME.driver``): ``node`` (0-255), ``encoder_m_per_count`` [m].

The voltage limit of every axis (its ``voltage_out`` interface) is ``voltage_full_scale_V``.
An error frame answers the command it names by ``seq``: no axis of it is applied or answered.
"""

from __future__ import annotations

import binascii
import math
import struct
import time
from typing import Annotated

import numpy as np
from pydantic import Field

from motorctl.driver import BusBudget, StopCheck
from motorctl.schema import StrictModel
from motorctl_drivers.split_phase import (
    CommonOptions,
    EncoderUnwrap,
    SplitPhaseDriver,
    make_budget,
    open_error,
    volts_to_counts,
)

CMD, QUERY, REPLY, ERROR, CONFIG, ACK = 0xA5, 0xA6, 0x5A, 0x5B, 0xA7, 0x5C
#: command flags (docs/serial-protocol.md): amplifier enable; fault reset (revision 2: the
#: channel's latched fault is cleared on this bit's rising edge in a command with enable 0)
FLAG_ENABLE, FLAG_FAULT_RESET = 0x01, 0x02
#: reply status bits: amplifier fault latched; amplifier on (driving); revision 2 (the device
#: keeps a latched fault until the fault-reset request; revision 1 devices send 0 here)
STATUS_FAULT, STATUS_ON, STATUS_REVISION_2 = 0x01, 0x02, 0x04
#: error codes of an error frame (docs/serial-protocol.md)
ERROR_CODES = {1: "bad request (unknown node or item count)", 2: "value out of range",
               3: "not allowed now", 4: "device failure"}
WATCHDOG_UNIT_S = 100e-6
_HEAD = 4
_CMD_ITEM = struct.Struct("<BBh")
_QUERY_ITEM = struct.Struct("<B")
_REPLY_ITEM = struct.Struct("<BBI")
MAX_AXES = 32
STANDARD_BAUDS = (115200, 230400, 460800, 921600, 1000000, 2000000, 3000000, 4000000, 6000000, 12000000)


def crc16(data: bytes) -> int:
    """CRC-16/CCITT-FALSE of ``data`` (poly 0x1021, init 0xFFFF): ``binascii.crc_hqx``."""
    return binascii.crc_hqx(data, 0xFFFF)


def frame_length(kind: int, n: int) -> int:
    """Length in bytes of a frame of ``kind`` carrying ``n`` axes."""
    body = {CMD: _CMD_ITEM.size * n, QUERY: _QUERY_ITEM.size * n, REPLY: _REPLY_ITEM.size * n, ERROR: 1,
            CONFIG: 2, ACK: 2}[kind]
    return _HEAD + body + 2


def _seal(buf: bytearray) -> bytes:
    buf[-2:] = crc16(bytes(buf[:-2])).to_bytes(2, "big")
    return bytes(buf)


def encode_command(address: int, seq: int, items) -> bytes:
    """Command frame. ``items``: per axis (node, flags: int (:data:`FLAG_ENABLE`,
    :data:`FLAG_FAULT_RESET`; a bool is the enable alone), u_counts: int16)."""
    buf = bytearray(frame_length(CMD, len(items)))
    buf[0:4] = bytes((CMD, address, seq & 0xFF, len(items)))
    for k, (node, flags, c) in enumerate(items):
        _CMD_ITEM.pack_into(buf, _HEAD + k * _CMD_ITEM.size, node, int(flags) & 0xFF, c)
    return _seal(buf)


def encode_query(address: int, seq: int, nodes) -> bytes:
    buf = bytearray(frame_length(QUERY, len(nodes)))
    buf[0:4] = bytes((QUERY, address, seq & 0xFF, len(nodes)))
    buf[4:4 + len(nodes)] = bytes(nodes)
    return _seal(buf)


def encode_reply(address: int, seq: int, items) -> bytes:
    """Reply frame. ``items``: per axis (node, status: int, counts: int, taken mod 2^32)."""
    buf = bytearray(frame_length(REPLY, len(items)))
    buf[0:4] = bytes((REPLY, address, seq & 0xFF, len(items)))
    for k, (node, st, c) in enumerate(items):
        _REPLY_ITEM.pack_into(buf, _HEAD + k * _REPLY_ITEM.size, node, st, c & 0xFFFFFFFF)
    return _seal(buf)


def encode_error(address: int, seq: int, n: int, code: int) -> bytes:
    buf = bytearray(frame_length(ERROR, n))
    buf[0:4] = bytes((ERROR, address, seq & 0xFF, n))
    buf[4] = code
    return _seal(buf)


def encode_config(address: int, seq: int, watchdog_units: int, kind: int = CONFIG) -> bytes:
    """Config frame (or, with ``kind=ACK``, its acknowledgement): the watchdog in units of
    100 us (uint16 little-endian, 1-65535)."""
    buf = bytearray(frame_length(kind, 1))
    buf[0:4] = bytes((kind, address, seq & 0xFF, 1))
    buf[4:6] = int(watchdog_units).to_bytes(2, "little")
    return _seal(buf)


def decode_body(kind: int, n: int, frame: bytes) -> list:
    """Items of a checked frame: CMD → [(node, flags, u_counts)], REPLY → [(node, status,
    counts_u32)], QUERY → [node], ERROR → [code]."""
    if kind == CMD:
        return [_CMD_ITEM.unpack_from(frame, _HEAD + k * _CMD_ITEM.size) for k in range(n)]
    if kind == REPLY:
        return [_REPLY_ITEM.unpack_from(frame, _HEAD + k * _REPLY_ITEM.size) for k in range(n)]
    if kind == QUERY:
        return list(frame[_HEAD:_HEAD + n])
    if kind in (CONFIG, ACK):
        return [int.from_bytes(frame[4:6], "little")]
    return [frame[4]]


class FrameParser:
    """Cuts frames out of a byte stream: hunts for a start byte, waits for the whole frame,
    checks the CRC; a bad frame costs one byte of resync and counts in ``bad_frames``."""

    def __init__(self, kinds=(CMD, QUERY, REPLY, ERROR, CONFIG, ACK)):
        self.buf = bytearray()
        self.kinds = set(kinds)
        self.bad_frames = 0

    def feed(self, data: bytes) -> list[tuple[int, int, int, int, bytes]]:
        """Add bytes; return the complete good frames as (kind, address, seq, n, frame)."""
        buf = self.buf
        buf += data
        out = []
        i = 0
        while len(buf) - i >= _HEAD + 2:
            kind = buf[i]
            n = buf[i + 3]
            if kind not in self.kinds or not 1 <= n <= MAX_AXES or (kind in (CONFIG, ACK) and n != 1):
                i += 1
                continue
            size = frame_length(kind, n)
            if len(buf) - i < size:
                break
            frame = bytes(buf[i:i + size])
            if crc16(frame[:-2]) != int.from_bytes(frame[-2:], "big"):
                self.bad_frames += 1
                i += 1
                continue
            out.append((kind, frame[1], frame[2], n, frame))
            i += size
        del buf[:i]
        return out


class SerialOptions(CommonOptions):
    """YAML ``driver:`` of the serial driver (see the module docstring)."""

    port: str
    baudrate: Annotated[int, Field(gt=0)] = 3_000_000
    address: Annotated[int, Field(ge=0, le=255)] = 1
    low_latency: bool = True
    voltage_full_scale_V: Annotated[float, Field(gt=0)] = 10.0
    bits_per_char: Annotated[int, Field(ge=7, le=12)] = 10
    turnaround_chars: Annotated[float, Field(ge=0)] = 1.0
    device_latency_s: Annotated[float, Field(ge=0)] = 10e-6
    watchdog_s: Annotated[float, Field(ge=100e-6, le=6.5535)] | None = 0.05
    rs485: bool = False


class SerialAxisOptions(StrictModel):
    """YAML ``axes.NAME.driver`` of the serial driver."""

    node: Annotated[int, Field(ge=0, le=255)]
    encoder_m_per_count: Annotated[float, Field(gt=0)] = 0.5e-6


class SerialDriver(SplitPhaseDriver):
    """The serial-link driver (pyserial). See the module docstring for frame and settings."""

    Options = SerialOptions
    AxisOptions = SerialAxisOptions

    def __init__(self, options: SerialOptions, axis_options: dict, period_s: float):
        super().__init__(options, axis_options, period_s)
        n = len(self.axis_names)
        if n > MAX_AXES:
            raise ValueError(f"serial frame carries at most {MAX_AXES} axes")
        self._unwrap = [EncoderUnwrap(32) for _ in range(n)]
        self._m_per_count = [axis_options[a].encoder_m_per_count for a in self.axis_names]
        self.port = None
        self.parser = FrameParser((REPLY, ERROR, ACK))
        self.low_latency = "off"
        self.watchdog = "not set (the device keeps its own)"
        self._ack = None
        self._nodes = [axis_options[a].node for a in self.axis_names]
        if len(set(self._nodes)) != n:
            raise ValueError(f"serial: two axes share a node number ({self._nodes})")
        self._index = {nd: i for i, nd in enumerate(self._nodes)}
        self._items = [(nd, False, 0) for nd in self._nodes]
        self._status = [0] * n               # the status byte of each axis's last reply

    def _open_transport(self) -> None:
        """Open the port (8N1 at ``baudrate``; RS-485 direction control when ``rs485``).

        Raises:
            OSError: the port is missing, not permitted, or refuses a line setting (one line).
        """
        import serial
        o = self.options
        try:
            if "://" in o.port:
                self.port = serial.serial_for_url(o.port, baudrate=o.baudrate, timeout=0, write_timeout=0)
                if o.port.startswith("socket://"):
                    import socket
                    self.port._socket.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            else:
                self.port = serial.Serial(o.port, baudrate=o.baudrate, timeout=0, write_timeout=0)
            if o.rs485:
                import serial.rs485
                self.port.rs485_mode = serial.rs485.RS485Settings()
        except (serial.SerialException, OSError, ValueError) as exc:
            if self.port is not None:
                try:
                    self.port.close()
                except Exception:  # noqa: BLE001
                    pass
                self.port = None
            raise open_error("serial port", f"{o.port} ({o.baudrate} baud 8N1{', RS-485' if o.rs485 else ''})",
                             exc) from None
        if o.low_latency:
            try:
                self.port.set_low_latency_mode(True)
                self.low_latency = "on"
            except (AttributeError, ValueError, OSError) as exc:
                self.low_latency = f"not supported ({type(exc).__name__})"
        self.port.reset_input_buffer()
        self._set_wait_fd(self.port.fileno())
        self.parser = FrameParser((REPLY, ERROR, ACK))

    #: docs/serial-protocol.md, revision 1: a command with enable 0 clears a latched fault
    FAULT_RESET = "a command with enable 0"

    def _set_up_device(self) -> None:
        """Set the device's command watchdog with a config frame (``watchdog_s``; the ack must
        carry a watchdog no longer than asked).

        Raises:
            OSError: the device refuses or lengthens the watchdog. ConnectionError: no answer.
        """
        if self.options.watchdog_s is not None:
            self._set_watchdog(self.options.watchdog_s)

    def _device_name(self) -> str:
        return f"serial device {self.options.address}"

    def _read_back_stop(self, answered: np.ndarray, deadline: float) -> list[StopCheck]:
        """A query after the stop command: each node's status must say amplifier off (bit 1
        clear: the protocol's "enable 0 → 0 V, amplifier disabled")."""
        try:
            self._query_once(max(0.01, deadline - time.perf_counter()))
        except (ConnectionError, OSError) as exc:
            return [StopCheck(a, False, f"{'answered the stop, ' if answered[i] else ''}no status read back: {exc}")
                    for i, a in enumerate(self.axis_names)]
        out = []
        for i, a in enumerate(self.axis_names):
            st = self._status[i]
            on = bool(st & 2)
            out.append(StopCheck(a, not on, f"node {self._nodes[i]} status 0x{st:02X}: amplifier "
                                            f"{'ON, driving' if on else 'off, 0 V'}"
                                            f"{', amplifier fault latched' if st & 1 else ''}"))
        return out

    def fault_reason(self, i: int) -> str:
        """The device's status while axis i reports an amplifier fault ('' otherwise), e.g.
        ``serial device 1 node 1: amplifier fault latched, amplifier off (status 0x05)``."""
        return self.drive_state(i) if self.amp_fault[i] else ""

    def drive_state(self, i: int) -> str:
        """The status of axis i's channel in the device's last reply, whatever it is, decoded
        (docs/serial-protocol.md, reply)."""
        st = self._status[i]
        return (f"serial device {self.options.address} node {self._nodes[i]}: "
                f"{'amplifier fault latched' if st & STATUS_FAULT else 'no fault'}, "
                f"amplifier {'on' if st & STATUS_ON else 'off'} (status 0x{st:02X})")

    def _clears_on_disable(self, i: int) -> bool:
        """Revision 1: the device's last reply leaves status bit 2 clear."""
        return not self._status[i] & STATUS_REVISION_2

    def _old_revision(self, names: list[str]) -> str:
        return (f"serial device {self.options.address} is of protocol revision 1 (its replies leave status "
                f"bit 2 clear): a command with enable 0 clears its latched amplifier fault, so a fault it "
                f"latched ({', '.join(names)}: its watchdog after a host went away, an over-current) cannot "
                f"stay latched until the operator's 'motorctl fault-reset'; revision 2 keeps it "
                f"(docs/serial-protocol.md, Revisions)")

    def _set_watchdog(self, seconds: float) -> None:
        units = max(1, min(0xFFFF, round(seconds / WATCHDOG_UNIT_S)))
        self.seq = (self.seq + 1) & self.SEQ_MASK
        self._ack = None
        self.port.write(encode_config(self.options.address, self.seq, units))
        deadline = time.perf_counter() + self.CONFIGURE_TIMEOUT_S
        while self._ack is None and time.perf_counter() < deadline:
            self._receive()
            time.sleep(0.0002)
        if self._ack is None:
            raise ConnectionError(f"serial device {self.options.address} on {self.options.port}: no answer to the "
                                  f"watchdog config frame within {self.CONFIGURE_TIMEOUT_S:g} s")
        kind, value = self._ack
        if kind == ERROR:
            raise OSError(f"serial device {self.options.address}: watchdog {seconds * 1e3:g} ms refused: error "
                          f"{value} ({ERROR_CODES.get(value, 'unknown')})")
        if value > units:
            raise OSError(f"serial device {self.options.address}: watchdog set to {value * 0.1:g} ms, longer than "
                          f"the {units * 0.1:g} ms asked for")
        self.watchdog = f"{value * 0.1:g} ms (config frame, acknowledged)"

    def _release_transport(self) -> None:
        if self.port is not None:
            port, self.port = self.port, None
            port.close()

    def _full_scale_V(self, axis: str) -> float:
        """``driver.voltage_full_scale_V`` [V] (one for the link): u = ±32767 ↔ ±this."""
        return float(self.options.voltage_full_scale_V)

    def _transmit_query(self, seq: int) -> None:
        self.port.write(encode_query(self.options.address, seq, self._nodes))

    def _transmit(self, seq: int, u_V: np.ndarray, enable: np.ndarray) -> None:
        fs = self.options.voltage_full_scale_V
        items = self._items
        nodes = self._nodes
        amp, pulses = self.amp_fault, self._pulses
        for i in range(len(items)):
            en = bool(enable[i])
            flags = FLAG_FAULT_RESET if pulses.bit(i, en, amp[i]) else (FLAG_ENABLE if en else 0)
            items[i] = (nodes[i], flags, volts_to_counts(float(u_V[i]), fs, 16) if en else 0)
        self.port.write(encode_command(self.options.address, seq, items))

    def _receive(self) -> None:
        data = self.port.read(4096)   # timeout=0: what has arrived, never waits
        if not data:
            return
        frames = self.parser.feed(data)
        self.counters["bad_frames"] = self.parser.bad_frames
        addr = self.options.address
        index = self._index
        for kind, a, seq, m, frame in frames:
            if a != addr:
                continue
            if kind == ACK or (kind == ERROR and self._ack is None and not self._outstanding):
                if seq == self.seq:
                    self._ack = (kind, decode_body(kind, m, frame)[0])
                continue
            if kind == ERROR:
                code = decode_body(ERROR, m, frame)[0]
                self._accept_error(seq, f"error frame code {code} ({ERROR_CODES.get(code, 'unknown')})")
                continue
            fresh = self._outstanding and (seq == self.seq or self._query)
            for node, status, raw in decode_body(REPLY, m, frame):
                i = index.get(node)
                if i is not None:
                    if fresh:
                        self._status[i] = status
                    self._accept(i, seq, raw, bool(status & 1))

    def budget(self, rate_hz: float) -> BusBudget:
        """Characters and gaps on the wire for one exchange of the whole group.

        wire = (request + reply bytes + turnaround_chars) × bits_per_char / baudrate
               + device_latency_s   (8N1: 10 bits per byte)
        """
        o = self.options
        n = len(self.axis_names)
        rt, source = self.budget_round_trip()
        chars = frame_length(CMD, n) + frame_length(REPLY, n)
        fixed = o.device_latency_s + rt
        wire = (chars + o.turnaround_chars) * o.bits_per_char / o.baudrate + o.device_latency_s
        room = o.max_bus_load / rate_hz - fixed
        need = (chars + o.turnaround_chars) * o.bits_per_char / room if room > 0 else math.inf
        fit = next((b for b in STANDARD_BAUDS if b >= need), None)
        fits = (f"raise driver.baudrate to {fit} (needs {need / 1e6:.2f} Mbaud)" if fit
                else "no baud rate carries it: lower round_trip_s (faster host) or fewer axes per link")
        what = (f"serial {o.baudrate} baud, {n} axes: {frame_length(CMD, n)} B command + "
                f"{frame_length(REPLY, n)} B reply + {o.turnaround_chars:g} char turnaround at "
                f"{o.bits_per_char} bits/char + {o.device_latency_s * 1e6:.0f} us device latency")
        return make_budget(rate_hz, wire, rt, o.max_bus_load, what, fits, source)

    def describe(self) -> dict:
        d = super().describe()
        d.update(transport="serial", port=self.options.port, baudrate=self.options.baudrate,
                 low_latency=self.low_latency, watchdog=self.watchdog,
                 protocol_revision=None if not self.round_trip["n"] else
                 1 if any(self._clears_on_disable(i) for i in range(len(self._nodes))) else 2)
        return d
