"""A name only where the record can tell: effects that share their evidence with a structure
the selection refused (docs/identification.md, "Ambiguities: a name only where the record can
tell").

After the selection, the residual can keep a structure no family may be named for: a candidate
that explains a share of it and was refused on its physics (:func:`~motorctl.ident.rules.
refused_on_physics`; the residual verdict warns on it). A named effect whose columns explain
the same part of the residual would then be named on evidence the warning also claims: a 4 N
disturbance at 11.5 Hz, the 46th harmonic of the 4 s program's period, refused as a force from
outside there, was named an amplifier dead-zone or a position friction shape. Each named effect
is judged again with that structure in the model (:func:`shared_evidence`): when it adds less
than :data:`~motorctl.ident.rules.MIN_HELDOUT_GAIN` to the held-out residual beside it, the two
cannot be told apart from this record; the effect is taken out of the model (not named, not
compensated) and reported as an :class:`Ambiguity` with both fits and the experiment that
separates them.

A time-periodic line at a harmonic of the program's period (:func:`~motorctl.effects.
periodic_disturbance.program_harmonic`) is a force of position too, when the motion repeats: a
force g(x(t)) repeats with the program and is a sum of its harmonics. So the force-of-position
families (:data:`POSITION_FAMILIES`) are also searched beside such a refused line
(:func:`harmonic_rivals`), named or not: one that explains the same columns is reported as the
line's rival. The experiment that resolves it: the same program at another speed (a feed
override): a time-periodic force keeps its frequency in Hz, a position-periodic one its period
in metres (its frequency scales with the speed).

Nothing here changes what the identifier names when the residual keeps no refused structure.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from motorctl.ident.rules import outcome

#: families whose force is a function of the position (times the friction shape or the
#: thrust): at a harmonic of a repeating program's period they explain what a time-periodic
#: line there does
POSITION_FAMILIES = ("cogging", "force_ripple", "periodic_friction", "position_friction_shape",
                     "position_dependent_friction", "spring")
#: the time-periodic family whose line at a program harmonic the position families are searched
#: against (:func:`harmonic_rivals`)
TIME_FAMILY = "periodic_disturbance"
#: the force of position that a hold at rest (stiction, a dead-zone, a coarse reading) can stand
#: for, told apart by slow constant-velocity passes (motorctl.commission.tune.pass_experiment)
SPRING_FAMILY = "spring"

#: what separates a time-periodic line from a force of position (the text of the report)
SPEED_EXPERIMENT = ("run the same program at another speed (e.g. a feed override of 0.7): a time-periodic "
                    "force keeps its frequency in Hz, a force of position keeps its period in metres (its "
                    "frequency in Hz scales with the speed)")
#: the same for any other pair: a record whose motion does not repeat with one period
OTHER_EXPERIMENT = ("record a program that moves the two apart (other speeds, other stroke positions, "
                    "a non-repeating sequence of moves) and identify again")


@dataclass(frozen=True, eq=False)
class Ambiguity:
    """A named (or, at a program harmonic, a searched) effect and a refused structure that
    explain the same part of the residual.

    ``named``, ``structure``: the two terms (:class:`~motorctl.ident.records.Term`); ``fit_named``,
    ``fit_structure``: the model of the other selected effects plus each alone
    (:class:`~motorctl.ident.records.Evaluated`); ``gain_named``, ``gain_structure``: their
    held-out gains [-] against the model with neither; ``gain_beside``: what ``named`` adds
    beside ``structure`` [-]; ``structure_reasons``: why the structure was refused;
    ``harmonic``: (k, T [s]) when the structure is a time-periodic line at the k-th harmonic of
    the program's period T; ``was_named``: ``named`` had been selected (else it was searched
    as the harmonic line's rival); ``others``: the other selected terms both fits share."""

    named: object
    structure: object
    fit_named: object
    fit_structure: object
    gain_named: float
    gain_structure: float
    gain_beside: float
    structure_reasons: tuple = ()
    harmonic: tuple | None = None
    was_named: bool = True
    others: tuple = ()


def _usable(term) -> bool:
    """A term whose columns can be added to another model (not an input shift)."""
    return term is not None and term.cols is not None and not term.delay


def _pair(fits, others: list, named, structure, gain_min: float):
    """(Ambiguity, or None when ``named`` adds at least ``gain_min`` beside ``structure``)."""
    none = fits.evaluate(others)
    with_s = fits.evaluate(others + [structure])
    with_n = fits.evaluate(others + [named])
    both = fits.evaluate(others + [structure, named])
    beside = 1.0 - both.heldout_rms / with_s.heldout_rms
    if outcome(passed=True, shares_with=None if not beside < gain_min else structure.family) != "ambiguous":
        return None
    return Ambiguity(named=named, structure=structure, fit_named=with_n, fit_structure=with_s,
                     gain_named=1.0 - with_n.heldout_rms / none.heldout_rms,
                     gain_structure=1.0 - with_s.heldout_rms / none.heldout_rms,
                     gain_beside=beside, others=tuple(others))


