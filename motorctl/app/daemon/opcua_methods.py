"""The CNC channel's methods (OPC 10000-4 5.11 Call; docs/opcua.md "Methods"): each goes to the
daemon through its control socket (:mod:`motorctl.client`), as ``motorctl`` does, with the same
checks and refusals. A refusal is the call's status code (BadInvalidArgument: a wrong request;
BadInvalidState: the machine's state; BadNotFound: no such program) with the daemon's words in
the channel's ``LastCommandError``; an accepted call returns the daemon's answer as JSON text.
Who may call is the permission rules' (:func:`motorctl.app.daemon.opcua_security.ruleset`).
"""

from __future__ import annotations

import asyncio
import os
import stat

from motorctl.app.daemon.opcua_space import AXES, CHANNEL

#: where a refused call's reason is written
LAST_ERROR = f"{CHANNEL}.LastCommandError"

#: programs LoadProgram keeps at once (the oldest go)
MAX_LOADED_PROGRAMS = 16
#: the largest program LoadProgram takes, and all it keeps together [bytes] (a larger one, up
#: to daemon.max_program_bytes: Start with its path, or the operator page)
OPCUA_MAX_PROGRAM_BYTES = 16 << 20
#: the files Start takes by path (nothing else on the daemon's host is read)
PROGRAM_SUFFIXES = (".ngc", ".nc", ".gcode", ".tap")
#: a command through the control socket is given up after this long [s]
COMMAND_TIMEOUT_S = 10.0
#: a program's answer (the daemon checks it whole first) [s]
PROGRAM_TIMEOUT_S = 30.0


def read_program(path: str, max_bytes: int) -> str:
    """The text of the G-code file ``path`` for Start, at most ``max_bytes`` read whatever the
    file does meanwhile (a file that grows past the limit after its size was seen is refused,
    not read whole). Raises OSError (no such file, unreadable) and ValueError (not a regular
    file: a FIFO would block the read, a device never end; larger than ``max_bytes``: the
    words say daemon.max_program_bytes)."""
    fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)       # (a FIFO's open would wait for a writer)
    with open(fd, "rb") as fh:
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            raise ValueError("not a regular file")
        data = fh.read(max_bytes + 1)
    if len(data) > max_bytes:
        raise ValueError(f"the program is larger than daemon.max_program_bytes = {max_bytes}")
    return data.decode("utf-8", errors="surrogateescape")


def program_limit(max_program_bytes: int) -> int:
    """The largest program LoadProgram takes [bytes]: daemon.max_program_bytes, at most
    :data:`OPCUA_MAX_PROGRAM_BYTES` (the server holds what it is given in memory)."""
    return min(int(max_program_bytes), OPCUA_MAX_PROGRAM_BYTES)


def _status_of(fn):
    """A method whose refusal (a raised UaStatusCodeError) is the call's StatusCode (asyncua
    answers any exception BadUnexpectedError); wrong arguments are BadInvalidArgument."""
    from asyncua import ua

    async def method(parent, *args):
        try:
            return await fn(parent, *args)
        except ua.UaStatusCodeError as exc:
            return ua.StatusCode(exc.code)
        except (TypeError, ValueError, AttributeError):
            return ua.StatusCode(ua.StatusCodes.BadInvalidArgument)

    return method


