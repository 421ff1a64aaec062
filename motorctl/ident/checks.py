"""Stage *judge* of one candidate: its plausibility (the size, significance and physical range of
its family's rule and the shared ones), the decision rule's gain and BIC tests, the simpler
accounts (:mod:`motorctl.ident.accounts`), and the residual verdict of a model."""

from __future__ import annotations

import functools
import math

import numpy as np

from motorctl.effects import family as effect_family
from motorctl.ident.accounts import accounts, explained_as_much
from motorctl.ident.fit import _coef, _cov, _sse_of
from motorctl.ident.idim import input_saturation
from motorctl.ident.records import _force, _found_in_measurement, _hold
from motorctl.ident.rules import (MAX_HELD_SHARE, MIN_BIC_DROP, MIN_HELDOUT_GAIN, MIN_SIZE_N, MIN_SIZE_SHARE,
                                  MIN_WALD, refused_on_physics)
from motorctl.ident.verdict import REST_SPEED_SHARE, residual_verdict


def _fall_share(without: Evaluated, ev: Evaluated, where: np.ndarray) -> float | None:
    """The share [-] of what ``ev`` explains beyond ``without`` (the fall of the squared
    residual, summed over the decimated samples) that lies ``where`` ((M,) bool, or weights in
    [0, 1]); None when it explains nothing."""
    fall = without.fit.residual ** 2 - ev.fit.residual ** 2
    total = float(fall.sum())
    if not total > 0.0:
        return None
    return float((where * fall).sum()) / total


