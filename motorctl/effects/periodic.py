"""Helpers shared by the periodic families: Fourier columns, periodograms, search grids, and the
position-periodic search of cogging, force ripple and periodic friction (not a family itself).

Position-periodic search (docs/identification.md, section 2, the cogging row): the period P is taken from the
peaks of a least-squares (Lomb-Scargle) periodogram of the residual against **position**
(moving samples, P from 1 mm to min(0.1 m, stroke/3)), then refined by minimising the joint LS
fit's SSE within the periodogram's resolution of each peak (±P/stroke, at most ±3 %; bounded
Brent search to 1/30 of that); a peak whose period lowers the SSE by less than
:data:`MIN_PEAK_DROP` is a noise peak and is not refined.
"""

from __future__ import annotations

import dataclasses
import math
import threading
from collections import OrderedDict

import numpy as np
from pydantic import model_validator

from motorctl.effects.base import Adaptable, CompTerm, EffectFamily
from motorctl.jit import njit
from motorctl.schema import NonNeg, StrictModel

#: Harmonics fitted for position- and time-periodic families.
N_HARMONICS = 2
#: Periodogram peaks refined by the joint fit (position- and time-periodic families).
N_PEAKS = 2
#: Least SSE drop at a periodogram peak for it to be refined (a candidate needs a held-out RMS
#: gain of 3 %, about 6 % of the SSE; refining moves the period by at most 3 %)
MIN_PEAK_DROP = 0.03
#: Largest relative distance from a periodogram peak at which the period is searched (the
#: spatial periodogram of a short stroke resolves a period to about P/stroke: 8 % for 32 mm over 0.4 m).
REFINE_SPAN = 0.03
#: Resolution of the refined period, as a share of the searched half-width (a period off by δP
#: shifts the phase by 2π·(stroke/P)·δP/P over the stroke: 0.2 rad at this share).
REFINE_TOL = 1.0 / 30.0
#: Least agreement of a position-periodic force fitted on each direction of motion separately.
MIN_DIRECTION_AGREEMENT = 0.5
#: Largest ratio of a position-periodic force's amplitude fitted on the faster half of the
#: moving samples to that on the slower half (a force of position keeps its amplitude; an
#: encoder's interpolation error fitted as a force grows with the squared speed)
MAX_SPEED_GROWTH = 2.0
#: The largest thrusts: this share of the record's (decimated) samples, those of the largest
#: |u|, where the amplifier saturates and the model's thrust shape (eq. 3) is least sure ...
THRUST_TAIL = 0.02
#: ... and the least share of what a position-periodic force explains in motion that it must
#: still explain without them (a force of position acts at every thrust). Measured, default
#: plant, X, 20 s, seed 1: cogging ×1, the force ripple ×0.3, ×0.5, ×1 and ×3 and the periodic
#: friction ×1 keep 0.73-1.00 of their share at every step, 0.88 and more at the step that
#: takes them; a 72 mm "ripple" on a clean plant whose viscous friction is 40 N·s/m (u at its
#: 10 V limit on 1.2 % of the samples) keeps 0.14 and 0.29 (seeds 18, 19). The families'
#: tables are unchanged (the default plant's seeds 1-3 and ×0.3, ×1.5; the rigid and
#: half-mode plants' seed 1)
MIN_TAIL_KEPT = 0.5
#: the start of that reason: it says the evidence is a few samples, not that the physics does
#: not fit (the residual verdict does not count it as a structure, nor as too little to be one)
FEW_SAMPLES = "seen only at the largest thrusts"
#: the least share of what a position-periodic force explains of the whole record's residual
#: that it must explain of the moving samples' (:meth:`PositionPeriodic.motion_check`): a period
#: of about a millimetre on a 1 kHz record passes the band only at the moves' ends, and there
#: it can take any value at the few positions the carriage rests at (an independent PID loop's
#: records, benchmarks/ident_unmodelled.py: a 1.1-1.3 mm cogging explained 19-94 % of the
#: residual and 2-10 % of the moving samples' on clean and LuGre records; the true ones
#: keep about all of it)
MIN_MOVING_KEPT = 0.5
#: the start of that reason: its evidence is the force held at rest, not a structure in motion
AT_REST_ONLY = "seen only where the carriage rests"
#: reasons that say a candidate's evidence is a few samples, not that its physics does not fit:
#: the residual verdict does not make a structure of them
NOT_A_STRUCTURE = (FEW_SAMPLES, AT_REST_ONLY)
#: Largest relative distance from a term's period P (and from P/2) at which the harmonic check
#: (:meth:`PositionPeriodic.harmonic_check`) refines each harmonic on its own: the SSE's main
#: lobe, ±P/stroke, up to this share (two forces whose periods lie farther from P are not
#: both taken by one locked pair). Independent simulation B (a 0.205 m stroke): 22.08 mm
#: locked, 23 mm true (4.2 %; its lobe ±10.8 %)
HARMONIC_SPAN = 0.12
#: Least phase slip [cycles over the stroke] between the second harmonic, refined on its own,
#: and twice the fundamental, refined on its own (stroke·|2/P1 − 1/P2|): below it the two
#: periods are one period and its harmonic to within half the record's resolution (one cycle
#: over the stroke: the Rayleigh resolution), and a better locked period, not two forces, is
#: what the unlocked pair finds. Measured (:meth:`PositionPeriodic.harmonic_check` at every
#: call of a selection): 3 N at 11 mm + 2.5 N at 23 mm (simulation B, seeds 1-3) 0.78-0.81
#: beside stiction; true cogging, force ripple and periodic friction 0.00-0.64 (the largest
#: where the plant has one harmonic and the second is noise, its period free: B's 19 mm
#: cogging), which the drop below tells apart
MIN_HARMONIC_SLIP = 0.5
#: ... and the least share of the SSE the locked pair leaves that the unlocked pair must explain
#: beyond it: two forces, not one period. Measured: simulation B's two periods 0.86-0.88 beside
#: stiction (0.04 at the first step, before it: not refused there); a true 29 mm cogging beside an
#: unmodelled 17 mm force (simulation A, seeds 1-3) 0.13; the true cogging (×0.5, ×1, 32 mm, 2
#: harmonics), force ripple and periodic friction of ``benchmarks/ident_families.py --seed 1``
#: and B's 19 mm cogging 0.00-0.03; other candidates 0.00-0.04
MIN_UNLOCKED_DROP = 0.25
#: Points of a report figure's curve.
SHAPE_POINTS = 2000


