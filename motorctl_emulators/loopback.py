"""Run a bus driver against the gantry I/O emulator on one machine, as processes (benchmarks,
trials, and the tests through ``tests/harness.py``).

* :func:`loopback_config`: a copy of a driver config aimed at this machine: serial on
  ``socket://127.0.0.1:PORT``, Modbus TCP on ``127.0.0.1:PORT``, CAN and CANopen on python-can's
  ``udp_multicast`` (a free UDP port, group 239.77.67.1).
* :class:`NetNamespace`: a private network namespace (``unshare -n``, root only) with ``lo``
  up and a route for 224.0.0.0/4 via ``lo``; commands run in it through ``nsenter``. CAN over
  udp_multicast is only ever used inside one, so no multicast leaves the machine.
* :class:`Emulator`: ``motorctl emulate`` as a child process (waits for its ``ready`` line,
  killed on exit), its plant from a simulated-gantry config (``--plant``).
* :func:`motorctl_cmd`: the argv that runs the motorctl CLI with this interpreter.
* :func:`sim_twin`: a driver config run on the sim driver with the emulator's plant config (the
  reference run).

Every child is started in its own session and killed by its pid on exit.
"""

from __future__ import annotations

import copy
import os
import signal
import socket
import subprocess
import sys
from pathlib import Path

import yaml

from motorctl.config import load_yaml

CAN_GROUP = "239.77.67.1"


#: the ports :func:`free_port` hands out lie in [PORT_FLOOR, the kernel's ephemeral range)
PORT_FLOOR = 10000
#: ports per process: each process takes them in turn from a block of its own (by pid)
PORT_BLOCK = 64
_port_calls = 0


def _ephemeral_low() -> int:
    """The low end of the kernel's ephemeral port range (32768 when it cannot be read)."""
    try:
        with open("/proc/sys/net/ipv4/ip_local_port_range", encoding="ascii") as f:
            return int(f.read().split()[0])
    except (OSError, ValueError, IndexError):
        return 32768


