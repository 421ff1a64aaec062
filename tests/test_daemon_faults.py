"""Faults through the simulated driver's fault injection, on the real daemon, via the CLI.

Each fault must give 0 V and amplifier off in the cycle it is detected (checked in the run log),
a latched fault with its reason in ``status``, ``start`` refused while latched, ``fault-reset``
refused while the cause persists and working once it is gone."""

from __future__ import annotations

import numpy as np
import pytest
from test_daemon_helpers import ctl, running_daemon, status, wait_for

from motorctl.recorder.runlog import read_log
from motorctl.loop.safety import (FAULT_AMP_FAULT, FAULT_FOLLOWING_ERROR, FAULT_IO_ERROR, FAULT_NAN,
                                  FAULT_I2T, FAULT_SOFT_LIMIT)

# (injection args, fault bit, reason in status, what blocks the reset until it is gone)
FAULTS = [
    (["push", "--force-n", "1500", "--cycles", "20"], FAULT_FOLLOWING_ERROR, "following error", None),
    (["read_error", "--cycles", "20"], FAULT_IO_ERROR, "driver error bucket full", None),
    (["nan", "--cycles", "1"], FAULT_NAN, "NaN/inf", None),
    # reported until the test clears it (--cycles 0): a refused reset whatever the CLI's start-up time
    (["amp_fault", "--cycles", str(10**9)], FAULT_AMP_FAULT, "amplifier fault", "amplifier still reports"),
    (["push", "--force-n", "-1500", "--cycles", "20"], FAULT_SOFT_LIMIT, "soft limit", "outside the soft limits"),
]


@pytest.fixture
def fault_daemon(tmp_path):
    with running_daemon(tmp_path, fault_axis=True) as d:
        yield d


def test_injected_faults_latch_zero_volts_and_reset(fault_daemon):
    sock = fault_daemon.sock
    x = lambda: status(sock)["axes"]["X"]  # noqa: E731
    log_path = status(sock)["log"]["path"]
    for args, bit, reason, blocker in FAULTS:
        r = ctl(sock, "start", "X")
        assert r.returncode == 0, r.stderr
        wait_for(lambda: x()["phase"] == "tracking" and x()["state"] == "enabled", 20, "X tracking")
        r = ctl(sock, "inject", "X", *args)
        assert r.returncode == 0, r.stderr
        st = wait_for(lambda: (s := x())["state"] == "fault" and s, 20, f"{reason} fault")
        assert reason in st["fault"] and st["fault_bits"] & bit
        assert not st["amplifier_enabled"] and st["u_V"] == 0.0
        # latched: start refused with one clear line
        r = ctl(sock, "start", "X")
        assert r.returncode == 1 and "in fault" in r.stderr and r.stderr.count("\n") == 1
        if blocker == "amplifier still reports":
            r = ctl(sock, "fault-reset", "X")
            assert r.returncode == 1 and blocker in r.stderr
            assert ctl(sock, "inject", "X", "amp_fault", "--cycles", "0").returncode == 0   # the cause goes
            c0 = status(sock)["loop"]["cycles"]
            wait_for(lambda: status(sock)["loop"]["cycles"] > c0 + 100, 30, "the amplifier fault to clear")
        elif blocker == "outside the soft limits":
            r = ctl(sock, "fault-reset", "X")
            assert r.returncode == 1 and blocker in r.stderr, r.stderr
            # push the carriage back inside by hand (the amplifier is off)
            assert ctl(sock, "inject", "X", "push", "--force-n", "300", "--cycles", "100").returncode == 0
            wait_for(lambda: x()["y_m"] > 0.0, 20, "X back inside the soft limits")
            c0 = status(sock)["loop"]["cycles"]
            wait_for(lambda: status(sock)["loop"]["cycles"] > c0 + 1000, 20, "X at rest")
        r = ctl(sock, "fault-reset", "X")
        assert r.returncode == 0, r.stderr
        assert "stays disabled" in r.stdout
        st = x()
        assert st["state"] == "disabled" and st["fault"] == ""
        assert status(sock)["axes"]["Y"]["state"] == "disabled", "the other axis is not touched"
    code, _, err = fault_daemon.terminate()
    assert code == 0
    assert sum("axis X fault" in line for line in err.splitlines()) == len(FAULTS), err

    log = read_log(log_path)
    fb, u, en = log.col("X.fault_bits"), log.col("X.u"), log.col("X.enabled")
    onsets = np.flatnonzero((fb[1:] != 0) & (fb[:-1] == 0)) + 1
    # the 5 injected faults and the shutdown latch of SIGTERM on a disabled axis: none
    assert len(onsets) == len(FAULTS)
    for k, (_, bit, _, _) in zip(onsets, FAULTS):
        # the fault's own bit among those latched until its reset (a push out of the soft
        # limits trips the following error first: the reading trips beyond the limit widened
        # by min_following_error_m)
        rows = fb[k:k + int(np.argmax(fb[k:] == 0))] if (fb[k:] == 0).any() else fb[k:]
        assert np.bitwise_or.reduce(rows.astype(np.int64)) & bit
        assert en[k - 1] == 1.0, "the axis was driven the cycle before"
        assert u[k] == 0.0 and en[k] == 0.0, "0 V and amplifier off in the cycle of the fault"
    events = [e for e in log.header["events"] if e["kind"] == "fault-X"]
    # a fault inside the after-window of an earlier one of the same kind is kept in that
    # window's log (listed under "also") rather than in a log of its own
    assert sum(1 + e["also"].count("fault-X") for e in events) == len(FAULTS)
    for e in events:
        k = e["cycle"]
        assert k in onsets
        ev = read_log(e["path"])
        assert ev.header["event"]["cycle"] == k
        t = ev.col("t")
        assert t[0] < k * log.header["period_s"] < t[-1], "the window holds before and after"



