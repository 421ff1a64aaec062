"""Files that readers of run logs write (export, plot): never over a run log, never half.

:func:`check_output` refuses an output that is one of the inputs (the same inode, through any
name or link) or any existing run log; :func:`atomic_output` writes to a temporary name in the
output's directory and renames it over the output only once everything is written, so a full
disk, an error or a kill leaves the old file (or none), never a partial one.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path

from motorctl.inputs import InputError, writable_file
from motorctl.recorder.runlog import MAGIC


def _is_run_log(p: Path) -> bool:
    try:
        with open(p, "rb") as fh:
            return fh.read(len(MAGIC)) == MAGIC
    except OSError:
        return False


def check_output(out: str | Path, inputs, what: str) -> Path:
    """Check, before anything is read or written, that ``out`` may be written.

    Args:
        out: the output file. inputs: paths of the files read (run logs, segments).
        what: the output's name in messages ("export", "plot").
    Raises:
        InputError: ``out`` is an input, an existing run log, a directory, or not writable
        (one line naming it).
    """
    p = Path(out)
    if p.exists():
        for src in inputs:
            try:
                same = os.path.samefile(p, src)
            except OSError:
                same = False
            if same:
                raise InputError(f"{p}: is the run log being read ({src}); the {what} needs "
                                 f"another file name")
        if p.is_file() and _is_run_log(p):
            raise InputError(f"{p}: is a motorctl run log; the {what} never overwrites one "
                             f"(name another file)")
    return writable_file(p, what)


@contextlib.contextmanager
def atomic_output(out: str | Path, what: str):
    """Yield a temporary path beside ``out``; on success rename it to ``out``. On any error
    the temporary file is removed; an OSError (e.g. ENOSPC, EFBIG) becomes an
    :class:`InputError` naming ``out``.
    """
    p = Path(out)
    fd, tmp = tempfile.mkstemp(prefix=f".{p.name}.", suffix=".part", dir=p.parent or ".")
    try:
        mask = os.umask(0)
        os.umask(mask)
        os.fchmod(fd, 0o666 & ~mask)
        os.close(fd)
        yield tmp
        os.replace(tmp, p)
    except OSError as exc:
        Path(tmp).unlink(missing_ok=True)
        raise InputError(f"{p}: cannot write the {what} "
                         f"({exc.strerror or exc}); nothing written") from None
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
