"""Stiction: a disabled simulated axis stands still against its offset force, as a real carriage
does (the smooth Coulomb term S_f(ẋ) alone lets it creep, 0.35 mm/s on X, until a soft limit
trips); with stiction off the plant is unchanged."""

from __future__ import annotations

import numpy as np
import yaml

from motorctl.app.build import build
from motorctl.config import config_from_dict


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
