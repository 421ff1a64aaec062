"""Input delay: the drive applies the commanded voltage τ later (transport delay of the drive's
input stage or fieldbus).

Physical model: u_applied(t) = u(t − τ). Its simulator option is the axis-level
``axes.NAME.driver.input_delay_s`` (not an ``effects:`` entry): τ = (n + f)·Ts applies, over each
period, the mean of the delayed held input, (1 − f)·u[k − n] + f·u[k − n − 1]
(:func:`delay_line`: the same impulse per period as the switch f·Ts into it, and the same phase
−ωτ in the band the loop controls). Identification: no columns; the
regression target becomes u(t − τ), τ from 0 to 5 ms in whole samples, then a 0.05-sample grid
within a sample of the best (FFT fractional shift of the decimated input), fitted on the samples
in motion (:meth:`InputDelayFamily.in_motion`); refused when the delays the phase of two
frequency bands say differ (:meth:`InputDelayFamily.not_transport`: a transport delay is a phase
−ωτ at every frequency, a load held with play lags only part of the force). The amplifier's
current loop the run log's config declares (``current_loop_hz``, ``current_loop_delay_s`` of the
axis's driver) is part of the nominal model, every input column filtered through it
(:func:`current_loop_filter`; :meth:`motorctl.ident.columns.Columns.input_columns`): a
first-order lag is a delay of 1/(2π f_c) in the band the fit sees, but not in the few ms after
each start, where a pure delay fitted for it left a difference the friction at low speed took up.
What is found is the lag beyond the hold and the declared loop: the report's ``delay_s``;
``total_delay_s`` adds the declared loop's lag (:func:`amplifier_lag`). Without a declared
loop (a CSV/MAT record) the found delay is all of the lag beyond the hold, a current loop
included. Compensation (not an additive d̂_eff, a
:class:`~motorctl.effects.base.CompHook`): the law predicts over τ, i.e. evaluates its
desired-compensation part v_a1 (eq. 13) on the desired trajectory at t + τ (the servo loop passes
that sample, :meth:`motorctl.control.base.Controller.preview`), and the estimator pairs each
velocity sample with the input applied over it, u[k − 1 − round(τ/Ts)].
"""

from __future__ import annotations

import math
from typing import Annotated, ClassVar

import numpy as np
from pydantic import Field

from motorctl.effects.base import CompHook, EffectFamily, PlantTerm
from motorctl.schema import StrictModel


def delay_line(n: int, frac: float = 0.0):
    """A delay of n + frac periods (n ≥ 0 whole, 0 ≤ frac < 1, n + frac > 0): ``delay(u) -> ``
    (1 − frac)·(u of n calls ago) + frac·(u of n + 1 calls ago) (0.0 before that), one call per
    period: the mean over the period of a held input delayed by (n + frac) periods. Pure floats
    (a ring buffer built once)."""
    if n < 0 or not 0.0 <= frac < 1.0 or n + frac <= 0.0:
        raise ValueError(f"delay of {n} + {frac} periods: needs n >= 0, 0 <= frac < 1, n + frac > 0")
    if frac == 0.0:
        buf = [0.0] * n
        i = 0

        def delay(u):
            nonlocal i
            out = buf[i]
            buf[i] = u
            i = (i + 1) % n
            return out
        return delay
    size = n + 2
    ring = [0.0] * size
    j = 0

    def delay_frac(u):
        nonlocal j
        ring[j] = u                                  # ring[j] = u now, ring[j - m] = u m calls ago
        out = (1.0 - frac) * ring[(j - n) % size] + frac * ring[(j - n - 1) % size]
        j = (j + 1) % size
        return out
    return delay_frac


#: a delay within this many periods of a whole number is that whole number (τ/Ts of a value
#: typed in seconds: 0.0006 / 0.0002 = 2.9999999999999996)
WHOLE_TOLERANCE = 1e-6


#: a total input delay (hold + found) within this distance of half a sample is the zero-order
#: hold of a sampled-data loop, not an effect [samples] (re-exported as motorctl.ident.select.HOLD_TOLERANCE)
HOLD_TOLERANCE = 0.15
#: the delays compared with the hold in these units of a sample (:func:`is_hold`): the grids'
#: steps of 0.05 land on whole hundredths, which binary floats do not (0.65 - 0.5 =
#: 0.15000000000000002)
HOLD_RESOLUTION = 1e-6


