"""Safety supervisor, LinuxCNC semantics: checks run every cycle before the write, so a fault
puts the axis at 0 V with the amplifier disabled in the same cycle. Faults latch with their
reason until :meth:`Supervisor.reset` is called and the cause is gone.

Checks per axis (see ``LimitsConfig``):
  * NaN/inf in the measured position or in the computed output;
  * driver errors through a leaky bucket (hm2_eth's rule): +increment per failed exchange,
    −decrement per clean one, fault at the limit;
  * encoder sanity: a change of the reading faster than ``encoder_max_speed_m_per_s`` over the
    cycles since the last good reading (lost answers widen the allowance, any loop rate);
  * soft position limits;
  * velocity-scaled following error: limit = max(min_fe, fe·|ẋ_d|/v_max) (motion/control.c);
  * amplifier fault reported by the drive;
  * loop-level faults (overrun policy, shutdown) set by the loop.

The checks are compiled (numba) float/int arithmetic on two preallocated arrays, called from
the compiled servo cycle (:mod:`motorctl.loop.cycle`) and from the methods here.
"""

from __future__ import annotations

import math
from typing import Annotated

import numpy as np
from pydantic import Field

from motorctl.jit import njit
from motorctl.schema import Position_m, StrictModel, quantity

FAULT_FOLLOWING_ERROR = 1
FAULT_SOFT_LIMIT = 2
FAULT_NAN = 4
FAULT_IO_ERROR = 8
FAULT_AMP_FAULT = 16
FAULT_ENCODER_JUMP = 32
FAULT_OVERRUN = 64
FAULT_SHUTDOWN = 128
FAULT_RECORDER = 256

FAULT_NAMES = {
    FAULT_FOLLOWING_ERROR: "following error",
    FAULT_SOFT_LIMIT: "soft limit",
    FAULT_NAN: "NaN/inf",
    FAULT_IO_ERROR: "driver error bucket full",
    FAULT_AMP_FAULT: "amplifier fault",
    FAULT_ENCODER_JUMP: "encoder jump",
    FAULT_OVERRUN: "overrun",
    FAULT_SHUTDOWN: "shutdown",
    FAULT_RECORDER: "recorder",
}


def describe_faults(bits: int) -> str:
    """Human-readable list of the fault bits, e.g. 'following error, soft limit'."""
    return ", ".join(name for bit, name in FAULT_NAMES.items() if bits & bit) or "none"


def with_drive_reason(reason: str, drive: str) -> str:
    """A fault line (:meth:`Supervisor.reason`) with what the drive said about it appended
    (``Driver.fault_reason``, e.g. "EMCY 0x2310 continuous over-current ..."); the drive's
    words only go with a latched fault."""
    return f"{reason}; drive: {drive}" if reason and drive else reason


#: how far an axis being recovered (jogged back inside its soft limits) may move outwards
#: from the farthest-in position it reached before the soft limit trips again [m]
RECOVERY_MARGIN_M = 0.0005


# the supervisor's state, one row per axis (:class:`Supervisor`: ``si`` int64, ``sf`` float64)
SI_FAULT, SI_BUCKET, SI_GAP, SI_IOERR, SI_INC, SI_DEC, SI_BLIM = range(7)
N_SI = 7
(SF_YLAST, SF_FEPEAK, SF_VAF, SF_LAF, SF_LO, SF_HI, SF_SOFTLO, SF_SOFTHI, SF_FE, SF_FEMIN, SF_VMAX,
 SF_JUMP) = range(12)
N_SF = 12


@njit
def sup_trip(si, sf, i, bit, value, limit):
    """Latch fault ``bit`` on axis i; the first fault keeps the value and limit that tripped it."""
    if si[i, SI_FAULT] == 0:
        sf[i, SF_VAF] = value
        sf[i, SF_LAF] = limit
    si[i, SI_FAULT] |= bit


