"""The effect-family seam: a family is one module and one entry point in the ``motorctl.effects``
group (motorctl.effects.registry), as a law is in ``motorctl.controllers``. A family outside the
package (tests/toy_family.py, registered through a ``*.dist-info/entry_points.txt`` on the path, as an
installed plugin is) is found by the registry after this package's families, which keep their
fixed order, and enters the simulator's and the compensation's YAML schemas; through the CLI it
is simulated (its plant term compiled), identified by ``motorctl identify`` and compensated (its
term compiled) by ``motorctl tune``, with no edit to motorctl."""

from __future__ import annotations

import json
import subprocess
import sys
from importlib.metadata import EntryPoint
from pathlib import Path

import pytest
import yaml

from harness import plugin_env as harness_plugin_env
from motorctl.effects import registry

#: the plugin's processes compile into a numba cache of their own (motorctl.jitcache.numba_folder):
#: they need not wait for the session's compile of the plain install's
pytestmark = pytest.mark.own_jit_cache
PROBE = ("import json; from motorctl.effects import FAMILIES, compensation_model, effects_model; "
         "print(json.dumps({'families': list(FAMILIES), 'sim': list(effects_model().model_fields), "
         "'comp': list(compensation_model().model_fields)}))")


@pytest.fixture(scope="module")
def plugin_env(tmp_path_factory) -> dict:
    """The toy family (tests/toy_family.py, quadratic drag) as the entry point of a package
    ``dragfamily`` outside motorctl."""
    return harness_plugin_env(tmp_path_factory.mktemp("plugin"), "dragfamily", registry.ENTRY_POINT_GROUP,
                              {"quadratic_drag": "toy_family:FAMILY"}, Path(__file__).parent)


def _run(env, *argv, cwd=None, timeout=120):
    return subprocess.run([sys.executable, *argv], env=env, cwd=cwd, capture_output=True, text=True, timeout=timeout)


def test_a_family_from_another_package_is_found_after_the_builtin_ones(plugin_env):
    r = _run(plugin_env, "-c", PROBE)
    assert r.returncode == 0, r.stderr
    got = json.loads(r.stdout)
    assert got["families"] == [*registry.BUILTIN_ORDER, "quadratic_drag"]
    assert got["sim"][-1] == "quadratic_drag" and got["comp"][-1] == "quadratic_drag"
    # without the plugin on the path: this package's families only, same order
    bare = _run({k: v for k, v in plugin_env.items() if k != "PYTHONPATH"}, "-c", PROBE)
    assert json.loads(bare.stdout)["families"] == list(registry.BUILTIN_ORDER)


def test_the_plugin_family_is_a_config_key(plugin_env, repo, tmp_path):
    """``axes.X.driver.effects.quadratic_drag`` is accepted with the plugin installed and named
    as an unknown key without it."""
    raw = yaml.safe_load((repo / "configs" / "gantry.yaml").read_text())
    raw["axes"]["X"]["driver"].setdefault("effects", {})["quadratic_drag"] = {"drag_N_s2_per_m2": 20.0}
    cfg = tmp_path / "drag.yaml"
    cfg.write_text(yaml.safe_dump(raw, sort_keys=False))
    r = _run(plugin_env, "-m", "motorctl", "check-config", str(cfg), cwd=repo)
    assert r.returncode == 0, r.stderr
    r = _run({k: v for k, v in plugin_env.items() if k != "PYTHONPATH"}, "-m", "motorctl", "check-config",
             str(cfg), cwd=repo)
    assert r.returncode == 2 and r.stderr.count("\n") == 1, r.stderr
    assert "axes.X.driver.effects.quadratic_drag" in r.stderr, r.stderr


