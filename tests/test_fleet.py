"""``motorctl fleet``: identification over a simulated fleet's run logs on Dask, the Parquet
dataset (hive partitions by machine and month, compacted), idempotence, a log cut mid-run not
counted as a second run, a corrupt log skipped by name, a worker killed mid-run survived, the
report's alarm on the worn machine only, robust to single bad days (on rows made here, no
simulation), and the CLI's exit codes (docs/fleet.md).

One small fleet for the whole file: 3 machines × 4 days × 1 log of 3 s, seeded, m02 with a
cogging force from day 2 on (written by 2 local processes while the cluster starts); one
LocalCluster of 2 single-thread worker processes on 127.0.0.1.
"""

from __future__ import annotations

import datetime as dt
import os
import shutil
import signal
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from functools import partial
from pathlib import Path

import pytest

pytest.importorskip("distributed")
pytest.importorskip("pyarrow")

import numpy as np  # noqa: E402

from motorctl.cli import main  # noqa: E402
from motorctl.fleet import jobs  # noqa: E402
from motorctl.fleet.report import analyse, change_point, write_report  # noqa: E402
from motorctl.fleet.simulate import default_bad_days, plant_of, simulate_fleet  # noqa: E402
from motorctl.recorder.runlog import open_log  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
WEAR = [{"machine": "m02", "kind": "cogging", "onset_day": 2}]
#: a test's own bound on one job [s] (the job is a few seconds)
JOB_TIMEOUT_S = 120


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    """The fleet's logs (2 local processes) written while the cluster starts, then identified."""
    import logging

    from distributed import Client, LocalCluster
    d = tmp_path_factory.mktemp("fleet")
    with ThreadPoolExecutor(1) as ex:
        sim = ex.submit(simulate_fleet, d / "logs", machines=3, days=4, logs_per_day=1, wear=WEAR,
                        duration_s=3.0, seed=7, workers=2)
        cluster = LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                               dashboard_address=None, memory_limit="2GiB", silence_logs=logging.ERROR)
        c = Client(cluster)
        truth = sim.result(timeout=JOB_TIMEOUT_S)
    out = d / "out"
    summary = jobs.run_fleet([d / "logs"], out, client=c)
    yield {"dir": d, "logs": d / "logs", "truth": truth, "out": out, "summary": summary}, c
    c.close()
    cluster.close()


@pytest.fixture(scope="module")
def fleet(setup):
    return setup[0]


@pytest.fixture(scope="module")
def client(setup):
    return setup[1]


def test_every_log_is_a_row_with_its_intervals_effects_and_hash(fleet):
    s = fleet["summary"]
    assert (s["logs"], s["identified"], s["skipped"], s["failed"]) == (12, 12, 0, [])
    rows = jobs.read_dataset(fleet["out"]).to_pylist()
    assert len(rows) == 12 and {r["machine"] for r in rows} == {"m01", "m02", "m03"}
    assert {r["axis"] for r in rows} == {"X"}
    assert len({r["log_sha256"] for r in rows}) == 12
    for r in rows:
        assert r["force_unit"] == "N" and r["time"].year == 2026
        for name, _ in jobs.PARAMETERS:
            assert r[f"{name}_lo"] < r[name] < r[f"{name}_hi"], (name, r["log_path"])
        assert 12.0 < r["mass_kg"] < 13.6          # the plant's 12.8 kg ± its spread
        assert isinstance(r["verdict"], str) and r["verdict"]
    # hive partitions machine=/month=, one file each after the job's compaction
    import pyarrow.dataset as ds
    t = ds.dataset(fleet["out"], partitioning="hive").to_table()
    assert t.num_rows == 12 and set(t.column("month").to_pylist()) == {"2026-10"}
    assert sorted(set(t.column("machine").to_pylist())) == ["m01", "m02", "m03"]
    assert sorted(p.parent.relative_to(fleet["out"]).as_posix() for p in jobs.part_files(fleet["out"])) == [
        f"machine={m}/month=2026-10" for m in ("m01", "m02", "m03")]
    worn = sorted((r["time"], r["effects_named"]) for r in rows if r["machine"] == "m02")
    assert ["cogging" in e for _, e in worn] == [False, False, True, True]
    amp = [e["value"] for r in rows if r["machine"] == "m02" for e in r["effects"]
           if e["name"] == "cogging" and e["parameter"] == "amplitudes_N[0]"]
    assert len(amp) == 2 and all(abs(a - 6.0) < 0.5 for a in amp)


