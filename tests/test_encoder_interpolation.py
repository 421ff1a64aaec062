"""The encoder_interpolation family told from cogging: the same position loop (a mass with
viscous and Coulomb friction, 1 kHz, seeded noise) once with an interpolation error of the
reading (y = x + a sin(2πx/P), no force) and once with a cogging force of the same period;
identify names the reading's error in the first (period and amplitude near the truth) and
cogging in the second, never the other. The data are written here as a CSV with a gain, the
way a user's measurement arrives."""

from __future__ import annotations

import numpy as np
import pytest

from motorctl.effects import FAMILIES
from motorctl.effects.encoder_interpolation import analytic_columns, reading_columns
from motorctl.ident.data import load_record
from motorctl.ident.pipeline import compensation_from_fit, summarise
from motorctl.ident.select import Identifier
from harness import LOOP_A1, loop_csv

A1 = LOOP_A1
P = 2e-3                                  # signal period [m]


def _loop_csv(path, enc_m: float = 0.0, cogging_N: float = 0.0, n: int = 20000, ts: float = 1e-3) -> str:
    """Slow sweeps (≤ 60 mm/s: the 2 mm error at up to 30 Hz, below the 100 Hz position filter
    of a 1 kHz record)."""
    t = np.arange(n) * ts
    xd = 0.02 * np.sin(2 * np.pi * 0.25 * t) + 0.01 * np.sin(2 * np.pi * 0.6 * t + 0.4)
    return loop_csv(path, xd, ts, y_noise_m=2e-8, u_noise_V=0.01, enc_m=enc_m, cogging_N=cogging_N, period_m=P)


@pytest.fixture(scope="module")
def found(tmp_path_factory):
    d = tmp_path_factory.mktemp("enc")
    out = {}
    for name, kw in (("reading", {"enc_m": 5e-6}), ("force", {"cogging_N": 3.0})):
        idf = Identifier(load_record(_loop_csv(d / f"{name}.csv", **kw), None, str(A1))).run()
        out[name] = summarise(idf)
        out[name + "_idf"] = idf
    return out


def test_a_reading_error_is_named_encoder_interpolation_not_a_force(found):
    s = found["reading"]
    names = [e["name"] for e in s["effects"]]
    assert "encoder_interpolation" in names, names
    assert not {"cogging", "force_ripple", "periodic_disturbance", "periodic_friction"} & set(names), names
    par = s["effects"][names.index("encoder_interpolation")]["parameters"]
    assert par["signal_period_m"] == pytest.approx(P, rel=0.02)
    assert par["amplitudes_m"][0] == pytest.approx(5e-6, rel=0.25)


def test_a_cogging_force_of_the_same_period_is_named_cogging(found):
    names = [e["name"] for e in found["force"]["effects"]]
    assert "cogging" in names and "encoder_interpolation" not in names, names


def test_an_effect_not_told_from_a_look_alike_is_not_compensated(found):
    """tune and --write-config compensate only what identify names: the cogging found above is
    compensated; the same fit marked as not told from the reading's error is not."""
    idf = found["force_idf"]
    comp, _, skipped = compensation_from_fit(idf)
    assert "cogging" in comp and "cogging" not in skipped
    ev = next(ev for ev, _ in idf.accepted if ev.term.family == "cogging")
    saved = ev.rivals
    try:
        ev.rivals = [("encoder_interpolation", 0.2)]
        comp, _, skipped = compensation_from_fit(idf)
    finally:
        ev.rivals = saved
    assert "cogging" not in comp and "cogging" in skipped


def test_columns_are_the_second_derivative_of_the_reading_error():
    """The exact columns (filtered, differentiated) match the analytic ë at a constant speed
    well below the filter, and the family compensates nothing (an error of the reading)."""
    fs, fq, v0 = 1000.0, 100.0, 0.02
    t = np.arange(4000) / fs
    x = v0 * t
    exact = reading_columns(x, fs, fq, P)
    ana = analytic_columns(x, np.full_like(x, v0), np.zeros_like(x), P)
    mid = slice(500, 3500)
    assert np.allclose(exact[mid], ana[mid], rtol=0, atol=0.02 * np.abs(ana[mid]).max())
    fam = FAMILIES["encoder_interpolation"]
    assert not fam.has_compensation and fam.plant_term((3e-6, P), 1e-3) is None