# ---------------------------------------------------------------------------- columns
def fourier(z: np.ndarray, period: float, k: int, scale=None, single: bool = False) -> np.ndarray:
    """sin, cos(2π j z / period) for j = 1..k, interleaved, shape (N, 2k) (each column
    contiguous: the transpose of a (2k, N) block).

    Args:
        z: abscissa (N,), position [m] or time [s]. period: same unit as z (> 0).
        k: harmonics. scale: optional (N,) multiplying every column (force ripple: f_u(u)).
        single: float32 columns, from the phase reduced to half a turn in double precision
            (its error 4e-7 rad, of the order of the sines' own round-off); 4× faster. For
            full-rate columns that are only decimated in single precision
            (:func:`motorctl.ident.idim.parallel_decimate`) or weighed by their coefficients.
    """
    if single:
        ph = z * (1.0 / period)
        ph -= np.rint(ph)
        ph *= 2.0 * np.pi
        ph = ph.astype(np.float32)
    else:
        ph = (2.0 * np.pi / period) * z
    out = np.empty((2 * k, len(z)), dtype=ph.dtype)
    s1, c1 = np.sin(ph, out=out[0]), np.cos(ph, out=out[1])
    for j in range(1, k):      # angle addition: sin((j+1)φ), cos((j+1)φ) from sin(jφ), cos(jφ)
        s, c = out[2 * j - 2], out[2 * j - 1]
        out[2 * j], out[2 * j + 1] = s * c1 + c * s1, c * c1 - s * s1
    if scale is not None:
        out *= np.asarray(scale, dtype=ph.dtype)
    return out.T


