"""The position-periodic families' speed check (cogging, force ripple, periodic friction): a force
of position keeps its amplitude at every speed, so a term whose amplitude on the faster half of
the moves differs from the slower half's by more than MAX_SPEED_GROWTH either way is refused, and
so is a term the check cannot judge (too few moving samples slow enough for its period to pass
the position filter: a reading's error at a period of a few mm shows only there). A ratio whose
±2σ interval reaches back within the bounds (a small effect's noisy halves) is not refused.
A force of position acts at every thrust as well: a term that explains less than MIN_TAIL_KEPT of
its share without the samples at the largest |u| is refused, and the residual verdict does not
count that reason alone as a structure. The identifier's ratio, interval and shares are given,
but for one identify run on a plant whose mode the cruise excites (the mass taken from the
whole record)."""

from __future__ import annotations

import math
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from motorctl.effects import FAMILIES
from motorctl.effects.periodic import FEW_SAMPLES, MAX_SPEED_GROWTH, MIN_TAIL_KEPT, THRUST_TAIL


def _reasons(family: str, growth: float, se: float = 0.0) -> list[str]:
    interval = (growth, growth - 2.0 * se, growth + 2.0 * se)
    ctx = SimpleNamespace(p=SimpleNamespace(fq=250.0), speed_growth_interval=lambda term, base, period: interval)
    term = SimpleNamespace(family=family, h=2.883e-3, cols=None)
    return FAMILIES[family].speed_check(ctx, term, [])


@pytest.mark.parametrize("family", ["cogging", "force_ripple", "periodic_friction"])
def test_a_force_of_position_keeps_its_amplitude_at_every_speed(family):
    # the true effects' ratios on the default and rigid plants lie in 0.77-1.68
    for growth in (1.0 / MAX_SPEED_GROWTH + 1e-9, 0.77, 1.0, 1.68, MAX_SPEED_GROWTH):
        assert _reasons(family, growth) == [], growth
    grows = _reasons(family, 2.72)
    assert len(grows) == 1 and "grows with the speed (x2.72" in grows[0]
    falls = _reasons(family, 0.17)
    assert len(falls) == 1 and "falls with the speed (x0.17" in falls[0]


@pytest.mark.parametrize("family", ["cogging", "force_ripple", "periodic_friction"])
def test_a_ratio_out_of_bounds_but_not_significantly_is_not_refused(family):
    # a 3.6 N cogging on the default plant: x2.15 from the slower to the faster half, its
    # amplitude on each half known to a few tenths of itself
    assert _reasons(family, 2.15, se=0.3) == []
    assert _reasons(family, 0.45, se=0.1) == []
    grows = _reasons(family, 3.0, se=0.2)
    assert len(grows) == 1 and "at least x2.60" in grows[0]
    falls = _reasons(family, 0.2, se=0.05)
    assert len(falls) == 1 and "at most x0.30" in falls[0]


@pytest.mark.parametrize("family", ["cogging", "force_ripple"])
def test_a_term_the_speed_check_cannot_judge_is_refused(family):
    out = _reasons(family, math.nan)
    assert len(out) == 1 and "too few moving samples" in out[0]
    assert "0.721 m/s" in out[0]          # f_q·P = 250 Hz · 2.883 mm, the speed the period passes
    assert len(_reasons(family, math.inf)) == 1


def test_the_speed_check_takes_the_mass_from_the_whole_record(tmp_path):
    """configs/gantry-half-mode.yaml (X's mode at 175 Hz), cogging 6 / 2 N at 32 mm, 20 s, seed 2.
    In the cruise at 2 m/s, the faster half of the moves, the carriage accelerates only at the
    cogging's own 62.5 Hz, as the loop leaves it: θ1 fitted there alone traded with the cogging's
    columns (0.124 for the record's 0.156) and its amplitude came out x2.87 the slower half's, so
    cogging was refused and nothing named. With θ1 the record's the ratio is x0.74, and identify
    names cogging within 10 %, without a warning."""
    from motorctl.commission.tune import make_log
    from motorctl.ident.data import load_record
    from motorctl.ident.pipeline import identify_record
    from motorctl.ident.select import Identifier
    root = Path(__file__).resolve().parents[1]
    path = tmp_path / "cogging_half_mode.mclog"
    make_log(str(path), {"cogging": {"amplitudes_N": [6.0, 2.0], "period_m": 0.032, "phases_rad": [0.3, 1.0]}},
             duration_s=20.0, seed=2, noise_N=None, base=str(root / "configs" / "gantry-half-mode.yaml"))
    rec = load_record(str(path), None, None, axis="X")
    idf = Identifier(rec)
    growth, lo, hi = idf.speed_growth_interval(idf.term("cogging", 0.032), [], 0.032)
    assert 1.0 / MAX_SPEED_GROWTH <= growth <= MAX_SPEED_GROWTH, (growth, lo, hi)
    _, s = identify_record(rec)
    found = {e["name"]: e["parameters"] for e in s["effects"]}
    assert "cogging" in found, (list(found), s["residual"]["text"])
    assert found["cogging"]["amplitudes_N"] == pytest.approx([6.0, 2.0], rel=0.1)
    assert found["cogging"]["period_m"] == pytest.approx(0.032, rel=0.01)
    assert not s["residual"]["structured"], s["residual"]["text"]


