"""Where numba's on-disk cache of the compiled kernels lives: a folder keyed by the sources.

numba keys a cached function on its own source file only (its SHA-256 in numba 0.61): the
servo cycle (``motorctl/loop/cycle.py``) calls kernels of other modules, whose machine code is
inlined into the cycle's, and an edit to one of them (``safety.py``, ``stream.py``, an effect's
kernel) left the cycle's stale code in the cache. motorctl therefore points ``NUMBA_CACHE_DIR``
at a folder named by a hash of every ``.py`` source of its packages (:func:`source_key`):
another source, another folder, a cold cache. Unchanged sources find their folder again (an
edit undone too).

The folder (:func:`cache_dir`): ``NUMBA_CACHE_DIR`` as it is when the user set it (nothing
keyed then); else ``<base>/numba/<checkout>/<key>`` with ``<base>`` = ``MOTORCTL_CACHE_DIR``
(the systemd units: ``/var/cache/motorctl``), else ``$XDG_CACHE_HOME/motorctl``, else
``~/.cache/motorctl``; ``<checkout>`` tells installs and checkouts apart (the packages' folder
name and a hash of its path), and :func:`configure` keeps the :data:`KEEP` folders of a
checkout used last, deleting its older ones.

No numba import here: :func:`configure` runs before numba reads its configuration (the CLI's
compile notice, :mod:`motorctl.jit`).
"""

from __future__ import annotations

import hashlib
import os
import shutil
from functools import lru_cache
from pathlib import Path

#: the packages whose sources hold compiled kernels (their ``.py`` files make the key)
PACKAGES = ("motorctl", "motorctl_drivers")
#: cache folders of one checkout kept (the current one and the ones used last)
KEEP = 3
#: the environment variable of the cache's base folder (the systemd units set it)
BASE_ENV = "MOTORCTL_CACHE_DIR"

#: the entry-point group whose packages add kernels to the compiled code -> kernel tables (the
#: effect families, :mod:`motorctl.effects.registry`)
KERNEL_ENTRY_POINTS = "motorctl.effects"

__all__ = ["BASE_ENV", "KEEP", "KERNEL_ENTRY_POINTS", "PACKAGES", "cache_dir", "configure", "numba_folder",
           "plugin_key", "source_key"]


def _package_roots() -> list[Path]:
    here = Path(__file__).resolve().parent            # motorctl/
    return [here.parent / name for name in PACKAGES if (here.parent / name).is_dir()]


def source_key(roots=None) -> str:
    """A hash (16 hex digits) of every ``.py`` file under ``roots`` (folders; default: this
    project's packages, :data:`PACKAGES`): their paths relative to the roots' parent and their
    bytes, in sorted order. About 1.5 MB of sources: a few milliseconds."""
    roots = [Path(r) for r in (roots if roots is not None else _package_roots())]
    h = hashlib.sha256()
    for root in roots:
        for path in sorted(root.rglob("*.py")):
            if "__pycache__" in path.parts:
                continue
            h.update(str(path.relative_to(root.parent)).encode() + b"\0")
            h.update(path.read_bytes())
            h.update(b"\0")
    return h.hexdigest()[:16]


def _base(environ) -> Path:
    if environ.get(BASE_ENV):
        return Path(environ[BASE_ENV])
    xdg = environ.get("XDG_CACHE_HOME")
    return (Path(xdg) if xdg else Path.home() / ".cache") / "motorctl"


def cache_dir(environ=None, roots=None) -> tuple[Path, bool]:
    """(the folder numba's cache belongs in, whether the user chose it: ``NUMBA_CACHE_DIR`` was
    set in ``environ`` (default ``os.environ``)). ``roots``: the package folders hashed
    (:func:`source_key`)."""
    environ = os.environ if environ is None else environ
    if environ.get("NUMBA_CACHE_DIR"):
        return Path(environ["NUMBA_CACHE_DIR"]), True
    roots = [Path(r) for r in (roots if roots is not None else _package_roots())]
    parent = roots[0].resolve().parent if roots else Path(__file__).resolve().parents[1]
    checkout = f"{parent.name}_{hashlib.sha1(str(parent).encode()).hexdigest()[:8]}"
    return _base(environ) / "numba" / checkout / source_key(roots), False


def _prune(folder: Path, keep: int = KEEP) -> None:
    """Delete the sibling folders of ``folder`` but the ``keep`` - 1 used last (best effort)."""
    try:
        others = [p for p in folder.parent.iterdir() if p.is_dir() and p != folder]
        others.sort(key=lambda p: p.stat().st_mtime, reverse=True)
    except OSError:
        return
    for p in others[keep - 1:]:
        shutil.rmtree(p, ignore_errors=True)


@lru_cache(maxsize=1)
def configure() -> str | None:
    """Point numba's cache at :func:`cache_dir` (once per process): sets ``NUMBA_CACHE_DIR`` in
    ``os.environ`` (child processes inherit the same folder) unless the user set it, creates
    the folder and prunes the checkout's older ones. Returns the folder, or None when it cannot
    be created (numba then keeps its own default: beside the sources, or the user's cache)."""
    folder, chosen = cache_dir()
    if chosen:
        return str(folder)
    try:
        folder.mkdir(parents=True, exist_ok=True)
        os.utime(folder)                             # "used last": the pruning's order
    except OSError:
        return None
    _prune(folder)
    os.environ["NUMBA_CACHE_DIR"] = str(folder)
    return str(folder)


@lru_cache(maxsize=1)
def plugin_key() -> str | None:
    """A hash (16 hex digits) of the names, versions and entry points of the packages other
    than motorctl that register :data:`KERNEL_ENTRY_POINTS`; None when none does.

    The dispatch over the code -> kernel tables is inlined into its callers, up to the servo
    cycle, and numba's cache sees neither a change of a kernel called from another module nor
    of a table read as a global: a process whose tables hold another package's kernels
    compiles and caches all of them apart (:func:`numba_folder`). After editing such a
    package's kernel, bump its version (or delete that folder)."""
    from importlib.metadata import entry_points
    own = []
    for ep in entry_points(group=KERNEL_ENTRY_POINTS):
        dist = getattr(ep, "dist", None)
        name = dist.metadata["Name"] if dist is not None else "?"
        if name != "motorctl":
            own.append(f"{name} {dist.version if dist is not None else '?'} {ep.name}={ep.value}")
    return hashlib.sha256("\n".join(sorted(own)).encode()).hexdigest()[:16] if own else None


def numba_folder() -> str | None:
    """The folder numba caches this process's kernels in: :func:`configure`'s (or the user's
    ``NUMBA_CACHE_DIR``), and with another package's kernels (:func:`plugin_key`) its
    ``motorctl-plugins-<key>`` subfolder (under ``$XDG_CACHE_HOME`` or ``~/.cache`` when no
    folder could be configured). None: numba's own default."""
    base = configure() or os.environ.get("NUMBA_CACHE_DIR")
    key = plugin_key()
    if key is None:
        return base
    base = base or os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(base, f"motorctl-plugins-{key}")
