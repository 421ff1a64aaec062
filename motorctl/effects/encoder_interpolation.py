"""Encoder interpolation (sub-divisional) error: the reading, not the carriage, is periodic.

Physical model (an incremental sin/cos scale read through an interpolator; Heidenhain,
"Interpolation and digitizing error" in the exposed linear encoders' catalogue; Renishaw,
"Sub-divisional error" application note): the measured position is

    y = x + e(x),   e(x) = Σ_k a_k sin(2π k x / P + φ_k)                          [m]

with P the scale's signal period (20 µm optical, 1-5 mm magnetic) and k = 1, 2 (offset and
amplitude mismatch of the two signals give the first harmonic, their phase error the second).
No force acts: the motor drives the true x, so u = θ1 ẍ + … = θ1 (ÿ − ë) + …, and the residual
of the paper's model on the measured y is −θ1 ë(y). Its signature differs from cogging's
(Σ A_k sin(2πkx/P), a force): ë = d²e/dt² grows with ẋ² (and ẍ), so the force it appears to
take is proportional to the squared speed, while e itself does not depend on the speed.

Its simulator option is the axis-level ``axes.NAME.driver.encoder_interpolation_m`` (amplitude
of the first harmonic) with ``encoder_signal_period_m`` (not an ``effects:`` entry; the encoder
model of ``motorctl_drivers.sim``).

Identification: columns d²/dt² of sin, cos(2π k y / P), k ≤ 2, each through the record's own
position filter and central differences (the same path ÿ takes), so β = −θ1 (s_k, c_k) and the
reading's error is e = −(Σ β_sk sin + β_ck cos)/θ1 [m]. P: the peaks of the spatial periodogram
of the residual (as cogging), refined on the joint LS fit.

Compensation: none in the law. The error is in the reading: it is corrected where the
position is read (the drive's or interpolator's correction table of the sin/cos signals'
offsets, amplitudes and phase, the Heydemann correction), not by a force; the report gives the
amplitudes and phases to enter there.
"""

from __future__ import annotations

import math
from typing import ClassVar

import numpy as np

from motorctl.effects.periodic import (
    MAX_SPEED_GROWTH,
    MIN_PEAK_DROP,
    N_HARMONICS,
    PositionPeriodic,
    amplitudes_phases,
    fourier,
)


def reading_columns(y: np.ndarray, fs: float, fq: float, period: float) -> np.ndarray:
    """d²/dt² of sin, cos(2π k y / P), k ≤ N_HARMONICS, interleaved (N, 2·N_HARMONICS), through
    the position filter of :func:`motorctl.ident.idim.prepare` (zero-phase Butterworth of order 4
    at fq [Hz]) and two central differences [1/s²]; y: raw measured position (N,) [m], fs [Hz],
    period P [m]."""
    from scipy.signal import butter, filtfilt   # identification only
    ts = 1.0 / fs
    b, a = butter(4, fq / (fs / 2))
    e = filtfilt(b, a, fourier(y, period, N_HARMONICS), axis=0)
    return np.gradient(np.gradient(e, ts, axis=0), ts, axis=0)


#: signal periods searched [m]: magnetic scales (1-5 mm) and coarse optical ones; a 20 µm optical
#: scale's error is far above the position filter at any speed the record moves with
PERIOD_MIN_M = 1e-3
PERIOD_MAX_M = 0.01
#: relative step of the period grid, refined within one step on the exact columns (the joint
#: fit resolves P to about P/stroke: 0.5 % for 2 mm over 0.4 m)
GRID_STEP = 0.01


def analytic_columns(x, v, a, period: float, fq: float | None = None) -> np.ndarray:
    """d²/dt² sin, cos(2π k x / P), k ≤ N_HARMONICS, interleaved (N, 2·N_HARMONICS), from the
    state: d²/dt² sin(wx) = −w²ẋ² sin(wx) + w ẍ cos(wx); with ``fq`` [Hz] each harmonic is
    weighed by the zero-phase order-4 Butterworth's gain at its frequency at this speed,
    1/(1 + (k|ẋ|/(P fq))⁸) (the grid search's cheap stand-in for :func:`reading_columns`).
    x [m], v [m/s], a [m/s²]: (N,)."""
    f = fourier(x, period, N_HARMONICS)
    out = np.empty_like(f)
    for k in range(N_HARMONICS):
        w = 2.0 * math.pi * (k + 1) / period
        s, c = f[:, 2 * k], f[:, 2 * k + 1]
        g = 1.0 if fq is None else 1.0 / (1.0 + ((k + 1) * np.abs(v) / (period * fq)) ** 8)
        out[:, 2 * k] = g * (-w * w * v * v * s + w * a * c)
        out[:, 2 * k + 1] = g * (-w * w * v * v * c - w * a * s)
    return out


