"""Encoder interpolation (sub-divisional) error: the reading, not the carriage, is periodic.

Physical model (an incremental sin/cos scale read through an interpolator; Heidenhain,
"Interpolation and digitizing error" in the exposed linear encoders' catalogue; Renishaw,
"Sub-divisional error" application note): the measured position is

    y = x + e(x),   e(x) = Σ_k a_k sin(2π k x / P + φ_k)                          [m]

with P the scale's signal period (20 µm optical, 0.5-5 mm magnetic) and k = 1, 2 (offset and
amplitude mismatch of the two signals give the first harmonic, their phase error the second).
No force acts: the motor drives the true x, so u = θ1 ẍ + … = θ1 (ÿ − ë) + …, and the residual
of the paper's model on the measured y is −θ1 ë(y). Its signature differs from cogging's
(Σ A_k sin(2πkx/P), a force): ë = d²e/dt² grows with ẋ² (and ẍ), so the force it appears to
take is proportional to the squared speed, while e itself does not depend on the speed.

Its simulator option is the axis-level ``axes.NAME.driver.encoder_interpolation_m`` (amplitude
of the first harmonic) with ``encoder_signal_period_m`` (not an ``effects:`` entry; the encoder
model of ``motorctl_drivers.sim``).

Identification, in the reading first: where the carriage is fast enough that the error's
frequency |ẋ|/P is at least twice the position filter's cut-off fq, the zero-phase filter
removes it from the filtered position x and the loop (far slower) does not follow it, so the
raw minus the filtered reading, y − x, is e(y) itself [m]. P is found there (spatial
periodogram of y − x against y in bands of periods, each on the samples fast enough for the
band; bounded Brent on the LS fit), and e's coefficients with it; the error is named when it
explains at least MIN_READING_SHARE of y − x held out. Its force in the identification is then
one column, ë of that e(y) through the record's own position filter and central differences
(the same path ÿ takes): β = −θ1 when the input carries what the error puts into ÿ
(``force_share`` = −β/θ1, judged within FORCE_SHARE_RANGE). Periods the reading cannot show
(too few fast samples: a slow program) are searched on the force: columns d²/dt² of sin,
cos(2π k y / P), k ≤ 2, β = −θ1 (s_k, c_k), e = −(Σ β_sk sin + β_ck cos)/θ1 [m], P over a log
grid with cheap columns refined on the exact ones.

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
    N_PEAKS,
    PositionPeriodic,
    amplitudes_phases,
    peak_periods,
    fourier,
)


def _position_filter(fs: float, fq: float):
    """(b, a) of the position filter of :func:`motorctl.ident.idim.prepare`, applied zero-phase
    there: Butterworth of order 4 at fq [Hz], for a sample rate fs [Hz]."""
    from scipy.signal import butter             # identification only
    return butter(4, fq / (fs / 2))


def reading_columns(y: np.ndarray, fs: float, fq: float, period: float) -> np.ndarray:
    """d²/dt² of sin, cos(2π k y / P), k ≤ N_HARMONICS, interleaved (N, 2·N_HARMONICS), through
    the position filter of :func:`motorctl.ident.idim.prepare` (zero-phase Butterworth of order 4
    at fq [Hz]) and two central differences [1/s²]; y: raw measured position (N,) [m], fs [Hz],
    period P [m]."""
    from scipy.signal import filtfilt           # identification only
    ts = 1.0 / fs
    b, a = _position_filter(fs, fq)
    e = filtfilt(b, a, fourier(y, period, N_HARMONICS), axis=0)
    return np.gradient(np.gradient(e, ts, axis=0), ts, axis=0)


#: a force-side period whose first harmonic is below this share of its second is taken as
#: half as long (P's second harmonic is P/2's fundamental: the grid's SSE cannot tell them)
HALF_PERIOD_SHARE = 0.25
#: relative step of the period grid, refined within one step on the exact columns (the joint
#: fit resolves P to about P/stroke: 0.5 % for 2 mm over 0.4 m)
GRID_STEP = 0.01


#: the reading's error is fitted on the samples at which its first harmonic's frequency |ẋ|/P
#: is at least this many times the position filter's cut-off fq: there the filter removes it
#: from x (its zero-phase gain |H|² = 1/(1 + (f/fq)⁸) is 0.4 % at 2 fq), so the raw reading
#: minus the filtered one, y − x, is the error itself, and the loop (its bandwidth far below
#: fq) does not follow it
PASS_FACTOR = 2.0
#: ... and the speed must have stayed there for this many filter time constants 1/fq either
#: side (the zero-phase filter's transient where a move starts or ends)
SETTLE_FQ = 2.5
#: period bands searched on the reading: each band [P, BAND_RATIO·P] uses the samples fast
#: enough for its longest period
BAND_RATIO = 1.5
#: signal periods searched [m]: magnetic and inductive scales (0.5-5 mm) and coarse optical
#: ones; a 20 µm optical scale's error is far above the position filter at any speed the record
#: moves with. The lower end is two bands below 1 mm (0.444 mm), so the bands from 1 mm up keep
#: their edges: a ±2.5 µm error at 0.8 mm, not searched from 1 mm, was named a force ripple at
#: 3.07 mm (default plant, seed 13), and is found in the reading from here (2.45 µm)
PERIOD_MIN_M = 1e-3 / BAND_RATIO ** 2
PERIOD_MAX_M = 0.01
#: least samples (and signal periods travelled) of a band for its fit to be made
MIN_READING_SAMPLES = 400
MIN_PERIODS_TRAVELLED = 50.0
#: spatial periodogram step of the reading search (relative): the SSE's main lobe is about
#: P/travel wide (0.5 % for 2 mm over 0.4 m), so the peaks are refined on the exact fit
READING_STEP = 0.002
#: each band's periodogram reaches this many steps beyond its edges: a peak is a local maximum,
#: so a period on a band's edge (the search's lower end, or 1 mm, 1.5 mm between two bands) is
#: found only on a grid that extends past it (a ±1.5 µm error at exactly 1 mm was missed)
EDGE_STEPS = 5
#: periods no band can show at :data:`PASS_FACTOR` are searched on the reading again where the
#: error's frequency is at least this many times fq, its columns weighed by the share of the
#: error the zero-phase filter leaves in y − x, 1 − 1/(1 + (f/fq)⁸) (0.96 at 1.5 fq): a 4 mm
#: error at a 2 m/s cruise (500 Hz = 2 fq exactly, the band's longest period 5.06 mm is out of
#: reach) was left to the force side, where cogging took it
SLOW_PASS_FACTOR = 1.5
#: least share of y − x's power (on the fast samples) the reading's error must explain, held
#: out (2-fold over the identifier's blocks), for the reading to name it: a scale's error
#: explains nearly all of it (0.99 at ±3 µm, 0.96 at ±1.5 µm on the default plant), noise and
#: vibration that are not locked to the position explain nothing
MIN_READING_SHARE = 0.3
#: bounds of the force's share: the fitted coefficient of the reading's inertial column over
#: −θ1 (1: the force carries exactly the θ1·ë the reading's error puts into ÿ)
FORCE_SHARE_RANGE = (0.5, 2.0)


class ReadingFit(float):
    """The searched parameter h of a reading's error found in the reading: its float value is
    the signal period P [m]; ``coef`` (2·N_HARMONICS,) [m] are e(y)'s sin, cos coefficients,
    interleaved (e = Σ s_k sin(2πky/P) + c_k cos(2πky/P)); ``share`` the held-out share of the
    fast samples' y − x it explains, ``samples`` how many samples the fit used."""

    def __new__(cls, period: float, coef, share: float = math.nan, samples: int = 0):
        obj = super().__new__(cls, float(period))
        obj.coef = tuple(float(c) for c in coef)
        obj.share, obj.samples = float(share), int(samples)
        return obj

    def __reduce__(self):
        return ReadingFit, (float(self), self.coef, self.share, self.samples)

    def __repr__(self) -> str:
        return f"ReadingFit({float(self):.6g}, share {self.share:.3f})"