class Methods:
    """The channel's methods over the daemon's control socket ``control``: ``space`` (the
    :class:`~motorctl.app.daemon.opcua_space.Space`: the last values written, LastCommandError),
    ``figures`` (:class:`~motorctl.app.daemon.opcua_values.Figures`: the program's name), the
    axis names in loop order, the daemon's ``max_program_bytes``."""

    def __init__(self, space, figures, control: str, names: list[str], max_program_bytes: int):
        self.space, self.figures, self.control, self.names = space, figures, control, list(names)
        self.limit = program_limit(max_program_bytes)
        self.max_program_bytes = int(max_program_bytes)
        self.programs: dict[str, str] = {}   # LoadProgram's programs by name

    async def add(self, channel) -> None:
        """The methods on the channel's object ``channel``."""
        from asyncua import ua
        S, D = ua.VariantType.String, ua.VariantType.Double
        ns = self.space.ns

        def arg(name, vt, desc):
            a = ua.Argument()
            a.Name, a.DataType, a.ValueRank = name, ua.NodeId(vt.value), -1
            a.Description = ua.LocalizedText(desc)
            return a

        out = [arg("Result", S, "the daemon's answer (JSON)")]
        axis = arg("Axis", S, f"axis name ({', '.join(self.names)}); empty: every axis (Enable), "
                              "every faulted axis (FaultReset)")
        for name, fn, ins in (
                ("Start", self.m_start, [arg("Program", S, "a name given to LoadProgram, or a file path on "
                                                           "the daemon's host")]),
                ("LoadProgram", self.m_load, [arg("Name", S, "the program's name"),
                                              arg("Text", S, f"G-code, at most {self.limit} bytes")]),
                ("Stop", self.m_stop, []), ("Hold", self.m_simple("hold"), []),
                ("Resume", self.m_simple("resume"), []), ("Abort", self.m_simple("abort"), []),
                ("Home", self.m_axis("home", False), [axis]),
                ("FaultReset", self.m_axis("fault-reset", True), [axis]),
                ("Enable", self.m_enable, [axis]),
                ("SetFeedOverride", self.m_override, [arg("Percent", D, "0 .. 150")])):
            await channel.add_method(ua.NodeId(f"{CHANNEL}.{name}", ns), ua.QualifiedName(name, ns),
                                     _status_of(fn), ins, out)

    async def _cmd(self, req: dict, timeout_s: float = COMMAND_TIMEOUT_S, program: tuple | None = None) -> dict:
        """One request through the control socket (a thread: the server goes on meanwhile)."""
        from motorctl.client import DaemonUnreachable, call, send_program
        try:
            if program is not None:
                ans = await asyncio.to_thread(send_program, self.control, program[1], program[0], timeout_s)
            else:
                ans = await asyncio.to_thread(call, self.control, req, timeout_s)
        except DaemonUnreachable as exc:
            ans = {"ok": False, "error": str(exc), "usage": False}
        return ans

    async def _answer(self, ans: dict):
        """The method's output, or its refusal as a status code (the reason in LastCommandError)."""
        import json

        from asyncua import ua
        if not ans.get("ok"):
            await self.space.write(LAST_ERROR, ans.get("error", "refused"))
            raise ua.UaStatusCodeError(ua.StatusCodes.BadInvalidArgument if ans.get("usage")
                                       else ua.StatusCodes.BadInvalidState)
        ans.pop("status", None)
        return [ua.Variant(json.dumps(ans, default=str), ua.VariantType.String)]

    async def m_load(self, parent, name, text):
        """Keep a program under a name: at most :attr:`limit` bytes, the programs kept together
        within it too and MAX_LOADED_PROGRAMS of them (the oldest go)."""
        from asyncua import ua
        name, text = str(name.Value or ""), str(text.Value or "")
        size = len(text.encode("utf-8", "surrogatepass"))
        if not name or size > self.limit:
            await self.space.write(LAST_ERROR, f"LoadProgram: {name!r}: " + (
                "no name" if not name else f"the program ({size} bytes) is larger than the {self.limit} bytes "
                                           "LoadProgram takes; Start a larger one by its path"))
            raise ua.UaStatusCodeError(ua.StatusCodes.BadInvalidArgument)
        self.programs.pop(name, None)
        self.programs[name] = text
        while len(self.programs) > MAX_LOADED_PROGRAMS or sum(
                len(t) for t in self.programs.values()) > self.limit and len(self.programs) > 1:
            self.programs.pop(next(iter(self.programs)))
        return [ua.Variant(f'{{"ok": true, "loaded": {size}}}', ua.VariantType.String)]

    async def m_start(self, parent, prog):
        from asyncua import ua
        name = str(prog.Value or "")
        if name in self.programs:
            text = self.programs[name]
        else:
            if not name.lower().endswith(PROGRAM_SUFFIXES):
                await self.space.write(LAST_ERROR, f"Start: {name!r}: no program loaded by that name, and not "
                                                   f"a G-code file ({', '.join(PROGRAM_SUFFIXES)})")
                raise ua.UaStatusCodeError(ua.StatusCodes.BadNotFound)
            try:
                text = await asyncio.to_thread(read_program, name, self.max_program_bytes)
            except ValueError as exc:
                await self.space.write(LAST_ERROR, f"Start: {name!r}: {exc}")
                raise ua.UaStatusCodeError(ua.StatusCodes.BadInvalidArgument) from None
            except OSError as exc:
                await self.space.write(LAST_ERROR, f"Start: {name!r}: no program loaded by that name, and not "
                                                   f"a readable file ({exc.strerror})")
                raise ua.UaStatusCodeError(ua.StatusCodes.BadNotFound) from None
            name = os.path.basename(name)
        ans = await self._cmd({}, PROGRAM_TIMEOUT_S, program=(name, text))
        if ans.get("ok"):
            self.figures.program = name
        return await self._answer(ans)

    def m_simple(self, cmd: str):
        async def m(parent):
            return await self._answer(await self._cmd({"cmd": cmd}))
        return m

    def _axes_of(self, v) -> list[str]:
        from asyncua import ua
        name = str(v.Value or "")
        if not name:
            return list(self.names)
        if name not in self.names:
            raise ua.UaStatusCodeError(ua.StatusCodes.BadInvalidArgument)
        return [name]

    def m_axis(self, cmd: str, faulted_only: bool):
        """Home (one axis: homing one runs at a time) or FaultReset ("" = every faulted axis)."""
        from asyncua import ua

        async def m(parent, axis):
            names = self._axes_of(axis)
            if len(names) > 1:
                if not faulted_only:
                    raise ua.UaStatusCodeError(ua.StatusCodes.BadInvalidArgument)
                names = [a for a in names if self.space.last.get(f"{AXES}{a}.IsFaulted")]
            ans = {"ok": True}
            for a in names:
                ans = await self._cmd({"cmd": cmd, "axis": a})
                if not ans.get("ok"):
                    break
            return await self._answer(ans)
        return m

    async def m_enable(self, parent, axis):
        ans = {"ok": True}
        for a in self._axes_of(axis):
            if self.space.last.get(f"{AXES}{a}.Phase") == "command":
                continue
            ans = await self._cmd({"cmd": "start", "axis": a, "mode": "command"})
            if not ans.get("ok"):
                break
        return await self._answer(ans)

    async def m_stop(self, parent):
        ans = {"ok": True}
        for a in self.names:
            if self.space.last.get(f"{AXES}{a}.Enabled") or \
                    self.space.last.get(f"{AXES}{a}.Phase") not in ("disabled", ""):
                ans = await self._cmd({"cmd": "stop", "axis": a})
                if not ans.get("ok"):
                    break
        return await self._answer(ans)

    async def m_override(self, parent, pct):
        return await self._answer(await self._cmd({"cmd": "override", "value": float(pct.Value) / 100.0}))


__all__ = ["Methods", "program_limit", "OPCUA_MAX_PROGRAM_BYTES", "PROGRAM_SUFFIXES", "MAX_LOADED_PROGRAMS"]