def is_hold(delay_samples: float) -> bool:
    """True when an input-to-acceleration delay [samples] is the half sample of a zero-order hold
    (a sampled-data loop: u written after y is read and held over the period), within
    :data:`HOLD_TOLERANCE` inclusive; compared in whole units of :data:`HOLD_RESOLUTION` so that a
    delay on the tolerance's edge (0.35 or 0.65) is the hold whichever side of 0.5 it lies."""
    return round(abs(float(delay_samples) - 0.5) / HOLD_RESOLUTION) <= round(HOLD_TOLERANCE / HOLD_RESOLUTION)
#: lowest frequency of the bands a delay's phase is compared on [Hz] (below: the program's own
#: moves, whose phase hardly depends on τ)
BAND_LOW_HZ = 15.0
#: largest difference of the delays the two bands say [samples] (default plant, 20 s: clean
#: 0.1, input delays of 0.2 and 0.6 ms 0.0-0.3; a load with 50 µm of play 1.6, 200 µm 6.3)
MAX_BAND_SPREAD = 0.6
#: step of the bands' delay grids [samples] (the minimum refined by a parabola)
BAND_STEP = 0.5
#: the delay is fitted on the samples moving faster than this [m/s] (:meth:`InputDelayFamily.
#: in_motion`): above the band a static friction holds in (0.01-1 mm/s), low enough not to
#: select the samples by the motion the noise gives them (20 s logs, default plant: 0.3 ms ->
#: 0.305, 0.6 ms -> 0.633 ms, against 0.331 and 0.656 on all samples; 2 % of the top speed
#: gave a 1.5-sample delay as 1.32 on a loop that dithers at rest)
V_HELD = 1e-3
#: step of the grid that refines the delay within a sample of the whole-sample best [samples]
FINE_STEP = 0.05


def amplifier_loop(header: dict, axis: str) -> tuple[float, float]:
    """(f_c [Hz], d_c [s]): the current loop a run log's config declares for ``axis``
    (``axes.NAME.driver``: ``current_loop_hz``, ``current_loop_delay_s``); (0, 0) when none is
    declared. Raises nothing: a missing or malformed entry counts as none."""
    drv = header
    for key in ("config", "axes", axis, "driver"):
        drv = drv.get(key) if isinstance(drv, dict) else None
    if not isinstance(drv, dict):
        return 0.0, 0.0
    fc, dc = drv.get("current_loop_hz") or 0.0, drv.get("current_loop_delay_s") or 0.0
    if not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v >= 0
               for v in (fc, dc)):
        return 0.0, 0.0
    return float(fc), float(dc)


def loop_lag(fc_hz: float, dc_s: float) -> float:
    """The lag [s] of a first-order current loop of bandwidth f_c [Hz] (0: none) behind a
    switching delay d_c [s], d_c + 1/(2π f_c), in the band identify fits (:func:`amplifier_lag`)."""
    return (1.0 / (2.0 * math.pi * fc_hz) if fc_hz > 0 else 0.0) + dc_s


def amplifier_lag(header: dict, axis: str) -> tuple[float, str]:
    """The input-to-force lag [s] of the amplifier's current loop that a run log's config declares
    for ``axis`` (:func:`amplifier_loop`: f_c, d_c), d_c + 1/(2π f_c), with a phrase saying so
    ("" when none is declared).

    A first-order current loop lags by atan(ω/(2π f_c)), which is ω/(2π f_c) within 0.3 % up to
    f_c/10 (100 Hz for 1 kHz: the band identify fits), so below that it is a delay of 1/(2π f_c).
    Raises nothing: a missing or malformed entry counts as none.
    """
    fc, dc = amplifier_loop(header, axis)
    lag = loop_lag(fc, dc)
    if lag <= 0.0:
        return 0.0, ""
    parts = ([f"{fc:g} Hz current loop"] if fc > 0 else []) + ([f"{dc * 1e6:g} us delay"] if dc > 0 else [])
    return lag, f"the amplifier's {' + '.join(parts)} the config declares: {lag * 1e6:.0f} us"


def delayed(cols: np.ndarray, delay: float) -> np.ndarray:
    """Full-rate columns (N,) or (N, k) ``delay`` samples later [samples] (a fraction by linear
    interpolation, the first/last value held beyond the ends); ``cols`` itself for 0."""
    if delay == 0:
        return cols
    n = np.arange(len(cols), dtype=float) - delay
    if cols.ndim == 1:
        return np.interp(n, np.arange(len(cols)), cols)
    return np.column_stack([np.interp(n, np.arange(len(cols)), c) for c in cols.T])


