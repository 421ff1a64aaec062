"""``motorctl identify DATA --write-config OUT.yaml [--config BASE.yaml]``: identify -> tuned config."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import yaml

from motorctl.app.job import run_job
from motorctl.commission.tune import make_log
from motorctl.cli import main
from motorctl.config import load_config, load_yaml

SPRING = {"spring": {"stiffness_N_per_m": 100.0, "rest_position_m": 0.1}}


@pytest.fixture(scope="module")
def spring_log(tmp_path_factory):
    path = tmp_path_factory.mktemp("wc") / "spring.mclog"
    make_log(str(path), SPRING, duration_s=6.0, seed=1)
    return str(path)


def test_write_config_from_a_run_log(spring_log, tmp_path, capsys):
    out = tmp_path / "tuned.yaml"
    assert main(["identify", spring_log, "--no-closed-loop", "--write-config", str(out)]) == 0
    text = out.read_text()
    cfg = load_yaml(out)
    ctl = cfg["axes"]["X"]["controller"]
    comp = ctl["compensation"]["spring"]
    # k in V/m = 100 N/m / 80 N/V; x0 from the record (its mean position), not 0
    assert comp["stiffness_V_per_m"] == pytest.approx(1.25, rel=0.03)
    assert 0.05 < comp["rest_position_m"] < 0.35
    # θ̂(0) from the fit, re-expressed about x0: the plant's θ1..θ3 = .16 .22 .25, and the
    # constant force of offset + spring, θ4 + k x0 in eq. (4), that of the plant: −.05 + 1.25·0.1
    th0 = np.array(ctl["theta_hat0"][:4])
    assert th0[:3] == pytest.approx([0.16, 0.22, 0.25], abs=0.03)
    k, x0 = comp["stiffness_V_per_m"], comp["rest_position_m"]
    assert th0[3] + k * x0 == pytest.approx(-0.05 + 1.25 * 0.1, abs=0.02)
    # every change is commented with its figure
    assert "# motorctl identify: theta_hat0 from the joint fit" in text
    assert "spring: stiffness_N_per_m" in text
    # what check-config checks, and it runs unchanged
    loaded = load_config(out)
    assert main(["check-config", str(out)]) == 0
    r = run_job(loaded, duration_s=0.5, clock="virtual").axes["X"]
    assert not r["fault"]


def test_bounds_widened_where_the_fit_lies_outside(spring_log, tmp_path):
    base = load_yaml(__import__("motorctl.ident.synth", fromlist=["GANTRY"]).GANTRY)
    base = copy.deepcopy(base)
    base["axes"] = {"X": base["axes"]["X"]}
    ctl = base["axes"]["X"]["controller"]
    ctl["theta_max"][2] = 0.15          # the plant's θ3 is 0.25
    ctl["theta_hat0"][2] = 0.1
    bpath = tmp_path / "base.yaml"
    bpath.write_text(yaml.safe_dump(base, sort_keys=False))
    out = tmp_path / "tuned.yaml"
    assert main(["identify", spring_log, "--no-closed-loop", "--config", str(bpath),
                 "--write-config", str(out)]) == 0
    c = load_yaml(out)["axes"]["X"]["controller"]
    assert c["theta_max"][2] > c["theta_hat0"][2] > 0.15
    assert "theta_max widened" in out.read_text()
    assert main(["check-config", str(out)]) == 0


def test_write_config_needs_a_base(tmp_path):
    t = np.arange(0, 2.0, 1e-3)
    y = 0.1 * np.sin(2 * np.pi * t)
    u = 0.5 * np.cos(2 * np.pi * t)
    csv = tmp_path / "d.csv"
    np.savetxt(csv, np.column_stack([t, y, u]), delimiter=",", header="t,y,u", comments="")
    assert main(["identify", str(csv), "--write-config", str(tmp_path / "o.yaml")]) == 2
