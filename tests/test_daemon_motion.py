"""Commanded motion through the daemon on the simulated gantry: ``start --mode command``,
``move``, feed hold and resume, abort, feed override, an underrun (the I/O process stopped: the
loop brakes jerk-limited on its own, no fault), refused commands that queue nothing; and the
loop's brake and setpoint ring on their own."""

from __future__ import annotations

import os
import signal
import time

import numpy as np
import pytest
import yaml
from test_daemon_helpers import REPO, Daemon, ctl, make_config, status, wait_for

from motorctl.loop.stream import SP_UNDERRUNS, SetpointRing, brake_step

TS = 2e-4


# --------------------------------------------------------------------------- the brake, alone
@pytest.mark.parametrize("v0,a0", [(0.4, 2.0), (-1.5, 0.0), (2.0, -40.0), (0.01, 40.0), (0.0, 5.0),
                                   (-0.3, -30.0)])
def test_the_brake_stops_within_a_max_and_j_max_without_reversing(v0, a0):
    a_max, j_max = 40.0, 4000.0
    x, v, a = 0.1, v0, a0
    vs, as_ = [v], [a]
    for _ in range(20000):
        x, v, a, rest = brake_step(x, v, a, a_max, j_max, TS)
        vs.append(v)
        as_.append(a)
        if rest:
            break
    assert rest and v == 0.0 and a == 0.0
    jerk = np.abs(np.diff(as_)) / TS
    assert jerk.max() <= j_max * (1 + 1e-9)
    assert np.abs(as_).max() <= max(a_max, abs(a0)) + 1e-9
    if v0 != 0.0:                      # it never moves back against its velocity
        assert np.all(np.sign(vs[1:]) * np.sign(v0) >= 0.0)


def test_the_ring_is_bounded_and_counts_what_it_holds():
    ring = SetpointRing(4, 2, shared=False)
    block = np.ones((6, 2, 3))
    assert ring.push(block, ring.epoch()) == 4          # full: the rest waits
    assert ring.depth() == 4 and ring.free() == 0
    assert ring.underruns() == 0 and int(ring.ctl[SP_UNDERRUNS]) == 0


# --------------------------------------------------------------------------- through the daemon
@pytest.fixture(scope="module")
def gantry(tmp_path_factory):
    """One daemon for the module, X and Y in command mode; X has a home switch at -4 mm and
    an index pulse at -2 mm, homing required (to 0.0 at the index), and is homed here."""
    tmp = tmp_path_factory.mktemp("motion")
    cfg = make_config(tmp)
    d = yaml.safe_load(cfg.read_text())
    d["axes"]["X"]["driver"].update(home_switch_m=-0.004, index_pulse_m=-0.002)
    d["gcode"] = {"words": {"M3": "torch", "M5": "torch", "S": "ignore"}, "axes": ["X", "Y"]}
    d["axes"]["X"]["homing"] = {"direction": -1, "search_speed_m_per_s": 0.02, "latch_speed_m_per_s": 0.002,
                                "back_off_m": 0.01, "position_m": 0.0, "required": True}
    cfg.write_text(yaml.safe_dump(d))
    dmn = Daemon(cfg, tmp / "motorctl.sock")
    try:
        dmn.wait_ready()
        for a in ("X", "Y"):
            r = ctl(dmn.sock, "start", a, "--mode", "command")
            assert r.returncode == 0, r.stderr
        wait_for(lambda: all(s["phase"] == "command" for s in status(dmn.sock)["axes"].values()), 10,
                 "command mode")
        dmn.refused = ctl(dmn.sock, "move", "X=0.1")          # before homing
        dmn.homing = ctl(dmn.sock, "home", "--all", "--timeout", "30")   # X alone has a homing: section
        dmn.homed_at = status(dmn.sock)["axes"]["X"]["y_m"]
        yield dmn
    finally:
        dmn.kill()


def test_homing_finds_the_index_and_sets_the_position(gantry):
    """Motion is refused until X is homed; homing ends with the index pulse (raw -2 mm) at
    0.0: the carriage stopped a fraction of a millimetre past the pulse reads that much above 0."""
    assert gantry.refused.returncode == 1 and "not homed" in gantry.refused.stderr, gantry.refused.stderr
    assert gantry.homing.returncode == 0 and "homed" in gantry.homing.stdout, gantry.homing.stdout
    st = status(gantry.sock)
    assert st["motion"]["homed"] == [True, False] and st["motion"]["homing"][0] == "homed"
    assert st["motion"]["homing_configured"] == [True, False] and gantry.homing.stdout.startswith("X: homed")
    r = ctl(gantry.sock, "home")                          # neither an axis nor --all
    assert r.returncode == 2 and "--all" in r.stderr and "Traceback" not in r.stderr, r.stderr
    assert 0.0 < gantry.homed_at < 0.001                  # off the index by the hold's reaction (< LEAD_S)
    _no_fault(gantry.sock)
    r = ctl(gantry.sock, "move", "X=0.0", "--wait")
    assert r.returncode == 0, r.stdout + r.stderr
    _settled(gantry.sock, np.array([0.0, status(gantry.sock)["axes"]["Y"]["y_m"]]), timeout=5.0)