def test_a_force_held_above_the_continuous_rating_trips_i2t_through_the_daemon(tmp_path):
    """X held at rest against a 100 N push (u about 1.25 V) with an I²t model rated 0.5 V
    continuous, 1 V for 0.1 s (docs/protection.md: trips after (1 - 0.25)·0.1 / (1.56 - 0.25)
    = 57 ms): the loop's I²t check trips, status names it, u is 0 V and the amplifier off from
    that row of the log on, the other axis untouched, and a fault reset takes it (the
    accumulator cleared; the axis stays disabled)."""
    with running_daemon(tmp_path, fault_axis=True, limits_x={"i2t_continuous_V": 0.5, "i2t_peak_V": 1.0,
                                                             "i2t_peak_time_s": 0.1}) as d:
        sock = d.sock
        x = lambda: status(sock)["axes"]["X"]  # noqa: E731
        log_path = status(sock)["log"]["path"]
        assert ctl(sock, "start", "X").returncode == 0
        wait_for(lambda: x()["phase"] == "tracking" and x()["state"] == "enabled", 20, "X tracking")
        assert ctl(sock, "inject", "X", "push", "--force-n", "100", "--cycles", "1000").returncode == 0
        st = wait_for(lambda: (s := x())["state"] == "fault" and s, 20, "the I2t trip", detail=lambda: x())
        assert "i2t" in st["fault"] and st["fault_bits"] & FAULT_I2T, st
        assert not st["amplifier_enabled"] and st["u_V"] == 0.0
        assert status(sock)["axes"]["Y"]["fault"] == ""
        r = ctl(sock, "fault-reset", "X")
        assert r.returncode == 0 and "stays disabled" in r.stdout, r.stdout + r.stderr
        assert x()["i2t_level"] == 0.0
        code, _, _ = d.terminate()
        assert code == 0
    log = read_log(log_path)
    fb, u, en = log.col("X.fault_bits"), log.col("X.u"), log.col("X.enabled")
    k = int(np.flatnonzero(fb.astype(np.int64) & FAULT_I2T)[0])
    assert en[k - 1] == 1.0 and abs(u[k - 1]) > 1.0, "driven against the push before"
    assert u[k] == 0.0 and en[k] == 0.0, "0 V and amplifier off in the cycle of the trip"
