"""Bus budgets: ``motorctl check-config`` refuses a rate the bus cannot carry, with the bus-time
figures and the setting that would fit, and accepts a feasible one."""

from __future__ import annotations

from pathlib import Path

import pytest

from motorctl.config import ConfigError, config_from_dict, load_config, load_yaml
from harness import run_cli

CONFIGS = Path(__file__).resolve().parents[1] / "configs"


def _write(tmp_path, base: str, rate: float, **driver) -> Path:
    import yaml
    d = load_yaml(CONFIGS / base)
    d["loop"]["rate_hz"] = rate
    d["driver"].update(driver)
    p = tmp_path / f"{Path(base).stem}-{rate:g}.yaml"
    p.write_text(yaml.safe_dump(d))
    return p


def test_check_config_refuses_classic_can_at_5khz_with_the_numbers():
    r = run_cli(["check-config", str(CONFIGS / "gantry-can-classic.yaml")])
    assert r.returncode == 2, r.stdout
    msg = r.stderr
    assert "loop.rate_hz" in msg and "5000 Hz is more than the bus can carry" in msg
    # 4 frames of 135 bits at 1 Mbit/s + the configured host round trip (30 us), never 0
    assert "wire 540.0 us + configured round trip 30.0 us = 570.0 us per cycle" in msg and "285%" in msg
    assert "at most 1404 Hz" in msg and "set loop.rate_hz to 1403 or less" in msg
    assert "fd: true" in msg                                        # the setting that would fit


def test_check_config_accepts_can_fd_group_frames_at_5khz():
    r = run_cli(["check-config", str(CONFIGS / "gantry-can.yaml")])
    assert r.returncode == 0, r.stderr
    assert "ok" in r.stdout and "wire 117.2 us + configured round trip 30.0 us = 147.2 us per cycle" in r.stdout


def test_classic_can_accepts_the_rate_its_budget_names(tmp_path):
    assert load_config(_write(tmp_path, "gantry-can-classic.yaml", 1400)).cfg.loop.rate_hz == 1400


def test_serial_budget_names_the_baud_rate_that_fits(tmp_path):
    with pytest.raises(ConfigError) as exc:
        load_config(_write(tmp_path, "gantry-serial.yaml", 5000, baudrate=115200))
    msg = str(exc.value)
    assert "serial 115200 baud" in msg and "14 B command + 18 B reply" in msg
    assert "raise driver.baudrate to 3000000 (needs 2.75 Mbaud)" in msg   # 30 us round trip, 10 us device
    assert load_config(CONFIGS / "gantry-serial.yaml").cfg.loop.rate_hz == 5000   # 3 Mbaud fits


def test_modbus_tcp_cannot_do_5khz_and_says_so(tmp_path):
    with pytest.raises(ConfigError) as exc:
        load_config(_write(tmp_path, "gantry-modbus.yaml", 5000))
    msg = str(exc.value)
    assert "Modbus TCP, 1 request(s) per cycle (FC23 unit 1 write 0+5 read 100+7)" in msg
    assert "configured round trip 400.0 us" in msg and "at most 2000 Hz" in msg
    assert load_config(CONFIGS / "gantry-modbus.yaml").cfg.loop.rate_hz == 2000


def test_modbus_rtu_budget_counts_characters_and_gaps_with_the_line_settings(tmp_path):
    d = load_yaml(CONFIGS / "gantry-modbus.yaml")
    d["loop"]["rate_hz"] = 1000
    d["driver"].update(transport="rtu", serial_port="/dev/ttyUSB0", baudrate=115200, round_trip_s=0.0)
    with pytest.raises(ConfigError) as exc:
        config_from_dict(d, "rtu.yaml")
    msg = str(exc.value)
    # FC23: 23 B request + 19 B answer + 2 x 3.5 gap chars = 49 chars x 11 bits (8E1) at 115200 Bd + 500 us
    assert "Modbus RTU 115200 Bd 8E1, 1 request(s) (FC23 unit 1 write 0+5 read 100+7), 49 chars" in msg
    assert "5178.8 us per cycle" in msg
    d["driver"].update(parity="N")                    # no hard-coded 8E1: 10 bits per character
    with pytest.raises(ConfigError) as exc:
        config_from_dict(d, "rtu.yaml")
    assert "8N1" in str(exc.value) and "4753.5 us per cycle" in str(exc.value)
    d["loop"]["rate_hz"] = 150
    assert config_from_dict(d, "rtu.yaml").period_s == pytest.approx(1 / 150)


