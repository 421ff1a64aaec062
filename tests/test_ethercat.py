"""EtherCAT end to end: ``motorctl run`` on pysoem (SOEM, a master nobody here wrote) against the
emulated segment (``motorctl emulate --transport ethercat``: a CiA 402 drive for X, an EK1100
coupler and EL5101 / EL4132 / EL2008-type terminals for Y) on a veth pair inside a network
namespace the test makes (root only). Plus the parts that need no network: the ESC model's
addressing, working counter, SII checksum and AL state machine; the budget; bad YAML.
"""

from __future__ import annotations

import os
import re
import shutil
import signal
import struct
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from harness import Emulator, NetNamespace, motorctl_cmd, parse_run_table, run_cli, run_cli_interrupted
from machine import module_paths, unreadable_as
from motorctl.loop.safety import FAULT_AMP_FAULT
from motorctl.recorder.runlog import read_log
from motorctl_emulators import esc as E

REPO = Path(__file__).resolve().parents[1]
CONFIG = REPO / "configs" / "gantry-ethercat.yaml"
PLANT = REPO / "configs" / "gantry.yaml"
VETH = ("ecm0", "ecm0-slave")

needs_netns = pytest.mark.skipif(os.geteuid() != 0 or shutil.which("unshare") is None or shutil.which("ip") is None,
                                 reason="needs root, unshare and ip (a network namespace with a veth pair)")


def _config(tmp_path: Path, config: Path = CONFIG, **driver) -> Path:
    d = yaml.safe_load(config.read_text())
    d["loop"]["clock"] = "virtual"        # lockstep with the emulated segment; SM-synchronous
    # lockstep: a frame that comes back is waited for far beyond a loaded host's stall
    d["driver"].update({"ifname": VETH[0], "sync0": False, "watchdog_ms": 200.0, "timeout_s": 0.5, **driver})
    path = tmp_path / "ethercat.yaml"
    path.write_text(yaml.safe_dump(d, sort_keys=False))
    return path


def _run(tmp_path, duration_s: float, faults=(), config: Path = CONFIG, after=None, **driver):
    """``motorctl run`` against the emulated segment; ``after(ns)``: run in the namespace
    before the emulator stops (its output is returned third)."""
    import pysoem  # noqa: F401 - the test extra installs it: missing is an error, never a skip
    cfg = _config(tmp_path, config, **driver)
    with NetNamespace(veth=VETH) as ns, Emulator("ethercat", cfg, plant=PLANT, prefix=ns.prefix,
                                                 faults=list(faults)) as emu:
        r = run_cli(["run", str(cfg), "--duration", f"{duration_s:g}", "--log", str(tmp_path / "run.mlog")],
                    prefix=ns.prefix, timeout_s=120)
        extra = after(ns) if after else None
        err = emu.stderr()
    return (r, err, extra) if after else (r, err)


#: a second pysoem master reads the drive's objects the driver changes (PRE-OP, CoE)
READ_DRIVE = """
import pysoem
m = pysoem.Master()
m.open("{ifname}")
m.config_init()
m.state = pysoem.PREOP_STATE
m.write_state()
assert m.state_check(pysoem.PREOP_STATE, 2_000_000) == pysoem.PREOP_STATE
s = m.slaves[0]
u = lambda i, k: int.from_bytes(s.sdo_read(i, k), "little")
print("found", [u(0x1C12, 0), u(0x1C12, 1), u(0x1600, 0), hex(u(0x1600, 1)), u(0x1C13, 0), u(0x1A00, 0),
                hex(u(0x1A00, 1)), u(0x6060, 0)])
"""


def _read_drive(ns) -> str:
    import sys
    r = subprocess.run([*ns.prefix, sys.executable, "-c", READ_DRIVE.format(ifname=VETH[0])],
                       capture_output=True, text=True, timeout=60)
    return r.stdout + r.stderr[-2000:]


