"""The servo loop: one process, one thread, every axis of a group, one bus exchange per cycle.

Cycle k (architecture.md, LinuxCNC's read → motion → pid → write order)::

    wake at the absolute deadline (CLOCK_MONOTONIC, integer ns): sleep to deadline − spin,
        then busy-wait the tail; lateness = wake − deadline
    driver.read()                       every axis
    per axis: supervisor input checks → trajectory sample at t = k·Ts → controller.update()
              → following-error/NaN checks; a faulted or disabled axis gets 0 V, enable off
    driver.write(u, enable)             every axis
    record                              one fixed-size row into a preallocated buffer
    timing                              read / control / write phases, turnaround = read start
                                        → write end, lateness, overruns

Overruns: when a wake is one or more whole periods late, the missed periods are counted and
skipped (the deadline is re-anchored on the period grid, ros2_control's rule), never caught up
in a burst. The trajectory time is t = k·Ts over executed cycles, so a simulated plant (which
advances one period per write) and the program stay aligned.

With a virtual clock the loop does not sleep: it runs as fast as it can, with the same results
for the same seed (the simulated plant advances one period per write either way).

Nothing in the cycle allocates a container, blocks, or logs: rows go into a preallocated
float64 buffer through a memoryview and are written to the run log after (or outside) the
cycle.
"""

from __future__ import annotations

import time

import numpy as np

from motorctl.runlog import AXIS_FIELDS, CYCLE_FIELDS, columns_for
from motorctl.safety import FAULT_SHUTDOWN, Supervisor

_NA = len(AXIS_FIELDS)
_NC = len(CYCLE_FIELDS)


