"""Stiction: a disabled simulated axis stands still against its offset force, as a real carriage
does (the smooth Coulomb term S_f(ẋ) alone lets it creep, 0.35 mm/s on X, until a soft limit
trips); with stiction off the plant is unchanged."""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from motorctl.app.build import build
from motorctl.config import config_from_dict
from motorctl_drivers.sim import AxisPlant, SimAxisOptions


def _idle_run(path, seconds: float, rate_hz: float, stiction: bool):
    d = yaml.safe_load(open(path))
    d["loop"]["rate_hz"] = rate_hz
    for ax in d["axes"].values():
        if not stiction:
            ax["driver"].pop("stiction_N", None)
    loaded = config_from_dict(d)
    asm = build(loaded, clock="virtual", capacity=1000, operated=True)   # every axis disabled
    y0 = asm.driver.position_m.copy()
    asm.loop.run(loaded.timebase.cycles(seconds))
    return loaded, asm, asm.driver.position_m - y0


def test_a_disabled_axis_stays_within_its_soft_limits_for_ten_minutes(default_yaml):
    loaded, asm, moved = _idle_run(default_yaml, 600.0, 1000.0, stiction=True)
    assert not any(asm.supervisor.fault), [asm.supervisor.reason(i) for i in range(len(moved))]
    assert np.all(np.abs(moved) < 1e-6), moved


def test_without_stiction_the_disabled_axis_creeps(default_yaml):
    _, _, moved = _idle_run(default_yaml, 2.0, 1000.0, stiction=False)
    assert abs(moved[0]) > 1e-4                     # X's -4 N offset moves it


def test_stiction_releases_under_a_breakaway_force(default_yaml):
    d = yaml.safe_load(open(default_yaml))
    asm = build(config_from_dict(d), ["X"], clock="virtual", capacity=10, operated=True)
    plant = asm.driver.plants[0]
    x0 = plant.x
    for _ in range(100):
        plant.step(0.25)                            # 20 N of motor force - 4 N offset: stuck
    assert plant.x == x0 and plant.xd == 0.0
    for _ in range(100):
        plant.step(0.5)                             # 40 N - 4 N > 25 N breakaway: it moves
    assert plant.x > x0 + 1e-7


def _plant(with_effects: bool, effects: dict, x0: float) -> AxisPlant:
    opt = SimAxisOptions.model_validate({
        "mass_kg": 12.8, "a1_N_per_V": 80.0, "viscous_N_s_per_m": 17.6, "coulomb_N": 20.0,
        "stiction_N": 25.0, "initial_position_m": x0, "effects": effects,
        "stiction_with_effects": with_effects})
    return AxisPlant(opt, 2e-4, np.random.default_rng(1), 4)


@pytest.mark.parametrize("with_effects", [False, True])
def test_static_friction_follows_an_effect_that_raises_the_kinetic_friction(with_effects):
    """At 0.4 m a 40 N/m slope makes the kinetic friction 36 N, above the 25 N breakaway. 30 N
    applied at rest: the plain Karnopp test lets the carriage go and it creeps where S_f(ẋ)·36 N
    balances 30 N; with the effects seen the breakaway there is 25 + 16 = 41 N and it stays."""
    p = _plant(with_effects, {"position_dependent_friction": {"coulomb_slope_N_per_m": 40.0}}, 0.4)
    for _ in range(2500):                            # 0.5 s at 30 N
        p.step(30.0 / 80.0)
    if with_effects:
        assert p.x == 0.4 and p.xd == 0.0
    else:
        assert 1e-4 < p.x - 0.4 and 1e-3 < p.xd < 0.05    # creeping at mm/s


@pytest.mark.parametrize("with_effects", [False, True])
def test_an_effects_force_pushes_a_carriage_at_rest(with_effects):
    """A spring stretched by 0.1 m pulls with 40 N, above the 25 N breakaway, with the motor off:
    only the Karnopp test that sees the effects' forces lets it go."""
    p = _plant(with_effects, {"spring": {"stiffness_N_per_m": 400.0, "rest_position_m": 0.0}}, 0.1)
    for _ in range(500):
        p.step(0.0)
    if with_effects:
        assert p.x < 0.1 - 1e-4
    else:
        assert p.x == 0.1 and p.xd == 0.0
