"""DCDIARC C1/C2: d̂0 bound, no allocation per step, parameter convergence (Theorem 2), modes."""

import tracemalloc

import numpy as np
import pytest

from motorctl.config import load_config
from motorctl.control.dcdiarc import DCDIARC, theory_k_s1
from motorctl.control.params import ControllerConfig
from motorctl.model import f_u

TS = 2e-4
X_PARAMS = dict(theta_min=[0.05, 0.08, 0.05, -0.5, -0.015, -0.002],
                theta_max=[0.3, 0.5, 0.5, 0.5, 0.0, 0.0],
                theta_hat0=[0.2, 0.2, 0.1, 0.0, 0.0, 0.0],
                gamma0=[2.0, 50.0, 100.0, 500.0, 0.05, 0.005])


def _section(**kw) -> ControllerConfig:
    return ControllerConfig.model_validate({**X_PARAMS, **kw})


def test_d_hat0_stays_within_its_bound_and_u_within_u_lim():
    c = DCDIARC(_section(), TS, "c2")
    rng = np.random.default_rng(3)
    for k in range(5000):
        u = c.update(rng.normal() * 0.01, 0.0, rng.normal(), rng.normal() * 50)
        assert abs(c.d_hat0) <= 1.0
        assert abs(u) <= 10.0
    assert np.all(c.theta_hat >= X_PARAMS["theta_min"]) and np.all(c.theta_hat <= X_PARAMS["theta_max"])


def test_c1_has_four_parameters_and_no_inversion():
    c = DCDIARC(_section(), TS, "c1")
    assert c.n_theta == 4 and c.theta_hat.shape == (4,)
    c.reset(0.0)
    u = c.update(1e-6, 0.0, 0.1, 1.0)
    assert u == pytest.approx(c.v)  # u = v for C1 when not saturated
    c2 = DCDIARC(_section(theta_hat0=[0.2, 0.2, 0.1, 0.0, -0.015, -0.002]), TS, "c2")
    c2.reset(0.0)
    u2 = c2.update(1e-6, 0.0, 0.0, 30.0)
    assert abs(u2) < 10.0  # not saturated, so f_u(u) = v exactly
    assert float(f_u(u2, c2.theta_hat[4], c2.theta_hat[5])) == pytest.approx(c2.v, abs=1e-9)


def test_step_allocates_nothing():
    c = DCDIARC(_section(), TS, "c2")
    for k in range(100):
        c.update(1e-6 * k, 0.0, 0.1, 1.0)
    tracemalloc.start()
    before = tracemalloc.take_snapshot()
    for k in range(2000):
        c.update(1e-6 * k, 1e-6 * k, 0.1, 1.0)
    after = tracemalloc.take_snapshot()
    tracemalloc.stop()
    grown = sum(s.size_diff for s in after.compare_to(before, "filename") if s.size_diff > 0)
    assert grown < 4096, grown  # no per-step growth (2000 steps would show >= 16 kB per 8 B)


def test_theory_mode_gain():
    ks1 = theory_k_s1(X_PARAMS["theta_min"], X_PARAMS["theta_max"], 250.0, 10.0)
    # the bound is large because g reaches 1800/pi at zero velocity (S_f's slope, docs/control-law.md; theory mode, eq. 14-15)
    assert ks1 > 1000
    c = DCDIARC(_section(mode="theory", theory={"k_s1": 300.0}), TS, "c2")
    c.reset(0.0)
    c.update(1e-5, 0.0, 1.0, 10.0)
    # k_s2 = (d_max + sum span_i |phi_d,i| + delta_d)^2 / (4 eta) > 0
    assert c.k_s_eff > 300.0
    with pytest.raises(ValueError, match="mode"):
        _section(mode="bogus").settings("c2")
    with pytest.raises(ValueError, match="kind"):
        DCDIARC(_section(), TS, "c3")


@pytest.fixture(scope="module")
def converged_run(gantry_yaml):
    """40 s of the X program with C2 on the clean simulated plant, Gamma checked throughout."""
    loaded = load_config(gantry_yaml)
    drv = loaded.make_driver(["X"])
    ctrl = DCDIARC(loaded.axes["X"].controller, TS, "c2")
    prog = loaded.axes["X"].trajectory.program()
    u = np.zeros(1)
    en = np.ones(1, dtype=bool)
    min_eig = np.inf
    asym = 0.0
    for k in range(int(40.0 / TS)):
        drv.read()
        xd, vd, ad = prog.sample(k * TS)
        u[0] = ctrl.update(drv.position_m[0], xd, vd, ad)
        drv.write(u, en)
        if k % 250 == 0:
            g = ctrl.estimator.gamma
            min_eig = min(min_eig, np.linalg.eigvalsh(g)[0])
            asym = max(asym, np.abs(g - g.T).max())
    return ctrl, drv.describe()["simulated"]["X"]["theta_true"], min_eig, asym


def test_theta_hat_converges_to_the_simulated_truth(converged_run):
    ctrl, truth, _, _ = converged_run
    truth = np.array(truth)
    rel = np.abs(ctrl.theta_hat[:4] - truth[:4]) / np.abs(truth[:4])
    assert np.all(rel < 0.10), (ctrl.theta_hat, truth, rel)
    # the combined cubic term at 9 V is identified (theta5 and theta6 alone are nearly collinear)
    assert float(f_u(9.0, *ctrl.theta_hat[4:])) == pytest.approx(float(f_u(9.0, *truth[4:])), rel=0.05)


def test_gamma_stays_symmetric_positive_definite(converged_run):
    _, _, min_eig, asym = converged_run
    assert min_eig > 0
    assert asym == 0.0
