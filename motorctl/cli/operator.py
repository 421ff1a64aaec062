"""Daemon subcommands of ``motorctl``: ``daemon``, ``start``, ``stop``, ``status``,
``fault-reset``, ``switch``, ``export`` (and ``inject`` for the simulated driver), plus the
global ``--socket PATH`` option.

The client commands talk to ``motorctl daemon`` over its Unix control socket (default
``/run/motorctl/motorctl.sock``, or ``$MOTORCTL_SOCKET``); the socket's mode (0660) and group
decide who may command the machine. Exit codes: 0 done; 1 the daemon refused or is not
reachable (not running, permission denied, axis in fault, stop not finished in time);
2 bad input (unknown axis or controller, unreadable log). Errors are one line on stderr.

``fault-reset --config CONFIG AXIS...`` needs no daemon: it opens the config's driver and sends
the drives' own fault reset (:mod:`motorctl.app.fault_reset`; refused, exit 1, while a daemon
answers on its socket; exit 1 when a drive stays in its fault, 3 when the stop after it is not
confirmed by the device).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import socket
import sys
import time

from motorctl.client import DEFAULT_SOCKET, DaemonUnreachable, call, send_program
from motorctl.control import CONTROLLER_NAMES


def socket_path(args) -> str:
    return getattr(args, "socket", None) or os.environ.get("MOTORCTL_SOCKET") or DEFAULT_SOCKET


def _checked(args, request: dict, timeout_s: float = 5.0) -> dict:
    from motorctl.cli import UsageError
    ans = call(socket_path(args), request, timeout_s)
    if not ans.get("ok"):
        if ans.get("usage"):
            raise UsageError(ans.get("error", "refused"))
        raise DaemonUnreachable(ans.get("error", "refused"))
    return ans


def _wrap(handler):
    def run(args) -> int:
        try:
            return handler(args)
        except DaemonUnreachable as exc:
            sys.stderr.write(f"motorctl: error: {exc}\n")
            return 1
    return run


# --------------------------------------------------------------------------- handlers
def cmd_daemon(args) -> int:
    """``motorctl daemon``: a SIGTERM/SIGINT while it loads and builds is one line
    (:func:`motorctl.cli.main`, then :func:`motorctl.app.daemon.run_daemon`'s own)."""
    from motorctl.app.warmup import say_if_cold
    say_if_cold()                                 # within a second, before numba is imported
    from motorctl.app.daemon import DaemonError, run_daemon
    try:
        return run_daemon(args.config, args.daemon_socket or args.socket, args.log_dir)
    except DaemonError as exc:
        sys.stderr.write(f"motorctl: error: {exc}\n")
        return 1


def cmd_start(args) -> int:
    req = {"cmd": "start", "axis": args.axis, "mode": args.mode}
    if args.controller:
        req["controller"] = args.controller
    ans = _checked(args, req)
    if args.mode == "command":
        sys.stdout.write(f"{args.axis}: enabled on {ans.get('controller')} in command mode, holding "
                         f"where it stands\n")
        return 0
    sys.stdout.write(f"{args.axis}: enabled on {ans.get('controller')}, approach "
                     f"{ans.get('approach_m', 0.0) * 1000:+.3f} mm in {ans.get('approach_s', 0.0):.3f} s, "
                     f"then the program\n")
    return 0


def cmd_stop(args) -> int:
    ans = _checked(args, {"cmd": "stop", "axis": args.axis})
    bound = float(ans.get("bound_s", 2.0))
    if args.no_wait or ans.get("was") == "disabled":
        sys.stdout.write(f"{args.axis}: {'already disabled' if ans.get('was') == 'disabled' else 'stopping'}\n")
        return 0
    st, took_s = _until_disabled(args, bound + 1.0, "come to rest", ans.get("cycle"))
    what = "0 V, amplifier off" if st["state"] == "disabled" else f"fault: {st['fault']}"
    sys.stdout.write(f"{args.axis}: stopped in {took_s:.3f} s ({what})\n")
    return 0 if st["state"] == "disabled" else 1


def _until_disabled(args, bound_s: float, what: str, c0: int | None) -> tuple[dict, float]:
    """Poll the axis until it is no longer enabled: (its status, the seconds it took on the loop's
    clock since cycle c0, the loop's count when the request took effect; None: the first
    status's). The bound is judged on the loop's cycle count, not this host's clock: on a busy PC a
    status answer can take seconds while the loop runs on time; a wall bound of 10x only
    catches a daemon whose loop no longer advances. Raises DaemonUnreachable past the bound."""
    t0 = time.monotonic()
    while time.monotonic() < t0 + 10.0 * bound_s + 30.0:
        whole = _checked(args, {"cmd": "status", "axis": args.axis})["status"]
        st, loop = whole["axes"][args.axis], whole["loop"]
        c0 = loop["cycles"] if c0 is None else c0
        took_s = (loop["cycles"] - c0) / loop["rate_hz"]
        if st["state"] != "enabled":
            return st, took_s
        if took_s > bound_s:
            break
        time.sleep(0.01)
    raise DaemonUnreachable(f"axis {args.axis} did not {what} within {bound_s:.2f} s of the loop's clock")


def cmd_switch(args) -> int:
    ans = _checked(args, {"cmd": "switch", "axis": args.axis, "controller": args.controller})
    sys.stdout.write(f"{args.axis}: {ans.get('from')} -> {args.controller} at cycle {ans.get('cycle')}\n")
    return 0


def cmd_fault_reset(args) -> int:
    """``fault-reset AXIS...`` through the daemon; ``fault-reset --config CONFIG AXIS...`` with no
    daemon: the drives' own reset from the config's driver (:mod:`motorctl.app.fault_reset`)."""
    if args.config:
        return _fault_reset_without_daemon(args)
    for axis in args.axis:
        ans = call(socket_path(args), {"cmd": "fault-reset", "axis": axis})
        if not ans.get("ok"):
            from motorctl.cli import UsageError
            if ans.get("usage"):
                raise UsageError(ans["error"])
            raise DaemonUnreachable(f"fault-reset {axis} refused: {ans.get('error')}")
        was = ans.get("was") or "no fault was latched"
        sys.stdout.write(f"{axis}: fault cleared ({was}); the axis stays disabled\n")
    return 0


def _fault_reset_without_daemon(args) -> int:
    from motorctl.app.fault_reset import reset_drive_faults
    from motorctl.config import load_config
    loaded = load_config(args.config, check_budget=False)
    sockets = [p for p in (getattr(args, "socket", None), os.environ.get("MOTORCTL_SOCKET")) if p]
    rep = reset_drive_faults(loaded, args.axis, sockets)
    out = sys.stdout
    for r in rep.axes:
        if not r.was:
            out.write(f"{r.axis}: no fault to reset; the drive: {r.now or 'no fault reported'}\n")
        elif r.cleared:
            out.write(f"{r.axis}: the drive's fault is reset: was {r.was}; now {r.now or 'no fault reported'}\n")
        elif not r.sent:
            out.write(f"{r.axis}: the device has no fault reset of its own (its own reset input, a power "
                      f"cycle): {r.now}\n")
        else:
            out.write(f"{r.axis}: the drive did not leave its fault within its reset's bound: {r.now}\n")
    for line in rep.stop:
        (out if rep.stop_confirmed else sys.stderr).write(line + "\n")
    if not rep.stop_confirmed:
        return 3
    return 0 if all(r.cleared for r in rep.axes) else 1


def cmd_jog(args) -> int:
    from motorctl.cli import UsageError
    given = [k for k in ("to_m", "by", "velocity") if getattr(args, k) is not None] + (["stop"] if args.stop else [])
    if len(given) != 1:
        raise UsageError("jog: give one of TO_M, --by M, --velocity M_PER_S or --stop")
    if given[0] != "to_m":                   # an axis in command mode (a move of the stream)
        req = {"cmd": "jog", "axis": args.axis, given[0]: True if given[0] == "stop" else getattr(args, given[0])}
        ans = _checked(args, req)
        if given[0] == "stop":
            sys.stdout.write(f"{args.axis}: jog stopping on the path\n")
            return 0
        k = _axis_index(ans, args.axis)
        sys.stdout.write(f"{args.axis}: jogging {ans['from_m'][k]:.6f} -> {ans['to_m'][k]:.6f} m in "
                         f"{ans['duration_s']:.3f} s "
                         f"(command mode{'; jog --stop ends it' if given[0] == 'velocity' else ''})\n")
        return _motion_wait(args, ans["duration_s"] * 10 + 30) if args.wait else 0
    ans = _checked(args, {"cmd": "jog", "axis": args.axis, "to_m": args.to_m, "speed": args.speed})
    if "duration_s" in ans:                  # the axis was in command mode: a move of the stream
        k = _axis_index(ans, args.axis)
        sys.stdout.write(f"{args.axis}: jogging {ans['from_m'][k]:.6f} -> {ans['to_m'][k]:.6f} m in "
                         f"{ans['duration_s']:.3f} s (command mode)\n")
        return _motion_wait(args, ans["duration_s"] * 10 + 30) if args.wait else 0
    sys.stdout.write(f"{args.axis}: jogging {ans.get('from_m', float('nan')):.6f} -> {args.to_m:.6f} m "
                     f"in {ans.get('move_s', 0.0):.3f} s"
                     + (" (recovering from outside the soft limits)" if ans.get("recovery") else "")
                     + "\n")
    st, _ = _until_disabled(args, float(ans.get("move_s", 0.0)) + float(ans.get("bound_s", 1.0)) + 1.0,
                            "finish the jog", ans.get("cycle"))
    if st["state"] == "fault":
        sys.stdout.write(f"{args.axis}: fault during the jog: {st['fault']}\n")
        return 1
    sys.stdout.write(f"{args.axis}: at {st['y_m']:.6f} m, 0 V, amplifier off\n")
    return 0


def _axis_index(ans: dict, axis: str) -> int:
    return list(ans.get("axes", [])).index(axis) if axis in ans.get("axes", []) else 0


def cmd_inject(args) -> int:
    ans = _checked(args, {"cmd": "inject", "axis": args.axis, "kind": args.kind,
                          "cycles": args.cycles, "jump_m": args.jump_m, "force_N": args.force_n})
    sys.stdout.write(f"{args.axis}: injected {args.kind} at cycle {ans.get('cycle')}\n")
    return 0


def progress_line(mo: dict) -> str:
    """The line being run, the share done and the time left (the planner's figures)."""
    return (f"line {mo['line']}  {mo['done'] * 100:5.1f} %  {mo['time_left_s']:7.2f} s left"
            + ("  (hold)" if mo["hold"] else ""))


def _motion_wait(args, timeout_s: float, progress: bool = False) -> int:
    """Until the daemon's motion is idle and every axis in command mode is within its in-position
    window (``limits.in_position_m``); the end position and why a program stopped early.
    progress: a progress line on stderr, rewritten in place (``--progress``)."""
    t0 = time.monotonic()
    while True:
        st = _checked(args, {"cmd": "status"})["status"]
        mo = st["motion"]
        if mo["idle"] and (mo["stopped_because"] or all(
                s.get("in_position", True) for s in st["axes"].values() if s["phase"] == "command")):
            break
        if progress:
            sys.stderr.write("\r" + progress_line(mo))
            sys.stderr.flush()
        if time.monotonic() - t0 > timeout_s:
            raise DaemonUnreachable(f"motion did not finish within {timeout_s:g} s")
        time.sleep(0.1 if progress else 0.02)
    if progress:
        sys.stderr.write("\r" + progress_line(mo) + "\n")
    where = ", ".join(f"{a}={s['y_m']:.6f}" for a, s in st["axes"].items() if s["phase"] == "command")
    faults = [f"{a}: {s['fault']}" for a, s in st["axes"].items() if s["fault"]]
    why = mo["stopped_because"]
    sys.stdout.write(f"done in {time.monotonic() - t0:.3f} s at {where or '-'} m"
                     + (f"; stopped early: {why}" if why else "") + "\n")
    for f in faults:
        sys.stdout.write(f"fault {f}\n")
    return 1 if (faults or why) else 0


def cmd_move(args) -> int:
    from motorctl.cli import UsageError
    targets = {}
    for word in args.targets:
        a, eq, v = word.partition("=")
        try:
            targets[a] = float(v)
        except ValueError:
            raise UsageError(f"move: {word!r}: each target is AXIS=POSITION in m, e.g. X=0.120") from None
        if not eq:
            raise UsageError(f"move: {word!r}: each target is AXIS=POSITION in m, e.g. X=0.120")
    req = {"cmd": "move", "targets": targets}
    if args.feed is not None:
        req["feed"] = args.feed
    ans = _checked(args, req)
    sys.stdout.write(f"move queued: {ans['duration_s']:.3f} s\n")
    return _motion_wait(args, ans["duration_s"] * 10 + 30) if args.wait else 0


def cmd_gcode(args) -> int:
    from motorctl.cli import UsageError
    if args.file == "-":
        text, name = sys.stdin.read(), "-"
    else:
        try:
            with open(args.file, encoding="utf-8") as fh:
                text = fh.read()
        except (OSError, UnicodeDecodeError) as exc:
            raise UsageError(f"{args.file}: cannot read: {getattr(exc, 'strerror', None) or exc}") from None
        name = args.file
    if args.from_line < 1:
        raise UsageError(f"gcode: --from-line {args.from_line}: must be a line number >= 1")
    ans = send_program(socket_path(args), text, name, from_line=args.from_line,
                       single_block=args.single_block)
    if not ans.get("ok"):
        if ans.get("usage"):
            raise UsageError(ans.get("error", "refused"))
        raise DaemonUnreachable(ans.get("error", "refused"))
    if ans.get("planning"):
        sys.stdout.write(f"{name}: {ans['segments']} segments checked, running; planned a window at a "
                         f"time ({ans['duration_s']:.3f} s in the first)\n")
    else:
        sys.stdout.write(f"{name}: {ans['segments']} segments queued, {ans['duration_s']:.3f} s at 100 %\n")
    for w in ans.get("warnings", []):
        sys.stderr.write(f"warning: {w}\n")
    if args.wait or args.progress:
        limit = 1e9 if ans.get("planning") else ans["duration_s"] * 10 + 30
        return _motion_wait(args, limit, progress=args.progress)
    return 0


def cmd_motion(args) -> int:
    req = {"cmd": args.command}
    if args.command == "override":
        req["value"] = args.value
    elif args.command == "optional-stop":
        req["value"] = args.state == "on"
    mo = _checked(args, req)["motion"]
    sys.stdout.write(f"{args.command}: queue {mo['queue_depth']}, override {mo['override']:g}, "
                     f"feed scale {mo['feed_scale']:.3f}{', holding' if mo['hold'] else ''}\n")
    return 0


def cmd_home(args) -> int:
    """``home AXIS`` or ``home --all``: every axis with a ``homing:`` section, one after the
    other in the config's order (LinuxCNC homes its joints in sequence)."""
    from motorctl.cli import UsageError
    if (args.axis is None) == (not args.all):
        raise UsageError("home: name one AXIS or give --all")
    if not args.all:
        return _home_one(args, args.axis)
    st = _checked(args, {"cmd": "status"})["status"]
    axes = [a for a, c in zip(st["axes"], st["motion"].get("homing_configured", [])) if c]
    if not axes:
        raise UsageError("home --all: no axis has a homing: section in the daemon's config")
    for a in axes:
        rc = _home_one(args, a)
        if rc:
            return rc
    return 0


def _home_one(args, axis: str) -> int:
    _checked(args, {"cmd": "home", "axis": axis})
    t0 = time.monotonic()
    names = None
    while time.monotonic() - t0 < args.timeout:
        st = _checked(args, {"cmd": "status"})["status"]
        names = names or list(st["axes"])
        state = st["motion"]["homing"][names.index(axis)]
        if state == "homed" or state.startswith("failed"):
            y = st["axes"][axis]["y_m"]
            sys.stdout.write(f"{axis}: {state} in {time.monotonic() - t0:.3f} s; at {y:.6f} m\n")
            return 0 if state == "homed" else 1
        time.sleep(0.05)
    raise DaemonUnreachable(f"homing {axis} did not finish within {args.timeout:g} s")


def cmd_wait(args) -> int:
    return _motion_wait(args, args.timeout)


def _us(x) -> str:
    return "-" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{x:.1f}"


def cmd_status(args) -> int:
    req = {"cmd": "status"}
    if args.axis:
        req["axis"] = args.axis
    st = _checked(args, req)["status"]
    if args.json:
        sys.stdout.write(json.dumps(st) + "\n")
        return 0
    from motorctl.cli import print_table
    rows = [["axis", "state", "ctrl", "y mm", "e um", "turn p50/p99/max us", "late p99/max us",
             "theta_hat", "fault"]]
    for a, s in st["axes"].items():
        tm = s["timing_since_start"]
        state = s["state"] if s["state"] != "enabled" else f"enabled/{s['phase']}"
        rows.append([a, state, s["controller"], f"{s['y_m'] * 1e3:.4f}",
                     f"{s['following_error_m'] * 1e6:.2f}" if s["state"] == "enabled" else "-",
                     f"{_us(tm['turnaround_p50_us'])}/{_us(tm['turnaround_p99_us'])}/{_us(tm['turnaround_max_us'])}",
                     f"{_us(tm['lateness_p99_us'])}/{_us(tm['lateness_max_us'])}",
                     "[" + ", ".join(f"{x:.4g}" for x in s.get("theta_hat", [])) + "]",
                     s["fault"] or "-"])
    out = sys.stdout
    print_table(rows, out)
    lp = st["loop"]
    out.write(f"loop: {lp['cycles']} cycles at {lp['rate_hz']:.0f} Hz; turnaround p50 "
              f"{_us(lp['turnaround_p50_us'])} / p99 {_us(lp['turnaround_p99_us'])} / p99.9 "
              f"{_us(lp['turnaround_p999_us'])} / max {_us(lp['turnaround_max_us'])} us; lateness p99 "
              f"{_us(lp['lateness_p99_us'])} / max {_us(lp['lateness_max_us'])} us; overruns {lp['overruns']}\n")
    mo = st.get("motion")
    if mo:
        out.write(f"motion: queue {mo['queue_depth']}, line {mo['line']} ({mo['done'] * 100:.1f} % done, "
                  f"{mo['time_left_s']:.2f} s left), feed {mo['feed_m_s'] * 1e3:.1f} mm/s, "
                  f"override {mo['override']:g}{' (hold)' if mo['hold'] else ''}; setpoints ahead "
                  f"{mo['ring_depth']}, underruns {mo['underruns']}; homed "
                  f"{', '.join(a for a, h in zip(st['axes'], mo['homed']) if h) or 'none'}"
                  + (f"; stopped early: {mo['stopped_because']}" if mo['stopped_because'] else "") + "\n")
    out.write(f"realtime: {st['realtime_summary']}\n")
    pr = st["process"]
    out.write(f"processes: loop pid {pr.get('loop_pid')} ({pr.get('python_threads')} python thread(s), "
              f"cpus {pr.get('cpu_affinity')}), I/O pid {pr.get('io_pid')}\n")
    lg = st["log"]
    out.write(f"log: {lg['path']} ({lg['rows']} rows, {lg['rows_flushed']} flushed, flush every "
              f"{lg['flush_s']:g} s, {len(lg['events'])} event log(s), {lg['lost_rows']} rows lost)\n")
    rt = lg.get("retention") or {}
    if rt:
        out.write(f"retention: {rt['bytes_per_s'] / 1e6:.2f} MB/s, {rt['kept_bytes'] / 1e6:.1f} of "
                  f"{rt['budget_bytes'] / 1e6:.0f} MB kept in {rt['kept_segments']} segment(s) and "
                  f"{rt['kept_events']} event log(s); the budget holds {rt['days_at_budget']:.2f} "
                  f"days of routine rows\n")
    return 0


def cmd_export(args) -> int:
    """A run log, or a daemon's run (its name or any segment: every kept segment in order),
    to CSV, .mat or MCAP, streamed chunk by chunk (memory bounded whatever the log length)."""
    from motorctl.inputs import InputError
    from motorctl.recorder.export import MCAP_CYCLE_TOPIC, export_csv, export_mat, export_mcap
    from motorctl.recorder.outfile import atomic_output, check_output
    from motorctl.recorder.runlog import LogError
    from motorctl.recorder.segments import open_run
    out = args.csv or args.mat or args.mcap
    if args.mcap:
        try:
            import mcap.writer  # noqa: F401
        except ImportError:
            raise InputError("export --mcap needs the mcap package: pip install 'motorctl[mcap]'") from None
    check_output(out, [args.log], "export")          # before the log is read
    run = open_run(args.log)
    check_output(out, [s.path for s in run.segments], "export")
    notes = []
    with atomic_output(out, "export") as tmp:       # renamed to `out` once complete
        if args.csv:
            n = export_csv(run, tmp)
        elif args.mcap:
            counts = export_mcap(run, tmp)
            n = counts.get(MCAP_CYCLE_TOPIC, 0)
            notes.append(", ".join(f"{t} {c}" for t, c in counts.items()))
        else:
            try:
                n, notes = export_mat(run, tmp)
            except LogError:
                raise
            except ValueError as exc:
                raise InputError(f"{args.log}: {exc}") from None
    if len(run.segments) > 1:
        notes.append(f"{len(run.segments)} segments")
    gaps = run.gaps
    if gaps:
        notes.append(f"{sum(g for _, g in gaps)} rows missing between segments (first at cycle "
                     f"{gaps[0][0]})")
    if run.truncated_bytes:
        notes.append(f"a partial last record of {run.truncated_bytes} bytes dropped")
    extra = f" ({'; '.join(notes)})" if notes else ""
    sys.stdout.write(f"{out}: {n} rows x {len(run.columns)} columns{extra}\n")
    return 0


# --------------------------------------------------------------------------- parsers
def register(parser: argparse.ArgumentParser, sub) -> None:
    """Add the daemon subcommands and the global ``--socket PATH`` option."""
    parser.add_argument("--socket", default=None, metavar="PATH",
                        help=f"the daemon's control socket (default: $MOTORCTL_SOCKET or {DEFAULT_SOCKET})")

    def client(name, help_, handler):
        p = sub.add_parser(name, help=help_)
        p.add_argument("--socket", default=argparse.SUPPRESS, metavar="PATH", help="the daemon's control socket")
        p.set_defaults(func=_wrap(handler))
        return p

    d = sub.add_parser("daemon", help="run the servo loop as a service (systemd Type=notify)")
    d.add_argument("config", help="the config YAML (its daemon section: socket, log_dir, scope)")
    d.add_argument("--socket", dest="daemon_socket", default=None, metavar="PATH",
                   help="control socket (default: daemon.socket of the config)")
    d.add_argument("--log-dir", default=None, help="run log directory (default: daemon.log_dir)")
    d.set_defaults(func=cmd_daemon)

    p = client("start", "enable an axis: bumpless approach from where it stands, then its program", cmd_start)
    p.add_argument("axis", help="the axis name, as in the config's axes")
    p.add_argument("--controller", choices=CONTROLLER_NAMES, help="controller to run (default: the current one)")
    p.add_argument("--mode", choices=("program", "command"), default="program",
                   help="program: the YAML program (default); command: hold where it stands and follow "
                        "move/gcode")

    p = client("move", "a coordinated straight move of axes in command mode (AXIS=POSITION in m)", cmd_move)
    p.add_argument("targets", nargs="+", metavar="AXIS=M", help="each axis's target position in metres, e.g. X=0.120")
    p.add_argument("--feed", type=float, default=None, metavar="M_PER_S", help="path speed limit [m/s]")
    p.add_argument("--wait", action="store_true", help="return when the motion has finished")

    p = client("gcode", "run a G-code program (FILE, or - for stdin) on the axes in command mode", cmd_gcode)
    p.add_argument("file", metavar="FILE", help="a G-code program (LinuxCNC's subset, docs/motion.md), or - for standard input")
    p.add_argument("--wait", action="store_true", help="return when the program has finished")
    p.add_argument("--progress", action="store_true",
                   help="show the line being run, the share done and the time left until it has finished")
    p.add_argument("--from-line", type=int, default=1, metavar="N",
                   help="run from line N (read from the start for the modal state; a rapid to where the "
                        "program stands at that line, the outputs as it left them, then on)")
    p.add_argument("--single-block", action="store_true",
                   help="stop after every block; 'motorctl resume' runs the next")

    client("hold", "feed hold: decelerate on the path, then hold", cmd_motion)
    client("resume", "resume after a feed hold", cmd_motion)
    client("abort", "stop on the path, hold, clear the queue", cmd_motion)
    p = client("optional-stop", "M1 pauses (on) or passes (off) from now on, the running program too",
               cmd_motion)
    p.add_argument("state", choices=("on", "off"), help="on: M1 pauses the program; off: it passes")
    p = client("override", "feed override (0.0 .. 1.5)", cmd_motion)
    p.add_argument("value", type=float, metavar="F", help="the feed override, 0.0 to 1.5 (1.0: as programmed)")
    p = client("home", "home an axis in command mode: search its switch, latch the index pulse, set "
                       "its position (axes.NAME.homing)", cmd_home)
    p.add_argument("axis", nargs="?", help="the axis to home, as in the config's axes")
    p.add_argument("--all", action="store_true", help="home every axis that has a homing: section, in turn")
    p.add_argument("--timeout", type=float, default=120.0, help="seconds per axis (default 120)")
    p = client("wait", "wait until the commanded motion has finished", cmd_wait)
    p.add_argument("--timeout", type=float, default=600.0, help="seconds (default 600)")

    p = client("stop", "bring an axis to rest, then 0 V and amplifier off", cmd_stop)
    p.add_argument("axis", help="the axis name, as in the config's axes")
    p.add_argument("--no-wait", action="store_true", help="return at once instead of waiting for rest")

    p = client("status", "state of the axes, the loop, the real-time set-up and the log", cmd_status)
    p.add_argument("axis", nargs="?", help="only this axis (default: every axis)")
    p.add_argument("--json", action="store_true", help="one JSON object")

    p = client("fault-reset", "clear an axis's latched fault (only when its cause is gone) and reset its "
                              "drive's own fault; through the daemon, or with --config and no daemon",
               cmd_fault_reset)
    p.add_argument("axis", nargs="+", help="the axis name(s), as in the config's axes")
    p.add_argument("--config", default=None, metavar="CONFIG",
                   help="no daemon: open the driver of this config, send each named drive's own fault "
                        "reset, report its state after, close (refused while a daemon answers)")

    p = client("switch", "switch an axis's controller at a cycle boundary", cmd_switch)
    p.add_argument("axis", help="the axis name, as in the config's axes")
    p.add_argument("--controller", choices=CONTROLLER_NAMES, required=True, help="the law to switch to")

    p = client("jog", "move a disabled axis to a position at reduced speed, then 0 V (also back "
                      "inside its soft limits after a soft-limit fault); an axis in command mode: "
                      "to a position, --by a distance or at --velocity until --stop", cmd_jog)
    p.add_argument("axis", help="the axis name, as in the config's axes")
    p.add_argument("to_m", type=float, nargs="?", default=None, metavar="TO_M",
                   help="target position [m], inside the soft limits")
    p.add_argument("--by", type=float, default=None, metavar="M",
                   help="command mode: move by this distance [m] (incremental jog)")
    p.add_argument("--velocity", type=float, default=None, metavar="M_PER_S",
                   help="command mode: move at this signed speed [m/s] toward the soft limit on its side "
                        "until 'jog AXIS --stop' (continuous jog)")
    p.add_argument("--stop", action="store_true", help="command mode: end a continuous jog (on the path)")
    p.add_argument("--wait", action="store_true", help="command mode: return when in position")
    p.add_argument("--speed", type=float, default=0.1,
                   help="fraction of the axis's v_max and a_max (default 0.1, at most 0.5)")

    p = client("inject", "inject a fault into the simulated driver (daemon.allow_fault_injection)", cmd_inject)
    p.add_argument("axis", help="the axis name, as in the config's axes")
    p.add_argument("kind", choices=("read_error", "nan", "amp_fault", "encoder_jump", "push"),
                   help="the fault: a failed read, a NaN reading, an amplifier fault, an encoder jump, a push")
    p.add_argument("--cycles", type=int, default=1, help="for how many cycles (default 1)")
    p.add_argument("--jump-m", type=float, default=0.0, help="encoder_jump: the jump [m]")
    p.add_argument("--force-n", type=float, default=0.0, help="push: the force on the carriage [N]")

    e = sub.add_parser("export", help="convert a run log (or a daemon's set of segments) to CSV, "
                                      "MATLAB .mat or MCAP (Foxglove, ROS 2 tools), streamed")
    e.add_argument("log", help="a run log, or a daemon run's name or any of its segments "
                               "(every kept segment is read, in order)")
    g = e.add_mutually_exclusive_group(required=True)
    g.add_argument("--csv", metavar="OUT", help="CSV: a header line of column names, then one line per recorded cycle")
    g.add_argument("--mat", metavar="OUT", help="MATLAB .mat (v5): one column vector per recorded signal, and data (N, W) where it fits")
    g.add_argument("--mcap", metavar="OUT", help="MCAP: JSON messages per axis and cycle, the header and "
                                                  "the faults as their own channels")
    e.set_defaults(func=cmd_export)
