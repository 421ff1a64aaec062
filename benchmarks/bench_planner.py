"""The motion planner's throughput: parse, soft-limit check and plan time per segment, and the
time to fill the loop's setpoints compared with the time they cover.

    python benchmarks/bench_planner.py [--segments 10000] [--block 50] [--program FILE.ngc]

* the default program: ``--segments`` straight segments of 0.1 mm at F6000 (100 mm/s) along a
  curve of radius 110-150 mm (a CAM spline written as G1 moves; G64 P0.01), the issue's streaming
  case; ``--program`` plans another file (axes X Y, machine words M3/M5/S ignored);
* the limits of configs/gantry.yaml (X: 2 m/s, 40 m/s², 4000 m/s³; Y: 1 m/s, 10 m/s², 1000 m/s³);
* fill: ``Trajectory.sample_into`` on the 5 kHz grid, blocks of ``--block`` cycles (the I/O side's
  ring refill), over the whole program: CPU time of this process per block
  (``time.process_time``: other processes' load does not count) against the block's duration
  (fill/real ≪ 1: streaming keeps ahead of the loop), median, p99 and worst, and the wall-clock
  worst (which a loaded machine inflates);
* check: ``check_limits`` per segment.

Single process, wall clock of this machine (``time.perf_counter``), best of 3 for the one-shot
steps (wall clock); the figures depend on the machine's load.
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import numpy as np

from motorctl.motion import AxisLimits, GcodeSettings, check_limits, parse, plan

LIMITS = [AxisLimits(2.0, 40.0, 4000.0), AxisLimits(1.0, 10.0, 1000.0)]
SOFT = {"X": (-0.02, 0.42), "Y": (-0.02, 0.42)}
SETTINGS = GcodeSettings(axes=["X", "Y"], words={"M3": "ignore", "M5": "ignore", "S": "ignore"})


def curve_program(segments: int, step_mm: float = 0.1, feed_mm_min: float = 6000.0) -> str:
    """``segments`` G1 moves of ``step_mm`` along a slowly varying curve (radius 110-150 mm: the
    filters' rounding, v²(T1² + T2²)/(24 R), stays within P0.01 at F6000 there), in the stroke."""
    lines = ["%", "G17 G21 G90 G94 G64 P0.01", "G0 X210 Y40", f"G1 F{feed_mm_min:g}"]
    x, y, heading = 210.0, 40.0, 0.0
    for k in range(segments):
        radius = 130.0 + 20.0 * math.sin(2 * math.pi * k / 3000.0)
        heading += step_mm / radius
        x += step_mm * math.cos(heading)
        y += step_mm * math.sin(heading)
        lines.append(f"N{k + 10} X{x:.4f} Y{y:.4f}")
    lines += ["M2", "%"]
    return "\n".join(lines) + "\n"


def best(f, n=3):
    out, t = None, math.inf
    for _ in range(n):
        t0 = time.perf_counter()
        out = f()
        t = min(t, time.perf_counter() - t0)
    return out, t


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--segments", type=int, default=10000)
    ap.add_argument("--block", type=int, default=50, help="cycles per fill (5 kHz)")
    ap.add_argument("--program", type=Path, default=None)
    a = ap.parse_args(argv)
    text = a.program.read_text() if a.program else curve_program(a.segments)
    name = a.program.name if a.program else f"curve-{a.segments}.ngc"
    prog, t_parse = best(lambda: parse(text, name, SETTINGS))
    n = len(prog.moves)
    _, t_check = best(lambda: check_limits(prog, SOFT))
    tr, t_plan = best(lambda: plan(prog, ["X", "Y"], LIMITS))
    h = 2e-4
    blocks = int(math.ceil(tr.duration / (a.block * h)))
    out = np.empty((a.block, 3, 2))
    dts = np.empty(blocks)
    vmax = 0.0
    walls = np.empty(blocks)
    for b in range(blocks):
        w0, t0 = time.perf_counter(), time.process_time()
        tr.sample_into(b * a.block * h, h, out)
        dts[b] = time.process_time() - t0
        walls[b] = time.perf_counter() - w0
        vmax = max(vmax, float(np.hypot(out[:, 1, 0], out[:, 1, 1]).max()))
    real = a.block * h
    print(f"program {name}: {n} moves, planned duration {tr.duration:.2f} s, top path speed "
          f"{vmax * 1e3:.1f} mm/s")
    print(f"parse        {t_parse * 1e3:8.1f} ms  ({t_parse / n * 1e6:.1f} us/segment)")
    print(f"check_limits {t_check * 1e3:8.1f} ms  ({t_check / n * 1e6:.2f} us/segment)")
    print(f"plan         {t_plan * 1e3:8.1f} ms  ({t_plan / n * 1e6:.1f} us/segment; "
          f"{tr.duration / t_plan:.0f}x real time)")
    print(f"fill blocks of {a.block} cycles ({real * 1e3:.0f} ms): median {np.median(dts) * 1e6:.0f} us, "
          f"p99 {np.percentile(dts, 99) * 1e6:.0f} us, worst {dts.max() * 1e6:.0f} us; "
          f"fill/real median {np.median(dts) / real:.3f}, worst {dts.max() / real:.3f} (CPU); wall worst "
          f"{walls.max() * 1e6:.0f} us")


if __name__ == "__main__":
    main()
