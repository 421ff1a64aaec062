"""The daemon's planner process: reads, checks and plans G-code programs away from the I/O
process, so that no program, however long, delays the setpoint stream or the recorder's drain.

The I/O process (:mod:`motorctl.app.daemon.io_side`) serves the socket, drains the recorder and
fills the setpoint ring from planned trajectories; planning a program took seconds of CPU under
its interpreter lock (a 720-segment CAM program: 1.4 s wall on a loaded host, long enough to
latch "recorder stalled"). Here it runs in a process of its own, forked by the I/O process
before its threads start, at the same (normal) priority as other work: on a busy host the
planning slows down, the feed and the drain do not.

**Priority**: with the loop's real-time set-up on (``loop.realtime.policy`` not ``off``) the
planner runs at nice :data:`PLAN_NICE`: above CPU-bound work at normal priority (so that a
program's check and its windows keep ahead beside it), below the loop (SCHED_FIFO) and the
I/O process's filler thread (SCHED_FIFO); the recorder's drain needs a few per cent of a core
and wakes with a sleeper's priority. Without that set-up (or the right to lower nice) it runs at
normal priority like the rest of the daemon.

A program goes through two passes over its text (a spooled file or the request's text), each
line by line with bounded memory (:class:`motorctl.motion.gcode.ProgramReader`):

1. **preview**: the whole program read and checked before anything moves (LinuxCNC's preview):
   the subset, the soft limits of every point and arc extreme
   (:func:`motorctl.motion.planner.check_segments`), the machine outputs its words switch,
   the axes it moves. The first error refuses the whole program (``file:line:column: why``);
2. **windows**: the program read again and planned a window at a time
   (:func:`motorctl.motion.planner.windows`: each window ends where the path is at rest, after
   about :data:`WINDOW_SOFT` moves, at the latest after :data:`WINDOW_HARD`), each window with
   its feed-override cap (:func:`motorctl.motion.planner.override_cap`). The first window is
   sent at once (motion starts); the next ones as the I/O process asks for them
   (:data:`AHEAD_WINDOWS` queued ahead of the one running), so memory stays bounded whatever the
   program's length.

Messages (pickled, :class:`~motorctl.app.daemon.protocol.Mailbox`), I/O → planner:
``{"op": "plan", "job": PlanJob}``, ``{"op": "more", "id"}`` (one more window),
``{"op": "cancel", "id"}``. Planner → I/O: ``{"op": "checked", "id", ...}`` or
``{"op": "refused", "id", "error"}``; ``{"op": "window", "id", "k", "traj", "last"}``;
``{"op": "failed", "id", "error"}``.
"""

from __future__ import annotations

import os
import select
import signal
import sys
from dataclasses import dataclass, field, replace

import numpy as np

from motorctl.app.pipes import Mailbox
from motorctl.app.lifetime import die_with_parent
from motorctl.motion import gcode as G
from motorctl.motion import planner as P

#: a window ends at the first point at rest after this many moves ...
WINDOW_SOFT = 1000
#: ... and at the latest after this many (an exact stop where the program has none)
WINDOW_HARD = 5000
#: windows planned and queued ahead of the one the filler runs
AHEAD_WINDOWS = 3
#: segments read per batch of a pass
BATCH = 2000
#: the planner process's nice value where the real-time set-up is on
PLAN_NICE = -8


@dataclass
class PlanJob:
    """One program to check and plan (pickled to the planner process).

    id: the job's number. path: a spooled program file (UTF-8), or None with ``text``.
    filename: named in errors. settings: the ``gcode:`` section (axes set to the machine's).
    start3: X Y Z before the program [m] (machine axes where they stand, 0 elsewhere).
    start: the machine axes before the program [m], in ``names`` order. offsets: the work
    offsets before it. soft: axis → (soft_min, soft_max) [m]. names: the machine's axes.
    limits: their v/a/j (:class:`motorctl.motion.planner.AxisLimits`). period: the loop's [s].
    outputs: the outputs the setpoint ring carries. cap: override_cap's keyword arguments.
    from_line: run from this source line (LinuxCNC's run from line: the program read from its
    start for the modal state, the motion from the line on, the way there a straight rapid from
    where the axes stand, then the machine words' outputs as the program left them before the
    line). single_block: an exact stop and a pause after every block (resume runs the next).
    """

    id: int
    path: str | None
    text: str | None
    filename: str
    settings: G.GcodeSettings
    start3: list
    start: list
    offsets: dict
    soft: dict
    names: list
    limits: list
    period: float
    outputs: list
    cap: dict = field(default_factory=dict)
    from_line: int = 1
    single_block: bool = False

    def lines(self):
        """The program's lines (a fresh pass)."""
        if self.path is not None:
            return open(self.path, encoding="utf-8", errors="strict", newline=None)
        return iter(self.text.splitlines())


