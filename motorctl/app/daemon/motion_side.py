"""Commanded motion on the daemon's I/O side: plans off the loop and streams setpoints.

A filler thread of the I/O process keeps ``lead_s`` (the config's ``daemon.motion_lead_s``,
default :data:`LEAD_S`) of setpoints (x_d, ẋ_d, ẍ_d per axis per cycle) ahead in the loop's
setpoint ring (:mod:`motorctl.loop.stream`), from a queue of planned trajectories (a ``move``:
Ruckig's time-optimal jerk-limited point-to-point with synchronised arrival; a G-code program:
``motorctl.motion``'s planner), in blocks of at most :data:`BLOCK_S`.

The trajectories are sampled on a path time s that advances by the feed scale f per cycle
(time scaling: x = p(s), ẋ = p'(s)·ḟ... precisely ẋ = p'(s)·f, ẍ = p''(s)·f² + p'(s)·ḟ), so
that the path is kept whatever f does:

* **feed override** 0.0..:data:`MAX_OVERRIDE`: f's target;
* **feed hold**: f's target 0: the motion decelerates on the path and holds; ``resume``
  brings f back to the override;
* **abort**: a feed hold, then the queue is cleared; the axes hold where they stopped.

f follows its target with a bounded rate and a bounded rate of change
(:data:`F_RATE_PER_S`, :data:`F_ACCEL_PER_S2`, scaled down for the fastest axis), so the
added acceleration p'(s)·ḟ stays a fraction of the axes' a_max and jerk-limited.

**Machine outputs** (a G-code program's mapped machine words, ``gcode.words``) travel in the ring:
every row carries the value of every output from its cycle on, switched at the row planned for
the word (the planner's event time), so the loop applies and records them in that very cycle
(LinuxCNC's motion-synchronised outputs). A feed hold keeps them as they are (LinuxCNC: the
spindle keeps turning in a feed hold); an abort switches the stop outputs (those of M3/M4/S/
M7/M8, :data:`motorctl.motion.gcode.STOP_WORDS`) off at the first row it rewrites; an underrun,
a stop or a fault switches them off in the loop itself.

An **underrun** (the loop found the ring empty while moving: it braked on its own, jerk-limited,
:mod:`motorctl.loop.stream`) is a pause, not the end: the program and the queue are kept, the
path time of the last setpoint the loop followed is noted (``SetpointRing.dry_row``), ``status``
says ``paused: underrun at line N ...``, and ``resume`` first moves (Ruckig) from where the brake
came to rest back onto the path at that point, then runs on from there with the feed scale
ramping up from 0, as after a feed hold. A stop of a commanded axis or a fault (the axis leaves
command mode) drops the program being run and the queue (``status`` says why); motion then
waits for new commands. Every target is checked against the axes' soft limits before anything
is queued.

**Programs** are read, checked and planned by :mod:`motorctl.app.program_planner` (in the
daemon, in a process of its own, a window at a time; :meth:`MotionSide.gcode` does the same
passes in the calling thread for in-process callers). While a program still has windows to
plan, :meth:`MotionSide.idle` is False; a window that is late only makes the path wait at rest
at the end of the previous one (every window ends at rest).

**Homing** (:meth:`MotionSide.home`, a thread of its own; LinuxCNC's sequence, the axis's
``homing:`` config): search the home switch at the search speed (a move toward it, held when
the switch trips), back off at the latch speed with the index latch armed until the index
pulse latches, then the loop shifts the axis's reading so that the latched position reads
``homing.position_m``.
"""

from __future__ import annotations

import collections
import math
import os
import threading
import time
from dataclasses import dataclass

import numpy as np

from motorctl.app.program_planner import PlanJob, plan_windows, preview
from motorctl.config import DaemonConfig
from motorctl.jit import njit
from motorctl.loop.cycle import STREAM
from motorctl.loop.stream import SP_OUT_STOP, SetpointRing
from motorctl.motion import gcode as G
from motorctl.motion import planner as P

#: seconds of setpoints kept ahead of the loop: the config's default (``daemon.motion_lead_s``)
LEAD_S = float(DaemonConfig.model_fields["motion_lead_s"].default)
#: the filler's wake period [s]
FILL_EVERY_S = 0.01
#: the ring is topped up in blocks of BLOCK_S (of a lead's 1/BLOCKS_PER_LEAD where that is
#: less): a trajectory's block sample has a fixed cost (the planner's filter windows, about 1.5
#: ms a call here), so a few large blocks a second cost a few per cent of a core where 50-row
#: blocks took 40 %; and no more, so that one block holds the lock and the interpreter for
#: milliseconds, not the whole lead (a 2 s block took 0.8-3 s and latched "recorder stalled"
#: on a loaded host)
BLOCK_S = 0.125
BLOCKS_PER_LEAD = 4
#: the highest feed override
MAX_OVERRIDE = 1.5
#: the feed scale's largest rate [1/s] and rate of change [1/s²] for an axis at a_max/v_max = 1 /s
F_RATE_PER_S, F_ACCEL_PER_S2 = 0.5, 2.0
#: above an override of 1: the part of each axis's a_max and j_max kept for the override's own
#: ramp (the terms p'·ḟ, 3p''·f·ḟ + p'·f̈ of the time scaling); the feed scale's rate is then
#: RAMP_SHARE/2 · min a_max/v_max and its rate of change RAMP_SHARE/2 · min j_max/v_max
RAMP_SHARE = 0.25
#: the override cap's bins of path time [s] (planner.override_cap)
CAP_BIN_S = 0.01
#: rows the loop may still take after a hold, resume, abort or override change: the rows beyond
#: them are written again at once (the ring keeps the lead ahead; this is the reaction time) [s]
GUARD_S = 0.004


class MotionError(ValueError):
    """A command refused before anything was queued (one line: what, where, what is allowed).
    ``usage``: the command itself was wrong (exit code 2), not the machine's state (1)."""

    def __init__(self, text: str, usage: bool = True):
        super().__init__(text)
        self.usage = usage


@dataclass
class AxisLimits:
    """One axis's limits: v_max [m/s], a_max [m/s²], j_max [m/s³], soft limits [m]."""

    v_max: float
    a_max: float
    j_max: float
    soft_min: float
    soft_max: float


@njit
def _ramp(f: float, fd: float, target: float, rate: float, accel: float, dt: float):
    """f one step of dt toward ``target`` with |ḟ| ≤ rate and |f̈| ≤ accel (the bang-bang rule
    of an accel-limited approach). Returns (f, ḟ)."""
    e = target - f
    if abs(e) <= accel * dt * dt and abs(fd) <= accel * dt:
        return target, 0.0
    want = math.copysign(min(rate, math.sqrt(2.0 * accel * abs(e))), e)
    if fd < want:
        fd = min(fd + accel * dt, want)
    else:
        fd = max(fd - accel * dt, want)
    f_new = f + fd * dt
    if (target - f_new) * e < 0:          # no overshoot
        return target, 0.0
    return f_new, fd


@njit
def _feed_target(holding, override, cap, cap_dt, s):
    """The feed scale's target at path time ``s`` [s]: 0 in a hold; else the override, above 1
    capped by ``cap`` (per bin of ``cap_dt`` [s] of path time: where the trajectory, planned at
    the full limits, would pass them; planner.override_cap), never below 1."""
    if holding:
        return 0.0
    t = override
    if t > 1.0:
        c = cap[min(int(s / cap_dt), cap.shape[0] - 1)]
        t = min(t, max(1.0, c))
    return t


