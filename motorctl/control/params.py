"""Settings of one DCDIARC controller and the theory-mode gain bound (no compiled code here,
so a config can be loaded and checked without loading the control kernels)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from motorctl.compensation import CompensationConfig
from motorctl.model import S_F_GAIN


@dataclass(frozen=True)
class ControllerParams:
    """All settings of one DCDIARC controller (spec §6.2, §7). Vectors have 4 (C1) or 6 (C2) entries.

    Attributes:
        kind: "c1" or "c2".  mode: "experiment" (constant k_s) or "theory" (k_s1 + k_s2, eq. 22).
        k_s [V s/m], k1 [1/s], gamma_d [V/m], d_hat_max [V].
        theta_min, theta_max, theta_hat0: the box Ω_θ and θ̂(0).  gamma0: diagonal of Γ(0).
        omega_f [rad/s]: H_f corner.  mu [1/s], nu, rho_M: LS settings (eq. 27).
        u_lim [V]: actuator limit u_M of Assumption 2 and the output clamp.
        k2 [V s/m], eta [V²·... ], delta_d [V]: theory-mode design numbers (eq. 14-15, 22).
        k_s1: theory-mode k_s1; None computes the smallest value meeting the bound of spec §3.3.
    """

    kind: str
    theta_min: tuple
    theta_max: tuple
    theta_hat0: tuple
    gamma0: tuple
    mode: str = "experiment"
    k_s: float = 95.0
    k1: float = 250.0
    gamma_d: float = 500.0
    d_hat_max: float = 1.0
    omega_f: float = 200.0
    mu: float = 0.0
    nu: float = 0.0
    rho_M: float = 1000.0
    u_lim: float = 10.0
    k2: float = 10.0
    eta: float = 0.05
    delta_d: float = 0.3
    k_s1: float | None = None
    compensation: CompensationConfig | None = None

    @property
    def n_theta(self) -> int:
        return 6 if self.kind == "c2" else 4


def theory_k_s1(theta_min, theta_max, k1: float, k2: float) -> float:
    """Smallest k_s1 meeting the PSD condition of spec §3.3 (paper eq. 14-15, as reconstructed).

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
