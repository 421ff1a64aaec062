"""The servo cycle of every axis in one compiled call (numba).

Per cycle the loop (:class:`motorctl.loop.servo.ServoLoop`) reads the driver, makes one call
to :func:`servo_cycle` and writes the driver. For every axis the call runs:

    supervisor input checks (NaN, encoder speed, soft limits, driver-error bucket, amplifier)
    → the sequencer: desired(k) of the axis's mode (module docstring of servo.py) and its
      transitions (approach → program, jog → hold, hold → idle, a stop request → hold)
    → the overrun policy's hold-and-ramp, or the law: a compiled law (LAW_DCDIARC,
      LAW_DCDIARC_COMP with its compensation and the desired trajectory at its preview, LAW_PID:
      :mod:`motorctl.control.kernels`) on the axis's rows, reset when the axis starts
    → the bumpless-switch blend, the following-error, NaN, I²t and oscillation checks of the
      output
    → a fault or disable: 0 V, amplifier off (and IDLE when operated)
    → the axis's part of the cycle record

An axis whose law has no compiled step (LAW_PY: a law from another package) stops before its
law (``phase`` CYCLE_BEFORE, the axis marked pending); the loop runs
:meth:`Controller.update` from Python and a second call (CYCLE_AFTER) finishes the pending
axes. Without such an axis the loop makes the one call (CYCLE_ALL).

State lives in preallocated arrays laid out by name, passed as one :class:`CycleState` (a
bundle, :func:`motorctl.jit.bundle`): the driver's ``pos``/``rerr``/``werr``/``ampf`` and the
outputs ``uo``/``en``; one row per axis of ``ax`` (int64, ``A_*``), ``axf`` (float64, ``X_*``),
the trajectory tables ``prog`` and ``move`` (:mod:`motorctl.loop.trajectory`), the supervisor's
``si``/``sf`` (:mod:`motorctl.loop.safety`), the law rows ``sig``/``cf``/``ci``/``cl``
(:meth:`Controller.attach`); ``buf`` is the record ring (:mod:`motorctl.loop.records`), ``offs``
the record's offsets and ``lp`` the loop's numbers. Nothing here allocates, blocks or logs.
"""

from __future__ import annotations

import numpy as np
from numba.experimental.structref import StructRefProxy

from motorctl.control.gtcf import gtcf_partner, gtcf_step
from motorctl.control.kernels import LAW_GTCF, LAW_PY, law_preview, law_reset, law_step
from motorctl.jit import BundleType, borrow, bundle, copy_into, define_bundle, njit
from motorctl.control.signals import N_SIGNALS, SIG_E
from motorctl.loop.safety import FAULT_OVERRUN, SI_FAULT, sup_check_input, sup_check_output, sup_rest, sup_trip
from motorctl.loop.stream import stream_outputs, stream_step
from motorctl.loop.trajectory import TABLE_HEAD, sample_table

#: the sequencer's modes (servo.py's module docstring)
IDLE, APPROACH, PROGRAM, HOLD, JOG, STREAM = 0, 1, 2, 3, 4, 5
#: what a call does: every axis through; up to the laws run from Python; those axes' rest
CYCLE_ALL, CYCLE_BEFORE, CYCLE_AFTER = 0, 1, 2

# per-axis int state (ax)
(A_MODE, A_KST, A_SETTLE, A_STOPREQ, A_ENABLED, A_RUNNING, A_OVR, A_BLEND, A_LAW, A_PEND,
 A_OK) = range(11)
N_A = 11
#: A_PEND: the law of this axis runs from Python now (PEND_RESET: reset it first)
PEND_NONE, PEND_UPDATE, PEND_RESET = 0, 1, 2
# per-axis float state (axf): held position, blend offset (NaN: not yet taken), last output;
# the sample handed to a law run from Python (y, x_d, ẋ_d, ẍ_d) and its output; in STREAM the
# setpoint taken from the stream (x, ẋ, ẍ) and the brake's a_max, j_max (motorctl.loop.stream)
X_HOLD, X_BLOFF, X_ULAST, X_Y, X_XD, X_VD, X_AD, X_U, X_SX, X_SV, X_SA, X_AMAX, X_JMAX = range(13)
N_X = 13
# the loop's numbers (lp)
LP_TS, LP_SETTLE, LP_OVR_RAMP, LP_BLEND_N, LP_DISABLE_ON_FAULT = range(5)
N_LP = 5
# record offsets (offs): per-axis fields, then the base of each axis, then that of the outputs
(O_Y, O_XD, O_VD, O_AD, O_U, O_EN, O_FB, O_SIG, O_MODE) = range(9)
O_AXIS = 9

