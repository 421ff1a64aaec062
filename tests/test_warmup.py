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


def test_the_cold_check_follows_numbas_cache_and_its_source_stamp(tmp_path):
    """A stand-in for the servo cycle's module, compiled with numba's on-disk cache under
    NUMBA_CACHE_DIR: cold before, warm after, cold again once its source changes."""
    import sys
    (tmp_path / "standin.py").write_text("from numba import njit\n\n@njit(cache=True)\n"
                                         "def servo_cycle(x):\n    return x + 1\n")
    script = (
        "import sys, motorctl.app.warmup as w\n"
        "w._CYCLE_MODULE = 'standin'\n"
        "before = w.cache_is_cold()\n"
        "import standin; standin.servo_cycle(1)\n"
        "after = w.cache_is_cold()\n"
        "open(standin.__file__, 'a').write('# edited\\n')\n"
        "print(before, after, w.cache_is_cold())\n")
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "numba"), "PYTHONPATH": str(tmp_path)}
    r = subprocess.run([sys.executable, "-c", script], cwd=tmp_path, env=env, capture_output=True,
                       text=True, timeout=300)
    assert r.stdout.split() == ["True", "False", "True"], r.stdout + r.stderr
