"""Helpers for the daemon tests: a test config, a daemon subprocess that is always killed in
teardown, and the CLI run as a subprocess (the operator's view). No tests in this module."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import time
from pathlib import Path

import yaml
from conftest import MOTORCTL

REPO = Path(__file__).resolve().parents[1]
GANTRY = REPO / "configs" / "gantry-rigid.yaml"   # the rigid plant the thresholds were set on
#: daemon.flush_s of the tests' daemons (shipped: 0.5 s): the largest allowed, so that the
#: recorder's stall bound (2·flush_s + 1 s = 3 s) is not reached by an I/O process a loaded host
#: delays. The shipped 0.5 s (a 2 s bound) latched "recorder stalled" in 3 of 81 daemon tests
#: beside the suite's other worker and a load of 10-12 on 2 CPUs (at 0.2 s, the 1.4 s bound
#: latched under benchmarks/suite_under_load.py's two spinners); the stall's own tests state
#: their bound from it
FLUSH_S = 1.0
#: loop.realtime.spin_us of the tests' daemons, with warm_caches off (shipped: 60 µs and the
#: rehearsal). As shipped a daemon's loop busy-waits about 65 % of a core at SCHED_FIFO on this
#: project's 2-CPU virtual machines (the tail, the rehearsal's earlier wake, the sleep's
#: overshoot); the suite runs up to three daemons at once (a test's own beside its module's,
#: and the other worker's), and their spinning starved every SCHED_OTHER process: an I/O
#: process that did not answer `start` within 5 s, a 0.5 s lead run dry, "recorder stalled".
#: On a gantry PC one daemon owns its core; the pacing itself is tested without a daemon
#: (tests/test_pacing.py, tests/test_compiled_cycle.py)
TEST_SPIN_US = 10.0


def as_test_daemon(d: dict, tmp: Path, flush_s: float | None = FLUSH_S) -> Path:
    """What a daemon test changes of a shipped config, and nothing else: the control socket and
    the run logs under ``tmp``, fault injection switched on, the run log's flush period
    ``flush_s`` (None: as shipped), no CPU wake-up latency request (on this project's virtual
    machines a daemon holding /dev/cpu_dma_latency beside CPU hogs froze the whole VM for
    seconds now and then: every daemon of both workers stalled 3.0 s at the same instant,
    docs/daemon.md), and a short busy-wait tail without the rehearsal (:data:`TEST_SPIN_US`;
    no daemon test is about either). SCHED_FIFO and mlockall stay as shipped. Returns the
    socket's path."""
    sock = tmp / "motorctl.sock"
    rt = d["loop"].setdefault("realtime", {})
    if rt.get("cpu_latency_us") is not None:
        rt["cpu_latency_us"] = None
    rt.update(spin_us=TEST_SPIN_US, warm_caches=False)
    d["daemon"].update(socket=str(sock), log_dir=str(tmp / "logs"), allow_fault_injection=True)
    if flush_s is not None:
        d["daemon"]["flush_s"] = flush_s
    return sock


def make_config(tmp: Path, *, fault_axis: bool = False, watchdog_s: float | None = None,
                policy: str | None = None, extra_daemon: dict | None = None, name: str = "cfg.yaml",
                busy_y: bool = False, limits_x: dict | None = None) -> Path:
    """configs/gantry-rigid.yaml as shipped, with :func:`as_test_daemon`'s paths and fault
    injection, and the test's own scenario where it asks for one: ``policy`` (the real-time
    policy; None: as shipped), ``watchdog_s`` (the driver's command watchdog; None: as shipped),
    ``extra_daemon`` (daemon keys), ``busy_y`` (Y's program mostly moving), ``fault_axis`` (X
    holds at 0 with a soft minimum 0.5 mm below it and a 1 mm following-error floor: a push
    gives a soft-limit or following-error fault; no offset force, so it does not creep while
    disabled), ``limits_x`` (keys of X's limits section replaced)."""
    d = yaml.safe_load(GANTRY.read_text())
    as_test_daemon(d, tmp)
    if policy is not None:
        d["loop"]["realtime"]["policy"] = policy
    if watchdog_s is not None:
        d["driver"]["watchdog_s"] = watchdog_s
    if extra_daemon:
        d["daemon"].update(extra_daemon)
    if busy_y:   # Y moves 0 <-> 0.4 m about 85 % of the time (a switch is likely mid-move)
        d["axes"]["Y"]["trajectory"].update(move_times_s=[0.0, 0.6], period_s=1.2)
        # C1 on Y follows within about 0.3 mm at the ends of moves: the gantry.yaml floor
        # (0.3 mm) would trip now and then while C1 is switched in
        d["axes"]["Y"]["limits"].update(min_following_error_m=0.001, following_error_m=0.002)
    if fault_axis:
        x = d["axes"]["X"]
        x["driver"]["offset_N"] = 0.0
        x["trajectory"] = {"points": [0.0]}
        x["limits"].update(soft_min_m=-0.0005, min_following_error_m=0.001, following_error_m=0.002)
    if limits_x:
        d["axes"]["X"]["limits"].update(limits_x)
    p = tmp / name
    p.write_text(yaml.safe_dump(d))
    return p


