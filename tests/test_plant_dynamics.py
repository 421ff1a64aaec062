"""The dynamics the paper neglects in the simulated plant (motorctl_drivers/sim.py): structural
mode, current loop with delay, encoder noise; the rigid plant unchanged when they are off; and
on the default plant, gains far beyond the commissioned ones destabilise the loop."""

import copy
import math

import numpy as np
import pytest

from motorctl.app.job import run_job
from motorctl.config import config_from_dict, load_config, load_yaml
from motorctl_drivers.sim import AxisPlant, SimAxisOptions, _rk4_plain

TS = 2e-4


def _plant(seed=0, **kw):
    opt = SimAxisOptions(**{"mass_kg": 10.0, "a1_N_per_V": 80.0, **kw})
    return AxisPlant(opt, TS, np.random.default_rng(seed), 4)


def test_structural_mode_rings_at_its_frequency_and_damping():
    f_hz, zeta = 200.0, 0.05
    p = _plant(mode_hz=f_hz, mode_damping=zeta, mode_load_fraction=0.4)
    p.step(1.0)                       # a force pulse, then free response
    rel = []
    for _ in range(400):             # 80 ms
        p.step(0.0)
        rel.append(p.x - p.xl)
    rel = np.array(rel)
    up = np.where((rel[:-1] < 0) & (rel[1:] >= 0))[0]
    frac = up + (-rel[up]) / (rel[up + 1] - rel[up])         # interpolated zero crossings
    fd = 1.0 / (np.mean(np.diff(frac)) * TS)
    assert fd == pytest.approx(f_hz * math.sqrt(1 - zeta ** 2), rel=0.01)
    peaks = [np.max(rel[int(a):int(b)]) for a, b in zip(frac[:-1], frac[1:])]
    delta = np.mean(np.log(np.array(peaks[:-1]) / np.array(peaks[1:])))   # log decrement
    assert delta / math.sqrt(4 * math.pi ** 2 + delta ** 2) == pytest.approx(zeta, rel=0.05)


def test_current_loop_step_has_the_configured_bandwidth_and_delay():
    bw, delay = 500.0, 3.5 * TS
    p = _plant(current_loop_hz=bw, current_loop_delay_s=delay)
    tau = 1.0 / (2 * math.pi * bw)
    forces = []
    for _ in range(20):
        p.step(1.0)
        forces.append(p.F)
    t = (np.arange(20) + 1) * TS
    expected = np.where(t > delay, 80.0 * (1 - np.exp(-(t - delay) / tau)), 0.0)
    assert np.allclose(forces, expected, rtol=1e-9, atol=1e-9)
    # the force reaches 1 - 1/e of the step one time constant 1/(2 pi bw) after the delay
    assert np.interp(delay + tau, t, forces) == pytest.approx(80.0 * (1 - math.exp(-1)), rel=0.02)


def test_encoder_noise_and_interpolation_error_have_the_configured_size():
    p = _plant(encoder_noise_m=2e-6, encoder_resolution_m=1e-9)
    p.x = 1e-3
    p.xl = p.x
    ys = []
    for _ in range(4000):
        p.step(0.0)
        ys.append(p.measured() - p.x)
    assert np.std(ys) == pytest.approx(2e-6, rel=0.05)
    q = _plant(encoder_interpolation_m=1e-6, encoder_signal_period_m=20e-6, encoder_resolution_m=1e-9)
    for x in np.linspace(0.0, 40e-6, 17):
        q.x = float(x)
        assert q.measured() - x == pytest.approx(1e-6 * math.sin(2 * math.pi * x / 20e-6), abs=1e-9)
    a, b = _plant(seed=3, encoder_noise_m=1e-6), _plant(seed=3, encoder_noise_m=1e-6)
    for _ in range(50):
        a.step(0.3)
        b.step(0.3)
        assert a.measured() == b.measured()


