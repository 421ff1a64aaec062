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
                         "motorctl.config", "motorctl.loop.servo", "motorctl.loop.safety"),
    "motorctl.loop": ("motorctl.app", "motorctl.cli", "motorctl.recorder", "motorctl.ident",
                      "motorctl.config", "motorctl.control"),
    "motorctl.recorder": ("motorctl.app", "motorctl.cli", "motorctl.control", "motorctl.ident"),
    "motorctl.app": ("motorctl.cli", "motorctl.commission"),
    "motorctl.commission": ("motorctl.cli",),
    "motorctl.ident": ("motorctl.cli", "motorctl.app", "motorctl.commission"),
}
#: the exceptions to FORBIDDEN, each with its reason: the compiled servo cycle calls the built-in
#: laws' compiled steps (motorctl.control.kernels; any other law still runs through the
#: Controller interface, from Python)
ALLOWED = {
    "motorctl.loop": ("motorctl.control.kernels",),
}


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
                if (_matches(imp, f) and not _matches(imp, module)
                        and not any(_matches(imp, a) for a in ALLOWED.get(owner, ()))):
                    bad.append(f"{module} imports {imp} (rule: {owner} must not import {f})")
    assert not bad, "\n".join(bad)


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

