"""An emulated CiA 402 servo drive per axis on CANopen, built on canopen's device side
(``motorctl emulate --transport canopen``).

Each axis is a ``canopen.LocalNode`` with the object dictionary of
:func:`motorctl_drivers.canopen_cia402.cia402_object_dictionary`: canopen's SDO server answers
the host's set-up, its NMT slave follows NMT commands and produces the heartbeat (0x1017), its
PDO maps (``node.rpdo`` / ``node.tpdo``, configured by the host through SDO) receive the RPDO and
pack the TPDO. What a drive adds on top is here:

* the drive's power state machine (CiA 402-2 §6.3): the controlword received in the RPDO is
  applied at the next SYNC (transmission type 1, synchronous), with its transitions 2-12 and the
  fault reset on the rising edge of bit 7 (15); the statusword codes the state;
* cyclic synchronous torque (0x6060 = 10): at each SYNC the target torque 0x6071 [per mille of
  the rated torque] becomes the amplifier's input (the voltage of the plant behind it, by the
  driver's scale ``full_scale_permille`` ↔ ``voltage_full_scale_V``) while in Operation enabled,
  0 otherwise; the plant steps one loop period and the TPDO (statusword, position actual 0x6064)
  carries the position at the end of that period. This is the time-compressed device of every
  emulator here, paced by its master: a real drive samples its position at the SYNC, one
  period earlier, which costs the loop one period of delay (docs/drivers.md);
* EMCY (CiA 301 §7.2.7): an injected fault (``--fault emcy=CODE:AXIS:START``, START counting
  SYNCs) puts the drive through Fault reaction active into Fault with 0x603F = CODE and sends
  the EMCY; the fault reset sends the error-reset EMCY (code 0);
* the heartbeat consumer (0x1016) and the abort connection option code (0x6007): once the
  host's first heartbeat has come, none for the consumer time → the option's action
  (1: Fault with EMCY 0x8130, 2: Disable voltage, 3: Quick stop), the torque 0 at once; printed
  as ``heartbeat consumer X: ...`` with CLOCK_MONOTONIC times. This is the drive's watchdog;
  ``--watchdog`` is not used (the plant bank's command watchdog stays off).

Faults (``--fault``, START counting SYNCs): emcy, drop (no TPDO), late (the TPDO held back: sent
``--late`` seconds after its SYNC and never before the next SYNC, so it misses its cycle whatever
the host's scheduling, and comes in a burst with the next one), corrupt (a short TPDO), stale (the
previous TPDO again), bus_off / disconnect (the node neither applies nor answers).
Every state change is printed: ``X: Switch on disabled -> Ready to switch on (controlword
0x0006, statusword 0x0021)``.
"""

from __future__ import annotations

import math
import time
from functools import partial

from motorctl_drivers import cia402
from motorctl_drivers.can_bus import open_bus
from motorctl_drivers.canopen_cia402 import CanopenOptions, cia402_object_dictionary
from motorctl_emulators.cia402_drive import STATUSWORD, drive_transition
from motorctl_emulators.device import Device, LateAnswers
from motorctl_emulators.plant_bank import PlantBank

class _Drive:
    """One emulated drive: its LocalNode and the state canopen does not keep."""

    def __init__(self, node, axis_options):
        self.node = node
        self.opts = axis_options
        self.state = cia402.SWITCH_ON_DISABLED
        self.cw_prev = 0
        self.error_code = 0
        self.pdo_loaded = False
        self.consumer_node = 0
        self.consumer_s = 0.0
        self.last_host_hb = math.nan        # monotonic time of the host's last heartbeat
        self.last_tpdo = None
        self.silent = False


