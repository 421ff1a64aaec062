"""The ONE assembly of a servo loop from a config: driver, controllers, supervisor, programs,
loop, run-log header, start-up and shutdown. ``motorctl run`` (:mod:`motorctl.app.job`) and
the daemon (:mod:`motorctl.app.daemon`) both build through :func:`build`, so nothing about the
loop can be wired in one of them only.

Order of a run::

    asm = build(loaded, ...)          parse-only driver, controllers compiled, loop built
    report = start(asm, policy)       real-time set-up (``required`` refuses before any I/O),
                                      then driver.configure() and driver.activate()
    asm.loop.run(n)                   cycles; ``motorctl run``: cycle 0 idle (the position
                                      read), then :func:`approach_all` (every axis from where
                                      it stands to its program's start), then the programs
    checks = shutdown(asm)            0 V and amplifiers off as a transaction of its own,
                                      answered and read back by the device (one
                                      StopCheck per axis), driver closed, real-time
                                      set-up undone (on every exit path)
"""

from __future__ import annotations

import datetime as _dt
import math
import socket
from dataclasses import dataclass, field
from importlib.metadata import PackageNotFoundError, version

from motorctl.config import ConfigError, LoadedConfig
from motorctl.control import configured_controllers, controller_class, make_controller
from motorctl.inputs import InputError
from motorctl.loop.records import RecordLayout
from motorctl.loop.rt import RealtimeReport, restore, setup_realtime
from motorctl.loop.safety import Supervisor
from motorctl.loop.servo import ServoLoop
from motorctl.loop.trajectory import Move

#: run-log header format (``format`` key); readers accept this and older
LOG_FORMAT = 2


def software_version() -> str:
    """The installed motorctl version ("unknown" when not installed)."""
    try:
        return version("motorctl")
    except PackageNotFoundError:
        return "unknown"


@dataclass
class Assembly:
    """A built loop and what it was built from.

    Attributes:
        loaded: the checked config. names: axes in loop order. driver: the driver (parsed,
        not yet configured). bank: per axis, controller name → built controller (every
        configured controller when built with ``all_controllers``, else the active one).
        active: per axis, the name of the controller driving it. supervisor, programs, loop.
    """

    loaded: LoadedConfig
    names: list
    driver: object
    bank: list
    active: list
    supervisor: Supervisor
    programs: list
    loop: ServoLoop
    clock: str
    started: str = field(default_factory=lambda: _dt.datetime.now(_dt.timezone.utc)
                         .isoformat(timespec="seconds"))

    def controller(self, i: int, name: str):
        """Axis i's built controller ``name``. Raises KeyError naming the built ones."""
        try:
            return self.bank[i][name]
        except KeyError:
            raise KeyError(f"controller {name!r} is not configured for axis {self.names[i]}; "
                           f"configured: {', '.join(self.bank[i])}") from None


def record_layout(loaded: LoadedConfig, names, outputs=()) -> RecordLayout:
    """The record's layout for axes ``names`` of ``loaded``: the fixed fields and, per axis, the
    own signals (:attr:`~motorctl.control.base.Controller.own_signals`) of every law its
    ``controller:`` section configures (any of them may run: ``--controller``, a switch), then
    the machine ``outputs`` of the loop's setpoint stream (none without one)."""
    own = {}
    for a in names:
        sigs = {}
        for law in configured_controllers(loaded.axes[a].controller):
            sigs.update(controller_class(law).own_signals)
        own[a] = sigs
    return RecordLayout(names, own, outputs)


