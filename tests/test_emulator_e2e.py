"""End to end through the real protocol stacks: ``motorctl emulate`` in its own process,
``motorctl run`` in another, C2 on the gantry program (X: 0 ↔ 0.4 m at 2 m/s; Y alongside),
compared with the sim driver on the same plant and seed at the same loop rate, in lockstep
with the device (the virtual clock: the verdict is about tracking, not the host's scheduling).

Rates (the highest each budget allows on this machine, :func:`loopback_rate`): the shipped
config's wire time plus the loopback round trip p99 measured here (``LOOPBACK_ROUND_TRIP_S``),
at most 80 % load, on a 500 Hz grid: serial 3 Mbaud 120 µs + 225 µs → 2000 Hz; CAN FD 1M/5M
group frames 117 µs + 515 µs (python-can udp_multicast) → 1000 Hz; Modbus TCP 434 µs → 1500 Hz;
CANopen (CiA 402 drives on canopen's device side, classic CAN 1 Mbit/s: SYNC + 2 RPDO + 2 TPDO
475 µs) + 445 µs → 500 Hz.

CAN and CANopen run over python-can's udp_multicast inside a private network namespace the test
makes (``unshare -n``, lo up, 224.0.0.0/4 via lo); serial over ``socket://127.0.0.1``; Modbus TCP
on 127.0.0.1. Also: the emulator's watchdog zeroes its output when the driver process is killed.

The plant is the paper's rigid one (``configs/gantry-rigid.yaml``): these tests are about the
transports; the unmodelled dynamics of ``configs/gantry.yaml`` are the controllers' business.
"""

from __future__ import annotations

import functools
import os
import signal
import subprocess
import time
from pathlib import Path

import pytest
import yaml
from conftest import RIGID_PLANT

from motorctl.app.job import run_job
from motorctl.config import config_from_dict
from motorctl.recorder.runlog import read_log
from harness import (
    LOOPBACK_WATCHDOG_S,
    Emulator,
    NetNamespace,
    loopback_e2e_config,
    motorctl_cmd,
    parse_run_table,
    run_cli,
    run_cli_interrupted,
    sim_twin,
    wait_for,
)

CONFIGS = Path(__file__).resolve().parents[1] / "configs"
#: the emulator's plant: the simulated gantry (the paper's rigid plant where the config exists)
PLANT = RIGID_PLANT
DURATION_S = 3.0
EXPECTED_RATE_HZ = {"serial": 2000.0, "can": 1000.0, "modbus": 1500.0, "canopen": 500.0}
#: lockstep with the same plant and seed: the runs agree to the printed digits but for the
#: transports' scaling (16-bit voltage counts, 0.5 um encoder counts): 2 % is plenty
TOLERANCE = 0.02
def _misses(got: dict, ref: dict) -> list[str]:
    """What of a run's table ``got`` fails the comparison with the sim run ``ref``: a fault, or
    e_M / e_F / L2[e] more than ``TOLERANCE`` from the sim's (one line each; [] when none)."""
    out = []
    for axis in ("X", "Y"):
        if got[axis]["fault"] != "":
            out.append(f"{axis}: {got[axis]['fault']}")
        for key in ("e_M_um", "e_F_um", "L2_um"):
            want = ref[axis][key]
            if abs(got[axis][key] - want) > TOLERANCE * want:
                out.append(f"axis {axis}: {key} {got[axis][key]:.3f} vs sim {want:.3f}")
    return out


@functools.lru_cache(maxsize=None)
def _sim_reference(rate: float) -> dict:
    """The sim-driver run at ``rate`` on the emulator's plant config (the transports' configs
    share controllers and programs, so one reference serves them all)."""
    import tempfile
    with tempfile.TemporaryDirectory() as tmp:
        d, _, _ = loopback_e2e_config("serial", CONFIGS, tmp)
    d["loop"]["rate_hz"] = rate
    res = run_job(config_from_dict(sim_twin(d, PLANT), "sim-twin"), controller="c2", duration_s=DURATION_S,
                  clock="virtual")
    return {a: dict(r) for a, r in res.axes.items()}


