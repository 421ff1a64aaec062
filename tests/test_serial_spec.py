"""docs/serial-protocol.md as a specification: a device written in this file from that page alone
(its own CRC, framing and scaling; nothing imported from motorctl_drivers.serial_link) against the
production serial driver over a pty pair, closing a position loop (a PD law here, on a
simulated mass behind the device), with the watchdog config, the fault latch and the fault-reset
request of revision 2, an error frame and a garbage burst on the line; and the same device
playing revision 1, which the driver recognises."""

from __future__ import annotations

import os
import select
import struct
import threading
import time
import tty
from pathlib import Path

import numpy as np
import pytest

from motorctl.config import config_from_dict, load_yaml

CONFIGS = Path(__file__).resolve().parents[1] / "configs"


# --------------------------------------------------------------------------- the device (from the doc)
def spec_driver(d: dict):
    """The serial driver for the spec device's config ``d``, its set-up timeout 5 s: the device
    is a thread of this process, which a loaded host may hold off past the shipped 1 s (a
    device that does not answer at all is the driver's own tests' business)."""
    drv = config_from_dict(d, "<spec>", check_budget=False).make_driver()
    drv.CONFIGURE_TIMEOUT_S = 5.0
    return drv


def crc_ccitt_false(data: bytes) -> int:
    """CRC-16/CCITT-FALSE: poly 0x1021, init 0xFFFF, no reflection, no final XOR."""
    crc = 0xFFFF
    for b in data:
        crc ^= b << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1021) & 0xFFFF if crc & 0x8000 else (crc << 1) & 0xFFFF
    return crc


def seal(body: bytes) -> bytes:
    return body + crc_ccitt_false(body).to_bytes(2, "big")


LENGTH = {0xA5: lambda n: 6 + 4 * n, 0xA6: lambda n: 6 + n, 0xA7: lambda n: 8}
N_OK = {0xA5: range(1, 33), 0xA6: range(1, 33), 0xA7: range(1, 2)}