#: the fields of :class:`CycleState`, in constructor order (module docstring)
CYCLE_FIELDS = ("pos", "rerr", "werr", "ampf", "uo", "en", "ax", "axf", "prog", "move", "si", "sf",
                "sig", "cf", "ci", "cl", "buf", "offs", "lp", "sp", "spc")


class CycleStateType(BundleType):
    """numba type of :class:`CycleState`."""


class CycleState(StructRefProxy):
    """The arrays of the servo cycle by name (:data:`CYCLE_FIELDS`, module docstring), passed
    to :func:`servo_cycle` as one argument; built by :func:`cycle_state`."""


define_bundle(CycleStateType, CycleState, CYCLE_FIELDS)


@njit
def _make_cycle_state(pos, rerr, werr, ampf, uo, en, ax, axf, prog, move, si, sf, sig, cf, ci, cl, buf, offs,
                      lp, sp, spc):
    return CycleState(pos, rerr, werr, ampf, uo, en, ax, axf, prog, move, si, sf, sig, cf, ci, cl, buf, offs, lp,
                      sp, spc)


def cycle_state(*arrays) -> CycleState:
    """The :class:`CycleState` of ``arrays``, one per name of :data:`CYCLE_FIELDS` in that order
    (the arrays themselves, not copies).

    Raises:
        ValueError: not one array per field.
    """
    if len(arrays) != len(CYCLE_FIELDS):
        raise ValueError(f"cycle_state takes {len(CYCLE_FIELDS)} arrays ({', '.join(CYCLE_FIELDS)}), "
                         f"got {len(arrays)}")
    return bundle(_make_cycle_state, CYCLE_FIELDS, arrays)


@njit
def _finish(i, ok, u, k, y, xd, vd, ad, ax, axf, si, sf, sig, uo, en, row, offs, lp):
    """After the law: a fault or disable gives 0 V with the amplifier off (IDLE when operated);
    the output, its enable and the axis's part of the record row."""
    if not ok:
        ax[i, A_RUNNING] = 0
        ax[i, A_OVR] = 0
        u = 0.0
        sup_rest(si, sf, i)                    # 0 V: the I²t model cools
        if lp[LP_DISABLE_ON_FAULT] != 0.0 and si[i, SI_FAULT] != 0 and ax[i, A_MODE] != IDLE:
            ax[i, A_MODE] = IDLE
            ax[i, A_ENABLED] = 0
            ax[i, A_STOPREQ] = 0
    uo[i] = u
    axf[i, X_ULAST] = u
    en[i] = ok
    b = offs[O_AXIS + i]
    row[b + offs[O_Y]] = y
    row[b + offs[O_XD]] = xd
    row[b + offs[O_VD]] = vd
    row[b + offs[O_AD]] = ad
    row[b + offs[O_U]] = u
    bs = b + offs[O_SIG]
    for j in range(N_SIGNALS):
        row[bs + j] = sig[i, j]
    row[b + offs[O_EN]] = 1.0 if ok else 0.0
    row[b + offs[O_FB]] = si[i, SI_FAULT]


@njit
def _output(i, u, vd, ax, axf, si, sf, sig, lp):
    """The law's output u [V] through the bumpless-switch blend and the output checks."""
    nb = ax[i, A_BLEND]
    if nb > 0:
        # bumpless switch: the step between the outgoing controller's last output and the
        # incoming one's first fades out linearly
        off = axf[i, X_BLOFF]
        if off != off:
            off = axf[i, X_ULAST] - u
            axf[i, X_BLOFF] = off
        u += off * nb / lp[LP_BLEND_N]
        ax[i, A_BLEND] = nb - 1
    return u, sup_check_output(si, sf, i, sig[i, SIG_E], vd, u)


@njit
def desired(i, k, ahead, ax, axf, prog, move, ts):
    """(x_d [m], ẋ_d [m/s], ẍ_d [m/s²]) of axis i at cycle k plus ``ahead`` [s] (0: the sample;
    a law's preview_s: its preview), by the axis's mode: its program, its approach or jog
    move, the held position; NaN in IDLE (the caller takes the measured position)."""
    m = ax[i, A_MODE]
    if m == PROGRAM:
        return sample_table(borrow(prog[i]), (k - ax[i, A_KST]) * ts + ahead)
    if m == APPROACH or m == JOG:
        mv = borrow(move[i])
        return sample_table(mv, mv[TABLE_HEAD + 2] + (k - ax[i, A_KST]) * ts + ahead)
    if m == HOLD:
        return axf[i, X_HOLD], 0.0, 0.0
    if m == STREAM:                            # the stream has no look-ahead: its sample
        return axf[i, X_SX], axf[i, X_SV], axf[i, X_SA]
    return np.nan, np.nan, np.nan