@njit
def friction_force(f, x, v, t, sf, p):
    """f + F_eff [N] of a position-periodic friction (the periodic_friction family's plant term)
    at position x [m] with sf = S_f(v) (v, t unused): f − (Σ_k A_k sin(w_k x + φ_k)) sf; the row
    p = (A_1 [N], w_1 [rad/m], φ_1 [rad], A_2, w_2, φ_2, ...)."""
    g = 0.0
    for j in range(0, p.shape[0], 3):
        g += p[j] * math.sin(p[j + 1] * x + p[j + 2])
    return f - g * sf


def amplitudes_phases(beta: np.ndarray, g: float) -> tuple[np.ndarray, np.ndarray]:
    """Amplitudes g·|(s_k, c_k)| and phases φ_k of F = −g Σ (s_k sin + c_k cos) = Σ A_k sin(· + φ_k),
    for interleaved coefficients beta = (s_1, c_1, s_2, c_2, ...) (2K,). Returns two (K,) arrays."""
    s, c = beta[0::2], beta[1::2]
    return g * np.hypot(s, c), np.arctan2(-c, -s)


def harmonics(w: float, sin_V: list, cos_V: list) -> tuple:
    """((w·k, a_k, b_k), ...) for k = 1..max(len): the shorter list padded with zeros."""
    n = max(len(sin_V), len(cos_V))
    a = list(sin_V) + [0.0] * (n - len(sin_V))
    b = list(cos_V) + [0.0] * (n - len(cos_V))
    return tuple((w * (k + 1), a[k], b[k]) for k in range(n))


@njit
def fourier_add(d, x, v, t, sf, p):
    """d + Σ_k a_k sin(w_k z) + b_k cos(w_k z) [V], z = t [s] when p[0] != 0 else x_d [m] (v, sf
    unused); the row p = (on_time, w_1, a_1, b_1, w_2, a_2, b_2, ...) of :func:`fourier_term`.
    The harmonics are added to d one at a time, in order."""
    z = t if p[0] != 0.0 else x
    for j in range(1, p.shape[0], 3):
        d += p[j + 1] * math.sin(p[j] * z) + p[j + 2] * math.cos(p[j] * z)
    return d


def fourier_term(harm: tuple, on_time: bool) -> CompTerm:
    """The compensation term Σ_k a_k sin(w_k z) + b_k cos(w_k z) [V] of :func:`harmonics`, with
    z = x_d [m] (position) or t [s] (``on_time``): a :class:`~motorctl.effects.base.CompTerm`
    of :func:`fourier_add`."""
    row = [1.0 if on_time else 0.0]
    for w, a, b in harm:
        row += [w, a, b]
    return CompTerm("add", fourier_add, row)


def fourier_beta(sin_V: list, cos_V: list) -> list[float]:
    """β of a Fourier compensation entry: a_1..a_n, b_1..b_n (the shorter list padded with 0),
    n = max(len)."""
    n = max(len(sin_V), len(cos_V))
    return [float(v) for v in list(sin_V) + [0.0] * (n - len(sin_V))] + \
        [float(v) for v in list(cos_V) + [0.0] * (n - len(cos_V))]


def fourier_beta_names(sin_V: list, cos_V: list) -> list[str]:
    """Names of :func:`fourier_beta`'s entries: sin_V[0], ..., cos_V[0], ..."""
    n = max(len(sin_V), len(cos_V))
    return [f"sin_V[{k}]" for k in range(n)] + [f"cos_V[{k}]" for k in range(n)]


@njit
def fourier_fill(out, j, x, v, t, sf, p):
    """The basis of an adapted Fourier entry: sin(w_k z), k = 1..n, then cos(w_k z) into
    out[j:j + 2n], z = t [s] when p[0] != 0 else x [m] (v, sf unused); the row p = (on_time, n,
    w_1, ..., w_n) of :func:`fourier_basis`."""
    z = t if p[0] != 0.0 else x
    n = int(p[1])
    for k in range(n):
        ph = p[2 + k] * z
        out[j + k] = math.sin(ph)
        out[j + n + k] = math.cos(ph)


