"""The daemon's wire formats: the control socket (one JSON object per line each way) and the
pipes between its two processes (length-prefixed pickled messages).

Socket requests (``motorctl.cli.operator`` is the client)::

    {"cmd": "status", "axis": "X"?}
    {"cmd": "start", "axis": "X", "controller": "c2"?}
    {"cmd": "stop" | "fault-reset", "axis": "X"}
    {"cmd": "switch", "axis": "X", "controller": "pid"}
    {"cmd": "inject", "axis": "X", "kind": "...", "cycles": 1, "jump_m": 0.0, "force_N": 0.0}
    {"cmd": "jog", "axis": "X", "to_m": 0.0, "speed": 0.1}    (speed: fraction of v_max, a_max)
    {"cmd": "start", "axis": "X", "mode": "command"}          (command mode: follows commanded motion)
    {"cmd": "move", "targets": {"X": 0.12, "Y": 0.05}, "feed": 0.1?}   ([m], [m/s])
    {"cmd": "gcode", "text": "G1 X10 F600\n...", "filename": "part.ngc"}
    {"cmd": "upload", "bytes": 123456}   then, after the answer {"ok": true, "continue": true,
                                         "upload": "token"}, the program's bytes on the same connection
    {"cmd": "gcode", "upload": "token", "filename": "part.ngc"}   (a program sent by upload)
        gcode's options: "from_line": N (run from that line; the way there a move),
        "single_block": true (a pause after every block; resume runs the next)
    {"cmd": "optional-stop", "value": true}                    (M1 pauses or not, from now on)
    {"cmd": "jog", "axis": "X", "by": 0.001 | "velocity": 0.01 | "stop": true}
        (an axis in command mode: a move by that much, toward its soft limit until stopped)
    {"cmd": "hold" | "resume" | "abort"}
    {"cmd": "override", "value": 0.8}                          (0.0 .. 1.5)
    {"cmd": "home", "axis": "X"}

A program longer than one request (:data:`MAX_REQUEST_BYTES`) is sent by ``upload``: the request
line announces its size in bytes (UTF-8), the daemon answers ``continue`` with a token (or
refuses: too large, too many uploads), the client sends the bytes on the same connection and the
daemon answers once they are all in; then ``gcode`` names the token instead of giving the text
(``motorctl.client.send_program``). Every request line stays within the bound.

Answers: ``{"ok": true, ...}`` or ``{"ok": false, "error": "...", "usage": bool}`` (``usage``:
the request itself was wrong, exit code 2 in the client).
"""

from __future__ import annotations

import grp
import json
import math
import os
import socket
from dataclasses import dataclass
from pathlib import Path

from motorctl.app.pipes import Mailbox  # noqa: F401 - the pipes' wire format, named beside the socket's

#: the longest request line accepted [bytes]; a longer one is refused and the connection closed
MAX_REQUEST_BYTES = 65536
#: commands of the socket protocol
COMMANDS = ("status", "start", "stop", "switch", "fault-reset", "inject", "jog", "move", "gcode", "upload",
            "hold", "resume", "abort", "override", "optional-stop", "home")
#: commands that need an axis
AXIS_COMMANDS = ("start", "stop", "switch", "fault-reset", "inject", "jog", "home")
#: the axis modes of ``start``
MODES = ("program", "command")
#: a jog's speed and acceleration as a fraction of the axis's v_max and a_max: (0, MAX_JOG_SPEED]
MAX_JOG_SPEED = 0.5


class DaemonError(RuntimeError):
    """The daemon cannot start (one line, e.g. the socket cannot be created)."""


class RequestError(ValueError):
    """A request is wrong (unknown command, axis or controller; bad JSON): a usage error."""


@dataclass(frozen=True)
class Request:
    """A checked request. ``axis`` is the axis index (None for a status of every axis)."""

    cmd: str
    axis: int | None
    controller: str | None = None
    inject: dict | None = None
    jog: dict | None = None
    mode: str = "program"
    motion: dict | None = None


