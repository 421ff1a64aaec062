"""A typed Python client of ``motorctl daemon`` over its control socket (the same wire protocol
as the ``motorctl`` command line: one JSON object per line each way,
:mod:`motorctl.app.daemon.protocol`).

    from motorctl.client import Client
    c = Client("/run/motorctl/motorctl.sock")
    c.start("X", mode="command"); c.start("Y", mode="command")
    c.move({"X": 0.120, "Y": 0.050}, feed=0.1)
    c.wait()
    print(c.status()["motion"])

Every method returns the daemon's answer (a dict) or raises :class:`Refused` (the daemon said
no: ``usage`` tells a wrong request from a refusal by the machine's state) or
:class:`DaemonUnreachable` (no daemon, permission denied, no answer in time).
"""

from __future__ import annotations

import json
import os
import socket
import time

#: the daemon's control socket unless told otherwise (``$MOTORCTL_SOCKET`` overrides it)
DEFAULT_SOCKET = "/run/motorctl/motorctl.sock"


class DaemonUnreachable(Exception):
    """Printed as one line; exit code 1."""


def _connect(path: str, timeout_s: float):
    """A connection to the daemon's socket; a full connection queue (many operators at once) is
    waited out with backoff within the timeout. Raises DaemonUnreachable."""
    deadline = time.monotonic() + timeout_s
    pause = 0.005
    while True:
        s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        s.settimeout(timeout_s)
        try:
            s.connect(path)
            return s
        except BlockingIOError:
            s.close()
            # the daemon's listen backlog is full (many operators at once): queue up
            if time.monotonic() + pause > deadline:
                raise DaemonUnreachable(f"the daemon at {path} is busy (connection queue "
                                        f"full for {timeout_s:g} s)") from None
            time.sleep(pause)
            pause = min(pause * 2, 0.1)
        except OSError as exc:
            s.close()
            if isinstance(exc, (FileNotFoundError, ConnectionRefusedError)):
                raise DaemonUnreachable(f"the daemon is not running (nothing answers at {path})") from None
            if isinstance(exc, PermissionError):
                raise DaemonUnreachable(f"permission denied on {path}: commanding the machine needs "
                                        f"membership of the socket's group") from None
            raise DaemonUnreachable(f"cannot reach the daemon at {path}: {exc.strerror or exc}") from None


def _answer(s, path: str, timeout_s: float, buf: bytes = b"") -> tuple[dict, bytes]:
    """The next answer line on ``s`` (and the bytes after it). Raises DaemonUnreachable."""
    try:
        while b"\n" not in buf:
            chunk = s.recv(65536)
            if not chunk:
                break
            buf += chunk
    except socket.timeout:
        raise DaemonUnreachable(f"the daemon at {path} did not answer within {timeout_s:g} s") from None
    except OSError as exc:
        raise DaemonUnreachable(f"lost the connection to the daemon at {path}: {exc.strerror or exc}") from None
    if b"\n" not in buf:
        raise DaemonUnreachable(f"the daemon at {path} closed the connection without answering")
    line, _, rest = buf.partition(b"\n")
    return json.loads(line.decode()), rest


def call(path: str, request: dict, timeout_s: float = 5.0) -> dict:
    """Send one request to the daemon and return its answer (a dict with 'ok'). A full
    connection queue (many operators at once) is waited out with backoff within the timeout.

    Raises:
        DaemonUnreachable: no daemon at ``path``, permission denied, or no answer in time.
    """
    s = _connect(path, timeout_s)
    try:
        s.sendall((json.dumps(request) + "\n").encode())
        return _answer(s, path, timeout_s)[0]
    except OSError as exc:
        raise DaemonUnreachable(f"lost the connection to the daemon at {path}: {exc.strerror or exc}") from None
    finally:
        s.close()


#: a program up to this many characters goes in the ``gcode`` request itself
ONE_REQUEST_CHARS = 16384


def send_program(path: str, text: str, filename: str, timeout_s: float = 5.0, *, from_line: int = 1,
                 single_block: bool = False) -> dict:
    """Send a G-code program of any length and queue it: in the request when short, else by
    ``upload`` (its bytes streamed on one connection, :mod:`motorctl.app.daemon.protocol`) then
    ``gcode`` naming it. The daemon checks the whole program before anything moves and answers
    when its first window is planned; the wait for that grows with the program (``timeout_s``
    plus 60 s per 10 MB). ``from_line``: run from that line; ``single_block``: a pause after
    every block. Returns the daemon's answer (``ok`` False: refused, with ``error``).

    Raises:
        DaemonUnreachable: as :func:`call`.
    """
    opts = {"from_line": int(from_line), "single_block": bool(single_block)}
    if len(text) <= ONE_REQUEST_CHARS:
        return call(path, {"cmd": "gcode", "text": text, "filename": filename, **opts},
                    max(timeout_s, 30.0))
    data = text.encode("utf-8", "surrogatepass")
    send_s = max(timeout_s, 30.0) + 60.0 * len(data) / 10e6
    s = _connect(path, send_s)
    try:
        s.sendall((json.dumps({"cmd": "upload", "bytes": len(data)}) + "\n").encode())
        ans, rest = _answer(s, path, send_s)
        if not ans.get("ok"):
            return ans
        s.sendall(data)
        ans, _ = _answer(s, path, send_s, rest)
    except OSError as exc:
        raise DaemonUnreachable(f"lost the connection to the daemon at {path}: {exc.strerror or exc}") from None
    finally:
        s.close()
    if not ans.get("ok"):
        return ans
    return call(path, {"cmd": "gcode", "upload": ans["upload"], "filename": filename, **opts}, send_s)


