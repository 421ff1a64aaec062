"""The flight recorder: a preallocated shared-memory ring of cycle records, drained by another
process to an append-only run log, plus event logs around every fault and overrun.

Shape of the data (:class:`motorctl.loop.records.RecordLayout`): one float64 row per
cycle with ``t``, lateness, turnaround and per-phase times [ns], overruns, and per axis y, x_d,
ẋ_d, ẍ_d, u, v, e, p, x2, θ̂1..θ̂6, d̂0, enabled and the fault bits.

Who does what:
  * the loop process (5 kHz, SCHED_FIFO) writes row ``k`` at ``k % capacity`` of
    :attr:`SharedRing.rows` through a memoryview, then publishes ``k + 1`` in
    ``ctl[CTL_HEARTBEAT]`` (:meth:`SharedRing.publish`, the heartbeat; LinuxCNC's
    ``threadbeat``). Nothing else: no syscall, no allocation;
  * the I/O process (SCHED_OTHER) runs a :class:`Drainer` that copies the new rows out of the
    ring, appends them to the run log's segments (:class:`~motorctl.recorder.segments.
    SegmentWriter`, ``os.write``), and ``fdatasync``\\ s at least every ``flush_s``. A crash
    (``kill -9``) of either process loses at most the rows after the last flush; ``read_log``
    drops a partial last record. If the drainer falls more than a ring behind, the
    overwritten rows are counted in :attr:`Drainer.lost_rows`, never read torn (the heartbeat
    is re-read after the copy);
  * a write that fails (a full disk: ENOSPC; any OSError) never ends the I/O process: the
    drainer sets a recorder fault code in ``ctl[CTL_REC_FAULT]`` (the loop side latches every
    axis with FAULT_RECORDER between cycles), keeps the rows it could not write in the ring
    and retries every :data:`RETRY_S`; rows the ring overwrote meanwhile count as lost;
  * the I/O process bumps ``ctl[CTL_REC_BEAT]`` at every wake; the loop side watches it
    between cycles and latches every axis when it stops for longer than the stall bound
    (``2·flush_s + 1 s``, :func:`stall_bound_s`);
  * around each fault (a fault bit appearing on an axis) or overrun (the overrun counter
    increasing), the drainer also writes an event log holding ``event_before_s`` before and
    ``event_after_s`` after it (the hm2 TRACER idea, LinuxCNC#4236), in the run-log format.

Ordering: the loop's row stores come before its heartbeat store, and the drainer's heartbeat
load before its row loads, through explicit fences (:mod:`motorctl.ordering`), so the
argument holds on weakly ordered CPUs too, not only on x86-64's total store order.
"""

from __future__ import annotations

import errno
import mmap
import os
import time

import numpy as np

from motorctl.jit import dispatcher_of
from motorctl.ordering import load_acquire, store_release, warm_up
from motorctl.recorder.runlog import LogWriter

CTL_HEARTBEAT = 0     # cycles executed and published (rows below are complete)
CTL_CMD_SEQ = 1       # bumped by the I/O process after it queued a command for the loop
CTL_STATE = 2         # loop state: 0 starting, 1 running, 2 stopping, 3 ended
CTL_REC_FAULT = 3     # I/O process: REC_OK, or why its drainer cannot write the log
CTL_REC_BEAT = 4      # I/O process: bumped at every wake (the loop side watches it)
CTL_SEGMENT = 5       # I/O process: the run-log segment being written (1, 2, ...)
CTL_REC_LATCHED = 6   # loop side: the REC_* code it latched the axes with (0: none)
CTL_SIZE = 16

#: recorder fault codes (``ctl[CTL_REC_FAULT]``, ``ctl[CTL_REC_LATCHED]``) and their reasons
REC_OK, REC_DISK_FULL, REC_WRITE_ERROR, REC_STALLED, REC_DIED = 0, 1, 2, 3, 4
REC_REASONS = {REC_DISK_FULL: "log disk full", REC_WRITE_ERROR: "log write error",
               REC_STALLED: "recorder stalled", REC_DIED: "recorder died"}
#: after a failed write the drainer tries again this often [s]
RETRY_S = 0.2

#: at most one overrun event log per this time [s] (overruns come in floods when loaded)
OVERRUN_EVENT_SPACING_S = 10.0
_HIST_BIN_NS = 250.0
_HIST_BINS = 40000    # 0 .. 10 ms


