"""Position-dependent friction: a Coulomb level that varies linearly along the stroke (guide
preload or lubrication changing with position).

Physical model:

    F_eff(x, ẋ) = −c (x − x_ref) S_f(ẋ)                                             [N]

Identification: column x·S_f(ẋ) (x_ref is absorbed by θ3, only the slope c is identifiable).
Compensation: d̂_eff(x_d, ẋ_d) = −c_V (x_d − x_ref) S_f(ẋ_d) [V]. The emitted x_ref is the
end of the record's position range where the friction is lowest (its minimum for c > 0, its
maximum for c < 0), so the term is a friction (c (x − x_ref) ≥ 0) over the whole identified
stroke and θ3 keeps the lowest Coulomb level (the fitted θ3 re-expressed about x_ref,
:meth:`PositionDependentFrictionFamily.theta_shift`: θ3 + c_V x_ref). Evaluated on the
reference velocity at rest (``docs/identification.md``, "At rest"), a term that is a friction
pulls the carriage toward the target; one about the record's mean position (the reference
before) is a negative friction on one side and pushes it away: on the default plant (63.5 N/m,
16 s) that made the compensation lose at standstill (+18.6 µm² of L2[e]² above the floor) and
tune drop it on 3 of 3 seeds, where the simulator's own term (x_ref = 0, the stroke's start)
removed 1.30/0.84/1.44 of the damage.
"""

from __future__ import annotations

from typing import ClassVar

import numpy as np

from motorctl.effects.base import Adaptable, CompTerm, EffectFamily, PlantTerm, Signals
from motorctl.effects.periodic import SHAPE_POINTS
from motorctl.jit import njit
from motorctl.model import s_f
from motorctl.schema import StrictModel


@njit
def comp_add(d, x, v, t, sf, p):
    """d − c (x_d − x_r) S_f(ẋ_d) [V]; the row p = (c [V/m], x_r [m])."""
    return d - p[0] * (x - p[1]) * sf


@njit
def comp_fill(out, j, x, v, t, sf, p):
    """The adapted column (x_r − x) S_f(ẋ) into out[j]; the row p = (x_r [m],)."""
    out[j] = (p[0] - x) * sf

class PositionDependentFriction(StrictModel):
    """Simulated position-dependent friction,
    ``axes.NAME.driver.effects.position_dependent_friction``: −c (x − x_ref) S_f(ẋ) [N].
    coulomb_slope_N_per_m: c [N/m]. reference_m: x_ref [m]."""

    coulomb_slope_N_per_m: float
    reference_m: float = 0.0


class PositionFrictionComp(Adaptable):
    """Compensation, ``axes.NAME.controller.compensation.position_dependent_friction``:
    −c (x − x_ref) S_f(ẋ) [V]. coulomb_slope_V_per_m: c (force / A1) [V/m]. reference_m [m].
    Adaptable (:class:`~motorctl.effects.base.Adaptable`): β = [c], x_ref fixed."""

    coulomb_slope_V_per_m: float
    reference_m: float = 0.0

    def beta(self):
        return [self.coulomb_slope_V_per_m]

    def beta_names(self):
        return ["coulomb_slope_V_per_m"]


@njit
def line_force(f, x, v, t, sf, p):
    """f + F_eff [N] of the straight-line friction (this family's plant term, and the
    one-segment case of position_friction_shape) at position x [m] with sf = S_f(v) (v, t
    unused): f − c (x − x_ref) sf; the row p = (c [N/m], x_ref [m])."""
    return f - p[0] * (x - p[1]) * sf


#: largest share of what a friction of position explains that fitting it on each direction of
#: motion apart may add (:func:`motorctl.ident.probes.direction_split_gain`).
#: Measured: the families' own shapes on the default plant (×0.5, ×1, ×2, seeds 1-2) 0.000-0.007;
#: a 10 kg load through ±100 µm of play (benchmarks/ident_unmodelled.py backlash100 seed 3,
#: taken as a 12-segment friction shape: the load's push, mirrored about mid-stroke out and back)
#: 0.080
MAX_DIRECTION_SPLIT = 0.04