def test_a_second_run_skips_every_log_by_its_content_hash(fleet, client):
    before = jobs.part_files(fleet["out"])
    s = jobs.run_fleet([fleet["logs"]], fleet["out"], client=client)
    assert (s["identified"], s["skipped"], s["rows"], s["failed"]) == (0, 12, 0, [])
    assert jobs.part_files(fleet["out"]) == before


def test_a_corrupt_log_is_named_and_skipped_the_others_written(fleet, client, tmp_path):
    src = tmp_path / "logs"
    src.mkdir()
    good = sorted(fleet["logs"].glob("m01/*.mclog"))[0]
    shutil.copy(good, src / "good.mclog")
    (src / "broken.mclog").write_bytes(b"MOTORCTL-RUNLOG\n" + b"\xff" * 40)
    (src / "cut.mclog").write_bytes(good.read_bytes()[:3000])          # the header cut short
    s = jobs.run_fleet([src], tmp_path / "out", client=client)
    assert s["identified"] == 1
    assert sorted(Path(u).name for u, _ in s["failed"]) == ["broken.mclog", "cut.mclog"]
    assert all(Path(u).name in msg for u, msg in s["failed"])
    rows = jobs.read_dataset(tmp_path / "out").to_pylist()
    assert [Path(r["log_path"]).name for r in rows] == ["good.mclog"]


def test_a_log_cut_mid_run_is_one_run_with_the_whole_log_not_a_second(fleet, client, tmp_path):
    whole = sorted(fleet["logs"].glob("m01/*.mclog"))[0]
    data = whole.read_bytes()
    n = open_log(str(whole)).n_rows
    cut, cut2 = tmp_path / "a" / "cut.mclog", tmp_path / "b" / "cut-shorter.mclog"
    for p, share in ((cut, 0.7), (cut2, 0.5)):
        p.parent.mkdir()
        p.write_bytes(data[: int(len(data) * share) + 5])           # mid-record: a partial record at the end
    out = tmp_path / "out"
    first = jobs.run_fleet([cut], out, client=client)            # the copy taken mid-run comes first
    assert (first["identified"], first["cut"], first["failed"]) == (1, [], [])
    (tmp_path / "c").mkdir()
    shutil.copy(whole, tmp_path / "c" / "whole.mclog")
    s = jobs.run_fleet([tmp_path / "c", cut2], out, client=client)
    assert (s["identified"], s["skipped"], s["failed"]) == (1, 1, [])
    assert [(Path(u).name, Path(w).name, m == n) for u, w, _, m in s["cut"]] == [("cut-shorter.mclog", "whole.mclog", True)]
    assert [(Path(u).name, Path(w).name) for u, w, _, _ in s["superseded"]] == [("cut.mclog", "whole.mclog")]
    rows = jobs.read_dataset(out).to_pylist()
    assert [(Path(r["log_path"]).name, r["log_records"]) for r in rows] == [("whole.mclog", n)]
    assert len(jobs.read_dataset(out, counted=False)) == 1 and len(jobs.part_files(out)) == 1   # compacted


def test_a_flat_dataset_from_before_the_partitions_is_read_and_moved_into_them(fleet, tmp_path):
    import pyarrow.dataset as ds
    import pyarrow.parquet as pq
    flat = jobs.read_dataset(fleet["out"]).drop_columns(["run_id", "log_records"])     # as written before
    pq.write_table(flat, tmp_path / "part-20261127T000000-1-00000.parquet")
    assert jobs.read_dataset(tmp_path).column("log_sha256").to_pylist() == flat.column("log_sha256").to_pylist()
    c = jobs.compact(tmp_path)
    assert (c["files_before"], c["files_after"], c["rows_dropped"]) == (1, 3, 0)
    assert ds.dataset(tmp_path, partitioning="hive").to_table().num_rows == 12


