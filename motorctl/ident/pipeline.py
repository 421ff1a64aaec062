"""The identification pipeline of ``motorctl identify`` and ``motorctl tune``, on a loaded
record: the stages run in order by a thin driver (:class:`~motorctl.ident.select.Identifier`,
:func:`identify_record`),
the summary (:func:`~motorctl.ident.explain.summarise`, the JSON of ``identify``), the
validation on a second record (:func:`validation`); what a fit gives the controller
(:mod:`motorctl.ident.tuned`) and the text report (:mod:`motorctl.ident.explain`) are
re-exported here.

The stages (docs/identification.md, "The stages in the code"), each a module with one job,
the records between them frozen dataclasses (:mod:`motorctl.ident.records`)::

    Record ─ fit.start ─► Fits (Setup + Structure) ─ selection.run ─► Selection ─ refine.joint_refit ─►
    Selection + Refined ─ judge (values_of, confirm_values, travel_shared, drop_unsupported) ─►
    Selection + ValuesModel ─ explain.summarise ─► summary (dict) ─ explain.text_report ─► text

No run happens here (the closed-loop before/after is :class:`motorctl.commission.closed_loop.ClosedLoop`),
and nothing here parses arguments (the CLI is :mod:`motorctl.cli.identify`).
"""

from __future__ import annotations

import contextlib
import math

import numpy as np
from threadpoolctl import threadpool_limits

from motorctl.ident.explain import (SATURATION_NOTE_SHARE, SIM_WINDOW_S, add_refused, fig,  # noqa: F401
                                    saturation_note, summarise, text_report)
from motorctl.ident.fit import start
from motorctl.ident.select import Identifier
from motorctl.ident.tuned import (BOX_MARGIN, compensation_from_fit, set_theta0, tuned_config,  # noqa: F401
                                  values_and_parameters, values_from, write_tuned_config)
from motorctl.recorder.runlog import LogError


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
