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
from motorctl.loop.records import MODE_APPROACH, MODE_HOLD, MODE_IDLE, MODE_PROGRAM
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
        n = round(0.7 / ts)                                               # the program's duration
        assert t[k] == pytest.approx(t0) and prog[k:k + n].all()          # every axis starts together
        assert (mode[2:k] == MODE_APPROACH).all()
        assert xd[k] == 0.0 and not rl.col(f"{a}.fault_bits").any()
        # then the stop (category 1): on to the move's end, hold, 0 V
        assert (mode[k + n:] != MODE_APPROACH).all() and not en[-1] and (mode[-1] in (MODE_HOLD, MODE_IDLE))


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


#: the emulators' runs end mid-move: 0.6 s of the program is 0.1 s into both axes' first move
#: (0 -> 0.4 m: X at 2 m/s, Y at 0.8 m/s)
MID_MOVE_S = 0.6
#: runs in a row against one emulator process
RUNS = 3


def _viscous_plant(repo, tmp_path) -> Path:
    """configs/gantry.yaml with carriages that have viscous friction only (no Coulomb friction,
    no stiction, no offset force): a carriage left at speed at 0 V coasts v·m/b (X from 2 m/s:
    1.45 m), a carriage at rest stays."""
    d = load_yaml(repo / "configs" / "gantry.yaml")
    for ax in d["axes"].values():
        ax["driver"].update(coulomb_N=0.0, stiction_N=0.0, offset_N=0.0)
    p = tmp_path / "viscous.yaml"
    p.write_text(yaml.safe_dump(d, sort_keys=False))
    return p


def _on_the_plant(repo, tmp_path, transport: str, plant: Path) -> tuple[Path, float]:
    """configs/gantry-<transport>.yaml aimed at a loopback port, with ``plant``'s controllers
    (tuned for the default plant the emulator simulates; the bus configs' are the paper's, for
    the rigid one), lockstep (virtual clock) at the rate the link's budget allows on loopback.
    Returns (path, rate [Hz])."""
    d = load_yaml(repo / "configs" / f"gantry-{transport}.yaml")
    src = load_yaml(plant)
    for a, ax in d["axes"].items():
        ax["controller"] = src["axes"][a]["controller"]
    d, path = loopback_config(d, tmp_path, driver={"round_trip_s": LOOPBACK_ROUND_TRIP_S[transport]})
    rate = loopback_rate(d)
    d["loop"].update(rate_hz=rate, clock="virtual")
    # lockstep: each cycle waits for its answer, far beyond a loaded host's stall
    d["driver"]["timeout_s"] = 0.05
    if transport == "serial":
        d["driver"]["watchdog_s"] = LOOPBACK_WATCHDOG_S
    path.write_text(yaml.safe_dump(d, sort_keys=False))
    return path, rate


def _assert_category_1_stop(rl, names, a_max, j_max, limits):
    """The rows of a run that ended mid-move: from the stop on, every axis runs on to its rest
    point within a_max [m/s²] and j_max [m/s³] (the jerk over the sampled ẍ_d), holds, then
    goes to 0 V with the amplifier off; it stands at rest inside the soft limits (lo, hi)."""
    ts = rl.header["period_s"]
    for a in names:
        mode, vd, ad = rl.col(f"{a}.mode"), rl.col(f"{a}.xd_dot"), rl.col(f"{a}.xd_ddot")
        en, y, xd = rl.col(f"{a}.enabled"), rl.col(f"{a}.y"), rl.col(f"{a}.x_d")
        prog = np.flatnonzero(mode == MODE_PROGRAM)
        end = int(np.argmax(en[prog[0]:] == 0)) + prog[0]       # the first row at 0 V after the program
        assert vd[end - 1] == 0.0 and ad[end - 1] == 0.0 and mode[end] == MODE_HOLD, (a, end)
        assert not en[end:].any() and not rl.col(f"{a}.fault_bits").any(), a
        stop = prog[0] + round(MID_MOVE_S / ts)                   # the run's duration ended here
        assert abs(vd[stop]) > 0.5, (a, vd[stop])                 # mid-move at the end of the duration
        assert np.abs(ad[stop:end]).max() <= a_max[a] * (1 + 1e-9), a
        assert np.abs(np.diff(ad[stop - 1:end])).max() <= j_max[a] * ts * (1 + 1e-6), a
        assert abs(y[-1] - xd[end - 1]) < 3e-4, (a, y[-1], xd[end - 1])     # at rest where it stopped
        assert limits[a][0] <= y[-1] <= limits[a][1], (a, y[-1])


