"""The judge after the selection: a name only where the effect's own values stand on their own.

An effect the selection took is named only when its size is told from zero: at least one of its
family's size parameters (:attr:`~motorctl.effects.base.EffectFamily.size_parameters`: a force,
a stiffness, a mass, a rate) has a 95 % interval (:func:`motorctl.ident.uncertainty.
fit_uncertainty`, the intervals the report states) that excludes 0. An interval that holds 0
never carries a name: the effect is taken out of the model and reported with the reason
(:func:`unsupported`), as the selection's own refusals are; the residual verdict then says what
it leaves ("unexplained", docs/identification.md, "Decision rule").
"""

from __future__ import annotations

from motorctl.effects import family as effect_family


def _intervals(ci95: dict, prefixes: tuple) -> list[tuple[str, float, float]]:
    """(name, lo, hi) of each finite interval of ``ci95`` ({name: [lo, hi] or [[lo, hi], ...]})
    whose name starts with one of ``prefixes``."""
    out = []
    for name, ci in ci95.items():
        if not name.startswith(prefixes):
            continue
        rows = ci if ci and isinstance(ci[0], (list, tuple)) else [ci]
        for i, row in enumerate(rows):
            if row is None or len(row) != 2 or row[0] is None or row[1] is None:
                continue
            label = name if len(rows) == 1 else f"{name}[{i}]"
            out.append((label, float(row[0]), float(row[1])))
    return out


def holds_zero(family: str, ci95: dict) -> str | None:
    """The reason an effect of ``family`` with the 95 % intervals ``ci95`` (the summary's
    ``parameters_ci95``) is not named: every interval of its size parameters holds 0; None when
    one excludes 0, or the family declares no size or the fit gives no interval of one."""
    found = _intervals(ci95, tuple(effect_family(family).size_parameters))
    if not found or any(lo > 0.0 or hi < 0.0 for _, lo, hi in found):
        return None
    said = ", ".join(f"{name} [{lo:.3g}, {hi:.3g}]" for name, lo, hi in found)
    return f"its size is not told from zero: the 95 % interval holds 0 ({said})"


def unsupported(terms: list, effect_intervals: list) -> list[tuple[str, str]]:
    """[(family, reason)] of the ``terms`` whose size is not told from zero (:func:`holds_zero`);
    ``effect_intervals``: per term, {"ci95": {...}} as :func:`~motorctl.ident.uncertainty.
    fit_uncertainty` gives them ("effects")."""
    out = []
    for term, eu in zip(terms, effect_intervals):
        why = holds_zero(term.family, eu.get("ci95", {}))
        if why:
            out.append((term.family, why))
    return out
