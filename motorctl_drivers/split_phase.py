"""The host side the CAN, serial and Modbus drivers share (one place each).

* :func:`volts_to_counts` / :func:`counts_to_volts`: the voltage command as a scaled signed
  integer (full scale ``full_scale_V`` ↔ the largest count of a ``bits``-wide signed field);
  :func:`to_unsigned` / :func:`to_signed`: two's complement on the wire. The emulated devices
  (``motorctl_emulators``) decode with the same functions.
* :class:`EncoderUnwrap`: a ``bits``-wide wrapping encoder counter → a continuous count
  (the difference of two readings modulo 2^bits, taken as the shortest signed step).
* :class:`CommonOptions`: the settings every bus driver has; :func:`make_budget`: the bus
  budget from the wire time and the measured host round trip.
* :class:`SplitPhaseDriver`: the cycle shared by the bus drivers. ``write()`` sends the command
  of cycle k with sequence number k (non-blocking); the device applies it for one period and
  answers with the encoder reading at the end of that period; ``read()`` of cycle k+1 polls
  (never blocks) for that answer until ``timeout_s`` (shorter than the period on a wall clock) has passed.
  This is LinuxCNC hostmot2's split-phase read-request/read: one exchange per cycle, and the
  same data flow as the simulated driver (write steps the plant, the next read sees it).
  A missing, late, stale (wrong sequence) or corrupt answer, or an error answer, sets
  ``read_error`` for the axes it carried; the position is extrapolated by the last measured
  one-cycle step for up to ``EXTRAPOLATE_CYCLES`` consecutive losses, then held (LinuxCNC's
  advice for a transient packet loss is to stand in for the feedback; the supervisor's leaky
  bucket still counts the cycle and faults the axis when losses persist). A failed send sets
  ``write_error``. Nothing raises inside the cycle.
* :class:`ResetPulses`: the operator's fault reset as a request bit pulsed in the cyclic
  commands (serial flags bit 1, a CAN layout's ``fault_reset`` bit, a Modbus map's
  ``fault_reset``); the host never sends it on its own.
"""

from __future__ import annotations

import math
import select
import time
from typing import Annotated, Literal

import numpy as np
from pydantic import Field

from motorctl.driver import BusBudget, Driver, LifecycleError, StopCheck
from motorctl.schema import StrictModel


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


# --------------------------------------------------------------------------- settings, budget
class CommonOptions(StrictModel):
    """Settings every bus driver has (merged into each driver's ``Options``).

    timeout_s: how long ``read()`` polls for the answer [s]; default half the period. With
        ``loop.clock: wall`` at most 0.8 of the period (the rest of the cycle needs the time;
        the config check refuses more); with ``loop.clock: virtual`` (lockstep with an
        emulated plant) any value: every cycle waits for its answers, so a device that is
        late now and then loses no command.
    round_trip_s: host round trip of one exchange on this machine [s] (driver stack + device
        answering; ``configure()`` measures it, ``benchmarks/bench_transports.py`` too). Added
        to the wire time in the budget. None (default): the median measured by ``configure()``
        once the driver is configured, before that the driver's ``DEFAULT_ROUND_TRIP_S`` (an
        assumption, named as such in the budget); never 0 unless set so explicitly.
    wait: how ``read()`` waits for the answer until ``timeout_s``: 'select' sleeps in
        select() on the transport's file descriptor (never past the deadline; the CPU is free
        meanwhile, so a SCHED_FIFO loop stays clear of RT throttling), 'spin' polls without
        sleeping (lowest latency, for an isolated core). Transports without a descriptor
        (python-can 'virtual') always spin.
    max_bus_load: the fraction of the period the bus may be busy (0.8 leaves room for
        retries and other traffic).
    """

    timeout_s: Annotated[float, Field(gt=0)] | None = None
    wait: Literal["select", "spin"] = "select"
    round_trip_s: Annotated[float, Field(ge=0)] | None = None
    max_bus_load: Annotated[float, Field(gt=0, le=1)] = 0.8


