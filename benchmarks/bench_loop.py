"""Benchmark: DCDIARC step cost and the 5 kHz servo loop on the simulated gantry.

Rerun:  python benchmarks/bench_loop.py [--config configs/gantry.yaml] [--seconds 60] [--steps 50000]

Part 1, step cost: each axis's controllers (C1, C2, and the PID+FF where the axis configures
``pid:``) run in closed loop with the simulated plant for --steps samples of its program; only
``controller.update()`` is timed (perf_counter_ns around each call, so the figure includes the
Python→kernel dispatch).
Part 2, the loop: ``motorctl run`` with both axes on C2 against the wall clock for --seconds,
once with SCHED_FIFO + mlockall (policy required) and once without (policy off); turnaround
(read start → write end, including the plant's RK4 in the simulated driver's write), wake
lateness and overruns. The machine is shared and noisy: compare medians and ratios taken in
one run.
"""

from __future__ import annotations

import argparse
import platform
import time

import numpy as np

from motorctl.app.job import run_job
from motorctl.config import load_config
from motorctl.control import configured_controllers, make_controller
from motorctl.loop.rt import RealtimeError


def step_cost(loaded, axis: str, kind: str, steps: int) -> np.ndarray:
    ts = loaded.period_s
    drv = loaded.make_driver([axis])
    ctrl = make_controller(loaded.axes[axis].controller, kind, ts)
    prog = loaded.axes[axis].trajectory.program()
    u = np.zeros(1)
    en = np.ones(1, dtype=bool)
    out = np.empty(steps, dtype=np.int64)
    clock = time.perf_counter_ns
    for k in range(steps):
        drv.read()
        xd, vd, ad = prog.sample(k * ts)
        y = float(drv.position_m[0])
        t0 = clock()
        u[0] = ctrl.update(y, xd, vd, ad)
        out[k] = clock() - t0
        drv.write(u, en)
    return out / 1e3


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default="configs/gantry.yaml")
    ap.add_argument("--seconds", type=float, default=60.0)
    ap.add_argument("--steps", type=int, default=50000)
    args = ap.parse_args()
    loaded = load_config(args.config)
    print(f"# motorctl loop benchmark on {platform.node()} ({platform.processor() or platform.machine()}), "
          f"python {platform.python_version()}, {time.strftime('%Y-%m-%d %H:%M:%S')}")
    print(f"# rerun: python benchmarks/bench_loop.py --config {args.config} --seconds {args.seconds:g} --steps {args.steps}")
    print("\n## controller step cost (us per axis, closed loop on the simulated plant)")
    print(f"{'axis':4} {'ctrl':4} {'median':>8} {'p99':>8} {'max':>8}")
    med = {}
    for axis in loaded.axes:
        kinds = [k for k in ("c1", "c2", "pid") if k in configured_controllers(loaded.axes[axis].controller)]
        for kind in kinds:
            c = step_cost(loaded, axis, kind, args.steps)
            med[axis, kind] = np.median(c)
            print(f"{axis:4} {kind:4} {np.median(c):8.2f} {np.percentile(c, 99):8.2f} {c.max():8.1f}")
        print(f"{axis:4} C2/C1 median ratio {med[axis, 'c2'] / med[axis, 'c1']:.2f} "
              f"(paper's dSPACE: 14 us / 10 us = 1.40)")
        if "pid" in kinds:
            print(f"{axis:4} PID/C2 median ratio {med[axis, 'pid'] / med[axis, 'c2']:.2f}")
    print(f"\n## {args.seconds:g} s wall-clock loop at {loaded.cfg.loop.rate_hz:g} Hz, axes {', '.join(loaded.axes)} on C2")
    for policy in ("required", "off"):
        label = "SCHED_FIFO + mlockall" if policy == "required" else "SCHED_OTHER"
        try:
            res = run_job(loaded, controller="c2", duration_s=args.seconds, clock="wall", realtime_policy=policy)
        except RealtimeError as exc:
            print(f"{label}: not available here ({exc})")
            continue
        tm = res.timing
        print(f"{label:22}: turnaround p50 {tm['turnaround_p50_us']:.1f} p99 {tm['turnaround_p99_us']:.1f} "
              f"p99.9 {tm['turnaround_p999_us']:.1f} max {tm['turnaround_max_us']:.1f} us | lateness p50 "
              f"{tm['lateness_p50_us']:.1f} p99 {tm['lateness_p99_us']:.1f} max {tm['lateness_max_us']:.1f} us | "
              f"overruns {tm['overruns']} in {tm['cycles']} cycles")


if __name__ == "__main__":
    main()
