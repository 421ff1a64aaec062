"""Frame encoders and decoders of the bus drivers: CRC, byte order, scaling, sign, counter wrap,
frame sizes and bus-time arithmetic, register plans, fault specs."""

from __future__ import annotations

import pytest

from motorctl_drivers import can_bus, modbus, serial_link
from motorctl_drivers.split_phase import (
    EncoderUnwrap,
    counts_to_volts,
    to_signed,
    to_unsigned,
    volts_to_counts,
)
from motorctl_emulators.plant_bank import FaultSpec


# --------------------------------------------------------------------------- scaling, sign, wrap
def test_voltage_scaling_sign_and_saturation():
    assert volts_to_counts(10.0, 10.0, 16) == 32767
    assert volts_to_counts(-10.0, 10.0, 16) == -32767
    assert volts_to_counts(25.0, 10.0, 16) == 32767          # saturates, never wraps
    assert volts_to_counts(-25.0, 10.0, 16) == -32767
    assert volts_to_counts(float("nan"), 10.0, 16) == 0      # NaN never reaches the amplifier
    c = volts_to_counts(-1.2345, 10.0, 16)
    assert c < 0 and abs(counts_to_volts(c, 10.0, 16) + 1.2345) <= 10.0 / 32767
    assert to_unsigned(-1, 16) == 0xFFFF and to_signed(0xFFFF, 16) == -1
    assert to_signed(0x7FFF, 16) == 32767 and to_signed(0x8000, 16) == -32768


@pytest.mark.parametrize("bits", [16, 24, 32])
def test_encoder_counter_wrap_both_ways(bits):
    mod = 1 << bits
    u = EncoderUnwrap(bits)
    assert u.update(mod - 3) == -3                 # first reading taken as signed
    assert u.update(2) == 2                        # forward across the wrap: +5 counts
    assert u.update(mod - 10) == -10               # backward across the wrap
    start = mod // 2 - 5                           # cross the signed boundary too
    u2 = EncoderUnwrap(bits)
    u2.update(start)
    assert u2.update((start + 100) % mod) == start + 100


def test_encoder_unwrap_follows_a_long_travel():
    u = EncoderUnwrap(16)
    true = 0
    for _ in range(2000):                          # 2000 × 1000 counts: 30 wraps of 16 bits
        true += 1000
        got = u.update(true % 65536)
    assert got == true


# --------------------------------------------------------------------------- serial frames
def test_serial_crc_is_ccitt_false():
    assert serial_link.crc16(b"123456789") == 0x29B1      # CRC-16/CCITT-FALSE check value


def test_serial_command_roundtrip_layout_and_byte_order():
    f = serial_link.encode_command(7, 300, [(1, True, -2), (2, False, 0x1234)])
    assert len(f) == serial_link.frame_length(serial_link.CMD, 2) == 14
    assert f[:4] == bytes((0xA5, 7, 300 & 0xFF, 2))
    assert f[4:8] == bytes((1, 1, 0xFE, 0xFF))             # node, flags, int16 little-endian -2
    assert f[8:12] == bytes((2, 0, 0x34, 0x12))
    assert int.from_bytes(f[-2:], "big") == serial_link.crc16(f[:-2])
    p = serial_link.FrameParser()
    ((kind, addr, seq, n, frame),) = p.feed(f)
    assert (kind, addr, seq, n) == (serial_link.CMD, 7, 44, 2)
    assert serial_link.decode_body(kind, n, frame) == [(1, True, -2), (2, False, 0x1234)]


def test_serial_reply_counts_wrap_to_u32_and_back():
    f = serial_link.encode_reply(1, 9, [(3, 1, -5)])
    ((kind, _, _, n, frame),) = serial_link.FrameParser().feed(f)
    ((node, status, raw),) = serial_link.decode_body(kind, n, frame)
    assert (node, status, raw) == (3, 1, 2**32 - 5)
    assert to_signed(raw, 32) == -5


