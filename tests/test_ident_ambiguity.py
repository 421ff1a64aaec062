"""A name only where the record can tell (docs/identification.md, "Ambiguities"): a force from
outside at a harmonic of the program's period is reported as ambiguous with a force of
position (named neither, compensated neither), the same force off the harmonic is still named;
a coarse encoder with nothing injected gets no spring; the EMPS offset is reported with the
publication's sign (and a validation error is printed).

The records are made here by a PID position loop in Python (8 s at 1 kHz, about 0.3 s each; no
simulated gantry: its 20 s logs take a minute each on a loaded machine), each identified once
per module. Deterministic: fixed seeds, no wall-clock verdict.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from harness import emps_path
from motorctl.ident.ambiguity import POSITION_FAMILIES, SPEED_EXPERIMENT
from motorctl.ident.data import load_record
from motorctl.ident.pipeline import compensation_from_fit, identify_record, text_report, validation

#: the loop's plant: mass [kg], force gain A1 [N/V], viscous [N s/m], Coulomb [N]
M, A1, B, FC = 10.0, 50.0, 20.0, 8.0
FS, DURATION_S = 1000.0, 8.0
#: the disturbance [N] and its frequencies: a harmonic of the 1 s program (and of the 2 s the
#: motion's self-correlation may pick), and one 0.37 Hz off (the record's resolution: 0.125 Hz)
DIST_N, AT_HARMONIC_HZ, OFF_HARMONIC_HZ = 4.0, 11.0, 11.37


def _program(duration_s: float = DURATION_S) -> np.ndarray:
    """Moves 0 ↔ 0.3 m with a raised-cosine speed (0.4 s each) and 0.1 s rests: a program of
    period 1 s, sampled at FS (N,) [m]."""
    n_move, n_rest = int(0.4 * FS), int(0.1 * FS)
    tau = np.arange(n_move) / n_move
    up = 0.3 * (tau - np.sin(2 * np.pi * tau) / (2 * np.pi))
    one = np.concatenate([up, np.full(n_rest, 0.3), up[::-1], np.zeros(n_rest)])
    n = int(duration_s * FS)
    return np.tile(one, n // len(one) + 1)[:n]


def _record(path, seed: int = 0, dist_Hz: float | None = None, y_noise_m: float = 2e-7,
            quantum_m: float = 0.0) -> str:
    """A PID loop tracking :func:`_program`, written as a CSV ``t,y,u`` (gain A1): the mass
    with viscous and Coulomb friction (explicit Euler at 1/FS), seeded noise on y and u, a
    force DIST_N·sin(2π f t + 0.4) [N] at ``dist_Hz`` (None: none), the reading rounded to
    ``quantum_m`` [m] (0: not). Returns the path as text."""
    rng = np.random.default_rng(seed)
    xd = _program()
    n, ts = len(xd), 1.0 / FS
    t = np.arange(n) * ts
    x = v = e_int = 0.0
    ys, us = np.empty(n), np.empty(n)
    for i in range(n):
        y = x + rng.normal(0.0, y_noise_m)
        if quantum_m:
            y = quantum_m * round(y / quantum_m)
        e = xd[i] - y
        e_int += e * ts
        vd = (xd[min(i + 1, n - 1)] - xd[i]) / ts
        u = float(np.clip(4000.0 * e + 40000.0 * e_int + 60.0 * (vd - v) + rng.normal(0.0, 0.02), -10.0, 10.0))
        f = A1 * u - B * v - FC * math.tanh(v / 1e-3)
        if dist_Hz is not None:
            f += DIST_N * math.sin(2 * math.pi * dist_Hz * t[i] + 0.4)
        v += f / M * ts
        x += v * ts
        ys[i], us[i] = y, u
    np.savetxt(path, np.column_stack([t, ys, us]), delimiter=",", header="t,y,u", comments="")
    return str(path)


@pytest.fixture(scope="module")
def found(tmp_path_factory):
    """(identifier, summary) of each record, identified once."""
    d = tmp_path_factory.mktemp("ambiguity")
    recs = {"harmonic": _record(d / "harmonic.csv", dist_Hz=AT_HARMONIC_HZ),
            "off": _record(d / "off.csv", dist_Hz=OFF_HARMONIC_HZ),
            "quantised": _record(d / "quantised.csv", y_noise_m=1e-6, quantum_m=5e-6)}
    return {k: identify_record(load_record(p, None, str(A1))) for k, p in recs.items()}


def test_a_line_at_a_program_harmonic_is_ambiguous_and_names_no_force_of_position(found):
    idf, s = found["harmonic"]
    named = {e["name"] for e in s["effects"]}
    assert not named & set(POSITION_FAMILIES), s["effects"]
    assert "periodic_disturbance" not in named
    amb = [a for a in s["ambiguous"] if a["families"][0] == "periodic_disturbance"]
    assert amb, s["ambiguous"]
    a = amb[0]
    assert a["text"].startswith("ambiguous: periodic disturbance (time) at 11")
    assert a["families"][1] in POSITION_FAMILIES and a["harmonic"] is not None
    assert a["compensated"] is False and a["experiment"] == SPEED_EXPERIMENT
    line = a["fits"][0]["parameters"]
    assert line["frequency_Hz"] == pytest.approx(AT_HARMONIC_HZ, abs=0.02)
    assert line["amplitude_N"] == pytest.approx(DIST_N, rel=0.1)
    # compensated neither: no entry for either family
    comp, _, _ = compensation_from_fit(idf)
    assert not set(comp) & set(a["families"]), comp
    assert "AMBIGUOUS: periodic disturbance (time)" in text_report(s)


def test_the_same_line_off_the_harmonic_is_named(found):
    _, s = found["off"]
    pd = [e for e in s["effects"] if e["name"] == "periodic_disturbance"]
    assert pd, s["effects"]
    assert pd[0]["parameters"]["frequency_Hz"] == pytest.approx(OFF_HARMONIC_HZ, abs=0.02)
    assert pd[0]["parameters"]["amplitude_N"] == pytest.approx(DIST_N, rel=0.1)
    assert not [a for a in s["ambiguous"] if "periodic_disturbance" in a["families"]]


def test_a_coarse_encoder_with_nothing_injected_gets_no_spring(found):
    _, s = found["quantised"]
    assert "spring" not in {e["name"] for e in s["effects"]}, s["effects"]


def test_emps_offset_with_the_publications_sign():
    """EMPS with the reference structure (sign friction, no hold): F_offset as published
    (−3.1648 N, Janot, Gautier & Brunot 2019), the model's force on the carriage its opposite;
    a validation record (here the same file) gets a residual and a relative error."""
    path = emps_path()
    if path is None:
        pytest.skip("EMPS data not available")
    rec = load_record(path, "t=t,y=qm,u=vir,yd=qg", "gtau")
    idf, s = identify_record(rec, friction="sign", zoh_delay=0.0)
    ph = s["nominal"]["physical"]
    assert ph["F_offset_N"] == pytest.approx(-3.1648, rel=0.01)
    assert ph["offset_N"] == pytest.approx(-ph["F_offset_N"])
    assert "F_offset -3.17" in text_report(s)
    v = validation(idf, rec)
    assert 0 < v["relative_error_percent_after"] <= v["relative_error_percent_before"] < 10