@njit
def _ramp_rows(f, fd, s, holding, override, cap, cap_dt, rate, accel, rate_hi, accel_hi, dt, pauses,
               duration, ss, ff, ffd, m, n, may_settle):
    """The rows of the feed scale's ramp, compiled: from row ``m`` up to row ``n`` (exclusive) of
    ``ss``, ``ff``, ``ffd`` (path time [s], f, ḟ [1/s]), f stepped by :func:`_ramp` toward its
    target (:func:`_feed_target`), at the high rate and
    acceleration while f or its target is above 1; a programmed pause (``pauses`` [s], in order)
    within a row's step ends it there, at rest, in a hold. Stops early: at rest in a hold,
    at ``duration`` (the row that reaches it), or, with ``may_settle`` and a row made, once f
    has settled on a positive target (the vectorised case again).
    Returns (m, f, ḟ, s, holding, paused, ended, settled)."""
    paused = False
    ended = False
    settled = False
    while m < n:
        if f == 0.0 and fd == 0.0 and holding:
            break                                   # at rest on the path: the loop holds the last row
        target = _feed_target(holding, override, cap, cap_dt, s)
        if m > 0 and may_settle and f == target and fd == 0.0 and target > 0.0:
            settled = True
            break
        if target > 1.0 or f > 1.0:
            f, fd = _ramp(f, fd, target, rate_hi, accel_hi, dt)
        else:
            f, fd = _ramp(f, fd, target, rate, accel, dt)
        s_new = s + f * dt
        for q in range(pauses.shape[0]):
            t_stop = pauses[q]
            if s < t_stop <= s_new:
                s_new = t_stop
                f = 0.0
                fd = 0.0
                holding = True
                paused = True
                break
        s = s_new
        ss[m] = s_new
        ff[m] = f
        ffd[m] = fd
        m += 1
        if s_new >= duration:
            ended = True
            break
    return m, f, fd, s, holding, paused, ended, settled


def warm_up() -> None:
    """Compile (or load the cached code of) the feed scale's compiled steps now, not at the first
    override or hold: the daemon calls it before it forks its I/O process (a compile there, with
    the cache cold after an install or an edit, held the I/O process for seconds while the loop
    ran, and the loop latched "recorder stalled"); ``motorctl warmup`` calls it too."""
    s, f, fd = np.zeros(1), np.zeros(1), np.zeros(1)
    _ramp_rows(1.0, 0.0, 0.0, False, 1.0, np.ones(1), 1.0, 1.0, 1.0, 1.0, 1.0, 2e-4, np.zeros(0), 1.0,
               s, f, fd, 0, 1, True)
    _feed_target(False, 1.0, np.ones(1), 1.0, 0.0)          # and the target, as _target calls it


