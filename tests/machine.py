"""What this machine offers the tests, decided from the machine itself before any code under test
runs (docs/testing.md, "Skips"): a test skips only when one of these says the machine lacks what
it needs, never on what the product reported (a regression must fail, not skip)."""

from __future__ import annotations

import resource
import subprocess
import sys
from pathlib import Path

#: capability numbers (linux/capability.h)
CAP_IPC_LOCK = 14


def has_capability(cap: int) -> bool:
    """``cap`` is in this process's effective set (/proc/self/status CapEff)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("CapEff:"):
                return bool(int(line.split()[1], 16) >> cap & 1)
    except OSError:
        pass
    return False


def mlockall_permitted() -> tuple[bool, str]:
    """May a process started from this one lock all its memory (mlockall(MCL_CURRENT |
    MCL_FUTURE))? With CAP_IPC_LOCK (root keeps it unless dropped) or an unlimited RLIMIT_MEMLOCK;
    a finite limit is below a Python process's mapped memory (hundreds of MiB with numpy), which
    MCL_CURRENT counts. Returns (permitted, why not)."""
    if has_capability(CAP_IPC_LOCK):
        return True, ""
    soft, _ = resource.getrlimit(resource.RLIMIT_MEMLOCK)
    if soft == resource.RLIM_INFINITY:
        return True, ""
    return False, (f"mlockall is not permitted here: no CAP_IPC_LOCK (not root) and RLIMIT_MEMLOCK "
                   f"is {soft} bytes, not unlimited")


#: what a process as ``nobody`` checks with this interpreter (-I -S: no site, nothing imported)
_READABLE = """
import os, sys
bad = [p for p in sys.argv[1:] if not os.access(p, os.R_OK | (os.X_OK if os.path.isdir(p) else 0))]
print("\\n".join(bad))
sys.exit(1 if bad else 0)
"""


def unreadable_as(prefix: list[str], paths: list[Path]) -> str:
    """The first problem a process run with ``prefix`` (e.g. setpriv to ``nobody``) has running
    this interpreter and reading ``paths`` (its files and folders, each folder searchable): ''
    when there is none. Only the interpreter itself runs (``-I -S``), none of the project's code."""
    r = subprocess.run([*prefix, sys.executable, "-I", "-S", "-c", _READABLE, *map(str, paths)],
                       capture_output=True, text=True, timeout=60)
    if r.returncode == 0:
        return ""
    if r.stdout.strip():
        return "cannot read " + ", ".join(r.stdout.split())
    return f"cannot run {sys.executable} (exit {r.returncode}): {r.stderr.strip()[-200:]}"


def module_paths(*names: str) -> list[Path]:
    """Where ``names`` (top-level modules) would be imported from, found without importing
    them (importlib's finder): the file or the package folder."""
    import importlib.util
    out = []
    for name in names:
        spec = importlib.util.find_spec(name)
        if spec is None:
            raise AssertionError(f"{name} is not installed in {sys.prefix} (pip install -e '.[test]')")
        if spec.submodule_search_locations:
            out.extend(Path(p) for p in spec.submodule_search_locations)
        elif spec.origin:
            out.append(Path(spec.origin))
    return out
