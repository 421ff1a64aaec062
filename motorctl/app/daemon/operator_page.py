"""The operator page: the machine's DRO and its commands in a browser, on the scope's web server
(docs/operator-page.md).

Served by the view process (:mod:`motorctl.app.daemon.views`, nice 0, away from the loop, the
ring and the recorder), on the same aiohttp application as the scope. It commands the daemon
the way the command line does: as a client of the control socket (one JSON line each way,
:mod:`motorctl.app.daemon.protocol`), so the daemon checks every command as it checks the CLI's,
and nothing of this page runs in the loop or I/O process. Every daemon request has a timeout
(:data:`CALL_TIMEOUT_S`) and at most :data:`MAX_CALLS` are in flight at once; the axes' status
is fetched at most every :data:`STATUS_MAX_AGE_S` whatever the number of pages.

Routes (``GET`` read only, everything else ``POST`` with a session):

* ``GET /operator``: the page (``scope_static/operator.html`` and ``operator.js``, no build step)
* ``GET /operator/session``: who is logged in, whether they may command, the CSRF token
* ``GET /operator/status``: the DRO (each axis's position [m], state, phase, fault) and motion
* ``POST /login`` (name, password; JSON or a form), ``POST /logout``
* ``POST /operator/cmd/{name}``: enable, disable, fault-reset, home, jog, jog-alive, mdi, hold,
  resume, abort, override (a JSON body)
* ``POST /operator/program?name=part.ngc``: the program's bytes as the body, streamed to the
  daemon with the protocol's ``upload`` (the size announced first; the daemon refuses a program
  beyond ``daemon.max_program_bytes`` before a byte of it is taken), then ``gcode`` naming the
  upload: the daemon checks the whole program before anything moves and its one-line refusal
  comes back as the answer's ``error``

Logins: the users file (``daemon.users_file``, :mod:`motorctl.app.users`, scrypt hashes; read
again when its modification time changes), checked through :class:`motorctl.app.login.LoginGuard`
as the OPC UA server checks them: the same time for an unknown name as for a known one, a
back-off per name and per client address, a name locked after its 6th failed login within a
minute (``daemon.login_lockout_s``; ``motorctl users unlock``), every refusal in the journal.
A login gives a random session token (256 bits) in an
HttpOnly, SameSite=Strict cookie; a session idle :data:`SESSION_IDLE_S` ends. Without a session,
or with the ``viewer`` role only, every command answers 403. Every ``POST`` but ``/login`` needs
the session's CSRF token in the ``X-CSRF-Token`` header, and a request whose ``Origin`` (or
``Sec-Fetch-Site``) says it came from another site is refused (403) before anything else.
Passwords are never logged, stored or sent on: one line per login (the name, the address and the
outcome) goes to the daemon's stderr.

A continuous jog (``jog`` with ``velocity``) is held by the page: it sends ``jog-alive`` while
the button is held down, and an axis not kept alive for :data:`JOG_DEADMAN_S` is stopped by this
process (a page closed, a network gone); a jog runs at most to the axis's soft limit.
"""

from __future__ import annotations

import asyncio
import hmac
import json
import os
import secrets
import sys
import time
from dataclasses import dataclass, field

#: the session cookie's name
SESSION_COOKIE = "motorctl_session"
#: a session unused this long ends [s]
SESSION_IDLE_S = 8 * 3600.0
#: sessions kept at once (the least recently used goes first)
MAX_SESSIONS = 64
#: the daemon's status is fetched at most this often, for all pages together [s]
STATUS_MAX_AGE_S = 0.1
#: a daemon request (but a program's) not answered within this is an error [s]
CALL_TIMEOUT_S = 5.0
#: daemon requests from this page in flight at once (more wait for a turn)
MAX_CALLS = 8
#: a program's answer may take this, plus PROGRAM_S_PER_10MB per 10 MB (the daemon checks the
#: whole program before it answers; motorctl.client.send_program's bound) [s]
PROGRAM_TIMEOUT_S, PROGRAM_S_PER_10MB = 30.0, 60.0
#: logins waiting for their password check at once; more are answered 429 at once
MAX_LOGINS_WAITING = 8
#: a wrong name or password is answered after this [s]
LOGIN_FAIL_DELAY_S = 0.5
#: a continuous jog not kept alive (jog-alive) this long is stopped [s]
JOG_DEADMAN_S = 0.6
#: a refused program's connection is closed this long after its answer, its body unread [s]
REFUSED_BODY_CLOSE_S = 2.0
#: the largest login or command body [bytes]
MAX_SMALL_BODY = 8192
#: the reply stream's line limit for the daemon's answers (a status is a few kB) [bytes]
ANSWER_LIMIT = 1 << 20

