"""identify's shortcuts give the results of the long way (docs/identification.md, "Speed"): the
decimation of a sine in closed form, the SSE of a candidate from the base's cached normal
equations and the input delay's grid fitted at once, each against the exact computation on a
short log of the simulated gantry with cogging.

(The same check on 20 s logs of the default plant and seven families, against another source
tree: ``benchmarks/ident_equivalence.py``; the times: ``benchmarks/bench_ident.py``.)
"""

from __future__ import annotations

import pickle

import numpy as np
import pytest

from motorctl.commission.tune import make_log
from motorctl.effects import family
from motorctl.effects.periodic import fourier
from motorctl.ident.data import load_record
from motorctl.ident.effects import parameters
from motorctl.ident.idim import ls_coef as _coef
from motorctl.ident.records import Term
from motorctl.ident.select import Identifier
from motorctl.ident.synth import EXAMPLES

DURATION_S = 5.0


@pytest.fixture(scope="module")
def record(tmp_path_factory):
    path = tmp_path_factory.mktemp("ident_speed") / "cogging.log"
    make_log(str(path), EXAMPLES["cogging"], duration_s=DURATION_S, seed=1)
    return load_record(str(path))


def _found(idf):
    _, betas = idf.coef_split(idf.final, idf.terms)
    return {t.family: parameters(t.family, t.h, b, idf.rec.gain, idf.p.fs) for t, b in zip(idf.terms, betas)}


def test_a_sine_in_time_decimates_to_the_gain_times_the_sine(record):
    idf = Identifier(record)
    p = idf.p
    for f in (0.7, 7.3, 40.0, 80.0):
        exact = p.dec(fourier(p.t, 1.0 / f, 1))
        closed = family("periodic_disturbance").decimated_columns(f, p)
        assert closed.shape == exact.shape
        assert np.linalg.norm(closed - exact) <= 2e-4 * np.linalg.norm(exact), f
    assert 0.97 < p.dec_gain(0.0) < 1.0                 # the Chebyshev filters' ripple at 0 Hz
    assert p.dec_gain(np.array([20.0, 400.0])).shape == (2,) and p.dec_gain(400.0) < 1e-6


def test_sse_from_the_cached_base_is_the_joint_fit(record):
    idf = Identifier(record)
    stiction = idf.term("stiction", 5e-4)            # weighs the other terms' columns
    for base in ([], [stiction], [stiction, idf.term("spring", None)]):
        for fam, h in (("cogging", 0.032), ("stribeck", 0.03), ("input_delay", 1.0), ("stiction", 1e-3)):
            if any(t.family == fam for t in base):
                continue
            terms = base + [idf.term(fam, h)]
            phi, y = idf.design(terms)
            r = y - phi @ _coef(phi, y)
            assert idf.sse(terms) == pytest.approx(float(r @ r), rel=1e-9), (fam, len(base))
    # the cached normal equations stay in their process: a pickled identifier fits the same
    again = pickle.loads(pickle.dumps(idf))
    terms = [stiction, idf.term("cogging", 0.032)]
    assert again.sse([again.term("stiction", 5e-4), again.term("cogging", 0.032)]) == pytest.approx(
        idf.sse(terms), rel=1e-12)
    # a candidate of other columns after a first fit on the same base: its own SSE
    t = Term("cogging", 0.032, idf.dec_cols("cogging", 0.032))
    first = idf.sse([stiction, t])
    assert idf.sse([stiction, Term("cogging", 0.032, idf.dec_cols("cogging", 0.045))]) != first


def _delay_sses_one_by_one(idf, base, grid, band=None, rows=None):
    """The input-delay SSEs the long way: for each delay its own shifted columns and joint fit
    (:func:`~motorctl.ident.idim.ls_coef`, as every fit of the identifier)."""
    p = idf.p
    ud = p.dec(idf.input_columns(idf.zoh))
    m = ud.shape[0]
    spec = np.fft.rfft(ud, axis=0)
    w = 2 * np.pi * np.fft.rfftfreq(m)
    phi0, _ = idf.design(base)
    if band is not None:
        f = np.fft.rfftfreq(m, p.nd / p.fs)
        keep = ((f >= band[0]) & (f < band[1])).astype(float)[:, None]
        spec = spec * keep
        phi0 = np.fft.irfft(np.fft.rfft(phi0, axis=0) * keep, n=m, axis=0)
    out = []
    for d in grid:
        sh = np.fft.irfft(spec * np.exp(-1j * w * (d / p.nd))[:, None], n=m, axis=0)
        phi = phi0.copy()
        if idf.n_theta == 6:
            phi[:, 4], phi[:, 5] = -sh[:, 1], -sh[:, 2]
        y = sh[:, 0]
        if rows is None:
            r = (y - phi @ _coef(phi, y))[4:-4]
        else:
            k = rows.copy()
            k[:4] = k[-4:] = False
            r = y[k] - phi[k] @ _coef(phi[k], y[k])
        out.append(float(r @ r))
    return np.array(out)


