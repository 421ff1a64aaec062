"""Projection (eq. 7-8), the LS estimator (25)-(28) and its covariance update."""

import numpy as np
import pytest
from conftest import examples
from hypothesis import given, settings
from hypothesis import strategies as st

from motorctl.control.estimator import LeastSquaresEstimator, lambda_max_exceeds, project_box
from motorctl.model import f_u, s_f_scalar

TMIN = np.array([0.05, 0.08, 0.05, -0.5, -0.015, -0.002])
TMAX = np.array([0.3, 0.5, 0.5, 0.5, 0.0, 0.0])
GAMMA0 = np.diag([2.0, 50.0, 100.0, 500.0, 0.05, 0.005])


def _spd(rng, n):
    a = rng.normal(size=(n, n))
    return a @ a.T + 0.1 * np.eye(n)


def _project(z, th, gam):
    n = len(th)
    z = z.copy()
    project_box(z, th, TMIN[:n], TMAX[:n], gam, np.zeros((n, n)), np.zeros((n, n)),
                np.zeros((3, n)), np.zeros(n, np.int64), np.zeros(n, np.bool_))
    return z


@settings(max_examples=examples(200), deadline=None)
@given(seed=st.integers(0, 2**31 - 1))
def test_projection_matches_block_formula_and_property_p2(seed):
    rng = np.random.default_rng(seed)
    n = 6
    gam = _spd(rng, n)
    th = rng.uniform(TMIN, TMAX)
    # put a random subset of parameters on a face
    on = rng.random(n) < 0.5
    upper = rng.random(n) < 0.5
    th[on & upper] = TMAX[on & upper]
    th[on & ~upper] = TMIN[on & ~upper]
    zeta = rng.normal(size=n) * 10
    z = _project(zeta, th, gam)
    # the active set: faces where the projected step would leave the box are closed
    act = [i for i in range(n) if (th[i] >= TMAX[i] and z[i] > 1e-12) or (th[i] <= TMIN[i] and z[i] < -1e-12)]
    assert act == []
    # z = zeta - Gamma[:, A] lam with lam = 0 off A, lam >= 0 on upper faces, <= 0 on lower ones
    lam = np.linalg.solve(gam, zeta - z)
    scale = 1e-8 * (1 + np.abs(zeta).max())
    for i in range(n):
        if abs(lam[i]) > scale:
            assert (th[i] >= TMAX[i] and lam[i] > 0) or (th[i] <= TMIN[i] and lam[i] < 0)
            assert abs(z[i]) <= scale
    # P2: theta_tilde^T (Gamma^-1 Proj(Gamma tau) - tau) <= 0 for any theta in the box
    tau = np.linalg.solve(gam, zeta)
    for _ in range(5):
        theta = rng.uniform(TMIN, TMAX)
        tt = th - theta
        assert tt @ (np.linalg.solve(gam, z) - tau) <= 1e-9 * (1 + np.abs(tau).max())


def test_projection_interior_is_identity_and_diagonal_is_componentwise():
    th = (TMIN + TMAX) / 2
    zeta = np.arange(1.0, 7.0)
    np.testing.assert_array_equal(_project(zeta, th, GAMMA0), zeta)
    th2 = th.copy()
    th2[0] = TMAX[0]
    th2[4] = TMIN[4]
    z = _project(np.array([1.0, 1.0, -1.0, 1.0, -1.0, 1.0]), th2, GAMMA0)
    np.testing.assert_array_equal(z, [0.0, 1.0, -1.0, 1.0, 0.0, 1.0])


def _drive(est, theta, n_steps, rng, ts=2e-4, amplitude=8.0):
    """Open-loop data from eq. (4) with d = 0: u rich in frequencies, the plant integrated finely."""
    x2 = 0.0
    u_prev = 0.0
    eigs = []
    t1, t2, t3, t4, t5, t6 = (float(v) for v in theta)
    h = ts / 10
    for k in range(n_steps):
        t = k * ts
        u = amplitude * (0.6 * np.sin(2 * np.pi * 1.3 * t) + 0.3 * np.sin(2 * np.pi * 7.1 * t)
                         + 0.1 * np.sin(2 * np.pi * 23.0 * t))
        # integrate the interval [k, k+1] with u held: 10 Euler substeps
        # (plain floats: numpy's per-scalar calls made this loop 20x slower; f_u and s_f of
        # motorctl.model in their scalar form, u held so f_u is taken once)
        v0 = x2
        force = u + t5 * u * abs(u) + t6 * u ** 3
        for _ in range(10):
            acc = (force - t2 * x2 - t3 * s_f_scalar(x2) + t4) / t1
            x2 += acc * h
        est.update(0.5 * (v0 + x2), u)  # mean velocity over the interval, the input held over it
        if k % 500 == 0:
            eigs.append(np.linalg.eigvalsh(est.gamma))
        u_prev = u
    return np.array(eigs), u_prev


