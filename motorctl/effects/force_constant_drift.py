"""A drifting force constant: the thrust per volt changes slowly during a run (a coil warming
up: copper resistance and magnet flux fall with temperature, typically −0.1 %/K).

Physical model (first order in time): F_m(u, t) = (1 + κ t) F_m(u), κ [1/s], i.e.

    F_eff = κ t A1 f_u(u)                                                                  [N]

Simulator: ``axes.NAME.driver.effects.force_constant_drift``: the motor force F_m(u) (eq. 3,
with its cubic terms) is multiplied by 1 + κ (t − t_0) from plant time t_0 on. Identification: column f_u(u)·(t − t̄) (t̄ the record's mid
time, so θ1 stays the mean level), β = −κ (F_eff = −A1 Cβ). Not compensable by an additive term:
θ̂1 adaptation (eq. 25-28) follows a slow gain drift; the report gives its rate so the user
can tell warm-up from a fault.
"""

from __future__ import annotations

from typing import ClassVar

import numpy as np

from motorctl.effects.base import EffectFamily, PlantTerm
from motorctl.effects.periodic import SHAPE_POINTS
from motorctl.jit import njit
from motorctl.schema import NonNeg, StrictModel

#: the largest plausible drift over one record, as a fraction of the force constant
MAX_DRIFT = 0.5


@njit
def plant_thrust(fm, x, t, p):
    """The thrust [N] at plant time t [s] (x unused): fm (1 + κ (t − t_0)) after t_0, else fm;
    the row p = (κ [1/s], t_0 [s])."""
    return fm * (1.0 + p[0] * (t - p[1])) if t > p[1] else fm


class ForceConstantDrift(StrictModel):
    """Simulated force-constant drift, ``axes.NAME.driver.effects.force_constant_drift``: the
    motor force is (1 + drift_per_s·(t − start_s)) F_m(u) from plant time start_s [s] on.
    drift_per_s: κ [1/s] (e.g. −0.005: −10 % in 20 s)."""

    drift_per_s: float
    start_s: NonNeg = 0.0


class ForceConstantDriftFamily(EffectFamily):
    name = "force_constant_drift"
    kernels = (("thrust", plant_thrust),)
    plant_force = "κ t A1 f_u(u)"
    sim_options = ForceConstantDrift
    example: ClassVar[dict] = {"force_constant_drift": {"drift_per_s": -0.01}}
    size_options: ClassVar[tuple[str, ...]] = ("drift_per_s",)

    # simulator
    def plant_term(self, o: ForceConstantDrift, period_s):
        return PlantTerm.compiled("thrust", plant_thrust, [o.drift_per_s, o.start_s])

    # identification
    def columns(self, h, p):
        """f_u(u)·(t − t̄), (N, 1) (u when the nominal θ5, θ6 are not fitted); h unused."""
        fu = p.u if p.fu is None else p.fu
        return (fu * (p.t - 0.5 * (p.t[0] + p.t[-1])))[:, None]

    def plausible(self, ctx, term, beta, theta, base):
        span = float(ctx.p.t[-1] - ctx.p.t[0])
        drift = -float(beta[0]) * span
        if abs(drift) > MAX_DRIFT:
            return [f"force constant drifts {100 * drift:.0f} % over the record (> {100 * MAX_DRIFT:g} %)"]
        return []

    def parameters(self, h, beta, gain, fs):
        # κ relative to the force constant: F_eff = −A1 β fu t, the nominal thrust A1 fu, so κ = −β
        return {"drift_per_s": float(-beta[0])}

    # report
    def shape(self, ctx, h, beta, gain):
        p = ctx.p
        ts = np.linspace(p.t[0], p.t[-1], SHAPE_POINTS)
        y = 100.0 * (-beta[0]) * (ts - 0.5 * (p.t[0] + p.t[-1]))
        return ts, y, "time [s]", "force constant change [%]"


FAMILY = ForceConstantDriftFamily()
