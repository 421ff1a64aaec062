"""``motorctl autotune``: measure an axis's frequency response through its driver, fit a physical
model, choose every controller's gains by one rule, verify them on the machine, write them.

Steps (any driver; the simulated one by default):

1. **measure** (:func:`measure_frf`): the axis is held by a conservative PID+FF (catalogue θ̂1(0),
   ω_n = 2π·20 Hz, ζ = 0.7, integral corner ω_n/5), rests at one end of its stroke (the rest
   noise of the encoder is recorded there), then makes one slow constant-velocity pass across
   the stroke (so Coulomb friction is a constant force and stiction never grips) while a
   periodic multisine r is added at the plant input: amplitude ramped up over its first period,
   every 1 Hz line from 10 Hz to 1 kHz and every 4th line up to 0.48 fs, line amplitudes
   ∝ f² below 60 Hz (the displacement stays a small share of the following-error limit) and
   scaled so that |r| ≤ 80 % of u_lim (32 periods: the heavy Y axis's response above 700 Hz, where
   the current loop shows, is a few nm per line). The pass stays 10 % of the stroke inside the soft limits,
   the supervisor's following-error limit is armed, and the excitation switches itself off
   (latched) if |e| reaches half the smallest following-error limit.
   The plant FRF is the indirect closed-loop estimate P = S_re/S_ru (scipy.signal.csd, one
   multisine period per segment, boxcar window, linear detrend; e = y − x_d), with the
   coherence r → e; the feedback does not bias it because r is independent of the noise.
2. **fit** (:func:`fit_plant`): θ1 = M/A1, θ2 = B/A1, one structural mode (frequency, damping,
   load share), the current-loop bandwidth and a transport delay, by scipy.optimize.least_squares
   on log(P_model/P_measured) weighted by the coherence, with the ZOH and its aliases
   (:func:`motorctl.app.loopshape.plant_model_frf`); a rigid model is kept when the mode does not
   lower the cost by 30 %.
3. **choose** (:func:`choose_gains`), ONE rule for every law, on the *measured* FRF:
   among each law's family (PID: P = θ1 ω², D = 2ζωθ1, I = P ω/r; C1/C2: k_s = 2ζωθ1,
   k1 = ω/(2ζ), γ_d of the config; ω on a log grid of 49 points from 30 to 3000 rad/s,
   ζ ∈ {0.3, 0.4, 0.5, 0.7, 1}, r ∈ {3, 5, 7, 10}; θ1 the fitted one), the *admissible* gains
   are those with gain margin ≥ 6 dB, phase margin ≥ 10° and peak sensitivity ≤ 16 dB at 100,
   75 and 50 % of their loop gain (the verification ladder; a lighter loop gain is also what
   a heavier load does; the back-off steps 35 and 25 % are tried only where they hold too).
   The floor is wide on purpose: the least L2[e] the machine accepts (no fault, saturation,
   rest noise; ``benchmarks/compare_laws.py --search``) lies at 10-20° of phase margin and
   11-16 dB of peak sensitivity on the default plant, and step 4 runs every candidate on the
   machine, which stops on oscillation. The first candidate is the admissible one of highest
   loop gain |L| at :data:`F_TRACK_HZ` = 2 Hz (the least sensitivity where the tracking error
   of a point-to-point program lives). The u noise at rest is predicted (the measured rest
   spectrum of y through |C|) and reported, but judged on the machine in step 4 (with
   stiction and quantisation the prediction is only a bound). C1 and C2 have the same
   linearisation at rest (u0 = 0), so they share the admissible set and the first candidate;
   each is verified with its own runs and written in its own mapping.
4. **verify** (:func:`verify`), every run ``verify_s`` of the axis's own program, judged by
   :func:`admissible`: a fault (following error, limits), more saturated samples than the
   configured controller on the same run plus :data:`SAT_SHARE` of the samples, u noise at
   rest above :data:`U_REST_FRACTION` of u_lim, or oscillation (a spectral line in u at rest
   ≥ :data:`OSC_RATIO` times the median of its spectrum, or the error spectrum ≥
   :data:`OSC_RATIO` times the configured controller's at some frequency) fails a run.

   a. *ladder* on the first candidate: 50 %, 75 %, 100 % of its loop gain (PID: P, I, D;
      C1/C2: k_s), a rung between two on a failure (when 50 % fails: 35 %, then 25 %).
   b. *search*: per shape (ζ, r), the highest admissible ω that passes. A failed run bounds ω
      from above (noise, saturation, oscillation, a fault of a ringing loop), or from below
      when it faults on its following error with u quiet at rest and no line in u or e
      (:func:`too_soft`: the loop is too soft for the program) or saturates more than a run
      of the shape at a higher ω did (its larger error drives u into the limit). The
      candidates are the admissible ω whose rest noise, read off the prediction of step 3
      through the shape's own runs (a power law through the nearest, of exponent
      :data:`NOISE_EXPONENT` or the one its runs fit: the prediction grows faster with ω
      than the machine's noise; a shape not yet run: in proportion to the latest run of
      any), is at most :data:`NOISE_SLACK` times the level (the run judges; the best often
      sits at the level). From where the previous shape's passed (the first shape: its
      highest candidate), down 1, 2, 4 ... grid points while runs fail high, up so while
      they pass or fail soft, then halving the bracket. Shapes
      in the order of their reach, the |L| at 2 Hz of their highest candidate (re-ranked
      after each shape); a shape whose reach is below :data:`PRUNE_SHARE` of that of the
      best run so far ends the search (the rest reach less still). At most
      :data:`SEARCH_RUNS` runs per shape and :data:`SEARCH_BUDGET` in all.
   c. *refinement* around the best run that passed at 100 %: its admissible neighbours on
      the family's grid (one step in ω, ζ or r, or in two of them at once), the highest |L|
      at 2 Hz first; the first that passes with a lower L2[e] becomes the centre; it stops
      when no neighbour improves, after :data:`REFINE_RUNS` runs.
   d. *winner*: the least L2[e] of every run that passed; a search winner climbs the ladder
      of a. (its 100 % run done); stopped on a lower rung it stands at the highest scale that
      passed, and the next best of another shape climbs (at most :data:`WINNER_TRIES`).

   The budget per law: a. 3-7 runs, b. at most :data:`SEARCH_BUDGET` = 14, c. at most
   :data:`REFINE_RUNS` = 6, d. at most 3 per winner tried (:data:`WINNER_TRIES` = 3): at
   most 36 runs per law, spent on the shapes that reach furthest (of the PID's 20 shapes
   a few are searched). Measured: 9-26 runs per law, 51-71 per axis on configs/gantry.yaml
   and configs/gantry-rigid.yaml (8 s runs; about 1 min per axis on the virtual clock).
5. **write** (:func:`write_config`, :func:`plot_bode`): ``DIR/autotuned.yaml`` (the gains,
   commented with the margins that chose them) and ``DIR/bode_<A>.png``.
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml
from scipy import optimize, signal

from motorctl.app.build import build, shutdown, start
from motorctl.app.loopshape import c_frf, loop_margins, plant_model_frf
from motorctl.config import LoadedConfig, config_from_dict
from motorctl.control import configured_controllers, controller_class
from motorctl.control.base import SIG_E, Controller
from motorctl.loop.trajectory import Move
from motorctl.metrics import REST_AFTER_S, tracking_indexes, u_rest_rms
from motorctl.metrics import rest_mask as _rest_mask

# ---------------------------------------------------------------- the rule (stated once)
GM_MIN_DB = 6.0          #: gain margin ≥ [dB] (default of :class:`Rule`)
PM_MIN_DEG = 10.0        #: phase margin ≥ [deg]
MS_MAX_DB = 16.0         #: peak sensitivity ≤ [dB] (|S| ≤ 6.3)
F_TRACK_HZ = 2.0         #: where the tracking error lives (the programs' moves last ~0.5 s) [Hz]
U_REST_FRACTION = 0.02   #: u RMS at rest ≤ this share of u_lim (0.2 V at 10 V, as benchmarks/tune_gains.py)
SAT_SHARE = 7.5e-5       #: saturated samples ≤ those of the configured controller on the same run
                         #: + this share of the run (15 in 40 s at 5 kHz)
OSC_RATIO = 100.0        #: oscillation: a line in u at rest this far above its spectrum's median,
                         #: or e's spectrum this far above the configured controller's
SCALES = (0.5, 0.75, 1.0)  #: verification ladder (share of the chosen loop gain)
BACKOFF = (0.35, 0.25)     #: tried in turn when 50 % fails; the first that passes is kept
SEARCH_RUNS = 6          #: runs per shape of the search, at most
SEARCH_BUDGET = 14       #: runs of the search over all shapes of a law, at most
PRUNE_SHARE = 0.5        #: the search skips the shapes whose quiet |L(F_TRACK_HZ)| is below this
                         #: share of that of the least L2[e] passed so far
NOISE_EXPONENT = 0.7     #: measured rest noise ~ predicted^this within a shape, until its own runs fit it
NOISE_SLACK = 1.1        #: the search still runs gains whose calibrated rest-noise prediction is
                         #: up to this factor above the level (the run judges; the prediction
                         #: grows ~6 % per ω step and the best often sits at the level itself)
REFINE_RUNS = 6          #: runs of the local refinement around the search's best, at most
WINNER_TRIES = 3         #: search winners whose ladder is climbed before the rule's gains are kept
SATURATED = "saturated samples"   #: the words of the saturation verdict (:func:`admissible`)

# ---------------------------------------------------------------- the measurement
HOLD_HZ, HOLD_ZETA, HOLD_R = 20.0, 0.7, 5.0   #: the conservative holding PID
PERIOD_S = 1.0           #: multisine period [s] (1 Hz lines)
F_LO, F_SHAPE = 10.0, 60.0   #: lowest line, corner of the f² rise of the amplitudes [Hz]
LINE_SPACING = 0.01      #: lines every max(1 Hz, 1 % of f): 1/6 of a mode's width at ζ = 0.03
F_BOOST = 250.0          #: line amplitudes rise ∝ f² above this [Hz] (the response falls ∝ 1/f² and faster)
F_HI_SHARE = 0.48        #: highest line as a share of fs
EXC_SHARE = 0.8          #: |r| ≤ this share of u_lim
DISP_SHARE = 0.08        #: displacement RMS (catalogue model, open loop) ≤ this share of the FE limit
GUARD_SHARE = 0.5        #: |e| ≥ this share of the smallest FE limit switches the excitation off
STROKE_MARGIN = 0.1      #: the pass keeps this share of the stroke from each soft limit
REST_S = 0.6             #: rest at the start of the pass (encoder noise at rest) [s]
PERIODS = 32             #: measured multisine periods (after one ramp and one settling period)



@dataclass(frozen=True)
class Rule:
    """The margins the rule demands on the measured response, at every rung of the ladder
    (gain margin ≥ gm_min_db [dB], phase margin ≥ pm_min_deg [deg], peak sensitivity ≤
    ms_max_db [dB]). The defaults are the rule's; a user may state others (``motorctl autotune
    --pm-min-deg ...``)."""

    gm_min_db: float = GM_MIN_DB
    pm_min_deg: float = PM_MIN_DEG
    ms_max_db: float = MS_MAX_DB

    def holds(self, mg) -> bool:
        return mg.meets(self.gm_min_db, self.pm_min_deg, self.ms_max_db)

    def text(self) -> str:
        return f"GM >= {self.gm_min_db:g} dB, PM >= {self.pm_min_deg:g} deg, |S| <= {self.ms_max_db:g} dB"


RULE = Rule()


class AutotuneError(ValueError):
    """The axis cannot be autotuned as configured (one line: what and why)."""


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


def _pass_plan(loaded: LoadedConfig, axis: str, duration_s: float):
    """(x_a, x_b, v [m/s]) of the constant-velocity pass: from the lower soft limit to the
    upper, 10 % of the stroke inside each, at the speed that lasts ``duration_s``."""
    lim = loaded.axes[axis].limits
    lo, hi = lim.soft_min_m, lim.soft_max_m
    if not (math.isfinite(lo) and math.isfinite(hi) and hi > lo):
        raise AutotuneError(f"axes.{axis}.limits: autotune needs finite soft limits (the stroke)")
    a, b = lo + STROKE_MARGIN * (hi - lo), hi - STROKE_MARGIN * (hi - lo)
    v = abs(b - a) / duration_s
    return a, b, min(v, 0.25 * lim.max_velocity_m_per_s)


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


def measure_frf(loaded: LoadedConfig, raw: dict, axis: str, clock: str = "virtual",
                progress=None, periods: int = PERIODS) -> dict:
    """Step 1 (module docstring) on the config's driver; ``periods`` measured periods (even:
    ``periods``/2 realisations of two periods, the first of each its transient).

    Returns:
        {"f_hz" (L,), "G" (L,) complex [m/V], "coherence" (L,), "coherence_u" (L,),
        "rest_psd": (f (M,), S_yy (M,) [m²/Hz]) of y at rest, "excitation_rms_V",
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
    v_app = min(0.1, 0.25 * lim.max_velocity_m_per_s)
    stroke = lim.soft_max_m - lim.soft_min_m
    capacity = tb.cycles(stroke / v_app + 1.0 + REST_S + pass_move.duration) + 8
    asm = build(loaded2, [axis], "pid", clock=clock, capacity=capacity, operated=True)
    start(asm, "off" if clock == "virtual" else loaded.cfg.loop.realtime.policy)
    try:
        y0 = _read_idle(asm)                     # where the axis stands
        if not lim.soft_min_m <= y0 <= lim.soft_max_m:
            raise AutotuneError(f"axis {axis} stands at {y0:.4f} m, outside its soft limits "
                                f"(motorctl jog it back first)")
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
    finally:
        shutdown(asm)
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
    out.update(f_hz=fr[lines], G=G[lines], coherence=c_re[lines],
               coherence_u=c_ru[lines])
    return out


# ================================================================ fit
def _initial_mode(f: np.ndarray, G: np.ndarray, th1: float):
    """(mode_hz, load_fraction) from the peak and the dip of |G| (2πf)² θ1 (nan: none)."""
    comp = np.abs(G) * (2.0 * math.pi * f) ** 2 * th1
    lc = np.log(comp)
    sm = np.convolve(lc, np.ones(5) / 5.0, mode="same")
    band = f > 2.0 * F_LO
    i_pk = int(np.argmax(np.where(band, sm, -np.inf)))
    below = band & (f < f[i_pk])
    if not below.any() or sm[i_pk] - np.median(sm[band]) < math.log(2.0):
        return math.nan, math.nan
    i_dip = int(np.argmin(np.where(below, sm, np.inf)))
    frac = 1.0 - (f[i_dip] / f[i_pk]) ** 2
    return float(f[i_pk]), float(min(max(frac, 0.05), 0.9))


def fit_plant(f: np.ndarray, G: np.ndarray, coh: np.ndarray, ts: float, theta_hat0) -> dict:
    """Step 2 (module docstring). Returns the fitted model (:data:`motorctl.app.loopshape.MODEL_KEYS`) plus "cost",
    "cost_rigid" (the rigid model's cost), "mode": True when the mode is kept.

    Args: f (L,) [Hz], G (L,) [m/V], coh (L,) coherence r → e, ts [s], theta_hat0 (6,).
    """
    w = 2.0 * math.pi * f
    # weights from the coherence smoothed over ±10 lines: a line's own coherence is high
    # exactly where its noise happened to add to the response, which would bias |G| upwards
    cs = np.clip(np.convolve(coh, np.ones(21) / 21.0, mode="same"), 0.0, 0.999)
    cs[:10], cs[-10:] = cs[10], cs[-11]
    wt = np.sqrt(cs / (1.0 - cs))
    ok = np.isfinite(G) & (np.abs(G) > 0)
    w, G, wt, f = w[ok], G[ok], wt[ok], f[ok]
    lo = f < 0.3 * f[-1]
    th1_0 = float(np.median(1.0 / (np.abs(G[lo]) * w[lo] ** 2)))
    fs = 1.0 / ts

    def model(x, with_mode):
        p = {"theta1": x[0], "theta2": x[1], "current_loop_hz": x[2], "delay_s": x[3],
             "mode_hz": x[4] if with_mode else 0.0, "mode_damping": x[5] if with_mode else 0.0,
             "load_fraction": x[6] if with_mode else 0.0}
        return p

    def resid(x, with_mode, log=True):
        # log: robust far from the solution; then G/G_model − 1, unbiased by the noise on G
        # (the log of a noisy magnitude is biased upwards where the coherence is low)
        gm = plant_model_frf(model(x, with_mode), ts, w)
        z = np.log(gm / G) if log else G / gm - 1.0
        return np.concatenate([wt * z.real, wt * (np.angle(gm / G) if log else z.imag)])

    def refine(sol, with_mode, lb, ub):
        x0 = np.clip(sol.x, lb, ub)
        return optimize.least_squares(resid, x0, args=(with_mode, False), x_scale="jac",
                                      bounds=(lb, ub))

    best_rigid = None
    for fc0 in (0.1 * fs, 0.2 * fs, 0.4 * fs):
        x0 = [th1_0, 0.1 * th1_0 * 2 * math.pi * F_LO, fc0, 0.0]
        sol = optimize.least_squares(resid, x0, args=(False,), x_scale="jac",
                                     bounds=([1e-6, 0.0, 10.0, 0.0], [1e6, 1e6, 10.0 * fs, 5.0 * ts]))
        if best_rigid is None or sol.cost < best_rigid.cost:
            best_rigid = sol
    best_rigid = refine(best_rigid, False, [1e-6, 0.0, 10.0, 0.0], [1e6, 1e6, 10.0 * fs, 5.0 * ts])
    out = model(best_rigid.x, False)
    out.update(cost=float(best_rigid.cost), cost_rigid=float(best_rigid.cost), mode=False)
    fm0, fr0 = _initial_mode(f, G, best_rigid.x[0])
    if math.isfinite(fm0):
        best = None
        for fc0 in (0.1 * fs, 0.2 * fs, 0.4 * fs):
            for z0 in (0.02, 0.08):
                x0 = list(best_rigid.x[:2]) + [fc0, 0.0, fm0, z0, fr0]
                sol = optimize.least_squares(
                    resid, x0, args=(True,), x_scale="jac",
                    bounds=([1e-6, 0.0, 10.0, 0.0, 0.5 * fm0, 1e-3, 0.01],
                            [1e6, 1e6, 10.0 * fs, 5.0 * ts, min(2.0 * fm0, 0.5 * fs), 0.5, 0.95]))
                if best is None or sol.cost < best.cost:
                    best = sol
        lb_m = [1e-6, 0.0, 10.0, 0.0, 0.5 * fm0, 1e-3, 0.01]
        ub_m = [1e6, 1e6, 10.0 * fs, 5.0 * ts, min(2.0 * fm0, 0.5 * fs), 0.5, 0.95]
        best = refine(best, True, lb_m, ub_m)
        if best.cost < 0.7 * best_rigid.cost:
            out = model(best.x, True)
            out.update(cost=float(best.cost), cost_rigid=float(best_rigid.cost), mode=True)
    return {k: float(v) if not isinstance(v, bool) else v for k, v in out.items()}


# ================================================================ the rule
OMEGA = tuple(float(x) for x in np.geomspace(30.0, 3000.0, 49))   #: [rad/s]


def loop_frf(meas: dict, model: dict, ts: float):
    """(w (K,) [rad/s] of :func:`grid_w`, the fitted model's FRF (K,), the FRF the rule runs on
    (K,)): the measured FRF where it was measured (coherence ≥ 0.5, interpolated between the
    lines) and the fitted model elsewhere (below 10 Hz, above the last line) [m/V]."""
    w = grid_w(ts)
    G_fit = plant_model_frf(model, ts, w)
    G_w = G_fit.copy()
    fm, Gm, ch = meas["f_hz"], meas["G"], meas["coherence"]
    good = ch >= 0.5
    f_w = w / (2.0 * math.pi)
    if good.sum() > 10:
        inside = (f_w >= fm[good][0]) & (f_w <= fm[good][-1])
        re = np.interp(f_w, fm[good], Gm[good].real)
        im = np.interp(f_w, fm[good], Gm[good].imag)
        G_w[inside] = re[inside] + 1j * im[inside]
    return w, G_fit, G_w


def margins_hold(law: str, g: dict, ts: float, w: np.ndarray, G_w: np.ndarray, theta_hat=None,
                 rule: Rule = RULE):
    """(:class:`Margins` of L = C G_w at 100 % of ``g``, whether the rule's margins hold at every
    rung of the verification ladder :data:`SCALES`). A loop with integral action can lose phase
    margin when its gain falls, and a heavier load lowers the loop gain the same way."""
    f = w / (2.0 * math.pi)
    L = controller_class(law).linearise(g, ts, w, theta_hat) * G_w
    mg = loop_margins(L, f)
    ok = rule.holds(mg) and all(rule.holds(loop_margins(sc * L, f)) for sc in SCALES[:-1])
    return mg, ok


def tunable_laws(section) -> list[str]:
    """The laws an axis's section configures that give autotune a gain family and a
    linearisation (:class:`motorctl.control.base.Controller`), sorted."""
    out = []
    for name in configured_controllers(section):
        cls = controller_class(name)
        try:
            fam = cls.gain_family(1.0, section.settings(name), OMEGA[:1])
            if fam:
                cls.linearise(fam[0], 1e-4, np.array([1.0]))
                out.append(name)
        except NotImplementedError:
            continue
    return out


def shape_of(g: dict) -> tuple:
    """A candidate's shape: its design numbers other than ω ("_zeta", "_r", ...)."""
    return tuple(sorted((k, v) for k, v in g.items() if k.startswith("_") and k not in ("_w", "_rest_V")))


def design_of(g: dict) -> tuple:
    """A candidate's place in its law's family: all its design numbers, ω included
    ((("_r", r), ("_w", ω), ("_zeta", ζ)) for the PID)."""
    return tuple(sorted((k, v) for k, v in g.items() if k.startswith("_") and k != "_rest_V"))


def neighbours(g: dict, grid: dict, members: dict) -> list[dict]:
    """The members of ``members`` ({:func:`design_of`: gains}) one grid step from ``g`` in one
    design number, or in two at once (the diagonals: e.g. a higher ω with a lower ζ), on the
    family's grid ``grid`` ({design key: sorted values}, :func:`choose_gains`)."""
    here = dict(design_of(g))
    keys = [k for k in grid if k in here]
    steps = [((k, s),) for k in keys for s in (1, -1)]
    steps += [((a, sa), (b, sb)) for i, a in enumerate(keys) for b in keys[i + 1:]
              for sa in (1, -1) for sb in (1, -1)]
    out = []
    for step in steps:
        d = dict(here)
        for k, s in step:
            j = grid[k].index(here[k]) + s
            if not 0 <= j < len(grid[k]):
                break
            d[k] = grid[k][j]
        else:
            m = members.get(tuple(sorted(d.items())))
            if m is not None:
                out.append(m)
    return out


def rest_noise(C: np.ndarray, rest_psd) -> float:
    """Predicted u RMS at rest [V]: the measured rest spectrum of y [m²/Hz] through |C| (a
    carriage held by stiction: the loop is open). C: C(e^{jωTs}) at the PSD's frequencies."""
    f, s = rest_psd
    df = f[1] - f[0]
    return float(math.sqrt(np.sum(np.abs(C[1:]) ** 2 * s[1:]) * df))


def grid_w(ts: float) -> np.ndarray:
    """The frequency grid of the margins [rad/s]: 1 Hz to 0.999 Nyquist, log-spaced."""
    return np.geomspace(2.0 * math.pi, 0.999 * math.pi / ts, 4000)


def choose_gains(law: str, G_w, w: np.ndarray, ts: float, theta1: float, section, rest_psd,
                 theta_hat=None, rule: Rule = RULE) -> dict | None:
    """Step 3 for one law on the plant FRF ``G_w`` (K,) at ``w`` (K,) [rad/s]: the family
    members whose margins hold at every step of the verification ladder.

    Returns:
        None when no candidate passes, else {"gains" (the highest |L| at F_TRACK_HZ),
        "margins" (:class:`Margins`), "u_rest_pred_V", "candidates" (how many passed),
        "backoff", "admissible": {shape: [gains, ... by ω, highest first]},
        "members": {:func:`design_of`: gains} (the same candidates, by their place in the
        family), "grid": {design key: sorted values over the whole family},
        "l_track": {:func:`design_of`: |L| at F_TRACK_HZ}}.
    """
    cls = controller_class(law)
    f = w / (2.0 * math.pi)
    wn = 2.0 * math.pi * rest_psd[0]
    best, n_ok, adm, members, l_track, grid = None, 0, {}, {}, {}, {}
    j_tr = int(np.argmin(np.abs(f - F_TRACK_HZ)))
    for g in cls.gain_family(theta1, section.settings(law), OMEGA):
        for k, v in design_of(g):
            grid.setdefault(k, set()).add(v)
        mg, ok = margins_hold(law, g, ts, w, G_w, theta_hat, rule)
        if not ok:
            continue
        L = cls.linearise(g, ts, w, theta_hat) * G_w
        un = rest_noise(cls.linearise(g, ts, np.maximum(wn, 1e-9), theta_hat), rest_psd)
        n_ok += 1
        g["_rest_V"] = un
        adm.setdefault(shape_of(g), []).append(g)
        members[design_of(g)] = g
        l_track[design_of(g)] = float(abs(L[j_tr]))
        key = (abs(L[j_tr]), -mg.ms_db)
        if best is None or key > best[0]:
            best = (key, g, mg, un)
    if best is None:
        return None
    L = cls.linearise(best[1], ts, w, theta_hat) * G_w
    backoff = [b for b in BACKOFF if rule.holds(loop_margins(b * L, f))]
    for v in adm.values():
        v.sort(key=lambda g: -g["_w"])
    return {"gains": best[1], "margins": best[2], "u_rest_pred_V": best[3], "candidates": n_ok,
            "backoff": backoff, "admissible": adm, "members": members, "l_track": l_track,
            "grid": {k: sorted(v) for k, v in grid.items()}}


# ================================================================ closed-loop runs
def scaled(law: str, g: dict, s: float) -> dict:
    """Gains ``g`` at share ``s`` of the loop gain (the law's own knob:
    :meth:`motorctl.control.base.Controller.scaled`)."""
    return controller_class(law).scaled(g, s)


def apply_gains(raw: dict, axis: str, law: str, g: dict, extra: dict | None = None) -> dict:
    """A copy of the config dict with ``law``'s tuned keys of ``g`` (and the settings in
    ``extra``, e.g. the PID's feedforward) in the law's own mapping of ``axis``'s
    ``controller:`` section (over the shared keys, which stay as they are)."""
    raw = copy.deepcopy(raw)
    sec = raw["axes"][axis]["controller"]
    own = dict(sec.get(law) or {})
    if extra:
        own.update(extra)
    own.update({k: float(g[k]) for k in controller_class(law).tuned_keys if k in g})
    sec[law] = own
    return raw


def rest_mask(rows: np.ndarray, lay, axis: str, ts: float) -> np.ndarray:
    """Samples of ``axis`` in the recorded ``rows`` where the command has not moved for
    :data:`~motorctl.metrics.REST_AFTER_S` (:func:`motorctl.metrics.rest_mask`)."""
    return _rest_mask(rows[:, lay.index(f"{axis}.xd_dot")], rows[:, lay.index(f"{axis}.xd_ddot")], ts,
                      REST_AFTER_S)


def oscillation_ratio(u: np.ndarray, rest: np.ndarray, ts: float) -> tuple[float, float]:
    """(peak/median of the PSD of u over its rest segments above 20 Hz, its frequency [Hz])."""
    edges = np.diff(np.concatenate([[0], rest.astype(int), [0]]))
    psd, f = None, None
    for a, b in zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)):
        if b - a < 512:
            continue
        f, p = signal.welch(u[a:b], fs=1.0 / ts, nperseg=512, detrend="linear")
        psd = p if psd is None else psd + p
    if psd is None:
        return math.nan, math.nan
    band = f > 20.0
    j = int(np.argmax(np.where(band, psd, -np.inf)))
    return float(psd[j] / np.median(psd[band])), float(f[j])


