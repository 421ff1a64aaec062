"""What the CAN, serial and Modbus drivers and their emulated devices share (one place each).

* :func:`volts_to_counts` / :func:`counts_to_volts`: the voltage command as a scaled signed
  integer (full scale ``full_scale_V`` ↔ the largest count of a ``bits``-wide signed field).
* :class:`EncoderUnwrap`: a ``bits``-wide wrapping encoder counter → a continuous count
  (the difference of two readings modulo 2^bits, taken as the shortest signed step).
* :class:`SplitPhaseDriver`: the cycle shared by the bus drivers. ``write()`` sends the command
  of cycle k with sequence number k (non-blocking); the device applies it for one period and
  answers with the encoder reading at the end of that period; ``read()`` of cycle k+1 polls
  (never blocks) for that answer until ``timeout_s`` (shorter than the period) has passed.
  This is LinuxCNC hostmot2's split-phase read-request/read: one exchange per cycle, and the
  same data flow as the simulated driver (write steps the plant, the next read sees it).
  A missing, late, stale (wrong sequence) or corrupt answer sets ``read_error`` for the axes
  it carried; the position is extrapolated by the last measured one-cycle step for up to
  ``EXTRAPOLATE_CYCLES`` consecutive losses, then held (LinuxCNC's
  advice for a transient packet loss is to stand in for the feedback; the supervisor's leaky
  bucket still counts the cycle and faults the axis when losses persist). A failed send sets ``write_error``. Nothing raises.
* :class:`PlantBank`: the device side of every emulator: the simulated plant of every axis
  (:class:`motorctl_drivers.sim.AxisPlant`, seeded as :class:`~motorctl_drivers.sim.SimDriver`
  seeds it), stepped one period per valid command, with a command watchdog (no valid command
  for ``watchdog_s`` → 0 V and an amplifier fault, latched until a command with the amplifier
  disabled) and a fault-injection schedule.
* :class:`EmulatorOptions`, :class:`FaultSpec`: the YAML ``driver.emulator`` section and one
  injected fault.
"""

from __future__ import annotations

import math
import select
import sys
import time
from typing import Annotated, Literal

import numpy as np
from pydantic import Field

from motorctl.driver import BusBudget, Driver
from motorctl.schema import StrictModel
from motorctl_drivers.sim import AxisPlant, SimAxisOptions

FAULT_KINDS = ("drop", "late", "corrupt", "stale", "exception", "disconnect", "bus_off")


# --------------------------------------------------------------------------- scaling
def volts_to_counts(u_V: float, full_scale_V: float, bits: int) -> int:
    """Voltage [V] → signed integer of ``bits`` bits, full scale ±``full_scale_V``; saturates; NaN → 0."""
    top = (1 << (bits - 1)) - 1
    if not (u_V == u_V):
        return 0
    c = round(u_V / full_scale_V * top)
    return top if c > top else (-top if c < -top else int(c))


def counts_to_volts(c: int, full_scale_V: float, bits: int) -> float:
    """Signed integer of ``bits`` bits → voltage [V] (inverse of :func:`volts_to_counts`)."""
    return c * full_scale_V / ((1 << (bits - 1)) - 1)


def to_unsigned(value: int, bits: int) -> int:
    """Two's complement of ``value`` in ``bits`` bits (the wire form of a signed field)."""
    return value & ((1 << bits) - 1)


def to_signed(raw: int, bits: int) -> int:
    """Unsigned ``bits``-bit wire value → signed int."""
    half = 1 << (bits - 1)
    return raw - (1 << bits) if raw >= half else raw


class EncoderUnwrap:
    """A wrapping ``bits``-wide encoder counter → a continuous count.

    ``update(raw)`` takes the unsigned wire value and returns the continuous count: the first
    reading is taken as a signed value, every later one adds the shortest signed step from
    the previous reading modulo 2^bits (valid while the axis moves less than half the counter
    range per cycle: 2^23 counts = 4.2 m at 0.5 µm for 24 bits).
    """

    def __init__(self, bits: int):
        self.bits = bits
        self.mod = 1 << bits
        self.half = 1 << (bits - 1)
        self.last = -1
        self.total = 0

    def update(self, raw: int) -> int:
        if self.last < 0:
            self.total = to_signed(raw, self.bits)
        else:
            d = (raw - self.last) & (self.mod - 1)
            if d >= self.half:
                d -= self.mod
            self.total += d
        self.last = raw
        return self.total


