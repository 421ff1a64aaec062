"""A daemon's run log as a numbered set of segment files, their retention, and reading the set
back as one run.

Names (in ``daemon.log_dir``)::

    motorctl-STAMP-PID.mlog                  the run's name (no file of that name is written)
    motorctl-STAMP-PID.0001.mlog, .0002 ...  its segments, in order
    motorctl-STAMP-PID.event01-KIND.mlog     its event logs (flight.Drainer)

Every segment is a complete run log (:mod:`motorctl.recorder.runlog`) with the run's header
plus ``segment: {run, index, first_cycle}``; its rows are the cycles ``first_cycle``,
``first_cycle + 1``, ... without a gap (rows the drainer lost start a new segment). The end
record (``ended``) and the run's ``events`` and ``commands`` are in the last segment's header.

Rotation (:class:`SegmentWriter`): a segment is closed when the next rows would take it past
``segment_bytes`` or when it is ``segment_s`` old; it is fsynced and closed, then the budget is
enforced, and only then is the next one created, so no written row is ever lost to rotation.

Retention (:class:`Retention`, before every new segment and every event log, and every
:data:`PRUNE_S`): over every run's files in the directory, routine segments older than
``max_age_s`` are deleted; then, while the closed files plus one full segment (plus the event
log about to be written) exceed ``budget_bytes``, the oldest routine segment goes first (event
logs are kept longer), event logs only once no routine segment is left to delete or when they
hold more than the budget less two segments (the one being written and the newest closed one),
overrun event logs before fault event logs, oldest first. So the directory never holds more than the budget. The
segment being written, and the last segment of a run whose process is alive (another daemon
on the same directory), are never deleted; files of other names are never touched.
"""

from __future__ import annotations

import os
import re
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from motorctl.recorder.runlog import CHUNK_ROWS, LogError, LogFile, LogWriter, RunLog, open_log

#: the run's name: motorctl-STAMP-PID
_RUN = r"motorctl-\d{8}T\d{6}-(?P<pid>\d+)"
_SEGMENT_RE = re.compile(rf"(?P<run>{_RUN})(?:\.(?P<index>\d{{4,}}))?\.mlog")
_EVENT_RE = re.compile(rf"(?P<run>{_RUN})\.event\d+-[A-Za-z0-9_-]+\.mlog")
#: event logs are kept before routine segments, up to the budget less this many segments
EVENT_ROOM_SEGMENTS = 2
#: how often the age limit is enforced (and the figures refreshed) besides every rotation
#: and event log [s]
PRUNE_S = 2.0


def segment_path(run_path: str, index: int) -> str:
    """Path of segment ``index`` (1, 2, ...) of the run named ``run_path`` (``….mlog``)."""
    base = run_path[:-5] if run_path.endswith(".mlog") else run_path
    return f"{base}.{index:04d}.mlog"


