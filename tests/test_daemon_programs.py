"""Programs as a CAM system sends them, through the daemon on the shipped gantry config: longer
than one request (sent in chunks), refused whole before anything moves (a Z word on an X-Y
machine, a soft limit on the last line, a program over daemon.max_program_bytes), any request
or program answered without ending the daemon (hypothesis), the planner process's death an
answer, and the operator's CLI path light (no numpy)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import yaml
from conftest import examples
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from test_daemon_helpers import (GANTRY, command_mode_daemon, ctl, make_config, no_fault, positions, status,
                                 to_command_mode, wait_for)

from motorctl.app.daemon.io_side import spool_beside
from motorctl.client import call

#: the module's daemon.max_program_bytes [bytes]: above one request (64 KiB), below the big one
MAX_PROGRAM = 200_000


@pytest.fixture(scope="module")
def machine(tmp_path_factory):
    """One daemon on configs/gantry.yaml (paths, realtime off, the program bound and the lead changed;
    no gcode: section, so the G-code axes are the machine's, X Y), both axes in command mode."""
    tmp = tmp_path_factory.mktemp("programs")
    # the lead of test_daemon_motion's daemon (1.5 s): without the real-time set-up (tests run
    # with policy off) the filler is starved on a loaded host; 0.5 s underran once under the suite
    cfg = make_config(tmp, extra_daemon={"max_program_bytes": MAX_PROGRAM, "motion_lead_s": 1.5})
    assert "gcode" not in yaml.safe_load(cfg.read_text())
    with command_mode_daemon(cfg) as dmn:
        yield dmn


@pytest.fixture(autouse=True)
def ready(request):
    """Each test starts from the same state whatever ran before (any order): both axes in command
    mode without a fault, no motion, the optional stop as configured (off)."""
    if "machine" not in request.fixturenames:
        yield
        return
    sock = request.getfixturevalue("machine").sock
    to_command_mode(sock)
    call(str(sock), {"cmd": "optional-stop", "value": False})
    yield


_y, _no_fault = positions, no_fault


def _steps(n: int, x0: float = 50.0, y0: float = 50.0, bad_last: bool = False) -> tuple[str, np.ndarray]:
    """n 0.1 mm steps at F6000 in rows of 500 (zig-zag), from (x0, y0) mm; the end [m]."""
    lines = ["G21 G90 G64 P0.01", f"G0 X{x0} Y{y0}", "F6000"]
    x, y, d = x0, y0, 1.0
    for k in range(n):
        if k and k % 500 == 0:
            y += 1.0
            d = -d
        else:
            x += 0.1 * d
        lines.append(f"G1 X{x:.3f} Y{y:.3f}")
    lines.append("G1 X500" if bad_last else "M2")
    return "\n".join(lines) + "\n", np.array([x, y]) * 1e-3


def test_a_program_longer_than_a_request_runs_to_its_end(machine, tmp_path):
    """3600 steps of 0.1 mm (68 kB: over one request's 64 KiB) through `motorctl gcode --wait`:
    sent in chunks, checked whole, run to within 5 um of its last point; no underrun, no fault."""
    sock = machine.sock
    text, end = _steps(3600)
    assert len(text) > 65536
    prog = tmp_path / "steps.ngc"
    prog.write_text(text)
    u0 = status(sock)["motion"]["underruns"]
    r = ctl(sock, "gcode", str(prog), "--wait")
    assert r.returncode == 0, r.stdout + r.stderr
    assert "3601 segments" in r.stdout, r.stdout          # the G0 to the start and 3600 steps
    wait_for(lambda: np.all(np.abs(_y(sock) - end) < 5e-6), 5, "the end point", detail=lambda: _y(sock) - end)
    assert status(sock)["motion"]["underruns"] == u0
    _no_fault(sock)
    spool = Path(str(sock) + ".programs")             # beside the socket, the run's file gone
    assert spool.is_dir() and not any(spool.iterdir())


def test_the_spool_left_by_a_killed_daemon_is_removed(tmp_path):
    """A daemon started on a socket whose last daemon was killed takes over its spool folder
    empty (nothing of the dead one's uploads left), mode 0700."""
    sock = tmp_path / "ctl.sock"
    left = tmp_path / "ctl.sock.programs"
    left.mkdir()
    (left / "dead.ngc").write_text("G1 X1\n")
    assert spool_beside(str(sock)) == str(left)
    assert not any(left.iterdir())
    assert left.stat().st_mode & 0o777 == 0o700


def test_a_program_refused_whole_moves_nothing(machine, tmp_path):
    """A Z word on this X-Y machine (the G-code axes default to the machine's), a soft limit on
    the last of 3000 lines, a program over daemon.max_program_bytes: each refused with one line
    (file:line:column, or the key), exit 2, nothing moved, the daemon still answering."""
    sock = machine.sock
    before = _y(sock)
    z = tmp_path / "z.ngc"
    z.write_text("G21 G90\nG0 Z1\n")
    r = ctl(sock, "gcode", str(z))
    assert r.returncode == 2 and f"{z}:2:4: Z1: axis Z is not on this machine" in r.stderr, r.stderr
    text, _ = _steps(3000, bad_last=True)
    last = tmp_path / "last.ngc"
    last.write_text(text)
    r = ctl(sock, "gcode", str(last))
    assert r.returncode == 2 and f"{last}:3004: X reaches 500.0000 mm" in r.stderr, r.stderr
    big = tmp_path / "big.ngc"
    big.write_text(_steps(11000)[0])
    assert big.stat().st_size > MAX_PROGRAM
    r = ctl(sock, "gcode", str(big))
    assert r.returncode == 2 and "daemon.max_program_bytes" in r.stderr, r.stderr
    assert len(r.stderr.strip().splitlines()) == 1, r.stderr
    mo = status(sock)["motion"]
    assert mo["idle"] and mo["queue_depth"] == 0
    assert np.all(np.abs(_y(sock) - before) < 2e-6)
    _no_fault(sock)


_WORD = st.sampled_from(list("GMXYZFIJKRNPSQTOA#[(;%/ ") + ["G1", "G0", "G2", "G3", "M3", "M2", "G92",
                                                             "G10 L2 P1", "G53", "G4", "M0", "\t", "\x00"])
_NUM = st.one_of(st.integers(-10**6, 10**6).map(str), st.floats(allow_nan=True, allow_infinity=True).map(repr),
                 st.sampled_from(["", ".", "-.5", "1e3", "nan", "inf", "0x10", "1 0"]))
_LINE = st.lists(st.tuples(_WORD, _NUM).map("".join), max_size=6).map(" ".join)
_PROGRAM = st.lists(_LINE, min_size=1, max_size=8).map("\n".join)
_VALUE = st.recursive(st.one_of(st.none(), st.booleans(), st.integers(), st.floats(), st.text(max_size=8)),
                      lambda c: st.one_of(st.lists(c, max_size=3), st.dictionaries(st.text(max_size=5), c, max_size=3)),
                      max_leaves=6)
_REQUEST = st.one_of(
    st.fixed_dictionaries({"cmd": st.sampled_from(["move", "jog", "override", "upload", "gcode", "inject",
                                                   "switch", "home", "nonsense", ""])},
                          optional={"axis": st.sampled_from(["X", "Y", "Z", "", None, 1]), "targets": _VALUE,
                                    "to_m": _VALUE, "speed": _VALUE, "value": _VALUE, "data": _VALUE,
                                    "offset": _VALUE, "upload": _VALUE, "text": _VALUE, "filename": _VALUE,
                                    "kind": _VALUE, "controller": _VALUE, "feed": _VALUE}),
    _VALUE)


def _state(sock) -> tuple:
    s = status(sock)
    return tuple((a["phase"], a["state"], a["fault"]) for a in s["axes"].values()), s["motion"]


def _refused_changes_nothing(sock, request) -> None:
    before, mo = _state(sock)
    y0 = _y(sock)
    ans = call(str(sock), request, 10.0) if isinstance(request, dict) else _raw(sock, request)
    assert isinstance(ans, dict) and "ok" in ans, ans
    after, mo1 = _state(sock)
    if ans["ok"]:                            # a valid command chosen by chance: it may act
        if mo1["queue_depth"] or not mo1["idle"]:
            call(str(sock), {"cmd": "abort"})
            wait_for(lambda: status(sock)["motion"]["idle"], 20, "the abort")
        return
    assert after == before, (request, ans, before, after)
    if mo["idle"] and mo1["idle"]:
        assert np.all(np.abs(_y(sock) - y0) < 2e-6), (request, ans)


def _raw(sock, value) -> dict:
    """Any JSON value as a request line (not only objects)."""
    import socket
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.settimeout(10.0)
    try:
        s.connect(str(sock))
        s.sendall((json.dumps(value) + "\n").encode())
        buf = b""
        while b"\n" not in buf:
            chunk = s.recv(65536)
            if not chunk:
                break
            buf += chunk
    finally:
        s.close()
    return json.loads(buf.split(b"\n", 1)[0])


@settings(max_examples=examples(150), deadline=None, suppress_health_check=list(HealthCheck))
@given(request=_REQUEST)
def test_any_request_is_an_answer_and_a_refused_one_changes_nothing(machine, request):
    """Random requests (any JSON value; objects with the protocol's keys and wrong values):
    every one answered; a refused one leaves every axis's phase, state, fault and position."""
    _refused_changes_nothing(machine.sock, request)


@settings(max_examples=examples(200), deadline=None, suppress_health_check=list(HealthCheck))
@given(text=_PROGRAM)
def test_any_program_is_an_answer_and_a_refused_one_moves_nothing(machine, text):
    """Random programs (words, numbers, comments, stray characters) through ``gcode``: every one
    answered (most refused with file:line:column); a refused one moves nothing."""
    _refused_changes_nothing(machine.sock, {"cmd": "gcode", "text": text, "filename": "random.ngc"})


def test_the_daemon_is_alive_after_the_random_requests(machine):
    """The daemon answers, its planner runs, and the axes are in command mode without a fault."""
    assert status(machine.sock)["process"]["planner_pid"]
    _no_fault(machine.sock)


def test_a_dead_planner_is_started_again(machine, tmp_path):
    """The planner process killed: the daemon starts a new one (one line on its stderr); the next
    program runs; the daemon, its axes and moves go on."""
    sock = machine.sock
    pid = status(sock)["process"]["planner_pid"]
    os.kill(pid, signal.SIGKILL)
    wait_for(lambda: status(sock)["process"]["planner_pid"] not in (None, pid), 60, "a new planner")
    prog = tmp_path / "p.ngc"
    prog.write_text("G21 G90\nG1 X60 Y60 F3000\nM2\n")
    r = ctl(sock, "gcode", str(prog), "--wait")
    assert r.returncode == 0, r.stdout + r.stderr
    assert np.all(np.abs(_y(sock) - np.array([0.060, 0.060])) < 5e-6)
    _no_fault(sock)


def _run(sock, tmp_path, name: str, text: str, *args) -> object:
    prog = tmp_path / name
    prog.write_text(text)
    return ctl(sock, "gcode", str(prog), *args)


def _paused_at(sock, where_mm) -> None:
    wait_for(lambda: status(sock)["motion"]["stopped_because"].startswith("paused"), 20, "a pause",
             detail=lambda: status(sock)["motion"])
    wait_for(lambda: np.all(np.abs(_y(sock) - np.array(where_mm) * 1e-3) < 5e-6), 5, f"rest at {where_mm}",
             detail=lambda: _y(sock))


def test_run_from_line_single_block_and_the_optional_stop(machine, tmp_path):
    """LinuxCNC's run from line (a rapid to where the program stands at that line, then on: the
    lines before it never run), single block (a pause after every block; resume runs the next),
    the optional stop switched at run time (M1 passes with it off, pauses with it on), and
    ``wait`` returning in position (every axis within limits.in_position_m)."""
    sock = machine.sock
    square = "G21 G90 G64 P0.01\nG0 X20 Y20\nG1 X40 Y20 F6000\nG1 X40 Y40\nG1 X60 Y40\nM2\n"
    # from beyond X 40 whatever ran before (the rapid to line 5's point then stays at X >= 40)
    assert ctl(sock, "move", "X=0.070", "Y=0.050", "--wait").returncode == 0
    r = _run(sock, tmp_path, "from.ngc", square, "--from-line", "5")
    assert r.returncode == 0, r.stderr
    xs = []
    wait_for(lambda: xs.append(_y(sock)[0]) or status(sock)["motion"]["idle"], 20, "the run from line 5")
    r = ctl(sock, "wait", "--timeout", "10")
    assert r.returncode == 0, r.stdout + r.stderr
    st = status(sock)
    assert all(a["in_position"] for a in st["axes"].values()), st["axes"]
    assert np.all(np.abs(_y(sock) - np.array([0.060, 0.040])) < 5e-6)
    assert min(xs) > 0.0399, min(xs)                      # never back to X 20 or 40 of line 2-3
    r = _run(sock, tmp_path, "far.ngc", square, "--from-line", "99")
    assert r.returncode == 2 and "beyond the program's last line (6)" in r.stderr, r.stderr

    r = _run(sock, tmp_path, "single.ngc", square, "--single-block")
    assert r.returncode == 0, r.stderr
    for pt in ((20, 20), (40, 20), (40, 40), (60, 40)):        # after every block, the last too
        _paused_at(sock, pt)
        assert ctl(sock, "resume").returncode == 0
    assert ctl(sock, "wait", "--timeout", "20").returncode == 0
    assert np.all(np.abs(_y(sock) - np.array([0.060, 0.040])) < 5e-6)

    m1 = "G21 G90\nG1 X30 Y30 F6000\nM1\nG1 X50 Y30\nM2\n"
    assert status(sock)["motion"]["optional_stop"] is False           # the config's gcode.optional_stop
    assert _run(sock, tmp_path, "m1.ngc", m1, "--wait").returncode == 0
    assert np.all(np.abs(_y(sock) - np.array([0.050, 0.030])) < 5e-6)
    assert ctl(sock, "optional-stop", "on").returncode == 0
    assert _run(sock, tmp_path, "m1b.ngc", m1).returncode == 0
    _paused_at(sock, (30, 30))
    assert ctl(sock, "resume").returncode == 0
    assert ctl(sock, "wait", "--timeout", "20").returncode == 0
    assert ctl(sock, "optional-stop", "off").returncode == 0
    _no_fault(sock)


def test_jog_of_an_axis_in_command_mode(machine):
    """Incremental (--by), to a position, and continuous (--velocity until --stop) jogs of an
    enabled axis in command mode; a jog past the soft limit is refused, nothing moves."""
    sock = machine.sock
    y0 = _y(sock)
    r = ctl(sock, "jog", "X", "--by", "0.002", "--wait")
    assert r.returncode == 0, r.stdout + r.stderr
    assert abs(_y(sock)[0] - (y0[0] + 0.002)) < 5e-6 and abs(_y(sock)[1] - y0[1]) < 5e-6
    assert ctl(sock, "jog", "Y", "0.050", "--wait").returncode == 0
    assert abs(_y(sock)[1] - 0.050) < 5e-6
    r = ctl(sock, "jog", "X", "--by", "1.0")
    assert r.returncode == 2 and "outside the soft limits" in r.stderr, r.stderr
    x1 = _y(sock)[0]
    r = ctl(sock, "jog", "X", "--velocity", "0.02")
    assert r.returncode == 0, r.stdout + r.stderr
    wait_for(lambda: _y(sock)[0] > x1 + 0.003, 10, "the continuous jog",
             detail=lambda: (status(sock)["motion"], {a: (s["state"], s["phase"], s["fault"])
                                                      for a, s in status(sock)["axes"].items()}))
    assert ctl(sock, "jog", "X", "--stop").returncode == 0
    wait_for(lambda: status(sock)["motion"]["idle"], 10, "the jog's stop")
    x2 = _y(sock)[0]
    assert x1 + 0.003 < x2 < 0.42
    wait_for(lambda: abs(_y(sock)[0] - x2) < 5e-6, 5, "at rest")
    _no_fault(sock)


@pytest.fixture
def shipped_rt(tmp_path):
    """A daemon with configs/gantry.yaml's real-time set-up as shipped (policy best_effort: the
    loop SCHED_FIFO, the setpoint filler SCHED_FIFO below it; without the CPU latency request,
    :func:`test_daemon_helpers.make_config`) and its default lead, both axes in command mode:
    the daemon a user runs beside a busy PC."""
    d = tmp_path / "rt"
    d.mkdir()
    cfg = make_config(d, policy=yaml.safe_load(GANTRY.read_text())["loop"]["realtime"]["policy"])
    with command_mode_daemon(cfg) as dmn:
        yield dmn


@pytest.mark.load
def test_the_override_flipped_above_one_and_back_never_runs_the_stream_dry(shipped_rt, tmp_path, cpu_hogs):
    """Beside CPU hogs (the ``load`` group), on the daemon as shipped (real-time set-up on), the
    feed override flipped 0.5 / 1.5 every 0.4 s through a 6 s program of circles at F3000 (below
    the axes' limits: the override's cap lets 1.5 through): the feed scale seen above 1 and below
    1, no underrun, no row lost, the program's end within 5 um, no fault. (Rows at f·Ts off the
    planner's grid once took 40-80 ms a 625-row block on arcs, more than the 125 ms they last
    under load, and ran the stream dry; with the real-time set-up off, as the file's other
    tests run, the SCHED_OTHER filler beside the hogs and the other worker underran once in
    three fresh-clone runs.)"""
    sock = shipped_rt.sock
    lost0 = status(sock)["log"]["lost_rows"]
    lines = ["G21 G90 G64 P0.01", "G0 X60 Y60", "F3000"]
    for _ in range(3):                       # arcs: each row of a ramp off the grid costs most there
        lines += ["G2 X90 Y60 R15", "G2 X60 Y60 R15"]
    u0 = status(sock)["motion"]["underruns"]
    assert _run(sock, tmp_path, "squares.ngc", "\n".join(lines) + "\nM2\n").returncode == 0
    scales, v = [], 0.5
    for _ in range(100):                     # the program takes 6-9 s; bounded whatever happens
        mo = status(sock)["motion"]
        if mo["idle"] or mo["stopped_because"]:
            break
        assert call(str(sock), {"cmd": "override", "value": v})["ok"]
        v = 2.0 - v
        time.sleep(0.4)
        scales.append(status(sock)["motion"]["feed_scale"])
    assert call(str(sock), {"cmd": "override", "value": 1.0})["ok"]
    assert max(scales) > 1.05 and min(scales) < 0.95, (scales, mo)
    mo = status(sock)["motion"]
    assert mo["underruns"] == u0 and not mo["stopped_because"], mo
    wait_for(lambda: np.all(np.abs(_y(sock) - np.array([0.060, 0.060])) < 5e-6), 5, "the end point")
    _no_fault(sock)
    assert status(sock)["log"]["lost_rows"] == lost0


def test_the_operator_cli_imports_no_numpy():
    """``motorctl status`` (the client path) loads neither numpy nor pydantic nor numba: it
    answers in a fraction of a second on a busy PC."""
    code = ("import sys; from motorctl.cli import main; rc = main(['--socket', '/nonexistent/s', 'status']); "
            "print(rc, sorted(m for m in ('numpy', 'pydantic', 'numba', 'scipy') if m in sys.modules))")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert r.stdout.strip() == "1 []", (r.stdout, r.stderr)
