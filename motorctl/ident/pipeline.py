"""The identification pipeline of ``motorctl identify`` and ``motorctl tune``, on a loaded
record: the stages run in order by a thin driver (:class:`Identifier`, :func:`identify_record`),
the summary (:func:`~motorctl.ident.explain.summarise`, the JSON of ``identify``), the
validation on a second record (:func:`validation`); what a fit gives the controller
(:mod:`motorctl.ident.tuned`) and the text report (:mod:`motorctl.ident.explain`) are
re-exported here.

The stages (docs/identification.md, "The stages in the code"), each a module with one job,
the records between them frozen dataclasses (:mod:`motorctl.ident.records`)::

    Record ─ fit.start ─► Fits (Setup + Structure) ─ select.run ─► Selection ─ refine.joint_refit ─►
    Selection + Refined ─ judge (values_of, confirm_values, travel_shared, drop_unsupported) ─►
    Selection + ValuesModel ─ explain.summarise ─► summary (dict) ─ explain.text_report ─► text

No run happens here (the closed-loop before/after is :class:`motorctl.commission.closed_loop.ClosedLoop`),
and nothing here parses arguments (the CLI is :mod:`motorctl.cli.identify`).
"""

from __future__ import annotations

import contextlib
import functools
import math

import numpy as np
from threadpoolctl import threadpool_limits

from motorctl.ident import judge as after
from motorctl.ident import probes, prune, refine, select
from motorctl.ident.checks import Judge
from motorctl.ident.columns import thrust_shape
from motorctl.ident.explain import (SATURATION_NOTE_SHARE, SIM_WINDOW_S, add_refused, fig,  # noqa: F401
                                    saturation_note, summarise, text_report)
from motorctl.ident.fit import start
from motorctl.ident.records import Refined
from motorctl.ident.rules import MAX_EFFECTS
from motorctl.ident.tuned import (BOX_MARGIN, compensation_from_fit, set_theta0, tuned_config,  # noqa: F401
                                  values_and_parameters, values_from, write_tuned_config)
from motorctl.recorder.runlog import LogError


def _read(*path: str) -> property:
    """A read-only attribute of the driver: the record at ``path`` (attribute names) from it."""
    def get(self):
        out = self
        for name in path:
            out = getattr(out, name)
        return out
    return property(get)


