"""The driver and command seams, as docs/architecture.md's "How to add" says: a driver is one
module and one entry point in ``motorctl.drivers``, a command one ``register`` function and one
entry point in ``motorctl.commands``. Both are written here, outside the package, and
registered through a ``*.dist-info/entry_points.txt`` on the path (as an installed plugin is);
the CLI then offers them with no edit to motorctl. (The law and family seams:
tests/test_controller_seam.py, tests/test_effect_entry_points.py.)"""

from __future__ import annotations

import subprocess
import sys

import pytest
import yaml

from harness import parse_run_table, plugin_env

#: a driver (the simulated one under another name, with an option of its own) and a command
PLUGIN = '''
from motorctl.cli import UsageError
from motorctl_drivers.sim import SimDriver, SimOptions


class TwinOptions(SimOptions):
    twin_label: str = ""


class TwinDriver(SimDriver):
    """The simulated plant, as a driver of another package."""
    Options = TwinOptions


def register(parser, subparsers):
    p = subparsers.add_parser("greet", help="say hello to an axis")
    p.add_argument("axis", help="the axis to greet")
    p.set_defaults(func=_greet)


def _greet(args):
    if not args.axis.isalpha():
        raise UsageError(f"greet: axis {args.axis!r}: letters only")
    print(f"hello {args.axis}")
    return 0
'''


@pytest.fixture(scope="module")
def env(tmp_path_factory) -> dict:
    root = tmp_path_factory.mktemp("seam")
    (root / "twinplug.py").write_text(PLUGIN)
    e = plugin_env(root, "twinplug", "motorctl.drivers", {"twin": "twinplug:TwinDriver"})
    info = next(root.glob("*.dist-info"))
    with open(info / "entry_points.txt", "a") as fh:
        fh.write("[motorctl.commands]\ngreet = twinplug:register\n")
    return e


def _cli(repo, env, *args):
    return subprocess.run([sys.executable, "-m", "motorctl", *args], cwd=repo, env=env,
                          capture_output=True, text=True, timeout=300)


def _config(repo, tmp_path, **driver) -> str:
    raw = yaml.safe_load((repo / "configs" / "gantry-rigid.yaml").read_text())
    del raw["axes"]["Y"]
    raw["driver"] = {**raw["driver"], "type": "twin", **driver}
    path = tmp_path / "twin.yaml"
    path.write_text(yaml.safe_dump(raw, sort_keys=False))
    return str(path)


def test_a_driver_is_one_module_and_one_entry_point(repo, env, tmp_path):
    cfg = _config(repo, tmp_path, twin_label="bench 2")
    p = _cli(repo, env, "run", cfg, "--virtual-clock", "--duration", "1")
    assert p.returncode == 0, p.stderr
    twin = parse_run_table(p.stdout)["X"]
    # the same plant and seed as the simulated driver's: the same figures
    raw = yaml.safe_load(open(cfg))
    del raw["driver"]["twin_label"]
    raw["driver"]["type"] = "sim"
    sim_cfg = tmp_path / "sim.yaml"
    sim_cfg.write_text(yaml.safe_dump(raw, sort_keys=False))
    p = _cli(repo, env, "run", str(sim_cfg), "--virtual-clock", "--duration", "1")
    assert p.returncode == 0, p.stderr
    assert twin == parse_run_table(p.stdout)["X"] and twin["fault"] == ""
    # its options model checks its own keys
    p = _cli(repo, env, "check-config", _config(repo, tmp_path, twin_colour="red"))
    assert p.returncode == 2 and p.stderr.count("\n") == 1, p.stderr
    assert "driver.twin_colour" in p.stderr, p.stderr


def test_a_command_is_one_register_function_and_one_entry_point(repo, env):
    p = _cli(repo, env, "greet", "X")
    assert p.returncode == 0 and p.stdout == "hello X\n", (p.stdout, p.stderr)
    p = _cli(repo, env, "--help")
    assert "greet" in p.stdout
    # bad input: one line, exit 2, no traceback
    p = _cli(repo, env, "greet", "X1")
    assert p.returncode == 2 and p.stderr == "motorctl: error: greet: axis 'X1': letters only\n", p.stderr