def fast_samples(p, period: float, factor: float = PASS_FACTOR) -> np.ndarray:
    """Boolean mask (N,) of the full-rate samples at which a reading's error of period
    ``period`` [m] is above the position filter (|ẋ| ≥ factor·fq·P, held for SETTLE_FQ/fq
    either side): there y − x is the error (see :data:`PASS_FACTOR`). p: a prepared record."""
    from scipy.ndimage import minimum_filter1d
    key = "_enc_slowest"
    sp = getattr(p, key, None)
    if sp is None:
        half = max(1, int(round(SETTLE_FQ * p.fs / p.fq)))
        sp = minimum_filter1d(np.abs(p.v), 2 * half + 1)
        setattr(p, key, sp)
    return sp >= factor * p.fq * period


def filter_gain(speed: np.ndarray, period: float, fq: float, k: int) -> np.ndarray:
    """Gain (M,) of the position filter, the zero-phase order-4 Butterworth at fq [Hz]
    (|H|² = 1/(1 + (f/fq)⁸), :func:`motorctl.ident.idim.prepare`), for harmonic k ≥ 1 of a
    reading's error of period ``period`` [m] at the speeds ``speed`` (M,) [m/s] (f = k|ẋ|/P):
    1/(1 + (k|ẋ|/(P fq))⁸)."""
    return 1.0 / (1.0 + (k * np.abs(speed) / (period * fq)) ** 8)


