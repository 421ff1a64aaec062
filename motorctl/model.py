"""The plant model of Chen, Yao & Wang (2013): one source of truth for every other module.

Physical form (paper eq. 1 and 3)::

    M ÿ = F_m(u) − B ẏ − A_f S_f(ẏ) + F_dis
    F_m(u) = A1 u + A2 u|u| + A3 u³                                     (3)

Normalised form used by the controllers (eq. 4)::

    θ1 ẍ = u − θ2 ẋ − θ3 S_f(ẋ) + θ4 + θ5 u|u| + θ6 u³ + d̃
    θ = [M/A1, B/A1, A_f/A1, F_dis0/A1, A2/A1, A3/A1]

Units: y [m], u [V], forces [N], θ1 [V s²/m], θ2 [V s/m], θ3 [V], θ4 [V], θ5 [1/V], θ6 [1/V²].
The controllers (``motorctl.control``), the simulated gantry (``motorctl_drivers.sim``) and the
identification tool (``motorctl.ident``) all take their equations from here.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

#: Slope constant of the friction shape function S_f (paper §"friction", docs/control-law.md, Friction shape) [s/m].
S_F_GAIN = 900.0
#: Number of parameters of the cubic model (C2) and of the linear model (C1).
N_THETA_CUBIC = 6
N_THETA_LINEAR = 4
THETA_NAMES = ("theta1", "theta2", "theta3", "theta4", "theta5", "theta6")
THETA_UNITS = ("V*s^2/m", "V*s/m", "V", "V", "1/V", "1/V^2")


def s_f(x):
    """Friction shape function S_f(x) = (2/π)·arctan(900·x) (docs/control-law.md, Friction shape).

    Args:
        x: velocity [m/s], scalar or array of any shape.
    Returns:
        Same shape as ``x``, dimensionless, |S_f| < 1. Odd, S_f'(0) = 1800/π s/m.
    """
    return (2.0 / np.pi) * np.arctan(S_F_GAIN * np.asarray(x, dtype=float))


def s_f_scalar(x: float) -> float:
    """S_f for one Python float, without numpy overhead (used inside the 5 kHz cycle)."""
    return 0.6366197723675814 * math.atan(S_F_GAIN * x)


def s_f_slope(x):
    """dS_f/dx = (2/π)·900/(1 + (900x)²) [s/m]; used for the bound g ≤ 1800/π (paper eq. 12)."""
    x = np.asarray(x, dtype=float)
    return (2.0 / np.pi) * S_F_GAIN / (1.0 + (S_F_GAIN * x) ** 2)


def f_u(u, theta5: float, theta6: float):
    """Normalised input nonlinearity v = u + θ5 u|u| + θ6 u³ (paper eq. 9).

    Args:
        u: input voltage [V], scalar or array.
        theta5: [1/V]; theta6: [1/V²].
    Returns:
        v [V], same shape as ``u``.
    """
    u = np.asarray(u, dtype=float)
    return u + theta5 * u * np.abs(u) + theta6 * u**3


def f_u_slope(r, theta5: float, theta6: float):
    """df_u/du at |u| = r ≥ 0: 1 + 2θ5 r + 3θ6 r² (paper eq. 4 and Assumption 2; docs/control-law.md, Model, Assumption 2)."""
    r = np.asarray(r, dtype=float)
    return 1.0 + 2.0 * theta5 * r + 3.0 * theta6 * r**2


def motor_force(u, a1: float, a2: float, a3: float):
    """Thrust F_m(u) = A1 u + A2 u|u| + A3 u³ [N] (paper eq. 3); u [V], A1 [N/V], A2 [N/V²], A3 [N/V³]."""
    u = np.asarray(u, dtype=float)
    return a1 * u + a2 * u * np.abs(u) + a3 * u**3


def assumption2_margin(theta5_range: tuple[float, float], theta6_range: tuple[float, float],
                       u_lim: float) -> float:
    """Smallest slope of f_u over the parameter box and |u| ≤ u_lim (paper Assumption 2).

    f_u'(r) = 1 + 2θ5 r + 3θ6 r² is affine in (θ5, θ6) for a fixed r, so its minimum over the
    box is at a corner; for each corner the minimum over r ∈ [0, u_lim] is at an end point or,
    when θ6 > 0 > θ5, at the interior vertex r = −θ5/(3θ6) (paper eq. 4 and Assumption 2; docs/control-law.md, Model).

    Args:
        theta5_range: (θ5min, θ5max) [1/V]. theta6_range: (θ6min, θ6max) [1/V²].
        u_lim: the physical voltage limit u_M [V], > 0.
    Returns:
        The minimum slope (dimensionless). Assumption 2 holds iff it is > 0.
    """
    worst = math.inf
    for t5 in theta5_range:
        for t6 in theta6_range:
            candidates = [0.0, u_lim]
            if t6 > 0.0 and t5 < 0.0:
                r_star = -t5 / (3.0 * t6)
                if 0.0 < r_star < u_lim:
                    candidates.append(r_star)
            for r in candidates:
                worst = min(worst, 1.0 + 2.0 * t5 * r + 3.0 * t6 * r * r)
    return worst


@dataclass(frozen=True)
class PhysicalAxis:
    """Physical parameters of one axis (paper eq. 1 and 3), SI units.

    Attributes:
        mass_kg: moving mass M [kg]. a1_N_per_V, a2_N_per_V2, a3_N_per_V3: force curve (3).
        viscous_N_s_per_m: B. coulomb_N: A_f. offset_N: the constant part of F_dis (θ4·A1).
    """

    mass_kg: float
    a1_N_per_V: float
    a2_N_per_V2: float
    a3_N_per_V3: float
    viscous_N_s_per_m: float
    coulomb_N: float
    offset_N: float = 0.0

    def theta(self) -> np.ndarray:
        """θ = [M, B, A_f, F_dis0, A2, A3]/A1, shape (6,) (paper eq. 4 table)."""
        a1 = self.a1_N_per_V
        return np.array([self.mass_kg, self.viscous_N_s_per_m, self.coulomb_N, self.offset_N,
                         self.a2_N_per_V2, self.a3_N_per_V3]) / a1

    @classmethod
    def from_theta(cls, theta, a1_N_per_V: float) -> "PhysicalAxis":
        """Inverse of :meth:`theta`: θ (4 or 6 entries; θ5 = θ6 = 0 when 4) and A1 [N/V]."""
        th = np.zeros(6)
        th[: len(theta)] = theta
        p = th * a1_N_per_V
        return cls(mass_kg=p[0], a1_N_per_V=a1_N_per_V, a2_N_per_V2=p[4], a3_N_per_V3=p[5],
                   viscous_N_s_per_m=p[1], coulomb_N=p[2], offset_N=p[3])


def idim_regressor(acc, vel, u, n_theta: int = N_THETA_CUBIC) -> np.ndarray:
    """Inverse-dynamics regressor of eq. (4): u = Φ θ + residual.

    Rearranging (4) with d̃ = 0: u = θ1 ẍ + θ2 ẋ + θ3 S_f(ẋ) − θ4 − θ5 u|u| − θ6 u³, so the rows
    are Φ = [ẍ, ẋ, S_f(ẋ), −1, −u|u|, −u³] (the first ``n_theta`` columns). This is −φ of the
    paper's filtered regressor (25) before filtering.

    Args:
        acc [m/s²], vel [m/s], u [V]: arrays of shape (N,).
        n_theta: 4 (linear model, C1) or 6 (cubic model, C2).
    Returns:
        Φ, shape (N, n_theta).
    Raises:
        ValueError: n_theta not 4 or 6, or shapes differ.
    """
    if n_theta not in (N_THETA_LINEAR, N_THETA_CUBIC):
        raise ValueError(f"n_theta must be 4 or 6, got {n_theta}")
    acc, vel, u = (np.asarray(a, dtype=float) for a in (acc, vel, u))
    if not (acc.shape == vel.shape == u.shape) or acc.ndim != 1:
        raise ValueError("acc, vel and u must be 1-D arrays of the same length")
    cols = [acc, vel, s_f(vel), -np.ones_like(acc), -u * np.abs(u), -u**3]
    return np.column_stack(cols[:n_theta])
