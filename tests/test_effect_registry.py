"""The effect-family registry is the one place a family is declared (docs/architecture.md).

The simulator's ``effects`` schema and plant, ``motorctl identify``'s candidates, searches and
checks, the controller's ``compensation`` schema and term, and the report all find a family
through :data:`motorctl.effects.FAMILIES`: a toy family registered here is simulated,
identified, compensated and drawn with no other edit. The compensation of every compensable
family cancels its plant force (signs), and no consumer module names a family.

This module's top level imports only the registry (not the simulator, the identification or
the config), so a fresh interpreter can load it, register the toy and then import those.
"""

from __future__ import annotations

import ast
import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from motorctl.effects import (
    FAMILIES,
    compensable,
    compensation_model,
    effects_model,
    family,
    simulated,
)
from motorctl.effects.base import EffectFamily, Signals
from motorctl.model import s_f_scalar
from toy_family import QuadraticDrag

ROOT = Path(__file__).resolve().parents[1]
TS = 2e-4
A1 = 80.0
ORDER = ("cogging", "force_ripple", "stribeck", "asymmetric_friction", "position_dependent_friction",
         "spring", "payload_change", "input_delay", "periodic_disturbance", "position_friction_shape",
         "stiction", "amplifier_dead_zone", "force_constant_drift", "periodic_friction",
         "encoder_interpolation", "structural_mode")
#: (x [m], ẋ [m/s], t [s]) where terms are compared: both directions, slow and fast, ẋ = 0
POINTS = [(x, v, t) for x in (-0.05, 0.013, 0.2, 0.37) for v in (-0.8, -0.01, 0.0, 0.004, 0.05, 0.8)
          for t in (0.0, 0.41, 2.3)]


@pytest.fixture
def toy(monkeypatch):
    fam = QuadraticDrag()
    monkeypatch.setitem(FAMILIES, fam.name, fam)
    return fam


# ---------------------------------------------------------------------------- helpers
def _driver_fragment(fam) -> dict:
    """The family's example as keys of ``axes.NAME.driver`` (an effects entry or an axis key)."""
    return {"effects": dict(fam.example)} if fam.sim_options is not None else dict(fam.example)


def _sim_options(fam):
    """The family's example options, as the simulator's schema reads them."""
    return fam.sim_options.model_validate(fam.example[fam.name])


def _plant_force(fam, sim_opts, x, v, t):
    """F_eff [N] of the family's plant term at (x, ẋ, t)."""
    term = fam.plant_term(sim_opts, TS)
    return term.force(0.0, x, v, t, s_f_scalar(v))


def _record(n=3000):
    from motorctl.ident.data import Record
    t = np.arange(n) * 1e-3
    return Record(t=t, y=0.05 * np.sin(2 * np.pi * 0.5 * t),
                  u=np.cos(2 * np.pi * 0.5 * t) + 0.1 * np.sin(2 * np.pi * 7 * t))


# ---------------------------------------------------------------------------- the registry
def test_registry_order_names_and_lookup():
    assert tuple(FAMILIES) == ORDER            # candidate and plant-force order: fixed
    for name, fam in FAMILIES.items():
        assert isinstance(fam, EffectFamily) and fam.name == name
        mod = __import__(f"motorctl.effects.{name}", fromlist=["FAMILY"])
        assert mod.FAMILY is fam               # one module per family
    assert family("spring") is FAMILIES["spring"]
    with pytest.raises(ValueError, match="unknown effect family 'nope'; families: cogging, force_ripple"):
        family("nope")
    assert [f.name for f in compensable()] == ["cogging", "spring", "periodic_disturbance", "stribeck",
                                               "asymmetric_friction", "position_dependent_friction",
                                               "position_friction_shape", "periodic_friction"]
    assert {f.name for f in simulated()} == set(ORDER) - {"input_delay", "stiction", "encoder_interpolation",
                                                                    "structural_mode"}


