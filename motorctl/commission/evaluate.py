"""One evaluation of a controller on an axis's program, for ``motorctl run --json``, autotune's
verification and the benchmarks alike: the run is the main job itself
(:func:`motorctl.app.job.run_job`, what ``motorctl run`` does), its run log is read back and the
commissioning's figures are taken from it (:func:`run_metrics`). The same gains give the same
counts whichever of them asks.
"""

from __future__ import annotations

import copy
import math
import tempfile
from pathlib import Path

import numpy as np
from scipy import signal

from motorctl.app.job import run_job
from motorctl.config import LoadedConfig, config_from_dict
from motorctl.metrics import REST_AFTER_S, rest_mask, runs, u_rest_rms
from motorctl.recorder.runlog import read_log

#: the job's indexes copied into every evaluation (:class:`motorctl.app.job.JobResult`)
JOB_KEYS = ("controller", "e_M_um", "e_F_um", "L2_um", "u_peak_V", "io_errors", "fault")


def oscillation_ratio(u: np.ndarray, rest: np.ndarray, ts: float) -> tuple[float, float]:
    """(peak/median of the Welch PSD of u over its rest segments above 20 Hz, its frequency
    [Hz]); (nan, nan) with no rest segment of 512 samples. u [V], rest: (N,)."""
    psd, f = None, None
    for a, b in zip(*runs(rest)):
        if b - a < 512:
            continue
        f, p = signal.welch(u[a:b], fs=1.0 / ts, nperseg=512, detrend="linear")
        psd = p if psd is None else psd + p
    if psd is None:
        return math.nan, math.nan
    band = f > 20.0
    j = int(np.argmax(np.where(band, psd, -np.inf)))
    return float(psd[j] / np.median(psd[band])), float(f[j])


def e_segment(n: int) -> int:
    """Welch segment of an n-sample error record: at most 1024 samples, and short enough for at
    least 16 averaged segments (50 % overlap), so that the ratio of two spectra is not a ratio
    of two single periodograms (each χ² with 2 degrees of freedom per line, whose ratio exceeds
    100 by chance on a few lines of every run)."""
    seg = 1024
    while seg > 64 and n < 8 * seg:
        seg //= 2
    return seg


def sat_dispersion(sat: np.ndarray) -> float:
    """The dispersion of a saturated-sample count: Σc²/Σc over the run's saturation episodes
    (c: the lengths of the runs of consecutive saturated samples; 1.0 when there is none).
    Saturation comes in episodes, not single samples, so a count varies between windows about
    this many times more than a Poisson count of the same mean: the count / this is nearly
    Poisson (the quasi-Poisson approximation of a compound Poisson count). sat: (N,) bool."""
    starts, ends = runs(sat)
    c = (ends - starts).astype(float)
    return float(np.sum(c * c) / np.sum(c)) if c.size else 1.0


def run_metrics(log_path: str, loaded: LoadedConfig, axis: str, program_only: bool = True) -> dict:
    """The commissioning's figures of one axis from a run log, over its enabled cycles of the
    program (:meth:`motorctl.recorder.runlog.RunLog.program_rows`: not the approach), or over
    every enabled cycle with ``program_only`` False (a circle-test's log: the hold, the G0
    approach, the circles and the dwells).

    Returns:
        {"saturated": samples at |u| = u_lim, "sat_dispersion" (:func:`sat_dispersion`),
        "samples", "u_rest_rms_V" (RMS of u about its mean at rest, :func:`motorctl.metrics.u_rest_rms`; nan with no rest), "period_samples"
        (of one program period), "sat_first" (saturated samples in the first program period),
        "u_rest_first_V" and "u_rest_later_V" (u RMS at rest over the
        first program period and over the others: an adaptive law's first period, θ̂ still
        moving, is noisier; nan with none), "osc_ratio",
        "osc_hz" (:func:`oscillation_ratio`), "e_psd": (f (M,) [Hz], S_ee (M,) [m²/Hz]),
        and with ``program_only`` False "u_peak_V" [V]}.
    Raises:
        LogError: the log cannot be read. KeyError: the axis is not in it.
    """
    log = read_log(log_path)
    a = log.axis(axis)
    on = a["enabled"] > 0.5 if "enabled" in a else np.ones(a["e"].size, bool)
    prog = log.program_rows(axis) if program_only else None
    if prog is not None:
        on &= prog
    e, u = a["e"][on], a["u"][on]
    ts = loaded.period_s
    rest = rest_mask(a["xd_dot"][on], a["xd_ddot"][on], ts, REST_AFTER_S)
    u_lim = loaded.axes[axis].controller.u_lim
    sat = np.abs(u) >= u_lim * (1.0 - 1e-12)
    out = {"saturated": int(np.sum(sat)), "sat_dispersion": sat_dispersion(sat), "samples": int(e.size),
           "u_rest_rms_V": u_rest_rms(u, rest)}
    if not program_only:             # (a job's u_peak_V is its own, over the whole run)
        out["u_peak_V"] = float(np.max(np.abs(u))) if u.size else math.nan
    n1 = int(round(loaded.axes[axis].trajectory.period_s / ts)) or e.size
    out["period_samples"] = n1
    out["sat_first"] = int(np.sum(sat[:n1]))
    out["u_rest_first_V"] = u_rest_rms(u[:n1], rest[:n1])
    out["u_rest_later_V"] = u_rest_rms(u[n1:], rest[n1:]) if e.size > n1 else math.nan
    out["osc_ratio"], out["osc_hz"] = oscillation_ratio(u, rest, ts)
    out["e_psd"] = signal.welch(e, fs=1.0 / ts, nperseg=e_segment(e.size), detrend="linear")
    return out


def job_evaluation(loaded: LoadedConfig, axis: str, law: str | None, seconds: float,
                   clock: str | None = "virtual", log_path: str | None = None) -> dict:
    """``motorctl run`` of ``axis`` alone with controller ``law`` (None: as configured) for
    ``seconds``, and its figures: the job's indexes (:data:`JOB_KEYS`, [µm, V]) and
    :func:`run_metrics`. ``log_path``: keep the run log there (None: a temporary one). The run
    starts as every ``motorctl run`` does: idle reads, the approach from where the axis stands
    (:func:`motorctl.app.build.approach_move`; a bus device keeps its carriage where the previous
    run left it), then the program, under the cycle's protections (:mod:`motorctl.loop.safety`:
    soft limits, following error, I²t, oscillation at rest), whose latched fault is ``fault``.

    Raises:
        OSError, ConfigError, InputError: as :func:`motorctl.app.job.run_job`.
    """
    with tempfile.TemporaryDirectory(prefix="motorctl-eval-") as tmp:
        path = log_path or str(Path(tmp) / "run.mlog")
        res = run_job(loaded, axes=[axis], controller=law, duration_s=seconds, clock=clock,
                      log_path=path)
        out = {k: res.axes[axis].get(k, math.nan) for k in JOB_KEYS}
        out["fault"] = out["fault"] or ""
        out.update(run_metrics(path, loaded, axis))
    return out


def evaluate(raw: dict, source: str, axis: str, law: str, seconds: float, clock: str = "virtual") -> dict:
    """:func:`job_evaluation` of the config dict ``raw`` (``source``: its file, for messages)."""
    return job_evaluation(config_from_dict(copy.deepcopy(raw), source), axis, law, seconds, clock)