def held_lag_response(fc_hz: float, dc_s: float, fs: float) -> tuple[np.ndarray, float]:
    """The acceleration a sampled-data loop's central differences see of one held input sample
    through a current loop: impulse response h (J + 1,) [-] and the ratio r [-] of its
    geometric tail (h[j + 1] = r h[j] for j ≥ J; r = 0: none).

    The input u_k is held over [t_k, t_k + Ts) (zero-order hold), delayed by d_c [s]
    (``current_loop_delay_s``: a switching instant, any value) and lagged by a first-order loop
    of bandwidth f_c [Hz] (time constant τ = 1/(2π f_c); 0: no lag), as the simulator applies
    it (exact under the hold). The central difference (x_{k+1} − 2 x_k + x_{k−1})/Ts² of the
    position the force F moves is the force weighted by a triangle of ±Ts about t_k, so with
    Q(t) the position response to a unit step of u (Q(w) = w²/2 − τ w + τ²(1 − e^{−w/τ}),
    w = t − d_c ≥ 0) and X(t) = Q(t) − Q(t − Ts) that to one held sample,
    h_j = (X((j+1)Ts) − 2 X(j Ts) + X((j−1)Ts)) / Ts². With f_c = d_c = 0 it is
    (0.5, 0.5): the hold's half sample (:data:`HOLD_TOLERANCE`).
    """
    ts = 1.0 / fs
    tau = 1.0 / (2.0 * math.pi * fc_hz) if fc_hz > 0 else 0.0

    def q(t):
        w = np.maximum(np.asarray(t, dtype=float) - dc_s, 0.0)
        if tau == 0.0:
            return 0.5 * w * w
        return 0.5 * w * w - tau * w + tau * tau * -np.expm1(-w / tau)

    n = int(math.ceil(dc_s / ts - 1e-9)) + 2
    j = np.arange(n + 1, dtype=float)

    def x(t):
        return q(t) - q(t - ts)
    h = (x((j + 1) * ts) - 2.0 * x(j * ts) + x((j - 1) * ts)) / (ts * ts)
    return h, (math.exp(-ts / tau) if tau > 0 else 0.0)


def current_loop_filter(fc_hz: float, dc_s: float, fs: float) -> tuple[np.ndarray, np.ndarray]:
    """(b, a) of the recursive filter (:func:`scipy.signal.lfilter`) whose impulse response is
    :func:`held_lag_response`: the input the acceleration sees, hold and current loop included,
    from the logged input. Exact: b_0 = h_0, b_j = h_j − r h_{j−1}, a = (1, −r)."""
    h, r = held_lag_response(fc_hz, dc_s, fs)
    b = np.concatenate([h[:1], h[1:] - r * h[:-1]])
    return b, np.array([1.0, -r])


def parabolic_min(grid: np.ndarray, sses: np.ndarray) -> float:
    """The grid value (K,) of the least SSE (K,), refined by the parabola through the SSEs of
    it and its two neighbours (not at the grid's ends, nor where they do not curve up)."""
    i = int(np.argmin(sses))
    d = float(grid[i])
    if 0 < i < len(grid) - 1:
        s0, s1, s2 = sses[i - 1], sses[i], sses[i + 1]
        den = s0 - 2 * s1 + s2
        if den > 0:
            d += 0.5 * (s0 - s2) / den * float(grid[1] - grid[0])
    return d


class FoundDelay(float):
    """A found input delay: its float value is the lag beyond the hold and the modelled current
    loop [samples] (the target's shift); ``amplifier_lag`` [samples] the lag of the amplifier's
    declared current loop the nominal model holds besides it (:func:`amplifier_lag`; 0: none
    declared); ``modelled``: the nominal model holds that lag (the identifier's
    ``current_loop``), else the float value includes it (the lag found as a delay)."""

    def __new__(cls, samples: float, amplifier_lag: float = 0.0, modelled: bool = False):
        obj = super().__new__(cls, float(samples))
        obj.amplifier_lag = float(amplifier_lag)
        obj.modelled = bool(modelled)
        return obj

    def beyond_hold(self) -> float:
        """All of the lag beyond the hold [samples]: the found delay, plus the declared loop's
        lag when the model holds it."""
        return float(self) + (self.amplifier_lag if self.modelled else 0.0)