def test_input_delay_sses_of_a_whole_grid_at_once_are_each_delay_s_own_fit(record, monkeypatch):
    """:func:`motorctl.ident.probes.delay_sses` shifts and fits every delay of the grid at once, the columns
    that do not move with the delay factored once: each SSE is that delay's own joint fit, with
    θ1..θ4 and θ1..θ6, a base that weighs the others (stiction), on the moving rows, on a band,
    and with the grid split into chunks."""
    import motorctl.ident.probes as probes
    first = Identifier(record).fits
    base = [first.term("stiction", 5e-4), first.term("cogging", 0.032)]
    grid = np.arange(0.0, 12.0, 0.7)
    moving = np.abs(first.p.v_d) > 1e-3
    for n_theta in (6, 4):
        idf = first.with_structure(n_theta=n_theta)
        for kw in ({}, {"rows": moving}, {"band": (15.0, 39.0)}):
            ref = _delay_sses_one_by_one(idf, base, grid, **kw)
            assert idf.delay_sses(base, grid, **kw) == pytest.approx(ref, rel=1e-10), (n_theta, kw)
    monkeypatch.setattr(probes, "DELAY_CHUNK_ELEMENTS", 3 * len(idf.p.t_d) * 4)     # 4 delays a chunk
    assert idf.delay_sses([], grid) == pytest.approx(_delay_sses_one_by_one(idf, [], grid), rel=1e-10)


def test_closed_form_disturbance_columns_give_the_filtered_result(record, monkeypatch):
    fast = Identifier(record).run()
    monkeypatch.setattr(type(family("periodic_disturbance")), "decimated_columns", lambda self, h, p: None)
    slow = Identifier(record).run()
    a, b = _found(slow), _found(fast)
    assert list(a) == list(b) and "cogging" in a
    for name in a:
        for k, v in a[name].items():
            assert np.allclose(np.atleast_1d(b[name][k]), np.atleast_1d(v), rtol=1e-6, atol=1e-9), (name, k)
    # the search's candidates were judged alike, the periodic disturbance's among them
    pd_fast = [c for step in fast.steps for c in step if c.term.family == "periodic_disturbance"]
    pd_slow = [c for step in slow.steps for c in step if c.term.family == "periodic_disturbance"]
    assert pd_fast and [c.ok for c in pd_fast] == [c.ok for c in pd_slow]
    assert np.allclose([c.term.h for c in pd_fast], [c.term.h for c in pd_slow], rtol=1e-6)


