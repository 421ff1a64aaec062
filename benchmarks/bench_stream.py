"""Commanded motion streaming end to end in one process, on the loop's virtual clock: the I/O
side's filler (motorctl.app.daemon.motion_side.MotionSide) feeding the setpoint ring, and the
loop's own compiled stream step (motorctl.loop.stream.stream_step) taking one row a cycle.

    python benchmarks/bench_stream.py [--program configs/cam_sample.ngc] [--override 1.0]
                                      [--hold-at-s T]

* the program is read with the gantry's machine words mapped (M3/M5 → output ``torch``, S
  ignored), planned from (0, 0) with the limits of configs/gantry.yaml, and streamed: the filler
  runs every FILL_EVERY_S of cycles (its period in the daemon), the loop step every cycle;
  ``--hold-at-s`` holds there and resumes 0.5 s later (the ring rewritten at once);
* filler CPU: ``time.thread_time`` around each filler call (this thread's CPU only: other
  processes' load does not count): per row streamed, as a share of the motion's duration (the
  filler's load on a core in the daemon), and the worst call;
* underruns: the loop's own counter (the ring empty while moving: a jerk-limited stop);
* contour error: the distance of every streamed setpoint (x_d per cycle) from the programmed
  path (motorctl.motion.path.contour_error; G64 P0.01 allows 10 µm of corner rounding),
  maximum and p99;
* the outputs set by the machine words, counted, with the largest speed of the setpoint at
  their row (0: set at rest, as M3/M5 stop the motion first).

The figures are this process's; they depend on the machine (not its load, except the wall time).

``--wall SECONDS`` measures instead the lead the filler needs on this host as it is loaded now:
the filler thread runs as in the daemon (``MotionSide.start``, waking every FILL_EVERY_S of wall
time, ``--lead`` seconds ahead, default 2), and a forked consumer process takes the rows at the
loop's rate by the wall clock (as a real-time loop would, whatever the load), recording how far
ahead the ring was at worst. The lead used up at worst (lead − least depth) is the longest the
filler fell behind; a lead must exceed it. Load the host as you want to judge it, e.g. two
spinners: ``for i in 1 2; do timeout 60 sh -c 'while :; do :; done' & done``.
"""

from __future__ import annotations

import argparse
import os
import struct
import time
from pathlib import Path

import numpy as np

from motorctl.app.daemon import motion_side as M
from motorctl.loop.cycle import STREAM
from motorctl.loop.stream import SP_UNDERRUNS, SetpointRing, stream_step
from motorctl.loop.stream import SP_READ, SP_WRITE
from motorctl.motion import GcodeSettings, contour_error, parse
from motorctl.motion.gcode import output_names