class Refused(Exception):
    """The daemon refused a request (one line). ``usage``: the request was wrong (exit code 2
    on the command line), else the machine's state refused it (1)."""

    def __init__(self, text: str, usage: bool = False):
        super().__init__(text)
        self.usage = usage


class Client:
    """The daemon at ``path`` (default: ``$MOTORCTL_SOCKET`` or :data:`DEFAULT_SOCKET`);
    ``timeout_s`` per request."""

    def __init__(self, path: str | None = None, timeout_s: float = 5.0):
        self.path = path or os.environ.get("MOTORCTL_SOCKET") or DEFAULT_SOCKET
        self.timeout_s = timeout_s

    def request(self, req: dict) -> dict:
        """One request; the answer when ok. Raises Refused, DaemonUnreachable."""
        ans = call(self.path, req, self.timeout_s)
        if not ans.get("ok"):
            raise Refused(ans.get("error", "refused"), bool(ans.get("usage")))
        return ans

    def status(self, axis: str | None = None) -> dict:
        """The status (axes, loop, motion: queue depth, G-code line, feed, override, ...)."""
        return self.request({"cmd": "status", **({"axis": axis} if axis else {})})["status"]

    def start(self, axis: str, mode: str = "program", controller: str | None = None) -> dict:
        """Enable ``axis``: ``program`` (its YAML program) or ``command`` (hold, then follow
        commanded motion)."""
        return self.request({"cmd": "start", "axis": axis, "mode": mode,
                             **({"controller": controller} if controller else {})})

    def stop(self, axis: str) -> dict:
        return self.request({"cmd": "stop", "axis": axis})

    def move(self, targets: dict[str, float], feed: float | None = None) -> dict:
        """Queue a coordinated straight move to ``targets`` ({axis: position [m]}), the path
        speed at most ``feed`` [m/s]. Returns its duration_s, from_m, to_m."""
        return self.request({"cmd": "move", "targets": dict(targets),
                             **({"feed": feed} if feed is not None else {})})

    def gcode(self, text: str, filename: str = "-", *, from_line: int = 1, single_block: bool = False) -> dict:
        """Queue a G-code program of any length (:func:`send_program`; refused whole with
        ``file:line:column`` when wrong)."""
        ans = send_program(self.path, text, filename, self.timeout_s, from_line=from_line,
                           single_block=single_block)
        if not ans.get("ok"):
            raise Refused(ans.get("error", "refused"), bool(ans.get("usage")))
        return ans

    def hold(self) -> dict:
        """Feed hold: decelerate on the path, then hold."""
        return self.request({"cmd": "hold"})

    def resume(self) -> dict:
        return self.request({"cmd": "resume"})

    def abort(self) -> dict:
        """Stop on the path, hold, clear the queue."""
        return self.request({"cmd": "abort"})

    def override(self, value: float) -> dict:
        """Feed override 0.0..1.5 (a time scale of the planned motion)."""
        return self.request({"cmd": "override", "value": float(value)})

    def home(self, axis: str) -> dict:
        return self.request({"cmd": "home", "axis": axis})

    def wait_started(self, timeout_s: float = 300.0, alive=None, poll_s: float = 0.2) -> dict:
        """Until the daemon answers with its real-time set-up done (``status()["realtime_summary"]``
        no longer "pending"): what a script that has just started ``motorctl daemon`` waits for.
        ``alive``: called between tries, False when the daemon's process has ended (then no
        more waiting). Returns that status. Raises DaemonUnreachable: not started within
        ``timeout_s`` [s], or ``alive()`` False."""
        end = time.monotonic() + timeout_s
        while True:
            try:
                st = self.status()
                if st["realtime_summary"] != "pending":
                    return st
            except DaemonUnreachable:
                pass
            if alive is not None and not alive():
                raise DaemonUnreachable("the daemon's process ended before it started")
            if time.monotonic() > end:
                raise DaemonUnreachable(f"the daemon did not start within {timeout_s:g} s")
            time.sleep(poll_s)

    def wait(self, timeout_s: float = 60.0, poll_s: float = 0.02) -> dict:
        """Until nothing is queued or streamed and every axis in command mode is within its
        in-position window (or ``timeout_s``: DaemonUnreachable). Returns the last status. A program cut short (underrun, abort, fault) ends the wait too: see
        ``status()["motion"]["stopped_because"]``."""
        end = time.monotonic() + timeout_s
        while True:
            st = self.status()
            mo = st["motion"]
            if mo["idle"] and (mo["stopped_because"] or all(
                    a.get("in_position", True) for a in st["axes"].values() if a["phase"] == "command")):
                return st
            if time.monotonic() > end:
                raise DaemonUnreachable(f"motion did not finish within {timeout_s:g} s")
            time.sleep(poll_s)