def evaluate(raw: dict, source: str, axis: str, law: str, seconds: float, clock: str = "virtual") -> dict:
    """A closed-loop run of ``axis``'s program with controller ``law`` on the config dict, on
    its driver: a jerk-limited approach at ≤ 0.1 m/s from where the axis stands to the
    program's start (as the daemon's ``start``), then ``seconds`` of the program, which alone
    is evaluated.

    Returns:
        :func:`motorctl.metrics.tracking_indexes` [µm, V] plus "u_rest_rms_V" (RMS of u about
        its mean at rest), "saturated" (samples at |u| = u_lim), "samples", "fault" ('' none),
        "osc_ratio", "osc_hz" (:func:`oscillation_ratio`).
    """
    loaded = config_from_dict(raw, source)
    tb = loaded.timebase
    lim = loaded.axes[axis].limits
    n = tb.cycles(seconds)
    v_app = min(0.1, 0.25 * lim.max_velocity_m_per_s)
    n_app_max = tb.cycles((lim.soft_max_m - lim.soft_min_m) / v_app + 1.0)
    asm = build(loaded, [axis], law, clock=clock, capacity=n + n_app_max + 8, operated=True)
    start(asm, "off" if clock == "virtual" else loaded.cfg.loop.realtime.policy)
    try:
        y0 = _read_idle(asm)                     # where the axis stands
        approach = Move(y0, asm.loop.programs[0].sample(0.0)[0], v_app, 2.0, 200.0)
        n_app = tb.cycles(approach.duration) + 1
        k0 = asm.loop.k
        asm.loop.start_axis(0, approach)
        asm.loop.run(n_app + n)
    finally:
        shutdown(asm)
    rows, lay = asm.loop.rows()[k0 + n_app:], asm.loop.layout
    ts = loaded.period_s
    t, e, u = (rows[:, lay.cycle("t")], rows[:, lay.index(f"{axis}.e")], rows[:, lay.index(f"{axis}.u")])
    rest = rest_mask(rows, lay, axis, ts)
    u_lim = loaded.axes[axis].controller.u_lim
    res = tracking_indexes(t, e, u, loaded.axes[axis].trajectory.period_s)
    res["u_rest_rms_V"] = u_rest_rms(u, rest)
    res["saturated"] = int(np.sum(np.abs(u) >= u_lim * (1.0 - 1e-12)))
    res["samples"] = int(rows.shape[0])
    res["fault"] = asm.supervisor.reason(0)
    res["osc_ratio"], res["osc_hz"] = oscillation_ratio(u, rest, ts)
    res["e_psd"] = signal.welch(e, fs=1.0 / ts, nperseg=e_segment(e.size), detrend="linear")
    return res


