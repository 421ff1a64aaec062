"""The cubic input inversion of eq. (9): every branch, monotonicity, |u| <= u_M, reference root-finder."""

import numpy as np
import pytest
from conftest import examples
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.optimize import brentq

from motorctl.control.inversion import invert_cubic
from motorctl.model import f_u

U_M = 10.0
CASES = [(-0.015, -0.002), (-0.0186, -0.0003), (-0.01, 0.001), (0.0, -0.002), (-0.013, 0.0),
         (-0.013, 1e-12), (-0.013, -1e-12)]


def _reference(v, t5, t6):
    f_max = float(f_u(U_M, t5, t6))
    if abs(v) >= f_max:
        return np.sign(v) * U_M
    return brentq(lambda u: float(f_u(u, t5, t6)) - v, -U_M, U_M, xtol=1e-14)


@pytest.mark.parametrize("t5,t6", CASES)
def test_agrees_with_brentq_and_inverts(t5, t6):
    for v in np.linspace(-12, 12, 241):
        u = invert_cubic(v, t5, t6, U_M)
        assert abs(u) <= U_M
        assert u == pytest.approx(_reference(v, t5, t6), abs=1e-9)
        if abs(u) < U_M:
            assert float(f_u(u, t5, t6)) == pytest.approx(v, abs=1e-9)


def test_spec_check_value():
    # eq. 9: v = 6.49 V with the X corner values gives u = 9.9065 V; f(10) = 6.5 V
    assert invert_cubic(6.49, -0.015, -0.002, U_M) == pytest.approx(9.9065, abs=1e-4)
    assert float(f_u(10.0, -0.015, -0.002)) == pytest.approx(6.5)


def test_c1_branch_is_identity_with_clip():
    assert invert_cubic(3.2, 0.0, 0.0, U_M) == 3.2
    assert invert_cubic(-3.2, 0.0, 0.0, U_M) == -3.2
    assert invert_cubic(12.0, 0.0, 0.0, U_M) == U_M
    assert invert_cubic(-12.0, 0.0, 0.0, U_M) == -U_M


def test_quadratic_branch_and_saturation():
    # theta6 = 0: stable quadratic root
    u = invert_cubic(5.0, -0.02, 0.0, U_M)
    assert u + (-0.02) * u * abs(u) == pytest.approx(5.0, abs=1e-12)
    # demand above f(u_M) saturates, with the sign of v
    f_max = float(f_u(U_M, -0.015, -0.002))
    assert invert_cubic(f_max + 0.01, -0.015, -0.002, U_M) == U_M
    assert invert_cubic(-(f_max + 0.01), -0.015, -0.002, U_M) == -U_M
    assert invert_cubic(0.0, -0.015, -0.002, U_M) == 0.0


def test_theta6_to_zero_is_continuous():
    # the Cardano pitfall (docs/control-law.md, The DCDIARC law): no accuracy loss as theta6 -> 0
    base = invert_cubic(4.0, -0.013, 0.0, U_M)
    for t6 in (1e-6, 1e-9, 1e-12, -1e-12, -1e-9):
        u = invert_cubic(4.0, -0.013, t6, U_M)
        assert u == pytest.approx(_reference(4.0, -0.013, t6), abs=1e-11)
        # du/dtheta6 = -u^3 / f'(u), about -85 V^3 here: the change scales with |theta6|
        assert abs(u - base) <= 100 * abs(t6) + 1e-12
    assert invert_cubic(1e-15, -0.013, 1e-9, U_M) == pytest.approx(1e-15, rel=1e-6)


@settings(max_examples=examples(300), deadline=None)
@given(t5=st.floats(-0.015, 0.0), t6=st.floats(-0.002, 0.0),
       v1=st.floats(-15, 15), v2=st.floats(-15, 15))
def test_odd_monotonic_and_bounded(t5, t6, v1, v2):
    u1 = invert_cubic(v1, t5, t6, U_M)
    u2 = invert_cubic(v2, t5, t6, U_M)
    assert abs(u1) <= U_M and abs(u2) <= U_M
    assert invert_cubic(-v1, t5, t6, U_M) == pytest.approx(-u1, abs=1e-12)
    if v1 < v2:
        assert u1 <= u2 + 1e-12