@pytest.fixture
def namespace_for():
    """A private network namespace for CAN (udp_multicast); nothing for the other transports."""
    held = []

    def make(transport):
        if transport not in ("can", "canopen"):
            return ()
        ns = NetNamespace().__enter__()
        held.append(ns)
        return ns.prefix
    yield make
    for ns in held:
        ns.__exit__(None, None, None)


@pytest.mark.parametrize("transport", ["serial", "can", "modbus", "canopen"])
def test_closed_loop_through_the_protocol_matches_the_sim_driver(transport, tmp_path, namespace_for):
    """C2 through the protocol, judged on tracking alone: the run is in lockstep with the
    emulated device (``loop.clock: virtual``: each cycle waits for its answer, up to a 50 ms
    read timeout), so the verdict does not depend on how the host schedules two processes on
    two cores, and the error bucket is the default (100). Mid-run the host is stopped for
    20 ms (SIGSTOP, SIGCONT): the device keeps the master's time (it steps its plant by the
    cycles the master numbers, not by its own clock) and the run tracks as the sim driver does.
    The wall-clock behaviour of each transport (late, lost and bad answers against the read
    timeout, the stand-in, the bucket) is test_drivers_faults'."""
    d, cfg, rate = loopback_e2e_config(transport, CONFIGS, tmp_path)
    assert rate == EXPECTED_RATE_HZ[transport], f"{transport}: budget now allows {rate} Hz"
    d["loop"]["clock"] = "virtual"
    d["driver"]["timeout_s"] = 0.05
    if transport == "canopen":
        # the drives' heartbeat consumers run on the wall clock: the 20 ms stall below on a
        # loaded VM must not reach them, as in test_canopen_e2e's lockstep runs (its SIGKILL
        # test keeps the shipped 50 ms)
        d["driver"].update(heartbeat_consumer_ms=1000, drive_heartbeat_timeout_ms=1000)
    cfg.write_text(yaml.safe_dump(d, sort_keys=False))
    prefix = namespace_for(transport)
    ref = _sim_reference(rate)
    log = tmp_path / "run.log"
    def stall(proc):                                        # a 20 ms host stall mid-run
        time.sleep(0.3)
        os.killpg(proc.pid, signal.SIGSTOP)
        time.sleep(0.020)
        os.killpg(proc.pid, signal.SIGCONT)

    with Emulator(transport, cfg, plant=PLANT, watchdog_s=LOOPBACK_WATCHDOG_S, prefix=prefix) as emu:
        first, r = run_cli_interrupted(["run", str(cfg), "--controller", "c2", "--duration", str(DURATION_S),
                                        "--log", str(log)], stall, prefix=prefix, timeout_s=120)
        emu_err = emu.stderr()
    out, err = r.stdout, r.stderr
    got = parse_run_table(out)
    assert set(got) == {"X", "Y"}, f"rc {r.returncode}\n{first}{out}\n{err}\n{emu_err}"
    assert f"at {rate:.0f} Hz for {DURATION_S:g} s (virtual clock)" in first
    misses = _misses(got, ref)
    for axis in ("X", "Y"):   # shown with pytest -s: the figures of the closing note
        print(f"{transport} {rate:.0f} Hz {axis}: " + ", ".join(
            f"{k} {got[axis][k]:.2f} (sim {ref[axis][k]:.2f})" for k in ("e_M_um", "e_F_um", "L2_um"))
            + f", io errors {got[axis]['io_errors']}")
    assert not misses, f"{transport} at {rate:.0f} Hz: {'; '.join(misses)}\n{out}"
    assert "X, Y at 0 V, amplifiers off (confirmed by the device" in out, out + err
    hdr = read_log(str(log)).header
    assert hdr["driver"]["transport"].startswith(transport)


