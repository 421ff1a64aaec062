"""Each driver against its emulated device in a thread of this process, over the transports the
end-to-end tests do not use: CAN on python-can's ``virtual`` bus (classic and FD), serial over a
pty pair, Modbus RTU over a pty (pymodbus RTU framer and CRC). Functional only (no timing):
the thread shares the GIL, so the read timeout is long."""

from __future__ import annotations

import contextlib
import threading
from pathlib import Path

import numpy as np
import pytest

from motorctl.config import config_from_dict, load_yaml
from motorctl_emulators.cli import build_device

CONFIGS = Path(__file__).resolve().parents[1] / "configs"


def _config(name: str, tmp_path, **driver) -> dict:
    d = load_yaml(CONFIGS / name)
    d["loop"]["rate_hz"] = 1000
    d["driver"].update(timeout_s=0.0009, wait="spin")
    d["driver"]["emulator"]["watchdog_s"] = 0.05
    d["driver"].update(driver)
    return d


@contextlib.contextmanager
def _serving(loaded, faults=()):
    """The emulated device of ``loaded`` served from a thread of this process (bounded join)."""
    dev = build_device(loaded, list(faults))
    stop = threading.Event()
    th = threading.Thread(target=dev.serve, kwargs={"stop": stop.is_set}, daemon=True)
    th.start()
    try:
        yield dev
    finally:
        stop.set()
        th.join(timeout=5)


def _exchange(d: dict, cycles: int = 40):
    loaded = config_from_dict(d, "<inprocess>", check_budget=False)
    with _serving(loaded) as dev:
        return _drive(loaded, dev, cycles)


def _drive(loaded, dev, cycles: int):
    import time
    drv = loaded.make_driver()
    try:
        drv.open()
        y0 = drv.position_m.copy()
        u = np.array([2.0, -2.0])
        en = np.ones(2, dtype=bool)
        errors = 0
        for _ in range(cycles):               # bounded
            drv.write(u, en)
            time.sleep(0.003)                 # the device thread needs the GIL to answer
            drv.read()
            errors += int(drv.read_error.any())
        moved = drv.position_m - y0
        # stop commanding: the device's watchdog trips and the next answer carries the fault
        time.sleep(0.15)
        drv._first_reading(timeout_s=1.0)
        fault_after_watchdog = drv.amp_fault.copy()
        drv.close()
        return moved, errors, fault_after_watchdog, dev.bank
    finally:
        if drv.connected:
            drv.close()


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


def test_modbus_rtu_over_a_pty(tmp_path):
    d = _config("gantry-modbus.yaml", tmp_path, transport="rtu", serial_port=str(tmp_path / "ttyRTU"),
                baudrate=115200)
    moved, errors, fault, bank = _exchange(d)
    assert moved[0] > 0 and moved[1] < 0, moved
    assert errors <= 10
    assert fault.all()


def test_lost_link_is_flagged_every_cycle_and_reconnect_happens_outside_the_loop(tmp_path):
    import time

    from motorctl_drivers.proto_common import FaultSpec
    from motorctl_emulators.harness import free_port
    d = _config("gantry-serial.yaml", tmp_path, port=f"socket://127.0.0.1:{free_port()}")
    loaded = config_from_dict(d, "<inprocess>", check_budget=False)
    with _serving(loaded, [FaultSpec.parse("disconnect:*:5:1")]) as dev:
        drv = loaded.make_driver()
        try:
            drv.open()
            u, en = np.zeros(2), np.ones(2, dtype=bool)
            flags = []
            for _ in range(12):                        # command 5 drops the link
                drv.write(u, en)
                time.sleep(0.01)
                drv.read()
                flags.append(bool(drv.read_error.any() or drv.write_error.any()))
            assert not any(flags[:5]) and all(flags[6:]), flags
            assert not drv.connected
            drv.reconnect()                            # blocking, outside the cycle
            assert drv.connected
            drv.write(u, np.zeros(2, dtype=bool))      # the loop decides what to enable: here nothing
            time.sleep(0.01)
            drv.read()
            assert not drv.read_error.any() and not drv.write_error.any()
            assert dev.bank.enabled == [False, False]  # the device saw the axes disabled
        finally:
            drv.close()
