"""Where a cold start's compile time goes: ``motorctl warmup CONFIG`` run in this process with
numba's ``numba:compile`` events recorded (each an overload compiled, not loaded from the cache),
then per kernel: the overloads compiled (signatures), the time inside its own compile (its
callees' compiles excluded) and including them. Meant for an empty ``NUMBA_CACHE_DIR``
(``bench_start.py --breakdown`` runs it so); on a warm cache it lists what still compiles.

Rerun:
    NUMBA_CACHE_DIR=$(mktemp -d) python benchmarks/compile_breakdown.py [configs/gantry-rigid.yaml] [--top 25]
"""

from __future__ import annotations

import argparse
import os
import time
from collections import defaultdict


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("config", nargs="?", default="configs/gantry-rigid.yaml")
    ap.add_argument("--top", type=int, default=25, help="rows of the table (by own time)")
    args = ap.parse_args()
    t_import = time.monotonic()
    from numba.core import event

    from motorctl.app.warmup import warmup
    from motorctl.config import load_config
    t_import = time.monotonic() - t_import

    stack: list[list] = []                 # [key, t_start, child seconds]
    own: dict[str, float] = defaultdict(float)
    incl: dict[str, float] = defaultdict(float)
    sigs: dict[str, list] = defaultdict(list)

    class _Listener(event.Listener):
        def on_start(self, ev):
            d = ev.data["dispatcher"]
            key = f"{d.py_func.__module__}.{d.py_func.__qualname__}"
            sigs[key].append(ev.data["args"])
            stack.append([key, time.perf_counter(), 0.0])

        def on_end(self, ev):
            key, t0, child = stack.pop()
            dt = time.perf_counter() - t0
            own[key] += dt - child
            if not any(k == key for k, _, _ in stack):
                incl[key] += dt
            if stack:
                stack[-1][2] += dt

    listener = _Listener()
    event.register("numba:compile", listener)
    try:
        t_load = time.monotonic()
        loaded = load_config(args.config)
        t_load = time.monotonic() - t_load
        res = warmup(loaded)
    finally:
        event.unregister("numba:compile", listener)
    total = sum(own.values())
    n_sig = sum(len(v) for v in sigs.values())
    print(f"# {args.config}: imports {t_import:.1f} s, config {t_load:.1f} s, warmup {res['seconds']:.1f} s; "
          f"{n_sig} overloads of {len(sigs)} functions compiled in {total:.1f} s; "
          f"NUMBA_CACHE_DIR={os.environ.get('NUMBA_CACHE_DIR', '-')}; load average {os.getloadavg()[0]:.1f}")
    print("| function | overloads | own [s] | with callees [s] |")
    print("|---|---|---|---|")
    for key in sorted(own, key=own.get, reverse=True)[:args.top]:
        print(f"| {key} | {len(sigs[key])} | {own[key]:.2f} | {incl[key]:.2f} |")
    dup = {k: v for k, v in sigs.items() if len(v) > 1}
    for key, v in sorted(dup.items()):
        print(f"# {key}: {len(v)} overloads: " + "; ".join(str(tuple(map(str, a))) for a in v)[:600])


if __name__ == "__main__":
    main()