def test_serial_parser_rejects_bad_crc_and_resyncs_in_a_stream():
    good = serial_link.encode_reply(1, 5, [(1, 0, 1000), (2, 0, 2000)])
    bad = bytearray(good)
    bad[6] ^= 0x01                                          # one flipped bit in the payload
    p = serial_link.FrameParser()
    stream = b"\x00\x17" + bytes(bad) + good[:5]
    assert p.feed(stream) == []
    frames = p.feed(good[5:])                               # the rest arrives later
    assert len(frames) == 1 and frames[0][2] == 5
    assert p.bad_frames >= 1


def test_serial_query_and_error_frames():
    q = serial_link.encode_query(1, 3, [4, 5])
    ((kind, _, seq, n, frame),) = serial_link.FrameParser().feed(q)
    assert kind == serial_link.QUERY and serial_link.decode_body(kind, n, frame) == [4, 5]
    e = serial_link.encode_error(1, 3, 2, 4)
    ((kind, _, _, n, frame),) = serial_link.FrameParser().feed(e)
    assert kind == serial_link.ERROR and serial_link.decode_body(kind, n, frame) == [4]


# --------------------------------------------------------------------------- CAN layout and bits
def test_can_pack_unpack_byte_order_and_sign():
    buf = bytearray(8)
    le = can_bus.IntField(offset=0, size=2, byteorder="little")
    be = can_bus.IntField(offset=2, size=3, byteorder="big")
    can_bus.pack_int(buf, le, -2)
    can_bus.pack_int(buf, be, 0x123456)
    assert buf[:5] == bytes((0xFE, 0xFF, 0x12, 0x34, 0x56))
    assert to_signed(can_bus.unpack_uint(buf, le), 16) == -2
    assert can_bus.unpack_uint(buf, be) == 0x123456


@pytest.mark.parametrize("n,nominal,worst", [(8, 111, 135), (4, 79, 95), (2, 63, 75)])
def test_classic_can_frame_bits_match_the_budget_table(n, nominal, worst):
    bits, data = can_bus.frame_bits(n, fd=False, extended_id=False)
    assert bits == worst and data == 0.0
    assert (44 + 8 * n + 3) == nominal


def test_can_fd_frame_time_matches_the_budget_table():
    nom, dat = can_bus.frame_bits(8, fd=True, extended_id=False)
    assert nom / 1e6 + dat / 5e6 == pytest.approx(56.6e-6, abs=0.1e-6)   # 1M/5M
    assert nom / 1e6 + dat / 2e6 == pytest.approx(90.5e-6, abs=0.1e-6)   # 1M/2M


def test_can_fd_lengths_and_classic_limit():
    assert can_bus.frame_length(10, fd=True) == 12
    assert can_bus.frame_length(33, fd=True) == 48
    with pytest.raises(ValueError, match="classic CAN"):
        can_bus.frame_length(9, fd=False)


def _can_axis(cmd_id, fb_id, v_off, c_off, bit, seq=None):
    return can_bus.CanAxisOptions(
        command={"id": cmd_id, "voltage": {"offset": v_off, "size": 2}, "enable": {"byte": 4, "bit": bit},
                 "sequence_byte": seq},
        feedback={"id": fb_id, "counts": {"offset": c_off, "size": 4}, "fault": {"byte": 8, "bit": bit},
                  "sequence_byte": None if seq is None else 9})


def test_can_frames_group_axes_sharing_an_id():
    ax = {"X": _can_axis(0x200, 0x180, 0, 0, 0, 5), "Y": _can_axis(0x200, 0x180, 2, 4, 1, 5)}
    (cmd,) = can_bus.build_frames(["X", "Y"], ax, "command", fd=True)
    (fb,) = can_bus.build_frames(["X", "Y"], ax, "feedback", fd=True)
    assert cmd.axes == [0, 1] and cmd.length == 6 and cmd.seq_byte == 5
    assert fb.length == 12                                   # 10 bytes → next FD length


