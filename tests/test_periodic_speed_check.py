"""The position-periodic families' speed check (cogging, force ripple, periodic friction): a force
of position keeps its amplitude at every speed, so a term whose amplitude on the faster half of
the moves differs from the slower half's by more than MAX_SPEED_GROWTH either way is refused, and
so is a term the check cannot judge (too few moving samples slow enough for its period to pass
the position filter: a reading's error at a period of a few mm shows only there). A ratio whose
±2σ interval reaches back within the bounds (a small effect's noisy halves) is not refused. No
identify run: the identifier's ratio and interval are given."""

from __future__ import annotations

import math
from types import SimpleNamespace

import pytest

from motorctl.effects import FAMILIES
from motorctl.effects.periodic import MAX_SPEED_GROWTH


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
