"""The flight recorder: ring → drainer → run log, crash safety (kill -9), event windows,
a failed write (ENOSPC) never losing or tearing a record, CSV/MAT export, run logs with a bad
header or a non-file path refused in one line, and the simulated drive's command watchdog."""

from __future__ import annotations

import csv
import errno
import json
import os
import signal
import struct
import time

import numpy as np
import pytest
from test_daemon_helpers import FLUSH_S, Daemon, _alive, ctl, make_config, status, wait_for

from motorctl.config import load_config
from motorctl.loop.records import columns_for
from motorctl.loop.timebase import Timebase
from motorctl.recorder.export import mat_name
from motorctl.recorder.flight import CTL_REC_FAULT, REC_DISK_FULL, REC_OK, Drainer, SharedRing
from motorctl.recorder.runlog import MAGIC, LogError, read_log
from motorctl.recorder.segments import SegmentWriter

TS = 1.0 / 5000


RUN = "motorctl-20240101T000000-1.mlog"
SEG1 = "motorctl-20240101T000000-1.0001.mlog"


def _ring_and_drainer(tmp_path, cap=1000, before=0.01, after=0.01, max_events=20,
                      overrun_before=0.1, overrun_after=0.1):
    cols = columns_for(["X"])
    ring = SharedRing(cap, len(cols), 1)
    hdr = {"columns": cols, "axes": ["X"], "period_s": TS}
    w = SegmentWriter(str(tmp_path / RUN), hdr)
    dr = Drainer(ring, w, hdr, ["X"], Timebase(TS), flush_s=0.1, event_before_s=before, event_after_s=after,
                 max_events=max_events, overrun_before_s=overrun_before, overrun_after_s=overrun_after)
    return cols, ring, dr


def _publish(ring, cols, k0, n, fault_at=None, overrun_at=None):
    ci = {c: j for j, c in enumerate(cols)}
    for k in range(k0, k0 + n):
        r = ring.rows[k % ring.capacity]
        r[:] = 0.0
        r[ci["t"]] = k * TS
        r[ci["turnaround_ns"]] = 20000.0 + k % 7
        r[ci["overruns"]] = 1.0 if overrun_at is not None and k >= overrun_at else 0.0
        r[ci["X.enabled"]] = 1.0
        r[ci["X.fault_bits"]] = 1.0 if fault_at is not None and k >= fault_at else 0.0
        ring.publish(k + 1)


def test_drainer_copies_every_row_in_order_and_cuts_an_event_window(tmp_path):
    cols, ring, dr = _ring_and_drainer(tmp_path)
    _publish(ring, cols, 0, 700)
    assert dr.poll() == 700
    _publish(ring, cols, 700, 600, fault_at=900)     # wraps the 1000-row ring
    dr.poll()
    dr.cut_events()
    dr.finish()
    dr.close()
    log = read_log(str(tmp_path / SEG1))
    assert np.array_equal(log.col("t"), np.arange(1300) * TS)
    assert dr.lost_rows == 0
    assert len(dr.events) == 1 and dr.events[0]["cycle"] == 900
    ev = read_log(dr.events[0]["path"])
    t = ev.col("t")
    assert t[0] == pytest.approx((900 - 50) * TS) and t[-1] == pytest.approx((900 + 49) * TS)
    assert dr.loop_stats.cycles == 1300 and dr.loop_stats.summary()["turnaround_max_us"] == pytest.approx(20.006)


def test_an_overrun_keeps_its_own_shorter_window(tmp_path):
    """Fault windows: event_before_s / event_after_s; overrun windows: overrun_before_s /
    overrun_after_s (daemon.overrun_event_*), so a flood of overruns costs little disk."""
    cols, ring, dr = _ring_and_drainer(tmp_path, before=0.04, after=0.02, overrun_before=0.004,
                                       overrun_after=0.002)
    _publish(ring, cols, 0, 900, fault_at=700, overrun_at=300)
    dr.poll()
    dr.cut_events()
    dr.finish()
    dr.close()
    ev = {e["kind"]: read_log(e["path"]) for e in dr.events}
    assert sorted(ev) == ["fault-X", "overrun"], dr.events
    assert ev["overrun"].data.shape[0] == 20 + 10 and ev["overrun"].col("t")[0] == pytest.approx(280 * TS)
    assert ev["fault-X"].data.shape[0] == 200 + 100 and ev["fault-X"].col("t")[0] == pytest.approx(500 * TS)