def cli(sock: Path | str | None, *args, timeout: float = 30.0, **kw) -> subprocess.CompletedProcess:
    """Run ``motorctl [--socket SOCK] ARGS`` as a subprocess (the operator's command line)."""
    cmd = list(MOTORCTL)
    if sock is not None:
        cmd += ["--socket", str(sock)]
    return subprocess.run(cmd + [str(a) for a in args], capture_output=True, text=True,
                          timeout=timeout, cwd=str(REPO), **kw)


class Result:
    def __init__(self, returncode: int, stdout: str, stderr: str):
        self.returncode, self.stdout, self.stderr = returncode, stdout, stderr


def ctl(sock: Path | str | None, *args) -> Result:
    """``motorctl [--socket SOCK] ARGS`` through ``motorctl.cli.main`` in this process: the same
    parser, handlers, output and exit code as the command line, without paying the 1-3 s
    interpreter start-up and imports of a subprocess on every call."""
    import contextlib
    import io

    from motorctl.cli import main
    argv = (["--socket", str(sock)] if sock is not None else []) + [str(a) for a in args]
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main(argv)
    return Result(code, out.getvalue(), err.getvalue())


def status(sock) -> dict:
    """The daemon's status through the client library (cheap, for polling)."""
    from motorctl.cli.operator import call
    ans = call(str(sock), {"cmd": "status"})
    assert ans["ok"], ans
    return ans["status"]


def cli_status(sock) -> dict:
    """``motorctl status --json`` as a subprocess."""
    r = cli(sock, "status", "--json")
    assert r.returncode == 0, r.stderr
    return json.loads(r.stdout)


def wait_for(pred, timeout: float, what: str, interval: float = 0.05, detail=None):
    end = time.monotonic() + timeout
    last = None
    while time.monotonic() < end:
        last = pred()
        if last:
            return last
        time.sleep(interval)
    raise AssertionError(f"timed out after {timeout} s waiting for {what} (last: {last!r})"
                         + (f"; {detail()!r}" if detail is not None else ""))


