"""Shared fixtures: paths of the repository and of the paper's gantry config, and the motorctl
program as this interpreter runs it (never looked up on PATH or at a fixed system path).

Property tests (hypothesis) give the same verdict on every run: the default profile ``ci`` is
derandomized (the examples follow from each test, with no example database relied on). A
developer looking for new failures runs them with fresh random examples, ten times as many:
``MOTORCTL_HYPOTHESIS=explore .venv/bin/python -m pytest -q tests/test_inputs.py
tests/test_estimator.py tests/test_inversion.py`` (a failure prints the
``@reproduce_failure`` blob to pin it)."""

import json
import os
import subprocess
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


#: the test files' own time [s] in a full run (tests/file_seconds.json): the sum of their tests'
#: set-up, call and tear-down (``--durations=0``; a fresh clone, cold cache, 2 cores, 2026-11-29:
#: only their order counts; test_autotune's without the wait for the session's compile its first
#: set-up held). xdist hands out whole files (``--dist loadfile``) in the collection's order
#: (``--no-loadscope-reorder``): the longest first, so that the two workers end together instead
#: of one running a long file last (xdist's own order, most tests first, ran the plugin family's
#: file near the end). Refresh: ``python benchmarks/suite_weights.py report.txt --write
#: tests/file_seconds.json`` on the output of ``pytest -v --durations=0``.
FILE_SECONDS: dict = json.loads((REPO / "tests" / "file_seconds.json").read_text())
#: where a file not in :data:`FILE_SECONDS` (a new one) goes: among the long ones, where a long
#: file costs the least and a short one nothing (at the end a long one keeps one worker busy alone)
UNMEASURED_SECONDS = 100.0


#: CPU-bound processes the ``load`` tests start beside the daemon, and the longest each lives [s]
HOGS, HOG_LIFE_S = 2, 120.0


@pytest.fixture
def cpu_hogs():
    """HOGS CPU-bound processes at normal priority for the test's duration (the busy PC of the
    ``load`` group: docs/testing.md); each ends by itself after HOG_LIFE_S, and is killed at the
    test's end."""
    code = f"import time\nt = time.monotonic() + {HOG_LIFE_S}\nwhile time.monotonic() < t: pass\n"
    procs = [subprocess.Popen([sys.executable, "-c", code]) for _ in range(HOGS)]
    try:
        yield procs
    finally:
        for p in procs:
            p.kill()
            p.wait(10)


@pytest.hookimpl(trylast=True)
def pytest_collection_modifyitems(config, items):
    """The test files longest first (:data:`FILE_SECONDS`), those marked ``own_jit_cache``
    before all (they need not wait for the session's compile: one worker runs them while the
    compile takes the other core, where both workers had waited for it); each file's tests in
    their order."""
    first = {}
    for i, item in enumerate(items):
        first.setdefault(item.nodeid.split("::", 1)[0], i)

    def key(item):
        f = item.nodeid.split("::", 1)[0]
        return (item.get_closest_marker("own_jit_cache") is None, -FILE_SECONDS.get(f, UNMEASURED_SECONDS),
                first[f])
    items.sort(key=key)


#: the lock the session's compile is held under (the controller's, then each worker's check)
WARMUP_LOCK = REPO / ".pytest_cache" / "numba-warmup.lock"
#: the configs whose servo cycle the session compiles before the tests run
WARMUP_CONFIGS = ("gantry-rigid.yaml", "gantry.yaml")


def _warmup_all(started=None, stop=None) -> None:
    """``motorctl warmup`` of :data:`WARMUP_CONFIGS` (the caller holds :data:`WARMUP_LOCK`; with
    a warm cache each loads it in about a second). ``started``: a list each warmup process is
    appended to (to kill it); ``stop``: a threading.Event, set: no further warmup is started.

    Raises:
        subprocess.CalledProcessError: a warmup failed (its stderr attached).
    """
    import subprocess
    for cfg in WARMUP_CONFIGS:
        if stop is not None and stop.is_set():
            return
        argv = [*MOTORCTL, "warmup", str(REPO / "configs" / cfg)]
        with subprocess.Popen(argv, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) as proc:
            if started is not None:
                started.append(proc)
            out, err = proc.communicate(timeout=900)
        if proc.returncode:
            raise subprocess.CalledProcessError(proc.returncode, argv, out, err)


