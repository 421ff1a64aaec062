"""identify on records of an independent simulation (benchmarks/ident_unmodelled.py: a PID loop on
a 15 kg linear motor with Karnopp friction, 1 kHz, 12 s, numpy only) with an effect no family
models: the warning, and no single wrong name.

* a force constant falling 20 % towards both ends of the stroke: on a back-and-forth program the
  input's sign goes with the end, so the lost thrust looked like a negative spring (−53 N/m,
  named beside the warning on 3 of 3 seeds); a spring restores, so a stiffness ≤ 0 is refused;
* a 10 kg load held with ±150 µm of play: its impacts lag the carriage, which fitted an input
  delay of 3.6 ms (3 of 3 seeds); the check that a delay's phase says the same at low and high
  frequencies did not run on a 1 kHz record (its bands began at a fixed 15 Hz, above a quarter
  of the decimated band's 40 Hz), and now does;
* nothing injected: a cogging of about 1 mm fitted the force the loop holds at the positions the
  carriage rests at (a position-periodic force must explain the moving samples too);
* two forces of position near a 2:1 ratio (simulation B's 23 and 11 mm): one cogging of 22.08 mm
  between them, its second harmonic taking the 11 mm force (a term's harmonics must be
  harmonics of one period).

Each record is simulated with a fixed seed: the same verdict on every run."""

from __future__ import annotations

import importlib.util

import pytest

from motorctl.ident.data import load_record
from motorctl.ident.pipeline import summarise
from motorctl.ident.select import Identifier

from conftest import REPO


@pytest.fixture(scope="module")
def bench():
    spec = importlib.util.spec_from_file_location("ident_unmodelled", REPO / "benchmarks" / "ident_unmodelled.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _identify(bench, case: str, seed: int, tmp_path, sim: str = "a") -> dict:
    """identify's summary of simulation ``sim``'s record of ``case`` at ``seed``."""
    b = bench.SIMS[sim]
    path = b["simulate"](b["cases"][case][0], seed, tmp_path / f"{case}.csv")
    return summarise(Identifier(load_record(path, None, str(b["gain"]))).run())


def test_thrust_lost_at_the_stroke_ends_is_warned_and_named_no_spring(bench, tmp_path):
    s = _identify(bench, "end_effect20", 1, tmp_path)
    assert "spring" not in {e["name"] for e in s["effects"]}, s["effects"]
    assert s["residual"]["structured"]


def test_a_load_in_play_on_a_1khz_record_is_warned_and_named_no_delay(bench, tmp_path):
    s = _identify(bench, "backlash150", 1, tmp_path)
    assert "input_delay" not in {e["name"] for e in s["effects"]}, s["effects"]
    assert s["residual"]["structured"]


def test_a_clean_record_names_no_millimetre_cogging(bench, tmp_path):
    """Nothing injected (seed 2): a cogging of 1.07 mm was named beside stiction and Stribeck,
    explaining 27 % of the record's residual and 3 % of the moving samples': the force the loop
    holds at the few positions the carriage rests at, which so short a period fits there."""
    s = _identify(bench, "clean", 2, tmp_path)
    assert "cogging" not in {e["name"] for e in s["effects"]}, s["effects"]


def test_presliding_friction_is_warned_against_the_travel_since_a_reversal(bench, tmp_path):
    """Dahl/LuGre friction with a presliding distance of 120 µm (seed 1): the friction builds
    up over the travel after each reversal, the model's within a few mm/s, so the residual is
    about −12 N in the first 15 µm of every move; against velocity it fell in the slowest bins
    with the samples at rest (9 % of the power, counted as stiction's) and nothing was said. The
    residual against the travel since the reversal tells it, with where."""
    s = _identify(bench, "lugre120um", 1, tmp_path)
    assert {e["name"] for e in s["effects"]} <= {"stiction", "stribeck"}, s["effects"]
    assert s["residual"]["structured"], s["residual"]["text"]
    found = [f for f in s["residual"]["findings"] if f["against"] == "travel"]
    assert found and found[0]["mean"] < -6.0, s["residual"]["findings"]
    assert "µm of travel since the motion reversed" in found[0]["where"]


def test_a_clean_record_has_no_deficit_after_a_reversal(bench, tmp_path):
    """Nothing injected (seed 1): the sign-shaped Coulomb friction against the model's smooth
    S_f and a fitted Stribeck hump leave 0.7 N (6 % of the Coulomb level) in the first 40 µm
    after a reversal: tested, not a structure."""
    s = _identify(bench, "clean", 1, tmp_path)
    travel = [t for t in s["residual"]["tested"] if t["against"] == "travel"]
    assert travel and not travel[0]["structured"], travel
    assert not s["residual"]["structured"], s["residual"]["text"]


def test_a_load_in_play_is_not_named_a_friction_of_position(bench, tmp_path):
    """A 10 kg load through ±100 µm of play (seed 3): the load's push lands mid-move, at other
    positions going out and back (+5.9/−3.4 N at 200-250 mm forward, +5.5/−3.6 N at 150-200 mm
    back), and a 12-segment friction shape of position was named for it. Fitted on each direction
    apart the shape explains 8 % more (a friction of position: at most 0.7 %), so it is refused,
    and the residual's warning is the answer."""
    s = _identify(bench, "backlash100", 3, tmp_path)
    names = {e["name"] for e in s["effects"]}
    assert not names & {"position_friction_shape", "position_dependent_friction"}, s["effects"]
    assert s["residual"]["structured"], s["residual"]["text"]


def test_a_delay_the_record_cannot_confirm_is_warned_not_left_unsaid(bench, tmp_path):
    """Simulation B (a cascade loop at 2 kHz with a tanh/Stribeck friction, seed 1): u acting 3
    samples late. The delay candidate explains 22 % of the held-out residual beside the nominal
    model, but its phase says 4.5 samples at 15-35 Hz and 3.8 at 35-80 Hz (2.2 and 3.1 once
    stiction is in), the band check that refuses a play's lag as a delay; beside stiction it
    still explained 4.2 % and was refused on its physics, below the 6 % a refused candidate then
    needed to be reported: the record was called clean. A refusal of what would be named (at
    least 4 %) is now the warning."""
    s = _identify(bench, "delay1500us", 1, tmp_path, sim="b")
    assert s["residual"]["structured"], s["residual"]["text"]
    assert "input_delay" in s["residual"]["text"], s["residual"]["text"]


def test_two_periods_near_two_to_one_are_not_named_one_cogging_between_them(bench, tmp_path):
    """Simulation B (seed 1): 3 N at 11 mm and 2.5 N at 23 mm (ratio 2.09). One cogging term of
    22.08 mm was named beside the warning, its second harmonic (11.04 mm, 3.0 N) taking the 11 mm
    force: a period 4 % from both. Refined on its own each harmonic finds its force (23.0 and
    11.0 mm, 0.8 cycles apart over the 0.205 m stroke) and explains 86-88 % of what the locked
    pair leaves, so the term is refused (its harmonics are two periods); a cogging may be named
    only at one of the true periods (within 3 %), and the warning stays."""
    s = _identify(bench, "two_periods", 1, tmp_path, sim="b")
    for e in s["effects"]:
        if e["name"] == "cogging":
            period = e["parameters"]["period_m"]
            assert min(abs(period / p - 1.0) for p in (0.011, 0.023)) <= 0.03, s["effects"]
    assert s["residual"]["structured"], s["residual"]["text"]