@pytest.mark.parametrize("name", ORDER)
def test_every_family_is_in_the_sim_schema_and_changes_the_plant(name):
    from motorctl_drivers.sim import AxisPlant, Effects, SimAxisOptions
    fam = FAMILIES[name]
    if fam.sim_options is not None:
        assert Effects.model_fields[name].annotation == (fam.sim_options | None)
    base = {"mass_kg": 12.8, "a1_N_per_V": A1, "viscous_N_s_per_m": 30.0, "coulomb_N": 10.0}
    opt = SimAxisOptions.model_validate({**base, **_driver_fragment(fam)})
    assert fam.sim_config(opt) is not None and fam.sim_config(SimAxisOptions.model_validate(base)) is None
    plants = [AxisPlant(o, TS, np.random.default_rng(0), 4) for o in (opt, SimAxisOptions.model_validate(base))]
    if getattr(fam, "measurement", False):
        # an error of the reading: the carriage moves as without it, the measured position differs
        assert fam.plant_term(fam.sim_config(opt), TS) is None
        for p in plants:
            for _ in range(300):
                p.step(2.0)
        assert plants[0].x == plants[1].x
        assert abs(plants[0].measured() - plants[1].measured()) > 4e-7      # a count of 0.5 um or more
        return
    # stiction (25 N) holds a carriage pushed with 16 N; every other effect shows at 160 N
    u0 = 0.2 if name == "stiction" else 2.0
    for p in plants:
        p.t = 4.6                      # just before the example payload change (4.65 s)
        for k in range(1000):
            p.step(u0 + 0.05 * u0 * math.sin(0.01 * k))
    assert abs(plants[0].x - plants[1].x) > 1e-7, name
    # a thrust, force or mass hook makes the plant leave the compiled plain integrator (an input
    # transform and the plant core's stiction need none)
    term = fam.plant_term(fam.sim_config(opt), TS)
    assert plants[0]._plain is False or term is None or (term.thrust, term.force, term.mass) == (None, None, None)


def test_effects_schema_has_exactly_the_simulated_families():
    from motorctl_drivers.sim import Effects
    assert list(Effects.model_fields) == [f.name for f in simulated()]


def test_identifier_candidates_are_the_registry():
    from motorctl.ident.select import Identifier
    assert Identifier(_record()).families == list(ORDER)
    with pytest.raises(ValueError, match="unknown effect family 'nope'"):
        Identifier(_record(), families=["nope"])


def test_compensation_schema_has_exactly_the_compensable_families():
    from motorctl.effects.compensation import CompensationConfig
    assert list(CompensationConfig.model_fields) == [f.name for f in compensable()]
    for f in compensable():
        assert CompensationConfig.model_fields[f.name].annotation == (f.comp_options | None)
    assert CompensationConfig().is_empty()


# ---------------------------------------------------------------------------- signs
#: hand-written matching parameters: plant (N, sim YAML) and compensation (V = N / A1, controller YAML)
MATCHING = {
    "cogging": ({"amplitudes_N": [12.0, 4.0], "period_m": 0.032, "phases_rad": [0.3, 1.0]},
                {"period_m": 0.032, "sin_V": [12.0 * math.cos(0.3) / A1, 4.0 * math.cos(1.0) / A1],
                 "cos_V": [12.0 * math.sin(0.3) / A1, 4.0 * math.sin(1.0) / A1]}),
    "spring": ({"stiffness_N_per_m": 100.0, "rest_position_m": 0.1},
               {"stiffness_V_per_m": 1.25, "rest_position_m": 0.1}),
    "periodic_disturbance": ({"amplitude_N": 6.0, "frequency_Hz": 7.3, "phase_rad": 0.4},
                             {"frequency_Hz": 7.3, "sin_V": [6.0 * math.cos(0.4) / A1],
                              "cos_V": [6.0 * math.sin(0.4) / A1]}),
    "stribeck": ({"force_N": 20.0, "velocity_m_per_s": 0.05}, {"force_V": 0.25, "velocity_m_per_s": 0.05}),
    "asymmetric_friction": ({"coulomb_N": 10.0, "viscous_N_s_per_m": 20.0},
                            {"coulomb_V": 0.125, "viscous_V_s_per_m": 0.25}),
    "position_dependent_friction": ({"coulomb_slope_N_per_m": 40.0, "reference_m": 0.2},
                                    {"coulomb_slope_V_per_m": 0.5, "reference_m": 0.2}),
    "position_friction_shape": ({"bumps": [{"center_m": 0.2, "width_m": 0.3, "amplitude_N": 8.0}]},
                                {"bumps": [{"center_m": 0.2, "width_m": 0.3, "amplitude_V": 0.1}]}),
    "periodic_friction": ({"amplitudes_N": [8.0], "period_m": 0.05, "phases_rad": [0.5]},
                          {"period_m": 0.05, "sin_V": [-8.0 * math.cos(0.5) / A1], "cos_V": [-8.0 * math.sin(0.5) / A1]}),
}


def test_every_compensable_family_has_a_sign_case():
    assert set(MATCHING) == {f.name for f in compensable()}