def e_segment(n: int) -> int:
    """Welch segment of an n-sample error record for :func:`e_line_ratio`: at most 1024 samples,
    and short enough for at least 16 averaged segments (50 % overlap), so that the ratio of two
    spectra is not a ratio of two single periodograms (each χ² with 2 degrees of freedom per
    line, whose ratio exceeds 100 by chance on a few lines of every run)."""
    seg = 1024
    while seg > 64 and n < 8 * seg:
        seg //= 2
    return seg


def e_line_ratio(res: dict, ref: dict) -> tuple[float, float]:
    """(largest ratio of a run's error spectrum to the reference run's above 20 Hz, where
    [Hz]). A loop near its stability limit rings at its crossover or a mode while the axis
    moves (at rest stiction can hold the carriage and hide it): e.g. X with PM −0.3° on the
    measured response: 724x at 444 Hz against ≤ 24x for loops with PM ≥ 15°."""
    f, p = res["e_psd"]
    fr, pr = ref["e_psd"]
    if f.shape != fr.shape:
        return math.nan, math.nan
    band = f > 20.0
    ratio = np.where(band, p / np.maximum(pr, 1e-300), -np.inf)
    j = int(np.argmax(ratio))
    return float(ratio[j]), float(f[j])


def admissible(res: dict, u_lim: float, ref: dict | None = None) -> str:
    """'' when a run meets the rule's closed-loop lines, else why not (one phrase). ref: the
    configured controller's run on the same program (:func:`evaluate`): its saturated samples
    are allowed (a program that drives u into its limit saturates whatever the gains), and an
    error spectrum :data:`OSC_RATIO` times its own at some frequency is an oscillation."""
    if res["fault"]:
        return f"fault: {res['fault']}"
    sat_ref = ref["saturated"] if ref else 0
    allowed = sat_ref + round(SAT_SHARE * res["samples"])
    if res["saturated"] > allowed:
        return f"{res['saturated']} {SATURATED} (> {allowed}: {sat_ref} as configured + {SAT_SHARE:.1e} of {res['samples']})"
    if not res["u_rest_rms_V"] <= U_REST_FRACTION * u_lim:
        return f"u at rest {res['u_rest_rms_V'] * 1e3:.0f} mV RMS (> {U_REST_FRACTION * u_lim * 1e3:.0f} mV)"
    if res["osc_ratio"] >= OSC_RATIO:
        return f"oscillation at {res['osc_hz']:.0f} Hz (line {res['osc_ratio']:.0f}x the median)"
    if ref:
        ratio, f = e_line_ratio(res, ref)
        if ratio >= OSC_RATIO:
            return f"oscillation at {f:.0f} Hz (e {ratio:.0f}x the configured controller's)"
    return ""


