"""Benchmark: the law's step cost, the compiled cycle, and the 5 kHz servo loop on the simulated gantry.

Rerun:  python benchmarks/bench_loop.py [--config configs/gantry.yaml] [--seconds 60] [--steps 50000]
        [--cpu N] [--slices 6] [--beside-seconds S]

Part 1, step cost: each axis's controllers (C1, C2, the PID+FF where the axis configures
``pid:``, and C2 with a compensation of cogging and Stribeck friction, ``c2+comp``) run in
closed loop with the simulated plant for --steps samples of its program. Printed first, the
step as the servo loop runs it: (b) in the compiled cycle
(motorctl/loop/cycle.py): the law's own cost, its compiled step replayed inside compiled code on
the samples of (a) (no clock per call: total / steps); (c) the whole compiled call of a cycle
(supervisor, desired(k), law, record row, and the call from Python), the record's control_ns
of a one-axis loop on the virtual clock, and of both axes. Then (a) ``controller.update()``
called from Python, as a caller outside the loop (a tool, a test) does: perf_counter_ns around
each call, so the figure includes the Python→kernel dispatch of 14 arguments, which the loop
does not pay.
Part 2, the loop: ``motorctl run``'s job with both axes on C2 against the wall clock for
--seconds, with SCHED_FIFO + mlockall (policy required) and its run log written, in --slices
turns with the machine's floor: benchmarks/floor.c (compiled here with cc), the loop's pacing
alone (sleep, spin, read the clock) at SCHED_FIFO 80 with memory locked, holding the CPU after
each wake for the loop's median turnaround; loop, floor, floor, loop, ... so that both meet the
same moments of a machine whose stalls come in bursts. Turnaround (read start → write end,
including the plant's RK4 in the simulated driver's write), overruns (whole periods missed)
and the loop thread's page faults (none after the real-time set-up's prefault: an overrun in a
turn without one is not the loop waiting on its own memory), per turn and pooled; the floor
holds the loop's CPU latency request (``loop.realtime.cpu_latency_us``) too. For the missed
periods and the overrun events (a wake one or more whole periods late, counted once: a 5 ms
stall of the VM is one event of 25 missed periods): the loop/floor ratio with a 95 % bootstrap
interval over the turns, and whether that interval decides it against 1.2×. The VM's stalls
come in bursts of seconds, so the turns, not the overruns, are the samples: six turns of 60 s
seldom decide anything; ``--seconds 300 --slices 30 --beside-seconds 0`` gives thirty. Then,
one after the other, the loop with ``loop.realtime.warm_caches`` off (no rehearsal of the next
cycle in the spin tail), without the CPU latency request (``cpu_latency_us: null``: idle CPUs
may sleep) and without SCHED_FIFO (policy off). All are pinned to ``--cpu`` (default: the last
CPU, as a deployment pins the loop to an isolated one; ``--cpu -1``: not pinned). The machine is
shared and noisy: compare medians and ratios taken in one run.
"""

from __future__ import annotations

import argparse
import os
import platform
import time
import warnings

import numpy as np

from motorctl.app.job import run_job
from motorctl.config import config_from_dict, load_config, load_yaml
from motorctl.control import configured_controllers, make_controller
from motorctl.loop.rt import RealtimeError


#: the compensation of the "c2+comp" rows: what identify writes for cogging and a Stribeck
#: friction (fixed terms, evaluated in the compiled cycle)
COMPENSATION = {"cogging": {"period_m": 0.032, "sin_V": [0.14, 0.03], "cos_V": [0.04, 0.04]},
                "stribeck": {"force_V": 0.05, "velocity_m_per_s": 0.01}}


def variants(loaded, loaded_comp, axis: str) -> list:
    """The rows of one axis: (label, config, controller kind): C1, C2, PID+FF where the axis
    configures it, and C2 with :data:`COMPENSATION`."""
    kinds = [k for k in ("c1", "c2", "pid") if k in configured_controllers(loaded.axes[axis].controller)]
    return [(k, loaded, k) for k in kinds] + [("c2+comp", loaded_comp, "c2")]


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
        u[0] = ctrl.update(y, xd, vd, ad, k * ts)
        out[k] = clock() - t0
        drv.write(u, en)
    return out / 1e3