def build(loaded: LoadedConfig, axes=None, controller: str | None = None, *, clock: str,
          capacity: int, buffer=None, heartbeat=None, operated: bool = False,
          all_controllers: bool = False, stream=None) -> Assembly:
    """Build driver, controllers, supervisor and loop for ``axes`` (default: all).

    Args:
        loaded: a checked config. controller: a controller name overriding every axis's
            ``type``. clock: 'wall' | 'virtual'. capacity: record rows (a ring when shorter
            than the run). buffer, heartbeat: shared-memory ring and heartbeat (daemon).
        operated: axes start disabled and follow operator commands (daemon).
        all_controllers: build every configured controller of each axis (so a switch is a
            swap of objects built beforehand).
        stream: the setpoint ring of commanded motion (:class:`motorctl.loop.stream.SetpointRing`,
            daemon); None: a private one-row ring.
    Raises:
        ConfigError: ``controller`` is not configured for an axis.
    """
    cfg = loaded.cfg
    names = list(axes) if axes else list(loaded.axes)
    tb = loaded.timebase
    driver = loaded.make_driver(names)
    active = [controller or loaded.axes[a].controller.type for a in names]
    bank = []
    for i, a in enumerate(names):
        section = loaded.axes[a].controller
        kinds = configured_controllers(section) if all_controllers else []
        if active[i] not in kinds:
            kinds = kinds + [active[i]]
        try:
            bank.append({k: make_controller(section, k, loaded.period_s) for k in kinds})
        except ValueError as exc:
            raise ConfigError(loaded.path, f"axes.{a}.controller", str(exc)) from None
        partner = getattr(bank[i][active[i]], "partner_name", None)   # a pair law (gtcf) needs its partner
        if partner is not None and (partner not in names or partner == a):
            raise ConfigError(loaded.path, f"axes.{a}.controller.{active[i]}.partner",
                              f"{partner!r} must be another axis of this run ({', '.join(names)})")
    programs = [loaded.axes[a].trajectory.program() for a in names]
    sup = Supervisor([loaded.axes[a].limits for a in names], tb.period_s)
    lc = cfg.loop
    loop = ServoLoop(driver, [bank[i][active[i]] for i in range(len(names))], programs, sup, tb,
                     capacity=capacity, clock=clock, spin_us=lc.realtime.spin_us,
                     warm_caches=lc.realtime.warm_caches, buffer=buffer,
                     heartbeat=heartbeat, overrun_policy=lc.overrun_policy,
                     overrun_hold=lc.overrun_hold_cycles, overrun_ramp_s=lc.overrun_ramp_s,
                     stop_settle_s=cfg.daemon.stop_settle_s,
                     operated=operated, stream=stream,
                     layout=record_layout(loaded, names, stream.outputs if stream is not None else ()))
    return Assembly(loaded, names, driver, bank, active, sup, programs, loop, clock)


def stop_bound_s(program, settle_s: float = 0.0) -> float:
    """The longest a category-1 stop (:meth:`motorctl.loop.servo.ServoLoop.stop_axis`) of an
    axis following ``program`` takes [s]: its longest move (a move in progress runs on to its
    end, the next rest point) plus ``settle_s`` held at rest before 0 V."""
    return max((m.duration for m in program.moves), default=0.0) + settle_s


class StartRefused(RuntimeError):
    """A run that may not start from where its axes stand (outside the soft limits, or a
    fault latched on the first reading); nothing was driven."""


def approach_move(asm: Assembly, i: int, y: float) -> Move:
    """The approach of axis i: a jerk-limited rest-to-rest Move from where it stands, y [m],
    to its program's first point, at the axis's trajectory limits (v_max, a_max, j_max);
    the daemon's ``start`` and ``motorctl run`` both start through it."""
    tc = asm.loaded.axes[asm.names[i]].trajectory
    return Move(float(y), float(asm.programs[i].sample(0.0)[0]), tc.v_max, tc.a_max, tc.j_max, 0.0)


def _cycles_to_cover(duration: float, ts: float) -> int:
    """The fewest cycles m with m·ts ≥ duration, in the cycle's own float arithmetic
    (:func:`motorctl.loop.cycle.servo_cycle` ends an approach at (k − k_start)·Ts ≥ its
    duration)."""
    m = max(0, math.ceil(duration / ts))
    while m > 0 and (m - 1) * ts >= duration:
        m -= 1
    while m * ts < duration:
        m += 1
    return m