def test_a_modbus_carriage_below_zero_starts_clean_on_the_shipped_map(repo, tmp_path):
    """A run's category-1 stop leaves a carriage where its move ended, often at the program's
    0 m, a count or two either side. configs/gantry-modbus.yaml's positions are signed (int32):
    carriages standing 3 counts below 0 (X) and 1 count below (Y) are read there, and the run
    approaches from there and exits 0. With the map's former uint32 the first reading was taken
    unsigned, 2147.48 m, and the run was refused outside the soft limits (the 10-runs
    measurement, docs/protection.md)."""
    plant = _viscous_plant(repo, tmp_path)
    d = load_yaml(plant)
    below = {"X": -1.5e-6, "Y": -0.5e-6}                 # -3 and -1 counts of 0.5 um
    for a, x in below.items():
        d["axes"][a]["driver"]["initial_position_m"] = x
    plant.write_text(yaml.safe_dump(d, sort_keys=False))
    cfg, _rate = _on_the_plant(repo, tmp_path, "modbus", plant)
    log = tmp_path / "run.mlog"
    with Emulator("modbus", cfg, plant=plant, watchdog_s=LOOPBACK_WATCHDOG_S) as emu:
        r = run_cli(["run", str(cfg), "--duration", "0.2", "--log", str(log)], timeout_s=120)
        assert r.returncode == 0, f"{r.stdout}{r.stderr}{emu.stderr()}"
    table = parse_run_table(r.stdout)
    assert set(table) == {"X", "Y"} and not any(t["fault"] for t in table.values()), r.stdout
    approach = read_log(str(log)).header["approach"]
    for a, x in below.items():
        assert approach[a]["from_m"] == pytest.approx(x, abs=1e-9), (a, approach[a])


@pytest.mark.parametrize("transport", ["serial", "modbus"])
def test_runs_that_end_mid_move_stop_in_category_1_and_the_next_starts_clean(repo, tmp_path, transport):
    """IEC 60204-1 §9.2.2 stop category 1 at the end of a run: ``motorctl run``s in a row
    against one emulator process (``motorctl emulate``) whose carriages have viscous friction
    only, each run's duration ending mid-move (X at 2 m/s, Y at 0.8 m/s). Each run brings every
    axis to rest under power along the move's jerk-limited profile (within the axis's a_max and
    j_max), then 0 V with the amplifier off confirmed by the device; the stop line says where
    they came to rest, inside the soft limits, and the next run starts from there without
    waiting (the axes stand still) and without a fault. Cut at 0 V instead (stop category 0),
    X coasts 1.45 m and every later run is refused outside the soft limits."""
    plant = _viscous_plant(repo, tmp_path)
    cfg, rate = _on_the_plant(repo, tmp_path, transport, plant)
    d = load_yaml(cfg)
    a_max = {a: ax["trajectory"]["a_max"] for a, ax in d["axes"].items()}
    j_max = {a: ax["trajectory"]["j_max"] for a, ax in d["axes"].items()}
    limits = {a: (ax["limits"]["soft_min_m"], ax["limits"]["soft_max_m"]) for a, ax in d["axes"].items()}
    logs = [tmp_path / f"run{k}.mlog" for k in range(RUNS)]
    with Emulator(transport, cfg, plant=plant, watchdog_s=LOOPBACK_WATCHDOG_S) as emu:
        for k, log in enumerate(logs):
            r = run_cli(["run", str(cfg), "--duration", f"{MID_MOVE_S:g}", "--log", str(log)], timeout_s=120)
            table = parse_run_table(r.stdout)
            assert r.returncode == 0 and set(table) == {"X", "Y"}, f"run {k + 1}: {r.stdout}{r.stderr}{emu.stderr()}"
            assert not any(t["fault"] for t in table.values()), f"run {k + 1}: {r.stdout}"
            stop = [ln for ln in r.stdout.splitlines() if ln.startswith("stop: ")]
            assert len(stop) == 1 and "at 0 V, amplifiers off (confirmed by the device" in stop[0], r.stdout
            rl = read_log(str(log))
            rest = rl.header["rest"]
            assert f"came to rest at X {rest['X']['at_m']:.6f} m, Y {rest['Y']['at_m']:.6f} m (stop category 1)" \
                in stop[0], stop[0]
            _assert_category_1_stop(rl, ("X", "Y"), a_max, j_max, limits)
            for a in ("X", "Y"):
                assert rest[a] == {"at_m": pytest.approx(0.4, abs=3e-4), "category": 1}, (k, a, rest)
                if k:            # stood still where the previous run left it (within 0.1 mm): two idle reads
                    assert rl.header["approach"][a]["from_m"] == pytest.approx(rest[a]["at_m"], abs=1e-4)
                    assert int(np.argmax(rl.col(f"{a}.mode") != MODE_IDLE)) == 2, (k, a)


