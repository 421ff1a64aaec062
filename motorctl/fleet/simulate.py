"""A simulated fleet: N machines, D days, K run logs a day, each machine with its own plant
spread and seed, wear injected on some and none on the others.

Every log is a real run log written by motorctl's recorder: the simulated gantry of
:func:`motorctl.ident.synth.gantry_dict` (the rigid plant, one axis, virtual clock) run by
:func:`motorctl.app.job.run_job`, as ``motorctl run`` with the sim driver does. The config
carries the machine's ``machine_id``, so the header names the machine; the header's ``started``
(the wall time of the simulation) is then set to the simulated day through the recorder's own
header update (:meth:`motorctl.recorder.runlog.LogWriter.update_header`), with the injected
truth beside it (``fleet_sim``).

Wear kinds (:data:`WEAR_KINDS`), from ``onset_day`` on (day d counts from 0):

* ``coulomb``: the plant's Coulomb friction × (1 + rate·(d − onset)), rate 0.01/day by default;
* ``cogging``: a cogging force of amplitude ``amplitude_N`` (6 N, period 32 mm) appears;
* ``encoder``: an encoder interpolation error of rate·(d − onset + 1) (0.4 µm/day, signal
  period 2 mm).

Bad days (:data:`BAD_DAY_PARAMETERS`): on one day only, a plant parameter of a machine is
multiplied by a factor (every log of that day; the next day the machine is back), e.g. Coulomb
friction × 1.25 on a cold morning: an outlier the report must not take for wear.
"""

from __future__ import annotations

import datetime as _dt
import json
import os
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

#: the kinds of wear and their default rate or size
WEAR_KINDS = {"coulomb": {"rate_per_day": 0.01}, "cogging": {"amplitude_N": 6.0},
              "encoder": {"rate_m_per_day": 0.4e-6}}
#: the identified parameter each kind of wear shows in (the report's names, motorctl.fleet.jobs)
WEAR_PARAMETER = {"coulomb": "coulomb_N", "cogging": "cogging.amplitudes_N[0]",
                  "encoder": "encoder_interpolation.amplitudes_m[0]"}
#: the plant parameters a bad day may scale, and the default factor of each
#: (:func:`default_bad_days`: Coulomb friction +25 %, viscous friction +25 %, a payload of +10 % mass)
BAD_DAY_PARAMETERS = {"coulomb_N": 1.25, "viscous_N_s_per_m": 1.25, "mass_kg": 1.10}
#: the plant's spread between machines: relative std of mass, viscous and Coulomb friction, and
#: the std of the force offset [N]
SPREAD = {"mass_kg": 0.02, "viscous_N_s_per_m": 0.05, "coulomb_N": 0.05, "offset_N": 0.3}
#: the first simulated day (UTC midnight); logs of a day start at 08:00 and follow each other by
#: an hour
START = "2026-10-01"


def machine_name(i: int) -> str:
    return f"m{i + 1:02d}"