def replayed_law_cost(loaded, axis: str, kind: str, steps: int) -> float:
    """(b): the compiled step of ``kind`` on samples of its own closed loop, inside compiled code
    [µs per step]; NaN for a law without a compiled step."""
    from motorctl.control.kernels import LAW_PY, N_LAYOUT, law_step
    from motorctl.jit import njit
    from motorctl.loop.records import N_SIGNALS
    ts = loaded.period_s
    drv = loaded.make_driver([axis])
    ctrl = make_controller(loaded.axes[axis].controller, kind, ts)
    if ctrl.law_code == LAW_PY:
        return float("nan")
    prog = loaded.axes[axis].trajectory.program()
    smp = np.empty((steps, 4))
    u = np.zeros(1)
    en = np.ones(1, dtype=bool)
    for k in range(steps):
        drv.read()
        xd, vd, ad = prog.sample(k * ts)
        y = float(drv.position_m[0])
        smp[k] = (y, xd, vd, ad)
        u[0] = ctrl.update(y, xd, vd, ad, k * ts)
        drv.write(u, en)
    fresh = make_controller(loaded.axes[axis].controller, kind, ts)
    nf, ni = fresh.state_size()
    sig, f, ii, lay = np.zeros(N_SIGNALS), np.zeros(nf), np.zeros(max(ni, 1), dtype=np.int64), \
        np.zeros(N_LAYOUT, dtype=np.int64)
    fresh.attach(sig, f, ii, lay)
    fresh.reset(float(smp[0, 0]))

    @njit
    def replay(law, smp, ts, sig, f, ii, lay):
        s = 0.0
        for k in range(smp.shape[0]):   # (no preview: the benchmark's compensation has no delay)
            y, xd, vd, ad = smp[k, 0], smp[k, 1], smp[k, 2], smp[k, 3]
            s += law_step(law, y, xd, vd, ad, xd, vd, ad, k * ts, sig, f, ii, lay)
        return s
    replay(fresh.law_code, smp[:10], ts, sig.copy(), f.copy(), ii.copy(), lay)        # compile
    t0 = time.perf_counter_ns()
    replay(fresh.law_code, smp, ts, sig, f, ii, lay)
    return (time.perf_counter_ns() - t0) / 1e3 / steps


def cycle_cost(loaded, axes: list, kind: str, steps: int) -> np.ndarray:
    """(c): the compiled call of each cycle [µs] (the record's control_ns), virtual clock."""
    from motorctl.app.build import build, shutdown, start
    asm = build(loaded, axes, kind, clock="virtual", capacity=steps)
    start(asm, "off")
    try:
        asm.loop.run(steps)
    finally:
        shutdown(asm)
    return asm.loop.rows()[:, asm.loop.layout.index("control_ns")] / 1e3


def build_floor(tmp: str) -> str:
    """Compile benchmarks/floor.c into ``tmp``; the executable's path."""
    import subprocess
    src = os.path.join(os.path.dirname(os.path.abspath(__file__)), "floor.c")
    exe = os.path.join(tmp, "floor")
    subprocess.run(["cc", "-O2", "-o", exe, src], check=True)
    return exe


def machine_floor(exe: str, seconds: float, period_ns: int, spin_us: float, cpu: int | None,
                  work_ns: int = 0, hold_file: str | None = None, latency_us: int | None = None) -> str:
    """The compiled floor for ``seconds`` on ``cpu`` (None: not pinned), holding the CPU
    ``work_ns`` after each wake, and the loop's PM QoS CPU latency request ``latency_us`` (None:
    none): its printed line (every hold [ns] into ``hold_file``)."""
    import subprocess
    n = int(seconds * 1e9 / period_ns)
    argv = [exe, str(period_ns), str(n), str(int(spin_us * 1e3)), str(-1 if cpu is None else cpu), str(work_ns),
            hold_file or "-", str(-1 if latency_us is None else latency_us)]
    return subprocess.run(argv, capture_output=True, text=True, check=True).stdout.strip()