def fourier_basis(w: float, n: int, on_time: bool) -> CompTerm:
    """The basis of an adapted Fourier entry (β = :func:`fourier_beta`): sin(k w z), k = 1..n,
    then cos(k w z), z = x_d or x [m] (position) or t [s] (``on_time``); w [rad/m or rad/s]. A
    :class:`~motorctl.effects.base.CompTerm` of :func:`fourier_fill`."""
    return CompTerm("fill", fourier_fill, [1.0 if on_time else 0.0, float(n)] + [w * (k + 1) for k in range(n)])


class AmplitudeStep(StrictModel):
    """Simulator options of a periodic effect whose amplitude drifts (tests of adapted
    compensation): from plant time ``step_at_s`` [s] on, the amplitude is multiplied by
    ``scale_after`` (both or neither; default: no step)."""

    step_at_s: NonNeg | None = None
    scale_after: float | None = None

    @model_validator(mode="after")
    def _step_pair(self):
        if (self.step_at_s is None) != (self.scale_after is None):
            raise ValueError("step_at_s and scale_after go together")
        return self


class FourierAdaptable(Adaptable):
    """:class:`~motorctl.effects.base.Adaptable` for a Fourier entry with ``sin_V``, ``cos_V``."""

    def beta(self):
        return fourier_beta(self.sin_V, self.cos_V)

    def beta_names(self):
        return fourier_beta_names(self.sin_V, self.cos_V)


def sin_cos_of(amplitude: float, phase: float) -> tuple[float, float]:
    """A sin(z + φ) = (A cos φ) sin z + (A sin φ) cos z: the (sin, cos) coefficients."""
    return amplitude * math.cos(phase), amplitude * math.sin(phase)


# ---------------------------------------------------------------------------- search grids
#: position bin of the spatial periodogram, as a share of the shortest period searched
BIN_SHARE = 1.0 / 16.0

#: elements (bins × periods) up to which the basis of a spatial periodogram is kept for the
#: next call on the same positions (a selection's steps search the same moving samples again
#: with another residual): two float64 arrays, at most 32 MB each
BASIS_MAX_ELEMENTS = 4_000_000
#: bases kept (the least recently used one goes first)
BASES_KEPT = 4
_bases: OrderedDict = OrderedDict()
_bases_lock = threading.Lock()


def _periodogram_basis(xc: np.ndarray, w: np.ndarray, omega: np.ndarray):
    """What the Lomb-Scargle periodogram of :func:`scipy.signal.lombscargle` (no floating mean)
    computes from the abscissa alone: cos and sin of ω x − τ (B, K) and their weighted squares
    (K,), for bin centres ``xc`` (B,), weights ``w`` (B,) summing to 1, angular frequencies
    ``omega`` (K,). Kept for the next call on the same bins while small
    (:data:`BASIS_MAX_ELEMENTS`, :data:`BASES_KEPT`); read only."""
    key = (xc.tobytes(), w.tobytes(), omega.tobytes())
    with _bases_lock:
        hit = _bases.get(key)
        if hit is not None:
            _bases.move_to_end(key)
            return hit
    wt = np.outer(xc, omega)
    c, s = np.cos(wt), np.sin(wt)
    cc = w @ (c * c)
    cs = w @ (c * s)
    tau = 0.5 * np.arctan2(2.0 * cs, cc - (1.0 - cc))
    wt -= tau
    c, s = np.cos(wt, out=c), np.sin(wt, out=s)
    cc = w @ (c * c)
    ss = 1.0 - cc
    eps = np.finfo(float).epsneg
    cc[cc < eps] = eps
    ss[ss < eps] = eps
    out = (c, s, cc, ss)
    for a in out:
        a.flags.writeable = False
    if c.size <= BASIS_MAX_ELEMENTS:
        with _bases_lock:
            _bases[key] = out
            while len(_bases) > BASES_KEPT:
                _bases.popitem(last=False)
    return out