@njit
def sup_check_input(si, sf, i, y, io_error, amp_fault):
    """Check axis i's reading y [m] before control (module docstring). True when the axis may
    be driven."""
    if io_error:
        si[i, SI_IOERR] += 1
        si[i, SI_GAP] += 1
        b = si[i, SI_BUCKET] + si[i, SI_INC]
        si[i, SI_BUCKET] = b
        if b >= si[i, SI_BLIM]:
            sup_trip(si, sf, i, FAULT_IO_ERROR, float(b), float(si[i, SI_BLIM]))
        return si[i, SI_FAULT] == 0
    b = si[i, SI_BUCKET] - si[i, SI_DEC]
    si[i, SI_BUCKET] = b if b > 0 else 0
    if amp_fault:
        sup_trip(si, sf, i, FAULT_AMP_FAULT, 1.0, 0.0)
    if not (y - y == 0.0):  # NaN or inf
        sup_trip(si, sf, i, FAULT_NAN, y, 0.0)
        return False
    last = sf[i, SF_YLAST]
    allowed = sf[i, SF_JUMP] * (si[i, SI_GAP] + 1)
    si[i, SI_GAP] = 0
    if last == last and abs(y - last) > allowed:
        sup_trip(si, sf, i, FAULT_ENCODER_JUMP, y - last, allowed)
    sf[i, SF_YLAST] = y
    lo = sf[i, SF_LO]
    hi = sf[i, SF_HI]
    if y < lo:
        sup_trip(si, sf, i, FAULT_SOFT_LIMIT, y, lo)
    elif y > hi:
        sup_trip(si, sf, i, FAULT_SOFT_LIMIT, y, hi)
    elif lo != sf[i, SF_SOFTLO] or hi != sf[i, SF_SOFTHI]:
        # recovering: the window follows the axis in, never out (RECOVERY_MARGIN_M slack)
        m = RECOVERY_MARGIN_M
        sf[i, SF_LO] = max(lo, min(y - m, sf[i, SF_SOFTLO]))
        sf[i, SF_HI] = min(hi, max(y + m, sf[i, SF_SOFTHI]))
    return si[i, SI_FAULT] == 0


@njit
def sup_check_output(si, sf, i, e, xd_dot, u):
    """Check axis i's following error e [m] (velocity-scaled limit at ẋ_d [m/s]) and output
    u [V]. True when u may be written."""
    if not (u - u == 0.0):
        sup_trip(si, sf, i, FAULT_NAN, u, 0.0)
        return False
    ae = abs(e)
    if ae > sf[i, SF_FEPEAK]:
        sf[i, SF_FEPEAK] = ae
    lim = sf[i, SF_FE] * abs(xd_dot) / sf[i, SF_VMAX]
    if lim < sf[i, SF_FEMIN]:
        lim = sf[i, SF_FEMIN]
    if ae > lim:
        sup_trip(si, sf, i, FAULT_FOLLOWING_ERROR, e, lim)
        return False
    return True


