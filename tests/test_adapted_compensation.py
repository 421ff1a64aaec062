"""Adapted compensation (motorctl/effects/compensation.py): an identified effect's linear coefficients β join θ̂.

With ``adapt: true`` on a ``controller.compensation.<family>`` entry, the effect's basis columns
c(x, ẋ, t) are appended to the estimator's regressor (filtered by H_f, on the measured signals)
and β̂ is adapted with θ̂ (same LS and box projection, eq. 7-8, 25-28); v_a1 subtracts β̂ᵀc on
the desired trajectory (eq. 13). Fixed amplitudes stay the default (bit-identical: see
tests/test_double_counting.py and tests/test_effect_registry.py).
"""

from __future__ import annotations

import numpy as np
import pytest

from motorctl.app.build import build, run_cycles
from motorctl.config import ConfigError, config_from_dict
from motorctl.control.dcdiarc import DCDIARC
from motorctl.effects import family
from motorctl.effects.compensation import Compensation, CompensationSection
from motorctl.ident.synth import gantry_dict
from motorctl.metrics import settled_indexes

A1 = 80.0
#: a time-periodic disturbance large enough to matter (0.375 V), small enough not to saturate u
#: on the program below; its amplitude steps by +30 % at STEP_S
DISTURBANCE = {"amplitude_N": 30.0, "frequency_Hz": 7.3, "phase_rad": 0.4}
STEP_S, SCALE = 6.0, 1.3
DURATION_S = 16.0
#: forgetting factor for all runs of the drift test (a drifting parameter needs μ > 0: with μ = 0
#: the LS gain decays like 1/t and β̂ would average the amplitudes before and after the step)
MU = 1.0


def _run(d: dict, axis: str = "X", duration_s: float | None = None):
    """Run the config dict ``d`` (virtual clock). Returns (settled indexes over program time
    after the first period, the controller, rows, layout)."""
    loaded = config_from_dict(d, "<adapted compensation>")
    n = loaded.timebase.cycles(duration_s or DURATION_S)
    asm = build(loaded, clock="virtual", capacity=n)
    rows, lay = run_cycles(asm, n)
    t = rows[:, lay.cycle("t")]
    idx = settled_indexes(t, rows[:, lay.index(f"{axis}.e")], rows[:, lay.index(f"{axis}.u")],
                          d["axes"][axis]["trajectory"]["period_s"])
    assert not asm.supervisor.reason(0), asm.supervisor.reason(0)
    return idx, asm.loop.controllers[0], rows, lay


def _drift_dict(effect: dict | None, comp: dict | None) -> dict:
    """Rigid X axis, seed 1, μ = MU, the paper's program at half the acceleration (20 m/s²: the
    full 40 m/s² already reaches the 10 V limit without any effect, so that any added force
    saturates u and no compensation can remove its damage)."""
    d = gantry_dict("X", effect, seed=1, noise_N=1.0, compensation=comp)
    d["axes"]["X"]["controller"]["mu"] = MU
    tr = d["axes"]["X"]["trajectory"]
    tr["a_max"], tr["j_max"] = 20.0, 2000.0
    return d


@pytest.fixture(scope="module")
def drift_runs():
    fam = family("periodic_disturbance")
    comp = fam.compensation_for(fam.sim_options(**DISTURBANCE), A1)
    drifting = {"periodic_disturbance": {**DISTURBANCE, "step_at_s": STEP_S, "scale_after": SCALE}}
    floor = _run(_drift_dict(None, None))
    fixed = _run(_drift_dict(drifting, {"periodic_disturbance": comp}))
    adapted = _run(_drift_dict(drifting, {"periodic_disturbance": {**comp, "adapt": True}}))
    return comp, floor, fixed, adapted