class Identifier:
    """The driver of the identification's stages on one record: it holds the records each stage
    returns and hands them to the next; all the work is the stages'.

    Args (the record opened by :func:`motorctl.ident.fit.start`):
        rec: a checked :class:`~motorctl.ident.data.Record`.
        n_theta: 4 or 6 to force the nominal structure (default: chosen from the input range).
        friction: 'sf' (the paper's S_f(ẋ) = (2/π)atan(900ẋ)) or 'sign' (the EMPS reference
            model's sign(ẋ)) for the Coulomb column.
        fq, nd: position cut-off [Hz] and decimation factor (default: idim.default_filters).
        families: effect family names to search (default: all of the registry, in its order).
        seed: the draw of the held-out folds' blocks.
        zoh_delay: delay [samples] between the logged input and the acceleration it causes
            (default 0.5 for motorctl run logs, whose input is a zero-order hold; for other
            files found in the data).
        on_nominal: called with the nominal θ̂ (n_theta,) each time the nominal model is
            fitted, before the effect search starts (e.g. to start a closed-loop run with it
            meanwhile); None: nothing.
        current_loop: model the amplifier's current loop the run log's config declares in every
            input column (off, default: the loop is fitted as an input delay, and when Stribeck
            is selected its values are taken on the loop's model, :func:`motorctl.ident.values.refit`).

    Raises:
        ValueError: unknown friction shape or effect family.

    Attributes:
        fits: the fit stage at the current structure (:class:`~motorctl.ident.fit.Fits`).
        judge: the judge on it (:class:`~motorctl.ident.checks.Judge`). selection: the
            :class:`~motorctl.ident.records.Selection` (None before :meth:`run`). refined: the
            joint refit's :class:`~motorctl.ident.records.Refined`. values: the values' model
            (:class:`~motorctl.ident.values.ValuesModel`, None before :meth:`find_values`).

    The fit stage's methods (``evaluate``, ``coef_split``, ``term``, ``design``, ...) and the
    judge's (``verdict``, ``implausible_in``, ...) are reached through it as before.
    """

    def __init__(self, rec, n_theta: int | None = None, friction: str = "sf", fq: float | None = None,
                 nd: int | None = None, families=None, seed: int = 0, zoh_delay: float | None = None,
                 on_nominal=None, current_loop: bool = False):
        self.fits = start(rec, n_theta=n_theta, friction=friction, fq=fq, nd=nd, families=families, seed=seed,
                          zoh_delay=zoh_delay, current_loop=current_loop)
        self.judge = Judge(self.fits)
        self.on_nominal = on_nominal
        self.selection = None
        self.refined = Refined()
        self.values = None

    # the stages, in order
    def run(self, max_effects: int = MAX_EFFECTS) -> "Identifier":
        """Stage *select* (:func:`motorctl.ident.select.run`). Returns self."""
        self.selection, self.judge = select.run(self.fits, max_effects, self.on_nominal)
        self.fits = self.judge.fits
        return self

    def joint_refit(self) -> "Identifier":
        """The searched parameters refitted jointly (:func:`motorctl.ident.refine.joint_refit`)."""
        self.selection, self.refined = refine.joint_refit(self.judge, self.selection)
        return self

    def refit(self):
        """The values' model a refit gives (:func:`motorctl.ident.values.refit`), or None."""
        from motorctl.ident.values import refit
        return refit(self.judge, self.selection)

    def find_values(self) -> "Identifier":
        """The values' model (:func:`motorctl.ident.judge.values_of`)."""
        self.values = after.values_of(self.judge, self.selection)
        return self

    def confirm_values(self) -> "Identifier":
        """:func:`motorctl.ident.judge.confirm_values`."""
        self.selection, self.values = after.confirm_values(self.judge, self.selection, self._values())
        return self

    def travel_shared(self) -> "Identifier":
        """:func:`motorctl.ident.judge.travel_shared`."""
        self.selection, self.values = after.travel_shared(self.judge, self.selection, self._values())
        return self

    def drop_unsupported(self) -> "Identifier":
        """:func:`motorctl.ident.judge.drop_unsupported`."""
        self.selection, self.values = after.drop_unsupported(self.judge, self.selection, self._values(),
                                                             self.rec.gain)
        return self

    def drop_after(self, dropped: list) -> "Identifier":
        """:func:`motorctl.ident.judge.drop_after` of ``dropped`` ([(family, reason)])."""
        self.selection, self.values = after.drop_after(self.judge, self.selection, dropped)
        return self

    def _values(self):
        """The values' model: the one :meth:`find_values` set, else the selection's own."""
        from motorctl.ident.values import of_selection
        return self.values if self.values is not None else of_selection(self.judge, self.selection)

    # what the records hold, read through the driver (the fit stage's own, rec, setup,
    # structure, p, n_theta, zoh, ..., through __getattr__)
    n_theta_reason, zoh_source = (_read("fits", "structure", n) for n in ("n_theta_reason", "zoh_source"))
    u_reach = _read("fits", "setup", "u_reach")
    nominal, steps, accepted, eliminated, researched, ambiguous, verdict_step = (
        _read("selection", n) for n in ("nominal", "steps", "accepted", "eliminated", "researched", "ambiguous",
                                        "verdict_step"))
    joint_moved, harmonics_cut = _read("refined", "moved"), _read("refined", "harmonics_cut")

    @property
    def families(self) -> list:
        return list(self.fits.families)

    @property
    def terms(self) -> list:
        return list(self.selection.terms)

    @terms.setter
    def terms(self, terms) -> None:
        from dataclasses import replace
        self.selection = replace(self.selection, terms=tuple(terms))

    @property
    def final(self):
        return self.selection.final

    @final.setter
    def final(self, ev) -> None:
        from dataclasses import replace
        self.selection = replace(self.selection, final=ev)

    @property
    def refitted(self):
        """The values' model when it is a refit's (else None)."""
        return self.values if self.values is not None and self.values.refitted else None

    @refitted.setter
    def refitted(self, values) -> None:
        self.values = values

    @functools.cached_property
    def saturation(self) -> dict | None:
        """Where the input sits at its limit (:func:`~motorctl.ident.idim.input_saturation`;
        None: nowhere): reported, the fit unchanged."""
        from motorctl.ident.idim import input_saturation
        return input_saturation(self.p.u, self.p.fs, self.rec.u_limit)

    def thrust_shape(self, u: np.ndarray, theta: np.ndarray) -> np.ndarray | None:
        """:func:`motorctl.ident.columns.thrust_shape` at this record's structure."""
        return thrust_shape(self.n_theta, self.u_reach, u, theta)

    explained_shares = probes.explained_shares

    def _doubt(self, base, accepted, current, last_step):
        """:func:`motorctl.ident.prune.doubt` with this identifier's judge."""
        return prune.doubt(self.judge, list(base), list(accepted), current, last_step)

    def _simplify(self, base, accepted, current):
        """:func:`motorctl.ident.prune.simplify` with this identifier's judge."""
        return prune.simplify(self.judge, list(base), list(accepted), current)

    def __getattr__(self, name: str):
        # the fit stage's read-outs and the judge's, as the identifier offered them before
        if name.startswith("__") or name in ("fits", "judge"):
            raise AttributeError(name)
        for part in (self.fits, self.judge):
            try:
                return getattr(part, name)
            except AttributeError:
                pass
        raise AttributeError(f"{type(self).__name__!s} has no attribute {name!r}")


