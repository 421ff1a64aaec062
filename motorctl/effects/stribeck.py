"""Stribeck friction: extra friction at low speed (the friction hump before full lubrication).

Physical model (Stribeck curve with the paper's smooth sign S_f(ẋ) = (2/π) atan(900 ẋ)):

    F_eff(ẋ) = −F_s exp(−(ẋ/v_s)²) S_f(ẋ)                                          [N]

Identification: column exp(−(ẋ/v_s)²) S_f(ẋ), v_s searched on a log grid from 2 mm/s to half
the peak speed, then refined. Compensation: d̂_eff(ẋ_d) = −F_V exp(−(ẋ_d/v_s)²) S_f(ẋ_d) [V].
"""

from __future__ import annotations

import math
from typing import ClassVar

import numpy as np

from motorctl.effects.base import Adaptable, CompTerm, EffectFamily, PlantTerm, Signals
from motorctl.effects.periodic import SHAPE_POINTS
from motorctl.jit import njit
from motorctl.model import s_f
from motorctl.schema import NonNeg, Pos, StrictModel


@njit
def plant_force(f, x, v, t, sf, p):
    """f + F_eff [N] at velocity v [m/s] with sf = S_f(v) (x, t unused):
    f − F_s exp(−(v/v_s)²) sf; the row p = (F_s [N], v_s [m/s])."""
    z = v / p[1]
    return f - p[0] * math.exp(-z * z) * sf


@njit
def comp_add(d, x, v, t, sf, p):
    """d − F_s exp(−(ẋ_d/v_s)²) S_f(ẋ_d) [V]; the row p = (F_s [V], v_s [m/s])."""
    z = v / p[1]
    return d - p[0] * math.exp(-z * z) * sf


@njit
def comp_fill(out, j, x, v, t, sf, p):
    """The adapted column −exp(−(ẋ/v_s)²) S_f(ẋ) into out[j]; the row p = (v_s [m/s],)."""
    z = v / p[0]
    out[j] = -math.exp(-z * z) * sf

class Stribeck(StrictModel):
    """Simulated Stribeck friction, ``axes.NAME.driver.effects.stribeck``:
    −F_s exp(−(ẋ/v_s)²) S_f(ẋ) [N]. force_N: F_s [N] (≥ 0). velocity_m_per_s: v_s [m/s]."""

    force_N: NonNeg
    velocity_m_per_s: Pos


class StribeckComp(Adaptable):
    """Stribeck compensation, ``axes.NAME.controller.compensation.stribeck``:
    −F exp(−(ẋ/v_s)²) S_f(ẋ) [V]. force_V: F (force / A1) [V]. velocity_m_per_s: v_s [m/s].
    Adaptable (:class:`~motorctl.effects.base.Adaptable`): β = [F], v_s fixed."""

    force_V: float
    velocity_m_per_s: Pos

    def beta(self):
        return [self.force_V]

    def beta_names(self):
        return ["force_V"]


def velocity_grid(ctx) -> np.ndarray:
    """Velocities [m/s] over ± the record's peak decimated speed (SHAPE_POINTS,), for the report."""
    vmax = float(np.max(np.abs(ctx.p.v_d)))
    return np.linspace(-vmax, vmax, SHAPE_POINTS)