def test_can_overlapping_fields_are_refused():
    ax = {"X": _can_axis(0x200, 0x180, 0, 0, 0), "Y": _can_axis(0x200, 0x181, 1, 0, 1)}
    with pytest.raises(ValueError, match="byte 1"):
        can_bus.build_frames(["X", "Y"], ax, "command", fd=False)


# --------------------------------------------------------------------------- Modbus
@pytest.mark.parametrize("word_order", ["big", "little"])
@pytest.mark.parametrize("dtype", ["int16", "uint16", "int32", "uint32", "float32"])
def test_modbus_values_match_pymodbus_conversion(dtype, word_order):
    """Our register codec against pymodbus's own (ModbusClientMixin.convert_*_registers)."""
    from pymodbus.client.mixin import ModbusClientMixin as M
    v = modbus.Value(address=0, type=dtype, word_order=word_order)
    x = {"int16": -1234, "uint16": 54321, "int32": -123456789, "uint32": 3_000_000_000, "float32": -1.5e-3}[dtype]
    dt = getattr(M.DATATYPE, dtype.upper())
    raw = x & ((1 << (16 * v.nregs)) - 1) if dtype != "float32" else x
    regs = modbus.value_to_registers(v, raw)
    assert list(regs) == M.convert_to_registers(x, dt, word_order=word_order)
    back = modbus.registers_to_value(v, regs)
    assert back == pytest.approx(raw) if dtype == "float32" else back == raw
    le = modbus.Value(address=0, type=dtype, word_order=word_order, byte_order="little")
    swapped = modbus.value_to_registers(le, raw)       # byte order: each register's two bytes swapped
    assert [((r & 0xFF) << 8) | (r >> 8) for r in swapped] == list(regs)
    assert modbus.registers_to_value(le, swapped) == back


def test_modbus_voltage_scale_offset_and_saturation():
    v = modbus.Value(address=0, type="uint16", scale=20.0 / 65535, offset=-10.0)     # 0..65535 = -10..+10 V
    assert modbus.volts_to_raw(v, -10.0, v.scale) == 0 and modbus.volts_to_raw(v, 10.0, v.scale) == 65535
    assert modbus.volts_to_raw(v, 0.0, v.scale) == 32768 and modbus.volts_to_raw(v, 99.0, v.scale) == 65535
    i16 = modbus.Value(address=0, type="int16")
    assert modbus.volts_to_raw(i16, float("nan"), 10 / 32767) == 0       # NaN never reaches the amplifier
    assert modbus.volts_to_raw(i16, -25.0, 10 / 32767) == -32768


def test_modbus_rtu_crc_and_frames_match_pymodbus():
    from pymodbus.framer import FramerRTU, FramerSocket
    from pymodbus.pdu import DecodePDU
    assert modbus.crc16(bytes.fromhex("010300000001")) == 0x0A84    # the classic Modbus RTU example
    r = modbus.Request(23, 7, 0, address=100, count=7, waddress=0, wcount=5)
    r.build(tcp=False)
    r.frame[r.pdu_off + r.data_off:r.pdu_off + r.data_off + 10] = bytes(range(10))
    c = modbus.crc16(r.frame[:-2])
    r.frame[-2:] = bytes((c & 0xFF, c >> 8))
    used, dev, _tid, pdu = FramerRTU(DecodePDU(is_server=True)).decode(bytes(r.frame))
    req = DecodePDU(is_server=True).decode(pdu)
    assert used == len(r.frame) and dev == 7 and req.function_code == 23
    assert (req.read_address, req.read_count, req.write_address) == (100, 7, 0)
    assert req.write_registers == [0x0001, 0x0203, 0x0405, 0x0607, 0x0809]
    t = modbus.Request(16, 3, 0, waddress=2, wcount=2)
    t.build(tcp=True)
    t.frame[0:2] = (0x1234).to_bytes(2, "big")
    used, dev, tid, pdu = FramerSocket(DecodePDU(is_server=True)).decode(bytes(t.frame))
    assert (used, dev, tid) == (len(t.frame), 3, 0x1234)
    assert DecodePDU(is_server=True).decode(pdu).function_code == 16