class Checks:
    """The judge of a candidate and the read-outs its family's checks use (a part of
    :class:`~motorctl.ident.select.Identifier`)."""

    def search(self, family: str, base: list, residual: np.ndarray) -> Evaluated | None:
        """Best candidate of ``family`` given the already selected ``base`` terms, evaluated
        (None when the record cannot show the effect). The search itself is the family's
        (:meth:`motorctl.effects.base.EffectFamily.search`); its note (e.g. the parameter at the
        edge of its grid) becomes a reason against the candidate."""
        found = effect_family(family).search(self, base, residual)
        if found is None:
            return None
        term, note = found
        ev = self.evaluate(base + [term])
        ev.term = term
        if note:
            ev.reasons.append(note)
        return ev

    def plausible(self, ev: Evaluated, base: list, without: Evaluated | None = None) -> list:
        """Reasons why the candidate is not physically plausible (empty list: plausible).
        ``without``: the model of ``base`` alone, evaluated, for :meth:`held_share` (None: that
        rule not applied)."""
        reasons = list(ev.reasons)
        term, fit = ev.term, ev.fit
        nt = self.n_theta
        th, sd = fit.coef[:nt], fit.std[:nt]
        if th[0] <= 0:
            reasons.append("theta1 <= 0")
        for i in (1, 2):
            if th[i] < -3 * sd[i]:
                reasons.append(f"theta{i + 1} significantly negative")
        if term.cols is not None:
            k = term.cols.shape[1]
            beta = fit.coef[-k:]
            bstd = fit.std[-k:]
            wald = float(np.sum((beta / bstd) ** 2)) / k
            if wald < MIN_WALD:
                reasons.append(f"coefficients not significant (Wald/column {wald:.1f} < {MIN_WALD:g})")
            contrib = term.cols @ beta
            u_range = float(np.percentile(np.abs(self.p.u_d), 99))
            fam = effect_family(term.family)
            size = float(np.percentile(np.abs(contrib), 99))
            ev.size = size
            if not _found_in_measurement(term):   # an error of the reading: its size was judged in the reading
                reasons += self.too_small(size)
            if np.max(np.abs(contrib)) > 0.5 * u_range and fam.force_bounded_by_input:
                reasons.append("effect larger than half the input range")
            held = None if without is None else self.held_share(ev, without, base)
            if held is not None and held[0] > MAX_HELD_SHARE:
                reasons.append(f"explained where held: {100 * held[0]:.0f} % of what it explains lies where the "
                               f"{held[1]} in the model holds the carriage (> {100 * MAX_HELD_SHARE:g} %), "
                               "the stick and slip at rest that the holding effect's model leaves")
            reasons += fam.plausible(self, term, beta, th, base)
        return reasons

    def too_small(self, size: float) -> list:
        """The reason against naming an effect whose force, the 99th percentile of |C β| over
        the decimated samples, is ``size`` [V]: below :data:`MIN_SIZE_SHARE` of the RMS input
        or, with the record's gain A1, below :data:`MIN_SIZE_N`; else []."""
        u_rms = float(np.sqrt(np.mean(self.p.u_d ** 2)))
        g = self.rec.gain
        if size < MIN_SIZE_SHARE * u_rms:
            return [f"too small to name: its force ({_force(size, g)}) is below "
                    f"{100 * MIN_SIZE_SHARE:g} % of the RMS input ({_force(u_rms, g)})"]
        if g and g * size < MIN_SIZE_N:
            return [f"too small to name: its force ({_force(size, g)}) is below {MIN_SIZE_N:g} N"]
        return []

    @functools.cached_property
    def saturation(self) -> dict | None:
        """Where the input sits at its limit (:func:`~motorctl.ident.idim.input_saturation`;
        None: nowhere): reported, the fit unchanged. Computed when asked (the summary): the
        refit's and the validation's identifiers of the same record do not need it."""
        return input_saturation(self.p.u, self.p.fs, self.rec.u_limit)

    def rest_share(self, ev: Evaluated) -> float:
        """The share [-] of what the candidate ``ev`` (fitted beside the final model's effects)
        explains, the fall of the squared residual from the final model to ``ev`` summed over the
        decimated samples, that lies near zero velocity (|ẋ| below
        :data:`~motorctl.ident.verdict.REST_SPEED_SHARE` of the record's peak speed); 0 when it
        explains nothing."""
        v = np.abs(self.p.v_d)
        return _fall_share(self.final, ev, v < REST_SPEED_SHARE * float(v.max())) or 0.0

    def held_share(self, ev: Evaluated, without: Evaluated, base: list) -> tuple[float, str] | None:
        """(share, family): the share [-] of what the candidate ``ev`` explains, the fall of the
        squared residual from ``without`` (the model of ``base``) to ``ev`` summed over the
        decimated samples, that lies where a family of ``base`` holds the carriage, each sample
        weighed by that hold (1 − the product of the families' ``other_weight``: stiction's
        w(ẋ) = exp(−(ẋ/h)²)). None when ``base`` holds nothing, the candidate holds the carriage
        itself (its family's ``other_weight``), is found in the measurement, or explains nothing.
        A dead-zone is judged too: beside stiction its columns are fitted in motion, where the
        input beyond its band loses A1·d (:mod:`motorctl.effects.amplifier_dead_zone`).

        Held samples are the holding effect's: its columns fit the input held at rest, and the
        other terms' columns are weighed out there (:meth:`design`). A candidate that still
        explains mostly there does so through the nominal θ it moves, fitting the short slips
        of the carriage's hunting at rest (a C2 loop under stiction) that the holding effect
        does not describe: the residual verdict counts a structure near zero velocity as the
        holding effect's too."""
        if effect_family(ev.term.family).other_weight(ev.term) is not None or _found_in_measurement(ev.term):
            return None
        weight, holder = _hold(base)
        if weight is None:
            return None
        share = _fall_share(without, ev, 1.0 - weight)
        return None if share is None else (share, holder)

    def explained_shares(self, term: Term, base: list, *rows: np.ndarray) -> tuple[float, ...]:
        """For each set of decimated samples in ``rows`` ((M,) bool each), the share [-] of the
        residual SSE of the model of ``base`` that adding ``term`` explains, both fitted jointly
        with the nominal θ on those samples only; 0 where they are too few for the fit or leave
        no residual. The two models' regressors are built once for all the sets."""
        phi0, y0 = self.design(base)
        phi1, y1 = self.design(base + [term])
        out = []
        for sel in rows:
            if sel.sum() < 4 * phi1.shape[1]:
                out.append(0.0)
                continue
            r0 = y0[sel] - phi0[sel] @ _coef(phi0[sel], y0[sel])
            r1 = y1[sel] - phi1[sel] @ _coef(phi1[sel], y1[sel])
            s0 = float(r0 @ r0)
            out.append((s0 - float(r1 @ r1)) / s0 if s0 > 0 else 0.0)
        return tuple(out)

    def direction_agreement(self, term: Term, base: list) -> float:
        """1 − ‖β₊ − β₋‖/(‖β₊‖ + ‖β₋‖) for the effect's coefficients fitted jointly with the
        nominal θ on the samples moving forward (β₊) and backward (β₋) separately (1: the same
        force both ways, as cogging and ripple must be; ≤ 0: unrelated)."""
        phi, y = self.design(base + [term])
        k = term.cols.shape[1]
        betas = []
        for sel in (self.p.v_d > 0, self.p.v_d < 0):
            sel = sel & self.moving
            if sel.sum() < 4 * phi.shape[1]:
                return 0.0
            betas.append(_coef(phi[sel], y[sel])[-k:])
        bp, bm = betas
        den = np.linalg.norm(bp) + np.linalg.norm(bm)
        return float(1.0 - np.linalg.norm(bp - bm) / den) if den > 0 else 0.0

    def direction_split_gain(self, term: Term, base: list) -> float:
        """What the effect's columns explain beyond their joint fit when fitted on each direction
        of motion with their own coefficients (the columns × [ẋ > 0] and × [ẋ < 0] in place of
        them, jointly with the nominal θ), as a share of what they explain: (SSE(base + term) −
        SSE(split)) / (SSE(base) − SSE(base + term)). About 0 for a force that is one function
        of the state whichever way the carriage moves (a friction of position: its columns carry
        S_f(ẋ)); large for a force that differs with the direction (a play taken up at other
        positions going out and back). NaN when the term explains nothing."""
        phi, y = self.design(base + [term])
        k = term.cols.shape[1]
        s_with, s0 = self.sse(base + [term]), self.sse(base)
        fwd = (self.p.v_d > 0)[:, None]
        split = np.hstack([phi[:, :-k], phi[:, -k:] * fwd, phi[:, -k:] * ~fwd])
        gain = s0 - s_with
        return float((s_with - _sse_of(split, y)) / gain) if gain > 0 else math.nan

    def speed_growth(self, term: Term, base: list, period: float) -> float:
        """‖β_fast‖/‖β_slow‖ for the effect's coefficients fitted jointly with the nominal θ
        (θ1 taken from the whole record, the other columns fitted on each half) on
        the slower and the faster half of the moving samples at which a spatial period
        ``period`` [m] passes the position filter (|ẋ| < fq·period): about 1 for a force of
        position (cogging, ripple) and for a reading's error in its own columns; a reading's
        error fitted as a force grows with ẋ² (ë = −w²ẋ² e). NaN when too few samples."""
        return self.speed_growth_interval(term, base, period)[0]

    def speed_growth_interval(self, term: Term, base: list, period: float) -> tuple[float, float, float]:
        """(r, lo, hi): :meth:`speed_growth` r and r ∓ 2 standard errors (each half's amplitude
        ‖β‖ with its standard error from the fit's covariance σ̂²(ΦᵀΦ)⁻¹ projected on β/‖β‖; the
        ratio's by the first-order propagation of the two). NaN (all three) when too few samples."""
        phi, y = self.design(base + [term])
        # θ1 from the whole record, not from each half: in the faster half (the cruise) the
        # carriage accelerates only as the effect itself makes it, at the effect's frequency, so
        # the mass is not measured there and trades with the effect's columns (half-mode plant,
        # 6 N cogging: θ1 0.124 there for the record's 0.156, the amplitude x2.9 the slower half's)
        y = y - _coef(phi, y)[0] * phi[:, 0]
        phi = phi[:, 1:]
        k = term.cols.shape[1]
        sp = np.abs(self.p.v_d)
        seen = self.moving & (sp < self.p.fq * period)
        nan = (math.nan, math.nan, math.nan)
        if seen.sum() < 8 * phi.shape[1]:
            return nan
        med = float(np.median(sp[seen]))
        norms, rel = [], []
        for sel in (seen & (sp <= med), seen & (sp > med)):
            if sel.sum() < 4 * phi.shape[1]:
                return nan
            coef = _coef(phi[sel], y[sel])
            b = coef[-k:]
            n = float(np.linalg.norm(b))
            norms.append(n)
            if n > 0:
                g = b / n
                cov = _cov(phi[sel], y[sel] - phi[sel] @ coef)[-k:, -k:]
                rel.append(math.sqrt(max(float(g @ cov @ g), 0.0)) / n)
        r = norms[1] / norms[0] if norms[0] > 0 else math.inf
        if len(rel) < 2:            # a zero amplitude on a half: the ratio 0 or inf, no interval
            return r, r, r
        se = r * math.hypot(rel[0], rel[1])
        return r, r - 2.0 * se, r + 2.0 * se

    def judge(self, ev: Evaluated, current: Evaluated, base: list, skip_accounts: tuple = ()) -> Evaluated:
        """The decision rule on candidate ``ev`` against ``current``, the model of ``base``:
        plausible (:meth:`plausible`), the held-out gain and the BIC drop, and no simpler account
        (:mod:`motorctl.ident.accounts`; those of the kinds in ``skip_accounts`` not asked: a
        rival judged as if that account were not there). Sets ``ok``, ``reasons``, ``gain``."""
        gain = 1.0 - ev.heldout_rms / current.heldout_rms
        reasons = self.plausible(ev, base, current)
        if gain < MIN_HELDOUT_GAIN:
            reasons.append(f"held-out gain {100 * gain:.1f} % < {100 * MIN_HELDOUT_GAIN:g} %")
        if current.bic - ev.bic < MIN_BIC_DROP:
            reasons.append(f"BIC drop {current.bic - ev.bic:.1f} < {MIN_BIC_DROP:g}")
        if not reasons and not _found_in_measurement(ev.term):
            # significant on its own: named only when no simpler account explains as much
            found = [a for a in self.accounts_of(base, current) if a.kind not in skip_accounts]
            reasons = explained_as_much(ev.term.family, ev.heldout_rms, found)
        ev.reasons = reasons
        ev.ok = not reasons
        ev.gain = gain
        return ev

    def accounts_of(self, base: list, current: "Evaluated") -> list:
        """The simpler accounts (:func:`motorctl.ident.accounts.accounts`) of the residual of
        ``current``, the model of ``base``; kept per base (the step's candidates share them)."""
        key = (self.zoh, self.n_theta, id(self.p.fu), id(self.nuisance)) + tuple(id(t) for t in base)
        cache = self.__dict__.setdefault("_accounts", {})
        hit = cache.get(key)
        if hit is None or hit[0] is not current.fit:
            if len(cache) > 64:
                cache.clear()
            hit = cache[key] = (current.fit, list(base), accounts(self, base, current.fit.residual))
        return hit[2]

    def implausible_in(self, terms: list, i: int) -> list:
        """The reasons of term ``terms[i]``'s family (its own
        :meth:`~motorctl.effects.base.EffectFamily.plausible`) against it in the joint fit of
        ``terms``; empty: plausible."""
        if terms[i].cols is None:
            return []
        theta, betas = self.coef_split(self.evaluate(terms), terms)
        return effect_family(terms[i].family).plausible(self, terms[i], betas[i], theta, terms[:i] + terms[i + 1:])

    def verdict(self, current: Evaluated, terms: list, gain: float = 1.0, unit: str = "V") -> dict:
        """The residual verdict (:func:`motorctl.ident.verdict.residual_verdict`) of ``current``,
        the model of ``terms``: the first of them whose family holds the carriage at rest
        (``acts_at_rest``) explains what is left there; a structure smaller than an effect
        would be named at (:meth:`least_size`) is not one."""
        at_rest = next((t.family for t in terms if effect_family(t.family).acts_at_rest), None)
        coulomb = float(self.coef_split(current, terms)[0][2])
        return residual_verdict(current.fit.residual, self.p, gain, unit, at_rest_by=at_rest,
                                min_size=self.least_size(), coulomb=coulomb)

    def least_size(self) -> float:
        """The least size of a force worth naming [V]: :data:`MIN_SIZE_SHARE` of the RMS input
        and, when the gain A1 is known, :data:`MIN_SIZE_N` (the effects' rule of
        :meth:`plausible`, applied to what the residual verdict reports)."""
        u_rms = float(np.sqrt(np.mean(self.p.u_d ** 2)))
        g = self.rec.gain
        return max(MIN_SIZE_SHARE * u_rms, MIN_SIZE_N / g if g else 0.0)

    def unexplained(self, current: Evaluated, terms: list, last_step: list) -> bool:
        """The residual of ``current`` (the model of ``terms``) keeps a structure no family
        explains: the residual verdict (:meth:`verdict`) or a candidate of ``last_step`` refused
        on its physics only (:func:`refused_on_physics`)."""
        if self.verdict(current, terms)["structured"]:
            return True
        return any(refused_on_physics(c) for c in last_step if not any(c.term is t for t in terms))