def test_adapted_compensation_follows_a_30_percent_amplitude_step(drift_runs):
    comp, (floor, *_), (fixed, *_), (adapted, ctl, *_) = drift_runs
    l2_floor = floor["L2_um"]
    # fixed amplitudes leave 30 % of the disturbance after the step: well above the floor
    assert fixed["L2_um"] > 1.1 * l2_floor, (fixed["L2_um"], l2_floor)
    # adapted: within 10 % of the effect-free floor (same plant, seed, μ)
    assert adapted["L2_um"] < 1.1 * l2_floor, (adapted["L2_um"], l2_floor)
    # β̂ went to the new amplitudes, θ̂ stayed where the effect-free run has it
    truth_after = SCALE * np.array(comp["sin_V"] + comp["cos_V"])
    assert ctl.beta_names == ["periodic_disturbance.sin_V[0]", "periodic_disturbance.cos_V[0]"]
    assert np.allclose(ctl.beta_hat, truth_after, rtol=0.05, atol=0.005), (ctl.beta_hat, truth_after)
    th_floor = drift_runs[1][1].theta_hat
    assert np.max(np.abs(ctl.theta_hat[:4] - th_floor[:4])) < 0.01, (ctl.theta_hat, th_floor)


def _truth(drv: dict) -> list:
    a1 = drv["a1_N_per_V"]
    return [drv["mass_kg"] / a1, drv["viscous_N_s_per_m"] / a1, drv["coulomb_N"] / a1,
            drv["offset_N"] / a1, drv["a2_N_per_V2"] / a1, drv["a3_N_per_V3"] / a1]


@pytest.mark.parametrize("effect", [
    {"spring": {"stiffness_N_per_m": 100.0, "rest_position_m": 0.1}},
    {"periodic_disturbance": {"amplitude_N": 6.0, "frequency_Hz": 7.3, "phase_rad": 0.4}},
])
def test_adapted_true_effect_started_at_truth_stays_there(effect):
    """Double counting, adapted case: the true effect compensated, θ̂(0) = θ and β̂(0) = β (the
    truth), μ = 0: θ̂ stays where it stays without the effect and β̂ stays at β."""
    name, opts = next(iter(effect.items()))
    fam = family(name)
    comp = fam.compensation_for(fam.sim_options(**opts), A1)
    beta = np.array(fam.comp_options(**comp).beta())
    runs = {}
    for key, eff, cmp in (("free", None, None), ("adapted", effect, {name: {**comp, "adapt": True}})):
        d = gantry_dict("X", eff, seed=3, noise_N=0.0, compensation=cmp)
        d["axes"]["X"]["controller"]["theta_hat0"] = _truth(d["axes"]["X"]["driver"])
        runs[key] = _run(d, duration_s=5.0)[1]
    th, th_free = runs["adapted"].theta_hat, runs["free"].theta_hat
    assert np.max(np.abs(th - th_free)) < 0.005, (th, th_free)
    assert np.allclose(runs["adapted"].beta_hat, beta, rtol=0.03, atol=1e-3), (runs["adapted"].beta_hat, beta)


def test_c1_adapts_too():
    """C1 (θ1..θ4) with an adapted entry: β̂ joins the four parameters."""
    d = gantry_dict("X", None)
    cfg = config_from_dict(d, "<x>").axes["X"].controller
    cfg = cfg.model_copy(update={"compensation": CompensationSection(
        spring={"stiffness_V_per_m": 1.0, "rest_position_m": 0.2, "adapt": True, "gamma0": 50.0})})
    c = DCDIARC(cfg, 2e-4, "c1")
    assert c.estimator.theta_hat.shape == (5,) and c.theta_hat.shape == (4,) and c.beta_hat[0] == 1.0
    assert c.estimator.gamma[4, 4] == 50.0
    c.reset(0.1)
    c.update(0.1, 0.1, 0.0, 0.0)
    # v_a1 subtracts β̂·c(x_d) = 1.0·(0.2 − 0.1) (at rest on the trajectory: p = 0)
    c0 = DCDIARC(cfg.model_copy(update={"compensation": CompensationSection()}), 2e-4, "c1")
    c0.reset(0.1)
    c0.update(0.1, 0.1, 0.0, 0.0)
    assert c.u == pytest.approx(c0.u - 0.1, abs=1e-6)   # (θ̂4, β̂ took one tiny LS step)