class EncoderInterpolationFamily(PositionPeriodic):
    name = "encoder_interpolation"
    plant_force = "none: reading y = x + Σ a_k sin(2πkx/P + φ_k)"
    example: ClassVar[dict] = {"encoder_interpolation_m": 3.0e-6, "encoder_signal_period_m": 2.0e-3}
    #: on a program whose moves are fast the error shows only at the moves' ends, where a
    #: force of position at the same period (cogging, a thrust ripple) can take nearly as much
    look_alike: ClassVar[tuple[str, ...]] = ("cogging", "force_ripple")
    size_options: ClassVar[tuple[str, ...]] = ("encoder_interpolation_m",)
    #: the effect is in the measurement: no plant force, the carriage moves as without it
    measurement: ClassVar[bool] = True
    #: the inertial term of a reading's error is not bounded by the input range
    force_bounded_by_input = False

    # simulator: the encoder model of the simulated driver (axis-level keys)
    def sim_config(self, axis_options):
        """(amplitude [m], signal period [m]) of the axis's interpolation error, or None when 0."""
        a = getattr(axis_options, "encoder_interpolation_m", 0.0)
        return (a, axis_options.encoder_signal_period_m) if a > 0 else None

    def plant_term(self, options, period_s):
        """None: the error is in the reading (the simulator's encoder model), not a force."""
        return None

    # identification
    def columns(self, h, p):
        """(N, 2·N_HARMONICS): ë of the reading's Fourier terms (:func:`reading_columns`); on
        signals without the raw position (:class:`~motorctl.effects.base.Signals`: a simulated
        fit's state) ë unfiltered, d²/dt² sin(wx) = −w²ẋ² sin(wx) + w ẍ cos(wx)."""
        y = getattr(p, "y", None)
        if y is not None and getattr(p, "fq", None):
            return reading_columns(y, p.fs, p.fq, h)
        return analytic_columns(p.x, p.v, p.a, h)

    def search(self, ctx, base, residual):
        return self._search(ctx, base)

    def _search(self, ctx, base):
        """P over a log grid from :data:`PERIOD_MIN_M` to :data:`PERIOD_MAX_M` (steps of
        :data:`GRID_STEP`) with cheap columns (ë of the decimated signals, unfiltered), then
        refined on the exact columns within one step (not when the best period lowers the SSE by
        less than MIN_PEAK_DROP: a noise minimum); the reading's error shows only where
        ẋ/P is below the position filter's cut-off (the moves' ends on a fast program), too
        few samples for the spatial periodogram cogging uses."""
        hi = min(PERIOD_MAX_M, ctx.stroke / 3.0)
        if hi <= PERIOD_MIN_M * 1.5 or ctx.moving.sum() < 50:
            return None
        grid = np.exp(np.arange(math.log(PERIOD_MIN_M), math.log(hi), GRID_STEP))
        p = ctx.p
        term, _ = ctx.best_over(self.name, grid, base,
                                cols_fn=lambda h: analytic_columns(p.x_d, p.v_d, p.a_d, h, p.fq))
        if ctx.sse(base + [term]) > (1.0 - MIN_PEAK_DROP) * ctx.sse(base):
            return term, None      # explains almost nothing at its best period: not refined
        term = ctx.best_between(self.name, term.h * (1.0 - GRID_STEP), term.h * (1.0 + GRID_STEP), base,
                                0.1 * GRID_STEP * term.h)
        note = None
        if term.h <= grid[1] or term.h >= grid[-2]:
            note = f"period {term.h:.4g} m at the edge of the searched range"
        return term, note

    def polish(self, ctx, term, others):
        """The whole grid again with the later effects in the model: before the stiction at
        rest is modelled the moves' ends, where the error shows, are its residual's."""
        found = self._search(ctx, others)
        return None if found is None else found[0]

    def parameters(self, h, beta, gain, fs, theta=None):
        """The reading's error e(x) = Σ a_k sin(2πkx/P + φ_k): a_k [m] = |β_k|/θ1 (θ1 = M/A1 of
        the same fit; without it the amplitudes of θ1·e in V·s²)."""
        th1 = float(theta[0]) if theta is not None and len(theta) and theta[0] > 0 else None
        amp, ph = amplitudes_phases(beta, 1.0)
        if th1 is None:
            return {"signal_period_m": float(h), "amplitudes_V_s2": [float(a) for a in amp],
                    "phases_rad": [float(p) for p in ph]}
        return {"signal_period_m": float(h), "amplitudes_m": [float(a / th1) for a in amp],
                "phases_rad": [float(p) for p in ph]}

    def plausible(self, ctx, term, beta, theta, base):
        """In its own columns (ë already carries ẋ²) the reading's error keeps its amplitude
        at every speed: the faster half of the moves must give it within a factor
        MAX_SPEED_GROWTH of the slower half. Not judged by direction: the error is the same
        both ways, but what the loop's unmodelled dynamics (a structural mode, the current
        loop) add to ë at 100-250 Hz differs with the speed profile of each direction."""
        growth = ctx.speed_growth(term, base, term.h)
        if math.isfinite(growth) and not 1.0 / MAX_SPEED_GROWTH <= growth <= MAX_SPEED_GROWTH:
            return [f"its amplitude changes with the speed (x{growth:.2f} from the slower to the faster half "
                    f"of the moves, outside [{1 / MAX_SPEED_GROWTH:g}, {MAX_SPEED_GROWTH:g}]): a reading's "
                    "error does not"]
        return []

    def shape(self, ctx, h, beta, gain):
        th1 = None
        xs = self.position_grid(ctx, h)
        y = fourier(xs, h, N_HARMONICS) @ beta
        if getattr(ctx, "final", None) is not None:
            th1 = float(ctx.final.fit.coef[0])
        if th1 and th1 > 0 and math.isfinite(th1):
            return xs, -y / th1, "position [m]", "reading error [m]"
        return xs, -y, "position [m]", "theta1 x reading error [V s^2]"


FAMILY = EncoderInterpolationFamily()