def test_a_simulated_run_that_ends_mid_move_stops_in_category_1(default_yaml, tmp_path):
    """The simulated driver, the default plant: a run whose duration ends mid-move (X at
    2 m/s, Y at 0.8 m/s) decelerates on the path within a_max/j_max to rest, then 0 V; the
    stop line names where the axes came to rest (stop category 1); the indexes cover the run's
    duration only (its program rows), the stop's rows are in the log."""
    log = tmp_path / "run.mlog"
    r = run_cli(["run", str(default_yaml), "--duration", f"{MID_MOVE_S:g}", "--virtual-clock", "--log", str(log)],
                timeout_s=600)
    assert r.returncode == 0, r.stdout + r.stderr
    d = load_yaml(default_yaml)
    rl = read_log(str(log))
    _assert_category_1_stop(rl, ("X", "Y"), {a: ax["trajectory"]["a_max"] for a, ax in d["axes"].items()},
                            {a: ax["trajectory"]["j_max"] for a, ax in d["axes"].items()},
                            {a: (ax["limits"]["soft_min_m"], ax["limits"]["soft_max_m"]) for a, ax in d["axes"].items()})
    assert "(stop category 1)" in r.stdout and rl.header["rest"]["X"]["category"] == 1, r.stdout
    # the indexes: the run's duration of program rows, as before the stop existed
    from motorctl.metrics import TrackingAccumulator
    ts = rl.header["period_s"]
    for a, row in parse_run_table(r.stdout).items():
        mode, t = rl.col(f"{a}.mode"), rl.col("t")
        k = np.flatnonzero(mode == MODE_PROGRAM)[:round(MID_MOVE_S / ts)]
        acc = TrackingAccumulator(4.0, ts)
        acc.add(t[k] - t[k[0]], rl.col(f"{a}.e")[k], rl.col(f"{a}.u")[k])
        assert row["e_M_um"] == pytest.approx(acc.indexes()["e_M_um"], abs=0.01), a


@pytest.mark.parametrize("during", ["build", "start"])
def test_sigterm_during_start_up_is_one_line_and_nothing_left_driven(default_yaml, monkeypatch, capsys, during):
    """SIGTERM while ``motorctl run`` starts up (in process, the signal sent to itself from
    inside the step): during the loop's build (the compile, before the device is opened) one
    line and exit 1, nothing driven; during the driver's set-up the run's own stop: no cycle,
    0 V confirmed by the device, one stop line (before, the build's signal ended the process
    with 143 and printed nothing)."""
    import os
    import signal

    import motorctl.app.job as job
    from motorctl.cli import main
    real = getattr(job, during)

    def signalled(*a, **k):
        os.kill(os.getpid(), signal.SIGTERM)
        return real(*a, **k)

    monkeypatch.setattr(job, during, signalled)
    code = main(["run", str(default_yaml), "--duration", "0.5", "--virtual-clock"])
    out, err = capsys.readouterr()
    assert code == 1 and "Traceback" not in err, (out, err)
    assert signal.getsignal(signal.SIGTERM) is signal.SIG_DFL     # the caller's handlers given back
    if during == "build":
        assert out == "" and err.splitlines()[-1] == ("motorctl: stopped by SIGTERM during start-up, before the "
                                                      "device was opened: nothing was driven"), (out, err)
    else:
        stop = [ln for ln in out.splitlines() if ln.startswith("stopped by SIGTERM: ")]
        assert len(stop) == 1 and "X, Y at 0 V, amplifiers off (confirmed by the device" in stop[0], out
        assert "loop:" not in out, out                                  # not one cycle ran
