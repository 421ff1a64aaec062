"""The command line's help is the reference: every subcommand, positional and option says what it
is, in plain text, and the README's command table names exactly the parser's subcommands."""

from __future__ import annotations

import argparse
import re
import subprocess
import sys
from pathlib import Path

import pytest

from motorctl.cli import build_parser

REPO = Path(__file__).resolve().parents[1]


def _subcommands(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            return dict(action.choices)
    raise AssertionError("motorctl has no subcommands")


def _texts(parser: argparse.ArgumentParser):
    """(where, text) of the parser's description and of every action's help."""
    yield f"{parser.prog}: description", parser.description or ""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for choice in action._choices_actions:
                yield f"{parser.prog} {choice.dest}: help", choice.help or ""
            continue
        yield f"{parser.prog} {'/'.join(action.option_strings) or action.dest}: help", action.help or ""


@pytest.fixture(scope="module")
def parser():
    return build_parser()


def test_no_markup_in_help(parser):
    found = []
    for p in [parser, *_subcommands(parser).values()]:
        found += [where for where, text in _texts(p) if "``" in text or ":func:" in text or ":mod:" in text]
    assert not found, f"RST markup in the help: {found}"


def test_every_argument_has_help(parser):
    missing = []
    for p in [parser, *_subcommands(parser).values()]:
        for action in p._actions:
            if isinstance(action, (argparse._HelpAction, argparse._SubParsersAction)):
                continue
            if not action.help:
                missing.append(f"{p.prog} {'/'.join(action.option_strings) or action.dest}")
    assert not missing, f"arguments without a help line: {missing}"


def test_every_subcommand_has_help(parser):
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    helped = {c.dest for c in sub._choices_actions if c.help}
    assert helped == set(sub.choices), f"subcommands without help: {set(sub.choices) - helped}"


def test_readme_command_table_matches_parser(parser):
    text = (REPO / "README.md").read_text(encoding="utf-8")
    section = text.split("\n## Commands\n", 1)[1].split("\n## ", 1)[0]
    listed = re.findall(r"^\| `motorctl ([a-z][a-z0-9-]*)", section, flags=re.M)
    assert len(listed) == len(set(listed)), f"a command listed twice: {listed}"
    assert set(listed) == set(_subcommands(parser)), (
        f"README command table vs parser: missing {sorted(set(_subcommands(parser)) - set(listed))}, "
        f"not a command {sorted(set(listed) - set(_subcommands(parser)))}")


def test_readme_names_every_extra():
    import tomllib
    extras = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["optional-dependencies"]
    text = (REPO / "README.md").read_text(encoding="utf-8")
    section = text.split("\n## Extras\n", 1)[1].split("\n## ", 1)[0]
    listed = set(re.findall(r"^\| `([a-z0-9-]+)` \|", section, flags=re.M))
    assert listed == set(extras), f"README extras vs pyproject: {sorted(set(extras) ^ listed)}"


def test_top_level_help_is_plain():
    r = subprocess.run([sys.executable, "-m", "motorctl", "--help"], capture_output=True, text=True,
                       timeout=120, cwd=REPO)
    assert r.returncode == 0, r.stderr
    assert "``" not in r.stdout and "motorctl" in r.stdout.splitlines()[0]


def test_a_missing_extra_is_named_in_one_line(tmp_path):
    """`motorctl plot` without matplotlib: one line naming the `plot` extra, exit 2, no traceback."""
    code = ("import sys; sys.modules['matplotlib'] = None; from motorctl.cli import main; "
            f"sys.exit(main(['plot', {str(tmp_path / 'none.mclog')!r}]))")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=REPO)
    assert r.returncode == 2, r.stderr
    assert r.stderr == ("motorctl: error: plot: needs the 'plot' extra (matplotlib is not installed): "
                        "pip install 'motorctl[plot]'\n")


def test_every_extra_module_names_a_real_extra():
    import tomllib

    from motorctl.cli import EXTRA_OF
    extras = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["optional-dependencies"]
    assert set(EXTRA_OF.values()) <= set(extras)


def test_ci_runs_the_readme_test_command():
    """.ci/run ends with exactly the command the README gives for the tests."""
    ci = (REPO / ".ci" / "run").read_text().strip().splitlines()[-1]
    text = (REPO / "README.md").read_text(encoding="utf-8")
    section = text.split("\n## The two commands\n", 1)[1].split("\n## ", 1)[0]
    assert ci.startswith("python3 -m venv .venv") and ci in section.splitlines()