def too_soft(res: dict, u_lim: float, ref: dict | None = None) -> bool:
    """Whether a failed run (:func:`admissible`) failed because its loop is too soft for the
    program: a following-error fault while u was quiet at rest and showed no line, in u at
    rest nor in e against ``ref`` (a loop that rings until it faults shows one). A higher
    loop gain of the same shape is then the way out, not a lower one."""
    if "following error" not in res["fault"]:
        return False
    if not res["u_rest_rms_V"] <= U_REST_FRACTION * u_lim or res["osc_ratio"] >= OSC_RATIO:
        return False
    return not (ref and e_line_ratio(res, ref)[0] >= OSC_RATIO)


def _run(raw, source, axis, law, g, extra, seconds, clock, ref, u_lim, label, scale, runs, progress):
    res = evaluate(apply_gains(raw, axis, law, g, extra), source, axis, law, seconds, clock)
    why = admissible(res, u_lim, ref)
    runs.append((label, scale, res, why))
    if progress:
        progress(f"verify {axis} {law} {label} at {scale:.0%}: L2 {res['L2_um']:.3f} um, e_M "
                 f"{res['e_M_um']:.2f} um, rest {res['u_rest_rms_V'] * 1e3:.0f} mV, sat "
                 f"{res['saturated']}: {why or 'ok'}")
    return res, why