def copy_rows(rows: np.ndarray, start: int, stop: int) -> np.ndarray:
    """A copy of cycles [start, stop) of a ring ``rows`` (capacity, width), cycle k in row
    k % capacity; (0, width) when stop ≤ start. The caller keeps stop − start ≤ capacity."""
    cap = rows.shape[0]
    if stop - start <= 0:
        return np.empty((0, rows.shape[1]))
    a, b = start % cap, stop % cap
    if a < b:
        return rows[a:b].copy()
    return np.concatenate([rows[a:], rows[:b]])


def take_rows(rows: np.ndarray, start: int, stop: int, published=None) -> tuple[np.ndarray, int]:
    """Cycles [start, stop) of the ring ``rows`` that it still holds: (the rows, the cycle of
    the first). ``published``: the writer's cycle count, read again after the copy so that rows
    overwritten meanwhile are dropped, never returned torn (None: no writer runs meanwhile)."""
    cap = rows.shape[0]
    start = max(start, stop - cap)
    out = copy_rows(rows, start, stop)
    if published is not None:
        torn = published() - cap - start          # overwritten while we copied
        if torn > 0:
            out, start = out[torn:], start + torn
    return out, start


class SharedRing:
    """Anonymous shared mapping for the loop and the I/O process; create it before ``fork``.

    Args:
        capacity: rows in the ring (choose ≥ (event_before_s + event_after_s + 2 s) · rate).
        width: floats per row (``len(columns)``). n_axes: axes of the loop.
        status_width: floats of the per-axis status block (the daemon's, published by the
            loop between cycles).
    Attributes:
        rows: (capacity, width) float64 view; ctl: (CTL_SIZE,) int64; status: (n_axes,
        status_width) float64.
    """

    def __init__(self, capacity: int, width: int, n_axes: int, status_width: int = 0):
        self.capacity, self.width, self.n_axes = int(capacity), int(width), int(n_axes)
        sw = self.status_width = int(status_width)
        nbytes = 8 * (CTL_SIZE + self.n_axes * sw + self.capacity * self.width)
        self._mm = mmap.mmap(-1, nbytes, flags=mmap.MAP_SHARED)
        buf = np.frombuffer(self._mm, dtype=np.uint8)
        buf.fill(0)        # every page made now: no store of the loop faults one in later
        off = 0
        self.ctl = buf[off:off + 8 * CTL_SIZE].view(np.int64)
        off += 8 * CTL_SIZE
        self.status = buf[off:off + 8 * self.n_axes * sw].view(np.float64).reshape(self.n_axes, sw)
        off += 8 * self.n_axes * sw
        self.rows = buf[off:].view(np.float64).reshape(self.capacity, self.width)
        warm_up()
        self._store_release = dispatcher_of(store_release)    # called once a cycle by the loop

    def publish(self, k: int) -> None:
        """Loop side: ``k`` cycles are complete (a release store after the rows' stores)."""
        self._store_release(self.ctl, CTL_HEARTBEAT, k)

    def published(self) -> int:
        """Rows written so far (the heartbeat; an acquire load before any row is read)."""
        return int(load_acquire(self.ctl, CTL_HEARTBEAT))

    def latest(self) -> np.ndarray | None:
        """A copy of the newest complete row, or None before the first cycle."""
        k = self.published()
        if k == 0:
            return None
        return self.rows[(k - 1) % self.capacity].copy()


def stall_bound_s(flush_s: float) -> float:
    """Longest the I/O process may go without a wake before the loop latches every axis
    with "recorder stalled" [s]: two flush intervals and a second (the documented bound on
    motion that is not logged)."""
    return 2.0 * float(flush_s) + 1.0


def hist_percentiles(hist: np.ndarray, qs=(50.0, 99.0, 99.9)) -> list[float]:
    """Percentiles [µs] of a histogram with :data:`_HIST_BIN_NS` bins (upper bin edge)."""
    total = int(hist.sum())
    if total == 0:
        return [float("nan")] * len(qs)
    cum = np.cumsum(hist)
    out = []
    for q in qs:
        idx = int(np.searchsorted(cum, q / 100.0 * total - 1e-9))
        out.append((idx + 1) * _HIST_BIN_NS / 1000.0)
    return out