#: the page's commands (each needs an operator's session)
COMMANDS = ("enable", "disable", "fault-reset", "home", "jog", "jog-alive", "mdi", "hold", "resume",
            "abort", "override")


class BadRequest(ValueError):
    """A command's body is wrong (400, one line)."""


@dataclass
class Session:
    """One login: the user's name and roles, the CSRF token, when it was last used [monotonic s]."""

    name: str
    roles: frozenset
    csrf: str = field(default_factory=lambda: secrets.token_urlsafe(32))
    seen: float = field(default_factory=time.monotonic)

    @property
    def operator(self) -> bool:
        return "operator" in self.roles


def _log(line: str) -> None:
    try:
        sys.stderr.write(f"motorctl: operator page: {line}\n")
        sys.stderr.flush()
    except (OSError, ValueError):
        pass


class OperatorPage:
    """The operator page's routes and state (view process).

    Args:
        socket_path: the daemon's control socket. users_file: ``daemon.users_file`` (None: no
            logins, the page read only). axes: the axis names.
        read_static: name -> bytes of a file of ``scope_static`` (the views' cache).
    """

    def __init__(self, socket_path: str, users_file: str | None, axes, read_static, lockout_s: float | None = None):
        from motorctl.app.login import LOCKOUT_S, LoginGuard, journal_to_stderr, state_path
        journal_to_stderr()
        self.guard = LoginGuard(state_path(socket_path), LOCKOUT_S if lockout_s is None else lockout_s,
                                "operator page")
        self.socket_path = socket_path
        self.users_file = users_file
        self.axes = list(axes)
        self.read_static = read_static
        self.sessions: dict[str, Session] = {}
        self._users = None
        self._users_mtime = None
        self._users_error = ""
        self._calls = None                    # asyncio.Semaphore, made in the loop
        self._login_check = None
        self._logins_waiting = 0
        self._status: dict | None = None
        self._status_t = -1e9
        self._status_gen = self._gen = 0
        self._status_lock = None
        self._jogs: dict[str, float] = {}     # axis -> keep-alive deadline [monotonic s]
        self._deadman = None
        if users_file:
            self._load_users()
            if self._users_error:
                _log(f"warning: logins off: {self._users_error}")

    # ------------------------------------------------------------------ set-up
    def add_routes(self, app) -> None:
        """The page's routes on the scope's application."""
        app.router.add_get("/operator", self._page)
        app.router.add_get("/operator/session", self._session_info)
        app.router.add_get("/operator/status", self._status_route)
        app.router.add_post("/login", self._login)
        app.router.add_post("/logout", self._logout)
        app.router.add_post("/operator/cmd/{name}", self._command)
        app.router.add_post("/operator/program", self._program)
        app.on_startup.append(self._on_startup)
        app.on_cleanup.append(self._on_cleanup)

    async def _on_startup(self, app) -> None:
        self._calls = asyncio.Semaphore(MAX_CALLS)
        self._login_check = asyncio.Semaphore(1)
        self._status_lock = asyncio.Lock()
        self._deadman = asyncio.get_running_loop().create_task(self._deadman_loop())

    async def _on_cleanup(self, app) -> None:
        if self._deadman is not None:
            self._deadman.cancel()

    def _load_users(self):
        """The users file, read again when its modification time changed (None: logins off)."""
        from motorctl.app.users import UsersError, load_users
        if not self.users_file:
            return None
        try:
            mtime = os.stat(self.users_file).st_mtime_ns
        except OSError as exc:
            self._users, self._users_error = None, f"{self.users_file}: {exc.strerror}"
            return None
        if mtime != self._users_mtime:
            try:
                self._users, self._users_error = load_users(self.users_file), ""
            except UsersError as exc:
                self._users, self._users_error = None, str(exc)
            self._users_mtime = mtime
        return self._users

    # ------------------------------------------------------------------ the daemon
    async def call(self, req: dict, timeout_s: float = CALL_TIMEOUT_S) -> dict:
        """One request to the daemon; its answer, or ``{"ok": False, "error": ..., "unreachable":
        True}`` (no daemon, no answer within ``timeout_s``). Never raises."""
        async with self._calls:
            try:
                return await asyncio.wait_for(self._call(req), timeout_s)
            except asyncio.TimeoutError:
                return _unreachable(f"the daemon did not answer within {timeout_s:g} s")
            except (OSError, ValueError, asyncio.IncompleteReadError) as exc:
                return _unreachable(f"cannot reach the daemon at {self.socket_path}: "
                                    f"{getattr(exc, 'strerror', None) or exc}")

    async def _call(self, req: dict) -> dict:
        reader, writer = await asyncio.open_unix_connection(self.socket_path, limit=ANSWER_LIMIT)
        try:
            writer.write((json.dumps(req) + "\n").encode())
            await writer.drain()
            return _answer(await reader.readline())
        finally:
            writer.close()

    async def status(self) -> dict:
        """The DRO's status (:func:`dro`), fetched at most every :data:`STATUS_MAX_AGE_S`."""
        async with self._status_lock:
            if (self._status is None or self._status_gen != self._gen
                    or time.monotonic() - self._status_t >= STATUS_MAX_AGE_S):
                gen, t0 = self._gen, time.monotonic()
                ans = await self.call({"cmd": "status"})
                self._status = dro(ans["status"]) if ans.get("ok") else {
                    "axes": {}, "motion": {}, "error": ans.get("error", "no status")}
                self._status_t, self._status_gen = t0, gen
            return self._status

    def _stale(self) -> None:
        """A command was answered: a status fetched before it (or while it ran) is not shown."""
        self._gen += 1

    async def _deadman_loop(self) -> None:
        """Stop a continuous jog that its page stopped keeping alive (every JOG_DEADMAN_S / 4)."""
        while True:
            await asyncio.sleep(JOG_DEADMAN_S / 4)
            now = time.monotonic()
            for axis, deadline in list(self._jogs.items()):
                if now > deadline:
                    self._jogs.pop(axis, None)
                    await self.call({"cmd": "jog", "axis": axis, "stop": True})

    # ------------------------------------------------------------------ sessions
    def session(self, request) -> Session | None:
        """The request's live session (None: no cookie, unknown or expired token)."""
        tok = request.cookies.get(SESSION_COOKIE)
        s = self.sessions.get(tok) if tok else None
        if s is None:
            return None
        now = time.monotonic()
        if now - s.seen > SESSION_IDLE_S:
            self.sessions.pop(tok, None)
            return None
        s.seen = now
        return s

    def _new_session(self, name: str, roles: frozenset) -> str:
        while len(self.sessions) >= MAX_SESSIONS:
            oldest = min(self.sessions, key=lambda t: self.sessions[t].seen)
            self.sessions.pop(oldest)
        tok = secrets.token_urlsafe(32)
        self.sessions[tok] = Session(name, roles)
        return tok

    @staticmethod
    def cross_site(request) -> bool:
        """The browser says the request came from another origin (``Origin`` naming another
        host:port than the request's ``Host``, or ``Sec-Fetch-Site`` other than same-origin /
        none). The scheme is not compared: behind a TLS proxy the page is https, this server http."""
        from urllib.parse import urlsplit
        origin = request.headers.get("Origin")
        if origin is not None and (origin == "null" or urlsplit(origin).netloc != request.host):
            return True
        site = request.headers.get("Sec-Fetch-Site")
        return site is not None and site not in ("same-origin", "none")

    def _allowed(self, request) -> Session | None:
        """The operator session of a command request (None: 403): same origin, a session with
        the operator role, its CSRF token in ``X-CSRF-Token``."""
        if self.cross_site(request):
            return None
        s = self.session(request)
        if s is None or not s.operator:
            return None
        if not hmac.compare_digest(request.headers.get("X-CSRF-Token", ""), s.csrf):
            return None
        return s

    # ------------------------------------------------------------------ routes
    async def _page(self, request):
        from aiohttp import web
        body = self.read_static("operator.html")
        return web.Response(body=body, content_type="text/html", charset="utf-8",
                            headers=_PAGE_HEADERS)

    async def _session_info(self, request):
        s = self.session(request)
        users = self._load_users()
        return _json({"user": s.name if s else None, "roles": sorted(s.roles) if s else [],
                      "operator": bool(s and s.operator), "csrf": s.csrf if s else None,
                      "logins": users is not None,
                      "logins_off": "" if users is not None else (
                          self._users_error or "no daemon.users_file in the config"),
                      "axes": self.axes, "jog_deadman_s": JOG_DEADMAN_S})

    async def _status_route(self, request):
        return _json(await self.status())

    async def _login(self, request):
        if self.cross_site(request):
            return _json({"ok": False, "error": "forbidden: the request came from another site"}, 403)
        try:
            form = await _small_body(request)
        except BadRequest as exc:
            return _json({"ok": False, "error": str(exc)}, 400)
        name, password = form.get("name"), form.get("password")
        if not isinstance(name, str) or not isinstance(password, str) or not name:
            return _json({"ok": False, "error": "login needs 'name' and 'password'"}, 400)
        users = self._load_users()
        if users is None:
            return _json({"ok": False, "error": "logins are off: " + (
                self._users_error or "no daemon.users_file in the config")}, 403)
        if self._logins_waiting >= MAX_LOGINS_WAITING:
            return _json({"ok": False, "error": "too many logins at once; retry"}, 429)
        self._logins_waiting += 1
        try:
            async with self._login_check:       # one scrypt check (16 MiB, tens of ms) at a time
                v = await asyncio.get_running_loop().run_in_executor(
                    None, self.guard.attempt, users, name, password, request.remote or "?")
        except OSError as exc:
            _log(f"login refused for {name[:64]!r}: the login state {self.guard.path}: {exc.strerror or exc}")
            return _json({"ok": False, "error": "logins are unavailable (the daemon's login state); retry"}, 503)
        finally:
            self._logins_waiting -= 1
        del password
        if v.why == "wrong":
            await asyncio.sleep(LOGIN_FAIL_DELAY_S)
            return _json({"ok": False, "error": "wrong name or password"}, 403)
        if not v.ok:
            retry = max(1, round(v.retry_s))
            return _json({"ok": False, "error": f"too many failed logins for this name or address; retry in "
                                                f"{retry} s"}, 429, {"Retry-After": str(retry)})
        roles = v.roles
        tok = self._new_session(name, roles)
        s = self.sessions[tok]
        resp = _json({"ok": True, "user": name, "roles": sorted(roles), "operator": s.operator,
                      "csrf": s.csrf})
        resp.set_cookie(SESSION_COOKIE, tok, httponly=True, samesite="Strict", path="/",
                        secure=request.secure)
        return resp

    async def _logout(self, request):
        if self.cross_site(request):
            return _json({"ok": False, "error": "forbidden"}, 403)
        tok = request.cookies.get(SESSION_COOKIE)
        s = self.sessions.get(tok) if tok else None
        if s is not None and hmac.compare_digest(request.headers.get("X-CSRF-Token", ""), s.csrf):
            self.sessions.pop(tok, None)
            _log(f"{s.name!r} logged out")
        resp = _json({"ok": True})
        resp.del_cookie(SESSION_COOKIE, path="/")
        return resp

    async def _command(self, request):
        s = self._allowed(request)
        if s is None:
            return _forbidden()
        name = request.match_info["name"]
        if name not in COMMANDS:
            return _json({"ok": False, "error": f"unknown command {name!r}; allowed: {', '.join(COMMANDS)}"}, 404)
        try:
            body = await _small_body(request)
            if name == "jog-alive":
                axis = self._axis(body)
                if axis in self._jogs:
                    self._jogs[axis] = time.monotonic() + JOG_DEADMAN_S
                return _json({"ok": True, "alive": axis in self._jogs})
            req = self.request_of(name, body)
        except BadRequest as exc:
            return _json({"ok": False, "error": str(exc), "usage": True}, 400)
        if name == "jog" and "velocity" in req:
            self._jogs[req["axis"]] = time.monotonic() + JOG_DEADMAN_S
        elif name == "jog" or name == "abort":
            for a in ([req["axis"]] if name == "jog" else list(self._jogs)):
                self._jogs.pop(a, None)
        ans = await self.call(req, PROGRAM_TIMEOUT_S if name == "mdi" else CALL_TIMEOUT_S)
        if name == "jog" and "velocity" in req and not ans.get("ok"):
            self._jogs.pop(req["axis"], None)
        self._stale()
        return _answer_response(ans)

    def _axis(self, body: dict) -> str:
        a = body.get("axis")
        if a not in self.axes:
            raise BadRequest(f"unknown axis {a!r}; axes: {', '.join(self.axes)}")
        return a

    def request_of(self, name: str, body: dict) -> dict:
        """The daemon request of a page command (:mod:`motorctl.app.daemon.protocol`).
        Raises BadRequest (one line)."""
        if name in ("hold", "resume", "abort"):
            return {"cmd": name}
        if name == "override":
            v = body.get("value")
            if isinstance(v, bool) or not isinstance(v, (int, float)):
                raise BadRequest("override needs 'value': a number 0.0 .. 1.5")
            return {"cmd": "override", "value": float(v)}
        if name == "mdi":
            line = body.get("line")
            if not isinstance(line, str) or not line.strip() or "\n" in line.strip() or len(line) > 1000:
                raise BadRequest("mdi needs 'line': one line of G-code (at most 1000 characters)")
            return {"cmd": "gcode", "text": line.strip() + "\n", "filename": "MDI"}
        axis = self._axis(body)
        if name == "enable":
            return {"cmd": "start", "axis": axis, "mode": "command"}
        if name == "disable":
            return {"cmd": "stop", "axis": axis}
        if name in ("fault-reset", "home"):
            return {"cmd": name, "axis": axis}
        kinds = [k for k in ("by", "velocity", "stop") if k in body]
        if len(kinds) != 1:
            raise BadRequest("jog takes one of 'by' (m), 'velocity' (m/s) or 'stop'")
        k = kinds[0]
        if k == "stop":
            return {"cmd": "jog", "axis": axis, "stop": True}
        v = body[k]
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise BadRequest(f"jog: '{k}' must be a number")
        return {"cmd": "jog", "axis": axis, k: float(v)}

    async def _program(self, request):
        """The request's body streamed to the daemon as an ``upload``, then ``gcode`` naming it.
        A program the daemon refuses before taking it (beyond ``daemon.max_program_bytes``: 413;
        too many uploads: 409) or a body without a Content-Length (411) is answered at once and
        its body not read (:func:`_refuse_unread`)."""
        s = self._allowed(request)
        if s is None:
            return _forbidden()
        n = request.content_length
        if n is None:
            return await _refuse_unread(request, {"ok": False, "error": "program: the request needs a Content-Length",
                                                  "usage": True}, 411)
        filename = request.query.get("name", "program.ngc")[:200] or "program.ngc"
        send_s = PROGRAM_TIMEOUT_S + PROGRAM_S_PER_10MB * n / 10e6
        sent = [0]
        async with self._calls:
            try:
                ans = await asyncio.wait_for(self._upload(request, n, sent), send_s)
            except asyncio.TimeoutError:
                ans = _unreachable(f"program: not sent within {send_s:.0f} s")
            except (OSError, ValueError, asyncio.IncompleteReadError) as exc:
                ans = _unreachable(f"program: cannot send it to the daemon: {getattr(exc, 'strerror', None) or exc}")
        if not ans.get("ok"):
            if sent[0] == 0 and n > 0:
                too_large = "max_program_bytes" in str(ans.get("error", ""))
                return await _refuse_unread(request, ans, 413 if too_large else None)
            return _answer_response(ans)
        ans = await self.call({"cmd": "gcode", "upload": ans["upload"], "filename": filename}, send_s)
        self._stale()
        return _answer_response(ans)

    async def _upload(self, request, n: int, sent: list) -> dict:
        """``upload`` of the body's ``n`` bytes; ``sent[0]``: the bytes read from the request."""
        reader, writer = await asyncio.open_unix_connection(self.socket_path, limit=ANSWER_LIMIT)
        try:
            writer.write((json.dumps({"cmd": "upload", "bytes": n}) + "\n").encode())
            await writer.drain()
            ans = _answer(await reader.readline())
            if not ans.get("ok"):
                return ans
            while sent[0] < n:
                chunk = await request.content.read(min(1 << 16, n - sent[0]))
                if not chunk:
                    return {"ok": False, "error": f"program: the page sent {sent[0]} of {n} bytes", "usage": True}
                writer.write(chunk)
                await writer.drain()          # the daemon's pace: memory stays bounded
                sent[0] += len(chunk)
            return _answer(await reader.readline())
        finally:
            writer.close()