def passed(speed: np.ndarray, period: float, fq: float) -> np.ndarray:
    """(M, 2·N_HARMONICS): the share of each harmonic k of a reading's error of period
    ``period`` [m] that the position filter removes from the filtered x, so leaves in y − x, at
    the speeds ``speed`` (M,) [m/s]: 1 − :func:`filter_gain`, for its sin and cos columns."""
    out = np.empty((speed.shape[0], 2 * N_HARMONICS))
    for k in range(N_HARMONICS):
        out[:, 2 * k] = out[:, 2 * k + 1] = 1.0 - filter_gain(speed, period, fq, k + 1)
    return out


def reading_fit(y: np.ndarray, r: np.ndarray, period: float, fold=None, speed=None,
                fq: float | None = None) -> tuple[np.ndarray, float, float]:
    """LS fit of r (M,) [m] (y − x on fast samples) by a constant and sin, cos(2πky/P), k ≤
    N_HARMONICS, at the readings y (M,) [m]; with ``speed`` (M,) [m/s] and ``fq`` [Hz] each
    column weighed by the share of the error y − x keeps there (:func:`passed`). Returns (coef
    (2·N_HARMONICS,) [m], SSE [m²], held-out share explained): the last over the two folds of
    ``fold`` (M,) (0/1), NaN without it."""
    cols = fourier(y, period, N_HARMONICS)
    if speed is not None:
        cols = cols * passed(speed, period, fq)
    f = np.column_stack([cols, np.ones_like(y)])
    coef = np.linalg.lstsq(f, r, rcond=None)[0]
    res = r - f @ coef
    share = math.nan
    if fold is not None:
        sse, tot = 0.0, 0.0
        for k in (0, 1):
            tr, te = fold == k, fold != k
            if tr.sum() < 4 * f.shape[1] or te.sum() < 4 * f.shape[1]:
                return coef[:-1], float(res @ res), math.nan
            c = np.linalg.lstsq(f[tr], r[tr], rcond=None)[0]
            e = r[te] - f[te] @ c
            d = r[te] - r[tr].mean()
            sse += float(e @ e)
            tot += float(d @ d)
        share = 1.0 - sse / tot if tot > 0 else math.nan
    return coef[:-1], float(res @ res), share


def carriage_motion(u: np.ndarray, fs: float, fq: float, theta1: float) -> np.ndarray:
    """The carriage's own position above the position filter (N,) [m]: (1 − |H|²) of the
    rigid-body motion ẍ = u/θ1 the input u (N,) [V] drives (θ1 = M/A1 [V·s²/m], paper eq. 9),
    H the position filter of :func:`motorctl.ident.idim.prepare` (zero-phase Butterworth of
    order 4 at fq [Hz]), in the frequency domain (−U/(θ1 ω²); 1 − |H|² falls as ω⁸ below fq, so
    the double integral's low frequencies do not enter). A servo that reads y = x + e(x) chases
    the error e above its bandwidth in part: y − x then holds e and that motion (20 s logs, 2 mm:
    the first harmonic on the rigid plant +11.0 % at ±1.5 µm, +8.6 % at ±3 µm without it, +2.8 %
    and +0.5 % with it; on the default plant at ±3 µm +3.9 % and −0.5 %)."""
    from scipy.signal import freqz              # identification only
    n = len(u)
    w = 2.0 * math.pi * np.fft.rfftfreq(n, 1.0 / fs)
    _, h = freqz(*_position_filter(fs, fq), worN=w / fs)     # rad/sample
    high = 1.0 - np.abs(h) ** 2
    spec = np.fft.rfft(u)
    out = np.zeros_like(spec)
    out[1:] = -spec[1:] * high[1:] / (theta1 * w[1:] ** 2)
    return np.fft.irfft(out, n)


