"""Each driver against its emulated device in a thread of this process, over the transports the
end-to-end tests do not use: CAN on python-can's ``virtual`` bus (classic and FD), serial over a
pty pair, Modbus RTU over a pty (pymodbus RTU framer and CRC). Functional only (no timing):
the thread shares the GIL, so the read timeout is long."""

from __future__ import annotations

import contextlib
from pathlib import Path

import numpy as np
import pytest

from motorctl.config import config_from_dict, load_yaml
from motorctl.driver import LifecycleError
from motorctl_emulators.device import build_device
from harness import device_thread, exchange
from motorctl_emulators.plant_bank import FaultSpec

CONFIGS = Path(__file__).resolve().parents[1] / "configs"
PLANT = CONFIGS / "gantry.yaml"        # the emulator's plant: the simulated gantry
WATCHDOG_S = 0.25                      # far above a loaded host's stall between two exchanges


#: the read timeout: lockstep, an answer that comes is waited for far beyond a loaded host's
#: stall of the device thread (an answer the device never sends waits it out: the tests that
#: lose answers on purpose shorten it for those reads)
READ_TIMEOUT_S = 2.0
#: the read timeout of a read whose answer is lost on purpose
LOST_TIMEOUT_S = 0.05


def _config(name: str, tmp_path, **driver) -> dict:
    d = load_yaml(CONFIGS / name)
    d["loop"]["rate_hz"] = 1000
    d["loop"]["clock"] = "virtual"     # lockstep: a loaded host's slow answer is no loss
    d["driver"].update(timeout_s=READ_TIMEOUT_S, wait="spin")
    d["driver"].update(driver)
    return d


@contextlib.contextmanager
def _serving(loaded, faults=()):
    """The emulated device of ``loaded`` served from a thread of this process (bounded join)."""
    with device_thread(build_device(loaded, PLANT, watchdog_s=WATCHDOG_S, faults=list(faults))) as dev:
        yield dev


def _exchange(d: dict, cycles: int = 40):
    loaded = config_from_dict(d, "<inprocess>", check_budget=False)
    with _serving(loaded) as dev:
        return _drive(loaded, dev, cycles)


#: the longest wait for the in-process device's answer [s] (it comes in milliseconds when idle)
ANSWER_WAIT_S = 10.0


def _drive(loaded, dev, cycles: int):
    import time
    drv = loaded.make_driver()
    # the device runs in a thread of this process: on a loaded host its first answer can take
    # more than the driver's 1 s set-up timeout; an answer ends the wait at once
    drv.CONFIGURE_TIMEOUT_S = ANSWER_WAIT_S
    try:
        drv.open()
        y0 = drv.position_m.copy()
        errors = 0
        for _ in range(cycles):               # bounded
            exchange(drv, [2.0, -2.0], [True, True], 1, sleep_s=0.003)
            errors += int(drv.read_error.any())
        moved = drv.position_m - y0
        # stop commanding: the device's watchdog trips and the next answer carries the fault
        time.sleep(2 * WATCHDOG_S)
        drv._first_reading(timeout_s=ANSWER_WAIT_S)
        fault_after_watchdog = drv.amp_fault.copy()
        drv.close()                           # deactivate (0 V, disabled, answer awaited), release
        assert drv.state == "finalized" and not drv.connected
        assert dev.bank.applied_V == [0.0, 0.0] and dev.bank.enabled == [False, False]
        return moved, errors, fault_after_watchdog, dev.bank
    finally:
        drv.close()                           # idempotent


@pytest.mark.parametrize("fd", [False, True])
def test_can_over_the_virtual_bus(fd, tmp_path):
    name = "gantry-can.yaml" if fd else "gantry-can-classic.yaml"
    d = _config(name, tmp_path, interface="virtual", channel=f"inproc-{fd}-{tmp_path.name}")
    moved, errors, fault, bank = _exchange(d)
    assert moved[0] > 0 and moved[1] < 0, moved          # +2 V moves X forward, -2 V moves Y back
    assert errors <= 10
    assert bank.commands[0] >= 40 and bank.applied_V[0] == 0.0
    assert fault.all()


def test_serial_over_a_pty(tmp_path):
    d = _config("gantry-serial.yaml", tmp_path, port=str(tmp_path / "ttyEMU"))
    moved, errors, fault, bank = _exchange(d)
    assert moved[0] > 0 and moved[1] < 0, moved
    assert errors <= 10
    assert fault.all()


