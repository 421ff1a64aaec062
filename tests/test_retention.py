"""Run-log retention: the daemon's run is a numbered set of segments kept within a byte budget
and an age; event logs outlive routine rows; a reader (and ``motorctl export``) reads the kept
segments as one run, in order, without a gap inside a segment; the figures are in ``status``."""

from __future__ import annotations

import csv
import os
import subprocess
import sys
import time

import numpy as np
import pytest
import yaml
from test_daemon_helpers import ctl, running_daemon, status, wait_for

from motorctl.config import ConfigError, config_from_dict
from motorctl.loop.records import columns_for
from motorctl.loop.timebase import Timebase
from motorctl.recorder.export import mat_name
from motorctl.recorder.flight import Drainer, SharedRing
from motorctl.recorder.runlog import read_log
from motorctl.recorder.segments import Retention, SegmentWriter, open_run, segment_path

TS = 1.0 / 5000
RUN = "motorctl-20240101T000000-1.mlog"


def _dir_bytes(d) -> int:
    return sum(e.stat().st_size for e in os.scandir(d))


def _check_segments(run):
    """Every kept segment: rows are its cycles first_cycle, first_cycle + 1, ... (no gap)."""
    for s in run.segments:
        t = np.concatenate(list(s.chunks(1000)))[:, 0] if s.n_rows else np.empty(0)
        k0 = s.header["segment"]["first_cycle"]
        assert np.array_equal(t, (k0 + np.arange(s.n_rows)) * TS), s.path
    idx = [s.header["segment"]["index"] for s in run.segments]
    assert idx == sorted(idx) and len(set(idx)) == len(idx), "segments in order"


def test_rotation_keeps_the_budget_and_every_event_log_and_segments_have_no_gap(tmp_path):
    cols = columns_for(["X"])
    ring = SharedRing(2000, len(cols), 1)
    hdr = {"columns": cols, "axes": ["X"], "period_s": TS}
    seg, budget = 64 << 10, 512 << 10
    ret = Retention(str(tmp_path), budget, seg, 1e9, row_bytes_per_s=8 * len(cols) / TS)
    w = SegmentWriter(str(tmp_path / RUN), hdr, reserve=4096, segment_bytes=seg, retention=ret)
    dr = Drainer(ring, w, hdr, ["X"], Timebase(TS), flush_s=0.1, event_before_s=0.02,
                 event_after_s=0.01)
    ci = {c: j for j, c in enumerate(cols)}
    k, peak = 0, 0
    for step in range(60):
        for _ in range(500):
            r = ring.rows[k % ring.capacity]
            r[:] = 0.0
            r[ci["t"]] = k * TS
            r[ci["X.fault_bits"]] = 1.0 if 4000 <= k % 10000 < 6000 else 0.0   # an event every 2 s
            ring.publish(k + 1)
            k += 1
        dr.poll()
        peak = max(peak, _dir_bytes(tmp_path))
        dr.cut_events()
        dr.maybe_flush(force=True)
        peak = max(peak, _dir_bytes(tmp_path))
    dr.finish()
    dr.close()
    assert w.index > 20 and ret.dropped_segments > 10, "it rotated and dropped old segments"
    assert peak <= budget and _dir_bytes(tmp_path) <= budget, (peak, budget)
    assert len(dr.events) == 3 and ret.dropped_events == 0
    for e in dr.events:
        ev = read_log(e["path"])                       # every event log survived ...
        assert ev.header["event"]["cycle"] == e["cycle"]
    run = open_run(str(tmp_path / RUN))
    first_kept = run.segments[0].header["segment"]["first_cycle"]
    assert dr.events[0]["cycle"] < first_kept, "... longer than the routine rows around it"
    _check_segments(run)
    assert run.gaps == [] and run.n_rows == k - first_kept, "the newest segments are kept"
    assert run.segments[-1].header["segment"]["index"] == w.index