def search_reading(p, lo: float, hi: float, fold_of=None, carriage=None) -> tuple[ReadingFit | None, list]:
    """The reading's error of period P in [lo, hi] [m] found in the reading itself: over bands
    [P, BAND_RATIO·P] (each grid :data:`EDGE_STEPS` steps wider), the fast samples of the band's
    longest period (:func:`fast_samples`), the spatial periodogram of y − x against y at
    :data:`READING_STEP` steps, its :data:`~motorctl.effects.periodic.N_PEAKS` highest peaks
    refined by bounded Brent on the fit's SSE (:func:`reading_fit`). A fit whose first harmonic
    is below :data:`HALF_PERIOD_SHARE` of its second is the error of period P/2 (P's second
    harmonic is its fundamental) and is fitted there. The bands too slow at
    :data:`PASS_FACTOR` are searched again at :data:`SLOW_PASS_FACTOR`, the columns weighed by
    what the filter leaves (:func:`passed`). p: a prepared record (raw reading y, filtered x,
    v, fs, fq). fold_of: a function of a full-rate mask giving the held-out fold (0/1) of its
    samples, or None (no held-out share). carriage: the carriage's own motion above the filter
    (N,) [m] (:func:`carriage_motion`), taken from y − x; None: none.

    Returns:
        (the best fit by held-out share (or SSE share) or None, the (lo, hi) period ranges
        [m] that no band could search: too few fast samples).
    """
    r_all = p.y - p.x if carriage is None else p.y - p.x - carriage
    best, blind = _search_bands(p, r_all, lo, hi, fold_of, PASS_FACTOR)
    slow_blind = []
    for a, b in blind:
        found, still = _search_bands(p, r_all, a, b, fold_of, SLOW_PASS_FACTOR)
        slow_blind += still
        if found is not None and (best is None or found.share > best.share):
            best = found
    return best, slow_blind


def _search_bands(p, r_all, lo: float, hi: float, fold_of, factor: float) -> tuple[ReadingFit | None, list]:
    """:func:`search_reading`'s bands of [lo, hi] [m] with the samples at ``factor``·fq·P, on
    the reading's part r_all (N,) [m]; below :data:`PASS_FACTOR` the columns are weighed by
    :func:`passed`."""
    from scipy.optimize import minimize_scalar

    best, blind = None, []
    edge = math.exp(EDGE_STEPS * READING_STEP)
    a = lo
    while a < hi * (1.0 - 1e-9):
        b = min(hi, a * BAND_RATIO)
        a_x, b_x = a / edge, b * edge
        sel = fast_samples(p, b_x, factor)
        n = int(sel.sum())
        travel = float(np.sum(np.abs(np.diff(p.x)[sel[1:]]))) if n else 0.0
        if n < MIN_READING_SAMPLES or travel < MIN_PERIODS_TRAVELLED * b_x:
            blind.append((a, b))
            a = b
            continue
        y, r = p.y[sel], r_all[sel]
        sp = (p.v[sel], p.fq) if factor < PASS_FACTOR else (None, None)
        grid = np.exp(np.arange(math.log(a_x), math.log(b_x), READING_STEP))
        fold = None if fold_of is None else fold_of(sel)
        span = np.ptp(y)
        d = r - r.mean()

        def refined(pk, lo_b, hi_b):
            half = max(READING_STEP, pk / max(span, pk)) * pk
            res = minimize_scalar(lambda h: reading_fit(y, r, float(h), None, *sp)[1], method="bounded",
                                  bounds=(max(lo_b, pk - half), min(hi_b, pk + half)),
                                  options={"xatol": 0.02 * READING_STEP * pk})
            coef, sse, share = reading_fit(y, r, float(res.x), fold, *sp)
            return float(res.x), coef, (share if fold is not None else 1.0 - sse / float(d @ d))
        for pk in peak_periods(y, r, grid, N_PEAKS):
            per, coef, score = refined(pk, a_x, b_x)
            if np.hypot(*coef[:2]) < HALF_PERIOD_SHARE * np.hypot(*coef[2:4]) and per / 2.0 >= lo / edge:
                per, coef, score = refined(per / 2.0, per / 2.0 / edge, per / 2.0 * edge)
            if best is None or score > best.share:
                best = ReadingFit(per, coef, score, n)
        a = b
    return best, blind


