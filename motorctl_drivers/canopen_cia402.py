"""CANopen CiA 402 driver (``type: canopen``): servo drives in cyclic synchronous torque mode,
on the ``canopen`` library over any python-can interface.

Set-up, outside the loop (blocking, SDO through ``canopen.RemoteNode`` with a notifier thread
that runs only while it is needed):

``configure()``, per drive (CiA 301 / CiA 402-2 objects):
  1. device type 0x1000 must name profile 402 (else the node is refused); NMT pre-operational;
  2. producer heartbeat 0x1017 = ``drive_heartbeat_ms``; heartbeat consumer 0x1016 off for now;
     abort connection option code 0x6007 = ``abort_connection_option``;
  3. modes of operation 0x6060 = 10 (cyclic synchronous torque; 0x6502 bit 9 checked where the
     drive has it); COB-ID SYNC 0x1005; communication cycle period 0x1006 = the loop period;
  4. the PDO mapping: RPDO ``rpdo`` = controlword 0x6040 + target torque 0x6071, TPDO ``tpdo`` =
     statusword 0x6041 + position actual 0x6064, both transmission type 1 (synchronous, every
     SYNC), the TPDO with "no RTR" (nothing relies on remote frames); the other PDOs 1-4 are
     switched off; the mapping is read back and compared;
  5. the ``sdo:`` writes of the axis from the YAML, each read back;
  6. the scales, read back and checked: the rated torque 0x6076 against ``rated_torque`` (when
     given), ``full_scale_permille`` against the max torque 0x6072 (the drive would clip above);
  7. the first reading (statusword and position by SDO), then ``round_trip_exchanges`` timed
     SDO uploads of the statusword: their median/max is the measured round trip
     (``describe()``, and the budget when ``round_trip_s`` is not set). A drive found in Fault
     stays in Fault: its error code 0x603F is read and named (a set-up warning,
     :meth:`fault_reason`), the first cycle faults the axis, and only the operator's
     ``motorctl fault-reset`` resets it (CiA 402 transition 15, :meth:`reset_fault`).

``activate()``: heartbeat consumer 0x1016 sub 1 = (``host_node_id`` << 16) | ``heartbeat_consumer_ms``
(read back), NMT start, wait for the drive's heartbeat to say Operational, then the notifier
stops: from here on ``read()``/``write()`` own the bus and never block.

Every cycle:
  * ``write(u, enable)``: per axis, the CiA 402 power state machine is stepped from the last
    statusword and the enable request (:class:`~motorctl_drivers.cia402.PowerStateMachine`:
    Shutdown → Switch on → Enable operation, confirmed by the statusword; Disable voltage when
    not enabled; a drive in Fault stays there until the operator's ``fault-reset``
    (:meth:`reset_fault`), then a rising edge of controlword bit 7 while the axis is disabled);
    the target torque is u scaled to per mille of the rated torque
    (±``voltage_full_scale_V`` ↔ ±``full_scale_permille``), 0 unless the axis is enabled *and*
    the drive is in Operation enabled. The RPDOs go out, then the SYNC (the master is the time
    base), and every ``host_heartbeat_ms`` the host's heartbeat (CiA 301 §7.2.8.3.2; it comes
    from the cycle itself, so a stalled or dead loop stops it).
  * ``read()``: the TPDOs answering that SYNC are collected (non-blocking, until ``timeout_s``);
    a TPDO that is missing is a read error (position extrapolated as for every bus driver).
    PDOs carry no sequence number; a synchronous TPDO (transmission type 1) is sent once per
    SYNC, so the driver counts both: the n-th TPDO of an axis answers the n-th SYNC, and only
    the one that answers the latest SYNC is fresh. Older ones (a drive that was late sends its
    TPDOs in a burst) are counted ``stale`` and not used: once, under a 2-core load, the first
    of three late TPDOs was taken as the answer to the latest SYNC, a position three periods
    (12 mm) old, and the following-error check faulted both axes. A lag that stays the same
    for two reads in a row means a TPDO was lost, not late: the count is realigned
    (``tpdo_resyncs``). An
    axis counts as enabled only in Operation enabled. The drive's heartbeat is watched: none for
    ``drive_heartbeat_timeout_ms`` is an amplifier fault at that read, named by
    :meth:`fault_reason` ("heartbeat lost, none for 52 ms"), not an I/O error the bucket would
    count for ten cycles; a heartbeat saying a state other than Operational
    (the drive went pre-operational or stopped, or booted again: CiA 301 §7.2.8.3.2) is an
    amplifier fault at that read, named by :meth:`fault_reason` ("left NMT Operational: its
    heartbeat says pre-operational (0x7F)"). An EMCY from the drive
    latches ``amp_fault`` with its error code and the CiA 301/402 meaning
    (:meth:`fault_reason`, ``describe()["emcy"]``); the latch clears once the axis is disabled
    and the drive has left Fault, which it does only on the operator's reset (above).

``close()``: every object the set-up wrote (0x1005, 0x1006, 0x1016, 0x1017, 0x6007, 0x6060, the
PDO communication and mapping parameters, the ``sdo:`` writes) is written back, in reverse
order, as it was uploaded just before the first write (``describe()["counters"]["restored"]``);
a failed set-up does the same. A reconnect keeps the values the first set-up found.

The drive side of a dead host: its heartbeat consumer (0x1016) misses the host's heartbeat for
``heartbeat_consumer_ms`` and performs the abort connection option (0x6007: 1 fault, 2 disable
voltage, 3 quick stop), so the motor stops without the host.

YAML (``driver:``)::

    type: canopen
    interface: socketcan | virtual | udp_multicast | ...   channel: can0   bus_options: {}
    bitrate: 1000000   fd: false   data_bitrate: 5000000   (budget; set on interfaces that take it)
    host_node_id: 127            # the host's heartbeat COB-ID 0x700 + this, named in 0x1016
    host_heartbeat_ms: 10        # produced from the cycle
    heartbeat_consumer_ms: 50    # 0x1016 on each drive: the drive acts after this without one
    abort_connection_option: 1   # 0x6007: 1 fault, 2 disable voltage, 3 quick stop
    drive_heartbeat_ms: 10       # 0x1017 on each drive
    drive_heartbeat_timeout_ms: 50   # the host's watch of the drive's heartbeat
    sync_cob_id: 0x80
    write_cycle_period: true     # 0x1006 = the loop period [us]
    sdo_timeout_s: 0.3   nmt_timeout_s: 1.0   round_trip_exchanges: 50
    timeout_s, wait, round_trip_s, max_bus_load: see split_phase.CommonOptions

per axis (``axes.NAME.driver``)::

    node_id: 1                   # 1-127
    rpdo: 1                      # which RPDO / TPDO (1-4) carries the axis (predefined COB-IDs)
    tpdo: 1
    voltage_full_scale_V: 10.0   # ±this ↔ ±full_scale_permille of the rated torque
    full_scale_permille: 1000
    rated_torque: null           # expected 0x6076 [mN m or mN]; read back and compared when set
    encoder_m_per_count: 0.5e-6  # position actual 0x6064 increments → m
    sdo: [{index: 0x6072, subindex: 0, value: 1500, size: 2}]   # more SDO writes, read back

Budget (:meth:`CanopenDriver.budget`): per cycle one SYNC, one RPDO and one TPDO per axis, and
the heartbeats amortised over the cycles between them, worst-case bit stuffing (ISO 11898-1;
:func:`motorctl_drivers.can_bus.frame_bits`), plus the round trip.
"""

from __future__ import annotations

import struct
import time
from typing import Annotated, Literal

import numpy as np
from pydantic import Field, model_validator

from motorctl.driver import BusBudget, StopCheck
from motorctl.schema import StrictModel
from motorctl_drivers import cia402
from motorctl_drivers.can_bus import frame_bits, open_bus
from motorctl_drivers.split_phase import (
    CommonOptions,
    EncoderUnwrap,
    SplitPhaseDriver,
    make_budget,
    one_line,
    round_trip_stats,
)

PDO_NOT_VALID = 1 << 31
RTR_NOT_ALLOWED = 1 << 30
NMT_OPERATIONAL = 5
#: NMT states in a heartbeat (CiA 301 Table 55)
NMT_STATE_NAMES = {0x00: "boot-up", 0x04: "stopped", 0x05: "operational", 0x7F: "pre-operational"}
TRACE_LEN = 32


