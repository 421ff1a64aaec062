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
    ring, appends them to the run log (``os.write``), and ``fdatasync``\\ s at least every
    ``flush_s``. A crash (``kill -9``) of either process loses at most the rows after the
    last flush; ``read_log`` drops a partial last record. If the drainer falls more than a
    ring behind, the overwritten rows are counted in :attr:`Drainer.lost_rows`, never read
    torn (the heartbeat is re-read after the copy);
  * around each fault (a fault bit appearing on an axis) or overrun (the overrun counter
    increasing), the drainer also writes an event log holding ``event_before_s`` before and
    ``event_after_s`` after it (the hm2 TRACER idea, LinuxCNC#4236), in the run-log format.

Ordering: the loop's row stores come before its heartbeat store, and the drainer's heartbeat
load before its row loads, through explicit fences (:mod:`motorctl.recorder.ordering`), so the
argument holds on weakly ordered CPUs too, not only on x86-64's total store order.
"""

from __future__ import annotations

import mmap
import time

import numpy as np

from motorctl.recorder.ordering import load_acquire, store_release, warm_up
from motorctl.recorder.runlog import LogWriter

CTL_HEARTBEAT = 0     # cycles executed and published (rows below are complete)
CTL_CMD_SEQ = 1       # bumped by the I/O process after it queued a command for the loop
CTL_STATE = 2         # loop state: 0 starting, 1 running, 2 stopping, 3 ended
CTL_SIZE = 16

#: at most one overrun event log per this time [s] (overruns come in floods when loaded)
OVERRUN_EVENT_SPACING_S = 10.0
_HIST_BIN_NS = 250.0
_HIST_BINS = 40000    # 0 .. 10 ms


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
        off = 0
        self.ctl = buf[off:off + 8 * CTL_SIZE].view(np.int64)
        off += 8 * CTL_SIZE
        self.status = buf[off:off + 8 * self.n_axes * sw].view(np.float64).reshape(self.n_axes, sw)
        off += 8 * self.n_axes * sw
        self.rows = buf[off:].view(np.float64).reshape(self.capacity, self.width)
        warm_up()

    def publish(self, k: int) -> None:
        """Loop side: ``k`` cycles are complete (a release store after the rows' stores)."""
        store_release(self.ctl, CTL_HEARTBEAT, k)

    def published(self) -> int:
        """Rows written so far (the heartbeat; an acquire load before any row is read)."""
        return int(load_acquire(self.ctl, CTL_HEARTBEAT))

    def latest(self) -> np.ndarray | None:
        """A copy of the newest complete row, or None before the first cycle."""
        k = self.published()
        if k == 0:
            return None
        return self.rows[(k - 1) % self.capacity].copy()


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


class _Stats:
    """Turnaround / lateness histograms and maxima (numpy, outside the loop)."""

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
        ring: the shared ring. writer: an open :class:`LogWriter` with the same columns.
        header: the run log's header (copied into event logs). axis_names: loop order.
        timebase: the loop's :class:`~motorctl.loop.timebase.Timebase`. flush_s: longest
        time between fdatasync calls [s].
        event_before_s, event_after_s: window kept around each fault/overrun [s].
        max_events: event logs per run (later events are only counted).
    """

    def __init__(self, ring: SharedRing, writer: LogWriter, header: dict, axis_names, timebase,
                 flush_s: float = 0.5, event_before_s: float = 2.0, event_after_s: float = 1.0,
                 max_events: int = 20):
        self.ring, self.writer, self.header = ring, writer, header
        self.axis_names = list(axis_names)
        self.period_s = timebase.period_s
        self.flush_s = float(flush_s)
        self.before = timebase.cycles(event_before_s)
        self.after = timebase.cycles(event_after_s)
        self.max_events = int(max_events)
        cols = list(header["columns"])
        self._c_turn = cols.index("turnaround_ns")
        self._c_late = cols.index("lateness_ns")
        self._c_ovr = cols.index("overruns")
        self._c_phase = [cols.index(c) for c in ("read_ns", "control_ns", "write_ns")]
        self._c_fault = [cols.index(f"{a}.fault_bits") for a in self.axis_names]
        self._c_en = [cols.index(f"{a}.enabled") for a in self.axis_names]
        self.drained = 0                 # next cycle index to copy
        self.lost_rows = 0
        self.flushed_rows = 0
        self.last_flush = time.monotonic()
        self.flushes = 0
        self.max_flush_gap_s = 0.0
        self.loop_stats = _Stats()
        self.axis_stats = [_Stats() for _ in self.axis_names]
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

    # ------------------------------------------------------------------ draining
    def _copy(self, start: int, stop: int) -> np.ndarray:
        cap = self.ring.capacity
        a, b = start % cap, stop % cap
        if stop - start <= 0:
            return np.empty((0, self.ring.width))
        if a < b:
            return self.ring.rows[a:b].copy()
        return np.concatenate([self.ring.rows[a:], self.ring.rows[:b]])

    def poll(self) -> int:
        """Drain the rows published since the last call; returns how many were appended."""
        ring, cap = self.ring, self.ring.capacity
        k = ring.published()
        start = self.drained
        if k <= start:
            return 0
        if k - start > cap:
            self.lost_rows += k - cap - start
            start = k - cap
        rows = self._copy(start, k)
        k2 = ring.published()
        torn = k2 - cap - start      # rows the loop overwrote while we copied
        if torn > 0:
            self.lost_rows += torn
            rows = rows[torn:]
            start += torn
        self.drained = k
        if rows.shape[0] == 0:
            return 0
        self.writer.append(rows)
        self._account(rows, start)
        return rows.shape[0]

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
            if p["k"] <= k < p["k"] + self.after:
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
        self.pending.append({"k": k, "kind": kind, "value": value, "also": []})

    def cut_events(self, force: bool = False) -> list[str]:
        """Write the event logs whose after-window has been drained (all pending if force)."""
        done = []
        cap = self.ring.capacity
        published = self.ring.published()
        for p in list(self.pending):
            end = p["k"] + self.after
            if self.drained < end and not force:
                continue
            end = min(end, self.drained)
            start = max(p["k"] - self.before, published - cap + 1, 0)
            rows = self._copy(start, end)
            if self.ring.published() - cap > start:      # overwritten while copying
                cut = self.ring.published() - cap - start
                rows, start = rows[cut:], start + cut
            base = self.writer.path[:-5] if self.writer.path.endswith(".mlog") else self.writer.path
            path = f"{base}.event{len(self.events) + 1:02d}-{p['kind']}.mlog"
            hdr = dict(self.header)
            hdr["event"] = {"kind": p["kind"], "value": p["value"], "also": p["also"],
                            "cycle": p["k"], "t_s": p["k"] * self.period_s,
                            "first_cycle": start, "rows": int(rows.shape[0])}
            try:
                with LogWriter(path, hdr) as w:
                    w.append(rows)
            except OSError as exc:
                path = f"(not written: {exc.strerror})"
            self.pending.remove(p)
            self.events.append({"kind": p["kind"], "cycle": p["k"], "t_s": p["k"] * self.period_s,
                                "also": p["also"], "path": path})
            done.append(path)
        return done

    def maybe_flush(self, force: bool = False) -> bool:
        """fdatasync the run log when ``flush_s`` has passed since the last one (or force)."""
        now = time.monotonic()
        if not force and now - self.last_flush < self.flush_s:
            return False
        self.writer.flush()
        self.max_flush_gap_s = max(self.max_flush_gap_s, now - self.last_flush)
        self.last_flush = now
        self.flushed_rows = self.writer.rows_written
        self.flushes += 1
        return True

    def finish(self) -> None:
        """Drain everything published, cut pending event logs, flush and close the log."""
        self.poll()
        self.cut_events(force=True)
        self.maybe_flush(force=True)
        self.writer.close()


__all__ = ["SharedRing", "Drainer", "hist_percentiles"]