def validation(idf: Identifier, rec2) -> dict:
    """The models fitted on DATA judged on a second record ``rec2`` (a record of
    :func:`motorctl.ident.data.load_record`, e.g. EMPS's ``DATA_EMPS_PULSES.mat``), nothing
    fitted again there: the nominal model and the augmented one (the found effects).

    Returns:
        ``{"source", "residual_rms_before", "residual_rms_after"}`` (N with a gain, else V: the
        residual of the force equation on rec2's decimated samples) and
        ``relative_error_percent_before`` / ``_after``: 100·‖residual‖/‖A1 u‖ on the same
        samples, the cross-test validation's "relative error" of the EMPS description
        (Script_IDIM_LS_CTV.m: 100·norm(error)/norm(force), decimated).
    Raises:
        ValueError, numpy.linalg.LinAlgError: rec2 too short or degenerate for the filters.
    """
    other = start(rec2, n_theta=idf.n_theta, friction=idf.friction, zoh_delay=idf.zoh,
                  current_loop=idf.current_loop)
    g = idf.rec.gain or 1.0
    r0 = idf.fits.residual_on(other, [], idf.nominal)
    r1 = idf.fits.residual_on(other, idf.terms, idf.final)
    _, target = other.design([])
    ref = float(np.linalg.norm(target)) or math.nan
    return {"source": rec2.source, "residual_rms_before": g * float(np.sqrt(np.mean(r0 ** 2))),
            "residual_rms_after": g * float(np.sqrt(np.mean(r1 ** 2))),
            "relative_error_percent_before": 100 * float(np.linalg.norm(r0)) / ref,
            "relative_error_percent_after": 100 * float(np.linalg.norm(r1)) / ref}