#: an axis stands still for a start when its reading moves slower than this between two idle
#: cycles (plus one count's worth, START_STILL_SLACK_M) [m/s]: a carriage that coasts (a run
#: that ended at speed, a device that keeps its time in lockstep with the master) is waited for
START_STILL_M_PER_S = 0.005
START_STILL_SLACK_M = 1e-6
#: the longest wait for the axes to stand still before a start is refused [s]: a carriage left
#: at speed coasts on friction alone (Y of the gantry from 2 m/s: about 5 s), and a device in
#: lockstep with the master moves it only while the master's cycles run
START_STILL_WAIT_S = 10.0


def moving_axes(asm: Assembly, y_before) -> list:
    """The axes that moved faster than :data:`START_STILL_M_PER_S` since the reading
    ``y_before`` [m] (n,) one cycle ago (names; [] when every axis stands still)."""
    bound = START_STILL_M_PER_S * asm.loop.period_s + START_STILL_SLACK_M
    return [a for i, a in enumerate(asm.names) if not abs(float(asm.driver.position_m[i]) - y_before[i]) <= bound]


def approach_all(asm: Assembly) -> tuple[int, list]:
    """Between cycles, after at least one idle cycle read every axis (``motorctl run``): every
    axis starts its :func:`approach_move` from the position read, the shorter approaches held
    at their start so that every approach ends in the same cycle and every program starts in
    the next one (the axes of a gantry keep their programs' timing).

    Returns:
        (the cycle the programs start at, the approaches (Move) in axis order).
    Raises:
        StartRefused: an axis stands outside its soft limits or has a latched fault; no
        axis was started.
    """
    loop, sup, drv = asm.loop, asm.supervisor, asm.driver
    ys = [float(drv.position_m[i]) for i in range(len(asm.names))]
    bad = []
    for i, a in enumerate(asm.names):
        lo, hi = asm.loaded.axes[a].limits.soft_min_m, asm.loaded.axes[a].limits.soft_max_m
        if not sup.stands_inside(i, ys[i]):
            bad.append(f"axis {a} stands at {ys[i]:.6f} m, outside its soft limits [{lo:g}, {hi:g}] m "
                       f"(jog it back inside with the daemon's 'motorctl jog')")
        elif sup.fault[i]:
            bad.append(f"axis {a} faulted on its first reading: {sup.reason(i)}")
    if bad:
        raise StartRefused("; ".join(bad) + "; nothing was driven")
    moves = [approach_move(asm, i, y) for i, y in enumerate(ys)]
    cover = [_cycles_to_cover(mv.duration, loop.period_s) for mv in moves]
    n = max(cover)
    k0 = loop.k
    for i, mv in enumerate(moves):
        loop.start_axis(i, mv, delay_cycles=n - cover[i])
    return k0 + n + 1, moves


def start(asm: Assembly, policy: str) -> RealtimeReport:
    """Real-time set-up (``policy`` 'off' | 'best_effort' | 'required'), then configure and
    activate the driver. With ``required`` a refusal raises before the driver is touched.

    Raises:
        RealtimeError: ``required`` and a step was refused. InputError: a driver setting this
        machine contradicts (e.g. no such network interface), prefixed with the file. OSError: the device cannot be
        reached (the driver is closed and the real-time set-up undone first).
    """
    rt = asm.loaded.cfg.loop.realtime
    report = setup_realtime(policy, rt.priority, rt.cpu, rt.lock_memory, rt.lock_pages,
                            rt.cpu_latency_us)
    try:
        try:
            asm.driver.configure()
            asm.driver.activate()
        except InputError as exc:       # a driver setting the machine contradicts: name the file
            raise InputError(f"{asm.loaded.path}: {exc}") from None
    except BaseException:
        try:
            asm.driver.close()          # whatever part of the transport was opened
        finally:
            restore()
        raise
    return report


