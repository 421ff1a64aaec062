"""An EtherCAT slave controller (ESC) model: the device side of an EtherCAT segment, in software.

Sources: ETG.1000.3/.4 (data link layer: frame, datagrams, working counter, addressing),
ETG.1000.6 (application layer: AL state machine, AL status codes, mailbox, CoE, SII), ETG.2010
(SII EEPROM contents and categories), and the register description of a Beckhoff ET1100/ET1200
ESC datasheet (section II) for the register addresses.

* :func:`build_sii`: an SII EEPROM image (identity, mailbox, general, string, FMMU, SyncM,
  TXPDO/RXPDO categories, the configuration-area checksum, CRC-8 x^8+x^2+x+1, seed 0xFF).
* :class:`Esc`: one slave's 64 KiB address space (registers 0x0000-0x0FFF, process RAM from
  0x1000) with what a master sees of an ESC: station address, DL status, AL control/status
  with the AL state machine and AL status codes on refused transitions, the EEPROM interface
  (0x0500-0x050F, 8-byte reads), sync managers (mailbox handshake on SM0/SM1, buffered process
  data on SM2/SM3) and FMMUs, the SM watchdog (0x0400 divider, 0x0420 time, 0x0440 status),
  the DC registers SOEM reads and writes (0x0900 receive-time latch, 0x0910 system time,
  0x0918, 0x0920 offset, 0x0928 delay, 0x0981 activation, 0x0990 start time, 0x09A0 SYNC0 cycle).
  The application behind it (a drive, a terminal) is a :class:`SlaveApp`.
* :class:`Segment`: a line of slaves as the frame passes them: every datagram of a frame
  (NOP, APRD/APWR/APRW, FPRD/FPWR/FPRW, BRD/BWR/BRW, LRD/LWR/LRW, ARMW, FRMW) addressed,
  answered and its working counter incremented as ETG.1000.4 §5.4 says (a logical write
  reaches, and counts in, a slave in OP only); the answer is the frame with the data read and
  the counters raised. Frames of another header type (4, 5) pass unchanged.

Where a naive model and an ESC differ, this one is the ESC: 0x0440 reads 1 from reset; a
watchdog trip zeroes the output pins, not the SM buffer in process RAM; an ESC that drives its
outputs itself (an EL2008-type terminal) stays in OP on a trip; an EEPROM write command without
the write-enable bit sets error bit 14 of 0x0502.

Time-compressed: a frame is handled at once, with the plant behind the slaves stepped inside
the logical datagram that writes the outputs (the application runs between the write and the
read of the same LRW), as the other emulators here answer with the position one period after
the command.
"""

from __future__ import annotations

import struct
import time

# --------------------------------------------------------------------------- constants
ETHERTYPE = 0x88A4
#: datagram command codes (ETG.1000.4 Table "EtherCAT command types")
NOP, APRD, APWR, APRW, FPRD, FPWR, FPRW, BRD, BWR, BRW, LRD, LWR, LRW, ARMW, FRMW = range(15)
COMMAND_NAMES = ("NOP", "APRD", "APWR", "APRW", "FPRD", "FPWR", "FPRW", "BRD", "BWR", "BRW",
                 "LRD", "LWR", "LRW", "ARMW", "FRMW")

#: registers (ESC datasheet section II)
REG_TYPE, REG_FMMU_COUNT, REG_SM_COUNT, REG_PORT_DESC, REG_FEATURES = 0x0000, 0x0004, 0x0005, 0x0007, 0x0008
REG_STATION, REG_ALIAS = 0x0010, 0x0012
REG_DL_CONTROL, REG_DL_STATUS = 0x0100, 0x0110
REG_AL_CONTROL, REG_AL_STATUS, REG_AL_CODE = 0x0120, 0x0130, 0x0134
REG_PDI_CONTROL = 0x0140
REG_WD_DIVIDER, REG_WD_PDI, REG_WD_PD, REG_WD_PD_STATUS, REG_WD_PD_COUNT = 0x0400, 0x0410, 0x0420, 0x0440, 0x0442
REG_EEP_CONFIG, REG_EEP_CONTROL, REG_EEP_ADDRESS, REG_EEP_DATA = 0x0500, 0x0502, 0x0504, 0x0508
REG_FMMU, REG_SM = 0x0600, 0x0800
REG_DC_RECV0, REG_DC_SYSTIME, REG_DC_RECV_PU, REG_DC_OFFSET, REG_DC_DELAY = 0x0900, 0x0910, 0x0918, 0x0920, 0x0928
REG_DC_ACTIVATION, REG_DC_START0, REG_DC_CYCLE0 = 0x0981, 0x0990, 0x09A0

