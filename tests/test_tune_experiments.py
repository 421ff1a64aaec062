"""The second experiments of ``motorctl tune`` on the simulated gantry (motorctl.commission.tune):
the record identify calls ambiguous is told apart by a run that moves the two explanations apart.

* slow passes (a spring, or a hold at rest): the default plant's X with a 5 µm encoder and
  1 µm of noise and nothing injected is where identify reports "stiction or spring" (a spring
  of about 7 N/m, docs/identification.md "Ambiguities"); the passes find no slope and name
  stiction. With a real 7 N/m spring the same experiment names the spring.
* the program at another speed (a time-periodic line at a program harmonic, or a force of
  position): 4 N at 11.5 Hz, harmonic 46 of the 4 s program, keeps its frequency at 0.7 x the
  speed and is named the time-periodic disturbance.

The ambiguity entries are written here as identify reports them (families, the fits' parameters);
the runs are the virtual clock's (the same figures on every run)."""

from __future__ import annotations

import copy

import pytest

from motorctl.commission.tune import pass_experiment, speed_experiment
from motorctl.config import load_yaml

#: the force gain of configs/gantry.yaml's X [N/V]
A1_X = 80.0


@pytest.fixture(scope="module")
def base(default_yaml):
    return load_yaml(default_yaml)


def _spring_or(other: str, k_N_per_m: float) -> dict:
    return {"text": f"{other} or spring", "families": [other, "spring"],
            "fits": [{"name": other, "parameters": {}},
                     {"name": "spring", "parameters": {"stiffness_N_per_m": k_N_per_m}}]}


def _x(base: dict, **driver) -> dict:
    d = copy.deepcopy(base)
    d["axes"]["X"]["driver"].update(driver)
    return d


def test_slow_passes_find_no_spring_behind_a_coarse_encoders_flat_reading(base, tmp_path):
    """Nothing injected, 5 µm counts and 1 µm noise: the input does not change with the position
    (0 within 3σ, far below the fitted 7 N/m), so stiction is left."""
    cfg = _x(base, encoder_resolution_m=5e-6, encoder_noise_m=1e-6)
    r = pass_experiment(cfg, "X", _spring_or("stiction", 6.97), tmp_path / "p.mclog", A1_X)
    assert r["named"] == "stiction", r["why"]
    assert abs(r["slope_V_per_m"]) < 3.0 * r["slope_std"] + 0.1 * r["spring_V_per_m"]
    assert {b["direction"] for b in r["bins"]} == {-1, 1}


def test_slow_passes_name_a_real_spring_with_its_stiffness(base, tmp_path):
    """A 7 N/m spring (0.0875 V/m at 80 N/V): the slope within 10 % of it, named."""
    cfg = _x(base, effects={"spring": {"stiffness_N_per_m": 7.0, "rest_position_m": 0.2}})
    r = pass_experiment(cfg, "X", _spring_or("stiction", 7.0), tmp_path / "p.mclog", A1_X)
    assert r["named"] == "spring", r["why"]
    assert r["slope_V_per_m"] == pytest.approx(7.0 / A1_X, rel=0.10)


def test_the_other_speed_keeps_a_time_periodic_line_and_names_it(base, tmp_path):
    """4 N at 11.5 Hz (harmonic 46 of the 4 s program): at 0.7 x the speed the line stays at
    11.5 Hz, so it is a force in time, not one of the position."""
    cfg = _x(base, effects={"periodic_disturbance": {"amplitude_N": 4.0, "frequency_Hz": 11.5,
                                                     "phase_rad": 0.4}})
    entry = {"text": "periodic disturbance (time) at 11.5 Hz or force_ripple",
             "families": ["periodic_disturbance", "force_ripple"],
             "fits": [{"name": "periodic_disturbance", "parameters": {"frequency_Hz": 11.5}},
                      {"name": "force_ripple", "parameters": {}}]}
    r = speed_experiment(cfg, "X", entry, tmp_path / "s.mclog", 12.0)
    assert r["named"] == "periodic_disturbance", r["why"]
