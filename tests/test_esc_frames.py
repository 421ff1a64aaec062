"""The ESC model as a master sees it, frame by frame (no network): raw EtherCAT frames into
:class:`motorctl_emulators.esc.Segment`, each point where an ESC (ETG.1000.4/.6, the ET1100
datasheet) differs from a naive model: the working counter in SAFE-OP, the reset value of
0x0440, the SM buffer after a watchdog trip, an EL2008-type terminal that stays in OP, frames of
header type 4/5, and an EEPROM write without write enable. The slaves' clock is a counter the
test advances.
"""

from __future__ import annotations

import struct

from motorctl_drivers.ethercat import EL2008, EL4132, EL5101
from motorctl_emulators import esc as E
from motorctl_emulators.ethercat_device import PD_IN, PD_OUT, _terminal_esc


def _frame(*datagrams, kind: int = 1) -> bytearray:
    body = bytearray()
    for k, (cmd, adp, ado, data) in enumerate(datagrams):
        more = 0x8000 if k < len(datagrams) - 1 else 0
        body += struct.pack("<BBHHHH", cmd, k, adp, ado, len(data) | more, 0) + data + b"\x00\x00"
    return bytearray(struct.pack("<H", len(body) | kind << 12)) + body


def _answers(frame: bytearray) -> list[tuple[bytes, int]]:
    """(data, working counter) of every datagram of an answered frame."""
    out, off = [], 2
    while off < len(frame):
        n = struct.unpack_from("<H", frame, off + 6)[0] & 0x7FF
        out.append((bytes(frame[off + 10:off + 10 + n]), struct.unpack_from("<H", frame, off + 10 + n)[0]))
        off += 12 + n
    return out


def _send(seg: E.Segment, *datagrams) -> list[tuple[bytes, int]]:
    f = _frame(*datagrams)
    assert seg.process(f)
    return _answers(f)


class Clock:
    def __init__(self):
        self.ns = 0

    def __call__(self) -> int:
        return self.ns


#: logical addresses: EL5101 outputs 0x0000 (6 bytes), inputs 0x0010 (10 bytes), EL4132 0x0020 (4),
#: EL2008 0x0030 (1)
LOGICAL = {EL5101: (0x0000, 0x0010), EL4132: (0x0020, None), EL2008: (0x0030, None)}
OUT_SIZE, IN_SIZE = {EL5101: 6, EL4132: 4, EL2008: 1}, {EL5101: 10}


def _segment(products, clock) -> E.Segment:
    """Slaves 0x1001... in SAFE-OP: station addresses, SM2/SM3 and FMMUs as SOEM programs them,
    SM2's watchdog 1 ms (10 units of 100 us)."""
    escs = []
    for k, p in enumerate(products, 1):
        e = _terminal_esc(p, k)
        e.clock_ns = clock
        e._t0 = 0
        escs.append(e)
    seg = E.Segment(escs)
    for k, p in enumerate(products, 1):
        st = 0x1000 + k
        assert _send(seg, (E.APWR, (1 - k) & 0xFFFF, E.REG_STATION, struct.pack("<H", st)))[0][1] == 1
        lout, lin = LOGICAL[p]
        sm = struct.pack("<HHBBBB", PD_OUT, OUT_SIZE[p], 0x64, 0, 1, 0)
        fm = struct.pack("<IHBBHBBBxxx", lout, OUT_SIZE[p], 0, 7, PD_OUT, 0, 0x02, 1)
        if p in IN_SIZE:
            sm += struct.pack("<HHBBBB", PD_IN, IN_SIZE[p], 0x20, 0, 1, 0)
            fm += struct.pack("<IHBBHBBBxxx", lin, IN_SIZE[p], 0, 7, PD_IN, 0, 0x01, 1)
        _send(seg, (E.FPWR, st, E.REG_SM, sm), (E.FPWR, st, E.REG_FMMU, fm),
              (E.FPWR, st, E.REG_WD_DIVIDER, struct.pack("<H", 2498)), (E.FPWR, st, E.REG_WD_PD, b"\x0a\x00"))
        for state in (E.PREOP, E.SAFEOP):
            _send(seg, (E.FPWR, st, E.REG_AL_CONTROL, struct.pack("<H", state)))
        assert escs[k - 1].state == E.SAFEOP
    return seg


def _al(seg, station) -> tuple[int, int]:
    data, wkc = _send(seg, (E.FPRD, station, E.REG_AL_STATUS, bytes(6)))[0]
    assert wkc == 1
    status, _r, code = struct.unpack("<HHH", data)
    return status, code


def _lrw(seg, data: bytes) -> tuple[bytes, int]:
    return _send(seg, (E.LRW, 0, 0, data))[0]


IMAGE = bytes(0x31)


def test_safe_op_counts_the_inputs_alone_and_takes_no_outputs():
    clock = Clock()
    seg = _segment([EL5101, EL4132], clock)
    out = bytearray(IMAGE)
    out[0x20:0x24] = b"\x10\x20\x30\x40"
    # SAFE-OP: the EL5101's inputs count 1; neither slave's outputs count nor land in its SM2
    _data, wkc = _lrw(seg, bytes(out))
    assert wkc == 1 and seg.slaves[1].outputs() == bytes(4)
    for st in (0x1001, 0x1002):
        _send(seg, (E.FPWR, st, E.REG_AL_CONTROL, struct.pack("<H", E.OP)))
    # OP: outputs 2 each, inputs 1 (ETG.1000.4 LRW); the outputs are in the SM buffer
    _data, wkc = _lrw(seg, bytes(out))
    assert wkc == 2 + 1 + 2 and seg.slaves[1].outputs() == b"\x10\x20\x30\x40"


