"""Stage *judge* of one candidate: its plausibility (the size, significance and physical range of
its family's rule and the shared ones), the decision rule's gain and BIC tests, the simpler
accounts (:mod:`motorctl.ident.accounts`), and the residual verdict of a model.

A :class:`Judge` works on the fits of one record at one structure
(:class:`~motorctl.ident.fit.Fits`) and the records it is handed: it returns new
:class:`~motorctl.ident.records.Evaluated` records and never keeps a selection.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from motorctl.effects import family as effect_family
from motorctl.ident.accounts import accounts, explained_as_much
from motorctl.ident.records import Evaluated, force_text, found_in_measurement, hold, without
from motorctl.ident.rules import (MAX_HELD_SHARE, MIN_BIC_DROP, MIN_HELDOUT_GAIN, MIN_SIZE_N, MIN_SIZE_SHARE,
                                  MIN_WALD, outcome)
from motorctl.ident.verdict import REST_SPEED_SHARE, Verdict, residual_verdict


def fall_share(before: Evaluated, ev: Evaluated, where: np.ndarray) -> float | None:
    """The share [-] of what ``ev`` explains beyond ``before`` (the fall of the squared
    residual, summed over the decimated samples) that lies ``where`` ((M,) bool, or weights in
    [0, 1]); None when it explains nothing."""
    fall = before.fit.residual ** 2 - ev.fit.residual ** 2
    total = float(fall.sum())
    if not total > 0.0:
        return None
    return float((where * fall).sum()) / total


class Judge:
    """The decision rule on candidates of one record (docs/identification.md, "Decision rule").

    Args:
        fits: the fit stage on the record at the structure the candidates are fitted at.
    """

    def __init__(self, fits):
        self.fits = fits
        self._accounts: dict = {}

    def at(self, fits) -> "Judge":
        """The judge on other fits of the same record (another structure)."""
        return Judge(fits)

    def search(self, family: str, base, residual: np.ndarray | None) -> Evaluated | None:
        """Best candidate of ``family`` given the already selected ``base`` terms, evaluated
        (None when the record cannot show the effect). The search itself is the family's
        (:meth:`motorctl.effects.base.EffectFamily.search`); its note (e.g. the parameter at the
        edge of its grid) becomes a reason against the candidate."""
        base = list(base)
        found = effect_family(family).search(self.fits, base, residual)
        if found is None:
            return None
        term, note = found
        ev = self.fits.evaluate(base + [term])
        return replace(ev, term=term, reasons=(note,) if note else ())

    def plausible(self, ev: Evaluated, base, before: Evaluated | None = None) -> tuple[list, float | None]:
        """(reasons why the candidate is not physically plausible (empty: plausible), the size of
        its force [V] or None). ``before``: the model of ``base`` alone, evaluated, for
        :meth:`held_share` (None: that rule not applied)."""
        fits = self.fits
        reasons = list(ev.reasons)
        term, fit = ev.term, ev.fit
        nt = fits.n_theta
        th, sd = fit.coef[:nt], fit.std[:nt]
        size = None
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
            u_range = float(np.percentile(np.abs(fits.p.u_d), 99))
            fam = effect_family(term.family)
            size = float(np.percentile(np.abs(contrib), 99))
            if not found_in_measurement(term):   # an error of the reading: its size was judged in the reading
                reasons += self.too_small(size)
            if np.max(np.abs(contrib)) > 0.5 * u_range and fam.force_bounded_by_input:
                reasons.append("effect larger than half the input range")
            held = None if before is None else self.held_share(ev, before, base)
            if held is not None and held[0] > MAX_HELD_SHARE:
                reasons.append(f"explained where held: {100 * held[0]:.0f} % of what it explains lies where the "
                               f"{held[1]} in the model holds the carriage (> {100 * MAX_HELD_SHARE:g} %), "
                               "the stick and slip at rest that the holding effect's model leaves")
            reasons += fam.plausible(fits, term, beta, th, list(base))
        return reasons, size

    def too_small(self, size: float) -> list:
        """The reason against naming an effect whose force, the 99th percentile of |C β| over
        the decimated samples, is ``size`` [V]: below :data:`MIN_SIZE_SHARE` of the RMS input
        or, with the record's gain A1, below :data:`MIN_SIZE_N`; else []."""
        u_rms = float(np.sqrt(np.mean(self.fits.p.u_d ** 2)))
        g = self.fits.rec.gain
        if size < MIN_SIZE_SHARE * u_rms:
            return [f"too small to name: its force ({force_text(size, g)}) is below "
                    f"{100 * MIN_SIZE_SHARE:g} % of the RMS input ({force_text(u_rms, g)})"]
        if g and g * size < MIN_SIZE_N:
            return [f"too small to name: its force ({force_text(size, g)}) is below {MIN_SIZE_N:g} N"]
        return []

    def rest_share(self, final: Evaluated, ev: Evaluated) -> float:
        """The share [-] of what the candidate ``ev`` (fitted beside the final model ``final``'s
        effects) explains, the fall of the squared residual from ``final`` to ``ev`` summed over
        the decimated samples, that lies near zero velocity (|ẋ| below
        :data:`~motorctl.ident.verdict.REST_SPEED_SHARE` of the record's peak speed); 0 when it
        explains nothing."""
        v = np.abs(self.fits.p.v_d)
        return fall_share(final, ev, v < REST_SPEED_SHARE * float(v.max())) or 0.0

    def held_share(self, ev: Evaluated, before: Evaluated, base) -> tuple[float, str] | None:
        """(share, family): the share [-] of what the candidate ``ev`` explains, the fall of the
        squared residual from ``before`` (the model of ``base``) to ``ev`` summed over the
        decimated samples, that lies where a family of ``base`` holds the carriage, each sample
        weighed by that hold (1 − the product of the families' ``other_weight``: stiction's
        w(ẋ) = exp(−(ẋ/h)²)). None when ``base`` holds nothing, the candidate holds the carriage
        itself (its family's ``other_weight``), is found in the measurement, or explains nothing.
        A dead-zone is judged too: beside stiction its columns are fitted in motion, where the
        input beyond its band loses A1·d (:mod:`motorctl.effects.amplifier_dead_zone`).

        Held samples are the holding effect's: its columns fit the input held at rest, and the
        other terms' columns are weighed out there (:meth:`~motorctl.ident.fit.Fits.design`). A
        candidate that still explains mostly there does so through the nominal θ it moves,
        fitting the short slips of the carriage's hunting at rest (a C2 loop under stiction)
        that the holding effect does not describe: the residual verdict counts a structure near
        zero velocity as the holding effect's too."""
        if effect_family(ev.term.family).other_weight(ev.term) is not None or found_in_measurement(ev.term):
            return None
        weight, holder = hold(base)
        if weight is None:
            return None
        share = fall_share(before, ev, 1.0 - weight)
        return None if share is None else (share, holder)

    def judge(self, ev: Evaluated, current: Evaluated, base, skip_accounts: tuple = ()) -> Evaluated:
        """The decision rule on candidate ``ev`` against ``current``, the model of ``base``:
        plausible (:meth:`plausible`), the held-out gain and the BIC drop, and no simpler account
        (:mod:`motorctl.ident.accounts`; those of the kinds in ``skip_accounts`` not asked: a
        rival judged as if that account were not there). Returns ``ev`` judged: ``ok``,
        ``reasons``, ``gain``, ``size``."""
        gain = 1.0 - ev.heldout_rms / current.heldout_rms
        reasons, size = self.plausible(ev, base, current)
        if gain < MIN_HELDOUT_GAIN:
            reasons.append(f"held-out gain {100 * gain:.1f} % < {100 * MIN_HELDOUT_GAIN:g} %")
        if current.bic - ev.bic < MIN_BIC_DROP:
            reasons.append(f"BIC drop {current.bic - ev.bic:.1f} < {MIN_BIC_DROP:g}")
        if not reasons and not found_in_measurement(ev.term):
            # significant on its own: named only when no simpler account explains as much
            found = [a for a in self.accounts_of(base, current) if a.kind not in skip_accounts]
            reasons = explained_as_much(ev.term.family, ev.heldout_rms, found)
        return replace(ev, reasons=tuple(reasons), ok=not reasons, gain=gain, size=size)

    def accounts_of(self, base, current: Evaluated) -> list:
        """The simpler accounts (:func:`motorctl.ident.accounts.accounts`) of the residual of
        ``current``, the model of ``base``; kept per base (the step's candidates share them)."""
        key = tuple(id(t) for t in base)
        hit = self._accounts.get(key)
        if hit is None or hit[0] is not current.fit:
            if len(self._accounts) > 64:
                self._accounts.clear()
            hit = self._accounts[key] = (current.fit, list(base), accounts(self.fits, list(base),
                                                                          current.fit.residual))
        return hit[2]

    def implausible_in(self, terms, i: int) -> list:
        """The reasons of term ``terms[i]``'s family (its own
        :meth:`~motorctl.effects.base.EffectFamily.plausible`) against it in the joint fit of
        ``terms``; empty: plausible."""
        terms = list(terms)
        if terms[i].cols is None:
            return []
        theta, betas = self.fits.coef_split(self.fits.evaluate(terms), terms)
        return effect_family(terms[i].family).plausible(self.fits, terms[i], betas[i], theta, without(terms, i))

    def verdict(self, current: Evaluated, terms, gain: float = 1.0, unit: str = "V") -> Verdict:
        """The residual verdict (:func:`motorctl.ident.verdict.residual_verdict`) of ``current``,
        the model of ``terms``: the first of them whose family holds the carriage at rest
        (``acts_at_rest``) explains what is left there; a structure smaller than an effect
        would be named at (:meth:`least_size`) is not one."""
        at_rest = next((t.family for t in terms if effect_family(t.family).acts_at_rest), None)
        coulomb = float(self.fits.coef_split(current, terms)[0][2])
        return residual_verdict(current.fit.residual, self.fits.p, gain, unit, at_rest_by=at_rest,
                                min_size=self.least_size(), coulomb=coulomb)

    def least_size(self) -> float:
        """The least size of a force worth naming [V]: :data:`MIN_SIZE_SHARE` of the RMS input
        and, when the gain A1 is known, :data:`MIN_SIZE_N` (the effects' rule of
        :meth:`plausible`, applied to what the residual verdict reports)."""
        u_rms = float(np.sqrt(np.mean(self.fits.p.u_d ** 2)))
        g = self.fits.rec.gain
        return max(MIN_SIZE_SHARE * u_rms, MIN_SIZE_N / g if g else 0.0)

    def unexplained(self, current: Evaluated, terms, last_step) -> bool:
        """The residual of ``current`` (the model of ``terms``) keeps a structure no family
        explains: the residual verdict (:meth:`verdict`) or a candidate of ``last_step`` refused
        on its physics only (:func:`~motorctl.ident.rules.outcome` 'unexplained')."""
        if self.verdict(current, terms).structured:
            return True
        return any(outcome(passed=False, refused=c) == "unexplained" for c in last_step
                   if not any(c.term is t for t in terms))


__all__ = ["Judge", "fall_share"]
