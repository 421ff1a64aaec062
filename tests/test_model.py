import numpy as np
import pytest

from motorctl.model import (PhysicalAxis, assumption2_margin, f_u, f_u_slope, idim_regressor,
                            motor_force, s_f, s_f_scalar, s_f_slope)


def test_s_f_shape_function():
    x = np.linspace(-1, 1, 2001)
    y = s_f(x)
    assert np.all(np.abs(y) < 1)
    np.testing.assert_allclose(s_f(-x), -y)
    assert s_f_slope(0.0) == pytest.approx(1800 / np.pi)
    # |S_f| = 0.9 at about 7 mm/s (S_f = (2/π) arctan(900 x), docs/control-law.md)
    assert s_f(0.007) == pytest.approx(0.9, abs=0.01)
    assert s_f_scalar(0.003) == pytest.approx(float(s_f(0.003)))


def test_assumption2_margin_of_the_paper_bounds():
    # X bounds at u_M = 10 V: 1 - 0.3 - 0.6 = 0.1 (Assumption 2 on the θ box, eq. 9; configs/gantry.yaml)
    assert assumption2_margin((-0.015, 0.0), (-0.002, 0.0), 10.0) == pytest.approx(0.1)
    # Y bounds of configs/gantry.yaml: 1 - 0.6 - 0.3 = 0.1
    assert assumption2_margin((-0.03, 0.0), (-0.001, 0.0), 10.0) == pytest.approx(0.1)
    # a box that is not monotonic at 10 V
    assert assumption2_margin((-0.03, 0.0), (-0.003, 0.0), 10.0) < 0
    # theta6 > 0 > theta5: interior minimum at r = -theta5/(3 theta6)
    m = assumption2_margin((-0.2, -0.2), (0.01, 0.01), 10.0)
    r = 0.2 / 0.03
    assert m == pytest.approx(1 - 0.4 * r + 0.03 * r * r)
    assert m == pytest.approx(float(f_u_slope(r, -0.2, 0.01)))


def test_force_curve_and_normalised_form_agree():
    ax = PhysicalAxis(12.8, 80.0, -1.04, -0.12, 17.6, 20.0, -4.0)
    th = ax.theta()
    np.testing.assert_allclose(th, [0.16, 0.22, 0.25, -0.05, -0.013, -0.0015])
    u = np.linspace(-10, 10, 41)
    np.testing.assert_allclose(motor_force(u, 80.0, -1.04, -0.12), 80.0 * f_u(u, th[4], th[5]))
    back = PhysicalAxis.from_theta(th, 80.0)
    np.testing.assert_allclose(back.theta(), th)
    assert back.mass_kg == pytest.approx(12.8)


def test_idim_regressor_reproduces_the_model():
    rng = np.random.default_rng(0)
    th = np.array([0.16, 0.22, 0.25, -0.05, -0.013, -0.0015])
    u = rng.uniform(-10, 10, 50)
    v = rng.uniform(-2, 2, 50)
    # acceleration of eq. (4) with d = 0
    acc = (f_u(u, th[4], th[5]) - th[1] * v - th[2] * s_f(v) + th[3]) / th[0]
    phi = idim_regressor(acc, v, u)
    assert phi.shape == (50, 6)
    np.testing.assert_allclose(phi @ th, u, atol=1e-12)
    assert idim_regressor(acc, v, u, 4).shape == (50, 4)
    with pytest.raises(ValueError):
        idim_regressor(acc, v, u, 5)
