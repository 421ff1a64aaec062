"""Strict config loading: every error case gives one line naming the file and key, exit 2."""

import copy

import pytest
import yaml

from motorctl.cli import main
from motorctl.config import ConfigError, load_config, load_yaml


@pytest.fixture(scope="module")
def base(gantry_yaml):
    return load_yaml(gantry_yaml)


def _check(tmp_path, capsys, data=None, text=None):
    path = tmp_path / "bad.yaml"
    path.write_text(text if text is not None else yaml.safe_dump(data))
    code = main(["check-config", str(path)])
    err = capsys.readouterr().err
    return code, err, str(path)


def _edit(base, dotted, value):
    data = copy.deepcopy(base)
    node = data
    keys = dotted.split(".")
    for k in keys[:-1]:
        node = node[k]
    if value is _DELETE:
        del node[keys[-1]]
    else:
        node[keys[-1]] = value
    return data


_DELETE = object()

CASES = [
    # (key path, value, expected key in the message, expected words)
    ("axes.X.controller.k_sx", 95.0, "axes.X.controller.k_sx", "unknown key; allowed here: type, u_lim"),
    ("axes.X.controller.k_s", "ninety-five", "axes.X.controller.k_s", "valid number"),
    ("axes.X.controller.k_s", -1.0, "axes.X.controller.k_s", "-1 V s/m is outside the physical range [0.001, 1e+07] V s/m"),
    ("axes.X.trajectory.v_max", 1.7096854882967697e-151, "axes.X.trajectory.v_max",
     "1.70969e-151 m/s is outside the physical range [1e-06, 20] m/s"),
    ("axes.X.driver.mass_kg", 1e300, "axes.X.driver.mass_kg", "1e+300 is no physical value of a gantry"),
    ("axes.X.controller.type", "c3", "axes.X.controller.type", "allowed here: c1, c2"),
    ("axes.X.controller.theta_min", [0.05, 0.08, 0.05, -0.5, -0.015], "axes.X.controller.theta_min", "at least 6"),
    ("axes.X.controller.theta_hat0", [0.4, 0.2, 0.1, 0.0, 0.0, 0.0], "axes.X.controller.theta_hat0[0]", "outside [theta_min, theta_max]"),
    ("axes.X.controller.theta_min", [0.05, 0.08, 0.05, -0.5, -0.03, -0.003], "axes.X.controller.theta_min", "Assumption 2"),
    ("axes.X.controller.gamma0", [2.0, 50.0, 100.0, 5000.0, 0.05, 0.005], "axes.X.controller.gamma0", "rho_M"),
    ("axes.X.controller.mu", True, "axes.X.controller.mu", "valid number"),
    ("axes.X.driver.mass_kg", 0.0, "axes.X.driver.mass_kg", "greater than 0"),
    ("axes.X.driver.effects", {"cogging": {"period_m": 0.06}}, "axes.X.driver.effects.cogging.amplitudes_N", "Field required"),
    ("driver.type", "nosuchbus", "driver.type", "no driver named 'nosuchbus'"),
    ("driver.seed", "one", "driver.seed", "valid integer"),
    ("loop.rate_hz", 50000.0, "loop.rate_hz", "less than or equal to 20000"),
    ("loop.clock", "sundial", "loop.clock", "'wall' or 'virtual'"),
    ("axes.X.trajectory.move_times_s", [0.5, 0.6], "axes.X.trajectory", "overlaps"),
    ("axes.X.trajectory.points", [0.0, 0.5], "axes.X.trajectory.points", "soft limits"),
    ("axes.X.limits.soft_min_m", 0.5, "axes.X.limits.soft_min_m", "below soft_max_m"),
    ("axes.X.controller", _DELETE, "axes.X.controller", "Field required"),
]


@pytest.mark.parametrize("dotted,value,key,words", CASES, ids=[c[0] + ":" + str(i) for i, c in enumerate(CASES)])
def test_config_errors_name_file_and_key(tmp_path, capsys, base, dotted, value, key, words):
    code, err, path = _check(tmp_path, capsys, _edit(base, dotted, value))
    assert code == 2
    assert err.count("\n") == 1, err  # one line
    assert err.startswith(f"motorctl: error: {path}: {key}"), err
    assert words in err, err
    assert "Traceback" not in err


def test_duplicate_key_is_refused(tmp_path, capsys, gantry_yaml):
    text = gantry_yaml.read_text().replace("      k_s: 95.0\n", "      k_s: 95.0\n      k_s: 50.0\n", 1)
    code, err, path = _check(tmp_path, capsys, text=text)
    assert code == 2
    assert "duplicate key 'k_s'" in err and path in err and "line" in err


def test_yaml_syntax_error_and_missing_file(tmp_path, capsys):
    code, err, path = _check(tmp_path, capsys, text="loop: [1, 2\n")
    assert code == 2 and path in err and "line" in err
    code = main(["check-config", str(tmp_path / "nope.yaml")])
    err = capsys.readouterr().err
    assert code == 2 and "nope.yaml" in err and "no such file" in err
    code, err, path = _check(tmp_path, capsys, text="- just\n- a list\n")
    assert code == 2 and "top level must be a mapping" in err


def test_the_shipped_config_is_valid(gantry_yaml, capsys):
    assert main(["check-config", str(gantry_yaml)]) == 0
    out = capsys.readouterr().out
    assert "ok: 2 axes (X, Y)" in out
    loaded = load_config(gantry_yaml)
    assert loaded.period_s == pytest.approx(2e-4)
    with pytest.raises(ConfigError):
        load_config(gantry_yaml.parent / "missing.yaml")


def test_a_laws_settings_are_parsed_once_from_yaml_to_the_controller(monkeypatch):
    """The loader's checks and the controller built from the section share one parse of each
    law's settings (the section keeps it); a copy of the section parses its own keys."""
    from motorctl.control import make_controller
    from motorctl.control.dcdiarc import DcdiarcConfig

    parsed = []
    real = DcdiarcConfig.model_validate.__func__

    def counting(cls, data, *a, **k):
        parsed.append(dict(data))
        return real(cls, data, *a, **k)

    monkeypatch.setattr(DcdiarcConfig, "model_validate", classmethod(counting))
    loaded = load_config("configs/gantry.yaml")
    section = loaded.axes["X"].controller
    assert len(parsed) == 2 * len(loaded.axes)          # c1 and c2 of each axis, once each
    ctl = make_controller(section, "c2", loaded.period_s)
    assert len(parsed) == 2 * len(loaded.axes)
    assert ctl.law is section.settings("c2")
    faster = section.model_copy(update={"u_lim": 5.0})
    assert faster.settings("c2") is not section.settings("c2") and len(parsed) == 2 * len(loaded.axes) + 1
    with pytest.raises(KeyError, match="unknown controller 'nope'; allowed: c1, c2, gtcf, pid"):
        make_controller(section, "nope", loaded.period_s)
