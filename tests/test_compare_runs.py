"""``motorctl compare-runs BEFORE AFTER``: same program periods, settling excluded the same way."""

from __future__ import annotations

import json

import numpy as np
import pytest

from motorctl.commission.tune import make_log
from motorctl.cli import main
from motorctl.commission.compare import compare_axis, window
from motorctl.metrics import tracking_indexes


def _rec(t0, t1, ts=1e-3, scale=1.0):
    t = np.arange(t0, t1, ts)
    e = scale * 1e-5 * np.sin(2 * np.pi * t) * (1 + 5 * (t < 1.0))   # big transient in period 0
    u = scale * np.cos(2 * np.pi * t)
    return t, e, u


def test_window_whole_common_periods_after_settling():
    tb, ta = np.arange(0, 8, 1e-3), np.arange(0, 12, 1e-3)
    assert window(tb, ta, 4.0, 1) == (4.0, 8.0)
    assert window(tb, ta, 2.0, 1) == (2.0, 8.0)
    assert window(tb, ta, None, 1)[0] == 0.0
    with pytest.raises(ValueError):
        window(np.arange(0, 1, 1e-3), np.arange(2, 3, 1e-3), 1.0, 1)


def test_compare_axis_ratio_and_settling_excluded():
    b = _rec(0, 5)
    a = _rec(0, 7, scale=0.5)        # longer: only the common periods count
    r = compare_axis(b, a, 1.0, 1)
    assert r["window_s"] == [1.0, 5.0]
    # the transient of the first period is out: e_M is the steady amplitude
    assert r["before"]["e_M_um"] == pytest.approx(10.0, rel=1e-3)
    assert r["ratio"]["L2_um"] == pytest.approx(0.5, rel=1e-6)
    assert r["ratio"]["u_peak_V"] == pytest.approx(0.5, rel=1e-6)
    m = (b[0] >= 1.0) & (b[0] < 5.0)
    ref = tracking_indexes(b[0][m], b[1][m], b[2][m], 1.0)
    assert r["before"]["L2_um"] == pytest.approx(ref["L2_um"])
    assert r["before"]["e_F_um"] == pytest.approx(ref["e_F_um"])


def test_l2_split_into_motion_and_standstill():
    """L2[e]'s parts where the desired velocity is not / is zero sum in squares to L2[e]; a
    record without ẋ_d has no split, and neither does a comparison with one."""
    t = np.arange(0.0, 2.0, 1e-3)
    xd_dot = np.where(t < 1.0, 0.5, 0.0)             # moving, then dwelling
    e = np.where(t < 1.0, 3e-6, 1e-6)
    idx = tracking_indexes(t, e, np.zeros_like(t), 0.0, xd_dot)
    assert idx["L2_motion_um"] == pytest.approx(3.0 / np.sqrt(2))
    assert idx["L2_standstill_um"] == pytest.approx(1.0 / np.sqrt(2))
    assert idx["L2_motion_um"] ** 2 + idx["L2_standstill_um"] ** 2 == pytest.approx(idx["L2_um"] ** 2)
    assert "L2_motion_um" not in tracking_indexes(t, e, np.zeros_like(t), 0.0)
    with pytest.raises(ValueError):
        tracking_indexes(t, e, np.zeros_like(t), 0.0, xd_dot[:-1])
    zero = np.zeros_like(t)
    u = np.where(t < 1.0, 1.0, 0.5 + 0.01 * np.sin(2 * np.pi * 50 * t))   # 10 mV peak at rest
    rec = (t, e, u, xd_dot, zero)
    both = compare_axis(rec, (t, 2 * e, u, xd_dot, zero), None, 0)
    assert both["ratio"]["L2_standstill_um"] == pytest.approx(2.0)
    assert both["after"]["L2_motion_um"] == pytest.approx(6.0 / np.sqrt(2))
    # u at rest from 0.3 s after the last move: its RMS about its mean, 10 mV / sqrt(2)
    assert both["before"]["u_rest_rms_V"] == pytest.approx(0.01 / np.sqrt(2), rel=1e-2)
    assert "L2_motion_um" not in compare_axis(rec, (t, e, u, None, None), None, 0)["ratio"]
    moving = (t, e, u, np.full_like(t, 0.5), zero)                       # never at rest
    none = compare_axis(moving, moving, None, 0)
    assert none["before"]["u_rest_rms_V"] is None and none["ratio"]["u_rest_rms_V"] is None


@pytest.fixture(scope="module")
def logs(tmp_path_factory):
    d = tmp_path_factory.mktemp("cr")
    before, after = d / "before.mclog", d / "after.mclog"
    eff = {"spring": {"stiffness_N_per_m": 100.0, "rest_position_m": 0.1}}
    make_log(str(before), eff, duration_s=8.0, seed=1)
    make_log(str(after), eff, duration_s=12.0, seed=1,
             compensation={"spring": {"stiffness_V_per_m": 1.25, "rest_position_m": 0.1}})
    return str(before), str(after)


def test_compare_runs_cli(logs, tmp_path, capsys):
    before, after = logs
    assert main(["compare-runs", before, before, "--json"]) == 0
    same = json.loads(capsys.readouterr().out)["axes"]["X"]
    assert same["window_s"] == [4.0, 8.0]          # period 4 s from the header, first excluded
    assert all(v == pytest.approx(1.0) for v in same["ratio"].values())
    out = tmp_path / "fig"
    assert main(["compare-runs", before, after, "--json", "--out", str(out)]) == 0
    r = json.loads(capsys.readouterr().out)
    x = r["axes"]["X"]
    assert x["window_s"] == [4.0, 8.0]             # aligned by program time: the common periods
    assert x["before"]["cycles"] == x["after"]["cycles"] == 20000
    assert x["ratio"]["L2_um"] < 0.95               # the spring compensated
    for run in ("before", "after"):                 # the logs record x_d's velocity: the split
        assert x[run]["L2_motion_um"] ** 2 + x[run]["L2_standstill_um"] ** 2 == pytest.approx(x[run]["L2_um"] ** 2)
        assert 0.0 < x[run]["u_rest_rms_V"] < 1.0       # the program dwells 1.5 s twice a period
    assert (out / "compare_runs_X.png").stat().st_size > 1000
    assert main(["compare-runs", before, after]) == 0
    text = capsys.readouterr().out
    assert "ratio" in text and "standstill" in text


def test_compare_runs_bad_input(logs, tmp_path):
    before, _ = logs
    assert main(["compare-runs", before, str(tmp_path / "missing.mclog")]) == 2
    assert main(["compare-runs", before, before, "--axis", "Z"]) == 2
    assert main(["compare-runs", before, before, "--period", "-1"]) == 2
