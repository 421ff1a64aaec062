"""Amplifier dead-zone and input offset: the amplifier passes nothing of the command within ±d of
its (offset) zero, a classic static nonlinearity of analogue ±10 V inputs.

Physical model: the input reaching the motor is u' = dz(u + o), dz(z) = sign(z)·max(|z| − d, 0),
d ≥ 0 the half-width [V], o the input offset [V]; the motor's force curve F_m (paper eq. 3)
acts on u'. Seen from the nominal model (f_u(u) = u + θ5 u|u| + θ6 u³, paper eq. 9):

    F_eff = −A1 (f_u(u) − f_u(dz(u + o)))       (θ5 = θ6 = 0: −A1 (clip(u + o, −d, d) − o))  [N]

Simulator: ``axes.NAME.driver.effects.amplifier_dead_zone`` (an input transform, once per
period). Identification, search: columns f_u(u) − f_u(dz(u)), [|u| < d] (first order in o; the
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
(:meth:`AmplifierDeadZoneFamily.search`, again in the final model: :meth:`polish`). Without a
holding force in the model (a plant without stiction, where the dead-zone is what holds the
carriage at rest) d is the least SSE on the grid, then the exact term (below) is kept when it
fits better: on the rigid plant the linear columns left o a third low (13.5 mV for 20 mV), the
exact term 19.9 mV, and d 0.150 V for 0.15 (0.142 on the grid).

The offset: beyond the band it is the same constant force as the plant's F_0 (θ4) in a model
with f_u = u; two things tell them apart, and the exact term f_u(u) − f_u(dz(u + o)) (one
column, :meth:`AmplifierDeadZoneFamily.refine`) sees both: where the band lies on the input
axis (the samples crossing it in motion, mostly the stick-slip at rest) and the force curve,
which bends about the input that passes the dead-zone, not about u (the lost force beyond the
band, f_u(u) − f_u(u + o ∓ d), depends on o differently at each |u|; F_0 does not). The linear
columns with f_u = u left o 45 % low to 29 % high on 20 s logs of the default plant; a thrust
mis-modelled as f_u = u there also made a phantom asymmetric friction of the force the band
takes at large |u| (d·f_u'(u), half of d at 8 V).
The values reported are taken again with stiction's stick state measured from the encoder's
reading (:func:`motorctl.ident.values.refit`, stiction's ``StickState``): the samples
crossing the band at each stop and breakaway, which fix o, are weighed by whether the carriage
is held, and Karnopp stiction holds it exactly still (the reading within one count), where the
selection's smooth velocity weight moved o with its band (20 mV: 23.9 mV on that weight, 19.8 mV
on the measured state; default plant, ×1).
Not compensable by an additive term in (x_d, ẋ_d, t): its inverse (u + d·sign(u)) needs the
law's own output; the report names it so the amplifier's zero can be adjusted.
"""

from __future__ import annotations

import math
from typing import ClassVar

import numpy as np

from motorctl.effects.base import EffectFamily, PlantTerm
from motorctl.effects.periodic import SHAPE_POINTS
from motorctl.effects.input_delay import delayed
from motorctl.model import f_u, f_u_slope
from motorctl.schema import NonNeg, StrictModel

#: searched half-widths d [V]
WIDTH_GRID = np.exp(np.linspace(math.log(5e-3), math.log(1.0), 20))
#: plausible β1 (the share of the band's input that does not reach the motor)
SHARE_RANGE = (0.7, 1.3)
#: fixed-point steps d ← β1·d of :meth:`AmplifierDeadZoneFamily.search` (at most), and the
#: relative change of d that ends them
WIDTH_STEPS, WIDTH_RTOL = 8, 1e-3
#: Gauss-Newton steps of :meth:`AmplifierDeadZoneFamily.refine` (at most)
REFINE_STEPS = 5
#: the offset's step that ends :meth:`AmplifierDeadZoneFamily.refine` [V]
OFFSET_XTOL = 1e-4


def dead_zone(z, d: float):
    """dz(z) = sign(z)·max(|z| − d, 0) (N,) [V]: what passes a dead-zone of half-width d [V]."""
    return np.sign(z) * np.maximum(np.abs(z) - d, 0.0)


class Band(float):
    """The dead-zone term's parameter h: its float value is the half-width d [V]. ``offset``: o
    [V], or None for the linear columns of the search (o first order, in β2); ``theta5`` [1/V],
    ``theta6`` [1/V²]: the force curve f_u(u) = u + θ5 u|u| + θ6 u³ (paper eq. 9) of the columns
    (0, 0: f_u = u); ``shift``: the input delay of the exact column [samples]; ``slope``: the
    exact column with its derivative in o (a Gauss-Newton step of :meth:`AmplifierDeadZoneFamily.
    refine`)."""

    def __new__(cls, d: float, offset: float | None = None, theta5: float = 0.0, theta6: float = 0.0,
                shift: float = 0.0, slope: bool = False):
        obj = super().__new__(cls, float(d))
        obj.offset = None if offset is None else float(offset)
        obj.theta5, obj.theta6, obj.shift, obj.slope = float(theta5), float(theta6), float(shift), bool(slope)
        return obj