def test_drainer_counts_rows_it_fell_behind_on_instead_of_reading_them_torn(tmp_path):
    cols, ring, dr = _ring_and_drainer(tmp_path)
    _publish(ring, cols, 0, 700)
    dr.poll()
    _publish(ring, cols, 700, 2500)                    # 2.5 rings without a drain
    dr.poll()
    assert dr.lost_rows == 1500
    dr.finish()
    dr.close()
    # the gap starts a new segment: each segment's rows are its cycles without a gap
    assert np.array_equal(read_log(str(tmp_path / SEG1)).col("t"), np.arange(700) * TS)
    seg2 = read_log(str(tmp_path / SEG1.replace("0001", "0002")))
    assert seg2.header["segment"]["first_cycle"] == 2200
    assert np.array_equal(seg2.col("t"), np.arange(2200, 3200) * TS)


def test_a_failed_write_keeps_the_rows_and_leaves_no_partial_record(tmp_path, monkeypatch):
    """ENOSPC in the middle of a write: the file is cut back to its last whole record, the
    drainer sets the recorder fault in the ring's control words (never raises), keeps the
    rows in the ring and writes them once the disk has room again: nothing lost, nothing torn."""
    cols, ring, dr = _ring_and_drainer(tmp_path)
    _publish(ring, cols, 0, 100)
    dr.poll()
    real_write = os.write
    full = {"on": True}
    fd = dr.writer.cur._fd

    def write(f, data):
        if f == fd and full["on"]:
            real_write(f, bytes(data)[:100])     # a partial record reaches the file, then:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return real_write(f, data)
    monkeypatch.setattr(os, "write", write)
    _publish(ring, cols, 100, 300)
    assert dr.poll() == 0
    assert dr.fault == REC_DISK_FULL and ring.ctl[CTL_REC_FAULT] == REC_DISK_FULL
    assert "log disk full" in dr.error
    assert os.path.getsize(tmp_path / SEG1) == dr.writer.cur.size, "cut back to whole records"
    assert read_log(str(tmp_path / SEG1)).data.shape[0] == 100
    full["on"] = False
    _publish(ring, cols, 400, 200)
    dr._retry_at = 0.0                            # (the retry interval has passed)
    assert dr.poll() == 500
    assert dr.fault == REC_OK and ring.ctl[CTL_REC_FAULT] == REC_OK and dr.lost_rows == 0
    dr.finish()
    dr.close()
    log = read_log(str(tmp_path / SEG1))
    assert log.truncated_bytes == 0
    assert np.array_equal(log.col("t"), np.arange(600) * TS)


def test_export_csv_and_mat(tmp_path):
    from scipy.io import loadmat
    cols, ring, dr = _ring_and_drainer(tmp_path)
    _publish(ring, cols, 0, 300)
    dr.finish()
    dr.close()
    log = read_log(str(tmp_path / SEG1))
    r = ctl(None, "export", tmp_path / RUN, "--csv", tmp_path / "run.csv")
    assert r.returncode == 0, r.stderr
    with open(tmp_path / "run.csv") as fh:
        rows = list(csv.reader(fh))
    assert rows[0] == cols and len(rows) == 301
    assert float(rows[5][0]) == pytest.approx(4 * TS)
    r = ctl(None, "export", tmp_path / SEG1, "--mat", tmp_path / "run.mat")
    assert r.returncode == 0, r.stderr
    m = loadmat(str(tmp_path / "run.mat"))
    assert m["data"].shape == (300, len(cols))
    assert np.array_equal(m["data"], log.data), "column-major layout of the streamed matrix"
    assert np.array_equal(m[mat_name("X.enabled")].ravel(), log.col("X.enabled"))
    assert [str(c[0]) for c in m["columns"].ravel()] == cols
    assert m["period_s"].item() == TS
    r = ctl(None, "export", tmp_path / "nope.mlog", "--csv", tmp_path / "x.csv")
    assert r.returncode == 2 and r.stderr.count("\n") == 1


