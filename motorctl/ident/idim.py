"""IDIM-LS pre-processing and the nominal fit.

Practice of the EMPS benchmark (Janot, Gautier, Brunot, "Data Set and Reference Models of EMPS",
2019, §3): zero-phase Butterworth low-pass of the position (order 4, cut-off ω_fq), central
differences for velocity and acceleration, then *parallel decimation*: the same low-pass +
down-sampling (the low-pass of :func:`scipy.signal.decimate`, zero phase, applied in the
frequency domain: :func:`parallel_decimate`) applied to every regressor column and to the input,
and ordinary least squares on the decimated system, eq. (10):
θ̂ = (Φ_Fpᵀ Φ_Fp)⁻¹ Φ_Fpᵀ y_Fp, with σ̂² = ‖y − Φθ̂‖²/(N − p) and cov θ̂ = σ̂² (ΦᵀΦ)⁻¹.

The nominal model is the paper's eq. (4) written as u = Φ θ (:func:`motorctl.model.idim_regressor`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from functools import lru_cache

from scipy.fft import irfft, next_fast_len, rfft
from scipy.signal import butter, cheby1, filtfilt, sosfreqz

from motorctl.metrics import runs
from motorctl.model import N_THETA_CUBIC, N_THETA_LINEAR, idim_regressor

#: |u| [V] that the 99.5th percentile of the input must reach for θ5, θ6 (u|u|, u³) to be fitted:
#: half the actuator range u_M = 10 V (paper eq. 4 and Assumption 2; docs/control-law.md, Model). Below it the paper's force curve departs
#: from a straight line by less than ~7 % (θ5 = −0.013 /V: θ5|u| = 0.065 at 5 V) and u|u|, u³
#: are nearly collinear with u, hence with θ1..θ3 under closed-loop excitation.
CUBIC_MIN_INPUT_V = 5.0
#: Samples (decimated) dropped at each end: the zero-phase filters' transients.
EDGE_S = 0.1
#: cut-off of the wide-band velocity (:attr:`Prepared.v_wide`) as a share of the sample rate
WIDE_CUTOFF_SHARE = 0.4
#: the shortest stretch of samples at the input's extreme that :func:`input_saturation` counts
#: as the amplifier's limit [s], and at least this many samples
RAIL_MIN_S, RAIL_MIN_SAMPLES = 1e-3, 3
#: the relative tolerance of "at the extreme" (a clipped input is logged at the limit itself)
RAIL_RTOL = 1e-9


def default_filters(fs: float) -> tuple[float, int]:
    """Position cut-off [Hz] and decimation factor for a sample rate ``fs`` [Hz].

    ω_fq = min(fs/10, 250 Hz) (≥ 5 ω_dyn for closed-loop bandwidths up to 50 Hz; 100 Hz for
    the 1 kHz EMPS data as in its script), n_d = fs/ω_fq, so the parallel filter's cut-off
    (0.4 fs/n_d = 0.4 ω_fq) sits below the position filter (EMPS description §3.2: ω_Fp ≥ 2 ω_dyn).
    """
    fq = min(fs / 10.0, 250.0)
    nd = max(1, int(round(fs / fq)))
    return fq, nd


def _stages(nd: int) -> list[int]:
    """Split a decimation factor into stages ≤ 13 (scipy's advice for IIR decimation)."""
    out, n = [], nd
    for f in range(13, 1, -1):
        while n % f == 0 and n > 1:
            out.append(f)
            n //= f
    if n != 1:  # a prime > 13: decimate once by it (FIR is safe for any factor)
        out.append(n)
    return out or [1]


@lru_cache(maxsize=32)
def _decimation_sos(q: int) -> np.ndarray:
    """The anti-aliasing filter of :func:`scipy.signal.decimate` (ftype='iir'): Chebyshev I,
    order 8, 0.05 dB ripple, cut-off 0.8 of the new Nyquist frequency (designed once per q)."""
    return cheby1(8, 0.05, 0.8 / q, output="sos")


#: samples (decimated) of odd extension before and after a column decimated by
#: :func:`parallel_decimate` (its ends join there in the circular FFT): beyond the transients of
#: the zero-phase filter (the decimated samples dropped at the record's ends, :data:`EDGE_S`)
EXTENSION = 32


@lru_cache(maxsize=16)
def _kept_gain(nd: int, length: int, num: int, dtype) -> np.ndarray:
    """|H(f)|² of :func:`decimation_gain` at the num//2 + 1 FFT bins (:func:`scipy.fft.rfftfreq`
    order) of a column ``length`` samples long that :func:`parallel_decimate` keeps when it
    down-samples to ``num``, divided by nd (the inverse FFT is num long), the unpaired bin at
    num/2 counted twice (it stands for its negative twin); read only, in ``dtype`` (designed
    once per factor and length)."""
    w = decimation_gain(1.0, nd, np.arange(num // 2 + 1) / length) / nd
    if num % 2 == 0:
        w[num // 2] *= 2.0
    w = w.astype(dtype)
    w.flags.writeable = False
    return w


def parallel_decimate(m: np.ndarray, nd: int, single: bool = False) -> np.ndarray:
    """Same zero-phase low-pass + down-sampling on every column (EMPS §3.2, "decimate" process).

    The low-pass is that of ``scipy.signal.decimate(m, q, ftype='iir', axis=0,
    zero_phase=True)`` per stage (stages ≤ 13: Chebyshev I, order 8, 0.05 dB ripple, cut-off
    0.8 of each stage's new Nyquist frequency, run forwards and backwards), applied as its
    zero-phase gain |H(f)|² (:func:`decimation_gain`) in the frequency domain, as
    :func:`scipy.signal.resample` (Fourier method) does with that window: of each column's
    FFT (:func:`scipy.fft.rfft`) only the bins below the new Nyquist frequency fs/(2 nd) are
    kept, weighed by the gain, and transformed back at the new rate: what lies above is
    removed, not folded (for nd = 20 the cascade of filters lets it through at −66 dB at
    fs/(2 nd) and below −120 dB from 1.2 fs/(2 nd), where it aliases into the band kept). Each
    column is extended by :data:`EXTENSION` decimated samples at both ends (odd extension about
    its end values, as :func:`scipy.signal.sosfiltfilt` does) and to a length with small prime
    factors (:func:`scipy.fft.next_fast_len`); sample k of the result is the filtered column at
    full-rate sample nd·k. Away from the ends (:data:`EDGE_S`) this is the cascade's
    ``sosfiltfilt`` to 1e-5 of a column's size (up to 1e-4 for a sharp one, e.g. sign(v)), at
    a third of its time.

    Args:
        m: shape (N,) or (N, k), float64, or float32 with ``single``. nd: decimation factor ≥ 1.
        single: the transforms in single precision (float32): 1.7× faster, and within 2e-6 of
            a column's RMS of the double-precision result (its round-off, below the filter's own
            1e-5 above); for the effect search's many candidate columns.
    Returns:
        Shape (ceil(N/nd),) or (ceil(N/nd), k), float64, each column contiguous.
    """
    dtype = np.float32 if single else np.float64
    out = np.asarray(m)
    if nd <= 1 or out.dtype != dtype:
        out = out.astype(np.float64, copy=False)    # single: float32 columns are taken as they are
    if nd <= 1:
        return out
    n = out.shape[0]
    lo = EXTENSION * nd
    num = next_fast_len(-(-(n + 2 * lo) // nd), real=True)
    length = nd * num
    src = out.T if out.ndim > 1 else out[None, :]
    tail = length - n - lo
    if n > max(lo, tail) + 1:
        # odd extension about the end values (numpy.pad's reflect_type="odd"), written in place
        rows = np.empty((src.shape[0], length), dtype=dtype)
        rows[:, lo:lo + n] = src
        rows[:, :lo] = 2.0 * src[:, :1] - src[:, lo:0:-1]
        rows[:, lo + n:] = 2.0 * src[:, -1:] - src[:, -2:-2 - tail:-1]
    else:       # a column shorter than its extension: reflected as often as needed
        rows = np.pad(src, ((0, 0), (lo, tail)), mode="reflect", reflect_type="odd").astype(dtype)
    spec = rfft(rows, axis=-1, overwrite_x=True)[:, :num // 2 + 1]
    spec *= _kept_gain(nd, length, num, dtype)
    dec = irfft(spec, n=num, axis=-1, overwrite_x=True)[:, EXTENSION:EXTENSION + -(-n // nd)]
    dec = dec.astype(np.float64)
    return dec.T if out.ndim > 1 else dec[0]


def decimation_gain(fs: float, nd: int, f_Hz) -> np.ndarray:
    """Gain [-] of :func:`parallel_decimate` (factor ``nd`` at the sample rate ``fs`` [Hz]) for a
    sine at frequency ``f_Hz`` [Hz] (scalar or array, within 0..fs/2): the product over its
    stages of |H_q(f)|² (each stage's Chebyshev filter run forwards and backwards, at that
    stage's rate; :func:`scipy.signal.sosfreqz`). Away from the record's ends, where the
    decimated samples of a sine are this gain times the sine's."""
    f = np.atleast_1d(np.asarray(f_Hz, dtype=float))
    g = np.ones_like(f)
    rate = fs
    for q in (_stages(nd) if nd > 1 else []):
        _, h = sosfreqz(_decimation_sos(q), worN=f, fs=rate)
        g = g * np.abs(h) ** 2
        rate /= q
    return g if np.ndim(f_Hz) else g[0]


@dataclass
class Prepared:
    """Filtered signals at full rate and the decimation set-up.

    Attributes:
        t, x, v, a, u: full rate (N,): time [s], filtered position [m], velocity [m/s],
            acceleration [m/s²], input [V]. y: raw position [m]. fs [Hz], fq [Hz] (position
            cut-off), nd (decimation factor). keep: slice of decimated samples kept (edges off).
        v_wide: full-rate velocity [m/s] (N,) of the position low-passed at
            :data:`WIDE_CUTOFF_SHARE` × fs (central differences): for a column that is a sharp
            nonlinear function of the velocity (Stribeck's hump of a few cm/s, passed in a few
            ms), evaluated before the parallel decimation filters it. On ``v`` (ω_fq) the hump
            is blurred in time and the fit widens it: v_s 0.0279 for 0.02 m/s on the default
            plant, 0.0228 on ``v_wide``.
        t_d, x_d, v_d, a_d, u_d: the decimated versions (M,) over ``keep``.
    """

    t: np.ndarray
    y: np.ndarray
    x: np.ndarray
    v: np.ndarray
    a: np.ndarray
    u: np.ndarray
    fs: float
    fq: float
    nd: int
    keep: slice
    t_d: np.ndarray = None
    x_d: np.ndarray = None
    v_d: np.ndarray = None
    a_d: np.ndarray = None
    u_d: np.ndarray = None
    fu: np.ndarray = None      # thrust shape f_u(u) [V] once the nominal θ5, θ6 are known (N,)
    v_wide: np.ndarray = None
    #: velocity [m/s] (N,) of Stribeck's S_f factor (None: ``v_wide``, as its hump)
    v_sf: np.ndarray = None
    #: decimated columns of these signals kept by :meth:`dec_once`, by key
    derived: dict = field(default_factory=dict, repr=False)
    #: a family's full-rate columns of this record may be float32
    #: (:func:`~motorctl.effects.periodic.fourier`'s ``single``): the identification only
    #: decimates them, in single precision (:meth:`dec`, ``single``), whose round-off is larger
    #: (:class:`~motorctl.effects.base.Signals`: False)
    columns_single: bool = True

    def dec(self, cols: np.ndarray, single: bool = False) -> np.ndarray:
        """Parallel-decimate full-rate columns (N,) or (N, k) and drop the edges (``single``:
        the transforms in single precision, :func:`parallel_decimate`)."""
        return parallel_decimate(cols, self.nd, single)[self.keep]

    def dec_once(self, key, full) -> np.ndarray:
        """:meth:`dec` of ``full()`` (a callable giving full-rate columns (N,) or (N, k) of
        these signals), computed on the first call with ``key`` (hashable) and kept: read only.
        For a family whose decimated columns are fixed combinations of a few (the decimation is
        linear)."""
        out = self.derived.get(key)
        if out is None:
            out = self.derived[key] = self.dec(full())
            out.flags.writeable = False
        return out

    def dec_gain(self, f_Hz):
        """Gain [-] of :meth:`dec` for a sine at frequency ``f_Hz`` [Hz] (scalar or array, |f|,
        at most fs/2; :func:`decimation_gain`): a sine in time decimates to this gain times its
        samples at t_d (the record's edges, where the filters' transients are, dropped)."""
        return decimation_gain(self.fs, self.nd, np.minimum(np.abs(f_Hz), self.fs / 2.0))


def prepare(t, y, u, fq: float | None = None, nd: int | None = None) -> Prepared:
    """Zero-phase Butterworth (order 4) on y, central differences, decimation set-up.

    Args:
        t [s], y [m], u [V]: shape (N,), uniform sampling.
        fq: position cut-off [Hz]; nd: decimation factor (defaults: :func:`default_filters`).
    Raises:
        ValueError: cut-off not below the Nyquist frequency.
    """
    t, y, u = (np.asarray(a, dtype=float) for a in (t, y, u))
    ts = (t[-1] - t[0]) / (len(t) - 1)
    fs = 1.0 / ts
    dfq, dnd = default_filters(fs)
    fq = float(fq or dfq)
    nd = int(nd or dnd)
    if not 0 < fq < fs / 2:
        raise ValueError(f"position cut-off {fq} Hz must be in (0, {fs / 2:g}) Hz")
    b, a_ = butter(4, fq / (fs / 2))
    x = filtfilt(b, a_, y - y[0]) + y[0]
    v = np.gradient(x, ts)          # central differences (one-sided at the ends)
    acc = np.gradient(v, ts)
    n_dec = -(-len(t) // nd)
    edge = int(np.ceil(EDGE_S * fs / nd)) + 2
    keep = slice(edge, n_dec - edge)
    p = Prepared(t=t, y=y, x=x, v=v, a=acc, u=u, fs=fs, fq=fq, nd=nd, keep=keep)
    if fq < WIDE_CUTOFF_SHARE * fs:
        bw, aw = butter(4, 2.0 * WIDE_CUTOFF_SHARE)
        p.v_wide = np.gradient(filtfilt(bw, aw, y - y[0]), ts)
    else:
        p.v_wide = v
    p.t_d = t[::nd][keep]
    dec = p.dec(np.column_stack([x, v, acc, u]))
    p.x_d, p.v_d, p.a_d, p.u_d = dec.T
    return p


def nominal_columns(p: Prepared, n_theta: int, u_full: np.ndarray | None = None) -> np.ndarray:
    """Decimated nominal regressor Φ_Fp, shape (M, n_theta) (columns of eq. 4, see model.py)."""
    u = p.u if u_full is None else u_full
    return p.dec(idim_regressor(p.a, p.v, u, n_theta))


@dataclass(frozen=True, eq=False)
class LSFit:
    """Ordinary LS on decimated data: coefficients, std, residual, condition number."""

    coef: np.ndarray
    std: np.ndarray
    residual: np.ndarray
    cond: float

    @property
    def rms(self) -> float:
        return float(np.sqrt(np.mean(self.residual ** 2)))


def unit_columns(phi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(phi's columns scaled to unit 2-norm, their norms (p,)) of phi (M, p): the scaling of the
    normal equations every least-squares fit here solves; a zero column keeps its scale 1."""
    sc = np.sqrt(np.einsum("ij,ij->j", phi, phi))
    sc[sc == 0] = 1.0
    return phi / sc, sc


def ls_coef(phi: np.ndarray, y: np.ndarray) -> np.ndarray:
    """LS coefficients (p,) of y (M,) on phi (M, p) by column-scaled normal equations (the fast
    path of the selection's many small fits; :func:`numpy.linalg.lstsq` when singular)."""
    a, sc = unit_columns(phi)
    try:
        return np.linalg.solve(a.T @ a, a.T @ y) / sc
    except np.linalg.LinAlgError:
        return np.linalg.lstsq(phi, y, rcond=None)[0]


def ls_sse(phi: np.ndarray, y: np.ndarray) -> float:
    """SSE of the LS fit of y (M,) on phi (M, p) (:func:`ls_coef`)."""
    r = y - phi @ ls_coef(phi, y)
    return float(r @ r)


def ls_cov(phi: np.ndarray, residual: np.ndarray) -> np.ndarray:
    """σ̂² (ΦᵀΦ)⁻¹ (p, p) of an LS fit on phi (M, p) with its residual (M,) (EMPS eq. 10)."""
    m, k = phi.shape
    return float(residual @ residual) / max(m - k, 1) * np.linalg.pinv(phi.T @ phi)


def ls(phi: np.ndarray, target: np.ndarray) -> LSFit:
    """θ̂ = argmin ‖target − Φθ‖ by the normal equations of the column-scaled Φ (Cholesky-free
    ``numpy.linalg.solve`` of a k×k system; :func:`numpy.linalg.lstsq` when that is singular);
    std from σ̂²(ΦᵀΦ)⁻¹ (EMPS eq. 10); the 2-norm condition number of Φ from the eigenvalues of
    ΦᵀΦ (cond(Φ) = √(λmax/λmin), as ``numpy.linalg.cond``). The k×k route keeps LAPACK's
    threaded SVD of the (M, k) matrix out of the selection's many fits.

    Args:
        phi: (M, p). target: (M,).
    """
    m, k = phi.shape
    a, sc = unit_columns(phi)
    g = a.T @ a
    try:
        gi = np.linalg.inv(g)
        coef = (gi @ (a.T @ target)) / sc
        if not np.all(np.isfinite(coef)):
            raise np.linalg.LinAlgError("not finite")
    except np.linalg.LinAlgError:
        coef = np.linalg.lstsq(phi, target, rcond=None)[0]
        gi = None
    r = target - phi @ coef
    s2 = float(r @ r) / max(m - k, 1)
    if gi is not None:
        std = np.sqrt(np.abs(s2 * np.diag(gi))) / sc
    else:
        std = np.full(k, np.inf)
    lam = np.linalg.eigvalsh(phi.T @ phi)
    cond = float(np.sqrt(lam[-1] / lam[0])) if lam.size and lam[0] > 0 else float("inf")
    return LSFit(coef=coef, std=std, residual=r, cond=cond)


def input_reach(u: np.ndarray) -> float:
    """The record's largest input |u|max [V]: the 99.5th percentile of |u| (u [V], shape (N,)),
    so that a few spikes do not set it."""
    return float(np.percentile(np.abs(u), 99.5))


def input_saturation(u: np.ndarray, fs: float, limit: float | None = None) -> dict | None:
    """Where the input sits at its limit: the samples at ±``limit`` (a run log's controller
    u_lim) or, when it is not known, at the record's largest or smallest input, within
    :data:`RAIL_RTOL`, in stretches of :data:`RAIL_MIN_S` or more (and
    :data:`RAIL_MIN_SAMPLES`), the way a controller's output clipped at ±u_lim is logged. A
    motion that touches its extreme once is not a limit.

    In such a stretch the loop is open: it catches up with the reference afterwards, often
    driving the amplifier from rail to rail, and the model (rigid, the current loop as a
    delay, fitted below the decimation's band) does not describe that motion
    (docs/identification.md, "Input saturation").

    Args:
        u: input [V] (N,). fs: sample rate [Hz]. limit: the input's limit [V] (> 0), or None.
    Returns:
        None when the input never sits at a limit; else {"limits_V": the limits [V] that held
        (the lower first), "share": the share of the samples at them, "stretches": their number,
        "longest_s": the longest [s], "known_limit": whether ``limit`` was given}.
    """
    u = np.asarray(u, dtype=float)
    if u.size == 0:
        return None
    known = limit is not None and math.isfinite(limit) and limit > 0
    tol = RAIL_RTOL * (float(limit) if known else float(np.max(np.abs(u))))
    need = max(RAIL_MIN_SAMPLES, int(np.ceil(RAIL_MIN_S * fs)))
    at, limits, lengths = np.zeros(u.size, dtype=bool), [], []
    sides = ((-float(limit), -1.0), (float(limit), 1.0)) if known else ((float(u.min()), -1.0), (float(u.max()), 1.0))
    for extreme, side in sides:
        on = (u <= extreme + tol) if side < 0 else (u >= extreme - tol)
        starts, ends = runs(on)
        long = (ends - starts) >= need
        if long.any():
            limits.append(extreme)
            lengths.extend((ends - starts)[long])
            for a, b in zip(starts[long], ends[long]):
                at[a:b] = True
    if not lengths:
        return None
    return {"limits_V": limits, "share": float(at.mean()), "stretches": len(lengths),
            "longest_s": float(max(lengths)) / fs, "known_limit": bool(known)}


def choose_n_theta(u: np.ndarray, forced: int | None = None) -> tuple[int, str]:
    """θ1..θ6 or θ1..θ4, with the reason.

    Args:
        u: input [V], shape (N,). forced: 4 or 6 to override.
    """
    reach = input_reach(u)
    if forced in (N_THETA_LINEAR, N_THETA_CUBIC):
        return forced, f"n_theta={forced} requested (|u| reaches {reach:.2f} V at the 99.5th percentile)"
    if reach >= CUBIC_MIN_INPUT_V:
        return N_THETA_CUBIC, (f"theta1..theta6: |u| reaches {reach:.2f} V (99.5th percentile) >= "
                               f"{CUBIC_MIN_INPUT_V:g} V, where u|u| and u^3 depart from u enough to be identified")
    return N_THETA_LINEAR, (f"theta1..theta4: |u| reaches only {reach:.2f} V (99.5th percentile) < "
                            f"{CUBIC_MIN_INPUT_V:g} V; there u|u| and u^3 are nearly collinear with u "
                            "and the cubic terms theta5, theta6 are not identifiable")