def preview(job: PlanJob) -> dict:
    """Pass 1 (module docstring): the whole program read and checked. Returns the ``checked``
    message's fields: segments (moves), lines, warnings, moved (machine axis indices),
    end (machine axes [m]), offsets. Raises ValueError (one line: ``file:line[:column]: why``)."""
    reader = G.ProgramReader(job.filename, job.settings, job.start3, job.offsets)
    moves, moved = 0, set()
    xy = "X" in job.names and "Y" in job.names
    src = job.lines()
    try:
        for batch in reader.batches(src, BATCH):
            P.check_segments(batch, job.filename, job.soft)
            for seg in batch:
                if isinstance(seg, G.Event):
                    if seg.target is not None and seg.target not in job.outputs:
                        raise ValueError(f"{job.filename}:{seg.line}:{seg.column}: {seg.word}: output "
                                         f"{seg.target} is not one the loop carries "
                                         f"({', '.join(job.outputs) or 'none'}); M62-M65 take P 0-{G.N_DIO - 1}")
                elif isinstance(seg, G.Arc):
                    if not xy:
                        raise ValueError(f"{job.filename}:{seg.line}: an arc needs axes X and Y (this "
                                         f"machine: {' '.join(job.names)})")
                    moves += 1
                    moved.update((0, 1))
                    if seg.start[2] != seg.end[2]:
                        moved.add(2)
                elif isinstance(seg, G.Line):
                    moves += 1
                    moved.update(k for k in range(3) if seg.start[k] != seg.end[k])
    except UnicodeDecodeError as exc:
        raise ValueError(f"{job.filename}: not UTF-8 text ({exc.reason} at byte {exc.start} of a "
                         f"block)") from None
    finally:
        if hasattr(src, "close"):
            src.close()
    if job.from_line > reader.lines_read:
        raise ValueError(f"{job.filename}: --from-line {job.from_line} is beyond the program's last line "
                         f"({reader.lines_read})")
    if job.from_line > 1:                # the way to the line may move every axis
        moved.update(G.AXES.index(a) for a in job.names)
    prog = reader.program([])
    end = [float(prog.end[G.AXES.index(a)]) for a in job.names]
    return {"segments": moves, "lines": reader.lines_read, "warnings": prog.warnings,
            "moved": sorted(job.names.index(G.AXES[k]) for k in moved if G.AXES[k] in job.names),
            "end": end, "offsets": {k: v for k, v in prog.offsets.items() if k in G.SYSTEMS}}


def from_line(batches, line: int, start3):
    """The segments of ``batches`` from source ``line`` on (PlanJob.from_line): first a rapid
    from ``start3`` (X Y Z [m]) to where the program stands at that line, then the last value
    each machine output was given before it, then the program."""
    pos = np.asarray(start3, dtype=float).copy()
    last: dict = {}
    begun = False
    for batch in batches:
        out = []
        for seg in batch:
            if not begun and seg.line < line:
                if isinstance(seg, (G.Line, G.Arc)):
                    pos = np.asarray(seg.end, dtype=float).copy()
                elif isinstance(seg, G.Event) and seg.target is not None:
                    last[seg.target] = replace(seg, synchronized=False)
                continue
            if not begun:
                begun = True
                if np.any(pos != np.asarray(start3, dtype=float)):
                    out.append(G.Line(np.asarray(start3, dtype=float).copy(), pos.copy(), None, 0.0, line))
                out.extend(last.values())
            out.append(seg)
        if out:
            yield out


def single_block(batches):
    """Every move of ``batches`` in exact stop with a pause after it (PlanJob.single_block)."""
    for batch in batches:
        out = []
        for seg in batch:
            if isinstance(seg, (G.Line, G.Arc)):
                out.append(replace(seg, tolerance=0.0))
                out.append(G.Pause(False, seg.line))
            else:
                out.append(seg)
        yield out


def plan_windows(job: PlanJob):
    """Pass 2 (module docstring): the program's trajectories, one per window, each with its
    override cap (``traj.cap``, ``traj.cap_dt``), ``traj.job`` = the job's id and
    ``traj.last`` (the program's final window). Raises ValueError as the planner does."""
    reader = G.ProgramReader(job.filename, job.settings, job.start3, job.offsets)
    start = [float(x) for x in job.start]
    src = job.lines()
    batches = reader.batches(src, BATCH)
    if job.from_line > 1:
        batches = from_line(batches, job.from_line, job.start3)
    if job.single_block:
        batches = single_block(batches)
    try:
        for segs, last in P.windows(batches, soft=WINDOW_SOFT, hard=WINDOW_HARD):
            prog = reader.program(segs)
            traj = P.plan(prog, job.names, job.limits, start=start, period=job.period)
            traj.cap = P.override_cap(traj, job.limits, period=job.period, **job.cap)
            traj.cap_dt = max(1, int(round(job.cap["bin_s"] / job.period))) * job.period
            traj.job, traj.last = job.id, last
            start = [float(x) for x in traj.end]
            yield traj
    finally:
        if hasattr(src, "close"):
            src.close()


