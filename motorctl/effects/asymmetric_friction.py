"""Asymmetric (direction-dependent) friction: different Coulomb and viscous levels forward.

Physical model (the EMPS reference model has separate F_c, F_v per direction; the nominal θ2,
θ3 carry the backward level, this family the difference):

    F_eff(ẋ) = −(ΔF_c S_f(ẋ) + ΔB ẋ)   for ẋ > 0,   0 otherwise                   [N]

Identification: columns S_f(ẋ)·[ẋ > 0], ẋ·[ẋ > 0] (no searched parameter). Compensation:
d̂_eff(ẋ_d) = −(ΔF_V S_f(ẋ_d) + ΔB_V ẋ_d) for ẋ_d > 0 [V].
"""

from __future__ import annotations

from typing import ClassVar

import numpy as np

from motorctl.effects.base import Adaptable, CompTerm, EffectFamily, PlantTerm, Signals
from motorctl.effects.stribeck import velocity_grid
from motorctl.jit import njit
from motorctl.model import s_f
from motorctl.schema import StrictModel


@njit
def plant_force(f, x, v, t, sf, p):
    """f + F_eff [N] at velocity v [m/s] with sf = S_f(v) (x, t unused): f − (ΔF_c sf + ΔB v)
    for v > 0, else f; the row p = (ΔF_c [N], ΔB [N s/m])."""
    return f - (p[0] * sf + p[1] * v) if v > 0.0 else f


@njit
def comp_add(d, x, v, t, sf, p):
    """d − (c S_f(ẋ_d) + b ẋ_d) in forward motion (ẋ_d > 0), else d [V]; the row p = (c [V],
    b [V s/m])."""
    return d - (p[0] * sf + p[1] * v) if v > 0.0 else d


@njit
def comp_fill(out, j, x, v, t, sf, p):
    """The adapted columns −S_f(ẋ), −ẋ in forward motion (0, 0 otherwise) into out[j:j + 2]
    (the row p is empty)."""
    if v > 0.0:
        out[j] = -sf
        out[j + 1] = -v
    else:
        out[j] = 0.0
        out[j + 1] = 0.0

#: "at rest" for :func:`held_offset`: |ẋ| below this [m/s] (the simulator's stiction band)
REST_V = 1e-4
#: least time at rest [s] for :func:`held_offset`
MIN_REST_S = 1.0


def held_offset(p, theta3: float) -> float | None:
    """The offset θ4 [V] (θ4·A1 = F_0, the constant force on the carriage) from the input held
    at rest, or None when the record cannot tell it.

    A carriage held by static friction (Karnopp) stays while |A1 u + F_0| ≤ F_s, so the input
    held at rest spans [(−F_s − F_0)/A1, (F_s − F_0)/A1], symmetric about −θ4, when the loop
    pushes it to the breakaway both ways (C2 hunting at rest does). Taken when the record is
    at rest (|ẋ| < :data:`REST_V`) for at least :data:`MIN_REST_S`, the held input takes both
    signs and its span reaches 2θ3 (static friction is at least the kinetic level): θ4 =
    −(max + min)/2 of u at rest.

    Args:
        p: the prepared record (full-rate v [m/s], u [V], fs [Hz]). theta3: the Coulomb level
            θ3 [V] of the fit.
    """
    rest = np.abs(p.v) < REST_V
    if rest.sum() < MIN_REST_S * p.fs:
        return None
    held = p.u[rest]
    lo, hi = float(held.min()), float(held.max())
    if not (lo < 0.0 < hi and hi - lo >= 2.0 * theta3 > 0.0):
        return None
    return -0.5 * (lo + hi)


class AsymmetricFriction(StrictModel):
    """Simulated asymmetric friction, ``axes.NAME.driver.effects.asymmetric_friction``:
    −(ΔF_c S_f(ẋ) + ΔB ẋ) for ẋ > 0 [N]. coulomb_N: ΔF_c [N]. viscous_N_s_per_m: ΔB [N·s/m]."""

    coulomb_N: float = 0.0
    viscous_N_s_per_m: float = 0.0