class StribeckFamily(EffectFamily):
    name = "stribeck"
    search_cost = 0.044
    kernels = (("force", plant_force), ("add", comp_add), ("fill", comp_fill))
    plant_force = "−F_s exp(−(ẋ/v_s)²) S_f(ẋ)"
    searched = "Stribeck velocity v_s [m/s]"
    sim_options = Stribeck
    example: ClassVar[dict] = {"stribeck": {"force_N": 20.0, "velocity_m_per_s": 0.05}}
    comp_options = StribeckComp
    comp_needs_sf = True
    compensation_rank = 4
    values_on_current_loop = True

    # simulator
    def plant_term(self, o: Stribeck, period_s):
        return PlantTerm.compiled("force", plant_force, [o.force_N, o.velocity_m_per_s])

    # identification
    def columns(self, h, p):
        """exp(−(ẋ_w/h)²) S_f(ẋ), (N, 1); h: Stribeck velocity v_s [m/s]. On a prepared record
        the hump's ẋ_w is its wide-band velocity (``v_wide``, :class:`motorctl.ident.idim.
        Prepared`: the hump is a sharp function of the true velocity, passed in a few ms and
        blurred on the position filter's), and S_f's ẋ its ``v_sf`` when set (the identifier
        with its ``current_loop`` sets the position filter's, as in the nominal Coulomb
        column), else the wide-band one too. Where the carriage creeps at a few mm/s (after a stop, friction and
        input balanced) the plant's force is (F_c + F_s) S_f(ẋ), and S_f (900 s/m) on the noisy
        wide-band velocity is not the nominal column's there (the column on ``v_wide`` alone:
        v_s 17-21 % low at 0.05 m/s on the default plant)."""
        vw = getattr(p, "v_wide", None)
        vw = p.v if vw is None else vw
        vs = getattr(p, "v_sf", None)
        return (np.exp(-(vw / h) ** 2) * s_f(vw if vs is None else vs))[:, None]

    def search(self, ctx, base, residual):
        p = ctx.p
        grid = np.exp(np.linspace(math.log(2e-3), math.log(max(0.5 * np.max(np.abs(p.v)), 3e-3)), 24))
        term, sses = ctx.best_over(self.name, grid, base)
        i = int(np.argmin(sses))
        if i in (0, len(grid) - 1):
            return term, f"Stribeck velocity {term.h:.3g} m/s at the edge of the searched range"
        # between the grid's neighbours (31 % steps) to 0.5 % of v_s: bounded Brent, about 12
        # fits (a fine grid of 7 % steps took 9)
        term = ctx.best_between(self.name, grid[i - 1], grid[i + 1], base, 0.005 * grid[i])
        return term, None

    def polish(self, ctx, term, others):
        """v_s searched again (:meth:`search`) with the final model's other effects: a Stribeck
        velocity found beside a stiction band that took up part of the low-speed friction (the
        band searched before the hump was modelled) is too wide (default plant, F_s 20 N,
        v_s 0.05 m/s: 0.093 beside a 1.65 mm/s band, 0.044 beside the band searched again).
        None when the search's value sits at its grid's edge, or when the identifier does not
        model the current loop (its ``current_loop``: the selection as before)."""
        return self.searched_again(ctx, others) if getattr(ctx, "current_loop", False) else None

    def plausible(self, ctx, term, beta, theta, base):
        if beta[0] <= 0:
            return ["Stribeck force must be positive (extra friction at low speed)"]
        return []

    def parameters(self, h, beta, gain, fs):
        g, unit = (gain, "N") if gain else (1.0, "V")
        return {"stribeck_velocity_m_per_s": float(h), f"force_{unit}": float(g * beta[0])}

    # compensation
    def compensation(self, h, beta, signals=None, beta_std=None):
        return self.adapt_entry({"force_V": float(beta[0]), "velocity_m_per_s": float(h)}, beta_std)

    def compensation_for(self, o: Stribeck, a1):
        return {"force_V": o.force_N / a1, "velocity_m_per_s": o.velocity_m_per_s}

    def compensator(self, o: StribeckComp):
        return CompTerm("add", comp_add, [o.force_V, o.velocity_m_per_s])

    def adapt_basis(self, o: StribeckComp):
        return CompTerm("fill", comp_fill, [o.velocity_m_per_s])

    # report
    def shape(self, ctx, h, beta, gain):
        vs = velocity_grid(ctx)
        zero = np.zeros_like(vs)
        y = -(gain or 1.0) * (self.columns(h, Signals(zero, vs, zero, zero, zero)) @ beta)
        return vs, y, "velocity [m/s]", "effect force [UNIT]"


FAMILY = StribeckFamily()
