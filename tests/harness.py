"""Test helpers (not installed): the CLI as a child process, a driver against an in-process
device, and, re-exported, the loopback tools of :mod:`motorctl_emulators.loopback` (config aimed
at this machine, network namespace, emulator process), so a test imports them from one place.

* :func:`run_cli`, :func:`run_cli_interrupted`: ``motorctl`` as a child process, bounded;
  :func:`parse_run_table`: the axis rows of ``motorctl run``'s table; :func:`wait_for`: bounded
  polling.
* :func:`device_thread`, :func:`exchange`: an emulated device served from a thread of the test
  process and driver cycles against it (python-can's ``virtual`` bus, ptys).
* :func:`emps_path`: the local EMPS record (never downloaded), or None.
* :func:`plugin_env`: an environment where a package outside motorctl registers entry points.
"""

from __future__ import annotations

import contextlib
import os
import subprocess
import threading
import time
from pathlib import Path

import numpy as np

from motorctl_emulators.loopback import (  # noqa: F401  (re-exported for the tests)
    CAN_GROUP,
    LOOPBACK_ROUND_TRIP_S,
    LOOPBACK_TIMEOUT_PERIODS,
    LOOPBACK_WATCHDOG_S,
    Emulator,
    NetNamespace,
    kill_child,
    free_port,
    loopback_config,
    loopback_e2e_config,
    loopback_rate,
    motorctl_cmd,
    sim_twin,
)


#: the project's shared data directory beside the clone (as CI has it), tried after MOTORCTL_DATA_DIR
SHARED_DATA_DIR = Path(__file__).resolve().parents[2] / "shared" / "data"


def emps_path() -> str | None:
    """The EMPS record ``emps/DATA_EMPS.mat`` (motorctl.datasets' layout) under
    ``$MOTORCTL_DATA_DIR`` first, then under the shared data directory beside the clone; None when
    neither has it (the tests that need it skip). Nothing is downloaded."""
    from motorctl.datasets import DATA_DIR_ENV, local_path
    roots = [os.environ[DATA_DIR_ENV]] if os.environ.get(DATA_DIR_ENV) else []
    for root in [*roots, SHARED_DATA_DIR]:
        path = local_path("emps", Path(root))
        if path.is_file():
            return str(path)
    return None


def plugin_env(root: Path, dist: str, group: str, entries: dict[str, str], *path: Path) -> dict:
    """``os.environ`` with ``root`` (and ``path``) on PYTHONPATH, where ``root/<dist>-0.1.dist-info``
    declares ``entries`` (name -> "module:attr") in entry-point ``group``: as an installed
    plugin package is seen by importlib.metadata."""
    info = Path(root) / f"{dist}-0.1.dist-info"
    info.mkdir()
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {dist}\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text(f"[{group}]\n" + "".join(f"{k} = {v}\n" for k, v in entries.items()))
    return {**os.environ, "PYTHONPATH": os.pathsep.join(str(p) for p in (root, *path))}