def _segmented_run(tmp_path, n_seg=4, rows=700, gap_after=None):
    cols = columns_for(["X", "Y"])
    hdr = {"columns": cols, "axes": ["X", "Y"], "period_s": TS}
    w = SegmentWriter(str(tmp_path / RUN), hdr, reserve=1024, segment_bytes=(1 << 20))
    rng = np.random.default_rng(1)
    parts, k = [], 0
    for s in range(n_seg):
        block = rng.standard_normal((rows, len(cols)))
        block[:, 0] = (k + np.arange(rows)) * TS
        w.append(block, k)
        parts.append(block)
        k += rows + (50 if gap_after == s else 0)
        w.rotate()
    return cols, np.concatenate(parts)


@pytest.mark.parametrize("which", ["run name", "a segment"])
def test_export_of_a_multi_segment_run_equals_the_concatenation(tmp_path, which):
    from scipy.io import loadmat
    cols, whole = _segmented_run(tmp_path)
    src = tmp_path / RUN if which == "run name" else segment_path(str(tmp_path / RUN), 3)
    r = ctl(None, "export", src, "--csv", tmp_path / "o.csv")
    assert r.returncode == 0, r.stderr
    assert f"{whole.shape[0]} rows x {len(cols)} columns (4 segments)" in r.stdout
    with open(tmp_path / "o.csv") as fh:
        rows = list(csv.reader(fh))
    assert rows[0] == cols
    assert np.array_equal(np.array(rows[1:], dtype=float), whole), "bit-exact, in order"
    r = ctl(None, "export", src, "--mat", tmp_path / "o.mat")
    assert r.returncode == 0, r.stderr
    m = loadmat(str(tmp_path / "o.mat"))
    assert np.array_equal(m["data"], whole)
    for j, c in enumerate(cols):
        assert np.array_equal(m[mat_name(c)].ravel(), whole[:, j])


def test_export_names_the_rows_missing_between_segments(tmp_path):
    cols, whole = _segmented_run(tmp_path, n_seg=3, gap_after=0)
    os.unlink(segment_path(str(tmp_path / RUN), 1))       # dropped by retention
    r = ctl(None, "export", tmp_path / RUN, "--csv", tmp_path / "o.csv")
    assert r.returncode == 0, r.stderr
    assert f"{2 * 700} rows" in r.stdout and "2 segments" in r.stdout
    # a gap between kept segments is named
    (tmp_path / "g").mkdir()
    _segmented_run(tmp_path / "g", n_seg=3, gap_after=1)
    r = ctl(None, "export", tmp_path / "g" / RUN, "--csv", tmp_path / "g.csv")
    assert r.returncode == 0 and "50 rows missing between segments (first at cycle 1400)" in r.stdout, r.stdout