def spatial_periodogram(x: np.ndarray, r: np.ndarray, periods: np.ndarray) -> np.ndarray:
    """Least-squares (Lomb-Scargle) periodogram of r against position x (uneven abscissa).

    r is first averaged in position bins of :data:`BIN_SHARE` of the shortest period, and the
    periodogram is taken over the bin centres weighted by the samples in each bin: a
    position-locked effect of period P is attenuated by at most sinc(BIN_SHARE) (0.6 %), what
    is not locked to position averages down, and the cost is the bins' (a few thousand over a
    stroke), not the samples' (100 000 in a 20 s log at 5 kHz). The normalised power of
    :func:`scipy.signal.lombscargle` (``normalize=True``, weights, no floating mean; Lomb 1976,
    Scargle 1982, with τ eliminating the cross term), equal to it to round-off; what depends on
    the positions alone is computed once for a selection's steps (:func:`_periodogram_basis`).

    Args:
        x [m], r: shape (M,), samples with the axis moving. periods [m]: shape (K,), > 0.
    Returns:
        Normalised power (K,), angular frequencies 2π/P.
    """
    periods = np.asarray(periods, dtype=float)
    if periods.size == 0 or x.size == 0:
        return np.zeros(periods.shape)
    dx = BIN_SHARE * float(periods.min())
    x0 = float(x.min())
    idx = ((x - x0) / dx).astype(np.int64)
    n = np.bincount(idx)
    s = np.bincount(idx, weights=r - r.mean())
    full = np.flatnonzero(n)
    xc = x0 + (full + 0.5) * dx
    rb = s[full] / n[full]
    w = n[full] / float(n.sum())
    y = rb - w @ rb
    c, sn, cc, ss = _periodogram_basis(xc, w, 2.0 * np.pi / periods)
    wy = w * y
    yc, ys, yy = wy @ c, wy @ sn, float(wy @ y)
    return (yc * yc / cc + ys * ys / ss) / yy


def peak_periods(x, r, periods, n_peaks=3) -> list:
    """The ``n_peaks`` highest local maxima of the spatial periodogram, as periods [m]."""
    pw = spatial_periodogram(x, r, periods)
    loc = np.flatnonzero((pw[1:-1] > pw[:-2]) & (pw[1:-1] >= pw[2:])) + 1
    loc = loc[np.argsort(pw[loc])[::-1]][:n_peaks]
    return [float(periods[i]) for i in loc]


def period_grid(stroke: float) -> np.ndarray:
    """Plausible cogging / ripple periods [m]: 1 mm .. min(0.1 m, stroke/3), 0.2 % steps.
    Empty (0,) when the stroke [m] is too short."""
    hi = min(0.1, stroke / 3.0)
    lo = 1e-3
    if hi <= lo * 1.5:
        return np.array([])
    return np.exp(np.arange(math.log(lo), math.log(hi), 0.002))


def spectral_lines(t_d: np.ndarray, r: np.ndarray, n: int, f_lo: float, f_hi: float) -> list[float]:
    """The frequencies [Hz] of the ``n`` strongest lines of ``r`` (M,) at the uniform instants
    ``t_d`` (M,) [s] between ``f_lo`` and ``f_hi`` [Hz], strongest first: the highest local
    maxima (:func:`scipy.signal.find_peaks`) of its periodogram (:func:`scipy.signal.periodogram`,
    Hann window, mean removed, zero-padded to 8 times its length), each refined by a parabola
    through the log-power of its bin and their neighbours. Empty when the band holds none."""
    from scipy.signal import find_peaks, periodogram
    m = len(r)
    if m < 16 or not float(t_d[-1] - t_d[0]) > 0:
        return []
    fs = (m - 1) / float(t_d[-1] - t_d[0])
    nfft = 1 << int(math.ceil(math.log2(8 * m)))
    f, pw = periodogram(r, fs=fs, window="hann", nfft=nfft, detrend="constant")
    idx = np.flatnonzero((f >= f_lo) & (f <= f_hi))
    if idx.size < 3:
        return []
    peaks = find_peaks(pw[idx])[0]
    peaks = idx[peaks[np.argsort(pw[idx][peaks])[::-1]][:n]]
    out = []
    for k in peaks:
        lo, mid, hi = (math.log(max(float(pw[j]), 1e-300)) for j in (k - 1, k, k + 1))
        den = lo - 2.0 * mid + hi
        out.append(float(f[k] + (0.5 * (lo - hi) / den if den < 0 else 0.0) * (f[1] - f[0])))
    return out


