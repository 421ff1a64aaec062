"""``motorctl export LOG --mcap OUT``: a run log as MCAP (the ``mcap`` library's writer), read back
with the ``mcap`` library's reader: every record on the cycle channel and on each axis's
channel, the header once, the latched faults as their own channel, JSON per the schemas."""

from __future__ import annotations

import json

import pytest
import yaml

from motorctl.app.job import run_job
from motorctl.cli import main
from motorctl.config import config_from_dict
from motorctl.loop.records import MODE_PROGRAM
from motorctl.recorder.runlog import read_log

import mcap  # noqa: E402,F401 - the test extra installs it (motorctl[all]): missing is an error, never a skip


@pytest.fixture(scope="module")
def faulted_log(tmp_path_factory, gantry_yaml):
    """A 0.5 s run on the rigid plant whose following-error limit (0.1 µm) trips both axes."""
    d = yaml.safe_load(gantry_yaml.read_text())
    for ax in d["axes"].values():
        ax["limits"].update(following_error_m=1e-7, min_following_error_m=1e-7)
    log = tmp_path_factory.mktemp("mcap") / "run.mclog"
    res = run_job(config_from_dict(d, "<tight>"), duration_s=0.5, clock="virtual", log_path=str(log))
    assert all("following error" in r["fault"] for r in res.axes.values()), res.axes
    return log


def test_export_mcap_reads_back_every_row_and_the_faults(faulted_log, tmp_path, capsys):
    from mcap.reader import make_reader
    out = tmp_path / "run.mcap"
    assert main(["export", str(faulted_log), "--mcap", str(out)]) == 0
    rl = read_log(str(faulted_log))
    n = rl.data.shape[0]
    # every row of the log: two idle cycles, a 0 s approach, then the 0.5 s program
    assert (rl.col("X.mode") == MODE_PROGRAM).sum() == 2500 and n == 2503
    assert capsys.readouterr().out.startswith(f"{out}: {n} rows x ")
    by_topic: dict[str, list] = {}
    schemas = {}
    with open(out, "rb") as fh:
        for schema, channel, message in make_reader(fh).iter_messages():
            by_topic.setdefault(channel.topic, []).append((message.log_time, json.loads(message.data)))
            schemas[channel.topic] = (schema.encoding, json.loads(schema.data), channel.message_encoding)
    assert len(by_topic["/motorctl/run"]) == 1 and by_topic["/motorctl/run"][0][1]["axes"] == ["X", "Y"]
    assert len(by_topic["/motorctl/cycle"]) == n
    for a in ("X", "Y"):
        msgs = by_topic[f"/motorctl/axis/{a}"]
        assert len(msgs) == n
        t_ns, last = msgs[-1]
        assert t_ns == round(rl.col("t")[-1] * 1e9)
        assert last["y"] == rl.axis(a)["y"][-1] and last["u"] == rl.axis(a)["u"][-1]
        enc, schema, menc = schemas[f"/motorctl/axis/{a}"]
        assert (enc, menc) == ("jsonschema", "json") and schema["properties"]["y"]["description"] == "[m]"
    faults = [m for _, m in by_topic["/motorctl/faults"]]
    assert {f["axis"] for f in faults} == {"X", "Y"}
    assert all("following error" in f["faults"] for f in faults)


def test_export_mcap_to_a_directory_is_one_line(faulted_log, tmp_path, capsys):
    assert main(["export", str(faulted_log), "--mcap", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("motorctl: error: ") and err.count("\n") == 1