def ladder(raw, source, axis, law, g, extra, backoff, seconds, clock, ref, u_lim, label, runs,
           progress=None, done=None) -> tuple[float, dict | None]:
    """Runs of ``g`` climbing :data:`SCALES`. A rung that saturates more than allowed is not
    passed, but the climb goes on (a lower loop gain can saturate more: its error is larger),
    after one run at the geometric mean of it and the last passed scale;
    a fault, u noise at rest or an oscillation stops it, and then one more run at the geometric
    mean of the last passed and the stopping scale; when 50 % stops it with nothing passed, the
    ``backoff`` scales in turn. ``done``: {scale: result} already run (and passed). Returns
    (the highest scale that passed, 0 when none; its result)."""
    passed, best, steps = 0.0, None, list(SCALES)
    done = done or {}
    while steps:
        sc = steps.pop(0)
        if sc in done:
            res, why = done[sc], ""
        else:
            res, why = _run(raw, source, axis, law, scaled(law, g, sc), extra, seconds, clock, ref,
                            u_lim, label, sc, runs, progress)
        if why and SATURATED in why:
            if passed > 0 and sc / passed > 1.2:       # one rung between, then climb on
                steps.insert(0, round(math.sqrt(passed * sc), 3))
            continue
        if why:
            lower = [b for b in backoff if b < sc]
            if sc <= SCALES[0] and lower and passed == 0:
                steps = lower[:1]
                continue
            if passed > 0 and sc / passed > 1.2:       # one rung between the last two
                steps = [round(math.sqrt(passed * sc), 3)]
                continue
            break
        if sc > passed:
            passed, best = sc, res
        if sc < SCALES[0]:
            break
    return passed, best


