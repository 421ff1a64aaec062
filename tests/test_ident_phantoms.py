"""A name only where it stands on its own (docs/identification.md, "Decision rule"): records of a
rigid axis simulated here in numpy with one effect injected by hand, and the name, "ambiguous" or
"unexplained" identify gives, never a phantom beside the right name.

The axis: M = 12.8 kg, A1 = 80 N/V, viscous 17.6 N·s/m, Coulomb 20 N as the model's S_f(ẋ) (no
stiction: the carriage is not held at rest), offset −4 N, under a PD loop with feedforward and
0.3 V of white noise on the input, 5 kHz, 0.2 m raised-cosine moves of 0.25 s with dwells, a
program period of 1.63 s (no harmonic of it at 50 Hz). u is held over each period (read y_k, then
write u_k). Each record: one seed, 5 s, about a second to simulate and one to identify.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from motorctl.effects.input_delay import is_hold
from motorctl.ident.data import Record
from motorctl.ident.judge import holds_zero
from motorctl.ident.pipeline import summarise
from motorctl.ident.select import Identifier

FS = 5000.0
M, A1, B, FC, F0 = 12.8, 80.0, 17.6, 20.0, -4.0
SUB = 4
CYCLE_S, MOVE_S, STROKE_M = 1.63, 0.25, 0.2
DURATION_S = 5.0


def _reference(n: int):
    """x_r, ẋ_r, ẍ_r (n,): 0 ↔ STROKE_M raised-cosine moves of MOVE_S, dwells, period CYCLE_S."""
    t = np.arange(n) / FS
    tc = np.mod(t, CYCLE_S)
    x, v, a = np.zeros(n), np.zeros(n), np.zeros(n)
    half = CYCLE_S / 2
    for start, sign, base in ((0.0, 1.0, 0.0), (half, -1.0, STROKE_M)):
        m = (tc >= start) & (tc < start + MOVE_S)
        s = (tc[m] - start) / MOVE_S
        x[m] = base + sign * STROKE_M * 0.5 * (1 - np.cos(np.pi * s))
        v[m] = sign * STROKE_M * 0.5 * np.pi / MOVE_S * np.sin(np.pi * s)
        a[m] = sign * STROKE_M * 0.5 * (np.pi / MOVE_S) ** 2 * np.cos(np.pi * s)
    x[(tc >= MOVE_S) & (tc < half)] = STROKE_M
    return x, v, a


def _simulate(seed=1, kf_drift=None, step=None, cogging=None, spring=0.0, vibration=None) -> Record:
    """A record of the axis with: ``kf_drift`` (a, τ): the force constant × 1 − a(1 − e^(−t/τ))
    (a coil warming towards a level); ``step`` (F [N], t [s]): a constant force from t on;
    ``cogging`` (A [N], P [m]): A sin(2πx/P + 0.5); ``spring`` k [N/m]: −k (x − 0.1 m);
    ``vibration`` (A [N], f [Hz]): A sin(2πft + 0.3)."""
    n = int(DURATION_S * FS)
    xr, vr, ar = _reference(n)
    noise = 0.3 * np.random.default_rng(seed).standard_normal(n)
    h = 1.0 / (FS * SUB)
    x = v = 0.0
    ys, us = np.empty(n), np.empty(n)
    for k in range(n):
        t = k / FS
        ys[k] = x
        u = 4000.0 * (xr[k] - x) + 40.0 * (vr[k] - v) + (M * ar[k] + B * vr[k]) / A1 + noise[k]
        u = min(max(u, -10.0), 10.0)
        us[k] = u
        f_m = A1 * u * (1.0 - kf_drift[0] * (1.0 - math.exp(-t / kf_drift[1])) if kf_drift else 1.0)
        if step is not None and t >= step[1]:
            f_m += step[0]
        for j in range(SUB):
            f = f_m - spring * (x - 0.1)
            if cogging:
                f += cogging[0] * math.sin(2 * math.pi * x / cogging[1] + 0.5)
            if vibration:
                f += vibration[0] * math.sin(2 * math.pi * vibration[1] * (t + j * h) + 0.3)
            acc = (f - B * v - FC * (2 / math.pi) * math.atan(900.0 * v) + F0) / M
            x += h * v + 0.5 * h * h * acc
            v += h * acc
    return Record(t=np.arange(n) / FS, y=ys, u=us, gain=A1, source="<numpy axis>", axis="X")


def _identify(**effect) -> dict:
    return summarise(Identifier(_simulate(**effect), zoh_delay=0.5).run())


def _names(s: dict) -> set:
    return {e["name"] for e in s["effects"]}


def test_a_saturating_force_constant_drift_gets_no_phantom_payload_change():
    """−15 % towards a level with τ = 3 s: the linear drift is named; a mass step at the drift's
    knee (0.41 kg at 1.7 s) is a smooth change of θ1's column, which explains as much."""
    s = _identify(kf_drift=(0.15, 3.0))
    assert _names(s) == {"force_constant_drift"}, s["effects"]
    assert s["effects"][0]["parameters"]["drift_per_s"] < 0


