"""What ships: the production drivers carry no emulator or test code, and the emulated devices are
found through their own entry-point group (docs/architecture.md).

The wheel is built from a copy of the sources (``pip wheel --no-deps``; pip builds in the source
tree, so building the working tree itself would leave build/ and egg-info behind in it)."""

from __future__ import annotations

import ast
import configparser
import shutil
import subprocess
import sys
import zipfile
from importlib.metadata import entry_points
from pathlib import Path

import pytest

from motorctl_emulators.device import ENTRY_POINT_GROUP, Device, load_device_class

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ("motorctl", "motorctl_drivers", "motorctl_emulators")
#: device-side names that must not appear in motorctl_drivers (besides any class named *Device)
EMULATOR_NAMES = {"PlantBank", "StreamEndpoint", "FaultSpec", "EmulatorOptions", "serve_forever"}
TRANSPORTS = {"can", "serial", "modbus", "canopen", "ethercat"}


def imports_of(tree: ast.AST, module: str) -> set[str]:
    """Every module ``tree`` (the source of ``module``, dotted) imports, anywhere in it (function
    bodies included), relative imports resolved; ``from P import name`` also counts as ``P.name``."""
    package = module.rpartition(".")[0]
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[:len(package.split(".")) - node.level + 1]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            out.add(mod)
            out.update(f"{mod}.{a.name}" for a in node.names)
    return out


def defined_names(tree: ast.Module) -> set[str]:
    """Classes and functions defined anywhere in ``tree``."""
    return {n.name for n in ast.walk(tree) if isinstance(n, (ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef))}


def _driver_sources() -> dict[str, ast.Module]:
    """Module name (``motorctl_drivers.__init__`` for the package) → parsed source of every
    module of motorctl_drivers in the working tree."""
    return {f"motorctl_drivers.{p.stem}": ast.parse(p.read_text())
            for p in sorted((REPO / "motorctl_drivers").glob("*.py"))}


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> zipfile.ZipFile:
    tmp = tmp_path_factory.mktemp("wheel")
    src = tmp / "src"
    src.mkdir()
    for name in ("pyproject.toml", "README.md"):
        shutil.copy2(REPO / name, src / name)
    for pkg in PACKAGES:
        shutil.copytree(REPO / pkg, src / pkg, ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
    r = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", str(tmp / "dist"), str(src)],
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, f"pip wheel failed:\n{r.stdout}\n{r.stderr}"
    (path,) = (tmp / "dist").glob("motorctl-*.whl")
    with zipfile.ZipFile(path) as zf:
        yield zf


def _wheel_modules(zf: zipfile.ZipFile, package: str) -> dict[str, ast.Module]:
    out = {}
    for name in zf.namelist():
        if name.startswith(f"{package}/") and name.endswith(".py"):
            mod = name[:-3].replace("/", ".")          # a package's own module: PKG.__init__
            out[mod] = ast.parse(zf.read(name).decode())
    return out


def test_wheel_drivers_hold_no_emulator_code(wheel):
    mods = _wheel_modules(wheel, "motorctl_drivers")
    assert {"motorctl_drivers.sim", "motorctl_drivers.can_bus", "motorctl_drivers.serial_link",
            "motorctl_drivers.modbus", "motorctl_drivers.split_phase", "motorctl_drivers.canopen_cia402",
            "motorctl_drivers.cia402", "motorctl_drivers.ethercat"} <= set(mods), sorted(mods)
    for mod, tree in mods.items():
        bad = sorted(m for m in imports_of(tree, mod) if m.split(".")[0] == "motorctl_emulators")
        assert not bad, f"{mod} imports {bad}"
        names = defined_names(tree)
        device_side = sorted(n for n in names if n in EMULATOR_NAMES or n.endswith("Device"))
        assert not device_side, f"{mod} defines device-side code: {device_side}"
    # and the emulators are shipped as their own package
    assert {f"motorctl_emulators.{t}_device" for t in TRANSPORTS - {"canopen"}} | {"motorctl_emulators.cia402_device"} \
        <= set(_wheel_modules(wheel, "motorctl_emulators"))


def test_wheel_ships_no_test_helpers(wheel):
    """The in-process exchange helpers and the CLI-as-a-child helpers only the tests use live in
    tests/harness.py; nothing of tests/ and no module that defines them is installed (the
    emulators a user runs, and their loopback tools, are)."""
    names = wheel.namelist()
    assert not [n for n in names if n.startswith("tests/") or n.endswith("/harness.py") or n == "harness.py"], names
    helpers = {"device_thread", "exchange", "run_cli", "run_cli_interrupted", "parse_run_table", "wait_for"}
    for pkg in PACKAGES:
        for mod, tree in _wheel_modules(wheel, pkg).items():
            found = sorted(defined_names(tree) & helpers)
            assert not found, f"{mod} defines test helpers {found}"
    assert "motorctl_emulators.loopback" in _wheel_modules(wheel, "motorctl_emulators")


def test_wheel_declares_the_emulator_entry_points(wheel):
    (ep_file,) = [n for n in wheel.namelist() if n.endswith(".dist-info/entry_points.txt")]
    cp = configparser.ConfigParser()
    cp.read_string(wheel.read(ep_file).decode())
    emulators = dict(cp[ENTRY_POINT_GROUP])
    assert set(emulators) == TRANSPORTS
    assert all(v.startswith("motorctl_emulators.") for v in emulators.values()), emulators
    assert set(emulators) <= set(cp["motorctl.drivers"]), "every device answers an installed driver"
    assert all(v.startswith("motorctl_drivers.") for v in cp["motorctl.drivers"].values())


def test_installed_emulator_entry_points_resolve_to_devices():
    names = {ep.name for ep in entry_points(group=ENTRY_POINT_GROUP)}
    assert names == TRANSPORTS, "reinstall the project (pip install -e .) after changing entry points"
    for name in names:
        cls = load_device_class(name)
        assert issubclass(cls, Device) and cls.__module__.startswith("motorctl_emulators.")
    with pytest.raises(KeyError, match="installed: can, canopen, ethercat, modbus, serial"):
        load_device_class("sim")


def test_only_the_sim_driver_holds_the_simulator():
    """No production module but sim itself imports motorctl_drivers.sim (the simulated plant)."""
    for mod, tree in _driver_sources().items():
        if mod == "motorctl_drivers.sim":
            continue
        imported = imports_of(tree, mod)
        assert "motorctl_drivers.sim" not in imported and not any(
            m.startswith("motorctl_drivers.sim.") for m in imported), f"{mod} imports the simulator"
        assert not any(m.split(".")[0] == "motorctl_emulators" for m in imported), f"{mod} imports emulator code"
