"""Cubic input inversion of the DCDIARC law (paper eq. 9, docs/control-law.md, The DCDIARC law).

Solves f(u) = u + θ̂5 u|u| + θ̂6 u³ = v for the unique root with |u| ≤ u_M. Under Assumption 2
f is odd and strictly increasing on |u| ≤ u_M, so sign(u) = sign(v) and r = |u| solves
g(r) = r + θ̂5 r² + θ̂6 r³ − |v| = 0 on [0, u_M].

Branches:
  * θ̂5 = θ̂6 = 0 (C1): u = v.
  * θ̂6 = 0, θ̂5 ≠ 0: the stable quadratic root r = 2w / (1 + √(1 + 4θ̂5 w)).
  * otherwise: safeguarded Newton on the bracket [0, u_M] (robust as θ̂6 → 0, where Cardano's
    formula loses accuracy, docs/control-law.md, The DCDIARC law pitfall).
  * |v| ≥ f(u_M): the demand exceeds the actuator; |u| = u_M.
"""

from __future__ import annotations

import math

from motorctl.jit import njit

_MAX_ITER = 60
_TOL = 1e-13


@njit
def invert_cubic(v: float, theta5: float, theta6: float, u_max: float) -> float:
    """Return u with u + θ5 u|u| + θ6 u³ = v and |u| ≤ u_max (paper eq. 9, docs/control-law.md, The DCDIARC law).

    Args:
        v: virtual input [V] (finite).
        theta5: θ̂5 [1/V]. theta6: θ̂6 [1/V²]. Must satisfy Assumption 2 on [0, u_max]
            (f strictly increasing); the parameter projection and the config check ensure it.
        u_max: the voltage limit u_M [V], > 0.
    Returns:
        u [V], |u| ≤ u_max; saturates at ±u_max when |v| ≥ f(u_max).
    Pure float arithmetic (numba-compiled; callable from Python and from other kernels).
    """
    if v >= 0.0:
        s = 1.0
        w = v
    else:
        s = -1.0
        w = -v
    if theta5 == 0.0 and theta6 == 0.0:
        return s * (w if w < u_max else u_max)
    f_max = u_max + theta5 * u_max * u_max + theta6 * u_max * u_max * u_max
    if w >= f_max:
        return s * u_max
    if theta6 == 0.0:
        disc = 1.0 + 4.0 * theta5 * w
        if disc <= 0.0:  # beyond the quadratic's turning point: cannot happen under Assumption 2
            return s * u_max
        r = 2.0 * w / (1.0 + math.sqrt(disc))
        return s * (r if r < u_max else u_max)
    # Safeguarded Newton on g(r) = r + θ5 r² + θ6 r³ − w, g(0) = −w ≤ 0 < g(u_max).
    lo = 0.0
    hi = u_max
    r = w if w < u_max else u_max
    for _ in range(_MAX_ITER):
        g = r + theta5 * r * r + theta6 * r * r * r - w
        if g == 0.0:
            break
        if g > 0.0:
            hi = r
        else:
            lo = r
        dg = 1.0 + 2.0 * theta5 * r + 3.0 * theta6 * r * r
        if dg > 0.0:
            r_new = r - g / dg
            if r_new < lo or r_new > hi:  # Newton left the bracket: bisect
                r_new = 0.5 * (lo + hi)
        else:
            r_new = 0.5 * (lo + hi)
        if abs(r_new - r) <= _TOL * (1.0 + r):
            r = r_new
            break
        r = r_new
    return s * r