def plan_main(inbox: Mailbox, outbox: Mailbox, parent_pid: int) -> int:
    """The planner process: jobs from ``inbox`` one at a time, answers to ``outbox``, until the
    pipe closes or the parent dies."""
    die_with_parent(parent_pid, signal.SIGKILL)
    for s in (signal.SIGINT, signal.SIGHUP, signal.SIGTERM):
        signal.signal(s, signal.SIG_IGN)
    job, gen, credit, k = None, None, 0, 0
    while True:
        busy = gen is not None and credit > 0
        ready, _, _ = select.select([inbox.rfd], [], [], 0 if busy else 1.0)
        if ready:
            msgs = inbox.recv()
            if msgs is None:
                return 0
            for m in msgs:
                op = m.get("op")
                if op == "plan":
                    if gen is not None:
                        gen.close()
                    job, gen, credit, k = m["job"], None, 1, 0
                    try:
                        info = preview(job)
                    except (ValueError, OSError) as exc:
                        outbox.send({"op": "refused", "id": job.id, "error": str(exc)})
                        job = None
                        continue
                    outbox.send({"op": "checked", "id": job.id, **info})
                    gen = plan_windows(job)
                elif op == "more" and job is not None and m["id"] == job.id:
                    credit += 1
                elif op == "cancel" and job is not None and m["id"] == job.id:
                    if gen is not None:
                        gen.close()
                    job, gen, credit = None, None, 0
        if gen is None or credit <= 0:
            continue
        try:
            traj = next(gen, None)
        except (ValueError, OSError) as exc:
            outbox.send({"op": "failed", "id": job.id, "error": str(exc)})
            job, gen, credit = None, None, 0
            continue
        credit -= 1
        last = traj is None or traj.last
        outbox.send({"op": "window", "id": job.id, "k": k, "traj": traj, "last": last})
        k += 1
        if last:
            job, gen, credit = None, None, 0


class PlannerLink:
    """The I/O process's end of the planner process: start it (:meth:`start`: a fresh
    interpreter, ``python -m motorctl.app.program_planner``, so that it may be started again
    from the threaded I/O process when it died), send a job, read its answers."""

    def __init__(self):
        self.pid = 0
        self.proc = None
        self.nice = 0
        self.starts = 0
        self.to_plan: Mailbox | None = None
        self.from_plan: Mailbox | None = None

    def start(self, nice: int = 0) -> None:
        """Start the planner process, at ``nice`` where permitted (else at normal priority).
        Raises OSError (no process or pipe to be had)."""
        import subprocess
        self.nice = nice
        r1, w1 = os.pipe()
        r2, w2 = os.pipe()
        try:
            self.proc = subprocess.Popen(
                [sys.executable, "-m", "motorctl.app.program_planner", str(r1), str(w2), str(nice)],
                pass_fds=(r1, w2), stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, close_fds=True)
        finally:
            os.close(r1)
            os.close(w2)
        self.pid = self.proc.pid
        self.starts += 1
        self.to_plan = Mailbox(wfd=w1)
        self.from_plan = Mailbox(rfd=r2)

    @property
    def rfd(self) -> int:
        return self.from_plan.rfd

    def send(self, msg: dict) -> None:
        self.to_plan.send(msg)

    def stop(self) -> None:
        """Close the pipes and reap the process."""
        if self.proc is None:
            return
        for fd in (self.to_plan.wfd, self.from_plan.rfd):
            try:
                os.close(fd)
            except OSError:
                pass
        try:
            self.proc.kill()
            self.proc.wait(5)
        except OSError:
            pass
        self.proc, self.pid = None, 0


def _main(argv: list[str]) -> int:
    """``python -m motorctl.app.program_planner RFD WFD NICE`` (started by :class:`PlannerLink`)."""
    rfd, wfd, nice = (int(a) for a in argv)
    try:
        os.setpriority(os.PRIO_PROCESS, 0, nice)
    except OSError:
        pass
    return plan_main(Mailbox(rfd=rfd), Mailbox(wfd=wfd), os.getppid())


if __name__ == "__main__":
    sys.exit(_main(sys.argv[1:]))