# --------------------------------------------------------------------------- YAML pieces
class FaultSpec(StrictModel):
    """One injected fault: ``kind`` on ``axis`` ('*' = every axis / the whole frame) for
    ``count`` commands, starting at the ``start``-th command the device receives (0-based).

    Kinds: drop (no reply), late (reply after ``late_s``), corrupt (bad CRC / bad frame),
    stale (the previous reply again, old sequence number), exception (an error reply:
    Modbus exception 0x04, or the frame's error flag), disconnect (close the link / stop
    answering), bus_off (CAN: the node leaves the bus, nothing sent or answered).
    """

    kind: Literal["drop", "late", "corrupt", "stale", "exception", "disconnect", "bus_off"]
    axis: str = "*"
    start: Annotated[int, Field(ge=0)] = 0
    count: Annotated[int, Field(ge=1)] = 1

    @classmethod
    def parse(cls, text: str) -> "FaultSpec":
        """``KIND[:AXIS[:START[:COUNT]]]`` (CLI form), e.g. ``drop:X:2000:5``. Raises ValueError."""
        parts = text.split(":")
        if not parts[0] or len(parts) > 4:
            raise ValueError(f"fault {text!r}: expected KIND[:AXIS[:START[:COUNT]]]")
        if parts[0] not in FAULT_KINDS:
            raise ValueError(f"fault {text!r}: unknown kind {parts[0]!r}; allowed: {', '.join(FAULT_KINDS)}")
        kw = {"kind": parts[0]}
        try:
            if len(parts) > 1 and parts[1]:
                kw["axis"] = parts[1]
            if len(parts) > 2:
                kw["start"] = int(parts[2])
            if len(parts) > 3:
                kw["count"] = int(parts[3])
        except ValueError:
            raise ValueError(f"fault {text!r}: START and COUNT are integers") from None
        return cls(**kw)


class EmulatorOptions(StrictModel):
    """YAML ``driver.emulator``: how ``motorctl emulate`` runs the plant behind the protocol.

    seed, substeps: as the sim driver's (same seed ⇒ same plant noise).
    watchdog_s: no valid command for this long → 0 V and amplifier fault [s].
    late_s: delay of a 'late' reply [s]. faults: injected faults (also ``--fault`` on the CLI).
    """

    seed: int = 0
    substeps: Annotated[int, Field(ge=1, le=100)] = 4
    watchdog_s: Annotated[float, Field(gt=0)] = 0.05
    late_s: Annotated[float, Field(ge=0)] = 0.002
    faults: list[FaultSpec] = []


class CommonOptions(StrictModel):
    """Settings every bus driver has (merged into each driver's ``Options``).

    timeout_s: how long ``read()`` polls for the answer [s]; default half the period; capped
        at 0.8 of the period (the rest of the cycle needs the time).
    round_trip_s: measured host round trip of one exchange on this machine [s] (driver stack
        + device answering; ``benchmarks/bench_transports.py`` measures it). Added to the wire
        time in the budget; 0 means 'wire only'.
    wait: how ``read()`` waits for the answer until ``timeout_s``: 'select' sleeps in
        select() on the transport's file descriptor (never past the deadline; the CPU is free
        meanwhile, so a SCHED_FIFO loop stays clear of RT throttling), 'spin' polls without
        sleeping (lowest latency, for an isolated core). Transports without a descriptor
        (python-can 'virtual') always spin.
    max_bus_load: the fraction of the period the bus may be busy (0.8 leaves room for
        retries and other traffic).
    emulator: the emulated device's settings (``motorctl emulate`` only; the driver ignores it).
    """

    timeout_s: Annotated[float, Field(gt=0)] | None = None
    wait: Literal["select", "spin"] = "select"
    round_trip_s: Annotated[float, Field(ge=0)] = 0.0
    max_bus_load: Annotated[float, Field(gt=0, le=1)] = 0.8
    emulator: EmulatorOptions = EmulatorOptions()


def make_budget(rate_hz: float, wire_s: float, round_trip_s: float, max_load: float,
                what: str, fits: str) -> BusBudget:
    """Budget from the wire time and the host round trip of one cycle.

    ``what``: the wire arithmetic, one line. ``fits``: a setting that would carry ``rate_hz``.
    """
    cycle = wire_s + round_trip_s
    max_rate = max_load / cycle if cycle > 0 else float("inf")
    detail = (f"{what}; wire {wire_s * 1e6:.1f} us + measured round trip {round_trip_s * 1e6:.1f} us "
              f"= {cycle * 1e6:.1f} us per cycle, {cycle * rate_hz * 100:.0f}% of the "
              f"{1e6 / rate_hz:.0f} us period at {rate_hz:g} Hz (limit {max_load * 100:.0f}% load)")
    suggestion = ""
    if rate_hz > max_rate:
        suggestion = f"set loop.rate_hz to {math.floor(max_rate):d} or less, or {fits}"
    return BusBudget(cycle_time_s=cycle, max_rate_hz=max_rate, detail=detail, suggestion=suggestion)


