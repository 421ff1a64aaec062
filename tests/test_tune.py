"""``motorctl tune CONFIG --axis A``: run → identify → tuned config → run again → compare, with the
effect-free floor on the simulated driver; and the same before/after over a real protocol
(serial, against ``motorctl emulate``), with ``compare-runs`` on the two real-driver logs."""

from __future__ import annotations

import copy
import json
import subprocess

import pytest
import yaml
from conftest import MOTORCTL, RIGID_PLANT

from motorctl.commission.tune import FILES, U_REST_SLACK, better, damage_removed, effect_free, effects_on
from motorctl.cli import main
from motorctl.cli.tune import text_report
from motorctl.config import config_from_dict, load_config, load_yaml
from motorctl.effects import FAMILIES
from motorctl.ident.synth import gantry_dict

SPRING = FAMILIES["spring"].example
DURATION = "8"
#: the emulated drive's command watchdog in the real-driver test [s]: longer than the
#: identification between the before and the after run takes on a loaded machine
IDENTIFY_GAP_S = 60.0


def _write(path, d: dict):
    path.write_text(yaml.safe_dump(d, sort_keys=False))
    return path


@pytest.fixture(scope="module")
def spring_tune(tmp_path_factory):
    """`motorctl tune --json` on the rigid X axis with an undeclared spring (8 s, virtual clock)."""
    d = tmp_path_factory.mktemp("tune")
    cfg = _write(d / "spring.yaml", gantry_dict("X", SPRING))
    out = d / "out"
    r = subprocess.run([*MOTORCTL, "tune", str(cfg), "--axis", "X", "--duration", DURATION, "--out", str(out),
                        "--json"], check=False, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    return json.loads(r.stdout), out


def test_tune_hands_over_no_compensation_the_loop_is_worse_with(tmp_path, default_yaml):
    """The shipped default plant has no undeclared effect; identify names phantom ones there (a
    spring and an input delay, from stiction, the mode and the current loop). Compensated, they
    make L2[e] worse, so tune keeps none of them and writes the config unchanged: the after run
    is the before run. Since ``run`` starts with idle cycles and an approach (the program 3
    cycles later on the plant's noise) the input delay's compensation (0.22 ms: the current
    loop's lag) makes L2[e] 4 % better on this seed (2.660 -> 2.547 um) and is kept, on seed 2
    it is dropped (the verdict turns on the noise's realization): what is kept made the loop
    better, what is dropped leaves the config unchanged."""
    out = tmp_path / "out"
    r = subprocess.run([*MOTORCTL, "tune", str(default_yaml), "--axis", "X", "--duration", DURATION, "--out",
                        str(out), "--virtual-clock", "--json"], check=False, capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 0, r.stderr
    res = json.loads(r.stdout)
    assert res["floor_effects_off"] == []                        # nothing to remove on this plant
    c = res["compare"]
    assert c is None or c["after"]["L2_um"] <= c["before"]["L2_um"], c
    assert set(res["kept"]) <= {"input_delay"}, res                # no phantom spring kept
    assert set(res["kept"]) | set(res["dropped"]) == set(res["compensation"]), res
    if res["kept"]:                                              # kept: the loop is better with it
        assert c["after"]["L2_um"] < c["before"]["L2_um"], c
    elif res["compensation"]:                                    # found, tried, dropped
        assert res["verdict"].startswith("no effect kept") and c["after"] == c["before"]
        assert "compensation" not in yaml.safe_load((out / FILES["tuned"]).read_text())["axes"]["X"]["controller"]


def test_tune_removes_the_springs_damage_against_the_floor(spring_tune):
    res, out = spring_tune
    assert res["driver"] == "sim" and res["clock"] == "virtual" and res["stopped"] is None
    assert res["kept"] == ["spring"] and res["dropped"] == {} and res["verdict"] is None
    # the fitted θ̂(0) is one of the changes the closed loop judges: run once without it
    assert (out / "without_theta_hat0.mclog").is_file() and res["files"]["without_theta_hat0"]
    assert res["theta_hat0"].startswith(("the fitted one", "the config's own: the loop is better without it"))
    assert [e["name"] for e in res["effects"]] == ["spring"] and "spring" in res["compensation"]
    assert res["floor_effects_off"] == ["spring"]
    for step in ("before", "tuned", "after", "floor_config", "floor"):
        assert (out / FILES[step]).is_file() and res["files"][step] == str(out / FILES[step])
    c = res["compare"]
    # the same program periods for all three runs (period 4 s, the first excluded)
    assert c["window_s"] == [4.0, 8.0]
    assert c["before"]["cycles"] == c["after"]["cycles"] == c["floor"]["cycles"]
    assert c["ratio"]["L2_um"] == pytest.approx(c["after"]["L2_um"] / c["before"]["L2_um"])
    b, a, f = (c[k]["L2_um"] for k in ("before", "after", "floor"))
    assert b > f                                   # the spring does damage
    assert res["damage_removed"] == pytest.approx((b - a) / (b - f))
    assert res["damage_removed"] >= 0.8
    assert res["e_M_not_worse"] and c["after"]["e_M_um"] <= c["before"]["e_M_um"]
    text = text_report(res)
    for word in ("effect found: spring", "before", "after", "ratio", "floor", "damage removed", "e_M not worse"):
        assert word in text


def test_tuned_config_checks_and_runs_unchanged(spring_tune, tmp_path, capsys):
    res, out = spring_tune
    tuned = out / FILES["tuned"]
    assert load_yaml(tuned)["axes"]["X"]["controller"]["compensation"] == res["compensation"]
    assert main(["check-config", str(tuned)]) == 0
    assert main(["run", str(tuned), "--duration", "1", "--log", str(tmp_path / "again.mclog")]) == 0
    # the floor is the same plant without the spring: nothing else changed
    floor = load_yaml(out / FILES["floor_config"])
    base = gantry_dict("X", SPRING)
    del base["axes"]["X"]["driver"]["effects"]
    assert floor == base


def test_a_config_without_an_effect_stops_after_the_first_run(tmp_path, capsys):
    cfg = _write(tmp_path / "clean.yaml", gantry_dict("X"))
    out = tmp_path / "out"
    assert main(["tune", str(cfg), "--axis", "X", "--duration", DURATION, "--out", str(out)]) == 0
    assert "no effect found" in capsys.readouterr().out
    assert sorted(p.name for p in out.iterdir()) == [FILES["before"]]


def test_bad_input_exits_2_with_one_line(tmp_path, capsys):
    cfg = _write(tmp_path / "clean.yaml", gantry_dict("X"))
    blocker = tmp_path / "a_file"
    blocker.write_text("")
    cases = [["tune", str(cfg)],                                        # no --axis
             ["tune", str(cfg), "--axis", "Z", "--out", str(tmp_path / "z")],
             ["tune", str(cfg), "--axis", "X", "--out", str(blocker)],  # --out not a directory
             ["tune", str(cfg), "--axis", "X", "--out", "/proc/motorctl-tune-test"],  # cannot be made
             ["tune", str(cfg), "--axis", "X", "--duration", "1", "--out", str(tmp_path / "short")],
             ["tune", str(tmp_path / "missing.yaml"), "--axis", "X", "--out", str(tmp_path / "m")]]
    for argv in cases:
        assert main(argv) == 2, argv
        err = capsys.readouterr()
        assert err.err.startswith("motorctl: error:") and err.err.count("\n") == 1, (argv, err.err)
        assert err.out == ""
    for d in ("z", "short", "m"):                # refused before anything was written
        assert not (tmp_path / d).exists()


@pytest.mark.parametrize("name", list(FAMILIES))
def test_effect_free_switches_every_removable_family_off_and_nothing_else(name):
    """The floor is the best a compensation can do: what no compensation removes stays on."""
    on = gantry_dict("X", FAMILIES[name].example)
    assert effects_on(config_from_dict(on), "X") == [name]
    off = effect_free(on)
    if FAMILIES[name].has_compensation:
        assert effects_on(config_from_dict(off), "X") == []
        assert off == gantry_dict("X")
    else:
        assert off == on
    assert on == gantry_dict("X", FAMILIES[name].example)       # the input is not modified


def test_damage_removed():
    assert damage_removed(5.0, 3.0, 3.0) == 1.0
    assert damage_removed(5.0, 4.0, 3.0) == 0.5
    assert damage_removed(3.0, 3.0, 3.0) is None                 # no damage: nothing to remove


# --------------------------------------------------------------------------- a real driver
def test_tune_and_compare_runs_over_the_serial_emulator(tmp_path, capsys):
    """The before/after on a real driver: configs/gantry-serial.yaml against ``motorctl emulate``
    (its plant: the rigid gantry with a spring on X), in lockstep with the device
    (``--virtual-clock``, a 50 ms read timeout, the driver's default error bucket: the verdict
    does not depend on the host's scheduling); then ``compare-runs`` on the two real-driver logs
    gives tune's table."""
    from pathlib import Path

    from harness import Emulator, loopback_e2e_config
    configs = Path(RIGID_PLANT).parent
    d, cfg, _rate = loopback_e2e_config("serial", configs, tmp_path)
    d["loop"]["clock"] = "virtual"
    d["driver"]["timeout_s"] = 0.05
    # the drive's command watchdog must outlast the identification between the two runs, else
    # it latches an amplifier fault that the after run starts with (the emulator trips it on a
    # disabled axis too): the host leaves it at the emulator's IDENTIFY_GAP_S
    d["driver"]["watchdog_s"] = None
    _write(cfg, d)
    plant = load_yaml(RIGID_PLANT)
    plant["axes"]["X"]["driver"]["effects"] = copy.deepcopy(SPRING)
    plant_path = _write(tmp_path / "plant.yaml", plant)
    out = tmp_path / "out"
    with Emulator("serial", cfg, plant=plant_path, watchdog_s=IDENTIFY_GAP_S):
        assert main(["tune", str(cfg), "--axis", "X", "--duration", DURATION, "--out", str(out), "--virtual-clock",
                     "--json"]) == 0
    res = json.loads(capsys.readouterr().out)
    assert res["driver"] == "serial" and res["clock"] == "virtual"
    assert res["floor_effects_off"] is None and "floor" not in res["compare"]
    # found and compensated; whether it is kept is the closed loop's verdict (at 2 kHz over this
    # one compared period the spring's compensation gives e_M 43.1 -> 41.8 um but L2[e] 8.60 ->
    # 8.74 um: dropped, and tuned.yaml is the config unchanged)
    assert "spring" in res["compensation"], res["effects"]
    assert set(res["kept"]) | set(res["dropped"]) == {"spring"}, (res["kept"], res["dropped"])
    assert not any(res["faults"].values())
    assert load_config(out / FILES["tuned"]).cfg.driver.type == "serial"
    assert main(["compare-runs", res["files"]["before"], res["files"]["after"], "--json"]) == 0
    cmp = json.loads(capsys.readouterr().out)["axes"]["X"]
    assert cmp == res["compare"]                       # tune's table is compare-runs'
    assert cmp["before"]["cycles"] == cmp["after"]["cycles"] > 0
    for k, v in cmp["ratio"].items():
        assert v == pytest.approx(cmp["after"][k] / cmp["before"][k])
    # identified from the real-driver log (no gain in its header: V units): the plant's spring
    k_V_per_m = FAMILIES["spring"].example["spring"]["stiffness_N_per_m"] / plant["axes"]["X"]["driver"]["a1_N_per_V"]
    assert res["compensation"]["spring"]["stiffness_V_per_m"] == pytest.approx(k_V_per_m, rel=0.05)


def test_better_lets_l2_decide_with_e_m_held_to_the_before_run():
    """A change stays undone when the loop without it has a lower L2[e], and an e_M no more than
    one encoder count above the before run's (not the current best's)."""
    before = {"L2_um": 3.3, "e_M_um": 20.6}
    best = {"L2_um": 3.0, "e_M_um": 11.1}
    assert better({"L2_um": 2.5, "e_M_um": 14.8}, best, before)        # lower L2, e_M below before
    assert not better({"L2_um": 2.5, "e_M_um": 14.8}, best)            # against the best's own e_M
    assert not better({"L2_um": 2.5, "e_M_um": 21.2}, best, before)    # e_M worse than before
    assert not better({"L2_um": 3.0, "e_M_um": 5.0}, best, before)     # L2 not lower


def test_better_holds_u_noise_at_rest_to_the_before_run():
    """u's RMS at rest may not grow more than U_REST_SLACK above the before run's; without the
    figure (a log without ẋ_d, or no rest in the window) L2[e] and e_M decide alone."""
    before = {"L2_um": 3.3, "e_M_um": 20.6, "u_rest_rms_V": 0.100}
    best = {"L2_um": 3.0, "e_M_um": 11.1, "u_rest_rms_V": 0.100}
    quiet = 0.100 * (1 + U_REST_SLACK) * 0.99
    noisy = 0.100 * (1 + U_REST_SLACK) * 1.01
    assert better({"L2_um": 2.5, "e_M_um": 14.8, "u_rest_rms_V": quiet}, best, before)
    assert not better({"L2_um": 2.5, "e_M_um": 14.8, "u_rest_rms_V": noisy}, best, before)
    assert better({"L2_um": 2.5, "e_M_um": 14.8}, best, before)
    assert better({"L2_um": 2.5, "e_M_um": 14.8, "u_rest_rms_V": None}, best, before)
