"""Benchmark: how many axes one core carries at 5 kHz. The simulated gantry's X axis (C2, its
program, its plant) copied to 1, 2, 4, 8 and 16 axes, each count run by ``motorctl run``'s job for
--seconds against the wall clock on one CPU, SCHED_FIFO where it is granted; beside them, in the
same run, the floor of the machine: a loop that only wakes at the same deadlines (sleep, then the
same spin tail as the servo loop) and reads the clock.

Rerun:  python benchmarks/bench_scale.py [--config configs/gantry.yaml] [--seconds 10] [--cpu 1]
        [--axes 1 2 4 8 16] [--spin-us 1000] [--warm-caches on|off|both] [--cpu-latency-us N|none]

Prints per axis count, with and without ``loop.realtime.warm_caches`` (the next cycle rehearsed
on copies in the spin tail): turnaround p50 / p99 / p99.9 / max [µs] per cycle and p50 per axis,
wake lateness p99, overruns; and the floor's lateness and overruns. The turnaround includes the
simulated plant (RK4 with substeps), which a real drive does not cost the host. The machine is
shared and noisy: compare the rows of one run.

``--spin-us`` at least the period (200 µs at 5 kHz) makes a polling loop that never sleeps, as on
a CPU given to the loop alone: its caches stay warm between cycles. A SCHED_FIFO task that never
sleeps meets the kernel's real-time throttling (``/proc/sys/kernel/sched_rt_runtime_us``, by
default 950000 of every 1000000 µs): it misses 50 ms every second unless that is set to -1, as
a real-time deployment does.
"""

from __future__ import annotations

import argparse
import copy
import os
import platform
import time

import numpy as np

from motorctl.app.job import run_job
from motorctl.config import config_from_dict, load_yaml
from motorctl.loop.rt import RealtimeError, restore, setup_realtime


def axes_config(base: dict, n: int, seconds: float, cpu: int) -> dict:
    """``base`` with its first axis copied to ``n`` axes (A0..A{n-1}, same program and plant)."""
    d = copy.deepcopy(base)
    first = next(iter(d["axes"].values()))
    d["axes"] = {f"A{i}": copy.deepcopy(first) for i in range(n)}
    d["loop"]["duration_s"] = seconds
    d["loop"]["clock"] = "wall"
    d["loop"]["realtime"].update(policy="best_effort", cpu=cpu)
    return d


def floor(seconds: float, period_ns: int, spin_us: float, cpu: int, latency_us: int | None) -> dict:
    """The machine's floor: wake at each deadline (sleep, then spin the last ``spin_us``), read
    the clock, nothing else, with the loop's real-time set-up (its CPU latency request
    ``latency_us`` included); lateness percentiles [µs] and whole periods missed."""
    try:
        setup_realtime("best_effort", 80, cpu, True, cpu_latency_us=latency_us)
        n = int(seconds * 1e9 / period_ns)
        late = np.empty(n, dtype=np.int64)
        mono, sleep, spin = time.monotonic_ns, time.sleep, int(spin_us * 1e3)
        deadline = mono() + period_ns
        missed = 0
        for k in range(n):
            rem = deadline - mono() - spin
            if rem > 0:
                sleep(rem * 1e-9)
            while mono() < deadline:
                pass
            late[k] = mono() - deadline
            if late[k] >= period_ns:
                missed += late[k] // period_ns
                deadline += (late[k] // period_ns) * period_ns
            deadline += period_ns
    finally:
        restore()
    la = late / 1e3
    return {"lateness_p50_us": float(np.percentile(la, 50)), "lateness_p99_us": float(np.percentile(la, 99)),
            "lateness_max_us": float(la.max()), "overruns": int(missed)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default="configs/gantry.yaml")
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--cpu", type=int, default=(os.cpu_count() or 1) - 1)
    ap.add_argument("--axes", type=int, nargs="+", default=[1, 2, 4, 8, 16])
    ap.add_argument("--spin-us", type=float, default=None,
                    help="loop.realtime.spin_us (default: the config's; at least the period: a polling loop)")
    ap.add_argument("--cpu-latency-us", default=None,
                    help="loop.realtime.cpu_latency_us of the loop and the floor: N [us] or 'none' "
                         "(default: the config's)")
    ap.add_argument("--warm-caches", choices=("on", "off", "both"), default="both",
                    help="loop.realtime.warm_caches of the rows (default both: each count with and without)")
    a = ap.parse_args()
    base = load_yaml(a.config)
    if a.spin_us is not None:
        base["loop"].setdefault("realtime", {})["spin_us"] = a.spin_us
    if a.cpu_latency_us is not None:
        base["loop"].setdefault("realtime", {})["cpu_latency_us"] = (
            None if a.cpu_latency_us == "none" else int(a.cpu_latency_us))
    rate = float(base["loop"].get("rate_hz", 5000.0))
    print(f"# motorctl scale benchmark on {platform.node()}, python {platform.python_version()}, "
          f"{time.strftime('%Y-%m-%d %H:%M:%S')}; {rate:g} Hz, {a.seconds:g} s per row, CPU {a.cpu}")
    print(f"# rerun: python benchmarks/bench_scale.py --config {a.config} --seconds {a.seconds:g} --cpu {a.cpu} "
          f"--axes {' '.join(map(str, a.axes))}" + (f" --spin-us {a.spin_us:g}" if a.spin_us is not None else "")
          + (f" --cpu-latency-us {a.cpu_latency_us}" if a.cpu_latency_us is not None else ""))
    print("axes | warm caches | turnaround p50 / p99 / p99.9 / max us | p50 per axis us | lateness p99 us | "
          "overruns | realtime")
    for n in a.axes:
        for warm in ((True, False) if a.warm_caches == "both" else (a.warm_caches == "on",)):
            d = axes_config(base, n, a.seconds, a.cpu)
            d["loop"]["realtime"]["warm_caches"] = warm
            loaded = config_from_dict(d, f"{a.config} x{n}")
            try:
                res = run_job(loaded, clock="wall")
            except RealtimeError as exc:
                print(f"{n:4d} | refused: {exc}")
                continue
            tm = res.timing
            rt = ", ".join(k for k, v in res.realtime.items() if v["obtained"])
            print(f"{n:4d} | {'on' if warm else 'off':11} | {tm['turnaround_p50_us']:.1f} / {tm['turnaround_p99_us']:.1f} / "
                  f"{tm['turnaround_p999_us']:.1f} / {tm['turnaround_max_us']:.1f} | "
                  f"{tm['turnaround_p50_us'] / n:.1f} | {tm['lateness_p99_us']:.1f} | {tm['overruns']} | {rt}")
    spin = float(base["loop"].get("realtime", {}).get("spin_us", 60))
    f = floor(a.seconds, int(round(1e9 / rate)), spin, a.cpu, loaded.cfg.loop.realtime.cpu_latency_us)
    print(f"floor (wake, read the clock): lateness p50 {f['lateness_p50_us']:.1f} / p99 {f['lateness_p99_us']:.1f} / "
          f"max {f['lateness_max_us']:.1f} us, overruns {f['overruns']}")


if __name__ == "__main__":
    main()
