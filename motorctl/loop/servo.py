"""The servo loop: one process, one thread, every axis of a group, one bus exchange per cycle.

Cycle k (architecture.md, LinuxCNC's read → motion → pid → write order)::

    wake at the absolute deadline (CLOCK_MONOTONIC, integer ns; motorctl.loop.pacing): sleep
        to deadline − spin, [rehearse the next cycle,] busy-wait the tail; lateness = wake −
        deadline
    driver.read()                       every axis
    servo_cycle(...)                    one compiled call for every axis (motorctl.loop.cycle):
                                        supervisor input checks → desired(k) of the axis's mode
                                        → the law → following-error/NaN checks (a faulted or
                                        disabled axis gets 0 V, enable off) → the record row
        [laws without a compiled step: controller.update() from Python (with preview() at
         t + τ for preview_s = τ > 0), then a second call finishes those axes]
    driver.write(u, enable)             every axis
    timing                              read / control / write phases, turnaround = read start
                                        → write end, lateness, overruns

Overruns: when a wake is one or more whole periods late, the missed periods are counted and
skipped (the deadline is re-anchored on the period grid, ros2_control's rule), never caught up
in a burst. The trajectory time is t = k·Ts over executed cycles, so a simulated plant (which
advances one period per write) and the program stay aligned.

With a virtual clock the loop does not sleep: it runs as fast as it can, with the same results
for the same seed (the simulated plant advances one period per write either way).

Nothing in the cycle allocates a container, blocks, or logs: rows go into a preallocated
float64 buffer (written to the run log after, or outside, the cycle); the per-axis state lives
in the arrays of :mod:`motorctl.loop.cycle`, and the attributes below are views of them.

Per-axis sequencing (used by the daemon; :meth:`run` alone keeps the old behaviour: every axis
follows its program at t = k·Ts from the first cycle)::

    IDLE      0 V, amplifier off; x_d recorded as the measured position
    STREAM    command mode: holds where it was enabled, then follows the setpoints streamed
              into the ring (:mod:`motorctl.loop.stream`); an empty ring while moving, or a
              stop, brakes it jerk-limited to rest (a stop then HOLDs and goes IDLE)
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
import resource
import time

import numpy as np

from motorctl.control.kernels import LAW_PY, N_LAYOUT, check_law_code
from motorctl.jit import entry
from motorctl.loop import cycle as C
from motorctl.loop.cycle import APPROACH, HOLD, IDLE, JOG, PROGRAM, STREAM, servo_cycle
from motorctl.loop.pacing import Pacer
from motorctl.loop.records import CONTROLLER_SIGNALS, N_SIGNALS, RecordLayout
from motorctl.loop.safety import FAULT_SHUTDOWN, SF_YLAST, Supervisor
from motorctl.loop.stream import SP_OUT_SEQ, SetpointRing
from motorctl.loop.timebase import Timebase
from motorctl.loop.trajectory import MOVE_W, TABLE_HEAD, Program

#: bumpless switch: the output step between two controllers fades out over this time [s]
SWITCH_BLEND_S = 0.01
#: how long the operator's fault reset waits for a drive to leave its fault once its reset was
#: sent (CiA 402 transition 15, a Modbus reset bit) before it is refused [s]
FAULT_RESET_WAIT_S = 0.1
#: the law rows' width (floats, ints): C2's state block is 220 and 12
LAW_ROW_FLOATS, LAW_ROW_INTS = 256, 16

MODE_NAMES = {IDLE: "disabled", APPROACH: "approach", PROGRAM: "tracking", HOLD: "stopping",
              JOG: "jog", STREAM: "command"}
__all__ = ["APPROACH", "HOLD", "IDLE", "JOG", "MODE_NAMES", "PROGRAM", "STREAM", "SWITCH_BLEND_S", "ServoLoop"]


def _page_faults() -> int:
    """The calling thread's page faults so far, minor and major (getrusage(2) RUSAGE_THREAD)."""
    ru = resource.getrusage(resource.RUSAGE_THREAD)
    return ru.ru_minflt + ru.ru_majflt


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
        warm_caches: in that tail, rehearse the next cycle (the driver's exchange and the
            cycle on copies, :func:`motorctl.loop.cycle.rehearse`, :meth:`Driver.rehearse`),
            waking :data:`motorctl.loop.pacing.REHEARSAL_NS` (or twice the last rehearsal)
            earlier for it, so that the cycle finds its code and data in the CPU's caches
            (wall clock only).
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
        layout: the record's :class:`RecordLayout` for the driver's axes, with the signals the
            laws declare of their own (``own``: those of every law the loop may run on an
            axis); None: the fixed fields only.
    Attributes (views of the cycle's state, indexed by axis): mode, enabled, stop_req;
        controllers, programs (lists); k (executed cycles), overruns; page_faults (the page
        faults the loop's thread took inside :meth:`run`, minor and major, getrusage(2)
        RUSAGE_THREAD: 0 once the real-time set-up has prefaulted its memory).
    Raises:
        ValueError: a wrong clock or policy, one controller or program too few or many, a
            buffer of the wrong shape, a layout of other axes.
    """

    def __init__(self, driver, controllers, programs, supervisor: Supervisor, timebase: Timebase,
                 capacity: int, clock: str = "wall", spin_us: float = 60.0, warm_caches: bool = True,
                 buffer=None,
                 heartbeat=None, on_slack=None, overrun_policy: str = "count",
                 overrun_hold: int = 5, overrun_ramp_s: float = 0.01, stop_settle_s: float = 0.0,
                 operated: bool = False, stream=None, layout: RecordLayout | None = None):
        if clock not in ("wall", "virtual"):
            raise ValueError(f"clock must be 'wall' or 'virtual', got {clock!r}")
        n = len(driver.axis_names)
        if len(controllers) != n or len(programs) != n:
            raise ValueError("one controller and one program per driver axis")
        if overrun_policy not in ("count", "ramp"):
            raise ValueError(f"overrun_policy must be 'count' or 'ramp', got {overrun_policy!r}")
        self.driver = driver
        self.axis_names = list(driver.axis_names)
        self.controllers = [None] * n
        self.programs = list(programs)
        self.supervisor = supervisor
        self.timebase = timebase
        self.period_s = timebase.period_s
        self.period_ns = timebase.period_ns
        self.clock = clock
        self.spin_ns = int(spin_us * 1000)
        self.warm_caches = bool(warm_caches)
        # the setpoint stream of commanded motion (motorctl.loop.stream; the daemon's is shared)
        self.stream = stream if stream is not None else SetpointRing(1, n, shared=False)
        self.layout = layout if layout is not None else RecordLayout(self.axis_names, outputs=self.stream.outputs)
        if self.layout.axis_names != self.axis_names:
            raise ValueError(f"layout of axes {self.layout.axis_names}, driver axes {self.axis_names}")
        if self.layout.outputs != self.stream.outputs:
            raise ValueError(f"layout of outputs {self.layout.outputs}, stream outputs {self.stream.outputs}")
        self.columns = self.layout.columns
        self.width = self.layout.width
        self.capacity = int(capacity)
        if buffer is None:
            # written once here (np.full, not calloc's untouched zero pages): the loop's first
            # store to a row never faults a page in, and mlockall's MCL_ONFAULT keeps it locked
            self.buf = np.full((self.capacity, self.width), 0.0)
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
        self.blend_cycles = timebase.cycles(SWITCH_BLEND_S, minimum=1)
        self.fault_reset_cycles = timebase.cycles(FAULT_RESET_WAIT_S, minimum=1)
        self._reset_until = [-1] * len(self.axis_names)   # the cycle a drive's reset is waited for until
        self.u_out = np.zeros(n)
        self.enable_out = np.zeros(n, dtype=bool)
        # the cycle's state (motorctl.loop.cycle), and views of it by name
        self.ax, self.axf = C.new_state(n)
        ax = self.ax
        self.mode = ax[:, C.A_MODE]            # sequencing state per axis (module docstring)
        self.enabled = ax[:, C.A_ENABLED]      # operator's request per axis
        self.stop_req = ax[:, C.A_STOPREQ]
        self._running = ax[:, C.A_RUNNING]     # controller was driving last cycle
        width = max(p.table.size for p in self.programs)
        self._prog = np.zeros((n, width))
        for i, p in enumerate(self.programs):
            self._prog[i, :p.table.size] = p.table
        self._move = np.zeros((n, TABLE_HEAD + MOVE_W))
        self._sig = np.full((n, N_SIGNALS), np.nan)
        # the laws' own signals (record columns own_start...): the last values, written into
        # every row after the cycle; per axis the (offset in the law's signals, offset here)
        # of the running law's
        self._own = np.full(self.layout.outputs_base - self.layout.own_start, np.nan)
        self._own_at = {key: j for j, key in enumerate((a, f) for a in self.axis_names for f in self.layout.own[a])}
        self._own_map = [()] * n
        # the law rows: wide enough for C2 (the largest compiled law), grown when a law needs more
        self._cf = np.zeros((n, LAW_ROW_FLOATS))
        self._ci = np.zeros((n, LAW_ROW_INTS), dtype=np.int64)
        self._args_changed = False
        self._cl = np.zeros((n, N_LAYOUT), dtype=np.int64)
        lay = self.layout
        self._offs = np.array([lay.axis_field(f) for f in ("y", "x_d", "xd_dot", "xd_ddot", "u", "enabled",
                                                            "fault_bits")]
                              + [lay.axis_field(next(iter(CONTROLLER_SIGNALS))), lay.axis_field("mode")]
                              + [lay.axis_base(i) for i in range(n)] + [lay.outputs_base], dtype=np.int64)
        self._lp = np.zeros(C.N_LP)
        self._lp[C.LP_TS] = self.period_s
        self._lp[C.LP_SETTLE] = self.stop_settle
        self._lp[C.LP_OVR_RAMP] = self.overrun_ramp
        self._lp[C.LP_BLEND_N] = self.blend_cycles
        self._lp[C.LP_DISABLE_ON_FAULT] = 1.0 if operated else 0.0
        self._py = []                          # axes whose law runs from Python
        for i, c in enumerate(controllers):
            self._adopt(i, c)
        self.k = 0                             # executed cycles
        self.overruns = 0
        self.page_faults = 0
        self.stop_requested = False
        self._resync = False
        self._o_cycle = tuple(lay.cycle(f) for f in ("t", "lateness_ns", "turnaround_ns", "read_ns",
                                                      "control_ns", "write_ns", "overruns"))
        if operated:
            self.idle_all()
        self._warm_up()

    def _cycle_arrays(self, copies: bool = False) -> tuple:
        """The arrays :func:`servo_cycle` works on, in the order of
        :data:`motorctl.loop.cycle.CYCLE_FIELDS`; ``copies``: copies of them (of the record
        ring, its first row), for a call that changes nothing."""
        drv = self.driver
        arrays = (drv.position_m, drv.read_error, drv.write_error, drv.amp_fault, self.u_out, self.enable_out,
                  self.ax, self.axf, self._prog, self._move, self.supervisor.si, self.supervisor.sf, self._sig,
                  self._cf, self._ci, self._cl, self.buf, self._offs, self._lp, self.stream.rows,
                  self.stream.ctl)
        if copies:
            arrays = tuple(a[:1].copy() if a is self.buf else a.copy() for a in arrays)
        return arrays

    def _cycle_state(self, copies: bool = False) -> C.CycleState:
        """:meth:`_cycle_arrays` as the bundle :func:`servo_cycle` takes
        (:class:`motorctl.loop.cycle.CycleState`)."""
        return C.cycle_state(*self._cycle_arrays(copies))

    def _warm_up(self) -> None:
        """Compile (or load from the cache) the cycle now and run it on copies of the state, so
        that the first cycle never pays for it (a drive's watchdog would not wait that long)."""
        st = self._cycle_state(copies=True)
        self._cycle = entry(servo_cycle, 0, 0, st)    # the compiled call, for every cycle
        for phase in (C.CYCLE_BEFORE, C.CYCLE_AFTER, C.CYCLE_ALL):
            self._cycle(phase, 0, st)
        # the rehearsal's refresh (wall clock): compiled, or loaded, on the virtual clock too, so
        # that ``motorctl warmup`` (a virtual-clock run) leaves nothing to compile for the daemon
        refresh = entry(C.refresh, 0, st, self._cycle_state(copies=True))
        self._refresh = refresh if self.clock == "wall" and self.warm_caches else None

    def _adopt(self, i: int, c) -> None:
        """Make c axis i's controller (between cycles): the outgoing one takes its state back
        (:meth:`Controller.detach`); a compiled law moves its state into the cycle's rows
        (:meth:`Controller.attach`, the rows grown when it needs more)."""
        old = self.controllers[i]
        if old is c:
            return
        if old is not None:
            old.detach()
        law = check_law_code(c.law_code, c.name)
        if law != LAW_PY and c.own_signals:
            raise ValueError(f"controller {c.name!r}: own signals are recorded from a law that runs from Python only")
        a = self.axis_names[i]
        self._own_map[i] = tuple((c.own_index(f), self._own_at[(a, f)]) for f in c.own_signals
                                 if (a, f) in self._own_at)
        for (_a, _f), j in self._own_at.items():
            if _a == a:
                self._own[j] = np.nan          # a signal the new law does not have: NaN, never stale
        if law != LAW_PY:
            nf, ni = c.state_size()
            if nf > self._cf.shape[1] or ni > self._ci.shape[1]:
                self._grow(max(nf, self._cf.shape[1]), max(ni, self._ci.shape[1]))
            if hasattr(c, "link_axes"):        # a pair law (gtcf): its partner's index in these rows
                c.link_axes(self.axis_names, i)
            c.attach(self._sig[i], self._cf[i], self._ci[i], self._cl[i])
        self.controllers[i] = c
        self.ax[i, C.A_LAW] = law
        self._py = [j for j in range(len(self.axis_names)) if self.ax[j, C.A_LAW] == LAW_PY]

    def _grow(self, nf: int, ni: int) -> None:
        """Wider law rows: the attached laws move into the new ones."""
        attached = [(j, c) for j, c in enumerate(self.controllers) if c is not None and c.law_code != LAW_PY]
        for _, c in attached:
            c.detach()
        self._cf = np.zeros((len(self.axis_names), nf))
        self._ci = np.zeros((len(self.axis_names), ni), dtype=np.int64)
        for j, c in attached:
            c.attach(self._sig[j], self._cf[j], self._ci[j], self._cl[j])
        self._args_changed = True

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
        faults = _page_faults()
        try:
            return self._run(int(n_cycles))
        finally:
            self.page_faults += _page_faults() - faults
            self._running[:] = 0
            self.safe_output()

    def _run(self, n_cycles: int) -> int:
        mono = time.monotonic_ns
        drv, cycle, mv, width, cap = self.driver, self._cycle, self._mv, self.width, self.capacity
        buf, own, own_at, own_end = self.buf, self._own, self.layout.own_start, self.layout.outputs_base
        hb, slack, u_out, en_out, period = self.heartbeat, self.on_slack, self.u_out, self.enable_out, self.period_ns
        oc_t, oc_late, oc_turn, oc_read, oc_ctrl, oc_write, oc_ovr = self._o_cycle
        st = self._use_state()
        out_ctl, out_names, out_vals = self.stream.ctl, self.stream.outputs, self.stream.applied()
        out_seq = -1 if out_names else out_ctl[SP_OUT_SEQ]   # with outputs: applied at the first cycle
        pacer = (Pacer(period, self.spin_ns, self._rehearse if self._refresh is not None else None)
                 if self.clock == "wall" else None)
        done = 0
        for _ in range(n_cycles):
            if self.stop_requested:
                break
            late = pacer.wait() if pacer is not None else 0
            if late >= period:
                self._overran(late // period)
            t0 = mono()
            drv.read()
            t1 = mono()
            k = self.k
            if not self._py:
                cycle(C.CYCLE_ALL, k, st)
            elif cycle(C.CYCLE_BEFORE, k, st):
                self._python_laws(k)
                cycle(C.CYCLE_AFTER, k, st)
            if own.size:
                buf[k % cap, own_at:own_end] = own
            t2 = mono()
            if out_ctl[SP_OUT_SEQ] != out_seq:   # the stream switched an output at this row
                out_seq = out_ctl[SP_OUT_SEQ]
                drv.apply_outputs(out_names, out_vals)
            drv.write(u_out, en_out)
            t3 = mono()
            base = (k % cap) * width
            mv[base + oc_t] = k * self.period_s
            mv[base + oc_late] = late
            mv[base + oc_turn] = t3 - t0
            mv[base + oc_read] = t1 - t0
            mv[base + oc_ctrl] = t2 - t1
            mv[base + oc_write] = t3 - t2
            mv[base + oc_ovr] = self.overruns
            drv.service()                    # the driver's work between exchanges, untimed
            self.k = k + 1
            done += 1
            if hb is not None:
                hb.publish(k + 1)
            if slack is not None:
                slack(self)
                if self._resync:             # a deliberate pause between cycles (reconnect)
                    self._resync = False
                    if pacer is not None:
                        pacer.restart()
                if self._args_changed:       # a switch grew the law rows
                    st = self._use_state()
        return done

    def _use_state(self) -> C.CycleState:
        """The cycle's bundle for the cycles to come (and the rehearsal's copies of it), made
        anew when a switch grew the law rows."""
        self._args_changed = False
        self._st = self._cycle_state()
        self._scratch = self._cycle_state(copies=True) if self._refresh is not None else None
        return self._st

    def _rehearse(self) -> None:
        """The next cycle run ahead on copies, in the pacer's tail before the deadline
        (``warm_caches``; :func:`motorctl.loop.cycle.rehearse`, :meth:`Driver.rehearse`)."""
        self.driver.rehearse(self.u_out, self.enable_out)
        C.rehearse(self._cycle, self._refresh, C.CYCLE_BEFORE if self._py else C.CYCLE_ALL, self.k, self._st,
                   self._scratch)

    def _overran(self, missed: int) -> None:
        """A wake ``missed`` whole periods late: counted; with the 'ramp' policy every driven
        axis not already ramping starts its hold-and-ramp."""
        self.overruns += missed
        if self.overrun_policy == "ramp":
            ax, total = self.ax, self.overrun_hold + self.overrun_ramp
            for i in range(len(self.axis_names)):
                if ax[i, C.A_RUNNING] and ax[i, C.A_OVR] == 0:
                    ax[i, C.A_OVR] = total

    def _python_laws(self, k: int) -> None:
        """The laws without a compiled step, for the axes the cycle left pending: reset when the
        axis starts, preview (the desired trajectory at t + preview_s, from what the axis
        follows now) and update; their output and signals go back to the cycle's rows."""
        ax, axf, ts = self.ax, self.axf, self.period_s
        for i in self._py:
            pend = ax[i, C.A_PEND]
            if pend == C.PEND_NONE:
                continue
            c = self.controllers[i]
            y, xd, vd, ad = axf[i, C.X_Y], axf[i, C.X_XD], axf[i, C.X_VD], axf[i, C.X_AD]
            if pend == C.PEND_RESET:
                c.reset(float(y))
            pre = c.preview_s
            if pre > 0.0:
                c.preview(*C.desired(i, k, pre, ax, axf, self._prog, self._move, ts))
            axf[i, C.X_U] = c.update(float(y), float(xd), float(vd), float(ad), k * ts)
            if self._own_map[i]:
                self._sig[i] = c.signals[:N_SIGNALS]
                for src, dst in self._own_map[i]:
                    self._own[dst] = c.signals[src]
            else:
                self._sig[i] = c.signals

    # ------------------------------------------------------------------ per-axis commands
    # Called between cycles (from on_slack or before run), never from inside a cycle.
    def idle_all(self) -> None:
        """Every axis IDLE and not requested (the daemon's state at start-up)."""
        self.mode[:] = IDLE
        self.enabled[:] = 0
        self.stop_req[:] = 0
        self._running[:] = 0

    def start_axis(self, i: int, approach, controller=None, delay_cycles: int = 0) -> None:
        """Enable axis i: reset its controller from the measured position, then follow the
        jerk-limited ``approach`` (a ``trajectory.Move`` from where the axis stands to the
        program's start) and the program after it. ``controller`` replaces the axis's
        controller when given (built beforehand); ``delay_cycles``: the axis holds the
        approach's start under control that many cycles before it moves. Raises RuntimeError
        if the axis is faulted."""
        self._enable(i, APPROACH, approach, controller, delay_cycles)

    def jog_axis(self, i: int, move, controller=None) -> None:
        """Move axis i along the jerk-limited ``move`` (from where it stands), hold at its end
        for the settle time, then 0 V and amplifier off (IDLE). Used to bring an axis back
        inside its soft limits (:meth:`Supervisor.begin_recovery`) or to position it.
        Raises RuntimeError if the axis is faulted or not idle."""
        if self.mode[i] != IDLE:
            raise RuntimeError(f"axis {self.axis_names[i]} is not disabled ({MODE_NAMES[int(self.mode[i])]})")
        self._enable(i, JOG, move, controller)

    def _enable(self, i: int, mode: int, move, controller, delay_cycles: int = 0) -> None:
        """Bumpless enable of axis i into ``mode`` along ``move`` (between cycles)."""
        if self.supervisor.fault[i]:
            raise RuntimeError(f"axis {self.axis_names[i]} is in fault: {self.supervisor.reason(i)}")
        if controller is not None:
            self._adopt(i, controller)
        self.controllers[i].reset(float(self.driver.position_m[i]))
        ax = self.ax
        ax[i, C.A_RUNNING] = 1
        self._move[i] = 0.0
        self._move[i, :move.table.size] = move.table
        ax[i, C.A_KST] = self.k + int(delay_cycles)    # before it: the move's start (sample_table)
        ax[i, C.A_STOPREQ] = 0
        ax[i, C.A_OVR] = 0
        ax[i, C.A_MODE] = mode
        ax[i, C.A_ENABLED] = 1

    def command_axis(self, i: int, a_max: float, j_max: float, controller=None) -> None:
        """Enable axis i in command mode (STREAM): reset its controller from the measured
        position and hold there, then follow the setpoints streamed into :attr:`stream`; an
        underrun or a stop brakes it with ``a_max`` [m/s²] and ``j_max`` [m/s³]
        (:mod:`motorctl.loop.stream`). Raises RuntimeError if the axis is faulted."""
        y = float(self.driver.position_m[i])
        axf = self.axf
        axf[i, C.X_SX], axf[i, C.X_SV], axf[i, C.X_SA] = y, 0.0, 0.0
        axf[i, C.X_AMAX], axf[i, C.X_JMAX] = a_max, j_max
        self._enable(i, STREAM, Program.hold(y), controller)

    def shift_axis(self, i: int, delta_m: float) -> None:
        """Between cycles, with the driver's reading of axis i shifted by ``delta_m`` [m] from
        the next read (homing): its STREAM setpoint and the encoder-jump check's last reading
        shift with it, and its law restarts from the new reading at the next cycle (bumpless,
        as at a start)."""
        self.axf[i, C.X_SX] += delta_m
        self.supervisor.sf[i, SF_YLAST] += delta_m
        self._running[i] = 0

    def stop_axis(self, i: int) -> None:
        """Ask axis i to come to rest along its jerk-limited profile, then 0 V, amplifier off."""
        if self.mode[i] != IDLE:
            self.stop_req[i] = 1

    def stop_all(self) -> None:
        """Stop category 1 of every axis (IEC 60204-1 §9.2.2): each driven axis comes to rest
        under power along its jerk-limited profile (:meth:`stop_axis`: a program or an approach
        runs on to its next rest point within the axis's a_max/j_max, a stream brakes), then
        0 V and amplifier off. A faulted axis is already at 0 V (category 0)."""
        for i in range(len(self.axis_names)):
            self.stop_axis(i)

    def at_rest(self) -> bool:
        """Every axis at 0 V with its amplifier off: idle (a stop has ended) or faulted."""
        return all(self.mode[i] == IDLE or self.supervisor.fault[i] for i in range(len(self.axis_names)))

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
        self._adopt(i, controller)
        if self._running[i]:
            controller.reset(float(self.driver.position_m[i]))
            self.axf[i, C.X_BLOFF] = math.nan
            self.ax[i, C.A_BLEND] = self.blend_cycles

    def fault_reset(self, i: int) -> tuple[bool, str]:
        """Fault reset of axis i in one call (between cycles; the axis stays disabled), for
        callers that run the cycles themselves (commissioning): the drive's own reset is sent
        while it reports a fault (:meth:`Driver.reset_fault`), and the supervisor's latch is
        cleared if the cause is gone now; a drive that has not left its fault yet refuses it
        ("the amplifier still reports a fault"). The daemon's ``fault-reset`` is
        :meth:`begin_fault_reset` and :meth:`poll_fault_reset` (one command that waits for the
        drive). Returns (cleared, why_not)."""
        if self.driver.amp_fault[i]:
            self.driver.reset_fault(i)
        return self._clear_latch(i)

    def _clear_latch(self, i: int) -> tuple[bool, str]:
        return self.supervisor.reset(i, float(self.driver.position_m[i]), bool(self.driver.amp_fault[i]))

    def begin_fault_reset(self, i: int) -> tuple[bool, bool, str]:
        """The operator's fault reset of axis i (between cycles; the axis stays disabled), the
        first step of one command. While the drive reports a fault it latched and has a reset
        of its own (:meth:`Driver.reset_fault`: CiA 402 transition 15, a Modbus reset bit; the
        only place a drive's fault is reset), that reset is sent and the answer waits for the
        drive to leave its fault: :meth:`poll_fault_reset` between the next cycles, at most
        :data:`FAULT_RESET_WAIT_S` of them. Otherwise the supervisor's latch is cleared at once
        if the cause is gone (:meth:`fault_reset`).

        Returns (pending, cleared, why_not): pending True when the drive's reset was sent (then
        cleared is False and why_not '')."""
        if self.driver.amp_fault[i] and self.driver.reset_fault(i):
            self._reset_until[i] = self.k + self.fault_reset_cycles
            return True, False, ""
        self._reset_until[i] = -1
        ok, why = self._clear_latch(i)
        return False, ok, why

    def poll_fault_reset(self, i: int) -> tuple[bool, bool, str]:
        """Between cycles, after :meth:`begin_fault_reset` sent the drive's reset: once the drive
        no longer reports its fault, the supervisor's latch is cleared if its other causes are
        gone; after :data:`FAULT_RESET_WAIT_S` of cycles with the drive
        still in its fault, the reset is refused naming the drive's state
        (:meth:`Driver.fault_state`). Nothing blocks: a few compares per call.

        Returns (done, cleared, why_not); done False while the drive is still being waited for."""
        until = self._reset_until[i]
        if until < 0:
            return True, False, "no fault reset of the drive is under way"
        if not self.driver.amp_fault[i]:
            self._reset_until[i] = -1
            ok, why = self._clear_latch(i)
            return True, ok, why
        if self.k < until:
            return False, False, ""
        self._reset_until[i] = -1
        wait_ms = self.fault_reset_cycles * self.period_s * 1e3
        state = self.driver.fault_state(i) or "it still reports a fault"
        return True, False, (f"the drive did not leave its fault within {wait_ms:.0f} ms of its reset "
                             f"({self.fault_reset_cycles} cycles): {state}")

    def shutdown_faults(self) -> None:
        """Latch FAULT_SHUTDOWN on every axis (SIGTERM / exit)."""
        for i in range(len(self.axis_names)):
            self.supervisor.trip(i, FAULT_SHUTDOWN)
