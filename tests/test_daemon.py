"""The real daemon as a subprocess on the simulated driver, driven only through the CLI.

Assertions are on the run log the daemon wrote (cycle counts and logged values), never on
wall-clock speed (CI runs SCHED_OTHER on noisy machines)."""

from __future__ import annotations

import numpy as np
import pytest
from test_daemon_helpers import FLUSH_S, cli, cli_status, ctl, make_config, running_daemon, status, wait_for

from motorctl.recorder.runlog import read_log
from motorctl.loop.safety import FAULT_SHUTDOWN

TS = 1.0 / 5000


@pytest.fixture
def daemon(tmp_path):
    with running_daemon(tmp_path, busy_y=True) as d:
        yield d


def _phase(sock, axis):
    return status(sock)["axes"][axis]


def _first_enabled_row(log, axis, after=0):
    en = log.col(f"{axis}.enabled")
    idx = np.flatnonzero((en[after:] > 0))
    assert idx.size, f"{axis} never enabled after row {after}"
    return after + int(idx[0])


def test_operator_session_start_stop_switch_sigterm(daemon, tmp_path):
    sock = daemon.sock
    st = cli_status(sock)
    assert all(a["state"] == "disabled" for a in st["axes"].values()), "every axis starts disabled"
    assert all(not a["amplifier_enabled"] for a in st["axes"].values())
    assert st["realtime"]["gc"]["obtained"] and st["process"]["python_threads"] == 1

    # bad input: one clear line, non-zero exit, nothing moved
    r = cli(sock, "start", "Z")
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and "unknown axis 'Z'" in r.stderr
    r = ctl(tmp_path / "nothing.sock", "status")
    assert r.returncode == 1 and "not running" in r.stderr and r.stderr.count("\n") == 1
    axes = status(sock)["axes"]
    assert all(a["state"] == "disabled" for a in axes.values()), \
        ("nothing moved", {n: (a["state"], a["fault"]) for n, a in axes.items()})

    r = cli(sock, "start", "X")
    assert r.returncode == 0, r.stderr
    r = ctl(sock, "start", "Y", "--controller", "c2")
    assert r.returncode == 0, r.stderr
    both = wait_for(lambda: (s := status(sock)) and all(
        a["state"] == "enabled" and a["phase"] == "tracking" for a in s["axes"].values()) and s,
        20, "X and Y tracking")
    both = cli_status(sock)
    for a in both["axes"].values():
        assert a["state"] == "enabled" and a["phase"] == "tracking"
        assert abs(a["following_error_m"]) < 3e-4
        assert a["amplifier_enabled"] and a["fault"] == ""

    # stop X while Y keeps running
    r = ctl(sock, "stop", "X")
    assert r.returncode == 0, r.stderr
    assert "0 V, amplifier off" in r.stdout
    s = status(sock)
    assert s["axes"]["X"]["state"] == "disabled" and not s["axes"]["X"]["amplifier_enabled"]
    assert s["axes"]["Y"]["state"] == "enabled"

    # switch Y C2 -> C1 -> C2 while it runs its program
    cycles = []
    for kind in ("c1", "c2", "c1", "c2"):
        c0 = status(sock)["loop"]["cycles"]
        wait_for(lambda: status(sock)["loop"]["cycles"] > c0 + 1500, 20, "0.3 s of Y")
        r = ctl(sock, "switch", "Y", "--controller", kind)
        assert r.returncode == 0, r.stderr
        cycles.append(int(r.stdout.rsplit("cycle", 1)[1]))
        assert status(sock)["axes"]["Y"]["controller"] == kind
    c0 = status(sock)["loop"]["cycles"]
    wait_for(lambda: status(sock)["loop"]["cycles"] > c0 + 2500, 20, "0.5 s of Y on C2")
    s = status(sock)
    assert s["axes"]["Y"]["state"] == "enabled", s["axes"]["Y"]["fault"]
    r = ctl(sock, "stop", "Y")
    assert r.returncode == 0, r.stderr

    # start both again, then SIGTERM: every axis at 0 V and disabled, log complete
    assert ctl(sock, "start", "X").returncode == 0
    assert ctl(sock, "start", "Y").returncode == 0
    wait_for(lambda: all(a["phase"] == "tracking" for a in status(sock)["axes"].values()), 20, "tracking")
    log_path = status(sock)["log"]["path"]
    code, out, err = daemon.terminate()
    assert code == 0, err
    assert "stopped by SIGTERM" in err

    log = read_log(log_path)
    t = log.col("t")
    assert log.truncated_bytes == 0
    assert np.allclose(np.diff(t), TS), "every cycle's record is in the log, none lost"
    assert log.header["realtime"]["gc"]["obtained"]
    for a in ("X", "Y"):
        u, en, fb = log.col(f"{a}.u"), log.col(f"{a}.enabled"), log.col(f"{a}.fault_bits")
        # the end: 0 V, amplifier off, shutdown latched on the axes that were driven
        assert np.all(u[-5:] == 0.0) and np.all(en[-5:] == 0.0)
        assert int(fb[-1]) & FAULT_SHUTDOWN
        first = np.flatnonzero(fb != 0)[0]
        assert en[first] == 0.0 and u[first] == 0.0, "0 V and amplifier off in the cycle of the signal"
        # bumpless starts: the first output after each start is the model's holding force at
        # rest (−θ̂4: the axis's offset, which the second start of an axis has adapted), no jump
        starts = np.flatnonzero((en[1:] > 0) & (en[:-1] == 0)) + 1
        assert len(starts) == 2
        th4 = log.col(f"{a}.theta_hat4")
        for k in starts:
            hold = -th4[k] if np.isfinite(th4[k]) else 0.0
            assert abs(u[k] - hold) < 0.3, f"{a}: first output {u[k]:.3f} V at a start, holding {hold:.3f} V"
            assert abs(log.col(f"{a}.e")[k]) < 5e-6
        # stops: at rest (x_d constant, zero velocity) before the amplifier goes off
        stops = np.flatnonzero((en[1:] == 0) & (en[:-1] > 0)) + 1
        k = stops[0]
        xd, vd = log.col(f"{a}.x_d"), log.col(f"{a}.xd_dot")
        assert np.all(vd[k - 200:k] == 0.0) and np.ptp(xd[k - 200:k]) == 0.0
    # switches happened at the cycles reported, without a jump in the output
    u = log.col("Y.u")
    du = np.abs(np.diff(u))
    steady = np.percentile(du[log.col("Y.enabled")[1:] > 0], 99.9)
    for c in cycles:
        row = int(np.searchsorted(t, c * TS - TS / 2))
        jump = np.max(du[row - 2:row + 3])
        assert jump < max(0.5, 3 * steady), f"switch at cycle {c}: output step {jump:.3f} V"
        assert np.max(np.abs(log.col("Y.e")[row:row + 2500])) < 5e-4


def test_malformed_config_refused(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("loop:\n  rate_hz: 5000\n  rate_hz: 4000\naxes: {}\n")
    r = cli(None, "daemon", bad, "--socket", tmp_path / "s.sock")
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and "duplicate key" in r.stderr
    assert not (tmp_path / "s.sock").exists()
    cfg = make_config(tmp_path)
    text = cfg.read_text().replace(f"flush_s: {FLUSH_S}", "flush_s: 3.0")
    cfg.write_text(text)
    r = ctl(None, "daemon", cfg)           # in-process: the check happens before anything starts
    assert r.returncode == 2 and "daemon.flush_s" in r.stderr and r.stderr.count("\n") == 1