def identify_record(rec, n_theta: int | None = None, friction: str = "sf",
                    zoh_delay: float | None = None, after_fit=None,
                    on_nominal=None, current_loop: bool = False) -> tuple[Identifier, dict]:
    """Fit the model to a loaded record, trace the residual to effects, and summarise.

    Args:
        rec: a record of :func:`motorctl.ident.data.load_record`. n_theta: 4, 6 or None (chosen
            from the input range). friction: 'sf' or 'sign'. zoh_delay: input delay of the
            logged input [samples] (None: 0.5 for run logs, detected for CSV/MAT).
        after_fit: called with the identifier once the fit is checked, before the summary
            (e.g. to start the closed-loop runs meanwhile); None: nothing.
        on_nominal: called with the nominal θ̂ (n_theta,) each time the nominal model is fitted,
            before the effect search (:class:`Identifier`); None: nothing.
        current_loop: model the current loop the run log's config declares in the nominal
            fit (:class:`Identifier`; off: fitted as an input delay).
    Returns:
        (the identifier after its run, the summary of :func:`summarise`; no validation or
        closed loop yet).
    Raises:
        LogError: the fit fails on the record or is physically meaningless (θ1 ≤ 0, simulated
        position fit below 0 %), with the likely cause.
    """
    # numpy's overflow/invalid warnings would add lines to stderr on a degenerate record; the
    # results are checked for finiteness and physical meaning instead (check_physical). BLAS on
    # one thread: the effect search runs its own threads (select.SEARCH_THREADS), and OpenBLAS's
    # threads inside their many small (M, k) products only contend with them for the cores
    # (benchmarks/bench_ident.py: run() 1.81 -> 1.69 s wall, 3.04 -> 2.74 s CPU)
    @contextlib.contextmanager
    def quiet():
        with np.errstate(all="ignore"), threadpool_limits(limits=1, user_api="blas"):
            yield

    try:
        with quiet():
            # select; the selected effects' searched parameters taken again jointly, each with
            # all the others in the model; the values' model (a refit on the declared current
            # loop's, the stick state's or a mode's model when needed); then the judge after the
            # selection: effects the more exact model does not confirm, a lost motion beside the
            # travel's force of a play, an effect whose size's 95 % interval holds 0
            idf = (Identifier(rec, n_theta=n_theta, friction=friction, zoh_delay=zoh_delay,
                              on_nominal=on_nominal, current_loop=current_loop)
                   .run().joint_refit().find_values().confirm_values().travel_shared().drop_unsupported())
    except (np.linalg.LinAlgError, FloatingPointError, ValueError) as exc:
        if isinstance(exc, LogError):
            raise
        msg = " ".join(str(exc).split())[:120]
        raise LogError(f"{rec.source}: the fit failed on this record ({type(exc).__name__}: {msg}); "
                       "check the units (t s, y m, u V) and that the axis moves with a varying input") from None
    # θ1 is judged on the model the user gets: with the found effects (a strong spring makes the
    # nominal fit's θ1 negative while the augmented one is right)
    check_physical(rec, max(idf.nominal.fit.coef[0], idf.final.fit.coef[0]), None)
    if after_fit is not None:
        after_fit(idf)
    with quiet():
        s = summarise(idf)
    check_physical(rec, max(s["nominal"]["theta"][0], s["augmented"]["theta"][0]),
                   (s["nominal"].get("simulation_fit_percent"), s["augmented"].get("simulation_fit_percent")))
    return idf, s


_CAUSES = ("check the sign of u (a positive u must push y positive), the units of y (m) and u "
           "(V, or N without --gain) and the time base (t in s)")


def check_physical(rec, theta1, sim_fits) -> None:
    """Refuse (LogError, exit 2) a fit without physical meaning: θ1 = M/A1 <= 0 (a negative or
    zero mass; the caller passes the larger of the nominal and the augmented fit's), or a
    simulated position fit below 0 % for both the nominal and the augmented model (worse than
    a constant). ``sim_fits``: (nominal %, augmented %) or None (not yet)."""
    th1 = float(theta1)
    if not (math.isfinite(th1) and th1 > 0):
        raise LogError(f"{rec.source}: the fit gives theta1 = {th1:.4g} <= 0 (a mass that is not positive), "
                       f"so the record does not follow the model; {_CAUSES}")
    if sim_fits is None:
        return
    fits = [float(f) for f in sim_fits if f is not None]
    if fits and not any(math.isfinite(f) for f in fits):
        raise LogError(f"{rec.source}: the fitted model's simulated position diverges (fit % not finite), "
                       f"so the record does not follow the model; {_CAUSES}")
    fits = [f for f in fits if math.isfinite(f)]
    if fits and max(fits) < 0:
        raise LogError(f"{rec.source}: the fitted model simulates the position worse than a constant "
                       f"(simulated position fit {max(fits):.4g} % < 0 %); {_CAUSES}")


def json_default(o):
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(type(o).__name__)


__all__ = ["BOX_MARGIN", "Identifier", "SATURATION_NOTE_SHARE", "SIM_WINDOW_S", "add_refused", "check_physical",
           "compensation_from_fit", "fig", "identify_record", "json_default", "saturation_note", "set_theta0",
           "summarise", "text_report", "tuned_config", "validation", "values_and_parameters", "values_from",
           "write_tuned_config"]