def _harmonic(p, term):
    if term.family != TIME_FAMILY or term.h is None:
        return None
    from motorctl.effects.periodic_disturbance import program_harmonic
    return program_harmonic(p, float(term.h))


def shared_evidence(judge, base: list, accepted: list, refused: list, gain_min: float, exempt=lambda t: False):
    """The selected effects that share their evidence with a refused structure, taken out.

    Args:
        judge: the selection's judge (:class:`~motorctl.ident.checks.Judge`: its ``fits``).
        base: the selected terms; accepted: their (Evaluated, held-out RMS before) pairs, in
            the same order. refused: candidates (Evaluated) of the final model refused on their
            physics (the residual verdict's structures). gain_min: the least held-out gain [-]
            an effect must add beside a structure to keep its name. exempt: terms never taken
            out (an error found in the reading itself).
    Returns:
        (terms, accepted, [Ambiguity]): the model without the effects that add less than
        ``gain_min`` beside a structure (the weakest first, then the rest judged again).
    """
    found = []
    structures = [c for c in refused if _usable(getattr(c, "term", None))]
    while structures and base:
        worst = None
        for i, t in enumerate(base):
            if exempt(t) or not _usable(t):
                continue
            others = base[:i] + base[i + 1:]
            for c in structures:
                if c.term.family == t.family:
                    continue
                a = _pair(judge.fits, others, t, c.term, gain_min)
                if a is not None and (worst is None or a.gain_beside < worst[0].gain_beside):
                    worst = (replace(a, structure_reasons=tuple(c.reasons), harmonic=_harmonic(judge.fits.p, c.term)), i)
        if worst is None:
            break
        a, i = worst
        found.append(a)
        base = base[:i] + base[i + 1:]
        accepted = accepted[:i] + accepted[i + 1:]
    return base, accepted, found


def harmonic_rivals(judge, base: list, refused: list, gain_min: float, already: list) -> list:
    """For each refused time-periodic line at a program harmonic, the force-of-position families
    (:data:`POSITION_FAMILIES`, those searched and not in ``base``) that explain the same columns:
    searched beside ``base``, each passing the selection's judgement there
    (:meth:`~motorctl.ident.checks.Judge.judge`: it would be named without the line) and
    adding less than ``gain_min`` beside the line. ``already``: ambiguities found so far (a pair is not
    reported twice). Returns [Ambiguity] with ``was_named`` False."""
    fits = judge.fits
    out = []
    seen = {(a.structure.family, a.named.family) for a in already}
    lines = [c for c in refused if _usable(getattr(c, "term", None)) and c.term.family == TIME_FAMILY]
    for c in lines:
        at = _harmonic(fits.p, c.term)
        if at is None:
            continue
        none = fits.evaluate(base)
        for fam in POSITION_FAMILIES:
            if fam not in fits.families or any(t.family == fam for t in base) or (TIME_FAMILY, fam) in seen:
                continue
            ev = judge.search(fam, base, none.fit.residual)
            # not a name the record would give it on its own (the line, its rival here, not
            # asked as its simpler account)
            if ev is None or not _usable(ev.term) or not judge.judge(ev, none, base, skip_accounts=("line",)).ok:
                continue
            a = _pair(fits, base, ev.term, c.term, gain_min)
            if a is None or a.gain_named < gain_min:
                continue
            out.append(replace(a, structure_reasons=tuple(c.reasons), harmonic=at, was_named=False))
    return out


#: half-width of the grid on which a verdict's line is refined, in the record's frequency
#: resolutions 1/L, and the grid's points (:func:`harmonic_lines`)
LINE_GRID_RESOLUTIONS, LINE_GRID_POINTS = 4.0, 81


