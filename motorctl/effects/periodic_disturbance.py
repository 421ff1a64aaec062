"""Time-periodic disturbance (an unbalanced neighbour machine, a pump, mains vibration).

Physical model:

    F_eff(t) = A sin(2π f t + φ)                                                     [N]

Identification: columns sin, cos(2π f t); f from the peaks of the residual's spectrum against
time, refined by the joint LS fit. Compensation: d̂_eff(t) = Σ_k a_k sin(2π k f t) +
b_k cos(2π k f t) [V].
"""

from __future__ import annotations

import math
from typing import ClassVar

import numpy as np

from motorctl.effects.base import EffectFamily, PlantTerm, Signals
from motorctl.effects.periodic import (
    N_PEAKS,
    SHAPE_POINTS,
    AmplitudeStep,
    FourierAdaptable,
    amplitudes_phases,
    fourier,
    fourier_add,
    fourier_fill,
    fourier_basis,
    fourier_term,
    harmonics,
    spectral_lines,
    sin_cos_of,
)
from motorctl.jit import njit
from motorctl.schema import Pos

#: share of the fitted force that the carriage's inertial force θ1·ẍ carries at f when the loop
#: itself oscillates (a structural mode at 150 Hz under C2: 0.80; a 6 N disturbance at 7.3 Hz,
#: fought by the loop: the inertial force 0.0014)
MIN_LOOP_SHARE = 0.3
#: share of the fitted force that the input carries at f when the loop itself oscillates (the
#: 150 Hz mode under C2: 1.01). A force from outside at f puts the shares |S| and |T| of the
#: loop's sensitivity and complementary sensitivity (S + T = 1) on the inertial force and the
#: input: both are a few tenths near the loop's crossover (a 6 N 50 Hz vibration on a PD loop of
#: 25 Hz: 0.47 and 0.44), so the input's share must say the loop drives the line itself
MIN_LOOP_DRIVE_SHARE = 0.75
#: largest inertial share judged: beyond it the program's own motion at f (leaking into a short
#: record's fit: the 6 s rigid-plant log of the 7.3 Hz example, share 6.0) dominates the fit
MAX_LOOP_SHARE = 3.0
#: least correlation of the decimated position with itself one program period later for the
#: record's motion to repeat (:func:`program_period`)
MIN_REPEAT_CORR = 0.99
#: least number of program periods in the record for a line to be judged against the program's
#: harmonics (fewer: the harmonics are not resolved apart)
MIN_PERIODS = 3
#: a line within this share of the record's frequency resolution 1/L of a harmonic of the
#: program's period is at that harmonic
HARMONIC_SHARE = 0.25
#: spectrum peaks the search refines
SEARCH_PEAKS = 4
#: Frequency grid step [Hz] of the spectrum search.
DF_HZ = 0.02


@njit
def plant_force(f, x, v, t, sf, p):
    """f + F_eff [N] at plant time t [s] (x, v, sf unused): f + A' sin(w t + φ), A' = A before
    t_s, A_2 from t_s on; the row p = (A [N], w [rad/s], φ [rad], t_s [s] (inf: no step), A_2 [N])."""
    return f + (p[4] if t >= p[3] else p[0]) * math.sin(p[1] * t + p[2])


def program_period(p) -> float | None:
    """The period T [s] with which the record's motion repeats (a cyclic program), or None.

    T is the lag in [0.5 s, L/:data:`MIN_PERIODS`] (L the record's length) at which the
    decimated position, less its mean, correlates most with itself (the correlation
    coefficient of x(t) and x(t + T) over their overlap), taken when that correlation is at
    least :data:`MIN_REPEAT_CORR`. ``p``: the prepared record (x_d [m], t_d [s], (M,))."""
    x = p.x_d - np.mean(p.x_d)
    m = len(x)
    dt = (p.t_d[-1] - p.t_d[0]) / max(m - 1, 1)
    lo, hi = int(math.ceil(0.5 / dt)), int((m - 1) / MIN_PERIODS)
    if hi <= lo or not float(x @ x) > 0:
        return None
    n = 1 << (2 * m - 1).bit_length()
    spec = np.fft.rfft(x, n)
    lags = np.arange(lo, hi + 1)
    cross = np.fft.irfft(spec * np.conj(spec), n)[lags]          # Σ x(t) x(t + lag)
    sq = np.cumsum(x * x)
    head, tail = sq[m - 1 - lags], sq[-1] - sq[lags - 1]           # Σ x² of x(t), of x(t + lag)
    corr = cross / np.sqrt(np.maximum(head * tail, 1e-300))
    k = int(np.argmax(corr))
    return float((lo + k) * dt) if corr[k] >= MIN_REPEAT_CORR else None


