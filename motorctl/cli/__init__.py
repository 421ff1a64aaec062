"""The ``motorctl`` command line.

Subcommands come from the modules in :data:`COMMAND_MODULES` (``run``, ``compare``,
``check-config``, ``plot`` in :mod:`motorctl.cli.run`; the daemon and its operator commands in
:mod:`motorctl.cli.operator`; ``identify`` in :mod:`motorctl.cli.identify`) and from other
installed packages through the ``motorctl.commands`` entry points, each a
``register(parser, subparsers)`` adding its parsers with ``set_defaults(func=handler)``; a
handler returns the exit code.

Exit codes: 0 success, 1 the job ran but failed (fault, comparison bound), 2 bad input
(config, arguments, data): one clear line on stderr, nothing started.
"""

from __future__ import annotations

import argparse
import gc
import importlib
import os
import signal
import sys
from importlib.metadata import entry_points

DEFAULT_CONFIG = "configs/gantry.yaml"

#: Modules of this package that add subcommands (the job, daemon control, identification). Other
#: installed packages add theirs through the ``motorctl.commands`` entry-point group (a
#: ``register(parser, subparsers)`` function), e.g. ``motorctl emulate``.
#: commands that compile the servo cycle when numba's cache is cold (they say so first)
COMPILING_COMMANDS = ("run", "daemon", "warmup")
COMMAND_MODULES = ("motorctl.cli.run", "motorctl.cli.operator", "motorctl.cli.identify", "motorctl.cli.runs",
                   "motorctl.cli.tune", "motorctl.cli.autotune", "motorctl.cli.data",
                   "motorctl.cli.motion", "motorctl.cli.fleet", "motorctl.cli.users", "motorctl.cli.opcua")
COMMAND_GROUP = "motorctl.commands"

#: the optional-dependency group (pyproject.toml) that installs each optional top-level module:
#: a command that needs one which is missing says so in one line naming the extra (exit 2)
EXTRA_OF = {"matplotlib": "plot", "aiohttp": "scope", "foxglove": "foxglove", "mcap": "mcap",
            "can": "can", "canopen": "can", "msgpack": "can", "serial": "serial", "pymodbus": "modbus",
            "pysoem": "ethercat", "pooch": "data", "asyncua": "opcua",
            "dask": "fleet", "distributed": "fleet", "pyarrow": "fleet", "fsspec": "fleet"}


class UsageError(Exception):
    """Bad input found by a handler: printed as one line, exit code 2."""


class Parser(argparse.ArgumentParser):
    """argparse with one-line errors (``motorctl: error: ...``, exit 2), as every other bad
    input gets; ``--help`` still prints the usage."""

    def error(self, message):
        self.exit(2, f"motorctl: error: {self.prog}: {message}\n")



def print_table(rows: list[list[str]], out) -> None:
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    for r in rows:
        out.write("  ".join(c.rjust(w) if i else c.ljust(w) for i, (c, w) in enumerate(zip(r, widths))) + "\n")


def build_parser() -> argparse.ArgumentParser:
    p = Parser(prog="motorctl", description="The motorctl command line: the servo loop, its daemon, "
                "identification and commissioning. motorctl COMMAND --help for each command.")
    sub = p.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True

    for mod in COMMAND_MODULES:
        importlib.import_module(mod).register(p, sub)
    for ep in sorted(entry_points(group=COMMAND_GROUP), key=lambda e: e.name):
        ep.load()(p, sub)
    return p


def main(argv=None) -> int:
    """Run one command (``argv``: its words; None: this process's command line) and return its
    exit code (see the module docstring)."""
    code = _command(argv)
    if argv is None:
        # the process's own command line: it exits next, and the interpreter's last garbage
        # collections would walk every object the imports made (numpy, scipy, pydantic: 0.1 s);
        # frozen, they are skipped. Exit handlers still run and files are closed by their owners
        # (every writer here closes its files; nothing is left to a collection to flush)
        gc.freeze()
    return code


def _command(argv) -> int:
    words = sys.argv[1:] if argv is None else list(argv)
    if words and words[0] in COMPILING_COMMANDS and not {"-h", "--help"} & set(words):
        # a signal while a long start-up loads and builds (before the device is opened, where
        # the command's own stop takes over) is one line, not a silent end
        old = {s: signal.signal(s, _start_up_signal) for s in (signal.SIGTERM, signal.SIGINT)}
        try:
            return _start_up(argv)
        except _StartUpSignal as exc:
            sys.stdout.flush()
            who = "motorctl daemon" if words[0] == "daemon" else "motorctl"
            sys.stderr.write(f"{who}: stopped by {exc} during start-up, before the device was opened: "
                             f"nothing was driven\n")
            return 0 if words[0] == "daemon" else 1    # a signal is the daemon's normal end
        finally:
            for s, h in old.items():
                signal.signal(s, h)
    return _run_command(argv)


class _StartUpSignal(Exception):
    """SIGTERM/SIGINT during a command's start-up, before its device is opened."""


def _start_up_signal(signum, _frame):
    raise _StartUpSignal(signal.Signals(signum).name)


def _start_up(argv) -> int:
    from motorctl.app.warmup import say_if_cold
    say_if_cold()         # before the parser's imports load numba: a cold start is not a hang
    return _run_command(argv)


def _run_command(argv) -> int:
    # not motorctl.config (its models load numba) nor motorctl.loop.rt or the run log (numpy,
    # pydantic): an operator command (status, hold, ...) imports only the client side
    from motorctl.inputs import ConfigError, InputError
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:               # --help (0) or a one-line usage error (2)
        return int(exc.code or 0)
    try:
        try:
            return int(args.func(args) or 0)
        except Exception as exc:
            if isinstance(exc, (ConfigError, UsageError, InputError) + _loaded_input_errors()):
                sys.stderr.write(f"motorctl: error: {exc}\n")
                return 2
            raise
    except FileNotFoundError as exc:
        sys.stderr.write(f"motorctl: error: {exc.filename}: no such file\n")
        return 2
    except ModuleNotFoundError as exc:
        extra = EXTRA_OF.get((exc.name or "").split(".")[0])
        if extra is None:
            raise
        sys.stderr.write(f"motorctl: error: {args.command}: needs the '{extra}' extra ({exc.name} is not "
                         f"installed): pip install 'motorctl[{extra}]'\n")
        return 2
    except BrokenPipeError:   # the reader went away (e.g. `motorctl status | head`)
        _quiet_stdout()
        return 0
    except OSError as exc:  # a driver that cannot reach its device, a log that cannot be written
        sys.stderr.write(f"motorctl: error: {exc}\n")
        return 1


#: input errors of modules a command may load (module → class): caught as bad input (exit 2),
#: looked up only where the command loaded the module (a command that never did cannot raise it)
_INPUT_ERRORS = {"motorctl.recorder.runlog": "LogError", "motorctl.loop.rt": "RealtimeError"}


def _loaded_input_errors() -> tuple:
    return tuple(getattr(sys.modules[m], c) for m, c in _INPUT_ERRORS.items() if m in sys.modules)


def _quiet_stdout() -> None:
    """After the reader of stdout went away, point stdout at /dev/null so the interpreter's
    final flush does not print a second 'Broken pipe' error."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.close(devnull)
    except (OSError, ValueError):
        pass


if __name__ == "__main__":
    sys.exit(main())

