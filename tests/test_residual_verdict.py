"""identify's residual verdict: on data with an effect no family models (a play of ±0.15 V in
the amplifier's input stage: backlash, a hysteresis with memory), it reports an unexplained structured residual and where it lives, beside whatever
effects it names; on the same loop without the dead-zone it reports none. The data come from a
small simulation written here (a position loop on a mass with viscous and Coulomb friction,
1 kHz, seeded noise), as a CSV with a gain, the way a user's measurement arrives."""

from __future__ import annotations

import numpy as np
import pytest

from motorctl.ident.data import load_record
from motorctl.ident.pipeline import summarise
from motorctl.ident.select import Identifier
from harness import LOOP_A1, loop_csv

A1 = LOOP_A1


def _loop_csv(path, play_V: float, n: int = 20000, ts: float = 1e-3) -> str:
    t = np.arange(n) * ts
    xd = 0.05 * np.sin(2 * np.pi * 0.5 * t) + 0.02 * np.sin(2 * np.pi * 1.3 * t + 0.4)
    return loop_csv(path, xd, ts, play_V=play_V)


@pytest.fixture(scope="module")
def verdicts(tmp_path_factory):
    out = {}
    for name, dz in (("play", 0.15), ("clean", 0.0)):
        path = _loop_csv(tmp_path_factory.mktemp("v") / f"{name}.csv", dz)
        out[name] = summarise(Identifier(load_record(path, None, str(A1))).run())
    return out


def test_an_effect_without_family_is_reported_unexplained(verdicts):
    s = verdicts["play"]
    res = s["residual"]
    assert res["structured"], res["tested"]
    inputs = [f for f in res["findings"] if f["against"] == "input"]
    assert inputs, res["findings"]
    # where: in the input
    f = inputs[0]
    assert "u" in f["where"] and f["share"] > 0.1, f
    assert "unexplained structured residual remains" in res["text"]


def test_the_same_loop_without_it_leaves_no_structure(verdicts):
    res = verdicts["clean"]["residual"]
    assert not res["structured"], res["findings"]
    assert {t["against"] for t in res["tested"]} == {"velocity", "input", "position", "time", "spectrum"}
