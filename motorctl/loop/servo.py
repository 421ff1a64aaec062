"""The servo loop: one process, one thread, every axis of a group, one bus exchange per cycle.

Cycle k (architecture.md, LinuxCNC's read → motion → pid → write order)::

    wake at the absolute deadline (CLOCK_MONOTONIC, integer ns): sleep to deadline − spin,
        then busy-wait the tail; lateness = wake − deadline
    driver.read()                       every axis
    per axis: supervisor input checks → trajectory sample at t = k·Ts (and at t + τ for a
              controller with preview_s = τ > 0: controller.preview()) → controller.update()
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

Per-axis sequencing (used by the daemon; :meth:`run` alone keeps the old behaviour: every axis
follows its program at t = k·Ts from the first cycle)::

    IDLE      0 V, amplifier off; x_d recorded as the measured position
    APPROACH  a jerk-limited Move from where the axis stands to the program's start
              (the controller was reset from the measured position: bumpless start)
    PROGRAM   the configured program, local time t − t_start
    HOLD      after a stop request the program runs to its next rest point (so the ramp to
              rest is the program's own jerk-limited profile), holds there stop_settle cycles,
              then 0 V, amplifier off, IDLE
    JOG       a jerk-limited Move to a target at reduced speed (operator's jog, e.g. back
              inside the soft limits), then HOLD

Commands (:meth:`start_axis`, :meth:`stop_axis`, :meth:`switch_axis`, :meth:`fault_reset`)
are called between cycles (in the ``on_slack`` hook), never inside one; a switch swaps to a
controller built beforehand and takes effect at the next cycle boundary.

Overrun policy ('count' or 'ramp', see ``LoopConfig``): with 'ramp', a missed period makes
every driven axis hold its last output for ``overrun_hold`` cycles, ramp to 0 V over
``overrun_ramp`` cycles, then latch FAULT_OVERRUN (0 V, amplifier off).
"""

from __future__ import annotations

import math
import time

import numpy as np

from motorctl.loop.records import CONTROLLER_SIGNALS, N_SIGNALS, RecordLayout
from motorctl.loop.safety import FAULT_OVERRUN, FAULT_SHUTDOWN, Supervisor
from motorctl.loop.timebase import Timebase

#: bumpless switch: the output step between two controllers fades out over this time [s]
SWITCH_BLEND_S = 0.01

IDLE, APPROACH, PROGRAM, HOLD, JOG = 0, 1, 2, 3, 4
MODE_NAMES = {IDLE: "disabled", APPROACH: "approach", PROGRAM: "tracking", HOLD: "stopping",
              JOG: "jog"}


