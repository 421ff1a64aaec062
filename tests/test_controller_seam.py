"""The controller seam: a fourth law is one module and one entry point. A PD law written here
(outside the package, registered through a ``*.dist-info/entry_points.txt`` on the path, as an
installed plugin is) is checked by its own settings model, built, run and switched to by the
CLI, on an axis whose section configures no other law (no C1/C2 keys, no ``pid:``); a signal it
declares of its own (its proportional part) is a column of the run log, with no edit to the
loop."""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import yaml

from harness import parse_run_table, plugin_env
from motorctl.loop.records import columns_for
from motorctl.recorder.runlog import read_log

PLUGIN = '''
import numpy as np
from motorctl.control.base import SIG_E, SIG_P, SIG_V, SIG_X2, Controller
from motorctl.schema import StrictModel, quantity


class PdSettings(StrictModel):
    P: quantity(0.0, 1e10, "V/m") = 0.0
    D: quantity(0.0, 1e8, "V s/m") = 0.0
    FF2: quantity(-1e6, 1e6, "V s^2/m") = 0.0


class PD(Controller):
    name = "pd"
    Settings = PdSettings
    tuned_keys = ("P", "D")
    own_signals = {"u_P": "V"}

    def __init__(self, s, ts, u_lim):
        super().__init__(ts, u_lim, 0)
        self.s = s
        self.y_prev = 0.0

    @classmethod
    def from_config(cls, section, ts):
        return cls(section.settings("pd"), ts, section.u_lim)

    @classmethod
    def linearise(cls, gains, ts, w, theta_hat=None, u0=0.0):
        return gains["P"] + gains["D"] * (1.0 - np.exp(-1j * np.asarray(w) * ts)) / ts

    def reset(self, y0):
        self.y_prev = y0

    def update(self, y, x_d, xd_dot, xd_ddot, t=0.0):
        e = y - x_d
        x2 = (y - self.y_prev) / self.ts
        self.y_prev = y
        v = self.s.FF2 * xd_ddot - self.s.P * e - self.s.D * (x2 - xd_dot)
        sig = self.signals
        sig[SIG_V], sig[SIG_E], sig[SIG_P], sig[SIG_X2] = v, e, x2 - xd_dot, x2
        sig[self.own_index("u_P")] = -self.s.P * e
        return min(max(v, -self.u_lim), self.u_lim)
'''


def _plugin_env(tmp_path) -> dict:
    (tmp_path / "pdlaw.py").write_text(PLUGIN)
    return plugin_env(tmp_path, "pdlaw", "motorctl.controllers", {"pd": "pdlaw:PD"})


def _pd_config(repo, tmp_path, **pd) -> str:
    raw = yaml.safe_load((repo / "configs" / "gantry.yaml").read_text())
    del raw["axes"]["Y"]
    sec = raw["axes"]["X"]["controller"]
    keep = ("u_lim", "theta_min", "theta_max", "theta_hat0")
    raw["axes"]["X"]["controller"] = {"type": "pd", **{k: sec[k] for k in keep},
                                      "pd": {"P": 2.0e4, "D": 60.0, "FF2": sec["theta_hat0"][0], **pd}}
    path = tmp_path / "pd.yaml"
    path.write_text(yaml.safe_dump(raw, sort_keys=False))
    return str(path)


def _cli(repo, env, *args):
    return subprocess.run([sys.executable, "-m", "motorctl", *args], cwd=repo, env=env,
                          capture_output=True, text=True, timeout=120)