def dro(st: dict) -> dict:
    """What the page shows of a daemon status: per axis its position and setpoint [m], state,
    phase, fault line, in-position; the motion's line, share done, time left [s], override,
    hold, why it stopped, homed."""
    axes = {}
    for a, s in st.get("axes", {}).items():
        axes[a] = {k: _finite(s.get(k)) if k.endswith("_m") else s.get(k)
                   for k in ("y_m", "x_d_m", "following_error_m", "state", "phase", "fault",
                             "in_position", "controller")}
    mo = st.get("motion", {})
    motion = {k: mo.get(k) for k in ("idle", "line", "done", "time_left_s", "override", "hold",
                                     "aborting", "planning", "queue_depth", "stopped_because",
                                     "homed", "homing", "underruns")}
    return {"axes": axes, "motion": motion, "error": ""}


def _finite(x):
    return x if isinstance(x, (int, float)) and x == x and abs(x) != float("inf") else None


def _answer(line: bytes) -> dict:
    if not line.endswith(b"\n"):
        raise ValueError("the daemon closed the connection without answering")
    ans = json.loads(line.decode())
    if not isinstance(ans, dict):
        raise ValueError("the daemon's answer is not a JSON object")
    return ans


def _unreachable(error: str) -> dict:
    return {"ok": False, "error": error, "unreachable": True}