def parse_request(line: bytes, axis_names: list, controllers: list) -> Request:
    """Check one request line against the daemon's axes and each axis's configured
    controllers (``controllers[i]``: names). Raises :class:`RequestError` (one line)."""
    try:
        req = json.loads(line.decode())
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise RequestError(f"bad request: {exc}") from None
    if not isinstance(req, dict):
        raise RequestError("bad request: not a JSON object")
    cmd = req.get("cmd")
    if cmd not in COMMANDS:
        raise RequestError(f"unknown command {cmd!r}; allowed: {', '.join(COMMANDS)}")
    a = req.get("axis")
    if cmd in ("move", "gcode", "override", "upload", "optional-stop"):
        return Request(cmd, None, motion=_motion_request(cmd, req, axis_names))
    if a is None and cmd not in AXIS_COMMANDS:
        return Request(cmd, None)
    if a not in axis_names:
        raise RequestError(f"unknown axis {a!r}; axes: {', '.join(axis_names)}")
    i = axis_names.index(a)
    ctrl = req.get("controller")
    if ctrl is not None or cmd == "switch":
        if cmd not in ("start", "switch") or ctrl not in controllers[i]:
            raise RequestError(f"unknown controller {ctrl!r} for axis {a}; allowed: "
                               f"{', '.join(controllers[i])}")
    inject = None
    if cmd == "inject":
        try:
            inject = {"kind": str(req.get("kind")), "cycles": int(req.get("cycles", 1)),
                      "jump_m": float(req.get("jump_m", 0.0)),
                      "force_N": float(req.get("force_N", 0.0))}
        except (TypeError, ValueError) as exc:
            raise RequestError(f"bad inject request: {exc}") from None
    jog = None
    if cmd == "jog" and ("by" in req or "velocity" in req or "stop" in req):
        jog = _command_jog(req)
    elif cmd == "jog":
        try:
            to_m, speed = float(req["to_m"]), float(req.get("speed", 0.1))
        except (KeyError, TypeError, ValueError):
            raise RequestError("jog needs 'to_m' (a position in m) and an optional 'speed'") from None
        if not math.isfinite(to_m) or not 0.0 < speed <= MAX_JOG_SPEED:
            raise RequestError(f"jog: to_m must be finite and speed within (0, {MAX_JOG_SPEED}] "
                               f"(got {to_m}, {speed})")
        jog = {"kind": "to", "to_m": to_m, "speed": speed}
    mode = req.get("mode", "program")
    if mode not in MODES or (mode != "program" and cmd != "start"):
        raise RequestError(f"mode {mode!r} is allowed with start only; modes: {', '.join(MODES)}")
    return Request(cmd, i, ctrl, inject, jog, mode)


def _command_jog(req: dict) -> dict:
    """A jog of an axis in command mode: ``by`` [m] (incremental), ``velocity`` [m/s] (toward
    the soft limit on its side until ``stop``), or ``stop`` (true)."""
    kinds = [k for k in ("by", "velocity", "stop") if k in req]
    if len(kinds) != 1:
        raise RequestError("jog in command mode takes one of 'by' (m), 'velocity' (m/s) or 'stop'")
    k = kinds[0]
    if k == "stop":
        if req["stop"] is not True:
            raise RequestError("jog: 'stop' must be true")
        return {"kind": "stop"}
    v = req[k]
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v == 0:
        raise RequestError(f"jog: '{k}' must be a finite number other than 0 (got {v!r})")
    return {"kind": k, k: float(v)}


def _motion_request(cmd: str, req: dict, axis_names: list) -> dict:
    """The checked arguments of move, gcode and override (module docstring)."""
    def number(v, what):
        try:
            x = float(v)
        except (TypeError, ValueError):
            raise RequestError(f"{cmd}: {what} must be a number (got {v!r})") from None
        if not math.isfinite(x):
            raise RequestError(f"{cmd}: {what} must be finite (got {v!r})")
        return x
    if cmd == "override":
        return {"value": number(req.get("value"), "value")}
    if cmd == "optional-stop":
        if not isinstance(req.get("value"), bool):
            raise RequestError("optional-stop needs 'value': true or false")
        return {"value": req["value"]}
    if cmd == "gcode":
        text, name, token = req.get("text"), req.get("filename", "-"), req.get("upload")
        if (text is None) == (token is None) or not isinstance(name, str) or not isinstance(
                text if token is None else token, str):
            raise RequestError("gcode needs 'filename' and either 'text' (the program) or 'upload' "
                               "(the token of a program sent in chunks), strings")
        from_line, single = req.get("from_line", 1), req.get("single_block", False)
        if isinstance(from_line, bool) or not isinstance(from_line, int) or from_line < 1:
            raise RequestError(f"gcode: 'from_line' must be a line number >= 1 (got {from_line!r})")
        if not isinstance(single, bool):
            raise RequestError("gcode: 'single_block' must be true or false")
        return {"text": text, "upload": token, "filename": name, "from_line": from_line,
                "single_block": single}
    if cmd == "upload":
        n = req.get("bytes")
        if isinstance(n, bool) or not isinstance(n, int) or n < 0:
            raise RequestError("upload needs 'bytes': the program's size in bytes (>= 0); its bytes follow "
                               "the answer 'continue' on the same connection")
        return {"bytes": n}
    targets = req.get("targets")
    if not isinstance(targets, dict) or not targets:
        raise RequestError("move needs 'targets': {axis: position in m, ...}")
    out = {}
    for a, v in targets.items():
        if a not in axis_names:
            raise RequestError(f"move: unknown axis {a!r}; axes: {', '.join(axis_names)}")
        out[axis_names.index(a)] = number(v, a)
    feed = req.get("feed")
    return {"targets": out, "feed": None if feed is None else number(feed, "feed")}