class ServoLoop:
    """Run read → control → write cycles for every axis of one driver.

    Args:
        driver: an opened :class:`motorctl.driver.Driver`.
        controllers: list of controllers (``DCDIARC``), one per driver axis, in driver order.
        programs: list of trajectories (``Program``), one per axis.
        supervisor: :class:`Supervisor` for the same axes.
        period_s: loop period [s].
        capacity: rows of the record buffer; the buffer is a ring when a run is longer.
        clock: 'wall' (paced by CLOCK_MONOTONIC) or 'virtual' (as fast as possible).
        spin_us: busy-wait tail before each deadline [µs] (wall clock only).
    """

    def __init__(self, driver, controllers, programs, supervisor: Supervisor, period_s: float,
                 capacity: int, clock: str = "wall", spin_us: float = 60.0):
        if clock not in ("wall", "virtual"):
            raise ValueError(f"clock must be 'wall' or 'virtual', got {clock!r}")
        n = len(driver.axis_names)
        if len(controllers) != n or len(programs) != n:
            raise ValueError("one controller and one program per driver axis")
        self.driver = driver
        self.axis_names = list(driver.axis_names)
        self.controllers = list(controllers)
        self.programs = list(programs)
        self.supervisor = supervisor
        self.period_s = float(period_s)
        self.period_ns = int(round(period_s * 1e9))
        self.clock = clock
        self.spin_ns = int(spin_us * 1000)
        self.columns = columns_for(self.axis_names)
        self.width = len(self.columns)
        self.capacity = int(capacity)
        self.buf = np.zeros((self.capacity, self.width))
        self._mv = memoryview(self.buf.reshape(-1))
        self.u_out = np.zeros(n)
        self.enable_out = np.zeros(n, dtype=bool)
        self.enabled = [True] * n       # operator's request per axis
        self._running = [False] * n     # controller was driving last cycle
        self.k = 0                      # executed cycles
        self.overruns = 0
        self.stop_requested = False

    # ------------------------------------------------------------------ control plane
    def request_stop(self) -> None:
        """Ask the loop to end after the current cycle (safe to call from a signal handler)."""
        self.stop_requested = True

    def rows(self) -> np.ndarray:
        """The recorded rows in time order (a view when the buffer has not wrapped)."""
        if self.k <= self.capacity:
            return self.buf[: self.k]
        s = self.k % self.capacity
        return np.concatenate([self.buf[s:], self.buf[:s]])

    def safe_output(self) -> None:
        """Write 0 V with every amplifier disabled (used on any exit path)."""
        self.u_out[:] = 0.0
        self.enable_out[:] = False
        self.driver.write(self.u_out, self.enable_out)

    # ------------------------------------------------------------------ the loop
    def run(self, n_cycles: int) -> int:
        """Run up to ``n_cycles`` cycles (fewer if a stop is requested). Returns cycles run.

        On return, and on any exception inside, the output is 0 V with amplifiers disabled.
        """
        try:
            return self._run(int(n_cycles))
        finally:
            for i in range(len(self.axis_names)):
                if self._running[i]:
                    self._running[i] = False
            self.safe_output()

    def _run(self, n_cycles: int) -> int:
        mono = time.monotonic_ns
        sleep = time.sleep
        drv = self.driver
        sup = self.supervisor
        ctrls = self.controllers
        progs = self.programs
        pos = drv.position_m
        rerr = drv.read_error
        werr = drv.write_error
        ampf = drv.amp_fault
        uo = self.u_out
        en = self.enable_out
        enabled = self.enabled
        running = self._running
        mv = self._mv
        cap = self.capacity
        width = self.width
        period = self.period_ns
        ts = self.period_s
        spin = self.spin_ns
        wall = self.clock == "wall"
        n = len(self.axis_names)
        rng = range(n)
        faults = sup.fault
        deadline = mono() + period
        done = 0
        for _ in range(n_cycles):
            if self.stop_requested:
                break
            if wall:
                rem = deadline - mono() - spin
                if rem > 0:
                    sleep(rem * 1e-9)
                while mono() < deadline:
                    pass
                wake = mono()
                late = wake - deadline
                if late >= period:
                    missed = late // period
                    self.overruns += missed
                    deadline += missed * period
                deadline += period
            else:
                late = 0
            t0 = mono()
            drv.read()
            t1 = mono()
            k = self.k
            t = k * ts
            base = (k % cap) * width
            for i in rng:
                # a write error last cycle counts like a read error this cycle
                ok = sup.check_input(i, pos[i], rerr[i] or werr[i], ampf[i]) and enabled[i]
                c = ctrls[i]
                xd, vd, ad = progs[i].sample(t)
                if ok:
                    if not running[i]:
                        c.reset(pos[i])
                        running[i] = True
                    u = c.update(pos[i], xd, vd, ad)
                    ok = sup.check_output(i, c.e, vd, u)
                if not ok:
                    running[i] = False
                    u = 0.0
                uo[i] = u
                en[i] = ok
                b = base + _NC + i * _NA
                mv[b] = pos[i]
                mv[b + 1] = xd
                mv[b + 2] = vd
                mv[b + 3] = ad
                mv[b + 4] = u
                mv[b + 5] = c.v
                mv[b + 6] = c.e
                mv[b + 7] = c.p
                mv[b + 8] = c.x2
                th = c.theta_hat
                for j in range(c.n_theta):
                    mv[b + 9 + j] = th[j]
                mv[b + 15] = c.d_hat0
                mv[b + 16] = 1.0 if ok else 0.0
                mv[b + 17] = faults[i]
            t2 = mono()
            drv.write(uo, en)
            t3 = mono()
            mv[base] = t
            mv[base + 1] = late
            mv[base + 2] = t3 - t0
            mv[base + 3] = t1 - t0
            mv[base + 4] = t2 - t1
            mv[base + 5] = t3 - t2
            mv[base + 6] = self.overruns
            self.k = k + 1
            done += 1
        return done

    def shutdown_faults(self) -> None:
        """Latch FAULT_SHUTDOWN on every axis (SIGTERM / exit)."""
        for i in range(len(self.axis_names)):
            self.supervisor.trip(i, FAULT_SHUTDOWN)