def test_sim_watchdog_drops_to_zero_volts_when_commands_stop(gantry_yaml, monkeypatch):
    """The simulated drive's command watchdog, on a monotonic clock the test moves (the drive
    reads ``time.monotonic_ns``): the verdict is the same whatever the host's stalls."""
    from types import SimpleNamespace

    import yaml

    import motorctl_drivers.sim as sim
    from motorctl.config import config_from_dict
    now = [10**12]
    monkeypatch.setattr(sim, "time", SimpleNamespace(monotonic_ns=lambda: now[0]))
    d = yaml.safe_load(open(gantry_yaml))
    watchdog_s = 0.25
    period_ns = round(1e9 / d["loop"]["rate_hz"])
    d["driver"]["watchdog_s"] = watchdog_s
    drv = config_from_dict(d).make_driver()
    drv.read()
    drv.write(np.array([5.0, 5.0]), np.array([True, True]))
    assert drv.amp_enabled.all() and drv.applied_u[0] == 5.0
    v_before = drv.plants[0].xd
    now[0] += round(watchdog_s * 1e9) // 2       # well inside the watchdog time
    drv.read()
    assert not drv.amp_fault.any() and drv.watchdog_bites == 0
    for _ in range(50):
        now[0] += period_ns
        drv.write(np.array([5.0, 5.0]), np.array([True, True]))
    v_at_last_write = drv.plants[0].xd
    assert v_at_last_write > v_before
    t_at_last_write = drv.plants[0].t
    gap_s = watchdog_s + 0.05
    now[0] += round(gap_s * 1e9)                 # the host stops commanding
    drv.read()
    assert drv.watchdog_bites == 1
    assert not drv.amp_enabled.any() and np.all(drv.applied_u == 0.0)
    assert drv.amp_fault.all(), "the drive reports the bite (the supervisor latches it)"
    # the plant coasted through the gap at 0 V: time went on, friction slowed it down
    assert drv.plants[0].t - t_at_last_write == pytest.approx(gap_s, abs=2 * period_ns * 1e-9)
    assert drv.plants[0].xd < 0.5 * v_at_last_write


def test_kill_9_log_readable_up_to_last_flush(tmp_path):
    cfg = make_config(tmp_path)
    d = Daemon(cfg, tmp_path / "motorctl.sock")
    try:
        d.wait_ready()
        assert ctl(d.sock, "start", "X").returncode == 0
        flushed = wait_for(lambda: (s := status(d.sock))["log"]["rows_flushed"] > 5000 and s, 30,
                           "5000 rows flushed")
        rows_flushed = flushed["log"]["rows_flushed"]
        path = flushed["log"]["path"]
        loop_pid, io_pid = flushed["process"]["loop_pid"], flushed["process"]["io_pid"]
        # kill -9 both processes at once (systemd's final SIGKILL of the cgroup)
        os.kill(io_pid, signal.SIGKILL)
        os.kill(loop_pid, signal.SIGKILL)
        d.proc.wait(timeout=10)
    finally:
        d.kill()
    log = read_log(path)
    n = log.data.shape[0]
    assert n >= rows_flushed, "everything flushed before the kill is readable"
    assert np.array_equal(log.col("t"), np.arange(n) * TS), "contiguous, no torn record"
    assert log.header["realtime"]["gc"]["obtained"]


