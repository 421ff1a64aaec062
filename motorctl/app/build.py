"""The ONE assembly of a servo loop from a config: driver, controllers, supervisor, programs,
loop, run-log header, start-up and shutdown. ``motorctl run`` (:mod:`motorctl.app.job`) and
the daemon (:mod:`motorctl.app.daemon`) both build through :func:`build`, so nothing about the
loop can be wired in one of them only.

Order of a run::

    asm = build(loaded, ...)          parse-only driver, controllers compiled, loop built
    report = start(asm, policy)       real-time set-up (``required`` refuses before any I/O),
                                      then driver.configure() and driver.activate()
    asm.loop.run(n)                   cycles
    checks = shutdown(asm)            0 V and amplifiers off as a transaction of its own,
                                      answered and read back by the device (one
                                      StopCheck per axis), driver closed, real-time
                                      set-up undone (on every exit path)
"""

from __future__ import annotations

import datetime as _dt
from dataclasses import dataclass, field
from importlib.metadata import PackageNotFoundError, version

from motorctl.config import LoadedConfig
from motorctl.control import configured_controllers
from motorctl.loop.rt import RealtimeReport, restore, setup_realtime
from motorctl.loop.safety import Supervisor
from motorctl.loop.servo import ServoLoop

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
        built = {}
        for k in kinds:
            built[k] = loaded.make_controllers([a], k)[0]
        bank.append(built)
    programs = [loaded.axes[a].trajectory.program() for a in names]
    sup = Supervisor([loaded.axes[a].limits for a in names], tb.period_s)
    lc = cfg.loop
    loop = ServoLoop(driver, [bank[i][active[i]] for i in range(len(names))], programs, sup, tb,
                     capacity=capacity, clock=clock, spin_us=lc.realtime.spin_us,
                     warm_caches=lc.realtime.warm_caches, buffer=buffer,
                     heartbeat=heartbeat, overrun_policy=lc.overrun_policy,
                     overrun_hold=lc.overrun_hold_cycles, overrun_ramp_s=lc.overrun_ramp_s,
                     stop_settle_s=cfg.daemon.stop_settle_s if operated else 0.0,
                     operated=operated, stream=stream)
    return Assembly(loaded, names, driver, bank, active, sup, programs, loop, clock)


def start(asm: Assembly, policy: str) -> RealtimeReport:
    """Real-time set-up (``policy`` 'off' | 'best_effort' | 'required'), then configure and
    activate the driver. With ``required`` a refusal raises before the driver is touched.

    Raises:
        RealtimeError: ``required`` and a step was refused. OSError: the device cannot be
        reached (the driver is closed and the real-time set-up undone first).
    """
    rt = asm.loaded.cfg.loop.realtime
    report = setup_realtime(policy, rt.priority, rt.cpu, rt.lock_memory, rt.lock_pages,
                            rt.cpu_latency_us)
    try:
        asm.driver.configure()
        asm.driver.activate()
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
