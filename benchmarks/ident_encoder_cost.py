"""CPU time of the encoder_interpolation family inside ``motorctl identify`` (its search and
polish, summed over every selection step) and of the whole identification.

Rerun:
    python benchmarks/ident_encoder_cost.py                  # a clean and an encoder log, 20 s
    python benchmarks/ident_encoder_cost.py LOG [LOG ...]     # your own run logs (axis X)

Without arguments two 20 s logs of ``configs/gantry.yaml``'s X axis (C2, virtual clock, seed 1)
are made in a temporary folder: the plant as it is, and with the ±3 µm interpolation error at a
2 mm signal period. The family's time is the thread CPU time (``time.thread_time``) around its
``search`` and ``polish`` calls, which run on the identifier's search threads; the whole is the
process CPU time of :func:`motorctl.ident.pipeline.identify_record`. On a loaded machine the
figures grow with the load (the printed load average says how loaded it was).
"""

from __future__ import annotations

import os
import sys
import tempfile
import time
from pathlib import Path

ENCODER = {"encoder_interpolation_m": 3.0e-6, "encoder_signal_period_m": 2.0e-3}


def measure(path: str) -> tuple[float, float, int]:
    """(family CPU [s], identify CPU [s], calls) for the run log ``path`` (axis X)."""
    from motorctl.effects import FAMILIES
    from motorctl.ident.data import load_record
    from motorctl.ident.pipeline import identify_record
    fam = FAMILIES["encoder_interpolation"]
    acc = {"cpu": 0.0, "n": 0}
    saved = {name: getattr(fam, name) for name in ("search", "polish")}

    def timed(fn):
        def call(*a, **k):
            t0 = time.thread_time()
            try:
                return fn(*a, **k)
            finally:
                acc["cpu"] += time.thread_time() - t0
                acc["n"] += 1
        return call
    try:
        for name, fn in saved.items():
            setattr(fam, name, timed(fn))
        t0 = time.process_time()
        identify_record(load_record(path, None, None, axis="X"))
        total = time.process_time() - t0
    finally:
        for name in saved:
            delattr(fam, name)       # back to the class's methods
    return acc["cpu"], total, acc["n"]


def main(argv=None) -> int:
    logs = list(argv if argv is not None else sys.argv[1:])
    with tempfile.TemporaryDirectory(prefix="motorctl-enc-cost-") as tmp:
        if not logs:
            from motorctl.commission.tune import make_log
            base = str(Path(__file__).resolve().parents[1] / "configs" / "gantry.yaml")
            for name, effect in (("clean", {}), ("encoder", ENCODER)):
                p = str(Path(tmp) / f"{name}.mclog")
                make_log(p, effect, duration_s=20.0, seed=1, base=base)
                logs.append(p)
        for p in logs:
            fam, total, n = measure(p)
            print(f"{Path(p).name}: encoder_interpolation {fam:.3f} s CPU over {n} calls; identify {total:.2f} s CPU")
    print(f"load average {os.getloadavg()[0]:.2f}; rerun: python benchmarks/ident_encoder_cost.py [LOG ...]")
    return 0


if __name__ == "__main__":
    sys.exit(main())
