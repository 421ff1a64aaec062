"""The simulated plant with effects runs compiled (motorctl.effects.plant, sim._hooked_step) and
gives the trajectory of the Python path fed with the effects' formulas written out in Python."""

from __future__ import annotations

import math

import numpy as np
import pytest

from motorctl.effects import FAMILIES, PlantTerm, plant
from motorctl_drivers.sim import AxisPlant, SimAxisOptions

TS = 2e-4
BASE = {"mass_kg": 12.8, "a1_N_per_V": 80.0, "viscous_N_s_per_m": 30.0, "coulomb_N": 10.0,
        "force_noise_N": 0.5}
FLEX = {"mode_hz": 80.0, "current_loop_hz": 800.0, "current_loop_delay_s": 3.3e-4}


def _reference_hooks(effects: dict) -> tuple[tuple, tuple, tuple]:
    """(thrust, force, mass) hooks of ``effects`` as plain Python formulas (module docstrings)."""
    thrust, force, mass = [], [], []
    if "cogging" in effects:
        o = effects["cogging"]
        harm = [(a, 2 * math.pi * (k + 1) / o["period_m"], o["phases_rad"][k])
                for k, a in enumerate(o["amplitudes_N"])]
        ts, sc = o.get("step_at_s", math.inf), o.get("scale_after", 1.0)
        force.append(lambda f, x, v, t, sf: f + sum((sc if t >= ts else 1.0) * a * math.sin(w * x + ph)
                                                    for a, w, ph in harm))
    if "force_ripple" in effects:
        o = effects["force_ripple"]
        harm = [(r, 2 * math.pi * (k + 1) / o["period_m"], o["phases_rad"][k]) for k, r in enumerate(o["fractions"])]
        thrust.append(lambda fm, x, t: fm * (1.0 + sum(r * math.sin(w * x + ph) for r, w, ph in harm)))
    if "stribeck" in effects:
        fs, vs = effects["stribeck"]["force_N"], effects["stribeck"]["velocity_m_per_s"]
        force.append(lambda f, x, v, t, sf: f - fs * math.exp(-(v / vs) ** 2) * sf)
    if "spring" in effects:
        k, x0 = effects["spring"]["stiffness_N_per_m"], effects["spring"]["rest_position_m"]
        force.append(lambda f, x, v, t, sf: f - k * (x - x0))
    if "payload_change" in effects:
        tc, dm = effects["payload_change"]["t_change_s"], effects["payload_change"]["mass_kg"]
        mass.append(lambda m, t: m + dm if t >= tc else m)
    return tuple(thrust), tuple(force), tuple(mass)


CASES = {
    "cogging-step": ({"cogging": {"amplitudes_N": [12.0, 4.0], "period_m": 0.032, "phases_rad": [0.3, 1.0],
                                  "step_at_s": 0.5, "scale_after": 1.5}}, {}),
    "ripple-stribeck-payload": ({"force_ripple": {"fractions": [0.06], "period_m": 0.045, "phases_rad": [0.5]},
                                 "stribeck": {"force_N": 8.0, "velocity_m_per_s": 0.01},
                                 "payload_change": {"t_change_s": 0.6, "mass_kg": 3.0}}, {}),
    "spring-cogging-flex": ({"cogging": {"amplitudes_N": [12.0], "period_m": 0.032, "phases_rad": [0.3]},
                             "spring": {"stiffness_N_per_m": 500.0, "rest_position_m": 0.01}}, FLEX),
    # Karnopp with the effects: their forces join the applied force, their friction the breakaway
    "stiction-with-effects": ({"cogging": {"amplitudes_N": [6.0], "period_m": 0.032, "phases_rad": [0.3]},
                               "stribeck": {"force_N": 8.0, "velocity_m_per_s": 0.01},
                               "spring": {"stiffness_N_per_m": 500.0, "rest_position_m": 0.01}},
                              {"stiction_N": 14.0, "stiction_with_effects": True, "force_noise_N": 0.0}),
}


@pytest.mark.parametrize("case", list(CASES))
def test_the_compiled_hooked_plant_follows_the_python_formulas(case):
    effects, extra = CASES[case]
    opt = SimAxisOptions.model_validate({**BASE, "effects": effects, **extra})
    fast = AxisPlant(opt, TS, np.random.default_rng(5), 4)
    ref = AxisPlant(opt, TS, np.random.default_rng(5), 4)
    assert fast._terms is not None                    # the whole period is compiled
    ref._terms = None                                 # the Python path, with the formulas above
    ref._thrust, ref._forces, ref._masses = _reference_hooks(effects)
    assert len(ref._forces) + len(ref._thrust) + len(ref._masses) == len(fast._terms[0])
    held = 0
    for k in range(6000):                             # 1.2 s: across the steps at 0.5 and 0.6 s
        u = 1.5 * math.sin(2 * math.pi * 0.7 * k * TS) + 0.3 * math.sin(0.05 * k)
        fast.step(u)
        ref.step(u)
        assert fast.x == pytest.approx(ref.x, rel=0.0, abs=1e-12), k
        assert fast.xd == pytest.approx(ref.xd, rel=0.0, abs=1e-12), k
        held += fast.xd == 0.0
    assert fast.t == ref.t and abs(fast.x) > 1e-3     # it moved
    assert held > 0 or "stiction_N" not in extra      # ... and stuck, where stiction is on


def test_every_simulated_family_with_a_plant_force_is_compiled():
    """A registered family's thrust, force or mass term has a kernel the compiled plant knows;
    its Python hook is the same kernel with its row bound."""
    for name, fam in FAMILIES.items():
        opt = SimAxisOptions.model_validate({**BASE, **({"effects": dict(fam.example)} if fam.sim_options
                                                         else dict(fam.example))})
        term = fam.plant_term(fam.sim_config(opt), TS)
        if term is None or (term.thrust, term.force, term.mass) == (None, None, None):
            continue
        assert term.kernel in plant.KERNELS, name
        codes, table, lengths = plant.rows([term])
        if term.force is not None:
            for x, v, t in ((0.013, 0.05, 0.2), (0.3, -0.01, 5.0), (0.1, 0.0, 0.0)):
                sf = 0.7 * math.copysign(1.0, v)
                assert plant.force(1.0, x, v, t, sf, codes, table, lengths) == term.force(1.0, x, v, t, sf)
        if term.thrust is not None:
            assert plant.thrust(50.0, 0.1, 3.0, codes, table, lengths) == term.thrust(50.0, 0.1, 3.0)
        if term.mass is not None:
            assert plant.mass(12.8, 5.0, codes, table, lengths) == term.mass(12.8, 5.0)


def test_a_python_only_term_takes_the_python_path():
    assert plant.rows([PlantTerm(force=lambda f, x, v, t, sf: f - v)]) is None
    with pytest.raises(ValueError, match="hook 'nope'"):
        PlantTerm.compiled("nope", plant.KERNELS[0], [1.0])
