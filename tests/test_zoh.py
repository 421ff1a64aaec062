"""The zero-order hold of a sampled-data loop is not an effect, for every data source.

A record of a loop that holds u over each period shows, seen from the central-difference
acceleration, an input delay of half a sample. ``identify`` attributes it to the hold (run logs:
known; CSV/MAT: detected) and still finds a real input delay well beyond it.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from motorctl.commission.tune import make_log
from motorctl.cli import main
from motorctl.ident.data import load_record
from motorctl.ident.select import Identifier, is_hold


def _csv(log: str, out) -> str:
    r = load_record(log)
    np.savetxt(out, np.column_stack([r.t, r.y, r.u]), delimiter=",", header="t,y,u", comments="", fmt="%.10g")
    return str(out)


@pytest.fixture(scope="module")
def records(tmp_path_factory):
    d = tmp_path_factory.mktemp("zoh")
    make_log(str(d / "clean.mclog"), None, duration_s=5.0, seed=11)
    make_log(str(d / "delay3.mclog"), {"input_delay_s": 0.0006}, duration_s=5.0, seed=11)   # 3 samples
    return {"clean_log": str(d / "clean.mclog"), "delay3_log": str(d / "delay3.mclog"),
            "clean_csv": _csv(str(d / "clean.mclog"), d / "clean.csv"),
            "delay3_csv": _csv(str(d / "delay3.mclog"), d / "delay3.csv")}


def _identify(path, capsys, *extra):
    assert main(["identify", path, "--json", "--no-closed-loop", *extra]) == 0
    return json.loads(capsys.readouterr().out)


def test_is_hold():
    assert is_hold(0.5) and is_hold(0.4) and is_hold(0.6)
    # EMPS (1 kHz, a real axis): 0.30 sample with sign friction, 0.85 with S_f: not the hold
    assert not is_hold(0.0) and not is_hold(0.3) and not is_hold(0.85) and not is_hold(3.0)


@pytest.mark.parametrize("source", ["clean_csv", "clean_log"])
def test_clean_sampled_data_record_gives_no_effect(records, capsys, source):
    s = _identify(records[source], capsys)
    assert s["effects"] == []
    assert s["filters"]["zoh_delay_samples"] == 0.5
    if source == "clean_csv":
        assert s["filters"]["zoh_source"].startswith("detected")


def test_input_delay_at_the_hold_is_rejected_as_the_hold(records):
    """Told there is no hold (--zoh-delay 0), the half sample is still not reported as a delay."""
    idf = Identifier(load_record(records["clean_csv"]), zoh_delay=0.0).run()
    assert all(t.family != "input_delay" for t in idf.terms)
    delay = [c for c in idf.steps[0] if c.term.family == "input_delay"][0]
    assert not delay.ok
    assert any("zero-order hold" in r for r in delay.reasons)


@pytest.mark.parametrize("source", ["delay3_csv", "delay3_log"])
def test_three_sample_delay_is_found(records, capsys, source):
    s = _identify(records[source], capsys)
    found = [e for e in s["effects"] if e["name"] == "input_delay"]
    assert found, s["candidates"][0]
    total = found[0]["parameters"]["delay_samples"] + s["filters"]["zoh_delay_samples"]
    # the plant delays u by 3 samples after the hold (3.5 in all); reported within one sample
    assert abs(found[0]["parameters"]["delay_samples"] - 3.0) <= 1.0
    assert abs(total - 3.5) <= 0.5
