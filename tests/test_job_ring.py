"""``motorctl run`` records into a bounded ring: the rows leave it while the run goes (a child
process on the wall clock, the loop between cycles on the virtual clock), so the log holds
every row in order and the indexes equal those of the whole log, with a ring far shorter
than the run."""

from __future__ import annotations

import numpy as np
import pytest

import motorctl.app.job as job
from motorctl.config import load_config
from motorctl.metrics import tracking_indexes
from motorctl.recorder.runlog import read_log


@pytest.mark.parametrize("clock", ["virtual", "wall"])
def test_a_run_longer_than_its_ring_logs_every_row_and_the_same_indexes(repo, tmp_path, monkeypatch, clock):
    monkeypatch.setattr(job, "RING_S", 0.1)            # 500 rows for a 1.5 s run of 7500
    loaded = load_config(repo / "configs" / "gantry.yaml")
    log = tmp_path / "run.mclog"
    res = job.run_job(loaded, duration_s=1.5, clock=clock, log_path=str(log), realtime_policy="off")
    # two idle cycles and a 0 s approach first; after the program the stop (category 1): both
    # axes stand at 0.4 m, so the row that sees it, then daemon.stop_settle_s held, then 0 V
    n = 7500 + 3 + 1 + round(loaded.cfg.daemon.stop_settle_s / loaded.period_s)
    assert res.cycles == n and res.lost_rows == 0
    rl = read_log(str(log))
    t = rl.col("t")
    assert len(t) == n and np.array_equal(t, np.arange(n) * loaded.period_s)
    assert rl.header["realtime"] != "pending" and rl.header["stop"]     # the end's facts are in
    for a in ("X", "Y"):
        ax = rl.axis(a)
        prog = np.flatnonzero(ax["mode"] == 2)[:7500]  # the indexes: the run's duration of the program's rows
        ref = tracking_indexes(t[prog] - t[prog][0], ax["e"][prog], ax["u"][prog],
                               loaded.axes[a].trajectory.period_s)
        for k, v in ref.items():
            assert res.axes[a][k] == pytest.approx(v, rel=1e-12), (a, k)
    assert res.timing["cycles"] == n


def test_a_run_that_never_cycles_leaves_no_log(repo, tmp_path):
    loaded = load_config(repo / "configs" / "gantry.yaml")
    log = tmp_path / "run.mclog"

    def refuse(*_a, **_k):
        raise OSError("no device")
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(job, "start", refuse)
        with pytest.raises(OSError, match="no device"):
            job.run_job(loaded, duration_s=0.5, clock="wall", log_path=str(log), realtime_policy="off")
    assert not log.exists()
