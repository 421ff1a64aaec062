"""Per transport on loopback: round trip of one exchange (median / p99) and the loop rate
actually sustained with two axes, each against ``motorctl emulate`` in its own process.

    python benchmarks/bench_transports.py [--transports serial,can,canopen,modbus,ethercat]
                                          [--exchanges 3000] [--cycles 4000]

* serial: pyserial ``socket://127.0.0.1:PORT``; modbus: Modbus TCP on 127.0.0.1 (pymodbus
  framer, FC23); can and canopen (CiA 402 drives: RPDOs + SYNC out, TPDOs back): python-can
  ``udp_multicast`` inside a private network namespace (needs root: unshare/nsenter), the
  measuring process runs in the namespace too; ethercat: raw EtherCAT frames (pysoem/SOEM) on a
  veth pair inside a private network namespace, a CiA 402 drive and the I/O terminals of
  configs/gantry-ethercat.yaml (SM-synchronous, one frame per cycle for both axes).
* round trip: ``write()`` (0 V, amplifier off, one period of plant) then ``read()`` polling for
  the answer, timed from the send to the decoded answer; the emulator runs at SCHED_FIFO 90,
  the measuring process at normal priority.
* sustained rate: the C2 servo loop on both axes of configs/gantry-<t>.yaml, clock unpaced
  (each cycle waits for its answer, read timeout 20 ms), ``--cycles`` cycles: cycles / wall
  time, with the read errors seen (should be 0).

The figures depend on the machine's load; they go into ``round_trip_s`` of the configs.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def inner(config: str, exchanges: int, cycles: int) -> dict:
    """Measure in this process against an emulator that is already serving ``config``."""
    import gc

    from motorctl.app.job import run_job
    from motorctl.config import load_config
    loaded = load_config(config, check_budget=False)
    drv = loaded.make_driver()
    drv.timeout_s = 0.02
    drv.open()
    n = len(drv.axis_names)
    u, en = np.zeros(n), np.zeros(n, dtype=bool)
    rt = np.empty(exchanges)
    gc.collect()
    gc.disable()
    clock = time.perf_counter
    try:
        for k in range(exchanges):
            t0 = clock()
            drv.write(u, en)
            drv.read()
            rt[k] = clock() - t0
    finally:
        gc.enable()
        drv.close()
    errors = dict(drv.counters)
    # the servo loop, unpaced: every cycle waits for its answer
    import motorctl.config as mc
    made = []
    orig = mc.LoadedConfig.make_driver

    def keep(self, names=None):
        d = orig(self, names)
        d.timeout_s = 0.02
        made.append(d)
        return d
    mc.LoadedConfig.make_driver = keep
    try:
        t0 = time.perf_counter()
        res = run_job(loaded, controller="c2", duration_s=cycles * loaded.period_s, clock="virtual")
        wall = time.perf_counter() - t0
    finally:
        mc.LoadedConfig.make_driver = orig
    return {"rt_median_us": float(np.median(rt) * 1e6), "rt_p99_us": float(np.percentile(rt, 99) * 1e6),
            "rt_p999_us": float(np.percentile(rt, 99.9) * 1e6), "rt_errors": errors,
            "loop_cycles": res.cycles, "loop_wall_s": wall, "loop_rate_hz": res.cycles / wall,
            "loop_io_errors": {a: r["io_errors"] for a, r in res.axes.items()},
            "loop_faults": {a: r["fault"] for a, r in res.axes.items()},
            "driver": made[-1].describe() if made else {}}


def measure(transport: str, tmp: Path, exchanges: int, cycles: int) -> dict:
    from motorctl_emulators.loopback import Emulator, NetNamespace, loopback_config
    driver = {"round_trip_s": 0.0}
    veth = None
    if transport == "ethercat":
        veth = ("ecb0", "ecb0-slave")
        driver.update(ifname=veth[0], watchdog_ms=1000.0)
    _, cfg = loopback_config(ROOT / "configs" / f"gantry-{transport}.yaml", tmp, rate_hz=1000, driver=driver)
    plant = ROOT / "configs" / "gantry.yaml"
    # EtherCAT's watchdog is the slaves' SM watchdog the driver sets (watchdog_ms), not --watchdog
    emulator = dict(plant=plant) if transport == "ethercat" else dict(plant=plant, watchdog_s=1.0)
    cmd = [sys.executable, __file__, "--inner", str(cfg), "--exchanges", str(exchanges),
           "--cycles", str(cycles)]
    if transport in ("can", "canopen", "ethercat"):
        with NetNamespace(veth=veth) as ns, Emulator(transport, cfg, prefix=ns.prefix, **emulator):
            out = subprocess.run([*ns.prefix, *cmd], capture_output=True, text=True, timeout=300)
    else:
        with Emulator(transport, cfg, **emulator):
            out = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    if out.returncode != 0:
        raise RuntimeError(f"{transport}: {out.stderr.strip()[-2000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--transports", default="serial,can,canopen,modbus,ethercat")
    ap.add_argument("--exchanges", type=int, default=3000)
    ap.add_argument("--cycles", type=int, default=4000)
    ap.add_argument("--inner", help=argparse.SUPPRESS)
    ap.add_argument("--json", action="store_true", help="print the figures as JSON")
    a = ap.parse_args()
    if a.inner:
        print(json.dumps(inner(a.inner, a.exchanges, a.cycles)))
        return 0
    results = {}
    with tempfile.TemporaryDirectory() as tmp:
        for t in a.transports.split(","):
            results[t] = measure(t, Path(tmp), a.exchanges, a.cycles)
    if a.json:
        print(json.dumps(results))
        return 0
    print(f"loopback, {a.exchanges} exchanges and {a.cycles} loop cycles per transport "
          f"(emulator at SCHED_FIFO 90, load average {open('/proc/loadavg').read().split()[0]})")
    print(f"{'transport':10} {'rt median us':>12} {'rt p99 us':>10} {'rt p99.9 us':>11} "
          f"{'2-axis loop Hz':>14} {'loop read errors':>16}")
    for t, r in results.items():
        print(f"{t:10} {r['rt_median_us']:12.1f} {r['rt_p99_us']:10.1f} {r['rt_p999_us']:11.1f} "
              f"{r['loop_rate_hz']:14.0f} {sum(r['loop_io_errors'].values()):16d}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