def shutdown(asm: Assembly) -> list:
    """0 V with every amplifier disabled, confirmed by the device
    (:meth:`motorctl.driver.Driver.deactivate`), the driver closed, the real-time set-up
    undone. Safe on every exit path and idempotent.

    Returns:
        the :class:`~motorctl.driver.StopCheck` of every axis (those of the last stop when the
        driver was not active).
    """
    checks = []
    try:
        checks = asm.driver.deactivate()
    finally:
        try:
            asm.driver.close()
        finally:
            restore()
    return checks


def stop_lines(checks) -> tuple[bool, list[str]]:
    """The operator's report of a stop: (every axis confirmed, lines). One line when every
    axis is confirmed ("X, Y at 0 V, amplifiers off (confirmed by the device: ...)"), else one
    line per axis that is not, naming what was read back."""
    if not checks:
        return False, ["the stop was not confirmed: the driver was not active"]
    bad = [c for c in checks if not c.confirmed]
    if not bad:
        return True, [f"{', '.join(c.axis for c in checks)} at 0 V, amplifiers off (confirmed by the device: "
                      + "; ".join(f"{c.axis} {c.held}" for c in checks) + ")"]
    return False, [f"axis {c.axis}: the stop is NOT confirmed by the device: {c.held}; the amplifier may still "
                   f"be energised" for c in bad]


def rest_words(rest: dict) -> str:
    """Where each axis ended, for the stop line: ``rest`` maps an axis name to
    ``{"at_m": its last reading [m], "category": 1 | 0}`` (IEC 60204-1 §9.2.2: 1, brought to
    rest under control, then 0 V; 0, the power removed at once: it may have coasted on, the
    reading is the last one before 0 V). E.g. "came to rest at X 0.400000 m, Y 0.000000 m
    (stop category 1)"."""
    parts = []
    for cat, what in ((1, "came to rest at"), (0, "power removed at once (stop category 0) at")):
        axes = [f"{a} {r['at_m']:.6f} m" for a, r in rest.items() if r["category"] == cat]
        if axes:
            parts.append(f"{what} {', '.join(axes)}" + (" (stop category 1)" if cat == 1 else ""))
    return "; ".join(parts)


def run_cycles(asm: Assembly, n_cycles: int, policy: str = "off"):
    """:func:`start`, ``n_cycles`` cycles, :func:`shutdown` on every exit path (tools, tests
    and benchmarks on the virtual clock). Returns (the loop's rows (n, width), its
    :class:`~motorctl.loop.records.RecordLayout`).

    Raises:
        as :func:`start`.
    """
    start(asm, policy)
    try:
        asm.loop.run(int(n_cycles))
    finally:
        shutdown(asm)
    return asm.loop.rows(), asm.loop.layout


def log_header(asm: Assembly, **extra) -> dict:
    """The run-log header (the one place it is built): software, config, axes, controllers,
    period, clock, record layout (columns and units), the driver's facts; ``extra`` adds or
    overrides keys (e.g. ``kind``, ``realtime``)."""
    loaded = asm.loaded
    header = {
        "format": LOG_FORMAT,
        "software": f"motorctl {software_version()}",
        "started": asm.started,
        "machine_id": loaded.cfg.machine_id or socket.gethostname(),
        "config_file": str(loaded.path),
        "config": loaded.cfg.model_dump(mode="json"),
        "driver_type": loaded.cfg.driver.type,
        "axes": list(asm.names),
        "controllers": {a: asm.active[i] for i, a in enumerate(asm.names)},
        "period_s": loaded.period_s,
        "clock": asm.clock,
        **asm.loop.layout.header(),
        "driver": asm.driver.describe(),
    }
    header.update(extra)
    return header