# --------------------------------------------------------------------------- settings
class SdoWrite(StrictModel):
    """One SDO download from the YAML (CiA 301 expedited transfer), read back after writing.

    index, subindex: the object. value: the integer written. size: bytes (1, 2, 4).
    signed: two's complement (INTEGERn) rather than UNSIGNEDn."""

    index: Annotated[int, Field(ge=0x1000, le=0xFFFF)]
    subindex: Annotated[int, Field(ge=0, le=255)] = 0
    value: int
    size: Literal[1, 2, 4] = 4
    signed: bool = False

    def encode(self) -> bytes:
        """The little-endian bytes of :attr:`value` (CiA 301: every numeric type LSB first).

        Raises:
            ValueError: the value does not fit ``size`` bytes."""
        return int(self.value).to_bytes(self.size, "little", signed=self.signed)


class CanopenOptions(CommonOptions):
    """YAML ``driver:`` of the CANopen CiA 402 driver (see the module docstring)."""

    interface: str = "socketcan"
    channel: str = "can0"
    bus_options: dict[str, str | int | float | bool] = {}
    bitrate: Annotated[int, Field(gt=0)] = 1_000_000
    fd: bool = False
    data_bitrate: Annotated[int, Field(gt=0)] = 5_000_000
    host_node_id: Annotated[int, Field(ge=1, le=127)] = 127
    host_heartbeat_ms: Annotated[int, Field(ge=1, le=65535)] = 10
    heartbeat_consumer_ms: Annotated[int, Field(ge=1, le=65535)] = 50
    abort_connection_option: Literal[1, 2, 3] = 1
    drive_heartbeat_ms: Annotated[int, Field(ge=1, le=65535)] = 10
    drive_heartbeat_timeout_ms: Annotated[int, Field(ge=1, le=65535)] = 50
    sync_cob_id: Annotated[int, Field(ge=1, le=0x7FF)] = 0x80
    write_cycle_period: bool = True
    sdo_timeout_s: Annotated[float, Field(gt=0, le=10)] = 0.3
    nmt_timeout_s: Annotated[float, Field(gt=0, le=30)] = 1.0
    round_trip_exchanges: Annotated[int, Field(ge=1, le=10000)] = 50
    host_watchdog: Literal["heartbeat", "none"] = "heartbeat"

    @model_validator(mode="after")
    def _heartbeats(self):
        if self.heartbeat_consumer_ms < 2 * self.host_heartbeat_ms:
            raise ValueError(f"heartbeat_consumer_ms ({self.heartbeat_consumer_ms}) must be at least twice "
                             f"host_heartbeat_ms ({self.host_heartbeat_ms}): one late heartbeat would stop "
                             f"the drives")
        if self.drive_heartbeat_timeout_ms < 2 * self.drive_heartbeat_ms:
            raise ValueError(f"drive_heartbeat_timeout_ms ({self.drive_heartbeat_timeout_ms}) must be at least "
                             f"twice drive_heartbeat_ms ({self.drive_heartbeat_ms})")
        return self


#: SDO abort codes that mean "the drive has no such object" (CiA 301 Table 22)
ABSENT_ABORT_CODES = (0x06020000, 0x06090011)


class AbsentObject(OSError):
    """The drive answered an SDO access with "object (or sub-index) does not exist"."""


#: one mapped object: [index, subindex, bits] (bits 8, 16 or 32)
PdoEntry = Annotated[list[int], Field(min_length=3, max_length=3)]


class PdoLayout(StrictModel):
    """One PDO of a drive whose mapping is fixed: its COB-ID and the objects it carries, in
    order, as (index, subindex, bits)."""

    cob_id: Annotated[int, Field(ge=1, le=0x7FF)]
    map: list[PdoEntry]