class ServoLoop:
    """Run read → control → write cycles for every axis of one driver.

    Args:
        driver: an active :class:`motorctl.driver.Driver`.
        controllers: list of :class:`motorctl.control.base.Controller`, one per driver axis,
            in driver order.
        programs: list of trajectories (``Program``), one per axis.
        supervisor: :class:`Supervisor` for the same axes.
        timebase: :class:`Timebase` of the loop (period; seconds → cycles).
        capacity: rows of the record buffer; the buffer is a ring when a run is longer.
        clock: 'wall' (paced by CLOCK_MONOTONIC) or 'virtual' (as fast as possible).
        spin_us: busy-wait tail before each deadline [µs] (wall clock only).
        buffer: optional preallocated record buffer, shape (capacity, layout.width) float64
            (e.g. a shared-memory ring drained by another process).
        heartbeat: optional object with ``publish(k)``, called with the number of executed
            cycles after every cycle (rows below it are complete), LinuxCNC's ``threadbeat``
            (the shared ring: :meth:`motorctl.recorder.flight.SharedRing.publish`, a release
            store).
        on_slack: optional callable(loop) run after every cycle, outside the timed part
            (command mailbox, status publishing); it must return quickly and not block.
        overrun_policy: 'count' or 'ramp'; overrun_hold: cycles; overrun_ramp_s: [s].
        stop_settle_s: how long a stopped axis holds its final position before 0 V [s].
        operated: True for the daemon: every axis starts IDLE and is enabled by
            :meth:`start_axis`; a fault also drops the operator's request. False (``run``):
            every axis follows its program from the first cycle.
    Raises:
        ValueError: a wrong clock or policy, one controller or program too few or many, a
            buffer of the wrong shape.
    """

    def __init__(self, driver, controllers, programs, supervisor: Supervisor, timebase: Timebase,
                 capacity: int, clock: str = "wall", spin_us: float = 60.0, buffer=None,
                 heartbeat=None, on_slack=None, overrun_policy: str = "count",
                 overrun_hold: int = 5, overrun_ramp_s: float = 0.01, stop_settle_s: float = 0.0,
                 operated: bool = False):
        if clock not in ("wall", "virtual"):
            raise ValueError(f"clock must be 'wall' or 'virtual', got {clock!r}")
        n = len(driver.axis_names)
        if len(controllers) != n or len(programs) != n:
            raise ValueError("one controller and one program per driver axis")
        if overrun_policy not in ("count", "ramp"):
            raise ValueError(f"overrun_policy must be 'count' or 'ramp', got {overrun_policy!r}")
        self.driver = driver
        self.axis_names = list(driver.axis_names)
        self.controllers = list(controllers)
        self.programs = list(programs)
        self.supervisor = supervisor
        self.timebase = timebase
        self.period_s = timebase.period_s
        self.period_ns = timebase.period_ns
        self.clock = clock
        self.spin_ns = int(spin_us * 1000)
        self.layout = RecordLayout(self.axis_names)
        self.columns = self.layout.columns
        self.width = self.layout.width
        self.capacity = int(capacity)
        if buffer is None:
            self.buf = np.zeros((self.capacity, self.width))
        else:
            if buffer.shape != (self.capacity, self.width) or buffer.dtype != np.float64:
                raise ValueError(f"buffer must be float64 of shape {(self.capacity, self.width)}")
            self.buf = buffer
        self._mv = memoryview(self.buf.reshape(-1))
        self.heartbeat = heartbeat
        self.on_slack = on_slack
        self.overrun_policy = overrun_policy
        self.overrun_hold = int(overrun_hold)
        self.overrun_ramp = timebase.cycles(overrun_ramp_s, minimum=1)
        self.stop_settle = timebase.cycles(stop_settle_s)
        self.disable_on_fault = bool(operated)
        self.u_out = np.zeros(n)
        self.enable_out = np.zeros(n, dtype=bool)
        self.enabled = [True] * n       # operator's request per axis
        self._running = [False] * n     # controller was driving last cycle
        self.mode = [PROGRAM] * n       # sequencing state per axis (see module docstring)
        self.k_start = [0] * n          # cycle at which the current segment's time is zero
        self.approach = [None] * n      # Move of the approach segment
        self.hold_x = [0.0] * n         # held position in HOLD [m]
        self.settle_left = [0] * n      # HOLD cycles left before 0 V
        self.stop_req = [False] * n
        self.blend_cycles = timebase.cycles(SWITCH_BLEND_S, minimum=1)
        self.blend_left = [0] * n       # switch blend cycles left per axis
        self.blend_off = [math.nan] * n  # output offset being faded out [V] (NaN: not yet taken)
        self.ovr_left = [0] * n         # overrun reaction cycles left per axis
        self.u_last = [0.0] * n         # last output written [V]
        self.k = 0                      # executed cycles
        self.overruns = 0
        self.stop_requested = False
        self._resync = False
        # offsets of the record, found by name once
        lay = self.layout
        self._o_cycle = tuple(lay.cycle(f) for f in ("t", "lateness_ns", "turnaround_ns", "read_ns",
                                                      "control_ns", "write_ns", "overruns"))
        self._o_axis = tuple(lay.axis_field(f) for f in ("y", "x_d", "xd_dot", "xd_ddot", "u",
                                                          "enabled", "fault_bits"))
        self._o_sig = lay.axis_field(next(iter(CONTROLLER_SIGNALS)))
        self._axis_base = tuple(lay.axis_base(i) for i in range(n))
        if operated:
            self.idle_all()

    # ------------------------------------------------------------------ control plane
    def resync(self) -> None:
        """From ``on_slack`` after a deliberate pause (a reconnection while every axis is
        idle): the next cycle starts one period from now instead of counting the pause as
        missed periods (overruns)."""
        self._resync = True

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
        mode = self.mode
        kst = self.k_start
        appr = self.approach
        hold_x = self.hold_x
        settle = self.settle_left
        stop_req = self.stop_req
        ovr_left = self.ovr_left
        u_last = self.u_last
        ramp_policy = self.overrun_policy == "ramp"
        ovr_total = self.overrun_hold + self.overrun_ramp
        ovr_ramp = float(self.overrun_ramp)
        hb = self.heartbeat
        slack = self.on_slack
        dis_on_fault = self.disable_on_fault
        bl_left = self.blend_left
        bl_off = self.blend_off
        bl_n = float(self.blend_cycles)
        oc_t, oc_late, oc_turn, oc_read, oc_ctrl, oc_write, oc_ovr = self._o_cycle
        o_y, o_xd, o_vd, o_ad, o_u, o_en, o_fb = self._o_axis
        o_sig = self._o_sig
        nsig = N_SIGNALS
        sig_e = list(CONTROLLER_SIGNALS).index("e")
        abase = self._axis_base
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
                    if ramp_policy:
                        for i in rng:
                            if running[i] and ovr_left[i] == 0:
                                ovr_left[i] = ovr_total
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
                y = pos[i]
                ok = sup.check_input(i, y, rerr[i] or werr[i], ampf[i]) and enabled[i]
                c = ctrls[i]
                m = mode[i]
                if m == PROGRAM:
                    xd, vd, ad = progs[i].sample((k - kst[i]) * ts)
                elif m == APPROACH:
                    mv_ = appr[i]
                    tl = (k - kst[i]) * ts
                    xd, vd, ad = mv_.sample(mv_.t0 + tl)
                    if tl >= mv_.duration:
                        mode[i] = PROGRAM
                        kst[i] = k + 1
                elif m == JOG:
                    mv_ = appr[i]
                    tl = (k - kst[i]) * ts
                    xd, vd, ad = mv_.sample(mv_.t0 + tl)
                    if tl >= mv_.duration:         # arrived: hold, then 0 V, amplifier off
                        mode[i] = HOLD
                        hold_x[i] = xd
                        settle[i] = self.stop_settle
                elif m == HOLD:
                    xd = hold_x[i]
                    vd = ad = 0.0
                    s_ = settle[i] - 1
                    settle[i] = s_
                    if s_ <= 0:
                        mode[i] = IDLE
                        enabled[i] = False
                        stop_req[i] = False
                        ok = False
                else:
                    xd = y
                    vd = ad = 0.0
                    ok = False
                if stop_req[i] and (m == PROGRAM or m == APPROACH) and vd == 0.0 and ad == 0.0:
                    mode[i] = HOLD
                    hold_x[i] = xd
                    settle[i] = self.stop_settle
                if ok:
                    n_o = ovr_left[i]
                    if n_o > 0:
                        # overrun policy 'ramp': hold the last output, ramp it to 0 V, latch
                        n_o -= 1
                        ovr_left[i] = n_o
                        u = u_last[i]
                        if n_o < ovr_ramp:
                            u = u * n_o / (n_o + 1.0)
                        if n_o == 0:
                            sup.trip(i, FAULT_OVERRUN)
                            ok = False
                    else:
                        if not running[i]:
                            c.reset(y)
                            running[i] = True
                        pre = c.preview_s
                        if pre > 0.0:
                            # the law predicts over an input delay: the desired trajectory
                            # at t + preview_s, from what the axis follows now
                            mn = mode[i]
                            if mn == PROGRAM:
                                c.preview(*progs[i].sample((k - kst[i]) * ts + pre))
                            elif mn == APPROACH or mn == JOG:
                                mv_ = appr[i]
                                c.preview(*mv_.sample(mv_.t0 + (k - kst[i]) * ts + pre))
                            else:
                                c.preview(xd, vd, ad)
                        u = c.update(y, xd, vd, ad, t)
                        nb = bl_left[i]
                        if nb > 0:
                            # bumpless switch: the step between the outgoing controller's last
                            # output and the incoming one's first fades out linearly
                            off = bl_off[i]
                            if off != off:
                                off = u_last[i] - u
                                bl_off[i] = off
                            u += off * nb / bl_n
                            bl_left[i] = nb - 1
                        ok = sup.check_output(i, c.signals[sig_e], vd, u)
                if not ok:
                    running[i] = False
                    ovr_left[i] = 0
                    u = 0.0
                    if dis_on_fault and faults[i] and mode[i] != IDLE:
                        mode[i] = IDLE
                        enabled[i] = False
                        stop_req[i] = False
                uo[i] = u
                u_last[i] = u
                en[i] = ok
                b = base + abase[i]
                mv[b + o_y] = y
                mv[b + o_xd] = xd
                mv[b + o_vd] = vd
                mv[b + o_ad] = ad
                mv[b + o_u] = u
                sg = c.signals
                bs = b + o_sig
                for j in range(nsig):
                    mv[bs + j] = sg[j]
                mv[b + o_en] = 1.0 if ok else 0.0
                mv[b + o_fb] = faults[i]
            t2 = mono()
            drv.write(uo, en)
            t3 = mono()
            mv[base + oc_t] = t
            mv[base + oc_late] = late
            mv[base + oc_turn] = t3 - t0
            mv[base + oc_read] = t1 - t0
            mv[base + oc_ctrl] = t2 - t1
            mv[base + oc_write] = t3 - t2
            mv[base + oc_ovr] = self.overruns
            self.k = k + 1
            done += 1
            if hb is not None:
                hb.publish(k + 1)
            if slack is not None:
                slack(self)
                if self._resync:             # a deliberate pause between cycles (reconnect)
                    self._resync = False
                    deadline = mono() + period
        return done

    # ------------------------------------------------------------------ per-axis commands
    # Called between cycles (from on_slack or before run), never from inside a cycle.
    def idle_all(self) -> None:
        """Every axis IDLE and not requested (the daemon's state at start-up)."""
        for i in range(len(self.axis_names)):
            self.mode[i] = IDLE
            self.enabled[i] = False
            self.stop_req[i] = False
            self._running[i] = False

    def start_axis(self, i: int, approach, controller=None) -> None:
        """Enable axis i: reset its controller from the measured position, then follow the
        jerk-limited ``approach`` (a ``trajectory.Move`` from where the axis stands to the
        program's start) and the program after it. ``controller`` replaces the axis's
        controller when given (built beforehand). Raises RuntimeError if the axis is faulted."""
        self._enable(i, APPROACH, approach, controller)

    def jog_axis(self, i: int, move, controller=None) -> None:
        """Move axis i along the jerk-limited ``move`` (from where it stands), hold at its end
        for the settle time, then 0 V and amplifier off (IDLE). Used to bring an axis back
        inside its soft limits (:meth:`Supervisor.begin_recovery`) or to position it.
        Raises RuntimeError if the axis is faulted or not idle."""
        if self.mode[i] != IDLE:
            raise RuntimeError(f"axis {self.axis_names[i]} is not disabled ({MODE_NAMES[self.mode[i]]})")
        self._enable(i, JOG, move, controller)

    def _enable(self, i: int, mode: int, move, controller) -> None:
        """Bumpless enable of axis i into ``mode`` along ``move`` (between cycles)."""
        if self.supervisor.fault[i]:
            raise RuntimeError(f"axis {self.axis_names[i]} is in fault: {self.supervisor.reason(i)}")
        if controller is not None:
            self.controllers[i] = controller
        self.controllers[i].reset(float(self.driver.position_m[i]))
        self._running[i] = True
        self.approach[i] = move
        self.k_start[i] = self.k
        self.stop_req[i] = False
        self.ovr_left[i] = 0
        self.mode[i] = mode
        self.enabled[i] = True

    def stop_axis(self, i: int) -> None:
        """Ask axis i to come to rest along its jerk-limited profile, then 0 V, amplifier off."""
        if self.mode[i] != IDLE:
            self.stop_req[i] = True

    def switch_axis(self, i: int, controller, keep_theta: bool = True) -> None:
        """Swap axis i's controller for ``controller`` (built beforehand) at this cycle
        boundary. The incoming controller inherits θ̂ (the common entries) and starts from the
        measured position; the difference between the outgoing controller's last output and
        the incoming one's first is added and faded out linearly over 10 ms (classic bumpless
        transfer), so the output does not step at the switch."""
        old = self.controllers[i]
        if controller is old:
            return
        if keep_theta:
            controller.inherit(old)
        if self._running[i]:
            controller.reset(float(self.driver.position_m[i]))
            self.blend_off[i] = math.nan
            self.blend_left[i] = self.blend_cycles
        self.controllers[i] = controller

    def fault_reset(self, i: int) -> tuple[bool, str]:
        """Clear axis i's latched fault if the cause is gone; the axis stays disabled."""
        ok, why = self.supervisor.reset(i, float(self.driver.position_m[i]),
                                        bool(self.driver.amp_fault[i]))
        return ok, why

    def shutdown_faults(self) -> None:
        """Latch FAULT_SHUTDOWN on every axis (SIGTERM / exit)."""
        for i in range(len(self.axis_names)):
            self.supervisor.trip(i, FAULT_SHUTDOWN)
