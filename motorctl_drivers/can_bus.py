"""CAN driver (python-can): classic CAN or CAN FD, layout of every frame from the YAML.

Each axis names the frame that carries its command and the frame that carries its feedback;
axes that name the same arbitration ID share that frame (one command frame and one feedback
frame for the whole group is the cheapest exchange: a dual-axis drive). Per cycle the driver
sends every command frame once (non-blocking) and, in the next cycle's ``read()``, drains the
receive queue with ``bus.recv(timeout=0)`` until every feedback frame of this cycle has come or
``timeout_s`` has passed (no Notifier thread, no blocking wait).

YAML (``driver:``)::

    type: can
    interface: socketcan | virtual | udp_multicast | ...   (any python-can interface by name)
    channel: can0
    bus_options: {}          # extra keyword arguments for can.Bus (e.g. receive_own_messages)
    bitrate: 1000000         # nominal (arbitration) bit rate [bit/s]
    fd: false                # CAN FD frames (data phase at data_bitrate, bit-rate switch on)
    data_bitrate: 5000000
    extended_id: false       # 29-bit identifiers
    timeout_s, wait, round_trip_s, max_bus_load: see split_phase.CommonOptions

per axis (``axes.NAME.driver``)::

    command:  {id: 0x200, voltage: {offset: 0, size: 2, byteorder: little},
               enable: {byte: 4, bit: 0}, fault_reset: {byte: 4, bit: 2}, sequence_byte: 5}
    feedback: {id: 0x180, counts: {offset: 0, size: 4, byteorder: little},
               fault: {byte: 8, bit: 0}, explicit_reset: {byte: 8, bit: 2}, sequence_byte: 9}
    voltage_full_scale_V: 10.0     # ±full-scale count of the voltage field ↔ ±this [V]
    encoder_m_per_count: 0.5e-6    # [m]; the counts field wraps at 2^(8 size), unwrapped here

The voltage field is a signed integer of ``size`` bytes; the counts field is an unsigned
counter of ``size`` bytes (2-4) that wraps; ``sequence_byte`` (optional, per frame) carries the
cycle counter mod 256 in the command and its echo in the feedback, so stale frames are
recognised. Frame length is the end of the last field, rounded up to a valid CAN FD length.
``configure()`` asks for the feedback frames with remote frames (RTR, classic format), which
the device answers without stepping the plant. An error frame on the bus counts as an error
answer. Frame formats and bit counts: ISO 11898-1:2015 (classic CAN and CAN FD).

Faults (docs/drivers.md, "CAN", revision 2 of these frames): ``fault`` is the drive's latched
amplifier fault; a drive of revision 2 keeps it until the rising edge of the command's
``fault_reset`` bit with the enable low, which the driver sends only on the operator's
``motorctl fault-reset`` (:meth:`CanDriver.reset_fault`), and sets ``explicit_reset`` in every
feedback frame to say so. A drive whose feedback leaves ``explicit_reset`` clear (or a layout
without it) is of revision 1: its command with the enable low clears the fault, and set-up says
the fault cannot stay latched.

The voltage limit of an axis (its ``voltage_out`` interface) is ``voltage_full_scale_V``.
"""

from __future__ import annotations

import math
from typing import Annotated, Literal

import numpy as np
from pydantic import Field, model_validator

from motorctl.driver import BusBudget
from motorctl.schema import StrictModel
from motorctl_drivers.split_phase import (
    CommonOptions,
    EncoderUnwrap,
    SplitPhaseDriver,
    make_budget,
    open_error,
    to_unsigned,
    volts_to_counts,
)

FD_LENGTHS = (0, 1, 2, 3, 4, 5, 6, 7, 8, 12, 16, 20, 24, 32, 48, 64)


# --------------------------------------------------------------------------- layout
class IntField(StrictModel):
    """An integer field of a frame: ``size`` bytes at ``offset``, ``byteorder``."""

    offset: Annotated[int, Field(ge=0, le=63)]
    size: Annotated[int, Field(ge=1, le=4)] = 2
    byteorder: Literal["little", "big"] = "little"


class BitRef(StrictModel):
    byte: Annotated[int, Field(ge=0, le=63)]
    bit: Annotated[int, Field(ge=0, le=7)] = 0


