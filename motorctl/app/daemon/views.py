"""The view process: the scope's web page and the Foxglove server, away from the drain.

The daemon's I/O process drains the ring to the run log; a viewer must never slow that down.
So the live views run in a process of their own, forked from the I/O process at its start,
ending with its parent (``PR_SET_PDEATHSIG``), at the I/O process's niceness (0,
:data:`VIEW_NICE`) with bounded work per wake (:data:`LINK_MESSAGES_PER_WAKE`): at +10, beside
CPU-bound processes at normal priority, its CPU share was a tenth of theirs and it took 23 s to
listen beside 4 of them (its start-up, aiohttp's import and set-up, is 0.6 s of CPU) and up to
75 s beside 12-15 (docs/benchmarks.md, 2026-11-27 late evening).
The I/O process makes the scope's frames (:class:`motorctl.app.daemon.scope.Scope`, cheap
numpy envelopes) and sends each one over a non-blocking ``SOCK_SEQPACKET`` socket pair
(:class:`ViewLink`): when the view process does not keep up, the frame is dropped and counted,
the send never waits. In the view process every page has its own bounded queue of
:data:`PAGE_QUEUE_FRAMES` frames (a slow page loses its oldest frames, counted and shown on the
page); each frame is encoded to JSON once, whatever the number of pages.

Beside the scope, the same server serves the operator page (``/operator``,
:mod:`motorctl.app.daemon.operator_page`) when :func:`start_views` is given the control socket's
path: it commands the daemon as a client of that socket, as the command line does, never through
the link (which only carries frames and states to this process).

Start-up is reported back over the same socket (``started``: what is served, what failed and
why); the I/O process prints one line per view and never waits for it.
"""

from __future__ import annotations

import asyncio
import collections
import importlib.util
import ipaddress
import json
import os
import pickle
import socket
import sys
import time
from importlib import resources

from motorctl.app.daemon.forked import HelperLink, fork_helper, helper_started

#: frames queued per page before its oldest are dropped (about 2.5 s at the I/O process's 20 ms)
PAGE_QUEUE_FRAMES = 128
#: a page is sent its queued frames this often [s]
SEND_EVERY_S = 0.05
#: the view process's niceness: the I/O process's own (0). Its work is bounded (a wake handles at
#: most LINK_MESSAGES_PER_WAKE messages of the link, a request answers from memory), so it cannot
#: take more than its share from the drain; at +10 a loaded host starved it for minutes
VIEW_NICE = 0
#: messages of the link handled per wake of the event loop before the requests get their turn
#: (the rest waits for the next wake; the link drops what does not fit, counted)
LINK_MESSAGES_PER_WAKE = 16
#: the socket pair's send buffer [bytes] (the kernel caps it at net.core.wmem_max)
LINK_BUFFER = 1 << 20
#: the largest message sent over the link [bytes]: the view process reads LINK_BUFFER at a time,
#: and a SOCK_SEQPACKET message longer than the read would be cut; a larger one is dropped
#: (counted) instead (the scope's frames stay far below it: scope.TAP_MAX_S)
LINK_MESSAGE_MAX = LINK_BUFFER // 2


def missing_extra(module: str, extra: str, what: str) -> str:
    """The warning line for a view whose library is not installed ("" when it is)."""
    if importlib.util.find_spec(module) is not None:
        return ""
    return f"motorctl: warning: {what} disabled: install motorctl[{extra}] ({module} is missing)"


def exposure_warning(key: str, host: str) -> str:
    """The warning line for a view that listens beyond loopback ("" on loopback)."""
    if host == "localhost":
        return ""
    try:
        if ipaddress.ip_address(host).is_loopback:
            return ""
    except ValueError:
        pass
    return (f"motorctl: warning: {key} {host}: reachable from the network, and the page has no "
            f"authentication (anyone who reaches it sees the machine live)")