def default_wear(machines: int, days: int) -> list[dict]:
    """The benchmark's wear: the first three machines (as many as there are) get coulomb,
    cogging and encoder wear, in that order, from a third of the way into the period."""
    onset = max(1, days // 3)
    return [{"machine": machine_name(i), "kind": k, "onset_day": onset}
            for i, k in zip(range(machines), WEAR_KINDS)]


def default_bad_days(machines: int, days: int) -> list[dict]:
    """The benchmark's bad days: the clean machines after the three worn ones of
    :func:`default_wear` (m04, m05, m06, as many as there are) get one bad day each, one kind
    of :data:`BAD_DAY_PARAMETERS` each, on days at 1/2, 2/3 and 5/6 of the period (so the
    replay sees each machine back after it)."""
    at = (days // 2, (2 * days) // 3, (5 * days) // 6)
    return [{"machine": machine_name(i), "day": d, "parameter": p, "factor": f}
            for i, d, (p, f) in zip(range(len(WEAR_KINDS), machines), at, BAD_DAY_PARAMETERS.items())]


def check_bad_days(bad_days: list[dict]) -> None:
    """Raises ValueError: a bad day's parameter not one of :data:`BAD_DAY_PARAMETERS`, or its
    factor not a positive number."""
    for b in bad_days:
        if b.get("parameter") not in BAD_DAY_PARAMETERS:
            raise ValueError(f"bad day {b}: unknown parameter {b.get('parameter')!r}; "
                             f"parameters: {', '.join(BAD_DAY_PARAMETERS)}")
        f = b.get("factor", BAD_DAY_PARAMETERS[b["parameter"]])
        if not (isinstance(f, (int, float)) and not isinstance(f, bool) and 0 < f < float("inf")):
            raise ValueError(f"bad day {b}: the factor must be a positive number")


def plant_of(machine: int, day: int, seed: int, wear: list[dict], base: dict,
             bad_days: list[dict] = ()) -> tuple[dict, dict]:
    """The simulated driver's axis section for machine index ``machine`` on ``day``: the base
    plant with the machine's spread (drawn from ``seed`` and the machine), its wear and its bad
    day (``bad_days``: [{"machine", "day", "parameter", "factor"}]). Returns (driver dict, the
    truth: {"wear": [...], "bad_day": [...], "plant": {...}})."""
    rng = np.random.default_rng([int(seed), int(machine)])
    drv = dict(base)
    for key, s in SPREAD.items():
        z = float(rng.standard_normal())
        drv[key] = float(base[key]) + s * z if key == "offset_N" else float(base[key]) * (1.0 + s * z)
    phase = float(rng.uniform(0, 2 * np.pi))
    name = machine_name(machine)
    applied = []
    for w in wear:
        if w["machine"] != name or day < int(w["onset_day"]):
            continue
        k, since = w["kind"], day - int(w["onset_day"])
        if k == "coulomb":
            drv["coulomb_N"] *= 1.0 + float(w.get("rate_per_day", WEAR_KINDS[k]["rate_per_day"])) * since
        elif k == "cogging":
            drv.setdefault("effects", {})
            drv["effects"] = dict(drv["effects"], cogging={
                "amplitudes_N": [float(w.get("amplitude_N", WEAR_KINDS[k]["amplitude_N"]))],
                "period_m": 0.032, "phases_rad": [phase]})
        elif k == "encoder":
            drv["encoder_interpolation_m"] = float(w.get("rate_m_per_day", WEAR_KINDS[k]["rate_m_per_day"])) * (since + 1)
            drv["encoder_signal_period_m"] = 0.002
        else:
            raise ValueError(f"unknown wear kind {k!r}; kinds: {', '.join(WEAR_KINDS)}")
        applied.append({"kind": k, "onset_day": int(w["onset_day"]), "days_since": since})
    bad = []
    for b in bad_days:
        if b["machine"] == name and int(b["day"]) == day:
            f = float(b.get("factor", BAD_DAY_PARAMETERS[b["parameter"]]))
            drv[b["parameter"]] *= f
            bad.append({"parameter": b["parameter"], "factor": f})
    plant = {k: drv[k] for k in SPREAD}
    return drv, {"wear": applied, "bad_day": bad, "plant": plant}


def _one_log(args) -> str:
    path, machine, day, k, seed, wear, bad_days, duration_s, started = args
    from motorctl.app.job import run_job
    from motorctl.config import config_from_dict
    from motorctl.ident.synth import gantry_dict
    from motorctl.recorder.runlog import LogWriter
    d = gantry_dict("X", None, seed=int(seed) * 100003 + machine * 1009 + day * 31 + k, noise_N=1.0)
    d["machine_id"] = machine_name(machine)
    drv, truth = plant_of(machine, day, seed, wear, d["axes"]["X"]["driver"], bad_days)
    d["axes"]["X"]["driver"] = drv
    loaded = config_from_dict(d, f"<fleet {machine_name(machine)} day {day}>")
    run_job(loaded, duration_s=duration_s, clock="virtual", log_path=str(path))
    w, header = LogWriter.reopen(str(path))
    try:
        header["started"] = started
        header["fleet_sim"] = {"machine": machine_name(machine), "day": day, "log": k, **truth}
        if not w.update_header(header):
            raise OSError(f"{path}: the simulated day does not fit in the header's reserve")
    finally:
        w.close()
    return str(path)


def simulate_fleet(out_dir, machines: int = 3, days: int = 4, logs_per_day: int = 1,
                   wear: list[dict] | None = None, duration_s: float = 2.0, seed: int = 0,
                   workers: int = 1, progress=None, bad_days: list[dict] | None = None) -> dict:
    """Write a simulated fleet's run logs: ``out_dir/<machine>/<machine>-d<day>-<k>.mclog``, and
    the truth as ``out_dir/fleet_truth.json``.

    Args:
        out_dir: folder (created). machines, days, logs_per_day: N, D, K (N·D·K logs).
        wear: [{"machine": "m01", "kind": "coulomb"|"cogging"|"encoder", "onset_day": d, and
            optionally the kind's rate or size of :data:`WEAR_KINDS`}] (None:
            :func:`default_wear`; [] none).
        bad_days: [{"machine": "m04", "day": d, "parameter": one of :data:`BAD_DAY_PARAMETERS`,
            "factor": f}]: that machine's plant parameter × f on day d only (None:
            :func:`default_bad_days`; [] none).
        duration_s: program seconds per log (the approach comes on top). seed: the fleet's seed
            (each machine's spread and each log's noise derive from it). workers: processes.
        progress: called with (logs written, total) (None: silent).
    Returns:
        {"logs": [paths], "wear": [...], "bad_days": [...], "machines": [names], "days",
        "logs_per_day", "seed", "start", "duration_s", "parameters"} (also written to
        fleet_truth.json).
    Raises:
        ValueError: a count below 1, an unknown wear kind or bad-day parameter. OSError: a log
        cannot be written.
    """
    if min(machines, days, logs_per_day) < 1:
        raise ValueError("machines, days and logs_per_day must be at least 1")
    wear = default_wear(machines, days) if wear is None else list(wear)
    for w in wear:
        if w["kind"] not in WEAR_KINDS:
            raise ValueError(f"unknown wear kind {w['kind']!r}; kinds: {', '.join(WEAR_KINDS)}")
    bad_days = default_bad_days(machines, days) if bad_days is None else list(bad_days)
    check_bad_days(bad_days)
    out = Path(out_dir)
    t0 = _dt.datetime.fromisoformat(START).replace(tzinfo=_dt.timezone.utc)
    jobs = []
    for m in range(machines):
        (out / machine_name(m)).mkdir(parents=True, exist_ok=True)
        for day in range(days):
            for k in range(logs_per_day):
                started = (t0 + _dt.timedelta(days=day, hours=8 + k)).isoformat(timespec="seconds")
                path = out / machine_name(m) / f"{machine_name(m)}-d{day:03d}-{k}.mclog"
                jobs.append((str(path), m, day, k, seed, wear, bad_days, float(duration_s), started))
    logs = []
    if workers <= 1:
        for j in jobs:
            logs.append(_one_log(j))
            if progress:
                progress(len(logs), len(jobs))
    else:
        with ProcessPoolExecutor(max_workers=int(workers)) as ex:
            for p in ex.map(_one_log, jobs):
                logs.append(p)
                if progress:
                    progress(len(logs), len(jobs))
    truth = {"logs": logs, "wear": wear, "bad_days": bad_days, "machines": [machine_name(m) for m in range(machines)],
             "days": days, "logs_per_day": logs_per_day, "seed": seed, "start": START,
             "duration_s": float(duration_s),
             "parameters": {w["machine"]: WEAR_PARAMETER[w["kind"]] for w in wear}}
    tmp = out / ".fleet_truth.json.tmp"
    tmp.write_text(json.dumps(truth, indent=1))
    os.replace(tmp, out / "fleet_truth.json")
    return truth


__all__ = ["BAD_DAY_PARAMETERS", "SPREAD", "START", "WEAR_KINDS", "WEAR_PARAMETER", "check_bad_days",
           "default_bad_days", "default_wear", "machine_name", "plant_of", "simulate_fleet"]
