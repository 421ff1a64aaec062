"""The live scope: the flight recorder's rows, decimated, to a web page and (optionally) to
Foxglove, served by the daemon's I/O process (never the loop process).

The I/O process hands every batch of rows it drains to :meth:`Scope.tap` (a few hundred rows
every 20 ms). The tap reduces them to frames of min/max envelopes per channel over buckets of
:data:`BUCKET_S` and appends the frames to a bounded deque (:data:`BACKLOG_FRAMES`): a page
that reads slowly misses frames (its cursor falls behind the deque's oldest one), the drainer
and the run log never wait for it. The frames go to the view process
(:mod:`motorctl.app.daemon.views`), which serves the page and Foxglove: nothing a viewer does
runs in the I/O process.

Channels per axis: y, x_d, e [m], u [V], p [m/s], θ̂1..θ̂6, d̂0 (:data:`motorctl.loop.records
.AXIS_FIELDS` units); per cycle: turnaround and lateness [µs]. Events in a frame (for the
page's single-shot trigger): a fault's onset, an overrun, the start of a program period.
"""

from __future__ import annotations

import collections
import math

import numpy as np

from motorctl.config import parse_listen
from motorctl.loop.records import AXIS_FIELDS

#: per-axis channels shown (record field names)
AXIS_CHANNELS = ("y", "x_d", "e", "u", "p", "theta_hat1", "theta_hat2", "theta_hat3", "theta_hat4",
                 "theta_hat5", "theta_hat6", "d_hat0")
#: cycle channels: record field -> (scope name, scale to its unit)
CYCLE_CHANNELS = {"turnaround_ns": ("turnaround_us", 1e-3), "lateness_ns": ("lateness_us", 1e-3)}
BUCKET_S = 0.002         #: one envelope point per this much loop time [s] (500 per second)
BACKLOG_FRAMES = 256     #: frames kept for slow pages (about 5 s at the I/O process's 20 ms)
#: the most loop time one frame covers [s]: a larger batch (the drain catching up a backlog) is
#: shown by its newest TAP_MAX_S only, so that no frame outgrows the view link's message
#: (views.LINK_BUFFER); the run log keeps every row (a live view shows now, not the past)
TAP_MAX_S = 0.5