@pytest.mark.parametrize("transport", ["serial", "can", "modbus"])
def test_emulator_watchdog_zeroes_output_when_the_driver_is_killed(transport, tmp_path, namespace_for):
    d, cfg, rate = loopback_e2e_config(transport, CONFIGS, tmp_path)
    prefix = namespace_for(transport)
    # the device's watchdog as the serial host sets it: far above a loaded host's stall
    with Emulator(transport, cfg, plant=PLANT, watchdog_s=LOOPBACK_WATCHDOG_S, prefix=prefix) as emu:
        run = subprocess.Popen([*prefix, *motorctl_cmd("run", str(cfg), "--duration", "60")],
                               stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
        try:
            assert wait_for(lambda: "first command Y" in emu.stderr(), 30.0), emu.stderr()
            assert wait_for(lambda: False, 0.3) is False          # let it drive a little
            assert "watchdog X:" not in emu.stderr() and "watchdog Y:" not in emu.stderr()   # no trip yet
            os.killpg(run.pid, signal.SIGKILL)                     # the driver dies mid-motion
            run.wait(timeout=10)
        finally:
            if run.poll() is None:
                os.killpg(run.pid, signal.SIGKILL)
                run.wait(timeout=10)
        assert wait_for(lambda: "watchdog X:" in emu.stderr() and "watchdog Y:" in emu.stderr(), 5.0), emu.stderr()
        if transport == "serial":         # the driver set the device's watchdog in configure()
            assert f"watchdog set to {LOOPBACK_WATCHDOG_S * 1e3:g} ms by the host" in emu.stderr()
        # the device keeps the fault latched across masters (serial and CAN revision 2, a Modbus
        # map's fault_reset bit): the next set-up warns and sends no reset; the operator's does
        if transport == "can":            # the bus is the namespace's: the reset as its own process
            r = run_cli(["fault-reset", "--config", str(cfg), "X", "Y"], prefix=prefix, timeout_s=60)
            assert r.returncode == 0, r.stdout + r.stderr
            # the reset's own set-up found both latched ("was"), and reset them
            assert r.stdout.count(": amplifier fault latched (byte 8 bit ") == 2, r.stdout
            assert r.stdout.count("the drive's fault is reset: was CAN ") == 2, r.stdout
        else:
            from motorctl.app.fault_reset import reset_drive_faults
            from motorctl.config import load_config
            loaded = load_config(cfg, check_budget=False)
            drv = loaded.make_driver()
            drv.open()
            try:
                assert drv.amp_fault.all() and not any("cleared" in n for n in drv.notices), drv.notices
                assert sum("set-up found the drive in its fault" in n for n in drv.notices) == 2, drv.notices
            finally:
                drv.close()
            rep = reset_drive_faults(loaded, ["X", "Y"])            # the operator's, no daemon: the reset bits
            assert [(x.sent, x.cleared) for x in rep.axes] == [(True, True)] * 2 and rep.stop_confirmed, rep
        assert emu.stderr().count("fault reset ") == 2, emu.stderr()
        out = emu.stop()
    stopped = [ln for ln in out.splitlines() if ln.startswith("stopped:")]
    assert stopped, out
    assert "applied_V {'X': 0.0, 'Y': 0.0}" in stopped[0]


def test_free_ports_lie_below_the_ephemeral_range_and_are_free():
    """The loopback servers' ports: below the kernel's ephemeral range (no socket binding 0 or
    connecting can be given one before its server binds it), a new one at each call, free."""
    import socket

    from motorctl_emulators.loopback import _ephemeral_low, free_port
    ports = [free_port() for _ in range(8)] + [free_port(socket.SOCK_DGRAM)]
    assert len(set(ports)) == len(ports)
    assert all(10000 <= p < _ephemeral_low() for p in ports)
    with socket.socket() as held:               # a port in use is skipped
        held.bind(("127.0.0.1", ports[0]))
        assert ports[0] not in [free_port() for _ in range(70)]