class _EarlyWarmup:
    """The session's compile started by the controlling pytest process in ``pytest_configure``,
    before the xdist workers start and collect: a thread holding :data:`WARMUP_LOCK` runs
    :func:`_warmup_all`; :func:`warm_numba_cache` in each worker waits for the lock. The
    controller imports no motorctl module (whose import points ``NUMBA_CACHE_DIR`` at the keyed
    folder in its environment, which the workers would inherit or not, by the thread's timing).
    A failure is not reported here: the worker finding the cache still cold compiles again and
    raises."""

    def __init__(self):
        import fcntl
        import threading
        WARMUP_LOCK.parent.mkdir(exist_ok=True)
        self._fh = open(WARMUP_LOCK, "w")
        fcntl.flock(self._fh, fcntl.LOCK_EX)          # held before any worker exists
        self._procs = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="numba-warmup", daemon=True)
        self._thread.start()

    def _run(self):
        import fcntl
        try:
            _warmup_all(self._procs, self._stop)
        except Exception:                              # noqa: BLE001 - the worker's own compile raises it
            pass
        finally:
            fcntl.flock(self._fh, fcntl.LOCK_UN)
            self._fh.close()

    def stop(self) -> None:
        """End a compile still running (a run shorter than the compile, an interrupted one)."""
        self._stop.set()
        for proc in self._procs:
            if proc.poll() is None:
                proc.kill()
        self._thread.join(60)


def pytest_configure(config):
    """In the controlling process (not in an xdist worker, not for ``--collect-only``): write the
    checkout's bytecode where Python is told not to (:func:`_compile_bytecode`), then start the
    session's compile at once (:class:`_EarlyWarmup`), so that it overlaps the workers' start-up
    and collection and the tests that need no compiled code of the main cache
    (``own_jit_cache``)."""
    config.addinivalue_line("markers", "own_jit_cache: the file's processes compile into a numba cache "
                                       "of their own (a plugin's): its tests do not wait for the session's "
                                       "compile of the main cache (warm_numba_cache)")
    if hasattr(config, "workerinput"):
        return
    config.pluginmanager.register(SkipRule(config), "motorctl-skip-rule")
    if config.option.collectonly:
        return
    if sys.flags.dont_write_bytecode or os.environ.get("PYTHONDONTWRITEBYTECODE"):
        _compile_bytecode()
    config.stash[_WARMUP_KEY] = _EarlyWarmup()


#: where the skips allowed on CI are stated (docs/testing.md, section "The skip table")
SKIP_TABLE_DOC = REPO / "docs" / "testing.md"
SKIP_TABLE_HEADING = "## The skip table"


def allowed_skips(doc: Path = SKIP_TABLE_DOC) -> list[tuple[str, str]]:
    """The rows of docs/testing.md's skip table: (test, condition), each cell in backticks. A
    skip is allowed when its test's node id starts with ``test`` (a file or one test) and its
    reason contains ``condition``.

    Raises:
        pytest.UsageError: no such section, or a row that is not two backticked cells and a why.
    """
    lines = doc.read_text().splitlines()
    try:
        i = lines.index(SKIP_TABLE_HEADING) + 1
    except ValueError:
        raise pytest.UsageError(f"{doc}: no section {SKIP_TABLE_HEADING!r} (the skips allowed on CI)") from None
    rows = []
    while i < len(lines) and not lines[i].startswith("## "):
        ln = lines[i].strip()
        i += 1
        if not ln.startswith("|") or set(ln) <= set("|-: ") or ln.startswith("| test |"):
            continue
        cells = [c.strip() for c in ln.strip("|").split("|")]
        if len(cells) != 3 or not all(len(c) > 2 and c[0] == c[-1] == "`" for c in cells[:2]) or not cells[2]:
            raise pytest.UsageError(f"{doc}: a skip table row is | `test` | `condition` | why |: {ln}")
        rows.append((cells[0][1:-1], cells[1][1:-1]))
    return rows


