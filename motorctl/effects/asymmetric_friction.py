"""Asymmetric (direction-dependent) friction: different Coulomb and viscous levels forward.

Physical model (the EMPS reference model has separate F_c, F_v per direction; the nominal θ2,
θ3 carry the backward level, this family the difference):

    F_eff(ẋ) = −(ΔF_c S_f(ẋ) + ΔB ẋ)   for ẋ > 0,   0 otherwise                   [N]

Identification: columns S_f(ẋ)·[ẋ > 0], ẋ·[ẋ > 0] (no searched parameter). Compensation:
d̂_eff(ẋ_d) = −(ΔF_V S_f(ẋ_d) + ΔB_V ẋ_d) for ẋ_d > 0 [V].
"""

from __future__ import annotations

import math
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
#: time [s] taken off each end of a stretch at rest for :func:`held_offset`: the position
#: filter's zero-phase impulse response (4th-order Butterworth at ω_fq = 250 Hz) spreads a
#: start over about ±2 ms, so a sample that close to motion is not surely held
REST_MARGIN_S = 2e-3
#: time [s] of held samples averaged at each extreme of the held input for :func:`held_offset`
#: (5 ms: the samples of about one approach to the breakaway): one sample's extreme carries
#: the loop's noise and a stop's transient, a mean of the extremes the same share of noise on
#: both sides, which the middle cancels
EXTREME_S = 5e-3


def held_offset(p, theta3: float, theta4: float | None = None, other: np.ndarray | None = None) -> float | None:
    """The offset θ4 [V] (θ4·A1 = F_0, the constant force on the carriage) from the input held
    at rest, or None when the record cannot tell it.

    A carriage held by static friction (Karnopp) stays while |A1 u + F_0 + F_other(x)| ≤ F_s,
    F_other the other effects' force at its rest position x (cogging's, a spring's), so the
    input held at rest less the input that force takes, u − u_other with u_other = −F_other/A1,
    spans [(−F_s − F_0)/A1, (F_s − F_0)/A1], symmetric about −θ4, when the loop pushes it to
    the breakaway both ways (C2 hunting at rest does). Taken on the samples at rest (|ẋ| <
    :data:`REST_V`, :data:`REST_MARGIN_S` away from motion) when there are at least
    :data:`MIN_REST_S` of them, the held input takes both signs and its span reaches twice the
    Coulomb level (static friction is at least the kinetic level): θ4 = −(hi + lo)/2 with hi,
    lo the means of the :data:`EXTREME_S` highest and lowest held inputs. Taken on u itself
    beside cogging, the extremes fall at the rest positions where its force helps most each
    way, and their middle is off by the cogging force there (rigid plant, cogging 12 + 4 N at
    rest at x = 0 and 0.4 m: θ4 −0.0066 V, with u_other −0.0473 V, true −0.05 V). With
    ``other`` the extremes of u − u_other are taken when their span is the narrower: the held
    input lies in one band only with the forces the hold really sees (the simulator's
    stiction, ``stiction_N``, sees the effects' forces only with ``stiction_with_effects``;
    without, u itself spans the band and u − u_other spans it widened by u_other's range).

    Args:
        p: the prepared record (full-rate v [m/s], u [V] (N,), fs [Hz]). theta3: the Coulomb
            level θ3 [V] of the fit. theta4: the fit's offset θ4 [V], or None. Given, the span
            is checked against the Coulomb level the fit's backward level θ3 + θ4 leaves with
            the held offset, θ3 + θ4 − θ4_held: beside a forward-only Coulomb column the fit
            fixes θ3 + θ4, not θ3 and θ4 apart (:meth:`AsymmetricFrictionFamily.parameters`).
            other: u_other [V] (N,), the input the other effects take at each sample
            (:func:`other_input`), or None.
    """
    rest = np.abs(np.asarray(p.v)) < REST_V
    margin = int(round(REST_MARGIN_S * p.fs))
    if margin > 0:
        # at rest with every sample within ±margin at rest too (moving samples counted by a cumsum)
        c = np.concatenate([[0], np.cumsum(~rest)])
        n = len(rest)
        i = np.arange(n)
        rest = (c[np.minimum(i + margin + 1, n)] - c[np.maximum(i - margin, 0)]) == 0
    if rest.sum() < MIN_REST_S * p.fs:
        return None
    k = max(1, int(round(EXTREME_S * p.fs)))
    u = np.asarray(p.u)[rest]
    lo, hi = _extremes(u, k)
    if other is not None:
        lo_o, hi_o = _extremes(u - np.asarray(other)[rest], k)
        if hi_o - lo_o < hi - lo:
            lo, hi = lo_o, hi_o
    th4 = -0.5 * (lo + hi)
    level = theta3 if theta4 is None else theta3 + theta4 - th4
    if not (lo < 0.0 < hi and hi - lo >= 2.0 * level > 0.0):
        return None
    return th4