def test_age_limit_event_share_and_live_runs(tmp_path):
    """Routine segments older than max_age go; event logs stay (until the budget needs them:
    overrun event logs first); the last segment of a live run is never deleted; other files
    are never touched."""
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    old = time.time() - 3600
    names = {
        f"motorctl-20240101T000000-{dead.pid}.0001.mlog": old,     # a finished run, old
        f"motorctl-20240101T000000-{dead.pid}.0002.mlog": old,
        f"motorctl-20240101T000000-{dead.pid}.event01-fault-X.mlog": old,
        f"motorctl-20240102T000000-{os.getpid()}.0001.mlog": old,   # a live run: old segment ...
        f"motorctl-20240102T000000-{os.getpid()}.0002.mlog": old,   # ... and the one it writes
        "motorctl-notes.txt": old, "other.mlog": old,
    }
    for n, t in names.items():
        (tmp_path / n).write_bytes(b"x" * 1000)
        os.utime(tmp_path / n, (t, t))
    ret = Retention(str(tmp_path), budget_bytes=1 << 20, segment_bytes=1 << 18, max_age_s=600.0)
    ret.prune()
    left = sorted(os.listdir(tmp_path))
    assert left == sorted([f"motorctl-20240101T000000-{dead.pid}.event01-fault-X.mlog",
                           f"motorctl-20240102T000000-{os.getpid()}.0002.mlog",
                           "motorctl-notes.txt", "other.mlog"])
    assert ret.dropped_segments == 3 and ret.kept_events == 1
    # over the budget with event logs beyond the budget less two segments (512 KiB): the
    # oldest event logs go first, before the (newer) routine segment
    routine = tmp_path / f"motorctl-20240104T000000-{dead.pid}.0001.mlog"
    routine.write_bytes(b"x" * (200 << 10))
    for i in range(8):
        p = tmp_path / f"motorctl-20240103T000000-{dead.pid}.event{i + 1:02d}-overrun.mlog"
        p.write_bytes(b"x" * (100 << 10))
        os.utime(p, (old + i, old + i))
    ret.prune()
    evs = sorted(n for n in os.listdir(tmp_path) if "20240103" in n)
    # 1026000 bytes closed + one 256 KiB segment: 239568 bytes over; the three oldest overrun
    # event logs make the room (overrun event logs go before the older fault event log)
    assert len(evs) == 5 and evs[0].endswith("event04-overrun.mlog"), evs
    assert routine.exists() and ret.dropped_events == 3
    assert (tmp_path / f"motorctl-20240101T000000-{dead.pid}.event01-fault-X.mlog").exists()
    assert _dir_bytes(tmp_path) + (1 << 18) <= 1 << 20, "room for one segment in the budget"


def test_retention_keys_are_bounded(gantry_yaml):
    base = yaml.safe_load(gantry_yaml.read_text())
    assert config_from_dict(base).cfg.daemon.log_budget_bytes >= 2 * base["daemon"]["log_segment_bytes"]
    for key, value, words in [("log_segment_bytes", 1000, "greater than or equal to 1048576"),
                              ("log_budget_bytes", 3 << 28, "at least 2 x log_segment_bytes"),
                              ("log_max_age_s", 1.0, "greater than or equal to 60"),
                              ("log_segment_s", 0.0, "greater than or equal to 1")]:
        d = yaml.safe_load(gantry_yaml.read_text())
        d["daemon"][key] = value
        with pytest.raises(ConfigError, match=f"daemon.{key}: .*{words}"):
            config_from_dict(d, "g.yaml")