#: the drag injected into the plant of the CLI tests [N s²/m²]: 20 × 1.3² = 34 N (0.4 V) at the
#: top speed of their moves, which sweep 0 ↔ 1.3 m/s (a_max 4 m/s², so that v|v| is told from
#: the viscous θ2 v and a Stribeck term)
DRAG = 20.0
#: what the plugin process compiled: the plant's and the compensation's tables and numba's cache
COMPILED = """
import json, sys
from numba import config
from motorctl.config import load_config
from motorctl.effects import plant
from motorctl.effects.compensation import COMP_KERNELS, Compensation
loaded = load_config(sys.argv[1])
p = loaded.make_driver().plants[0]
c = Compensation(loaded.axes["X"].controller.compensation)
from pathlib import Path
import motorctl.loop.cycle as cycle
from motorctl.app.warmup import _cache_folders, cache_is_cold
print(json.dumps({"plant": [plant.KERNELS[int(k)].__name__ for k in p._terms[0]], "period_compiled": p.period_compiled,
                  "comp": [COMP_KERNELS[int(c.table[7])][1].__name__], "cache": config.CACHE_DIR or "",
                  "notice_looks_in": [str(f) for f in _cache_folders(Path(cycle.__file__))], "cold": cache_is_cold()}))
"""


@pytest.fixture(scope="module")
def drag_tune(plugin_env, repo, tmp_path_factory) -> tuple[Path, dict]:
    """``motorctl tune`` (4 s runs, virtual clock) of axis X of configs/gantry.yaml with the
    plugin's drag in the plant: (its output directory, its JSON)."""
    out = tmp_path_factory.mktemp("drag")
    raw = yaml.safe_load((repo / "configs" / "gantry.yaml").read_text())
    del raw["axes"]["Y"]
    raw["axes"]["X"]["driver"]["effects"] = {"quadratic_drag": {"drag_N_s2_per_m2": DRAG}}
    raw["axes"]["X"]["trajectory"]["a_max"] = 4.0
    cfg = out / "drag.yaml"
    cfg.write_text(yaml.safe_dump(raw, sort_keys=False))
    r = _run(plugin_env, "-m", "motorctl", "tune", str(cfg), "--axis", "X", "--duration", "4", "--virtual-clock",
             "--out", str(out / "tune"), "--json", cwd=repo, timeout=900)
    assert r.returncode == 0, r.stderr[-3000:]
    return out / "tune", json.loads(r.stdout)


