"""The emulated drive group behind a serial link (``motorctl emulate --transport serial``).

Frames and CRC are the driver's (:mod:`motorctl_drivers.serial_link`). The device speaks
revision 2 of docs/serial-protocol.md (a latched amplifier fault stays until the fault-reset
request, status bit 2 in every reply) and can play revision 1 (:meth:`SerialDevice.play_revision`).
"""

from __future__ import annotations

from motorctl_drivers.serial_link import (
    ACK,
    CMD,
    CONFIG,
    FLAG_ENABLE,
    FLAG_FAULT_RESET,
    QUERY,
    STATUS_FAULT,
    STATUS_ON,
    STATUS_REVISION_2,
    WATCHDOG_UNIT_S,
    FrameParser,
    SerialOptions,
    decode_body,
    encode_config,
    encode_error,
    encode_reply,
)
from motorctl_drivers.split_phase import counts_to_volts
from motorctl_emulators.device import Device, LateAnswers
from motorctl_emulators.plant_bank import PlantBank
from motorctl_emulators.stream import StreamEndpoint


class SerialDevice(Device):
    """Listens on ``driver.port`` (socket:// → a TCP server on that address; a path → a pty whose
    slave is linked there) and answers command and query frames for ``driver.address``.
    Faults: drop and bus_off (no answer), late (the reply after ``late_s`` and never before the
    next frame from the host: :class:`~motorctl_emulators.device.LateAnswers`), corrupt (bad
    CRC), stale (the previous reply), exception (an error frame, the command not applied),
    disconnect (close the connection).

    Revision 2 (the default): a channel's latched amplifier fault is cleared only by the
    rising edge of the command's fault-reset flag with the enable low, and the watchdog
    latches only a channel whose amplifier was on (the bank's reset input,
    :class:`~motorctl_emulators.plant_bank.PlantBank`); revision 1: any command with the
    enable low clears it and the watchdog latches every commanded channel.

    Raises:
        OSError: the endpoint cannot be opened.
    """

    def __init__(self, options: SerialOptions, axis_options: dict, bank: PlantBank):
        super().__init__(options, axis_options, bank)
        self.m_per_count = [axis_options[a].encoder_m_per_count for a in bank.names]
        self.index = {axis_options[a].node: i for i, a in enumerate(bank.names)}
        self.ep = StreamEndpoint(options.port)
        self.parser = FrameParser((CMD, QUERY, CONFIG))
        self._last_reply = None
        self.late = LateAnswers(bank)
        self.clock = bank.master_time(256)      # the master's time from the frames' seq
        self.play_revision(2)

    def play_revision(self, revision: int) -> None:
        """Answer as a device of protocol ``revision`` (1 or 2, docs/serial-protocol.md)."""
        if revision not in (1, 2):
            raise ValueError(f"serial protocol revision {revision!r}: 1 or 2")
        self.revision = revision
        self.bank.reset_input = [revision == 2] * len(self.bank.names)

    def _reply(self, seq: int, nodes) -> bytes:
        b = self.bank
        items = []
        for nd in nodes:
            i = self.index[nd]
            items.append((nd, (STATUS_FAULT if b.amp_fault[i] else 0) | (STATUS_ON if b.enabled[i] else 0)
                          | (STATUS_REVISION_2 if self.revision == 2 else 0), b.counts(i, self.m_per_count[i])))
        return encode_reply(self.options.address, seq, items)

    def poll(self, timeout_s: float) -> None:
        data = self.ep.wait(timeout_s)
        if not data:
            return
        b = self.bank
        address = self.options.address
        for kind, addr, seq, m, frame in self.parser.feed(data):
            self.late.release()                 # a late reply goes out before the next frame's
            if addr != address:
                continue
            named = decode_body(QUERY, m, frame) if kind == QUERY else \
                [it[0] for it in decode_body(CMD, m, frame)] if kind == CMD else []
            if len(set(named)) != len(named):    # a node twice in one frame: bad request, nothing applied
                self.ep.send(encode_error(address, seq, m, 1))
                continue
            if kind != CMD:
                self.clock.seen(seq)
            if kind == QUERY:
                nodes = [nd for nd in named if nd in self.index]
                self.ep.send(self._reply(seq, nodes) if nodes else encode_error(address, seq, m, 1))
                continue
            if kind == CONFIG:                 # the host sets the command watchdog
                units = decode_body(CONFIG, m, frame)[0]
                if units == 0:
                    self.ep.send(encode_error(address, seq, 1, 2))
                    continue
                b.watchdog_s = units * WATCHDOG_UNIT_S
                b.log(f"watchdog set to {b.watchdog_s * 1e3:g} ms by the host")
                self.ep.send(encode_config(address, seq, units, ACK))
                continue
            items = [it for it in decode_body(CMD, m, frame) if it[0] in self.index]
            nodes = [it[0] for it in items]
            if not items:                        # no known node: bad request, nothing applied
                self.ep.send(encode_error(address, seq, m, 1))
                continue
            fault = b.next_fault([self.index[nd] for nd in nodes])
            if fault == "exception":
                self.ep.send(encode_error(address, seq, m, 4))
                continue
            if fault == "disconnect":
                self.ep.disconnect()
                return
            periods = self.clock.periods(seq)
            for nd, flags, c in items:
                b.command(self.index[nd], counts_to_volts(c, self.options.voltage_full_scale_V, 16),
                          bool(flags & FLAG_ENABLE), periods, reset=bool(flags & FLAG_FAULT_RESET))
            reply = self._reply(seq, nodes)
            if fault in ("drop", "bus_off"):
                pass
            elif fault == "stale" and self._last_reply is not None:
                self.ep.send(self._last_reply)
            elif fault == "corrupt":
                bad = bytearray(reply)
                bad[-1] ^= 0xFF
                self.ep.send(bytes(bad))
            elif fault == "late":
                self.late.hold(self.ep.send, reply)
            else:
                self.ep.send(reply)
            self._last_reply = reply

    def close(self) -> None:
        self.ep.close()
