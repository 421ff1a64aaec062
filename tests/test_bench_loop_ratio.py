"""benchmarks/bench_loop.py's verdict on the loop's overruns against the floor's: the ratio of
the totals over turns run in pairs, its bootstrap interval over the turns, and whether that
interval decides the 1.2× (no loop is run: the counts are given)."""

from __future__ import annotations

import importlib.util
import re
from pathlib import Path

_PATH = Path(__file__).resolve().parents[1] / "benchmarks" / "bench_loop.py"
_spec = importlib.util.spec_from_file_location("bench_loop_bench", _PATH)
bl = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(bl)


def _interval(line: str) -> tuple[float, float]:
    lo, hi = re.search(r"interval ([\d.]+)-([\d.]+)x", line).groups()
    return float(lo), float(hi)


def test_a_loop_that_misses_far_fewer_periods_is_decided_below_the_limit():
    line = bl.turns_ratio("missed periods", [3, 4, 5, 2, 6, 1, 4, 3], [20, 30, 25, 40, 22, 35, 28, 31])
    assert "ratio 0.12x" in line
    lo, hi = _interval(line)
    assert lo < 0.12 < hi <= 1.2
    assert "<= 1.2x decided" in line


def test_a_loop_that_misses_far_more_is_decided_above():
    line = bl.turns_ratio("missed periods", [20, 30, 25, 40, 22, 35], [3, 4, 5, 2, 6, 1])
    assert _interval(line)[0] > 1.2
    assert "> 1.2x decided" in line


def test_one_burst_in_one_turn_leaves_the_ratio_undecided():
    # 90 of the loop's 120 missed periods in one turn (a stall of the VM in that turn): the
    # totals say 2.1x, and an interval that took the 176 periods as independent would call
    # that decided (binomial: about 1.5-3.0x); over the turns it is not (0.6x without that turn)
    line = bl.turns_ratio("missed periods", [90, 5, 5, 5, 5, 5, 5], [8, 8, 8, 8, 8, 8, 8])
    assert "ratio 2.14x" in line
    lo, hi = _interval(line)
    assert lo < 1.2 < hi
    assert "does not decide it" in line


def test_the_same_counts_give_the_same_line():
    counts = ([7, 0, 12, 3, 9, 1, 4, 30, 2, 6], [5, 8, 3, 0, 11, 6, 2, 9, 14, 1])
    assert bl.turns_ratio("overrun events", *counts) == bl.turns_ratio("overrun events", *counts)


def test_too_few_turns_or_no_floor_overruns_give_no_interval():
    assert "too few turns" in bl.turns_ratio("overrun events", [1, 2], [3, 1])
    assert "the floor had none" in bl.turns_ratio("overrun events", [1, 2, 4], [0, 0, 0])
    line = bl.turns_ratio("overrun events", [0, 0, 0, 5], [1, 0, 2, 0])
    assert "ratio 1.67x" in line and "no interval" in line