def test_a_lost_answer_after_a_run_of_losses_is_stood_in_for_by_one_cycles_step(tmp_path):
    """Answers to commands 21-23 are lost, 24 comes, 25 is lost again. The stand-in for 25 adds
    one cycle's step: the displacement measured at 24 divided over the four cycles it spans
    (it added all four: the stand-in ran three steps ahead of the plant)."""
    d = _config("gantry-serial.yaml", tmp_path, port=str(tmp_path / "ttyEMU"))
    loaded = config_from_dict(d, "<inprocess>", check_budget=False)
    faults = [FaultSpec.parse("drop:*:20:3"), FaultSpec.parse("drop:*:24:1")]   # 0-based command counts
    with _serving(loaded, faults) as dev:
        drv = loaded.make_driver()
        try:
            drv.open()
            lost = []
            for k in range(25):                   # bounded
                # the answers the device drops are not waited for long; every other one is
                drv.timeout_s = LOST_TIMEOUT_S if k in (20, 21, 22, 24) else READ_TIMEOUT_S
                exchange(drv, [2.0, -2.0], [True, True], 1, sleep_s=0.003)
                lost.append(bool(drv.read_error[0]))
            step = drv._step[0]
            gap = drv.position_m[0] - dev.bank.plants[0].measured()   # stand-in minus the plant
        finally:
            drv.close()
    assert lost[20:25] == [True, True, True, False, True], lost
    assert step > 0 and abs(gap) < 0.5 * step, (gap, step)


def test_modbus_rtu_over_a_pty(tmp_path):
    d = _config("gantry-modbus.yaml", tmp_path, transport="rtu", serial_port=str(tmp_path / "ttyRTU"),
                baudrate=115200)
    moved, errors, fault, bank = _exchange(d)
    assert moved[0] > 0 and moved[1] < 0, moved
    assert errors <= 10
    assert fault.all()


def test_lost_link_is_flagged_every_cycle_and_reconnect_happens_outside_the_loop(tmp_path):

    from harness import free_port
    d = _config("gantry-serial.yaml", tmp_path, port=f"socket://127.0.0.1:{free_port()}")
    loaded = config_from_dict(d, "<inprocess>", check_budget=False)
    with _serving(loaded, [FaultSpec.parse("disconnect:*:5:1")]) as dev:
        drv = loaded.make_driver()
        try:
            drv.open()
            u, en = np.zeros(2), np.ones(2, dtype=bool)
            flags = []
            for _ in range(12):                        # command 5 drops the link
                exchange(drv, u, en, 1, sleep_s=0.01)
                flags.append(bool(drv.read_error.any() or drv.write_error.any()))
            assert not any(flags[:5]) and all(flags[6:]), flags
            assert not drv.connected
            drv.reconnect()                            # blocking, outside the cycle
            assert drv.connected
            exchange(drv, u, [False, False], 1, sleep_s=0.01)   # the loop decides what to enable: here nothing
            assert not drv.read_error.any() and not drv.write_error.any()
            assert dev.bank.enabled == [False, False]  # the device saw the axes disabled
        finally:
            drv.close()


def test_lifecycle_deactivate_reaches_the_device_and_activate_starts_again(tmp_path):
    """configure → activate → cycles → deactivate (the device has applied 0 V with the amplifier
    off when it returns) → activate again → close; nothing outside that order is allowed."""
    d = _config("gantry-serial.yaml", tmp_path, port=str(tmp_path / "ttyLC"))
    loaded = config_from_dict(d, "<inprocess>", check_budget=False)
    with _serving(loaded) as dev:
        drv = loaded.make_driver()
        try:
            with pytest.raises(LifecycleError):
                drv.activate()                     # not configured yet
            drv.configure()
            assert drv.state == "inactive" and drv.connected and dev.bank.commands == [0, 0]
            drv.activate()
            exchange(drv, [1.0, 1.0], [True, True], 5)
            assert dev.bank.enabled == [True, True]
            drv.deactivate()
            assert drv.state == "inactive"
            assert dev.bank.enabled == [False, False] and dev.bank.applied_V == [0.0, 0.0]
            drv.activate()
            drv.read()                              # nothing outstanding after a re-activation
            assert not drv.read_error.any()
            drv.close()
            assert drv.state == "finalized"
            with pytest.raises(LifecycleError):
                drv.reconnect()                     # a closed driver stays closed
        finally:
            drv.close()


def test_configure_releases_the_link_when_the_device_does_not_answer(tmp_path, monkeypatch):
    import os
    master, slave = os.openpty()                    # a port with nobody behind it
    try:
        d = _config("gantry-serial.yaml", tmp_path, port=os.ttyname(slave))
        drv = config_from_dict(d, "<inprocess>", check_budget=False).make_driver()
        monkeypatch.setattr(drv, "CONFIGURE_TIMEOUT_S", 0.05)
        with pytest.raises(ConnectionError, match="no answer"):
            drv.configure()
        assert drv.state == "unconfigured" and drv.port is None and not drv.connected
    finally:
        os.close(master)
        os.close(slave)


