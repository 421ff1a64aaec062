"""Emulated EtherCAT slaves behind a veth pair (``motorctl emulate --transport ethercat``).

The device answers raw EtherCAT frames (EtherType 0x88A4) on the other end of the veth pair
whose one end is the driver's ``ifname`` (found with iproute2; the test or the user creates the
pair, e.g. inside a network namespace). Every slave is an
:class:`~motorctl_emulators.esc.Esc` with the application of its profile:

* ``profile: cia402`` axes: a CiA 402 servo drive per axis at its ``slave`` position, with a
  CoE mailbox (SDO expedited, normal and segmented upload, expedited and normal download, SDO
  abort codes of ETG.1000.6 Table 40, emergency messages) and an object dictionary whose PDO
  mapping (0x1600, 0x1A00) and assignment (0x1C12, 0x1C13) the master writes in PRE-OP. In OP
  and Operation enabled with modes of operation 10 (cyclic synchronous torque), the target
  torque 0x6071 [per mille of the rated torque] is the amplifier input through the axis's
  ``full_scale_permille`` ↔ ``voltage_full_scale_V``; the statusword follows the power state
  machine of :mod:`~motorctl_emulators.cia402_drive`.
* ``profile: io`` axes: the paper's amplifier behind I/O terminals: an incremental encoder
  terminal (EL5101 type: 32-bit counter, status, latch), a ±10 V analog output terminal (EL4132
  type: 2 channels of 16 bits), a digital output terminal (EL2008 type: 8 channels, the
  amplifier enable). Positions no axis names are couplers (EK1100 type, no process data).

The plant (:class:`~motorctl_emulators.plant_bank.PlantBank`) steps inside the process-data
datagram, between the write of the outputs and the read of the inputs, once any slave is in
OP (the frames of the set-up, in SAFE-OP, read the inputs without stepping: the position
queries of the other emulators). The master's time:
without SYNC0 one plant period per process-data frame; with SYNC0 active (the master wrote
0x0981 = 3) the plant steps as many periods as SYNC0 events have passed on the slave's clock
since the last frame: the periods without a frame coast on what the outputs held, and of two
frames within one period the later one's outputs are applied at the next SYNC0 (as a drive
latches its outputs at SYNC0). Plant time is then the slave's clock, as on a machine.

SM watchdog (0x0420 × (0x0400 + 2) × 40 ns, SM2's watchdog bit): no outputs for that long in
OP → the outputs to 0 (drive: Fault 0x8100 with an emergency; terminals: 0 V, enable off) while
the SM buffer keeps the last data, as an ESC's does; the drive, the EL5101 and the EL4132 go to
SAFE-OP with AL status code 0x001B, the EL2008 (outputs driven by its ESC) stays in OP and
drives again with the next frame's outputs. In SAFE-OP a logical write is not taken and not
counted in the working counter (only the inputs are). The plant bank's command watchdog is not
used.

Faults (``--fault KIND:AXIS:START:COUNT``, START counting process-data frames): drop (no
answer), late (answer after ``--late``), corrupt (the axis's slaves do not count: a short
working counter), emcy[=CODE] (the drive faults with that error code, 0x603F and an emergency
message), disconnect (no answer from then on).
"""

from __future__ import annotations

import math
import re
import select
import socket
import struct
import time

from motorctl_drivers import cia402
from motorctl_drivers.ethercat import (
    EL2008,
    EL4132,
    EL5101,
    EK1100,
    VENDOR_BECKHOFF,
    EthercatOptions,
    segment_roles,
)
from motorctl_drivers.split_phase import counts_to_volts
from motorctl_emulators import esc as E
from motorctl_emulators.cia402_drive import STATUSWORD, drive_transition
from motorctl_emulators.device import Device
from motorctl_emulators.plant_bank import PlantBank

#: the emulated drive's identity (a drive from the market has its vendor's)
VENDOR_MOTORCTL, PRODUCT_CIA402 = 0x00000DC2, 0x00000192
MBX_SIZE = 128
MBX_OUT, MBX_IN, PD_OUT, PD_IN = 0x1000, 0x1080, 0x1100, 0x1180
#: the error code of a drive whose SM watchdog ran out (CiA 301: communication)
WATCHDOG_ERROR_CODE = 0x8100