class SpecDevice:
    """A bridge with channels ``nodes``; each channel drives a mass of ``gain`` m/s² per volt,
    full scale 10 V, 0.5 µm per count, stepped ``dt`` per command (a device paced by its master).
    ``revision``: the protocol revision it speaks (the doc's table "Revisions")."""

    def __init__(self, fd: int, address: int, nodes, dt: float, gain: float = 2.0, revision: int = 2):
        self.fd, self.address, self.dt, self.gain = fd, address, dt, gain
        self.revision = revision
        self.x = {n: 0.0 for n in nodes}
        self.v = {n: 0.0 for n in nodes}
        self.u = {n: 0.0 for n in nodes}
        self.on = {n: False for n in nodes}
        self.fault = {n: False for n in nodes}
        self.reset_bit = {n: False for n in nodes}     # flags bit 1 of the channel's last command
        self.watchdog_s = 0.05
        self.last_cmd = None
        self.buf = bytearray()
        self.log: list[str] = []
        self.refuse_next = False
        self.refuse_query = False
        self.ignore_next = False        # the next command is lost on the way: neither applied nor answered
        self.garbage_next = False
        self.stop = threading.Event()

    def counts(self, n: int) -> int:
        return round(self.x[n] / 0.5e-6) & 0xFFFFFFFF

    def handle(self, frame: bytes) -> None:
        kind, addr, seq, n = frame[0], frame[1], frame[2], frame[3]
        if addr != self.address:
            return
        if kind == 0xA7:
            wd = struct.unpack_from("<H", frame, 4)[0]
            if wd == 0:
                os.write(self.fd, seal(bytes((0x5B, addr, seq, n, 2))))
                return
            self.watchdog_s = wd * 100e-6
            self.log.append(f"watchdog {wd}")
            os.write(self.fd, seal(bytes((0x5C, addr, seq, 1)) + struct.pack("<H", wd)))
            return
        named = [frame[4 + k] for k in range(n)] if kind == 0xA6 else [frame[4 + 4 * k] for k in range(n)]
        if len(set(named)) != len(named):                       # a node twice: bad request
            os.write(self.fd, seal(bytes((0x5B, addr, seq, n, 1))))
            return
        if kind == 0xA6:
            if self.refuse_query:
                os.write(self.fd, seal(bytes((0x5B, addr, seq, n, 3))))
                return
            nodes = [nd for nd in named if nd in self.x]
            if not nodes:                                       # no known node: bad request
                os.write(self.fd, seal(bytes((0x5B, addr, seq, n, 1))))
                return
            items = [(nd, self.status(nd), self.counts(nd)) for nd in nodes]
        else:
            if self.ignore_next:
                self.ignore_next = False
                return
            if self.refuse_next:
                self.refuse_next = False
                os.write(self.fd, seal(bytes((0x5B, addr, seq, n, 4))))
                return
            items = []
            for k in range(n):
                nd, flags, u = struct.unpack_from("<BBh", frame, 4 + 4 * k)
                if nd not in self.x:
                    continue
                latched = self.counts(nd)                       # 1. latch
                en, reset = bool(flags & 1), bool(flags & 2)
                if self.revision == 1 and not en:
                    self.fault[nd] = False                      # 2. revision 1: any enable 0 resets
                elif reset and not self.reset_bit[nd] and not en:
                    self.fault[nd] = False                      # 2. bit 1's rising edge with enable 0
                    self.log.append(f"fault reset {nd}")
                self.reset_bit[nd] = reset
                self.on[nd] = en and not self.fault[nd]         # 3. apply
                self.u[nd] = u / 32767 * 10.0 if self.on[nd] else 0.0
                items.append((nd, self.status(nd), latched))
            if not items:
                os.write(self.fd, seal(bytes((0x5B, addr, seq, n, 1))))
                return
            self.last_cmd = time.monotonic()
            for nd in self.x:                                    # the period of this command
                self.v[nd] += self.gain * self.u[nd] * self.dt
                self.x[nd] += self.v[nd] * self.dt
        body = bytes((0x5A, addr, seq, len(items))) + b"".join(struct.pack("<BBI", nd, st, c) for nd, st, c in items)
        if self.garbage_next:
            self.garbage_next = False
            os.write(self.fd, bytes((0x5A, addr, 0x5A, 0x33, 0xA6, 0x02)) + seal(body)[:-1] + b"\x00")
            return
        os.write(self.fd, seal(body))

    def status(self, nd: int) -> int:
        return (1 if self.fault[nd] else 0) | (2 if self.on[nd] else 0) | (4 if self.revision == 2 else 0)

    def check_watchdog(self) -> None:
        """Per channel in the doc; every channel here is commanded by every frame. It runs from the
        first command and while the host is idle too; revision 2 latches only a channel whose
        amplifier is on, revision 1 every one."""
        if self.last_cmd is not None and time.monotonic() - self.last_cmd > self.watchdog_s:
            for nd in self.x:
                if self.revision == 1 or self.on[nd]:
                    self.fault[nd], self.on[nd], self.u[nd] = True, False, 0.0
            self.last_cmd = None
            self.log.append("watchdog tripped")

    def expire_watchdog(self) -> None:
        """The host has been silent for longer than the watchdog (its last command moved back in
        time; the serving thread's next check trips the watchdog): no fixed sleep of the test."""
        if self.last_cmd is not None:
            self.last_cmd -= 2 * self.watchdog_s + 1.0

    def serve(self) -> None:
        while not self.stop.is_set():
            r, _, _ = select.select([self.fd], [], [], 0.005)
            self.check_watchdog()
            if not r:
                continue
            self.buf += os.read(self.fd, 4096)
            buf = self.buf
            while len(buf) >= 4:                                 # scan, wait, check (the doc's rules)
                kind, n = buf[0], buf[3]
                if kind not in LENGTH or n not in N_OK[kind]:
                    del buf[0]
                    continue
                size = LENGTH[kind](n)
                if len(buf) < size:
                    break
                frame = bytes(buf[:size])
                if crc_ccitt_false(frame[:-2]) != int.from_bytes(frame[-2:], "big"):
                    del buf[0]
                    continue
                del buf[:size]
                self.handle(frame)