def test_estimator_converges_and_gamma_stays_spd():
    theta = np.array([0.16, 0.22, 0.25, -0.05, -0.013, -0.0015])
    est = LeastSquaresEstimator([0.2, 0.2, 0.1, 0.0, 0.0, 0.0], TMIN, TMAX, GAMMA0, 200.0, 2e-4)
    eigs, _ = _drive(est, theta, 40000, np.random.default_rng(0))
    assert np.all(eigs[:, 0] > 0)                      # Gamma positive definite throughout
    np.testing.assert_array_equal(est.gamma, est.gamma.T)  # exactly symmetric
    assert np.all(est.theta_hat >= TMIN) and np.all(est.theta_hat <= TMAX)
    rel = np.abs(est.theta_hat[:4] - theta[:4]) / np.abs(theta[:4])
    assert np.all(rel < 0.05), (est.theta_hat, rel)
    # the cubic terms are correlated (θ5 and θ6 are nearly collinear at these inputs): judge the fitted curve at 10 V
    assert float(f_u(10.0, *est.theta_hat[4:])) == pytest.approx(float(f_u(10.0, *theta[4:])), rel=0.02)


def test_forgetting_with_freeze_keeps_gamma_bounded():
    est = LeastSquaresEstimator([0.2, 0.2, 0.1, 0.0, 0.0, 0.0], TMIN, TMAX, GAMMA0, 200.0, 2e-4,
                                mu=5.0, rho_M=1000.0)
    # no excitation: with forgetting Gamma grows until the freeze branch of eq. (27) holds it
    for _ in range(20000):
        est.update(0.0, 0.0)
    lam = np.linalg.eigvalsh(est.gamma)
    assert lam[-1] <= 1000.0 * (1 + 1e-9)
    assert lam[0] > 0
    assert lam[-1] > np.max(np.diag(GAMMA0))  # it did grow (mu acted)
    assert est.frozen


@settings(max_examples=examples(200), deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(4, 9), side=st.sampled_from([-1.0, 1.0]))
def test_freeze_test_agrees_with_the_largest_eigenvalue(seed, n, side):
    """eq. (27)'s freeze test, decided by a Cholesky factorisation, gives λ_max(sΓ − c g gᵀ) > ρ
    as the eigenvalue does, for ρ just below or just above it (n: 4 or 6 parameters plus
    adapted coefficients)."""
    rng = np.random.default_rng(seed)
    gam = _spd(rng, n) * 10.0 ** rng.uniform(-2, 3)
    g = rng.normal(size=n) * np.sqrt(np.diag(gam))
    scale = 1.0 + rng.uniform(0.0, 1e-3)
    c = rng.uniform(0.0, 0.9) * scale / (g @ np.linalg.solve(gam, g))     # keeps sΓ − c g gᵀ SPD
    lam = np.linalg.eigvalsh(scale * gam - c * np.outer(g, g))[-1]
    rho = lam * (1.0 + side * 10.0 ** rng.uniform(-9, 0))
    w = np.full((n, n), np.nan)
    assert lambda_max_exceeds(gam, g, scale, c, rho, w) == (lam > rho)


def test_frozen_at_rest_allocates_nothing():
    """With forgetting and no excitation Γ grows until eq. (27) freezes it, then the freeze test
    runs every sample: numba's allocation counter (NUMBA_NRT_STATS, a fresh interpreter) shows
    no allocation over 1000 such samples run from compiled code, as the servo cycle runs them."""
    import os
    import subprocess
    import sys
    code = (
        "import numpy as np\n"
        "from numba import njit\n"
        "from numba.core.runtime import rtsys\n"
        "from motorctl.control.estimator import LeastSquaresEstimator, ls_update\n"
        "@njit\n"
        "def samples(count, cols, *arrays):\n"
        "    for _ in range(count):\n"
        "        ls_update(0.0, 0.0, 0.0, 1.0, cols, *arrays)\n"
        "est = LeastSquaresEstimator([0.2, 0.2, 0.1, 0, 0, 0], [0.05, 0.08, 0.05, -0.5, -0.015, -0.002],\n"
        "    [0.3, 0.5, 0.5, 0.5, 0, 0], np.diag([2.0, 50, 100, 500, 0.05, 0.005]), 200.0, 2e-4, mu=5.0, rho_M=1000.0)\n"
        "samples(20000, est.cols, *est.kernel_args())\n"
        "a = rtsys.get_allocation_stats()\n"
        "samples(1000, est.cols, *est.kernel_args())\n"
        "b = rtsys.get_allocation_stats()\n"
        "print(int(est.frozen), b.alloc - a.alloc)\n")
    env = {**os.environ, "NUMBA_NRT_STATS": "1"}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    frozen, allocs = map(int, out.stdout.split())
    assert frozen == 1, out.stdout
    assert allocs <= 20, out.stdout            # the call from Python boxes its arrays once, not per sample


def test_bad_sizes_and_initial_estimate_outside_box():
    with pytest.raises(ValueError, match="4 or 6"):
        LeastSquaresEstimator([0.2] * 5, TMIN[:5], TMAX[:5], np.eye(5), 200.0, 2e-4)
    with pytest.raises(ValueError, match="outside"):
        LeastSquaresEstimator([0.4, 0.2, 0.1, 0.0, 0.0, 0.0], TMIN, TMAX, GAMMA0, 200.0, 2e-4)
    with pytest.raises(ValueError, match="6x6"):
        LeastSquaresEstimator([0.2, 0.2, 0.1, 0.0, 0.0, 0.0], TMIN, TMAX, np.eye(4), 200.0, 2e-4)