def free_port(kind: int = socket.SOCK_STREAM) -> int:
    """A free port on 127.0.0.1 (TCP by default; ``socket.SOCK_DGRAM`` for UDP) for a server
    a test starts next.

    It lies below the kernel's ephemeral range, so no socket that binds port 0 or connects in
    the meantime (another test's client, on another worker) can be given it before the server
    binds it; each process takes the ports of its own block of :data:`PORT_BLOCK` (by pid) in
    turn, each checked by binding it.

    Raises:
        OSError: no port of the block is free.
    """
    global _port_calls
    blocks = max(1, (_ephemeral_low() - PORT_FLOOR) // PORT_BLOCK)
    base = PORT_FLOOR + (os.getpid() % blocks) * PORT_BLOCK
    for _ in range(PORT_BLOCK):
        port = base + _port_calls % PORT_BLOCK
        _port_calls += 1
        with socket.socket(socket.AF_INET, kind) as s:
            try:
                s.bind(("127.0.0.1", port))
            except OSError:
                continue
            return port
    raise OSError(f"no free port in 127.0.0.1:{base}..{base + PORT_BLOCK - 1}")


def loopback_config(base: str | Path | dict, out_dir: str | Path, rate_hz: float | None = None,
                    driver: dict | None = None, name: str | None = None) -> tuple[dict, Path]:
    """Copy a driver config, aim it at this machine, write it to ``out_dir``; returns (dict, path).

    ``driver``: extra keys set in the ``driver:`` section.
    """
    d = copy.deepcopy(base) if isinstance(base, dict) else load_yaml(base)
    drv = d["driver"]
    t = drv["type"]
    if t == "serial":
        drv["port"] = f"socket://127.0.0.1:{free_port()}"
    elif t == "modbus":
        if drv.get("transport", "tcp") == "tcp":
            drv["host"], drv["port"] = "127.0.0.1", free_port()
        else:
            drv["serial_port"] = f"socket://127.0.0.1:{free_port()}"
    elif t in ("can", "canopen"):
        drv.update(interface="udp_multicast", channel=CAN_GROUP,
                   bus_options={"port": free_port(socket.SOCK_DGRAM)})
    drv.update(driver or {})
    if rate_hz is not None:
        d["loop"]["rate_hz"] = rate_hz
    path = Path(out_dir) / f"{name or t}.yaml"
    path.write_text(yaml.safe_dump(d, sort_keys=False))
    return d, path


#: Host round trip of one exchange on loopback (p99, emulator at SCHED_FIFO 90), measured with
#: benchmarks/bench_transports.py on the shared 2-core development VM under its usual load
#: (load average ~2.8 from other jobs; idle, serial was 64 us; canopen: RPDOs + SYNC out, TPDOs
#: back through canopen's device side, measured at load average 5.9). The budget adds it to the wire
#: time of the shipped config; :func:`loopback_rate` takes the highest rate on a 500 Hz grid
#: that budget allows.
LOOPBACK_ROUND_TRIP_S = {"serial": 225e-6, "can": 515e-6, "modbus": 434e-6, "canopen": 445e-6}
#: read timeout of the loopback runs, in periods: the answer then has 1.75 periods from the
#: send; the rest of the cycle (control, write: ~60 us for two axes) still fits at ≤ 2.5 kHz.
LOOPBACK_TIMEOUT_PERIODS = 0.75
#: the emulator's watchdog in the loopback runs [s]: long enough that the loaded shared VM does
#: not trip it mid-run, short enough that a killed driver is noticed at once
LOOPBACK_WATCHDOG_S = 0.2


def loopback_rate(d: dict) -> float:
    """The highest loop rate (multiple of 500 Hz) the driver's budget allows for config ``d``."""
    import math

    from motorctl.config import config_from_dict
    b = config_from_dict(d, "<loopback>", check_budget=False).make_driver().budget(1000.0)
    return float(math.floor(b.max_rate_hz / 500.0) * 500)


def loopback_e2e_config(transport: str, configs_dir: str | Path, out_dir: str | Path,
                        name: str | None = None) -> tuple[dict, Path, float]:
    """configs/gantry-<transport>.yaml aimed at this machine, with the measured loopback round
    trip, at the highest rate its budget allows, read timeout ``LOOPBACK_TIMEOUT_PERIODS``.
    Returns (dict, path, rate_hz)."""
    rt = LOOPBACK_ROUND_TRIP_S[transport]
    d, _ = loopback_config(Path(configs_dir) / f"gantry-{transport}.yaml", out_dir,
                           driver={"round_trip_s": rt}, name=name)
    rate = loopback_rate(d)
    d["loop"]["rate_hz"] = rate
    d["driver"]["timeout_s"] = LOOPBACK_TIMEOUT_PERIODS / rate
    if d["driver"]["type"] == "serial":     # the device watchdog the driver sets in configure()
        d["driver"]["watchdog_s"] = LOOPBACK_WATCHDOG_S
    path = Path(out_dir) / f"{name or transport}.yaml"
    path.write_text(yaml.safe_dump(d, sort_keys=False))
    return d, path, rate


def sim_twin(d: dict, plant: str | Path) -> dict:
    """Driver config ``d`` on the sim driver of the emulator's plant config ``plant``: its
    ``driver:`` section and each axis's ``axes.NAME.driver`` (the plant), everything else
    (loop rate, controllers, programs, limits) from ``d``."""
    p = load_yaml(plant)
    s = copy.deepcopy(d)
    s["driver"] = copy.deepcopy(p["driver"])
    for name, ax in s["axes"].items():
        ax["driver"] = copy.deepcopy(p["axes"][name]["driver"])
    return s


def motorctl_cmd(*args: str) -> list[str]:
    """argv running the motorctl CLI with this Python."""
    return [sys.executable, "-m", "motorctl", *args]


def kill_child(proc: subprocess.Popen, sig=signal.SIGKILL) -> None:
    """Send ``sig`` to a child started in its own session (its process group), then reap it
    (bounded); nothing when it has ended."""
    if proc.poll() is None:
        try:
            os.killpg(proc.pid, sig)     # the child's own session: its pid is the group id
        except ProcessLookupError:
            pass
    try:
        proc.wait(timeout=5)
    except subprocess.TimeoutExpired:
        pass


class NetNamespace:
    """A private network namespace held by a ``sleep`` child; ``prefix`` runs a command in it.

    ``veth``: (name, peer name) of a veth pair made inside it, both ends up (EtherCAT: the
    master on one end, the emulated segment on the other).
    """

    def __init__(self, veth: tuple[str, str] | None = None):
        self.proc = None
        self.prefix: list[str] = []
        self.veth = veth

    def __enter__(self):
        pair = ""
        if self.veth:
            a, b = self.veth
            pair = (f"ip link add {a} type veth peer name {b} && ip link set {a} up && "
                    f"ip link set {b} up && ")
        self.proc = subprocess.Popen(
            ["unshare", "-n", "--", "sh", "-c",
             "ip link set lo up && ip route add 224.0.0.0/4 dev lo && " + pair + "echo ok && exec sleep 600"],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
        line = self.proc.stdout.readline().strip()
        if line != "ok":
            err = self.proc.stderr.read() if self.proc.poll() is not None else ""
            kill_child(self.proc)
            raise RuntimeError(f"cannot make a network namespace (needs root, unshare, ip): {err.strip()}")
        self.prefix = ["nsenter", "-t", str(self.proc.pid), "-n", "--"]
        return self

    def __exit__(self, *exc):
        kill_child(self.proc)


class Emulator:
    """``motorctl emulate`` in a child process (optionally inside a namespace ``prefix``).

    ``plant``: the simulated-gantry config (``--plant``; None: the command's default);
    ``watchdog_s``, ``late_s``: ``--watchdog``, ``--late`` (None: the command's defaults);
    ``faults``: ``--fault`` specs; ``extra``: more arguments.
    """

    def __init__(self, transport: str, config: str | Path, plant: str | Path | None = None, faults=(),
                 watchdog_s: float | None = None, late_s: float | None = None, prefix=(), extra=()):
        opts = [] if plant is None else ["--plant", str(plant)]
        for flag, v in (("--watchdog", watchdog_s), ("--late", late_s)):
            if v is not None:
                opts += [flag, repr(float(v))]
        self.argv = [*prefix, *motorctl_cmd("emulate", "--transport", transport, str(config), *opts,
                                            *[a for f in faults for a in ("--fault", f)], *extra)]
        self.proc = None
        self.ready = ""
        self.stderr_path = None

    def __enter__(self):
        import tempfile
        self._err = tempfile.NamedTemporaryFile("w+", prefix="emulator-", suffix=".err", delete=False)
        self.stderr_path = self._err.name
        self.proc = subprocess.Popen(self.argv, stdout=subprocess.PIPE, stderr=self._err, text=True,
                                     start_new_session=True)
        self.ready = self.proc.stdout.readline().strip()
        if not self.ready.startswith("ready:"):
            kill_child(self.proc)
            raise RuntimeError(f"emulator did not start: {self.ready!r} {self.stderr()}")
        return self

    def stderr(self) -> str:
        try:
            return Path(self.stderr_path).read_text()
        except (OSError, TypeError):
            return ""

    def stop(self) -> str:
        """SIGTERM, wait, return what it printed after the ready line."""
        if self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGTERM)
        try:
            out, _ = self.proc.communicate(timeout=5)
        except subprocess.TimeoutExpired:
            kill_child(self.proc)
            out = ""
        return out or ""

    def __exit__(self, *exc):
        kill_child(self.proc)
        self._err.close()
        try:
            os.unlink(self.stderr_path)
        except OSError:
            pass
