"""Step 1 of ``motorctl autotune``: the measured frequency response (multisine at the plant
input during a slow constant-velocity pass, indirect closed-loop estimate) and the
constant-velocity passes that the friction is fitted from."""

from __future__ import annotations

import contextlib
import copy
import math

import numpy as np
from scipy import signal, stats

from motorctl.app.build import build, shutdown, start
from motorctl.commission.fit import theta56_corners
from motorctl.commission.rule import AutotuneError, F_LO, F_SHAPE, HOLD_HZ, HOLD_R, HOLD_ZETA, DISP_SHARE, EXC_SHARE, F_BOOST, F_HI_SHARE, GUARD_SHARE, LINE_SPACING, PERIODS, PERIOD_S, REST_S, STROKE_MARGIN
from motorctl.commission.rule import (FRICTION_A_MAX, FRICTION_A_SHARE, FRICTION_CRUISE, FRICTION_SKIP_S,
                                      FRICTION_SPEEDS, FRICTION_V_SHARE)
from motorctl.config import LoadedConfig, config_from_dict
from motorctl.control.base import Controller, SIG_E
from motorctl.loop.servo import IDLE
from motorctl.loop.trajectory import Move


# ================================================================ excitation
def multisine(ts: float, theta1: float, u_lim: float, fe_min_m: float, realisations: int,
              repeats: int, seed: int = 0):
    """The excitation: ``realisations`` random-phase multisines of the same amplitude spectrum
    at the plant input, each repeated ``repeats`` periods (module docstring, step 1). New
    realisations turn the plant's nonlinear distortion (the force curve of eq. 3, friction)
    into noise that the averaging removes and the coherence shows, instead of a periodic error
    that looks coherent; the first period of each is its transient (not used).

    Args:
        ts: period [s]. theta1: catalogue θ̂1 = M/A1 [V s²/m] (sizes the displacement).
        u_lim: output limit [V]. fe_min_m: the smallest following-error limit [m].
        realisations, repeats: counts. seed: of the phases.
    Returns:
        (r (realisations·repeats·N,) [V], lines (L,) int: the excited DFT bins of a period of N samples).
    """
    n = int(round(PERIOD_S / ts))
    df = 1.0 / (n * ts)
    k, kk, k_hi = [], int(math.ceil(F_LO / df)), int(F_HI_SHARE / ts / df)
    while kk <= k_hi:                          # spacing max(1 bin, LINE_SPACING · f)
        k.append(kk)
        kk += max(1, int(LINE_SPACING * kk))
    k = np.asarray(k)
    f = k * df
    amp = np.minimum(1.0, (f / F_SHAPE) ** 2) * (1.0 + f / F_BOOST) ** 2
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(realisations):
        best = None
        for _ in range(8):                    # the lowest crest factor of 8 draws
            spec = np.zeros(n // 2 + 1, dtype=complex)
            spec[k] = amp * np.exp(1j * rng.uniform(0.0, 2.0 * math.pi, k.size)) * n / 2.0
            r = np.fft.irfft(spec, n)
            if best is None or np.max(np.abs(r)) < np.max(np.abs(best)):
                best = r
        out += [best] * repeats
    r = np.concatenate(out)
    disp_rms = math.sqrt(np.sum((amp / (theta1 * (2.0 * math.pi * f) ** 2)) ** 2) / 2.0)
    scale = min(EXC_SHARE * u_lim / np.max(np.abs(r)), DISP_SHARE * fe_min_m / disp_rms)
    return r * scale, k


class Excited(Controller):
    """A controller plus an excitation r added at its output (the plant input).

    ``r[j]`` is added at loop cycle k0 + j (k from the loop time t = k·Ts); the sum is clipped to
    ±u_lim. If |e| ≥ ``guard_m`` the excitation stops for good (:attr:`tripped`). Publishes
    the inner controller's signals. Allocation-free."""

    def __init__(self, inner: Controller, r: np.ndarray, k0: int, guard_m: float):
        self.inner = inner
        super().__init__(inner.ts, inner.u_lim, inner.n_theta)
        self.name = inner.name
        self.r = np.ascontiguousarray(r, dtype=float)
        self.k0 = int(k0)
        self.guard = float(guard_m)
        self.tripped = False

    # the inner controller's arrays, wherever they live (a law the loop lets go of takes its
    # state back into arrays of its own: Controller.detach)
    signals = property(lambda self: self.inner.signals, lambda self, _v: None)
    theta_hat = property(lambda self: self.inner.theta_hat, lambda self, _v: None)

    @classmethod
    def from_config(cls, section, ts):      # pragma: no cover - built by autotune only
        raise ValueError("Excited wraps a built controller")

    def reset(self, y0: float) -> None:
        self.inner.reset(y0)

    def update(self, y, x_d, xd_dot, xd_ddot, t=0.0):
        u = self.inner.update(y, x_d, xd_dot, xd_ddot, t)
        j = int(t / self.ts + 0.5) - self.k0
        if 0 <= j < self.r.shape[0] and not self.tripped:
            if abs(self.inner.signals[SIG_E]) >= self.guard:
                self.tripped = True
            else:
                u += self.r[j]
        lim = self.u_lim
        return lim if u > lim else (-lim if u < -lim else u)


def hold_gains(theta_hat0) -> dict:
    """The conservative holding PID+FF from the catalogue θ̂(0) (module docstring, step 1)."""
    t1 = float(theta_hat0[0])
    w = 2.0 * math.pi * HOLD_HZ
    p = t1 * w * w
    i = p * w / HOLD_R
    return {"P": p, "I": i, "D": 2.0 * HOLD_ZETA * w * t1, "FF0": 0.0, "FF1": float(theta_hat0[1]),
            "FF2": t1, "bias": -float(theta_hat0[3]), "deadband": 0.0, "maxerror": 0.0,
            "maxerror_i": 1.0 / i, "maxoutput": 0.0}


def _stroke(loaded: LoadedConfig, axis: str):
    """(x_a, x_b) [m] of a measurement's passes: from the lower soft limit to the upper,
    :data:`STROKE_MARGIN` of the stroke inside each.

    Raises:
        AutotuneError: the axis has no finite soft limits."""
    lim = loaded.axes[axis].limits
    lo, hi = lim.soft_min_m, lim.soft_max_m
    if not (math.isfinite(lo) and math.isfinite(hi) and hi > lo):
        raise AutotuneError(f"axes.{axis}.limits: autotune needs finite soft limits (the stroke)")
    return lo + STROKE_MARGIN * (hi - lo), hi - STROKE_MARGIN * (hi - lo)


def _pass_plan(loaded: LoadedConfig, axis: str, duration_s: float):
    """(x_a, x_b, v [m/s]) of the constant-velocity pass (:func:`_stroke`) at the speed that
    lasts ``duration_s``."""
    a, b = _stroke(loaded, axis)
    v = abs(b - a) / duration_s
    return a, b, min(v, 0.25 * loaded.axes[axis].limits.max_velocity_m_per_s)


def _read_idle(asm) -> float:
    """Idle cycles (0 V, amplifier off) until the axis's position is read without a fault, then
    that position [m]. A drive whose command watchdog bit while no loop ran between two runs
    reports one amplifier fault; it is reset here as an operator's ``fault-reset`` would (the
    supervisor refuses while the cause persists).

    Raises:
        AutotuneError: the fault persists (one line, the supervisor's reason).
    """
    for _ in range(3):
        asm.loop.run(1)
        if not asm.supervisor.fault[0]:
            return float(asm.driver.position_m[0])
        asm.loop.run(1)
        asm.loop.fault_reset(0)
    raise AutotuneError(f"axis {asm.names[0]} is in fault: {asm.supervisor.reason(0)}")


def _approach_speed(lim) -> float:
    """The speed of a move to a measurement's start [m/s]: 0.1 m/s, at most a quarter of the
    axis's max velocity."""
    return min(0.1, 0.25 * lim.max_velocity_m_per_s)


@contextlib.contextmanager
def _held(loaded2: LoadedConfig, axis: str, clock: str, capacity: int):
    """The axis built alone under the holding PID of ``loaded2`` (operated: it moves only on a
    command), started, read at idle: yields (assembly, y0 [m] where the axis stands); shut
    down (0 V, amplifier off, driver closed) on every exit path.

    Raises:
        AutotuneError: the axis is in fault or stands outside its soft limits.
    """
    lim = loaded2.axes[axis].limits
    asm = build(loaded2, [axis], "pid", clock=clock, capacity=capacity, operated=True)
    start(asm, "off" if clock == "virtual" else loaded2.cfg.loop.realtime.policy)
    try:
        y0 = _read_idle(asm)                     # where the axis stands
        if not lim.soft_min_m <= y0 <= lim.soft_max_m:
            raise AutotuneError(f"axis {axis} stands at {y0:.4f} m, outside its soft limits "
                                f"(motorctl jog it back first)")
        yield asm, y0
    finally:
        shutdown(asm)


def measure_frf(loaded: LoadedConfig, raw: dict, axis: str, clock: str = "virtual",
                progress=None, periods: int = PERIODS) -> dict:
    """Step 1 (module docstring) on the config's driver; ``periods`` measured periods (even:
    ``periods``/2 realisations of two periods, the first of each its transient).

    Returns:
        {"f_hz" (L,), "G" (L,) complex [m/V], "coherence" (L,), "coherence_u" (L,),
        "rest_psd": (f (M,), S_yy (M,) [m²/Hz]) of y at rest, "u_cov" (the analysed window's
        var(u) [V²], cov(u|u|, u) [V³], cov(u³, u) [V⁴]: :func:`motorctl.commission.fit.input_gain`), "excitation_rms_V",
        "excitation_peak_V", "e_max_m", "guard_m", "stroke_m": (min y, max y) during the run,
        "soft_limits_m", "fault" ('' when none), "tripped" (the excitation guard fired),
        "pass": (x_a, x_b, v)}.
    Raises:
        AutotuneError: no soft limits. OSError: the driver cannot reach its device.
    """
    sec = loaded.axes[axis].controller
    lim = loaded.axes[axis].limits
    ts = loaded.period_s
    tb = loaded.timebase
    raw = copy.deepcopy(raw)
    raw["axes"][axis]["controller"]["pid"] = hold_gains(sec.theta_hat0)
    raw["axes"][axis]["controller"]["type"] = "pid"
    fe_min = min(lim.min_following_error_m, lim.following_error_m)
    r, lines = multisine(ts, float(sec.theta_hat0[0]), sec.u_lim, fe_min, periods // 2 + 1, 2)
    n_per = int(round(PERIOD_S / ts))
    r[:n_per] *= np.linspace(0.0, 1.0, n_per, endpoint=False)     # amplitude ramp
    r1 = r[n_per:]
    exc_s = r.size * ts
    x_a, x_b, v = _pass_plan(loaded, axis, exc_s + 1.0)
    a_pass = 2.0
    raw["axes"][axis]["trajectory"] = {"points": [x_a, x_b], "move_times_s": [REST_S, 86400.0],
                                       "period_s": 0.0, "v_max": v, "a_max": a_pass,
                                       "j_max": 100.0 * a_pass}
    loaded2 = config_from_dict(raw, str(loaded.path))
    prog = loaded2.axes[axis].trajectory.program()
    pass_move = prog.moves[0]
    # the excitation starts when the pass cruises (sampled on the move's own profile)
    tt = np.arange(0.0, pass_move.duration, ts)
    vd = np.array([pass_move.sample(REST_S + x)[1] for x in tt])
    cruise = np.flatnonzero(np.abs(vd) >= 0.999 * v)
    if cruise.size == 0 or (cruise[-1] - cruise[0]) < r.size + 100:
        raise AutotuneError(f"axes.{axis}.limits: the stroke is too short for a "
                            f"{exc_s:.0f} s pass at {v:.3g} m/s")
    v_app = _approach_speed(lim)
    stroke = lim.soft_max_m - lim.soft_min_m
    capacity = tb.cycles(stroke / v_app + 1.0 + REST_S + pass_move.duration) + 8
    with _held(loaded2, axis, clock, capacity) as (asm, y0):
        approach = Move(y0, x_a, v_app, a_pass, 100.0 * a_pass)
        k_prog = asm.loop.k + tb.cycles(approach.duration) + 1
        k_exc = k_prog + tb.cycles(REST_S) + int(cruise[0]) + 50
        n_total = k_exc + r.size + 50 - asm.loop.k
        exc = Excited(asm.controller(0, "pid"), r, k_exc, GUARD_SHARE * fe_min)
        asm.loop.start_axis(0, approach, exc)
        if progress:
            progress(f"measure {axis}: rest {REST_S:g} s at {x_a:.3f} m, pass to {x_b:.3f} m at "
                     f"{v * 1e3:.1f} mm/s with a multisine of {np.sqrt(np.mean(r1 ** 2)):.2f} V RMS "
                     f"(peak {np.max(np.abs(r1)):.2f} V), {periods} periods of {PERIOD_S:g} s")
        asm.loop.run(min(n_total, capacity - asm.loop.k))
    rows, lay = asm.loop.rows(), asm.loop.layout
    y = rows[:, lay.index(f"{axis}.y")]
    e = rows[:, lay.index(f"{axis}.e")]
    u = rows[:, lay.index(f"{axis}.u")]
    fault = asm.supervisor.reason(0)
    rr = np.zeros(rows.shape[0])
    m = min(r.size, rows.shape[0] - k_exc)
    if m > 0:
        rr[k_exc:k_exc + m] = r[:m]
    s0 = k_exc + 2 * n_per      # after the ramp and its settling: periods/2 realisations of 2 periods
    s1 = s0 + periods * n_per
    out = {"fault": fault, "tripped": exc.tripped, "pass": (x_a, x_b, v),
           "excitation_rms_V": float(np.sqrt(np.mean(r1 ** 2))),
           "excitation_peak_V": float(np.max(np.abs(r1))),
           "e_max_m": float(np.nanmax(np.abs(e))), "guard_m": GUARD_SHARE * fe_min,
           "stroke_m": (float(np.min(y)), float(np.max(y))),
           "soft_limits_m": (lim.soft_min_m, lim.soft_max_m)}
    # rest spectrum of y: the carriage held at x_a before the pass
    r0 = k_prog + tb.cycles(0.2)
    r1_ = k_prog + tb.cycles(REST_S) - 10
    out["rest_psd"] = signal.welch(y[r0:r1_], fs=1.0 / ts, nperseg=min(1024, r1_ - r0),
                                   detrend="linear")
    if fault or exc.tripped or s1 > rows.shape[0]:
        return out
    kw = {"fs": 1.0 / ts, "window": "boxcar", "nperseg": n_per, "noverlap": 0, "detrend": "linear"}
    keep = np.concatenate([np.arange(s0 + (2 * j + 1) * n_per, s0 + (2 * j + 2) * n_per)
                           for j in range(periods // 2)])
    rs, es, us = rr[keep], e[keep], u[keep]
    fr, s_re = signal.csd(rs, es, **kw)
    _, s_ru = signal.csd(rs, us, **kw)
    _, c_re = signal.coherence(rs, es, **kw)
    _, c_ru = signal.coherence(rs, us, **kw)
    G = s_re / s_ru
    # the covariances the input nonlinearity's best linear gain needs (fit.input_gain)
    ud = us - np.mean(us)
    out.update(f_hz=fr[lines], G=G[lines], coherence=c_re[lines],
               coherence_u=c_ru[lines],
               u_cov={"var": float(np.mean(ud * ud)), "abs2": float(np.mean(ud * (us * np.abs(us)))),
                      "cube": float(np.mean(ud * us ** 3))})
    return out


# ================================================================ friction
def friction_plan(loaded: LoadedConfig, axis: str):
    """The constant-velocity passes of :func:`measure_friction`: (x_a, x_b [m], speeds [m/s]
    (:data:`FRICTION_SPEEDS` of the top speed), a [m/s²]). The top speed is the least of
    :data:`FRICTION_V_SHARE` of the axis's max velocity, the program's v_max and the speed that
    keeps :data:`FRICTION_CRUISE` of the pass at constant velocity; the passes run between
    x_a and x_b, inside the soft limits (:func:`_stroke`).

    Raises:
        AutotuneError: no finite soft limits."""
    x_a, x_b = _stroke(loaded, axis)
    lim, tc = loaded.axes[axis].limits, loaded.axes[axis].trajectory
    a = min(FRICTION_A_SHARE * tc.a_max, FRICTION_A_MAX)
    v_top = min(FRICTION_V_SHARE * lim.max_velocity_m_per_s, tc.v_max,
                math.sqrt((1.0 - FRICTION_CRUISE) * (x_b - x_a) * a))
    return x_a, x_b, [s * v_top for s in FRICTION_SPEEDS], a


def measure_friction(loaded: LoadedConfig, raw: dict, axis: str, theta1: float, clock: str = "virtual",
                     progress=None) -> dict:
    """The friction of the axis from constant-velocity passes: steady-state force against speed
    (paper eq. 4 at ẍ ≈ 0: u + θ5 u|u| + θ6 u³ = θ1 ẍ + θ2 ẋ + θ3 S_f(ẋ) − θ4), the standard
    test of a servo axis's friction (Armstrong-Hélouvry, Dupont, Canudas de Wit, "A survey of
    models, analysis tools and compensation methods for the control of machines with
    friction", Automatica 30(7), 1994, §3.1).

    The axis, held by the conservative PID+FF of :func:`hold_gains` on the fitted ``theta1``,
    jogs to x_a, then makes one pass up to x_b and one back at each speed of
    :func:`friction_plan` (jerk-limited moves, all between x_a and x_b: inside the soft limits,
    the supervisor's following-error and limit checks armed). On each pass's cruise, from
    :data:`FRICTION_SKIP_S` after it starts to 50 ms before it ends, the mean of u (θ5, θ6 of the
    section's θ̂(0): the force curve of eq. 3) and the velocity and acceleration of a parabola
    fitted to y give one row of :func:`motorctl.model.idim_regressor`; θ1 ẍ is taken off with
    the fitted θ1 and (θ2, θ3, θ4) fitted to the rows by linear least squares, with the
    standard deviation of each from the residual variance (σ² (AᵀA)⁻¹).

    The passes cannot tell the friction's shape at their speeds (the paper's S_f, eq. 4, is
    0.993 at 0.1 m/s, a Coulomb friction's sign is 1) nor θ5, θ6 (one force level per speed): the
    95 % interval "ci95" spans the fits with S_f and with the sign, each at the corners of the
    bounds' box of θ5, θ6 (Ω_θ, eq. 5), each widened by its Student-t quantile (P − 3 degrees of
    freedom) times its σ.

    Args:
        theta1: fitted M/A1 [V s²/m]. clock: 'virtual' | 'wall'.
    Returns:
        {"theta2" [V s/m], "theta3" [V], "theta4" [V], "sigma": {same keys}, "ci95": {same keys:
        [lo, hi]: the 95 % interval over what the passes cannot tell (below)}, "passes": [(v [m/s],
        u [V]) per pass], "duration_s" (the passes' time on the machine), "fault" ('' when
        none), "stroke_m": (min y, max y)}; no "theta2" when the passes faulted.
    Raises:
        AutotuneError: no soft limits, a pass too short for a window, the axis in fault or
        outside its soft limits. OSError: the driver cannot reach its device.
    """
    from motorctl.model import idim_regressor
    sec = loaded.axes[axis].controller
    lim = loaded.axes[axis].limits
    tb, ts = loaded.timebase, loaded.period_s
    th = np.asarray(sec.theta_hat0, dtype=float).copy()
    th[0] = theta1
    raw = copy.deepcopy(raw)
    raw["axes"][axis]["controller"]["pid"] = hold_gains(th)
    raw["axes"][axis]["controller"]["type"] = "pid"
    loaded2 = config_from_dict(raw, str(loaded.path))
    x_a, x_b, speeds, a = friction_plan(loaded, axis)
    moves = [Move(p, q, v, a, 100.0 * a) for v in speeds for p, q in ((x_a, x_b), (x_b, x_a))]
    settle = tb.cycles(loaded.cfg.daemon.stop_settle_s) + tb.cycles(0.05)
    v_app = _approach_speed(lim)
    n_app = tb.cycles((lim.soft_max_m - lim.soft_min_m) / v_app + 1.0) + settle
    capacity = n_app + sum(tb.cycles(m.duration) + settle for m in moves) + 16
    windows = []                   # (first row, last row) of each pass's cruise
    for m in moves:
        tt = np.arange(0.0, m.duration, ts)
        vd = np.abs([m.sample(x)[1] for x in tt])
        cruise = np.flatnonzero(vd >= 0.999 * vd.max())
        j0, j1 = cruise[0] + tb.cycles(FRICTION_SKIP_S), cruise[-1] - tb.cycles(0.05)
        if j1 - j0 < tb.cycles(0.1):
            raise AutotuneError(f"axes.{axis}.limits: the stroke is too short for a friction pass "
                                f"at {m.v_max:.3g} m/s")
        windows.append((int(j0), int(j1)))
    if progress:
        progress(f"friction {axis}: passes between {x_a:.3f} and {x_b:.3f} m at "
                 + ", ".join(f"{v * 1e3:.0f}" for v in speeds) + f" mm/s, both ways ({a:g} m/s^2)")
    starts, fault = [], ""
    with _held(loaded2, axis, clock, capacity) as (asm, y0):
        for m in [Move(y0, x_a, v_app, a, 100.0 * a)] + moves:
            if asm.supervisor.fault[0]:
                break
            starts.append(asm.loop.k)
            asm.loop.jog_axis(0, m)
            asm.loop.run(tb.cycles(m.duration) + settle)
            while asm.loop.mode[0] != IDLE and not asm.supervisor.fault[0]:
                asm.loop.run(1)                  # the hold after the move ends in 0 V, amplifier off
        fault = asm.supervisor.reason(0) if asm.supervisor.fault[0] else ""
        k_end = asm.loop.k
    rows, lay = asm.loop.rows(), asm.loop.layout
    y = rows[:, lay.index(f"{axis}.y")]
    u = rows[:, lay.index(f"{axis}.u")]
    out = {"fault": fault, "duration_s": (k_end - starts[0]) * ts if starts else 0.0,
           "stroke_m": (float(np.min(y)), float(np.max(y))), "passes": []}
    if fault or len(starts) < len(moves) + 1:
        return out
    phi, b = [], []
    for k0, (j0, j1) in zip(starts[1:], windows):
        sl = slice(k0 + j0, k0 + j1)
        t = (np.arange(j1 - j0) - 0.5 * (j1 - j0)) * ts
        c2, c1, _ = np.polyfit(t, y[sl], 2)            # y ≈ c0 + c1 t + c2 t², t from the centre
        um = float(np.mean(u[sl]))
        row = idim_regressor(np.array([2.0 * c2]), np.array([c1]), np.array([um]), 6)[0]
        phi.append(row[1:4])
        b.append(um - theta1 * row[0] - row[4:6] @ th[4:6])
        out["passes"].append((float(c1), um))
    A, b = np.asarray(phi), np.asarray(b)
    keys = ("theta2", "theta3", "theta4")
    x, sd, dof = _friction_fit(A, b)
    out.update({k: float(v) for k, v in zip(keys, x)})
    out["sigma"] = {k: float(v) for k, v in zip(keys, sd)}
    # what the passes cannot tell: the friction's shape (the model's S_f or a sign at the
    # passes' speeds) and θ5, θ6 anywhere in the bounds' box (Ω_θ, eq. 5); the 95 % interval
    # holds each variant's own Student-t interval
    q = float(stats.t.ppf(0.975, dof))
    uu = np.asarray([p_[1] for p_ in out["passes"]])             # each pass's mean u [V]
    nl = np.column_stack([-uu * np.abs(uu), -uu ** 3])          # eq. 4's θ5, θ6 columns
    th56_0 = th[4:6]                                             # as b was taken
    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
    for th56 in np.asarray(theta56_corners(sec.theta_min, sec.theta_max) or [th56_0], dtype=float):
        for shape in (A, np.column_stack([A[:, 0], np.sign(A[:, 1]), A[:, 2]])):
            xv, sv, _ = _friction_fit(shape, b + nl @ (th56_0 - th56))
            lo, hi = np.minimum(lo, xv - q * sv), np.maximum(hi, xv + q * sv)
    out["ci95"] = {k: [float(a_), float(b_)] for k, a_, b_ in zip(keys, lo, hi)}
    return out


def _friction_fit(A: np.ndarray, b: np.ndarray):
    """Least squares of the passes' rows A (P, 3) [θ2, θ3, θ4 columns] on b (P,) [V]: (θ (3,),
    σ (3,) from the residual variance σ² (AᵀA)⁻¹, degrees of freedom P − 3 (at least 1))."""
    x = np.linalg.lstsq(A, b, rcond=None)[0]
    dof = max(A.shape[0] - A.shape[1], 1)
    s2 = float(np.sum((A @ x - b) ** 2)) / dof
    return x, np.sqrt(np.maximum(np.diag(np.linalg.pinv(A.T @ A)) * s2, 0.0)), dof
