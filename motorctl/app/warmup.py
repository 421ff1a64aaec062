"""The first start's compile: say it, and let it happen ahead of time.

numba compiles the servo cycle and the control kernels for this CPU the first time they run
after an install (or an edit of the sources) and caches the machine code on disk, under
``NUMBA_CACHE_DIR`` (by default a folder keyed by the sources, :mod:`motorctl.jitcache`); later
starts load it. :func:`cache_is_cold` tells (without importing
numba) whether the servo cycle's cache index is missing or stale for its source, so the CLI
can print :data:`COMPILE_LINE` at once instead of staying silent for 25-70 s;
:func:`warmup` (``motorctl warmup``) compiles everything a config uses with no device opened.
"""

from __future__ import annotations

import hashlib
import importlib.util
import os
import pickle
import sys
import time
from pathlib import Path

from motorctl.control import configured_controllers, make_controller
from motorctl.jitcache import numba_folder

COMPILE_LINE = "compiling the servo cycle for this CPU (first run only, ~30 s)..."
#: the compiled function whose cache index stands for the whole set
_CYCLE_MODULE, _CYCLE_FUNCTION = "motorctl.loop.cycle", "servo_cycle"


def _index_pattern(src: Path) -> str:
    return f"{src.stem}.{_CYCLE_FUNCTION}-*.py{sys.version_info.major}{sys.version_info.minor}.nbi"


def _cache_folders(src: Path) -> list[Path]:
    """Where numba keeps ``src``'s cache (numba.core.caching's locators, in their order): the
    folder :func:`motorctl.jitcache.numba_folder` points it at when there is one, else
    ``__pycache__`` beside the source, else the user-wide cache; the last two are keyed by the
    source folder's name and the SHA-1 of its path."""
    folder = src.parent.resolve()
    sub = f"{folder.name}_{hashlib.sha1(str(folder).encode()).hexdigest()}"
    chosen = numba_folder()             # the folder motorctl.jit points numba at
    if chosen:
        return [Path(chosen) / sub]
    user = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "numba" / sub
    return [src.parent / "__pycache__", user]


def _fresh(index: Path, src: Path) -> bool:
    """The index was written for this source (numba's stamp: the source's SHA-256, or its
    (mtime, size) in older numba). An index it cannot read counts as fresh (no false notice)."""
    try:
        with open(index, "rb") as fh:
            pickle.load(fh)                               # numba's version
            stamp = pickle.loads(fh.read())[0]
        if isinstance(stamp, bytes):
            return stamp == hashlib.sha256(src.read_bytes()).digest()
        st = src.stat()
        return tuple(stamp) == (st.st_mtime, st.st_size)
    except Exception:                                      # noqa: BLE001 - a notice, not a check
        return True


def cache_is_cold() -> bool:
    """True when no numba cache index of the servo cycle fits its current source, in the
    places numba looks (:func:`_cache_folders`), numba's cache folder being set first
    (:func:`motorctl.jitcache.numba_folder`: keyed by the package's sources, so that an edit to
    any of them makes it cold)."""
    if os.environ.get("NUMBA_DISABLE_JIT") == "1":
        return False
    spec = importlib.util.find_spec(_CYCLE_MODULE)
    if spec is None or not spec.origin:
        return False
    src = Path(spec.origin)
    for folder in _cache_folders(src):
        try:
            if any(_fresh(p, src) for p in folder.glob(_index_pattern(src))):
                return False
        except OSError:
            continue
    return True


_said = []


def say_if_cold(out=sys.stderr) -> bool:
    """Print :data:`COMPILE_LINE` (flushed, once per process) when the cache is cold; returns
    whether it is."""
    cold = cache_is_cold()
    if cold and not _said:
        out.write(f"motorctl: {COMPILE_LINE}\n")
        out.flush()
        _said.append(True)
    return cold


def warmup(loaded, cycles: int = 20) -> dict:
    """Compile what ``loaded`` (a checked config) runs: the daemon's feed scale steps, every
    configured controller of every axis and, when the driver is the simulator, the servo cycle (``cycles`` virtual-clock
    cycles, no log, no real time). A hardware driver is never opened: its servo cycle compiles
    at the first start.

    Returns: {"seconds": wall time [s], "cycle": whether the servo cycle was compiled}.
    """
    from motorctl.app.daemon.motion_side import warm_up as motion_warm_up
    t0 = time.monotonic()
    motion_warm_up()                  # the daemon's feed scale steps (its I/O process)
    for ax in loaded.axes.values():
        for kind in configured_controllers(ax.controller):
            make_controller(ax.controller, kind, loaded.period_s)
    sim = loaded.cfg.driver.type == "sim"
    if sim:
        from motorctl.app.job import run_job
        run_job(loaded, duration_s=cycles * loaded.period_s, clock="virtual", realtime_policy="off")
    return {"seconds": time.monotonic() - t0, "cycle": sim}