# --------------------------------------------------------------------------- driver side
class SplitPhaseDriver(Driver):
    """Base of the bus drivers (see the module docstring for the cycle).

    Subclasses implement ``_transmit(seq, u_V, enable)`` (send the command; set
    ``write_error``; never block) and ``_receive()`` (drain what has arrived without blocking
    and call :meth:`_accept` for each answer that decodes and passes its CRC), plus ``open``,
    ``close`` and ``_query()`` (one blocking exchange that reads positions without stepping,
    used by ``open``).

    Counters (for ``describe()`` and the benchmark): timeouts, stale, bad_frames, exceptions.
    """

    SEQ_MASK = 0xFF
    EXTRAPOLATE_CYCLES = 8

    def __init__(self, options, axis_options, period_s):
        super().__init__(options, axis_options, period_s)
        n = len(self.axis_names)
        t = options.timeout_s if options.timeout_s is not None else 0.5 * period_s
        self.timeout_s = min(t, 0.8 * period_s)
        self.seq = 0
        self._outstanding = False
        self._got = np.zeros(n, dtype=bool)
        self._step = [0.0] * n               # last measured one-cycle step [m] (extrapolation)
        self._y_last = [math.nan] * n        # last measured position [m]
        self._lost = [0] * n                 # consecutive lost answers per axis
        self._query = False                  # open()'s query: any sequence number will do
        self._wait_fds: list = []            # descriptors read() may select() on
        self._any_lost = False
        self._unwrap: list[EncoderUnwrap] = []
        self._m_per_count = [1.0] * n
        self.connected = False
        self.counters = {"timeouts": 0, "stale": 0, "bad_frames": 0, "exceptions": 0, "send_errors": 0}

    def _set_wait_fd(self, fd) -> None:
        """Called by ``open()`` with the transport's file descriptor (None: none, spin)."""
        self._wait_fds = [fd] if fd is not None and fd >= 0 and self.options.wait == "select" else []

    # --- hooks
    def _transmit(self, seq: int, u_V: np.ndarray, enable: np.ndarray) -> None:  # pragma: no cover
        raise NotImplementedError

    def _receive(self) -> None:  # pragma: no cover
        raise NotImplementedError

    def _accept(self, i: int, seq: int, raw_counts: int, fault: bool) -> None:
        """Take axis i's answer if it carries the expected sequence number (else: stale)."""
        if not self._outstanding or (seq != self.seq and not self._query):
            self.counters["stale"] += 1
            return
        if self._got[i]:
            return
        self._got[i] = True
        y = self._unwrap[i].update(raw_counts) * self._m_per_count[i]
        self._step[i] = y - self._y_last[i] if self._y_last[i] == self._y_last[i] else 0.0
        self._y_last[i] = y
        self.position_m[i] = y
        self.amp_fault[i] = fault

    def _accept_error(self, i: int, seq: int) -> None:
        """Axis i's exchange got an error reply (exception) this cycle."""
        self.counters["exceptions"] += 1

    # --- cycle
    def read(self) -> None:
        if not self._outstanding:
            self.read_error[:] = False
            return
        got = self._got
        clock = time.perf_counter
        deadline = clock() + self.timeout_s
        fds = self._wait_fds
        try:
            while True:
                self._receive()
                if got.all():
                    break
                left = deadline - clock()
                if left <= 0.0:
                    break
                if fds:
                    select.select(fds, (), (), left)
        except Exception:  # noqa: BLE001  (a transport error inside the cycle is a read error)
            self.connected = False
        if not got.all():
            self.counters["timeouts"] += 1
            pos, step, lost = self.position_m, self._step, self._lost
            for i in range(len(got)):
                if not got[i]:   # stand in for a lost answer (still flagged as read_error):
                    lost[i] += 1  # hold the last velocity for EXTRAPOLATE_CYCLES, then the position
                    if lost[i] <= self.EXTRAPOLATE_CYCLES:
                        pos[i] += step[i]
                else:
                    lost[i] = 0
        elif self._any_lost:
            self._lost[:] = [0] * len(got)
        np.logical_not(got, out=self.read_error)
        self._any_lost = not got.all()
        self._outstanding = False

    def write(self, u_V: np.ndarray, enable: np.ndarray) -> None:
        self.seq = (self.seq + 1) & self.SEQ_MASK
        self._got[:] = False
        if not self.connected:
            self.write_error[:] = True
            return
        self.write_error[:] = False
        try:
            self._transmit(self.seq, u_V, enable)
        except Exception:  # noqa: BLE001
            self.counters["send_errors"] += 1
            self.write_error[:] = True
            self.connected = False
            return
        self._outstanding = True

    def _transmit_query(self, seq: int) -> None:  # pragma: no cover
        raise NotImplementedError

    WARMUP_QUERIES = 50

    def _first_reading(self, timeout_s: float = 1.0) -> None:
        """Blocking queries of every axis's position (no plant step), for ``open()``: the first
        must answer within ``timeout_s``; ``WARMUP_QUERIES`` more warm up both ends' code
        paths and caches (the first exchanges of a fresh link are several times slower).

        Raises:
            ConnectionError: the device did not answer within ``timeout_s``.
        """
        self._query_once(timeout_s)
        for _ in range(self.WARMUP_QUERIES):
            self._query_once(timeout_s)

    def _query_once(self, timeout_s: float) -> None:
        self.seq = (self.seq + 1) & self.SEQ_MASK
        self._got[:] = False
        self._outstanding = True
        self._query = True
        try:
            self._transmit_query(self.seq)
            ok = self.exchange_blocking(timeout_s)
        finally:
            self._query = False
        if not ok:
            missing = [a for a, g in zip(self.axis_names, self._got) if not g]
            raise ConnectionError(f"{type(self).__name__}: no answer from axes {', '.join(missing)} "
                                  f"within {timeout_s:g} s")
        self.read_error[:] = False
        self.write_error[:] = False

    def exchange_blocking(self, timeout_s: float) -> bool:
        """Wait (blocking, outside the loop) for the outstanding answer; True when every axis answered."""
        deadline = time.perf_counter() + timeout_s
        while not self._got.all() and time.perf_counter() < deadline:
            self._receive()
            time.sleep(0.0002)
        ok = bool(self._got.all())
        self._outstanding = False
        return ok

    def reconnect(self) -> None:
        """Close and open the transport again (blocking; call outside the loop). The axes stay
        faulted in the supervisor until an operator resets them: nothing is re-enabled here."""
        try:
            self._close()
        except Exception:  # noqa: BLE001
            pass
        self._configure()
        self._activate()

    def describe(self) -> dict:
        return {"timeout_s": self.timeout_s, "counters": dict(self.counters)}