def _y(sock) -> np.ndarray:
    ax = status(sock)["axes"]
    return np.array([ax["X"]["y_m"], ax["Y"]["y_m"]])


def _settled(sock, goal, tol=10e-6, timeout=5.0) -> np.ndarray:
    wait_for(lambda: np.all(np.abs(_y(sock) - goal) < tol), timeout, f"the axes within {tol} m of {goal}",
             detail=lambda: _y(sock))
    return _y(sock)


def _no_fault(sock):
    for a, s in status(sock)["axes"].items():
        assert s["state"] == "enabled" and s["phase"] == "command" and not s["fault"], (a, s)


def test_move_ends_on_its_target(gantry):
    sock = gantry.sock
    r = ctl(sock, "move", "X=0.120", "Y=0.050", "--wait")
    assert r.returncode == 0, r.stdout + r.stderr
    assert "done in" in r.stdout
    _settled(sock, np.array([0.120, 0.050]))
    st = status(sock)["motion"]
    assert st["queue_depth"] == 0 and st["underruns"] == 0 and st["stopped_because"] == ""
    _no_fault(sock)


def test_a_refused_move_queues_nothing(gantry):
    sock = gantry.sock
    before = _y(sock)
    r = ctl(sock, "move", "X=0.500")                        # soft_max_m 0.42
    assert r.returncode == 2 and "outside the soft limits" in r.stderr, r.stderr
    r = ctl(sock, "move", "Z=0.1")
    assert r.returncode == 2 and "unknown axis" in r.stderr, r.stderr
    r = ctl(sock, "move", "X")
    assert r.returncode == 2 and "AXIS=POSITION" in r.stderr, r.stderr
    r = ctl(sock, "override", "2")
    assert r.returncode == 2 and "0.0..1.5" in r.stderr, r.stderr
    time.sleep(0.2)
    assert status(sock)["motion"]["queue_depth"] == 0
    assert np.all(np.abs(_y(sock) - before) < 10e-6)


def _on_line(p, a, b) -> float:
    """Distance of p from the segment a-b [m]."""
    d = b - a
    s = np.clip(np.dot(p - a, d) / np.dot(d, d), 0.0, 1.0)
    return float(np.linalg.norm(p - (a + s * d)))


def test_feed_hold_stops_on_the_path_and_resume_finishes(gantry):
    sock = gantry.sock
    a, b = _y(sock), np.array([0.220, 0.150])
    assert ctl(sock, "move", "X=0.220", "Y=0.150", "--feed", "0.05").returncode == 0
    time.sleep(0.8)
    assert ctl(sock, "hold").returncode == 0
    wait_for(lambda: status(sock)["motion"]["feed_scale"] == 0.0 and status(sock)["motion"]["ring_depth"] == 0,
             5, "the hold to come to rest")
    time.sleep(0.1)
    p1 = _y(sock)
    time.sleep(0.3)
    p2 = _y(sock)
    assert np.all(np.abs(p2 - p1) < 5e-6)                 # held
    assert 0.01 < np.linalg.norm(p1 - a) < np.linalg.norm(b - a) - 0.01   # mid-path
    assert _on_line(p1, a, b) < 20e-6                     # on the path
    assert status(sock)["motion"]["queue_depth"] == 1
    assert ctl(sock, "resume").returncode == 0
    assert ctl(sock, "wait", "--timeout", "20").returncode == 0
    _settled(sock, b)
    _no_fault(sock)


def test_abort_stops_on_the_path_and_clears_the_queue(gantry):
    sock = gantry.sock
    a, b = _y(sock), np.array([0.120, 0.050])
    assert ctl(sock, "move", "X=0.120", "Y=0.050", "--feed", "0.05").returncode == 0
    assert ctl(sock, "move", "X=0.300").returncode == 0    # queued behind it
    time.sleep(0.6)
    assert ctl(sock, "abort").returncode == 0
    r = ctl(sock, "wait", "--timeout", "10")
    assert r.returncode == 1 and "aborted" in r.stdout, r.stdout
    mo = status(sock)["motion"]
    assert mo["queue_depth"] == 0 and not mo["hold"]
    time.sleep(0.1)
    p = _y(sock)
    assert _on_line(p, a, b) < 20e-6 and np.linalg.norm(p - b) > 0.01
    _no_fault(sock)
    r = ctl(sock, "move", "X=0.120", "Y=0.050", "--wait")   # moves again after an abort
    assert r.returncode == 0, r.stdout + r.stderr
    _settled(sock, b)


def test_feed_override_scales_the_feed(gantry):
    sock = gantry.sock
    assert ctl(sock, "override", "0.5").returncode == 0
    try:
        assert ctl(sock, "move", "X=0.170", "--feed", "0.05").returncode == 0
        feeds = []
        end = time.monotonic() + 0.8
        while time.monotonic() < end:
            mo = status(sock)["motion"]
            feeds.append(mo["feed_m_s"])
            assert mo["feed_scale"] <= 0.5 + 1e-9
            time.sleep(0.02)
        assert 0.02 < max(feeds) <= 0.025 + 1e-6       # half of 0.05 m/s
        assert ctl(sock, "wait", "--timeout", "20").returncode == 0
        _settled(sock, np.array([0.170, 0.050]))
    finally:
        assert ctl(sock, "override", "1.0").returncode == 0