class CommandLayout(StrictModel):
    """An axis's command fields: ``voltage``, ``enable`` (the amplifier), ``fault_reset``
    (revision 2: the operator's reset request, taken on its rising edge with the enable low)."""

    id: Annotated[int, Field(ge=0, le=0x1FFFFFFF)]
    voltage: IntField
    enable: BitRef
    fault_reset: BitRef | None = None
    sequence_byte: Annotated[int, Field(ge=0, le=63)] | None = None


class FeedbackLayout(StrictModel):
    """An axis's feedback fields: ``counts``, ``fault`` (latched amplifier fault),
    ``explicit_reset`` (set by a drive of revision 2: its fault stays until ``fault_reset``)."""

    id: Annotated[int, Field(ge=0, le=0x1FFFFFFF)]
    counts: IntField
    fault: BitRef
    explicit_reset: BitRef | None = None
    sequence_byte: Annotated[int, Field(ge=0, le=63)] | None = None


class CanOptions(CommonOptions):
    """YAML ``driver:`` of the CAN driver (see the module docstring)."""

    interface: str = "virtual"
    channel: str = "motorctl"
    bus_options: dict[str, str | int | float | bool] = {}
    bitrate: Annotated[int, Field(gt=0)] = 1_000_000
    fd: bool = False
    data_bitrate: Annotated[int, Field(gt=0)] = 5_000_000
    extended_id: bool = False


class CanAxisOptions(StrictModel):
    """YAML ``axes.NAME.driver`` of the CAN driver."""

    command: CommandLayout
    feedback: FeedbackLayout
    voltage_full_scale_V: Annotated[float, Field(gt=0)] = 10.0
    encoder_m_per_count: Annotated[float, Field(gt=0)] = 0.5e-6

    @model_validator(mode="after")
    def _reset_pair(self):
        if self.feedback.explicit_reset is not None and self.command.fault_reset is None:
            raise ValueError("feedback.explicit_reset (a drive of revision 2) needs command.fault_reset, "
                             "the bit its fault is reset by")
        return self


def frame_length(n_bytes: int, fd: bool) -> int:
    """Smallest valid data length ≥ n_bytes (classic: ≤ 8; FD: 0-8, 12, 16, 20, 24, 32, 48, 64).

    Raises:
        ValueError: the fields do not fit one frame.
    """
    if not fd:
        if n_bytes > 8:
            raise ValueError(f"{n_bytes} bytes do not fit a classic CAN frame (8); set fd: true")
        return n_bytes
    for n in FD_LENGTHS:
        if n >= n_bytes:
            return n
    raise ValueError(f"{n_bytes} bytes do not fit a CAN FD frame (64)")


def frame_bits(n_bytes: int, fd: bool, extended_id: bool) -> tuple[float, float]:
    """Worst-case bits of one frame: (bits at the nominal rate, bits at the data rate).

    Classic CAN (ISO 11898-1): 44 + 8n bits (11-bit ID; 64 + 8n with 29-bit) plus 3 bits
    interframe space, plus at most ⌊(34 + 8n − 1)/4⌋ stuff bits (54 + 8n with 29-bit IDs).
    CAN FD: arbitration (SOF, ID, r1, IDE, EDL, r0, BRS = 17 bits; 37 with 29-bit IDs) with
    stuffing, and CRC delimiter, ACK, EOF, IFS (13 bits) at the nominal rate; ESI, DLC, data,
    stuff count (4), CRC (17 bits up to 16 bytes, 21 above) with its fixed stuff bits (one per
    4) and the dynamic stuff bits of the data at the data rate.
    """
    if not fd:
        base = (64 if extended_id else 44) + 8 * n_bytes + 3
        stuffable = (54 if extended_id else 34) + 8 * n_bytes
        return base + (stuffable - 1) // 4, 0.0
    arb = 37 if extended_id else 17
    nominal = arb + (arb - 1) // 4 + 13
    crc = 17 if n_bytes <= 16 else 21
    data = 1 + 4 + 8 * n_bytes + (4 + crc) + math.ceil((4 + crc) / 4) + (5 + 8 * n_bytes - 1) // 4
    return float(nominal), float(data)


def pack_int(buf: bytearray, f: IntField, value: int) -> None:
    """Write ``value`` (two's complement, ``f.size`` bytes, ``f.byteorder``) into ``buf``."""
    buf[f.offset:f.offset + f.size] = to_unsigned(value, 8 * f.size).to_bytes(f.size, f.byteorder)


def unpack_uint(data, f: IntField) -> int:
    """The unsigned integer of field ``f`` in ``data`` (``f.size`` bytes, ``f.byteorder``)."""
    return int.from_bytes(data[f.offset:f.offset + f.size], f.byteorder)