# ---------------------------------------------------------------- the largest thrusts (thrust_check)
def _thrust_reasons(family: str, full: float, kept: float, u_d):
    """The thrust check's reasons with the identifier's shares given: ``full`` on the moving
    samples, ``kept`` on those without the largest |u|; also the rows it asked about."""
    asked = []

    def shares(term, base, *rows):
        asked.extend(r.copy() for r in rows)
        return full, kept
    u_d = np.asarray(u_d, dtype=float)
    ctx = SimpleNamespace(p=SimpleNamespace(u_d=u_d), moving=np.ones(u_d.size, dtype=bool), explained_shares=shares)
    term = SimpleNamespace(family=family, h=0.0716, cols=None)
    return FAMILIES[family].thrust_check(ctx, term, []), asked


@pytest.mark.parametrize("family", ["cogging", "force_ripple", "periodic_friction"])
def test_a_force_of_position_is_seen_away_from_the_largest_thrusts(family):
    u = np.linspace(-10.0, 10.0, 1001)
    # the true effects keep 0.73-1.00 of their share without the largest thrusts
    for kept in (0.4, 0.73 * 0.4, MIN_TAIL_KEPT * 0.4):
        out, asked = _thrust_reasons(family, 0.4, kept, u)
        assert out == [], kept
    # the rows left out are the THRUST_TAIL of the samples with the largest |u|, both signs
    full_rows, kept_rows = asked
    assert full_rows.all()
    left = np.abs(u[~kept_rows])
    assert (~kept_rows).sum() == pytest.approx(THRUST_TAIL * u.size, abs=2)
    assert left.min() >= np.abs(u[kept_rows]).max()
    # a clean plant driven to its limit: a 72 mm "ripple" keeps 0.14-0.29 of its share
    out, _ = _thrust_reasons(family, 0.234, 0.033, u)
    assert len(out) == 1 and out[0].startswith(FEW_SAMPLES), out
    assert "23.4 %" in out[0] and "3.3 %" in out[0]


def test_a_candidate_refused_only_for_its_few_samples_is_not_a_structure():
    """The residual verdict reports a candidate refused on its physics; one refused because its
    evidence is a few samples at the largest thrusts is not reported for that alone, and that
    reason does not hide what its other reasons say (a ripple not the same both ways)."""
    from motorctl.ident.select import REFUSED_GAIN, refused_on_physics

    def cand(*reasons):
        return SimpleNamespace(ok=False, gain=2 * REFUSED_GAIN, reasons=list(reasons))
    few = f"{FEW_SAMPLES}: it explains 23.4 % of the moving samples' residual, 3.3 % without ..."
    physics = "not the same force in both directions (agreement 0.04 < 0.5)"
    assert not refused_on_physics(cand(few))
    assert refused_on_physics(cand(physics, few))
    assert refused_on_physics(cand(physics))
    assert not refused_on_physics(cand(physics, few, "held-out gain 1.8 % < 3 %"))


def test_the_explained_share_is_fitted_on_the_rows_given():
    """Identifier.explained_shares: the share of the base model's residual SSE that the term's
    columns explain, both fitted on the rows given only."""
    from motorctl.ident.select import Identifier
    rng = np.random.default_rng(7)
    m = 2000
    phi0 = rng.standard_normal((m, 3))
    noise = 0.1 * rng.standard_normal(m)
    tail = np.zeros(m, dtype=bool)
    tail[-40:] = True
    # a column ten times larger on the last 2 % of the rows (a thrust fraction at the largest
    # |u|), and a residual that follows it there only
    col = (rng.standard_normal(m) * np.where(tail, 10.0, 1.0))[:, None]
    y = phi0 @ np.array([1.0, -2.0, 0.5]) + np.where(tail, col[:, 0], 0.0) + noise
    fake = SimpleNamespace(design=lambda terms: (np.hstack([phi0] + [col] * len(terms)), y))
    term = SimpleNamespace(cols=col)
    full, kept = Identifier.explained_shares(fake, term, [], np.ones(m, dtype=bool), ~tail)
    assert full > 0.5 and abs(kept) < 0.01, (full, kept)
    # a term that explains the residual on every row keeps its share without the tail
    y_all = phi0 @ np.array([1.0, -2.0, 0.5]) + 0.3 * col[:, 0] + noise
    fake_all = SimpleNamespace(design=lambda terms: (np.hstack([phi0] + [col] * len(terms)), y_all))
    assert Identifier.explained_shares(fake_all, term, [], ~tail)[0] > 0.8
    assert Identifier.explained_shares(fake, term, [], tail & (np.arange(m) % 7 == 0)) == (0.0,)   # too few rows