@needs_netns
def test_soem_brings_the_segment_to_op_and_the_loop_runs_both_profiles(tmp_path):
    r, err, found = _run(tmp_path, 1.0, after=_read_drive)
    table = parse_run_table(r.stdout)
    assert r.returncode == 0 and set(table) == {"X", "Y"}, f"{r.stdout}\n{r.stderr}\n{err}"
    # SAFE-OP's short working counter (outputs not counted) is expected there: no error counted;
    # the loop's last frame is received before the stop (SOEM would add two frames' counters up)
    from motorctl.recorder.runlog import open_log
    counters = open_log(tmp_path / "run.mlog").header["driver"]["counters"]
    assert counters["wkc_errors"] == 0 and counters["no_frame"] == 0, repr(counters)
    # the drive's PDO mapping and mode of operation as the driver found them (the emulated drive's
    # defaults: 0x1600 = controlword, 0x1A00 = statusword, mode 0), not the CST mapping of the run
    assert "found [1, 5632, 1, '0x60400010', 1, 1, '0x60410010', 0]" in found, found
    # the paper's program through a CiA 402 drive (per mille torque) and through ±10 V terminals:
    # the errors of the simulated gantry's first second (X 36.4 um, Y 11.0 um), not a runaway
    assert 20.0 < table["X"]["e_M_um"] < 60.0 and 5.0 < table["Y"]["e_M_um"] < 20.0, r.stdout
    assert table["X"]["io_errors"] == 0 and table["Y"]["io_errors"] == 0, r.stdout
    # the stop is read back from the devices: the drive's statusword and torque, the terminals'
    # output buffers in the ESC's RAM
    assert re.search(r"confirmed by the device: X statusword 0x0240 \(Switch on disabled\), torque actual "
                     r"0x6077 = 0 per mille; Y slave 4 channel 1 holds 0 \(0\.000 V\), slave 5 channel 1 = 0 "
                     r"\(amplifier off\)", r.stdout), r.stdout
    assert "1: motorctl CiA402 drive, 2: EK1100" in err and "first command X" in err
    _within_10_percent_of_the_sim(table, 1.0)


@needs_netns
def test_a_run_after_a_run_that_ended_mid_move_approaches_and_runs(tmp_path):
    """Two ``motorctl run``s against one emulated segment: the first's duration ends mid-move
    (0.53 s: X at 1 m/s, Y at 0.25 m/s, both leaving 0 for 0.4 m); its stop is of category 1
    (IEC 60204-1 §9.2.2): the move runs on to its end at 0.4 m, then 0 V; the second approaches
    from where the first came to rest to the program's first point and runs its program without
    a fault (without the approach: a following error at its first cycle, millimetres off)."""
    import pysoem  # noqa: F401 - the test extra installs it: missing is an error, never a skip
    from motorctl.loop.records import MODE_APPROACH, MODE_IDLE, MODE_PROGRAM
    cfg = _config(tmp_path)
    logs = [tmp_path / "first.mlog", tmp_path / "second.mlog"]
    with NetNamespace(veth=VETH) as ns, Emulator("ethercat", cfg, plant=PLANT, prefix=ns.prefix) as emu:
        for log, seconds in zip(logs, ("0.53", "0.3")):
            r = run_cli(["run", str(cfg), "--duration", seconds, "--log", str(log)], prefix=ns.prefix, timeout_s=120)
            table = parse_run_table(r.stdout)
            assert r.returncode == 0 and set(table) == {"X", "Y"}, f"{r.stdout}\n{r.stderr}\n{emu.stderr()}"
            assert not table["X"]["fault"] and not table["Y"]["fault"], r.stdout
    first, second = (read_log(str(p)) for p in logs)
    t = first.col("t")
    end = int(np.searchsorted(t, first.header["program_start_s"] + 0.53))
    for a in ("X", "Y"):
        assert first.col(f"{a}.xd_dot")[end] > 0.2, a                    # the duration ended mid-move
        assert first.col(f"{a}.xd_dot")[-1] == 0.0, a                    # ... and the stop at rest
        rest = first.header["rest"][a]
        frm = second.header["approach"][a]["from_m"]
        assert rest["category"] == 1 and abs(rest["at_m"] - 0.4) < 0.002, (a, rest)
        assert abs(frm - rest["at_m"]) < 0.001 and frm < 0.42, (a, frm, rest)   # stood where it stopped
        mode = second.col(f"{a}.mode")
        i, j = int(np.argmax(mode != MODE_IDLE)), int(np.argmax(mode == MODE_PROGRAM))
        k = int(np.searchsorted(second.col("t"), second.header["program_end_s"]))   # its stop's rows follow
        assert i >= 2 and (mode[i:j] == MODE_APPROACH).all() and j - i > 100 and (mode[j:k] == MODE_PROGRAM).all()
        assert not second.col(f"{a}.fault_bits").any()