class ViewLink(HelperLink):
    """The I/O process's end of the view process: a listener of the scope (:meth:`on_frame`).

    Attributes:
        sent, dropped: frames handed over / dropped because the view process was behind.
        pid: the view process. alive: False once it has ended (nothing is sent any more).
    """

    def _send(self, obj) -> bool:
        if not self.alive:
            return False
        data = pickle.dumps(obj, protocol=pickle.HIGHEST_PROTOCOL)
        if len(data) > LINK_MESSAGE_MAX:   # never a truncated message: dropped, counted
            return False
        try:
            self.sock.send(data)
            return True
        except (BlockingIOError, InterruptedError):
            return False
        except OSError:
            self.alive = False
            return False

    def on_frame(self, frame: dict) -> None:
        """The scope's listener (I/O thread): never blocks, never raises."""
        if self._send(("frame", frame)):
            self.sent += 1
        else:
            self.dropped += 1

    def set_status(self, status: dict, t_s: float) -> None:
        """The axes' states (``t_s``: the loop time of the newest frame [s]) and the drops."""
        self._send(("status", {"status": status, "t": t_s, "link_dropped": self.dropped}))

    def receive(self) -> list:
        """The view process's reports waiting on the socket (non-blocking); EOF marks it gone.
        Read even once a frame's send has found the view process gone (``alive`` False): what it
        reported before it ended (a view it could not serve) is still waiting here."""
        out = []
        reset = False
        while True:
            try:
                data = self.sock.recv(1 << 16)
            except (BlockingIOError, InterruptedError):
                break
            except ConnectionResetError:
                # a view process that ended with frames of ours unread: the kernel reports the
                # reset once, on the first recv, before the reports still queued (AF_UNIX
                # SOCK_SEQPACKET: the socket's error is taken before its queue)
                self.alive = False
                if reset:
                    break
                reset = True
                continue
            except OSError:
                data = b""
            if not data:
                self.alive = False
                break
            out.append(pickle.loads(data))
        return out


def start_views(scope, serve_scope: bool, foxglove_listen: str | None,
                operator: dict | None = None) -> ViewLink | None:
    """Fork the view process (call with no thread running). Returns the I/O process's link (None
    with one warning line when the fork fails).
    ``operator``: {"socket": the control socket's path, "users_file": daemon.users_file or
    None}: the operator page (:mod:`motorctl.app.daemon.operator_page`) beside the scope's."""
    forked = fork_helper("view", lambda sock, parent: view_main(sock, scope, serve_scope, foxglove_listen, parent,
                                                                operator), LINK_BUFFER)
    return None if forked is None else ViewLink(*forked)


def view_main(sock: socket.socket, scope, serve_scope: bool, foxglove_listen: str | None,
              parent_pid: int, operator: dict | None = None) -> int:
    """The view process: serve what is configured until the link closes or the parent dies."""
    helper_started(parent_pid, VIEW_NICE)
    loop = asyncio.new_event_loop()
    asyncio.set_event_loop(loop)
    views = Views(scope, operator)
    report = {"scope": None, "foxglove": None}
    if serve_scope:
        try:
            loop.run_until_complete(views.serve_page())
            report["scope"] = ""
        except BaseException as exc:            # noqa: BLE001 - any failure: one line, no view
            report["scope"] = _why(exc)
    if foxglove_listen:
        try:
            from motorctl.app.daemon.foxglove_live import FoxglovePublisher
            views.foxglove = FoxglovePublisher(foxglove_listen, scope)
            views.foxglove.start()
            report["foxglove"] = ""
        except BaseException as exc:            # noqa: BLE001
            views.foxglove = None
            report["foxglove"] = _why(exc)
    sock.setblocking(True)
    sock.send(pickle.dumps(("started", report)))
    if report["scope"] != "" and report["foxglove"] != "":
        return 0
    sock.setblocking(False)
    loop.add_reader(sock.fileno(), views.on_readable, sock, loop)
    try:
        loop.run_forever()
    finally:
        views.close(loop)
    return 0


def _why(exc: BaseException) -> str:
    return f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__


class _Page:
    __slots__ = ("queue", "dropped")

    def __init__(self):
        self.queue: collections.deque = collections.deque(maxlen=PAGE_QUEUE_FRAMES)
        self.dropped = 0