class TimingStats:
    """Turnaround / lateness histograms (bins of 0.25 µs up to 10 ms) and maxima, accumulated
    batch by batch outside the loop (:meth:`add`: arrays (N,) [ns]); :meth:`summary` gives the
    percentiles [µs] as upper bin edges, so memory does not grow with the run."""

    def __init__(self):
        self.reset()

    def reset(self):
        self.turn = np.zeros(_HIST_BINS, dtype=np.int64)
        self.late = np.zeros(_HIST_BINS, dtype=np.int64)
        self.turn_max = 0.0
        self.late_max = 0.0
        self.cycles = 0

    def add(self, turn_ns: np.ndarray, late_ns: np.ndarray) -> None:
        if turn_ns.size == 0:
            return
        ti = np.clip((turn_ns / _HIST_BIN_NS).astype(np.int64), 0, _HIST_BINS - 1)
        li = np.clip((late_ns / _HIST_BIN_NS).astype(np.int64), 0, _HIST_BINS - 1)
        self.turn += np.bincount(ti, minlength=_HIST_BINS)
        self.late += np.bincount(li, minlength=_HIST_BINS)
        self.turn_max = max(self.turn_max, float(turn_ns.max()))
        self.late_max = max(self.late_max, float(late_ns.max()))
        self.cycles += int(turn_ns.size)

    def summary(self) -> dict:
        t50, t99, t999 = hist_percentiles(self.turn)
        l50, l99, l999 = hist_percentiles(self.late)
        return {"cycles": self.cycles,
                "turnaround_p50_us": t50, "turnaround_p99_us": t99, "turnaround_p999_us": t999,
                "turnaround_max_us": self.turn_max / 1000.0,
                "lateness_p50_us": l50, "lateness_p99_us": l99, "lateness_p999_us": l999,
                "lateness_max_us": self.late_max / 1000.0}


