"""Amplifier dead-zone and input offset: the amplifier passes nothing of the command within ±d of
its (offset) zero, a classic static nonlinearity of analogue ±10 V inputs.

Physical model: the input reaching the motor is u' = dz(u + o), dz(z) = sign(z)·max(|z| − d, 0),
d ≥ 0 the half-width [V], o the input offset [V]. Seen from the nominal model (F_m = A1 u):

    F_eff = A1 (u' − u) = −A1 (clip(u + o, −d, d) − o)                                    [N]

Simulator: ``axes.NAME.driver.effects.amplifier_dead_zone`` (an input transform, once per
period). Identification: columns clip(u, −d, d), [|u| < d] (the first-order expansion in o; the
constant −o is θ4's); β1 the share of the band's input lost (1 for a dead-zone), β2 ≈ o.
At rest a dead-zone and a static friction look alike (both leave the carriage where it is,
whatever the small input): without a holding force in the model, d is the band that fits the
rest samples best (a log grid from 5 mV to 1 V). With stiction in the model the columns are
fitted on the samples in motion (stiction's ``other_weight``), and there the dead-zone takes
A1·d from every input beyond the band, −A1·d·sign(u): a force on the sign of the *input*, which
friction (on the sign of ẋ) is not while the carriage decelerates. That force fixes β1·d; the
band's inside is crossed in about a sample at each zero crossing of u, too briefly to fix d by
its shape. So d is then the width whose share β1 is 1 (a dead-zone passes nothing within it):
the crossing β1 = 1 on the grid, then the fixed point d ← β1·d
(:meth:`AmplifierDeadZoneFamily.search`, again in the final model: :meth:`polish`). The offset o
is weakly determined: beyond the band it is the same constant force as the plant's F_0 (θ4),
only the band's crossings tell them apart. Not compensable by an additive term in
(x_d, ẋ_d, t): its inverse (u + d·sign(u)) needs the law's own output; the report names it so
the amplifier's zero can be adjusted.
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
#: fixed-point steps d ← β1·d of :meth:`AmplifierDeadZoneFamily.search` (at most), and the
#: relative change of d that ends them
WIDTH_STEPS, WIDTH_RTOL = 8, 1e-3


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
    before_current_loop = True

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
        """The least SSE on :data:`WIDTH_GRID`, refined on a finer grid. With a holding force
        at rest in ``base`` (stiction, whose :meth:`~motorctl.effects.base.EffectFamily.
        other_weight` leaves these columns the samples in motion) and a plausible share there
        (β1 within :data:`SHARE_RANGE`; else that candidate is returned, to be refused): the
        width is then the half-width whose share β1 is 1 (module docstring), β1 on the grid
        (> 1 below the true width, where the column's ±h is smaller than the force beyond the
        band, < 1 above it), the crossing of least SSE interpolated on the log grid, then the
        fixed point d ← β1·d."""
        from motorctl.effects import FAMILIES
        term, sses = ctx.best_over(self.name, WIDTH_GRID, base)
        i = int(np.argmin(sses))
        if i in (0, len(WIDTH_GRID) - 1):
            return term, f"dead-zone half-width {term.h:.3g} V at the edge of the searched range"
        fine = np.exp(np.linspace(math.log(WIDTH_GRID[i - 1]), math.log(WIDTH_GRID[i + 1]), 7))
        term = ctx.best_over(self.name, fine, base)[0]
        lo, hi = SHARE_RANGE
        if (not any(FAMILIES[t.family].other_weight(t) is not None for t in base)
                or not lo <= float(ctx.evaluate(base + [term]).fit.coef[-2]) <= hi):
            return term, None
        fits = [ctx.evaluate(base + [ctx.term(self.name, float(h))]) for h in WIDTH_GRID]
        share = np.array([float(f.fit.coef[-2]) for f in fits])
        sse = np.array([float(f.fit.residual @ f.fit.residual) for f in fits])
        cross = [i for i in range(len(WIDTH_GRID) - 1) if share[i] >= 1.0 > share[i + 1]]
        if not cross:
            i = int(np.argmin(np.abs(np.log(np.maximum(share, 1e-9)))))
            return ctx.term(self.name, float(WIDTH_GRID[i])), (
                f"no half-width in {WIDTH_GRID[0]:.3g}-{WIDTH_GRID[-1]:.3g} V at which the band's input is lost "
                f"whole (share {share.min():.2f}-{share.max():.2f})")
        i = min(cross, key=lambda k: min(sse[k], sse[k + 1]))
        lg = np.log(WIDTH_GRID)
        w = math.log(share[i]) / (math.log(share[i]) - math.log(max(share[i + 1], 1e-9)))
        d = float(np.exp(lg[i] + w * (lg[i + 1] - lg[i])))
        term = ctx.term(self.name, d)
        for _ in range(WIDTH_STEPS):
            new = d * float(ctx.evaluate(base + [term]).fit.coef[-2])
            if not WIDTH_GRID[0] <= new <= WIDTH_GRID[-1]:
                break
            term = ctx.term(self.name, new)
            done = abs(new - d) <= WIDTH_RTOL * d
            d = new
            if done:
                break
        return term, None

    def polish(self, ctx, term, others):
        """The width's fixed point again with the final model's ``others`` (the force beyond
        the band is shared with a friction or a delay found after it)."""
        new, note = self.search(ctx, others, None)
        return None if note else new

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