def program_harmonic(p, f_Hz: float) -> tuple[int, float] | None:
    """(k, T): the line at ``f_Hz`` [Hz] is the k-th harmonic of the program's period T [s]
    (:func:`program_period`): within :data:`HARMONIC_SHARE` of the record's resolution 1/L of
    k/T; None when it is not, or the motion does not repeat."""
    period = program_period(p)
    if period is None:
        return None
    k = int(round(f_Hz * period))
    length = float(p.t_d[-1] - p.t_d[0])
    return (k, period) if k >= 1 and abs(f_Hz - k / period) < HARMONIC_SHARE / length else None


class PeriodicDisturbance(AmplitudeStep):
    """Simulated disturbance, ``axes.NAME.driver.effects.periodic_disturbance``:
    A sin(2π f t + φ) [N]. amplitude_N: A [N]. frequency_Hz: f [Hz]. phase_rad: φ [rad].
    step_at_s, scale_after: a drifting amplitude (tests of adapted compensation): from plant
    time step_at_s [s] on, A is multiplied by scale_after (both or neither; default: no step)."""

    amplitude_N: float
    frequency_Hz: Pos
    phase_rad: float = 0.0


class FourierTime(FourierAdaptable):
    """Compensation, ``axes.NAME.controller.compensation.periodic_disturbance``:
    Σ_k a_k sin(2π k f t) + b_k cos(2π k f t) [V] (force / A1); shorter list padded with 0.
    Adaptable (:class:`~motorctl.effects.base.Adaptable`): β = sin_V then cos_V, f fixed."""

    frequency_Hz: Pos
    sin_V: list[float] = []
    cos_V: list[float] = []


