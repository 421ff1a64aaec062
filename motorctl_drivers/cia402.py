"""The CiA 402 drive profile, independent of the fieldbus (CANopen here; EtherCAT CoE reuses it).

Sources: CiA 402-2 (IEC 61800-7-201/-301) "Drives and motion control device profile" and
CiA 301 "CANopen application layer and communication profile". Everything here is plain
integer arithmetic on preallocated state: the cyclic part (:meth:`PowerStateMachine.step`)
allocates nothing and never blocks.

* Object indexes (:data:`CONTROLWORD`, ...) and the process-data mapping the motorctl drivers
  use in cyclic synchronous torque mode (:data:`RX_MAP`, :data:`TX_MAP`).
* The power state machine (CiA 402-2 §6.3, figure "state machine of the power drive system"):
  :func:`decode_state` reads the state from the statusword (0x6041), :class:`PowerStateMachine`
  chooses the controlword (0x6040) that moves the drive one transition towards what the axis's
  enable request asks for, confirmed cycle by cycle by the statusword.
* Error codes (CiA 301 Table 21 "Emergency error codes", CiA 402-2 Annex "error codes"):
  :func:`error_meaning` names a 16-bit error code as carried by an EMCY message or 0x603F.
* Scaling: target torque 0x6071 in per mille of the rated torque 0x6076
  (:func:`volts_to_permille`).
"""

from __future__ import annotations

# --------------------------------------------------------------------------- objects
#: CiA 301 communication objects used to set a drive up
DEVICE_TYPE = 0x1000            # UNSIGNED32; bits 0-15 device profile number (402 = 0x0192)
ERROR_REGISTER = 0x1001         # UNSIGNED8
COB_ID_SYNC = 0x1005            # UNSIGNED32
COMM_CYCLE_PERIOD = 0x1006      # UNSIGNED32 [us]
COB_ID_EMCY = 0x1014            # UNSIGNED32
CONSUMER_HEARTBEAT = 0x1016     # ARRAY of UNSIGNED32: bits 16-23 node-ID, bits 0-15 time [ms]
PRODUCER_HEARTBEAT = 0x1017     # UNSIGNED16 [ms]
RPDO_COMM, RPDO_MAPPING = 0x1400, 0x1600
TPDO_COMM, TPDO_MAPPING = 0x1800, 0x1A00

#: CiA 402-2 drive objects
ABORT_CONNECTION = 0x6007       # INTEGER16 abort connection option code (§ "common entries")
ERROR_CODE = 0x603F             # UNSIGNED16 last error code
CONTROLWORD = 0x6040            # UNSIGNED16
STATUSWORD = 0x6041             # UNSIGNED16
MODES_OF_OPERATION = 0x6060     # INTEGER8
MODES_DISPLAY = 0x6061          # INTEGER8
POSITION_ACTUAL = 0x6064        # INTEGER32 [increments]
TARGET_TORQUE = 0x6071          # INTEGER16 [per mille of rated torque]
MAX_TORQUE = 0x6072             # UNSIGNED16 [per mille of rated torque]
RATED_TORQUE = 0x6076           # UNSIGNED32 [mN m; mN for a linear motor]
TORQUE_ACTUAL = 0x6077          # INTEGER16 [per mille]
SUPPORTED_MODES = 0x6502        # UNSIGNED32, bit 9 = cyclic synchronous torque

PROFILE_402 = 402
MODE_CST = 10                   # cyclic synchronous torque mode (0x6060 value)
SUPPORTED_CST_BIT = 1 << 9

#: abort connection option codes (0x6007)
ABORT_OPTIONS = {0: "no action", 1: "fault signal", 2: "disable voltage command",
                 3: "quick stop command"}

#: the process data of one axis in cyclic synchronous torque mode: (index, subindex, bits)
#: received by the drive (RPDO): controlword, target torque
RX_MAP = ((CONTROLWORD, 0, 16), (TARGET_TORQUE, 0, 16))
#: transmitted by the drive (TPDO): statusword, position actual value
TX_MAP = ((STATUSWORD, 0, 16), (POSITION_ACTUAL, 0, 32))

# --------------------------------------------------------------------------- state machine
NOT_READY = 0
SWITCH_ON_DISABLED = 1
READY_TO_SWITCH_ON = 2
SWITCHED_ON = 3
OPERATION_ENABLED = 4
QUICK_STOP_ACTIVE = 5
FAULT_REACTION_ACTIVE = 6
FAULT = 7
UNKNOWN = 8

STATE_NAMES = ("Not ready to switch on", "Switch on disabled", "Ready to switch on", "Switched on",
               "Operation enabled", "Quick stop active", "Fault reaction active", "Fault", "unknown")

#: statusword bit patterns (CiA 402-2 Table "state coding"): (mask, value, state)
_STATE_CODING = ((0x4F, 0x00, NOT_READY), (0x4F, 0x40, SWITCH_ON_DISABLED),
                 (0x6F, 0x21, READY_TO_SWITCH_ON), (0x6F, 0x23, SWITCHED_ON),
                 (0x6F, 0x27, OPERATION_ENABLED), (0x6F, 0x07, QUICK_STOP_ACTIVE),
                 (0x4F, 0x0F, FAULT_REACTION_ACTIVE), (0x4F, 0x08, FAULT))