#: the page's own headers: no framing by other sites (clickjacking), no sniffing
_PAGE_HEADERS = {"X-Frame-Options": "DENY", "Content-Security-Policy": "frame-ancestors 'none'",
                 "X-Content-Type-Options": "nosniff", "Cache-Control": "no-store"}


def _json(obj: dict, status: int = 200, headers: dict | None = None):
    from aiohttp import web
    return web.json_response(obj, status=status, headers={"Cache-Control": "no-store", **(headers or {})})


async def _refuse_unread(request, ans: dict, status: int | None):
    """Answer a request whose body is refused unread (``status``: the HTTP status; None: as
    :func:`_answer_response`), at once, and close its connection :data:`REFUSED_BODY_CLOSE_S`
    later without reading the body: reading is paused, so a client sending gigabytes is held by
    TCP's window instead of being read and discarded (aiohttp would read on for up to 10 s at
    the network's speed), and has that long to read the answer."""
    resp = _answer_response(ans) if status is None else _json(
        {"ok": False, "error": ans.get("error", "refused"), "usage": bool(ans.get("usage"))}, status)
    resp.force_close()
    await resp.prepare(request)
    await resp.write_eof()
    tr = request.transport
    if tr is not None and not tr.is_closing():
        tr.pause_reading()
        asyncio.get_running_loop().call_later(REFUSED_BODY_CLOSE_S, tr.close)
    return resp


