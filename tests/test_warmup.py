"""The first start says it compiles: with a cold numba cache ``motorctl run`` prints the
compile line before anything else (before numba is even imported); with a warm one it does
not, and ``motorctl warmup`` says it loaded the cache."""

from __future__ import annotations

import os
import subprocess

from conftest import MOTORCTL, REPO

from motorctl.app.warmup import COMPILE_LINE


def test_a_cold_cache_is_announced_first(tmp_path):
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "numba")}    # empty: cold
    proc = subprocess.Popen([*MOTORCTL, "run", str(REPO / "configs" / "gantry-rigid.yaml"),
                             "--virtual-clock", "--duration", "0.01"], cwd=REPO, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        first = proc.stderr.readline()
    finally:
        proc.kill()
        proc.communicate(timeout=30)
    assert first == f"motorctl: {COMPILE_LINE}\n"


def test_a_warm_cache_is_silent_and_warmup_loads_it(gantry_yaml):
    r = subprocess.run([*MOTORCTL, "warmup", str(gantry_yaml)], cwd=REPO, capture_output=True,
                       text=True, timeout=600)
    assert r.returncode == 0 and r.stderr == "", r.stderr
    assert r.stdout.startswith("warmup: the controllers and the servo cycle loaded from the cache")
    r = subprocess.run([*MOTORCTL, "run", str(gantry_yaml), "--virtual-clock", "--duration", "0.01"],
                       cwd=REPO, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0 and COMPILE_LINE not in r.stderr, r.stderr