def encode_answer(obj: dict) -> bytes:
    """One answer line."""
    return (json.dumps(obj) + "\n").encode()


class LineBuffer:
    """Per-connection framing: bytes in, complete lines out, survives partial reads.

    Raises:
        RequestError: a line longer than :data:`MAX_REQUEST_BYTES`.
    """

    def __init__(self):
        self._buf = b""

    def take_rest(self) -> bytes:
        """The bytes received after the line returned last (an upload's first bytes)."""
        rest, self._buf = self._buf, b""
        return rest

    def feed(self, data: bytes) -> bytes | None:
        """Add received bytes; the first complete line (without its newline) or None."""
        self._buf += data
        if b"\n" in self._buf:
            line, _, self._buf = self._buf.partition(b"\n")
            if len(line) > MAX_REQUEST_BYTES:
                raise RequestError(f"request longer than {MAX_REQUEST_BYTES} bytes")
            return line
        if len(self._buf) > MAX_REQUEST_BYTES:
            raise RequestError(f"request longer than {MAX_REQUEST_BYTES} bytes")
        return None


# --------------------------------------------------------------------------- the socket
def _resolve_group(group) -> int | None:
    if group is None:
        return None
    if isinstance(group, int):
        return group
    try:
        return grp.getgrnam(group).gr_gid
    except KeyError:
        raise DaemonError(f"daemon.group: no group named {group!r}") from None


def bind_control_socket(path: str, group=None, backlog: int = 64) -> socket.socket:
    """Create the listening Unix socket at ``path`` with mode 0660 and the given group.

    A stale socket file is replaced; a live one (another daemon answers) is an error.
    Raises:
        DaemonError: one line naming the path and the reason (permission, missing directory,
        another daemon running, unknown group).
    """
    gid = _resolve_group(group)
    p = Path(path)
    if not p.parent.exists() and str(p.parent).startswith("/run/motorctl"):
        try:
            os.makedirs(p.parent, mode=0o750, exist_ok=True)
        except OSError as exc:
            raise DaemonError(f"cannot create {p.parent}: {exc.strerror}") from None
    if p.exists() or p.is_socket():
        probe = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            probe.connect(str(p))
            probe.close()
            raise DaemonError(f"another daemon is already serving {p}")
        except (ConnectionRefusedError, FileNotFoundError):
            pass
        except PermissionError:
            raise DaemonError(f"cannot use the control socket {p}: permission denied") from None
        finally:
            probe.close()
        try:
            p.unlink()
        except OSError as exc:
            raise DaemonError(f"cannot replace the stale socket {p}: {exc.strerror}") from None
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM | socket.SOCK_CLOEXEC)
    old = os.umask(0o117)
    try:
        s.bind(str(p))
    except OSError as exc:
        s.close()
        raise DaemonError(f"cannot create the control socket {p}: {exc.strerror}") from None
    finally:
        os.umask(old)
    try:
        os.chmod(p, 0o660)
        if gid is not None:
            os.chown(p, -1, gid)
    except OSError as exc:
        s.close()
        p.unlink(missing_ok=True)
        raise DaemonError(f"cannot set the group/mode of {p}: {exc.strerror}") from None
    s.listen(backlog)
    return s