def test_an_underrun_brakes_to_rest_without_a_fault(gantry):
    """The I/O process (the planner) stopped for 0.8 s mid-move: the ring runs dry, the loop
    brakes on its own and holds; the program is dropped with the reason; no fault."""
    sock = gantry.sock
    io = gantry.io_pid
    u0 = status(sock)["motion"]["underruns"]
    assert ctl(sock, "move", "X=0.300", "Y=0.200", "--feed", "0.1").returncode == 0
    time.sleep(0.5)
    os.kill(io, signal.SIGSTOP)
    try:
        time.sleep(0.8)          # > LEAD_S of loop cycles even on a loaded host (no real-time)
    finally:
        os.kill(io, signal.SIGCONT)
    r = ctl(sock, "wait", "--timeout", "10")
    assert r.returncode == 1 and "underrun" in r.stdout, r.stdout
    mo = status(sock)["motion"]
    assert mo["underruns"] == u0 + 1 and mo["queue_depth"] == 0 and not mo["braking"]
    _no_fault(sock)
    p1 = _y(sock)
    time.sleep(0.2)
    assert np.all(np.abs(_y(sock) - p1) < 5e-6)           # held at rest
    assert ctl(sock, "move", "X=0.120", "Y=0.050", "--wait").returncode == 0


def test_a_gcode_program_ends_on_its_last_point(gantry):
    """configs/square_and_circle.ngc (a 100 mm square at F6000, an R20 circle at F3000, G0 to
    X10 Y20) through the daemon: within 10 um of (10, 20) mm, no fault, no underrun."""
    sock = gantry.sock
    u0 = status(sock)["motion"]["underruns"]
    r = ctl(sock, "gcode", str(REPO / "configs" / "square_and_circle.ngc"), "--wait")
    assert r.returncode == 0, r.stdout + r.stderr
    _settled(sock, np.array([0.010, 0.020]))
    assert status(sock)["motion"]["underruns"] == u0
    _no_fault(sock)


def test_a_bad_gcode_program_is_refused_whole(gantry, tmp_path):
    sock = gantry.sock
    before = _y(sock)
    bad = tmp_path / "bad.ngc"
    bad.write_text("G21 G90\nG1 X20 Y20 F600\nG1 X30 Q5\n")
    r = ctl(sock, "gcode", str(bad))
    assert r.returncode == 2 and f"{bad}:3:" in r.stderr, r.stderr
    out = tmp_path / "out.ngc"
    out.write_text("G21 G90\nG1 X20 Y20 F600\nG1 X500\n")      # X 0.5 m: outside the soft limits
    r = ctl(sock, "gcode", str(out))
    assert r.returncode == 2 and f"{out}:3" in r.stderr, r.stderr
    time.sleep(0.2)
    assert status(sock)["motion"]["queue_depth"] == 0
    assert np.all(np.abs(_y(sock) - before) < 10e-6)


def test_mapped_machine_words_run_and_progress_is_shown(gantry, tmp_path):
    """The config's gcode: section reaches the daemon's reader: M3/M5 switch output torch, S is
    ignored with a warning; --progress ends at 100 % with no time left."""
    sock = gantry.sock
    prog = tmp_path / "cut.ngc"
    prog.write_text("G21 G90 G64 P0.01\nG0 X20 Y20\nM3 S1000\nG1 X30 F3000\nM5\nM2\n")
    r = ctl(sock, "gcode", str(prog), "--progress")
    assert r.returncode == 0, r.stdout + r.stderr
    assert "S1000 ignored" in r.stderr and "100.0 %" in r.stderr and "0.00 s left" in r.stderr, r.stderr
    mo = status(sock)["motion"]
    assert mo["outputs"] == {"torch": 0.0} and mo["done"] == 1.0
    _settled(sock, np.array([0.030, 0.020]))
    _no_fault(sock)


def test_the_circular_test_reports_the_iso_figures():
    """A small ISO 230-4 test (R 10 mm at 50 mm/s, C2) on the motion path: both circles
    measured, no underrun, G(b) within the tens of micrometres the figures of docs/commands.md
    show, H at most G(b), F_min <= 0 <= ... bracketing the nominal radius."""
    from motorctl.app.circle_test import run_circle_test
    from motorctl.config import load_config
    r = run_circle_test(load_config(REPO / "configs" / "gantry.yaml"), 0.01, 0.05, "c2")
    g = r.result
    assert r.underruns == 0
    assert min(len(r.paths["cw"][0]), len(r.paths["ccw"][0])) > 0.9 * 2 * np.pi * 0.01 / 0.05 / TS
    assert 0.0 < g.G_cw <= g.G_b < 30e-6 and 0.0 < g.G_ccw <= g.G_b
    assert 0.0 <= g.H <= g.G_b
    assert g.F_min < g.F_max and abs(g.radius_lsc - 0.01) < 20e-6