@pytest.mark.parametrize("name", list(MATCHING))
def test_compensation_input_is_minus_plant_force_over_a1(name):
    """d̂_eff = F_eff / A1 is subtracted in v_a1 (eq. 13): the input gains −F_eff / A1."""
    from motorctl.effects.compensation import Compensation, CompensationConfig
    fam = FAMILIES[name]
    sim, comp = MATCHING[name]
    sim_opts = fam.sim_options.model_validate(sim)
    c = Compensation(CompensationConfig.model_validate({name: comp}))
    forces = []
    for x, v, t in POINTS:
        f = _plant_force(fam, sim_opts, x, v, t)
        forces.append(f)
        u_added = -c.value(x, v, t)                   # what the compensation adds to the input [V]
        assert u_added == pytest.approx(-f / A1, rel=1e-9, abs=1e-12), (x, v, t)
    assert max(abs(f) for f in forces) > 1.0          # the effect is there at these points
    # the family's own conversion (compensation_for) cancels the force too
    mine = fam.comp_options.model_validate(fam.compensation_for(sim_opts, A1))
    add = fam.compensator(mine)
    for x, v, t in POINTS:
        assert add(0.0, x, v, t, s_f_scalar(v)) == pytest.approx(_plant_force(fam, sim_opts, x, v, t) / A1,
                                                                 rel=1e-9, abs=1e-12)


@pytest.mark.parametrize("name", [f.name for f in compensable()])
def test_compensation_from_a_fit_is_minus_the_fitted_columns(name):
    """identify fits u = Φθ + Cβ (F_eff = −A1 Cβ); its compensation entry must give d̂_eff = −Cβ."""
    from motorctl.effects.compensation import Compensation, CompensationConfig
    from motorctl.ident.effects import compensation
    fam = FAMILIES[name]
    from motorctl.effects.position_friction_shape import knot_grid
    h = {"cogging": 0.032, "stribeck": 0.05, "periodic_disturbance": 7.3, "periodic_friction": 0.05,
         "position_friction_shape": knot_grid(-0.05, 0.4, 4)}.get(name)
    x, v, t = (np.array(a, dtype=float) for a in zip(*POINTS))
    cols = fam.columns(h, Signals(x, v, np.zeros_like(x), np.zeros_like(x), t))
    beta = np.random.default_rng(3).uniform(0.05, 0.3, cols.shape[1])
    c = Compensation(CompensationConfig.model_validate(compensation(name, h, beta)))
    got = np.array([c.value(*pt) for pt in POINTS])
    assert np.allclose(got, -(cols @ beta), rtol=1e-9, atol=1e-12)
    assert np.max(np.abs(got)) > 1e-3


def test_composed_compensation_is_the_sum_of_the_terms():
    from motorctl.effects.compensation import Compensation, CompensationConfig
    both = Compensation(CompensationConfig.model_validate({n: comp for n, (_, comp) in MATCHING.items()}))
    parts = [Compensation(CompensationConfig.model_validate({n: comp})) for n, (_, comp) in MATCHING.items()]
    for pt in POINTS:
        assert both.value(*pt) == pytest.approx(sum(p.value(*pt) for p in parts), rel=1e-12, abs=1e-12)


# ---------------------------------------------------------------------------- a toy family, no other edit
def test_toy_family_is_simulated(toy):
    from motorctl_drivers.sim import AxisPlant, SimAxisOptions
    effects = effects_model()(quadratic_drag={"drag_N_s2_per_m2": 50.0})   # the schema the sim builds
    opt = SimAxisOptions(mass_kg=10.0, a1_N_per_V=A1).model_copy(update={"effects": effects})
    p = AxisPlant(opt, TS, np.random.default_rng(0), 4)
    p.xd = 1.0
    for _ in range(500):
        p.step(0.0)
    # m v' = −c v²  →  v(t) = v0 / (1 + c v0 t / m)
    assert p.xd == pytest.approx(1.0 / (1.0 + 50.0 * 500 * TS / 10.0), rel=1e-9)