# --------------------------------------------------------------------------- the test
#: the wait for an answer that is not made bad on purpose [s]: the device thread answers in
#: about a millisecond, but two spinning processes have held it off for more than 0.5 s
GOOD_ANSWER_WAIT_S = 5.0


def test_a_device_written_from_the_spec_closes_the_loop_over_a_pty(tmp_path):
    assert crc_ccitt_false(b"123456789") == 0x29B1                 # the doc's check value
    master, slave = os.openpty()
    tty.setraw(master)
    tty.setraw(slave)
    rate = 500.0
    dev = SpecDevice(master, address=1, nodes=(1, 2), dt=1.0 / rate)
    th = threading.Thread(target=dev.serve, daemon=True)
    th.start()
    d = load_yaml(CONFIGS / "gantry-serial.yaml")
    d["loop"]["rate_hz"] = rate
    d["loop"]["clock"] = "virtual"                                  # lockstep: the host waits for each reply
    # reply timeout and watchdog far above a loaded VM's stalls (the device coasts once its
    # watchdog cuts the drive): the verdict must not depend on them
    d["driver"].update(port=os.ttyname(slave), baudrate=115200, timeout_s=0.05, wait="select",
                       watchdog_s=1.0, round_trip_s=0.0005)
    drv = spec_driver(d)
    try:
        drv.open()
        assert dev.log[0] == "watchdog 10000" and dev.watchdog_s == pytest.approx(1.0)
        assert drv.describe()["watchdog"] == "1000 ms (config frame, acknowledged)"
        target = np.array([0.002, -0.001])                         # 2 mm and -1 mm
        y0 = drv.position_m.copy()
        kp, kd = 2000.0, 60.0                                       # V/m, V s/m on a 2 m/s^2/V mass
        prev = np.zeros(2)
        errs = 0
        for k in range(600):                                        # bounded: 1.2 s of plant time
            e = target - (drv.position_m - y0)
            u = np.clip(kp * e + kd * (e - prev) * rate, -10.0, 10.0)
            prev = e
            if k == 300:
                dev.refuse_next = True                             # one error frame (code 4)
            if k == 350:
                dev.garbage_next = True                            # junk + a reply with a bad CRC
            # the two answers made bad on purpose wait out 50 ms; every good one is waited for
            # far beyond a loaded host's stall of the device thread
            drv.timeout_s = 0.05 if k in (300, 350) else GOOD_ANSWER_WAIT_S
            drv.write(u, np.ones(2, dtype=bool))
            time.sleep(0.001)
            drv.read()
            errs += int(drv.read_error.any())
        final = drv.position_m - y0
        assert np.all(np.abs(final - target) < 50e-6), final        # settled within 50 um
        assert dev.on == {1: True, 2: True} and not any(dev.fault.values())
        assert drv.counters["exceptions"] == 1 and drv.counters["bad_frames"] >= 1, drv.counters
        assert errs <= 2, (errs, drv.counters)                      # the two injected
        # the watchdog: the host falls silent while both channels drive, the device latches both
        dev.expire_watchdog()
        _latched(dev)
        assert "watchdog tripped" in dev.log and all(dev.fault.values())
        drv.timeout_s = GOOD_ANSWER_WAIT_S
        _cycles(drv, np.ones(2, dtype=bool), 1)
        assert drv.amp_fault.all()                                  # status bit 0 in the reply
        _cycles(drv, np.zeros(2, dtype=bool), 3)                    # enable 0 alone: still latched
        assert drv.amp_fault.all() and not any(ln.startswith("fault reset") for ln in dev.log)
        assert drv.reset_fault(0) and drv.reset_fault(1)            # the operator's reset: flags bit 1
        _cycles(drv, np.zeros(2, dtype=bool), 2)
        assert not drv.amp_fault.any() and dev.u == {1: 0.0, 2: 0.0}
        assert dev.log.count("fault reset 1") == dev.log.count("fault reset 2") == 1, dev.log
    finally:
        drv.close()
        dev.stop.set()
        th.join(timeout=2)
        os.close(master)
        os.close(slave)