class DelayComp(StrictModel):
    """Delay compensation, ``axes.NAME.controller.compensation.input_delay``: delay_s, the
    input delay τ [s] beyond the loop's own zero-order hold (0 … 0.1 s) the law predicts over
    (identify writes the total lag it found, the amplifier's current loop included)."""

    delay_s: Annotated[float, Field(ge=0.0, le=0.1)]


class InputDelayFamily(EffectFamily):
    name = "input_delay"
    search_cost = 0.1
    plant_force = "u acts τ later"
    searched = "delay τ [samples]"
    example: ClassVar[dict] = {"input_delay_s": 0.0006}
    size_options: ClassVar[tuple[str, ...]] = ("input_delay_s",)
    shifts_input = True
    searched_on_current_loop = True
    hook_options = DelayComp

    # simulator
    def sim_config(self, axis_options):
        """``input_delay_s`` [s] of the axis, or None when 0."""
        d = axis_options.input_delay_s
        return d if d > 0 else None

    def plant_term(self, delay_s, period_s):
        """Delay line of delay_s / period_s periods, the fraction as :func:`delay_line`'s mean
        over the period (None when that is 0)."""
        q = delay_s / period_s
        n = round(q)
        if abs(q - n) > WHOLE_TOLERANCE:
            n = math.floor(q)
            return PlantTerm(input=delay_line(n, q - n))
        return PlantTerm(input=delay_line(n)) if n > 0 else None

    # identification
    def columns(self, h, p):
        """None: the family shifts the target instead of adding columns."""
        return

    def input_shift(self, h):
        return float(h) if h else 0.0

    def search(self, ctx, base, residual):
        """The delay d [samples] beyond the hold (and the declared current loop the context
        models: its ``modelled_lag`` [samples]) of least SSE on the samples in motion
        (:meth:`in_motion`): whole samples to 5 ms, then :meth:`refine`; the term's h is a
        :class:`FoundDelay` carrying the modelled loop's lag."""
        p = ctx.p
        modelled = float(getattr(ctx, "modelled_lag", 0.0) or 0.0)
        if modelled > 0:
            lag = modelled
        else:
            rec = getattr(ctx, "rec", None)
            lag = amplifier_lag(getattr(rec, "header", None) or {}, getattr(rec, "axis", ""))[0] * p.fs

        def term(d):
            return ctx.term(self.name, FoundDelay(d, lag, modelled > 0))
        dmax = self.search_limit(p.fs)
        grid = np.arange(0, dmax + 1)
        sses = ctx.delay_sses(base, grid, rows=self.in_motion(ctx))
        i = int(np.argmin(sses))
        d = parabolic_min(grid, sses)
        if 0 < i < len(grid) - 1:
            d = self.refine(ctx, base, float(grid[i]))
        if i == 0:
            return term(0.0), "best delay is 0 samples beyond the zero-order hold"
        total = ctx.zoh + d
        if is_hold(total):
            return term(d), (f"total input delay {total:.2f} sample is the zero-order hold of a "
                             "sampled-data loop (half a sample), not an effect")
        note = f"delay {d:g} samples at the edge of the searched range" if i == len(grid) - 1 else None
        return term(d), note or self.not_transport(ctx, base, dmax)

    @staticmethod
    def search_limit(fs: float) -> int:
        """The longest delay searched [samples] at the sample rate ``fs`` [Hz]: 5 ms, 3 to 40."""
        return max(3, min(round(0.005 * fs), 40))

    def recheck(self, ctx, term, base):
        """:meth:`not_transport` on the final model's other terms ``base``: a delay that was
        one transport delay beside an effect elimination dropped may not be without it (a
        play's lag, passed beside a Stribeck term: X, a_max 25, the 200 µm play)."""
        if not self.input_shift(term.h):
            return None
        return self.not_transport(ctx, base, self.search_limit(ctx.p.fs))

    @staticmethod
    def refine(ctx, base, d0: float) -> float:
        """The least-SSE delay [samples] within one sample of the grid's best d0, on a grid of
        :data:`FINE_STEP` refined by a parabola: the SSE over τ is not a parabola across a whole
        sample (a 3-sample delay's parabola through the integer grid said 3.36, the fine grid
        3.0x)."""
        fine = np.arange(d0 - 1.0, d0 + 1.0 + 1e-9, FINE_STEP)
        return parabolic_min(fine, ctx.delay_sses(base, fine, rows=InputDelayFamily.in_motion(ctx)))

    @staticmethod
    def in_motion(ctx) -> np.ndarray:
        """The decimated samples (M,) bool the delay is fitted on: |ẋ| above :data:`V_HELD`. A
        carriage held by static friction (or hunting about its target) does not move through
        its dynamics, and the input there is stiction's, whatever the delay."""
        return np.abs(ctx.p.v_d) > V_HELD

    @staticmethod
    def bands(fs_d: float) -> tuple[tuple[float, float], tuple[float, float]]:
        """The two frequency bands [Hz] a delay's phase slope is compared on: from lo to the
        geometric mean with the decimation filter's cut-off hi = 0.4·fs_d, and from there to
        hi; lo = :data:`BAND_LOW_HZ`, or a quarter of hi where that is lower (15-39 and 39-100
        Hz at fs_d = 250 Hz, a 5 kHz run log; 10-20 and 20-40 Hz at fs_d = 100 Hz, a 1 kHz
        record, where a fixed 15 Hz left no upper band and a play's lag was named a delay)."""
        hi = 0.4 * fs_d
        lo = min(BAND_LOW_HZ, hi / 4.0)
        mid = (lo * hi) ** 0.5
        return (lo, mid), (mid, hi)

    def not_transport(self, ctx, base, dmax: int) -> str | None:
        """A transport delay is a phase −ωτ at every frequency: the delay that fits the lower
        and the upper band of :meth:`bands` alone (grid of :data:`BAND_STEP` samples) must agree
        within :data:`MAX_BAND_SPREAD`. A lag of part of the force only (a load in play:
        backlash, whose impacts lag the carriage by a time that depends on the motion) fits a
        longer delay in the upper band. Returns the reason, or None."""
        p = ctx.p
        bands = self.bands(p.fs / p.nd)
        grid = np.arange(0.0, dmax + 1e-9, BAND_STEP)
        taus = [parabolic_min(grid, ctx.delay_sses(base, grid, band=b)) for b in bands]
        if abs(taus[1] - taus[0]) <= MAX_BAND_SPREAD:
            return None
        (l0, h0), (l1, h1) = bands
        return (f"not a transport delay: its phase says {taus[0]:.1f} samples at {l0:.3g}-{h0:.3g} Hz and "
                f"{taus[1]:.1f} at {l1:.3g}-{h1:.3g} Hz (a delay is the same at every frequency, spread <= "
                f"{MAX_BAND_SPREAD:g}): a lag of part of the force (a load held with play, backlash)")

    def parameters(self, h, beta, gain, fs):
        """delay_samples: the lag found beyond the hold (and beyond the declared current loop
        when the model holds it, :class:`FoundDelay`) [samples]; amplifier_lag_s: the declared
        loop's lag (0 when none is declared); total_delay_s: all of the lag beyond the hold
        (what the compensation previews); delay_s: the transport delay beyond the loop,
        total_delay_s − amplifier_lag_s."""
        lag = float(getattr(h, "amplifier_lag", 0.0))
        total = h.beyond_hold() if isinstance(h, FoundDelay) else float(h)
        return {"delay_samples": float(h), "delay_s": (total - lag) / fs, "total_delay_s": total / fs,
                "amplifier_lag_s": lag / fs}

    # compensation (a preview, not an additive d̂_eff)
    def compensation(self, h, beta, signals=None):
        """delay_s = (h + the declared current loop's lag) · the record's sample period (from
        ``signals``: its ``fs`` or its time column): all of the lag beyond the hold; None without
        signals or without a lag beyond the hold (a found delay of 0 beyond a modelled loop still
        previews the loop's lag)."""
        total = h.beyond_hold() if isinstance(h, FoundDelay) else float(h or 0.0)
        if signals is None or not total:
            return None
        fs = getattr(signals, "fs", None)
        if not fs:
            t = np.asarray(signals.t, dtype=float)
            fs = (len(t) - 1) / (t[-1] - t[0])
        return {"delay_s": total / float(fs)}

    def compensation_for(self, delay_s, a1):
        return {"delay_s": float(delay_s)}

    def comp_hook(self, o: DelayComp) -> CompHook:
        return CompHook(preview_s=o.delay_s)

    # report
    def shape(self, ctx, h, beta, gain):
        """A1 (u(t − τ) − u(t)) against time: what the delay changes in the input the nominal
        model applies (hold and declared current loop included)."""
        g = gain or 1.0
        pr = ctx.p
        return (pr.t_d, g * ctx.target(ctx.zoh + h) - g * ctx.target(ctx.zoh), "time [s]",
                "A1 (u(t - tau) - u(t)) [UNIT]")


FAMILY = InputDelayFamily()
