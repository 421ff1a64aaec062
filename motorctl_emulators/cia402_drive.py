"""The drive side of the CiA 402 power state machine, independent of the fieldbus: what an
emulated drive does with the controlword (CANopen: ``cia402_device``; EtherCAT CoE:
``ethercat_device``).

Source: CiA 402-2 (IEC 61800-7-201) §6.3, figure "state machine of the power drive system",
and the state coding table of the statusword 0x6041.
"""

from __future__ import annotations

from motorctl_drivers import cia402

#: statusword of each state (CiA 402-2 state coding; bit 5 "quick stop" is 1 when not quick
#: stopping, bit 4 "voltage enabled" in the powered states, bit 9 "remote": controlled by the bus)
STATUSWORD = {
    cia402.NOT_READY: 0x0000, cia402.SWITCH_ON_DISABLED: 0x0040, cia402.READY_TO_SWITCH_ON: 0x0031,
    cia402.SWITCHED_ON: 0x0033, cia402.OPERATION_ENABLED: 0x0037, cia402.QUICK_STOP_ACTIVE: 0x0017,
    cia402.FAULT_REACTION_ACTIVE: 0x001F, cia402.FAULT: 0x0008,
}


def drive_transition(state: int, cw: int, cw_prev: int) -> int:
    """The drive's next state after controlword ``cw`` (previous one ``cw_prev``), CiA 402-2
    §6.3 transitions 2-12 and 15 (commands decoded by bits 0-3 and 7)."""
    if state == cia402.FAULT:
        return cia402.SWITCH_ON_DISABLED if cw & 0x80 and not cw_prev & 0x80 else state
    if state == cia402.FAULT_REACTION_ACTIVE:
        return cia402.FAULT                                    # 14: the reaction is over
    if state == cia402.NOT_READY:
        return cia402.SWITCH_ON_DISABLED                       # 1: automatic
    disable_voltage = cw & 0x02 == 0
    quick_stop = cw & 0x06 == 0x02
    shutdown = cw & 0x87 == 0x06
    switch_on = cw & 0x8F == 0x07
    enable_op = cw & 0x8F == 0x0F
    if state == cia402.SWITCH_ON_DISABLED:
        return cia402.READY_TO_SWITCH_ON if shutdown else state                          # 2
    if state == cia402.READY_TO_SWITCH_ON:
        if disable_voltage or quick_stop:
            return cia402.SWITCH_ON_DISABLED                                             # 7
        return cia402.SWITCHED_ON if switch_on or enable_op else state                   # 3
    if state == cia402.SWITCHED_ON:
        if disable_voltage or quick_stop:
            return cia402.SWITCH_ON_DISABLED                                             # 10
        if shutdown:
            return cia402.READY_TO_SWITCH_ON                                             # 6
        return cia402.OPERATION_ENABLED if enable_op else state                          # 4
    if state == cia402.OPERATION_ENABLED:
        if disable_voltage:
            return cia402.SWITCH_ON_DISABLED                                             # 9
        if quick_stop:
            return cia402.QUICK_STOP_ACTIVE                                              # 11
        if shutdown:
            return cia402.READY_TO_SWITCH_ON                                             # 8
        return cia402.SWITCHED_ON if switch_on else state                                # 5
    if state == cia402.QUICK_STOP_ACTIVE:
        return cia402.SWITCH_ON_DISABLED                                                 # 12
    return state