@pytest.fixture
def spec_device():
    """A :class:`SpecDevice` (address 1, channels 1 and 2, 500 Hz) serving one end of a pty pair
    from a thread; yields (device, a serial config dict for the other end)."""
    master, slave = os.openpty()
    tty.setraw(master)
    tty.setraw(slave)
    dev = SpecDevice(master, address=1, nodes=(1, 2), dt=1.0 / 500)
    th = threading.Thread(target=dev.serve, daemon=True)
    th.start()
    d = load_yaml(CONFIGS / "gantry-serial.yaml")
    d["loop"]["rate_hz"] = 500.0
    d["loop"]["clock"] = "virtual"                                  # lockstep: the host waits for each reply
    d["driver"].update(port=os.ttyname(slave), baudrate=115200, timeout_s=0.05, wait="select",
                       watchdog_s=1.0, round_trip_s=0.0005)
    try:
        yield dev, d
    finally:
        dev.stop.set()
        th.join(timeout=2)
        os.close(master)
        os.close(slave)


def test_a_latched_fault_stays_across_set_ups_until_the_operators_reset(spec_device):
    """Revision 2 (docs/serial-protocol.md): a run that ends with its stop leaves nothing latched
    (its watchdog latches no disabled channel); a host that falls silent while both channels
    drive leaves both latched, and that stays: the stop's enable 0 does not clear it, the next
    set-up sends no reset, warns naming each channel's status, and the refusal names it and the
    command; idle cycles do not clear it; the operator's reset of X clears X alone; the set-up
    after that finds Y alone. Each stop is confirmed by the status read back."""
    from motorctl.driver import drive_fault_refusal
    dev, d = spec_device
    drv = _stopped_after(spec_driver(d), dev, enabled=True, lose_first_stop=True)
    assert drv.stop_attempts >= 2, drv.stop_attempts       # the lost stop command and at least one more
    assert drv.stop_checks[0].held == "node 1 status 0x04: amplifier off, 0 V", drv.stop_checks
    dev.expire_watchdog()
    _idle_checked(dev)
    assert not any(dev.fault.values()), dev.log             # a clean stop: nothing latched
    drv = spec_driver(d)
    try:
        drv.open()
        assert not [n for n in drv.notices if "warning" in n], drv.notices
        _cycles(drv, np.ones(2, dtype=bool), 20)
        dev.expire_watchdog()                                # the host falls silent while driving
        _latched(dev)
    finally:
        drv.close()                                          # its stop comes later: enable 0, no reset
    assert all(dev.fault.values()), dev.log
    drv = spec_driver(d)
    try:
        drv.open()
        state = {a: f"serial device 1 node {n}: amplifier fault latched, amplifier off (status 0x05)"
                 for a, n in (("X", 1), ("Y", 2))}
        for a in ("X", "Y"):
            assert f"warning: axis {a}: set-up found the drive in its fault ({state[a]}); it stays there until " \
                   f"the operator's 'motorctl fault-reset'" in drv.notices, drv.notices
        assert not any("cleared" in n or "revision 1" in n for n in drv.notices), drv.notices
        _cycles(drv, np.zeros(2, dtype=bool), 10)            # the run's idle cycles
        assert drv.amp_fault.all() and drv.describe()["protocol_revision"] == 2
        assert drive_fault_refusal(drv, config="cfg.yaml") == "; ".join(
            f"axis {a}'s drive is in its fault ({state[a]}); it stays there until the operator resets it: "
            f"'motorctl fault-reset --config cfg.yaml {a}' (no daemon running) or 'motorctl fault-reset {a}' "
            f"(through the daemon)" for a in ("X", "Y"))
        assert drv.reset_fault(0)
        _cycles(drv, np.zeros(2, dtype=bool), 3)
        assert list(drv.amp_fault) == [False, True] and drv.drive_state(0).endswith("no fault, amplifier off "
                                                                                     "(status 0x04)")
    finally:
        drv.close()
    assert dev.fault == {1: False, 2: True} and dev.log.count("fault reset 1") == 1, dev.log
    drv = spec_driver(d)
    try:
        drv.open()
    finally:
        drv.close()
    assert [n.split(":")[1] for n in drv.notices if "set-up found the drive" in n] == [" axis Y"], drv.notices


