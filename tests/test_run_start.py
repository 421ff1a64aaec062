"""``motorctl run`` starts as the daemon's ``start`` does: cycle 0 idle reads where the axes
stand, a jerk-limited approach to the programs' first points, then the programs; the indexes
take the program's rows only. A run after one that ended elsewhere (mid-move, a fault) starts
cleanly; a start outside the soft limits is refused with nothing driven."""

from __future__ import annotations

import numpy as np
import pytest
import yaml
from harness import device_thread, run_cli

from motorctl.app.job import run_job
from motorctl.config import config_from_dict, load_yaml
from motorctl.loop.records import MODE_APPROACH, MODE_IDLE, MODE_PROGRAM
from motorctl.recorder.runlog import read_log


def _at(default_yaml, tmp_path, **initial):
    """configs/gantry.yaml with the sim's axes starting at ``initial`` [m], as a file."""
    d = yaml.safe_load(open(default_yaml))
    for a, x in initial.items():
        d["axes"][a]["driver"]["initial_position_m"] = x
    p = tmp_path / "start.yaml"
    p.write_text(yaml.safe_dump(d))
    return p


def test_a_run_from_mid_stroke_approaches_then_runs_the_program(default_yaml, tmp_path):
    """Where a run that ended mid-move left the axes (X at 0.2 m, Y at 0.05 m): no fault, the
    approach in the rows (mode approach), the program from its first point after it."""
    log = tmp_path / "run.log"
    r = run_cli(["run", str(_at(default_yaml, tmp_path, X=0.2, Y=0.05)), "--duration", "0.7",
                 "--virtual-clock", "--log", str(log)], timeout_s=600)
    assert r.returncode == 0, r.stdout + r.stderr
    rl = read_log(str(log))
    h, ts = rl.header, rl.header["period_s"]
    assert h["approach"]["X"]["from_m"] == pytest.approx(0.2, abs=1e-5) and h["approach"]["X"]["to_m"] == 0.0
    t0 = h["program_start_s"]
    # two idle cycles (the axes stand still: two readings agree), the approaches, the programs
    assert t0 == pytest.approx(max(a["duration_s"] for a in h["approach"].values()) + 3 * ts, abs=ts)
    t = rl.col("t")
    for a in ("X", "Y"):
        mode, u, en, xd = rl.col(f"{a}.mode"), rl.col(f"{a}.u"), rl.col(f"{a}.enabled"), rl.col(f"{a}.x_d")
        assert (mode[:2] == MODE_IDLE).all() and not u[:2].any() and not en[:2].any()   # read, not driven
        prog = mode == MODE_PROGRAM
        k = int(np.argmax(prog))
        assert t[k] == pytest.approx(t0) and prog[k:].all()               # every axis starts together
        assert (mode[2:k] == MODE_APPROACH).all()
        assert xd[k] == 0.0 and not rl.col(f"{a}.fault_bits").any()
        assert int(prog.sum()) == round(0.7 / ts)                         # the program's duration


def test_a_start_outside_the_soft_limits_is_refused_and_nothing_is_driven(default_yaml, tmp_path):
    log = tmp_path / "run.log"
    r = run_cli(["run", str(_at(default_yaml, tmp_path, X=0.5)), "--duration", "0.5", "--virtual-clock",
                 "--log", str(log)], timeout_s=600)
    assert r.returncode == 1, r.stdout + r.stderr
    assert r.stderr.count("\n") == 1 and "Traceback" not in r.stderr, r.stderr
    assert "axis X stands at 0.500000 m, outside its soft limits [-0.02, 0.42] m" in r.stderr, r.stderr
    rl = read_log(str(log))
    assert rl.col("X.u").shape[0] >= 1
    for a in ("X", "Y"):
        assert not rl.col(f"{a}.u").any() and not rl.col(f"{a}.enabled").any()


def test_serial_emulator_runs_after_a_run_that_ended_away_from_the_start(repo, tmp_path, monkeypatch):
    """Three runs in a row against one serial device (in-process, over a pty): the first ends
    mid-program (1.5 s: X and Y stand at 0.4 m, the program starts at 0), each later one
    approaches from where the axes stand and exits without a fault (without the approach the
    program's first point is 0.4 m away: a following error at once)."""
    from motorctl_drivers.serial_link import SerialDriver
    from motorctl_emulators.device import build_device
    monkeypatch.setattr(SerialDriver, "CONFIGURE_TIMEOUT_S", 10.0)     # the device shares our GIL
    d = load_yaml(repo / "configs" / "gantry-serial.yaml")
    d["loop"].update(rate_hz=1000, clock="virtual")
    # the device shares this process's GIL: its watchdog far above a loaded host's stalls
    d["driver"].update(port=str(tmp_path / "ttyEMU"), timeout_s=2.0, wait="spin", watchdog_s=1.0)
    loaded = config_from_dict(d, "<serial>", check_budget=False)
    starts = []
    # the emulator's plant: the paper's rigid one, as the end-to-end tests (at this 1 kHz loop the C2
    # gains of configs/gantry.yaml excite its 350 Hz mode: a limit cycle at rest, rightly tripped)
    with device_thread(build_device(loaded, repo / "configs" / "gantry-rigid.yaml", watchdog_s=0.25)):
        for _ in range(3):
            res = run_job(loaded, duration_s=1.5, clock="virtual")
            assert all(not r["fault"] for r in res.axes.values()), [(r["fault"], res.cycles, res.approach) for r in res.axes.values()]
            starts.append(res.approach["X"]["from_m"])
    assert abs(starts[0]) < 1e-3 and all(abs(s - 0.4) < 1e-3 for s in starts[1:]), starts
