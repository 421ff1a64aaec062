"""The supervisor's I²t and oscillation-at-rest protection (docs/protection.md): the compiled
checks on fed outputs (virtual time: one call is one period), the config's ranges, and the
unstable gain of the field (X on C2, k_s 250, k1 1800) latched through ``motorctl run``."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import yaml
from harness import run_cli

from motorctl.commission.evaluate import evaluate
from motorctl.commission.verify import _Verification
from motorctl.config import ConfigError, config_from_dict, load_yaml
from motorctl.control.pid import PID
from motorctl.loop.safety import FAULT_I2T, FAULT_OSCILLATION, Supervisor, sup_check_output
from motorctl.recorder.runlog import read_log


@pytest.fixture(scope="module")
def gantry(default_yaml):
    return yaml.safe_load(open(default_yaml))   # configs/gantry.yaml: the realistic plant


def _supervisor(gantry, **limits):
    d = {**gantry, "axes": {a: {**v, "limits": {**v["limits"], **limits}} for a, v in gantry["axes"].items()}}
    ld = config_from_dict(d)
    return Supervisor([ld.axes["X"].limits], ld.period_s), ld.period_s


def _feed(sup, u, vd):
    """Feed the outputs u (N,) at reference speeds vd (N,) through the output check (no
    following error); the index of the first refused one, or None."""
    for k in range(u.shape[0]):
        if not sup_check_output(sup.si, sup.sf, 0, 0.0, vd[k], u[k]):
            return k
    return None


def test_i2t_holds_the_peak_for_its_time_and_the_continuous_for_ever(gantry):
    sup, ts = _supervisor(gantry)            # 4.4 V continuous, 10 V for 1 s
    n = round(1.0 / ts)
    k = _feed(sup, np.full(2 * n, 10.0), np.full(2 * n, 1.0))
    assert k is not None and abs(k - n) <= 1, k          # 10 V from cold: refused after 1 s
    assert sup.fault[0] == FAULT_I2T and "i2t" in sup.reason(0)
    sup, _ = _supervisor(gantry)
    assert _feed(sup, np.full(5 * n, 4.4), np.full(5 * n, 1.0)) is None   # the continuous rating
    # 7 V: (10² − 4.4²)·1 s / (7² − 4.4²) = 2.72 s
    sup, _ = _supervisor(gantry)
    k = _feed(sup, np.full(4 * n, 7.0), np.full(4 * n, 1.0))
    assert abs(k * ts - (100 - 4.4 ** 2) / (49 - 4.4 ** 2)) < 2 * ts


def test_i2t_cools_at_the_continuous_rating(gantry):
    sup, ts = _supervisor(gantry, i2t_peak_time_s=0.5)
    n = round(0.4 / ts)                                  # 0.4 of 0.5 s at 10 V
    assert _feed(sup, np.full(n, 10.0), np.full(n, 1.0)) is None
    assert _feed(sup, np.zeros(5 * n), np.full(5 * n, 1.0)) is None    # 2 s at 0 V: cold again
    assert sup.i2t[0] == 0.0
    assert _feed(sup, np.full(n, 10.0), np.full(n, 1.0)) is None


def test_oscillation_at_rest_trips_after_one_window_with_its_frequency(gantry):
    sup, ts = _supervisor(gantry)
    t = np.arange(round(1.0 / ts)) * ts
    u = 1.0 + 3.0 * np.sin(2 * np.pi * 50.0 * t)         # 2.1 V RMS about a 1 V holding force
    k = _feed(sup, u, np.zeros_like(u))
    assert k == round(0.5 / ts) - 1                       # the end of the first 0.5 s window
    assert sup.fault[0] == FAULT_OSCILLATION
    assert abs(sup.oscillation_hz[0] - 50.0) <= 1.0          # a 0.5 s window counts to 1 Hz
    assert "oscillation at 49 Hz" in sup.reason(0)


@pytest.mark.parametrize("u_of_t,vd", [
    (lambda t: 3.0 * np.sin(2 * np.pi * 50.0 * t), 0.1),      # the same while the reference moves
    (lambda t: 1.5 * np.sin(2 * np.pi * 50.0 * t), 0.0),      # 1.06 V RMS at rest
    (lambda t: 4.0 + 0.0 * t, 0.0),                           # a holding force, no oscillation
    (lambda t: 3.0 * np.sin(2 * np.pi * 2.0 * t), 0.0),       # 2 Hz: a slow drift, not a limit cycle
], ids=["moving", "small", "dc", "slow"])
def test_what_is_not_an_oscillation_at_rest_does_not_trip(gantry, u_of_t, vd):
    sup, ts = _supervisor(gantry)
    t = np.arange(round(2.0 / ts)) * ts
    assert _feed(sup, u_of_t(t), np.full(t.shape, vd)) is None, sup.reason(0)


@pytest.mark.parametrize("key,value,words", [
    ("i2t_continuous_V", 10.0, "must be below i2t_peak_V"),
    ("i2t_peak_V", 0.0, "outside the physical range"),
    ("oscillation_window_s", 100.0, "outside the physical range"),
    ("oscillation_rms_V", -1.0, "outside the physical range"),
])
def test_the_protections_settings_are_checked(gantry, key, value, words):
    with pytest.raises(ConfigError) as exc:
        _supervisor(gantry, **{key: value})
    assert f"axes.X.limits.{key}" in str(exc.value) and words in str(exc.value)


def test_an_unstable_gain_is_latched_at_0V_within_a_window_of_rest(gantry, tmp_path):
    """X on C2 with k_s 250, k1 1800 settles into a limit cycle at rest (±10 V, hundreds of
    Hz): ``motorctl run`` for 20 s on the virtual clock exits 1 with the oscillation, 0 V and
    the amplifier off from the tripping cycle to the run's end, 0.5 s (one window, the time
    docs/protection.md states) after the reference came to rest."""
    d = {**gantry}
    d["axes"] = {**gantry["axes"], "X": {**gantry["axes"]["X"],
                                         "controller": {**gantry["axes"]["X"]["controller"], "k_s": 250.0,
                                                        "k1": 1800.0}}}
    cfg = tmp_path / "unstable.yaml"
    cfg.write_text(yaml.safe_dump(d))
    log = tmp_path / "run.log"
    r = run_cli(["run", str(cfg), "--axis", "X", "--controller", "c2", "--duration", "20", "--virtual-clock",
                 "--log", str(log)], timeout_s=600)
    assert r.returncode == 1, r.stdout + r.stderr
    assert "oscillation" in r.stdout or "i2t" in r.stdout, r.stdout
    rl = read_log(str(log))
    t, fb, u, en, vd = (rl.col(c) for c in ("t", "X.fault_bits", "X.u", "X.enabled", "X.xd_dot"))
    k = int(np.argmax(fb != 0))
    assert fb[k] != 0 and int(fb[k]) & (FAULT_I2T | FAULT_OSCILLATION)
    assert not np.any(u[k:]) and not np.any(en[k:])       # the tripping cycle writes 0 V, enable off
    moving = np.flatnonzero(vd[:k] != 0.0)
    rest = t[moving[-1] + 1] if moving.size else t[0]
    assert t[k] - rest <= 0.5 + 2 * rl.header["period_s"], (t[k], rest)
    assert math.isclose(rl.header["program_start_s"], 3 * rl.header["period_s"])   # 2 idle, 1 approach


#: gains a search can reach that settle into a limit cycle at rest (the issue's): X on C2 (474 Hz,
#: 8.2 V RMS), Y on PID at ω_n 1400 rad/s, integral corner ω_n/3, ζ 0.3 (314 Hz, 7.5 V RMS) and
#: ζ 1.0 (583 Hz, 6.0 V RMS), both tripping in their first window at rest; at ζ 0.7 the chatter
#: grows to the 2 V trip only after 5.5 s (docs/protection.md), beyond these 2 s runs
UNSTABLE = [("X", "c2", {"k_s": 250.0, "k1": 1800.0, "gamma_d": 500.0})] + [
    ("Y", "pid", g) for g in PID.gain_family(0.55, None, [1400.0])
    if g["_r"] == 3.0 and g["_zeta"] in (0.3, 1.0)]


@pytest.mark.parametrize("axis,law,gains", UNSTABLE, ids=["X-c2", "Y-pid-zeta0.3", "Y-pid-zeta1.0"])
def test_autotune_steps_down_a_candidate_whose_run_trips_and_never_hands_it_over(default_yaml, axis, law, gains):
    """Autotune's confirmation (:func:`motorctl.commission.verify.verify`'s last step) of a
    candidate that passed its short run but whose full run (2 s on the virtual clock, through
    ``motorctl run``'s job and the cycle's supervisor) latches the oscillation: the candidate is
    refused on that fault and only its gains stepped down are tried; what comes back (if
    anything) is a step down whose own runs all passed, never the tripping gains."""
    raw = load_yaml(default_yaml)
    ref = evaluate(raw, str(default_yaml), axis, law, 2.0)
    v = _Verification(raw, str(default_yaml), axis, law, {"holds": lambda g: True}, 2.0, "virtual", ref, None,
                      None)
    v.found.append((0.0, gains, 1.0, "search"))
    best = v.confirm(None, 2.0, ref)
    label, scale, res, why = v.runs[0]
    assert scale == 1.0 and why.startswith("fault: ") and ("oscillation" in why or "i2t" in why), v.runs[0]
    assert [r[0] for r in v.runs[1:]] and all(r[1] < 1.0 for r in v.runs[1:]), [r[:2] for r in v.runs]
    assert best is None or (best[2] < 1.0 and best[1] != gains), best


def test_tune_never_hands_over_a_config_whose_run_trips(default_yaml, tmp_path, monkeypatch):
    """``motorctl tune`` whose tuned config (here: the identification's, with X's C2 at k_s 250,
    k1 1800) latches the oscillation in its after run: tune stops with the fault, and no
    ``tuned.yaml`` is left for anyone to load (it is ``tuned-rejected.yaml``)."""
    from motorctl.commission.tune import FILES, tune
    from motorctl.ident import pipeline
    real = pipeline.write_tuned_config

    def unstable(idf, s, base, axis, base_name, path):
        new = real(idf, s, base, axis, base_name, path)
        new["axes"][axis]["controller"].update(k_s=250.0, k1=1800.0)
        Path(path).write_text(yaml.safe_dump(new, sort_keys=False))
        return new

    monkeypatch.setattr(pipeline, "write_tuned_config", unstable)
    out = tmp_path / "out"
    res = tune(str(default_yaml), "X", out, duration_s=4.0, clock="virtual")
    assert res["faults"]["before"] == "" and "oscillation" in res["faults"]["after"], res["faults"]
    assert res["stopped"].startswith("the after run faulted: oscillation") and "not handed over" in res["stopped"]
    assert not (out / FILES["tuned"]).exists() and "tuned" not in res["files"]
    rejected = yaml.safe_load((out / FILES["rejected"]).read_text())
    assert rejected["axes"]["X"]["controller"]["k_s"] == 250.0