# SDO abort codes (ETG.1000.6 Table 40; CiA 301 Table 22)
ABORT_UNSUPPORTED = 0x06010000
ABORT_WRITE_ONLY = 0x06010001
ABORT_READ_ONLY = 0x06010002
ABORT_SI0_NOT_ZERO = 0x06010003
ABORT_CA_UNSUPPORTED = 0x06010004
ABORT_NO_OBJECT = 0x06020000
ABORT_NOT_MAPPABLE = 0x06040041
ABORT_PDO_LENGTH = 0x06040042
ABORT_LENGTH = 0x06070010
ABORT_NO_SUBINDEX = 0x06090011
ABORT_VALUE_RANGE = 0x06090030
ABORT_STATE = 0x08000022
ABORT_COMMAND = 0x05040001


class _Entry:
    __slots__ = ("bits", "signed", "access", "mappable", "value")

    def __init__(self, bits, signed=False, access="rw", mappable=False, value=0):
        self.bits, self.signed, self.access, self.mappable, self.value = bits, signed, access, mappable, value


class SdoAbort(Exception):
    def __init__(self, code):
        super().__init__(f"SDO abort 0x{code:08X}")
        self.code = code


class CoeDrive(E.SlaveApp):
    """A CiA 402 drive's application: object dictionary, CoE SDO server, power state machine."""

    def __init__(self, serial: int):
        od: dict[tuple[int, int], _Entry] = {}
        ro, rw = "ro", "rw"

        def add(index, sub, bits, signed=False, access=rw, mappable=False, value=0):
            od[(index, sub)] = _Entry(bits, signed, access, mappable, value)

        add(0x1000, 0, 32, access=ro, value=0x00020000 | cia402.PROFILE_402)
        add(0x1001, 0, 8, access=ro, mappable=True)
        add(0x1008, 0, 0, access=ro, value=b"motorctl emulated CiA 402 servo drive (EtherCAT CoE, "
                                          b"cyclic synchronous torque), firmware 1.0, "
                                          b"object dictionary after CiA 402-2 and ETG.6010")
        for sub, v in enumerate((4, VENDOR_MOTORCTL, PRODUCT_CIA402, 1, serial)):
            add(0x1018, sub, 8 if sub == 0 else 32, access=ro, value=v)
        for index, default in ((0x1600, [0x60400010]), (0x1A00, [0x60410010])):
            add(index, 0, 8, value=len(default))
            for k in range(1, 9):
                add(index, k, 32, value=default[k - 1] if k <= len(default) else 0)
        for sub, v in enumerate((4, 1, 2, 3, 4)):
            add(0x1C00, sub, 8, access=ro, value=v)
        for index, pdo in ((0x1C12, 0x1600), (0x1C13, 0x1A00)):
            add(index, 0, 8, value=1)
            add(index, 1, 16, value=pdo)
        add(0x603F, 0, 16, access=ro, mappable=True)
        add(0x6040, 0, 16, mappable=True)
        add(0x6041, 0, 16, access=ro, mappable=True)
        add(0x6060, 0, 8, signed=True, mappable=True)
        add(0x6061, 0, 8, signed=True, access=ro, mappable=True)
        add(0x6064, 0, 32, signed=True, access=ro, mappable=True)
        add(0x6071, 0, 16, signed=True, mappable=True)
        add(0x6072, 0, 16, value=3000)
        add(0x6076, 0, 32, value=100000)
        add(0x6077, 0, 16, signed=True, access=ro, mappable=True)
        add(0x6502, 0, 32, access=ro, value=cia402.SUPPORTED_CST_BIT | (1 << 7) | (1 << 8))
        self.od = od
        self.state = cia402.SWITCH_ON_DISABLED
        self.cw_prev = 0
        self.upload: tuple[bytes, int, int] | None = None     # segmented upload in progress
        self.counter = 0
        self._layout()

    # ----------------------------------------------------------------- mapping
    def _mapped(self, pdo: int) -> list[tuple[int, int, int]]:
        n = self.od[(pdo, 0)].value
        out = []
        for k in range(1, n + 1):
            v = self.od[(pdo, k)].value
            out.append((v >> 16, (v >> 8) & 0xFF, v & 0xFF))
        return out

    def _assigned(self, assign: int) -> list[tuple[int, int, int]]:
        out = []
        for k in range(1, self.od[(assign, 0)].value + 1):
            out += self._mapped(self.od[(assign, k)].value)
        return out

    def _layout(self) -> None:
        """Take the assigned mapping as the process data layout (at PRE-OP → SAFE-OP)."""
        self.rx = self._assigned(0x1C12)
        self.tx = self._assigned(0x1C13)

    @property
    def outputs_size(self) -> int:
        return sum(b for *_, b in self._assigned(0x1C12)) // 8

    @property
    def inputs_size(self) -> int:
        return sum(b for *_, b in self._assigned(0x1C13)) // 8

    def state_change(self, old, new):
        if old == E.PREOP and new == E.SAFEOP:
            self._layout()
        if new < E.OP and self.state == cia402.OPERATION_ENABLED:
            self.state = cia402.SWITCH_ON_DISABLED       # leaving OP: the power stage goes off
        return 0

    def watchdog_expired(self):
        self.fault(WATCHDOG_ERROR_CODE)

    def fault(self, code: int) -> None:
        """Fault reaction → Fault with error code ``code`` in 0x603F and an emergency message."""
        self.state = cia402.FAULT
        self.od[(0x603F, 0)].value = code
        self.od[(0x1001, 0)].value = 0x81 if code & 0xFF00 == 0x8100 else 0x01
        self.esc.post(self._coe(1, struct.pack("<HB5s", code, self.od[(0x1001, 0)].value, b"")))

    # ----------------------------------------------------------------- cyclic
    def cycle(self, outputs: bytes, op: bool) -> tuple[float, bool]:
        """Apply the outputs (in OP) and step the power state machine; returns (u [V] the
        amplifier gets, whether it is on) for the axis's scale, the caller's."""
        vals = self._unpack(outputs, self.rx)
        cw = vals.get(0x6040, 0) if op else 0
        if op:
            for index, sub, _bits in self.rx:
                e = self.od[(index, sub)]
                if e.access == "rw":
                    e.value = vals[index]
        was_fault = self.state == cia402.FAULT
        if op:
            self.state = drive_transition(self.state, cw, self.cw_prev)
        elif self.state != cia402.FAULT:
            self.state = cia402.SWITCH_ON_DISABLED          # outside OP the power stage is off
        if was_fault and self.state != cia402.FAULT:        # fault reset: the error-reset emergency
            self.od[(0x603F, 0)].value = 0
            self.od[(0x1001, 0)].value = 0
            self.esc.post(self._coe(1, struct.pack("<HB5s", 0, 0, b"")))
        self.cw_prev = cw
        mode = self.od[(0x6060, 0)].value
        self.od[(0x6061, 0)].value = mode
        on = op and self.state == cia402.OPERATION_ENABLED and mode == cia402.MODE_CST
        return (self.od[(0x6071, 0)].value if on else 0), on

    def set_actual(self, position: int, torque: int) -> None:
        od = self.od
        od[(0x6041, 0)].value = STATUSWORD[self.state] | cia402.SW_REMOTE
        od[(0x6064, 0)].value = ((position + 2**31) % 2**32) - 2**31
        od[(0x6077, 0)].value = torque
        self.esc.set_inputs(self._pack(self.tx))

    def _unpack(self, data: bytes, layout) -> dict[int, int]:
        out, off = {}, 0
        for index, sub, bits in layout:
            n = bits // 8
            out[index] = int.from_bytes(data[off:off + n], "little", signed=self.od[(index, sub)].signed)
            off += n
        return out

    def _pack(self, layout) -> bytes:
        return b"".join((self.od[(i, s)].value & ((1 << b) - 1)).to_bytes(b // 8, "little") for i, s, b in layout)

    # ----------------------------------------------------------------- CoE
    def _coe(self, service: int, body: bytes) -> bytes:
        self.counter = self.counter % 7 + 1
        coe = struct.pack("<H", service << 12) + body
        return struct.pack("<HHBB", len(coe), 0, 0, 0x03 | (self.counter << 4)) + coe

    def _abort(self, index, sub, code) -> bytes:
        return self._coe(3, struct.pack("<BHBI", 0x80, index, sub, code))

    def mailbox(self, request: bytes) -> list[bytes]:
        length, _addr, _chan, mtype = struct.unpack_from("<HHBB", request, 0)
        if mtype & 0x0F != 0x03:                 # only CoE: a mailbox error "unsupported protocol"
            return [struct.pack("<HHBBHH", 4, 0, 0, 0x00, 0x01, 0x02)]
        coe = request[6:6 + length]
        if len(coe) < 2 or coe[1] >> 4 != 2:      # not an SDO request
            return [struct.pack("<HHBBHH", 4, 0, 0, 0x00, 0x01, 0x05)]
        cmd = coe[2]
        index, sub = struct.unpack_from("<HB", coe, 3)
        try:
            if cmd & 0xE0 == 0x60:                                # upload segment request
                return [self._upload_segment(cmd)]
            if cmd & 0x10:
                raise SdoAbort(ABORT_CA_UNSUPPORTED)
            if cmd & 0xE0 == 0x40:                                # initiate upload
                return [self._upload(index, sub)]
            if cmd & 0xE0 == 0x20:                                # initiate download
                if cmd & 0x02:                                    # expedited
                    n = 4 - ((cmd >> 2) & 3) if cmd & 0x01 else 4
                    data = coe[6:6 + n]
                else:
                    size = struct.unpack_from("<I", coe, 6)[0]
                    data = coe[10:10 + size]
                    if len(data) != size:
                        raise SdoAbort(ABORT_LENGTH)
                self._download(index, sub, bytes(data))
                return [self._coe(3, struct.pack("<BHBI", 0x60, index, sub, 0))]
            raise SdoAbort(ABORT_COMMAND)
        except SdoAbort as exc:
            self.upload = None
            return [self._abort(index, sub, exc.code)]

    def _entry(self, index, sub) -> _Entry:
        if (index, sub) in self.od:
            return self.od[(index, sub)]
        if any(i == index for i, _ in self.od):
            raise SdoAbort(ABORT_NO_SUBINDEX)
        raise SdoAbort(ABORT_NO_OBJECT)

    def _upload(self, index, sub) -> bytes:
        e = self._entry(index, sub)
        data = e.value if isinstance(e.value, bytes) else \
            (e.value & ((1 << e.bits) - 1)).to_bytes(e.bits // 8, "little")
        if len(data) <= 4:
            cmd = 0x43 | ((4 - len(data)) << 2)
            return self._coe(3, struct.pack("<BHB", cmd, index, sub) + data + bytes(4 - len(data)))
        if len(data) <= MBX_SIZE - 6 - 10:                   # normal: the data in the response
            return self._coe(3, struct.pack("<BHBI", 0x41, index, sub, len(data)) + data)
        self.upload = (data, index, sub)                     # segmented: the size, then segments
        return self._coe(3, struct.pack("<BHBI", 0x41, index, sub, len(data)))

    def _upload_segment(self, cmd) -> bytes:
        if self.upload is None:
            raise SdoAbort(ABORT_COMMAND)
        rest, index, sub = self.upload
        room = MBX_SIZE - 6 - 3
        seg, rest = rest[:room], rest[room:]
        last = not rest
        self.upload = None if last else (rest, index, sub)
        toggle = cmd & 0x10
        pad = max(0, 7 - len(seg))
        c = toggle | (pad << 1) | (0x01 if last else 0)
        return self._coe(3, bytes((c,)) + seg + bytes(pad))

    def _download(self, index, sub, data: bytes) -> None:
        e = self._entry(index, sub)
        if e.access == "ro":
            raise SdoAbort(ABORT_READ_ONLY)
        if isinstance(e.value, bytes) or len(data) != e.bits // 8:
            raise SdoAbort(ABORT_LENGTH)
        v = int.from_bytes(data, "little", signed=e.signed)
        pdo_objects = (0x1600, 0x1A00, 0x1C12, 0x1C13)
        if index in pdo_objects and self.esc.state != E.PREOP:
            raise SdoAbort(ABORT_STATE)
        if index in pdo_objects and sub > 0 and self.od[(index, 0)].value != 0:
            raise SdoAbort(ABORT_SI0_NOT_ZERO)
        if index in (0x1600, 0x1A00) and sub == 0:
            if v > 8:
                raise SdoAbort(ABORT_VALUE_RANGE)
            bits = 0
            for k in range(1, v + 1):
                m = self.od[(index, k)].value
                target = (m >> 16, (m >> 8) & 0xFF)
                t = self.od.get(target)
                if t is None or not t.mappable or t.bits != m & 0xFF or \
                        (index == 0x1600 and t.access == "ro"):
                    raise SdoAbort(ABORT_NOT_MAPPABLE)
                bits += t.bits
            if bits > 8 * 64:
                raise SdoAbort(ABORT_PDO_LENGTH)
        if index in (0x1C12, 0x1C13) and sub > 0 and v not in ((0x1600,) if index == 0x1C12 else (0x1A00,)):
            raise SdoAbort(ABORT_VALUE_RANGE)
        if index in (0x1C12, 0x1C13) and sub == 0 and v > 1:
            raise SdoAbort(ABORT_VALUE_RANGE)
        if index == 0x6060 and v != cia402.MODE_CST and v != 0:
            raise SdoAbort(ABORT_VALUE_RANGE)
        e.value = v


class Terminal(E.SlaveApp):
    """An I/O terminal's application: fixed PDOs (from the SII), outputs as the master wrote them.

    ``leaves_op_on_watchdog``: False for a terminal whose ESC drives the outputs itself (EL2008
    type: no microcontroller; on a watchdog trip its pins go to 0 and it stays in OP).
    """

    def __init__(self, outputs_size: int, inputs_size: int, leaves_op_on_watchdog: bool = True):
        self.outputs_size, self.inputs_size = outputs_size, inputs_size
        self.leaves_op_on_watchdog = leaves_op_on_watchdog

    def watchdog_expired(self):
        pass                                         # the ESC's output pins are 0: 0 V, enable off


def _drive_esc(serial: int) -> E.Esc:
    app = CoeDrive(serial)
    syncms = [(MBX_OUT, MBX_SIZE, 0x26, E.SM_MBX_OUT), (MBX_IN, MBX_SIZE, 0x22, E.SM_MBX_IN),
              (PD_OUT, 0, 0x64, E.SM_PD_OUT), (PD_IN, 0, 0x20, E.SM_PD_IN)]
    sii = E.build_sii(vendor_id=VENDOR_MOTORCTL, product_code=PRODUCT_CIA402, revision=1, serial=serial,
                      name="motorctl CiA402 drive", mailbox=(MBX_OUT, MBX_SIZE, MBX_IN, MBX_SIZE),
                      syncms=syncms, coe_details=0x01 | 0x04 | 0x08)
    return E.Esc(sii, app, syncms, dc=True)


def _terminal_esc(product: int, serial: int) -> E.Esc:
    name, out_entries, in_entries = {
        EK1100: ("EK1100 EtherCAT coupler", [], []),
        EL5101: ("EL5101 incremental encoder interface",
                 [(0x7000, 1, 16), (0x7000, 2, 32)], [(0x6000, 1, 16), (0x6000, 2, 32), (0x6000, 3, 32)]),
        EL4132: ("EL4132 2Ch. Ana. Output +/-10V", [(0x7000, 1, 16), (0x7010, 1, 16)], []),
        EL2008: ("EL2008 8Ch. Dig. Output 24V", [(0x7000 + 0x10 * k, 1, 1) for k in range(8)], []),
    }[product]
    out_size = sum(b for *_, b in out_entries) // 8
    in_size = sum(b for *_, b in in_entries) // 8
    syncms, rx, tx = [], [], []
    if out_size:
        syncms.append((PD_OUT, out_size, 0x64, E.SM_PD_OUT))
        rx = [(0x1600, len(syncms) - 1, out_entries)]
    if in_size:
        syncms.append((PD_IN, in_size, 0x20, E.SM_PD_IN))
        tx = [(0x1A00, len(syncms) - 1, in_entries)]
    sii = E.build_sii(vendor_id=VENDOR_BECKHOFF, product_code=product, revision=0x00100000, serial=serial,
                      name=name, mailbox=None, syncms=syncms, txpdos=tx, rxpdos=rx)
    return E.Esc(sii, Terminal(out_size, in_size, leaves_op_on_watchdog=product != EL2008), syncms,
                 dc=product != EK1100)


def veth_peer(ifname: str) -> str:
    """The other end of the veth pair ``ifname`` belongs to, as iproute2 names it in this
    network namespace (``ip -o link show dev IFNAME``: ``N: IFNAME@PEER: ...``; sysfs would show
    the namespace /sys was mounted in, not this one).

    Raises:
        OSError: no such interface, or it is not one end of a veth pair in this namespace.
    """
    import subprocess
    try:
        out = subprocess.run(["ip", "-o", "link", "show", "dev", ifname], capture_output=True, text=True,
                             timeout=5).stdout
    except (OSError, subprocess.TimeoutExpired) as exc:
        raise OSError(f"EtherCAT emulator: cannot ask iproute2 about {ifname!r} ({exc})") from None
    m = re.match(r"\d+: ([^:@]+)@([^:]+):", out)
    if not out:
        raise OSError(f"EtherCAT emulator: no network interface {ifname!r} here")
    if not m or m.group(2).startswith("if"):
        raise OSError(f"EtherCAT emulator: {ifname!r} is not one end of a veth pair in this network namespace "
                      f"(create one: ip link add {ifname} type veth peer name {ifname}-slave)")
    return m.group(2)


class EthercatDevice(Device):
    """The emulated EtherCAT segment of a ``type: ethercat`` config (see the module docstring).

    Raises:
        OSError: the interface is not one end of a veth pair, or the raw socket cannot be opened
            (needs CAP_NET_RAW). ValueError: the axes' slave positions conflict.
    """

    def __init__(self, options: EthercatOptions, axis_options: dict, bank: PlantBank):
        super().__init__(options, axis_options, bank)
        names = bank.names
        roles = segment_roles(axis_options)
        n = max(roles)
        self.slaves: list[E.Esc] = []
        for pos in range(1, n + 1):
            product = roles.get(pos, EK1100)
            self.slaves.append(_drive_esc(pos) if product == 0 else _terminal_esc(product, pos))
        self.segment = E.Segment(self.slaves, self._on_outputs)
        self.peer = veth_peer(options.ifname)
        self.sock = socket.socket(socket.AF_PACKET, socket.SOCK_RAW, socket.htons(E.ETHERTYPE))
        self.sock.bind((self.peer, 0))
        self.sock.setblocking(False)
        self._last_sync = [None] * len(names)
        self._silent = False
        self._port_down = False
        self._fault_now: dict[int, str] = {}
        self.frames = 0
        bank.log(f"EtherCAT segment on {self.peer} (peer of {options.ifname}): " + ", ".join(
            f"{k + 1}: {self._name(s)}" for k, s in enumerate(self.slaves)))

    @staticmethod
    def _name(s: E.Esc) -> str:
        raw = s.sii[0x80:]
        n = raw[5]
        return raw[6:6 + n].decode("ascii", "replace")

    # ----------------------------------------------------------------- the plant
    def _periods(self, i: int, s: E.Esc) -> int:
        """Plant periods this frame stands for (see the module docstring)."""
        if not s.sync0_active:
            return 1
        cycle = struct.unpack_from("<I", s.mem, E.REG_DC_CYCLE0)[0] or 1
        k = s.system_time_ns() // cycle
        last = self._last_sync[i]
        self._last_sync[i] = k
        if last is None:
            return 1
        return max(0, min(k - last, round(self.bank.watchdog_s / self.bank.period_s)))

    def _apply(self, i: int, u: float, on: bool, periods: int) -> None:
        """The plant of axis i after a frame that stands for ``periods`` SYNC0 periods (0: two
        frames within one period: these outputs wait for the next SYNC0, nothing steps)."""
        b = self.bank
        if periods == 0:
            b.applied_V[i] = u if on else 0.0
            b.enabled[i] = on
            return
        b.command(i, u if on else 0.0, on, periods)

    def _on_outputs(self, wrote) -> None:
        if not wrote:
            return
        b = self.bank
        self.frames += 1
        step = any(s.state == E.OP for s in wrote)     # SAFE-OP frames (set-up) read, never step
        for i, a in enumerate(b.names):
            o = self.axis_options[a]
            spec = b.next_fault_spec([i]) if step else None
            kind = spec.kind if spec else None
            if kind:
                self._fault_now[i] = kind
            if o.profile == "cia402":
                s = self.slaves[o.slave - 1]
                app: CoeDrive = s.app
                if kind == "emcy":
                    app.fault(spec.code)
                    b.log(f"{a}: fault 0x{spec.code:04X} {cia402.error_meaning(spec.code)} (injected)")
                target, on = app.cycle(s.outputs(), s.state == E.OP)
                u = cia402.permille_to_volts(target, o.voltage_full_scale_V, o.full_scale_permille)
                if step:
                    self._apply(i, u, on, self._periods(i, s))
                b.amp_fault[i] = app.state == cia402.FAULT
                torque = cia402.volts_to_permille(b.applied_V[i], o.voltage_full_scale_V, o.full_scale_permille)
                app.set_actual(b.counts(i, o.encoder_m_per_count), torque)
            else:
                ao, do, enc = (self.slaves[o.analog_out.slave - 1], self.slaves[o.enable.slave - 1],
                               self.slaves[o.encoder.slave - 1])
                raw = ao.output_pins()
                k = 2 * (o.analog_out.channel - 1)
                counts = int.from_bytes(raw[k:k + 2], "little", signed=True) if len(raw) >= k + 2 else 0
                u = counts_to_volts(counts, o.voltage_full_scale_V, 16)
                dbyte = do.output_pins()
                on = bool(dbyte and dbyte[0] >> (o.enable.channel - 1) & 1)
                if step:
                    self._apply(i, u, on, self._periods(i, ao))
                c = b.counts(i, o.encoder_m_per_count) & 0xFFFFFFFF
                enc.set_inputs(struct.pack("<HII", 0x0000, c, 0))

    # ----------------------------------------------------------------- frames
    def poll(self, timeout_s: float) -> None:
        if self._silent:
            time.sleep(timeout_s)
            return
        r, _, _ = select.select([self.sock], [], [], max(0.0, timeout_s))
        if not r:
            return
        while True:
            try:
                frame = self.sock.recv(2048)
            except BlockingIOError:
                return
            except OSError as exc:           # the port went down (ENETDOWN): a slave waits for the cable
                if not self._port_down:
                    self._port_down = True
                    self.bank.log(f"port down ({exc.strerror}): waiting for the link")
                time.sleep(timeout_s)
                return
            if self._port_down:
                self._port_down = False
                self.bank.log("port up: answering again")
            if len(frame) < 16 or frame[12:14] != b"\x88\xa4":
                continue
            payload = bytearray(frame[14:])
            self._fault_now.clear()
            if not self.segment.process(payload):
                continue
            kinds = set(self._fault_now.values())
            if "disconnect" in kinds:
                self._silent = True
                self.bank.log("disconnect: the segment stops answering")
                return
            if "drop" in kinds:
                continue
            if "corrupt" in kinds:
                self._short_wkc(payload)
            if "late" in kinds:
                time.sleep(self.bank.late_s)
            src = bytes((frame[6] | 0x02,)) + frame[7:12]
            try:
                self.sock.send(frame[0:6] + src + frame[12:14] + payload)
            except OSError:
                pass

    @staticmethod
    def _short_wkc(payload: bytearray) -> None:
        """Lower the working counter of the process-data datagram by one (a slave that did not count)."""
        off = 2
        while off + 12 <= len(payload):
            cmd = payload[off]
            n = struct.unpack_from("<H", payload, off + 6)[0] & 0x07FF
            w = off + 10 + n
            if cmd in (E.LRD, E.LWR, E.LRW):
                struct.pack_into("<H", payload, w, max(0, struct.unpack_from("<H", payload, w)[0] - 1))
            more = struct.unpack_from("<H", payload, off + 6)[0] & 0x8000
            off = w + 2
            if not more:
                break

    def serve(self, stop=None, duration_s: float | None = None) -> None:
        """Answer frames until ``stop()`` or ``duration_s``; the ESCs' SM watchdogs run between frames."""
        end = time.monotonic() + duration_s if duration_s else math.inf
        due = 0.0
        try:
            while (stop is None or not stop()) and time.monotonic() < end:
                self.poll(0.002)
                now = time.monotonic()
                if now >= due:                   # every 0.5 ms: the watchdog times are >= 0.1 ms
                    due = now + 0.0005
                    for k, s in enumerate(self.slaves):
                        if s.check_watchdog():
                            self._watchdog(k, s)
        finally:
            self.close()

    def _watchdog(self, k: int, s: E.Esc) -> None:
        b = self.bank
        b.watchdog_trips += 1
        state = f"SAFE-OP + error 0x{E.AL_SM_WATCHDOG:04X}" if s.app.leaves_op_on_watchdog else "stays in OP"
        b.log(f"slave {k + 1}: SM watchdog, no outputs for {s.watchdog_time_ns() / 1e6:g} ms: outputs 0, "
              f"{state} ({s.watchdog_gap_ns / 1e6:.1f} ms after the last outputs)")
        for i, a in enumerate(b.names):
            o = self.axis_options[a]
            if k + 1 in [p for p, _ in o.slave_roles()]:
                b.applied_V[i] = 0.0
                b.enabled[i] = False
                if o.profile == "cia402":
                    b.amp_fault[i] = True

    def close(self) -> None:
        if self.sock is not None:
            s, self.sock = self.sock, None
            s.close()

