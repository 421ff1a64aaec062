"""``motorctl autotune`` end to end on the simulated driver (virtual clock): the excitation stays
inside the stroke and under the following-error guard, the fitted model finds the simulated
axis, and the written config carries gains with their margins."""

from __future__ import annotations

import json
import subprocess
import sys

import yaml

from motorctl.app.autotune import GM_MIN_DB, MS_MAX_DB, PM_MIN_DEG
from motorctl.config import load_yaml


def _autotune(repo, tmp_path, *args):
    return subprocess.run([sys.executable, "-m", "motorctl", "autotune", *args],
                          cwd=repo, capture_output=True, text=True, timeout=300)


def test_autotune_sim_end_to_end(repo, tmp_path):
    out = tmp_path / "at"
    p = _autotune(repo, tmp_path, "configs/gantry.yaml", "--axis", "X", "--out", str(out),
                  "--virtual-clock", "--verify-seconds", "4", "--json")
    assert p.returncode == 0, p.stderr
    res = json.loads(p.stdout)["axes"]["X"]
    meas, model = res["measurement"], res["model"]
    plant = load_yaml(repo / "configs" / "gantry.yaml")["axes"]["X"]["driver"]
    # the excitation never left the stroke nor reached the guard (half the FE limit)
    lo, hi = meas["soft_limits_m"]
    assert lo < meas["stroke_m"][0] and meas["stroke_m"][1] < hi
    assert meas["e_max_m"] < meas["guard_m"]
    # the fit finds the simulated axis: M/A1, the structural mode, the current loop (10 %)
    assert abs(model["theta1"] / (plant["mass_kg"] / plant["a1_N_per_V"]) - 1.0) < 0.10
    assert abs(model["mode_hz"] / plant["mode_hz"] - 1.0) < 0.10
    assert abs(model["current_loop_hz"] / plant["current_loop_hz"] - 1.0) < 0.10
    # gains for both law groups, verified, with margins that hold the rule
    assert set(res["gains"]) == {"c1/c2", "pid"}
    for law in ("c2", "pid"):
        m = res["margins"][law]
        assert m["pm_deg"] >= PM_MIN_DEG - 5.0 and m["ms_db"] <= MS_MAX_DB + 1.0
        assert m["gm_db"] is None or m["gm_db"] >= GM_MIN_DB - 1.0
    assert all(v["fault"] == "" for v in res["verify"] if v["verdict"] == "ok")
    written = yaml.safe_load((out / "autotuned.yaml").read_text())
    assert written["axes"]["X"]["controller"]["pid"]["P"] == res["gains"]["pid"]["P"]
    assert "PM" in (out / "autotuned.yaml").read_text().splitlines()[4]
    check = subprocess.run([sys.executable, "-m", "motorctl", "check-config", str(out / "autotuned.yaml")],
                           cwd=repo, capture_output=True, text=True, timeout=60)
    assert check.returncode == 0, check.stderr


def test_autotune_refuses_an_unknown_axis(repo, tmp_path):
    p = _autotune(repo, tmp_path, "configs/gantry.yaml", "--axis", "Z", "--out", str(tmp_path))
    assert p.returncode == 2
    assert p.stderr.count("\n") == 1 and "--axis Z" in p.stderr