class Frame:
    """One arbitration ID of the layout: ``id``, ``length`` [bytes], ``axes`` (indexes of the
    axes it carries), ``seq_byte`` (index of the sequence byte, or None)."""

    def __init__(self, fid: int, axes: list[int], length: int, seq_byte: int | None):
        self.id, self.axes, self.length, self.seq_byte = fid, axes, length, seq_byte


def build_frames(names, axis_options, kind: str, fd: bool) -> list[Frame]:
    """Group the axes by the ID of their ``kind`` ('command' or 'feedback') frame; check that
    fields and bits do not overlap and that axes sharing a frame share its sequence byte.

    Raises:
        ValueError: overlapping fields or bits, disagreeing sequence bytes, a frame too long.
    """
    by_id: dict[int, list[int]] = {}
    for i, a in enumerate(names):
        by_id.setdefault(getattr(axis_options[a], kind).id, []).append(i)
    frames = []
    for fid, idx in by_id.items():
        used: dict[int, str] = {}
        used_bits: dict[tuple[int, int], str] = {}
        seqs = {getattr(axis_options[names[i]], kind).sequence_byte for i in idx}
        if len(seqs) > 1:
            raise ValueError(f"{kind} frame 0x{fid:X}: axes disagree on sequence_byte ({sorted(s for s in seqs if s is not None)})")
        seq = seqs.pop()
        end = 0
        for i in idx:
            lay = getattr(axis_options[names[i]], kind)
            f = lay.voltage if kind == "command" else lay.counts
            roles = ("enable", "fault_reset") if kind == "command" else ("fault", "explicit_reset")
            spans = [(f.offset, f.size, f"{names[i]} {'voltage' if kind == 'command' else 'counts'}")]
            for off, size, what in spans:
                for b in range(off, off + size):
                    if b in used:
                        raise ValueError(f"{kind} frame 0x{fid:X}: byte {b} used by {used[b]} and {what}")
                    used[b] = what
            end = max(end, f.offset + f.size)
            for role in roles:
                bit = getattr(lay, role)
                if bit is None:
                    continue
                what = f"{names[i]} {role}"
                if (bit.byte, bit.bit) in used_bits:
                    raise ValueError(f"{kind} frame 0x{fid:X}: byte {bit.byte} bit {bit.bit} used by "
                                     f"{used_bits[bit.byte, bit.bit]} and {what}")
                used_bits[bit.byte, bit.bit] = what
                end = max(end, bit.byte + 1)
                if bit.byte in used and not used[bit.byte].startswith("bits"):
                    raise ValueError(f"{kind} frame 0x{fid:X}: byte {bit.byte} used by {used[bit.byte]} and {what}")
                used.setdefault(bit.byte, "bits")
        if seq is not None:
            if seq in used:
                raise ValueError(f"{kind} frame 0x{fid:X}: sequence byte {seq} used by {used[seq]}")
            end = max(end, seq + 1)
        frames.append(Frame(fid, idx, frame_length(end, fd), seq))
    return frames


def open_bus(options):
    """The python-can bus of ``options`` (``can.Bus(interface, channel, **bus_options)``; the bit
    rates are passed to interfaces that set them, ``fd`` to every interface but udp_multicast,
    which takes FD frames anyway). Used by the CAN and CANopen drivers and their emulated devices.

    Raises:
        OSError: the interface cannot be opened (one line: the interface, the channel and why;
            python-can's CanError and a missing interface module are turned into it).
    """
    import can
    kw = dict(options.bus_options)
    if options.interface not in ("virtual", "udp_multicast"):
        kw.setdefault("bitrate", options.bitrate)
        if options.fd:
            kw.setdefault("data_bitrate", options.data_bitrate)
    if options.interface != "udp_multicast":
        kw.setdefault("fd", options.fd)
    try:
        return can.Bus(interface=options.interface, channel=options.channel, **kw)
    except (can.CanError, OSError, ImportError, ValueError, TypeError) as exc:
        raise open_error("CAN interface", f"{options.interface}:{options.channel}", exc) from None