def _within_10_percent_of_the_sim(table: dict, duration_s: float) -> None:
    """e_M and L2[e] of a run through the segment within 10 % of the simulated driver's on the
    same plant, seed and program (lockstep: the same samples)."""
    from motorctl.app.job import run_job
    from motorctl.config import load_config
    ref = run_job(load_config(PLANT), controller="c2", duration_s=duration_s, clock="virtual")
    for a in ("X", "Y"):
        for key in ("e_M_um", "L2_um"):
            assert abs(table[a][key] - ref.axes[a][key]) <= 0.10 * ref.axes[a][key], (a, key, table[a], ref.axes[a])


@needs_netns
def test_the_paper_set_up_on_terminals_for_both_axes(tmp_path):
    """configs/gantry-ethercat-io.yaml: both amplifiers behind one EL4132 (two channels) and one
    EL2008, each encoder on its EL5101; the stop read back from the terminals' RAM."""
    r, err = _run(tmp_path, 1.0, config=REPO / "configs" / "gantry-ethercat-io.yaml")
    table = parse_run_table(r.stdout)
    assert r.returncode == 0 and set(table) == {"X", "Y"}, f"{r.stdout}\n{r.stderr}\n{err}"
    assert table["X"]["io_errors"] == 0 and table["Y"]["io_errors"] == 0, r.stdout
    assert "X slave 4 channel 1 holds 0 (0.000 V), slave 5 channel 1 = 0 (amplifier off); Y slave 4 channel 2 " \
           "holds 0 (0.000 V), slave 5 channel 2 = 0 (amplifier off)" in r.stdout, r.stdout
    _within_10_percent_of_the_sim(table, 1.0)


@needs_netns
def test_a_short_working_counter_latches_a_fault_that_names_it(tmp_path):
    # from the 500th process-data frame on, Y's slaves do not count: 9 of 10. The slaves still
    # take every frame's outputs, so only a host stall (either process held off for longer than
    # the SM watchdog, on the wall clock) could take them out of OP (SAFE-OP + 0x001B, which the
    # driver would then report, truthfully, instead): a 5 s SM watchdog, far beyond any stall
    r, err = _run(tmp_path, 0.6, faults=["corrupt:Y:500:100000"], watchdog_ms=5000.0)
    table = parse_run_table(r.stdout)
    assert table["X"]["fault"] and table["Y"]["fault"], f"{r.stdout}\n{r.stderr}\n{err}"
    assert "driver error bucket full" in table["Y"]["fault"], r.stdout
    assert "drive: EtherCAT working counter 9 of 10" in table["Y"]["fault"], r.stdout
    # a segment that still does not count fully cannot confirm the stop: said, exit code 3
    assert r.returncode == 3 and "axis Y: the stop is NOT confirmed by the device: no complete working " \
        "counter after the stop (last 9 of 10)" in r.stderr, r.stderr


@needs_netns
def test_an_emergency_of_the_drive_latches_its_code_and_meaning(tmp_path):
    """The drive faults (EMCY 0x2310) mid-run: X latches, named by 0x603F. The drive stays in
    Fault: a new master's set-up finds it there (``motorctl run`` would be refused naming its state
    and the command, :func:`motorctl.driver.drive_fault_refusal`; before: "amplifier fault (value 1,
    limit 0)" alone), and ``motorctl fault-reset --config CONFIG X`` (no daemon) sends transition
    15 over the process data."""
    def after(ns):
        return run_cli(["fault-reset", "--config", str(tmp_path / "ethercat.yaml"), "X"], prefix=ns.prefix,
                       timeout_s=120)

    r, err, reset = _run(tmp_path, 0.6, faults=["emcy=0x2310:X:1000"], after=after)
    table = parse_run_table(r.stdout)
    assert r.returncode == 1 and "amplifier fault" in table["X"]["fault"] and table["Y"]["fault"] == "", \
        f"{r.stdout}\n{r.stderr}\n{err}"
    assert "error code 0x603F = 0x2310 continuous over-current" in table["X"]["fault"], r.stdout
    assert "X: fault 0x2310 continuous over-current (injected)" in err
    # collected through pysoem's emergency callback, not its deprecated exception (FutureWarning)
    assert "FutureWarning" not in r.stderr, r.stderr
    assert reset.returncode == 0, reset.stdout + reset.stderr
    assert re.search(r"^X: the drive's fault is reset: was EtherCAT slave 1 \(CiA 402 drive, axis X\) is in Fault "
                     r"\(statusword 0x[0-9A-F]{4}\); EtherCAT slave 1 \(CiA 402 drive, axis X\): error code 0x603F = "
                     r"0x2310 continuous over-current; now EtherCAT slave 1 \(CiA 402 drive, axis X\) is in Switch on "
                     r"disabled", reset.stdout, re.M), reset.stdout
    assert "X, Y at 0 V, amplifiers off (confirmed by the device" in reset.stdout, reset.stdout
    print(reset.stdout)


