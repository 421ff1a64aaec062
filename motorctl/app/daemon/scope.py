"""The live scope: the flight recorder's rows, decimated, to a web page and (optionally) to
Foxglove, served by the daemon's I/O process (never the loop process).

The I/O process hands every batch of rows it drains to :meth:`Scope.tap` (a few hundred rows
every 20 ms). The tap reduces them to frames of min/max envelopes per channel over buckets of
:data:`BUCKET_S` and appends the frames to a bounded deque (:data:`BACKLOG_FRAMES`): a page
that reads slowly misses frames (its cursor falls behind the deque's oldest one), the drainer
and the run log never wait for it. The web server (aiohttp, on its own thread and event loop)
serves the page (uPlot, vendored under ``scope_static/``, no network at run time) and a
WebSocket ``/ws`` that sends each client the frames it has not seen, plus the axes' states
and latched faults with their reasons. Read-only: the server has no route that reaches the
loop.

Channels per axis: y, x_d, e [m], u [V], p [m/s], θ̂1..θ̂6, d̂0 (:data:`motorctl.loop.records
.AXIS_FIELDS` units); per cycle: turnaround and lateness [µs]. Events in a frame (for the
page's single-shot trigger): a fault's onset, an overrun, the start of a program period.
"""

from __future__ import annotations

import asyncio
import collections
import json
import math
import threading
from importlib import resources

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
SEND_EVERY_S = 0.05      #: a client is sent its new frames this often [s]


class Scope:
    """Decimated recorder rows for live viewers.

    Args:
        listen: "host:port" of the web page and its WebSocket (None: frames only, for
            :attr:`listeners`; :meth:`start` is not called).
        layout: the run's :class:`~motorctl.loop.records.RecordLayout`. names: axis names.
        period_s: loop period [s]. program_periods_s: {axis: program period [s] (0: none)}.
    Attributes:
        frames_made, frames_dropped_by_clients: counters (shown by ``status``-like views).
    """

    def __init__(self, listen: str | None, layout, names, period_s: float, program_periods_s: dict):
        self.host, self.port = parse_listen(listen) if listen else ("", 0)
        self.names = list(names)
        self.period_s = float(period_s)
        self.bucket = max(1, int(round(BUCKET_S / period_s)))
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
        self.frames_dropped_by_clients = 0
        self.last_t = math.nan       # loop time of the newest bucket [s]
        self._carry = None          # rows of an unfinished bucket
        self._last = None           # the last row seen (edges of events)
        self._loop = None
        self._thread = None
        self._runner = None
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

    # ------------------------------------------------------------------ the server's thread
    def start(self) -> None:
        """Bind and serve on a daemon thread. Raises OSError when the address cannot be bound
        (the caller reports it; the daemon goes on without the scope)."""
        ready = threading.Event()
        failure: list = []

        def main():
            loop = asyncio.new_event_loop()
            asyncio.set_event_loop(loop)
            self._loop = loop
            try:
                loop.run_until_complete(self._serve())
            except OSError as exc:
                failure.append(exc)
                ready.set()
                return
            ready.set()
            loop.run_forever()

        self._thread = threading.Thread(target=main, name="motorctl-scope", daemon=True)
        self._thread.start()
        ready.wait(10.0)
        if failure:
            raise failure[0]

    async def _serve(self) -> None:
        from aiohttp import web

        app = web.Application()
        app.router.add_get("/", self._index)
        app.router.add_get("/ws", self._ws)
        app.router.add_get("/meta", self._meta)
        app.router.add_get("/static/{name}", self._static)
        self._runner = web.AppRunner(app, access_log=None)
        await self._runner.setup()
        await web.TCPSite(self._runner, self.host, self.port).start()

    def stop(self) -> None:
        """Stop serving (bounded)."""
        loop = self._loop
        if loop is None or not loop.is_running():
            return

        async def down():
            if self._runner is not None:
                await self._runner.cleanup()
        try:
            asyncio.run_coroutine_threadsafe(down(), loop).result(2.0)
        except Exception:              # noqa: BLE001 - shutting down anyway
            pass
        loop.call_soon_threadsafe(loop.stop)
        self._thread.join(2.0)

    def meta(self) -> dict:
        return {"axes": self.names, "channels": self.labels, "units": self.units,
                "bucket_s": self.bucket * self.period_s, "program_periods_s": dict(zip(self.names, self.prog))}

    async def _index(self, request):
        return await self._static_file("index.html", "text/html")

    async def _static(self, request):
        name = request.match_info["name"]
        kinds = {".js": "application/javascript", ".css": "text/css", ".txt": "text/plain"}
        kind = next((v for k, v in kinds.items() if name.endswith(k)), None)
        if kind is None or "/" in name or name.startswith("."):
            from aiohttp import web
            raise web.HTTPNotFound()
        return await self._static_file(name, kind)

    async def _static_file(self, name: str, kind: str):
        from aiohttp import web
        try:
            body = resources.files("motorctl.app.daemon").joinpath("scope_static", name).read_bytes()
        except (FileNotFoundError, IsADirectoryError):
            raise web.HTTPNotFound() from None
        return web.Response(body=body, content_type=kind, charset="utf-8" if kind != "application/javascript" else None)

    async def _meta(self, request):
        from aiohttp import web
        return web.json_response(self.meta())

    async def _ws(self, request):
        from aiohttp import web
        ws = web.WebSocketResponse(heartbeat=10.0)
        await ws.prepare(request)
        await ws.send_str(json.dumps({"meta": self.meta()}))
        cursor = self.seq
        while not ws.closed:
            frames = [f for f in list(self.frames) if f["seq"] > cursor]
            if frames:
                if frames[0]["seq"] > cursor + 1 and cursor:
                    self.frames_dropped_by_clients += frames[0]["seq"] - cursor - 1
                cursor = frames[-1]["seq"]
            msg = {"frames": frames, "status": self.status, "scope_error": self.error}
            try:
                await ws.send_str(json.dumps(msg))
            except (ConnectionResetError, RuntimeError):
                break
            await asyncio.sleep(SEND_EVERY_S)
        return ws


def _clean(a) -> list:
    """Floats for JSON (NaN → None)."""
    return [None if not math.isfinite(x) else float(x) for x in np.asarray(a, dtype=float)]