#: statusword bits
SW_READY_TO_SWITCH_ON, SW_SWITCHED_ON, SW_OPERATION_ENABLED, SW_FAULT = 0x01, 0x02, 0x04, 0x08
SW_VOLTAGE_ENABLED, SW_QUICK_STOP, SW_SWITCH_ON_DISABLED, SW_WARNING = 0x10, 0x20, 0x40, 0x80
SW_REMOTE = 0x200

#: controlword commands (CiA 402-2 Table "command coding")
CW_DISABLE_VOLTAGE = 0x0000     # transitions 7, 9, 10, 12 -> Switch on disabled
CW_SHUTDOWN = 0x0006            # transitions 2, 6, 8 -> Ready to switch on
CW_SWITCH_ON = 0x0007           # transition 3 -> Switched on (5 from Operation enabled)
CW_ENABLE_OPERATION = 0x000F    # transition 4 -> Operation enabled
CW_QUICK_STOP = 0x0002          # transitions 7, 10, 11
CW_FAULT_RESET = 0x0080         # transition 15 on the rising edge of bit 7


def decode_state(statusword: int) -> int:
    """The power state (:data:`NOT_READY` ... :data:`FAULT`) coded in ``statusword`` (0x6041).

    Returns :data:`UNKNOWN` for a pattern the profile does not define."""
    for mask, value, state in _STATE_CODING:
        if statusword & mask == value:
            return state
    return UNKNOWN


class PowerStateMachine:
    """Steps one drive's power state machine from the host, one controlword per cycle.

    ``step(statusword, enable)`` returns the controlword for this cycle: it moves the drive one
    transition towards Operation enabled while ``enable`` is requested (Shutdown → Switch on →
    Enable operation, each sent until the statusword confirms the state), towards Switch on
    disabled (Disable voltage, the power stage off at once) while it is not. A drive in Fault
    stays there (Disable voltage, bit 7 low) until the operator's :meth:`request_reset`: then,
    while the axis is not enabled, a rising edge of controlword bit 7 (0x0000, then 0x0080,
    transition 15 of CiA 402 §6.3.2, repeated every :attr:`RESET_RETRY_CYCLES` for at most
    :attr:`RESET_TRIES` edges) until the drive leaves Fault. The host never resets a drive's
    fault on its own: the fault stays latched in the drive, named by its error code, until the
    operator says so. A drive in Fault reaction active is left to finish its reaction. Nothing blocks: a transition the drive
    has not confirmed is simply asked for again in the next cycle.

    Attributes (all ints/bools, updated by :meth:`step`):
        state: the decoded state of the last statusword. enabled: True only in Operation
        enabled (the axis may be given torque). fault: Fault or Fault reaction active.
        controlword: the last controlword returned. transitions: number of state changes seen.
    """

    RESET_RETRY_CYCLES = 8
    #: rising edges of bit 7 one operator's reset sends at most
    RESET_TRIES = 3

    def __init__(self):
        self.state = UNKNOWN
        self.statusword = 0
        self.controlword = CW_DISABLE_VOLTAGE
        self.enabled = False
        self.fault = False
        self.transitions = 0
        self._reset_phase = 0
        self._reset_left = 0                 # cycles of the operator's reset still to send

    def request_reset(self) -> None:
        """The operator's fault reset (between cycles): the next :meth:`step` calls of a drive
        in Fault with the axis not enabled send the rising edge of bit 7 (class docstring)."""
        self._reset_phase = 0
        self._reset_left = self.RESET_TRIES * self.RESET_RETRY_CYCLES

    def step(self, statusword: int, enable: bool) -> int:
        """Controlword (0x6040) for this cycle from the drive's ``statusword`` (0x6041) and the
        axis's enable request. Allocation-free."""
        state = decode_state(statusword)
        if state != self.state:
            self.transitions += 1
            self.state = state
        self.statusword = statusword
        self.enabled = state == OPERATION_ENABLED
        self.fault = state == FAULT or state == FAULT_REACTION_ACTIVE
        if state == FAULT:
            if enable or self._reset_left <= 0:
                cw = CW_DISABLE_VOLTAGE      # latched in the drive until the operator's reset
                self._reset_phase = 0
            else:                            # 0x00, 0x80 (rising edge), hold, ..., retry
                cw = CW_FAULT_RESET if self._reset_phase == 1 else CW_DISABLE_VOLTAGE
                self._reset_phase = (self._reset_phase + 1) % self.RESET_RETRY_CYCLES
                self._reset_left -= 1
        else:
            self._reset_phase = 0
            if state != FAULT_REACTION_ACTIVE:
                self._reset_left = 0         # out of Fault: the reset is done
            if not enable or state in (FAULT_REACTION_ACTIVE, NOT_READY, QUICK_STOP_ACTIVE, UNKNOWN):
                cw = CW_DISABLE_VOLTAGE
            elif state == SWITCH_ON_DISABLED:
                cw = CW_SHUTDOWN
            elif state == READY_TO_SWITCH_ON:
                cw = CW_SWITCH_ON
            else:                            # Switched on or Operation enabled
                cw = CW_ENABLE_OPERATION
        self.controlword = cw
        return cw