class FixedPdos(StrictModel):
    """A drive whose PDO mapping is hard-wired (CiA 301 allows a static mapping): the RPDO
    must carry the controlword 0x6040/16 and the target torque 0x6071/16, the TPDO the
    statusword 0x6041/16 and the position actual value 0x6064/32 (other objects may sit
    between them; they are sent as 0 / ignored), each at most 8 bytes."""

    rpdo: PdoLayout
    tpdo: PdoLayout

    @model_validator(mode="after")
    def _check(self):
        for what, pdo, need in (("rpdo", self.rpdo, cia402.RX_MAP), ("tpdo", self.tpdo, cia402.TX_MAP)):
            for k, (index, sub, bits) in enumerate(pdo.map):
                if not (0x1000 <= index <= 0xFFFF and 0 <= sub <= 255 and bits in (8, 16, 32)):
                    raise ValueError(f"{what}.map[{k}] = [{index}, {sub}, {bits}]: allowed [index 0x1000-0xFFFF, "
                                     f"subindex 0-255, bits 8 | 16 | 32]")
            for index, sub, bits in need:
                if (index, sub, bits) not in [tuple(e) for e in pdo.map]:
                    raise ValueError(f"{what}.map must carry 0x{index:04X}:{sub:02X} ({bits} bits)")
            if sum(e[2] for e in pdo.map) > 64:
                raise ValueError(f"{what}.map holds more than 8 bytes (one classic CAN frame)")
        return self

    @staticmethod
    def offsets(pdo: PdoLayout) -> dict[int, int]:
        """Object index → byte offset in the PDO."""
        out, bit = {}, 0
        for index, _sub, bits in pdo.map:
            out.setdefault(index, bit // 8)
            bit += bits
        return out


class CanopenAxisOptions(StrictModel):
    """YAML ``axes.NAME.driver`` of the CANopen CiA 402 driver."""

    node_id: Annotated[int, Field(ge=1, le=127)]
    rpdo: Annotated[int, Field(ge=1, le=4)] = 1
    tpdo: Annotated[int, Field(ge=1, le=4)] = 1
    voltage_full_scale_V: Annotated[float, Field(gt=0)] = 10.0
    full_scale_permille: Annotated[int, Field(ge=1, le=32767)] = 1000
    rated_torque: Annotated[int, Field(ge=0)] | None = None
    encoder_m_per_count: Annotated[float, Field(gt=0)] = 0.5e-6
    sdo: list[SdoWrite] = []
    fixed_pdos: FixedPdos | None = None

    def rpdo_cob(self) -> int:
        """The COB-ID of this axis's RPDO (declared, or the predefined one of ``rpdo``)."""
        return self.fixed_pdos.rpdo.cob_id if self.fixed_pdos else rpdo_cob_id(self.rpdo, self.node_id)

    def tpdo_cob(self) -> int:
        """The COB-ID of this axis's TPDO (declared, or the predefined one of ``tpdo``)."""
        return self.fixed_pdos.tpdo.cob_id if self.fixed_pdos else tpdo_cob_id(self.tpdo, self.node_id)


def rpdo_cob_id(n: int, node_id: int) -> int:
    """Predefined connection set (CiA 301 §7.3.5): RPDO n (1-4) → 0x200 + 0x100 (n-1) + node."""
    return 0x200 + 0x100 * (n - 1) + node_id


def tpdo_cob_id(n: int, node_id: int) -> int:
    """Predefined connection set: TPDO n (1-4) → 0x180 + 0x100 (n-1) + node."""
    return 0x180 + 0x100 * (n - 1) + node_id


# --------------------------------------------------------------------------- object dictionary
def cia402_object_dictionary(node_id: int):
    """A ``canopen.ObjectDictionary`` of a CiA 402 servo drive with the objects this driver
    uses (CiA 301 communication area: 0x1000, 0x1001, 0x1005, 0x1006, 0x1014, 0x1016, 0x1017,
    0x1018, PDO parameters 0x1400-0x1403, 0x1600-0x1603, 0x1800-0x1803, 0x1A00-0x1A03; CiA 402-2:
    0x603F, 0x6007, 0x6040, 0x6041, 0x6060, 0x6061, 0x6064, 0x6071, 0x6072, 0x6076, 0x6077,
    0x6502), built in code instead of an EDS. Defaults are those of a drive as delivered: PDOs
    invalid, no heartbeat, profile 402 servo drive. The emulated drive serves the same
    dictionary."""
    from canopen import objectdictionary as odm
    od = odm.ObjectDictionary()
    od.node_id = node_id

    def var(name, index, sub=0, dtype=odm.UNSIGNED32, access="rw", default=0, mappable=False):
        v = odm.ODVariable(name, index, sub)
        v.data_type, v.access_type, v.default, v.pdo_mappable = dtype, access, default, mappable
        return v

    def record(name, index, members):
        r = odm.ODRecord(name, index)
        r.add_member(var("Highest sub-index supported", index, 0, odm.UNSIGNED8, "ro", max(m[0] for m in members)))
        for sub, mname, dtype, access, default in members:
            r.add_member(var(mname, index, sub, dtype, access, default))
        od.add_object(r)

    od.add_object(var("Device type", cia402.DEVICE_TYPE, dtype=odm.UNSIGNED32, access="ro",
                      default=0x00020000 | cia402.PROFILE_402))
    od.add_object(var("Error register", cia402.ERROR_REGISTER, dtype=odm.UNSIGNED8, access="ro", mappable=True))
    od.add_object(var("COB-ID SYNC", cia402.COB_ID_SYNC, default=0x80))
    od.add_object(var("Communication cycle period", cia402.COMM_CYCLE_PERIOD, default=0))
    od.add_object(var("COB-ID EMCY", cia402.COB_ID_EMCY, access="ro", default=0x80 + node_id))
    a = odm.ODArray("Consumer heartbeat time", cia402.CONSUMER_HEARTBEAT)
    a.add_member(var("Highest sub-index supported", cia402.CONSUMER_HEARTBEAT, 0, odm.UNSIGNED8, "ro", 1))
    a.add_member(var("Consumer heartbeat time 1", cia402.CONSUMER_HEARTBEAT, 1, odm.UNSIGNED32, "rw", 0))
    od.add_object(a)
    od.add_object(var("Producer heartbeat time", cia402.PRODUCER_HEARTBEAT, dtype=odm.UNSIGNED16, default=0))
    record("Identity object", 0x1018, [(1, "Vendor-ID", odm.UNSIGNED32, "ro", 0),
                                       (2, "Product code", odm.UNSIGNED32, "ro", 402),
                                       (3, "Revision number", odm.UNSIGNED32, "ro", 1),
                                       (4, "Serial number", odm.UNSIGNED32, "ro", node_id)])
    for n in range(4):
        record(f"RPDO communication parameter {n + 1}", cia402.RPDO_COMM + n,
               [(1, "COB-ID used by RPDO", odm.UNSIGNED32, "rw", PDO_NOT_VALID | rpdo_cob_id(n + 1, node_id)),
                (2, "Transmission type", odm.UNSIGNED8, "rw", 255)])
        record(f"RPDO mapping parameter {n + 1}", cia402.RPDO_MAPPING + n,
               [(k, f"Application object {k}", odm.UNSIGNED32, "rw", 0) for k in range(1, 9)])
        od[cia402.RPDO_MAPPING + n][0].access_type = "rw"
        record(f"TPDO communication parameter {n + 1}", cia402.TPDO_COMM + n,
               [(1, "COB-ID used by TPDO", odm.UNSIGNED32, "rw", PDO_NOT_VALID | tpdo_cob_id(n + 1, node_id)),
                (2, "Transmission type", odm.UNSIGNED8, "rw", 255),
                (3, "Inhibit time", odm.UNSIGNED16, "rw", 0),
                (5, "Event timer", odm.UNSIGNED16, "rw", 0),
                (6, "SYNC start value", odm.UNSIGNED8, "rw", 0)])
        record(f"TPDO mapping parameter {n + 1}", cia402.TPDO_MAPPING + n,
               [(k, f"Application object {k}", odm.UNSIGNED32, "rw", 0) for k in range(1, 9)])
        od[cia402.TPDO_MAPPING + n][0].access_type = "rw"
    od.add_object(var("Abort connection option code", cia402.ABORT_CONNECTION, dtype=odm.INTEGER16, default=1))
    od.add_object(var("Error code", cia402.ERROR_CODE, dtype=odm.UNSIGNED16, access="ro", mappable=True))
    od.add_object(var("Controlword", cia402.CONTROLWORD, dtype=odm.UNSIGNED16, mappable=True))
    od.add_object(var("Statusword", cia402.STATUSWORD, dtype=odm.UNSIGNED16, access="ro", mappable=True))
    od.add_object(var("Modes of operation", cia402.MODES_OF_OPERATION, dtype=odm.INTEGER8, mappable=True))
    od.add_object(var("Modes of operation display", cia402.MODES_DISPLAY, dtype=odm.INTEGER8, access="ro",
                      mappable=True))
    od.add_object(var("Position actual value", cia402.POSITION_ACTUAL, dtype=odm.INTEGER32, access="ro",
                      mappable=True))
    od.add_object(var("Target torque", cia402.TARGET_TORQUE, dtype=odm.INTEGER16, mappable=True))
    od.add_object(var("Max torque", cia402.MAX_TORQUE, dtype=odm.UNSIGNED16, default=3000))
    od.add_object(var("Motor rated torque", cia402.RATED_TORQUE, dtype=odm.UNSIGNED32, default=100000))
    od.add_object(var("Torque actual value", cia402.TORQUE_ACTUAL, dtype=odm.INTEGER16, access="ro",
                      mappable=True))
    od.add_object(var("Supported drive modes", cia402.SUPPORTED_MODES, access="ro",
                      default=cia402.SUPPORTED_CST_BIT | (1 << 7) | (1 << 8)))
    return od


def sdo_abort_text(exc) -> str:
    """One line for a canopen SDO failure (abort code and its CiA 301 text, or the timeout)."""
    code = getattr(exc, "code", None)
    return f"SDO abort 0x{code:08X} ({one_line(exc)})" if code is not None else one_line(exc)


# --------------------------------------------------------------------------- driver
class CanopenDriver(SplitPhaseDriver):
    """The CANopen CiA 402 driver. See the module docstring for set-up, cycle and settings.

    Counters (``describe()``): as every bus driver, plus ``heartbeat_lost`` (cycles without a
    fresh drive heartbeat), ``emcy`` (EMCY messages received), ``error_frames``,
    ``tpdo_resyncs`` (TPDO counts realigned after a lost TPDO).
    """

    Options = CanopenOptions
    AxisOptions = CanopenAxisOptions
    LAST_WINS = True
    DEFAULT_ROUND_TRIP_S = 100e-6
    NOTIFIER_TIMEOUT_S = 0.02

    def __init__(self, options: CanopenOptions, axis_options: dict, period_s: float):
        super().__init__(options, axis_options, period_s)
        names = self.axis_names
        n = len(names)
        self._ax = [axis_options[a] for a in names]
        nodes = [o.node_id for o in self._ax]
        if len(set(nodes)) != n:
            raise ValueError(f"canopen: two axes share a node_id ({nodes})")
        if options.host_node_id in nodes:
            raise ValueError(f"canopen: host_node_id {options.host_node_id} is also a drive's node_id")
        ids = [o.rpdo_cob() for o in self._ax] + [o.tpdo_cob() for o in self._ax]
        reserved = {options.sync_cob_id, 0x700 + options.host_node_id}
        clash = [i for i in ids if i in reserved or ids.count(i) > 1]
        if clash:
            raise ValueError(f"canopen: PDO COB-IDs {', '.join(hex(c) for c in sorted(set(clash)))} collide with "
                             f"each other, the SYNC or the host heartbeat")
        if period_s * 1000.0 > options.host_heartbeat_ms:
            raise ValueError(f"canopen: host_heartbeat_ms {options.host_heartbeat_ms} is shorter than the loop "
                             f"period ({period_s * 1e3:g} ms): the heartbeat comes from the cycle")
        self._unwrap = [EncoderUnwrap(32) for _ in range(n)]
        self._m_per_count = [o.encoder_m_per_count for o in self._ax]
        self._sm = [cia402.PowerStateMachine() for _ in range(n)]
        self._statusword = [0] * n
        self._tpdo_axis = {o.tpdo_cob(): i for i, o in enumerate(self._ax)}
        self._hb_axis = {0x700 + o.node_id: i for i, o in enumerate(self._ax)}
        self._emcy_axis = {0x80 + o.node_id: i for i, o in enumerate(self._ax)}
        self._hb_last = [0.0] * n          # perf_counter of the drive's last heartbeat
        self._hb_state = [0] * n           # NMT state in it
        self._hb_timeout = options.drive_heartbeat_timeout_ms * 1e-3
        self._hb_every = max(1, int(options.host_heartbeat_ms * 1e-3 / period_s + 1e-9))
        self._hb_count = 0
        self.emcy_code = [0] * n           # last EMCY error code per axis (0: none)
        self.emcy_count = [0] * n
        self.emcy_register = [0] * n
        self._emcy_latched = [False] * n
        self._emcy_named = [False] * n       # fault_reason names the EMCY until re-enabled
        self._nmt_named = [0] * n            # the NMT state a heartbeat said, not Operational (0: none)
        self._hb_named = [0.0] * n           # the heartbeat's silence when it was found lost [s] (0: none)
        self._was_fault = [False] * n
        self._setup_code = [0] * n           # error code 0x603F of a drive found in Fault at set-up (0: none)
        # the statusword trace per axis: preallocated ring of (statusword) at each state change
        self._trace = [[0] * TRACE_LEN for _ in range(n)]
        self._trace_n = [0] * n
        # PDO layout per axis (byte offsets and lengths): the driver's own mapping, confirmed by
        # its read-back in configure(), or the declared fixed mapping
        self._cw_off, self._tt_off = [0] * n, [2] * n
        self._sw_off, self._pos_off = [0] * n, [2] * n
        self._rpdo_len, self._tpdo_len = [4] * n, [6] * n
        for i, o in enumerate(self._ax):
            if o.fixed_pdos is not None:
                rx, tx = FixedPdos.offsets(o.fixed_pdos.rpdo), FixedPdos.offsets(o.fixed_pdos.tpdo)
                self._cw_off[i], self._tt_off[i] = rx[cia402.CONTROLWORD], rx[cia402.TARGET_TORQUE]
                self._sw_off[i], self._pos_off[i] = tx[cia402.STATUSWORD], tx[cia402.POSITION_ACTUAL]
                self._rpdo_len[i] = sum(e[2] for e in o.fixed_pdos.rpdo.map) // 8
                self._tpdo_len[i] = sum(e[2] for e in o.fixed_pdos.tpdo.map) // 8
        self._has_consumer = [True] * n     # the drive has the heartbeat consumer 0x1016
        self._changed: list[dict] = [{} for _ in range(n)]   # (index, sub) -> bytes before configure
        self._reconnecting = False
        self.bus = None
        self.network = None
        self.nodes = []
        self._notifier = None
        self._rx_msgs = []
        self._sync_msg = None
        self._hb_msg = None
        self.drive_info: list[dict] = [{} for _ in range(n)]
        self.counters.update(heartbeat_lost=0, emcy=0, error_frames=0, tpdo_resyncs=0, nmt_left=0, restored=0)
        self._syncs = 0                    # SYNCs sent since activate()
        self._tpdos = [0] * n              # TPDOs received per axis since activate()
        self._lag_now = [0] * n            # this read: the lag of the newest stale TPDO (0: none)
        self._lag_prev = [0] * n           # the same at the end of the read before (0: fresh or none)

    # ------------------------------------------------------------------ transport
    def other_master(self) -> str:
        """A master already on the bus: its SYNC (``sync_cob_id``) or its heartbeat (0x700 +
        ``host_node_id``) heard within three host heartbeat times (CiA 301: a running master
        sends both); '' when the bus is quiet. Opens and releases the bus (unconfigured only)."""
        self._require("other_master", "unconfigured")
        o = self.options
        ids = {o.sync_cob_id: "SYNC", 0x700 + o.host_node_id: "host heartbeat"}
        bus = open_bus(o)
        try:
            deadline = time.monotonic() + 3 * o.host_heartbeat_ms * 1e-3 + 0.02
            while (left := deadline - time.monotonic()) > 0:
                msg = bus.recv(timeout=left)
                if msg is not None and msg.arbitration_id in ids:
                    return (f"a {ids[msg.arbitration_id]} (0x{msg.arbitration_id:03X}) on CAN {o.interface} "
                            f"{o.channel}: another master drives this bus")
        finally:
            bus.shutdown()
        return ""

    def _open_transport(self) -> None:
        import canopen
        self.bus = open_bus(self.options)
        self._set_wait_fd(None)
        try:
            fd = self.bus.fileno()
            if fd is not None and fd >= 0:
                self._set_wait_fd(fd)
        except (NotImplementedError, AttributeError, OSError):
            pass
        self.network = canopen.Network(self.bus)     # no connect(): the notifier is ours to start/stop
        self.nodes = []
        for i, o in enumerate(self._ax):
            node = canopen.RemoteNode(o.node_id, cia402_object_dictionary(o.node_id))
            node.sdo.RESPONSE_TIMEOUT = self.options.sdo_timeout_s
            self._track_downloads(i, node)
            self.network.add_node(node)
            self.nodes.append(node)
        self._start_notifier()
        self._build_messages()

    def _track_downloads(self, i: int, node) -> None:
        """Keep, for every object the set-up writes on drive i, what it held before (uploaded
        just before the first write), so that close, or a failed configure, puts it back."""
        sdo = node.sdo
        download = sdo.download
        changed = self._changed[i]

        def tracked(index, subindex, data, force_segment=False):
            key = (index, subindex)
            if self.state == "unconfigured" and key not in changed:
                try:
                    changed[key] = bytes(sdo.upload(index, subindex))
                except Exception:  # noqa: BLE001  (nothing to restore: write-only, absent, ...)
                    changed[key] = None
            return download(index, subindex, data, force_segment)

        sdo.download = tracked
        sdo.untracked_download = download

    def _restore(self) -> int:
        """Write back, in reverse order, what configure changed on the drives (best effort).
        Returns how many objects were restored."""
        n = 0
        for i, node in enumerate(self.nodes):
            for (index, sub), old in reversed(list(self._changed[i].items())):
                if old is None:
                    continue
                try:
                    node.sdo.untracked_download(index, sub, old)
                    n += 1
                except Exception:  # noqa: BLE001  (best effort: the drive may be gone)
                    pass
            self._changed[i].clear()
        return n

    def _start_notifier(self) -> None:
        import can
        if self._notifier is None:
            self._notifier = can.Notifier(self.bus, self.network.listeners, timeout=self.NOTIFIER_TIMEOUT_S)
            self.network.notifier = self._notifier

    def _stop_notifier(self) -> None:
        if self._notifier is not None:
            notifier, self._notifier = self._notifier, None
            notifier.stop(timeout=1.0)
            if self.network is not None:
                self.network.notifier = None

    def _build_messages(self) -> None:
        import can
        o = self.options
        fd = o.fd
        self._rx_msgs = [can.Message(arbitration_id=a.rpdo_cob(), is_extended_id=False,
                                     data=bytearray(self._rpdo_len[i]), dlc=self._rpdo_len[i], is_fd=fd,
                                     bitrate_switch=fd, check=True)
                         for i, a in enumerate(self._ax)]
        self._sync_msg = can.Message(arbitration_id=o.sync_cob_id, is_extended_id=False, data=bytearray(0), dlc=0)
        self._hb_msg = can.Message(arbitration_id=0x700 + o.host_node_id, is_extended_id=False,
                                   data=bytearray((NMT_OPERATIONAL,)), dlc=1)

    def _release_transport(self) -> None:
        self._stop_notifier()
        if self.network is not None:
            for node in self.nodes:
                try:
                    self.network.pop(node.id, None)
                except Exception:  # noqa: BLE001
                    pass
            self.network = None
        self.nodes = []
        if self.bus is not None:
            bus, self.bus = self.bus, None
            bus.shutdown()

    def _full_scale_V(self, axis: str) -> float:
        """``axes.NAME.driver.voltage_full_scale_V`` [V] (↔ ``full_scale_permille``)."""
        return float(self.axis_options[axis].voltage_full_scale_V)

    # ------------------------------------------------------------------ SDO helpers (blocking)
    def _where(self, i: int) -> str:
        return f"canopen node {self._ax[i].node_id} (axis {self.axis_names[i]})"

    def _upload(self, i: int, index: int, sub: int) -> bytes:
        from canopen.sdo import SdoAbortedError, SdoCommunicationError
        try:
            return bytes(self.nodes[i].sdo.upload(index, sub))
        except SdoCommunicationError as exc:
            raise ConnectionError(f"{self._where(i)}: no SDO answer reading 0x{index:04X}:{sub:02X} "
                                  f"within {self.options.sdo_timeout_s:g} s ({one_line(exc)})") from None
        except SdoAbortedError as exc:
            cls = AbsentObject if getattr(exc, "code", None) in ABSENT_ABORT_CODES else OSError
            raise cls(f"{self._where(i)}: reading 0x{index:04X}:{sub:02X}: {sdo_abort_text(exc)}") from None

    def _read_uint(self, i: int, index: int, sub: int = 0, signed: bool = False) -> int:
        return int.from_bytes(self._upload(i, index, sub), "little", signed=signed)

    def _write(self, i: int, index: int, sub: int, data: bytes, check: bool = True) -> None:
        """SDO download, then (``check``) upload and compare: the drive must hold what was written."""
        from canopen.sdo import SdoAbortedError, SdoCommunicationError
        try:
            self.nodes[i].sdo.download(index, sub, data)
        except SdoCommunicationError as exc:
            raise ConnectionError(f"{self._where(i)}: no SDO answer writing 0x{index:04X}:{sub:02X} "
                                  f"within {self.options.sdo_timeout_s:g} s ({one_line(exc)})") from None
        except SdoAbortedError as exc:
            cls = AbsentObject if getattr(exc, "code", None) in ABSENT_ABORT_CODES else OSError
            raise cls(f"{self._where(i)}: writing 0x{index:04X}:{sub:02X} = 0x{data[::-1].hex()}: "
                      f"{sdo_abort_text(exc)}") from None
        if check:
            back = self._upload(i, index, sub)
            if back[:len(data)] != data:
                raise OSError(f"{self._where(i)}: 0x{index:04X}:{sub:02X} reads back 0x{back[::-1].hex()} "
                              f"after writing 0x{data[::-1].hex()}")

    def _write_optional(self, i: int, index: int, sub: int, data: bytes, what: str) -> bool:
        """Write an object a drive may lack: an "object does not exist" abort is a notice (one
        line, in :attr:`notices`), not a failure. Returns True when written."""
        try:
            self._write(i, index, sub, data)
            return True
        except AbsentObject as exc:
            self._notice(f"{exc} ({what}; optional, not set)")
            return False

    def _try_upload(self, i: int, index: int, sub: int = 0) -> bytes | None:
        """Upload an optional object: None when the drive aborts (the object does not exist)."""
        from canopen.sdo import SdoAbortedError
        try:
            return bytes(self.nodes[i].sdo.upload(index, sub))
        except SdoAbortedError:
            return None
        except Exception as exc:  # noqa: BLE001
            raise ConnectionError(f"{self._where(i)}: reading 0x{index:04X}:{sub:02X}: {one_line(exc)}") from None

    # ------------------------------------------------------------------ lifecycle
    def _configure(self) -> None:
        """Open the bus and set every drive up (module docstring, steps 1-7).

        Raises:
            OSError: the interface cannot be opened; a drive refuses a setting, is not a CiA 402
                drive, or its scales do not match (one line naming node, axis, object).
            ConnectionError: a drive does not answer SDO within ``sdo_timeout_s``, or its
                heartbeat does not come.
        The bus is released again on any failure.
        """
        self._open_transport()
        self.connected = True
        if not self._reconnecting:          # a reconnect keeps what the first set-up found
            for changed in self._changed:
                changed.clear()
        try:
            for i in range(len(self._ax)):
                self._setup_drive(i)
            self._measure_round_trip()
        except (OSError, ConnectionError, ValueError) as exc:
            restored = self._restore()
            self._close()
            if restored:
                raise type(exc)(f"{exc}; the {restored} object(s) the set-up had changed on the drives are "
                                f"restored") from None
            raise
        except BaseException:
            self._restore()
            self._close()
            raise
        if self.options.host_watchdog == "none":
            drives = ", ".join(self._where(i) for i in range(len(self._ax)))
            self._notice(f"{drives}: no device-side watchdog (driver.host_watchdog: none): a drive "
                         f"keeps its last torque if this host stops sending; give each drive a watchdog of its "
                         f"own", warning=True)

    def _setup_drive(self, i: int) -> None:
        o, a = self.options, self._ax[i]
        node = self.nodes[i]
        info = self.drive_info[i]
        dtype = self._read_uint(i, cia402.DEVICE_TYPE)
        if dtype & 0xFFFF != cia402.PROFILE_402:
            raise OSError(f"{self._where(i)}: device type 0x{dtype:08X} is profile {dtype & 0xFFFF}, "
                          f"not a CiA 402 drive")
        info["device_type"] = f"0x{dtype:08X}"
        node.nmt.state = "PRE-OPERATIONAL"
        self._write(i, cia402.PRODUCER_HEARTBEAT, 0, o.drive_heartbeat_ms.to_bytes(2, "little"))
        self._has_consumer[i] = False
        if o.host_watchdog == "heartbeat":
            try:
                self._write(i, cia402.CONSUMER_HEARTBEAT, 1, bytes(4))
            except AbsentObject:
                raise OSError(f"{self._where(i)} has no heartbeat consumer 0x1016: it would keep its last torque "
                              f"if this host stopped; give the drive a watchdog of its own and set "
                              f"driver.host_watchdog: none to run without one") from None
            self._has_consumer[i] = True
            self._write_optional(i, cia402.ABORT_CONNECTION, 0,
                                 o.abort_connection_option.to_bytes(2, "little", signed=True),
                                 "abort connection option: the drive's own reaction to a lost heartbeat")
        modes = self._try_upload(i, cia402.SUPPORTED_MODES)
        if modes is not None and not int.from_bytes(modes, "little") & cia402.SUPPORTED_CST_BIT:
            raise OSError(f"{self._where(i)}: supported drive modes 0x6502 = 0x{int.from_bytes(modes, 'little'):08X} "
                          f"has no cyclic synchronous torque (bit 9)")
        self._write(i, cia402.MODES_OF_OPERATION, 0, bytes((cia402.MODE_CST,)))
        if not self._write_optional(i, cia402.COB_ID_SYNC, 0, o.sync_cob_id.to_bytes(4, "little"),
                                    "COB-ID SYNC: the drive listens on 0x080") and o.sync_cob_id != 0x80:
            raise OSError(f"{self._where(i)} has no COB-ID SYNC 0x1005, so it takes the SYNC on 0x080; set "
                          f"driver.sync_cob_id: 0x80 (it is 0x{o.sync_cob_id:03X})")
        if o.write_cycle_period:
            self._write_optional(i, cia402.COMM_CYCLE_PERIOD, 0, round(self.period_s * 1e6).to_bytes(4, "little"),
                                 "communication cycle period")
        if a.fixed_pdos is not None:
            self._check_fixed_pdos(i)
        else:
            self._map_pdos(i)
        for w in a.sdo:
            try:
                data = w.encode()
            except OverflowError:
                raise ValueError(f"axis {self.axis_names[i]}: sdo 0x{w.index:04X}:{w.subindex:02X} value "
                                 f"{w.value} does not fit {w.size} bytes") from None
            self._write(i, w.index, w.subindex, data)
        raw = self._try_upload(i, cia402.RATED_TORQUE)
        rated = None if raw is None else int.from_bytes(raw, "little")
        raw = self._try_upload(i, cia402.MAX_TORQUE)
        max_t = None if raw is None else int.from_bytes(raw, "little")
        info.update(rated_torque=rated, max_torque_permille=max_t)
        if rated is None:
            self._notice(f"{self._where(i)} has no rated torque 0x6076: the V -> per mille scale "
                         f"(full_scale_permille) is taken as configured, unchecked")
        elif a.rated_torque is not None and rated != a.rated_torque:
            raise OSError(f"{self._where(i)}: rated torque 0x6076 is {rated}, the config says {a.rated_torque}: "
                          f"the V -> per mille scale would be wrong")
        if max_t is None:
            self._notice(f"{self._where(i)} has no max torque 0x6072: full_scale_permille "
                         f"{a.full_scale_permille} is not checked against the drive's clip")
        elif a.full_scale_permille > max_t:
            raise OSError(f"{self._where(i)}: full_scale_permille {a.full_scale_permille} is above the drive's max "
                          f"torque 0x6072 = {max_t} per mille (the drive would clip); lower it or raise 0x6072 "
                          f"with an sdo: write")
        mode = self._read_uint(i, cia402.MODES_OF_OPERATION, signed=True)
        if mode != cia402.MODE_CST:
            raise OSError(f"{self._where(i)}: modes of operation 0x6060 reads {mode}, not 10 (CST)")
        emcy = self._try_upload(i, cia402.COB_ID_EMCY)
        if emcy is not None:
            cid = int.from_bytes(emcy, "little")
            if not cid & PDO_NOT_VALID and (cid & 0x7FF) != 0x80 + a.node_id:
                self._emcy_axis.pop(0x80 + a.node_id, None)
                self._emcy_axis[cid & 0x7FF] = i
        sw = self._read_uint(i, cia402.STATUSWORD)
        self._setup_code[i] = 0
        if cia402.decode_state(sw) in (cia402.FAULT, cia402.FAULT_REACTION_ACTIVE):
            self._found_in_fault(i, sw)
        pos = self._read_uint(i, cia402.POSITION_ACTUAL, signed=True)
        self._statusword[i] = sw
        self._sm[i].step(sw, False)
        self._record_trace(i, sw)
        y = self._unwrap[i].update(pos & 0xFFFFFFFF) * self._m_per_count[i]
        self._y_last[i] = y
        self.position_m[i] = y
        info.update(statusword=f"0x{sw:04X}", state=cia402.STATE_NAMES[cia402.decode_state(sw)],
                    scale={"permille_per_V": a.full_scale_permille / a.voltage_full_scale_V,
                           "m_per_count": a.encoder_m_per_count})

    def _map_pdos(self, i: int) -> None:
        """RPDO/TPDO mapping through canopen's PDO maps (SDO), the other PDOs switched off, read back."""
        a = self._ax[i]
        node = self.nodes[i]
        from canopen.sdo import SdoAbortedError
        for n in range(1, 5):            # switch off the PDOs this driver does not use
            for comm, used in ((cia402.RPDO_COMM, a.rpdo), (cia402.TPDO_COMM, a.tpdo)):
                if n == used:
                    continue
                try:
                    cid = int.from_bytes(bytes(node.sdo.upload(comm + n - 1, 1)), "little")
                except SdoAbortedError:
                    continue             # the drive has fewer PDOs
                except Exception as exc:  # noqa: BLE001
                    raise ConnectionError(f"{self._where(i)}: reading 0x{comm + n - 1:04X}:01: {one_line(exc)}") from None
                if not cid & PDO_NOT_VALID:
                    self._write(i, comm + n - 1, 1, (cid | PDO_NOT_VALID).to_bytes(4, "little"))
        for maps, num, cob, layout, rtr in ((node.rpdo, a.rpdo, rpdo_cob_id(a.rpdo, a.node_id), cia402.RX_MAP, True),
                                            (node.tpdo, a.tpdo, tpdo_cob_id(a.tpdo, a.node_id), cia402.TX_MAP, False)):
            m = maps[num]
            try:
                m.read()
                m.clear()
                for index, sub, bits in layout:
                    m.add_variable(index, sub, bits)
                m.cob_id = cob
                m.trans_type = 1
                m.rtr_allowed = rtr
                m.enabled = True
                m.save()
                m.read()                 # read back what the drive holds now
            except Exception as exc:  # noqa: BLE001
                raise OSError(f"{self._where(i)}: PDO mapping 0x{m.map_array.od.index:04X}: "
                              f"{sdo_abort_text(exc)}") from None
            got = [(v.index, v.subindex, v.length) for v in m.map]
            if got != list(layout) or m.cob_id != cob or m.trans_type != 1 or not m.enabled:
                raise OSError(f"{self._where(i)}: PDO 0x{m.com_record.od.index:04X} reads back COB-ID 0x{m.cob_id:X}, "
                              f"transmission type {m.trans_type}, mapping "
                              f"{[(hex(x), s, b) for x, s, b in got]} instead of what was written")
            offs = {v.index: v.offset // 8 for v in m.map}
            if maps is node.rpdo:
                self._cw_off[i], self._tt_off[i] = offs[cia402.CONTROLWORD], offs[cia402.TARGET_TORQUE]
                self._rpdo_len[i] = m.length // 8
            else:
                self._sw_off[i], self._pos_off[i] = offs[cia402.STATUSWORD], offs[cia402.POSITION_ACTUAL]
                self._tpdo_len[i] = m.length // 8
            self.drive_info[i][("rpdo" if maps is node.rpdo else "tpdo")] = {
                "cob_id": f"0x{cob:03X}", "map": [f"0x{x:04X}:{s:02X}/{b}" for x, s, b in got],
                "transmission_type": m.trans_type}

    def _found_in_fault(self, i: int, sw: int) -> None:
        """A drive found in Fault at set-up (an earlier run's fault, its heartbeat consumer
        when an earlier host died) stays in Fault: the host never resets a drive's fault on its
        own. Its error code 0x603F (where it has one) is read by SDO and named with the state
        and statusword by :meth:`fault_reason` and a set-up warning; the first cycle faults the
        axis, and only the operator's ``motorctl fault-reset`` (:meth:`reset_fault`: CiA 402
        transition 15) takes it out."""
        raw = self._try_upload(i, cia402.ERROR_CODE)
        self._setup_code[i] = 0 if raw is None else int.from_bytes(raw[:2], "little")
        self._statusword[i] = sw
        self._notice_drive_fault(i, self._found_text(i, sw))

    def _found_text(self, i: int, sw: int) -> str:
        code = self._setup_code[i]
        return (f"{self._where(i)} is in {cia402.STATE_NAMES[cia402.decode_state(sw)]} (statusword 0x{sw:04X}"
                + (f", error code 0x603F = {cia402.describe_error(code)}" if code else "") + ")")

    def _check_fixed_pdos(self, i: int) -> None:
        """A drive with a fixed mapping (``fixed_pdos``): where it has the PDO parameter
        objects, the PDO whose COB-ID is the declared one is found and its mapping read and
        compared; where it has none, the mapping is taken as declared (a notice says so)."""
        a = self._ax[i]
        for what, pdo, comm, mapping in (("RPDO", a.fixed_pdos.rpdo, cia402.RPDO_COMM, cia402.RPDO_MAPPING),
                                         ("TPDO", a.fixed_pdos.tpdo, cia402.TPDO_COMM, cia402.TPDO_MAPPING)):
            found = None
            for n in range(512):
                raw = self._try_upload(i, comm + n, 1)
                if raw is None:
                    break
                if int.from_bytes(raw, "little") & 0x7FF == pdo.cob_id:
                    found = n
                    break
            want = [tuple(e) for e in pdo.map]
            self.drive_info[i][what.lower()] = {"cob_id": f"0x{pdo.cob_id:03X}", "fixed": True,
                                                "map": [f"0x{x:04X}:{s:02X}/{b}" for x, s, b in want]}
            if found is None:
                self._notice(f"{self._where(i)}: {what} 0x{pdo.cob_id:03X} has no readable mapping "
                             f"(no 0x{comm:04X}.. parameter object carries it): taken as declared in fixed_pdos")
                continue
            count = self._read_uint(i, mapping + found, 0)
            got = []
            for k in range(1, count + 1):
                v = self._read_uint(i, mapping + found, k)
                got.append((v >> 16, (v >> 8) & 0xFF, v & 0xFF))
            if got != want:
                raise OSError(f"{self._where(i)}: {what} 0x{pdo.cob_id:03X} maps "
                              f"{[(hex(x), s_, b) for x, s_, b in got]}, fixed_pdos declares "
                              f"{[(hex(x), s_, b) for x, s_, b in want]}")

    def _measure_round_trip(self) -> None:
        """``round_trip_exchanges`` SDO uploads of the statusword, timed (median/max → describe)."""
        clock = time.perf_counter
        times = []
        n = len(self._ax)
        for k in range(self.options.round_trip_exchanges):
            i = k % n
            t0 = clock()
            self._upload(i, cia402.STATUSWORD, 0)
            times.append(clock() - t0)
        self.round_trip = round_trip_stats(times)

    def _activate(self) -> None:
        """Heartbeat consumer on every drive, NMT start, wait for Operational; then the notifier
        stops and the cycle owns the bus.

        Raises:
            OSError / ConnectionError: a drive refuses 0x1016 or does not report Operational
            within ``nmt_timeout_s``.
        """
        o = self.options
        self._start_notifier()
        consumer = (o.host_node_id << 16) | o.heartbeat_consumer_ms
        for i, node in enumerate(self.nodes):
            if self._has_consumer[i]:
                self._write(i, cia402.CONSUMER_HEARTBEAT, 1, consumer.to_bytes(4, "little"))
            self._sm[i].__init__()
            self._emcy_latched[i] = False
            self._emcy_named[i] = False
            self._nmt_named[i] = 0
            self._hb_named[i] = 0.0
        self._prime_commands()
        for i, node in enumerate(self.nodes):
            node.nmt.state = "OPERATIONAL"
        deadline = time.monotonic() + o.nmt_timeout_s
        for i, node in enumerate(self.nodes):
            while True:                 # a heartbeat received after the start must say Operational
                left = deadline - time.monotonic()
                if left <= 0:
                    raise ConnectionError(f"{self._where(i)}: no heartbeat saying Operational within "
                                          f"{o.nmt_timeout_s:g} s of NMT start (heartbeat {o.drive_heartbeat_ms} ms)")
                try:
                    if node.nmt.wait_for_heartbeat(timeout=min(left, 0.2)) == "OPERATIONAL":
                        break
                except Exception:  # noqa: BLE001  (NmtError: none yet; try again until the deadline)
                    pass
        self._stop_notifier()
        now = time.perf_counter()
        for i, node in enumerate(self.nodes):
            self._hb_last[i] = now
            self._hb_state[i] = NMT_OPERATIONAL
        while self.bus.recv(timeout=0) is not None:   # heartbeats and the like from the set-up
            pass
        n = len(self._ax)
        self._syncs = 0
        self._tpdos[:] = [0] * n
        self._lag_now[:] = [0] * n
        self._lag_prev[:] = [0] * n
        super()._activate()
        self._hb_count = 0

    def _prime_commands(self) -> None:
        """RPDO data of every axis: Disable voltage, 0 torque."""
        for msg in self._rx_msgs:
            msg.data[:] = bytes(len(msg.data))

    def _read_back_stop(self, answered: np.ndarray, deadline: float) -> list[StopCheck]:
        """More 0-torque, Disable-voltage cycles until every drive's statusword has left the
        powered states (Operation enabled, Quick stop active, Fault reaction active), then the
        torque actual value 0x6077 by SDO where the drive has it: confirmed when the drive is
        unpowered and its torque is 0."""
        n = len(self._ax)
        zeros, off = np.zeros(n), np.zeros(n, dtype=bool)
        powered = (cia402.OPERATION_ENABLED, cia402.QUICK_STOP_ACTIVE, cia402.FAULT_REACTION_ACTIVE)
        retry = max(self.STOP_RETRY_S, 4.0 * self.timeout_s)
        clock = time.perf_counter
        fresh = answered.copy()
        while self.connected and clock() < deadline and \
                any(cia402.decode_state(self._statusword[i]) in powered for i in range(n)):
            self.write(zeros, off)
            self.exchange_blocking(max(0.0, min(retry, deadline - clock())))
            fresh |= self._got
        torque: list = [None] * n
        why = [""] * n
        try:
            self._start_notifier()
            for i in range(n):
                raw = self._try_upload(i, cia402.TORQUE_ACTUAL)
                torque[i] = None if raw is None else int.from_bytes(raw[:2], "little", signed=True)
        except Exception as exc:  # noqa: BLE001  (reported per axis)
            why = [one_line(exc)] * n
        out = []
        for i, a in enumerate(self.axis_names):
            sw = self._statusword[i]
            state = cia402.decode_state(sw)
            t = torque[i]
            ok = bool(fresh[i]) and state not in powered and (t is None or t == 0) and not why[i]
            tq = (f"torque actual 0x6077 = {t} per mille" if t is not None else
                  (f"torque actual not read ({why[i]})" if why[i] else "no torque actual 0x6077 to read back"))
            out.append(StopCheck(a, ok, f"{'' if fresh[i] else 'no TPDO after the stop, last '}statusword "
                                        f"0x{sw:04X} ({cia402.STATE_NAMES[state]}), {tq}"))
        return out

    def _deactivate(self) -> None:
        """After the final 0-torque, Disable-voltage cycle (written by the base class): wait for
        its TPDO, then (SDO, notifier running again) heartbeat consumer off and NMT
        pre-operational, so the drives neither expect heartbeats nor act on PDOs."""
        super()._deactivate()
        if not self.connected or self.bus is None:
            return
        try:
            self._start_notifier()
            for i, node in enumerate(self.nodes):
                if self._has_consumer[i]:
                    self._write(i, cia402.CONSUMER_HEARTBEAT, 1, bytes(4), check=False)
                node.nmt.state = "PRE-OPERATIONAL"
        except Exception:  # noqa: BLE001  (stopping anyway: the drives' consumers stop them)
            self.connected = False

    def _reconnect(self, timeout_s: float | None) -> None:
        """As every split-phase driver's; the objects found by the first set-up stay the ones
        :meth:`_close` restores (the set-up again writes the same values)."""
        self._reconnecting = True
        try:
            super()._reconnect(timeout_s)
        finally:
            self._reconnecting = False

    def _close(self) -> None:
        """Every object the set-up changed written back as found (SDO, after the drives are
        pre-operational; counted in ``restored``), then the bus released."""
        if self.connected and self.bus is not None and any(self._changed) and not self._reconnecting:
            try:
                self._start_notifier()
                self.counters["restored"] += self._restore()
            except Exception:  # noqa: BLE001  (closing anyway)
                pass
        self.connected = False
        self._outstanding = False
        self._release_transport()

    # ------------------------------------------------------------------ cycle
    def _transmit_query(self, seq: int) -> None:  # pragma: no cover  (configure reads by SDO)
        raise NotImplementedError("the CANopen driver reads its first position by SDO")

    def _transmit(self, seq: int, u_V: np.ndarray, enable: np.ndarray) -> None:
        bus = self.bus
        ax = self._ax
        sms = self._sm
        cw_offs, tt_offs = self._cw_off, self._tt_off
        pack = _U16.pack_into
        packs = _I16.pack_into
        for i, msg in enumerate(self._rx_msgs):
            en = bool(enable[i])
            sm = sms[i]
            cw = sm.step(self._statusword[i], en)
            if self._setup_code[i] and not sm.fault:
                self._setup_code[i] = 0             # out of the Fault set-up found: no longer its reason
            if not en and not sm.fault and self._emcy_latched[i]:
                self._emcy_latched[i] = False       # disabled and out of Fault: the latch is reset
            elif en and sm.enabled and (self._emcy_named[i] or self._nmt_named[i] or self._hb_named[i]):
                self._emcy_named[i] = False         # enabled again: the EMCY is history
                self._nmt_named[i] = 0
                self._hb_named[i] = 0.0
            a = ax[i]
            t = cia402.volts_to_permille(float(u_V[i]), a.voltage_full_scale_V, a.full_scale_permille) \
                if en and sm.enabled else 0
            data = msg.data
            pack(data, cw_offs[i], cw)
            packs(data, tt_offs[i], t)
            try:
                bus.send(msg, timeout=0)
            except Exception:  # noqa: BLE001  (CanError / OSError: bus-off, queue full, link down)
                self.counters["send_errors"] += 1
                self.write_error[i] = True
        bus.send(self._sync_msg, timeout=0)
        self._syncs += 1
        self._hb_count += 1
        if self._hb_count >= self._hb_every:
            self._hb_count = 0
            bus.send(self._hb_msg, timeout=0)

    def _record_trace(self, i: int, sw: int) -> None:
        k = self._trace_n[i]
        if k < TRACE_LEN:
            self._trace[i][k] = sw
            self._trace_n[i] = k + 1

    def _receive(self) -> None:
        bus = self.bus
        tp, hb, em = self._tpdo_axis, self._hb_axis, self._emcy_axis
        while True:
            msg = bus.recv(timeout=0)
            if msg is None:
                return
            cid = msg.arbitration_id
            data = msg.data
            i = tp.get(cid)
            if i is not None:
                if len(data) < self._tpdo_len[i] or msg.is_remote_frame:
                    self.counters["bad_frames"] += 1
                    continue
                self._tpdos[i] += 1
                lag = self._syncs - self._tpdos[i]
                if lag > 0:                 # answers an earlier SYNC: late, not this cycle's
                    self.counters["stale"] += 1
                    self._lag_now[i] = lag
                    continue
                if lag < 0:                 # more TPDOs than SYNCs (the count started behind)
                    self._tpdos[i] = self._syncs
                sw = _U16.unpack_from(data, self._sw_off[i])[0]
                pos = _I32.unpack_from(data, self._pos_off[i])[0]
                if sw != self._statusword[i] and cia402.decode_state(sw) != cia402.decode_state(self._statusword[i]):
                    self._record_trace(i, sw)
                self._statusword[i] = sw
                st = sw & 0x4F
                fault = st == 0x08 or st == 0x0F
                self._accept(i, self.seq, pos & 0xFFFFFFFF, fault or self._emcy_latched[i])
                continue
            i = hb.get(cid)
            if i is not None:
                if len(data) >= 1:
                    self._hb_last[i] = time.perf_counter()
                    self._hb_state[i] = data[0] & 0x7F
                continue
            i = em.get(cid)
            if i is not None:
                if len(data) >= 3:
                    code = data[0] | data[1] << 8
                    self.counters["emcy"] += 1
                    self.emcy_register[i] = data[2]
                    if code != 0:
                        self.emcy_code[i] = code
                        self.emcy_count[i] += 1
                        self._emcy_latched[i] = True
                        self._emcy_named[i] = True
                        self.amp_fault[i] = True
                continue
            if msg.is_error_frame:
                self.counters["error_frames"] += 1

    def read(self) -> None:
        super().read()
        got = self._got
        now_lag, prev = self._lag_now, self._lag_prev
        for i in range(len(now_lag)):
            lag = now_lag[i]
            now_lag[i] = 0
            if got[i] or lag == 0:
                prev[i] = 0
            elif lag == prev[i]:            # the same lag two reads in a row: a TPDO was lost
                self._tpdos[i] += lag
                self.counters["tpdo_resyncs"] += 1
                prev[i] = 0
            else:
                prev[i] = lag
        now = time.perf_counter()
        lim = self._hb_timeout
        for i in range(len(self._hb_last)):
            if now - self._hb_last[i] > lim:
                # the drive's heartbeat is lost (CiA 301 §7.2.8.3.2, the heartbeat consumer's
                # event): an amplifier fault at this read, named, not an I/O error left to the
                # bucket (its ten cycles named the loss "driver error bucket full")
                self.read_error[i] = False
                self.amp_fault[i] = True
                if not self._hb_named[i]:
                    self._hb_named[i] = now - self._hb_last[i]
                self.counters["heartbeat_lost"] += 1
            elif self._hb_state[i] != NMT_OPERATIONAL:
                # the drive says it left Operational (CiA 301 §7.2.8.3.2: pre-operational,
                # stopped, a boot-up after a reset): no PDOs act any more, so an amplifier fault
                # at once, not an I/O error in the bucket (which would hide it)
                self.read_error[i] = False
                self.amp_fault[i] = True
                self._nmt_named[i] = self._hb_state[i] or 0x100     # boot-up (0) named too
                self.counters["nmt_left"] += 1
            if self._emcy_latched[i]:
                self.amp_fault[i] = True

    def reset_fault(self, i: int) -> bool:
        """The operator's fault reset of axis i's drive: CiA 402 transition 15 (the rising edge
        of controlword bit 7) in the next RPDOs while the axis is disabled, until the drive
        leaves Fault (:meth:`PowerStateMachine.request_reset`). Never sent otherwise."""
        self._sm[i].request_reset()
        return True

    # ------------------------------------------------------------------ reports
    def fault_state(self, i: int) -> str:
        """Axis i's drive's CiA 402 power state and statusword (0x6041) as last read, with what
        it said about its fault (:meth:`fault_reason`), e.g. "canopen node 1 (axis X) is in
        Fault (statusword 0x0218); EMCY 0x2310 ...". Outside the cycle."""
        sw = self._statusword[i]
        said = self.fault_reason(i)
        return (f"{self._where(i)} is in {cia402.STATE_NAMES[cia402.decode_state(sw)]} (statusword 0x{sw:04X})"
                + (f"; {said}" if said else ""))

    def fault_reason(self, i: int) -> str:
        """Why axis i reports an amplifier fault, one line ('' when it does not): the EMCY
        error code and its CiA 301/402 meaning (from the EMCY until the axis is in Operation
        enabled again, so the report after the fault reset still names it), or the drive's
        Fault state."""
        if (self._emcy_latched[i] or self._emcy_named[i]) and self.emcy_code[i]:
            return (f"EMCY {cia402.describe_error(self.emcy_code[i])} from {self._where(i)} "
                    f"(error register 0x{self.emcy_register[i]:02X})")
        if self._hb_named[i]:
            return (f"{self._where(i)}: heartbeat lost, none for {self._hb_named[i] * 1e3:.0f} ms "
                    f"(drive_heartbeat_timeout_ms {self.options.drive_heartbeat_timeout_ms})")
        if self._nmt_named[i]:
            state = self._nmt_named[i] & 0xFF
            return (f"{self._where(i)} left NMT Operational: its heartbeat says "
                    f"{NMT_STATE_NAMES.get(state, f'state 0x{state:02X}')} (0x{state:02X})")
        if self._sm[i].fault or self.amp_fault[i]:
            if self._setup_code[i]:
                return (f"error code 0x603F = {cia402.describe_error(self._setup_code[i])} "
                        f"(the drive was in Fault at set-up)")
            return f"{self._where(i)} in {cia402.STATE_NAMES[self._sm[i].state]} (statusword 0x{self._statusword[i]:04X})"
        return ""

    def drive_state(self, i: int) -> str:
        """Axis i's drive's CiA 402 power state and statusword (0x6041) as last read, whatever
        it is, e.g. "canopen node 1 (axis X) is in Switch on disabled (statusword 0x0250)"."""
        sw = self._statusword[i]
        return f"{self._where(i)} is in {cia402.STATE_NAMES[cia402.decode_state(sw)]} (statusword 0x{sw:04X})"

    def statusword_trace(self, i: int) -> list[tuple[int, str]]:
        """The statuswords at each state change of axis i since configure (first 32), with names."""
        return [(sw, cia402.STATE_NAMES[cia402.decode_state(sw)]) for sw in self._trace[i][:self._trace_n[i]]]

    def budget(self, rate_hz: float) -> BusBudget:
        """Bus time of one cycle: SYNC (0 bytes) + per axis one RPDO (4 bytes) and one TPDO
        (6 bytes), worst-case stuffing, classic CAN at ``bitrate`` or CAN FD (PDOs with bit rate
        switch at ``data_bitrate``), plus the round trip. The heartbeats (host and drives, 1 byte
        each) are a fixed share of the bus, independent of the rate: it is taken off
        ``max_bus_load``."""
        o = self.options
        n = len(self.axis_names)
        rt, source = self.budget_round_trip()
        hb_share = (1.0 / (o.host_heartbeat_ms * 1e-3) + n / (o.drive_heartbeat_ms * 1e-3)) \
            * frame_bits(1, False, False)[0] / o.bitrate
        load = max(o.max_bus_load - hb_share, 1e-6)

        def wire(fd: bool, dbr: int) -> float:
            t = frame_bits(0, False, False)[0] / o.bitrate
            for size in (4, 6):
                nom, dat = frame_bits(size, fd, False)
                t += n * (nom / o.bitrate + dat / dbr)
            return t

        w = wire(o.fd, o.data_bitrate)
        kind = (f"CAN FD {o.bitrate / 1e6:g}M/{o.data_bitrate / 1e6:g}M" if o.fd
                else f"classic CAN {o.bitrate / 1e6:g} Mbit/s")
        what = (f"CANopen {kind}, {n} axes: SYNC + {n} RPDO (4 B) + {n} TPDO (6 B) per cycle, worst-case "
                f"stuffing, heartbeats {hb_share * 100:.1f}% of the bus")
        room = load / rate_hz - rt
        fits = "fewer axes per bus (no CAN setting carries this rate)"
        if not o.fd and wire(True, 5_000_000) <= room:
            fits = f"fd: true, data_bitrate: 5000000 ({wire(True, 5_000_000) * 1e6:.1f} us per cycle)"
        elif o.fd and o.data_bitrate < 8_000_000 and wire(True, 8_000_000) <= room:
            fits = f"data_bitrate: 8000000 ({wire(True, 8_000_000) * 1e6:.1f} us per cycle)"
        return make_budget(rate_hz, w, rt, load, what, fits, source)

    def describe(self) -> dict:
        d = super().describe()
        o = self.options
        d.update(transport="canopen", interface=o.interface, channel=o.channel, fd=o.fd, bitrate=o.bitrate,
                 heartbeat={"host_node_id": o.host_node_id, "host_ms": o.host_heartbeat_ms,
                            "drive_consumer_ms": o.heartbeat_consumer_ms,
                            "abort_connection_option": f"{o.abort_connection_option} "
                                                       f"({cia402.ABORT_OPTIONS[o.abort_connection_option]})",
                            "drive_producer_ms": o.drive_heartbeat_ms,
                            "drive_timeout_ms": o.drive_heartbeat_timeout_ms})
        axes = {}
        for i, a in enumerate(self.axis_names):
            axes[a] = {"node_id": self._ax[i].node_id, **self.drive_info[i],
                       "state": cia402.STATE_NAMES[self._sm[i].state],
                       "statusword": f"0x{self._statusword[i]:04X}",
                       "statusword_trace": [f"0x{sw:04X} {name}" for sw, name in self.statusword_trace(i)],
                       "emcy": None if not self.emcy_count[i] else {
                           "code": f"0x{self.emcy_code[i]:04X}", "meaning": cia402.error_meaning(self.emcy_code[i]),
                           "count": self.emcy_count[i], "error_register": f"0x{self.emcy_register[i]:02X}"},
                       "fault_reason": self.fault_reason(i)}
        d["drives"] = axes
        d["emcy"] = {a: cia402.describe_error(self.emcy_code[i]) for i, a in enumerate(self.axis_names)
                     if self.emcy_count[i]}
        return d


_U16 = struct.Struct("<H")
_I16 = struct.Struct("<h")
_I32 = struct.Struct("<i")