#: AL states (ETG.1000.6 §6.4.1)
INIT, PREOP, BOOT, SAFEOP, OP = 1, 2, 3, 4, 8
AL_ERROR, AL_ACK = 0x10, 0x10
STATE_NAMES = {INIT: "INIT", PREOP: "PRE-OP", BOOT: "BOOT", SAFEOP: "SAFE-OP", OP: "OP"}

#: AL status codes (ETG.1000.6 Table 11), those this model raises
AL_INVALID_STATE_CHANGE = 0x0011
AL_UNKNOWN_STATE = 0x0012
AL_BOOTSTRAP_NOT_SUPPORTED = 0x0013
AL_INVALID_MAILBOX_CONFIG = 0x0016
AL_SM_WATCHDOG = 0x001B
AL_INVALID_OUTPUT_CONFIG = 0x001D
AL_INVALID_INPUT_CONFIG = 0x001E
AL_INVALID_SYNC_CYCLE = 0x0035
AL_CODE_TEXT = {0x0000: "no error", AL_INVALID_STATE_CHANGE: "invalid requested state change",
                AL_UNKNOWN_STATE: "unknown requested state", AL_BOOTSTRAP_NOT_SUPPORTED: "bootstrap not supported",
                AL_INVALID_MAILBOX_CONFIG: "invalid mailbox configuration", AL_SM_WATCHDOG: "sync manager watchdog",
                AL_INVALID_OUTPUT_CONFIG: "invalid output configuration",
                AL_INVALID_INPUT_CONFIG: "invalid input configuration", AL_INVALID_SYNC_CYCLE: "invalid sync cycle time"}

#: SyncM types (ETG.2010 SyncM category)
SM_MBX_OUT, SM_MBX_IN, SM_PD_OUT, SM_PD_IN = 1, 2, 3, 4
#: mailbox protocols (SII word 0x001C)
MBX_COE = 0x0004
#: SII category types (ETG.2010 Table 4)
CAT_STRINGS, CAT_GENERAL, CAT_FMMU, CAT_SYNCM, CAT_TXPDO, CAT_RXPDO, CAT_DC, CAT_END = 10, 30, 40, 41, 50, 51, 60, 0xFFFF
#: the smallest SYNC0 cycle the emulated slaves accept [ns]
MIN_SYNC0_CYCLE_NS = 100_000


def crc8_sii(data: bytes) -> int:
    """The SII configuration-area checksum (ETG.2010 §2.2: CRC-8, polynomial x^8+x^2+x+1 = 0x07,
    initial value 0xFF, no reflection) of ``data`` (words 0-6, 14 bytes)."""
    crc = 0xFF
    for b in data:
        crc ^= b
        for _ in range(8):
            crc = ((crc << 1) ^ 0x07) & 0xFF if crc & 0x80 else (crc << 1) & 0xFF
    return crc


