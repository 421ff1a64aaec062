"""Spring: a restoring force linear in position (cable carrier, bellows).

Physical model (Hooke):

    F_eff(x) = −k (x − x_0)                                                          [N]

Identification: column x (x_0 is absorbed by θ4, only the stiffness k is identifiable).
Compensation: d̂_eff(x_d) = −k_V (x_d − x_0) [V]. The emitted x_0 is the record's mean position,
so that the term has zero mean over the identified motion and the nominal θ4 keeps the mean
force (the fitted θ4 re-expressed about x_0, :meth:`SpringFamily.theta_shift`: θ4 − k_V x_0).
"""

from __future__ import annotations

from typing import ClassVar

import numpy as np

from motorctl.effects.base import Adaptable, CompTerm, EffectFamily, PlantTerm, Signals
from motorctl.effects.periodic import SHAPE_POINTS
from motorctl.jit import njit
from motorctl.schema import StrictModel


@njit
def plant_force(f, x, v, t, sf, p):
    """f + F_eff [N] at position x [m] (v, t, sf unused): f − k (x − x_0); the row
    p = (k [N/m], x_0 [m])."""
    return f - p[0] * (x - p[1])


@njit
def comp_add(d, x, v, t, sf, p):
    """d − k (x_d − x_0) [V]; the row p = (k [V/m], x_0 [m])."""
    return d - p[0] * (x - p[1])


@njit
def comp_fill(out, j, x, v, t, sf, p):
    """The adapted spring's column x_0 − x into out[j]; the row p = (x_0 [m],)."""
    out[j] = p[0] - x

class Spring(StrictModel):
    """Simulated spring, ``axes.NAME.driver.effects.spring``: −k (x − x_0) [N].
    stiffness_N_per_m: k [N/m]. rest_position_m: x_0 [m]."""

    stiffness_N_per_m: float
    rest_position_m: float = 0.0


class SpringComp(Adaptable):
    """Spring compensation, ``axes.NAME.controller.compensation.spring``: −k (x − x_0) [V].
    stiffness_V_per_m: k (force / A1) [V/m]. rest_position_m: x_0 [m]. Adaptable
    (:class:`~motorctl.effects.base.Adaptable`): β = [k], x_0 fixed."""

    stiffness_V_per_m: float
    rest_position_m: float = 0.0

    def beta(self):
        return [self.stiffness_V_per_m]

    def beta_names(self):
        return ["stiffness_V_per_m"]


class SpringFamily(EffectFamily):
    name = "spring"
    size_parameters = ("stiffness_",)
    search_cost = 0.002
    kernels = (("force", plant_force), ("add", comp_add), ("fill", comp_fill))
    plant_force = "−k (x − x_0)"
    sim_options = Spring
    example: ClassVar[dict] = {"spring": {"stiffness_N_per_m": 100.0, "rest_position_m": 0.1}}
    comp_options = SpringComp
    compensation_rank = 2

    # simulator
    def plant_term(self, o: Spring, period_s):
        return PlantTerm.compiled("force", plant_force, [o.stiffness_N_per_m, o.rest_position_m])

    # identification
    def columns(self, h, p):
        """x, (N, 1); h unused."""
        return p.x[:, None]

    def plausible(self, ctx, term, beta, theta, base):
        """A spring restores: k > 0 (the input holds +k_V (x − x_0) against −k (x − x_0)). A
        fitted k ≤ 0 is a force pushing away from the middle of the stroke, which a thrust lost
        towards both ends of a back-and-forth program (a linear motor's end effect) also gives,
        since there the input's sign goes with the end: no spring."""
        if not beta[0] > 0.0:
            return ["negative stiffness: a force pushing away from the rest position is not a spring"]
        return []

    def parameters(self, h, beta, gain, fs):
        g, unit = (gain, "N") if gain else (1.0, "V")
        return {f"stiffness_{unit}_per_m": float(g * beta[0])}

    # compensation
    def compensation(self, h, beta, signals=None, beta_std=None):
        """x_0: the record's mean position (0 without ``signals``)."""
        x0 = float(np.mean(signals.x)) if signals is not None else 0.0
        return self.adapt_entry({"stiffness_V_per_m": float(beta[0]), "rest_position_m": x0}, beta_std)

    def theta_shift(self, entry, n_theta):
        """u = … − θ4 + k_V x = … − (θ4 − k_V x_0) + k_V (x − x_0): Δθ4 = −k_V x_0."""
        d = np.zeros(n_theta)
        d[3] = -entry["stiffness_V_per_m"] * entry["rest_position_m"]
        return d

    def compensation_for(self, o: Spring, a1):
        return {"stiffness_V_per_m": o.stiffness_N_per_m / a1, "rest_position_m": o.rest_position_m}

    def compensator(self, o: SpringComp):
        return CompTerm("add", comp_add, [o.stiffness_V_per_m, o.rest_position_m])

    def adapt_basis(self, o: SpringComp):
        return CompTerm("fill", comp_fill, [o.rest_position_m])

    # report
    def shape(self, ctx, h, beta, gain):
        pr = ctx.p
        xs = np.linspace(pr.x_d.min(), pr.x_d.max(), SHAPE_POINTS)
        zero = np.zeros_like(xs)
        y = -(gain or 1.0) * (self.columns(h, Signals(xs, zero, zero, zero, zero)) @ beta)
        return xs, y, "position [m]", "effect force [UNIT]"


FAMILY = SpringFamily()
