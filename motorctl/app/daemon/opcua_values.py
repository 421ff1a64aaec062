"""The OPC UA server's figures: what the I/O process sends (:func:`snapshot`) and what each
variable of the address space (:mod:`motorctl.app.daemon.opcua_space`) shows of it
(:class:`Figures`; the table in docs/opcua.md).

Units: the NodeSet's EngineeringUnits where it gives them (ZeroOffset [mm], the feedrates
[mm/min], overrides and ActLoad [%]); positions in metres (the NodeSet gives none for
CncPositionVariableType) as are motorctl's own figures. A Mandatory figure the daemon does not
have is a null value with the status BadNotSupported (:data:`NOT_SUPPORTED`, why in words); a
figure that is a constant of this machine is written once (:meth:`Figures.constants`).
"""

from __future__ import annotations

import datetime as _dt
import math
import time

import numpy as np

from motorctl.app.daemon.opcua_space import AXES, CHANNEL, IFACE

#: CncChannelProgramStatus (OPC 40502): Stopped, Running, Waiting, Interrupted, Canceled
PROG_STOPPED, PROG_RUNNING, PROG_WAITING, PROG_INTERRUPTED, PROG_CANCELED = range(5)
#: CncChannelStatus (OPC 40502): Active, Interrupted, Reset
CH_ACTIVE, CH_INTERRUPTED, CH_RESET = range(3)
#: CncAxisStatus (OPC 40502): InPosition, Moving, Parked
AX_IN_POSITION, AX_MOVING, AX_PARKED = range(3)
#: CncOperationMode (OPC 40502): Manual, MDA, Automatic
OP_MANUAL, OP_MDA, OP_AUTOMATIC = range(3)
#: m -> mm, m/s -> mm/min, a share -> %
MM, MM_PER_MIN, PERCENT = 1e3, 6e4, 100.0
#: the program name of a line run by MDI (the operator page's, ``motorctl gcode -``'s)
MDI_NAMES = ("MDI", "-")
#: the Cartesian frames' coordinates (PosTcpBcs<c>, PosTcpWcs<c>); an axis of that name gives one
TCP_COORDINATES = "XYZABC"

#: Mandatory figures that the daemon does not have, by BrowseName (an axis's, the channel's):
#: BadNotSupported, and why
NOT_SUPPORTED = {
    "ActPower": "no power is measured: the amplifier takes a voltage command and reports no current",
    "ActTorque": "a linear motor: no torque (and its force is not measured)",
    "CmdTorque": "a linear motor: no torque; the command is a voltage (ActLoad)",
    "ActGFunctions": "the daemon does not keep the program's modal G state (ActModalOffsetFunction: 54)",
    "ActMFunctions": "the daemon does not keep the program's M state",
    "ActJogIncrement": "jogs are by a distance given with each jog, not a selected increment",
    "ActProgramBlock": "the daemon does not keep the program's text beside the line it runs",
    "DryRunFeed": "no dry run",
}
#: the status of NOT_SUPPORTED figures (OPC 10000-4 7.34.2 Bad_NotSupported)
BAD_NOT_SUPPORTED = 0x803D0000

#: descriptions of the served figures whose meaning is this machine's (by BrowseName)
DESCRIPTIONS = {
    "ActLoad": "|u| / u_lim: the share of the controller's output range the command uses [%]",
    "IsInactive": "the amplifier is off",
    "IsVirtual": "the simulated plant (driver type sim), no hardware",
    "ActChannel": "the channel that runs this axis's programs",
    "ZeroOffset": "the G54 work offset of this axis [mm]",
    "ActFeedrate": "the path speed of the setpoint (override included) [mm/min]",
    "CmdFeedrate": "the programmed path feed [mm/min]",
    "ActOverride": "feed override [%]", "CmdOverride": "feed override [%]",
    "ActProgramLine": "source line of the motion the loop runs (0: none)",
    "ActMainProgramLine": "as ActProgramLine (no subprograms)",
    "ActProgramFile": "the program running or run last, as named when sent",
    "ActMainProgramFile": "as ActProgramFile (no subprograms)",
    "ActOperationMode": "Automatic while a program runs, MDA while an MDI line runs, else Manual",
    "CmdOperationMode": "as ActOperationMode (the daemon's mode is the one commanded)",
    "BlockMode": "the program runs block by block (single_block)",
    "ToolId": "0: no tool (no tool changer)",
    "ActModalOffsetFunction": "work offset system programs start in (G54)",
    **NOT_SUPPORTED,
}


