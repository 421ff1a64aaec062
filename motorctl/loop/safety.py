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

Everything here is plain float/int arithmetic on preallocated lists.
"""

from __future__ import annotations

import math
from typing import Annotated

from pydantic import Field

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


class Supervisor:
    """Per-axis latched fault state.

    Args:
        limits: one ``LimitsConfig`` per axis, in loop order.
        period_s: loop period [s] (turns the encoder speed bound into a per-cycle one).
    Attributes:
        fault: list[int] of latched fault bits per axis (0 = healthy); :meth:`reason` words them.
        fe_peak: list[float] high-water mark of |following error| [m] per axis.
    """

    def __init__(self, limits: list, period_s: float):
        n = len(limits)
        self.limits = limits
        self.fault = [0] * n
        self.bucket = [0] * n
        self.fe_peak = [0.0] * n
        self.y_last = [math.nan] * n
        self.value_at_fault = [0.0] * n   # the offending value (m, or error count)
        self.limit_at_fault = [0.0] * n
        self.io_errors = [0] * n          # total failed exchanges (counted, even below the limit)
        self._soft_lo = [lim.soft_min_m for lim in limits]
        self._soft_hi = [lim.soft_max_m for lim in limits]
        # the window the position is checked against: the soft limits, widened to where the
        # axis stands during a recovery (begin_recovery) and narrowing as it comes back in
        self._lo = list(self._soft_lo)
        self._hi = list(self._soft_hi)
        self._fe = [lim.following_error_m for lim in limits]
        self._fe_min = [lim.min_following_error_m for lim in limits]
        self._vmax = [lim.max_velocity_m_per_s for lim in limits]
        self._jump = [lim.encoder_max_speed_m_per_s * period_s for lim in limits]  # per cycle
        self._gap = [0] * n               # cycles since the last good reading
        self._inc = [lim.error_bucket_increment for lim in limits]
        self._dec = [lim.error_bucket_decrement for lim in limits]
        self._blim = [lim.error_bucket_limit for lim in limits]

    def _trip(self, i: int, bit: int, value: float, limit: float) -> None:
        if self.fault[i] == 0:
            self.value_at_fault[i] = value
            self.limit_at_fault[i] = limit
        self.fault[i] |= bit

    def check_input(self, i: int, y: float, io_error: bool, amp_fault: bool) -> bool:
        """Check axis i's reading before control. Returns True when the axis may be driven."""
        if io_error:
            self.io_errors[i] += 1
            self._gap[i] += 1
            b = self.bucket[i] + self._inc[i]
            self.bucket[i] = b
            if b >= self._blim[i]:
                self._trip(i, FAULT_IO_ERROR, float(b), float(self._blim[i]))
            return self.fault[i] == 0
        b = self.bucket[i] - self._dec[i]
        self.bucket[i] = b if b > 0 else 0
        if amp_fault:
            self._trip(i, FAULT_AMP_FAULT, 1.0, 0.0)
        if not (y - y == 0.0):  # NaN or inf
            self._trip(i, FAULT_NAN, y, 0.0)
            return False
        last = self.y_last[i]
        allowed = self._jump[i] * (self._gap[i] + 1)
        self._gap[i] = 0
        if last == last and abs(y - last) > allowed:
            self._trip(i, FAULT_ENCODER_JUMP, y - last, allowed)
        self.y_last[i] = y
        lo, hi = self._lo[i], self._hi[i]
        if y < lo:
            self._trip(i, FAULT_SOFT_LIMIT, y, lo)
        elif y > hi:
            self._trip(i, FAULT_SOFT_LIMIT, y, hi)
        elif lo != self._soft_lo[i] or hi != self._soft_hi[i]:
            # recovering: the window follows the axis in, never out (RECOVERY_MARGIN_M slack)
            m = RECOVERY_MARGIN_M
            self._lo[i] = max(lo, min(y - m, self._soft_lo[i]))
            self._hi[i] = min(hi, max(y + m, self._soft_hi[i]))
        return self.fault[i] == 0

    def check_output(self, i: int, e: float, xd_dot: float, u: float) -> bool:
        """Check the following error e [m] and the output u [V]. True when u may be written."""
        if not (u - u == 0.0):
            self._trip(i, FAULT_NAN, u, 0.0)
            return False
        ae = abs(e)
        if ae > self.fe_peak[i]:
            self.fe_peak[i] = ae
        lim = self._fe[i] * abs(xd_dot) / self._vmax[i]
        if lim < self._fe_min[i]:
            lim = self._fe_min[i]
        if ae > lim:
            self._trip(i, FAULT_FOLLOWING_ERROR, e, lim)
            return False
        return True

    def trip(self, i: int, bit: int) -> None:
        """Latch a loop-level fault (overrun policy, shutdown) on axis i."""
        self._trip(i, bit, 0.0, 0.0)

    def reason(self, i: int) -> str:
        """One line: the latched faults of axis i and the value that tripped the first one."""
        bits = self.fault[i]
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
        if y < self._soft_lo[i] or y > self._soft_hi[i]:
            return False, (f"position {y:.6f} m is outside the soft limits "
                           f"[{self._soft_lo[i]}, {self._soft_hi[i]}] m")
        if amp_fault:
            return False, "the amplifier still reports a fault"
        self._clear(i, y)
        self._lo[i], self._hi[i] = self._soft_lo[i], self._soft_hi[i]
        return True, ""

    def _clear(self, i: int, y: float) -> None:
        self.fault[i] = 0
        self.bucket[i] = 0
        self.y_last[i] = y
        self.fe_peak[i] = 0.0

    def inside(self, i: int, x: float) -> bool:
        """True when position x [m] lies within axis i's soft limits."""
        return self._soft_lo[i] <= x <= self._soft_hi[i]

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
        lo, hi = self._soft_lo[i], self._soft_hi[i]
        if not lo <= target <= hi:
            return False, f"target {target:.6f} m is outside the soft limits [{lo}, {hi}] m"
        if amp_fault:
            return False, "the amplifier still reports a fault"
        self._clear(i, y)
        m = RECOVERY_MARGIN_M
        self._lo[i], self._hi[i] = min(lo, y - m), max(hi, y + m)
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