class SegmentWriter:
    """Write a run log as segments (see the module docstring). Outside the cycle only.

    Args:
        run_path: the run's name, ``DIR/motorctl-STAMP-PID.mlog``. header: the run's header
            (dict with ``columns``). reserve: header bytes reserved in every segment.
        segment_bytes: largest segment [bytes] (a fresh segment takes at least one row).
        segment_s: oldest a segment gets before the next rows go to a new one [s].
        retention: a :class:`Retention` run before each new segment is created (or None).
    Attributes:
        index: the segment being written (1 ...); path: its file; first_cycle: its first
        row's cycle; next_cycle: the cycle of the next row it can take without a gap;
        rows_written and bytes_written: over every segment of the run.
    Raises:
        OSError: the first segment cannot be created.
    """

    def __init__(self, run_path: str, header: dict, reserve: int = 0,
                 segment_bytes: int = 1 << 29, segment_s: float = 3600.0, retention=None):
        self.run_path = str(run_path)
        self.run = Path(self.run_path).name[:-5]
        self.header = header
        self.reserve = int(reserve)
        self.segment_bytes = int(segment_bytes)
        self.segment_s = float(segment_s)
        self.retention = retention
        if retention is not None:
            retention.writer = self
        self.rec = 8 * len(header["columns"])
        self.index = 0
        self.cur: LogWriter | None = None
        self.opened = 0.0
        self.rows_written = 0
        self.bytes_closed = 0
        self.first_cycle = self.next_cycle = 0
        self._open(0)

    @property
    def path(self) -> str:
        """The segment being written (or the last one, between a rotation and the next rows)."""
        return segment_path(self.run_path, max(self.index, 1))

    @property
    def bytes_written(self) -> int:
        return self.bytes_closed + (self.cur.size if self.cur is not None else 0)

    def _segment_header(self) -> dict:
        return {**self.header, "segment": {"run": self.run, "index": self.index,
                                           "first_cycle": int(self.first_cycle)}}

    def _open(self, first_cycle: int) -> None:
        if self.retention is not None:
            self.retention.prune()            # room for one whole segment within the budget
        self.index += 1
        self.first_cycle = int(first_cycle)
        try:
            self.cur = LogWriter(self.path, self._segment_header(), reserve=self.reserve)
        except OSError:
            self.index -= 1
            raise
        self.opened = time.monotonic()
        self.next_cycle = self.first_cycle

    def rotate(self) -> None:
        """Close the segment being written (fsync, then close); the next rows start a new
        one. Raises OSError (the fsync failed; the descriptor is closed all the same)."""
        if self.cur is not None:
            cur, self.cur = self.cur, None
            self.bytes_closed += cur.size
            cur.close()

    def append(self, rows: np.ndarray, first_cycle: int) -> None:
        """Append rows (k, W) whose first row is cycle ``first_cycle``: a gap in the cycles,
        a full segment or an old one closes the segment and the rows go on in the next.

        Raises:
            OSError: a write, an fsync or a new segment failed. The rows up to
            ``next_cycle`` are written; a retry goes on from there.
        """
        k0, n = int(first_cycle), rows.shape[0]
        i = 0
        while i < n:
            cur = self.cur
            if cur is not None and k0 + i != self.next_cycle:
                if cur.rows_written == 0:     # nothing in it yet: it starts here instead
                    self.first_cycle = self.next_cycle = k0 + i
                    cur.update_header(self._segment_header())
                else:
                    self.rotate()
                    cur = None
            elif cur is not None and cur.rows_written and (
                    cur.size + self.rec > self.segment_bytes
                    or time.monotonic() - self.opened >= self.segment_s):
                self.rotate()
                cur = None
            if cur is None:
                self._open(k0 + i)
                cur = self.cur
            fit = max(1, (self.segment_bytes - cur.size) // self.rec)
            part = rows[i:i + fit]
            cur.append(part)
            self.rows_written += part.shape[0]
            i += part.shape[0]
            self.next_cycle = k0 + i

    def update_header(self, header: dict) -> bool:
        """Set the run's header (later segments get it) and rewrite the current segment's
        in place (the last closed one's when no segment is open: a new one could not be
        created). False when it does not fit the reserved space. Raises OSError, LogError."""
        self.header = header
        if self.cur is not None:
            return self.cur.update_header(self._segment_header())
        if self.index == 0:
            return True
        w, old = LogWriter.reopen(self.path)
        try:
            return w.update_header({**header, "segment": old.get("segment")})
        finally:
            w.close()

    def flush(self) -> None:
        """fdatasync the segment being written. Raises OSError."""
        if self.cur is not None:
            self.cur.flush()

    def release(self) -> None:
        """Close this process's descriptor without syncing (the other process writes on)."""
        if self.cur is not None:
            self.cur.release()

    def close(self) -> None:
        """fsync and close the segment being written. Raises OSError."""
        self.rotate()


# --------------------------------------------------------------------------- retention
@dataclass
class _File:
    path: str
    size: int
    mtime: float
    run: str
    pid: int
    index: int          # segment index (0: a log of one file); -1: an event log


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:
        return True
    return True


@dataclass
class Retention:
    """Keep ``log_dir`` within a byte budget and an age (see the module docstring).

    Args:
        log_dir: the directory. budget_bytes: most bytes of run logs and event logs kept.
        segment_bytes: the largest segment (room for one is kept free within the budget).
        max_age_s: routine segments older than this are deleted [s].
        row_bytes_per_s: bytes of records a second (for :meth:`figures`).
    Attributes:
        writer: the :class:`SegmentWriter` whose segment is never deleted (set by it).
        kept_*: what the last scan found; dropped_segments / dropped_events: deleted so far;
        errors: deletions or scans that failed (the next prune tries again).
    """

    log_dir: str
    budget_bytes: int
    segment_bytes: int
    max_age_s: float
    row_bytes_per_s: float = 0.0
    writer: SegmentWriter | None = None
    kept_bytes: int = 0
    kept_segments: int = 0
    kept_events: int = 0
    kept_event_bytes: int = 0
    oldest_segment_age_s: float = 0.0
    dropped_segments: int = 0
    dropped_events: int = 0
    errors: int = 0
    last_prune: float = field(default=0.0)
    started: float = field(default_factory=time.monotonic)

    @property
    def event_cap_bytes(self) -> int:
        """Most bytes of event logs kept before routine segments: the budget less
        :data:`EVENT_ROOM_SEGMENTS` segments."""
        return max(self.budget_bytes - EVENT_ROOM_SEGMENTS * self.segment_bytes, 0)

    def scan(self) -> list[_File]:
        """The run logs and event logs in ``log_dir`` (other files are never touched)."""
        out = []
        with os.scandir(self.log_dir) as it:
            for e in it:
                m = _SEGMENT_RE.fullmatch(e.name)
                ev = None if m else _EVENT_RE.fullmatch(e.name)
                if not (m or ev):
                    continue
                try:
                    st = e.stat(follow_symlinks=False)
                except OSError:
                    continue
                if not e.is_file(follow_symlinks=False):
                    continue
                g = (m or ev)
                idx = -1 if ev else int(m.group("index") or 0)
                out.append(_File(e.path, st.st_size, st.st_mtime, g.group("run"), int(g.group("pid")), idx))
        return out

    def prune(self, extra_bytes: int = 0) -> None:
        """Delete what the age and the budget require now, keeping room for one whole
        segment and ``extra_bytes`` more (an event log about to be written). Never raises:
        a failed scan or deletion is counted in ``errors`` and tried again later."""
        self.last_prune = time.monotonic()
        try:
            files = self.scan()
        except OSError:
            self.errors += 1
            return
        w = self.writer
        cur = w.path if w is not None and w.cur is not None else None
        own = w.run if w is not None else None
        last: dict = {}                   # run -> its highest segment index
        for f in files:
            if f.index >= 0:
                last[f.run] = max(last.get(f.run, 0), f.index)

        def protected(f: _File) -> bool:  # may still be written to
            if f.path == cur:
                return True
            return (f.index >= 0 and f.run != own and f.index == last[f.run]
                    and _pid_alive(f.pid))
        now = time.time()
        keep = []
        for f in files:
            if f.index >= 0 and not protected(f) and now - f.mtime > self.max_age_s:
                self._delete(f)
            else:
                keep.append(f)
        routine = sorted((f for f in keep if f.index >= 0 and not protected(f)),
                         key=lambda f: (f.mtime, f.run, f.index))
        # overrun event logs go before fault event logs, each oldest first
        events = sorted((f for f in keep if f.index < 0),
                        key=lambda f: ("-overrun." not in f.path, f.mtime, f.path))
        closed = sum(f.size for f in keep if f.path != cur)
        ev_bytes = sum(f.size for f in events)
        gone = set()
        while closed + self.segment_bytes + extra_bytes > self.budget_bytes and (routine or events):
            if events and (ev_bytes > self.event_cap_bytes or not routine):
                f = events.pop(0)
                ev_bytes -= f.size
            else:
                f = routine.pop(0)
            if self._delete(f):
                gone.add(f.path)
                closed -= f.size
        kept = [f for f in keep if f.path not in gone]
        self.kept_bytes = sum(f.size for f in kept)
        self.kept_segments = sum(1 for f in kept if f.index >= 0)
        self.kept_events = sum(1 for f in kept if f.index < 0)
        self.kept_event_bytes = sum(f.size for f in kept if f.index < 0)
        seg = [f.mtime for f in kept if f.index >= 0]
        self.oldest_segment_age_s = now - min(seg) if seg else 0.0

    def _delete(self, f: _File) -> bool:
        try:
            os.unlink(f.path)
        except FileNotFoundError:
            return True
        except OSError:
            self.errors += 1
            return False
        if f.index < 0:
            self.dropped_events += 1
        else:
            self.dropped_segments += 1
        return True

    def maybe_prune(self, now: float) -> None:
        """Prune every :data:`PRUNE_S` (the age limit; rotations and event logs prune
        before they write)."""
        if now - self.last_prune >= PRUNE_S:
            self.prune()

    def figures(self) -> dict:
        """For ``status``: the rate the run writes [bytes/s, measured: the bytes written over
        the run's time, its rows at the records' rate, so that the start-up and a loaded host
        do not move it], the records' rate [bytes/s], what is kept against the budget [bytes],
        and how many days of routine rows the budget holds at the records' rate next to the
        event logs kept now (``days_at_budget``, at most ``max_age_s``)."""
        w = self.writer
        if w is not None and self.row_bytes_per_s > 0:
            up = max(w.rows_written * w.rec / self.row_bytes_per_s, 1e-9)
        else:
            up = max(time.monotonic() - self.started, 1e-9)
        room = max(self.budget_bytes - self.kept_event_bytes, self.segment_bytes)
        days = (min(room / self.row_bytes_per_s, self.max_age_s) / 86400.0
                if self.row_bytes_per_s > 0 else 0.0)
        return {"bytes_per_s": (w.bytes_written / up) if w is not None else 0.0,
                "row_bytes_per_s": self.row_bytes_per_s,
                "kept_bytes": self.kept_bytes, "budget_bytes": self.budget_bytes,
                "kept_segments": self.kept_segments, "kept_events": self.kept_events,
                "kept_event_bytes": self.kept_event_bytes,
                "oldest_segment_age_s": self.oldest_segment_age_s,
                "segment_bytes": self.segment_bytes, "max_age_s": self.max_age_s,
                "days_at_budget": days,
                "dropped_segments": self.dropped_segments, "dropped_events": self.dropped_events,
                "errors": self.errors}


# --------------------------------------------------------------------------- reading
@dataclass
class Run:
    """A run read as one: its segments in order (one file for a plain run log).

    Attributes:
        path: what was asked for. segments: list of :class:`~motorctl.recorder.runlog.LogFile`.
        header: the last segment's header (it holds ``ended``, ``events``, ``commands``).
        columns; n_rows (all segments); truncated_bytes (partial records ignored); gaps:
        list of (cycle, rows) missing between kept segments (dropped by retention or lost).
    """

    path: str
    segments: list

    @property
    def header(self) -> dict:
        return self.segments[-1].header

    @property
    def columns(self) -> list:
        return self.segments[0].columns

    @property
    def axes(self) -> list:
        return self.segments[-1].axes

    @property
    def n_rows(self) -> int:
        return sum(s.n_rows for s in self.segments)

    @property
    def truncated_bytes(self) -> int:
        return sum(s.truncated_bytes for s in self.segments)

    @property
    def gaps(self) -> list:
        out = []
        for a, b in zip(self.segments, self.segments[1:]):
            ka, kb = _first_cycle(a), _first_cycle(b)
            if ka is not None and kb is not None and kb != ka + a.n_rows:
                out.append((ka + a.n_rows, kb - ka - a.n_rows))
        return out

    def chunks(self, rows: int = CHUNK_ROWS):
        """Every record of every segment in order, in arrays of at most ``rows`` rows
        (memory bounded by ``rows``). Raises LogError, OSError."""
        for s in self.segments:
            yield from s.chunks(rows)

    def read(self) -> RunLog:
        """The whole run in memory as one :class:`RunLog` (the last segment's header)."""
        parts = [s.read() for s in self.segments]
        data = np.concatenate(parts) if len(parts) > 1 else parts[0]
        return RunLog(self.header, self.columns, data, self.truncated_bytes)


def _first_cycle(lf: LogFile):
    seg = lf.header.get("segment")
    k = seg.get("first_cycle") if isinstance(seg, dict) else None
    return k if isinstance(k, int) and not isinstance(k, bool) and k >= 0 else None


def open_run(path: str) -> Run:
    """Open a run for reading: a plain run log or event log (one file), or a daemon's run
    given by its name (``motorctl-STAMP-PID.mlog``, the file need not exist) or by any of its
    segments, which reads every kept segment in order.

    Raises:
        LogError: nothing readable at ``path``, a damaged file, or segments that do not fit
        together (other columns, the same index twice); one line naming the file.
    """
    path = str(path)
    p = Path(path)
    run = None
    if os.path.lexists(path):
        first = open_log(path)
        seg = first.header.get("segment")
        if not isinstance(seg, dict) or "event" in first.header:
            return Run(path, [first])
        run = seg.get("run")
        if not isinstance(run, str) or not re.fullmatch(_RUN, run):
            raise LogError(f"{path}: damaged header ('segment.run' is not a run name)")
    elif re.fullmatch(_RUN + r"\.mlog", p.name):
        run = p.name[:-5]
    if run is None:
        raise LogError(f"{path}: no such file")
    names = []
    try:
        entries = os.listdir(p.parent if str(p.parent) else ".")
    except OSError as exc:
        raise LogError(f"{path}: cannot list its directory ({exc.strerror or exc})") from None
    for name in entries:
        m = _SEGMENT_RE.fullmatch(name)
        if m and m.group("run") == run and m.group("index"):
            names.append((int(m.group("index")), str(p.parent / name)))
    if not names:
        raise LogError(f"{path}: no such file (and no segments {run}.NNNN.mlog beside it)")
    segs = [open_log(q) for _, q in sorted(names)]
    for (idx, q), s in zip(sorted(names), segs):
        if s.columns != segs[0].columns:
            raise LogError(f"{q}: other columns than {segs[0].path}; not a segment of the same run")
        hs = s.header.get("segment")
        if not isinstance(hs, dict) or hs.get("index") != idx or hs.get("run") != run \
                or _first_cycle(s) is None:
            raise LogError(f"{q}: damaged header ('segment' does not name this run and index {idx})")
    return Run(path, segs)


def read_run(path: str) -> RunLog:
    """:func:`open_run` then every record in memory (for plots; exports stream with
    :meth:`Run.chunks`). Raises LogError, OSError."""
    return open_run(path).read()


def close_orphaned(run_path: str, index: int, ring, ended: dict) -> dict:
    """After the process that wrote a run died: finish its segment ``index`` from the shared
    ring and write the end record. Called by the loop process once its loop has ended.

    The rows the ring still holds after the segment's last whole record are appended (a
    partial record is cut off first), unless that would leave a gap; ``ended`` gets
    ``cycles``, ``lost_rows`` (published but in no segment) and ``written_by``. Returns it.

    Raises:
        LogError: the segment is not a readable run log. OSError: it cannot be written.
    """
    path = segment_path(run_path, max(int(index), 1))
    w, header = LogWriter.reopen(path)
    try:
        seg = header.get("segment")
        k0 = seg.get("first_cycle") if isinstance(seg, dict) else None
        k_file = (k0 if isinstance(k0, int) else 0) + w.rows_written
        pub = ring.published()
        lost = max(pub - k_file, 0)
        if 0 < lost <= ring.capacity and ring.width == w.width:
            try:
                w.append(ring.rows[np.arange(k_file, pub) % ring.capacity])
                lost = 0
            except OSError:
                pass                      # (a full disk) the end record still goes in
        ended = {**ended, "cycles": int(pub), "lost_rows": int(lost), "written_by": "loop process"}
        w.update_header({**header, "ended": ended})
    finally:
        w.close()
    return ended


__all__ = ["SegmentWriter", "Retention", "Run", "open_run", "read_run", "segment_path",
           "close_orphaned"]