def _mb_axis(v, c, pos, status, **kw):
    return modbus.ModbusAxisOptions(voltage={"address": v}, enable={"address": c, "bit": 0},
                                    position={"address": pos, "type": "int32", "scale": 0.5e-6},
                                    fault={"address": status}, **kw)


@pytest.mark.parametrize("dtype, signed", [("uint32", "int32"), ("uint16", "int16")])
def test_modbus_an_unsigned_position_is_refused_by_name(dtype, signed):
    """A drive's position counter is signed: an unsigned position map would read a carriage one
    count below 0 as the type's largest count (uint32 at 0.5 um: 2147.48 m), so it is refused
    at the config check, naming the type and the signed one to declare."""
    with pytest.raises(ValueError, match=f"position.type {dtype}: a position counter is signed; "
                                         f"declare the same register {signed}"):
        modbus.ModbusAxisOptions(voltage={"address": 0}, enable={"address": 1, "bit": 0},
                                 position={"address": 100, "type": dtype, "scale": 0.5e-6})


def test_modbus_register_plan_one_fc23_where_the_device_has_it():
    opts = modbus.ModbusOptions(sequence_register=4, sequence_echo_register=106)
    ax = {"X": _mb_axis(0, 1, 100, 102), "Y": _mb_axis(2, 3, 103, 105)}
    assert modbus.RegisterPlan(["X", "Y"], ax, opts, fc23={0: True}).summary() == \
        ["FC23 unit 1 write 0+5 read 100+7"]
    assert modbus.RegisterPlan(["X", "Y"], ax, opts, fc23={0: False}).summary() == \
        ["FC16 unit 1 write 0+5", "FC03 unit 1 read 100+7"]


def test_modbus_register_plan_coils_discrete_inputs_and_units():
    ax = {"X": modbus.ModbusAxisOptions(voltage={"address": 10}, enable={"table": "coil", "address": 0},
                                        position={"table": "input", "address": 0, "type": "int32", "scale": 1e-6},
                                        fault={"table": "discrete", "address": 3, "active": "low"}),
          "Y": modbus.ModbusAxisOptions(unit_id=2, voltage={"address": 10, "type": "float32", "scale": 1.0},
                                        enable={"table": "coil", "address": 0},
                                        position={"table": "input", "address": 0, "type": "float32", "scale": 1.0})}
    plan = modbus.RegisterPlan(["X", "Y"], ax, modbus.ModbusOptions(unit_id=1))
    assert plan.summary() == ["FC06 unit 1 write 10+1", "FC05 unit 1 write 0+1", "FC04 unit 1 read 0+2",
                              "FC02 unit 1 read 3+1", "FC16 unit 2 write 10+2", "FC05 unit 2 write 0+1",
                              "FC04 unit 2 read 0+2"]
    with pytest.raises(ValueError, match="used twice"):
        modbus.RegisterPlan(["X", "Y"], {"X": _mb_axis(0, 1, 100, 102), "Y": _mb_axis(1, 2, 103, 105)},
                            modbus.ModbusOptions())


# --------------------------------------------------------------------------- fault specs
def test_fault_spec_parsing():
    f = FaultSpec.parse("drop:X:2000:5")
    assert (f.kind, f.axis, f.start, f.count) == ("drop", "X", 2000, 5)
    assert FaultSpec.parse("bus_off").axis == "*"
    with pytest.raises(ValueError, match="unknown kind"):
        FaultSpec.parse("explode:X")
    with pytest.raises(ValueError, match="integers"):
        FaultSpec.parse("drop:X:soon")
    e = FaultSpec.parse("emcy=0x4310:Y:700")
    assert (e.kind, e.code, e.axis, e.start) == ("emcy", 0x4310, "Y", 700)
    assert FaultSpec.parse("emcy").code == 0x2310
    with pytest.raises(ValueError, match="only emcy"):
        FaultSpec.parse("drop=3")