def test_a_revision_1_device_is_named_and_cleared_as_before(spec_device):
    """The same device playing revision 1 (status bit 2 clear; any command with enable 0 clears a
    latched fault; its watchdog latches a disabled channel too): the driver does not pretend to
    keep the fault: a warning names the revision and says the fault cannot stay latched, the
    old reset clears what the watchdog latched, with a notice, and the axes start unfaulted."""
    dev, d = spec_device
    dev.revision = 1
    _stopped_after(spec_driver(d), dev, enabled=False)
    dev.expire_watchdog()
    _latched(dev)                                           # disabled, and latched all the same
    drv = spec_driver(d)
    try:
        drv.open()
        assert not drv.amp_fault.any() and drv.describe()["protocol_revision"] == 1
        warn = [n for n in drv.notices if n.startswith("warning: ")]
        assert warn == ["warning: serial device 1 is of protocol revision 1 (its replies leave status bit 2 "
                        "clear): a command with enable 0 clears its latched amplifier fault, so a fault it "
                        "latched (X, Y: its watchdog after a host went away, an over-current) cannot stay "
                        "latched until the operator's 'motorctl fault-reset'; revision 2 keeps it "
                        "(docs/serial-protocol.md, Revisions)"], drv.notices
        assert any("at set-up, cleared the amplifier fault latched on X, Y" in n for n in drv.notices), drv.notices
        assert drv.reset_fault(0)                           # every disabled command is its reset
    finally:
        drv.close()


def _cycles(drv, enable, n: int) -> None:
    """``n`` exchanges at 0.5 V / -0.5 V with ``enable`` (bool, (2,)), each answer waited for
    (up to :data:`GOOD_ANSWER_WAIT_S`: far beyond a loaded host's stall of the device thread)."""
    timeout, drv.timeout_s = drv.timeout_s, GOOD_ANSWER_WAIT_S
    try:
        for _ in range(n):                                  # bounded
            drv.write(np.array([0.5, -0.5]), enable)
            time.sleep(0.001)
            drv.read()
    finally:
        drv.timeout_s = timeout


def _stopped_after(drv, dev, enabled: bool, lose_first_stop: bool = False):
    """``drv`` set up, 20 cycles (``enabled``), then its confirmed stop and close; returns it."""
    try:
        drv.open()
        _cycles(drv, np.full(2, enabled), 20)
        assert not drv.amp_fault.any() and dev.on == {1: enabled, 2: enabled}
        dev.ignore_next = lose_first_stop
        checks = drv.deactivate()
    finally:
        drv.close()
    assert [c.confirmed for c in checks] == [True, True], checks
    assert dev.on == {1: False, 2: False} and dev.u == {1: 0.0, 2: 0.0}
    return drv


def _idle_checked(dev, bound_s: float = 10.0) -> None:
    """Until the device's thread has run its watchdog check after :meth:`SpecDevice.expire_watchdog`."""
    end = time.monotonic() + bound_s
    while dev.last_cmd is not None and time.monotonic() < end:
        time.sleep(0.02)


def _latched(dev, bound_s: float = 10.0) -> None:
    """Idle until the device's thread has latched every channel on its watchdog (1 s; bounded:
    a hang), not a fixed sleep (1.3 s) its thread may be starved past on a loaded host."""
    end = time.monotonic() + bound_s
    while not all(dev.fault.values()) and time.monotonic() < end:
        time.sleep(0.02)


def test_an_error_frame_at_set_up_is_the_devices_error_at_once(spec_device):
    dev, d = spec_device
    dev.refuse_query = True
    drv = spec_driver(d)
    drv.CONFIGURE_TIMEOUT_S = 60.0        # waiting it out would take a minute: far from any host's stall
    t0 = time.monotonic()
    with pytest.raises(ConnectionError) as err:
        drv.open()
    assert time.monotonic() - t0 < 20.0, "waited for the set-up timeout instead of taking the error frame"
    assert "the device refused the position query: error frame code 3 (not allowed now)" in str(err.value)