class Views:
    """The view process's state: the pages' queues, the last status, the Foxglove publisher."""

    def __init__(self, scope, operator: dict | None = None):
        self.scope = scope
        self.operator = operator
        self.meta = json.dumps({"meta": scope.meta()})
        self.pages: set[_Page] = set()
        self.status_json = "{}"
        self.link_dropped = 0
        self.foxglove = None
        self.runner = None
        self.static: dict[str, bytes] = {}

    # ------------------------------------------------------------------ from the I/O process
    def on_readable(self, sock: socket.socket, loop) -> None:
        """At most :data:`LINK_MESSAGES_PER_WAKE` messages, then the event loop's other work:
        a link that always has data (a view process behind) never starves the requests."""
        for _ in range(LINK_MESSAGES_PER_WAKE):
            try:
                data = sock.recv(LINK_BUFFER)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                data = b""
            if not data:                       # the I/O process closed the link or ended
                loop.stop()
                return
            kind, obj = pickle.loads(data)
            if kind == "frame":
                self.on_frame(obj)
            elif kind == "status":
                self.link_dropped = int(obj["link_dropped"])
                self.status_json = json.dumps(obj["status"])
                if self.foxglove is not None:
                    self.foxglove.publish_status(obj["status"], obj["t"])

    def on_frame(self, frame: dict) -> None:
        if self.pages:
            text = json.dumps(frame)
            for page in self.pages:
                if len(page.queue) == PAGE_QUEUE_FRAMES:
                    page.dropped += 1
                page.queue.append(text)
        if self.foxglove is not None:
            self.foxglove.on_frame(frame)

    # ------------------------------------------------------------------ the web page
    async def serve_page(self) -> None:
        from aiohttp import web

        app = web.Application()
        app.router.add_get("/", self._index)
        app.router.add_get("/ws", self._ws)
        app.router.add_get("/meta", self._meta)
        app.router.add_get("/static/{name}", self._static)
        if self.operator is not None:     # the operator page: a client of the control socket
            from motorctl.app.daemon.operator_page import OperatorPage
            OperatorPage(self.operator["socket"], self.operator.get("users_file"), self.scope.names,
                         self._static_bytes, lockout_s=self.operator.get("lockout_s")).add_routes(app)
        self.runner = web.AppRunner(app, access_log=None)
        await self.runner.setup()
        await web.TCPSite(self.runner, self.scope.host, self.scope.port).start()

    def close(self, loop) -> None:
        try:
            if self.runner is not None:
                loop.run_until_complete(asyncio.wait_for(self.runner.cleanup(), 2.0))
        except BaseException:                   # noqa: BLE001 - ending anyway
            pass
        if self.foxglove is not None:
            self.foxglove.stop()

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

    def _static_bytes(self, name: str) -> bytes:
        """A file of ``scope_static`` (read once). Raises aiohttp's HTTPNotFound."""
        body = self.static.get(name)
        if body is None:
            try:
                body = resources.files("motorctl.app.daemon").joinpath("scope_static", name).read_bytes()
            except (FileNotFoundError, IsADirectoryError):
                from aiohttp import web
                raise web.HTTPNotFound() from None
            self.static[name] = body          # a handful of vendored files: read once
        return body

    async def _static_file(self, name: str, kind: str):
        from aiohttp import web
        body = self._static_bytes(name)
        return web.Response(body=body, content_type=kind,
                            charset="utf-8" if kind != "application/javascript" else None)

    async def _meta(self, request):
        from aiohttp import web
        return web.Response(text=self.meta[len('{"meta": '):-1], content_type="application/json")

    async def _ws(self, request):
        """Each page: its frames since it connected (bounded, oldest dropped first), the axes'
        states and the frames it missed, every :data:`SEND_EVERY_S`.

        The handler reads what the page sends while a task of its own sends to it: aiohttp
        answers a page's close frame (RFC 6455 §5.5.1) and its pings only inside a read, so a
        handler that only sends leaves a closing page waiting for its own timeout (10 s in
        aiohttp's client) while frames are still queued for it."""
        from aiohttp import web
        ws = web.WebSocketResponse(heartbeat=10.0)
        await ws.prepare(request)
        page = _Page()
        self.pages.add(page)
        sender = asyncio.get_running_loop().create_task(self._send_to(ws, page))
        try:
            async for _ in ws:                      # a page sends nothing of use: read to answer
                pass
        finally:
            self.pages.discard(page)
            sender.cancel()
        return ws

    async def _send_to(self, ws, page: _Page) -> None:
        """The sending side of :meth:`_ws`: the metadata once, then the page's queued frames."""
        try:
            await ws.send_str(self.meta)
            while not ws.closed:
                frames = list(page.queue)
                page.queue.clear()
                msg = (f'{{"frames": [{", ".join(frames)}], "status": {self.status_json}, '
                       f'"dropped": {page.dropped + self.link_dropped}, "scope_error": ""}}')
                await ws.send_str(msg)
                await asyncio.sleep(SEND_EVERY_S)
        except (ConnectionError, RuntimeError):     # the page went away mid-send
            pass
