"""``motorctl export`` on a ~1 GB run log: peak memory and time (streamed export).

Makes a synthetic two-axis run log of about 1 GB (43 columns, ~2.9 million records, as a
daemon writes in about 10 minutes at 5 kHz) in a temporary directory, runs
``motorctl export LOG --csv OUT`` and ``--mat OUT`` each in a child process, and prints each
child's peak resident memory (``ru_maxrss`` from ``os.wait4``) and wall time; the .mat file is
checked with ``scipy.io.loadmat`` (first and last rows). Everything is deleted afterwards.

Rerun::

    python benchmarks/bench_export.py                 # ~1 GB; needs ~5 GB free in $TMPDIR
    MOTORCTL_BENCH_EXPORT_GB=0.2 python benchmarks/bench_export.py
    python benchmarks/bench_export.py --segments 4    # the same bytes as a rotated set
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time

import numpy as np

from motorctl.loop.records import columns_for
from motorctl.recorder.segments import SegmentWriter

CHUNK = 100_000


def make_log(tmp: str, gb: float, segments: int) -> tuple[str, int, int]:
    """A synthetic run (rows of a two-axis gantry, t = k Ts) of about ``gb`` GB in
    ``segments`` segments. Returns (run path, rows, columns)."""
    cols = columns_for(["X", "Y"])
    w = len(cols)
    n = int(gb * 1e9 / (8 * w))
    run = os.path.join(tmp, "motorctl-20240101T000000-1.mlog")
    seg_bytes = int(n * 8 * w / segments) + (1 << 20)
    wr = SegmentWriter(run, {"columns": cols, "axes": ["X", "Y"], "period_s": 2e-4},
                       reserve=16384, segment_bytes=seg_bytes)
    rng = np.random.default_rng(0)
    base = rng.standard_normal((CHUNK, w))
    k = 0
    while k < n:
        m = min(CHUNK, n - k)
        block = base[:m].copy()
        block[:, 0] = (k + np.arange(m)) * 2e-4
        wr.append(block, k)
        k += m
    wr.close()
    return run, n, w


def run_child(args: list[str]) -> tuple[float, float, str]:
    """(peak RSS [MB], wall time [s], stdout) of ``motorctl ARGS`` in a child process."""
    t0 = time.monotonic()
    p = subprocess.Popen([sys.executable, "-m", "motorctl", *args], stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True)
    _, status, ru = os.wait4(p.pid, 0)
    dt = time.monotonic() - t0
    out, err = p.stdout.read(), p.stderr.read()
    p.returncode = os.waitstatus_to_exitcode(status)
    if p.returncode != 0:
        raise SystemExit(f"motorctl {' '.join(args)} failed ({p.returncode}): {err.strip()}")
    return ru.ru_maxrss / 1024.0, dt, out.strip()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--gb", type=float, default=float(os.environ.get("MOTORCTL_BENCH_EXPORT_GB", "1.0")))
    ap.add_argument("--segments", type=int, default=1)
    ap.add_argument("--keep", action="store_true", help="keep the temporary directory")
    a = ap.parse_args()
    tmp = tempfile.mkdtemp(prefix="motorctl-bench-export-")
    try:
        t0 = time.monotonic()
        run, n, w = make_log(tmp, a.gb, a.segments)
        size = sum(os.path.getsize(os.path.join(tmp, f)) for f in os.listdir(tmp))
        print(f"log: {size / 1e9:.3f} GB, {n} rows x {w} columns, {a.segments} segment(s) "
              f"(made in {time.monotonic() - t0:.1f} s)")
        src = run if a.segments > 1 else run.replace(".mlog", ".0001.mlog")
        base_rss, _, _ = run_child(["--help"])
        print(f"baseline (motorctl --help): peak RSS {base_rss:.0f} MB")
        for fmt in ("mat", "csv"):
            out = os.path.join(tmp, f"out.{fmt}")
            rss, dt, line = run_child(["export", src, f"--{fmt}", out])
            print(f"export --{fmt}: peak RSS {rss:.0f} MB, {dt:.1f} s, "
                  f"{os.path.getsize(out) / 1e9:.2f} GB written ({line})")
            if fmt == "mat":
                from scipy.io import loadmat
                m = loadmat(out, variable_names=["X_y", "t", "columns"])
                assert m["t"].shape == (n, 1) and m["t"][-1, 0] == (n - 1) * 2e-4
                print(f"  loadmat: t {m['t'].shape}, {len(m['columns'])} column names: ok")
            os.unlink(out)
    finally:
        if a.keep:
            print(f"kept {tmp}")
        else:
            shutil.rmtree(tmp, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