def test_a_fourth_law_is_one_module_and_one_entry_point(repo, tmp_path):
    env = _plugin_env(tmp_path)
    cfg = _pd_config(repo, tmp_path)
    p = _cli(repo, env, "check-config", cfg)
    assert p.returncode == 0, p.stderr
    log = tmp_path / "pd.mclog"
    p = _cli(repo, env, "run", cfg, "--virtual-clock", "--duration", "2", "--log", str(log))
    assert p.returncode == 0, p.stderr
    row = parse_run_table(p.stdout)["X"]
    assert row["fault"] == "" and row["e_M_um"] < 300.0, p.stdout
    # the law's own signal is a column after the fixed ones, its unit in the header
    rl = read_log(str(log))
    assert rl.columns[-1] == "X.u_P" and rl.header["units"][-1] == "V"
    assert rl.columns[:-1] == columns_for(["X"])
    prog = rl.program_rows("X")
    assert prog.sum() > 1000
    np.testing.assert_allclose(rl.col("X.u_P")[prog], -2.0e4 * rl.col("X.e")[prog], rtol=1e-12, atol=1e-12)
    # the law's own model checks its own mapping: file, key, what is allowed
    bad = _pd_config(repo, tmp_path, Q=1.0)
    p = _cli(repo, env, "check-config", bad)
    assert p.returncode == 2 and p.stderr.count("\n") == 1, p.stderr
    assert "axes.X.controller.pd.Q: unknown key; allowed here: P, D, FF2" in p.stderr
    # a law that keeps the base gain family (none) is not autotuned: a clear refusal, no traceback
    cfg = _pd_config(repo, tmp_path)           # (the bad file above took its path)
    p = _cli(repo, env, "autotune", cfg, "--axis", "X", "--law", "pd", "--out", str(tmp_path / "at"))
    assert p.returncode == 2 and p.stderr.count("\n") == 1, p.stderr
    assert "--law pd: not a law axis X configures" in p.stderr, p.stderr
    # without the plugin the same file names the laws that are installed
    p = _cli(repo, {k: v for k, v in env.items() if k != "PYTHONPATH"}, "check-config", cfg)
    assert p.returncode == 2 and "axes.X.controller" in p.stderr and "pd" in p.stderr, p.stderr


def test_a_section_with_only_a_pid_needs_no_dcdiarc_keys(repo, tmp_path):
    raw = yaml.safe_load((repo / "configs" / "gantry.yaml").read_text())
    sec = raw["axes"]["X"]["controller"]
    raw["axes"]["X"]["controller"] = {"type": "pid", "pid": sec["pid"],
                                      **{k: sec[k] for k in ("u_lim", "theta_min", "theta_max", "theta_hat0")}}
    path = tmp_path / "pid-only.yaml"
    path.write_text(yaml.safe_dump(raw, sort_keys=False))
    p = _cli(repo, dict(os.environ), "check-config", str(path))
    assert p.returncode == 0, p.stderr
    # C2 is not configured on X: asking for it is a clear error, nothing started
    p = _cli(repo, dict(os.environ), "run", str(path), "--controller", "c2", "--virtual-clock", "--duration", "0.1")
    assert p.returncode == 2 and p.stderr.count("\n") == 1, p.stderr
    assert "axes.X.controller" in p.stderr and "'c2'" in p.stderr, p.stderr


def test_each_law_declares_its_settings_linearisation_and_records():
    from motorctl.control import CONTROLLER_NAMES, controller_class
    from motorctl.loop.records import CONTROLLER_SIGNALS
    assert set(CONTROLLER_NAMES) >= {"c1", "c2", "pid"}
    for name in ("c1", "c2", "pid"):
        cls = controller_class(name)
        assert cls.name == name and cls.Settings is not None
        assert set(cls.records) <= set(CONTROLLER_SIGNALS) and "e" in cls.records
        assert cls.tuned_keys and all(k in cls.Settings.model_fields for k in cls.tuned_keys)
    assert "theta_hat5" in controller_class("c2").records and "theta_hat5" not in controller_class("c1").records


def test_own_signals_follow_every_axis_fixed_fields():
    """A law's own signals are the row's last columns (a reader of the fixed fields reads any
    log); one named like a fixed field is refused; a law names only the signals it declares."""
    import pytest

    from motorctl.control import controller_class
    from motorctl.loop.records import RecordLayout
    lay = RecordLayout(["X", "Y"], {"Y": {"u_P": "V"}})
    assert lay.columns[:lay.own_start] == columns_for(["X", "Y"])
    assert lay.columns[lay.own_start:] == ["Y.u_P"] and lay.units[-1] == "V" and lay.width == lay.own_start + 1
    with pytest.raises(ValueError, match="axis X: own signal 'u' is a fixed axis field"):
        RecordLayout(["X"], {"X": {"u": "V"}})
    with pytest.raises(KeyError, match="controller 'c2' declares no signal 'u_P'; own signals: none"):
        controller_class("c2").own_index("u_P")