def _extremes(u: np.ndarray, k: int) -> tuple[float, float]:
    """(lo, hi): the means of the k lowest and the k highest of u (n,)."""
    part = np.partition(u, (k - 1, len(u) - k))
    return float(np.mean(part[:k])), float(np.mean(part[-k:]))


def other_input(fitted, name: str) -> np.ndarray | None:
    """u_other [V] (N,): the input the effects of the identification's values' model
    (``fitted.terms``, β of ``fitted.final``, on the record ``fitted.fits.p``) other than
    ``name`` take at each sample, Σ C_k β_k on the full-rate columns; None when ``fitted`` has no
    final model or no such effect.

    Left out: the terms without columns (a delay of the input) and those of a family that
    holds the carriage at rest (stiction's ``other_weight``): their columns there are the held
    input itself, not a force on the carriage.
    """
    terms = list(getattr(fitted, "terms", None) or [])
    if getattr(fitted, "final", None) is None or not terms:
        return None
    from motorctl.effects import family
    betas = fitted.fits.coef_split(fitted.final, terms)[1]
    out = None
    for t, b in zip(terms, betas):
        fam = family(t.family)
        if t.family == name or t.cols is None or fam.other_weight(t) is not None:
            continue
        f = fam.fitted(t.h, fitted.fits.p, b)
        if f is None:
            continue
        out = f if out is None else out + f
    return out


