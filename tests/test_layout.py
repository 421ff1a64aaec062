"""The house's rules, read from the source (ast): imports flow one way (docs/architecture.md)."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]

#: package prefix -> prefixes it must never import
FORBIDDEN = {
    "motorctl": ("motorctl_drivers", "motorctl_emulators"),
    "motorctl_drivers": ("motorctl_emulators", "motorctl.app", "motorctl.cli", "motorctl.ident",
                         "motorctl.commission"),
    "motorctl.model": ("motorctl.",),
    "motorctl.schema": ("motorctl.",),
    "motorctl.effects": ("motorctl.control", "motorctl.loop", "motorctl.app", "motorctl.cli",
                         "motorctl.recorder", "motorctl.ident", "motorctl.config"),
    "motorctl.control": ("motorctl.app", "motorctl.cli", "motorctl.recorder", "motorctl.ident",
                         "motorctl.config", "motorctl.loop"),
    "motorctl.loop": ("motorctl.app", "motorctl.cli", "motorctl.recorder", "motorctl.ident",
                      "motorctl.config"),
    "motorctl.recorder": ("motorctl.app", "motorctl.cli", "motorctl.control", "motorctl.ident"),
    "motorctl.app": ("motorctl.cli", "motorctl.commission"),
    "motorctl.commission": ("motorctl.cli",),
    "motorctl.ident": ("motorctl.cli", "motorctl.app", "motorctl.commission"),
    # a pure library: the daemon's I/O side plans with it, the loop never does
    "motorctl.motion": ("motorctl.loop", "motorctl.app", "motorctl.cli", "motorctl.recorder",
                        "motorctl.control", "motorctl.ident", "motorctl.config", "motorctl.commission"),
}
#: the loop runs the laws (motorctl.control: their compiled steps through
#: motorctl.control.kernels, their published signals from motorctl.control.signals); the laws
#: never import the loop. No exceptions to FORBIDDEN.


def _modules():
    for pkg in ("motorctl", "motorctl_drivers", "motorctl_emulators"):
        for path in sorted((REPO / pkg).rglob("*.py")):
            rel = path.relative_to(REPO).with_suffix("")
            parts = list(rel.parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            yield ".".join(parts), path


def _imports(path: Path) -> list[str]:
    out = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            out += [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            out.append(node.module)
    return out


def _matches(name: str, prefix: str) -> bool:
    return name == prefix.rstrip(".") or name.startswith(prefix if prefix.endswith(".") else prefix + ".")


@pytest.mark.parametrize("module,path", list(_modules()), ids=lambda x: str(x))
def test_imports_flow_one_way(module, path):
    bad = []
    for owner, forbidden in FORBIDDEN.items():
        if not _matches(module, owner):
            continue
        for imp in _imports(path):
            for f in forbidden:
                if _matches(imp, f) and not _matches(imp, module):
                    bad.append(f"{module} imports {imp} (rule: {owner} must not import {f})")
    assert not bad, "\n".join(bad)


def test_no_import_circle():
    """No module imports, even inside a function, one that imports it back (graphlib finds a
    circle; ``from pkg import mod`` counts as importing pkg.mod)."""
    import graphlib
    mods = dict(_modules())
    graph = {}
    for module, path in mods.items():
        deps = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                deps |= {a.name for a in node.names}
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                deps |= {f"{node.module}.{a.name}" if f"{node.module}.{a.name}" in mods else node.module
                         for a in node.names}
        graph[module] = {d for d in deps if d in mods and d != module}
    try:
        tuple(graphlib.TopologicalSorter(graph).static_order())
    except graphlib.CycleError as exc:
        pytest.fail(f"import circle: {' -> '.join(exc.args[1])}")


def test_the_loop_is_built_in_one_place():
    """Only motorctl/app/build.py constructs a ServoLoop or a Supervisor in production code."""
    builders = []
    for module, path in _modules():
        for node in ast.walk(ast.parse(path.read_text())):
            if (isinstance(node, ast.Call) and isinstance(node.func, ast.Name)
                    and node.func.id in ("ServoLoop", "Supervisor")):
                builders.append(module)
    assert set(builders) == {"motorctl.app.build"}, builders


def test_the_loop_process_does_not_load_scipy_to_build_its_loop():
    """Importing what builds and runs the loop (the CLI's run path, the daemon's loop side) loads
    none of scipy's subpackages (530 modules of scipy.signal and scipy.stats did before):
    identification, spectra and splines import them where they use them. Building a loop loads
    scipy.linalg only (the estimator's filter discretisation, at build time)."""
    import subprocess
    import sys
    heavy = ("signal", "stats", "interpolate", "optimize", "io", "linalg", "sparse", "fft", "ndimage")
    code = ("import sys, motorctl.app.build, motorctl.app.job, motorctl.app.daemon.loop_side; "
            f"print(sorted(m for m in sys.modules if m.split('.')[:1] == ['scipy'] and "
            f"len(m.split('.')) > 1 and m.split('.')[1] in {heavy!r}))")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True)
    assert r.stdout.strip() == "[]", r.stdout[:300]        # (numba itself imports the bare package)

