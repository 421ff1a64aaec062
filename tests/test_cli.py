"""The CLI end to end: run (virtual and wall clock), the run log, plot, compare --json, SIGTERM."""

import gc
import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
from conftest import MOTORCTL, console_script

from motorctl.cli import main
from motorctl.recorder.runlog import read_log


def test_run_prints_indexes_and_writes_a_log(tmp_path, capsys, gantry_yaml):
    log = tmp_path / "run.mclog"
    code = main(["run", str(gantry_yaml), "--duration", "2", "--virtual-clock", "--log", str(log)])
    out = capsys.readouterr().out
    assert code == 0
    for word in ("e_M um", "e_F um", "L2[e] um", "u_peak V", "turnaround p50", "p99.9", "overruns", "realtime:"):
        assert word in out
    rl = read_log(str(log))
    assert rl.axes == ["X", "Y"]
    prog = rl.col("X.mode") == 2                    # two idle cycles, a 0 s approach, the program
    assert prog[3:10003].all() and prog[:3].sum() == 0
    # then the stop (category 1): X stands at 0 already, the row that sees it, the settle held, 0 V
    settle = round(0.1 * 5000)
    assert rl.data.shape[0] == 10003 + 1 + settle and (rl.col("X.mode")[10004:] == 3).all()
    assert not rl.col("X.enabled")[-1] and rl.col("X.enabled")[-2]
    t = rl.col("t")
    assert np.allclose(np.diff(t), 2e-4)
    assert rl.header["driver"]["simulated"]["X"]["theta_true"][0] == pytest.approx(0.16)
    # the indexes printed are those of the log's program rows
    e = rl.col("X.e")[3:10003]
    assert f"{np.max(np.abs(e)) * 1e6:.2f}" in out
    assert np.all(rl.col("X.enabled")[2:-1] == 1.0)


def test_run_one_axis_with_c1(capsys, gantry_yaml):
    code = main(["run", str(gantry_yaml), "--axis", "Y", "--controller", "c1", "--duration", "1", "--virtual-clock"])
    out = capsys.readouterr().out
    assert code == 0
    lines = [ln for ln in out.splitlines() if ln.startswith(("X ", "Y "))]
    assert len(lines) == 1 and lines[0].split()[1] == "c1"


def test_unknown_axis_is_a_clear_error(capsys, gantry_yaml):
    assert main(["run", str(gantry_yaml), "--axis", "Z", "--duration", "1", "--virtual-clock"]) == 2
    err = capsys.readouterr().err
    assert "no axis 'Z'" in err and "X, Y" in err


def test_plot_makes_figures(tmp_path, capsys, gantry_yaml):
    log = tmp_path / "run.mclog"
    assert main(["run", str(gantry_yaml), "--duration", "4.5", "--virtual-clock", "--log", str(log)]) == 0
    capsys.readouterr()
    assert main(["plot", str(log), "--out", str(tmp_path / "fig")]) == 0
    files = capsys.readouterr().out.split()
    assert len(files) >= 4
    for f in files:
        data = open(f, "rb").read()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 5000


def test_plot_rejects_a_non_log(tmp_path, capsys):
    bad = tmp_path / "x.mclog"
    bad.write_bytes(b"hello")
    assert main(["plot", str(bad)]) == 2
    assert "not a motorctl run log" in capsys.readouterr().err


def test_console_script_compare_json_short(gantry_yaml):
    # the installed console script (beside this interpreter), as a user runs it: stdout is
    # exactly one JSON object
    p = subprocess.run([str(console_script()), "compare", str(gantry_yaml), "--duration", "2", "--json"],
                       capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr
    obj = json.loads(p.stdout)
    assert set(obj) == {"X", "Y"}
    for ax in obj.values():
        assert set(ax) == {"c1", "c2", "pid"}      # every controller configured on both axes
        for r in ax.values():
            assert set(r) == {"e_M_um", "e_F_um", "L2_um", "u_peak_V"}


def test_sigterm_stops_a_wall_clock_run_safely(tmp_path, gantry_yaml):
    log = tmp_path / "term.mclog"
    p = subprocess.Popen([*MOTORCTL, "run", str(gantry_yaml), "--duration", "60",
                          "--log", str(log), "--realtime", "off"],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        first = p.stdout.readline()  # printed once the driver is open, just before the first cycle
        assert first.startswith("running X, Y at 5000 Hz"), first
        time.sleep(1.0)
        p.send_signal(signal.SIGTERM)
        out, err = p.communicate(timeout=60)
    finally:
        if p.poll() is None:
            p.kill()
    assert "stopped by SIGTERM" in out, (out, err)
    rl = read_log(str(log))
    assert 0 < rl.data.shape[0] < 60 * 5000
    assert rl.header["stopped_by_signal"] == "SIGTERM"
    assert os.path.getsize(log) > 0


def test_the_default_config_runs_without_a_fault(capsys, default_yaml):
    """configs/gantry.yaml (structural modes, current loop, encoder noise) at its chosen gains:
    every controller configured runs a short virtual-clock program without a fault."""
    for kind in ("c1", "c2", "pid"):
        code = main(["run", str(default_yaml), "--duration", "3", "--virtual-clock", "--controller", kind])
        out = capsys.readouterr().out
        assert code == 0, out
        rows = [ln.split() for ln in out.splitlines() if ln.split()[:1] in (["X"], ["Y"])]
        assert [r[1] for r in rows] == [kind, kind] and all(r[-1] == "-" for r in rows), out


def test_only_the_process_command_line_freezes_the_collector(capsys):
    """main() on the process's own command line freezes the garbage collector before the
    process exits (its last collections would walk every imported object); a call with words,
    in a caller's process (these tests), leaves the caller's collector alone."""
    before = gc.get_freeze_count()
    assert main(["--help"]) == 0 and "COMMAND" in capsys.readouterr().out
    assert gc.get_freeze_count() == before
    code = ("import gc, sys; from motorctl.cli import main; sys.argv = ['motorctl', '--help']; "
            "rc = main(); sys.stderr.write(f'{rc} {gc.get_freeze_count()}')")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    rc, frozen = done.stderr.split()
    assert rc == "0" and int(frozen) > 0 and "COMMAND" in done.stdout