def test_modbus_map_is_split_into_the_requests_it_needs_and_overlaps_are_refused():
    d = load_yaml(CONFIGS / "gantry-modbus.yaml")
    d["axes"]["Y"]["driver"]["voltage"]["address"] = 10            # a gap: no single write block
    drv = config_from_dict(d, "gaps.yaml", check_budget=False).make_driver()
    assert drv.plan.summary() == ["FC16 unit 1 write 0+2", "FC16 unit 1 write 3+2", "FC06 unit 1 write 10+1",
                                  "FC03 unit 1 read 100+7"]
    b = drv.budget(1000)
    assert "4 request(s) per cycle" in b.detail and b.max_rate_hz < 1000     # 4 x 400 us: too slow
    d["axes"]["Y"]["driver"]["voltage"]["address"] = 0             # on X's voltage
    with pytest.raises(ConfigError, match="address 0 is used twice"):
        config_from_dict(d, "overlap.yaml")


def test_round_trip_is_never_trusted_as_zero():
    """Unset round_trip_s: the driver's assumed figure until configure() measures one."""
    d = load_yaml(CONFIGS / "gantry-can.yaml")
    del d["driver"]["round_trip_s"]
    drv = config_from_dict(d, "rt.yaml", check_budget=False).make_driver()
    assert drv.budget_round_trip() == (drv.DEFAULT_ROUND_TRIP_S, "assumed") and drv.DEFAULT_ROUND_TRIP_S > 0
    assert "assumed round trip 100.0 us" in drv.budget(5000).detail
    drv.round_trip = {"n": 50, "median_s": 250e-6, "max_s": 900e-6}   # what configure() stores
    assert drv.budget_round_trip() == (250e-6, "measured")
    assert "measured round trip 250.0 us" in drv.budget(1000).detail
    desc = drv.describe()
    assert desc["round_trip"] == {"n": 50, "median_us": 250.0, "max_us": 900.0, "budget_us": 250.0,
                                  "budget_source": "measured"}
    assert desc["budget"]["fits"] is False                        # 5 kHz with 117 + 250 us: no


def test_check_config_refuses_canopen_sync_and_two_axes_on_classic_can_and_names_the_rate(tmp_path):
    p = _write(tmp_path, "gantry-canopen.yaml", 5000)
    r = run_cli(["check-config", str(p)])
    assert r.returncode == 2, r.stdout
    msg = r.stderr
    # SYNC 55 + 2 x (RPDO 95 + TPDO 115) bits at 1 Mbit/s = 475 us, + 100 us configured round trip
    assert "CANopen classic CAN 1 Mbit/s, 2 axes: SYNC + 2 RPDO (4 B) + 2 TPDO (6 B)" in msg
    assert "wire 475.0 us + configured round trip 100.0 us = 575.0 us per cycle" in msg
    assert "at most 1357 Hz" in msg and "set loop.rate_hz to 1357 or less" in msg
    assert run_cli(["check-config", str(_write(tmp_path, "gantry-canopen.yaml", 1357))]).returncode == 0
    ok = run_cli(["check-config", str(CONFIGS / "gantry-canopen.yaml")])
    assert ok.returncode == 0 and "1000 Hz" in ok.stdout, ok.stderr


def test_a_read_timeout_longer_than_the_paced_period_is_refused_and_allowed_in_lockstep(tmp_path):
    """driver.timeout_s above 0.8 of the period leaves a wall-clocked cycle no time after a late
    answer: check-config refuses it, naming the key and what is allowed; with loop.clock virtual
    (lockstep with an emulated plant) the driver waits as long as configured."""
    import yaml
    cfg = _write(tmp_path, "gantry-modbus.yaml", 500.0, timeout_s=0.02)
    r = run_cli(["check-config", str(cfg)])
    assert r.returncode == 2, r.stdout
    assert "driver.timeout_s" in r.stderr and "at most 0.0016 s with loop.clock wall" in r.stderr, r.stderr
    assert "Traceback" not in r.stderr
    d = load_yaml(cfg)
    d["loop"]["clock"] = "virtual"
    cfg.write_text(yaml.safe_dump(d))
    assert load_config(cfg).make_driver().timeout_s == 0.02         # honoured, not cut to the period
    assert load_config(_write(tmp_path, "gantry-modbus.yaml", 500.0)).make_driver().timeout_s == 0.001  # default: half
