"""The thrust shape f_u(u) = u + θ5 u|u| + θ6 u³ (paper eq. 9) on which the columns of the
effects that scale the thrust are built (the force ripple's, the force-constant drift's): the
fitted curve's, unless it keeps less than MIN_THRUST_SHARE of the linear thrust at the record's
largest input (a strong ripple bends the nominal θ5, θ6 that far; no motor saturates so), then u.
No identify run: the identifier's input and θ̂ are given."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from motorctl.ident.idim import input_reach
from motorctl.ident.select import MIN_THRUST_SHARE, Identifier
from motorctl.model import f_u

#: inputs [V] reaching ±10 V, as on the default plant's logs
U = np.linspace(-10.0, 10.0, 2001)


def _shape(theta, n_theta=6, u=U):
    ident = SimpleNamespace(n_theta=n_theta, p=SimpleNamespace(u=u), u_reach=input_reach(u))
    return Identifier.thrust_shape(ident, u, np.asarray(theta, dtype=float))


def test_a_motors_saturation_is_the_columns_thrust_shape():
    # the default plant's curve: f_u(10 V) = 7.2 V, 0.72 of the linear thrust
    theta = [0.16, 0.22, 0.25, -0.05, -0.013, -0.0015]
    assert np.array_equal(_shape(theta), f_u(U, -0.013, -0.0015))


def test_a_curve_that_keeps_less_than_the_least_share_gives_u():
    # the nominal fit of the default plant with an 18 % force ripple: f_u(10 V)/10 V = 0.26
    bent = [0.06, 0.26, -0.026, -0.036, -0.1652, 0.0091]
    assert float(f_u(10.0, bent[4], bent[5])) / 10.0 < MIN_THRUST_SHARE
    assert _shape(bent) is None
    # the rule reads the record's largest input: the same curve up to 3 V keeps 0.75
    small = np.linspace(-3.0, 3.0, 601)
    assert float(f_u(3.0, bent[4], bent[5])) / 3.0 > MIN_THRUST_SHARE
    assert np.array_equal(_shape(bent, u=small), f_u(small, bent[4], bent[5]))


def test_the_share_is_the_bound():
    # θ6 = 0: f_u(r)/r = 1 + θ5 r, so θ5 = (share − 1)/r puts the curve on the bound
    r = input_reach(U)
    on = (MIN_THRUST_SHARE - 1.0) / r
    assert _shape([0, 0, 0, 0, on * (1 - 1e-6), 0.0]) is not None
    assert _shape([0, 0, 0, 0, on * (1 + 1e-3), 0.0]) is None


def test_without_the_cubic_terms_the_columns_use_u():
    assert _shape([0.16, 0.22, 0.25, -0.05], n_theta=4) is None