# ---------------------------------------------------------------------------- position-periodic
class PositionPeriodic(EffectFamily):
    """Common search and checks of the position-periodic families (cogging, force ripple)."""

    searched = "period P [m]"

    def peak_data(self, ctx, residual: np.ndarray):
        """(x [m], r) (M',) of the samples whose spatial periodogram gives the candidate
        periods, or None when there are too few."""
        raise NotImplementedError

    def search(self, ctx, base, residual):
        grid = period_grid(ctx.stroke)
        if grid.size == 0 or ctx.moving.sum() < 50:
            return None
        data = self.peak_data(ctx, residual)
        if data is None:
            return None
        best = None
        sse_base = ctx.sse(base)
        for pk in peak_periods(data[0], data[1], grid, N_PEAKS):
            term = ctx.term(self.name, pk)
            sse = ctx.sse(base + [term])
            if sse > (1.0 - MIN_PEAK_DROP) * sse_base:
                # at its peak the period explains almost nothing: a noise peak, not refined
                if best is None or sse < best[0]:
                    best = (sse, term)
                continue
            term = self._refine(ctx, pk, base)
            sse = ctx.sse(base + [term])
            if best is None or sse < best[0]:
                best = (sse, term)
        if best is None:   # no periodogram peak at all
            return None
        term = best[1]
        note = None
        if term.h <= grid[1] or term.h >= grid[-2]:
            note = f"period {term.h:.4g} m at the edge of the searched range"
        return term, note

    def _refine(self, ctx, period: float, base: list):
        """The term minimising the joint-LS SSE near ``period`` [m]: the true period lies
        within the periodogram's resolution of its peak, ΔP/P ≈ P/stroke (the SSE's main
        lobe, one minimum), searched there, at most ±REFINE_SPAN."""
        half = min(REFINE_SPAN, period / ctx.stroke)
        return ctx.best_between(self.name, period * (1.0 - half), period * (1.0 + half), base,
                                REFINE_TOL * half * period)

    def polish(self, ctx, term, others):
        """The period refined again around the selected one with the other effects modelled
        (an effect found later, e.g. stiction, shifts the SSE's minimum of the first search)."""
        return self._refine(ctx, term.h, others)

    def plausible(self, ctx, term, beta, theta, base):
        out = []
        agree = ctx.direction_agreement(term, base)
        if agree < MIN_DIRECTION_AGREEMENT:
            out.append(f"not the same force in both directions (agreement {agree:.2f} < "
                       f"{MIN_DIRECTION_AGREEMENT:g}): a position-periodic force does not "
                       "depend on the direction of motion")
        out += self.speed_check(ctx, term, base)
        out += self.thrust_check(ctx, term, base)
        out += self.motion_check(ctx, term, base)
        if not out:
            # last, and only when nothing else refused it: a reason of its own would make a
            # structure of a candidate refused for a few samples (NOT_A_STRUCTURE)
            out += self.harmonic_check(ctx, term, base)
        return out

    def harmonic_check(self, ctx, term, base) -> list[str]:
        """The harmonics of a term are harmonics of one period: the reason against a term whose
        fundamental and second harmonic, each refined on its own, are two periods, else [].

        The term's columns hold k = 1, 2 at one period P (:data:`N_HARMONICS`); two forces of
        position whose periods are near a 2:1 ratio are fitted by it as a compromise (simulation
        B's 23 and 11 mm: P = 22.08 mm, its second harmonic at 11.04 mm takes the 11 mm force).
        The fundamental's sin/cos pair is refined alone within ±min(P/stroke,
        :data:`HARMONIC_SPAN`) of P with the second harmonic (at P/2) in the model beside
        ``base``, then the second harmonic's pair alone within ±min(P/(2·stroke),
        :data:`HARMONIC_SPAN`) of P/2 beside that fundamental (bounded Brent, to
        :data:`REFINE_TOL` of each half-width). Refused when the two refined periods P1, P2
        slip by at least :data:`MIN_HARMONIC_SLIP` cycles over the stroke (stroke·|2/P1 − 1/P2|)
        and the unlocked pair explains at least :data:`MIN_UNLOCKED_DROP` of the SSE the locked
        term leaves. Terms of one harmonic (pruned): nothing to check. About 25 fits of one
        harmonic's columns; run only on a term no other check refused."""
        cols = term.cols
        if cols is None or cols.ndim != 2 or cols.shape[1] < 4 or ctx.stroke <= 0:
            return []
        from scipy.optimize import minimize_scalar

        period = float(term.h)

        def pair(h, c=None):
            # the first harmonic's sin/cos columns at period h [m] (its own term, no other harmonic)
            c = ctx.dec_cols(term.family, h) if c is None else c
            return dataclasses.replace(term, h=float(h), cols=np.ascontiguousarray(c[:, :2]))

        def refine(centre, other):
            half = min(HARMONIC_SPAN, centre / ctx.stroke)
            with_other = base + [other]
            res = minimize_scalar(lambda h: ctx.sse(with_other + [pair(h)]),
                                  bounds=(centre * (1.0 - half), centre * (1.0 + half)),
                                  method="bounded", options={"xatol": REFINE_TOL * half * centre})
            return pair(res.x)

        first = refine(period, pair(0.5 * period, cols[:, 2:4]))
        second = refine(0.5 * period, first)
        p1, p2 = first.h, second.h
        slip = ctx.stroke * abs(2.0 / p1 - 1.0 / p2)
        if slip < MIN_HARMONIC_SLIP:
            return []
        locked = ctx.sse(base + [term])
        unlocked = ctx.sse(base + [first, second])
        drop = (locked - unlocked) / locked if locked > 0 else 0.0
        if drop < MIN_UNLOCKED_DROP:
            return []
        return [f"its harmonics are two periods ({1e3 * p1:.1f} and {1e3 * p2:.1f} mm, ratio {p1 / p2:.2f}, not 2: "
                f"{slip:.2f} cycles apart over the stroke, >= {MIN_HARMONIC_SLIP:g}; fitted apart they explain "
                f"{100 * drop:.0f} % of what the {1e3 * period:.2f} mm pair leaves, >= {100 * MIN_UNLOCKED_DROP:g} %): "
                "two forces of position, not one periodic force and its harmonic"]

    def motion_check(self, ctx, term, base) -> list[str]:
        """A force of position acts in motion as at rest: the reason against a term that
        explains less than :data:`MIN_MOVING_KEPT` of its share of the whole record's residual
        on the moving samples (both fitted jointly with the nominal θ, :func:`~motorctl.ident.
        probes.explained_shares`), else []. What it explained is the force the loop
        holds at the positions the carriage rests at (a hold the model's friction does not
        describe), which a short period fits at those few positions (:data:`AT_REST_ONLY`: not
        a structure for the residual verdict)."""
        full, moving = ctx.explained_shares(term, base, np.ones(len(ctx.moving), dtype=bool), ctx.moving)
        if full > 0 and moving < MIN_MOVING_KEPT * full:
            return [f"{AT_REST_ONLY}: it explains {100 * full:.1f} % of the record's residual, {100 * moving:.1f} % "
                    f"of the moving samples' (< {MIN_MOVING_KEPT:g} of it; a force of position acts in motion too)"]
        return []

    def thrust_check(self, ctx, term, base) -> list[str]:
        """A force of position acts at every thrust: the reason against a term that explains
        less than :data:`MIN_TAIL_KEPT` of its share of the moving samples' residual once the
        :data:`THRUST_TAIL` of the record's samples with the largest |u| are left out (both
        fitted jointly with the nominal θ, :func:`~motorctl.ident.probes.
        explained_shares`), else []. What it explained sits where the amplifier saturates and
        the thrust shape is least sure: a few samples at the program's hardest accelerations,
        at fixed positions, which a period fits (a clean plant whose viscous friction drives u
        to its limit: a 72 mm ripple, 6 % of the held-out residual, named on two seeds). Its
        evidence is those few samples, not a structure: the residual verdict does not report a
        candidate refused for this alone (:data:`FEW_SAMPLES`)."""
        a = np.abs(ctx.p.u_d)
        kept = a < np.quantile(a, 1.0 - THRUST_TAIL)
        full, part = ctx.explained_shares(term, base, ctx.moving, ctx.moving & kept)
        if full > 0 and part < MIN_TAIL_KEPT * full:
            return [f"{FEW_SAMPLES}: it explains {100 * full:.1f} % of the moving samples' residual, "
                    f"{100 * part:.1f} % without the {100 * THRUST_TAIL:g} % of samples at the largest |u| "
                    f"(< {MIN_TAIL_KEPT:g} of it; a force of position acts at every thrust)"]
        return []

    def speed_check(self, ctx, term, base) -> list[str]:
        """A force of position keeps its amplitude at every speed: the reason against a term
        whose amplitude on the faster half of the moving samples is more than
        :data:`MAX_SPEED_GROWTH` times that on the slower half (an encoder's interpolation
        error looks so: the encoder_interpolation family) or less than 1/MAX_SPEED_GROWTH
        times (what the load's play leaves at the ends of the moves fitted at a long period),
        beyond the ratio's ±2σ interval
        (:func:`~motorctl.ident.probes.speed_growth_interval`: a small effect's
        halves are noisy; a 3.6 N cogging measured ×2.15), else []. Measured ratios of the true
        effects (default and rigid plants, examples ×0.5, ×1): cogging 0.95-1.68, force ripple
        0.77-0.96, periodic friction 0.78-1.20.

        The halves are taken among the samples slow enough for the period P to pass the position
        filter (|ẋ| < f_q·P). When too few are (a period of a few mm: only the ends of the moves),
        the check cannot be made, and the term is refused too: a reading's error at such a
        period is seen only there, as a force of any shape (a ripple's fraction, cogging), and
        its growth with the speed, the one feature that tells them, cannot be measured."""
        growth, lo, hi = ctx.speed_growth_interval(term, base, term.h)
        if math.isnan(growth):
            return [f"too few moving samples slow enough for its period to pass the position filter "
                    f"(|v| < {ctx.p.fq * term.h:.3g} m/s) to check that its amplitude keeps at every "
                    "speed: a reading's error (encoder interpolation) is seen there as well"]
        if lo > MAX_SPEED_GROWTH:
            return [f"its amplitude grows with the speed (x{growth:.2f}, at least x{lo:.2f}, from the slower to "
                    f"the faster half of the moves, > {MAX_SPEED_GROWTH:g}): not a force of position; a "
                    "reading's error (encoder interpolation) does so"]
        if hi < 1.0 / MAX_SPEED_GROWTH:
            return [f"its amplitude falls with the speed (x{growth:.2f}, at most x{hi:.2f}, from the slower to "
                    f"the faster half of the moves, < {1.0 / MAX_SPEED_GROWTH:g}): not a force of position"]
        return []

    @staticmethod
    def position_grid(ctx, period: float) -> np.ndarray:
        """Positions [m] over at most four periods of the record's range (K,), for the report."""
        pr = ctx.p
        x_hi = min(pr.x_d.max(), pr.x_d.min() + 4.0 * period)
        return np.linspace(pr.x_d.min(), x_hi, SHAPE_POINTS)