class Scope:
    """Decimated recorder rows for live viewers.

    Args:
        listen: "host:port" of the web page and its WebSocket (None: frames only, for
            :attr:`listeners`; :meth:`start` is not called).
        layout: the run's :class:`~motorctl.loop.records.RecordLayout`. names: axis names.
        period_s: loop period [s]. program_periods_s: {axis: program period [s] (0: none)}.
    Attributes:
        frames_made: frames made so far.
    """

    def __init__(self, listen: str | None, layout, names, period_s: float, program_periods_s: dict):
        self.host, self.port = parse_listen(listen) if listen else ("", 0)
        self.names = list(names)
        self.period_s = float(period_s)
        self.bucket = max(1, int(round(BUCKET_S / period_s)))
        self.max_rows = max(self.bucket, int(round(TAP_MAX_S / period_s)))
        #: rows of drained batches left out of the frames (a backlog beyond TAP_MAX_S)
        self.rows_skipped = 0
        self.cols, self.labels, self.units, self.scales = [], [], [], []
        for name in self.names:
            for f in AXIS_CHANNELS:
                self.cols.append(layout.index(f"{name}.{f}"))
                self.labels.append(f"{name}.{f}")
                self.units.append(AXIS_FIELDS[f])
                self.scales.append(1.0)
        for f, (label, scale) in CYCLE_CHANNELS.items():
            self.cols.append(layout.cycle(f))
            self.labels.append(label)
            self.units.append("us")
            self.scales.append(scale)
        self.cols_a = np.asarray(self.cols)
        self.scales_a = np.asarray(self.scales)
        self.t_col = layout.cycle("t")
        self.ov_col = layout.cycle("overruns")
        self.fault_cols = [layout.index(f"{n}.fault_bits") for n in self.names]
        self.prog = [float(program_periods_s.get(n, 0.0)) for n in self.names]
        self.frames: collections.deque = collections.deque(maxlen=BACKLOG_FRAMES)
        self.seq = 0
        self.status: dict = {}
        self.frames_made = 0
        self.last_t = math.nan       # loop time of the newest bucket [s]
        self._carry = None          # rows of an unfinished bucket
        self._last = None           # the last row seen (edges of events)
        self.error = ""
        #: callables given each new frame in the I/O thread (the Foxglove publisher); they
        #: must return quickly and never raise
        self.listeners: list = []

    # ------------------------------------------------------------------ I/O thread
    def tap(self, rows: np.ndarray, start: int) -> None:
        """Rows (N, C) of cycles start.. (from the drainer): envelope them into a frame.
        Never raises (a scope problem must not touch the recorder)."""
        try:
            self._tap(rows)
        except Exception as exc:       # noqa: BLE001 - the live view is best effort
            self.error = f"{type(exc).__name__}: {exc}"

    def _tap(self, rows: np.ndarray) -> None:
        if rows.shape[0] == 0:
            return
        if rows.shape[0] > self.max_rows:   # a backlog: its newest TAP_MAX_S only
            self.rows_skipped += rows.shape[0] - self.max_rows
            rows = rows[-self.max_rows:]
            self._carry = None
        events = self._events(rows)
        if self._carry is not None:
            rows = np.concatenate([self._carry, rows])
        n = (rows.shape[0] // self.bucket) * self.bucket
        self._carry = rows[n:].copy() if n < rows.shape[0] else None
        if n == 0:
            return
        sel = rows[:n][:, self.cols_a] * self.scales_a
        b = sel.reshape(n // self.bucket, self.bucket, -1)
        lo, hi = b.min(axis=1), b.max(axis=1)      # NaN (a signal the law has not) stays NaN
        t = rows[:n:self.bucket, self.t_col]
        self.last_t = float(t[-1])
        self.seq += 1
        frame = {"seq": self.seq, "t": _clean(t),
                 "min": {lab: _clean(lo[:, j]) for j, lab in enumerate(self.labels)},
                 "max": {lab: _clean(hi[:, j]) for j, lab in enumerate(self.labels)},
                 "events": events}
        self.frames.append(frame)
        self.frames_made += 1
        for listener in self.listeners:
            listener(frame)

    def _events(self, rows: np.ndarray) -> list:
        out = []
        prev = self._last if self._last is not None else rows[0]
        both = np.vstack([prev[None, :], rows])
        t = both[:, self.t_col]
        ov = np.flatnonzero(np.diff(both[:, self.ov_col]) > 0)
        if ov.size:
            out.append({"kind": "overrun", "t": float(t[ov[0] + 1])})
        for i, c in enumerate(self.fault_cols):
            onset = np.flatnonzero((both[:-1, c] == 0) & (both[1:, c] != 0))
            if onset.size:
                out.append({"kind": "fault", "axis": self.names[i], "t": float(t[onset[0] + 1])})
            if self.prog[i] > 0:
                k = np.floor(t / self.prog[i] + 1e-9)
                starts = np.flatnonzero(np.diff(k) > 0)
                if starts.size:
                    out.append({"kind": "period", "axis": self.names[i], "t": float(t[starts[0] + 1])})
        self._last = rows[-1].copy()
        return out

    def set_status(self, status: dict) -> None:
        """The axes' states and faults (a new dict each time: the server only reads it)."""
        self.status = status

    def meta(self) -> dict:
        return {"axes": self.names, "channels": self.labels, "units": self.units,
                "bucket_s": self.bucket * self.period_s, "program_periods_s": dict(zip(self.names, self.prog))}


def _clean(a) -> list:
    """Floats for JSON (NaN → None)."""
    return [None if not math.isfinite(x) else float(x) for x in np.asarray(a, dtype=float)]
