"""The recorder fails, the loop never blocks and no motion goes unlogged: a full disk (a real
tmpfs when this runs as root, and a simulated ENOSPC), a stalled I/O process (SIGSTOP) and a
killed one (SIGKILL). Every axis latches FAULT_RECORDER with its reason in ``status``; the
header gets its end record; the socket does not outlive the daemon."""

from __future__ import annotations

import errno
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from test_daemon_helpers import FLUSH_S, REPO, Daemon, ctl, make_config, status, wait_for

from motorctl.loop.safety import FAULT_RECORDER
from motorctl.recorder.flight import stall_bound_s
from motorctl.recorder.runlog import read_log
from motorctl.recorder.segments import open_run

TS = 1.0 / 5000

#: the daemon with the run log's appends failing with ENOSPC while FLAG exists
SIMULATED_ENOSPC = """
import errno, os, sys
import motorctl.recorder.runlog as runlog
flag = os.environ["MOTORCTL_TEST_ENOSPC"]
append = runlog.LogWriter.append
def full(self, rows):
    if os.path.exists(flag):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
    return append(self, rows)
runlog.LogWriter.append = full
from motorctl.cli import main
sys.exit(main(sys.argv[1:]))
"""


class _SimulatedFullDisk(Daemon):
    def __init__(self, config: Path, sock: Path, flag: Path):
        self.config, self.sock, self.io_pid = config, sock, None
        self.proc = subprocess.Popen(
            [sys.executable, "-c", SIMULATED_ENOSPC, "daemon", str(config), "--socket", str(sock)],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=str(REPO),
            env=dict(os.environ, MOTORCTL_TEST_ENOSPC=str(flag)))


def _config(tmp: Path) -> Path:
    """make_config with soft limits of ±5 m: these tests latch every axis on a recorder fault,
    maybe mid-move at 2 m/s, and a carriage that coasts out of the ±20 mm margin of the shipped
    limits would latch a soft limit as well (seen under a 4-process load), which is not what
    they are about."""
    import yaml
    p = make_config(tmp)
    d = yaml.safe_load(p.read_text())
    for ax in d["axes"].values():
        ax["limits"].update(soft_min_m=-5.0, soft_max_m=5.0)
    p.write_text(yaml.safe_dump(d))
    return p


def _start_both(sock):
    for a in ("X", "Y"):
        r = ctl(sock, "start", a)
        assert r.returncode == 0, r.stderr
    wait_for(lambda: all(s["phase"] == "tracking" for s in status(sock)["axes"].values()), 20,
             "X and Y tracking")


#: how long before the count a ``status`` answer carries the I/O process's wake counter may have
#: moved last (the wake, then the request handled) [s]
WAKE_TO_ANSWER_S = 0.1


def _fill(path: Path) -> None:
    """A ballast file in ``path`` takes what its file system has left (writes until ENOSPC):
    the disk is full when the test says, not when the daemon's log reaches the size (a small
    tmpfs that filled by itself filled before the axes started on a loaded host)."""
    block = b"\0" * (1 << 20)
    with open(path / "ballast", "wb", buffering=0) as fh:
        for _ in range(4096):                        # (bounded: 4 GiB)
            try:
                fh.write(block)
            except OSError as exc:
                if exc.errno == errno.ENOSPC:
                    return
                raise
    raise AssertionError(f"{path} did not fill up")


def _mount_tmpfs(path: Path, size: str) -> str:
    """Mount a tmpfs of ``size`` at ``path`` (the machine's capability, tried before the daemon
    starts): '' when mounted, else why not."""
    path.mkdir(parents=True, exist_ok=True)
    if os.geteuid() != 0:
        return "mounting a tmpfs needs root"
    try:
        r = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(path)],
                           capture_output=True, text=True, timeout=10)
    except (OSError, subprocess.TimeoutExpired) as exc:
        return f"mount -t tmpfs: {exc}"
    return "" if r.returncode == 0 else f"mount -t tmpfs refused here: {r.stderr.strip()[-200:]}"