def test_daemon_rotates_within_its_budget_keeps_every_event_and_reports_it(tmp_path):
    """Segments of 1 MiB against a budget of 8 MiB: the oldest routine segments go, the three
    fault event logs stay. Their window is 0.3 s here (0.54 MB each): at the shipped 3 s (5.4 MB
    each) two could not both fit in what the budget leaves beside two segments, and the test had
    passed only where the faults came close enough for one log to take the next (1 kept in a CI
    run)."""
    seg, budget = 1 << 20, 8 << 20
    with running_daemon(tmp_path, extra_daemon={"log_segment_bytes": seg, "log_budget_bytes": budget,
                                                "event_before_s": 0.2, "event_after_s": 0.1}) as d:
        sock, logs = d.sock, tmp_path / "logs"
        peak = 0
        for _ in range(3):                           # three fault event logs on X
            assert ctl(sock, "start", "X").returncode == 0
            wait_for(lambda: status(sock)["axes"]["X"]["phase"] == "tracking", 20, "X tracking")
            assert ctl(sock, "inject", "X", "nan").returncode == 0
            wait_for(lambda: status(sock)["axes"]["X"]["state"] == "fault", 20, "X fault")
            assert ctl(sock, "fault-reset", "X").returncode == 0
            peak = max(peak, _dir_bytes(logs))

        def rotated():
            nonlocal peak
            peak = max(peak, _dir_bytes(logs))
            s = status(sock)
            return s["log"]["segment"] >= 14 and s["log"]["events_pending"] == 0 and s
        st = wait_for(rotated, 40, "14 segments", interval=0.05)
        time.sleep(2.5)                              # a periodic prune refreshes the figures
        st = status(sock)
        ret = st["log"]["retention"]
        run_path = st["log"]["run"]
        code, _, err = d.terminate()
        assert code == 0, err
    assert peak <= budget and _dir_bytes(logs) <= budget, (peak, budget)
    assert ret["budget_bytes"] == budget and 0 < ret["kept_bytes"] <= budget
    assert ret["dropped_segments"] >= 5 and ret["kept_events"] >= 3, ret
    # per second of the run's own time: the rows' bytes and the segments' headers, whatever the host
    assert 1.0 <= ret["bytes_per_s"] / ret["row_bytes_per_s"] < 1.5, ret
    # 8-byte floats, one row of the daemon's axes' record per cycle at 5 kHz
    assert ret["row_bytes_per_s"] == 8 * len(columns_for(list(st["axes"]))) * 5000
    assert ret["days_at_budget"] == pytest.approx(
        (budget - ret["kept_event_bytes"]) / ret["row_bytes_per_s"] / 86400)
    run = open_run(run_path)
    events = [e for e in run.header["events"] if e["kind"] == "fault-X"]
    # (a fault inside the after-window of the one before is kept in that event log)
    assert sum(1 + e["also"].count("fault-X") for e in events) == 3
    assert run.header["ended"]["reason"] == "SIGTERM"
    for e in events:
        assert read_log(e["path"]).header["event"]["cycle"] == e["cycle"], "every event log kept"
    assert run.segments[0].header["segment"]["index"] > 1, "the oldest segments were dropped"
    assert run.gaps == [] and run.header["ended"]["lost_rows"] == 0
    _check_segments(run)
    assert run.n_rows + run.segments[0].header["segment"]["first_cycle"] == run.header["ended"]["cycles"]


def test_a_segment_that_cannot_be_created_loses_no_row_and_takes_the_end_record(tmp_path, monkeypatch):
    """Rotation on a full disk: the closed segment is whole, the drainer faults instead of
    raising, the end record goes into the last segment there is, and once a new segment can
    be created the rows go on from the next cycle."""
    import errno

    import motorctl.recorder.segments as segments
    from motorctl.recorder.flight import REC_DISK_FULL, REC_OK
    cols = columns_for(["X"])
    ring = SharedRing(5000, len(cols), 1)
    hdr = {"columns": cols, "axes": ["X"], "period_s": TS}
    w = SegmentWriter(str(tmp_path / RUN), hdr, reserve=2048, segment_bytes=64 << 10)
    dr = Drainer(ring, w, hdr, ["X"], Timebase(TS))
    ci = {c: j for j, c in enumerate(cols)}

    def publish(k0, n):
        for k in range(k0, k0 + n):
            ring.rows[k % ring.capacity, :] = 0.0
            ring.rows[k % ring.capacity, ci["t"]] = k * TS
            ring.publish(k + 1)

    class FullDisk(segments.LogWriter):
        def __init__(self, *a, **kw):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
    publish(0, 100)
    dr.poll()
    monkeypatch.setattr(segments, "LogWriter", FullDisk)
    publish(100, 400)                                # more than the first segment holds
    dr.poll()
    assert dr.fault == REC_DISK_FULL and w.cur is None and w.index == 1
    first = read_log(segment_path(str(tmp_path / RUN), 1))
    assert first.truncated_bytes == 0 and np.array_equal(first.col("t"), np.arange(w.next_cycle) * TS)
    assert w.update_header({**hdr, "ended": {"reason": "test"}})
    assert read_log(segment_path(str(tmp_path / RUN), 1)).header["ended"] == {"reason": "test"}
    monkeypatch.undo()
    dr._retry_at = 0.0
    dr.poll()
    assert dr.fault == REC_OK and dr.lost_rows == 0 and w.index == 2
    dr.finish()
    dr.close()
    run = open_run(str(tmp_path / RUN))
    assert run.gaps == [] and run.n_rows == 500
    _check_segments(run)