def run_cli(argv: list[str], prefix=(), timeout_s: float = 60.0) -> subprocess.CompletedProcess:
    """Run a motorctl command (with an optional namespace prefix), bounded in time."""
    proc = subprocess.Popen([*prefix, *motorctl_cmd(*argv)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        out, err = proc.communicate(timeout=timeout_s)
    finally:
        kill_child(proc)
    return subprocess.CompletedProcess(proc.args, proc.returncode, out, err)


def run_cli_interrupted(argv: list[str], act, prefix=(), timeout_s: float = 60.0):
    """Run a motorctl command, wait for its first line of stdout (``run`` prints it just before
    the first cycle), call ``act(proc)`` (e.g. sleep, then send a signal to ``proc.pid``'s
    group), then wait for the end (bounded; killed on exit). Returns (first line,
    CompletedProcess with the rest of stdout and stderr)."""
    proc = subprocess.Popen([*prefix, *motorctl_cmd(*argv)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        first = proc.stdout.readline()
        if first:
            act(proc)
        out, err = proc.communicate(timeout=timeout_s)
    finally:
        kill_child(proc)
    return first, subprocess.CompletedProcess(proc.args, proc.returncode, out, err)


def parse_run_table(stdout: str) -> dict:
    """Axis rows of ``motorctl run``'s table →
    {axis: {e_M_um, e_F_um, L2_um, u_peak_V, io_errors, fault}}."""
    out = {}
    for line in stdout.splitlines():
        parts = line.split()
        if len(parts) >= 8 and parts[1] != "ctrl":
            try:
                vals = [float(x) for x in parts[2:6]]
                io_errors = int(parts[6])
            except ValueError:
                continue
            fault = " ".join(parts[7:])
            out[parts[0]] = dict(zip(("e_M_um", "e_F_um", "L2_um", "u_peak_V"), vals),
                                 io_errors=io_errors, fault="" if fault == "-" else fault)
    return out


def wait_for(pred, timeout_s: float, step_s: float = 0.05) -> bool:
    """Poll ``pred()`` until true or ``timeout_s`` has passed (bounded)."""
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if pred():
            return True
        time.sleep(step_s)
    return bool(pred())


def exchange(drv, u_V, enable, n: int = 1, sleep_s: float = 0.003) -> None:
    """``n`` cycles of a driver against an in-process device (:func:`device_thread`): write
    ``u_V`` [V] and ``enable`` (one value per axis), sleep ``sleep_s`` [s] (the device thread
    needs the GIL to answer), read."""
    u, en = np.asarray(u_V, dtype=float), np.asarray(enable, dtype=bool)
    for _ in range(n):
        drv.write(u, en)
        time.sleep(sleep_s)
        drv.read()


@contextlib.contextmanager
def device_thread(dev):
    """Serve the emulated device ``dev`` from a daemon thread of this process (in-process
    tests over python-can's virtual bus); stopped and joined (bounded, 5 s) on exit."""
    stop = threading.Event()
    th = threading.Thread(target=dev.serve, kwargs={"stop": stop.is_set}, daemon=True)
    th.start()
    try:
        yield dev
    finally:
        stop.set()
        th.join(timeout=5)


#: the plant of :func:`loop_csv`: mass [kg], force gain A1 [N/V], viscous [N s/m], Coulomb [N]
LOOP_M, LOOP_A1, LOOP_B, LOOP_FC = 10.0, 50.0, 20.0, 8.0


def loop_csv(path, xd: np.ndarray, ts: float = 1e-3, seed: int = 0, y_noise_m: float = 2e-7,
             u_noise_V: float = 0.02, play_V: float = 0.0, enc_m: float = 0.0, cogging_N: float = 0.0,
             period_m: float = 2e-3, d_on_reading: bool = False) -> str:
    """A PID position loop on the measured y tracking ``xd`` (N,) [m], written as a CSV
    ``t,y,u`` (a user's measurement; gain :data:`LOOP_A1`): a mass with viscous and Coulomb
    friction, explicit Euler at ``ts`` [s], seeded noise on y and u. Optional, each off at 0: a
    play of ±play_V [V] in the amplifier's input (backlash, no family models it), an
    interpolation error enc_m·sin(2πx/P) [m] of the reading and a cogging force
    cogging_N·sin(2πx/P) [N], P = period_m. d_on_reading: the loop's derivative term on the
    reading's backward difference (a servo that chases the reading's error), else on the true
    velocity. Returns the path as text."""
    import math
    rng = np.random.default_rng(seed)
    n = len(xd)
    t = np.arange(n) * ts
    x = v = e_int = u_amp = y_prev = 0.0
    ys, us = np.empty(n), np.empty(n)
    k = 2 * np.pi / period_m
    for i in range(n):
        y = x + enc_m * math.sin(k * x) + rng.normal(0.0, y_noise_m)
        e = xd[i] - y
        e_int += e * ts
        vd = (xd[min(i + 1, n - 1)] - xd[i]) / ts
        v_read = (y - y_prev) / ts if d_on_reading and i else v
        y_prev = y
        u = float(np.clip(4000.0 * e + 40000.0 * e_int + 60.0 * (vd - v_read) + rng.normal(0.0, u_noise_V), -10.0, 10.0))
        u_amp = max(u - play_V, min(u + play_V, u_amp))     # play operator (backlash)
        a = (LOOP_A1 * u_amp - LOOP_B * v - LOOP_FC * math.tanh(v / 1e-3) + cogging_N * math.sin(k * x)) / LOOP_M
        v += a * ts
        x += v * ts
        ys[i], us[i] = y, u
    np.savetxt(path, np.column_stack([t, ys, us]), delimiter=",", header="t,y,u", comments="")
    return str(path)


def fast_moves_xd(fs: float = 5000.0, duration: float = 6.0) -> np.ndarray:
    """Moves 0 ↔ 0.3 m with a raised-cosine speed (peak 1.5 m/s, 0.4 s each) and 0.1 s rests,
    sampled at fs [Hz] for ``duration`` [s] (N,) [m]: at cruise a 2 mm encoder error is at
    750 Hz, far above the 250 Hz position filter of 5 kHz."""
    n_move, n_rest = int(0.4 * fs), int(0.1 * fs)
    tau = np.arange(n_move) / n_move
    up = 0.3 * (tau - np.sin(2 * np.pi * tau) / (2 * np.pi))
    one = np.concatenate([up, np.full(n_rest, 0.3), up[::-1], np.zeros(n_rest)])
    n = int(duration * fs)
    return np.tile(one, n // len(one) + 1)[:n]