def verify(raw: dict, source: str, axis: str, law: str, choice: dict, seconds: float,
           clock: str = "virtual", ref: dict | None = None, extra: dict | None = None,
           progress=None, search_runs: int = SEARCH_BUDGET) -> dict:
    """Step 4 for one law (module docstring): the ladder on the rule's first candidate, the
    search over the admissible shapes, the local refinement around its best, the ladder on
    the winner.

    Args:
        choice: :func:`choose_gains`'s result. ref: the configured controller's run on the same
        program (:func:`evaluate`). extra: settings written with the gains (the PID's feedforward).
        search_runs: the search's budget (b.); the refinement's is the lesser of it and
        :data:`REFINE_RUNS`.
    Returns:
        {"gains" (None when nothing passed), "scale" (of the winner's own gains), "from" ('rule'
        or 'search'), "L2_um", "runs": [(label, scale, result, verdict)]}.
    """
    v = _Verification(raw, source, axis, law, choice, seconds, clock, ref, extra, progress)
    g0 = choice["gains"]
    s0, r0 = v.ladder(g0, choice["backoff"], "rule")
    rule_best = (r0["L2_um"], scaled(law, g0, s0), s0, "rule") if s0 > 0 else None
    v.calibrate_on_rule()
    v.tried[design_of(g0)] = (r0, "") if s0 == 1.0 else (None, "failed in the ladder")
    if s0 == 1.0:
        v.found.append((r0["L2_um"], g0, 1.0, "rule"))
    v.search(search_runs)
    v.refine(min(REFINE_RUNS, search_runs))
    best = v.winner(rule_best)
    if best is None:
        return {"gains": None, "scale": 0.0, "from": "", "L2_um": math.nan, "runs": v.runs}
    return {"gains": best[1], "scale": best[2], "from": best[3], "L2_um": best[0], "runs": v.runs}


class _Verification:
    """What the steps of :func:`verify` share for one law: the runs made, the designs tried and
    their verdicts, the family members that passed at 100 %, and the calibration of the rest
    noise on the machine against the prediction.

    The calibration: the prediction (the open loop of a carriage held by stiction) is a bound
    that grows faster with ω than the noise does; so a member's noise is read off its
    prediction as a power law through the nearest run of its shape, with the shape's own
    exponent once it has two runs (NOISE_EXPONENT until then); a shape not yet run: in
    proportion to the latest run of any (a run that faulted says nothing of the noise).
    """

    def __init__(self, raw, source, axis, law, choice, seconds, clock, ref, extra, progress):
        self.raw, self.source, self.axis, self.law, self.choice = raw, source, axis, law, choice
        self.seconds, self.clock, self.ref, self.extra, self.progress = seconds, clock, ref, extra, progress
        self.u_lim = config_from_dict(raw, source).axes[axis].controller.u_lim
        self.rest_max = U_REST_FRACTION * self.u_lim
        self.runs: list = []      # (label, scale, result, verdict)
        self.tried: dict = {}     # {design: (result or None, verdict)}
        self.found: list = []     # (L2, gains, 1.0, 'rule' | 'search') passed at 100 %
        self.obs: dict = {}       # {shape: [(predicted, measured) rest noise [V]]}
        self.last: list = []      # the latest (predicted, measured) of any shape

    def ladder(self, g, backoff, label, done=None):
        """:func:`ladder` of ``g`` with this law's settings."""
        return ladder(self.raw, self.source, self.axis, self.law, g, self.extra, backoff, self.seconds,
                      self.clock, self.ref, self.u_lim, label, self.runs, self.progress, done=done)

    def calibrate_on_rule(self) -> None:
        """The first calibration point: the ladder's run whose noise most exceeds its prediction."""
        pred = self.choice["u_rest_pred_V"]
        pts = [(sc * pred, res["u_rest_rms_V"]) for _, sc, res, _ in self.runs
               if not res["fault"] and res["u_rest_rms_V"] > 0 and pred > 0]
        self.last = [max(pts, key=lambda x: x[1] / x[0])] if pts else []

    def noise_of(self, g) -> float:
        """The rest noise [V] expected of the design ``g`` (class docstring)."""
        own = self.obs.get(shape_of(g), [])
        if not (own or self.last) or g["_rest_V"] <= 0:
            return 0.0
        if not own:                             # another shape's run: in proportion
            return self.last[0][1] * g["_rest_V"] / self.last[0][0]
        beta = NOISE_EXPONENT
        lp = np.log([x[0] for x in own])
        if np.ptp(lp) > 0.05:
            beta = float(np.clip(np.polyfit(lp, np.log([x[1] for x in own]), 1)[0], 0.25, 1.0))
        p0, a0 = min(own, key=lambda x: abs(math.log(g["_rest_V"] / x[0])))
        return a0 * (g["_rest_V"] / p0) ** beta

    def noisy(self, g) -> bool:
        return self.noise_of(g) > NOISE_SLACK * self.rest_max

    def trial(self, g, label):
        """A run of ``g`` at 100 % (once per design); recorded, calibrated on. Returns
        (result, verdict: '' when it passed)."""
        key = design_of(g)
        if key in self.tried:
            return self.tried[key]
        res, why = _run(self.raw, self.source, self.axis, self.law, g, self.extra, self.seconds, self.clock,
                        self.ref, self.u_lim, label, 1.0, self.runs, self.progress)
        self.tried[key] = (res, why)
        if not why:
            self.found.append((res["L2_um"], g, 1.0, "search"))
        if not res["fault"] and res["u_rest_rms_V"] > 0 and g["_rest_V"] > 0:   # nan: False
            self.obs.setdefault(shape_of(g), []).append((g["_rest_V"], res["u_rest_rms_V"]))
            self.last[:] = [(g["_rest_V"], res["u_rest_rms_V"])]
        return res, why

    def reach(self, members) -> float:
        """|L| at F_TRACK_HZ of the shape's highest admissible ω whose noise is quiet."""
        g = next((g for g in members if not self.noisy(g)), members[-1])
        return self.choice["l_track"][design_of(g)]

    def search(self, budget: int) -> None:
        """Per shape, the highest ω that passes, bracketed on the shape's admissible ω (those
        whose rest noise, so calibrated, stays below the level). A run that fails by noise,
        saturation, oscillation or a fault of a ringing loop bounds ω from above; one that
        faults on its following error while quiet, or saturates more than at a higher ω (too
        soft for the program), bounds it from below. Shapes in the order of the |L| at
        F_TRACK_HZ of their highest quiet admissible ω (re-ranked after each shape, the
        calibration moving on), at most SEARCH_RUNS runs per shape and ``budget`` in all."""
        choice, u_lim = self.choice, self.u_lim
        w_hint, left, spent = None, dict(choice["admissible"]), 0
        while left and spent < budget:
            members = left.pop(max(left, key=lambda k: self.reach(left[k])))
            lead = min(self.found, key=lambda b: b[0], default=None)
            if lead is not None and design_of(lead[1]) in choice["l_track"] and \
                    self.reach(members) < PRUNE_SHARE * choice["l_track"][design_of(lead[1])]:
                break                               # the rest reach less still: ranked
            n = len(members)
            top = next((j for j, g in enumerate(members) if not self.noisy(g)), n - 1)
            p = top if w_hint is None else max(top, min(range(n),
                                                       key=lambda j: abs(members[j]["_w"] - w_hint)))
            # positions: ω falls with j; hi < boundary ≤ ok < lo (hi: failed high, lo: failed soft)
            hi, lo, ok, down, up, sat = -1, n, None, 1, 1, {}
            for _ in range(SEARCH_RUNS):
                if spent >= budget:
                    break
                n_before = len(self.runs)
                res, why = self.trial(members[p], _fmt_shape(members[p]))
                spent += len(self.runs) - n_before
                if res is not None and why and SATURATED in why:
                    sat[p] = res["saturated"]
                if not why:
                    ok = p if ok is None else min(ok, p)
                elif res is not None and (too_soft(res, u_lim, self.ref) or (
                        p in sat and any(j < p and sat[j] < sat[p] for j in sat))):
                    lo = min(lo, p)                 # (saturating more than at a higher ω: its error)
                else:
                    hi = max(hi, p)
                # the highest ω whose noise, calibrated anew on this run, stays below the level
                # (a shape with no noise of its own yet, all its runs faulted: no ceiling)
                top = (next((j for j, g in enumerate(members) if j > hi and not self.noisy(g)), n - 1)
                       if shape_of(members[0]) in self.obs else hi + 1)
                floor_ = max(hi, top - 1)           # every position ≤ this fails or is noisy
                if ok is not None:
                    if ok - floor_ <= 1:
                        break
                    if hi < 0:                      # nothing above has failed yet: climb
                        p, up = max(top, ok - up), up * 2
                    else:
                        p = (floor_ + ok) // 2
                elif lo - floor_ <= 1:              # no ω left between the two kinds of failure
                    break
                elif lo < n and hi < 0:             # only too soft so far: climb
                    p, up = max(floor_ + 1, p - up), up * 2
                elif lo < n:                        # failed on both sides: halve the window
                    p = (floor_ + lo) // 2
                else:                               # only too high so far: descend
                    p, down = min(n - 1, max(top, p + down)), down * 2
            if ok is not None:
                w_hint = members[ok]["_w"]

    def refine(self, budget: int) -> None:
        """From the best family member that passed, one grid step at a time (ω, ζ, r, and two of
        them at once) to an admissible neighbour not yet run, the highest |L| at F_TRACK_HZ
        first; move to the first that passes with a lower L2[e], stop when none does or after
        ``budget`` runs."""
        choice = self.choice
        center = min(self.found, key=lambda b: b[0], default=None)
        while center is not None and budget > 0:
            near = [g for g in neighbours(center[1], choice["grid"], choice["members"])
                    if design_of(g) not in self.tried and not self.noisy(g)]
            near.sort(key=lambda g: -choice["l_track"][design_of(g)])
            moved = None
            for g in near[:budget]:
                budget -= 1
                res, why = self.trial(g, "near " + _fmt_shape(g))
                if not why and res["L2_um"] < center[0]:
                    moved = (res["L2_um"], g, 1.0, "search")
                    break
            center = moved

    def winner(self, rule_best):
        """The least L2[e] of every run that passed: (L2, gains, scale, from) or None. A search
        winner climbs the ladder too (its 100 % run is already done); when a rung below stops
        it, it stands at the highest scale that passed (as the rule's gains do) and the next
        best climbs, at most WINNER_TRIES of them, one per shape; the least L2[e] of what stood
        is kept."""
        accepted = [rule_best] if rule_best is not None else []
        climbs, stopped = 0, set()
        for cand in sorted((b for b in self.found if b[3] == "search"), key=lambda b: b[0]):
            if climbs == WINNER_TRIES or (accepted and min(a[0] for a in accepted) <= cand[0]):
                break
            if shape_of(cand[1]) in stopped:        # its shape stopped on a lower rung already
                continue
            climbs += 1
            sc, res_sc = self.ladder(cand[1], (), "winner", done={1.0: self.tried[design_of(cand[1])][0]})
            if sc == 1.0:
                accepted.append(cand)
                break
            stopped.add(shape_of(cand[1]))
            if sc > 0.0:
                accepted.append((res_sc["L2_um"], scaled(self.law, cand[1], sc), sc, "search"))
        return min(accepted, key=lambda b: b[0], default=None)


