"""The emulated drive(s) on the CAN bus (``motorctl emulate --transport can``).

Frame layout, bus options and codecs are the driver's (:mod:`motorctl_drivers.can_bus`).
"""

from __future__ import annotations

from motorctl_drivers.can_bus import (
    CanOptions,
    Frame,
    build_frames,
    open_bus,
    pack_int,
    unpack_uint,
)
from motorctl_drivers.split_phase import counts_to_volts, to_signed
from motorctl_emulators.device import Device, LateAnswers
from motorctl_emulators.plant_bank import PlantBank


class CanDevice(Device):
    """A command frame steps the axes it carries and is answered with the feedback frames of
    those axes (sequence byte echoed); a remote frame on a feedback ID is answered without a
    step. Faults: drop, late (the feedback after ``late_s`` and never before the next command
    frame of that ID: :class:`~motorctl_emulators.device.LateAnswers`), corrupt (a frame shorter
    than the layout), stale (the previous feedback again), exception (an error frame instead of
    the answer), disconnect and bus_off (the node is silent: it neither applies nor answers).

    Revision 2 (the default, on every axis whose layout has ``command.fault_reset`` and
    ``feedback.explicit_reset``): the drive keeps a latched amplifier fault until the rising
    edge of ``fault_reset`` with the enable low, sets ``explicit_reset`` in every feedback
    frame, and its command timeout latches only an amplifier that was on (the bank's reset
    input, :class:`~motorctl_emulators.plant_bank.PlantBank`). Revision 1
    (:meth:`play_revision`, or a layout without those bits): a command with the enable low
    clears the fault.

    Raises:
        ValueError: the layout does not build (as the driver's). can.CanError, OSError: the bus
        cannot be opened.
    """

    def __init__(self, options: CanOptions, axis_options: dict, bank: PlantBank):
        super().__init__(options, axis_options, bank)
        names = bank.names
        self.lay = [axis_options[a] for a in names]
        self.cmd = {f.id: f for f in build_frames(names, axis_options, "command", options.fd)}
        self.fb = build_frames(names, axis_options, "feedback", options.fd)
        self.fb_of_axis = {i: f for f in self.fb for i in f.axes}
        self.bus = open_bus(options)
        self.last = {}
        self.late = LateAnswers(bank)      # keyed by the command frame's ID
        self.clocks = {}                   # command frame id -> MasterTime (its sequence byte)
        self.play_revision(2)

    def play_revision(self, revision: int) -> None:
        """Answer as drives of ``revision`` (1 or 2) of the CAN frames (docs/drivers.md, CAN):
        revision 2 only on the axes whose layout has the bits it needs."""
        if revision not in (1, 2):
            raise ValueError(f"CAN frames revision {revision!r}: 1 or 2")
        self.rev2 = [revision == 2 and o.command.fault_reset is not None and o.feedback.explicit_reset is not None
                     for o in self.lay]
        self.bank.reset_input = list(self.rev2)

    def _feedback(self, f: Frame, seq: int):
        import can
        b = self.bank
        data = bytearray(f.length)
        for i in f.axes:
            fl = self.lay[i].feedback
            pack_int(data, fl.counts, b.counts(i, self.lay[i].encoder_m_per_count))
            if b.amp_fault[i]:
                data[fl.fault.byte] |= 1 << fl.fault.bit
            if self.rev2[i]:
                data[fl.explicit_reset.byte] |= 1 << fl.explicit_reset.bit
        if f.seq_byte is not None:
            data[f.seq_byte] = seq
        fd = self.options.fd
        return can.Message(arbitration_id=f.id, is_extended_id=self.options.extended_id, data=data,
                           is_fd=fd, bitrate_switch=fd)

    def poll(self, timeout_s: float) -> None:
        import can
        msg = self.bus.recv(timeout=timeout_s)
        if msg is None or msg.is_error_frame:
            return
        b = self.bank
        if msg.is_remote_frame:
            for f in self.fb:
                if f.id == msg.arbitration_id:
                    self.bus.send(self._feedback(f, 0))
            return
        f = self.cmd.get(msg.arbitration_id)
        if f is None or len(msg.data) < f.length:
            return
        self.late.release(f.id)             # a late answer goes out before this command's
        data = msg.data
        seq = data[f.seq_byte] if f.seq_byte is not None else 0
        periods = 1
        if f.seq_byte is not None:          # the master's time from the frame's sequence byte
            clock = self.clocks.get(f.id)
            if clock is None:
                clock = self.clocks[f.id] = b.master_time(256)
            periods = clock.periods(seq)
        fault = b.next_fault(f.axes)
        if fault in ("disconnect", "bus_off"):
            return
        if fault == "exception":
            self.bus.send(can.Message(arbitration_id=0, is_error_frame=True, is_extended_id=False))
            return
        for i in f.axes:
            c = self.lay[i].command
            bits = 8 * c.voltage.size
            u = counts_to_volts(to_signed(unpack_uint(data, c.voltage), bits), self.lay[i].voltage_full_scale_V, bits)
            reset = c.fault_reset is not None and bool(data[c.fault_reset.byte] >> c.fault_reset.bit & 1)
            b.command(i, u, bool(data[c.enable.byte] >> c.enable.bit & 1), periods, reset=reset)
        if fault == "drop":
            return
        done = set()
        for i in f.axes:
            fbf = self.fb_of_axis[i]
            if fbf.id in done:
                continue
            done.add(fbf.id)
            reply = self._feedback(fbf, seq)
            if fault == "stale" and fbf.id in self.last:
                self.bus.send(self.last[fbf.id])
            elif fault == "corrupt":
                bad = can.Message(arbitration_id=fbf.id, is_extended_id=self.options.extended_id,
                                  data=reply.data[:max(0, fbf.length - 3)], is_fd=self.options.fd)
                self.bus.send(bad)
            elif fault == "late":
                self.late.hold(self.bus.send, reply, key=f.id)
            else:
                self.bus.send(reply)
            self.last[fbf.id] = reply

    def close(self) -> None:
        if self.bus is not None:
            bus, self.bus = self.bus, None
            bus.shutdown()