def harmonic_lines(judge, current, base: list) -> list:
    """The residual verdict's periodic lines (``against`` "spectrum", structured) of the model
    ``current`` (of ``base``) that lie at a harmonic of the program's period, each as a
    refused structure: an :class:`~motorctl.ident.records.Evaluated` of its ``term`` (a
    ``periodic_disturbance`` term, its frequency refined on the joint fit within
    ±:data:`LINE_GRID_RESOLUTIONS`/L of the verdict's) beside ``base``, not ok, with its
    ``reasons`` and ``gain`` (its held-out gain on ``current``, [-]). A line there that the
    selection left in the residual (the time-periodic family refused it, or did not search it
    at that frequency) is a structure as much as a refused candidate."""
    import re

    from motorctl.effects import family
    from motorctl.effects.base import Signals
    from motorctl.effects.periodic_disturbance import program_harmonic
    fits = judge.fits
    if TIME_FAMILY not in fits.families:
        return []
    out = []
    verdict = judge.verdict(current, base)
    length = float(fits.p.t_d[-1] - fits.p.t_d[0])
    fast = Signals.decimated(fits.p)
    fam = family(TIME_FAMILY)
    for f in verdict["findings"]:
        m = re.match(r"periodic at ([0-9.eE+-]+) Hz", f.get("where", ""))
        if f.get("against") != "spectrum" or not m or not length > 0:
            continue
        f0 = float(m.group(1))
        grid = f0 + np.linspace(-1.0, 1.0, LINE_GRID_POINTS) * LINE_GRID_RESOLUTIONS / length
        term, _ = fits.best_over(TIME_FAMILY, grid[grid > 0], base, lambda h: fam.columns(h, fast))
        at = program_harmonic(fits.p, float(term.h))
        if at is None:
            continue
        ev = fits.evaluate(base + [term])
        why = (f"a line the residual keeps at {float(term.h):.4g} Hz, harmonic {at[0]} of the program's "
               f"period {at[1]:.4g} s (the motion repeats with it): not told from a force in step with the moves")
        out.append(replace(ev, reasons=(why,), gain=1.0 - ev.heldout_rms / current.heldout_rms, ok=False))
    return out


def _label(term, harmonic) -> str:
    if term.family == TIME_FAMILY:
        what = f"periodic disturbance (time) at {float(term.h):.4g} Hz"
        if harmonic is not None:
            what += f", harmonic {harmonic[0]} of the program's period {harmonic[1]:.4g} s"
        return what
    return term.family


def summaries(fits, ambiguities: list, gain: float | None, unit: str) -> list:
    """The ``ambiguous`` entries of ``identify``'s JSON: for each :class:`Ambiguity` ``text``
    ("ambiguous: A or B"), ``families`` [structure, named], ``fits`` (each one's parameters,
    in N with a gain else V, and held-out gain in %), ``gain_beside_percent`` (what the named
    one adds beside the other), ``structure_refused`` (its reasons), ``was_named``,
    ``experiment`` (what separates them), ``compensated`` false."""
    from motorctl.ident import effects as fx
    out = []
    for a in ambiguities:
        fitted = []
        for term, ev, g in ((a.structure, a.fit_structure, a.gain_structure), (a.named, a.fit_named, a.gain_named)):
            th, betas = fits.coef_split(ev, list(a.others) + [term])
            try:
                params = fx.parameters(term.family, term.h, betas[-1], gain, fits.p.fs, theta=th, p=fits.p)
            except Exception as exc:        # noqa: BLE001 - a family's parameters need the full context
                params = {"note": f"parameters not available ({type(exc).__name__})"}
            fitted.append({"name": term.family, "parameters": {k: _num(v) for k, v in params.items()},
                         "heldout_gain_percent": 100 * g,
                         "heldout_rms": (gain or 1.0) * ev.heldout_rms})
        first = _label(a.structure, a.harmonic)
        text = f"ambiguous: {first} or {a.named.family}"
        out.append({"text": text, "families": [a.structure.family, a.named.family], "fits": fitted,
                    "gain_beside_percent": 100 * a.gain_beside, "structure_refused": list(a.structure_reasons),
                    "harmonic": None if a.harmonic is None else {"k": a.harmonic[0], "program_period_s": a.harmonic[1]},
                    "was_named": a.was_named, "compensated": False, "residual_unit": unit,
                    "experiment": SPEED_EXPERIMENT if (a.harmonic is not None or a.named.family in POSITION_FAMILIES
                                                       and a.structure.family == TIME_FAMILY) else OTHER_EXPERIMENT})
    return out


def _num(v):
    if isinstance(v, (np.floating, np.integer)):
        return v.item()
    if isinstance(v, float) and not math.isfinite(v):
        return None
    return v


def text_lines(entries: list) -> list:
    """Report lines of :func:`summaries`' entries."""
    lines = []
    for e in entries:
        lines.append(f"AMBIGUOUS: {e['text'][len('ambiguous: '):]}: the record cannot tell them apart "
                     f"({e['families'][1]} adds {e['gain_beside_percent']:.1f} % beside the other); "
                     "named neither, compensated neither")
        for f in e["fits"]:
            ps = ", ".join(f"{k} {v:.4g}" if isinstance(v, float) else f"{k} {v}" for k, v in f["parameters"].items()
                           if not isinstance(v, (list, dict)))
            lines.append(f"  as {f['name']}: {ps} (held-out gain {f['heldout_gain_percent']:.1f} %)")
        lines.append(f"  to tell them apart: {e['experiment']}")
    return lines


#: the other speed of :func:`motorctl.commission.tune.speed_experiment`, as a share of the program's
SPEED_SCALE = 0.7


__all__ = ["Ambiguity", "OTHER_EXPERIMENT", "POSITION_FAMILIES", "SPEED_EXPERIMENT", "TIME_FAMILY",
           "SPEED_SCALE", "harmonic_rivals", "shared_evidence", "summaries", "text_lines"]
