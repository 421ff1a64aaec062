"""Bus budgets: ``motorctl check-config`` refuses a rate the bus cannot carry, with the bus-time
figures and the setting that would fit, and accepts a feasible one."""

from __future__ import annotations

from pathlib import Path

import pytest

from motorctl.config import ConfigError, config_from_dict, load_config, load_yaml
from motorctl_emulators.harness import run_cli

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
    assert "540.0 us per cycle" in msg and "270%" in msg          # 4 frames of 135 bits at 1 Mbit/s
    assert "at most 1481 Hz" in msg and "set loop.rate_hz to 1481 or less" in msg
    assert "fd: true" in msg                                        # the setting that would fit


def test_check_config_accepts_can_fd_group_frames_at_5khz():
    r = run_cli(["check-config", str(CONFIGS / "gantry-can.yaml")])
    assert r.returncode == 0, r.stderr
    assert "ok" in r.stdout and "117.2 us per cycle" in r.stdout


def test_classic_can_accepts_the_rate_its_budget_names(tmp_path):
    assert load_config(_write(tmp_path, "gantry-can-classic.yaml", 1400)).cfg.loop.rate_hz == 1400


def test_serial_budget_names_the_baud_rate_that_fits(tmp_path):
    with pytest.raises(ConfigError) as exc:
        load_config(_write(tmp_path, "gantry-serial.yaml", 5000, baudrate=115200))
    msg = str(exc.value)
    assert "serial 115200 baud" in msg and "14 B command + 18 B reply" in msg
    assert "raise driver.baudrate to 3000000 (needs 2.20 Mbaud)" in msg
    assert load_config(CONFIGS / "gantry-serial.yaml").cfg.loop.rate_hz == 5000   # 3 Mbaud fits


def test_modbus_tcp_cannot_do_5khz_and_says_so(tmp_path):
    with pytest.raises(ConfigError) as exc:
        load_config(_write(tmp_path, "gantry-modbus.yaml", 5000))
    msg = str(exc.value)
    assert "Modbus TCP, 1 FC23 request per cycle" in msg
    assert "measured round trip 400.0 us" in msg and "at most 2000 Hz" in msg
    assert load_config(CONFIGS / "gantry-modbus.yaml").cfg.loop.rate_hz == 2000


def test_modbus_rtu_budget_counts_characters_and_gaps(tmp_path):
    d = load_yaml(CONFIGS / "gantry-modbus.yaml")
    d["loop"]["rate_hz"] = 1000
    d["driver"].update(transport="rtu", serial_port="/dev/ttyUSB0", baudrate=115200, round_trip_s=0.0)
    with pytest.raises(ConfigError) as exc:
        config_from_dict(d, "rtu.yaml")
    msg = str(exc.value)
    # FC23: 23 B request + 19 B answer + 2 × 3.5 gap chars = 49 chars × 11 bits at 115200 Bd + 500 us
    assert "Modbus RTU 115200 Bd, FC23 23 B request + 19 B answer" in msg and "5178.8 us per cycle" in msg
    d["loop"]["rate_hz"] = 150
    assert config_from_dict(d, "rtu.yaml").period_s == pytest.approx(1 / 150)


def test_modbus_map_needing_more_than_one_request_is_refused(tmp_path):
    d = load_yaml(CONFIGS / "gantry-modbus.yaml")
    d["axes"]["Y"]["driver"]["voltage_register"] = 10
    with pytest.raises(ConfigError, match="not contiguous"):
        config_from_dict(d, "gaps.yaml")