class MotionSide:
    """The commanded motion of the daemon's axes (module docstring).

    Args:
        stream: the loop's setpoint ring. latest: callable giving the newest record row (or
            None). layout: the record layout. names: axis names. limits: AxisLimits per axis.
        modes: callable giving the axes' sequencing modes (the status block). period_s: loop
            period. homing: the axes' HomingConfig (None: none). inputs(i): (home switch,
            index latch [m] or NaN) of axis i. to_loop(msg): a command to the loop process,
            its answer (blocking; from another thread than the I/O process's own).
        gcode_settings: the config's ``gcode:`` section (machine words, G28 point, optional stop);
            the outputs its words switch must be the ring's (``stream.outputs``).
        lead_s: setpoints kept ahead of the loop [s] (at most the ring's length).
    Raises:
        ValueError: a lead the ring cannot hold.
    """

    def __init__(self, stream: SetpointRing, latest, layout, names, limits, modes, period_s: float,
                 homing=None, inputs=None, to_loop=None, gcode_settings: G.GcodeSettings | None = None,
                 lead_s: float = LEAD_S):
        self.stream, self.latest, self.names, self.limits = stream, latest, list(names), limits
        self.modes, self.dt = modes, period_s
        self._pva = [P.AxisLimits(lim.v_max, lim.a_max, lim.j_max) for lim in limits]
        self.n = len(self.names)
        self._xcol = [layout.index(f"{a}.x_d") for a in self.names]
        self._vcol = [layout.index(f"{a}.xd_dot") for a in self.names]
        self.homing = list(homing or [None] * self.n)
        self.homing_required = [bool(h is not None and h.required) for h in self.homing]
        self.homed = [False] * self.n
        self.homing_state = [""] * self.n
        self.inputs, self.to_loop = inputs, to_loop
        self._homing_thread: threading.Thread | None = None
        #: set by an abort or a fault: the homing sequence ends at its next step, whenever it comes
        #: (before its first move is queued too)
        self._homing_abort = threading.Event()
        self.lead = max(BLOCKS_PER_LEAD, int(round(lead_s / period_s)))
        if self.lead > stream.capacity:
            raise ValueError(f"a lead of {lead_s:g} s is {self.lead} rows; the setpoint ring holds "
                             f"{stream.capacity}")
        ratio = min(lim.a_max / lim.v_max for lim in limits)
        self.f_rate, self.f_accel = F_RATE_PER_S * ratio, F_ACCEL_PER_S2 * ratio * ratio
        self.f_rate_hi = 0.5 * RAMP_SHARE * ratio
        self.f_accel_hi = min(0.5 * RAMP_SHARE * min(lim.j_max / lim.v_max for lim in limits), self.f_accel)
        # path time an override ramp from MAX_OVERRIDE down to 1 covers (its look-ahead), with margin
        self.cap_ahead_s = 1.2 * MAX_OVERRIDE * ((MAX_OVERRIDE - 1.0) / self.f_rate_hi
                                                 + 2.0 * self.f_rate_hi / self.f_accel_hi)
        self.guard = max(4, int(round(GUARD_S / period_s)))
        #: the most rows one fill generates, whatever the lead (BLOCK_S)
        self._chunk = max(1, min(self.lead // BLOCKS_PER_LEAD, int(round(BLOCK_S / period_s))))
        cap = stream.capacity
        #: the filler's state after each ring row (by row index % capacity): path time, feed
        #: scale and its rate, trajectory, programs done; rows below _hist_from are not ours
        self._hs, self._hf, self._hfd = np.zeros(cap), np.zeros(cap), np.zeros(cap)
        self._htraj: list = [None] * cap
        self._hdone = np.zeros(cap, dtype=np.int64)
        self._hist_from = stream.written()
        self._rewrite = False            # a hold/resume/abort/override asks to rewrite the ring
        self._guard_now = self.guard     # the guard of the next rewrite (widened after a miss)
        self._defer_clear: str | None = None
        self._off_pending = False        # an abort's stop outputs still to switch off
        self.rewrites = 0
        self._wake = threading.Event()
        settings = gcode_settings or G.GcodeSettings()
        if "axes" not in settings.model_fields_set:          # the machine's axes, not X Y Z
            settings = settings.model_copy(update={"axes": [a for a in self.names if a in G.AXES]})
        #: M1 pauses (the config's gcode.optional_stop, switched at run time by optional-stop);
        #: programs are read with every M1 as a pause, the filler passes those it should not take
        self.optional_stop = settings.optional_stop
        self.gcode_settings = settings.model_copy(update={"optional_stop": True})
        #: the program being planned in windows (its job id, 0: none) and the axes it moves
        self.planning, self.planning_axes = 0, []
        self._jobs = 0
        #: bumped at every _clear: a program still being planned is then cancelled
        self.clears = 0
        #: after an underrun: (trajectory, path time [s]) of the last setpoint the loop followed,
        #: where ``resume`` goes back onto the path
        self._dry: tuple | None = None
        self._resume_s = None            # (trajectory, path time) to start at when it is popped
        self._underruns_seen = stream.underruns()
        n_out = len(stream.outputs)
        self._stop_mask = np.array([bool(int(stream.ctl[SP_OUT_STOP]) >> j & 1) for j in range(n_out)],
                                   dtype=bool)
        self._out = np.zeros(n_out)      # the outputs after the last row generated
        self._bout = np.zeros((self.lead, n_out))
        #: the work offsets (G54 ... G59.3 → X Y Z origin [m]) the last accepted program left, the
        #: ones the next program starts with (LinuxCNC keeps them, set by G10 L2)
        self.work_offsets: dict[str, np.ndarray] = {}
        self.pending: collections.deque = collections.deque()   # (ring row, Event) not yet taken
        self.outputs: dict[str, float] = {o: 0.0 for o in stream.outputs}
        #: (ring row, output, value, setpoint positions (n,) [m]) of every machine word the loop took
        self.output_log: list[tuple[int, str, float, np.ndarray]] = []
        self._bev: list = []             # (row of the block, Event) of the block being generated
        self._ev_i = 0                   # the next event of the trajectory being streamed
        self._bs, self._bf, self._bfd = np.zeros(self.lead), np.zeros(self.lead), np.zeros(self.lead)
        self._btraj: list = [None] * self.lead
        self.lock = threading.Lock()
        self.queue: collections.deque = collections.deque()
        self.cur = None                  # the trajectory being streamed
        self.s = 0.0                     # its path time [s]
        self.last = np.zeros((self.n, 3))
        self.f, self.fd = 1.0, 0.0       # the feed scale and its rate
        self.override = 1.0
        self.holding = self.aborting = False
        self.epoch = stream.epoch()
        self.reason = ""                 # why the last program ended early
        self.done_programs = 0
        self.queued_programs = 0
        self.feed_m_s = 0.0
        self.used: list[int] = []        # the axes the queued motion moves
        self._block = np.zeros((self.lead, self.n, 3))
        self._s, self._f, self._fd = np.zeros(self.lead), np.zeros(self.lead), np.zeros(self.lead)
        self._steps = np.arange(1.0, self.lead + 1.0)
        warm_up()                        # (a no-op where the daemon compiled it before its fork)
        self._grid = np.zeros((self.lead + 2, 3, self.n))   # sample_into's layout (k, x/v/a, axis)
        #: SCHED_FIFO priority of the filler thread (0: none), below the loop's: a busy host must
        #: not starve the planner for longer than the lead (set by the daemon where real-time is on)
        self.fifo_priority = 0
        self.trace: list | None = None   # the source line of every row streamed (when a list)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    # ---------------------------------------------------------------- commands (any thread)
    def where(self) -> np.ndarray:
        """(n,) the commanded position of every axis now: the end of what is queued, or the
        newest setpoint the loop recorded."""
        with self.lock:
            if self.queue:
                return np.array(self.queue[-1].end)
            if self.cur is not None:
                return np.array(self.cur.end)
        row = self.latest()
        if row is None:
            raise MotionError("the loop has not run yet; retry in a moment", usage=False)
        return np.array([row[c] for c in self._xcol])

    def check_axes(self, axes: list[int], what: str) -> None:
        """Raises MotionError unless every axis of ``axes`` is in command mode (and homed where
        its homing is required)."""
        modes = self.modes()
        for i in axes:
            if int(modes[i]) != STREAM:
                raise MotionError(f"{what}: axis {self.names[i]} is not in command mode; run "
                                  f"'motorctl start {self.names[i]} --mode command' first", usage=False)
            if self.homing_required[i] and not self.homed[i]:
                raise MotionError(f"{what}: axis {self.names[i]} is not homed (homing.required); "
                                  f"run 'motorctl home {self.names[i]}' first", usage=False)

    def check_inside(self, goal, what: str) -> None:
        for i, x in enumerate(goal):
            lim = self.limits[i]
            if not (lim.soft_min <= x <= lim.soft_max):
                raise MotionError(f"{what}: {self.names[i]} = {x:.6f} m is outside the soft limits "
                                  f"[{lim.soft_min:g}, {lim.soft_max:g}] m")

    def move(self, targets: dict, feed: float | None = None, _homing: bool = False) -> dict:
        """Queue a coordinated straight move to ``targets`` ({axis index: position [m]}) at
        most ``feed`` [m/s] along the path. Returns its figures. Raises MotionError (nothing
        queued)."""
        if self.aborting:
            raise MotionError("move: an abort is running; retry when it has stopped", usage=False)
        if self._homing_thread is not None and self._homing_thread.is_alive() and not _homing:
            raise MotionError("move: homing runs; wait for it", usage=False)
        if not _homing:
            self.check_axes(list(targets), "move")
        start = self.where()
        goal = start.copy()
        for i, x in targets.items():
            if not math.isfinite(x):
                raise MotionError(f"move: {self.names[i]} must be a finite position in m (got {x})")
            goal[i] = x
        self.check_inside(goal, "move")
        if feed is not None and not feed > 0:
            raise MotionError(f"move: --feed must be > 0 m/s (got {feed})")
        try:
            traj = P.point_to_point(start, goal, self._pva, feed=feed, axes=self.names)
        except ValueError as exc:
            raise MotionError(f"move: {exc}") from None
        self.enqueue([traj], list(targets), homing=_homing)
        return {"duration_s": traj.duration, "axes": list(self.names), "from_m": start.tolist(),
                "to_m": goal.tolist()}

    def program_job(self, filename: str, text: str | None = None, path: str | None = None,
                    from_line: int = 1, single_block: bool = False) -> PlanJob:
        """A G-code program (``text``, or the file at ``path``) to read, check and plan from
        where the axes are commanded now (:mod:`motorctl.app.program_planner`; ``from_line``,
        ``single_block``: :class:`PlanJob`). Raises MotionError: an axis not named X, Y or Z,
        motion that cannot take a program now."""
        bad = [a for a in self.names if a not in G.AXES]
        if bad:
            raise MotionError(f"gcode: the axes must be named among {', '.join(G.AXES)} "
                              f"(got {', '.join(self.names)})", usage=False)
        if self.planning:
            raise MotionError("gcode: a program is still being planned; wait for it or abort",
                              usage=False)
        start = self.where()
        start3 = [float(start[self.names.index(a)]) if a in self.names else 0.0 for a in G.AXES]
        self._jobs += 1
        return PlanJob(self._jobs, path, text, filename, self.gcode_settings, start3,
                       [float(x) for x in start], dict(self.work_offsets),
                       {a: (lim.soft_min, lim.soft_max) for a, lim in zip(self.names, self.limits)},
                       list(self.names), list(self._pva), self.dt, list(self.stream.outputs),
                       {"share": RAMP_SHARE, "bin_s": CAP_BIN_S, "ahead_s": self.cap_ahead_s},
                       from_line, single_block)

    def accept_checked(self, job: PlanJob, info: dict) -> list[int]:
        """The preview of ``job`` passed: check that the axes it moves may move now (command
        mode, homed). Returns those axes. Raises MotionError (nothing queued)."""
        self.check_axes(info["moved"], "gcode")
        return list(info["moved"])

    def begin_program(self, job: PlanJob, axes: list[int], first, last: bool, offsets: dict) -> None:
        """Queue the first window of a checked program; while ``last`` is False more follow
        (:meth:`add_window`)."""
        with self.lock:
            self.planning = 0 if last else job.id
            self.planning_axes = list(axes)
        if first is not None:
            self.enqueue([first], axes)
        self.work_offsets = offsets

    def add_window(self, job_id: int, traj, last: bool) -> bool:
        """Queue one more window of the program being planned. False (nothing queued) when that
        program was dropped meanwhile (an abort, a stop, a fault)."""
        with self.lock:
            if self.planning != job_id:
                return False
            if last:
                self.planning = 0
            if traj is not None:
                self.used = sorted(set(self.used) | set(self.planning_axes))
                self.queue.append(traj)
            self._wake.set()
        return True

    def windows_ahead(self, job_id: int) -> int:
        """Windows of program ``job_id`` queued and not yet begun."""
        with self.lock:
            return sum(1 for t in self.queue if getattr(t, "job", None) == job_id)

    def set_optional_stop(self, on: bool) -> None:
        """M1 pauses (True) or passes (False) from now on, in the program running too."""
        with self.lock:
            self.optional_stop = bool(on)

    def _pauses(self, cur) -> list[float]:
        """(lock held) The path times where ``cur`` pauses: its M0s, its M1s with the optional
        stop on, single block's stops."""
        return [t for t, p in cur.stops if not p.optional or self.optional_stop]

    def jog(self, i: int, kind: str, value: float = 0.0, feed: float | None = None) -> dict:
        """Jog axis i in command mode (LinuxCNC's jog of an enabled joint): ``by`` value [m]
        from where it is commanded (incremental), ``velocity`` value [m/s] toward the soft
        limit on its side until ``stop`` (continuous; an abort ends it on the path), or
        ``to`` value [m] (at most ``feed`` [m/s]). Raises MotionError (nothing queued): not in
        command mode, motion running, a target outside the soft limits."""
        name = self.names[i]
        if kind == "stop":
            self.abort()
            return {"jog": "stopping"}
        self.check_axes([i], "jog")
        if not self.idle():
            raise MotionError(f"jog {name}: motion is running; wait for it or abort", usage=False)
        here = float(self.where()[i])
        lim = self.limits[i]
        if kind == "by":
            target = here + value
        elif kind == "velocity":
            target, feed = (lim.soft_max if value > 0 else lim.soft_min), abs(value)
            if abs(value) > lim.v_max:
                raise MotionError(f"jog {name}: velocity {value:g} m/s is above v_max {lim.v_max:g} m/s")
        else:
            target = value
        if not lim.soft_min <= target <= lim.soft_max:
            raise MotionError(f"jog {name}: {target:.6f} m is outside the soft limits "
                              f"[{lim.soft_min:g}, {lim.soft_max:g}] m")
        return self.move({i: target}, feed)

    def gcode(self, text: str, filename: str) -> dict:
        """Read, check and plan a G-code program (``motorctl.motion``: the subset LinuxCNC
        reads, look-ahead planning within each axis's v/a/j) from where the axes are commanded
        now, and queue it, in the calling thread (the daemon does the same passes in its planner
        process). Raises MotionError (``file:line:column: why``; nothing queued)."""
        job = self.program_job(filename, text=text)
        try:
            info = preview(job)
            axes = self.accept_checked(job, info)
            trajs = list(plan_windows(job))
        except ValueError as exc:        # GcodeError, LimitError: one line with file:line:column
            raise MotionError(str(exc)) from None
        self.enqueue(trajs, axes)
        self.work_offsets = info["offsets"]
        return {"duration_s": float(sum(t.duration for t in trajs)), "segments": info["segments"],
                "end_m": [float(x) for x in trajs[-1].end], "warnings": list(info["warnings"])}

    def enqueue(self, trajs: list, axes: list[int], homing: bool = False) -> None:
        """Queue planned trajectories moving ``axes`` (checked already). ``homing``: a move of
        the homing sequence, refused (MotionError) once an abort or a fault has ended homing:
        checked under the lock an abort takes, so no abort can fall between the check and the
        queueing."""
        for traj in trajs:                   # the override's cap along it (planner.override_cap)
            if getattr(traj, "cap", None) is None:
                traj.cap = P.override_cap(traj, self._pva, share=RAMP_SHARE, period=self.dt, bin_s=CAP_BIN_S,
                                          ahead_s=self.cap_ahead_s)
                traj.cap_dt = max(1, int(round(CAP_BIN_S / self.dt))) * self.dt
        with self.lock:
            if homing and self._homing_abort.is_set():
                raise MotionError("aborted", usage=False)
            self.used = sorted(set(self.used) | set(axes)) if (self.cur or self.queue) else list(axes)
            self.queue.extend(trajs)
            self.queued_programs += 1
            self.reason = ""

    def _asap(self) -> None:
        """(lock held) The rows beyond the next GUARD_S are written again at the filler's next
        wake, which is now."""
        self._rewrite = True
        self._wake.set()

    def hold(self) -> None:
        with self.lock:
            self.holding = True
            self._asap()

    def resume(self) -> None:
        """Go on after a feed hold, a programmed pause (M0/M1) or an underrun (module
        docstring: first back onto the path where the loop last followed it)."""
        with self.lock:
            if self.aborting:
                return
            if self._dry is not None:
                self._back_onto_path()
            self.holding = False
            if self.reason.startswith("paused"):
                self.reason = ""
            self._asap()

    def _back_onto_path(self) -> None:
        """(lock held) After an underrun: a move from where the loop holds to the path point
        where it ran dry, then that trajectory from there (its feed scale ramping up from 0)."""
        traj, s0, outs = self._dry
        self._dry = None
        row = self.latest()
        if row is None:
            return
        here = np.array([row[c] for c in self._xcol])
        out = np.empty((1, 3, self.n))
        traj.sample_into(s0, self.dt, out)
        there = out[0, 0].copy()
        self.queue.appendleft(traj)
        self._resume_s = (traj, s0, outs)
        if float(np.max(np.abs(there - here))) > 1e-9:
            back = P.point_to_point(here, there, self._pva, axes=self.names)
            back.cap = np.full(2, 1.0)
            back.cap_dt = max(back.duration, self.dt)
            self.queue.appendleft(back)
        self.cur, self.s, self.f, self.fd = None, 0.0, self.override, 0.0

    def abort(self) -> None:
        """Stop every commanded motion: a feed hold on the path, then the queue, the program being
        planned and homing dropped (module docstring); whenever it comes, also before homing
        has queued its first move."""
        self._homing_abort.set()
        self._stop_on_path()

    def _stop_on_path(self) -> None:
        """The motion held on the path and the queue dropped once at rest (homing's own stop at
        the switch or the index, and :meth:`abort`'s)."""
        with self.lock:
            self.aborting = self.holding = True
            # nothing left to plan may still be in the ring (a move shorter than the lead):
            # then the rewrite stops it; only an empty ring means nothing runs
            if self.cur is None and not self.queue and self.stream.depth() == 0:
                self._clear("aborted")
            self._asap()

    def set_override(self, f: float) -> None:
        if not (math.isfinite(f) and 0.0 <= f <= MAX_OVERRIDE):
            raise MotionError(f"override: the feed override must be within 0.0..{MAX_OVERRIDE} (got {f})")
        with self.lock:
            self.override = float(f)
            if self.cur is None:             # nothing running: the next move starts at it
                self.f, self.fd = self.override, 0.0
            self._asap()

    def fault_stop(self, why: str) -> None:
        """A fault latched on an axis (the loop has put it at 0 V and drained the setpoint ring):
        the commanded motion ends at once whatever it was doing (streaming, held, paused after an
        underrun, being planned, homing), ``stopped_because`` is ``why``; the stop outputs go off
        (the loop has switched them off already)."""
        with self.lock:
            self._homing_abort.set()
            self._clear(why)
            self._rewrite = False
            self._off_pending = False

    def settle_abort(self) -> bool:
        """An abort whose motion has come to rest is over: nothing streams or is queued, the ring
        is drained and the loop's brake is done, so the queue is cleared and the abort ended
        (``stopped_because`` 'aborted'), whether or not the filler's rewrite ended it (the I/O
        process asks at every wake). True when it ended one."""
        with self.lock:
            if not (self.aborting and self.cur is None and not self.queue and not self.planning
                    and self.stream.depth() == 0 and not self.stream.braking()):
                return False
            self._clear("aborted")
            self._rewrite = False
            return True

    def homing_runs(self) -> bool:
        """The homing sequence's thread is running."""
        return self._homing_thread is not None and self._homing_thread.is_alive()

    def _busy(self) -> bool:
        """(lock held) Something is queued, streamed, being planned, or paused after an underrun."""
        return self.cur is not None or bool(self.queue) or bool(self.planning) or self._dry is not None

    def _held(self) -> bool:
        """(lock held) A feed hold, a programmed pause, an underrun's pause."""
        return self.holding or self._dry is not None or self.reason.startswith("paused")

    def idle(self) -> bool:
        """Nothing queued or streaming, and the ring drained."""
        with self.lock:
            busy = self._busy()
        return not busy and self.stream.depth() == 0 and not self.stream.braking()

    def progress(self) -> tuple[int, float, float]:
        """(source line, share done 0..1, time left [s]) of the motion the loop runs now: the
        row it took last (not the filler's, the lead ahead), the planned durations of it and of the
        queue, the time left at the current override (the planner's prediction; a hold stops it).
        (0, 1.0, 0.0) when nothing runs."""
        with self.lock:
            taken = self.stream.consumed() - 1
            k = taken % self.stream.capacity
            traj = self._htraj[k] if self._hist_from <= taken < self.stream.written() else None
            busy = self.cur is not None or bool(self.queue)
            if traj is None or not busy and self.stream.depth() == 0:
                return 0, 1.0, 0.0
            s = min(float(self._hs[k]), traj.duration)
            later = [t for t in ([self.cur] if self.cur is not None and self.cur is not traj else [])
                     + list(self.queue)]
            total = traj.duration + sum(t.duration for t in later)
            left = total - s
        rate = self.override if self.override > 0 else 1.0
        return int(traj.line_at(s)), (s / total if total > 0 else 1.0), left / rate

    def status(self) -> dict:
        """``status``' ``motion`` block, one instant of it: what is queued, held and streamed
        read under one hold of the lock, the ring's depth and brake read once, ``idle`` (as
        :meth:`idle` says) and ``held`` (a feed hold, a programmed pause, an underrun's pause)
        from those same values (the machine state is computed from this block: two reads had
        let it say idle beside a motion that was not)."""
        line, done, left = self.progress()
        with self.lock:
            depth = len(self.queue) + (self.cur is not None) + (self._dry is not None)
            busy, held = self._busy(), self._held()
            ring_depth, braking = self.stream.depth(), self.stream.braking()
            out = {"queue_depth": depth, "line": line, "done": done, "time_left_s": left,
                   "feed_m_s": self.feed_m_s,
                   "override": self.override, "feed_scale": self.f, "hold": self.holding, "held": held,
                   "aborting": self.aborting, "ring_depth": ring_depth, "planning": bool(self.planning),
                   "underruns": self.stream.underruns(), "braking": braking,
                   "stopped_because": self.reason, "homed": list(self.homed), "outputs": dict(self.outputs),
                   "optional_stop": self.optional_stop,
                   "homing": list(self.homing_state), "homing_configured": [h is not None for h in self.homing],
                   "homing_runs": self.homing_runs(),
                   "filler_alive": self._thread is not None and self._thread.is_alive(),
                   "idle": not busy and ring_depth == 0 and not braking}
        return out

    # ---------------------------------------------------------------- homing
    def home(self, i: int) -> dict:
        """Start homing axis i (module docstring) in a thread; ``status()["homing"][i]`` says
        how it goes ("searching", "latching", "homed", "failed: ..."). Raises MotionError: no
        homing config, no homing inputs, not in command mode, motion running."""
        name = self.names[i]
        if self.homing[i] is None:
            raise MotionError(f"home: axis {name} has no homing: section in its config")
        if self.inputs is None or self.to_loop is None:
            raise MotionError(f"home: the driver of axis {name} has no home switch or index input", usage=False)
        if int(self.modes()[i]) != STREAM:
            raise MotionError(f"home: axis {name} is not in command mode; run 'motorctl start {name} "
                              f"--mode command' first", usage=False)
        if not self.idle() or (self._homing_thread is not None and self._homing_thread.is_alive()):
            raise MotionError("home: motion or homing is running; wait for it", usage=False)
        self.homed[i] = False
        self._homing_abort.clear()
        self.homing_state[i] = "searching"
        self._homing_thread = threading.Thread(target=self._home, args=(i,), name="motorctl-homing", daemon=True)
        self._homing_thread.start()
        return {"homing": "started"}

    def _until(self, pred, what: str, timeout_s: float) -> None:
        end = time.monotonic() + timeout_s
        while not pred():
            if time.monotonic() > end:
                raise MotionError(f"{what} not within {timeout_s:g} s")
            time.sleep(0.002)

    def _run_until(self, i: int, target: float, speed: float, pred, what: str) -> bool:
        """A move of axis i toward ``target`` at ``speed``, held (abort) as soon as ``pred()``;
        True when pred came true."""
        lim = self.limits[i]
        target = min(max(target, lim.soft_min), lim.soft_max)
        info = self.move({i: target}, speed, _homing=True)
        hit = False
        end = time.monotonic() + info["duration_s"] * 2 + 5.0
        while time.monotonic() < end:
            if self._homing_abort.is_set():
                break
            if pred():
                hit = True
                self._stop_on_path()
                break
            if self.idle():
                break
            time.sleep(0.001)
        self._until(self.idle, f"{what}: the axis at rest", 10.0)
        if self._homing_abort.is_set():
            raise MotionError("aborted", usage=False)
        return hit or pred()

    def _home(self, i: int) -> None:
        cfg = self.homing[i]
        d = cfg.direction
        try:
            if self._homing_abort.is_set():
                raise MotionError("aborted", usage=False)
            y0 = float(self.where()[i])
            if not self.inputs(i)[0] and not self._run_until(
                    i, y0 + d * cfg.search_distance_m, cfg.search_speed_m_per_s,
                    lambda: self.inputs(i)[0], "search"):
                raise MotionError(f"no home switch within {cfg.search_distance_m:g} m")
            self.homing_state[i] = "latching"
            ans = self.to_loop({"op": "arm_index", "axis": i})
            if not ans.get("ok"):
                raise MotionError(f"the index latch not armed: {ans.get('error', 'refused')}")
            # a latch of before (the last homing's) must not be taken for this one's
            self._until(lambda: not math.isfinite(self.inputs(i)[1]), "the index latch cleared", 2.0)
            y1 = float(self.where()[i])
            if not self._run_until(i, y1 - d * cfg.back_off_m, cfg.latch_speed_m_per_s,
                                   lambda: math.isfinite(self.inputs(i)[1]), "latch"):
                raise MotionError(f"no index pulse within {cfg.back_off_m:g} m off the switch")
            latch = self.inputs(i)[1]
            if self._homing_abort.is_set():
                raise MotionError("aborted", usage=False)
            delta = cfg.position_m - latch
            here = float(self.where()[i]) + delta
            lim = self.limits[i]
            if not lim.soft_min <= here <= lim.soft_max:
                raise MotionError(f"the index latched at {latch:.6f} m would put the axis at {here:.6f} m, "
                                  f"outside its soft limits [{lim.soft_min:g}, {lim.soft_max:g}] m; "
                                  f"position not set")
            ans = self.to_loop({"op": "set_position", "axis": i, "delta_m": delta})
            if not ans.get("ok"):
                raise MotionError(ans.get("error", "set position refused"))
            time.sleep(0.02)                   # a few cycles: the newest setpoint is shifted
            self.homed[i] = True
            self.homing_state[i] = "homed"
        except Exception as exc:  # noqa: BLE001 - reported in status, the axis holds
            self.homing_state[i] = f"failed: {exc}"

    # ---------------------------------------------------------------- the filler
    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name="motorctl-motion", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._wake.set()
        if self._thread is not None:
            self._thread.join(1.0)

    def _run(self) -> None:
        if self.fifo_priority:
            try:                             # this thread only (Linux: 0 is the calling thread)
                os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(self.fifo_priority))
            except OSError:
                pass                         # not permitted: SCHED_OTHER as the rest of the process
        while not self._stop.is_set():
            self._wake.wait(FILL_EVERY_S)
            self._wake.clear()
            if self._stop.is_set():
                break
            try:
                self.issue_events()
                while self.fill() and not self._stop.is_set():
                    time.sleep(0)            # the drain and the socket between two blocks
            except Exception as exc:  # noqa: BLE001 - the filler never dies: the loop brakes
                with self.lock:
                    self._clear(f"planner error: {type(exc).__name__}: {exc}")

    def _clear(self, why: str) -> None:
        """(lock held) Drop what is streamed and queued (and the program still being planned)."""
        self.clears += 1
        self.planning = 0
        self._dry = self._resume_s = None
        self.queue.clear()
        self.cur = None
        self.s = 0.0
        self.aborting = self.holding = False
        self.f, self.fd = self.override, 0.0
        self.reason = why
        self.feed_m_s = 0.0
        self._hist_from = self.stream.written()
        self.pending.clear()
        self._off_pending = why == "aborted"   # the stop outputs off once the ring is drained

    def fill(self) -> int:
        """Top the ring up toward the lead by one block of at most ``_chunk`` rows (the filler
        calls it again at once while it writes rows). Returns the rows written."""
        ring = self.stream
        with self.lock:
            ep = ring.epoch()
            if ep != self.epoch:             # the loop braked on its own (underrun or stop)
                self.epoch = ep
                dry = ring.underruns() != self._underruns_seen
                self._underruns_seen = ring.underruns()
                if self.cur is not None or self.queue or self.planning:
                    if not (dry and self._pause_at_dry()):
                        self._clear("underrun" if dry else "stopped")
            if ring.braking():
                return 0
            if ring.depth() == 0 and self.cur is None:   # the loop's outputs (it may have switched some off)
                self._out[:] = ring.applied()
                if self._off_pending:
                    self._off_pending = False
                    self._stop_outputs_at_rest()
            if self._rewrite:
                n = self._rewind(ep)
                if n is not None:
                    return n
            need = min(self.lead - ring.depth(), ring.free(), self._chunk)
            if need < self._chunk or (self.cur is None and not self.queue):
                return 0
            if self._gone():
                return 0
            self._bev.clear()
            n = self._generate(need)
            self._push(n, ep)
            return n

    def _pause_at_dry(self) -> bool:
        """(lock held) An underrun (module docstring): keep the program, note the trajectory and
        path time of the last row the loop followed, hold. False when that row is not one of
        ours (then the caller drops the program as before)."""
        ring = self.stream
        q = ring.dry_row()
        if q < self._hist_from or q >= ring.written():
            return False
        cap = ring.capacity
        k = q % cap
        t0 = self._htraj[k]
        if t0 is None or t0.duration <= 0.0:
            return False
        later: list = []
        for r in range(q + 1, ring.written()):
            t = self._htraj[r % cap]
            if t is not None and t is not t0 and (not later or later[-1] is not t):
                later.append(t)
        if self.cur is not None and self.cur is not t0 and (not later or later[-1] is not self.cur):
            later.append(self.cur)
        rest = [t for t in self.queue if t is not t0 and t not in later]
        self.queue.clear()
        self.queue.extend(later + rest)
        s0 = min(float(self._hs[k]), t0.duration)
        self.cur, self.s, self.f, self.fd = None, 0.0, self.override, 0.0
        self._dry = (t0, s0, ring.row_outputs(k).copy())
        self.holding = True
        self._hist_from = ring.written()
        self.pending.clear()
        self._bev.clear()
        self.reason = (f"paused: underrun at line {int(t0.line_at(s0))} (the setpoints ran dry; the "
                       f"axes braked to rest); resume goes back onto the path and on")
        return True

    def _stop_outputs_at_rest(self) -> None:
        """(lock held) Nothing streams: the stop outputs still on go off in one row at rest where
        the loop holds (an abort that found nothing to rewrite)."""
        ring = self.stream
        row = self.latest()
        if (row is None or not np.any(ring.applied()[self._stop_mask]) or ring.depth() or ring.braking()
                or self._gone()):
            return
        self._out[:] = ring.applied()
        self._out[self._stop_mask] = 0.0
        self._block[0, :, 0] = [row[c] for c in self._xcol]   # the setpoint the loop holds
        self._block[0, :, 1:] = 0.0
        self._bs[0], self._bf[0], self._bfd[0] = 0.0, self.f, 0.0
        self._btraj[0] = None
        self._bev.clear()
        self._push(1, ring.epoch())

    def _gone(self) -> bool:
        """(lock held) A moved axis left command mode (a fault or a stop): the program is dropped,
        no more rows (the loop brakes). True then."""
        modes = self.modes()
        gone = [self.names[i] for i in self.used if int(modes[i]) != STREAM]
        if gone:
            self._clear(f"axis {gone[0]} left command mode")
        return bool(gone)

    def _push(self, n: int, ep: int, cut: int | None = None) -> bool:
        """(lock held) The block's first n rows into the ring at its write index (``cut``: in
        place of the ring's rows from index ``cut`` on, :meth:`SetpointRing.replace`), with the
        filler's state after each (for a rewrite) and the block's events tied to their rows.
        False (nothing changed) when the loop came within two rows of ``cut``."""
        if not n and cut is None:
            return True
        ring = self.stream
        outs = self._bout[:n]
        outs[:] = self._out
        for q, ev in self._bev:              # in row order: each switches its output from its row on
            if ev.target is not None:
                outs[q:, ring.outputs.index(ev.target)] = ev.value
        if cut is None:
            w = ring.written()
            ring.push(self._block[:n], ep, outs)
        else:
            if ring.replace(cut, self._block[:n], ep, outs) is None:
                return False
            w = cut
            while self.pending and self.pending[-1][0] >= cut:
                self.pending.pop()
        self.pending.extend((w + q, ev) for q, ev in self._bev)
        if n:
            self._out[:] = outs[n - 1]
        k = (w + np.arange(n)) % ring.capacity
        self._hs[k], self._hf[k], self._hfd[k] = self._bs[:n], self._bf[:n], self._bfd[:n]
        self._hdone[k] = self.done_programs
        for q in range(n):
            self._htraj[k[q]] = self._btraj[q]
        return True

    def _state(self) -> tuple:
        return (self.cur, self.s, self.f, self.fd, list(self.queue), self.done_programs, self._ev_i,
                self.last.copy(), self.reason, self.holding, self.feed_m_s,
                None if self.trace is None else list(self.trace))

    def _restore(self, st: tuple) -> None:
        (self.cur, self.s, self.f, self.fd, q, self.done_programs, self._ev_i, last, self.reason,
         self.holding, self.feed_m_s, trace) = st
        self.queue.clear()
        self.queue.extend(q)
        self.last[:] = last
        if trace is not None:
            self.trace[:] = trace

    def _rewind(self, ep: int) -> int | None:
        """(lock held) Rewrite the ring's rows beyond the next ``guard`` cycles for a new hold,
        resume, abort or override: the filler's state is put back to the last row kept (its
        trajectory, path time, feed scale and rate; the trajectories begun after it back in
        front of the queue), the rows from there generated, then put in place of the ring's
        rows from the cut on in one compiled step (SetpointRing.replace): the loop never waits
        for the generation. When the loop came within two rows of the cut meanwhile, nothing is
        changed and it is tried again at once with a guard of at least twice the rows the loop
        took while the rows were generated. Returns the rows written, or None (nothing to
        rewrite: the caller tops up as usual)."""
        ring = self.stream
        w, r0 = ring.written(), ring.consumed()
        cut = r0 + self._guard_now
        if cut >= w or cut - 1 < self._hist_from or self._gone():   # no rows of ours beyond the guard
            self._rewrite = False
            if self.aborting:                # what is left ends within the guard: the abort is done
                self._clear("aborted")
            return None
        before = self._state()
        cap = ring.capacity
        k0 = (cut - 1) % cap
        t0 = self._htraj[k0]
        later: list = []
        for q in range(cut, w):
            t = self._htraj[q % cap]
            if t is not t0 and (not later or later[-1] is not t):
                later.append(t)
        self.queue.extendleft(reversed(later))
        ended = t0 is None or self._hs[k0] >= t0.duration
        self.cur = None if ended else t0
        self.s = 0.0 if ended else float(self._hs[k0])
        self.f, self.fd = (self.override, 0.0) if ended else (float(self._hf[k0]), float(self._hfd[k0]))
        self.done_programs = int(self._hdone[k0])
        self.last[:] = ring.setpoint(k0)
        self._out[:] = ring.row_outputs(k0)
        if self.aborting:                    # LinuxCNC's abort: spindle, torch and coolant off now
            self._out[self._stop_mask] = 0.0
        if self.trace is not None:
            del self.trace[len(self.trace) - (w - cut):]
        if self.cur is not None:
            self._ev_i = sum(1 for t, _ in self.cur.events if t <= self.s)
        self._bev.clear()
        self._defer_clear = ""
        # two blocks at once (0.25 s, half a lead of 0.5 s or less; 3-10 ms for an override's
        # ramp beside CPU hogs): what the rewrite leaves ahead must outlast a filler kept off the
        # CPU for a while (one block left a SCHED_OTHER filler beside CPU hogs to run dry on a
        # flipped override), and its generation, whatever the lead, is what the guard must
        # cover (else it is tried again with a wider guard); fill() tops the ring up to the
        # lead afterwards as usual
        n = self._generate(min(2 * self._chunk, cap - (cut - r0)))
        why, self._defer_clear = self._defer_clear, None
        if not self._push(n, ep, cut):       # the loop came too close: retry wider, at once
            self._restore(before)
            taken = ring.consumed() - r0     # the rows the loop took while this was generated
            self._guard_now = min(max(2 * self._guard_now, 2 * taken), self.lead // 2)
            self._wake.set()
            return 0
        self._rewrite = False
        self._guard_now = self.guard
        if why:
            self._clear(why)
        self.rewrites += 1
        return n

    def issue_events(self) -> int:
        """Note the machine words whose ring row the loop has taken (the loop itself applied
        their outputs at that row, :mod:`motorctl.loop.stream`): ``output_log``, and ``outputs``
        as the loop applies them now. Returns how many were taken."""
        ring = self.stream
        for j, o in enumerate(ring.outputs):
            self.outputs[o] = float(ring.applied()[j])
        done = 0
        if not self.pending:
            return 0
        taken = ring.consumed()
        with self.lock:
            while self.pending and self.pending[0][0] < taken:
                row, ev = self.pending.popleft()
                if ev.target is None:        # mapped to 'ignore': warned about when queued
                    continue
                self.output_log.append((row, ev.target, float(ev.value), ring.setpoint(row)[:, 0].copy()))
                done += 1
        return done

    def _target(self, cur, s: float) -> float:
        """The feed scale's target at path time s of ``cur`` (:func:`_feed_target`)."""
        return float(_feed_target(self.holding, self.override, cur.cap, cur.cap_dt, s))

    def _clear_or_defer(self, why: str) -> None:
        """(lock held) _clear, or, while a rewrite generates, after its rows are pushed."""
        if self._defer_clear is None:
            self._clear(why)
        else:
            self._defer_clear = why

    def _generate(self, need: int) -> int:
        """(lock held) Up to ``need`` rows into the block; fewer when the queue runs out or a
        hold has come to rest. The path times of a run of rows within one trajectory first
        (the feed scale's ramp, programmed pauses), then one block sample of them."""
        dt, out = self.dt, self._block
        j = 0
        while j < need:
            if self.cur is None:
                if not self.queue or self.holding:
                    if self.aborting:
                        self._clear_or_defer("aborted")
                    return j
                self.cur = self.queue.popleft()
                self.s = 0.0
                self._ev_i = 0
                self.f, self.fd = self._target(self.cur, 0.0), 0.0   # from rest: the override at once
                if self._resume_s is not None and self._resume_s[0] is self.cur:
                    # back on the path where an underrun stopped it: from rest, f ramps up, and
                    # the outputs the loop switched off at the underrun as they were there
                    _, self.s, outs = self._resume_s
                    self._resume_s = None
                    self.f, self.fd = 0.0, 0.0
                    self._ev_i = sum(1 for t, _ in self.cur.events if t <= self.s)
                    line = int(self.cur.line_at(self.s))
                    for o, v in zip(self.stream.outputs, outs):
                        self._bev.append((j, G.Event("resume", o, float(v), False, line, 0)))
            cur, m, ended, step, steady, uniform = self.cur, 0, False, 0.0, False, 0
            ss, ff, ffd = self._s, self._f, self._fd
            target = self._target(cur, self.s)
            if self.f == target and self.fd == 0.0 and target > 0.0:
                # the steady case, vectorised: s advances by f·Ts a row, up to the end, a pause,
                # or a change of the override's cap
                m = need - j
                ss[:m] = self.s + self.f * dt * self._steps[:m]
                if self.override > 1.0:
                    # the bins this block reaches (a change beyond its last row does not shorten it)
                    b0 = int(self.s / cur.cap_dt)
                    tb = np.minimum(self.override, np.maximum(1.0, cur.cap[b0:int(ss[m - 1] / cur.cap_dt) + 2]))
                    moved = np.flatnonzero(tb != self.f)
                    if moved.size:
                        s_cap = (b0 + int(moved[0])) * cur.cap_dt
                        m = max(1, min(m, int(np.searchsorted(ss[:m], s_cap, side="left"))))
                limit = min([t for t in self._pauses(cur) if t > self.s] + [cur.duration])
                over = int(np.searchsorted(ss[:m], limit, side="left"))
                hit = over < m
                if hit:
                    m = over + 1             # the row that reaches the limit (a pause: at it)
                    if limit < cur.duration:
                        ss[m - 1] = limit
                    else:
                        ended = True
                ff[:m], ffd[:m] = self.f, 0.0
                step = self.f * dt               # uniform rows (the last one may stop short)
                uniform = m - 1 if hit and limit < cur.duration else m
                self.s = float(ss[m - 1])
                if not ended and hit:
                    self.f, self.fd, self.holding = 0.0, 0.0, True
                    self.reason = "paused (M0/M1); resume goes on"
                    ff[m - 1] = 0.0
            if j + m < need and not ended:
                # the ramp's rows (an override's change, a hold, a resume), compiled; a programmed
                # pause (M0, M1) within them: at rest there, in a hold
                m, self.f, self.fd, self.s, self.holding, paused, ended, steady = _ramp_rows(
                    self.f, self.fd, self.s, self.holding, self.override, cur.cap, cur.cap_dt, self.f_rate,
                    self.f_accel, self.f_rate_hi, self.f_accel_hi, dt, np.array(self._pauses(cur), dtype=float),
                    cur.duration, ss, ff, ffd, m, need - j, step == 0.0)
                if paused:
                    self.reason = "paused (M0/M1); resume goes on"
            if m:
                rows = out[j:j + m]
                if uniform:                  # s0 + k·f·Ts by construction
                    self._sample(cur, ss[:uniform], rows[:uniform], step)
                if uniform < m:              # a pause's row, the ramp's rows
                    self._sample(cur, ss[uniform:m], rows[uniform:])
                if ended:                    # past its end: at rest there exactly
                    rows[-1, :, 0] = cur.end
                    rows[-1, :, 1:] = 0.0
                if self.trace is not None:
                    self.trace.extend(int(cur.line_at(t)) for t in ss[:m])
                rows[:, :, 2] = rows[:, :, 2] * (ff[:m] ** 2)[:, None] + rows[:, :, 1] * ffd[:m, None]
                rows[:, :, 1] *= ff[:m, None]
                self.last[:] = rows[-1]
                self._bs[j:j + m], self._bf[j:j + m], self._bfd[j:j + m] = ss[:m], ff[:m], ffd[:m]
                self._btraj[j:j + m] = [cur] * m
                evs = cur.events
                while self._ev_i < len(evs) and (ended or evs[self._ev_i][0] - 1e-9 <= ss[m - 1]):
                    # the row at its planned time (within 1 ns: the rows' times are sums of f·Ts)
                    q = min(int(np.searchsorted(ss[:m], evs[self._ev_i][0] - 1e-9, side="left")), m - 1)
                    self._bev.append((j + q, evs[self._ev_i][1]))
                    self._ev_i += 1
                self.feed_m_s = float(np.linalg.norm(rows[-1, :, 1]))
                j += m
            if ended:
                self.cur = None
                self.s = 0.0
                if not self.queue:
                    self.done_programs = self.queued_programs
                    self.feed_m_s = 0.0
                    return j
            elif not steady and (not m or j < need):          # came to rest in a hold
                if self.aborting:
                    self._clear_or_defer("aborted")
                return j
        return j

    def _sample(self, traj, s: np.ndarray, rows: np.ndarray, step: float = 0.0) -> None:
        """rows[k] = (x, ẋ, ẍ) per axis ((m, n_axes, 3)) of ``traj`` at its times s[k] [s]
        (increasing; ``step`` > 0: s[k] = s[0] + k·step). A planned path (it has a ``period``)
        is sampled on its own grid, the fast path of ``sample_into`` (rows off it at f·Ts apart
        took 40-80 ms a 625-row block on arcs, more than the 125 ms they last on a busy PC;
        on it 1.5 ms), with cubic Hermite in x and linear in ẋ, ẍ between grid points (error
        below a nanometre at 0.2 ms); other trajectories (Ruckig's) at the rows' own times
        when they are uniform, else on a grid of their largest spacing the same way."""
        m = s.size
        if step <= 0.0:
            diffs = np.diff(s)
            ds = float(diffs.max()) if m > 1 else 0.0
            uniform = m == 1 or ds <= 0.0 or bool(np.all(np.abs(diffs - ds) <= 1e-12))
        else:
            ds, uniform = step, True
        g = self._grid
        h = getattr(traj, "period", None)
        if uniform and (not h or m == 1 or abs(ds - h) <= 1e-12 * h):
            traj.sample_into(float(s[0]), ds, g[:m])
            rows[:] = g[:m].transpose(0, 2, 1)
            return
        if h:                                # a planned path: on its own grid
            ds = float(h)
            n_g = int(math.ceil((s[-1] - s[0]) / ds)) + 2
            if n_g > g.shape[0]:
                g = np.empty((n_g, 3, self.n))
        else:
            n_g = min(int(math.ceil((s[-1] - s[0]) / ds)) + 1, g.shape[0])
        traj.sample_into(float(s[0]), ds, g[:n_g])
        u = np.clip((s - s[0]) / ds, 0.0, n_g - 1 - 1e-12)
        k = np.minimum(u.astype(np.int64), n_g - 2)
        w = (u - k)[:, None]
        x0, x1 = g[k, 0], g[k + 1, 0]
        v0, v1 = g[k, 1] * ds, g[k + 1, 1] * ds
        w2, w3 = w * w, w * w * w
        rows[:, :, 0] = ((2 * w3 - 3 * w2 + 1) * x0 + (w3 - 2 * w2 + w) * v0 + (-2 * w3 + 3 * w2) * x1
                         + (w3 - w2) * v1)
        rows[:, :, 1] = (1 - w) * g[k, 1] + w * g[k + 1, 1]
        rows[:, :, 2] = (1 - w) * g[k, 2] + w * g[k + 1, 2]
