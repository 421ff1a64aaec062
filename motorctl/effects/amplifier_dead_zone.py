"""Amplifier dead-zone and input offset: the amplifier passes nothing of the command within ±d of
its (offset) zero, a classic static nonlinearity of analogue ±10 V inputs.

Physical model: the input reaching the motor is u' = dz(u + o), dz(z) = sign(z)·max(|z| − d, 0),
d ≥ 0 the half-width [V], o the input offset [V]. Seen from the nominal model (F_m = A1 u):

    F_eff = A1 (u' − u) = −A1 (clip(u + o, −d, d) − o)                                    [N]

Simulator: ``axes.NAME.driver.effects.amplifier_dead_zone`` (an input transform, once per
period). Identification: columns clip(u, −d, d), [|u| < d] (the first-order expansion in o; the
constant −o is θ4's), d searched on a log grid from 5 mV to 1 V: β1 ≈ 1 for a dead-zone (0 < β1 < 1:
a reduced gain near zero), β2 ≈ o (β1 within :data:`SHARE_RANGE`: a share well below 1 is a
holding force at rest, stiction's, not a band the amplifier drops). Not compensable by an additive term in (x_d, ẋ_d, t): its
inverse (u + d·sign(u)) needs the law's own output; the report names it so the amplifier's
zero can be adjusted.
"""

from __future__ import annotations

import math
from typing import ClassVar

import numpy as np

from motorctl.effects.base import EffectFamily, PlantTerm
from motorctl.effects.periodic import SHAPE_POINTS
from motorctl.schema import NonNeg, StrictModel

#: searched half-widths d [V]
WIDTH_GRID = np.exp(np.linspace(math.log(5e-3), math.log(1.0), 20))
#: plausible β1 (the share of the band's input that does not reach the motor)
SHARE_RANGE = (0.7, 1.3)


class AmplifierDeadZone(StrictModel):
    """Simulated amplifier dead-zone, ``axes.NAME.driver.effects.amplifier_dead_zone``: the motor
    gets dz(u + offset_V) [V]. dead_zone_V: half-width d [V] (≥ 0). offset_V: input offset o [V]."""

    dead_zone_V: NonNeg
    offset_V: float = 0.0


class AmplifierDeadZoneFamily(EffectFamily):
    name = "amplifier_dead_zone"
    plant_force = "−A1 (clip(u + o, −d, d) − o)"
    searched = "dead-zone half-width d [V]"
    sim_options = AmplifierDeadZone
    example: ClassVar[dict] = {"amplifier_dead_zone": {"dead_zone_V": 0.15, "offset_V": 0.02}}
    size_options: ClassVar[tuple[str, ...]] = ("dead_zone_V",)
    look_alike: ClassVar[tuple[str, ...]] = ("stiction",)
    acts_at_rest = True

    # simulator
    def plant_term(self, o: AmplifierDeadZone, period_s):
        d, off = o.dead_zone_V, o.offset_V

        def input(u):
            z = u + off
            if z > d:
                return z - d
            if z < -d:
                return z + d
            return 0.0
        return PlantTerm(input=input)

    # identification
    def columns(self, h, p):
        """clip(u, −h, h), [|u| < h], (N, 2); h: half-width d [V]."""
        u = p.u
        return np.column_stack([np.clip(u, -h, h), (np.abs(u) < h).astype(float)])

    def search(self, ctx, base, residual):
        term, sses = ctx.best_over(self.name, WIDTH_GRID, base)
        i = int(np.argmin(sses))
        if i in (0, len(WIDTH_GRID) - 1):
            return term, f"dead-zone half-width {term.h:.3g} V at the edge of the searched range"
        fine = np.exp(np.linspace(math.log(WIDTH_GRID[i - 1]), math.log(WIDTH_GRID[i + 1]), 7))
        term, _ = ctx.best_over(self.name, fine, base)
        return term, None

    def plausible(self, ctx, term, beta, theta, base):
        lo, hi = SHARE_RANGE
        out = []
        if not lo <= beta[0] <= hi:
            out.append(f"share of the band's input lost {beta[0]:.2f} outside [{lo:g}, {hi:g}] "
                       "(a dead-zone passes nothing within it)")
        if abs(beta[1]) > term.h:
            out.append(f"input offset {beta[1]:.3g} V larger than the dead-zone's half-width {term.h:.3g} V")
        return out

    def parameters(self, h, beta, gain, fs):
        return {"dead_zone_V": float(h), "lost_share": float(beta[0]), "offset_V": float(beta[1])}

    # report
    def shape(self, ctx, h, beta, gain):
        u = np.linspace(-3 * h, 3 * h, SHAPE_POINTS)
        y = -(gain or 1.0) * (np.clip(u, -h, h) * beta[0] + (np.abs(u) < h) * beta[1])
        return u, y, "input u [V]", "effect force [UNIT]"


FAMILY = AmplifierDeadZoneFamily()
