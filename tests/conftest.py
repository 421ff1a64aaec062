"""Shared fixtures: paths of the repository and of the paper's gantry config, and the motorctl
program as this interpreter runs it (never looked up on PATH or at a fixed system path).

Property tests (hypothesis) give the same verdict on every run: the default profile ``ci`` is
derandomized (the examples follow from each test, with no example database relied on). A
developer looking for new failures runs them with fresh random examples, ten times as many:
``MOTORCTL_HYPOTHESIS=explore .venv/bin/python -m pytest -q tests/test_inputs.py
tests/test_estimator.py tests/test_inversion.py`` (a failure prints the
``@reproduce_failure`` blob to pin it)."""

import os
import sys
import sysconfig
from pathlib import Path

import pytest
from hypothesis import settings

settings.register_profile("ci", derandomize=True, database=None, print_blob=True)
settings.register_profile("explore", derandomize=False, database=None, print_blob=True)
#: the hypothesis profile of this run: ``ci`` (fixed examples) unless MOTORCTL_HYPOTHESIS says
HYPOTHESIS_PROFILE = os.environ.get("MOTORCTL_HYPOTHESIS", "ci")
if HYPOTHESIS_PROFILE not in ("ci", "explore"):
    raise pytest.UsageError(f"MOTORCTL_HYPOTHESIS={HYPOTHESIS_PROFILE!r}: allowed: ci, explore")
settings.load_profile(HYPOTHESIS_PROFILE)


def examples(n: int) -> int:
    """How many examples a property test draws: ``n`` (``ci``), ten times as many (``explore``)."""
    return n * (10 if HYPOTHESIS_PROFILE == "explore" else 1)

REPO = Path(__file__).resolve().parents[1]

#: the plant the emulators run behind their protocols in the tests: the paper's rigid gantry
RIGID_PLANT = REPO / "configs" / "gantry-rigid.yaml"

#: argv prefix that runs the motorctl CLI with the interpreter running the tests
MOTORCTL = [sys.executable, "-m", "motorctl"]


def console_script() -> Path:
    """The ``motorctl`` console script installed beside this interpreter (e.g. .venv/bin).

    Raises:
        AssertionError: the project is not installed into this interpreter's environment.
    """
    for d in (Path(sys.executable).parent, Path(sysconfig.get_path("scripts"))):
        exe = d / "motorctl"
        if exe.is_file():
            return exe
    raise AssertionError(f"no motorctl console script beside {sys.executable}: install the "
                         f"project into this environment (pip install -e .)")


@pytest.fixture(scope="session")
def repo() -> Path:
    return REPO


@pytest.fixture(scope="session")
def gantry_yaml(repo) -> Path:
    """The paper's gantry on the rigid plant (configs/gantry-rigid.yaml): the model the
    paper's figures, the estimator's convergence and the loop's sequencing tests are stated
    on. The default config (configs/gantry.yaml, with the unmodelled dynamics) is
    :func:`default_yaml`."""
    return repo / "configs" / "gantry-rigid.yaml"


@pytest.fixture(scope="session")
def default_yaml(repo) -> Path:
    """configs/gantry.yaml: the default of every command (the realistic plant)."""
    return repo / "configs" / "gantry.yaml"


@pytest.fixture(scope="session", autouse=True)
def warm_numba_cache():
    """Compile the servo cycle once for the whole session (``motorctl warmup``), under a file
    lock so that the workers of one run wait for one compile instead of each compiling (and
    each daemon test waiting for a loop that is still compiling). Free when the cache is warm."""
    import fcntl
    import subprocess

    from motorctl.app.warmup import cache_is_cold
    if not cache_is_cold():
        return
    lock = REPO / ".pytest_cache" / "numba-warmup.lock"
    lock.parent.mkdir(exist_ok=True)
    with open(lock, "w") as fh:
        fcntl.flock(fh, fcntl.LOCK_EX)
        try:
            if cache_is_cold():
                for cfg in ("gantry-rigid.yaml", "gantry.yaml"):
                    subprocess.run([*MOTORCTL, "warmup", str(REPO / "configs" / cfg)], cwd=REPO,
                                   capture_output=True, timeout=900, check=True)
        finally:
            fcntl.flock(fh, fcntl.LOCK_UN)