def in_turn(loaded, exe: str, seconds: float, slices: int, cpu: int | None, spin_us: float, tmp: str) -> None:
    """The loop (``motorctl run``'s job, both axes on C2, SCHED_FIFO + mlockall, its log
    written) and the floor holding the CPU for the loop's median turnaround, in ``slices``
    turns of seconds/slices each, in the order loop-floor, floor-loop, ... so that both see
    the same machine: the VM's stalls come in bursts of seconds, and two runs one after the
    other compare two moments of it. Prints each turn and the pooled figures."""
    from motorctl.recorder.runlog import read_log
    period_ns = int(round(1e9 / loaded.cfg.loop.rate_hz))
    part = seconds / slices
    turn, hold, ovr, missed, faults, work_ns = [], [], [], [], [], 0
    ev_loop, ev_floor = [], []                     # overrun events: wakes one or more periods late
    print(f"{'turn':>4} {'loop overruns':>14} {'floor overruns':>15} {'loop turnaround p99.9':>22} "
          f"{'floor hold p99.9':>17} us {'loop page faults':>17}")

    def loop_part(r):
        log = os.path.join(tmp, f"turn{r}.mclog")
        res = run_job(loaded, controller="c2", duration_s=part, clock="wall", log_path=log,
                      realtime_policy="required")
        rl = read_log(log)
        turn.append(rl.col("turnaround_ns") / 1e3)
        ovr.append(res.timing["overruns"])
        faults.append(res.timing["page_faults"])
        cum = rl.col("overruns")                   # missed periods so far, per cycle
        ev_loop.append(int(np.count_nonzero(np.diff(cum, prepend=0.0) > 0)))
        os.unlink(log)

    def floor_part(r):
        f = os.path.join(tmp, f"hold{r}.bin")
        line = machine_floor(exe, part, period_ns, spin_us, cpu, work_ns, f,
                             loaded.cfg.loop.realtime.cpu_latency_us)
        missed.append(int(line.split()[4]))
        ev_floor.append(int(line.split("events=")[1].split()[0]))
        hold.append(np.fromfile(f, dtype=np.int64) / 1e3)
        os.unlink(f)

    for r in range(slices):
        if r % 2 == 0:
            loop_part(r)
            work_ns = work_ns or int(np.median(turn[0]) * 1e3)
            floor_part(r)
        else:
            floor_part(r)
            loop_part(r)
        print(f"{r + 1:4d} {ovr[-1]:14d} {missed[-1]:15d} {np.percentile(turn[-1], 99.9):22.1f} "
              f"{np.percentile(hold[-1], 99.9):17.1f}    {faults[-1]:17d}")
    t, h = np.concatenate(turn), np.concatenate(hold)
    print(f"{'loop, pooled':22}: turnaround p50 {np.median(t):.1f} p99 {np.percentile(t, 99):.1f} p99.9 "
          f"{np.percentile(t, 99.9):.1f} max {t.max():.1f} us | overruns {sum(ovr)} in {len(t)} cycles | "
          f"page faults {sum(faults)}")
    print(f"{'floor, pooled':22}: holding the CPU {work_ns / 1e3:.1f} us after each wake: p50 {np.median(h):.1f} "
          f"p99 {np.percentile(h, 99):.1f} p99.9 {np.percentile(h, 99.9):.1f} max {h.max():.1f} us | "
          f"overruns {sum(missed)} in {len(h)} cycles")
    print(turns_ratio("missed periods", ovr, missed))
    print(turns_ratio("overrun events", ev_loop, ev_floor))