def _fmt_shape(g: dict) -> str:
    return "w {:.0f}".format(g["_w"]) + "".join(f" {k[1:]} {v:g}" for k, v in shape_of(g))


# ================================================================ the whole procedure
def autotune(loaded: LoadedConfig, raw: dict, axis: str, clock: str = "virtual",
             verify_s: float | None = None, progress=None, periods: int = PERIODS,
             rule: Rule = RULE, laws=None, measure_only: bool = False,
             search_runs: int = SEARCH_BUDGET) -> dict:
    """Steps 1-4 for one axis and the laws ``laws`` (None: every law of :func:`tunable_laws`;
    ``measure_only``: steps 1-2, no law; ``search_runs``: :func:`verify`'s). Returns
    {"measure", "model", "theta_hat0", "w", "G_fit", "G_w", "choice": {law: ...}, "verify":
    {law: ...}, "reference" (None when measure_only), "gains": {law: gains written}, "extra":
    {law: settings written with them}}.

    Raises:
        AutotuneError: the measurement faulted or tripped its guard, or no law could be tuned.
    """
    sec = loaded.axes[axis].controller
    ts = loaded.period_s
    meas = measure_frf(loaded, raw, axis, clock, progress, periods)
    if meas["fault"] or meas["tripped"] or "G" not in meas:
        why = meas["fault"] or ("the excitation guard fired (|e| reached "
                                f"{meas['guard_m'] * 1e6:.0f} um)" if meas["tripped"] else "too short")
        raise AutotuneError(f"axis {axis}: the measurement stopped: {why}")
    model = fit_plant(meas["f_hz"], meas["G"], meas["coherence"], ts, sec.theta_hat0)
    if progress:
        progress(f"fit {axis}: theta1 {model['theta1']:.4g} V s^2/m (theta_hat1(0) "
                 f"{sec.theta_hat0[0]:.4g}), theta2 {model['theta2']:.3g} V s/m, mode "
                 f"{model['mode_hz']:.1f} Hz zeta {model['mode_damping']:.3f} load "
                 f"{model['load_fraction']:.2f}, current loop {model['current_loop_hz']:.0f} Hz, "
                 f"delay {model['delay_s'] * 1e6:.1f} us")
    w, G_fit, G_w = loop_frf(meas, model, ts)
    th = np.asarray(sec.theta_hat0, dtype=float)
    fitted = th.copy()              # θ1 from the fit; θ2..θ6 (friction, offset) as configured:
    fitted[0] = model["theta1"]     # the FRF above 10 Hz does not see them
    done = {"axis": axis, "measure": meas, "model": model, "theta_hat0": th.tolist(), "w": w,
            "G_fit": G_fit, "G_w": G_w, "choice": {}, "verify": {}, "reference": None,
            "gains": {}, "extra": {}, "ts": ts, "section": sec, "rule": rule}
    if measure_only:
        return done
    period = loaded.axes[axis].trajectory.period_s
    vs = verify_s if verify_s is not None else max(2.0 * period, 1.0)
    ref = evaluate(raw, str(loaded.path), axis, sec.type, vs, clock)
    if progress:
        progress(f"verify {axis}: as configured ({sec.type}): L2 {ref['L2_um']:.3f} um, "
                 f"{ref['saturated']} saturated samples")
    choice, ver, gains, extra = {}, {}, {}, {}
    for law in (laws or tunable_laws(sec)):
        ch_ = choose_gains(law, G_w, w, ts, model["theta1"], sec, meas["rest_psd"], th, rule)
        choice[law] = ch_
        if ch_ is None:
            continue
        if progress:
            m = ch_["margins"]
            progress(f"rule {axis} {law}: {_fmt_gains(law, ch_['gains'])}: GM {m.gm_db:.1f} dB, PM "
                     f"{m.pm_deg:.1f} deg, |S| {m.ms_db:.1f} dB, crossover {m.wc_hz:.0f} Hz, rest "
                     f"{ch_['u_rest_pred_V'] * 1e3:.0f} mV predicted ({ch_['candidates']} passed "
                     f"in {len(ch_['admissible'])} shapes)")
        extra[law] = controller_class(law).model_settings(fitted) or None
        ver[law] = verify(raw, str(loaded.path), axis, law, ch_, vs, clock, ref, extra[law], progress,
                          search_runs)
        if ver[law]["gains"] is not None:
            gains[law] = ver[law]["gains"]
    if not choice or all(c is None for c in choice.values()):
        raise AutotuneError(f"axis {axis}: no gains of any law meet the rule on the measured response")
    return done | {"choice": choice, "verify": ver, "reference": ref, "gains": gains, "extra": extra}