def _forbidden():
    return _json({"ok": False, "error": "forbidden: log in as an operator (a viewer and a page without "
                                        "a login are read only)"}, 403)


def _answer_response(ans: dict):
    """The daemon's answer as the page's: 200 ok, 409 refused (its one line), 502 unreachable."""
    if ans.get("ok"):
        return _json(ans)
    return _json({"ok": False, "error": ans.get("error", "refused"), "usage": bool(ans.get("usage"))},
                 502 if ans.get("unreachable") else 409)


async def _small_body(request) -> dict:
    """A login's or command's body: JSON or a form, at most MAX_SMALL_BODY bytes. Raises BadRequest."""
    if request.content_length is not None and request.content_length > MAX_SMALL_BODY:
        raise BadRequest(f"the body is larger than {MAX_SMALL_BODY} bytes")
    raw = await request.content.read(MAX_SMALL_BODY + 1)
    if len(raw) > MAX_SMALL_BODY:
        raise BadRequest(f"the body is larger than {MAX_SMALL_BODY} bytes")
    if not raw.strip():
        return {}
    if request.content_type == "application/x-www-form-urlencoded":
        from urllib.parse import parse_qsl
        try:
            return dict(parse_qsl(raw.decode(), keep_blank_values=True))
        except UnicodeDecodeError:
            raise BadRequest("the form is not UTF-8") from None
    try:
        body = json.loads(raw.decode())
    except (UnicodeDecodeError, json.JSONDecodeError):
        raise BadRequest("the body is neither JSON nor a form") from None
    if not isinstance(body, dict):
        raise BadRequest("the body is not a JSON object")
    return body
