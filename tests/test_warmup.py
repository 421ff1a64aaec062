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


def _copy_packages(dst):
    """A copy of the packages whose sources key numba's cache folder (motorctl.jitcache)."""
    import shutil

    from motorctl.jitcache import PACKAGES
    for name in PACKAGES:
        shutil.copytree(REPO / name, dst / name, ignore=shutil.ignore_patterns("__pycache__"))
    return [dst / name for name in PACKAGES]


def test_an_edit_to_a_callee_module_changes_the_cache_folder(tmp_path):
    """numba keys a cached kernel on its own file only: an edit to a module the servo cycle
    calls into (safety.py, stream.py, an effect's kernel) must give another cache folder, and
    undoing it the same one again."""
    from motorctl.jitcache import cache_dir
    roots = _copy_packages(tmp_path / "src")
    env = {"XDG_CACHE_HOME": str(tmp_path / "cache")}
    before, chosen = cache_dir(env, roots)
    assert not chosen and (tmp_path / "cache" / "motorctl" / "numba") in before.parents
    for rel in ("motorctl/loop/safety.py", "motorctl/loop/stream.py", "motorctl_drivers/sim.py"):
        src = tmp_path / "src" / rel
        text = src.read_text()
        src.write_text(text.replace("0.0", "0.00", 1))
        edited, _ = cache_dir(env, roots)
        assert edited.parent == before.parent and edited != before, rel
        src.write_text(text)
        assert cache_dir(env, roots)[0] == before, rel
    assert cache_dir({**env, "NUMBA_CACHE_DIR": str(tmp_path / "mine")}, roots) == (tmp_path / "mine", True)


def test_motorctl_points_numba_at_the_keyed_folder_and_prunes_old_ones(tmp_path):
    """Without NUMBA_CACHE_DIR, numba's first use (motorctl.jit.load: a kernel compiled or loaded)
    sets numba's cache folder (and the variable, for child processes) to the keyed one, and keeps
    the checkout's KEEP used last; importing a module of kernels does not set it yet."""
    import sys

    from motorctl.jitcache import KEEP, cache_dir
    env = {k: v for k, v in os.environ.items() if k not in ("NUMBA_CACHE_DIR", "MOTORCTL_CACHE_DIR")}
    env["XDG_CACHE_HOME"] = str(tmp_path)
    folder, _ = cache_dir(env)
    old = [folder.parent / f"old{i}" for i in range(KEEP + 2)]
    for i, p in enumerate(old):
        p.mkdir(parents=True)
        os.utime(p, (1e9 + i, 1e9 + i))                   # old4 used last
    r = subprocess.run([sys.executable, "-c", "import os, numba, motorctl.effects.cogging, motorctl.jit\n"
                        "assert 'NUMBA_CACHE_DIR' not in os.environ\n"
                        "motorctl.jit.load()\n"
                        "print(numba.config.CACHE_DIR, os.environ['NUMBA_CACHE_DIR'])"],
                       cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120)
    assert r.stdout.split() == [str(folder)] * 2, r.stdout + r.stderr
    assert sorted(p.name for p in folder.parent.iterdir()) == sorted([folder.name] + [p.name for p in old[-(KEEP - 1):]])


def test_numba_is_imported_at_a_kernels_first_use_not_by_its_module(tmp_path):
    """The identification's and the families' modules define their kernels without importing
    numba (motorctl identify calls none of them); a kernel's first call imports numba, compiles
    it into the cache folder and returns what the Python function returns; a kernel compiled
    after that calls a lazily defined one."""
    import sys
    (tmp_path / "caller.py").write_text(
        "from motorctl.effects.cogging import plant_force\nfrom motorctl.jit import njit\n\n"
        "@njit\ndef twice(x, p):\n    return plant_force(0.0, x, 0.0, 0.0, None, p) * 2.0\n")
    script = ("import sys\nimport numpy as np\n"
              "import motorctl.ident.pipeline, motorctl.ident.simfit, motorctl.effects.plant, "
              "motorctl.effects.compensation\n"
              "from motorctl.effects.cogging import plant_force\n"
              "print('numba' in sys.modules)\n"
              "p = np.array([np.inf, 1.0, 2.0, 100.0, 0.3])\n"
              "print(plant_force(1.0, 0.01, 0.0, 0.0, None, p) == plant_force.py_func(1.0, 0.01, 0.0, 0.0, None, p))\n"
              "import caller\n"
              "print(caller.twice(0.01, p) == 2.0 * plant_force.py_func(0.0, 0.01, 0.0, 0.0, None, p))\n"
              "print('numba' in sys.modules, type(plant_force.dispatcher).__name__, len(plant_force.overloads))\n")
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "numba"), "PYTHONPATH": str(tmp_path)}
    r = subprocess.run([sys.executable, "-c", script], cwd=REPO, env=env, capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 0, r.stderr
    assert r.stdout.split() == ["False", "True", "True", "True", "CPUDispatcher", "1"], r.stdout + r.stderr
    assert any((tmp_path / "numba").rglob("*.nbi")), "nothing cached"