# --------------------------------------------------------------------------- driver
class CanDriver(SplitPhaseDriver):
    """The CAN driver. See the module docstring for layout and settings."""

    Options = CanOptions
    AxisOptions = CanAxisOptions
    #: revision 1's reset of a fault the drive latched (its own command timeout included): the
    #: enable low (a drive of revision 2 takes only the ``fault_reset`` bit)
    FAULT_RESET = "a command with enable 0"

    def __init__(self, options: CanOptions, axis_options: dict, period_s: float):
        super().__init__(options, axis_options, period_s)
        names = self.axis_names
        self.cmd_frames = build_frames(names, axis_options, "command", options.fd)
        self.fb_frames = build_frames(names, axis_options, "feedback", options.fd)
        self._fb_by_id = {f.id: f for f in self.fb_frames}
        self._lay = [axis_options[a] for a in names]
        self._unwrap = [EncoderUnwrap(8 * o.feedback.counts.size) for o in self._lay]
        self._m_per_count = [o.encoder_m_per_count for o in self._lay]
        self.bus = None
        self._msgs = []
        self._explicit = [False] * len(names)     # the feedback's explicit_reset bit, last seen

    def _message(self, fid: int, length: int, remote: bool = False):
        import can
        o = self.options
        fd = o.fd and not remote
        return can.Message(arbitration_id=fid, is_extended_id=o.extended_id, is_remote_frame=remote,
                           dlc=0 if remote else length, data=None if remote else bytearray(length), is_fd=fd,
                           bitrate_switch=fd, check=True)

    def _open_transport(self) -> None:
        self.bus = open_bus(self.options)
        self._msgs = [self._message(f.id, f.length) for f in self.cmd_frames]
        try:
            self._set_wait_fd(self.bus.fileno())
        except (NotImplementedError, AttributeError, OSError):
            self._set_wait_fd(None)          # e.g. 'virtual': no descriptor, poll
        while self.bus.recv(timeout=0) is not None:   # stale frames from before
            pass

    def _release_transport(self) -> None:
        if self.bus is not None:
            bus, self.bus = self.bus, None
            bus.shutdown()

    def _device_name(self) -> str:
        return f"CAN {self.options.interface} {self.options.channel}"

    def _full_scale_V(self, axis: str) -> float:
        """``axes.NAME.driver.voltage_full_scale_V`` [V]: the ±full-scale count of the voltage field."""
        return float(self.axis_options[axis].voltage_full_scale_V)

    def _transmit_query(self, seq: int) -> None:
        for f in self.fb_frames:
            self.bus.send(self._message(f.id, f.length, remote=True), timeout=0)

    def _transmit(self, seq: int, u_V: np.ndarray, enable: np.ndarray) -> None:
        lay = self._lay
        bus = self.bus
        amp, pulses = self.amp_fault, self._pulses
        for f, msg in zip(self.cmd_frames, self._msgs):
            data = msg.data
            data[:] = bytes(len(data))
            for i in f.axes:
                c = lay[i].command
                en = bool(enable[i])
                pack_int(data, c.voltage, volts_to_counts(float(u_V[i]), lay[i].voltage_full_scale_V,
                                                         8 * c.voltage.size) if en else 0)
                if en:
                    data[c.enable.byte] |= 1 << c.enable.bit
                if pulses.bit(i, en, amp[i]) and c.fault_reset is not None:
                    data[c.fault_reset.byte] |= 1 << c.fault_reset.bit
            if f.seq_byte is not None:
                data[f.seq_byte] = seq
            try:
                bus.send(msg, timeout=0)
            except Exception:  # noqa: BLE001  (CanError / OSError: bus-off, queue full, link down)
                self.counters["send_errors"] += 1
                for i in f.axes:
                    self.write_error[i] = True

    def _receive(self) -> None:
        bus = self.bus
        fb = self._fb_by_id
        lay = self._lay
        while True:
            msg = bus.recv(timeout=0)
            if msg is None:
                return
            if msg.is_error_frame:
                self._accept_error(None)      # an error frame carries no sequence number
                continue
            f = fb.get(msg.arbitration_id)
            if f is None or msg.is_remote_frame:
                continue                      # not ours (or our own command seen on the bus)
            data = msg.data
            if len(data) < f.length:
                self.counters["bad_frames"] += 1
                continue
            seq = data[f.seq_byte] if f.seq_byte is not None else self.seq
            for i in f.axes:
                fl = lay[i].feedback
                self._accept(i, seq, unpack_uint(data, fl.counts), bool(data[fl.fault.byte] >> fl.fault.bit & 1))
                if fl.explicit_reset is not None:
                    self._explicit[i] = bool(data[fl.explicit_reset.byte] >> fl.explicit_reset.bit & 1)

    # --- the drive's fault
    def _clears_on_disable(self, i: int) -> bool:
        """Revision 1: axis i's last feedback left ``explicit_reset`` clear, or the layout has none."""
        return not self._explicit[i]

    def _old_revision(self, names: list[str]) -> str:
        why = []
        for a in names:
            fl = self._lay[self.axis_names.index(a)].feedback
            b = fl.explicit_reset
            why.append(f"{a} (the layout names no feedback explicit_reset bit)" if b is None else
                       f"{a} (its drive leaves feedback 0x{fl.id:X} byte {b.byte} bit {b.bit}, explicit_reset, clear)")
        return (f"{self._device_name()}: the drives of {', '.join(why)} are of revision 1 of the CAN frames: a "
                f"command with the enable low clears a latched amplifier fault, so a fault a drive latched (its "
                f"command timeout after a host went away, an over-current) cannot stay latched until the "
                f"operator's 'motorctl fault-reset'; revision 2 keeps it (docs/drivers.md, CAN)")

    def drive_state(self, i: int) -> str:
        """Axis i's fault bit in the drive's last feedback frame, whatever it is."""
        fl = self._lay[i].feedback
        on = bool(self.amp_fault[i])
        return (f"{self._device_name()} feedback 0x{fl.id:X} (axis {self.axis_names[i]}): "
                f"{'amplifier fault latched' if on else 'no fault'} (byte {fl.fault.byte} bit {fl.fault.bit} "
                f"{'set' if on else 'clear'})")

    def fault_reason(self, i: int) -> str:
        """The drive's fault bit while axis i reports an amplifier fault ('' otherwise)."""
        return self.drive_state(i) if self.amp_fault[i] else ""

    def budget(self, rate_hz: float) -> BusBudget:
        """Bits on the wire for one cycle: every command frame and every feedback frame once,
        worst-case stuffing (see :func:`frame_bits`)."""
        o = self.options
        frames = [f.length for f in self.cmd_frames] + [f.length for f in self.fb_frames]
        wire = self._wire(frames, o.fd, o.data_bitrate)
        kind = (f"CAN FD {o.bitrate / 1e6:g}M/{o.data_bitrate / 1e6:g}M" if o.fd
                else f"classic CAN {o.bitrate / 1e6:g} Mbit/s")
        what = (f"{kind}, {len(self.axis_names)} axes: {len(self.cmd_frames)} command + "
                f"{len(self.fb_frames)} feedback frames of {'/'.join(str(n) for n in frames)} B, "
                f"worst-case stuffing")
        rt, source = self.budget_round_trip()
        # settings that would carry the rate, cheapest change first
        room = o.max_bus_load / rate_hz - rt
        fits = []
        grouped = [min(sum(f.length for f in self.cmd_frames), 64),
                   min(sum(f.length for f in self.fb_frames), 64)]
        for fd, dbr, fr, label in (
                (True, 5_000_000, frames, "fd: true, data_bitrate: 5000000"),
                (True, 5_000_000, [frame_length(grouped[0], True), frame_length(grouped[1], True)],
                 "fd: true, data_bitrate: 5000000 and one command + one feedback frame for the group "
                 "(the same id for every axis)"),
                (True, 8_000_000, [frame_length(grouped[0], True), frame_length(grouped[1], True)],
                 "fd: true, data_bitrate: 8000000 and one command + one feedback frame for the group")):
            t = self._wire(fr, fd, dbr)
            if t <= room:
                fits.append(f"{label} ({t * 1e6:.1f} us per cycle)")
                break
        fit = fits[0] if fits else "fewer axes per bus (no CAN setting carries this rate)"
        return make_budget(rate_hz, wire, rt, o.max_bus_load, what, fit, source)

    def _wire(self, lengths, fd: bool, data_bitrate: int) -> float:
        o = self.options
        t = 0.0
        for n in lengths:
            nom, dat = frame_bits(n, fd, o.extended_id)
            t += nom / o.bitrate + dat / data_bitrate
        return t

    def describe(self) -> dict:
        d = super().describe()
        o = self.options
        d.update(transport="can", interface=o.interface, channel=o.channel, fd=o.fd,
                 bitrate=o.bitrate, data_bitrate=o.data_bitrate if o.fd else None,
                 command_ids=[f.id for f in self.cmd_frames], feedback_ids=[f.id for f in self.fb_frames],
                 protocol_revision=None if not self.round_trip["n"] else
                 {a: 1 if self._clears_on_disable(i) else 2 for i, a in enumerate(self.axis_names)})
        return d