@pytest.mark.parametrize("name", ["gantry-can.yaml", "gantry-can-classic.yaml", "gantry-serial.yaml",
                                  "gantry-modbus.yaml"])
def test_voltage_out_limit_is_the_drive_full_scale(name, tmp_path):
    d = _config(name, tmp_path)
    per_axis = "voltage_full_scale_V" in d["axes"]["X"]["driver"]
    (d["axes"]["X"]["driver"] if per_axis else d["driver"])["voltage_full_scale_V"] = 12.0
    drv = config_from_dict(d, "<inprocess>", check_budget=False).make_driver()
    assert drv.voltage_limit_V("X") == 12.0
    assert drv.voltage_limit_V("Y") == (10.0 if per_axis else 12.0)
    vout = {i.name: i for i in drv.command_interfaces("X")}["voltage_out"]
    assert (vout.min, vout.max) == (-12.0, 12.0)


@pytest.mark.parametrize("name", ["gantry-serial.yaml", "gantry-modbus.yaml"])
def test_port_failures_are_one_clear_line(name, tmp_path):
    """A missing device and a path that is no tty (its line settings are refused) give one line
    naming the port and why, and `motorctl run` prints it without a traceback."""
    import yaml

    from harness import run_cli
    not_a_tty = tmp_path / "plainfile"
    not_a_tty.write_text("")
    for port, why in ((str(tmp_path / "ttyNONE"), "no such device"),
                      (str(not_a_tty), "line settings were refused")):
        extra = {"port": port} if name == "gantry-serial.yaml" else {"transport": "rtu", "serial_port": port,
                                                                    "parity": "O", "stopbits": 2}
        d = _config(name, tmp_path, **extra)
        drv = config_from_dict(d, "<ports>", check_budget=False).make_driver()
        with pytest.raises(OSError) as exc:
            drv.configure()
        msg = str(exc.value)
        assert port in msg and why in msg and "\n" not in msg, msg
        if name == "gantry-modbus.yaml":
            assert "8O2" in msg                                   # the line settings asked for
        assert drv.state == "unconfigured"
        d["loop"]["rate_hz"] = 100                                # a rate every transport's budget takes
        cfg = tmp_path / "cfg.yaml"
        cfg.write_text(yaml.safe_dump(d))
        r = run_cli(["run", str(cfg), "--duration", "0.1"], timeout_s=60)
        assert r.returncode == 1 and r.stderr.startswith("motorctl: error: ") and "Traceback" not in r.stderr, r.stderr
        assert why in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr


@pytest.mark.parametrize("name", ["gantry-serial.yaml", "gantry-can.yaml", "gantry-modbus.yaml"])
def test_commands_the_device_never_received_cost_no_plant_time(name, tmp_path):
    """The device keeps the master's time: the driver numbers its commands (serial seq, CAN
    sequence byte, Modbus sequence register), so after two commands that never reached the
    device the next one steps the plant three periods, the two missing ones coasting on the
    voltage the amplifier held (checked against a copy of the plant stepped so)."""
    import copy

    from harness import free_port
    where = {"gantry-serial.yaml": {"port": f"socket://127.0.0.1:{free_port()}"},
             "gantry-can.yaml": {"interface": "virtual", "channel": f"mt-{tmp_path.name}"},
             "gantry-modbus.yaml": {"transport": "tcp", "host": "127.0.0.1", "port": free_port()}}[name]
    d = _config(name, tmp_path, **where)             # no answer is lost: each one is waited for
    d["loop"]["clock"] = "virtual"                     # lockstep: every answer is waited for
    loaded = config_from_dict(d, "<inprocess>", check_budget=False)
    # a 5 s device watchdog: a loaded host's stall between two commands must not trip it here
    with device_thread(build_device(loaded, PLANT, watchdog_s=5.0)) as dev:
        drv = loaded.make_driver()
        try:
            drv.open()
            exchange(drv, [2.0, -2.0], [True, True], 20, sleep_s=0.003)
            assert not drv.read_error.any() and dev.bank.applied_V[0] == pytest.approx(2.0, abs=1e-3)
            twin = copy.deepcopy(dev.bank.plants[0])
            held = dev.bank.applied_V[0]
            drv.seq = (drv.seq + 2) & drv.SEQ_MASK     # two commands lost on the way
            exchange(drv, [1.0, -1.0], [True, True], 1, sleep_s=0.003)
            got = float(drv.position_m[0])
        finally:
            drv.close()
    clocks = list(dev.clocks.values()) if hasattr(dev, "clocks") else [dev.clock]
    assert [c.coasted for c in clocks] == [2] * len(clocks), [c.coasted for c in clocks]
    for u in (held, held, 1.0):
        twin.step(u)
    assert got == pytest.approx(twin.measured(), abs=1e-9)