class SkipRule:
    """Skips are for what the machine lacks (docs/testing.md): every skip of the run is checked
    against the skip table (:func:`allowed_skips`); those not in it are listed at the end of the
    summary, and with ``CI=true`` (as CI runs ``.ci/run``) they fail the run (exit 1). In the
    controlling process only (xdist's workers' reports come to it)."""

    def __init__(self, config):
        self.ci = os.environ.get("CI") == "true"
        self.allowed = allowed_skips()
        self.refused: list[tuple[str, str]] = []

    def pytest_runtest_logreport(self, report):
        if not report.skipped or hasattr(report, "wasxfail"):
            return
        lr = report.longrepr
        reason = lr[2] if isinstance(lr, tuple) and len(lr) == 3 else str(lr)
        reason = reason.removeprefix("Skipped: ")
        if not any(report.nodeid.startswith(t) and c in reason for t, c in self.allowed):
            self.refused.append((report.nodeid, reason))

    def pytest_sessionfinish(self, session, exitstatus):
        if self.ci and self.refused and session.exitstatus == pytest.ExitCode.OK:
            session.exitstatus = pytest.ExitCode.TESTS_FAILED

    def pytest_terminal_summary(self, terminalreporter):
        if not self.refused:
            return
        tr = terminalreporter
        verdict = "fail this run (CI=true)" if self.ci else "would fail CI (CI=true)"
        tr.section(f"skips not in docs/testing.md's skip table: they {verdict}", sep="=", red=True)
        for nodeid, reason in self.refused:
            tr.line(f"SKIPPED {nodeid}: {reason}")


#: the folders of the modules the suite's processes import from this checkout
BYTECODE_DIRS = ("motorctl", "motorctl_drivers", "motorctl_emulators", "tests")


def _compile_bytecode() -> None:
    """This checkout's bytecode written ahead (``__pycache__``, which git ignores), as pip writes
    an installed package's, when Python is told not to write it (``PYTHONDONTWRITEBYTECODE``):
    otherwise each of the suite's processes (hundreds of ``motorctl`` commands, emulators and
    daemons) compiles every module of this checkout it imports, 0.05-0.1 s of its start. Only
    modules whose source changed are compiled again."""
    import compileall
    for d in BYTECODE_DIRS:
        compileall.compile_dir(str(REPO / d), quiet=2)


_WARMUP_KEY = pytest.StashKey[_EarlyWarmup]()


def pytest_unconfigure(config):
    early = config.stash.get(_WARMUP_KEY, None)
    if early is not None:
        early.stop()


@pytest.fixture(scope="module", autouse=True)
def warm_numba_cache(request):
    """Wait for the session's compile of the servo cycle (``motorctl warmup`` of
    :data:`WARMUP_CONFIGS`, started by the controller, :class:`_EarlyWarmup`) under a file lock,
    so that the workers of one run wait for one compile instead of each compiling (and each
    daemon test waiting for a loop that is still compiling). Module-scoped, so that it runs before
    the module's own fixtures (a daemon for the module); a module marked ``own_jit_cache`` does not
    wait. Free when the cache is warm (one check per worker).

    Raises:
        subprocess.CalledProcessError: the compile failed (run again here, its stderr attached).
    """
    if request.node.get_closest_marker("own_jit_cache"):
        return
    if not _warm:
        import fcntl

        from motorctl.app.warmup import cache_is_cold
        try:
            if cache_is_cold():
                WARMUP_LOCK.parent.mkdir(exist_ok=True)
                with open(WARMUP_LOCK, "w") as fh:
                    fcntl.flock(fh, fcntl.LOCK_EX)
                    try:
                        if cache_is_cold():            # (not compiled while this waited)
                            _warmup_all()
                    finally:
                        fcntl.flock(fh, fcntl.LOCK_UN)
            _warm.append(None)
        except Exception as exc:                       # noqa: BLE001 - raised again for every module
            _warm.append(exc)
    if _warm[0] is not None:
        raise _warm[0]


#: this process's one check of the session's compile: [None] done, [exception] it failed
_warm: list = []
