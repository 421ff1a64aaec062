"""The simulated gantry: RK4 under ZOH, encoder quantisation, input delay, determinism."""

import numpy as np
import pytest

from motorctl.config import load_config
from motorctl.app.job import run_job
from motorctl_drivers.sim import AxisPlant, SimAxisOptions

TS = 2e-4


def _plant(**kw):
    opt = SimAxisOptions(**{"mass_kg": 10.0, "a1_N_per_V": 80.0, **kw})
    return AxisPlant(opt, TS, np.random.default_rng(0), 4)


def test_free_mass_follows_the_analytic_solution():
    p = _plant()
    for _ in range(1000):
        p.step(1.0)  # 80 N on 10 kg: 8 m/s^2
    t = 1000 * TS
    assert p.x == pytest.approx(0.5 * 8.0 * t * t, rel=1e-12)
    assert p.xd == pytest.approx(8.0 * t, rel=1e-12)


def test_viscous_decay_matches_rk4_accuracy():
    p = _plant(viscous_N_s_per_m=50.0)
    p.xd = 1.0
    for _ in range(500):
        p.step(0.0)
    assert p.xd == pytest.approx(np.exp(-5.0 * 500 * TS), rel=1e-9)  # B/M = 5 1/s


def test_encoder_quantisation_is_half_a_micron():
    p = _plant()
    p.x = 1.23456789e-3
    q = p.measured()
    assert abs(q - p.x) <= 0.25e-6 + 1e-15
    assert q / 0.5e-6 == pytest.approx(round(q / 0.5e-6), abs=1e-9)


def test_input_delay_shifts_the_input_by_whole_samples():
    a, b = _plant(), _plant(input_delay_s=3 * TS)
    us = [0.0, 1.0, -0.5, 2.0, 0.0, 0.0, 0.0, 0.0]
    xa, xb = [], []
    for u in us:
        a.step(u)
        b.step(u)
        xa.append(a.x)
        xb.append(b.x)
    # b sees u[k-3]: its first three periods are at rest, then it repeats a's start
    assert xb[:3] == [0.0, 0.0, 0.0]
    b2 = _plant()
    for u in [0.0, 0.0, 0.0] + us[:5]:
        b2.step(u)
    assert b.x == pytest.approx(b2.x, rel=1e-12)


def test_wall_and_virtual_clock_give_identical_runs(gantry_yaml):
    loaded = load_config(gantry_yaml)
    wall = run_job(loaded, axes=["X"], duration_s=1.0, clock="wall", realtime_policy="off")
    virt = run_job(loaded, axes=["X"], duration_s=1.0, clock="virtual")
    for k in ("e_M_um", "e_F_um", "L2_um", "u_peak_V"):
        assert wall.axes["X"][k] == virt.axes["X"][k]
    assert wall.axes["X"]["theta_hat"] == virt.axes["X"]["theta_hat"]


def test_same_seed_same_noise_other_seed_other_noise(gantry_yaml):
    import copy

    from motorctl.config import config_from_dict, load_yaml
    data = load_yaml(gantry_yaml)
    data["axes"]["X"]["driver"]["force_noise_N"] = 20.0
    runs = []
    for seed in (5, 5, 6):
        d = copy.deepcopy(data)
        d["driver"]["seed"] = seed
        runs.append(run_job(config_from_dict(d, "noise"), axes=["X"], duration_s=1.0, clock="virtual").axes["X"])
    assert runs[0]["L2_um"] == runs[1]["L2_um"]
    assert runs[0]["L2_um"] != runs[2]["L2_um"]