def test_adapted_basis_is_the_fixed_term():
    """β·c(x, ẋ, t) of every adaptable family is the fixed term at the same point."""
    entries = {
        "cogging": {"period_m": 0.032, "sin_V": [0.1, 0.03], "cos_V": [0.05]},
        "spring": {"stiffness_V_per_m": 1.25, "rest_position_m": 0.1},
        "periodic_disturbance": {"frequency_Hz": 7.3, "sin_V": [0.07], "cos_V": [-0.02]},
        "stribeck": {"force_V": 0.25, "velocity_m_per_s": 0.05},
        "asymmetric_friction": {"coulomb_V": 0.125, "viscous_V_s_per_m": 0.25},
        "position_dependent_friction": {"coulomb_slope_V_per_m": 0.5, "reference_m": 0.2},
    }
    for name, e in entries.items():
        fixed = Compensation(CompensationSection(**{name: e}))
        adapted = Compensation(CompensationSection(**{name: {**e, "adapt": True}}))
        assert adapted.n_beta == len(family(name).comp_options(**e).beta()) and not adapted.additive
        out = np.zeros(adapted.n_beta)
        for x, v, t in [(0.013, 0.8, 0.41), (0.37, -0.01, 2.3), (0.2, 0.004, 0.0)]:
            adapted.fill(out, x, v, t)
            assert float(adapted.beta0 @ out) == pytest.approx(fixed.value(x, v, t), rel=1e-12, abs=1e-15), name


@pytest.mark.parametrize("entry,message", [
    ({"adapt": True, "beta_min": [0.0]}, "beta_min: needs 2 entries"),
    ({"adapt": True, "beta_min": [0.1, 0.0], "beta_max": [0.2, 0.1]}, "outside"),
    ({"adapt": True, "gamma0": [1.0, 2.0, 3.0]}, "gamma0: needs one value or 2"),
    ({"adapt": True, "gamma0": -1.0}, "gamma0"),
    ({"adapt": "yes"}, "adapt"),
])
def test_bad_adapt_keys_are_named(entry, message):
    d = gantry_dict("X", None, compensation={"periodic_disturbance": {
        "frequency_Hz": 7.3, "sin_V": [0.07], "cos_V": [0.03], **entry}})
    with pytest.raises(ConfigError, match="compensation.periodic_disturbance") as exc:
        config_from_dict(d, "<x>")
    assert message in str(exc.value)


def test_default_box_and_identify_entry():
    """Without beta_min/beta_max the box is β ∓ ADAPT_MARGIN·max|β|; identify's entry writes it
    out with adapt false (fixed behaviour unchanged until a user flips it)."""
    from motorctl.effects.base import ADAPT_MARGIN
    fam = family("periodic_disturbance")
    entry = fam.compensation(7.3, np.array([-0.07, -0.03]))
    assert entry["adapt"] is False and entry["sin_V"] == [0.07] and entry["cos_V"] == [0.03]
    w = ADAPT_MARGIN * 0.07
    assert entry["beta_min"] == pytest.approx([0.07 - w, 0.03 - w])
    assert entry["beta_max"] == pytest.approx([0.07 + w, 0.03 + w])
    opts = fam.comp_options(**{k: v for k, v in entry.items() if not k.startswith("beta")})
    assert opts.adapt_box() == (pytest.approx(entry["beta_min"]), pytest.approx(entry["beta_max"]))
    wide = fam.compensation(7.3, np.array([-0.07, -0.03]), beta_std=[0.1, 0.0])
    assert wide["beta_max"][0] == pytest.approx(0.07 + 0.3)