@pytest.mark.parametrize("disk", ["tmpfs", "simulated"])
def test_full_disk_latches_every_axis_keeps_answering_and_ends_the_header(tmp_path, disk):
    logs = tmp_path / "logs"
    cfg = _config(tmp_path)
    flag = tmp_path / "disk-full"
    if disk == "tmpfs":
        lacks = _mount_tmpfs(logs, "64m")
        if lacks:
            pytest.skip(lacks)
        d = Daemon(cfg, tmp_path / "motorctl.sock")
    else:
        d = _SimulatedFullDisk(cfg, tmp_path / "motorctl.sock", flag)
    try:
        d.wait_ready()
        _start_both(d.sock)
        if disk == "tmpfs":
            _fill(logs)                               # the rest of the tmpfs taken: full from now
        flag.touch()

        def latched():
            s = status(d.sock)
            return all(a["state"] == "fault" for a in s["axes"].values()) and s
        st = wait_for(latched, 20, "every axis latched")
        for a in st["axes"].values():
            assert a["fault"] == "recorder: log disk full" and a["fault_bits"] == FAULT_RECORDER
            assert not a["amplifier_enabled"] and a["u_V"] == 0.0
        assert st["log"]["recorder_fault"] == "log disk full"
        # the daemon keeps answering, the loop keeps running, and nothing restarts the axes
        c0 = st["loop"]["cycles"]
        for _ in range(20):
            assert status(d.sock)["axes"]["X"]["state"] == "fault"
        wait_for(lambda: status(d.sock)["loop"]["cycles"] > c0 + 2500, 20, "the loop running on")
        r = ctl(d.sock, "fault-reset", "X")
        assert r.returncode == 1 and "recorder is still faulted (log disk full)" in r.stderr, r.stderr
        r = ctl(d.sock, "start", "Y")
        assert r.returncode == 1 and "in fault" in r.stderr
        if disk == "simulated":                       # room again: writing resumes, reset works
            flag.unlink()
            wait_for(lambda: status(d.sock)["log"]["recorder_fault"] == "", 20, "the log written again")
            r = ctl(d.sock, "fault-reset", "X")
            assert r.returncode == 0, r.stderr
        path = status(d.sock)["log"]["path"]
        code, _, err = d.terminate()
        assert code == 0, err
        assert "cannot write the run log" in err and "log disk full" in err
        assert not (tmp_path / "motorctl.sock").exists()
        log = read_log(path)                          # (before the tmpfs goes)
    finally:
        d.kill()
        if disk == "tmpfs":
            subprocess.run(["umount", "-l", str(logs)], capture_output=True)
    ended = log.header["ended"]
    assert ended["reason"] == "SIGTERM" and "log disk full" in ended["recorder"]
    assert log.truncated_bytes == 0
    if disk == "tmpfs":
        assert ended["lost_rows"] > 0                 # the disk stayed full to the end
        assert np.allclose(np.diff(log.col("t")), TS), "what was written is whole and contiguous"


def test_sigkill_of_the_io_process_latches_ends_the_log_and_removes_the_socket(tmp_path):
    d = Daemon(_config(tmp_path), tmp_path / "motorctl.sock")
    try:
        st = d.wait_ready()
        _start_both(d.sock)
        st = status(d.sock)
        run = st["log"]["run"]
        os.kill(d.io_pid, signal.SIGKILL)
        code = d.proc.wait(timeout=20)
        err = d.proc.stderr.read()
    finally:
        d.kill()
    assert code == 1, err
    assert "the recorder process died" in err and "end record written by the loop process" in err
    assert not (tmp_path / "motorctl.sock").exists(), "the socket file is removed"
    log = open_run(run).read()
    ended = log.header["ended"]
    assert ended["written_by"] == "loop process" and ended["reason"] == "recorder process died"
    assert ended["lost_rows"] == 0 and log.data.shape[0] == ended["cycles"], "the ring's rows appended"
    assert np.allclose(np.diff(log.col("t")), TS)
    for a in ("X", "Y"):
        fb, en = log.col(f"{a}.fault_bits"), log.col(f"{a}.enabled")
        k = int(np.argmax((fb.astype(np.int64) & FAULT_RECORDER) != 0))
        assert fb[k] != 0 and en[k - 1] == 1.0, "driven until the recorder died"
        assert np.all(en[k:] == 0.0) and np.all(log.col(f"{a}.u")[k:] == 0.0)
        assert k > st["loop"]["cycles"] and log.data.shape[0] - k < 100, "latched at once, then ended"


def test_sigstop_of_the_io_process_beyond_the_bound_latches_every_enabled_axis(tmp_path):
    bound = stall_bound_s(FLUSH_S)
    d = Daemon(_config(tmp_path), tmp_path / "motorctl.sock")
    try:
        d.wait_ready()
        _start_both(d.sock)
        k_before = status(d.sock)["loop"]["cycles"]
        os.kill(d.io_pid, signal.SIGSTOP)
        t_stop = time.monotonic()
        try:
            time.sleep(bound + 1.0)
        finally:
            os.kill(d.io_pid, signal.SIGCONT)
        assert time.monotonic() - t_stop >= bound + 1.0
        st = status(d.sock)
        for a in st["axes"].values():
            assert a["state"] == "fault" and a["fault"] == "recorder: recorder stalled", a
            assert not a["amplifier_enabled"]
        # the recorder is awake again: the fault can be reset (the axis stays disabled)
        r = ctl(d.sock, "fault-reset", "X")
        assert r.returncode == 0, r.stderr
        path = st["log"]["path"]
        code, _, err = d.terminate()
        assert code == 0, err
    finally:
        d.kill()
    log = read_log(path)
    assert log.header["ended"]["lost_rows"] == 0
    periods = np.arange(log.data.shape[0]) + log.col("overruns")    # loop periods elapsed
    for a in ("X", "Y"):
        fb, en = log.col(f"{a}.fault_bits"), log.col(f"{a}.enabled")
        k = int(np.argmax((fb.astype(np.int64) & FAULT_RECORDER) != 0))
        assert fb[k] != 0 and en[k - 1] == 1.0
        # no motion unlogged beyond the bound: latched the bound after the last wake the
        # loop saw (that wake's count came before k_before by the I/O process's handling of the
        # status request: 22 ms seen on a loaded host; WAKE_TO_ANSWER_S)
        stall_s = (periods[k] - periods[k_before]) * TS
        assert bound - WAKE_TO_ANSWER_S <= stall_s <= bound + 1.0, stall_s
        assert np.all(en[k:] == 0.0)