def _thrust(u: np.ndarray, theta5: float, theta6: float) -> np.ndarray:
    """f_u(u) (N,) [V] (paper eq. 9, :func:`motorctl.model.f_u`), u itself when θ5 = θ6 = 0
    (the search's grid: no copy)."""
    return u if theta5 == 0.0 and theta6 == 0.0 else f_u(u, theta5, theta6)


def _shape(ctx, terms, ev=None) -> tuple[float, float]:
    """θ5, θ6 of the joint fit of ``terms`` (``ev``: that fit, when the caller has it); 0, 0
    without the cubic terms."""
    if ctx.n_theta != 6:
        return 0.0, 0.0
    coef = (ev or ctx.evaluate(terms)).fit.coef
    return float(coef[4]), float(coef[5])


class AmplifierDeadZone(StrictModel):
    """Simulated amplifier dead-zone, ``axes.NAME.driver.effects.amplifier_dead_zone``: the motor
    gets dz(u + offset_V) [V]. dead_zone_V: half-width d [V] (≥ 0). offset_V: input offset o [V]."""

    dead_zone_V: NonNeg
    offset_V: float = 0.0


class AmplifierDeadZoneFamily(EffectFamily):
    name = "amplifier_dead_zone"
    search_cost = 0.056
    plant_force = "−A1 (f_u(u) − f_u(dz(u + o)))"
    searched = "dead-zone half-width d [V]"
    sim_options = AmplifierDeadZone
    example: ClassVar[dict] = {"amplifier_dead_zone": {"dead_zone_V": 0.15, "offset_V": 0.02}}
    size_options: ClassVar[tuple[str, ...]] = ("dead_zone_V",)
    look_alike: ClassVar[tuple[str, ...]] = ("stiction",)
    acts_at_rest = True
    lost_motion = True
    values_on_stick_state = True
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
        """The lost input [V], (N, k); h: the half-width d [V], a :class:`Band` (a float: the
        linear form with f_u = u). f_u(u) = u + θ5 u|u| + θ6 u³ (paper eq. 9) on ``h.theta5``,
        ``h.theta6``: the motor's force curve acts on what passes the dead-zone.

        Linear form (``h.offset`` None; the search): f_u(u) − f_u(dz(u)), [|u| < d], (N, 2):
        β1 the share of the band's input lost, β2 ≈ o (first order in o; the constant −o is
        θ4's). Exact form (``h.offset`` = o): f_u(u) − f_u(dz(u + o)), (N, 1), delayed by
        ``h.shift`` samples (the model's input delay: the dead-zone acts before the current
        loop); with ``h.slope`` also its derivative in o, −f_u'(dz(u + o))·[|u + o| > d],
        (N, 2)."""
        u = p.u
        th5, th6 = getattr(h, "theta5", 0.0), getattr(h, "theta6", 0.0)
        offset = getattr(h, "offset", None)
        d = float(h)
        if offset is None:
            return np.column_stack([_thrust(u, th5, th6) - _thrust(dead_zone(u, d), th5, th6),
                                    (np.abs(u) < d).astype(float)])
        passed = dead_zone(u + offset, d)
        cols = [_thrust(u, th5, th6) - _thrust(passed, th5, th6)]
        if getattr(h, "slope", False):       # ∂/∂o: −f_u'(dz(u + o)) beyond the band, 0 within
            cols.append(-f_u_slope(np.abs(passed), th5, th6) * (np.abs(u + offset) > d))
        lost = np.column_stack(cols)
        s = getattr(h, "shift", 0.0)
        return delayed(lost, s) if s > 0 else lost

    def search(self, ctx, base, residual):
        """The least SSE on :data:`WIDTH_GRID`, refined on a finer grid. With a holding force
        at rest in ``base`` (stiction, whose :meth:`~motorctl.effects.base.EffectFamily.
        other_weight` leaves these columns the samples in motion) and a plausible share there
        (β1 within :data:`SHARE_RANGE`; else that candidate is returned, to be refused): the
        width is then the half-width whose share β1 is 1 (module docstring), β1 on the grid
        (> 1 below the true width, where the column's ±h is smaller than the force beyond the
        band, < 1 above it), the crossing of least SSE interpolated on the log grid, then the
        fixed point d ← β1·d on the linear columns with the fit's own force curve; then the
        offset (:meth:`refine`): the exact term. Without a holding force (and a plausible
        share) the exact term refined from the grid's width, when its SSE is the lower."""
        from motorctl.effects import FAMILIES
        term, sses = ctx.best_over(self.name, WIDTH_GRID, base)
        i = int(np.argmin(sses))
        if i in (0, len(WIDTH_GRID) - 1):
            return term, f"dead-zone half-width {term.h:.3g} V at the edge of the searched range"
        fine = np.exp(np.linspace(math.log(WIDTH_GRID[i - 1]), math.log(WIDTH_GRID[i + 1]), 7))
        term = ctx.best_over(self.name, fine, base)[0]
        lo, hi = SHARE_RANGE
        if not lo <= float(ctx.evaluate(base + [term]).fit.coef[-2]) <= hi:
            return term, None
        if not any(FAMILIES[t.family].other_weight(t) is not None for t in base):
            exact = self.refine(ctx, base, term)
            return (exact if ctx.sse(base + [exact]) < ctx.sse(base + [term]) else term), None
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
        th5, th6 = _shape(ctx, base)
        term = ctx.term(self.name, Band(d, None, th5, th6))
        for _ in range(WIDTH_STEPS):
            new = d * float(ctx.evaluate(base + [term]).fit.coef[-2])
            if not WIDTH_GRID[0] <= new <= WIDTH_GRID[-1]:
                break
            term = ctx.term(self.name, Band(new, None, th5, th6))
            done = abs(new - d) <= WIDTH_RTOL * d
            d = new
            if done:
                break
        return self.refine(ctx, base, term), None

    def refine(self, ctx, base, term):
        """The exact term (:meth:`columns`, exact form) from a linear one found with a holding
        force in ``base``: Gauss-Newton steps on the offset, each a joint fit of the exact column
        at (d, o) and its derivative in o (β1, β2: o ← o + β2/β1, at most ±d/2 a step), with
        d ← β1·d and the force curve θ5, θ6 of that fit, until o moves less than
        :data:`OFFSET_XTOL` and β1 is within :data:`WIDTH_RTOL` of 1 (:data:`REFINE_STEPS` at
        most). Starts from the linear fit's β2.

        Beyond the band an input offset is the same constant force as the plant's F_0 (θ4) but
        for two things the exact column sees: where the band lies on the input axis (the
        samples crossing it in motion, mostly the stick-slip at rest), and the motor's force
        curve, which bends about the input that passes the dead-zone (u + o), not about u:
        the lost force at u beyond the band is f_u(u) − f_u(u + o ∓ d), whose dependence on
        o changes with |u| where F_0 does not."""
        d = float(term.h)
        ev = ctx.evaluate(base + [term])
        o = float(np.clip(ev.fit.coef[-1], -0.5 * d, 0.5 * d))
        th5, th6 = _shape(ctx, base + [term], ev)
        shift = ctx.zoh + sum(t.delay for t in base)
        for _ in range(REFINE_STEPS):
            ev = ctx.evaluate(base + [ctx.term(self.name, Band(d, o, th5, th6, shift, slope=True))])
            b1, b2 = (float(c) for c in ev.fit.coef[-2:])
            if not SHARE_RANGE[0] <= b1 <= SHARE_RANGE[1]:
                break
            step = float(np.clip(b2 / b1, -0.5 * d, 0.5 * d))
            o += step
            d *= b1
            th5, th6 = _shape(ctx, base, ev)
            if abs(step) <= OFFSET_XTOL and abs(b1 - 1.0) <= WIDTH_RTOL:
                break
        return ctx.term(self.name, Band(d, o, th5, th6, shift))

    def polish(self, ctx, term, others):
        """The width's fixed point and the offset again with the final model's ``others`` (the
        force beyond the band is shared with a friction or a delay found after it)."""
        new, note = self.search(ctx, others, None)
        return None if note else new

    def plausible(self, ctx, term, beta, theta, base):
        lo, hi = SHARE_RANGE
        out = []
        if not lo <= beta[0] <= hi:
            out.append(f"share of the band's input lost {beta[0]:.2f} outside [{lo:g}, {hi:g}] "
                       "(a dead-zone passes nothing within it)")
        offset = _offset(term.h, beta)
        if abs(offset) > term.h:
            out.append(f"input offset {offset:.3g} V larger than the dead-zone's half-width {term.h:.3g} V")
        return out

    def parameters(self, h, beta, gain, fs):
        return {"dead_zone_V": float(h), "lost_share": float(beta[0]), "offset_V": _offset(h, beta)}

    # report
    def shape(self, ctx, h, beta, gain):
        d, o = float(h), _offset(h, beta)
        u = np.linspace(-3 * d, 3 * d, SHAPE_POINTS)
        y = -(gain or 1.0) * beta[0] * (np.clip(u + o, -d, d) - o)
        return u, y, "input u [V]", "effect force [UNIT]"


def _offset(h, beta) -> float:
    """The input offset o [V] of a fitted term: the exact term's own, else β2 (first order)."""
    offset = getattr(h, "offset", None)
    return float(beta[1]) if offset is None else offset


FAMILY = AmplifierDeadZoneFamily()
