"""benchmarks/tune_families.py's row of several seeds: the run of the median damage removed,
every seed's figure beside it (no simulation: tune's results are given)."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

_PATH = Path(__file__).resolve().parents[1] / "benchmarks" / "tune_families.py"
_spec = importlib.util.spec_from_file_location("tune_families_bench", _PATH)
tf = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(tf)


def _res(d, l2_after=2.7, e_m_ok=True):
    """A tune result with the keys the table reads (floor 2.5, before 3.3 µm)."""
    idx = lambda l2: {"L2_um": l2, "e_M_um": 20.0}   # noqa: E731
    return {"damage_removed": d, "e_M_not_worse": e_m_ok, "effects": [{"name": "spring"}],
            "compare": {"before": idx(3.3), "after": idx(l2_after), "floor": idx(2.5)}}


def test_median_of_three_seeds_is_the_middle_run():
    runs = [_res(0.65, 2.78), _res(0.93, 2.56), _res(0.60, 2.82)]
    res, figs = tf.median_run(runs)
    assert res is runs[0]
    assert figs == [0.65, 0.93, 0.60]


def test_a_failed_seed_counts_lowest_and_even_counts_take_the_lower_middle():
    refused = {"refused": "no motion"}
    res, figs = tf.median_run([_res(0.9), refused, _res(0.85)])
    assert res["damage_removed"] == 0.85 and figs == [0.9, None, 0.85]
    res, _ = tf.median_run([_res(0.9), refused, _res(0.85), _res(0.1)])
    assert res["damage_removed"] == 0.1
    res, _ = tf.median_run([refused, refused, _res(0.9)])
    assert res is refused
    with pytest.raises(ValueError):
        tf.median_run([])


def test_row_shows_every_seed_beside_the_median():
    runs = [_res(0.65, 2.78), _res(0.93, 2.56), _res(0.60, 2.82)]
    res, figs = tf.median_run(runs)
    r = tf.row("spring", res, "stiffness_N_per_m 159", figs)
    assert r[5] == "0.65 (seeds 0.65/0.93/0.60)"
    assert r[4].startswith("2.780 / 20.00")
    assert tf.row("spring", res, "x", [0.65])[5] == "0.65"
    assert tf.row("spring", {"refused": "x"}, "x", [None, None, None])[5] == "—"