def build_sii(*, vendor_id: int, product_code: int, revision: int, serial: int, name: str,
              mailbox: tuple[int, int, int, int] | None, syncms: list[tuple[int, int, int, int]],
              txpdos=(), rxpdos=(), coe_details: int = 0) -> bytes:
    """An SII EEPROM image (ETG.2010).

    Args:
        vendor_id, product_code, revision, serial: the identity (words 0x0008-0x000F).
        name: the device name (string 1, the general category's name and order index).
        mailbox: (rx offset, rx size, tx offset, tx size) of the standard mailbox, None: none.
        syncms: per SM (start address, length, control byte, type 1-4); enable 1.
        txpdos, rxpdos: per PDO (index, SM, [(index, subindex, bit length), ...]).
        coe_details: the general category's CoE details byte (bit 0 SDO, bit 2 PDO assign,
            bit 3 PDO configuration, bit 5 complete access).
    Returns:
        the image, a whole number of 16-bit words.
    """
    w = bytearray(0x80)
    struct.pack_into("<HHHH", w, 0, 0x0C08 if mailbox else 0x0005, 0, 0, 0)  # PDI control, config
    w[14] = crc8_sii(bytes(w[:14]))
    struct.pack_into("<IIII", w, 0x10, vendor_id, product_code, revision, serial)
    if mailbox:
        struct.pack_into("<HHHHH", w, 0x30, *mailbox, MBX_COE)
    struct.pack_into("<HH", w, 0x7C, 1, 1)        # size (1 KiBit - 1 ... here 2 KiBit), version 1
    cats = bytearray()

    def cat(kind, body):
        nonlocal cats
        if len(body) % 2:
            body += b"\x00"
        cats += struct.pack("<HH", kind, len(body) // 2) + body

    raw = name.encode("ascii")[:255]
    cat(CAT_STRINGS, bytes((1, len(raw))) + raw)
    general = bytearray(32)
    general[2] = 1      # order index: string 1
    general[3] = 1      # name index: string 1
    general[5] = coe_details
    cat(CAT_GENERAL, bytes(general))
    fmmu = bytes((1, 2, 3 if mailbox else 0, 0))   # FMMU use: outputs, inputs, mailbox state, 0 unused
    cat(CAT_FMMU, fmmu)
    body = b"".join(struct.pack("<HHBBBB", start, length, control, 0, 1, kind)
                    for start, length, control, kind in syncms)
    cat(CAT_SYNCM, body)
    for kind, pdos in ((CAT_TXPDO, txpdos), (CAT_RXPDO, rxpdos)):
        if not pdos:
            continue
        body = bytearray()
        for index, sm, entries in pdos:
            body += struct.pack("<HBBBBH", index, len(entries), sm, 0, 0, 0)
            for eindex, esub, bits in entries:
                body += struct.pack("<HBBBBH", eindex, esub, 0, 0, bits, 0)
        cat(kind, bytes(body))
    return bytes(w) + bytes(cats) + struct.pack("<H", CAT_END)


class SlaveApp:
    """The application behind an ESC (what a device's microcontroller does), hooks of :class:`Esc`.

    Attributes set by the subclass: ``outputs_size`` and ``inputs_size`` (bytes of process data
    through SM2 and SM3 in the current mapping).
    """

    outputs_size = 0
    inputs_size = 0

    def attach(self, esc: "Esc") -> None:
        self.esc = esc

    def mailbox(self, request: bytes) -> list[bytes]:
        """A mailbox write (master → slave), header included; returns the answers to queue."""
        return []

    def state_change(self, old: int, new: int) -> int:
        """A transition the ESC accepts (after its own checks); returns 0, or an AL status code
        that refuses it."""
        return 0

    #: the SM watchdog takes the slave to SAFE-OP (AL status code 0x001B): a device with a
    #: microcontroller behind the ESC. False: an ESC driving its outputs itself (digital I/O
    #: PDI, an EL2008-type terminal): the output pins go to 0 and the slave stays in OP, driving
    #: again with the next frame's outputs (ET1100 datasheet, "Watchdog": the digital outputs
    #: are reset; the AL state is the application's business)
    leaves_op_on_watchdog = True

    def watchdog_expired(self) -> None:
        """The SM watchdog ran out: outputs to their safe state."""


class Esc:
    """One EtherCAT slave controller (see the module docstring).

    Args:
        sii: the SII EEPROM image (:func:`build_sii`).
        app: the application behind it.
        syncms: as for :func:`build_sii` (the ESC's view of the SM layout it expects).
        dc: the ESC has distributed clocks (feature register bit 2).
        clock_ns: the local clock [ns] (default ``time.monotonic_ns``).
    """

    def __init__(self, sii: bytes, app: SlaveApp, syncms, *, dc: bool = False, clock_ns=time.monotonic_ns):
        self.mem = bytearray(0x10000)
        self.sii = bytearray(sii)
        self.app = app
        self.syncms = list(syncms)
        self.dc = dc
        self.clock_ns = clock_ns
        self._t0 = clock_ns()
        m = self.mem
        m[REG_TYPE] = 0x11                     # an ET1100-type ESC
        m[REG_FMMU_COUNT], m[REG_SM_COUNT] = 8, 8
        m[0x0006] = 8                          # 8 KiB process RAM
        m[REG_PORT_DESC] = 0x0F                # ports 0, 1 EBUS/MII
        struct.pack_into("<H", m, REG_FEATURES, 0x0004 if dc else 0x0000)   # bit 2: DC
        struct.pack_into("<H", m, REG_PDI_CONTROL, 0x0005 if not self.has_mailbox else 0x0008)
        struct.pack_into("<HH", m, REG_WD_DIVIDER, 2498, 0)                 # 100 us per unit
        struct.pack_into("<H", m, REG_WD_PDI, 1000)
        struct.pack_into("<H", m, REG_WD_PD, 1000)                          # 100 ms
        struct.pack_into("<H", m, REG_WD_PD_STATUS, 1)                      # 1: not expired (reset value)
        struct.pack_into("<H", m, REG_EEP_CONTROL, 0x0040)                  # 8-byte reads
        self.state = INIT
        self._set_al(INIT, 0)
        self.mbx_queue: list[bytes] = []
        self.last_outputs_ns = None            # local time of the last process-data write
        self.watchdog_gap_ns = 0               # at the last trip: last outputs → outputs 0 [ns]
        self.watchdog_trips = 0
        self.outputs_expired = False          # tripped, and no outputs written since
        self.outputs_written = False
        self.sync0_active = False
        self._fmmus: list[tuple[int, int, int, int]] = []    # active (logical start, length, physical, type)
        self._sms: list[tuple[int, int, int, int]] = [(0, 0, 0, 0)] * 8   # (start, length, control, activate)
        app.attach(self)

    @property
    def has_mailbox(self) -> bool:
        return any(kind == SM_MBX_OUT for *_, kind in self.syncms)

    # ----------------------------------------------------------------- helpers
    def local_ns(self) -> int:
        return self.clock_ns() - self._t0

    def u16(self, addr: int) -> int:
        return struct.unpack_from("<H", self.mem, addr)[0]

    def station(self) -> int:
        return self.u16(REG_STATION)

    def sm(self, n: int) -> tuple[int, int, int, int]:
        """(start, length, control, activate) of SM n as the master programmed it."""
        return self._sms[n]

    def _reload(self, addr: int, end: int) -> None:
        """Re-read the SM and FMMU settings after a write that touched them."""
        if addr < REG_SM + 64 and end > REG_SM:
            self._sms = [(s, ln, c, a) for s, ln, c, _st, a, _p in
                         (struct.unpack_from("<HHBBBB", self.mem, REG_SM + 8 * n) for n in range(8))]
        if addr < REG_FMMU + 128 and end > REG_FMMU:
            f = []
            for k in range(8):
                lstart, flen, _sb, _eb, pstart, _psb, ftype, act = struct.unpack_from("<IHBBHBBB", self.mem,
                                                                                      REG_FMMU + 16 * k)
                if act & 1 and flen:
                    f.append((lstart, flen, pstart, ftype))
            self._fmmus = f

    def sm_status(self, n: int, full: bool) -> None:
        a = REG_SM + 8 * n + 5
        self.mem[a] = (self.mem[a] | 0x08) if full else (self.mem[a] & ~0x08 & 0xFF)

    def sm_full(self, n: int) -> bool:
        return bool(self.mem[REG_SM + 8 * n + 5] & 0x08)

    def _set_al(self, state: int, code: int) -> None:
        self.state = state
        struct.pack_into("<H", self.mem, REG_AL_STATUS, state | (AL_ERROR if code else 0))
        struct.pack_into("<H", self.mem, REG_AL_CODE, code)

    def al_error(self) -> bool:
        return bool(self.mem[REG_AL_STATUS] & AL_ERROR)

    def dl_status(self, first: bool, last: bool) -> None:
        """DL status 0x0110 for a slave in a line: port 0 open with communication; port 1 open
        with communication unless last; ports 2, 3 closed (loop closed)."""
        v = 0x0001 | 0x0010 | 0x0200 | 0x5000
        v |= 0x0400 if last else (0x0020 | 0x0800)
        struct.pack_into("<H", self.mem, REG_DL_STATUS, v)

    # ----------------------------------------------------------------- register access
    def read(self, addr: int, n: int) -> bytes:
        """Physical read of ``n`` bytes at ``addr`` (a datagram's read); side effects of a
        read: the system time is sampled, the mailbox SM1 is emptied by reading its last byte."""
        m = self.mem
        if addr <= REG_DC_SYSTIME + 7 and addr + n > REG_DC_SYSTIME:
            struct.pack_into("<Q", m, REG_DC_SYSTIME, self.system_time_ns() & 0xFFFFFFFFFFFFFFFF)
        data = bytes(m[addr:addr + n])
        if self.has_mailbox and self.state >= PREOP:
            start, length, *_ = self.sm(1)
            if length and addr <= start + length - 1 < addr + n and self.sm_full(1):
                self.sm_status(1, False)
                self._next_mailbox()
        return data

    def readable(self, addr: int, n: int) -> bool:
        """A read of the mailbox SM1 area counts only when the mailbox is full (ETG.1000.4
        §5.4: an access the ESC refuses does not raise the working counter)."""
        if self.has_mailbox:
            start, length, *_ = self.sm(1)
            if length and addr < start + length and addr + n > start:
                return self.sm_full(1)
            start, length, *_ = self.sm(0)
            if length and addr < start + length and addr + n > start:
                return False
        return True

    def writable(self, addr: int, n: int) -> bool:
        if self.has_mailbox:
            start, length, *_ = self.sm(0)
            if length and addr < start + length and addr + n > start:
                return self.state >= PREOP and not self.sm_full(0)
            start, length, *_ = self.sm(1)
            if length and addr < start + length and addr + n > start:
                return False
        return True

    _READ_ONLY = ((0x0000, 0x0010), (REG_DL_STATUS, REG_DL_STATUS + 2), (REG_AL_STATUS, REG_AL_STATUS + 6),
                  (REG_WD_PD_STATUS, REG_WD_PD_STATUS + 2))

    def write(self, addr: int, data: bytes) -> None:
        """Physical write (a datagram's write) and its side effects."""
        m = self.mem
        end = addr + len(data)
        if addr <= REG_EEP_CONTROL + 1 and end > REG_EEP_CONTROL:
            status = self.u16(REG_EEP_CONTROL)
        for lo, hi in self._READ_ONLY:
            if addr < hi and end > lo:
                keep = bytes(m[lo:hi])
                m[addr:end] = data
                m[lo:hi] = keep
                break
        else:
            m[addr:end] = data
        if addr < REG_FMMU + 128 and end > REG_FMMU or addr < REG_SM + 64 and end > REG_SM:
            self._reload(addr, end)
        if addr <= REG_AL_CONTROL < end:
            self._al_control(self.u16(REG_AL_CONTROL))
        if addr <= REG_EEP_CONTROL + 1 and end > REG_EEP_CONTROL:
            self._eeprom(status)
        if addr <= REG_DC_RECV0 < end:
            t = self.local_ns()
            struct.pack_into("<IIII", m, REG_DC_RECV0, t & 0xFFFFFFFF, t & 0xFFFFFFFF, t & 0xFFFFFFFF,
                             t & 0xFFFFFFFF)
            struct.pack_into("<Q", m, REG_DC_RECV_PU, t)
        if addr <= REG_DC_ACTIVATION < end:
            self.sync0_active = m[REG_DC_ACTIVATION] & 0x03 == 0x03
        if self.has_mailbox and self.state >= PREOP:
            start, length, *_ = self.sm(0)
            if length and addr <= start + length - 1 < end:
                self.sm_status(0, True)
                request = bytes(m[start:start + length])
                self.sm_status(0, False)       # the application takes the request at once
                self.mbx_queue.extend(self.app.mailbox(request))
                self._next_mailbox()

    def system_time_ns(self) -> int:
        return self.local_ns() + struct.unpack_from("<q", self.mem, REG_DC_OFFSET)[0]

    def _next_mailbox(self) -> None:
        """Put the next queued answer into SM1 when it is empty."""
        if not self.mbx_queue or self.sm_full(1):
            return
        start, length, *_ = self.sm(1)
        if not length:
            return
        msg = self.mbx_queue.pop(0)[:length]
        self.mem[start:start + length] = msg + bytes(length - len(msg))
        self.sm_status(1, True)

    def post(self, message: bytes) -> None:
        """Queue a mailbox message from the slave (e.g. an emergency)."""
        self.mbx_queue.append(message)
        if self.state >= PREOP:
            self._next_mailbox()

    # ----------------------------------------------------------------- EEPROM
    def _eeprom(self, status_before: int) -> None:
        m = self.mem
        command = (m[REG_EEP_CONTROL + 1] & 0x07)
        write_enable = m[REG_EEP_CONTROL] & 0x01        # ECAT write enable, cleared by the command
        status = 0x0040
        word = struct.unpack_from("<I", m, REG_EEP_ADDRESS)[0]
        if command == 0x01:                     # read 8 bytes from the word address
            chunk = bytes(self.sii[2 * word:2 * word + 8])
            m[REG_EEP_DATA:REG_EEP_DATA + 8] = chunk + b"\xff" * (8 - len(chunk))
        elif command == 0x02:                   # write one word (0x0508) at the word address
            if not write_enable:
                status |= 0x4000                # error write enable: a write command without it
            elif 2 * word + 2 > len(self.sii):
                status |= 0x2000                # acknowledge/command error: beyond the EEPROM
            else:
                self.sii[2 * word:2 * word + 2] = m[REG_EEP_DATA:REG_EEP_DATA + 2]
        elif command not in (0x00, 0x04):      # 0x04 reload: the configuration is the image's
            status |= 0x2000
        struct.pack_into("<H", m, REG_EEP_CONTROL, status)

    # ----------------------------------------------------------------- AL state machine
    def _al_control(self, value: int) -> None:
        req, ack = value & 0x0F, value & AL_ACK
        if self.al_error() and not ack:
            return                               # an error indication waits for its acknowledge
        cur = self.state
        if req == cur:
            self._set_al(cur, 0)
            return
        if req not in (INIT, PREOP, BOOT, SAFEOP, OP):
            self._set_al(cur, AL_UNKNOWN_STATE)
            return
        if req == BOOT:
            self._set_al(cur, AL_BOOTSTRAP_NOT_SUPPORTED)
            return
        code = 0
        if req > cur:
            allowed = {INIT: PREOP, PREOP: SAFEOP, SAFEOP: OP}
            if allowed.get(cur) != req:
                code = AL_INVALID_STATE_CHANGE
            elif req == PREOP:
                code = self._check_mailbox()
            elif req == SAFEOP:
                code = self._check_process_data()
        if not code:
            code = self.app.state_change(cur, req)
        if code:
            self._set_al(cur, code)
            return
        if req == INIT:
            self.mbx_queue.clear()
            for n in (0, 1):
                self.sm_status(n, False)
        if req < SAFEOP:
            self.outputs_written = False
        if req == OP:
            self.last_outputs_ns = self.local_ns()
        self._set_al(req, 0)
        if req >= PREOP:
            self._next_mailbox()

    def _check_mailbox(self) -> int:
        for n, (start, length, control, kind) in enumerate(self.syncms):
            if kind in (SM_MBX_OUT, SM_MBX_IN):
                s, ln, _c, act = self.sm(n)
                if (s, ln) != (start, length) or not act & 1:
                    return AL_INVALID_MAILBOX_CONFIG
        return 0

    def _check_process_data(self) -> int:
        for n, (start, _length, _control, kind) in enumerate(self.syncms):
            if kind == SM_PD_OUT:
                size, code = self.app.outputs_size, AL_INVALID_OUTPUT_CONFIG
            elif kind == SM_PD_IN:
                size, code = self.app.inputs_size, AL_INVALID_INPUT_CONFIG
            else:
                continue
            s, ln, _c, act = self.sm(n)
            if size and (s != start or ln != size or not act & 1):
                return code
        if self.sync0_active:
            cycle = struct.unpack_from("<I", self.mem, REG_DC_CYCLE0)[0]
            if cycle < MIN_SYNC0_CYCLE_NS:
                return AL_INVALID_SYNC_CYCLE
        return 0

    # ----------------------------------------------------------------- process data, watchdog
    def pd_sm(self, kind: int) -> tuple[int, int] | None:
        """(start, length) of the process-data SM of ``kind`` (SM_PD_OUT / SM_PD_IN)."""
        for n, (start, length, _c, k) in enumerate(self.syncms):
            if k == kind:
                s, ln, _ctl, _act = self.sm(n)
                return s, ln
        return None

    def outputs(self) -> bytes:
        sm = self.pd_sm(SM_PD_OUT)
        return bytes(self.mem[sm[0]:sm[0] + sm[1]]) if sm and sm[1] else b""

    def set_inputs(self, data: bytes) -> None:
        sm = self.pd_sm(SM_PD_IN)
        if sm and sm[1]:
            self.mem[sm[0]:sm[0] + min(sm[1], len(data))] = data[:sm[1]]

    def watchdog_time_ns(self) -> int:
        """The SM watchdog time [ns] (0x0420 × (0x0400 + 2) × 40 ns), 0 when off (time 0, or
        SM2's watchdog-enable bit 6 clear)."""
        for n, (_s, _l, _c, kind) in enumerate(self.syncms):
            if kind == SM_PD_OUT:
                if not self.sm(n)[2] & 0x40:
                    return 0
                break
        else:
            return 0
        return self.u16(REG_WD_PD) * (self.u16(REG_WD_DIVIDER) + 2) * 40

    def check_watchdog(self) -> bool:
        """Trip the SM watchdog when OP has seen no outputs for the watchdog time: the output
        pins to 0 (the SM buffer in process RAM keeps the last data written, as an ESC's does),
        0x0440 = 0, the counter 0x0442 raised; a slave that :attr:`SlaveApp.leaves_op_on_watchdog`
        goes to SAFE-OP with AL status code 0x001B, another stays in OP and drives again with the
        next outputs. True when it tripped now."""
        if self.state != OP or self.last_outputs_ns is None or self.outputs_expired:
            return False
        wd = self.watchdog_time_ns()
        if not wd or self.local_ns() - self.last_outputs_ns <= wd:
            return False
        struct.pack_into("<H", self.mem, REG_WD_PD_STATUS, 0)
        self.mem[REG_WD_PD_COUNT] = (self.mem[REG_WD_PD_COUNT] + 1) & 0xFF
        self.watchdog_trips += 1
        self.outputs_expired = True
        self.watchdog_gap_ns = self.local_ns() - self.last_outputs_ns
        self.app.watchdog_expired()
        if self.app.leaves_op_on_watchdog:
            self._set_al(SAFEOP, AL_SM_WATCHDOG)
        return True

    def output_pins(self) -> bytes:
        """What the outputs drive: the SM buffer in OP, zeros below OP or after a watchdog
        trip until the next outputs."""
        data = self.outputs()
        return data if self.state == OP and not self.outputs_expired else bytes(len(data))

    def outputs_done(self) -> None:
        """The master wrote the outputs (a logical write reached SM2)."""
        self.last_outputs_ns = self.local_ns()
        self.outputs_written = True
        self.outputs_expired = False
        struct.pack_into("<H", self.mem, REG_WD_PD_STATUS, 1)


class Segment:
    """Slaves in a line and the frames that pass them (see the module docstring).

    Args:
        slaves: the ESCs in wiring order (position 1 first).
        on_outputs: called once per logical datagram that wrote outputs, between its writes and
            its reads (the applications run and the plant steps there).
    """

    def __init__(self, slaves: list[Esc], on_outputs=None):
        self.slaves = list(slaves)
        self.on_outputs = on_outputs or (lambda written: None)
        for k, s in enumerate(self.slaves):
            s.dl_status(k == 0, k == len(self.slaves) - 1)
        self.frames = 0
        self.passed = 0
        self.counts = {name: 0 for name in COMMAND_NAMES}

    def process(self, payload: bytearray) -> bool:
        """Handle the EtherCAT frame ``payload`` (the Ethernet payload: the 2-byte EtherCAT
        header, then datagrams), updated in place. True: the frame goes on (back to the master);
        False: it is dropped (shorter than its header, or a type 1 frame whose length field
        runs past its end). Only type 1 (DLPDUs) is processed; every other type (4: network
        variables, 5: mailbox gateway) passes the slaves unchanged, as ETG.1000.4 §5.2 has an
        ESC forward the frames it does not process (counted in ``passed``)."""
        if len(payload) < 2:
            return False
        hdr = struct.unpack_from("<H", payload, 0)[0]
        length, kind = hdr & 0x07FF, hdr >> 12
        if kind != 1:
            self.passed += 1
            return True
        if length + 2 > len(payload):
            return False
        self.frames += 1
        off = 2
        while off + 12 <= len(payload):
            cmd, _idx, a1, a2, lenf, _irq = struct.unpack_from("<BBHHHH", payload, off)
            n = lenf & 0x07FF
            data_off = off + 10
            if data_off + n + 2 > len(payload):
                break
            wkc = struct.unpack_from("<H", payload, data_off + n)[0]
            if cmd < len(COMMAND_NAMES):
                self.counts[COMMAND_NAMES[cmd]] += 1
                wkc, a1 = self._datagram(cmd, a1, a2, payload, data_off, n, wkc)
                struct.pack_into("<H", payload, off + 2, a1)
            struct.pack_into("<H", payload, data_off + n, wkc & 0xFFFF)
            off = data_off + n + 2
            if not lenf & 0x8000:
                break
        return True

    def _datagram(self, cmd, a1, a2, buf, doff, n, wkc):
        if cmd == NOP:
            return wkc, a1
        if cmd in (LRD, LWR, LRW):
            return self._logical(cmd, (a2 << 16) | a1, buf, doff, n, wkc), a1
        rd = cmd in (APRD, FPRD, BRD, APRW, FPRW, BRW)
        wr = cmd in (APWR, FPWR, BWR, APRW, FPRW, BRW)
        for s in self.slaves:
            if cmd in (APRD, APWR, APRW, ARMW):
                hit = a1 == 0
                a1 = (a1 + 1) & 0xFFFF
            elif cmd in (FPRD, FPWR, FPRW, FRMW):
                hit = a1 == s.station()
            else:                                           # broadcast: every slave, position counts
                hit = True
                a1 = (a1 + 1) & 0xFFFF
            if cmd in (ARMW, FRMW):                         # the addressed slave reads, the others write
                if hit:
                    if s.readable(a2, n):
                        buf[doff:doff + n] = s.read(a2, n)
                        wkc += 1
                elif s.writable(a2, n):
                    s.write(a2, bytes(buf[doff:doff + n]))
                    wkc += 1
                continue
            if not hit:
                continue
            inc = 0
            old = bytes(buf[doff:doff + n])
            if rd and s.readable(a2, n):
                data = s.read(a2, n)
                if cmd == BRD:                              # broadcast read: ORed into the datagram
                    buf[doff:doff + n] = bytes(x | y for x, y in zip(buf[doff:doff + n], data))
                else:
                    buf[doff:doff + n] = data
                inc += 1
            if wr and s.writable(a2, n):
                s.write(a2, old if cmd in (APRW, FPRW) and rd else bytes(buf[doff:doff + n]))
                inc += 2
            if cmd in (APRD, FPRD, BRD, APWR, FPWR, BWR):
                inc = min(inc, 1)
            wkc += inc
        return wkc, a1

    def _logical(self, cmd, la, buf, doff, n, wkc):
        """A logical datagram: outputs are taken (and counted) in OP only, since an ESC's
        output SM is enabled by the application in OP (ETG.1000.6 §6.4.1: SAFE-OP keeps the
        outputs in their safe state), so in SAFE-OP the working counter counts the inputs
        alone; inputs are read (and counted) in SAFE-OP and OP. ``on_outputs`` gets every slave
        the datagram mapped outputs of (their applications read their inputs' sources there)."""
        wrote = []
        reads = []
        for s in self.slaves:
            if s.state < SAFEOP:
                continue
            did_r = did_w = False
            for lstart, flen, pstart, ftype in s._fmmus:
                lo, hi = max(la, lstart), min(la + n, lstart + flen)
                if lo >= hi:
                    continue
                phys = pstart + (lo - lstart)
                if ftype & 0x02 and cmd in (LWR, LRW):      # outputs (master writes)
                    if s.state == OP:
                        s.write(phys, bytes(buf[doff + lo - la:doff + hi - la]))
                    did_w = True
                if ftype & 0x01 and cmd in (LRD, LRW):      # inputs (master reads)
                    reads.append((s, phys, lo - la, hi - lo))
                    did_r = True
            if did_w:
                wrote.append(s)
                if s.state == OP:
                    s.outputs_done()
                    wkc += 2 if cmd == LRW else 1
            if did_r:
                wkc += 1
        self.on_outputs(wrote)
        for s, phys, rel, ln in reads:
            buf[doff + rel:doff + rel + ln] = s.read(phys, ln)
        return wkc