def test_a_force_step_gets_no_phantom_stiction():
    """+12 N from t = 2.4 s on a plant without stiction: a force step explains more than the
    stiction the held input suggested; nothing is named and the verdict warns."""
    s = _identify(step=(12.0, 2.4))
    assert _names(s) == set(), s["effects"]
    assert s["residual"]["structured"], s["residual"]["text"]


@pytest.mark.parametrize("effect, name", [({"cogging": (8.0, 0.024)}, "cogging"),
                                          ({"spring": 100.0}, "spring")])
def test_clean_friction_with_one_effect_gets_that_name_alone(effect, name):
    s = _identify(**effect)
    assert _names(s) == {name}, s["effects"]


def test_a_50hz_vibration_is_named_a_periodic_disturbance_near_50hz():
    """6 N at 50 Hz, about the PD loop's crossover (the input carries 0.44 and the carriage's
    inertia 0.47 of the line: a force from outside, not the loop's own oscillation): the search
    starts at the residual's strongest line."""
    s = _identify(vibration=(6.0, 50.0))
    assert _names(s) == {"periodic_disturbance"}, s["effects"]
    p = s["effects"][0]["parameters"]
    assert abs(p["frequency_Hz"] - 50.0) < 0.5 and abs(p["amplitude_N"] - 6.0) < 0.6, p


def test_an_interval_that_holds_zero_carries_no_name():
    """EMPS's asymmetric friction as it was named: 13.47 N with [−14.2, 41.1]."""
    assert holds_zero("asymmetric_friction", {"coulomb_N": [-14.2, 41.1], "viscous_N_s_per_m": [None, None]})
    assert holds_zero("asymmetric_friction", {"coulomb_N": [2.0, 41.1], "viscous_N_s_per_m": [-5.0, 3.0]}) is None
    assert holds_zero("cogging", {"amplitudes_N": [[-1.0, 2.0], [-0.5, 0.4]], "period_m": [0.03, 0.04]})
    assert holds_zero("cogging", {"amplitudes_N": [[1.0, 2.0], [-0.5, 0.4]]}) is None
    assert holds_zero("stiction", {"velocity_band_m_per_s": [-1.0, 1.0]}) is None    # declares no size


def test_the_hold_tolerance_is_inclusive_on_both_sides():
    """0.65 − 0.5 is 0.15000000000000002 in binary floats: the edge is the hold on both sides."""
    assert is_hold(0.65) and is_hold(0.35) and is_hold(0.5 + 0.15000000000000002)
    assert is_hold(float(np.arange(0.0, 1.5 + 1e-9, 0.05)[13]))         # the hold grid's 0.65
    assert not is_hold(0.651) and not is_hold(0.349)
