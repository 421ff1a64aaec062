"""The input boundary shared by every command: files read with a size cap, refused when they are
not regular files, decoded with a clear error; output paths checked writable before any work
starts; values summarised (never printed whole) in error messages.

Every function raises :class:`InputError` (a ``ValueError``) with one line naming the file or
the argument, what was wrong and what is allowed; the CLI prints it and exits 2.
"""

from __future__ import annotations

import math
import os
import stat
from pathlib import Path

#: largest config file read [bytes]
MAX_CONFIG_BYTES = 1 << 20


class InputError(ValueError):
    """Bad input (a file, an argument): one line; exit code 2 in the CLI."""


class ConfigError(ValueError):
    """A config file is wrong. ``str()`` is the one-line message: ``FILE: KEY: what, allowed``.
    Raised by :mod:`motorctl.config` (defined here, with the other input errors, so that the CLI
    catches it without loading the config's models)."""

    def __init__(self, file: str, key: str, message: str):
        self.file, self.key, self.message = str(file), key, message
        super().__init__(f"{file}: {key}: {message}" if key else f"{file}: {message}")

    def __reduce__(self):
        # rebuilt from its three parts (it crosses from a worker process, e.g. identify's
        # closed loop, as itself)
        return type(self), (self.file, self.key, self.message)


def summarize(value, limit: int = 60) -> str:
    """A short description of a value for an error message: scalars as repr (cut to ``limit``
    characters), containers by type and size (a YAML alias bomb is never expanded)."""
    if isinstance(value, dict):
        return f"a mapping of {len(value)} key(s)"
    if isinstance(value, (list, tuple)):
        return f"a list of {len(value)} item(s)"
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def regular_file(path: str | Path, what: str, max_bytes: int) -> os.stat_result:
    """Check that ``path`` is a regular file of at most ``max_bytes`` (no FIFO, device or
    directory: reading those can block forever or never end). Returns its stat."""
    try:
        st = os.stat(path)
    except FileNotFoundError:
        raise InputError(f"{path}: no such file") from None
    except OSError as exc:
        raise InputError(f"{path}: cannot read the {what} ({exc.strerror or exc})") from None
    if stat.S_ISDIR(st.st_mode):
        raise InputError(f"{path}: is a directory; a {what} file is needed")
    if not stat.S_ISREG(st.st_mode):
        kind = "a FIFO" if stat.S_ISFIFO(st.st_mode) else "a device or socket"
        raise InputError(f"{path}: is {kind}, not a regular file; the {what} must be a regular file")
    if st.st_size > max_bytes:
        raise InputError(f"{path}: {st.st_size} bytes is too large for a {what} "
                         f"(at most {max_bytes} bytes)")
    return st


def read_text(path: str | Path, what: str, max_bytes: int = MAX_CONFIG_BYTES) -> str:
    """Read a UTF-8 text file (a UTF-8 byte-order mark is accepted and dropped).

    Raises:
        InputError: not a regular file, too large, unreadable, or not UTF-8 (UTF-16 is named).
    """
    regular_file(path, what, max_bytes)
    try:
        with open(path, "rb") as fh:
            data = fh.read(max_bytes + 1)
    except OSError as exc:
        raise InputError(f"{path}: cannot read the {what} ({exc.strerror or exc})") from None
    if len(data) > max_bytes:
        raise InputError(f"{path}: too large for a {what} (at most {max_bytes} bytes)")
    if data.startswith((b"\xff\xfe", b"\xfe\xff")):
        raise InputError(f"{path}: the {what} is UTF-16 text; save it as UTF-8")
    if data.startswith(b"\xef\xbb\xbf"):
        data = data[3:]
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = data[: exc.start].count(b"\n") + 1
        raise InputError(f"{path}: line {line}: the {what} is not UTF-8 text (byte "
                         f"0x{data[exc.start]:02x}); save it as UTF-8") from None


def writable_file(path: str | Path, what: str) -> Path:
    """Check, before any work starts, that a file can be written at ``path`` (its folder
    exists or can be created; ``path`` is not a directory). Creates the folder.

    Raises:
        InputError: one line naming the path and the reason.
    """
    p = Path(path)
    if p.is_dir():
        raise InputError(f"{p}: is a directory; the {what} needs a file name")
    try:
        p.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"{p}: cannot create the folder for the {what} "
                         f"({exc.strerror or exc})") from None
    existed = p.exists()
    try:
        with open(p, "ab"):
            pass
    except OSError as exc:
        raise InputError(f"{p}: cannot write the {what} ({exc.strerror or exc})") from None
    if not existed:
        p.unlink(missing_ok=True)
    return p


def writable_dir(path: str | Path, what: str) -> Path:
    """Check that ``path`` is (or can be created as) a writable directory.

    Raises:
        InputError: a file is in the way, or the directory cannot be created or written.
    """
    p = Path(path)
    if p.exists() and not p.is_dir():
        raise InputError(f"{p}: is a file; the {what} needs a directory")
    try:
        p.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"{p}: cannot create the {what} directory ({exc.strerror or exc})") from None
    if not os.access(p, os.W_OK | os.X_OK):
        raise InputError(f"{p}: the {what} directory is not writable")
    return p


def finite_number(text: str, name: str, lo: float, hi: float, lo_open: bool = True) -> float:
    """Parse a command-line number that must be finite and within (lo, hi] ([lo, hi] when
    ``lo_open`` is False). Raises InputError naming the argument and the allowed range."""
    try:
        x = float(text)
    except (TypeError, ValueError):
        raise InputError(f"{name}: {summarize(text)} is not a number") from None
    bad_lo = x <= lo if lo_open else x < lo
    if not math.isfinite(x) or bad_lo or x > hi:
        rng = f"{'(' if lo_open else '['}{lo:g}, {hi:g}]"
        raise InputError(f"{name}: {summarize(text)} is outside {rng}")
    return x


def seconds_arg(text: str) -> float:
    """argparse ``type=`` of a duration [s]: finite, > 0, at most 10^6 s.

    Raises:
        argparse.ArgumentTypeError: with the allowed range (argparse makes it one line).
    """
    import argparse
    try:
        return finite_number(text, "duration", 0.0, 1e6)
    except InputError as exc:
        raise argparse.ArgumentTypeError(str(exc).split(": ", 1)[1]) from None