def _kill_once(marker, *args):
    """The window task, except that the first call kills its own worker process."""
    if not os.path.exists(marker):
        Path(marker).write_text("killed")
        os.kill(os.getpid(), signal.SIGKILL)
    return jobs.identify_window(*args)


def test_a_worker_killed_mid_task_does_not_lose_the_job(fleet, client, tmp_path):
    import cloudpickle
    cloudpickle.register_pickle_by_value(sys.modules[__name__])     # the workers need not import this file
    try:
        logs = sorted(fleet["logs"].glob("m03/*.mclog"))[:2]
        marker = tmp_path / "killed"
        with ThreadPoolExecutor(1) as ex:          # bounded: a hung job fails the test, not the run
            s = ex.submit(jobs.run_fleet, logs, tmp_path / "out", client=client,
                          task=partial(_kill_once, str(marker))).result(timeout=JOB_TIMEOUT_S)
    finally:
        cloudpickle.unregister_pickle_by_value(sys.modules[__name__])
    assert marker.read_text() == "killed"
    assert (s["identified"], s["failed"]) == (2, [])
    assert len(jobs.read_dataset(tmp_path / "out")) == 2


def test_the_report_flags_the_worn_machine_with_the_right_parameter_and_nothing_else(fleet, tmp_path):
    r = write_report(fleet["out"], tmp_path / "report")
    alarms = [(f["machine"], f["axis"], f["parameter"]) for f in r["alarms"]]
    assert alarms == [("m02", "X", "cogging.amplitudes_N[0]")]
    a = r["alarms"][0]
    assert a["change"]["shape"] == "step" and a["when"].startswith("2026-10-03")
    assert 5.5 < a["change"]["delta"] < 6.5
    assert [Path(p).name for p in a["logs"]] == ["m02-d002-0.mclog", "m02-d003-0.mclog"]
    md = Path(r["summary"]).read_text()
    assert "m02-d002-0.mclog" in md and "cogging.amplitudes_N[0]" in md and "m01 X, m03 X" in md
    assert sorted(Path(p).name for p in r["plots"]) == ["m01.png", "m02.png", "m03.png"]
    assert all(Path(p).read_bytes()[:4] == b"\x89PNG" for p in r["plots"])


def _rows(coulomb, days=12, per_day=2, seed=3):
    """Dataset rows of identified fits without a simulation: {machine: day -> Coulomb factor}
    over 20 N, each parameter with noise of 0.4 % + 0.01 and its interval."""
    rng = np.random.default_rng(seed)
    base = {"mass_kg": 12.8, "viscous_N_s_per_m": 40.0, "coulomb_N": 20.0, "offset_N": 0.1}
    t0 = dt.datetime(2026, 10, 1, 8, tzinfo=dt.timezone.utc)
    out = []
    for m, factor in coulomb.items():
        for d in range(days):
            for k in range(per_day):
                r = {"machine": m, "axis": "X", "time": t0 + dt.timedelta(days=d, hours=k), "force_unit": "N",
                     "log_path": f"/{m}-d{d}-{k}.mclog", "effects": []}
                for name, _ in jobs.PARAMETERS:
                    sig = 0.004 * base[name] + 0.01
                    val = base[name] * (factor(d) if name == "coulomb_N" else 1.0) + sig * rng.standard_normal()
                    r[name], r[f"{name}_lo"], r[f"{name}_hi"] = val, val - 1.96 * sig, val + 1.96 * sig
                out.append(r)
    return out