class AsymmetricFrictionComp(Adaptable):
    """Asymmetric friction compensation, ``axes.NAME.controller.compensation.asymmetric_friction``:
    −(ΔF S_f(ẋ) + ΔB ẋ) for ẋ > 0 [V]. coulomb_V [V], viscous_V_s_per_m [V·s/m] (force / A1).
    Adaptable (:class:`~motorctl.effects.base.Adaptable`): β = [ΔF, ΔB]."""

    coulomb_V: float = 0.0
    viscous_V_s_per_m: float = 0.0

    def beta(self):
        return [self.coulomb_V, self.viscous_V_s_per_m]

    def beta_names(self):
        return ["coulomb_V", "viscous_V_s_per_m"]


class AsymmetricFrictionFamily(EffectFamily):
    name = "asymmetric_friction"
    kernels = (("force", plant_force), ("add", comp_add), ("fill", comp_fill))
    plant_force = "−(ΔF_c S_f(ẋ) + ΔB ẋ), ẋ > 0 only"
    sim_options = AsymmetricFriction
    example: ClassVar[dict] = {"asymmetric_friction": {"coulomb_N": 10.0, "viscous_N_s_per_m": 20.0}}
    comp_options = AsymmetricFrictionComp
    comp_needs_sf = True
    compensation_rank = 5

    # simulator
    def plant_term(self, o: AsymmetricFriction, period_s):
        return PlantTerm.compiled("force", plant_force, [o.coulomb_N, o.viscous_N_s_per_m])

    # identification
    def columns(self, h, p):
        """S_f(ẋ)·[ẋ > 0], ẋ·[ẋ > 0], (N, 2); h unused."""
        v = p.v
        pos = (v > 0).astype(float)
        return np.column_stack([s_f(v) * pos, v * pos])

    def parameters(self, h, beta, gain, fs, theta=None, p=None):
        """ΔF_c and ΔB [N, N·s/m; V, V·s/m without the gain]. In motion a constant offset force
        (θ4's column −1) and the forward-only Coulomb column S_f(ẋ)·[ẋ > 0] = (S_f + |S_f|)/2
        are collinear: the fit fixes the two levels θ3 + β − θ4 (forward) and θ3 + θ4
        (backward), not β and θ4 apart, and a carriage held at rest shows neither (its input
        there is unconstrained). When the record's input held at rest spans the breakaway both
        ways (:func:`held_offset`), θ4 is taken from there and ΔF_c = β − 2θ4 + 2θ4_held: on
        the default plant (offset −4 N, stiction 25 N) 7.64 N became 6.5 N for 6 N."""
        g, unit = (gain, "N") if gain else (1.0, "V")
        dfc = float(beta[0])
        if theta is not None and p is not None and len(theta) > 3:
            th4 = held_offset(p, float(theta[2]))
            if th4 is not None:
                dfc += 2.0 * (th4 - float(theta[3]))
        return {f"coulomb_{unit}": float(g * dfc), f"viscous_{unit}_s_per_m": float(g * beta[1])}

    # compensation
    def compensation(self, h, beta, signals=None, beta_std=None):
        return self.adapt_entry({"coulomb_V": float(beta[0]), "viscous_V_s_per_m": float(beta[1])}, beta_std)

    def compensation_for(self, o: AsymmetricFriction, a1):
        return {"coulomb_V": o.coulomb_N / a1, "viscous_V_s_per_m": o.viscous_N_s_per_m / a1}

    def compensator(self, o: AsymmetricFrictionComp):
        return CompTerm("add", comp_add, [o.coulomb_V, o.viscous_V_s_per_m])

    def adapt_basis(self, o: AsymmetricFrictionComp):
        return CompTerm("fill", comp_fill, [])

    # report
    def shape(self, ctx, h, beta, gain):
        vs = velocity_grid(ctx)
        zero = np.zeros_like(vs)
        y = -(gain or 1.0) * (self.columns(h, Signals(zero, vs, zero, zero, zero)) @ beta)
        return vs, y, "velocity [m/s]", "effect force [UNIT]"


FAMILY = AsymmetricFrictionFamily()