class Cia402Device(Device):
    """One emulated CiA 402 drive per axis of a ``type: canopen`` config, on its bus.

    Raises:
        OSError: the bus cannot be opened.
    """

    def __init__(self, options: CanopenOptions, axis_options: dict, bank: PlantBank):
        import canopen
        super().__init__(options, axis_options, bank)
        self.bus = open_bus(options)
        self.network = canopen.Network(self.bus)           # dispatched by poll(), no notifier thread
        self.drives: list[_Drive] = []
        for name in bank.names:
            o = axis_options[name]
            node = canopen.LocalNode(o.node_id, cia402_object_dictionary(o.node_id))
            self.network.add_node(node)
            d = _Drive(node, o)
            node.add_read_callback(lambda index, subindex, od, d=d: self._on_read(d, index, subindex))
            node.add_write_callback(lambda index, subindex, od, data, d=d: self._on_write(d, index, subindex, data))
            self.drives.append(d)
        self.network.subscribe(options.sync_cob_id, self._on_sync)
        self.network.subscribe(0x700 + options.host_node_id, self._on_host_heartbeat)
        self.syncs = 0
        self.late = LateAnswers(bank)                        # late TPDOs, released by the next SYNC
        for d in self.drives:                                # power on: boot-up, pre-operational
            d.node.nmt.send_command(0x81)
            d.node.nmt.send_command(0x80)

    # ------------------------------------------------------------------ object access
    def _statusword(self, d: _Drive) -> int:
        return STATUSWORD[d.state] | cia402.SW_REMOTE

    def _on_read(self, d: _Drive, index: int, subindex: int):
        i = self.drives.index(d)
        if index == cia402.STATUSWORD:
            return self._statusword(d)
        if index == cia402.POSITION_ACTUAL:
            return self._counts(i)
        if index == cia402.MODES_DISPLAY:
            return self._mode(d)
        if index == cia402.ERROR_CODE:
            return d.error_code
        if index == cia402.TORQUE_ACTUAL:          # what the amplifier applies, per mille
            return cia402.volts_to_permille(self.bank.applied_V[i], d.opts.voltage_full_scale_V,
                                            d.opts.full_scale_permille)
        return None

    def _mode(self, d: _Drive) -> int:
        raw = d.node.data_store.get(cia402.MODES_OF_OPERATION, {}).get(0)
        return int.from_bytes(raw, "little", signed=True) if raw else 0

    def _on_write(self, d: _Drive, index: int, subindex: int, data: bytes) -> None:
        if index == cia402.CONTROLWORD:          # by SDO (pre-operational): acts at once
            cw = int.from_bytes(data[:2], "little")
            i = self.drives.index(d)
            self._set_state(i, drive_transition(d.state, cw, d.cw_prev), cw)
            d.cw_prev = cw
        elif index == cia402.CONSUMER_HEARTBEAT and subindex == 1:
            v = int.from_bytes(data, "little")
            d.consumer_node = (v >> 16) & 0x7F
            d.consumer_s = (v & 0xFFFF) * 1e-3
            d.last_host_hb = math.nan      # monitoring starts with the next heartbeat (CiA 301)
        elif cia402.RPDO_COMM <= index <= cia402.TPDO_MAPPING + 3:
            d.pdo_loaded = False           # reload the PDO configuration before the next use

    def _counts(self, i: int) -> int:
        v = self.bank.counts(i, self.axis_options[self.bank.names[i]].encoder_m_per_count)
        return ((v + (1 << 31)) % (1 << 32)) - (1 << 31)      # INTEGER32 wraps

    # ------------------------------------------------------------------ the drive's behaviour
    def _set_state(self, i: int, new: int, cw: int) -> None:
        d = self.drives[i]
        if new != d.state:
            self.bank.log(f"{self.bank.names[i]}: {cia402.STATE_NAMES[d.state]} -> {cia402.STATE_NAMES[new]} "
                          f"(controlword 0x{cw:04X}, statusword 0x{STATUSWORD[new] | cia402.SW_REMOTE:04X})")
            if d.state == cia402.FAULT and new != cia402.FAULT:
                d.error_code = 0
                self._emcy(d, 0)           # error reset (CiA 301: the error has gone)
            d.state = new
        self.bank.amp_fault[i] = d.state in (cia402.FAULT, cia402.FAULT_REACTION_ACTIVE)

    def _emcy(self, d: _Drive, code: int) -> None:
        register = 0 if code == 0 else 0x01 | (0x02 if code >> 12 == 2 else 0) | (0x04 if code >> 12 == 3 else 0) \
            | (0x08 if code >> 12 == 4 else 0) | (0x10 if code >> 8 == 0x81 else 0)
        d.node.emcy.send(code, register, b"motor")

    def _fault(self, i: int, code: int, why: str) -> None:
        d = self.drives[i]
        d.error_code = code
        self.bank.log(f"{self.bank.names[i]}: fault 0x{code:04X} {cia402.error_meaning(code)} ({why}) at "
                      f"t={time.monotonic():.6f}")
        self._emcy(d, code)
        self._set_state(i, cia402.FAULT_REACTION_ACTIVE, d.cw_prev)
        self._zero(i)

    def _zero(self, i: int) -> None:
        self.bank.applied_V[i] = 0.0
        self.bank.enabled[i] = False

    def _load_pdos(self, d: _Drive) -> None:
        d.node.rpdo.read()                 # from its own dictionary, as the host configured it
        d.node.tpdo.read()
        d.pdo_loaded = True

    def _on_sync(self, can_id, data, timestamp) -> None:
        self.syncs += 1
        b = self.bank
        self.late.release()                # a late answer goes out before this SYNC's (a burst)
        for i, d in enumerate(self.drives):
            if d.silent or d.node.nmt.state != "OPERATIONAL":
                continue
            if not d.pdo_loaded:
                self._load_pdos(d)
            rp = next((m for m in d.node.rpdo.map.values() if m.enabled), None)
            tp = next((m for m in d.node.tpdo.map.values() if m.enabled), None)
            if rp is None or tp is None:
                continue
            cw = rp[cia402.CONTROLWORD].raw if rp.is_received else 0
            target = rp[cia402.TARGET_TORQUE].raw if rp.is_received else 0
            spec = b.next_fault_spec([i])
            kind = spec.kind if spec else None
            if kind in ("bus_off", "disconnect"):
                d.silent = True
                b.log(f"{b.names[i]}: node {d.opts.node_id} leaves the bus")
                continue
            if kind == "emcy":
                self._fault(i, spec.code, "injected")
            else:
                self._set_state(i, drive_transition(d.state, cw, d.cw_prev), cw)
            d.cw_prev = cw
            on = d.state == cia402.OPERATION_ENABLED and self._mode(d) == cia402.MODE_CST
            u = cia402.permille_to_volts(target, d.opts.voltage_full_scale_V, d.opts.full_scale_permille) if on else 0.0
            b.command(i, u, on)            # holds u for one period: the plant steps
            if not on:
                self._zero(i)
            b.amp_fault[i] = d.state in (cia402.FAULT, cia402.FAULT_REACTION_ACTIVE)
            tp[cia402.STATUSWORD].raw = self._statusword(d)
            tp[cia402.POSITION_ACTUAL].raw = self._counts(i)
            frame = bytes(tp.data)
            if kind == "drop":
                continue
            if kind == "stale" and d.last_tpdo is not None:
                self.network.send_message(tp.cob_id, d.last_tpdo)
            elif kind == "corrupt":
                self.network.send_message(tp.cob_id, frame[:2])
            elif kind == "late":
                self.late.hold(partial(self.network.send_message, tp.cob_id), frame)
            else:
                tp.transmit()
            d.last_tpdo = frame

    def _on_host_heartbeat(self, can_id, data, timestamp) -> None:
        now = time.monotonic()
        node = can_id - 0x700
        for d in self.drives:
            if d.consumer_s > 0 and d.consumer_node == node:
                d.last_host_hb = now

    def _check_consumers(self, act: bool = True) -> float:
        """Act on every expired heartbeat consumer (``act``; False: only look); return the
        seconds until the next check."""
        now = time.monotonic()
        due = 0.01
        for i, d in enumerate(self.drives):
            if not d.consumer_s > 0 or d.last_host_hb != d.last_host_hb:
                continue
            left = d.last_host_hb + d.consumer_s - now
            if left > 0 or not act:
                due = min(due, max(0.0, left))
                continue
            option = int.from_bytes(d.node.data_store.get(cia402.ABORT_CONNECTION, {}).get(0, b"\x01\x00"),
                                    "little", signed=True)
            self.bank.log(f"heartbeat consumer {self.bank.names[i]}: no heartbeat from node {d.consumer_node} "
                          f"for {d.consumer_s * 1e3:g} ms (last at t={d.last_host_hb:.6f}, now t={now:.6f}): "
                          f"abort connection option {option} ({cia402.ABORT_OPTIONS.get(option, '?')}): torque 0")
            d.last_host_hb = math.nan      # re-armed by the next heartbeat
            self.bank.watchdog_trips += 1
            self._zero(i)
            if option == 1:
                self._fault(i, 0x8130, "heartbeat consumer")
            elif option in (2, 3):
                self._set_state(i, cia402.SWITCH_ON_DISABLED if option == 2 else cia402.QUICK_STOP_ACTIVE, 0)
        return due

    # ------------------------------------------------------------------ Device
    def poll(self, timeout_s: float) -> None:
        # the consumers act only once what has come in is taken in: after a stall of this
        # process, heartbeats waiting in the socket still count (a drive's consumer runs on its
        # own, not behind its receive queue)
        due = self._check_consumers(act=False)
        msg = self.bus.recv(timeout=max(0.0, min(timeout_s, due)))
        while msg is not None:
            for d in self.drives:          # PDOs are (re)loaded as soon as the node is operational
                if not d.pdo_loaded and d.node.nmt.state == "OPERATIONAL":
                    self._load_pdos(d)
            if not msg.is_error_frame and not msg.is_remote_frame:
                self.network.notify(msg.arbitration_id, msg.data, msg.timestamp)
            msg = self.bus.recv(timeout=0)
        self._check_consumers()

    def serve(self, stop=None, duration_s: float | None = None) -> None:
        """As :meth:`Device.serve`, with the heartbeat consumers as the drive's watchdog (the
        plant bank's command watchdog is not used: a CiA 402 drive's is its consumer)."""
        end = time.monotonic() + duration_s if duration_s else math.inf
        try:
            while (stop is None or not stop()) and time.monotonic() < end:
                self.poll(0.005)
        finally:
            self.close()

    def close(self) -> None:
        for d in self.drives:
            try:
                d.node.nmt.stop_heartbeat()
            except Exception:  # noqa: BLE001
                pass
        if self.bus is not None:
            bus, self.bus = self.bus, None
            bus.shutdown()