def analytic_columns(x, v, a, period: float, fq: float | None = None) -> np.ndarray:
    """d²/dt² sin, cos(2π k x / P), k ≤ N_HARMONICS, interleaved (N, 2·N_HARMONICS), from the
    state: d²/dt² sin(wx) = −w²ẋ² sin(wx) + w ẍ cos(wx); with ``fq`` [Hz] each harmonic is
    weighed by the position filter's gain at its frequency at this speed (:func:`filter_gain`;
    the grid search's cheap stand-in for :func:`reading_columns`).
    x [m], v [m/s], a [m/s²]: (N,)."""
    f = fourier(x, period, N_HARMONICS)
    out = np.empty_like(f)
    for k in range(N_HARMONICS):
        w = 2.0 * math.pi * (k + 1) / period
        s, c = f[:, 2 * k], f[:, 2 * k + 1]
        g = 1.0 if fq is None else filter_gain(v, period, fq, k + 1)
        out[:, 2 * k] = g * (-w * w * v * v * s + w * a * c)
        out[:, 2 * k + 1] = g * (-w * w * v * v * c - w * a * s)
    return out


class EncoderInterpolationFamily(PositionPeriodic):
    name = "encoder_interpolation"
    search_cost = 0.3
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
        """The force the reading's error puts into the fit: ÿ of the reading carries ë, so
        u − θ1·a leaves −θ1·ë. With h a :class:`ReadingFit` (the error found in the reading)
        one column (N, 1), ë of its e(y) through the record's position filter
        (:func:`reading_columns` @ coef, β ≈ −θ1); with a plain period P [m] (the force-side
        search of a record too slow for the reading) (N, 2·N_HARMONICS), β = −θ1 (s_k, c_k).
        On signals without the raw position (:class:`~motorctl.effects.base.Signals`: a
        simulated fit's state) ë unfiltered, d²/dt² sin(wx) = −w²ẋ² sin(wx) + w ẍ cos(wx)."""
        y = getattr(p, "y", None)
        if y is not None and getattr(p, "fq", None):
            cols = reading_columns(y, p.fs, p.fq, h)
        else:
            cols = analytic_columns(p.x, p.v, p.a, h)
        if isinstance(h, ReadingFit):
            return cols @ np.asarray(h.coef)[:, None]
        return cols

    def search(self, ctx, base, residual):
        """The error in the reading itself first (:meth:`reading`): y − x on the samples fast
        enough for the error to be above the position filter. Named there (a
        :class:`ReadingFit` term, its force column judged by the selection) when it explains
        at least :data:`MIN_READING_SHARE` of y − x held out; nothing when it explains less
        and every period could be searched there. Periods whose band had too few fast samples
        (a slow program) are searched on the force (:meth:`_search`)."""
        fit, blind = self.reading(ctx)
        if fit is not None and fit.share >= MIN_READING_SHARE:
            return ctx.term(self.name, fit), None
        if not blind:
            return None
        return self._search(ctx, base, blind)

    @staticmethod
    def sized_in_reading(term) -> bool:
        """True for a term found in the reading (a :class:`ReadingFit`): its size was judged
        there (:data:`MIN_READING_SHARE` of y − x), so the identifier does not judge its force
        against the RMS input (at ±1.5 µm on the default plant the force is 1.3 N, below 1 %
        of it, and its held-out gain 16 %)."""
        return isinstance(term.h, ReadingFit)

    def reading(self, ctx) -> tuple[ReadingFit | None, list]:
        """:func:`search_reading` over :data:`PERIOD_MIN_M` … min(:data:`PERIOD_MAX_M`,
        stroke/3) on the identifier's record, the held-out share over its blocks' folds, the
        carriage's own motion the input drives (:func:`carriage_motion`, θ1 of the nominal fit)
        taken from y − x; once per identifier (the reading does not depend on the effects)."""
        cached = ctx.memo.get("encoder_reading")
        if cached is not None:
            return cached
        hi = min(PERIOD_MAX_M, ctx.stroke / 3.0)
        if hi <= PERIOD_MIN_M * 1.5:
            out = (None, [])
        else:
            p = ctx.p
            fold = getattr(ctx, "fold", None)

            def fold_of(sel):
                if fold is None:
                    return None
                j = np.flatnonzero(sel) // p.nd - p.keep.start
                return fold[np.clip(j, 0, len(fold) - 1)]
            theta1 = float(ctx.evaluate([]).fit.coef[0])
            carriage = carriage_motion(ctx.delayed_u(ctx.zoh), p.fs, p.fq, theta1) if theta1 > 0 else None
            out = search_reading(p, PERIOD_MIN_M, hi, fold_of, carriage)
        ctx.memo["encoder_reading"] = out
        return out

    def unnamed_evidence(self, ctx):
        """The reading's error found in y − x (:meth:`reading`, at least
        :data:`MIN_READING_SHARE` of it held out) that the selection did not name, because its
        force did not confirm it (too fast for the position filter and the loop to pass: the
        input carries next to nothing of θ1·ë) or the input carries another force: its period
        and amplitudes, for the verdict. None when the reading shows none."""
        fit, _ = self.reading(ctx)
        if fit is None or not fit.share >= MIN_READING_SHARE:
            return None
        amp, _ = amplitudes_phases(-np.asarray(fit.coef), 1.0)
        harm = ", ".join(f"{1e6 * a:.2f}" for a in amp)
        return (f"the reading carries a periodic error of {harm} um (harmonics 1..{len(amp)}) at a signal period "
                f"of {1e3 * float(fit):.4g} mm ({100 * fit.share:.0f} % of the raw minus the filtered position "
                "held out) that the force model does not name: an encoder interpolation error that the input does "
                "not confirm, to be corrected where the position is read")

    def _search(self, ctx, base, ranges):
        """P over a log grid in ``ranges`` ((lo, hi) [m], the periods the reading could not
        search; steps of :data:`GRID_STEP`) with cheap columns (ë of the decimated signals,
        weighed by the filter's gain), then refined on the exact columns within one step (not
        when the best period lowers the SSE by less than MIN_PEAK_DROP: a noise minimum); the
        reading's error then shows in the force only where ẋ/P is below the position filter's
        cut-off."""
        if ctx.moving.sum() < 50:
            return None
        grid = np.concatenate([np.exp(np.arange(math.log(a), math.log(b), GRID_STEP)) for a, b in ranges])
        if grid.size < 3:
            return None
        p = ctx.p
        cheap = ctx.memo.setdefault("encoder_cheap", {})     # the same grid at every step

        def cols(h):
            c = cheap.get(h)
            if c is None:
                c = cheap[h] = analytic_columns(p.x_d, p.v_d, p.a_d, h, p.fq)
            return c
        term, _ = ctx.best_over(self.name, grid, base, cols_fn=cols)
        if ctx.sse(base + [term]) > (1.0 - MIN_PEAK_DROP) * ctx.sse(base):
            return term, None      # explains almost nothing at its best period: not refined
        term = ctx.best_between(self.name, term.h * (1.0 - GRID_STEP), term.h * (1.0 + GRID_STEP), base,
                                0.1 * GRID_STEP * term.h)
        beta = ctx.evaluate(base + [term]).fit.coef[-2 * N_HARMONICS:]
        if term.h / 2.0 >= grid[0] and np.hypot(*beta[:2]) < HALF_PERIOD_SHARE * np.hypot(*beta[2:4]):
            # no first harmonic: the error of period P/2 (its fundamental), which P's second
            # harmonic fits as well
            term = ctx.best_between(self.name, term.h / 2.0 * (1.0 - GRID_STEP), term.h / 2.0 * (1.0 + GRID_STEP),
                                    base, 0.05 * GRID_STEP * term.h)
        note = None
        if term.h <= grid[1] or term.h >= grid[-2]:
            note = f"period {term.h:.4g} m at the edge of the searched range"
        return term, note

    def polish(self, ctx, term, others):
        """A force-side term: the whole grid again with the later effects in the model (before
        the stiction at rest is modelled the moves' ends, where the error shows, are its
        residual's). A term found in the reading does not depend on the force model: kept."""
        if isinstance(term.h, ReadingFit):
            return None
        found = self.search(ctx, others, None)
        return None if found is None else found[0]

    def parameters(self, h, beta, gain, fs, theta=None):
        """The reading's error e(x) = Σ a_k sin(2πkx/P + φ_k), amplitudes_m a_k [m], phases_rad
        φ_k, signal_period_m P. Found in the reading (a :class:`ReadingFit`): a_k, φ_k from its
        fit of y − x, ``reading_share`` the held-out share of y − x it explains and
        ``force_share`` = −β/θ1, how much of the inertial force θ1·ë the input carries (1: all).
        Found on the force: a_k = |β_k|/θ1 (θ1 = M/A1 of the same fit; without it the
        amplitudes of θ1·e in V·s²)."""
        th1 = float(theta[0]) if theta is not None and len(theta) and theta[0] > 0 else None
        if isinstance(h, ReadingFit):
            amp, ph = amplitudes_phases(-np.asarray(h.coef), 1.0)
            out = {"signal_period_m": float(h), "amplitudes_m": [float(a) for a in amp],
                   "phases_rad": [float(p) for p in ph], "reading_share": h.share}
            if th1 is not None:
                out["force_share"] = float(-beta[0] / th1)
            return out
        amp, ph = amplitudes_phases(beta, 1.0)
        if th1 is None:
            return {"signal_period_m": float(h), "amplitudes_V_s2": [float(a) for a in amp],
                    "phases_rad": [float(p) for p in ph]}
        return {"signal_period_m": float(h), "amplitudes_m": [float(a / th1) for a in amp],
                "phases_rad": [float(p) for p in ph]}

    def plausible(self, ctx, term, beta, theta, base):
        """Found in the reading: the input must carry the inertial force of the reading's
        error, −β/θ1 within :data:`FORCE_SHARE_RANGE` (ÿ of the reading carries ë whatever the
        loop does, so u − θ1·a leaves −θ1·ë): a force of its own at that period (cogging)
        would need another β. Found on the force: in its own columns (ë already carries ẋ²)
        the error keeps its amplitude at every speed: the faster half of the moves must give
        it within a factor MAX_SPEED_GROWTH of the slower half (not judged by direction: what
        the loop's unmodelled dynamics add to ë at 100-250 Hz differs with each direction's
        speed profile)."""
        if isinstance(term.h, ReadingFit):
            share = -float(beta[0]) / float(theta[0]) if theta[0] > 0 else math.nan
            lo, hi = FORCE_SHARE_RANGE
            if not lo <= share <= hi:
                return [f"the input carries {share:.2f} of the inertial force theta1*e'' of the error found in "
                        f"the reading (outside [{lo:g}, {hi:g}]): not the reading's error alone"]
            return []
        growth = ctx.speed_growth(term, base, term.h)
        if math.isfinite(growth) and not 1.0 / MAX_SPEED_GROWTH <= growth <= MAX_SPEED_GROWTH:
            return [f"its amplitude changes with the speed (x{growth:.2f} from the slower to the faster half "
                    f"of the moves, outside [{1 / MAX_SPEED_GROWTH:g}, {MAX_SPEED_GROWTH:g}]): a reading's "
                    "error does not"]
        return []

    def reading_error(self, h, beta, theta1, x):
        """e(x) [m] (N,) at the carriage's positions x [m] (N,): found in the reading (a
        :class:`ReadingFit`), its own fit of y − x; found on the force, −Cβ/θ1 (C the sin, cos
        columns of the period h [m], β (2·N_HARMONICS,), θ1 > 0 [V·s²/m])."""
        if isinstance(h, ReadingFit):
            return fourier(x, h, N_HARMONICS) @ np.asarray(h.coef)
        return -(fourier(x, h, N_HARMONICS) @ np.asarray(beta)) / theta1

    def shape(self, ctx, h, beta, gain):
        """The reading's error e(x) [m] over at most four periods (:meth:`reading_error`; on the
        force without θ1: θ1·e in V·s²)."""
        th1 = None
        xs = self.position_grid(ctx, h)
        if not isinstance(h, ReadingFit) and getattr(ctx, "final", None) is not None:
            th1 = float(ctx.final.fit.coef[0])
        if isinstance(h, ReadingFit) or (th1 and th1 > 0 and math.isfinite(th1)):
            return xs, self.reading_error(h, beta, th1, xs), "position [m]", "reading error [m]"
        return xs, -(fourier(xs, h, N_HARMONICS) @ beta), "position [m]", "theta1 x reading error [V s^2]"


FAMILY = EncoderInterpolationFamily()