def test_the_watchdog_status_reads_1_at_reset_and_0_after_a_trip_that_keeps_the_sm_buffer():
    clock = Clock()
    seg = _segment([EL4132], clock)
    data, wkc = _send(seg, (E.FPRD, 0x1001, E.REG_WD_PD_STATUS, bytes(2)))[0]
    assert (data, wkc) == (b"\x01\x00", 1)
    _send(seg, (E.FPWR, 0x1001, E.REG_AL_CONTROL, struct.pack("<H", E.OP)))
    out = bytearray(IMAGE)
    out[0x20:0x24] = b"\xff\x3f\x00\x00"          # channel 1 at +5 V
    assert _lrw(seg, bytes(out))[1] == 2
    esc = seg.slaves[0]
    clock.ns += 900_000
    assert not esc.check_watchdog()                # 0.9 ms of the 1 ms
    clock.ns += 200_000
    assert esc.check_watchdog()
    assert _al(seg, 0x1001) == (E.SAFEOP | E.AL_ERROR, E.AL_SM_WATCHDOG)
    assert _send(seg, (E.FPRD, 0x1001, E.REG_WD_PD_STATUS, bytes(2)))[0][0] == b"\x00\x00"
    # the pins at 0 V, the SM buffer (process RAM, read with FPRD) with the last data written
    assert esc.output_pins() == bytes(4)
    assert _send(seg, (E.FPRD, 0x1001, PD_OUT, bytes(4)))[0] == (b"\xff\x3f\x00\x00", 1)
    # SAFE-OP now: the next frame neither counts nor changes the buffer
    assert _lrw(seg, bytes(IMAGE))[1] == 0 and esc.outputs() == b"\xff\x3f\x00\x00"


def test_an_el2008_type_terminal_stays_in_op_on_a_trip_and_drives_with_the_next_frame():
    clock = Clock()
    seg = _segment([EL4132, EL2008], clock)
    for st in (0x1001, 0x1002):
        _send(seg, (E.FPWR, st, E.REG_AL_CONTROL, struct.pack("<H", E.OP)))
    out = bytearray(IMAGE)
    out[0x30] = 0x01                                 # the amplifier enable
    assert _lrw(seg, bytes(out))[1] == 4
    clock.ns += 2_000_000
    assert [s.check_watchdog() for s in seg.slaves] == [True, True]
    assert _al(seg, 0x1001) == (E.SAFEOP | E.AL_ERROR, E.AL_SM_WATCHDOG)
    assert _al(seg, 0x1002) == (E.OP, 0)             # no AL error: the ESC drives the pins itself
    do = seg.slaves[1]
    assert do.output_pins() == b"\x00" and do.outputs() == b"\x01"
    assert not do.check_watchdog()                   # tripped once, not again each check
    # the next frame: the EL4132 (SAFE-OP) does not count, the EL2008 drives the enable again
    assert _lrw(seg, bytes(out))[1] == 2 and do.output_pins() == b"\x01"
    assert _send(seg, (E.FPRD, 0x1002, E.REG_WD_PD_STATUS, bytes(2)))[0][0] == b"\x01\x00"


def test_frames_of_header_type_4_and_5_pass_the_slaves_unchanged():
    seg = _segment([EL4132], Clock())
    for kind in (4, 5):
        f = _frame((E.FPRD, 0x1001, E.REG_STATION, bytes(2)), kind=kind)
        before = bytes(f)
        assert seg.process(f) and bytes(f) == before
    assert seg.passed == 2
    # a type 1 frame whose length runs past its end is dropped
    f = _frame((E.FPRD, 0x1001, E.REG_STATION, bytes(2)))
    assert not seg.process(f[:-4])


def test_an_eeprom_write_without_write_enable_sets_the_error_bit_14():
    seg = _segment([EL4132], Clock())
    word = 0x0008                                    # vendor ID, low word

    def eeprom(control: int, data: bytes = b"") -> int:
        ds = [(E.FPWR, 0x1001, E.REG_EEP_ADDRESS, struct.pack("<I", word))]
        if data:
            ds.append((E.FPWR, 0x1001, E.REG_EEP_DATA, data))
        ds += [(E.FPWR, 0x1001, E.REG_EEP_CONTROL, struct.pack("<H", control)),
               (E.FPRD, 0x1001, E.REG_EEP_CONTROL, bytes(2))]
        return struct.unpack("<H", _send(seg, *ds)[-1][0])[0]

    assert eeprom(0x0200, b"\x34\x12") & 0x4000                   # write, no write enable
    assert seg.slaves[0].sii[2 * word:2 * word + 2] == b"\x02\x00"  # unchanged (Beckhoff 0x0002)
    status = eeprom(0x0201, b"\x34\x12")                          # write with write enable
    assert not status & 0x6000 and seg.slaves[0].sii[2 * word:2 * word + 2] == b"\x34\x12"
    assert not eeprom(0x0100) & 0x6000                            # read it back through 0x0508
    assert _send(seg, (E.FPRD, 0x1001, E.REG_EEP_DATA, bytes(2)))[0][0] == b"\x34\x12"