def test_toy_family_is_identified_and_drawn(toy):
    """Open-loop data of a plant with the toy's drag: identify names it, with its parameter."""
    from motorctl.ident.data import Record
    from motorctl.ident.effects import parameters
    from motorctl.ident.report import effect_shape
    from motorctl.ident.select import Identifier
    from motorctl_drivers.sim import AxisPlant, SimAxisOptions
    assert Identifier(_record()).families == list(ORDER) + ["quadratic_drag"]
    opt = SimAxisOptions(mass_kg=12.8, a1_N_per_V=A1, viscous_N_s_per_m=30.0, coulomb_N=10.0,
                         force_noise_N=0.5)
    opt = opt.model_copy(update={"effects": effects_model()(quadratic_drag={"drag_N_s2_per_m2": 20.0})})
    p = AxisPlant(opt, TS, np.random.default_rng(1), 4)
    t = np.arange(30000) * TS
    u = 0.5 * np.sin(2 * np.pi * 0.7 * t) + 0.3 * np.sin(2 * np.pi * 2.3 * t + 1.0)
    y = np.empty_like(t)
    for k in range(len(t)):
        y[k] = p.measured()
        p.step(float(u[k]))
    idf = Identifier(Record(t=t, y=y, u=u, gain=A1), zoh_delay=0.5,
                     families=["quadratic_drag", "spring", "stribeck", "asymmetric_friction"]).run()
    assert [tm.family for tm in idf.terms] == ["quadratic_drag"], [c.reasons for c in idf.steps[0]]
    (beta,) = idf.coef_split(idf.final, idf.terms)[1]
    found = parameters("quadratic_drag", None, beta, A1, 5000.0)
    assert found["drag_N_s2_per_m2"] == pytest.approx(20.0, rel=0.05)
    xv, yv, xl, _ = effect_shape(idf, idf.terms[0], beta)
    assert xl == "velocity [m/s]" and np.allclose(yv, -found["drag_N_s2_per_m2"] * xv * np.abs(xv))


def test_toy_family_is_compensated(toy):
    from motorctl.effects.compensation import Compensation
    from motorctl.ident.effects import compensation
    assert compensable()[-1] is toy                    # default rank: after the others
    cfg = compensation_model()(**compensation("quadratic_drag", None, np.array([0.25])))
    assert not cfg.is_empty()
    c = Compensation(cfg)
    assert c.value(0.1, 0.5, 0.0) == pytest.approx(-0.25 * 0.25, rel=1e-15)
    assert c.value(0.1, -0.5, 0.0) == pytest.approx(0.25 * 0.25, rel=1e-15)


_E2E = r"""
import importlib.util, json, os, sys
sys.path.insert(0, os.path.dirname(sys.argv[1]))   # tests/: the toy family's module
spec = importlib.util.spec_from_file_location("registry_test", sys.argv[1])
mod = importlib.util.module_from_spec(spec); spec.loader.exec_module(mod)
from motorctl.effects import FAMILIES
if sys.argv[2] == "register":
    FAMILIES["quadratic_drag"] = mod.QuadraticDrag()     # the one registry entry
from motorctl.app.job import run_job
from motorctl.config import ConfigError, config_from_dict
from motorctl.ident.synth import gantry_dict
EFFECT = {"quadratic_drag": {"drag_N_s2_per_m2": 20.0}}
COMP = {"quadratic_drag": {"drag_V_s2_per_m2": 0.25}}
def yaml_dict(effects, compensation):   # as a user writes it: axes.X.driver.effects, controller.compensation
    d = gantry_dict("X", None, seed=1, compensation=compensation)
    if effects:
        d["axes"]["X"]["driver"]["effects"] = effects
    return d
out = {"errors": {}}
for key, eff, comp in (("driver", EFFECT, None), ("compensation", None, COMP)):
    try:
        config_from_dict(yaml_dict(eff, comp), key)
    except ConfigError as exc:
        out["errors"][key] = str(exc)
if not out["errors"]:
    loaded = config_from_dict(yaml_dict(EFFECT, COMP), "toy")
    drv = loaded.make_driver(["X"])
    out["described"] = drv.describe()["simulated"]["X"]["effects"]
    out["forces"] = len(drv.plants[0]._forces)
    out["compensation"] = loaded.axes["X"].controller.compensation.model_dump(exclude_none=True)
    res = run_job(loaded, duration_s=0.3, clock="virtual").axes["X"]
    out["fault"] = res["fault"]
print(json.dumps(out))
"""


@pytest.mark.parametrize("mode", ["register", "none"])
def test_registered_family_reaches_the_yaml_schemas_end_to_end(mode):
    """A fresh interpreter where the toy is one registry entry: the config accepts it under
    ``driver.effects`` and ``controller.compensation``, the plant applies it and a run passes;
    without the entry the same YAML is refused."""
    r = subprocess.run([sys.executable, "-c", _E2E, __file__, mode], capture_output=True, text=True,
                       cwd=str(ROOT), timeout=300, check=False)
    assert r.returncode == 0, r.stderr[-3000:]
    out = json.loads(r.stdout.strip().splitlines()[-1])
    if mode == "register":
        assert out["errors"] == {}
        assert out["described"] == {"quadratic_drag": {"drag_N_s2_per_m2": 20.0}}
        assert out["forces"] == 1
        assert out["compensation"] == {"quadratic_drag": {"drag_V_s2_per_m2": 0.25}}
        assert out["fault"] == ""
    else:
        err = out["errors"]
        assert "axes.X.driver.effects.quadratic_drag: unknown key" in err["driver"], err
        assert "axes.X.controller.compensation.quadratic_drag: unknown key" in err["compensation"], err


