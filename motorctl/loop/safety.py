"""Safety supervisor, LinuxCNC semantics: checks run every cycle before the write, so a fault
puts the axis at 0 V with the amplifier disabled in the same cycle. Faults latch with their
reason until :meth:`Supervisor.reset` is called and the cause is gone.

Checks per axis (see ``LimitsConfig``):
  * NaN/inf in the measured position or in the computed output;
  * driver errors through a leaky bucket (hm2_eth's rule): +increment per failed exchange,
    −decrement per clean one, fault at the limit;
  * encoder sanity: a change of the reading faster than ``encoder_max_speed_m_per_s`` over the
    cycles since the last good reading (lost answers widen the allowance, any loop rate);
  * soft position limits: every commanded target is checked against them before anything
    moves (the planner, a jog); the reading trips beyond them widened by the following error
    allowed at rest (``min_following_error_m``): a move that ends at a limit may settle a count
    or two beyond it, a carriage further out is not following its command (a push, a coast at
    0 V after a fault at speed);
  * velocity-scaled following error: limit = max(min_fe, fe·|ẋ_d|/v_max) (motion/control.c);
  * amplifier fault reported by the drive;
  * I²t of the output (:func:`sup_check_thermal`): the drive's thermal protection of the coil;
  * sustained oscillation at rest (:func:`sup_check_thermal`): a limit cycle while ẋ_d = 0;
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
FAULT_I2T = 512
FAULT_OSCILLATION = 1024

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
    FAULT_I2T: "i2t",
    FAULT_OSCILLATION: "oscillation",
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
(SI_FAULT, SI_BUCKET, SI_GAP, SI_IOERR, SI_INC, SI_DEC, SI_BLIM, SI_OSC_N, SI_OSC_WIN, SI_OSC_X, SI_OSC_SGN,
 SI_OSC_REST) = range(12)
N_SI = 12
(SF_YLAST, SF_FEPEAK, SF_VAF, SF_LAF, SF_LO, SF_HI, SF_SOFTLO, SF_SOFTHI, SF_FE, SF_FEMIN, SF_VMAX,
 SF_JUMP, SF_TS, SF_I2T, SF_I2T_CONT, SF_I2T_LIM, SF_I2T_PEAK, SF_OSC_MEAN, SF_OSC_S2, SF_OSC_ALPHA, SF_OSC_RMS,
 SF_OSC_HZ, SF_OSC_PEAK, SF_OSC_F, SF_OSC_S1) = range(25)
N_SF = 25


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
    rlo = sf[i, SF_SOFTLO] - sf[i, SF_FEMIN]     # the reading's window (module docstring)
    rhi = sf[i, SF_SOFTHI] + sf[i, SF_FEMIN]
    if y < lo:
        sup_trip(si, sf, i, FAULT_SOFT_LIMIT, y, lo)
    elif y > hi:
        sup_trip(si, sf, i, FAULT_SOFT_LIMIT, y, hi)
    elif lo != rlo or hi != rhi:
        # recovering: the window follows the axis in, never out (RECOVERY_MARGIN_M slack)
        m = RECOVERY_MARGIN_M
        sf[i, SF_LO] = max(lo, min(y - m, rlo))
        sf[i, SF_HI] = min(hi, max(y + m, rhi))
    return si[i, SI_FAULT] == 0


@njit
def sup_check_thermal(si, sf, i, xd_dot, u):
    """Axis i's output u [V] (ẋ_d [m/s] its reference's speed) through the I²t model and the
    oscillation detector; True when u may be written, else FAULT_I2T or FAULT_OSCILLATION is
    latched.

    I²t (the drives' "I²t time limit": Copley Controls Accelnet/Xenus user guides, "I2T
    current limiting"; Kollmorgen AKD "foldback"): the accumulator A [V² s] integrates
    u² − u_cont² every period (never below 0, so it cools at u_cont² per second at 0 V) and
    trips above (u_peak² − u_cont²)·t_peak: u_peak may be held for t_peak from cold, any u up
    to u_cont for ever. u [V] is the current command of the amplifier (u ∝ coil current).

    Oscillation at rest: while ẋ_d = 0, consecutive windows of ``oscillation_window_s``: the
    RMS of u about the window's mean (what oscillates, not a holding force) and the crossings
    of u through its running mean (first-order, time constant a fifth of a window, from the
    first sample of rest); a window whose RMS exceeds ``oscillation_rms_V`` with crossings at
    ≥ ``oscillation_min_hz`` (crossings / 2 per second) trips, its frequency kept
    (``oscillation_hz``). Any ẋ_d ≠ 0 ends the window: a trip comes one window after the
    reference came to rest at the earliest.
    """
    a = sf[i, SF_I2T] + (u * u - sf[i, SF_I2T_CONT]) * sf[i, SF_TS]
    a = a if a > 0.0 else 0.0
    sf[i, SF_I2T] = a
    if a > sf[i, SF_I2T_PEAK]:
        sf[i, SF_I2T_PEAK] = a
    if a > sf[i, SF_I2T_LIM]:
        sup_trip(si, sf, i, FAULT_I2T, a, sf[i, SF_I2T_LIM])
        return False
    if xd_dot != 0.0:
        si[i, SI_OSC_REST] = 0
        si[i, SI_OSC_N] = 0
        return True
    if si[i, SI_OSC_REST] == 0:                # rest begins: a new window, the mean from here
        si[i, SI_OSC_REST] = 1
        si[i, SI_OSC_N] = 0
        si[i, SI_OSC_SGN] = 0
        sf[i, SF_OSC_MEAN] = u
    m = sf[i, SF_OSC_MEAN] + sf[i, SF_OSC_ALPHA] * (u - sf[i, SF_OSC_MEAN])
    sf[i, SF_OSC_MEAN] = m
    d = u - m
    n = si[i, SI_OSC_N]
    if n == 0:
        si[i, SI_OSC_X] = 0
        sf[i, SF_OSC_S1] = 0.0
        sf[i, SF_OSC_S2] = 0.0
    sf[i, SF_OSC_S1] += u
    sf[i, SF_OSC_S2] += u * u
    sgn = 1 if d > 0.0 else (-1 if d < 0.0 else 0)
    if sgn != 0:
        if sgn == -si[i, SI_OSC_SGN]:
            si[i, SI_OSC_X] += 1
        si[i, SI_OSC_SGN] = sgn
    n += 1
    if n < si[i, SI_OSC_WIN]:
        si[i, SI_OSC_N] = n
        return True
    si[i, SI_OSC_N] = 0
    mean = sf[i, SF_OSC_S1] / n
    var = sf[i, SF_OSC_S2] / n - mean * mean
    rms = math.sqrt(var) if var > 0.0 else 0.0
    if rms > sf[i, SF_OSC_PEAK]:
        sf[i, SF_OSC_PEAK] = rms
    f = si[i, SI_OSC_X] / (2.0 * n * sf[i, SF_TS])
    if rms > sf[i, SF_OSC_RMS] and f >= sf[i, SF_OSC_HZ]:
        sf[i, SF_OSC_F] = f
        sup_trip(si, sf, i, FAULT_OSCILLATION, rms, sf[i, SF_OSC_RMS])
        return False
    return True


@njit
def sup_rest(si, sf, i):
    """A period of axis i at 0 V (disabled or faulted): the I²t accumulator cools by
    u_cont²·Ts (:func:`sup_check_thermal`), and the oscillation window ends."""
    a = sf[i, SF_I2T] - sf[i, SF_I2T_CONT] * sf[i, SF_TS]
    sf[i, SF_I2T] = a if a > 0.0 else 0.0
    si[i, SI_OSC_REST] = 0
    si[i, SI_OSC_N] = 0


@njit
def sup_check_output(si, sf, i, e, xd_dot, u):
    """Check axis i's following error e [m] (velocity-scaled limit at ẋ_d [m/s]) and output
    u [V] (NaN, then :func:`sup_check_thermal`). True when u may be written."""
    if not (u - u == 0.0):
        sup_trip(si, sf, i, FAULT_NAN, u, 0.0)
        return False
    if not sup_check_thermal(si, sf, i, xd_dot, u):
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
        i2t, i2t_limit, i2t_peak: the I²t accumulator, its trip level and high-water mark
        [V² s]; oscillation_rms_peak, oscillation_rms_limit: the largest RMS of a window at
        rest and the trip level [V]; oscillation_hz: the frequency of the window that tripped
        [Hz] (:func:`sup_check_thermal`).
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
            # the window the reading is checked against (SF_LO, SF_HI): the soft limits
            # (SF_SOFTLO, SF_SOFTHI) widened by the following error allowed at rest (module
            # docstring), and further to where the axis stands during a recovery
            # (begin_recovery), narrowing as it comes back in
            sf[i, SF_SOFTLO], sf[i, SF_SOFTHI] = lim.soft_min_m, lim.soft_max_m
            sf[i, SF_FE] = lim.following_error_m
            sf[i, SF_FEMIN] = lim.min_following_error_m
            sf[i, SF_LO] = lim.soft_min_m - lim.min_following_error_m
            sf[i, SF_HI] = lim.soft_max_m + lim.min_following_error_m
            sf[i, SF_VMAX] = lim.max_velocity_m_per_s
            sf[i, SF_JUMP] = lim.encoder_max_speed_m_per_s * period_s     # per cycle
            sf[i, SF_TS] = period_s
            sf[i, SF_I2T_CONT] = lim.i2t_continuous_V ** 2
            sf[i, SF_I2T_LIM] = (lim.i2t_peak_V ** 2 - lim.i2t_continuous_V ** 2) * lim.i2t_peak_time_s
            n_win = max(2, round(lim.oscillation_window_s / period_s))
            si[i, SI_OSC_WIN] = n_win
            sf[i, SF_OSC_ALPHA] = min(1.0, 5.0 / n_win)   # the running mean: a fifth of a window
            sf[i, SF_OSC_RMS] = lim.oscillation_rms_V
            sf[i, SF_OSC_HZ] = lim.oscillation_min_hz
        self.si, self.sf = si, sf
        self.fault = si[:, SI_FAULT]
        self.bucket = si[:, SI_BUCKET]
        self.io_errors = si[:, SI_IOERR]
        self.fe_peak = sf[:, SF_FEPEAK]
        self.y_last = sf[:, SF_YLAST]
        self.value_at_fault = sf[:, SF_VAF]
        self.limit_at_fault = sf[:, SF_LAF]
        self.i2t = sf[:, SF_I2T]
        self.i2t_limit = sf[:, SF_I2T_LIM]
        self.i2t_peak = sf[:, SF_I2T_PEAK]
        self.oscillation_rms_peak = sf[:, SF_OSC_PEAK]
        self.oscillation_rms_limit = sf[:, SF_OSC_RMS]
        self.oscillation_hz = sf[:, SF_OSC_F]

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
        at = f" at {self.oscillation_hz[i]:.3g} Hz" if bits & FAULT_OSCILLATION else ""
        return (f"{describe_faults(bits)}{at} (value {self.value_at_fault[i]:.6g}, "
                f"limit {self.limit_at_fault[i]:.6g})")

    def reset(self, i: int, y: float, amp_fault: bool) -> tuple[bool, str]:
        """Clear axis i's latched fault if its cause is gone (outside the cycle).

        Returns (cleared, why_not). Refused while the position is NaN or stands outside the
        soft limits (:meth:`stands_inside`), or the amplifier still reports a fault.
        """
        if not (y - y == 0.0):
            return False, "position reading is not finite"
        if not self.stands_inside(i, y):
            lo, hi = float(self.sf[i, SF_SOFTLO]), float(self.sf[i, SF_SOFTHI])
            return False, f"position {y:.6f} m is outside the soft limits [{lo}, {hi}] m"
        if amp_fault:
            return False, "the amplifier still reports a fault"
        self._clear(i, y)
        self.sf[i, SF_LO], self.sf[i, SF_HI] = self._reading_window(i)
        return True, ""

    def _reading_window(self, i: int) -> tuple[float, float]:
        tol = float(self.sf[i, SF_FEMIN])
        return float(self.sf[i, SF_SOFTLO]) - tol, float(self.sf[i, SF_SOFTHI]) + tol

    def stands_inside(self, i: int, y: float) -> bool:
        """True when a reading y [m] of axis i stands inside its soft limits as the reading is
        judged: widened by the following error allowed at rest (``min_following_error_m``;
        module docstring). A commanded target is judged by :meth:`inside`."""
        lo, hi = self._reading_window(i)
        return bool(lo <= y <= hi)

    def _clear(self, i: int, y: float) -> None:
        self.fault[i] = 0
        self.bucket[i] = 0
        self.y_last[i] = y
        self.fe_peak[i] = 0.0
        self.i2t[i] = 0.0            # a reset is the operator's word that the coil has cooled

    def inside(self, i: int, x: float) -> bool:
        """True when a commanded position x [m] lies within axis i's soft limits."""
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
        rlo, rhi = self._reading_window(i)
        self.sf[i, SF_LO], self.sf[i, SF_HI] = min(rlo, y - m), max(rhi, y + m)
        return True, ""


class LimitsConfig(StrictModel):
    """Supervisor limits (LinuxCNC semantics). Lengths in m, velocities in m/s.

    following_error_m applies at max_velocity_m_per_s and scales with |ẋ_d| down to
    min_following_error_m; encoder_max_speed_m_per_s bounds the speed a change of the encoder
    reading may show (over the cycles since the last good reading): no physical motion is faster.
    i2t_* and oscillation_* (docs/protection.md): the I²t model of the amplifier's output and the
    oscillation-at-rest detector (:func:`sup_check_thermal`); i2t_continuous_V < i2t_peak_V.
    """

    soft_min_m: Position_m = -1.0
    soft_max_m: Position_m = 1.0
    following_error_m: quantity(1e-7, 1.0, "m") = 0.002
    min_following_error_m: quantity(1e-7, 1.0, "m") = 0.0005
    #: the in-position window: commanded motion has ended (``wait``, ``move --wait``) once its
    #: planned motion is done and |x_d − y| is within this on every axis in command mode
    in_position_m: quantity(1e-8, 0.01, "m") = 5e-6
    max_velocity_m_per_s: quantity(1e-6, 50.0, "m/s") = 3.0
    encoder_max_speed_m_per_s: quantity(1e-3, 1000.0, "m/s") = 10.0
    error_bucket_increment: Annotated[int, Field(ge=1)] = 10
    error_bucket_decrement: Annotated[int, Field(ge=1)] = 1
    error_bucket_limit: Annotated[int, Field(ge=1)] = 100
    #: I²t protection (:func:`sup_check_thermal`): the amplifier's continuous and peak output
    #: and how long the peak may be held from cold. Defaults: the ±10 V amplifier's full scale
    #: as peak for 1 s, continuous 4.4 V (peak/continuous 2.3: servo drives rate 2-3x)
    i2t_continuous_V: quantity(0.1, 100.0, "V") = 4.4
    i2t_peak_V: quantity(0.1, 100.0, "V") = 10.0
    i2t_peak_time_s: quantity(0.01, 60.0, "s") = 1.0
    #: oscillation at rest (:func:`sup_check_thermal`): window, RMS and frequency that trip
    oscillation_window_s: quantity(0.05, 10.0, "s") = 0.5
    oscillation_rms_V: quantity(0.01, 100.0, "V") = 2.0
    oscillation_min_hz: quantity(0.1, 10000.0, "Hz") = 5.0