def levels_in_motion(fitted, name: str, with_std: bool = False) -> tuple[float, np.ndarray, tuple | None] | None:
    """The constant force θ4 in motion [V] and the term ``name``'s β of the values' model
    (``fitted.terms``) fitted again on the samples in motion only (``fitted.fits.moving``), or
    None when ``fitted`` has no such term or the record does not move both ways.

    The friction levels and slopes of each direction are properties of motion; the samples near
    rest follow the Karnopp stick and slip of each start and stop, which the model's columns
    there (S_f on the 250 Hz velocity, stiction's weight) do not describe, and in the joint fit
    they pull each direction's Coulomb/viscous split (default plant, 5 N + 10 N·s/m: ΔB 8.9
    N·s/m and ΔF_c − 2F_0 14.8 N on all samples, 9.9 and 13.05 N on the moving ones; truth 10
    and 13). Columns that vanish in motion (stiction's) are left out; the offset and the
    forward Coulomb column are nearly collinear there, which leaves ΔF_c − 2θ4 and ΔB well
    determined (least squares, minimum norm). The constant force is the fit's own θ4, the
    other effects' columns beside it (a spring's k·x, cogging's harmonics): what the input held
    at rest is compared with once those effects' input there is taken off it
    (:func:`held_offset` with :func:`other_input`).

    Returns:
        (θ4 [V], β (2,) [V, V·s/m], with ``with_std`` (σ of ΔB [V·s/m], σ of ΔF_c − 2θ4 [V]) of
        that fit, its Newey-West σ and the model error the record shows against the fit on all
        samples, ``fitted.fits.rows_std``; else None).
    """
    terms = list(getattr(fitted, "terms", None) or [])
    idx = next((i for i, t in enumerate(terms) if t.family == name), None)
    if idx is None:
        return None
    fits = fitted.fits
    phi, y = fits.design(terms)
    nt = fits.n_theta
    widths = [0 if t.cols is None else t.cols.shape[1] for t in terms]
    start = nt + sum(widths[:idx])
    sel = fits.moving
    if not ((sel & (fits.p.v_d > 0)).any() and (sel & (fits.p.v_d < 0)).any()):
        return None
    if with_std:
        combos = np.zeros((2, phi.shape[1]))
        combos[0, start + 1] = 1.0                              # ΔB
        combos[1, start], combos[1, 3] = 1.0, -2.0              # ΔF_c − 2θ4
        coef, std = fits.rows_std(phi, y, sel, combos)
        return float(coef[3]), coef[start:start + 2], (float(std[0]), float(std[1]))
    a, b = phi[sel], y[sel]
    norms = np.sqrt(np.einsum("ij,ij->j", a, a))
    live = norms > 1e-9 * norms.max()
    coef = np.zeros(phi.shape[1])
    coef[live] = np.linalg.lstsq(a[:, live] / norms[live], b, rcond=None)[0] / norms[live]
    return float(coef[3]), coef[start:start + 2], None


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
    size_parameters = ("coulomb_", "viscous_")
    search_cost = 0.003
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

    def parameters(self, h, beta, gain, fs, theta=None, p=None, fitted=None):
        """ΔF_c and ΔB [N, N·s/m; V, V·s/m without the gain].

        With the identification's values' model ``fitted``, ΔB and ΔF_c − 2θ4 come from that
        model fitted again on the samples in motion (:func:`levels_in_motion`). In motion a
        constant offset force (θ4's column −1) and the forward-only Coulomb column S_f(ẋ)·[ẋ > 0]
        = (S_f + |S_f|)/2 are collinear: the fit fixes the two levels θ3 + β − θ4 (forward) and
        θ3 + θ4 (backward), not β and θ4 apart, and a carriage held at rest shows neither (its
        input there is unconstrained). When the record's input held at rest spans the breakaway
        both ways (:func:`held_offset`), θ4 is taken from there and ΔF_c = β − 2θ4 + 2θ4_held
        (β, θ4 of the fit in motion; of the joint fit ``beta``, ``theta`` without ``fitted``),
        the held input taken less the other effects' input at rest (:func:`other_input`) with
        ``fitted``. Without the held offset ΔF_c is the joint fit's β: in motion alone nothing
        tells it from the offset, near rest the joint fit has S_f's transitions (EMPS, sign
        friction: 9.2 N against 16.4 N from the fit in motion; the description's −0.48 N)."""
        return self._levels(beta, gain, theta, p, fitted, False)[0]

    def refitted_std(self, h, beta, gain, theta=None, p=None, fitted=None):
        """σ of what :meth:`parameters` takes from the fit in motion (:func:`levels_in_motion`:
        its Newey-West σ and the model error the record shows against the fit on all samples):
        ΔB always, ΔF_c = β − 2θ4 + 2θ4_held when the held offset is known (θ4_held, from the
        extremes of the held input, taken as exact)."""
        return self._levels(beta, gain, theta, p, fitted, True)[1]

    def _levels(self, beta, gain, theta, p, fitted, with_std: bool) -> tuple[dict, dict]:
        """(the parameters, {name: σ} of those from the fit in motion, with ``with_std``)
        (:meth:`parameters`)."""
        g, unit = (gain, "N") if gain else (1.0, "V")
        dfc, db = float(beta[0]), float(beta[1])
        names = (f"coulomb_{unit}", f"viscous_{unit}_s_per_m")
        std = {}
        if theta is not None and p is not None and len(theta) > 3:
            th4 = float(theta[3])
            moving = levels_in_motion(fitted, self.name, with_std) if fitted is not None else None
            held = held_offset(p, float(theta[2]), float(theta[3]),
                               other_input(fitted, self.name) if fitted is not None else None)
            if moving is not None:
                th4_m, beta_m, sd = moving
                db = float(beta_m[1])
                if sd is not None:
                    std[names[1]] = g * sd[0]
                if held is not None:
                    dfc, th4 = float(beta_m[0]), th4_m
                    if sd is not None:
                        std[names[0]] = g * sd[1]
            if held is not None:
                dfc += 2.0 * (held - th4)
        return {names[0]: float(g * dfc), names[1]: float(g * db)}, {k: v for k, v in std.items() if math.isfinite(v)}

    def named_by(self, standing):
        """"asymmetric viscous friction" when only ΔB stands, "asymmetric Coulomb friction" when
        only ΔF_c does."""
        if all(n.startswith("viscous_") for n in standing):
            return "asymmetric viscous friction"
        if all(n.startswith("coulomb_") for n in standing):
            return "asymmetric Coulomb friction"
        return self.name

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