def test_a_family_from_another_package_is_identified_and_compensated_by_the_cli(plugin_env, repo, drag_tune):
    out, tuned = drag_tune
    # motorctl identify on tune's first run log: the drag found, near the injected one
    r = _run(plugin_env, "-m", "motorctl", "identify", str(out / "before.mclog"), "--no-closed-loop", "--json",
             cwd=repo, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    found = {e["name"]: e["parameters"] for e in json.loads(r.stdout)["effects"]}
    assert found["quadratic_drag"]["drag_N_s2_per_m2"] == pytest.approx(DRAG, rel=0.05), found
    # tune compensates it (d̂_eff = F_eff / A1, A1 = 80 N/V) and keeps it: the loop is better with it
    assert tuned["faults"] == {"before": "", "after": "", "floor": ""}, tuned["faults"]
    assert "quadratic_drag" in tuned["kept"] and tuned["dropped"] == {}, tuned
    comp = tuned["compensation"]["quadratic_drag"]["drag_V_s2_per_m2"]
    assert comp == pytest.approx(DRAG / 80.0, rel=0.05)
    assert tuned["e_M_not_worse"] is True
    assert tuned["compare"]["ratio"]["L2_um"] < 0.6, tuned["compare"]


def test_a_family_from_another_package_runs_compiled(plugin_env, repo, drag_tune):
    """The plugin's kernels are rows of the tables built from the registry: the plant runs the
    drag's period compiled, the law its compensation; numba caches that process's kernels
    apart from the plain install's (their compiled dispatch differs)."""
    out, _ = drag_tune
    r = _run(plugin_env, "-c", COMPILED, str(out / "tuned.yaml"), cwd=repo)
    assert r.returncode == 0, r.stderr[-3000:]
    got = json.loads(r.stdout)
    assert got["plant"] == ["drag_force"] and got["period_compiled"] is True, got
    assert got["comp"] == ["drag_add"], got
    assert "motorctl-plugins-" in got["cache"], got
    # the compile notice looks where this process's cycle is cached: warm after tune compiled it
    assert all(f.startswith(got["cache"]) for f in got["notice_looks_in"]), got
    assert got["cold"] is False, got


#: a plugin process that imports numba before motorctl (as a plugin's own module may), then
#: compiles the plant's dispatch over its kernel table (the first kernel compiled re-reads
#: numba's environment: motorctl.jit.load)
FIRST_NUMBA = """
import json, os, sys
import numba                                  # before motorctl.jitcache sets NUMBA_CACHE_DIR
import numpy as np
from motorctl.effects import plant
from motorctl.model import s_f_scalar
plant.force(0.0, 0.1, 0.2, 0.0, s_f_scalar(0.2), np.zeros(0, np.int64), np.zeros((0, 1)), np.zeros(0, np.int64))
plant.mass(1.0, 0.0, np.zeros(0, np.int64), np.zeros((0, 1)), np.zeros(0, np.int64))
root = sys.argv[1]
print(json.dumps(sorted({os.path.relpath(d, root) for d, _, fs in os.walk(root) for f in fs if f.endswith(".nbi")})))
"""


def test_a_plugin_process_caches_every_kernel_apart(plugin_env, repo, tmp_path):
    """Every kernel a plugin process compiles lies in its own cache folder
    (``motorctl-plugins-<key>``), none in the plain install's, where a plain process would
    load a dispatch compiled over the plugin's table (it failed there on the plugin's module,
    and a plugin process that loaded the plain table ran its plant to NaN): also when numba was
    imported before motorctl, whose first compile re-reads numba's environment."""
    cache = tmp_path / "cache"
    # a cache of its own: not the session's (NUMBA_CACHE_DIR, set by the session's own compile,
    # would be taken as the user's choice, and the plugin folder nested in it)
    env = {k: v for k, v in plugin_env.items() if k not in ("NUMBA_CACHE_DIR", "MOTORCTL_CACHE_DIR")}
    r = _run({**env, "XDG_CACHE_HOME": str(cache)}, "-c", FIRST_NUMBA, str(cache), cwd=repo, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    folders = json.loads(r.stdout.strip().splitlines()[-1])
    assert any("effects_" in f for f in folders), folders
    assert all("motorctl-plugins-" in f for f in folders), folders


def _eps(*pairs):
    return lambda group: [EntryPoint(n, v, group) for n, v in pairs]


def _builtin_eps():
    return [(n, f"motorctl.effects.{n}:FAMILY") for n in registry.BUILTIN_ORDER]


def test_stale_metadata_is_named(monkeypatch):
    """Metadata installed before the group existed: the error says to reinstall."""
    monkeypatch.setattr(registry, "entry_points", _eps())
    with pytest.raises(registry.RegistryError, match=r"cogging, force_ripple.*missing.*reinstall"):
        registry.load_families()


def test_an_entry_point_must_load_a_family_of_its_name(monkeypatch):
    monkeypatch.setattr(registry, "entry_points", _eps(*_builtin_eps(), ("drag", "motorctl.effects.spring:FAMILY")))
    with pytest.raises(registry.RegistryError, match="drag = motorctl.effects.spring:FAMILY: not an EffectFamily "
                                                     "named 'drag'"):
        registry.load_families()
    monkeypatch.setattr(registry, "entry_points", _eps(*_builtin_eps(), ("spring", "other.pkg:FAMILY")))
    with pytest.raises(registry.RegistryError, match="'spring' registered twice"):
        registry.load_families()


def test_a_kernel_no_family_declares_is_refused_when_the_axis_is_built():
    """No fall-through: a compiled term whose kernel is not in the tables (its family did not
    declare it in ``kernels``, or is not registered) is refused by name, never run as another
    term nor silently from Python."""
    from motorctl.effects.base import CompTerm, PlantTerm
    from motorctl.effects.compensation import _code
    from motorctl.effects.plant import rows
    from toy_family import FAMILY, drag_add, drag_force
    with pytest.raises(ValueError, match="plant term kernel 'drag_force' is not declared in its effect family's "
                                         "kernels .*; known: force plant_force"):
        rows([PlantTerm.compiled("force", drag_force, [1.0])])
    with pytest.raises(ValueError, match="compensation term kernel 'drag_add' is not declared"):
        _code(CompTerm("add", drag_add, [1.0]))      # (what Compensation builds its table with)
    # a kernel declared under two kinds is refused when the tables are built
    with pytest.raises(registry.RegistryError, match="quadratic_drag.*drag_force declared as 'force' and 'add'"):
        registry.kernel_table([FAMILY, type("Twice", (type(FAMILY),), {"kernels": (("add", drag_force),)})()],
                              ("force", "add"))
