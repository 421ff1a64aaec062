"""A name only where it stands on its own (docs/identification.md, "Decision rule"): records of a
rigid axis simulated in numpy with one effect injected by hand, and the name, "ambiguous" or
"unexplained" identify gives, never a phantom beside the right name.

The axis (:func:`motorctl.ident.synth.numpy_axis`): M = 12.8 kg, A1 = 80 N/V, viscous 17.6 N·s/m,
Coulomb 20 N as the model's S_f(ẋ) (no stiction: the carriage is not held at rest), offset −4 N,
under a PD loop with feedforward and 0.3 V of white noise on the input, 5 kHz, 0.2 m
raised-cosine moves of 0.25 s with dwells, a program period of 1.63 s (no harmonic of it at
50 Hz), u held over each period. Each record: one seed, 4 s (:data:`DURATION_S`), about 0.2 s
to simulate and one to identify (CPU); nothing compiled runs here.
"""

from __future__ import annotations

import numpy as np
import pytest

from motorctl.effects.input_delay import is_hold
from motorctl.ident.judge import claims, holds_zero
from motorctl.ident.pipeline import summarise
from motorctl.ident.select import Identifier
from motorctl.ident.synth import numpy_axis


@pytest.fixture(scope="module", autouse=True)
def warm_numba_cache():
    """The records here are simulated and identified in numpy alone (no compiled kernel runs):
    the module does not wait for the session's compile of the servo cycle (tests/conftest.py)."""
    return None


#: record length [s]: 4 s keep every case below as at 5 s (the names, the warnings, 6.09 N at
#: 50.00 Hz) for 0.8 of the identification's time
DURATION_S = 4.0


def _identify(**effect) -> dict:
    return summarise(Identifier(numpy_axis(DURATION_S, 1, **effect), zoh_delay=0.5).run())


def _names(s: dict) -> set:
    return {e["name"] for e in s["effects"]}


def test_a_saturating_force_constant_drift_gets_no_phantom_payload_change():
    """−15 % towards a level with τ = 3 s: the linear drift is named; a mass step at the drift's
    knee (0.41 kg at 1.7 s) is a smooth change of θ1's column, which explains as much."""
    s = _identify(kf_drift=(0.15, 3.0))
    assert _names(s) == {"force_constant_drift"}, s["effects"]
    assert s["effects"][0]["parameters"]["drift_per_s"] < 0


def test_a_force_step_gets_no_phantom_stiction():
    """+12 N from t = 2.4 s on a plant without stiction: a force step explains more than the
    stiction the held input suggested; nothing is named and the verdict warns."""
    s = _identify(step=(12.0, 2.4))
    assert _names(s) == set(), s["effects"]
    assert s["residual"]["structured"], s["residual"]["text"]


@pytest.mark.parametrize("effect, name", [({"cogging": (8.0, 0.024)}, "cogging"),
                                          ({"spring_N_per_m": 100.0}, "spring")])
def test_clean_friction_with_one_effect_gets_that_name_alone(effect, name):
    s = _identify(**effect)
    assert _names(s) == {name}, s["effects"]


def test_a_50hz_vibration_is_named_a_periodic_disturbance_near_50hz():
    """6 N at 50 Hz, about the PD loop's crossover (the input carries 0.44 and the carriage's
    inertia 0.47 of the line: a force from outside, not the loop's own oscillation): the search
    starts at the residual's strongest line."""
    s = _identify(vibration=(6.0, 50.0))
    assert _names(s) == {"periodic_disturbance"}, s["effects"]
    p = s["effects"][0]["parameters"]
    assert abs(p["frequency_Hz"] - 50.0) < 0.5 and abs(p["amplitude_N"] - 6.0) < 0.6, p


def test_an_interval_that_holds_zero_carries_no_name():
    """EMPS's asymmetric friction as it was named: 13.47 N with [−14.2, 41.1]."""
    assert holds_zero("asymmetric_friction", {"coulomb_N": [-14.2, 41.1], "viscous_N_s_per_m": [None, None]})
    assert holds_zero("asymmetric_friction", {"coulomb_N": [2.0, 41.1], "viscous_N_s_per_m": [-5.0, 3.0]}) is None
    assert holds_zero("cogging", {"amplitudes_N": [[-1.0, 2.0], [-0.5, 0.4]], "period_m": [0.03, 0.04]})
    assert holds_zero("cogging", {"amplitudes_N": [[1.0, 2.0], [-0.5, 0.4]]}) is None
    assert holds_zero("stiction", {"velocity_band_m_per_s": [-1.0, 1.0]}) is None    # declares no size


def test_an_effect_is_named_by_the_size_that_stands():
    """EMPS's asymmetric friction (default options) as it is now named: ΔB −75.8 N·s/m with its
    own interval [−82.1, −69.6] (the fit in motion), ΔF_c 2.93 N with [−1.59, 7.44]: named by
    ΔB, ΔF_c not claimed; both standing: the family's own name."""
    ci = {"coulomb_N": [-1.59, 7.44], "viscous_N_s_per_m": [-82.05, -69.58]}
    assert holds_zero("asymmetric_friction", ci) is None
    assert claims("asymmetric_friction", ci) == ("asymmetric viscous friction", [("coulomb_N", -1.59, 7.44)])
    assert claims("asymmetric_friction", {"coulomb_N": [7.05, 12.77], "viscous_N_s_per_m": [18.2, 21.9]}) == \
        ("asymmetric_friction", [])
    assert claims("asymmetric_friction", {"coulomb_N": [2.0, 9.0], "viscous_N_s_per_m": [-5.0, 3.0]})[0] == \
        "asymmetric Coulomb friction"
    # a family without a name of its own for a part keeps its name; the part is not claimed
    assert claims("cogging", {"amplitudes_N": [[1.0, 2.0], [-0.5, 0.4]]}) == ("cogging", [("amplitudes_N[1]", -0.5, 0.4)])


def test_the_hold_tolerance_is_inclusive_on_both_sides():
    """0.65 − 0.5 is 0.15000000000000002 in binary floats: the edge is the hold on both sides."""
    assert is_hold(0.65) and is_hold(0.35) and is_hold(0.5 + 0.15000000000000002)
    assert is_hold(float(np.arange(0.0, 1.5 + 1e-9, 0.05)[13]))         # the hold grid's 0.65
    assert not is_hold(0.651) and not is_hold(0.349)