REPO = Path(__file__).resolve().parents[1]
DT = 2e-4
LIMITS = [M.AxisLimits(2.0, 40.0, 4000.0, -0.02, 0.42), M.AxisLimits(1.0, 10.0, 1000.0, -0.02, 0.42)]
SETTINGS = GcodeSettings(axes=["X", "Y"], words={"M3": "torch", "M5": "torch", "S": "ignore"})


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--program", default=str(REPO / "configs/cam_sample.ngc"))
    ap.add_argument("--override", type=float, default=1.0)
    ap.add_argument("--hold-at-s", type=float, default=None)
    ap.add_argument("--wall", type=float, default=None, metavar="SECONDS")
    ap.add_argument("--lead", type=float, default=2.0)
    args = ap.parse_args()
    if args.wall is not None:
        return wall_lead(args)
    text = Path(args.program).read_text()
    outs, stop = output_names(SETTINGS)
    ring = SetpointRing(int(0.5 / DT), 2, shared=False, outputs=outs, stop_outputs=stop)
    ms = M.MotionSide(ring, lambda: np.zeros(4), ["X.x_d", "X.xd_dot", "Y.x_d", "Y.xd_dot"], ["X", "Y"],
                      LIMITS, lambda: np.array([STREAM, STREAM]), DT, gcode_settings=SETTINGS, lead_s=0.5)
    # the loop's per-axis arrays as the compiled cycle has them: mode, stop; x, v, a, a_max, j_max
    ax = np.zeros((2, 2), dtype=np.int64)
    ax[:, 0] = STREAM
    axf = np.zeros((2, 5))
    axf[:, 3] = [lim.a_max for lim in LIMITS]
    axf[:, 4] = [lim.j_max for lim in LIMITS]
    stream_step(ring.rows, ring.ctl, ax, axf, 0, STREAM, 1, 0, 3, DT)     # compile
    ms.set_override(args.override)
    t0 = time.perf_counter()
    info = ms.gcode(text, Path(args.program).name)
    t_plan = time.perf_counter() - t0
    every = int(round(M.FILL_EVERY_S / DT))
    n_max = int((info["duration_s"] / min(args.override, 1.0) + 5.0) / DT)
    xs = np.zeros((n_max, 2))
    cpu, worst = 0.0, 0.0
    hold_k = None if args.hold_at_s is None else int(args.hold_at_s / DT)
    wall = time.perf_counter()
    k = 0
    for k in range(n_max):
        if k == hold_k:
            ms.hold()
        if hold_k is not None and k == hold_k + int(0.5 / DT):
            ms.resume()
        if k % every == 0 or ms._rewrite:
            c0 = time.thread_time()
            ms.fill()
            ms.issue_events()
            dc = time.thread_time() - c0
            cpu += dc
            worst = max(worst, dc)
        stream_step(ring.rows, ring.ctl, ax, axf, 0, STREAM, 1, 0, 3, DT)
        xs[k] = axf[:, 0]
        if k > every and ms.idle():
            break
    wall = time.perf_counter() - wall
    n = k + 1
    prog = parse(text, Path(args.program).name, SETTINGS)
    err = contour_error(prog, xs[:n], ("X", "Y"))
    rows = ring.consumed()
    print(f"program {args.program}: {info['segments']} segments, planned {info['duration_s']:.3f} s "
          f"(parse + check + plan + override cap {t_plan * 1e3:.1f} ms), override {args.override:g}"
          + (f", hold at {args.hold_at_s:g} s for 0.5 s" if hold_k is not None else ""))
    print(f"streamed {rows} rows in {n} cycles ({n * DT:.3f} s of loop time, {wall:.2f} s wall)")
    print(f"filler CPU: {cpu / rows * 1e6:.2f} us per row, {cpu / (n * DT) * 100:.2f} % of a core, "
          f"worst call {worst * 1e3:.2f} ms (its period {M.FILL_EVERY_S * 1e3:g} ms)")
    print(f"underruns: {int(ring.ctl[SP_UNDERRUNS])}; ring rewrites (hold/resume/override): {ms.rewrites}")
    print(f"contour error of the setpoints: max {err.max() * 1e6:.2f} um, p99 {np.percentile(err, 99) * 1e6:.2f} um")
    print(f"outputs set: {len(ms.output_log)}; end at ({xs[n - 1, 0] * 1e3:.4f}, {xs[n - 1, 1] * 1e3:.4f}) mm, "
          f"program end ({prog.end[0] * 1e3:.4f}, {prog.end[1] * 1e3:.4f}) mm")


def wall_lead(args) -> None:
    """``--wall``: the least depth of the ring over ``args.wall`` s of wall time (docstring)."""
    outs, stop = output_names(SETTINGS)
    ring = SetpointRing(int(2 * args.lead / DT) + 10, 2, shared=True, outputs=outs, stop_outputs=stop)
    ms = M.MotionSide(ring, lambda: np.zeros(4), ["X.x_d", "X.xd_dot", "Y.x_d", "Y.xd_dot"], ["X", "Y"],
                      LIMITS, lambda: np.array([STREAM, STREAM]), DT, gcode_settings=SETTINGS, lead_s=args.lead)
    text = Path(args.program).read_text()
    info = ms.gcode(text, Path(args.program).name)
    while ms.fill():                                  # the whole lead, before the clock starts
        pass
    r_fd, w_fd = os.pipe()
    pid = os.fork()
    if pid == 0:                                      # the consumer: the loop's rate by the wall clock
        os.close(r_fd)
        t0 = time.monotonic()
        least, dry = float("inf"), 0
        end = min(args.wall, info["duration_s"] - 0.5)
        while (el := time.monotonic() - t0) < end:
            target = int(el / DT)
            w = int(ring.ctl[SP_WRITE])
            least = min(least, (w - target) * DT)
            if target > w:
                dry += 1
            ring.ctl[SP_READ] = min(target, w)
            time.sleep(0.001)
        os.write(w_fd, struct.pack("<dq", least, dry))
        os._exit(0)
    os.close(w_fd)
    c0 = time.process_time()
    ms.start()
    least, dry = struct.unpack("<dq", os.read(r_fd, 16))
    os.waitpid(pid, 0)
    ms.stop()
    cpu = time.process_time() - c0
    load = os.getloadavg()[0]
    print(f"program {args.program}: {info['duration_s']:.1f} s planned; lead {args.lead:g} s; "
          f"{min(args.wall, info['duration_s'] - 0.5):.1f} s of wall time, load average {load:.1f}")
    print(f"least lead left {least:.3f} s: the filler fell {args.lead - least:.3f} s behind at worst; "
          f"samples with the ring dry: {dry}; filler CPU {cpu:.2f} s")


if __name__ == "__main__":
    main()