# (cached with the laws' steps compiled in: motorctl.control.kernels says when to renew the cache)
@njit
def servo_cycle(phase, k, st):
    """One servo cycle k of every axis (module docstring) on the :class:`CycleState` ``st``;
    ``phase``: CYCLE_ALL, CYCLE_BEFORE or CYCLE_AFTER. Reads st.pos [m] and the driver's flags
    (n,), writes st.uo [V] and st.en (n,) and the record row k % capacity of st.buf. Returns the
    number of axes left pending (laws to run from Python)."""
    # borrowed views (motorctl.jit.borrow): the bundle holds the arrays through the call
    pos, rerr, werr, ampf = borrow(st.pos), borrow(st.rerr), borrow(st.werr), borrow(st.ampf)
    uo, en, ax, axf = borrow(st.uo), borrow(st.en), borrow(st.ax), borrow(st.axf)
    prog, move, si, sf = borrow(st.prog), borrow(st.move), borrow(st.si), borrow(st.sf)
    sig, cf, ci, cl = borrow(st.sig), borrow(st.cf), borrow(st.ci), borrow(st.cl)
    buf, offs, lp = borrow(st.buf), borrow(st.offs), borrow(st.lp)
    ts = lp[LP_TS]
    n = pos.shape[0]
    row = borrow(buf[k % buf.shape[0]])
    pending = 0
    if phase != CYCLE_AFTER:                   # the setpoint stream: one row for every STREAM axis
        sp = borrow(st.sp)
        stream_step(sp, borrow(st.spc), ax, axf, A_MODE, STREAM, A_STOPREQ, X_SX, X_AMAX, ts)
        stream_outputs(sp, n, row, offs[O_AXIS + n])   # the outputs applied this cycle, recorded
    for i in range(n):
        if phase == CYCLE_AFTER:
            if ax[i, A_PEND] == PEND_NONE:
                continue
            ax[i, A_PEND] = PEND_NONE
            u, ok = _output(i, axf[i, X_U], axf[i, X_VD], ax, axf, si, sf, sig, lp)
            _finish(i, ok, u, k, axf[i, X_Y], axf[i, X_XD], axf[i, X_VD], axf[i, X_AD], ax, axf, si, sf, sig,
                    uo, en, row, offs, lp)
            continue
        y = pos[i]
        # a write error last cycle counts like a read error this cycle
        ok = sup_check_input(si, sf, i, y, rerr[i] or werr[i], ampf[i]) and ax[i, A_ENABLED] != 0
        m = ax[i, A_MODE]
        xd, vd, ad = desired(i, k, 0.0, ax, axf, prog, move, ts)
        row[offs[O_AXIS + i] + offs[O_MODE]] = m     # the mode x_d of this row comes from
        if m == APPROACH or m == JOG:
            if (k - ax[i, A_KST]) * ts >= move[i, TABLE_HEAD + 3]:
                if m == APPROACH:
                    ax[i, A_MODE] = PROGRAM
                    ax[i, A_KST] = k + 1
                else:                                  # arrived: hold, then 0 V, amplifier off
                    ax[i, A_MODE] = HOLD
                    axf[i, X_HOLD] = xd
                    ax[i, A_SETTLE] = int(lp[LP_SETTLE])
        elif m == HOLD:
            s = ax[i, A_SETTLE] - 1
            ax[i, A_SETTLE] = s
            if s <= 0:
                ax[i, A_MODE] = IDLE
                ax[i, A_ENABLED] = 0
                ax[i, A_STOPREQ] = 0
                ok = False
        elif m == IDLE:
            xd = y
            vd = 0.0
            ad = 0.0
            ok = False
        if ax[i, A_STOPREQ] != 0 and (m == PROGRAM or m == APPROACH or m == STREAM) and vd == 0.0 and ad == 0.0:
            ax[i, A_MODE] = HOLD
            axf[i, X_HOLD] = xd
            ax[i, A_SETTLE] = int(lp[LP_SETTLE])
        u = 0.0
        if ok:
            n_o = ax[i, A_OVR]
            if n_o > 0:
                # overrun policy 'ramp': hold the last output, ramp it to 0 V, latch
                n_o -= 1
                ax[i, A_OVR] = n_o
                u = axf[i, X_ULAST]
                if n_o < lp[LP_OVR_RAMP]:
                    u = u * n_o / (n_o + 1.0)
                if n_o == 0:
                    sup_trip(si, sf, i, FAULT_OVERRUN, 0.0, 0.0)
                    ok = False
            else:
                law = ax[i, A_LAW]
                if law == LAW_PY:
                    ax[i, A_PEND] = PEND_UPDATE if ax[i, A_RUNNING] != 0 else PEND_RESET
                    ax[i, A_RUNNING] = 1
                    axf[i, X_Y] = y
                    axf[i, X_XD] = xd
                    axf[i, X_VD] = vd
                    axf[i, X_AD] = ad
                    pending += 1
                    continue
                if ax[i, A_RUNNING] == 0:
                    law_reset(law, y, borrow(cf[i]), borrow(cl[i]))
                    ax[i, A_RUNNING] = 1
                tau = law_preview(law, borrow(cf[i]), borrow(cl[i]))
                if tau > 0.0:                          # the law's preview: from the mode it now has
                    xf, vf, af = desired(i, k, tau, ax, axf, prog, move, ts)
                else:
                    xf, vf, af = xd, vd, ad
                if law == LAW_GTCF:            # a pair: the partner's measurement and desired sample too
                    j = gtcf_partner(borrow(cf[i]), borrow(cl[i]))
                    xj, vj, _aj = desired(j, k, 0.0, ax, axf, prog, move, ts)
                    u = gtcf_step(y, xd, vd, ad, xf, vf, af, k * ts, pos[j], xj, vj,
                                  ax[j, A_LAW] == law and ax[j, A_RUNNING] != 0, borrow(sig[i]), borrow(cf[i]),
                                  borrow(ci[i]), borrow(cl[i]), borrow(cf[j]), borrow(cl[j]))
                else:
                    u = law_step(law, y, xd, vd, ad, xf, vf, af, k * ts, borrow(sig[i]), borrow(cf[i]),
                                 borrow(ci[i]), borrow(cl[i]))
                u, ok = _output(i, u, vd, ax, axf, si, sf, sig, lp)
        _finish(i, ok, u, k, y, xd, vd, ad, ax, axf, si, sf, sig, uo, en, row, offs, lp)
    return pending


