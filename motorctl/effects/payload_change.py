"""Payload change: the moving mass steps by Δm at time t_c (a part loaded on the carriage).

Physical model: M(t) = M + Δm·[t ≥ t_c] in M ẍ = …, i.e. F_eff = −Δm ẍ·[t ≥ t_c] [N] seen
from the nominal model. Identification: column ẍ·[t ≥ t_c] (a step of θ1), t_c searched on a
50 ms grid (middle of a flat minimum). Not compensable: it is a mass, not an additive force in
(x_d, ẋ_d, t) (the adaptation of θ̂1 follows it).
"""

from __future__ import annotations

from typing import ClassVar

import numpy as np

from motorctl.effects.base import EffectFamily, PlantTerm, Signals
from motorctl.effects.periodic import SHAPE_POINTS
from motorctl.jit import njit
from motorctl.schema import NonNeg, StrictModel


@njit
def plant_mass(m, t, p):
    """The moving mass [kg] at plant time t [s]: m + Δm from t_c on, else m; the row
    p = (t_c [s], Δm [kg])."""
    return m + p[1] if t >= p[0] else m


class PayloadChange(StrictModel):
    """Simulated payload change, ``axes.NAME.driver.effects.payload_change``: the mass grows by
    mass_kg [kg] (may be negative) from plant time t_change_s [s] on."""

    t_change_s: NonNeg
    mass_kg: float


class PayloadChangeFamily(EffectFamily):
    name = "payload_change"
    size_parameters = ("mass_kg", "theta1_step")
    search_cost = 0.031
    kernels = (("mass", plant_mass),)
    plant_force = "mass step Δm from t_c on"
    searched = "change time t_c [s]"
    sim_options = PayloadChange
    example: ClassVar[dict] = {"payload_change": {"t_change_s": 4.65, "mass_kg": 2.0}}
    force_bounded_by_input = False

    # simulator
    def plant_term(self, o: PayloadChange, period_s):
        return PlantTerm.compiled("mass", plant_mass, [o.t_change_s, o.mass_kg])

    # identification
    def columns(self, h, p):
        """ẍ·[t ≥ h], (N, 1); h: change time t_c [s]."""
        return (p.a * (p.t >= h))[:, None]

    def search(self, ctx, base, residual):
        p = ctx.p
        lo, hi = p.t_d[0] + 1.0, p.t_d[-1] - 1.0
        if hi <= lo:
            return None
        a_d, t_d = p.a_d, p.t_d
        coarse = np.arange(lo, hi, 0.05)

        def approx(h):
            return (a_d * (t_d >= h))[:, None]
        _, sses = ctx.best_over(self.name, coarse, base, approx)
        smin = sses.min()
        # flat minimum (no acceleration between two moves): take the middle of the flat set
        near = coarse[sses <= smin + 1e-6 * max(smin, 1e-300) + 1e-12]
        h = float(0.5 * (near.min() + near.max()))
        return ctx.term(self.name, h), None

    def plausible(self, ctx, term, beta, theta, base):
        """A mass that steps: |Δm| ≤ 2M with M + Δm > 0, and a step, not a smooth change of θ1's
        column over the record (:meth:`smooth_columns`, fitted in the same model, leaves a
        held-out RMS no lower than the step's): a force constant drifting towards a level (a
        coil warming up, saturating) is a smooth change of the same column, which a step at
        the drift's knee fitted beside the linear drift (0.4 kg at 1.7 s beside a 15 %
        drift of time constant 3 s, 8 s records)."""
        if theta[0] + beta[0] <= 0 or abs(beta[0]) > 2 * theta[0]:
            return ["mass step not plausible (|dM| > 2 M or mass <= 0)"]
        if term.cols is not None:
            smooth = ctx.heldout_with(base, self.smooth_columns(ctx.p))
            step = ctx.heldout_with(base, term.cols)
            if smooth <= step:
                return [f"a smooth change of the mass column over the record explains as much as a step "
                        f"(held-out RMS {smooth:.4g} against {step:.4g}): a drift, not a payload change"]
        return []

    @staticmethod
    def smooth_columns(p) -> np.ndarray:
        """ẍ·τ and ẍ·τ² at the decimated instants, τ = (t − t_0)/L ∈ [0, 1] (M, 2): θ1 changing
        smoothly over the record, the simpler account of a mass step (two parameters, as the
        step's β and t_c). ``p``: the prepared record (a_d [m/s²], t_d [s])."""
        tau = (p.t_d - p.t_d[0]) / max(float(p.t_d[-1] - p.t_d[0]), 1e-12)
        return np.column_stack([p.a_d * tau, p.a_d * tau * tau])

    def parameters(self, h, beta, gain, fs):
        g = gain if gain else 1.0
        return {"t_change_s": float(h), "mass_kg" if gain else "theta1_step_V_s2_per_m": float(g * beta[0])}

    # report
    def shape(self, ctx, h, beta, gain):
        pr = ctx.p
        ts = np.linspace(pr.t_d[0], pr.t_d[-1], SHAPE_POINTS)
        zero = np.zeros_like(ts)
        y = (gain or 1.0) * (self.columns(h, Signals(zero, zero, np.ones_like(ts), zero, ts)) @ beta)
        return ts, y, "time [s]", f"mass step [{'kg' if gain else 'V s^2/m'}]"


FAMILY = PayloadChangeFamily()