def test_single_bad_days_raise_no_alarm_while_wear_still_does():
    coulomb = {"m01": lambda d: 1 + 0.02 * max(0, d - 6),          # wear: +2 %/day from day 6
               "m02": lambda d: 1.25 if d == 5 else 1.0,            # a bad day, then back
               "m03": lambda d: 1.25 if d == 9 else 1.0,            # a bad day two days before the end
               "m04": lambda d: 1.25 if d == 11 else 1.0,           # a bad last day: held on one day only
               "m05": lambda d: 1.0, "m06": lambda d: 1.0}
    rows = _rows(coulomb)
    for last in (8, 9, 10, 11):                                     # the report on the logs up to each day
        res = analyse([r for r in rows if (r["time"] - rows[0]["time"]).days <= last])
        alarms = {(f["machine"], f["parameter"]) for f in res["findings"] if f["alarm"]}
        assert alarms <= {("m01", "coulomb_N")}, (last, alarms)
    assert alarms == {("m01", "coulomb_N")}
    by = {f["machine"]: f for f in res["findings"] if f["parameter"] == "coulomb_N"}
    assert by["m01"]["change"]["shape"] == "hinge" and by["m01"]["held"]["recent"]
    assert "held on 1 of 1 days" in by["m04"]["why"]


def test_huber_change_point_is_not_dragged_by_one_bad_day():
    t = np.repeat(np.arange(12.0), 2)
    y = np.full(24, 20.0) + 0.05 * np.random.default_rng(1).standard_normal(24)
    y[10:12] *= 1.25                                                # two readings of one day
    cp = change_point(t, y, np.full(24, 0.05 ** 2))
    assert abs(cp["delta"]) < 0.1 and cp["z"] < 6 and cp["downweighted"] >= 2
    y[16:] += 2.0                                                   # a real step on day 8
    cp = change_point(t, y, np.full(24, 0.05 ** 2))
    assert (cp["shape"], cp["k"]) == ("step", 16) and abs(cp["delta"] - 2.0) < 0.1


def test_a_bad_day_scales_its_parameter_on_that_day_only():
    bad = default_bad_days(machines=8, days=20)
    assert [(b["machine"], b["parameter"], b["day"]) for b in bad] == [
        ("m04", "coulomb_N", 10), ("m05", "viscous_N_s_per_m", 13), ("m06", "mass_kg", 16)]
    base = {"mass_kg": 12.8, "viscous_N_s_per_m": 40.0, "coulomb_N": 20.0, "offset_N": 0.0}
    (on, truth), (after, _) = (plant_of(3, d, 1, [], base, bad) for d in (10, 11))
    assert on["coulomb_N"] == pytest.approx(1.25 * after["coulomb_N"]) and on["mass_kg"] == after["mass_kg"]
    assert truth["bad_day"] == [{"parameter": "coulomb_N", "factor": 1.25}]


def _cli(*words):
    return subprocess.Popen([sys.executable, "-m", "motorctl", "fleet", *map(str, words)], cwd=REPO,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def test_the_cli_identifies_reports_and_refuses_bad_input_in_one_line(fleet, client, tmp_path):
    addr = client.scheduler.address
    procs = {
        "again": _cli("identify", fleet["logs"], "--out", fleet["out"], "--scheduler", addr),
        "report": _cli("report", fleet["out"], "--out", tmp_path / "rep", "--no-plots"),
        "missing": _cli("identify", tmp_path / "nope", "--out", tmp_path / "o1"),
        "bad_url": _cli("identify", fleet["logs"], "--out", tmp_path / "o2", "--scheduler", "http://x"),
    }
    res = {k: (p.communicate(timeout=JOB_TIMEOUT_S), p.returncode) for k, p in procs.items()}
    (out, err), code = res["again"]
    assert code == 0 and "12 skipped" in out, err
    (out, err), code = res["report"]
    assert code == 0 and "ALARM m02 X cogging.amplitudes_N[0]" in out and "1 alarms" in out, err
    for k, needle in (("missing", "nope: no such file or folder"), ("bad_url", "not a scheduler address")):
        (out, err), code = res[k]
        assert code == 2 and err.count("\n") == 1 and needle in err and "Traceback" not in err, (k, err)
    # in-process: an output that is a file, a report without a dataset
    (tmp_path / "file").write_text("x")
    assert main(["fleet", "identify", str(fleet["logs"]), "--out", str(tmp_path / "file")]) == 2
    assert main(["fleet", "report", str(tmp_path)]) == 2
