"""identify's residual verdict: on data with an effect no family models (a play of ±0.15 V in
the amplifier's input stage: backlash, a hysteresis with memory), it reports an unexplained structured residual and where it lives, beside whatever
effects it names; on the same loop without the dead-zone it reports none. The data come from a
small simulation written here (a position loop on a mass with viscous and Coulomb friction,
1 kHz, seeded noise), as a CSV with a gain, the way a user's measurement arrives."""

from __future__ import annotations

from pathlib import Path

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
    assert {t["against"] for t in res["tested"]} == {"velocity", "input", "position", "time", "travel", "spectrum"}


def test_a_candidate_refused_on_its_physics_is_reported_unexplained():
    """A last-step candidate that explains a share of the held-out residual and is refused only
    on its physics (a line the loop itself oscillates at) makes the verdict 'unexplained'; one
    that explains too little, or is also weak, does not; a selected one never."""
    from types import SimpleNamespace

    from motorctl.ident.pipeline import add_refused

    def cand(family, gain, *reasons, ok=False):
        return SimpleNamespace(term=SimpleNamespace(family=family), ok=ok, gain=gain, reasons=list(reasons))
    resonance = "the loop itself oscillates at 67.75 Hz (...): a resonance of the loop or the structure"
    step = [cand("periodic_disturbance", 0.10, resonance),
            cand("cogging", 0.20, "not the same force in both directions", "held-out gain 2.0 % < 3 %"),
            cand("stribeck", 0.03, "Stribeck force must be positive"),
            cand("spring", 0.30, ok=True)]
    clean = {"structured": False, "findings": [],
             "text": "the residual shows no structure (against velocity, input, position, time, spectrum)"}
    clean = add_refused(clean, step, [step[3]])
    assert clean["structured"] and [f["against"] for f in clean["findings"]] == ["periodic_disturbance"]
    assert clean["text"].startswith("unexplained structured residual remains: what periodic_disturbance "
                                    "would explain (10 % of the held-out residual), refused: the loop itself")
    quiet = {"structured": False, "findings": [], "text": "the residual shows no structure (against x)"}
    quiet = add_refused(quiet, step[1:], [])
    assert not quiet["structured"] and quiet["text"] == "the residual shows no structure (against x)"


def test_the_loop_check_tells_a_resonance_from_a_disturbance():
    """The shares measured on the default plant (150 Hz mode: inertial 0.80, input 1.01; the
    7.3 Hz example disturbance: inertial 0.0014) and the rigid plant's short log (inertial 6.0,
    where the program's own motion dominates: not judged)."""
    from motorctl.effects.periodic_disturbance import FAMILY
    assert FAMILY.loop_oscillates(0.80, 1.01)
    assert not FAMILY.loop_oscillates(0.0014, 1.0)
    assert not FAMILY.loop_oscillates(6.0, 7.7)
    assert not FAMILY.loop_oscillates(0.8, 0.05)       # the input does not follow: above the bandwidth


def test_the_stick_and_slip_at_rest_is_the_stiction_s_not_a_phantom_or_a_warning(tmp_path):
    """The default plant with a 100 N/m spring (configs/gantry.yaml, X, 20 s, seed 4, its own
    0.5 N of force noise): the C2 loop hunts at rest under the plant's stiction, and the short
    slips of that hunting are what no column describes. An asymmetric friction of 2.5 N (no
    such friction on the plant) explained them through the nominal θ it moved, 78 % of what it
    explained lying where the stiction holds the carriage, and was named beside the spring; then
    a Stribeck friction at the top of its range (1 m/s), 116 % there (the samples in motion
    worse), was warned as an unexplained structure. Both are now the stiction's
    (``MAX_HELD_SHARE``): the plant's effects only, the spring within 10 %, no warning, and the
    refusal says why."""
    from motorctl.commission.tune import make_log
    from motorctl.ident.pipeline import identify_record
    from motorctl.ident.synth import EXAMPLES
    log = str(tmp_path / "spring_seed4.log")
    make_log(log, EXAMPLES["spring"], duration_s=20.0, seed=4, axis="X", noise_N=None,
             base=Path(__file__).resolve().parents[1] / "configs" / "gantry.yaml")
    idf, s = identify_record(load_record(log, axis="X"))
    found = {e["name"]: e["parameters"] for e in s["effects"]}
    assert set(found) == {"stiction", "spring", "input_delay"}, found
    assert found["spring"]["stiffness_N_per_m"] == pytest.approx(EXAMPLES["spring"]["spring"]["stiffness_N_per_m"],
                                                                 rel=0.1)
    assert not s["residual"]["structured"], s["residual"]["text"]
    held = [c for step in s["candidates"] for c in step if any(r.startswith("explained where held")
                                                               for r in c["reasons"])]
    assert {"asymmetric_friction", "stribeck"} <= {c["name"] for c in held}, held


def test_the_stick_and_slip_beyond_stictions_band_is_stictions_not_a_warning(tmp_path):
    """The default config's Y axis (52 kg, its 120 Hz mode), nothing added, 8 s, seed 1: the
    last step's Stribeck candidate sits at its search's 2 mm/s edge with a negative force and
    explains 26 % of the held-out residual, nearly all of it at 0.5-2 mm/s, just beyond the
    named stiction's band: the stick and slip at rest that stiction's model leaves. It is
    counted as stiction's, as the velocity test counts a structure near zero velocity; the
    code before warned "unexplained structured residual" on this clean log."""
    from motorctl.commission.tune import make_log
    log = tmp_path / "y.mclog"
    make_log(str(log), None, duration_s=8.0, seed=1, noise_N=None, axis="Y",
             base=Path(__file__).resolve().parents[1] / "configs" / "gantry.yaml")
    idf = Identifier(load_record(str(log))).run()
    s = summarise(idf)
    assert "stiction" in [e["name"] for e in s["effects"]], s["effects"]
    r = s["residual"]
    assert not r["structured"], r["text"]
    counted = [t for t in r["tested"] if t["against"] == "stribeck"]
    assert counted and counted[0]["explained_by"] == "stiction" and not counted[0]["structured"], r["tested"]
    assert "counted as stiction's" in r["text"]