class PeriodicDisturbanceFamily(EffectFamily):
    name = "periodic_disturbance"
    size_parameters = ("amplitude_",)
    search_cost = 0.015
    kernels = (("force", plant_force), ("add", fourier_add), ("fill", fourier_fill))
    plant_force = "A sin(2πft + φ)"
    searched = "frequency f [Hz]"
    sim_options = PeriodicDisturbance
    example: ClassVar[dict] = {"periodic_disturbance": {"amplitude_N": 6.0, "frequency_Hz": 7.3, "phase_rad": 0.4}}
    comp_options = FourierTime
    compensation_rank = 3
    line_from_residual = True

    # simulator
    def plant_term(self, o: PeriodicDisturbance, period_s):
        a, w, ph = o.amplitude_N, 2.0 * math.pi * o.frequency_Hz, o.phase_rad
        step = [math.inf, a] if o.step_at_s is None else [o.step_at_s, a * o.scale_after]
        return PlantTerm.compiled("force", plant_force, [a, w, ph] + step)

    # identification
    def columns(self, h, p):
        """sin, cos(2π h t), (N, 2); h: frequency f [Hz]."""
        return fourier(p.t, 1.0 / h, 1)

    def decimated_columns(self, h, p):
        """The decimated columns (M, 2) in closed form: the decimation is a linear filter, so a
        sine in time comes out as the same sine at the decimated instants t_d times the
        filter's gain at h (``p.dec_gain``; its ends' transients are dropped with the record's
        edges: within 5e-5 of the filtered columns up to 68 Hz on a 20 s, 5 kHz log, 3e-4 at
        95 Hz). ``p``: the prepared record (t_d [s], dec_gain)."""
        return float(p.dec_gain(h)) * fourier(p.t_d, 1.0 / h, 1)

    def search(self, ctx, base, residual):
        """The residual spectrum's strongest lines (:data:`SEARCH_PEAKS`,
        :func:`~motorctl.effects.periodic.spectral_lines`: its periodogram's highest peaks), each
        refined on the joint fit; of those a force from outside can be (:meth:`loop_shares`), the lowest SSE
        (a line of the loop's own oscillation, or of the program's moves, is passed over so
        that a smaller outside line behind it is still found); none such: the lowest SSE."""
        p = ctx.p
        fs_d = p.fs / p.nd   # decimated sample rate [Hz]
        fast = Signals.decimated(p)
        best = None
        for f0 in spectral_lines(p.t_d, residual, SEARCH_PEAKS, 0.5, 0.35 * fs_d):
            grid = np.linspace(f0 - DF_HZ, f0 + DF_HZ, 9)
            term, _ = ctx.best_over(self.name, grid, base, lambda h: self.columns(h, fast))
            ev = ctx.evaluate(base + [term])
            sse = float(ev.fit.residual @ ev.fit.residual)
            outside = not self.loop_oscillates(*self.loop_shares(ctx, term, ev.fit.coef[-2:],
                                                                  ev.fit.coef[:ctx.n_theta]))
            key = (not outside, sse)
            if best is None or key < best[0]:
                best = (key, term)
        return None if best is None else (best[1], None)

    def polish(self, ctx, term, others):
        """The spectrum's peaks searched again (:meth:`search`) on the residual of the final
        model's other effects. Taken before them (the input delay of the current loop not yet
        modelled), the line's sideband can fit best: the program's moves modulate what the
        loop leaves of the disturbance, and a 7.3 Hz line was taken at 7.8 Hz (default plant,
        seeds 2 and 3), where in the final model 7.3 Hz leaves a quarter of the SSE."""
        found = self.search(ctx, others, ctx.evaluate(others).fit.residual)
        return None if found is None else found[0]

    @staticmethod
    def loop_shares(ctx, term, beta, theta) -> tuple[float, float]:
        """(θ1·|ẍ_f|, |u_f|) as shares of the fitted force's amplitude |β| at the term's
        frequency f (sin, cos fits of the decimated ẍ and u): the carriage's inertial force and
        the input at f."""
        p = ctx.p
        amp = float(np.hypot(beta[0], beta[1]))
        if not amp > 0:
            return 0.0, 0.0
        cols = term.cols[:, :2]
        ca = np.linalg.lstsq(cols, p.a_d, rcond=None)[0]
        cu = np.linalg.lstsq(cols, p.u_d, rcond=None)[0]
        return (abs(float(theta[0])) * float(np.hypot(ca[0], ca[1])) / amp,
                float(np.hypot(cu[0], cu[1])) / amp)

    @staticmethod
    def loop_oscillates(inertial: float, drive: float) -> bool:
        """The shares of :meth:`loop_shares` say the loop itself oscillates at f: the input
        carries the line at ≥ :data:`MIN_LOOP_DRIVE_SHARE` of the fitted force and the
        carriage's inertial force at ≥ :data:`MIN_LOOP_SHARE`, the inertial force at most
        :data:`MAX_LOOP_SHARE` of it (beyond, the
        program's own motion at f dominates the fit and the test cannot tell)."""
        return MIN_LOOP_SHARE <= inertial <= MAX_LOOP_SHARE and drive >= MIN_LOOP_DRIVE_SHARE

    def plausible(self, ctx, term, beta, theta, base):
        """A force from outside is either fought by the loop (the input carries it, the
        carriage hardly moves at f) or, above the loop's bandwidth, moves the carriage while
        the input does not follow. When both the input and the carriage's inertial force θ1·ẍ
        carry the line at :data:`MIN_LOOP_DRIVE_SHARE` and :data:`MIN_LOOP_SHARE` of the fitted
        force or more (:meth:`loop_oscillates`), the loop itself
        oscillates at f with the carriage: a resonance (a structural mode, a lightly damped or
        unstable loop), which a notch or a lower bandwidth treats, not a compensation."""
        inertial, drive = self.loop_shares(ctx, term, beta, theta)
        if self.loop_oscillates(inertial, drive):
            return [f"the loop itself oscillates at {term.h:.4g} Hz (the input carries {drive:.2f} and the "
                    f"carriage's inertial force {inertial:.2f} of the fitted force, >= {MIN_LOOP_DRIVE_SHARE:g} and "
                    f"{MIN_LOOP_SHARE:g}): "
                    "a resonance of the loop or the structure, not a force from outside"]
        at = program_harmonic(ctx.p, float(term.h))
        if at is not None:
            k, period = at
            return [f"at {term.h:.4g} Hz, harmonic {k} of the program's period {period:.4g} s (the motion repeats "
                    "with it): a force in step with the moves, an error of the model that repeats with the "
                    "program, is not told from one from outside"]
        return []

    def parameters(self, h, beta, gain, fs):
        g, unit = (gain, "N") if gain else (1.0, "V")
        amp, ph = amplitudes_phases(beta, g)
        return {"frequency_Hz": float(h), f"amplitude_{unit}": float(amp[0]), "phase_rad": float(ph[0])}

    # compensation
    def compensation(self, h, beta, signals=None, beta_std=None):
        """β_std: standard deviations of the fitted (sin, cos) coefficients, or None."""
        return self.adapt_entry({"frequency_Hz": float(h), "sin_V": [float(-beta[0])],
                                 "cos_V": [float(-beta[1])]}, beta_std)

    def compensation_for(self, o: PeriodicDisturbance, a1):
        s, c = sin_cos_of(o.amplitude_N / a1, o.phase_rad)
        return {"frequency_Hz": o.frequency_Hz, "sin_V": [s], "cos_V": [c]}

    def compensator(self, o: FourierTime):
        return fourier_term(harmonics(2.0 * math.pi * o.frequency_Hz, o.sin_V, o.cos_V), on_time=True)

    def adapt_basis(self, o: FourierTime):
        return fourier_basis(2.0 * math.pi * o.frequency_Hz, len(o.beta()) // 2, on_time=True)

    # report
    def shape(self, ctx, h, beta, gain):
        ts = ctx.p.t_d[0] + np.linspace(0, 3.0 / h, SHAPE_POINTS)
        zero = np.zeros_like(ts)
        y = -(gain or 1.0) * (self.columns(h, Signals(zero, zero, zero, zero, ts)) @ beta)
        return ts, y, "time [s]", "effect force [UNIT]"


FAMILY = PeriodicDisturbanceFamily()