# --------------------------------------------------------------------------- device side
class PlantBank:
    """The emulated axes: plants, watchdog, amplifier state, fault schedule.

    Args:
        names: axis names in config order. plants: their ``SimAxisOptions``.
        period_s: loop period [s] (one command = one period). opts: :class:`EmulatorOptions`.
        faults: extra :class:`FaultSpec` (from the CLI) added to ``opts.faults``.
    """

    def __init__(self, names: list[str], plants: list[SimAxisOptions], period_s: float,
                 opts: EmulatorOptions, faults: list[FaultSpec] = (), log=None):
        self.names = list(names)
        rng = np.random.default_rng(opts.seed)           # the sim driver's seeding, axis by axis
        seeds = rng.integers(0, 2**63 - 1, size=len(names))
        self.plants = [AxisPlant(p, period_s, np.random.default_rng(int(s)), opts.substeps)
                       for p, s in zip(plants, seeds)]
        self.opts = opts
        n = len(names)
        self.amp_fault = [False] * n
        self.applied_V = [0.0] * n
        self.enabled = [False] * n
        self.commands = [0] * n          # valid commands applied per axis
        self.received = [0] * n          # command frames received per axis (the fault schedule's clock)
        self.last_cmd = [math.nan] * n   # monotonic time of the last valid command
        self.watchdog_trips = 0
        self.faults = list(opts.faults) + list(faults)
        for f in self.faults:
            if f.axis != "*" and f.axis not in self.names:
                raise ValueError(f"fault on unknown axis {f.axis!r}; axes: {', '.join(self.names)}")
        self.log = log or (lambda msg: print(msg, file=sys.stderr, flush=True))

    def next_fault(self, axes) -> str | None:
        """Count one received command frame for ``axes`` (indexes) and return the fault
        scheduled for it (None: answer normally). A frame-level fault hits every axis it carries."""
        kind = None
        for f in self.faults:
            for k in axes:
                if f.axis in ("*", self.names[k]) and f.start <= self.received[k] < f.start + f.count:
                    kind = f.kind
                    break
            if kind:
                break
        for k in axes:
            self.received[k] += 1
        return kind

    def command(self, i: int, u_V: float, enable: bool) -> None:
        """Apply one valid command to axis i: hold u_V for one period (0 V when disabled or faulted)."""
        self.last_cmd[i] = time.monotonic()
        if self.commands[i] == 0:
            self.log(f"first command {self.names[i]}")
        self.commands[i] += 1
        if not enable:
            self.amp_fault[i] = False   # a disabled command resets a latched fault, as a drive's reset
        on = enable and not self.amp_fault[i]
        u = u_V if on and u_V == u_V else 0.0
        self.enabled[i] = on
        self.applied_V[i] = u
        self.plants[i].step(u)

    def counts(self, i: int, m_per_count: float) -> int:
        """Axis i's encoder count: the plant's quantised position in counts of ``m_per_count``."""
        return int(round(self.plants[i].measured() / m_per_count))

    def check_watchdog(self) -> float:
        """Trip the watchdog of every axis whose last command is older than ``watchdog_s``.

        Returns the seconds until the next check is due (for the server's select timeout).
        """
        now = time.monotonic()
        wd = self.opts.watchdog_s
        due = wd
        for i, t in enumerate(self.last_cmd):
            if t != t:
                continue
            left = t + wd - now
            if left <= 0:
                if not self.amp_fault[i] or self.applied_V[i] != 0.0:
                    self.amp_fault[i] = True
                    self.applied_V[i] = 0.0
                    self.enabled[i] = False
                    self.watchdog_trips += 1
                    self.log(f"watchdog {self.names[i]}: no command for {wd * 1e3:.1f} ms: "
                             f"0 V, amplifier fault")
                self.last_cmd[i] = math.nan
            else:
                due = min(due, left)
        return due


