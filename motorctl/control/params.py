"""The settings of every controller of an axis (one schema) and the theory-mode gain bound (no
compiled code here, so a config can be loaded and checked without loading the control kernels)."""

from __future__ import annotations

import math
from typing import Annotated, Literal

import numpy as np
from pydantic import Field

from motorctl.effects.compensation import CompensationConfig, CompensationSection
from motorctl.model import S_F_GAIN
from motorctl.schema import NonNeg, Pos, StrictModel, Vec6, quantity


class FilterConfig(StrictModel):
    """H_f = ω_f²/(s + ω_f)² of the estimator's regressor (docs/control-law.md, Order of operations) [S]."""

    omega_f: quantity(1e-2, 1e6, "rad/s") = 200.0


class TheoryConfig(StrictModel):
    """Theory-mode design numbers (eq. 14-15, 22): k2 [V s/m], eta, delta_d [V], optional k_s1."""

    k2: Pos = 10.0
    eta: Pos = 0.05
    delta_d: NonNeg = 0.3
    k_s1: Pos | None = None


class PidConfig(StrictModel):
    """LinuxCNC ``pid`` gains and limits (hal/components/pid.c, manual page pid(9)), in SI units.

    Read by :class:`motorctl.control.pid.PID` (the per-sample calculation is in its module
    docstring). LinuxCNC's error = command − feedback = x_d − y (the opposite sign of the
    published tracking error e = y − x_d); the output u [V] pushes +x. A gain of 0 (or a limit
    of 0) switches that term (or that limit) off, as in LinuxCNC. Unlike LinuxCNC, FF1 and FF2
    (and the command part of the D term) use the trajectory's analytic ẋ_d and ẍ_d.

    Attributes:
        P [V/m], I [V/(m s)], D [V s/m]: feedback gains on the error, its integral and its
            derivative (ẋ_d − ẏ); ≥ 0.
        FF0 [V/m], FF1 [V s/m], FF2 [V s²/m]: feedforward of the command x_d, its velocity ẋ_d
            and its acceleration ẍ_d (for this plant FF1 ≈ θ2, FF2 ≈ θ1 of the model, eq. 4).
        bias [V]: constant output offset (≈ −θ4).
        deadband [m]: |error| ≤ deadband counts as 0; above it the error is reduced by it. ≥ 0.
        maxerror [m]: the error is clipped to ±maxerror before the deadband (0 = none).
        maxerror_i [m s]: the integral of the error is clipped to ±maxerror_i (0 = none).
        maxoutput [V]: output limit; the output is clipped to ±min(maxoutput, u_lim)
            (0 = u_lim of the section).
    """

    P: quantity(0.0, 1e10, "V/m") = 0.0
    I: quantity(0.0, 1e12, "V/(m s)") = 0.0
    D: quantity(0.0, 1e8, "V s/m") = 0.0
    FF0: quantity(-1e10, 1e10, "V/m") = 0.0
    FF1: quantity(-1e8, 1e8, "V s/m") = 0.0
    FF2: quantity(-1e6, 1e6, "V s^2/m") = 0.0
    bias: quantity(-1e3, 1e3, "V") = 0.0
    deadband: quantity(0.0, 1.0, "m") = 0.0
    maxerror: quantity(0.0, 100.0, "m") = 0.0
    maxerror_i: quantity(0.0, 1e4, "m s") = 0.0
    maxoutput: quantity(0.0, 1e3, "V") = 0.0


class ControllerConfig(StrictModel):
    """An axis's ``controller:`` section: the one schema of every controller's settings.

    ``type`` names the active controller (:data:`motorctl.control.CONTROLLERS`). C1 and C2 (the
    DCDIARC law, the paper's Section 6, §7) read the top-level keys; C1 uses the first four entries of
    the 6-vectors. A PID reads ``pid`` (and ``u_lim``). Every controller of the section can
    be switched to at run time.

    Attributes:
        mode: "experiment" (constant k_s) or "theory" (k_s1 + k_s2, eq. 22).
        k_s [V s/m], k1 [1/s], gamma_d [V/m], d_hat_max [V], u_lim [V] (u_M of Assumption 2
        and the output clamp). theta_min, theta_max, theta_hat0: the box Ω_θ and θ̂(0).
        gamma0: diagonal of Γ(0). filter.omega_f [rad/s]. mu [1/s], nu, rho_M: LS settings
        (eq. 27). theory: theory-mode numbers. compensation: identified effects
        (:data:`~motorctl.effects.compensation.CompensationSection`: additive terms in v_a1,
        eq. 13, fixed or adapted with θ̂; force ripple, eq. 9; input-delay preview).
    """

    type: str = "c2"
    mode: Literal["experiment", "theory"] = "experiment"
    k_s: quantity(1e-3, 1e7, "V s/m") = 95.0
    k1: quantity(1e-3, 1e6, "1/s") = 250.0
    gamma_d: quantity(0.0, 1e9, "V/m") = 500.0
    d_hat_max: quantity(0.0, 1e3, "V") = 1.0
    u_lim: quantity(1e-3, 1e3, "V") = 10.0
    theta_min: Vec6
    theta_max: Vec6
    theta_hat0: Vec6
    gamma0: Annotated[list[Pos], Field(min_length=6, max_length=6)]
    filter: FilterConfig = FilterConfig()
    mu: quantity(0.0, 1e4, "1/s") = 0.0
    nu: NonNeg = 0.0
    rho_M: Pos = 1000.0
    theory: TheoryConfig = TheoryConfig()
    compensation: CompensationSection = CompensationSection()
    pid: PidConfig | None = None


def theory_k_s1(theta_min, theta_max, k1: float, k2: float) -> float:
    """Smallest k_s1 meeting the PSD condition of paper eq. 13-15; docs/control-law.md, The DCDIARC law (paper eq. 14-15, as reconstructed).

    k_s1 ≥ k2 + θ1 k1 − θ2 − θ3 g + (θ2 + θ3 g)²/(2 θ1 k1) for all θ ∈ Ω_θ, 0 ≤ g ≤ 1800/π.
    The right side is convex in g and in (θ2, θ3), so the maximum over the box corners and the
    end points of g is exact; a grid in g guards the corner enumeration.
    """
    g_max = 2.0 * S_F_GAIN / math.pi
    worst = -math.inf
    for t1 in (theta_min[0], theta_max[0]):
        for t2 in (theta_min[1], theta_max[1]):
            for t3 in (theta_min[2], theta_max[2]):
                for g in np.linspace(0.0, g_max, 65):
                    val = k2 + t1 * k1 - t2 - t3 * g + (t2 + t3 * g) ** 2 / (2.0 * t1 * k1)
                    worst = max(worst, val)
    return float(worst)
