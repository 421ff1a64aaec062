"""``motorctl run`` starts as the daemon's ``start`` does: cycle 0 idle reads where the axes
stand, a jerk-limited approach to the programs' first points, then the programs; the indexes
take the program's rows only. A run after one that ended elsewhere (mid-move, a fault) starts
cleanly; a start outside the soft limits is refused with nothing driven."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml
from harness import (LOOPBACK_ROUND_TRIP_S, LOOPBACK_WATCHDOG_S, Emulator, loopback_config, loopback_rate,
                     parse_run_table, run_cli)

from motorctl.config import load_yaml
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


#: the serial emulator's runs: the first ends mid-move (X at 1 m/s, Y at 0.25 m/s: both
#: accelerating out of 0 towards 0.4 m), the others once both stand at 0.4 m
FIRST_S, LATER_S = 0.53, 1.2


def _serial_on_the_default_plant(repo, tmp_path) -> tuple[Path, float]:
    """configs/gantry-serial.yaml aimed at a loopback port, with configs/gantry.yaml's
    controllers (those tuned for the default plant the emulator simulates; the serial config's
    are the paper's, for the rigid one), lockstep (virtual clock) at the rate the serial link's
    budget allows on loopback. Returns (path, rate [Hz])."""
    d = load_yaml(repo / "configs" / "gantry-serial.yaml")
    plant = load_yaml(repo / "configs" / "gantry.yaml")
    for a, ax in d["axes"].items():
        ax["controller"] = plant["axes"][a]["controller"]
    d, path = loopback_config(d, tmp_path, driver={"round_trip_s": LOOPBACK_ROUND_TRIP_S["serial"]})
    rate = loopback_rate(d)
    d["loop"].update(rate_hz=rate, clock="virtual")
    # lockstep: each cycle waits for its answer, far beyond a loaded host's stall
    d["driver"].update(timeout_s=0.05, watchdog_s=LOOPBACK_WATCHDOG_S)
    path.write_text(yaml.safe_dump(d, sort_keys=False))
    return path, rate


def test_five_serial_emulator_runs_in_a_row_the_first_ending_mid_move(repo, tmp_path):
    """Five ``motorctl run``s against one serial emulator process (``motorctl emulate``, the
    default plant: stiction, the 350 Hz mode, noise), the first ending mid-move. The plant stands
    still between runs (it steps with the master's cycles), so run 2's idle cycles see the
    carriages coast at 0 V to where friction stops them and wait for it; every later run
    approaches from where the axes stand and runs its program without a fault (without the
    approach the program's first point is up to 0.4 m away: a following error at cycle 0, the
    issue's "4 of 4 faulted"). Between runs the device's watchdog latches (no host for longer
    than 0.2 s): each run clears it at set-up."""
    cfg, rate = _serial_on_the_default_plant(repo, tmp_path)
    logs = [tmp_path / f"run{k}.mlog" for k in range(5)]
    with Emulator("serial", cfg, plant=repo / "configs" / "gantry.yaml", watchdog_s=LOOPBACK_WATCHDOG_S) as emu:
        for k, log in enumerate(logs):
            r = run_cli(["run", str(cfg), "--duration", f"{FIRST_S if k == 0 else LATER_S:g}", "--log", str(log)],
                        timeout_s=120)
            table = parse_run_table(r.stdout)
            assert r.returncode == 0 and set(table) == {"X", "Y"}, f"run {k + 1}: {r.stdout}{r.stderr}{emu.stderr()}"
            assert not any(t["fault"] for t in table.values()), f"run {k + 1}: {r.stdout}"
    runs = [read_log(str(p)) for p in logs]
    ts = 1.0 / rate
    for a in ("X", "Y"):
        assert runs[0].col(f"{a}.xd_dot")[-1] > 0.2, a                     # the first ended mid-move
        for k in range(1, 5):
            rl, prev = runs[k], runs[k - 1]
            frm = rl.header["approach"][a]["from_m"]
            if k == 1:   # coasted on from where the first run ended, stopped inside the soft limits
                assert prev.col(f"{a}.y")[-1] + 0.01 < frm < 0.42, (a, frm)
            else:        # the previous run's program ended standing at 0.4 m
                assert frm == pytest.approx(prev.col(f"{a}.y")[-1], abs=2e-6) == pytest.approx(0.4, abs=1e-4)
            # idle reads (run 2: until the coasting carriages stood), the approach, the program
            mode = rl.col(f"{a}.mode")
            i, j = int(np.argmax(mode != MODE_IDLE)), int(np.argmax(mode == MODE_PROGRAM))
            assert i >= (2 if k > 1 else 10) and (mode[:i] == MODE_IDLE).all(), (a, k, i)
            assert (mode[i:j] == MODE_APPROACH).all() and (mode[j:] == MODE_PROGRAM).all()
            assert (j - i) * ts >= rl.header["approach"][a]["duration_s"] - ts, (a, k, i, j)
            assert j - i > 100 and mode.size - j == round(LATER_S * rate)
            assert not rl.col(f"{a}.fault_bits").any()
