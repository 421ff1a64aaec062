"""The identification's view of the effect families.

Every family adds columns C(h) to the nominal IDIM regressor, u = Φθ + Cβ (input units, V), with
at most one searched hyper-parameter h (period, Stribeck velocity, change time, delay,
frequency); the force the effect adds to the plant is then F_eff = −A1·Cβ (N). The families,
their columns, searches, checks and parameter names live one module each in ``motorctl.effects``
(table in its docstring); the functions here look them up in the registry
:data:`motorctl.effects.FAMILIES` by name, for the callers that hold a family name.
"""

from __future__ import annotations

import inspect

import numpy as np

from motorctl.effects import FAMILIES, family
from motorctl.effects.base import Signals
from motorctl.effects.periodic import (
    N_HARMONICS,
    peak_periods,
    period_grid,
    spatial_periodogram,
)

__all__ = [
    "FAMILIES",
    "N_HARMONICS",
    "columns",
    "columns_fast",
    "compensation",
    "parameters",
    "peak_periods",
    "period_grid",
    "spatial_periodogram",
]


def columns(name: str, h, p) -> np.ndarray | None:
    """Full-rate columns (N, k) of family ``name`` at hyper-parameter h on the signals of ``p``
    (a prepared record or :class:`~motorctl.effects.base.Signals`); None for an input delay.

    Raises:
        ValueError: unknown family.
    """
    return family(name).columns(h, p)


def columns_fast(name: str, h, p) -> np.ndarray | None:
    """The columns of :func:`columns` evaluated on the *decimated* signals of ``p`` (M, k): a cheap
    approximation for the grid searches (the exact columns are filtered at full rate)."""
    return family(name).columns(h, Signals.decimated(p))


def parameters(name: str, h, beta: np.ndarray, gain: float | None, fs: float, theta=None, p=None,
               fitted=None) -> dict:
    """Physical parameters of a fitted term, names ending in their unit: forces in N when the
    gain A1 [N/V] is known, otherwise in V (force / A1). fs: sample rate [Hz]. theta: the
    nominal θ̂ of the same fit (n_theta,), for a family whose parameters need it (a reading's
    error: β = −θ1·e); None: not given. p: the prepared record
    (:class:`motorctl.ident.idim.Prepared`), for a family whose parameters need more of the
    record than its fit (asymmetric friction: the input held at rest); None: not given. fitted:
    the values' model (:class:`motorctl.ident.values.ValuesModel`: ``terms``, ``final``, ``fits``),
    for a family that fits its parameters again on part of the record (asymmetric friction: the
    samples in motion); None: not given.

    Raises:
        ValueError: unknown family.
    """
    fam = family(name)
    takes = inspect.signature(fam.parameters).parameters
    kw = {}
    if theta is not None and "theta" in takes:
        kw["theta"] = theta
    if p is not None and "p" in takes:
        kw["p"] = p
    if fitted is not None and "fitted" in takes:
        kw["fitted"] = fitted
    return fam.parameters(h, beta, gain, fs, **kw)


def compensation(name: str, h, beta: np.ndarray, signals=None, beta_std=None) -> dict | None:
    """The ``controller.compensation`` YAML entry ``{name: {...}}`` (V units, d̂_eff = −Cβ) of a
    found effect, or None when the family has no compensation term d̂_eff(x_d, ẋ_d, t).
    ``signals`` (:class:`~motorctl.effects.base.Signals` of the record) give the references a
    family takes from the record (spring x_0, position-dependent friction x_ref); ``beta_std``
    (k,): the fit's standard deviations of β, from which an adaptable family writes its
    projection box (β ∓ 3σ, at least the default margin).

    Raises:
        ValueError: unknown family.
    """
    fam = family(name)
    params = inspect.signature(fam.compensation).parameters
    kw = {}
    if "signals" in params:     # (a family written before the references came from the record: none)
        kw["signals"] = signals
    if "beta_std" in params and beta_std is not None:
        kw["beta_std"] = beta_std
    entry = fam.compensation(h, beta, **kw)
    return None if entry is None else {name: entry}
