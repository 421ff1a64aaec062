"""identify's shortcuts give the results of the long way (docs/identification.md, "Speed"): the
decimation of a sine in closed form and the SSE of a candidate from the base's cached normal
equations, each against the exact computation on a short log of the simulated gantry with
cogging.

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
from motorctl.ident.select import Identifier, Term, _coef
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
    # a candidate whose columns change after a first fit on the same base: its own SSE
    t = Term("cogging", 0.032, idf.dec_cols("cogging", 0.032))
    first = idf.sse([stiction, t])
    t.cols = idf.dec_cols("cogging", 0.045)
    assert idf.sse([stiction, t]) != first


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