class Supervisor:
    """Per-axis latched fault state.

    The state lives in two arrays the compiled cycle works on, one row per axis: ``si``
    (int64, ``SI_*`` columns) and ``sf`` (float64, ``SF_*``); the checks are the compiled
    :func:`sup_check_input` / :func:`sup_check_output`, also called by the methods here.

    Args:
        limits: one ``LimitsConfig`` per axis, in loop order.
        period_s: loop period [s] (turns the encoder speed bound into a per-cycle one).
    Attributes (column views of the state, indexed by axis):
        fault: latched fault bits (0 = healthy); :meth:`reason` words them.
        fe_peak: high-water mark of |following error| [m]. bucket, io_errors (total failed
        exchanges, counted even below the limit), value_at_fault, limit_at_fault.
    """

    def __init__(self, limits: list, period_s: float):
        n = len(limits)
        self.limits = limits
        si = np.zeros((n, N_SI), dtype=np.int64)
        sf = np.zeros((n, N_SF))
        for i, lim in enumerate(limits):
            si[i, SI_INC] = lim.error_bucket_increment
            si[i, SI_DEC] = lim.error_bucket_decrement
            si[i, SI_BLIM] = lim.error_bucket_limit
            sf[i, SF_YLAST] = math.nan
            # the window the position is checked against (SF_LO, SF_HI): the soft limits,
            # widened to where the axis stands during a recovery (begin_recovery) and
            # narrowing as it comes back in
            sf[i, SF_LO] = sf[i, SF_SOFTLO] = lim.soft_min_m
            sf[i, SF_HI] = sf[i, SF_SOFTHI] = lim.soft_max_m
            sf[i, SF_FE] = lim.following_error_m
            sf[i, SF_FEMIN] = lim.min_following_error_m
            sf[i, SF_VMAX] = lim.max_velocity_m_per_s
            sf[i, SF_JUMP] = lim.encoder_max_speed_m_per_s * period_s     # per cycle
        self.si, self.sf = si, sf
        self.fault = si[:, SI_FAULT]
        self.bucket = si[:, SI_BUCKET]
        self.io_errors = si[:, SI_IOERR]
        self.fe_peak = sf[:, SF_FEPEAK]
        self.y_last = sf[:, SF_YLAST]
        self.value_at_fault = sf[:, SF_VAF]
        self.limit_at_fault = sf[:, SF_LAF]

    def check_input(self, i: int, y: float, io_error: bool, amp_fault: bool) -> bool:
        """Check axis i's reading before control. Returns True when the axis may be driven."""
        return sup_check_input(self.si, self.sf, i, y, io_error, amp_fault)

    def check_output(self, i: int, e: float, xd_dot: float, u: float) -> bool:
        """Check the following error e [m] and the output u [V]. True when u may be written."""
        return sup_check_output(self.si, self.sf, i, e, xd_dot, u)

    def trip(self, i: int, bit: int) -> None:
        """Latch a loop-level fault (overrun policy, shutdown) on axis i."""
        sup_trip(self.si, self.sf, i, bit, 0.0, 0.0)

    def reason(self, i: int) -> str:
        """One line: the latched faults of axis i and the value that tripped the first one."""
        bits = int(self.fault[i])
        if not bits:
            return ""
        return (f"{describe_faults(bits)} (value {self.value_at_fault[i]:.6g}, "
                f"limit {self.limit_at_fault[i]:.6g})")

    def reset(self, i: int, y: float, amp_fault: bool) -> tuple[bool, str]:
        """Clear axis i's latched fault if its cause is gone (outside the cycle).

        Returns (cleared, why_not). Refused while the position is NaN or outside the soft
        limits, or the amplifier still reports a fault.
        """
        if not (y - y == 0.0):
            return False, "position reading is not finite"
        lo, hi = float(self.sf[i, SF_SOFTLO]), float(self.sf[i, SF_SOFTHI])
        if y < lo or y > hi:
            return False, f"position {y:.6f} m is outside the soft limits [{lo}, {hi}] m"
        if amp_fault:
            return False, "the amplifier still reports a fault"
        self._clear(i, y)
        self.sf[i, SF_LO], self.sf[i, SF_HI] = lo, hi
        return True, ""

    def _clear(self, i: int, y: float) -> None:
        self.fault[i] = 0
        self.bucket[i] = 0
        self.y_last[i] = y
        self.fe_peak[i] = 0.0

    def inside(self, i: int, x: float) -> bool:
        """True when position x [m] lies within axis i's soft limits."""
        return bool(self.sf[i, SF_SOFTLO] <= x <= self.sf[i, SF_SOFTHI])

    def begin_recovery(self, i: int, y: float, target: float, amp_fault: bool) -> tuple[bool, str]:
        """Let axis i be moved back inside its soft limits (a jog to ``target`` [m], outside
        the cycle). Allowed when the position y [m] is finite, the target lies inside the
        limits and the amplifier is healthy: the checks of :meth:`reset` with "inside the
        limits" replaced by "the target is inside". Every latched fault is cleared (whatever
        else latched with the soft limit, e.g. the NaN reading of an axis that then coasted out,
        is judged as :meth:`reset` judges it; a reset that must wait for the axis to be inside
        could otherwise never come), and the position window is widened to where the axis
        stands (plus RECOVERY_MARGIN_M); it narrows as the axis comes in, so moving further out
        trips the soft limit again. Returns (allowed, why_not)."""
        if not (y - y == 0.0):
            return False, "position reading is not finite"
        lo, hi = float(self.sf[i, SF_SOFTLO]), float(self.sf[i, SF_SOFTHI])
        if not lo <= target <= hi:
            return False, f"target {target:.6f} m is outside the soft limits [{lo}, {hi}] m"
        if amp_fault:
            return False, "the amplifier still reports a fault"
        self._clear(i, y)
        m = RECOVERY_MARGIN_M
        self.sf[i, SF_LO], self.sf[i, SF_HI] = min(lo, y - m), max(hi, y + m)
        return True, ""


class LimitsConfig(StrictModel):
    """Supervisor limits (LinuxCNC semantics). Lengths in m, velocities in m/s.

    following_error_m applies at max_velocity_m_per_s and scales with |ẋ_d| down to
    min_following_error_m; encoder_max_speed_m_per_s bounds the speed a change of the encoder
    reading may show (over the cycles since the last good reading): no physical motion is faster.
    """

    soft_min_m: Position_m = -1.0
    soft_max_m: Position_m = 1.0
    following_error_m: quantity(1e-7, 1.0, "m") = 0.002
    min_following_error_m: quantity(1e-7, 1.0, "m") = 0.0005
    max_velocity_m_per_s: quantity(1e-6, 50.0, "m/s") = 3.0
    encoder_max_speed_m_per_s: quantity(1e-3, 1000.0, "m/s") = 10.0
    error_bucket_increment: Annotated[int, Field(ge=1)] = 10
    error_bucket_decrement: Annotated[int, Field(ge=1)] = 1
    error_bucket_limit: Annotated[int, Field(ge=1)] = 100