def _fmt_gains(law: str, g: dict) -> str:
    return " ".join(f"{k} {g[k]:.4g}" for k in controller_class(law).tuned_keys if k in g)


def final_margins(res: dict) -> dict:
    """Margins of the written gains on the measured FRF: {law: Margins}."""
    return {law: loop_margins(c_frf(law, g, res["ts"], res["w"], res["theta_hat0"]) * res["G_w"],
                              res["w"] / (2.0 * math.pi))
            for law, g in res["gains"].items()}


def write_config(raw: dict, results: list, source: str, path) -> dict:
    """Step 5: ``raw`` with every autotuned axis's gains (each law in its own mapping of the
    ``controller:`` section), checked as check-config does, written to ``path`` with a comment
    block per axis (model, rule, margins, verification).

    Raises:
        ConfigError: the result does not pass the checks (nothing written). OSError.
    """
    new = copy.deepcopy(raw)
    lines = [f"# motorctl autotune of {source}: per law, among the gains whose margins on the measured",
             f"# frequency response hold ({(results[0]['rule'] if results else RULE).text()} at 100/75/50 %), "
             f"the least L2[e] of a run",
             f"# of the axis's program that passes (no fault, saturation <= as configured + {SAT_SHARE:.1e} "
             f"of samples, u rest RMS <= {U_REST_FRACTION:g} u_lim, no oscillation); ladder 50/75/100 %."]
    for res in results:
        a, mdl = res["axis"], res["model"]
        lines.append(f"# axis {a}: fitted theta1 = M/A1 {mdl['theta1']:.4g} V s^2/m (config theta_hat1(0) "
                     f"{res['theta_hat0'][0]:.4g}), theta2 {mdl['theta2']:.3g} V s/m, mode "
                     f"{mdl['mode_hz']:.1f} Hz (zeta {mdl['mode_damping']:.3f}, load "
                     f"{mdl['load_fraction']:.2f}), current loop {mdl['current_loop_hz']:.0f} Hz, delay "
                     f"{mdl['delay_s'] * 1e6:.1f} us")
        mg = final_margins(res)
        for law in res["choice"]:
            if law not in res["gains"]:
                lines.append(f"#   {law}: not tuned (kept as configured)")
                continue
            g, v, m = res["gains"][law], res["verify"][law], mg[law]
            new = apply_gains(new, a, law, g, res["extra"].get(law))
            how = ("the rule's first candidate" if v["from"] == "rule" else "the search's best")
            lines.append(f"#   {law}: {_fmt_gains(law, g)} ({v['scale']:.0%} of {how}, L2 {v['L2_um']:.3f} um): "
                         f"GM {m.gm_db:.1f} dB at {m.gm_hz:.0f} Hz, PM {m.pm_deg:.1f} deg, |S|max "
                         f"{m.ms_db:.1f} dB, crossover {m.wc_hz:.0f} Hz")
    config_from_dict(new, str(path), check_budget=False)
    text = "\n".join(lines) + "\n" + yaml.safe_dump(new, sort_keys=False, default_flow_style=None)
    Path(path).write_text(text, encoding="utf-8")
    return new


def plot_bode(res: dict, path) -> str:
    """Step 5: the Bode plot (measured and fitted plant; each law's loop gain with its
    crossover, GM and PM marked) as PNG. Needs matplotlib (the ``plot`` extra)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    w, ts = res["w"], res["ts"]
    f = w / (2.0 * math.pi)
    meas = res["measure"]
    fig, ax = plt.subplots(2, 1, figsize=(10, 8), sharex=True)
    ax[0].loglog(meas["f_hz"], np.abs(meas["G"]), ".", ms=2, color="0.5", label="plant, measured")
    ax[0].loglog(f, np.abs(res["G_fit"]), "k-", lw=1, label="plant, fitted model")
    ax[1].semilogx(meas["f_hz"], np.degrees(np.angle(meas["G"])), ".", ms=2, color="0.5")
    ax[1].semilogx(f, np.degrees(np.angle(res["G_fit"])), "k-", lw=1)
    mg = final_margins(res)
    colors = ("tab:green", "tab:blue", "tab:red", "tab:purple", "tab:orange")
    for j, law in enumerate(res["gains"]):
        color = colors[j % len(colors)]
        L = c_frf(law, res["gains"][law], ts, w, res["theta_hat0"]) * res["G_w"]
        m = mg[law]
        lab = f"L {law}: GM {m.gm_db:.1f} dB, PM {m.pm_deg:.0f}°, |S| {m.ms_db:.1f} dB"
        ax[0].loglog(f, np.abs(L), color=color, lw=1, label=lab)
        ph = np.degrees(np.unwrap(np.angle(L)))
        ph -= 360.0 * math.ceil(ph[0] / 360.0)
        ax[1].semilogx(f, ph, color=color, lw=1)
        if math.isfinite(m.wc_hz):
            ax[0].axvline(m.wc_hz, color=color, ls=":", lw=0.8)
            ax[1].axvline(m.wc_hz, color=color, ls=":", lw=0.8)
        if math.isfinite(m.gm_hz):
            ax[0].plot([m.gm_hz], [10 ** (-m.gm_db / 20)], "v", color=color)
    ax[0].axhline(1.0, color="0.7", lw=0.8)
    ax[1].axhline(-180.0, color="0.7", lw=0.8)
    ax[0].set_ylabel("|G| [m/V], |L| [-]")
    ax[1].set_ylabel("phase [deg]")
    ax[1].set_xlabel("frequency [Hz]")
    ax[1].set_ylim(-720, 180)
    ax[0].legend(fontsize=8)
    ax[0].set_title(f"axis {res['axis']}: measured plant (indirect closed-loop estimate) and loop gains")
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return str(path)