# --------------------------------------------------------------------------- scaling
def volts_to_permille(u_V: float, full_scale_V: float, full_scale_permille: int) -> int:
    """Voltage command [V] → target torque 0x6071 [per mille of rated torque], INTEGER16:
    ±``full_scale_V`` ↔ ±``full_scale_permille``; saturates; NaN → 0."""
    if not (u_V == u_V):
        return 0
    c = round(u_V / full_scale_V * full_scale_permille)
    top = full_scale_permille
    return top if c > top else (-top if c < -top else int(c))


def permille_to_volts(t: int, full_scale_V: float, full_scale_permille: int) -> float:
    """Inverse of :func:`volts_to_permille` [V]."""
    return t * full_scale_V / full_scale_permille


# --------------------------------------------------------------------------- error codes
#: error code → meaning (CiA 301 Table 21; CiA 402-2 Annex, IEC 61800-7-201 error codes)
ERROR_CODES = {
    0x0000: "error reset or no error",
    0x1000: "generic error",
    0x2000: "current",
    0x2100: "current, device input side",
    0x2110: "short circuit/earth leakage (input)",
    0x2200: "current inside the device",
    0x2220: "continuous over-current (device internal)",
    0x2230: "short circuit/earth leakage (device internal)",
    0x2300: "current, device output side",
    0x2310: "continuous over-current",
    0x2320: "short circuit/earth leakage (motor side)",
    0x2330: "earth leakage (motor side)",
    0x2340: "short circuit (motor side)",
    0x3000: "voltage",
    0x3100: "mains voltage",
    0x3110: "mains over-voltage",
    0x3120: "mains under-voltage",
    0x3130: "mains phase failure",
    0x3200: "voltage inside the device",
    0x3210: "DC link over-voltage",
    0x3220: "DC link under-voltage",
    0x3300: "output voltage",
    0x3310: "output over-voltage",
    0x4000: "temperature",
    0x4100: "ambient temperature",
    0x4200: "device temperature",
    0x4210: "excess temperature device",
    0x4300: "drive temperature",
    0x4310: "excess temperature drive",
    0x4400: "supply temperature",
    0x5000: "device hardware",
    0x5100: "supply",
    0x5110: "supply low voltage",
    0x5200: "control",
    0x5400: "power section",
    0x5410: "output stages",
    0x5500: "data storage",
    0x6000: "device software",
    0x6010: "reset by watchdog",
    0x6100: "internal software",
    0x6200: "user software",
    0x6300: "data set",
    0x6320: "parameter error",
    0x7000: "additional modules",
    0x7100: "power",
    0x7110: "brake chopper",
    0x7120: "motor",
    0x7121: "motor blocked",
    0x7122: "motor error or commutation malfunction",
    0x7300: "sensor",
    0x7303: "resolver 1 fault",
    0x7305: "incremental sensor 1 fault",
    0x7310: "speed",
    0x7320: "position",
    0x7500: "communication",
    0x8000: "monitoring",
    0x8100: "communication",
    0x8110: "CAN overrun (objects lost)",
    0x8120: "CAN in error passive mode",
    0x8130: "life guard error or heartbeat error",
    0x8140: "recovered from bus off",
    0x8150: "CAN-ID collision",
    0x8200: "protocol error",
    0x8210: "PDO not processed due to length error",
    0x8220: "PDO length exceeded",
    0x8240: "unexpected SYNC data length",
    0x8250: "RPDO timeout",
    0x8300: "torque control",
    0x8311: "excess torque",
    0x8400: "velocity speed controller",
    0x8500: "position controller",
    0x8600: "positioning controller",
    0x8611: "following error",
    0x8612: "reference limit",
    0x8700: "sync controller",
    0x9000: "external error",
    0xF000: "additional functions",
    0xFF00: "device specific",
}


def error_meaning(code: int) -> str:
    """The meaning of a CiA 301/402 error code: the exact entry, else its group
    (code & 0xFFF0, & 0xFF00, & 0xF000), marked 'group'; 'device specific' for 0xFFxx."""
    if code in ERROR_CODES:
        return ERROR_CODES[code]
    if code & 0xFF00 == 0xFF00:
        return ERROR_CODES[0xFF00]
    for mask in (0xFFF0, 0xFF00, 0xF000):
        if code & mask in ERROR_CODES:
            return f"{ERROR_CODES[code & mask]} (group)"
    return "unknown error code"


def describe_error(code: int) -> str:
    """One line naming an error code and its meaning, e.g. '0x2310 continuous over-current'."""
    return f"0x{code:04X} {error_meaning(code)}"