def _signalled(cfg: Path, steps, stop_emulator: bool = False, log: Path | None = None):
    """``motorctl run`` (30 s) against the segment, sent ``steps`` [(after_s, signal), ...] from
    its first line on. Returns (its CompletedProcess, the emulator's stop lines when
    ``stop_emulator`` (0.5 s after the run), the emulator's stderr). ``log``: the run's log."""
    import pysoem  # noqa: F401 - the test extra installs it: missing is an error, never a skip
    with NetNamespace(veth=VETH) as ns, Emulator("ethercat", cfg, plant=PLANT, prefix=ns.prefix) as emu:
        def act(proc):
            for after_s, sig in steps:
                time.sleep(after_s)
                os.killpg(proc.pid, sig)
        _first, r = run_cli_interrupted(["run", str(cfg), "--duration", "30", *(["--log", str(log)] if log else [])],
                                        act, prefix=ns.prefix,
                                        timeout_s=60)
        out = ""
        if stop_emulator:
            time.sleep(0.5)
            out = emu.stop()
        err = emu.stderr()
    return r, out, err


@needs_netns
def test_the_sm_watchdog_drops_the_outputs_when_the_host_stops(tmp_path):
    _r, out, err = _signalled(_config(tmp_path, watchdog_ms=20.0), [(1.0, signal.SIGKILL)], stop_emulator=True)
    trips = re.findall(r"slave (\d): SM watchdog, no outputs for 20 ms: outputs 0, (?:SAFE-OP \+ error 0x001B|"
                       r"stays in OP) \(([\d.]+) ms after the last outputs\)", err)
    assert sorted({k for k, _ in trips}) == ["1", "3", "4", "5"], err          # every slave with outputs
    # measured by the slaves' own clock: outputs 0 within 100 ms of the killed host's last frame
    assert all(20.0 <= float(gap) < 100.0 for _, gap in trips), err
    print("SM watchdog after kill -9: outputs 0 " + ", ".join(f"slave {k} {gap} ms" for k, gap in trips)
          + " after the last frame")
    assert "applied_V {'X': 0.0, 'Y': 0.0}" in out, out