def turns_ratio(what: str, loop: list, floor: list, limit: float = 1.2) -> str:
    """The loop's total of ``what`` against the floor's, over turns run in pairs (``loop[r]`` and
    ``floor[r]`` back to back), with a 95 % percentile bootstrap interval that resamples the
    pairs (``scipy.stats.bootstrap``, paired, a fixed seed: the same counts give the same line).

    The turns, not the single overruns, are what can be resampled: the VM's stalls come in
    bursts of seconds, so the counts of one turn are neither independent events (a 4 ms stall is
    one late wake worth 20 missed periods) nor drawn at a constant rate through a run, and an
    interval that assumes either is too narrow. Returns a line with the ratio, its interval and
    whether the interval decides ``ratio <= limit``; with fewer than three pairs, no interval."""
    from scipy.stats import bootstrap
    a, b = np.asarray(loop, dtype=float), np.asarray(floor, dtype=float)
    head = f"{what + ', loop / floor':22}: {a.sum():.0f} / {b.sum():.0f}"
    if b.sum() == 0:
        return f"{head}: the floor had none"
    est = a.sum() / b.sum()
    if len(a) < 3:
        return f"{head}: ratio {est:.2f}x (too few turns for an interval)"

    def ratio(x, y, axis=-1):
        return x.sum(axis=axis) / y.sum(axis=axis)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")           # resamples with no floor overruns: handled below
        ci = bootstrap((a, b), ratio, paired=True, vectorized=True, method="percentile", n_resamples=20000,
                       random_state=np.random.default_rng(0)).confidence_interval
    lo, hi = ci.low, ci.high
    if not (np.isfinite(lo) and np.isfinite(hi)):
        return f"{head}: ratio {est:.2f}x (no interval: resamples with no floor overruns)"
    verdict = (f"<= {limit:g}x decided" if hi <= limit else f"> {limit:g}x decided" if lo > limit
               else f"{limit:g}x inside the interval: this run does not decide it")
    return (f"{head}: ratio {est:.2f}x, 95% interval {lo:.2f}-{hi:.2f}x (bootstrap over the {len(a)} turns): "
            f"{verdict}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default="configs/gantry.yaml")
    ap.add_argument("--seconds", type=float, default=60.0)
    ap.add_argument("--steps", type=int, default=50000)
    ap.add_argument("--cpu", type=int, default=(os.cpu_count() or 1) - 1,
                    help="CPU of the wall-clock loop and the floor (default: the last; -1: not pinned)")
    ap.add_argument("--spin-us", type=float, default=None,
                    help="loop.realtime.spin_us of the wall-clock loop and the floor (default: the config's; "
                         "at least the period: the loop never sleeps, a polling loop on a dedicated CPU)")
    ap.add_argument("--slices", type=int, default=6,
                    help="turns of the loop and the floor in turn over --seconds (1: one run of each)")
    ap.add_argument("--beside-seconds", type=float, default=None,
                    help="length of each of the three runs beside the turns (default: --seconds; 0: none)")
    args = ap.parse_args()
    if args.slices < 1 or args.seconds / args.slices < 1.0:
        ap.error("--slices must be at least 1, with --seconds / --slices at least 1 s")
    loaded = load_config(args.config)
    cpu = None if args.cpu < 0 else args.cpu
    raw = load_yaml(args.config)
    raw["loop"].setdefault("realtime", {})["cpu"] = cpu
    if args.spin_us is not None:
        raw["loop"]["realtime"]["spin_us"] = args.spin_us
    pinned = config_from_dict(raw, args.config)
    raw["loop"]["realtime"]["warm_caches"] = False
    pinned_cold = config_from_dict(raw, f"{args.config} without warm_caches")
    raw["loop"]["realtime"].update(warm_caches=True, cpu_latency_us=None)
    pinned_no_qos = config_from_dict(raw, f"{args.config} without a CPU latency request")
    spin_us = pinned.cfg.loop.realtime.spin_us
    raw = load_yaml(args.config)
    for axis in raw["axes"]:
        raw["axes"][axis]["controller"]["compensation"] = COMPENSATION
    loaded_comp = config_from_dict(raw, f"{args.config} with the benchmark's compensation")
    print(f"# motorctl loop benchmark on {platform.node()} ({platform.processor() or platform.machine()}), "
          f"python {platform.python_version()}, {time.strftime('%Y-%m-%d %H:%M:%S')}")
    print(f"# rerun: python benchmarks/bench_loop.py --config {args.config} --seconds {args.seconds:g} --steps {args.steps} "
          f"--cpu {args.cpu} --slices {args.slices}" + (f" --spin-us {args.spin_us:g}" if args.spin_us is not None else "")
          + (f" --beside-seconds {args.beside_seconds:g}" if args.beside_seconds is not None else ""))
    print("\n## the controller step as the servo loop runs it (us per axis): (b) the law's own step inside the compiled "
          "cycle, (c) the compiled call of a cycle, one axis")
    print(f"{'axis':4} {'ctrl':7} {'law':>8} {'call p50':>9} {'call p99':>9}")
    for axis in loaded.axes:
        for label, cfg, kind in variants(loaded, loaded_comp, axis):
            law = replayed_law_cost(cfg, axis, kind, args.steps)
            c = cycle_cost(cfg, [axis], kind, args.steps)
            print(f"{axis:4} {label:7} {law:8.2f} {np.median(c):9.2f} {np.percentile(c, 99):9.2f}")
    c = cycle_cost(loaded, list(loaded.axes), "c2", args.steps)
    print(f"all axes ({', '.join(loaded.axes)}) on c2: call p50 {np.median(c):.2f} p99 {np.percentile(c, 99):.2f} us")
    print("\n## (a) controller.update() called from Python, for a caller outside the loop (us per axis, closed loop "
          "on the simulated plant)")
    print(f"{'axis':4} {'ctrl':7} {'median':>8} {'p99':>8} {'max':>8}")
    med = {}
    for axis in loaded.axes:
        for label, cfg, kind in variants(loaded, loaded_comp, axis):
            c = step_cost(cfg, axis, kind, args.steps)
            med[axis, label] = np.median(c)
            print(f"{axis:4} {label:7} {np.median(c):8.2f} {np.percentile(c, 99):8.2f} {c.max():8.1f}")
        print(f"{axis:4} C2/C1 median ratio {med[axis, 'c2'] / med[axis, 'c1']:.2f} "
              f"(paper's dSPACE: 14 us / 10 us = 1.40)")
        if (axis, "pid") in med:
            print(f"{axis:4} PID/C2 median ratio {med[axis, 'pid'] / med[axis, 'c2']:.2f}")
    print(f"\n## {args.seconds:g} s wall-clock loop at {loaded.cfg.loop.rate_hz:g} Hz, axes {', '.join(loaded.axes)} on C2"
          f"{'' if cpu is None else f', CPU {cpu}'}, spin {spin_us:g} us"
          f"{' (never sleeps: polling)' if spin_us * 1e-6 >= pinned.period_s else ''}")
    import tempfile
    with tempfile.TemporaryDirectory() as tmp:
        try:
            exe = build_floor(tmp)
        except (OSError, ValueError) as exc:
            exe = None
            print(f"floor: not built ({exc})")
        print(f"### the loop and the floor in turn ({args.slices} turns of {args.seconds / args.slices:g} s each; "
              "SCHED_FIFO 80 + mlockall, warm caches, the run log written)")
        try:
            if exe is not None:
                in_turn(pinned, exe, args.seconds, args.slices, cpu, spin_us, tmp)
        except RealtimeError as exc:
            print(f"not available here ({exc})")
    beside = args.seconds if args.beside_seconds is None else args.beside_seconds
    if beside <= 0:
        return
    print(f"### beside them, {beside:g} s each, one after the other")
    for policy, cfg, label in (("required", pinned_cold, "warm_caches off"),
                               ("required", pinned_no_qos, "cpu_latency_us null"), ("off", pinned, "SCHED_OTHER")):
        try:
            res = run_job(cfg, controller="c2", duration_s=beside, clock="wall", realtime_policy=policy)
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