@njit
def refresh(k, st, scratch):
    """``scratch`` (a :class:`CycleState` of copies, its record ring one row:
    ``ServoLoop._cycle_state(copies=True)``) set to ``st``: every array but the record ring.
    The rehearsal's first step: the loop then runs its own compiled cycle on ``scratch``
    (:func:`rehearse`); reading ``st`` here brings the real state into the CPU's caches, and
    the record row cycle k will write (one read per 64-byte line of it, into the rehearsal's
    own row, which its cycle then overwrites)."""
    copy_into(scratch.pos, st.pos)
    copy_into(scratch.rerr, st.rerr)
    copy_into(scratch.werr, st.werr)
    copy_into(scratch.ampf, st.ampf)
    copy_into(scratch.uo, st.uo)
    copy_into(scratch.en, st.en)
    copy_into(scratch.ax, st.ax)
    copy_into(scratch.axf, st.axf)
    copy_into(scratch.prog, st.prog)
    copy_into(scratch.move, st.move)
    copy_into(scratch.si, st.si)
    copy_into(scratch.sf, st.sf)
    copy_into(scratch.sig, st.sig)
    copy_into(scratch.cf, st.cf)
    copy_into(scratch.ci, st.ci)
    copy_into(scratch.cl, st.cl)
    copy_into(scratch.offs, st.offs)
    copy_into(scratch.lp, st.lp)
    copy_into(scratch.spc, st.spc)
    row = st.buf[k % st.buf.shape[0]]
    for j in range(0, row.shape[0], 8):
        scratch.buf[0, j] = row[j]


def rehearse(cycle, refresh_, phase, k, st, scratch) -> None:
    """Cycle k run ahead on ``scratch``, refreshed from ``st`` first (:func:`refresh`), by the
    loop's own compiled entry ``cycle`` (``refresh_``: :func:`refresh`'s). Run while the loop
    waits out its deadline, it brings what the real cycle will touch into the CPU's caches
    (after a sleep they are cold: other work ran on the core): the state it reads, and its
    machine code itself, since it is the very entry the real cycle calls (a compiled caller of
    ``servo_cycle`` would run a copy of its code of its own). With the same driver reading it
    computes what the real cycle will; nothing of ``st`` is written. ``phase``: CYCLE_ALL, or
    CYCLE_BEFORE when laws run from Python."""
    refresh_(k, st, scratch)
    cycle(phase, k, scratch)


def new_state(n: int) -> tuple[np.ndarray, np.ndarray]:
    """(ax, axf) for n axes: every axis in PROGRAM and requested, no blend offset taken."""
    ax = np.zeros((n, N_A), dtype=np.int64)
    ax[:, A_MODE] = PROGRAM
    ax[:, A_ENABLED] = 1
    axf = np.zeros((n, N_X))
    axf[:, X_BLOFF] = np.nan
    return ax, axf