@needs_netns
def test_a_host_pause_beyond_the_sm_watchdog_faults_both_axes_from_the_al_status(tmp_path):
    """The host stopped 30 ms (SIGSTOP) with a 10 ms SM watchdog: the drive, the EL5101 and the
    EL4132 go to SAFE-OP with AL status code 0x001B, the EL2008 stays in OP. The frame after the
    pause comes back short, the driver reads AL status before the next one, and that one faults
    both axes as amplifier faults naming the code: the terminal axis is not held "enabled"
    through the error bucket (at most the one short frame counts as an I/O error): in the log,
    within three cycles of the one the pause fell in, both in the same cycle."""
    r, _out, err = _signalled(_config(tmp_path, watchdog_ms=10.0),
                              [(0.3, signal.SIGSTOP), (0.03, signal.SIGCONT), (0.3, signal.SIGTERM)],
                              log=tmp_path / "run.mlog")
    table = parse_run_table(r.stdout)
    assert set(table) == {"X", "Y"}, f"{r.stdout}\n{r.stderr}\n{err}"
    assert "stays in OP" in err and "SAFE-OP + error 0x001B" in err, err
    for a, slave in (("X", "slave 1 (CiA 402 drive, axis X)"), ("Y", "slave 3 (EL5101, axis Y)")):
        fault = table[a]["fault"]
        assert "amplifier fault" in fault and f"{slave} left OP: SAFE-OP + error, AL status code 0x001B" in fault, \
            r.stdout
    assert table["Y"]["io_errors"] <= 1, r.stdout
    # the log: both axes fault in one cycle as amplifier faults, 0 V and off from there on. The
    # stall that tripped the watchdog (the SIGSTOP, or on a loaded host an earlier one of its
    # own) is seen in the log when it fell inside a cycle's timed part (turnaround > 10 ms in
    # cycle k_p; a stall between cycles is not timed): the first frame after it goes out in k_p
    # or k_p + 1, comes back short at the next read, the AL status is read in service() and the
    # next read faults: k_p + 3 at the latest. (The short frames are I/O errors: at most one
    # counted, above, is the same bound whichever stall it was.)
    rl = read_log(str(tmp_path / "run.mlog"))
    fy, fx = rl.col("Y.fault_bits"), rl.col("X.fault_bits")
    k = int(np.argmax(fy != 0))
    assert fy[k] == FAULT_AMP_FAULT and fx[k] == FAULT_AMP_FAULT and not fx[:k].any(), (k, fx[k], fy[k])
    stalls = np.flatnonzero(rl.col("turnaround_ns")[:k] > 10e6)
    if stalls.size and k - stalls[-1] <= 10:
        assert k - stalls[-1] <= 3, (stalls[-1], k)
    for a in ("X", "Y"):
        assert not rl.col(f"{a}.u")[k:].any() and not rl.col(f"{a}.enabled")[k:].any()
    # on the master's clock (its exchanges, one per cycle): each axis is named from its slave's AL
    # status within 2 frames of the first frame that came back short (that frame's read flags
    # it, service() reads the AL status, the next read faults the axis)
    drv = rl.header["driver"]
    trip = drv["al_trip"]
    print(f"EtherCAT watchdog trip: {trip}, counters {drv['counters']}")
    assert trip is not None and set(trip["named_after_frames"]) == {"X", "Y"}, drv
    for a, n in trip["named_after_frames"].items():
        assert n is not None and 1 <= n <= 2, (a, trip, drv["counters"])
    # the stop judged against the slaves' states now: the drive in Fault, the EL4132 in its safe
    # state, the EL2008 (in OP) written off and read back
    assert "amplifiers off (confirmed by the device" in r.stdout and "its safe state" in r.stdout, \
        f"{r.stdout}\n{r.stderr}"


@needs_netns
def test_a_refused_transition_names_the_al_status_code(tmp_path):
    # SYNC0 at 83 us: the emulated slaves take no cycle under 100 us and refuse SAFE-OP
    import pysoem  # noqa: F401 - the test extra installs it: missing is an error, never a skip
    cfg = _config(tmp_path, sync0=True, round_trip_s=1e-6)
    d = yaml.safe_load(cfg.read_text())
    d["loop"]["rate_hz"] = 12000
    cfg.write_text(yaml.safe_dump(d, sort_keys=False))
    with NetNamespace(veth=VETH) as ns, Emulator("ethercat", cfg, plant=PLANT, prefix=ns.prefix):
        r = run_cli(["run", str(cfg), "--duration", "0.1"], prefix=ns.prefix, timeout_s=60)
    assert r.returncode != 0 and "Traceback" not in r.stderr, r.stderr
    assert "SAFE-OP refused" in r.stderr and "AL status code 0x0035" in r.stderr, r.stderr


KICKCAT_MASTER = """
import kickcat
link = kickcat.create_link("{ifname}", "")
link.set_timeout(0.1)      # a frame's answer may wait out a loaded host (100 ms)
bus = kickcat.Bus(link)
bus.init(2.0)
sl = bus.slaves()
print("slaves", [s.address for s in sl])
print("device type", bus.read_sdo(sl[0], 0x1000, 0, kickcat.Access.PARTIAL, 4, 0.1).hex())
bus.create_mapping(4096)
print("image", [(s.input_size, s.output_size) for s in sl])
bus.request_state(kickcat.State.SAFE_OP)
bus.wait_for_state(kickcat.State.SAFE_OP, 1.0)
def error(*a):
    raise RuntimeError(a)
def cycle():
    bus.send_logical_read(error); bus.send_logical_write(error)
    bus.finalize_datagrams(); bus.process_awaiting_frames()
# in SAFE-OP and on the way to OP an ESC does not count the outputs: no working-counter check
for s in sl:
    if s.output_size:
        s.set_output_bytes(bytes(s.output_size))
bus.process_data_no_check()
bus.request_state(kickcat.State.OPERATIONAL)
for _ in range(200):
    bus.process_data_no_check()
    try:
        bus.wait_for_state(kickcat.State.OPERATIONAL, 0.002)
        break
    except Exception:
        pass
cycle()                # OP: both working counters checked
print("states", [str(bus.get_state(s)) for s in sl])
print("drive inputs", sl[0].input_data.hex())
"""