# ---------------------------------------------------------------------------- I/O process side
class Columns:
    """Column indices of the fields a snapshot takes from a ring row."""

    def __init__(self, layout, names):
        ix = layout.index
        self.y = np.asarray([ix(f"{a}.y") for a in names])
        self.xd = np.asarray([ix(f"{a}.x_d") for a in names])
        self.v = np.asarray([ix(f"{a}.x2") for a in names])
        self.vd = np.asarray([ix(f"{a}.xd_dot") for a in names])
        self.e = np.asarray([ix(f"{a}.e") for a in names])
        self.u = np.asarray([ix(f"{a}.u") for a in names])
        self.en = np.asarray([ix(f"{a}.enabled") for a in names])
        self.t = layout.cycle("t")


def snapshot(io, cols: Columns, slow: bool) -> dict:
    """The figures the server shows, from the I/O process's own state (``io``: its
    :class:`~motorctl.app.daemon.io_side.IOSide`); nothing is read from the loop but the status
    block and the newest row. Units: metres, m/s, V, seconds, µs; ``slow``: also the turnaround
    percentiles and the work offsets. Raises nothing the caller does not catch."""
    from motorctl.app.daemon.status import ST, fault_text
    from motorctl.loop.safety import with_drive_reason
    from motorctl.recorder.flight import CTL_REC_LATCHED, REC_REASONS

    ring, mo = io.plan.ring, io.motion
    row = ring.latest()
    st = ring.status
    n = len(io.names)
    bits = [int(b) for b in st[:, ST["fault"]]]
    modes = [int(m) for m in st[:, ST["mode"]]]
    nan = [math.nan] * n
    if row is None:
        t, y, xd, v, vd, e, u, en = 0.0, nan, nan, nan, nan, nan, nan, [False] * n
    else:
        t = float(row[cols.t])
        y, xd, v = row[cols.y].tolist(), row[cols.xd].tolist(), row[cols.v].tolist()
        vd, e, u = row[cols.vd].tolist(), row[cols.e].tolist(), row[cols.u].tolist()
        en = [bool(x > 0) for x in row[cols.en]]
    faults = []
    rec = REC_REASONS.get(int(ring.ctl[CTL_REC_LATCHED]), "")
    for i in range(n):
        if bits[i]:
            text = fault_text(bits[i], st[i, ST["value"]], st[i, ST["limit"]], rec)
            faults.append(with_drive_reason(text, io.drive_reasons[i]))
        else:
            faults.append("")
    line, done, left = mo.progress()
    job = io.job
    snap = {"t": t, "cycles": int(ring.published()), "y": y, "x_d": xd, "v": v, "xd_dot": vd,
            "e": e, "u": u, "enabled": en, "modes": modes, "fault_bits": bits, "faults": faults,
            "homed": [bool(h) for h in mo.homed], "line": int(line), "done": float(done),
            "left_s": float(left), "override": float(mo.override), "hold": bool(mo.holding),
            "aborting": bool(mo.aborting), "idle": bool(mo.idle()), "feed_m_s": float(mo.feed_m_s),
            "stopped_because": str(mo.reason),
            "program": job["job"].filename if job is not None else None,
            "single_block": bool(getattr(job["job"], "single_block", False)) if job is not None else False}
    if slow:
        snap["turnaround"] = [{k: float(v) for k, v in io.drainer.axis_stats[i].summary().items()
                               if k.startswith("turnaround")} for i in range(n)]
        g54 = mo.work_offsets.get("G54")
        snap["zero_offset"] = [0.0] * n if g54 is None else [
            float(g54["XYZ".index(a)]) if a in "XYZ" and len(a) == 1 else 0.0 for a in io.names]
    return snap


def axes_info(loaded, names) -> list[dict]:
    """What the server needs of each axis from the config (``loaded``: a LoadedConfig):
    name, rotational (False: linear motors), virtual (driver type ``sim``), u_lim [V], soft
    limits [m], v_max [m/s]."""
    cfg = loaded.cfg
    out = []
    for a in names:
        ax = cfg.axes[a]
        out.append({"name": a, "rotational": False, "virtual": cfg.driver.type == "sim",
                    "u_lim": float(ax.controller.u_lim), "soft_m": (float(ax.limits.soft_min_m),
                                                                    float(ax.limits.soft_max_m)),
                    "v_max": float(ax.trajectory.v_max)})
    return out


