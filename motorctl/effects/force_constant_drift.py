"""A drifting force constant: the thrust per volt changes slowly during a run (a coil warming
up: copper resistance and magnet flux fall with temperature, typically −0.1 %/K).

Physical model (first order in time): F_m(u, t) = (1 + κ (t − t_0)) F_m(u), κ [1/s] relative to
the force constant at t_0, i.e.

    F_eff = κ (t − t_0) A1 f_u(u)                                                          [N]

Simulator: ``axes.NAME.driver.effects.force_constant_drift``: the motor force F_m(u) (eq. 3,
with its cubic terms) is multiplied by 1 + κ (t − t_0) from plant time t_0 on.

Identification: column f_u(u)·(t − t_r), t_r the record's first sample time, β = −κ. This is
exact, not a first-order expansion: dividing eq. (1) by A1 (1 + κ (t − t_r)) gives
f_u(u) (1 + κ (t − t_r)) = θ_r φ with θ_r the nominal θ at t_r, so u = θ_r φ − κ (t − t_r) f_u(u)
(+ the nominal cubic columns), linear in θ_r and κ; κ is relative to the force constant at the
record's start (t_0 = t_r when the drift starts with the record). f_u is the thrust shape of the
joint fit's own θ5, θ6 (:meth:`ForceConstantDriftFamily.search` iterates them to a fixed point):
the nominal fit's θ5, θ6 are biased by the drift itself (the inputs grow as the force constant
falls, so the largest inputs come late and a saturating thrust curve absorbs part of the drift),
and a column on them leaves κ 56 % high on a 20 s log with κ = −0.01/s (+1 % with the fixed point).
Not compensable by an additive term: θ̂1 adaptation (eq. 25-28) follows a slow gain drift; the
report gives its rate so the user can tell warm-up from a fault.
"""

from __future__ import annotations

from typing import ClassVar

import numpy as np

from motorctl.effects.base import EffectFamily, PlantTerm
from motorctl.effects.periodic import SHAPE_POINTS
from motorctl.jit import njit
from motorctl.model import f_u
from motorctl.schema import NonNeg, StrictModel

#: the largest plausible drift over one record, as a fraction of the force constant
MAX_DRIFT = 0.5
#: fixed-point iterations of the thrust shape's θ5, θ6 in the drift's column (:meth:`search`;
#: converged within 1e-4 of κ after 3 on 20 s logs)
SHAPE_ITERATIONS = 4


class DriftReference(float):
    """The drift term's parameter h: its float value is the reference time t_r [s] the drift is
    counted from (the record's first sample time); ``theta5`` [1/V], ``theta6`` [1/V²]: the
    thrust shape f_u(u) = u + θ5 u|u| + θ6 u³ (paper eq. 9) of its column (0, 0: f_u = u)."""

    def __new__(cls, t_ref: float, theta5: float = 0.0, theta6: float = 0.0):
        obj = super().__new__(cls, float(t_ref))
        obj.theta5, obj.theta6 = float(theta5), float(theta6)
        return obj


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
    size_parameters = ("drift_per_s",)
    search_cost = 0.015
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
        """f_u(u)·(t − t_r), (N, 1). h: a :class:`DriftReference` (t_r and the shape's θ5, θ6);
        None: t_r = the first of ``p.t``, f_u = ``p.fu`` (u when the nominal θ5, θ6 are not fitted)."""
        if h is None:
            fu, t_ref = (p.u if p.fu is None else p.fu), float(p.t[0])
        else:
            fu, t_ref = f_u(p.u, h.theta5, h.theta6), float(h)
        return (fu * (p.t - t_ref))[:, None]

    def decimated_columns(self, h, p):
        """The decimated column (M, 1) at h from three the record decimates once: the
        decimation is linear, so dec(f_u(u)·τ) = dec(u τ) + θ5 dec(u|u| τ) + θ6 dec(u³ τ), τ = t −
        t_r (the same to rounding, 1e-16 of the column). Each of :meth:`search`'s fixed-point
        iterations then costs no full-rate f_u (8 ms on a 100 000-sample record) nor a
        decimation. None for h None (the column on ``p.fu``: :meth:`columns`)."""
        if h is None:
            return None
        t_ref = float(h)

        def full():
            u, tau = p.u, p.t - t_ref
            return np.column_stack([u * tau, u * np.abs(u) * tau, u ** 3 * tau])
        d = p.dec_once((self.name, t_ref), full)
        return d[:, :1] + h.theta5 * d[:, 1:2] + h.theta6 * d[:, 2:3]

    def search(self, ctx, base, residual):
        """The column on the joint fit's own thrust shape: start from the nominal θ5, θ6 and take
        those of the fit with the drift's column until they settle (:data:`SHAPE_ITERATIONS`);
        with θ1..θ4 only (no cubic terms) f_u = u, one fit."""
        t_ref = float(ctx.p.t[0])
        if ctx.n_theta != 6:
            return ctx.term(self.name, DriftReference(t_ref)), None
        th = ctx.evaluate(base).fit.coef
        for _ in range(SHAPE_ITERATIONS):
            term = ctx.term(self.name, DriftReference(t_ref, th[4], th[5]))
            th = ctx.evaluate(base + [term]).fit.coef
        return term, None

    def polish(self, ctx, term, others):
        """The thrust shape's fixed point again with the final model's ``others`` (θ5, θ6 move
        when stiction or a delay join the model)."""
        return self.search(ctx, others, None)[0]

    def plausible(self, ctx, term, beta, theta, base):
        span = float(ctx.p.t[-1] - ctx.p.t[0])
        drift = -float(beta[0]) * span
        if abs(drift) > MAX_DRIFT:
            return [f"force constant drifts {100 * drift:.0f} % over the record (> {100 * MAX_DRIFT:g} %)"]
        return []

    def parameters(self, h, beta, gain, fs):
        # κ relative to the force constant at t_r: f_u(u)(1 − β (t − t_r)) = θ_r φ, so κ = −β
        return {"drift_per_s": float(-beta[0])}

    # report
    def shape(self, ctx, h, beta, gain):
        p = ctx.p
        ts = np.linspace(p.t[0], p.t[-1], SHAPE_POINTS)
        y = 100.0 * (-beta[0]) * (ts - (p.t[0] if h is None else float(h)))
        return ts, y, "time [s]", "force constant change [%]"


FAMILY = ForceConstantDriftFamily()