@needs_netns
def test_kickcat_brings_the_emulated_segment_to_op_too(tmp_path):
    """A second master nobody here wrote (KickCAT 2.5's Python binding): scan, SII (sizes from
    the PDO categories of the terminals, from CoE for the drive), an expedited SDO upload, and
    INIT → PRE-OP → SAFE-OP → OP of all five slaves with process data."""
    import sys
    import kickcat  # noqa: F401 - the test extra installs it: missing is an error, never a skip
    cfg = _config(tmp_path)
    with NetNamespace(veth=VETH) as ns, Emulator("ethercat", cfg, plant=PLANT, prefix=ns.prefix):
        r = subprocess.run([*ns.prefix, sys.executable, "-c", KICKCAT_MASTER.format(ifname=VETH[0])],
                           capture_output=True, text=True, timeout=60)
    out = r.stdout
    assert r.returncode == 0, out + r.stderr[-2000:]
    assert "slaves [1001, 1002, 1003, 1004, 1005]" in out and "device type 92010200" in out, out
    # the drive as delivered (statusword, controlword); EL5101 10 in / 6 out; EL4132 4 out; EL2008 1 out
    assert "image [(2, 2), (0, 0), (10, 6), (0, 4), (0, 1)]" in out, out
    assert "states " + str(["State.OPERATIONAL"] * 5) in out, out
    assert "drive inputs 4002" in out, out       # Switch on disabled, remote


SETPRIV = shutil.which("setpriv")


@needs_netns
@pytest.mark.skipif(SETPRIV is None, reason="needs setpriv (util-linux)")
def test_the_loop_needs_no_root_only_net_raw_and_net_admin(tmp_path):
    """As ``nobody`` with CAP_NET_RAW and CAP_NET_ADMIN as ambient capabilities (what
    systemd/ethercat.conf grants) the run reaches OP and stops confirmed; with CAP_NET_RAW alone
    it stops at once with a one-line error (SOEM's promiscuous-mode request is refused)."""
    import tempfile
    import pysoem  # noqa: F401 - the test extra installs it: missing is an error, never a skip
    work = Path(tempfile.mkdtemp(prefix="motorctl-nobody-"))   # pytest's own tmp is root's only
    work.chmod(0o777)
    try:
        _as_nobody_run(work)
    finally:
        shutil.rmtree(work, ignore_errors=True)