class StreamEndpoint:
    """The device end of a byte stream, for the emulators of the serial and Modbus drivers.

    ``url``: ``socket://HOST:PORT`` or ``tcp://HOST:PORT`` (listen on HOST:PORT, one client at a
    time; a new client replaces the old one), or a filesystem path (make a pty pair, raw mode,
    and symlink PATH to its slave device, the way socat's ``link=`` does).
    """

    def __init__(self, url: str):
        import os
        import socket
        self.url = url
        self.client = None
        self.listener = None
        self.master = None
        self._link = None
        if url.startswith(("socket://", "tcp://")):
            hostport = url.split("://", 1)[1]
            host, _, port = hostport.rpartition(":")
            self.listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            self.listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            self.listener.bind((host or "127.0.0.1", int(port)))
            self.listener.listen(1)
        else:
            import tty
            self.master, self._slave = os.openpty()
            tty.setraw(self._slave)
            tty.setraw(self.master)
            name = os.ttyname(self._slave)
            if os.path.lexists(url):
                os.unlink(url)
            os.symlink(name, url)
            self._link = url

    def wait(self, timeout_s: float) -> bytes | None:
        """Wait up to ``timeout_s`` for bytes; accept a new client on the way. None: nothing."""
        import os
        import select
        import socket
        fds = [f for f in (self.listener, self.client, self.master) if f is not None]
        r, _, _ = select.select(fds, [], [], max(timeout_s, 0.0))
        if not r:
            return None
        if self.listener is not None and self.listener in r:
            conn, _ = self.listener.accept()
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            if self.client is not None:
                self.client.close()
            self.client = conn
            return None
        if self.master is not None:
            try:
                return os.read(self.master, 4096)
            except OSError:
                return None
        try:
            data = self.client.recv(4096)
        except OSError:
            data = b""
        if not data:
            self.client.close()
            self.client = None
            return None
        return data

    def send(self, data: bytes) -> None:
        import os
        if self.master is not None:
            os.write(self.master, data)
        elif self.client is not None:
            try:
                self.client.sendall(data)
            except OSError:
                self.client.close()
                self.client = None

    def disconnect(self) -> None:
        """Drop the link: close the client connection (a pty cannot be unplugged: no-op)."""
        if self.client is not None:
            self.client.close()
            self.client = None

    def close(self) -> None:
        import os
        for s in (self.client, self.listener):
            if s is not None:
                s.close()
        if self.master is not None:
            os.close(self.master)
            os.close(self._slave)
        if self._link and os.path.islink(self._link):
            os.unlink(self._link)


def serve_forever(poll, bank: PlantBank, stop=None, duration_s: float | None = None) -> None:
    """The emulator's main loop: ``poll(timeout_s)`` handles whatever arrived; the watchdog
    runs between requests. Ends when ``stop()`` is true or after ``duration_s``."""
    end = time.monotonic() + duration_s if duration_s else math.inf
    while (stop is None or not stop()) and time.monotonic() < end:
        due = bank.check_watchdog()
        poll(min(due, 0.01))