class Drainer:
    """Copy new rows from a :class:`SharedRing` into a run log; flush; cut event logs.

    Args:
        ring: the shared ring. writer: an open
        :class:`~motorctl.recorder.segments.SegmentWriter` with the same columns.
        header: the run log's header (copied into event logs). axis_names: loop order.
        timebase: the loop's :class:`~motorctl.loop.timebase.Timebase`. flush_s: longest
        time between fdatasync calls [s].
        event_before_s, event_after_s: window kept around each fault [s].
        overrun_before_s, overrun_after_s: window kept around an overrun [s] (shorter: an
            overrun's trace is the timing of a few cycles; a fault's is the motion before it).
        max_events: event logs per run (later events are only counted).
    Attributes:
        drained: next cycle to account (statistics, events); written: next cycle to write
        (behind ``drained`` while writes fail); lost_rows: published rows in no segment;
        fault: REC_OK or the REC_* code of the last failed write/flush (also in
        ``ring.ctl[CTL_REC_FAULT]``); error: its message; write_errors: failures so far.
    None of the methods raises OSError: a failed write sets ``fault`` and is retried.
    """

    def __init__(self, ring: SharedRing, writer, header: dict, axis_names, timebase,
                 flush_s: float = 0.5, event_before_s: float = 2.0, event_after_s: float = 1.0,
                 max_events: int = 20, overrun_before_s: float = 0.1, overrun_after_s: float = 0.1):
        self.ring, self.writer, self.header = ring, writer, header
        #: callables (rows (N, C), first cycle) given every batch of rows drained (a live
        #: view); they must return quickly and never raise
        self.taps: list = []
        self.axis_names = list(axis_names)
        self.period_s = timebase.period_s
        self.flush_s = float(flush_s)
        # (before, after) [cycles] per event kind
        self._window = {"fault": (timebase.cycles(event_before_s), timebase.cycles(event_after_s)),
                        "overrun": (timebase.cycles(overrun_before_s), timebase.cycles(overrun_after_s))}
        self.max_events = int(max_events)
        cols = list(header["columns"])
        self._c_turn = cols.index("turnaround_ns")
        self._c_late = cols.index("lateness_ns")
        self._c_ovr = cols.index("overruns")
        self._c_phase = [cols.index(c) for c in ("read_ns", "control_ns", "write_ns")]
        self._c_fault = [cols.index(f"{a}.fault_bits") for a in self.axis_names]
        self._c_en = [cols.index(f"{a}.enabled") for a in self.axis_names]
        self.drained = 0                 # next cycle index to account
        self.written = 0                 # next cycle index to write
        self.lost_rows = 0
        self.flushed_rows = 0
        self.last_flush = time.monotonic()
        self.flushes = 0
        self.max_flush_gap_s = 0.0
        self.fault = REC_OK
        self.error = ""
        self.write_errors = 0
        self._retry_at = 0.0
        self.loop_stats = TimingStats()
        self.axis_stats = [TimingStats() for _ in self.axis_names]
        self.phase_max_ns = [0.0, 0.0, 0.0]
        self._prev_fault = [0.0] * len(self.axis_names)
        self._prev_en = [0.0] * len(self.axis_names)
        self._prev_ovr = 0.0
        self.overruns = 0
        self.pending: list[dict] = []    # events waiting for their after-window
        self.events: list[dict] = []     # events recorded (with their event log path)
        self.events_dropped = 0
        self.fault_onsets: list[dict] = []   # every fault onset, for the once-only report
        self.overrun_spacing = timebase.cycles(OVERRUN_EVENT_SPACING_S)
        self._last_overrun_k = -(1 << 62)
        ring.ctl[CTL_SEGMENT] = writer.index

    # ------------------------------------------------------------------ draining
    def _take(self, start: int, stop: int) -> tuple[np.ndarray, int]:
        """Rows [start, stop) still in the ring, never torn: (rows, cycle of rows[0])."""
        return take_rows(self.ring.rows, start, stop, self.ring.published)

    def poll(self) -> int:
        """Account the rows published since the last call (statistics, events) and write
        what the log still lacks; returns the rows written."""
        k = self.ring.published()
        fresh = None
        if k > self.drained:
            in_step = self.written == self.drained
            rows, start = self._take(self.drained, k)
            if rows.shape[0]:
                self._account(rows, start)
                for tap in self.taps:
                    tap(rows, start)
            self.drained = k
            fresh = (rows, start) if in_step else None
        return self._write(k, fresh)

    def _write(self, k: int, fresh) -> int:
        if self.written >= k:
            return 0
        now = time.monotonic()
        if self.fault and now < self._retry_at:
            return 0
        rows, start = fresh if fresh is not None else self._take(self.written, k)
        if start > self.written:            # overwritten before they were written
            self.lost_rows += start - self.written
            self.written = start
        if rows.shape[0] == 0:
            return 0
        try:
            self.writer.append(rows, start)
        except OSError as exc:
            if start < self.writer.next_cycle <= k:      # the part written before the error
                self.written = self.writer.next_cycle
            self._failed(exc, now)
            return 0
        finally:
            self.ring.ctl[CTL_SEGMENT] = self.writer.index
        self.written = k
        if self.fault:
            self._recovered()
        return rows.shape[0]

    def _failed(self, exc: OSError, now: float) -> None:
        code = REC_DISK_FULL if exc.errno in (errno.ENOSPC, errno.EDQUOT) else REC_WRITE_ERROR
        self.fault = code
        self.error = f"{REC_REASONS[code]}: {exc.strerror or exc}"
        self.write_errors += 1
        self._retry_at = now + RETRY_S
        self.ring.ctl[CTL_REC_FAULT] = code

    def _recovered(self) -> None:
        self.fault = REC_OK
        self.ring.ctl[CTL_REC_FAULT] = REC_OK

    def _account(self, rows: np.ndarray, start: int) -> None:
        turn = rows[:, self._c_turn]
        late = rows[:, self._c_late]
        self.loop_stats.add(turn, late)
        for j, c in enumerate(self._c_phase):
            self.phase_max_ns[j] = max(self.phase_max_ns[j], float(rows[:, c].max()))
        for i in range(len(self.axis_names)):
            en = rows[:, self._c_en[i]]
            prev = np.concatenate(([self._prev_en[i]], en[:-1]))
            rises = np.flatnonzero((en > 0) & (prev <= 0))
            if rises.size:                 # the axis was (re)started: statistics since start
                self.axis_stats[i].reset()
                sel = slice(int(rises[-1]), None)
                m = en[sel] > 0
                self.axis_stats[i].add(turn[sel][m], late[sel][m])
            else:
                m = en > 0
                self.axis_stats[i].add(turn[m], late[m])
            self._prev_en[i] = float(en[-1])
            f = rows[:, self._c_fault[i]]
            prevf = np.concatenate(([self._prev_fault[i]], f[:-1]))
            for r in np.flatnonzero((f != 0) & (prevf == 0)):
                self._event(start + int(r), f"fault-{self.axis_names[i]}", int(f[r]))
            self._prev_fault[i] = float(f[-1])
        ovr = rows[:, self._c_ovr]
        prevo = np.concatenate(([self._prev_ovr], ovr[:-1]))
        self.overruns = int(ovr[-1])
        for r in np.flatnonzero(ovr > prevo)[:4]:
            self._event(start + int(r), "overrun", int(ovr[r]))
        self._prev_ovr = float(ovr[-1])

    def _event(self, k: int, kind: str, value: int) -> None:
        if kind.startswith("fault-"):
            self.fault_onsets.append({"k": k, "axis": kind[6:], "bits": value})
        for p in self.pending:             # merge into an open window of the same kind
            if p["k"] <= k < p["k"] + p["after"]:
                if p["kind"] == kind:
                    p["also"].append(kind)
                    return
                p["also"].append(kind)     # noted there, and still an event of its own
        if len(self.events) + len(self.pending) >= self.max_events:
            self.events_dropped += 1
            return
        if kind == "overrun":
            # overruns come in floods on a loaded SCHED_OTHER machine: one event log per
            # 10 s at most, and never more than half of the budget (faults keep the rest)
            n_ovr = sum(1 for e in self.events + self.pending if e["kind"] == "overrun")
            if (n_ovr >= max(self.max_events // 2, 1)
                    or k - self._last_overrun_k < self.overrun_spacing):
                self.events_dropped += 1
                return
            self._last_overrun_k = k
        before, after = self._window["overrun" if kind == "overrun" else "fault"]
        self.pending.append({"k": k, "kind": kind, "value": value, "also": [], "before": before,
                             "after": after})

    def cut_events(self, force: bool = False) -> list[str]:
        """Write the event logs whose after-window has been drained (all pending if force)."""
        done = []
        cap = self.ring.capacity
        published = self.ring.published()
        for p in list(self.pending):
            end = p["k"] + p["after"]
            if self.drained < end and not force:
                continue
            end = min(end, self.drained)
            start = max(p["k"] - p["before"], published - cap + 1, 0)
            rows = copy_rows(self.ring.rows, start, end)
            if self.ring.published() - cap > start:      # overwritten while copying
                cut = self.ring.published() - cap - start
                rows, start = rows[cut:], start + cut
            run = self.writer.run_path
            base = run[:-5] if run.endswith(".mlog") else run
            path = f"{base}.event{len(self.events) + 1:02d}-{p['kind']}.mlog"
            hdr = dict(self.header)
            hdr["event"] = {"kind": p["kind"], "value": p["value"], "also": p["also"],
                            "cycle": p["k"], "t_s": p["k"] * self.period_s,
                            "first_cycle": start, "rows": int(rows.shape[0])}
            retention = self.writer.retention
            if retention is not None:       # room for it within the budget first
                retention.prune(extra_bytes=rows.nbytes + 65536)   # (+ its header)
            try:
                with LogWriter(path, hdr) as w:
                    w.append(rows)
            except OSError as exc:         # (a full disk) no partial event log stays behind
                try:
                    os.unlink(path)
                except OSError:
                    pass
                path = f"(not written: {exc.strerror})"
            self.pending.remove(p)
            self.events.append({"kind": p["kind"], "cycle": p["k"], "t_s": p["k"] * self.period_s,
                                "also": p["also"], "path": path})
            done.append(path)
        return done

    def maybe_flush(self, force: bool = False) -> bool:
        """fdatasync the run log when ``flush_s`` has passed since the last one (or force).
        A failed fdatasync sets the fault (and is retried at the next call)."""
        now = time.monotonic()
        if not force and now - self.last_flush < self.flush_s:
            return False
        try:
            self.writer.flush()
        except OSError as exc:
            self._failed(exc, now)
            return False
        self.max_flush_gap_s = max(self.max_flush_gap_s, now - self.last_flush)
        self.last_flush = now
        self.flushed_rows = self.writer.rows_written
        self.flushes += 1
        return True

    def finish(self) -> None:
        """Drain everything published (one last try even after a failed write; what still
        cannot be written counts as lost) and cut the pending event logs. Then the caller
        writes the end record and calls :meth:`close`."""
        self._retry_at = 0.0
        self.poll()
        if self.written < self.drained:
            self.lost_rows += self.drained - self.written
            self.written = self.drained
        self.cut_events(force=True)

    def close(self) -> None:
        """Flush and close the run log (a failure is kept in ``fault``/``error``)."""
        self.maybe_flush(force=True)
        try:
            self.writer.close()
        except OSError as exc:
            self._failed(exc, time.monotonic())


__all__ = ["SharedRing", "Drainer", "hist_percentiles", "stall_bound_s", "REC_REASONS"]