def _as_nobody_run(tmp_path: Path) -> None:
    import sys
    cfg = _config(tmp_path)
    cfg.chmod(0o644)
    # nobody cannot use numba's cache beside the sources (not writable), and compiling every
    # kernel took 20 s; what is tested here is the capabilities, so the kernels run as Python
    env = ["env", f"HOME={tmp_path}", "NUMBA_DISABLE_JIT=1"]

    def as_nobody(caps):
        return [*env, SETPRIV, "--reuid=65534", "--regid=65534", "--clear-groups",
                f"--inh-caps={caps}", f"--ambient-caps={caps}"]
    # the machine first (only the interpreter runs, none of the project's code): can nobody
    # reach this clone and its environment at all? (a clone under root's 0700 home cannot)
    lacks = unreadable_as(as_nobody("+net_raw"), [Path(sys.prefix) / "pyvenv.cfg", *module_paths(
        "motorctl", "motorctl_drivers", "motorctl_emulators", "pysoem", "numpy", "yaml")])
    if lacks:
        pytest.skip(f"nobody cannot reach this clone's environment here: {lacks}")
    # then the project: what nobody can reach it imports (a failure here is the project's)
    probe = subprocess.run([*as_nobody("+net_raw"), sys.executable, "-c", "import motorctl, pysoem"],
                           capture_output=True, text=True, timeout=60)
    assert probe.returncode == 0, probe.stderr[-2000:]
    with NetNamespace(veth=VETH) as ns, Emulator("ethercat", cfg, plant=PLANT, prefix=ns.prefix):
        argv = ["run", str(cfg), "--duration", "0.3", "--log", str(tmp_path / "run.mlog")]
        raw_only = subprocess.run([*ns.prefix, *as_nobody("+net_raw"), *motorctl_cmd(*argv)],
                                  capture_output=True, text=True, timeout=120, cwd=tmp_path)
        both = subprocess.run([*ns.prefix, *as_nobody("+net_raw,+net_admin"), *motorctl_cmd(*argv)],
                              capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert raw_only.returncode == 1 and "Traceback" not in raw_only.stderr, raw_only.stderr
    assert "cannot open it for raw frames" in raw_only.stderr, raw_only.stderr
    assert both.returncode == 0, both.stdout + both.stderr
    assert "amplifiers off (confirmed by the device" in both.stdout, both.stdout


# --------------------------------------------------------------------------- no network
def _frame(*datagrams) -> bytearray:
    body = bytearray()
    for k, (cmd, adp, ado, data) in enumerate(datagrams):
        more = 0x8000 if k < len(datagrams) - 1 else 0
        body += struct.pack("<BBHHHH", cmd, k, adp, ado, len(data) | more, 0) + data + b"\x00\x00"
    return bytearray(struct.pack("<H", len(body) | 0x1000)) + body


def _wkcs(frame: bytearray) -> list[int]:
    out, off = [], 2
    while off < len(frame):
        n = struct.unpack_from("<H", frame, off + 6)[0] & 0x7FF
        out.append(struct.unpack_from("<H", frame, off + 10 + n)[0])
        off += 12 + n
    return out


def test_the_esc_model_counts_addresses_and_refuses_what_a_slave_refuses():
    from motorctl_emulators.ethercat_device import _drive_esc, _terminal_esc
    from motorctl_drivers.ethercat import EL4132, EL5101
    seg = E.Segment([_drive_esc(1), _terminal_esc(EL5101, 2), _terminal_esc(EL4132, 3)])
    # BRD counts the slaves; APWR at position 2 (ADP -1 from the master) sets one station address
    f = _frame((E.BRD, 0, E.REG_TYPE, b"\x00\x00"), (E.APWR, (-1) & 0xFFFF, E.REG_STATION, b"\x02\x10"),
               (E.FPRD, 0x1002, E.REG_STATION, b"\x00\x00"), (E.FPRD, 0x1009, E.REG_STATION, b"\x00\x00"))
    assert seg.process(f)
    assert _wkcs(f) == [3, 1, 1, 0]
    # the SII the ESC serves through 0x0500: identity and the configuration-area checksum
    sii = seg.slaves[1].sii
    assert struct.unpack_from("<II", sii, 0x10) == (0x00000002, EL5101)
    assert sii[14] == E.crc8_sii(sii[:14])
    # INIT -> OP is not a transition: AL status keeps INIT with the error bit and code 0x0011
    f = _frame((E.FPWR, 0x1002, E.REG_AL_CONTROL, b"\x08\x00"), (E.FPRD, 0x1002, E.REG_AL_STATUS, bytes(6)))
    seg.process(f)
    status, _r, code = struct.unpack_from("<HHH", f, 2 + 12 + 2 + 10)
    assert (status, code) == (E.INIT | E.AL_ERROR, E.AL_INVALID_STATE_CHANGE)
    # PRE-OP without the mailbox sync managers programmed: 0x0016 on the drive
    f = _frame((E.APWR, 0, E.REG_AL_CONTROL, b"\x12\x00"), (E.APRD, 0, E.REG_AL_STATUS, bytes(6)))
    seg.process(f)
    status, _r, code = struct.unpack_from("<HHH", f, 2 + 12 + 2 + 10)
    assert (status, code) == (E.INIT | E.AL_ERROR, E.AL_INVALID_MAILBOX_CONFIG)


def test_check_config_carries_two_axes_at_5_khz_and_says_what_it_costs():
    r = run_cli(["check-config", str(CONFIG)])
    assert r.returncode == 0, r.stderr
    assert "driver ethercat, 5000 Hz" in r.stdout and "EtherCAT, 1 frame of 68 bytes" in r.stdout, r.stdout


def test_an_io_axis_without_its_enable_is_a_clear_error(tmp_path):
    d = yaml.safe_load(CONFIG.read_text())
    del d["axes"]["Y"]["driver"]["enable"]
    p = tmp_path / "bad.yaml"
    p.write_text(yaml.safe_dump(d, sort_keys=False))
    r = run_cli(["check-config", str(p)])
    assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr
    assert "axes.Y.driver" in r.stderr and "profile io needs enable" in r.stderr, r.stderr


def test_an_interface_this_machine_does_not_have_is_refused_before_anything_starts(tmp_path):
    cfg = _config(tmp_path, ifname="nosuchnic0")
    log = tmp_path / "run.mclog"
    r = run_cli(["run", str(cfg), "--duration", "1", "--log", str(log)])
    assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr
    errors = [ln for ln in r.stderr.splitlines() if ln.startswith("motorctl: error:")]
    assert len(errors) == 1, r.stderr
    assert str(cfg) in r.stderr and "driver.ifname" in r.stderr and "'nosuchnic0'" in r.stderr, r.stderr
    assert "lo" in r.stderr.split("it has:")[1], r.stderr      # the interfaces it has are named
    assert not log.exists() and list(tmp_path.iterdir()) == [cfg]


@needs_netns
def test_an_unplugged_segment_faults_with_the_working_counter_and_the_daemon_reconnects(tmp_path):
    """The daemon on EtherCAT, both axes tracking; the segment's cable is pulled (the veth's
    slave end down): both axes latch a fault that names the working counter (0 V, amplifier
    off); the cable back: the daemon scans and brings the segment to OP again by itself, with
    nothing re-enabled; fault-reset and start work and X tracks again."""
    import pysoem  # noqa: F401 - the test extra installs it: missing is an error, never a skip
    from conftest import RIGID_PLANT
    from test_daemon_helpers import Daemon, as_test_daemon, ctl, status, wait_for

    d = yaml.safe_load(CONFIG.read_text())
    d["loop"].update(rate_hz=1000, clock="wall")       # the Python segment keeps up on a loaded VM
    d["loop"]["realtime"]["policy"] = "off"
    d["driver"].update(ifname=VETH[0], sync0=False, watchdog_ms=200.0, timeout_s=0.0005)
    sock = as_test_daemon(d, tmp_path)
    for ax in d["axes"].values():
        ax["limits"]["following_error_m"] = 0.01       # the subject here is the link
    cfg = tmp_path / "ethercat-daemon.yaml"
    cfg.write_text(yaml.safe_dump(d, sort_keys=False))

    def link(state: str) -> None:
        subprocess.run([*ns.prefix, "ip", "link", "set", VETH[1], state], check=True, timeout=10)

    with NetNamespace(veth=VETH) as ns, Emulator("ethercat", cfg, plant=RIGID_PLANT, prefix=ns.prefix):
        daemon = Daemon(cfg, sock, prefix=ns.prefix)
        try:
            daemon.wait_ready()
            for a in ("X", "Y"):
                assert ctl(sock, "start", a).returncode == 0
            wait_for(lambda: all(s["phase"] == "tracking" for s in status(sock)["axes"].values()), 30,
                     "X and Y tracking")
            link("down")                                  # the cable is pulled
            st = wait_for(lambda: (s := status(sock))["axes"]["X"]["state"] == "fault"
                          and s["axes"]["Y"]["state"] == "fault" and not s["link"]["connected"] and s, 20,
                          "both axes faulted and the link down")
            for a in ("X", "Y"):
                ax = st["axes"][a]
                assert "EtherCAT working counter 0 of 10 (no frame came back" in ax["fault"], ax
                assert not ax["amplifier_enabled"] and ax["u_V"] == 0.0, ax
            time.sleep(0.5)                               # out for longer than the 200 ms SM watchdog:
            link("up")                                    # the slaves are in SAFE-OP + error when it is back
            seen: list = []
            st = wait_for(lambda: (s := status(sock))["link"]["connected"] and s or seen.append(s["link"]), 30,
                          "the link back", detail=lambda: seen[-1:])
            assert st["link"]["reconnects"] == 1, st["link"]          # scanned and brought to OP again
            for a in ("X", "Y"):                          # nothing re-enabled
                assert st["axes"][a]["state"] == "fault" and not st["axes"][a]["amplifier_enabled"], st["axes"][a]
            wait_for(lambda: ctl(sock, "fault-reset", "X").returncode == 0, 10, "fault-reset X")
            assert ctl(sock, "start", "X").returncode == 0
            wait_for(lambda: status(sock)["axes"]["X"]["phase"] == "tracking", 30, "X tracking again")
        finally:
            daemon.kill()
