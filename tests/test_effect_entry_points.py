"""The effect-family seam: a family is one module and one entry point in the ``motorctl.effects``
group (motorctl.effects.registry), as a law is in ``motorctl.controllers``. A family outside the
package (tests/toy_family.py, registered through a ``*.dist-info/entry_points.txt`` on the path, as an
installed plugin is) is found by the registry after this package's families, which keep their
fixed order, and enters the simulator's and the compensation's YAML schemas."""

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

PROBE = ("import json; from motorctl.effects import FAMILIES, compensation_model, effects_model; "
         "print(json.dumps({'families': list(FAMILIES), 'sim': list(effects_model().model_fields), "
         "'comp': list(compensation_model().model_fields)}))")


@pytest.fixture(scope="module")
def plugin_env(tmp_path_factory) -> dict:
    """The toy family (tests/toy_family.py, quadratic drag) as the entry point of a package
    ``dragfamily`` outside motorctl."""
    return harness_plugin_env(tmp_path_factory.mktemp("plugin"), "dragfamily", registry.ENTRY_POINT_GROUP,
                              {"quadratic_drag": "toy_family:FAMILY"}, Path(__file__).parent)


def _run(env, *argv, cwd=None):
    return subprocess.run([sys.executable, *argv], env=env, cwd=cwd, capture_output=True, text=True, timeout=120)


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