def test_kill_9_of_the_loop_process_recorder_keeps_everything_published(tmp_path):
    cfg = make_config(tmp_path)
    d = Daemon(cfg, tmp_path / "motorctl.sock")
    try:
        st = d.wait_ready()
        path = st["log"]["path"]
        c0 = st["loop"]["cycles"]
        os.kill(d.proc.pid, signal.SIGKILL)
        d.proc.wait(timeout=10)
        wait_for(lambda: not _alive(d.io_pid), 10, "the I/O process to finish and exit")
    finally:
        d.kill()
    log = read_log(path)
    assert log.data.shape[0] >= c0
    assert log.header["ended"]["reason"] == "loop process killed"
    assert log.header["ended"]["lost_rows"] == 0
    assert log.data.shape[0] == log.header["ended"]["cycles"]
    assert not (tmp_path / "motorctl.sock").exists()


def test_flush_interval_config_is_bounded(gantry_yaml, tmp_path):
    text = gantry_yaml.read_text().replace("flush_s: 0.5", "flush_s: 0.5\n  bogus: 1")
    p = tmp_path / "c.yaml"
    p.write_text(text)
    from motorctl.config import ConfigError
    with pytest.raises(ConfigError, match="daemon.bogus"):
        load_config(p)


def test_stalled_loop_sim_drive_watchdog_drops_to_zero_volts(tmp_path):
    """Commands stop arriving (the loop process is stopped): the simulated drive's watchdog
    puts the axis at 0 V with the amplifier off; the daemon latches the amplifier fault.

    Deterministic under load: the stall is confirmed (the heartbeat stops) and lasts at least
    twice the drive's watchdog measured on CLOCK_MONOTONIC; after it, the loop publishes a new
    fault at once, so the fault must be in the first status taken once the heartbeat has moved
    on. The only waits are for progress, bounded by the configured times."""
    watchdog_s, flush_s = 0.5, FLUSH_S
    cfg = make_config(tmp_path, watchdog_s=watchdog_s)
    progress_bound_s = 40 * (watchdog_s + flush_s)  # a loaded 2-core VM, SCHED_OTHER loop
    d = Daemon(cfg, tmp_path / "motorctl.sock")
    try:
        d.wait_ready()
        assert ctl(d.sock, "start", "X").returncode == 0
        wait_for(lambda: status(d.sock)["axes"]["X"]["phase"] == "tracking", progress_bound_s,
                 "X tracking")
        k_stop = status(d.sock)["loop"]["cycles"]
        os.kill(d.proc.pid, signal.SIGSTOP)
        t_stop = time.monotonic()
        try:
            k_a = status(d.sock)["loop"]["cycles"]
            time.sleep(max(0.0, 2 * watchdog_s - (time.monotonic() - t_stop)))
            k_b = status(d.sock)["loop"]["cycles"]
            assert k_a == k_b, "the loop kept running while stopped"
        finally:
            os.kill(d.proc.pid, signal.SIGCONT)
        assert time.monotonic() - t_stop >= 2 * watchdog_s
        wait_for(lambda: status(d.sock)["loop"]["cycles"] > k_b + 50, progress_bound_s,
                 "the loop to run on after the stall")
        st = status(d.sock)["axes"]["X"]
        assert st["state"] == "fault", st
        assert "amplifier fault" in st["fault"] and not st["amplifier_enabled"]
        path = status(d.sock)["log"]["path"]
        code, _, _ = d.terminate()
        assert code == 0
    finally:
        d.kill()
    log = read_log(path)
    late, turn, fb = log.col("lateness_ns"), log.col("turnaround_ns"), log.col("X.fault_bits")
    en = log.col("X.enabled")
    gap = k_stop + int(np.argmax(late[k_stop:] > watchdog_s * 1e9))   # the cycle after the stall
    assert late[gap] > 1.8 * watchdog_s * 1e9
    # the stop can land between a cycle's read and its write: that cycle's turnaround then holds
    # the stall, and its write met a drive whose watchdog had fired (its row may show it off)
    first = gap - 1 if turn[gap - 1] > watchdog_s * 1e9 else gap
    assert en[first - 1] == 1.0, (first, en[first - 3:gap + 2], fb[first - 3:gap + 2], turn[first - 3:gap + 2])
    assert fb[gap] != 0 and log.col("X.u")[gap] == 0.0 and en[gap] == 0.0


