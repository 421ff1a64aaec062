"""Compensation and estimator share one model (no double counting).

With an identified effect compensated (d̂_eff subtracted in v_a1, eq. 13), the estimator must
see the input the model sees, u + d̂_eff (eq. 4, motorctl/effects/base.py sign convention).
Otherwise θ̂ absorbs the effect's mean while v_a1 also subtracts the whole effect.
"""

from __future__ import annotations

import numpy as np
import pytest

from motorctl.app.job import run_job
from motorctl.config import config_from_dict
from motorctl.control.dcdiarc import DCDIARC
from motorctl.effects import family
from motorctl.ident.synth import gantry_dict


def _truth(drv: dict) -> list:
    """θ of the simulated X axis (paper units, eq. 4) from its driver section."""
    a1 = drv["a1_N_per_V"]
    return [drv["mass_kg"] / a1, drv["viscous_N_s_per_m"] / a1, drv["coulomb_N"] / a1,
            drv["offset_N"] / a1, drv["a2_N_per_V2"] / a1, drv["a3_N_per_V3"] / a1]


def _run(effect: dict | None, duration_s: float = 5.0):
    """θ̂ after ``duration_s`` of C2 on the X axis with ``effect`` on the plant and its true
    compensation configured, θ̂(0) = the plant's θ. Returns (θ, θ̂ (6,), the axis result)."""
    d = gantry_dict("X", effect, seed=3, noise_N=0.0)
    drv = d["axes"]["X"]["driver"]
    ctl = d["axes"]["X"]["controller"]
    truth = _truth(drv)
    if effect:
        name, opts = next(iter(effect.items()))
        fam = family(name)
        ctl["compensation"] = {name: fam.compensation_for(fam.sim_options(**opts), drv["a1_N_per_V"])}
    ctl["theta_hat0"] = truth
    r = run_job(config_from_dict(d, "<double counting>"), duration_s=duration_s, clock="virtual")
    return np.array(truth), np.array(r.axes["X"]["theta_hat"]), r.axes["X"]


@pytest.fixture(scope="module")
def effect_free():
    return _run(None)


@pytest.mark.parametrize("effect,tol", [
    # mean over the program −k(x̄ − x0)/A1 = −0.125 V: θ̂4 moved by −0.11 V when the estimator
    # was not told
    ({"spring": {"stiffness_N_per_m": 100.0, "rest_position_m": 0.1}}, 0.005),
    # −F_s e^{−(ẋ/v_s)²} S_f(ẋ) (0.25 V): θ̂3 moved by +0.05 V when the estimator was not told;
    # what is left (0.017) is d̂_eff evaluated on ẋ_d instead of ẋ where the term is steep
    ({"stribeck": {"force_N": 20.0, "velocity_m_per_s": 0.05}}, 0.025),
])
def test_theta_stays_at_truth_with_the_true_effect_compensated(effect, tol, effect_free):
    truth, th, r = _run(effect)
    _, th_free, _ = effect_free
    assert not r["fault"]
    # θ̂ behaves as on the plant without the effect (θ2/θ3 trade off a little along the
    # program's S_f(ẋ) ≈ 1 direction even then: same drift both ways)
    assert np.max(np.abs(th - th_free)) < tol, (th, th_free)
    assert abs(th[3] - truth[3]) < 0.01, (th, truth)
    assert abs(th[0] - truth[0]) / truth[0] < 0.03, (th, truth)


def test_estimator_input_is_u_plus_compensation():
    """The kernel's linear input channel holds u[k−1] + d̂_eff[k−1] (the pair held together)."""
    d = gantry_dict("X", None)
    cfg = config_from_dict(d, "<x>")
    ctl_cfg = cfg.axes["X"].controller.model_copy(update={"compensation": type(
        cfg.axes["X"].controller.compensation)(spring={"stiffness_V_per_m": 2.0, "rest_position_m": 0.0})})
    c = DCDIARC(ctl_cfg, 2e-4, "c2")
    c.reset(0.0)
    c.update(0.0, 0.1, 0.0, 0.0)            # d̂_eff = −2·0.1 = −0.2 V
    u0 = c.u
    c.update(0.0, 0.1, 0.0, 0.0)
    assert c.estimator._inp[3] == pytest.approx(u0 - 0.2)
    assert c.estimator._inp[4] == pytest.approx(u0 * abs(u0))
