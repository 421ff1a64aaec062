"""The loop's CPU: a pinned run gives the process its CPUs back, and the loop's helper
processes keep off the loop's CPU (motorctl.loop.rt)."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

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