# ---------------------------------------------------------------------------- the one place
CONSUMERS = ["motorctl_drivers/sim.py", "motorctl/effects/compensation.py", "motorctl/ident/select.py",
             "motorctl/ident/report.py", "motorctl/ident/simfit.py", "motorctl/ident/synth.py",
             "motorctl/ident/idim.py", "motorctl/ident/data.py", "motorctl/ident/effects.py",
             "motorctl/cli/identify.py"]


@pytest.mark.parametrize("path", CONSUMERS)
def test_no_consumer_names_a_family(path):
    """No ``if family == "cogging"`` chains: a family name appears as a string only in its module
    and the registry (docstrings, being longer strings, do not count)."""
    tree = ast.parse((ROOT / path).read_text())
    named = sorted({n.value for n in ast.walk(tree)
                    if isinstance(n, ast.Constant) and isinstance(n.value, str) and n.value in FAMILIES})
    assert named == [], f"{path} names effect families {named}: look them up in motorctl.effects.FAMILIES"


def test_effect_modules_import_no_consumer():
    """Imports flow one way: motorctl.effects never imports the simulator, ident, app or cli."""
    banned = ("motorctl_drivers", "motorctl.ident", "motorctl.app", "motorctl.cli", "motorctl.config",
              "motorctl.control")
    for path in sorted((ROOT / "motorctl" / "effects").glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            mods = ([a.name for a in node.names] if isinstance(node, ast.Import)
                    else [node.module or ""] if isinstance(node, ast.ImportFrom) else [])
            for m in mods:
                assert not m.startswith(banned), f"{path.name} imports {m}"


# ---------------------------------------------------------------------------- code -> kernel tables
def test_plant_and_compensation_codes_are_checked_against_their_tables():
    """One table each from a code to its compiled kernel: a code outside it, or one of another
    hook / kind, is refused with the known codes named; the compiled dispatch gives NaN for it
    (the axis faults), never another family's term."""
    from motorctl.effects import compensation, plant

    for code, (hook, kernel) in enumerate(plant.PLANT_KERNELS):
        assert plant.check_plant_code(code, hook) == code
        assert plant.KERNELS[code] is kernel
    for code, (kind, kernel) in enumerate(compensation.COMP_KERNELS):
        assert compensation.check_comp_code(code, kind) == code
    n = len(plant.PLANT_KERNELS)
    with pytest.raises(ValueError, match=f"plant term code {n} is not a compiled 'force' kernel; known: 0 "):
        plant.check_plant_code(n, "force")
    thrust_code = [h for h, _ in plant.PLANT_KERNELS].index("thrust")
    with pytest.raises(ValueError, match="not a compiled 'force' kernel"):
        plant.check_plant_code(thrust_code, "force")
    with pytest.raises(ValueError, match="compensation term code -1 is not a compiled 'add' kernel"):
        compensation.check_comp_code(-1, "add")
    fill_code = [k for k, _ in compensation.COMP_KERNELS].index("fill")
    with pytest.raises(ValueError, match="not a compiled 'add' kernel"):
        compensation.check_comp_code(fill_code, "add")

    codes, lengths, table = np.array([n], dtype=np.int64), np.array([1], dtype=np.int64), np.zeros((1, 1))
    assert math.isnan(plant.force(1.0, 0.0, 0.0, 0.0, 0.0, codes, table, lengths))
    assert math.isnan(plant.thrust(1.0, 0.0, 0.0, codes, table, lengths))
    # a known code of another hook leaves the value as it is
    codes[0] = thrust_code
    assert plant.force(1.0, 0.0, 0.0, 0.0, 0.0, codes, table, lengths) == 1.0
    tab = np.zeros(compensation.T_HEAD + 4)
    tab[compensation.T_N_ADD] = 1.0
    tab[compensation.T_HEAD:compensation.T_HEAD + 2] = (len(compensation.COMP_KERNELS), 1.0)
    assert math.isnan(compensation.comp_value(tab, 0.0, 0.0, 0.0))