def test_all_options_off_is_bitwise_the_rigid_plant():
    kw = dict(viscous_N_s_per_m=17.6, coulomb_N=20.0, offset_N=-4.0, a2_N_per_V2=-1.04,
              a3_N_per_V3=-0.12)
    off = dict(mode_hz=0.0, current_loop_hz=0.0, current_loop_delay_s=0.0, encoder_noise_m=0.0,
               encoder_interpolation_m=0.0)
    p, r = _plant(**kw, **off), _plant(**kw)
    assert p._plain and r._plain
    x, v, t = 0.0, 0.0, 0.0
    for k in range(3000):
        u = 3.0 * math.sin(k * 0.01)
        p.step(u)
        x, v, t = _rk4_plain(x, v, t, u, TS / 4, 4, 10.0, 80.0, -1.04, -0.12, 17.6, 20.0, -4.0, 0.0, 0.0)
        assert (p.x, p.xd, p.measured()) == (x, v, r.measured() if r.step(u) is None else None)


def test_flex_kernel_without_mode_matches_the_rigid_plant_closely():
    """The second compiled kernel with a current loop far faster than the period ≈ rigid."""
    p, r = _plant(current_loop_hz=1e6, viscous_N_s_per_m=5.0), _plant(viscous_N_s_per_m=5.0)
    for k in range(2000):
        u = math.sin(k * 0.01)
        p.step(u)
        r.step(u)
    assert p.x == pytest.approx(r.x, rel=1e-4)


def _run(raw, axis, kind, gains, seconds=1.5):
    d = copy.deepcopy(raw)
    c = d["axes"][axis]["controller"]
    (c["pid"] if kind == "pid" else c).update(gains)
    return run_job(config_from_dict(d, "test"), axes=[axis], controller=kind, duration_s=seconds,
                   clock="virtual").axes[axis]


@pytest.mark.parametrize("kind,high", [
    ("pid", {"P": 6e5, "I": 1e8, "D": 180.0, "maxerror_i": 1e-8}),
    ("c2", {"k_s": 180.0, "k1": 3333.0}),
])
def test_gains_far_beyond_the_chosen_ones_destabilise_the_default_plant(default_yaml, kind, high):
    raw = load_yaml(default_yaml)
    chosen = _run(raw, "X", kind, {})
    assert not chosen["fault"]
    hi = _run(raw, "X", kind, high)
    # oscillation (error many times that of the chosen gains, at the output limit) or a trip
    assert hi["fault"] or (hi["L2_um"] > 5 * chosen["L2_um"] and hi["u_peak_V"] >= 10.0), (hi, chosen)


def test_rigid_config_gives_todays_figures(repo):
    """configs/gantry-rigid.yaml = today's plant: the first 2 s of `compare` as before the
    unmodelled dynamics were added (40 s figures: see the change's report). e_M to the bit;
    L2[e] to 1e-12 (its sum of squares is taken in blocks of the run as it is drained: the same
    samples, summed in another order than when the figure was pinned). Re-pinned when ``run``
    began with idle cycles and an approach (docs/protection.md): the program 3 cycles later
    on the plant's noise; X L2[e] 4.143264 -> 4.142843, Y 3.335206 -> 3.334483 (-0.01 %,
    -0.02 %), e_M and the PID's to the bit."""
    loaded = load_config(repo / "configs" / "gantry-rigid.yaml")
    res = run_job(loaded, controller="c2", duration_s=2.0, clock="virtual").axes
    assert res["X"]["e_M_um"] == 32.133333333295155
    assert res["X"]["L2_um"] == pytest.approx(4.142842732547611, rel=1e-12)
    assert res["Y"]["L2_um"] == pytest.approx(3.334482997737583, rel=1e-12)
    res = run_job(loaded, controller="pid", duration_s=2.0, clock="virtual").axes
    assert res["X"]["L2_um"] == pytest.approx(1.961293019070531, rel=1e-12)