def _raw_log(path, header, rows=b""):
    """A file in the run-log layout with any JSON header (valid or not)."""
    blob = json.dumps(header).encode()
    blob += b" " * ((-(len(MAGIC) + 8 + len(blob))) % 8)
    path.write_bytes(MAGIC + struct.pack("<Q", len(blob)) + blob + rows)
    return path


BAD_HEADERS = [
    (["t", "X.y"], "not an object"),
    ({"columns": ["t", "X.y"], "axes": 5}, "'axes' is not a list of names"),
    ({"columns": ["t", "X.y"], "axes": "X"}, "'axes' is not a list of names"),
    ({"columns": ["t", "X.y"], "axes": [1]}, "'axes' is not a list of names"),
    ({"columns": [1, 2]}, "'columns' is not a non-empty list of names"),
    ({"columns": "t"}, "'columns' is not a non-empty list of names"),
    ({"axes": ["X"]}, "'columns' is not a non-empty list of names"),
    ({"columns": ["t", "t"]}, "column 't' appears twice"),
    ({"columns": ["t"], "period_s": "fast"}, "'period_s' is not a positive number"),
    ("just a string", "not an object"),
]


@pytest.mark.parametrize("header,why", BAD_HEADERS, ids=[w for _, w in BAD_HEADERS])
def test_a_bad_header_is_one_line_in_read_log_export_and_plot(tmp_path, header, why):
    bad = _raw_log(tmp_path / "bad.mlog", header, np.zeros(4).tobytes())
    with pytest.raises(LogError) as ei:
        read_log(str(bad))
    msg = str(ei.value)
    assert msg.startswith(f"{bad}: ") and why in msg and "\n" not in msg
    for args in (["export", bad, "--csv", tmp_path / "o.csv"], ["export", bad, "--mat", tmp_path / "o.mat"],
                 ["plot", bad, "--out", tmp_path / "fig"]):
        r = ctl(None, *args)
        assert r.returncode == 2, (args, r.stderr)
        assert r.stderr.count("\n") == 1 and why in r.stderr and "Traceback" not in r.stderr, r.stderr


def test_a_header_whose_axes_lack_columns_is_refused_by_plot_in_one_line(tmp_path):
    bad = _raw_log(tmp_path / "ax.mlog", {"columns": ["t"], "axes": ["X"], "period_s": TS},
                   np.arange(4.0).tobytes())
    r = ctl(None, "plot", bad, "--out", tmp_path / "fig")
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and "no column 'X.x_d'" in r.stderr, r.stderr
    r = ctl(None, "export", bad, "--csv", tmp_path / "o.csv")     # export needs no axis columns
    assert r.returncode == 0 and "4 rows x 1 columns" in r.stdout, r.stderr


@pytest.mark.parametrize("kind", ["fifo", "directory", "device"])
def test_a_log_path_that_is_not_a_regular_file_is_one_line(tmp_path, kind):
    if kind == "fifo":
        p = tmp_path / "pipe.mlog"
        os.mkfifo(p)                     # reading it would block forever
        word = "FIFO"
    elif kind == "directory":
        p = tmp_path / "dir.mlog"
        p.mkdir()
        word = "directory"
    else:
        p = "/dev/zero"                  # reading it would never end
        word = "device"
    with pytest.raises(LogError, match=word):
        read_log(str(p))
    for args in (["export", p, "--csv", tmp_path / "o.csv"], ["plot", p, "--out", tmp_path / "fig"]):
        r = ctl(None, *args)
        assert r.returncode == 2 and r.stderr.count("\n") == 1 and word in r.stderr, r.stderr
