"""``motorctl fleet``: identification over a simulated fleet's run logs on Dask, the Parquet
dataset, idempotence, a corrupt log skipped by name, a worker killed mid-run survived, the
report's alarm on the worn machine only, and the CLI's exit codes (docs/fleet.md).

One small fleet for the whole file: 3 machines × 4 days × 1 log of 3 s, seeded, m02 with a
cogging force from day 2 on (written by 2 local processes while the cluster starts); one
LocalCluster of 2 single-thread worker processes on 127.0.0.1.
"""

from __future__ import annotations

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

from motorctl.cli import main  # noqa: E402
from motorctl.fleet import jobs  # noqa: E402
from motorctl.fleet.report import write_report  # noqa: E402
from motorctl.fleet.simulate import simulate_fleet  # noqa: E402

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