def make_budget(rate_hz: float, wire_s: float, round_trip_s: float, max_load: float,
                what: str, fits: str, source: str = "measured") -> BusBudget:
    """Budget from the wire time [s] and the host round trip [s] of one cycle.

    ``what``: the wire arithmetic, one line. ``fits``: a setting that would carry ``rate_hz``.
    ``source``: where the round trip comes from ('measured', 'configured', 'assumed').
    max rate = ``max_load`` / (wire + round trip) [Hz].
    """
    cycle = wire_s + round_trip_s
    max_rate = max_load / cycle if cycle > 0 else float("inf")
    detail = (f"{what}; wire {wire_s * 1e6:.1f} us + {source} round trip {round_trip_s * 1e6:.1f} us "
              f"= {cycle * 1e6:.1f} us per cycle, {cycle * rate_hz * 100:.0f}% of the "
              f"{1e6 / rate_hz:.0f} us period at {rate_hz:g} Hz (limit {max_load * 100:.0f}% load)")
    suggestion = ""
    if rate_hz > max_rate:
        suggestion = f"set loop.rate_hz to {math.floor(max_rate):d} or less, or {fits}"
    return BusBudget(cycle_time_s=cycle, max_rate_hz=max_rate, detail=detail, suggestion=suggestion)


def round_trip_stats(samples_s) -> dict:
    """Median and maximum [s] of measured exchange times ``samples_s`` (a sequence of floats)."""
    xs = sorted(samples_s)
    n = len(xs)
    if n == 0:
        return {"n": 0, "median_s": None, "max_s": None}
    med = xs[n // 2] if n % 2 else 0.5 * (xs[n // 2 - 1] + xs[n // 2])
    return {"n": n, "median_s": med, "max_s": xs[-1]}


def one_line(exc: BaseException) -> str:
    """An exception as one line (its first line; the type name when it has no text)."""
    text = str(exc).strip().splitlines()
    return text[0] if text else type(exc).__name__


def open_error(what: str, where: str, exc: BaseException) -> OSError:
    """A one-line :class:`OSError` for a link that cannot be opened or set up (``what``: e.g.
    'serial port', ``where``: its name), saying whether it is missing, refused (permission) or
    refused a line setting. The CLI prints it as ``motorctl: error: ...`` (no traceback)."""
    import errno as _errno
    err = getattr(exc, "errno", None)
    msg = one_line(exc)
    low = msg.lower()
    if err == _errno.ENOENT or "no such file" in low or ("could not open port" in low and "no such" in low):
        why = "no such device"
    elif err in (_errno.EACCES, _errno.EPERM) or "permission denied" in low:
        why = "permission denied (add the user to the device's group, e.g. dialout)"
    elif err in (_errno.ECONNREFUSED,) or "connection refused" in low:
        why = "connection refused (nothing listens there)"
    elif err in (_errno.EINVAL, _errno.ENOTTY) or "invalid" in low or "not supported" in low \
            or "unsupported" in low or "inappropriate ioctl" in low:
        why = f"the line settings were refused ({msg})"
    else:
        why = msg
    return OSError(f"{what} {where}: {why}")


# --------------------------------------------------------------------------- the operator's reset
class ResetPulses:
    """The operator's reset of a device's latched fault as a request bit in the cyclic commands,
    one per axis: after :meth:`request` (``motorctl fault-reset``, between cycles), :meth:`bit`
    is True in one command of every :attr:`EVERY` (a rising edge each time, after commands with
    the bit clear) while the axis is disabled and its device reports the fault, at most
    :attr:`TRIES` times, and False otherwise: never on the host's own account, never with the
    amplifier enabled. A device takes the reset on the bit's rising edge with the enable low, as
    a CiA 402 drive takes controlword bit 7 (CiA 402 §6.3.2, transition 15): a request the
    device misses (a lost command) is sent again :attr:`EVERY` cycles later. Allocation-free.

    Args:
        n: number of axes.
    """

    #: cycles between two pulses of a disabled, faulted axis
    EVERY = 8
    #: pulses one operator's reset sends at most
    TRIES = 3

    def __init__(self, n: int):
        self._left = [0] * n                 # cycles of the operator's reset still to send
        self._count = [0] * n

    def request(self, i: int) -> None:
        """The operator's reset of axis ``i`` (outside the cycle): pulse from the next command on."""
        self._count[i] = 0
        self._left[i] = self.TRIES * self.EVERY

    def bit(self, i: int, enable: bool, fault: bool) -> bool:
        """The reset request of axis ``i`` in this cycle's command, its amplifier ``enable`` and
        the ``fault`` its device reported last. A device that no longer reports the fault ends
        the request."""
        if not enable and fault and self._left[i] > 0:
            self._left[i] -= 1
            self._count[i] = (self._count[i] + 1) % self.EVERY
            return self._count[i] == 1
        if not fault:
            self._left[i] = 0
        self._count[i] = 0
        return False


# --------------------------------------------------------------------------- the driver
class SplitPhaseDriver(Driver):
    """Base of the bus drivers (see the module docstring for the cycle).

    Subclasses implement the transport:

    * ``_open_transport()``: open the link (may block); call :meth:`_set_wait_fd`.
    * ``_release_transport()``: close the link; idempotent, never raises for a dead link.
    * ``_transmit(seq, u_V, enable)``: send the command (never block; a failed frame of a
      multi-frame transport sets ``write_error`` for its axes).
    * ``_transmit_query(seq)``: send a request for every axis's position that does not step
      the plant (serial query frame, CAN remote frames, Modbus FC03).
    * ``_receive()``: drain what has arrived without blocking and call :meth:`_accept` for
      each axis answer that decodes and passes its CRC, :meth:`_accept_error` for an error
      answer.

    and :meth:`Driver._full_scale_V` from their settings. The lifecycle hooks are here:
    ``_configure`` opens the transport and checks the device answers (:meth:`_first_reading`),
    ``_activate`` starts the cycle from rest, ``_deactivate`` waits for the answer to the
    0 V command, ``_close`` releases the transport; ``_reconnect`` re-opens a lost link (:attr:`link_down`).

    Counters (for ``describe()`` and the benchmark): timeouts, stale, bad_frames, exceptions,
    send_errors.
    """

    SEQ_MASK = 0xFF
    EXTRAPOLATE_CYCLES = 8
    WARMUP_QUERIES = 50
    #: the round trip the budget assumes before ``configure()`` has measured one and none is
    #: configured [s] (a host with a USB or PCIe adapter, not this machine's loopback)
    DEFAULT_ROUND_TRIP_S = 100e-6
    #: a later answer for an axis that already has one this cycle replaces it (counted stale):
    #: for transports without a sequence number (CANopen PDOs), the newest frame is the freshest
    LAST_WINS = False
    #: how long ``_configure`` waits for the device's first answer [s]
    CONFIGURE_TIMEOUT_S = 1.0
    #: how long ``_deactivate`` waits for the answer to the final 0 V command [s]
    DEACTIVATE_TIMEOUT_S = 0.05
    #: the stop command is sent again after this long without an answer [s] (at least
    #: four read timeouts)
    STOP_RETRY_S = 0.05
    #: the link counts as down (:attr:`link_down`) when no axis has answered for this long [s]
    LINK_DOWN_S = 0.2
    #: the old protocol revision's fault reset in words (serial and CAN revision 1: a command
    #: with enable 0), for the axes whose device clears a latched fault on it
    #: (:meth:`_clears_on_disable`); :meth:`_reset_latched` sends it. None: no such revision
    FAULT_RESET: str | None = None

    def __init__(self, options, axis_options, period_s):
        super().__init__(options, axis_options, period_s)
        n = len(self.axis_names)
        self.timeout_s = options.timeout_s if options.timeout_s is not None else 0.5 * period_s
        self.seq = 0
        self._outstanding = False
        self._got = np.zeros(n, dtype=bool)
        self._step = [0.0] * n               # last measured one-cycle step [m] (extrapolation)
        self._y_last = [math.nan] * n        # last measured position [m]
        self._lost = [0] * n                 # consecutive lost answers per axis
        self._query = False                  # a position query: any sequence number will do
        self._wait_fds: list = []            # descriptors read() may select() on
        self._any_lost = False
        self._query_error = ""               # an error answer to a set-up query (one line)
        self.stop_attempts = 0               # stop commands sent by the last _stop()
        self._unwrap: list[EncoderUnwrap] = []
        self._m_per_count = [1.0] * n
        self._offset_m = [0.0] * n
        self.connected = False
        self._down_cycles = max(1, round(self.LINK_DOWN_S / period_s))
        self.round_trip = round_trip_stats(())      # measured by configure()
        self.counters = {"timeouts": 0, "stale": 0, "bad_frames": 0, "exceptions": 0, "send_errors": 0}
        self._reset_at_setup = False         # configure() sent the fault reset (it starts the watchdog)
        self._pulses = ResetPulses(n)        # the operator's reset request (reset_fault)

    def _set_wait_fd(self, fd) -> None:
        """Called by ``_open_transport()`` with the transport's file descriptor (None: none, spin)."""
        self._wait_fds = [fd] if fd is not None and fd >= 0 and self.options.wait == "select" else []

    # --- transport hooks (subclasses)
    def _open_transport(self) -> None:  # pragma: no cover
        raise NotImplementedError

    def _release_transport(self) -> None:  # pragma: no cover
        raise NotImplementedError

    def _transmit(self, seq: int, u_V: np.ndarray, enable: np.ndarray) -> None:  # pragma: no cover
        raise NotImplementedError

    def _transmit_query(self, seq: int) -> None:  # pragma: no cover
        raise NotImplementedError

    def _receive(self) -> None:  # pragma: no cover
        raise NotImplementedError

    # --- lifecycle hooks
    def _configure(self) -> None:
        """Open the transport, set the device up (:meth:`_set_up_device`), check that every
        axis answers (:meth:`_first_reading`), then say what the device reports latched
        (:meth:`_found_latched`: a fault stays latched until the operator's reset, but on a
        device of the old protocol revision).

        Raises:
            OSError: the link cannot be opened; the device refuses its set-up.
            ConnectionError: the device did not answer within ``CONFIGURE_TIMEOUT_S`` (the
            transport is released again).
        """
        self._open_transport()
        self.connected = True
        try:
            self._set_up_device()
            self._first_reading(self.CONFIGURE_TIMEOUT_S)
            self._found_latched()
        except BaseException:
            self._close()
            raise

    def _clears_on_disable(self, i: int) -> bool:
        """Hook: axis i's device is of the old protocol revision, whose command with the enable
        low clears a fault it latched (:data:`FAULT_RESET`), as its last answer says (default
        False: the device keeps its fault until the operator's reset request)."""
        return False

    def _old_revision(self, names: list[str]) -> str:
        """Hook: the set-up warning for the axes ``names`` whose device is of the old revision
        (:meth:`_clears_on_disable`): which device, how the driver told, and that a fault it
        latched cannot stay latched until the operator's reset."""
        return (f"{self._device_name()}: the device of {', '.join(names)} clears a latched fault on "
                f"{self.FAULT_RESET} (the old protocol revision): a fault it latched cannot stay latched "
                f"until the operator's 'motorctl fault-reset'")

    def _found_latched(self) -> None:
        """What set-up does with the faults its first reading found latched in the device (a
        fault of an earlier run, its command watchdog after an earlier host went away while it
        drove). A device that keeps its fault until the operator's reset request: nothing is
        sent, a warning names the device's state (:meth:`Driver._notice_drive_fault`); the first
        cycle faults the axis and ``motorctl run`` is refused
        (:func:`motorctl.driver.drive_fault_refusal`). A device of the old revision
        (:meth:`_clears_on_disable`) would clear it with the first disabled command of the run:
        a warning says it cannot keep a fault latched, and its reset is sent at once, as before
        (:meth:`_reset_latched`)."""
        old = [self._clears_on_disable(i) for i in range(len(self.axis_names))]
        if any(old):
            self._notice(self._old_revision([a for a, o in zip(self.axis_names, old) if o]), warning=True)
        for i, o in enumerate(old):
            if self.amp_fault[i] and not o:
                self._notice_drive_fault(i, self.fault_state(i) or "the device reports an amplifier fault")
        self._reset_latched("set-up")

    def reset_fault(self, i: int) -> bool:
        """The operator's reset of axis i's device fault (:meth:`Driver.reset_fault`): the
        protocol's reset request, pulsed in the next commands while the axis is disabled and
        its device reports the fault (:class:`ResetPulses`). On a device of the old revision
        (:meth:`_clears_on_disable`) every disabled command is its reset, and the cycles send
        those anyway: True, nothing more to send."""
        if not self._clears_on_disable(i):
            self._pulses.request(i)
        return True

    def _set_up_device(self) -> None:
        """The protocol's set-up messages after the transport is open (default: none)."""

    def _device_name(self) -> str:
        """The device in messages (e.g. 'serial device 1')."""
        return type(self).__name__

    def _reset_latched(self, when: str) -> None:
        """The old revision's fault reset (:data:`FAULT_RESET`: a command with enable 0 and 0 V
        to every axis) where a position query shows a latched fault on an axis whose device is of
        that revision (:meth:`_clears_on_disable`), at set-up (``when`` 'set-up') and again at
        ``activate()`` ('start': the reset starts the device's command watchdog, which may
        latch again before the first cycle). A fault it cleared is a notice; one still latched
        stays in :attr:`amp_fault` (the supervisor faults the axis at the first cycle, with
        :meth:`fault_reason`). Nothing on a device that keeps its fault (the operator's reset
        alone clears it).

        Raises:
            ConnectionError: the device does not answer the reset, or answers with an error.
        """
        if self.FAULT_RESET is None:
            return
        if when == "set-up":
            self._reset_at_setup = False
        old = [self._clears_on_disable(i) for i in range(len(self.axis_names))]
        if not any(old):
            return
        self._query_once(self.CONFIGURE_TIMEOUT_S)
        before = self.amp_fault & np.array(old)
        if not before.any():
            return                      # nothing latched: no command (it would start the watchdog)
        n = len(self.axis_names)
        self.write(np.zeros(n), np.zeros(n, dtype=bool))
        self._query_error = ""
        self._query = True          # an error answering the reset ends the wait at once
        try:
            ok = self.exchange_blocking(self.CONFIGURE_TIMEOUT_S)
        finally:
            self._query = False
        if self._query_error or not ok:
            why = self._query_error or f"no reply within {self.CONFIGURE_TIMEOUT_S:g} s"
            raise ConnectionError(f"{self._device_name()}: the fault reset ({self.FAULT_RESET}) at {when}: {why}")
        cleared = [a for i, a in enumerate(self.axis_names) if before[i] and not self.amp_fault[i]]
        if when == "set-up":
            self._reset_at_setup = bool(cleared)
        elif self._reset_at_setup:
            return                      # latched again by the watchdog that set-up's reset started
        if cleared:
            self._notice(f"{self._device_name()}: at {when}, cleared the amplifier fault latched on "
                         f"{', '.join(cleared)} (a watchdog or a fault of an earlier run) with the "
                         f"old protocol revision's reset, {self.FAULT_RESET}")

    def _activate(self) -> None:
        """Start the cycle from rest: on a device of the old revision, clear what it latched
        since ``configure()`` (:meth:`_reset_latched`), then nothing outstanding, no
        extrapolation carried over from an earlier activation. The protocols have nothing else
        to start on the device: the amplifier enable travels in every command."""
        self._reset_latched("start")
        n = len(self.axis_names)
        self._outstanding = False
        self._got[:] = False
        self._step[:] = [0.0] * n
        self._lost[:] = [0] * n
        self._any_lost = False
        self.read_error[:] = False
        self.write_error[:] = False

    def _stop(self, timeout_s: float) -> list[StopCheck]:
        """The stop as a transaction of its own (blocking, outside the loop), within ``timeout_s``:

        1. settle what is in flight: wait for the answer to the last cycle's command (a device
           that serves one request at a time, as pymodbus's server does, drops a request
           queued behind a late one);
        2. send 0 V with every amplifier off, again every ``STOP_RETRY_S`` until every axis
           has answered it;
        3. read back what the device holds (:meth:`_read_back_stop`).
        """
        names = self.axis_names
        n = len(names)
        clock = time.perf_counter
        deadline = clock() + timeout_s
        if not self.connected:
            return [StopCheck(a, False, "the link is down: the stop could not be sent") for a in names]
        retry = max(self.STOP_RETRY_S, 4.0 * self.timeout_s)
        if self._outstanding:
            self.exchange_blocking(max(0.0, min(retry, deadline - clock())))
        zeros, off = np.zeros(n), np.zeros(n, dtype=bool)
        answered = np.zeros(n, dtype=bool)
        self.stop_attempts = 0
        while not answered.all() and self.connected and clock() < deadline:
            self.stop_attempts += 1
            self.write(zeros, off)
            self.exchange_blocking(max(0.0, min(retry, deadline - clock())))
            answered |= self._got
        if not answered.any():
            why = "the link failed" if not self.connected else \
                f"no answer to {self.stop_attempts} stop command(s) within {timeout_s:g} s"
            return [StopCheck(a, False, why) for a in names]
        return self._read_back_stop(answered, deadline)

    def _read_back_stop(self, answered: np.ndarray, deadline: float) -> list[StopCheck]:
        """Hook: what each axis's device holds after the stop command, read back before
        ``deadline`` (``time.perf_counter`` time). ``answered``: (n_axes,) bool, the axes
        that answered the stop command. Default: the protocol's answer is the confirmation (a
        device applies a command before it answers it)."""
        return [StopCheck(a, bool(answered[i]),
                          "answered the 0 V, amplifier-off command" if answered[i]
                          else "no answer to the 0 V, amplifier-off command")
                for i, a in enumerate(self.axis_names)]

    def _deactivate(self) -> None:
        """Wait (at most ``DEACTIVATE_TIMEOUT_S``) for an answer still outstanding after the
        stop (:meth:`_stop`), so nothing is in flight. A dead link is left as it is
        (``connected`` False)."""
        if not (self._outstanding and self.connected):
            self._outstanding = False
            return
        try:
            self.exchange_blocking(self.DEACTIVATE_TIMEOUT_S)
        except Exception:  # noqa: BLE001  (stopping anyway)
            self.connected = False
        self._outstanding = False

    def _close(self) -> None:
        """Release the transport (sends nothing: 0 V was written by ``deactivate()``)."""
        self.connected = False
        self._outstanding = False
        self._release_transport()

    def _link_down(self) -> bool:
        """The transport failed, or every axis has missed ``LINK_DOWN_S`` of answers."""
        return not self.connected or (self.state == "active" and min(self._lost) >= self._down_cycles)

    def _reconnect(self, timeout_s: float | None) -> None:
        """Release and re-open the transport, then check the device answers as
        ``_configure`` does (within ``timeout_s``, default ``CONFIGURE_TIMEOUT_S``)."""
        try:
            self._close()
        except Exception:  # noqa: BLE001  (a dead link may refuse to close cleanly)
            pass
        saved = self.CONFIGURE_TIMEOUT_S
        if timeout_s is not None:
            self.CONFIGURE_TIMEOUT_S = float(timeout_s)
        try:
            self._configure()
        finally:
            self.CONFIGURE_TIMEOUT_S = saved
        if self.state == "active":
            self._activate()

    # --- answers
    def _accept(self, i: int, seq: int, raw_counts: int, fault: bool) -> None:
        """Take axis i's answer if it carries the expected sequence number (else: stale)."""
        if not self._outstanding or (seq != self.seq and not self._query):
            self.counters["stale"] += 1
            return
        if self._got[i]:
            if self.LAST_WINS:          # a newer frame of the same axis: the older one was late
                self.counters["stale"] += 1
                y = self._unwrap[i].update(raw_counts) * self._m_per_count[i] + self._offset_m[i]
                self._step[i] += y - self._y_last[i]
                self._y_last[i] = y
                self.position_m[i] = y
                self.amp_fault[i] = fault
            return
        self._got[i] = True
        y = self._unwrap[i].update(raw_counts) * self._m_per_count[i] + self._offset_m[i]
        # one cycle's step: after lost answers the last measurement is lost + 1 cycles old
        self._step[i] = (y - self._y_last[i]) / (self._lost[i] + 1) if self._y_last[i] == self._y_last[i] else 0.0
        self._y_last[i] = y
        self.position_m[i] = y
        self.amp_fault[i] = fault

    def _accept_error(self, seq: int | None, why: str = "") -> None:
        """An error answer (serial error frame, Modbus exception, CAN error frame) came in.

        The axes of the request get no position from it, so ``read()`` flags them; the answer
        is counted in ``exceptions`` when it answers the outstanding request (``seq`` is
        its sequence number; None where the transport carries none, e.g. a CAN error frame),
        in ``stale`` when it answers an older one. ``why``: the device's words (e.g. "error
        frame code 1 (bad request)"); an error answering a set-up query ends the query at once
        with them (:meth:`_query_once` raises).
        """
        if seq is not None and (not self._outstanding or (seq != self.seq and not self._query)):
            self.counters["stale"] += 1
            return
        self.counters["exceptions"] += 1
        if self._query:
            self._query_error = why or "an error answer"

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

    # --- blocking exchanges (outside the loop)
    def _first_reading(self, timeout_s: float = 1.0) -> None:
        """Blocking queries of every axis's position (no plant step): the first must answer
        within ``timeout_s`` [s]; ``WARMUP_QUERIES`` more warm up both ends' code paths and
        caches (the first exchanges of a fresh link are several times slower).

        Raises:
            ConnectionError: the device did not answer within ``timeout_s``.
        """
        self._query_once(timeout_s)
        clock = time.perf_counter
        times = []
        for _ in range(self.WARMUP_QUERIES):
            t0 = clock()
            self._query_once(timeout_s)
            times.append(clock() - t0)
        self.round_trip = round_trip_stats(times)

    def _query_once(self, timeout_s: float) -> None:
        self.seq = (self.seq + 1) & self.SEQ_MASK
        self._got[:] = False
        self._outstanding = True
        self._query = True
        self._query_error = ""
        try:
            self._transmit_query(self.seq)
            ok = self.exchange_blocking(timeout_s)
        finally:
            self._query = False
        if self._query_error:
            raise ConnectionError(f"{type(self).__name__}: the device refused the position query: "
                                  f"{self._query_error}")
        if not ok:
            missing = [a for a, g in zip(self.axis_names, self._got) if not g]
            raise ConnectionError(f"{type(self).__name__}: no answer from axes {', '.join(missing)} "
                                  f"within {timeout_s:g} s")
        self.read_error[:] = False
        self.write_error[:] = False

    def exchange_blocking(self, timeout_s: float) -> bool:
        """Wait (blocking, outside the loop) up to ``timeout_s`` [s] for the outstanding
        answer (a set-up query: until an error answer too); True when every axis answered."""
        deadline = time.perf_counter() + timeout_s
        while not self._got.all() and not self._query_error and time.perf_counter() < deadline:
            self._receive()
            time.sleep(0.0002)
        ok = bool(self._got.all())
        self._outstanding = False
        return ok

    def budget_round_trip(self) -> tuple[float, str]:
        """The round trip [s] the budget uses and where it comes from: ``round_trip_s`` when
        configured, else the median ``configure()`` measured, else ``DEFAULT_ROUND_TRIP_S``."""
        if self.options.round_trip_s is not None:
            return float(self.options.round_trip_s), "configured"
        if self.round_trip.get("median_s") is not None:
            return float(self.round_trip["median_s"]), "measured"
        return float(self.DEFAULT_ROUND_TRIP_S), "assumed"

    def describe(self) -> dict:
        rt = self.round_trip
        used, source = self.budget_round_trip()
        d = {"timeout_s": self.timeout_s, "counters": dict(self.counters),
             "round_trip": {"n": rt["n"],
                            "median_us": None if rt["median_s"] is None else round(rt["median_s"] * 1e6, 1),
                            "max_us": None if rt["max_s"] is None else round(rt["max_s"] * 1e6, 1),
                            "budget_us": round(used * 1e6, 1), "budget_source": source}}
        try:
            b = self.budget(1.0 / self.period_s)
            d["budget"] = {"cycle_us": round(b.cycle_time_s * 1e6, 1), "max_rate_hz": round(b.max_rate_hz, 1),
                           "fits": bool(1.0 / self.period_s <= b.max_rate_hz), "detail": b.detail}
        except Exception as exc:  # noqa: BLE001  (a report must not fail the run)
            d["budget"] = {"error": one_line(exc)}
        return d