class Daemon:
    """``motorctl daemon CONFIG`` as a subprocess (``prefix``: e.g. a network namespace's
    nsenter); :meth:`kill` in teardown, always."""

    def __init__(self, config: Path, sock: Path, extra_args=(), env=None, preexec=None, prefix=(),
                 output=subprocess.PIPE):
        """``output``: where the daemon's stdout and stderr go (default: pipes :meth:`terminate`
        reads at the end; a descriptor: there)."""
        self.config, self.sock = config, sock
        self.proc = subprocess.Popen(
            [*prefix, *MOTORCTL, "daemon", str(config), "--socket", str(sock),
             *extra_args],
            stdout=output, stderr=output, text=True, cwd=str(REPO),
            env=env, preexec_fn=preexec)
        self.io_pid = None

    def wait_ready(self, timeout: float = 60.0) -> dict:
        def ready():
            if self.proc.poll() is not None:
                raise AssertionError(f"daemon exited {self.proc.returncode}: {self.proc.stderr.read()}")
            if not self.sock.exists():
                return None
            try:
                st = status(self.sock)
            except Exception:
                return None
            return st if st["process"].get("loop_pid") and st["loop"]["cycles"] > 0 else None
        st = wait_for(ready, timeout, "the daemon to run")
        self.io_pid = st["process"]["io_pid"]
        return st

    def diagnosis(self) -> str:
        """What a failure in a fixture needs to be traced afterwards: the scheduler state and
        kernel wait channel of the loop and I/O processes (/proc), the load, whether the daemon
        answers a status within 10 s now (and what it says of the loop, the recorder, the axes)
        and the daemon's stderr so far (non-blocking)."""
        parts = [f"load {os.getloadavg()}"]
        for what, pid in (("loop", self.proc.pid), ("io", self.io_pid)):
            try:
                stat = Path(f"/proc/{pid}/stat").read_text().split(")")[-1].split()
                wchan = Path(f"/proc/{pid}/wchan").read_text()
                parts.append(f"{what} pid {pid}: state {stat[0]}, wchan {wchan or '-'}, "
                             f"utime {stat[11]} stime {stat[12]} ticks")
            except (OSError, IndexError, TypeError):
                parts.append(f"{what} pid {pid}: not readable")
        t0 = time.monotonic()
        try:
            from motorctl.client import call
            st = call(str(self.sock), {"cmd": "status"}, timeout_s=10.0)["status"]
            parts.append(f"status answered after {time.monotonic() - t0:.2f} s: loop {st.get('loop')}, "
                         f"log {({k: st['log'].get(k) for k in ('max_flush_gap_s', 'recorder_fault', 'error')})}, motion "
                         f"{({k: st['motion'].get(k) for k in ('idle', 'stopped_because', 'filler_alive')})}, axes "
                         f"{ {a: (x['state'], x['phase'], x['fault']) for a, x in st['axes'].items()} }")
        except Exception as exc:  # noqa: BLE001 - a diagnosis never raises
            parts.append(f"status: {type(exc).__name__}: {exc} after {time.monotonic() - t0:.2f} s")
        if self.proc.stderr is not None:
            try:
                os.set_blocking(self.proc.stderr.fileno(), False)
                parts.append("stderr: " + (self.proc.stderr.read() or "")[-2000:])
            except (OSError, TypeError, ValueError):
                pass
        return "\n".join(parts)

    def terminate(self, timeout: float = 20.0) -> tuple[int, str, str]:
        self.proc.send_signal(signal.SIGTERM)
        out, err = self.proc.communicate(timeout=timeout)
        return self.proc.returncode, out, err

    def kill(self) -> None:
        for pid in (self.proc.pid, self.io_pid):
            if pid:
                try:
                    os.kill(pid, signal.SIGKILL)
                except (ProcessLookupError, PermissionError):
                    pass
        try:
            self.proc.communicate(timeout=10)
        except (subprocess.TimeoutExpired, ValueError):
            pass
        if self.io_pid:
            end = time.monotonic() + 5
            while time.monotonic() < end and _alive(self.io_pid):
                time.sleep(0.02)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    try:  # a zombie counts as gone
        with open(f"/proc/{pid}/stat") as fh:
            return fh.read().split(")")[-1].split()[0] != "Z"
    except OSError:
        return False


def run_log_path(st: dict) -> str:
    return st["log"]["path"]


@contextlib.contextmanager
def running_daemon(tmp: Path, **config_kw):
    """A daemon on ``make_config(tmp, **config_kw)``, ready; killed on exit (bounded)."""
    d = Daemon(make_config(tmp, **config_kw), tmp / "motorctl.sock")
    try:
        d.wait_ready()
        yield d
    finally:
        d.kill()


def to_command_mode(sock) -> None:
    """Every axis of the daemon at ``sock`` enabled in command mode without a fault (a fault
    reset, an axis in another phase stopped and started again), motion idle (an abort)."""
    if not status(sock)["motion"]["idle"]:
        assert ctl(sock, "abort").returncode == 0
        wait_for(lambda: status(sock)["motion"]["idle"], 20, "the abort", detail=lambda: status(sock)["motion"])
    for a, s in status(sock)["axes"].items():
        if s["fault"]:
            assert ctl(sock, "fault-reset", a).returncode == 0
        if s["phase"] != "command":
            if s["state"] == "enabled":
                assert ctl(sock, "stop", a).returncode == 0
            r = ctl(sock, "start", a, "--mode", "command")
            assert r.returncode == 0, r.stderr
    wait_for(lambda: all(s["phase"] == "command" for s in status(sock)["axes"].values()), 10, "command mode")


@contextlib.contextmanager
def command_mode_daemon(cfg: Path):
    """``motorctl daemon`` of ``cfg`` (its socket beside it) with every axis in command mode;
    killed after."""
    dmn = Daemon(cfg, cfg.parent / "motorctl.sock")
    try:
        dmn.wait_ready()
        try:
            to_command_mode(dmn.sock)
        except AssertionError as exc:
            raise AssertionError(f"{exc}\n{dmn.diagnosis()}") from None
        yield dmn
    finally:
        dmn.kill()


def positions(sock) -> "np.ndarray":
    """(X, Y) where the axes stand [m]."""
    import numpy as np
    ax = status(sock)["axes"]
    return np.array([ax["X"]["y_m"], ax["Y"]["y_m"]])


def no_fault(sock) -> None:
    """Every axis enabled in command mode without a fault."""
    for a, s in status(sock)["axes"].items():
        assert s["state"] == "enabled" and s["phase"] == "command" and not s["fault"], (a, s)