def direction_check(ctx, term, base) -> list[str]:
    """The reason a friction of position (this family's or position_friction_shape's ``term``)
    is refused when it is not one force whichever way the carriage passes (:data:`MAX_DIRECTION_SPLIT`),
    else none."""
    g = ctx.direction_split_gain(term, base)
    if g > MAX_DIRECTION_SPLIT:
        return [f"not one friction both ways: fitted on each direction of motion apart it explains "
                f"{100 * g:.0f} % more (> {100 * MAX_DIRECTION_SPLIT:g} %); a friction of position has one "
                "magnitude at a position whichever way the carriage passes it"]
    return []


class PositionDependentFrictionFamily(EffectFamily):
    name = "position_dependent_friction"
    size_parameters = ("coulomb_slope_",)
    search_cost = 0.002
    kernels = (("force", line_force), ("add", comp_add), ("fill", comp_fill))
    plant_force = "−c (x − x_ref) S_f(ẋ)"
    sim_options = PositionDependentFriction
    example: ClassVar[dict] = {"position_dependent_friction": {"coulomb_slope_N_per_m": 40.0, "reference_m": 0.0}}
    comp_options = PositionFrictionComp
    comp_needs_sf = True
    compensation_rank = 6

    # simulator
    def plant_term(self, o: PositionDependentFriction, period_s):
        return PlantTerm.compiled("force", line_force, [o.coulomb_slope_N_per_m, o.reference_m])

    # identification
    def columns(self, h, p):
        """x·S_f(ẋ), (N, 1); h unused."""
        return (p.x * s_f(p.v))[:, None]

    def plausible(self, ctx, term, beta, theta, base):
        x = ctx.p.x_d
        if min(theta[2] + beta[0] * x.min(), theta[2] + beta[0] * x.max()) < 0:
            return ["Coulomb level would turn negative over the stroke"]
        return direction_check(ctx, term, base)

    def parameters(self, h, beta, gain, fs):
        g, unit = (gain, "N") if gain else (1.0, "V")
        return {f"coulomb_slope_{unit}_per_m": float(g * beta[0])}

    # compensation
    def compensation(self, h, beta, signals=None, beta_std=None):
        """x_ref: the end of the record's position range (``signals.x`` [m]) where the fitted
        friction is lowest, min x for c ≥ 0, max x for c < 0 (0 without ``signals``): the term
        c (x − x_ref) S_f is then a friction over the whole identified stroke."""
        xr = 0.0
        if signals is not None and len(signals.x):
            xr = float(np.min(signals.x) if beta[0] >= 0 else np.max(signals.x))
        return self.adapt_entry({"coulomb_slope_V_per_m": float(beta[0]), "reference_m": xr}, beta_std)

    def theta_shift(self, entry, n_theta):
        """u = … + θ3 S_f + c_V x S_f = … + (θ3 + c_V x_ref) S_f + c_V (x − x_ref) S_f:
        Δθ3 = c_V x_ref."""
        d = np.zeros(n_theta)
        d[2] = entry["coulomb_slope_V_per_m"] * entry["reference_m"]
        return d

    def compensation_for(self, o: PositionDependentFriction, a1):
        return {"coulomb_slope_V_per_m": o.coulomb_slope_N_per_m / a1, "reference_m": o.reference_m}

    def compensator(self, o: PositionFrictionComp):
        return CompTerm("add", comp_add, [o.coulomb_slope_V_per_m, o.reference_m])

    def adapt_basis(self, o: PositionFrictionComp):
        return CompTerm("fill", comp_fill, [o.reference_m])

    # report
    def shape(self, ctx, h, beta, gain):
        pr = ctx.p
        xs = np.linspace(pr.x_d.min(), pr.x_d.max(), SHAPE_POINTS)
        zero = np.zeros_like(xs)
        v = np.full_like(xs, 0.1 * float(np.max(np.abs(pr.v_d))))
        y = -(gain or 1.0) * (self.columns(h, Signals(xs, v, zero, zero, zero)) @ beta)
        return xs, y, "position [m]", "effect force [UNIT] (moving forward)"


FAMILY = PositionDependentFrictionFamily()
