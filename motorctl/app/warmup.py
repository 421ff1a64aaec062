"""The first start's compile: say it, and let it happen ahead of time.

numba compiles the servo cycle and the control kernels for this CPU the first time they run
after an install and caches the machine code on disk (beside the sources, or under
``NUMBA_CACHE_DIR``); later starts load it. :func:`cache_is_cold` tells (without importing
numba) whether the servo cycle's cache index is missing or older than its source, so the CLI
can print :data:`COMPILE_LINE` at once instead of staying silent for 25-70 s;
:func:`warmup` (``motorctl warmup``) compiles everything a config uses with no device opened.
"""

from __future__ import annotations

import importlib.util
import os
import sys
import time
from pathlib import Path

COMPILE_LINE = "compiling the servo cycle for this CPU (first run only, ~30 s)..."
#: the compiled function whose cache index stands for the whole set
_CYCLE_MODULE, _CYCLE_FUNCTION = "motorctl.loop.cycle", "servo_cycle"


def _index_pattern(src: Path) -> str:
    return f"{src.stem}.{_CYCLE_FUNCTION}-*.py{sys.version_info.major}{sys.version_info.minor}.nbi"


def cache_is_cold() -> bool:
    """True when the servo cycle's numba cache index is absent (or older than its source) in
    every place numba looks: ``NUMBA_CACHE_DIR`` (mirroring the source's path) when set, else
    the ``__pycache__`` beside the source."""
    spec = importlib.util.find_spec(_CYCLE_MODULE)
    if spec is None or not spec.origin:
        return False
    src = Path(spec.origin)
    if os.environ.get("NUMBA_DISABLE_JIT") == "1":
        return False
    where = os.environ.get("NUMBA_CACHE_DIR")
    folder = (Path(where) / src.parent.resolve().relative_to("/")) if where else src.parent / "__pycache__"
    try:
        mtime = src.stat().st_mtime
        return not any(p.stat().st_mtime >= mtime for p in folder.glob(_index_pattern(src)))
    except (OSError, ValueError):
        return True


def say_if_cold(out=sys.stderr) -> bool:
    """Print :data:`COMPILE_LINE` (flushed) when the cache is cold; returns whether it was."""
    cold = cache_is_cold()
    if cold:
        out.write(f"motorctl: {COMPILE_LINE}\n")
        out.flush()
    return cold


def warmup(loaded, cycles: int = 20) -> dict:
    """Compile what ``loaded`` (a checked config) runs: every configured controller of every
    axis and, when the driver is the simulator, the servo cycle (``cycles`` virtual-clock
    cycles, no log, no real time). A hardware driver is never opened: its servo cycle compiles
    at the first start.

    Returns: {"seconds": wall time [s], "cycle": whether the servo cycle was compiled}.
    """
    from motorctl.control import configured_controllers

    t0 = time.monotonic()
    for a, ax in loaded.axes.items():
        for kind in configured_controllers(ax.controller):
            loaded.make_controllers([a], kind)
    sim = loaded.cfg.driver.type == "sim"
    if sim:
        from motorctl.app.job import run_job
        run_job(loaded, duration_s=cycles * loaded.period_s, clock="virtual", realtime_policy="off")
    return {"seconds": time.monotonic() - t0, "cycle": sim}