def test_parallel_decimation_is_the_zero_phase_cascade_without_folding():
    """The decimation in the frequency domain (the cascade's |H|² on the bins kept) gives the cascade's filtfilt per stage away from the ends, keeps the
    full-rate sample nd·k as sample k, and removes what lies above the new Nyquist frequency
    instead of folding it into the band kept."""
    from scipy.signal import sosfiltfilt

    from motorctl.ident.idim import _decimation_sos, _stages, decimation_gain, parallel_decimate
    fs, nd, n = 5000.0, 20, 60001
    t = np.arange(n) / fs
    rng = np.random.default_rng(3)
    slow = np.cumsum(np.cumsum(rng.standard_normal(n))) * 1e-6           # a smooth, non-periodic drift
    x = np.column_stack([slow, np.sin(2 * np.pi * 37.0 * t), np.sign(np.sin(2 * np.pi * 1.3 * t))])
    cascade = x
    for q in _stages(nd):
        cascade = sosfiltfilt(_decimation_sos(q), cascade, axis=0)[::q]
    dec = parallel_decimate(x, nd)
    assert dec.shape == cascade.shape == (-(-n // nd), 3)
    mid = slice(40, -40)                                  # the ends (0.16 s) off, as Prepared.keep does
    for j in range(3):
        err = np.max(np.abs(dec[mid, j] - cascade[mid, j])) / np.max(np.abs(cascade[mid, j]))
        assert err < 2e-4, j
    # sample k is the full-rate sample nd·k: a 37 Hz sine comes out as its gain times the sine there
    assert np.max(np.abs(dec[mid, 1] - decimation_gain(fs, nd, 37.0) * x[::nd, 1][mid])) < 1e-4
    assert np.array_equal(parallel_decimate(x[:, 1], nd), dec[:, 1])
    # 130 Hz, above the new Nyquist frequency (125 Hz): folded to 120 Hz by the cascade at its gain
    # there (1.2e-4), removed here (what is left, 5e-6, is the leakage of the record's ends)
    above = np.sin(2 * np.pi * 130.0 * t)
    folded = above
    for q in _stages(nd):
        folded = sosfiltfilt(_decimation_sos(q), folded)[::q]
    inner = slice(200, -200)
    assert np.max(np.abs(parallel_decimate(above, nd)[inner])) < 1e-5 < 1e-4 < np.max(np.abs(folded[inner]))


def test_parallel_decimation_is_scipy_s_fourier_resampling_and_single_precision_is_its_round_off():
    """The kept bins weighed by the cascade's gain are scipy.signal.resample with that window
    (to round-off), on a long column and on one shorter than its extension (reflected as often
    as needed); the single-precision transforms stay within 2e-6 of each column's RMS."""
    from scipy.fft import fftfreq, next_fast_len
    from scipy.signal import resample

    from motorctl.ident.idim import EXTENSION, decimation_gain, parallel_decimate

    def by_resample(m, nd):                  # the window of |H|² over every bin, as scipy takes it
        n = m.shape[0]
        lo = EXTENSION * nd
        length = nd * next_fast_len(-(-(n + 2 * lo) // nd), real=True)
        rows = np.pad(m.T, ((0, 0), (lo, length - n - lo)), mode="reflect", reflect_type="odd")
        win = decimation_gain(1.0, nd, np.abs(fftfreq(length)))
        return resample(rows, length // nd, window=win, axis=-1)[:, EXTENSION:EXTENSION + -(-n // nd)].T

    rng = np.random.default_rng(5)
    for n, nd in ((60001, 20), (100003, 10), (500, 20)):
        t = np.arange(n) / 5000.0
        x = np.column_stack([0.2 + 0.1 * np.sin(2 * np.pi * 0.3 * t), np.cos(2 * np.pi * 41.0 * t),
                             np.sign(np.sin(2 * np.pi * 1.3 * t)), rng.standard_normal(n)])
        ref = by_resample(x, nd)
        double, single = parallel_decimate(x, nd), parallel_decimate(x, nd, single=True)
        assert double.shape == single.shape == ref.shape and single.dtype == np.float64
        scale = np.sqrt(np.mean(ref ** 2, axis=0))
        assert np.all(np.max(np.abs(double - ref), axis=0) < 1e-12 * scale), n
        err = np.max(np.abs(single - ref), axis=0) / scale
        assert np.all(err < 2e-6) and np.all(err > 1e-9), (n, err)     # float32's, not float64's


def test_the_spatial_periodogram_is_scipy_s_lomb_scargle_and_its_basis_is_kept_per_abscissa():
    """The binned periodogram equals scipy.signal.lombscargle on the same bins (normalised, the
    bins' counts as weights) to round-off, for two residuals on the same positions (the second
    from the kept basis) and for another abscissa (a new basis)."""
    from scipy.signal import lombscargle

    from motorctl.effects import periodic
    from motorctl.effects.periodic import BIN_SHARE, period_grid, spatial_periodogram

    def by_scipy(x, r, periods):
        dx = BIN_SHARE * float(periods.min())
        idx = ((x - x.min()) / dx).astype(np.int64)
        n = np.bincount(idx)
        full = np.flatnonzero(n)
        rb = np.bincount(idx, weights=r - r.mean())[full] / n[full]
        return lombscargle(x.min() + (full + 0.5) * dx, rb - np.average(rb, weights=n[full]),
                           2.0 * np.pi / periods, normalize=True, weights=n[full].astype(float))

    rng = np.random.default_rng(11)
    grid = period_grid(0.4)
    periodic._bases.clear()
    for lo, hi in ((0.1, 0.3), (0.1, 0.3), (0.05, 0.35)):
        x = np.sort(rng.uniform(lo, hi, 700))
        for r in (0.3 * np.sin(2 * np.pi * x / 0.032) + rng.standard_normal(700), rng.standard_normal(700)):
            ref = by_scipy(x, r, grid)
            got = spatial_periodogram(x, r, grid)
            assert np.max(np.abs(got - ref)) < 1e-12 * np.max(ref)
    assert len(periodic._bases) == 3         # one basis per abscissa (positions drawn three times)