# ---------------------------------------------------------------------------- the server side
class Figures:
    """Writes snapshots into a :class:`~motorctl.app.daemon.opcua_space.Space` (``space``) for
    the axes ``axes`` (:func:`axes_info`'s dicts, in loop order)."""

    def __init__(self, space, axes: list[dict]):
        self.space, self.axes = space, axes
        self.names = [a["name"] for a in axes]
        self.tcp = {c: self.names.index(c) for c in TCP_COORDINATES if c in self.names}
        self.program = ""                    # the program run last (name)
        self.base: float | None = None       # UTC [s] of loop time 0
        self.snapshots = 0

    async def constants(self) -> None:
        """The figures that are constants of this machine, the EURanges, the descriptions, and
        the NOT_SUPPORTED figures' status (once, after the objects are made)."""
        from asyncua import ua
        s = self.space
        w = s.write
        for key in [k for k in s.vars if k.rsplit(".", 1)[-1] in DESCRIPTIONS]:
            await s.describe(key, DESCRIPTIONS[key.rsplit(".", 1)[-1]])
        await w(f"{IFACE}.VendorName", "motorctl")
        await w(f"{IFACE}.CncTypeName", "motorctl")
        await w(f"{IFACE}.Version", "1.0.0")
        channel = ua.NodeId(CHANNEL, s.ns)
        vmax = math.sqrt(sum(a["v_max"] ** 2 for a in self.axes))
        for j, ax in enumerate(self.axes):
            p = AXES + ax["name"]
            await w(f"{p}.ActChannel", channel)
            await w(f"{p}.IsRotational", bool(ax["rotational"]))
            await w(f"{p}.IsVirtual", bool(ax["virtual"]))
            await w(f"{p}.Id", j + 1)
            lo, hi = ax["soft_m"]
            for pos in ("PosDirect", "PosIndirect"):
                await s.set_range(f"{p}.{pos}", lo, hi)
            await s.set_range(f"{p}.ZeroOffset", lo * MM, hi * MM)
            await s.set_range(f"{p}.ActLoad", 0.0, 100.0)
            for name in ("ActPower", "ActTorque", "CmdTorque"):
                await s.write_bad(f"{p}.{name}", BAD_NOT_SUPPORTED)
        c = CHANNEL
        await w(f"{c}.Id", 1)
        await w(f"{c}.ToolId", 0)
        await w(f"{c}.ActModalOffsetFunction", 54)
        for name in ("ActOverride", "CmdOverride"):
            await s.set_range(f"{c}.{name}", 0.0, 150.0)
        for name in ("ActFeedrate", "CmdFeedrate"):
            await s.set_range(f"{c}.{name}", 0.0, vmax * MM_PER_MIN)
        for name in ("ActGFunctions", "ActMFunctions", "ActJogIncrement", "ActProgramBlock", "DryRunFeed"):
            await s.write_bad(f"{c}.{name}", BAD_NOT_SUPPORTED)
        for frame in ("Bcs", "Wcs"):
            for coord in TCP_COORDINATES:
                key = f"{c}.PosTcp{frame}{coord}"
                if coord in self.tcp:
                    await s.set_range(key, *self.axes[self.tcp[coord]]["soft_m"])
                    continue
                for child in ("", ".ActPos", ".CmdPos", ".RemDist"):
                    await s.write_bad(key + child, BAD_NOT_SUPPORTED)

    async def apply(self, snap: dict) -> None:
        """Write one snapshot's values: the live figures every time (their SourceTimestamp is
        the row's loop time), the others when they changed."""
        from motorctl.loop.servo import MODE_NAMES
        if self.base is None:
            self.base = time.time() - snap["t"]
        ts = _dt.datetime.fromtimestamp(self.base + snap["t"], _dt.timezone.utc)
        w = self.space.write
        await w(f"{IFACE}.LoopTime", snap["t"], ts, True)
        await w(f"{IFACE}.LoopCycles", snap["cycles"], ts)
        for i, ax in enumerate(self.axes):
            p = f"{AXES}{ax['name']}."
            for key, field in (("ActPos", "y"), ("CmdPos", "x_d"), ("ActSpeed", "v"),
                               ("CmdSpeed", "xd_dot"), ("FollowingError", "e")):
                await w(p + key, float(snap[field][i]), ts, True)
            for pos in ("PosDirect", "PosIndirect"):
                await self._position(p + pos, float(snap["y"][i]), float(snap["x_d"][i]), ts, True)
            en = snap["enabled"][i]
            moving = abs(snap["xd_dot"][i]) > 0.0
            await w(p + "ActStatus", AX_PARKED if not en else (AX_MOVING if moving else AX_IN_POSITION), ts)
            await w(p + "IsReferenced", snap["homed"][i], ts)
            await w(p + "Enabled", en, ts)
            await w(p + "IsInactive", not en, ts)
            u = snap["u"][i]
            await w(p + "ActLoad", PERCENT * abs(u) / ax["u_lim"] if en and math.isfinite(u) else 0.0, ts)
            await w(p + "Phase", MODE_NAMES.get(snap["modes"][i], "?"), ts)
            await w(p + "IsFaulted", bool(snap["fault_bits"][i]), ts)
            await w(p + "FaultBits", snap["fault_bits"][i], ts)
            await w(p + "FaultReason", snap["faults"][i], ts)
            if "turnaround" in snap:
                tr = snap["turnaround"][i]
                await w(p + "TurnaroundP50", tr["turnaround_p50_us"], ts)
                await w(p + "TurnaroundP99", tr["turnaround_p99_us"], ts)
                await w(p + "TurnaroundMax", tr["turnaround_max_us"], ts)
                await w(p + "ZeroOffset", snap["zero_offset"][i] * MM, ts)
        await self._channel(snap, ts)
        self.snapshots += 1

    async def _channel(self, snap: dict, ts) -> None:
        w, c = self.space.write, CHANNEL + "."
        if snap["program"]:
            self.program = snap["program"]
        running = not snap["idle"]
        if snap["hold"] and running:
            prog, chan = PROG_INTERRUPTED, CH_INTERRUPTED
        elif running:
            prog, chan = (PROG_CANCELED if snap["aborting"] else PROG_RUNNING), CH_ACTIVE
        else:
            prog, chan = (PROG_CANCELED if snap["stopped_because"] else PROG_STOPPED), CH_RESET
        mode = OP_MANUAL if not running else (OP_MDA if self.program in MDI_NAMES else OP_AUTOMATIC)
        for name in ("ActProgramName", "ActMainProgramName", "ActProgramFile", "ActMainProgramFile"):
            await w(c + name, self.program, ts)
        for name in ("ActProgramLine", "ActMainProgramLine"):
            await w(c + name, str(snap["line"]), ts)
        await w(c + "ActProgramStatus", prog, ts)
        await w(c + "ActStatus", chan, ts)
        await w(c + "ActOperationMode", mode, ts)
        await w(c + "CmdOperationMode", mode, ts)
        await w(c + "BlockMode", snap["single_block"], ts)
        for name in ("FeedOverride", "ActOverride", "CmdOverride"):
            await w(c + name, snap["override"] * PERCENT, ts)
        await w(c + "FeedHold", snap["hold"], ts)
        path = math.sqrt(sum(v * v for v in snap["xd_dot"] if math.isfinite(v)))
        await w(c + "ActFeedrate", path * MM_PER_MIN, ts)
        await w(c + "CmdFeedrate", snap["feed_m_s"] * MM_PER_MIN, ts)
        await w(c + "ProgramDone", snap["done"], ts)
        await w(c + "TimeLeft", snap["left_s"], ts)
        await w(c + "StoppedBecause", snap["stopped_because"], ts)
        offsets = self.space.last
        for coord, i in self.tcp.items():
            y, xd = float(snap["y"][i]), float(snap["x_d"][i])
            g54 = offsets.get(f"{AXES}{coord}.ZeroOffset") or 0.0
            for frame, off in (("Bcs", 0.0), ("Wcs", g54 / MM)):
                await self._position(f"{c}PosTcp{frame}{coord}", y - off, xd - off, ts)

    async def _position(self, key: str, act: float, cmd: float, ts, always: bool = False) -> None:
        """A CncPositionVariable: its ActPos, CmdPos (written every time when ``always``),
        RemDist = commanded - measured [m], and its own value, the CncPositionDataType of them."""
        w = self.space.write
        await w(f"{key}.ActPos", act, ts, always)
        await w(f"{key}.CmdPos", cmd, ts, always)
        await w(f"{key}.RemDist", cmd - act, ts)
        await w(key, self.space.position(act, cmd, cmd - act), ts)


__all__ = ["Columns", "snapshot", "axes_info", "Figures", "NOT_SUPPORTED", "BAD_NOT_SUPPORTED"]
