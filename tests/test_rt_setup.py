"""The loop process's real-time set-up (motorctl.loop.rt): a pinned run gives the process its
CPUs back, the loop's helper processes keep off the loop's CPU, and the CPU latency request is
held while the loop runs and dropped after, and the prefault leaves the loop no copy-on-write
fault from a helper forked before it."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest
from machine import mlockall_permitted

#: (permitted, why not): the machine's own answer, before any of the product's code runs
MLOCKALL = mlockall_permitted()

PROBE = """
import json, os
from motorctl.loop.rt import keep_off, restore, setup_realtime
before = sorted(os.sched_getaffinity(0))
rep = setup_realtime("best_effort", 10, 0, lock_memory=False)
pinned = sorted(os.sched_getaffinity(0))
restore()
after = sorted(os.sched_getaffinity(0))
os.sched_setaffinity(0, {0})              # a helper forked from a pinned loop process
keep_off(0)
helper = sorted(os.sched_getaffinity(0))
print(json.dumps({"before": before, "pinned": pinned, "after": after, "helper": helper,
                  "affinity": rep.ok("affinity"), "policy": os.sched_getscheduler(0)}))
"""


@pytest.mark.skipif(len(os.sched_getaffinity(0)) < 2, reason="needs two CPUs")
def test_a_pinned_run_gives_its_cpus_back_and_a_helper_keeps_off_the_loops_cpu():
    r = subprocess.run([sys.executable, "-c", PROBE], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    got = json.loads(r.stdout)
    assert got["affinity"] and got["pinned"] == [0], got
    assert got["after"] == got["before"], got
    assert 0 not in got["helper"] and got["helper"], got
    assert got["policy"] == os.SCHED_OTHER


LATENCY_PROBE = """
import json, os, struct
from motorctl.loop.rt import CPU_DMA_LATENCY, restore, setup_realtime

def held():
    return [fd for fd in os.listdir("/proc/self/fd")
            if os.path.realpath(f"/proc/self/fd/{fd}") == CPU_DMA_LATENCY]

def value():
    with open(CPU_DMA_LATENCY, "rb") as f:
        return struct.unpack("=i", f.read(4))[0]

none = setup_realtime("off", cpu_latency_us=7)      # policy off: no request
off = {"step": "cpu_latency" in none.steps, "held": len(held())}
restore()
rep = setup_realtime("best_effort", 10, None, lock_memory=False, cpu_latency_us=7)
during = {"ok": rep.ok("cpu_latency"), "held": len(held()), "value": value()}
restore()
print(json.dumps({"off": off, "during": during, "after": len(held())}))
"""


@pytest.mark.skipif(not os.access("/dev/cpu_dma_latency", os.W_OK),
                    reason="needs a writable /dev/cpu_dma_latency (root)")
def test_the_cpu_latency_request_is_held_while_the_loop_runs_and_dropped_after():
    r = subprocess.run([sys.executable, "-c", LATENCY_PROBE], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    got = json.loads(r.stdout)
    assert got["off"] == {"step": False, "held": 0}, got
    # the kernel's target is the least of all requests held: at most ours
    assert got["during"]["ok"] and got["during"]["held"] == 1 and got["during"]["value"] <= 7, got
    assert got["after"] == 0, got


COW_PROBE = """
import json, os, resource
import numpy as np
from motorctl.loop.rt import restore, setup_realtime

PAGES = 1024

def faults():
    ru = resource.getrusage(resource.RUSAGE_THREAD)
    return ru.ru_minflt + ru.ru_majflt

def store_per_page(a):
    f0 = faults()
    a.view(np.uint8)[::4096] = 1               # one store per page
    return faults() - f0

a = np.full(PAGES * 512, 2.0)                   # written: resident, private (4 MiB each)
b = np.full(PAGES * 512, 2.0)
r, w = os.pipe()
pid = os.fork()                                 # as the run's drain, the daemon's I/O process
if pid == 0:
    os.close(w)
    os.read(r, 1)                               # holds the shared pages until the parent is done
    os._exit(0)
os.close(r)
shared = store_per_page(a)                      # copy-on-write: every first store faults
rep = setup_realtime("best_effort", 10, None, lock_memory=True, lock_pages="touched")
prefaulted = store_per_page(b)
restore()
os.close(w)
os.waitpid(pid, 0)
print(json.dumps({"shared": shared, "prefaulted": prefaulted, "mlockall": rep.ok("mlockall"),
                  "prefault": rep.steps.get("prefault")}))
"""


@pytest.mark.skipif(not MLOCKALL[0], reason=MLOCKALL[1])
def test_the_setup_prefaults_what_a_fork_left_copy_on_write_so_the_loop_takes_no_fault():
    """Where the machine permits mlockall (decided beforehand, tests/machine.py), the set-up must
    obtain it: a refusal here is the set-up's failure, not a reason to skip."""
    r = subprocess.run([sys.executable, "-c", COW_PROBE], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    got = json.loads(r.stdout)
    assert got["mlockall"], got
    assert got["shared"] >= 1024, got                     # the probe sees the faults it is about
    assert got["prefault"][0], got
    assert got["prefaulted"] <= 8, got                   # none for the 1024 pages, a few for Python itself
