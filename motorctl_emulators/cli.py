"""``motorctl emulate``: the gantry I/O emulator, the device side of a bus driver in its own process.

It reads the same YAML as the driver (``driver.type`` must be the ``--transport``): the device
settings from ``driver:``, the plant of every axis from ``axes.NAME.driver.plant`` (a
:class:`motorctl_drivers.sim.SimAxisOptions`, the sim driver's per-axis plant) and seed,
substeps, watchdog and injected faults from ``driver.emulator``. The plant advances one loop
period (``1/loop.rate_hz``) per valid command it receives, as an encoder-counter plus
amplifier-input module paced by its master would; with the same plant and seed a run through
the emulator meets the same plant as a run on the sim driver.

Watchdog: no valid command for ``driver.emulator.watchdog_s`` → 0 V and an amplifier fault
(reported in every reply, latched until a command with the amplifier disabled).

Fault injection: ``--fault KIND[:AXIS[:START[:COUNT]]]`` (repeatable; also
``driver.emulator.faults``), KIND one of drop, late, corrupt, stale, exception, disconnect,
bus_off; START counts the command frames the device has received (0-based).

The first line on stdout is ``ready: ...`` once the device listens. SIGTERM/SIGINT end it.
"""

from __future__ import annotations

import signal
import sys

TRANSPORTS = ("can", "serial", "modbus")


def build_device(loaded, faults=()):
    """The device object (``.serve(stop, duration_s)``, ``.bank``) for a checked config."""
    from motorctl_drivers.proto_common import PlantBank
    dtype = loaded.cfg.driver.type
    names = list(loaded.axes)
    missing = [a for a in names if getattr(loaded.axis_driver_options[a], "plant", None) is None]
    if missing:
        raise ValueError(f"axes {', '.join(missing)} have no driver.plant section: the emulator "
                         f"needs the plant of every axis")
    bank = PlantBank(names, [loaded.axis_driver_options[a].plant for a in names], loaded.period_s,
                     loaded.driver_options.emulator, list(faults))
    if dtype == "serial":
        from motorctl_drivers.serial_link import SerialDevice
        return SerialDevice(loaded.driver_options, loaded.axis_driver_options, bank)
    if dtype == "can":
        from motorctl_drivers.can_bus import CanDevice
        return CanDevice(loaded.driver_options, loaded.axis_driver_options, bank)
    if dtype == "modbus":
        from motorctl_drivers.modbus import ModbusDevice
        return ModbusDevice(loaded.driver_options, loaded.axis_driver_options, bank)
    raise ValueError(f"driver type {dtype!r} has no emulator; emulated: {', '.join(TRANSPORTS)}")


def cmd_emulate(args) -> int:
    from motorctl.cli import UsageError
    from motorctl.config import ConfigError, load_config
    from motorctl_drivers.proto_common import FaultSpec
    try:
        loaded = load_config(args.config, check_budget=False)
    except ConfigError as exc:
        raise UsageError(str(exc)) from None
    if loaded.cfg.driver.type != args.transport:
        raise UsageError(f"{args.config}: driver.type is {loaded.cfg.driver.type!r}, "
                         f"not the --transport {args.transport!r}")
    try:
        faults = [FaultSpec.parse(f) for f in args.fault or ()]
        dev = build_device(loaded, faults)
    except (ValueError, OSError) as exc:
        raise UsageError(f"{args.config}: {exc}") from None
    rt = "SCHED_OTHER"
    if args.priority > 0:
        import os
        try:  # the emulator stands in for hardware: let the machine's load not delay it
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(args.priority))
            rt = f"SCHED_FIFO {args.priority}"
        except (OSError, AttributeError) as exc:
            rt = f"SCHED_OTHER (SCHED_FIFO refused: {exc})"
    import gc
    gc.collect()
    gc.freeze()     # no collector pauses while serving (the frames are freed by reference counting)
    gc.disable()
    stop = []
    for s in (signal.SIGTERM, signal.SIGINT):
        signal.signal(s, lambda signum, _f: stop.append(signum))
    b = dev.bank
    sys.stdout.write(f"ready: {args.transport} emulator, axes {', '.join(b.names)}, "
                     f"{1 / loaded.period_s:g} Hz plant period, watchdog "
                     f"{b.opts.watchdog_s * 1e3:g} ms, {len(b.faults)} faults scheduled, {rt}\n")
    sys.stdout.flush()
    dev.serve(stop=lambda: bool(stop), duration_s=args.duration)
    sys.stdout.write(f"stopped: commands {dict(zip(b.names, b.commands))}, "
                     f"applied_V {dict(zip(b.names, b.applied_V))}, "
                     f"amp_fault {dict(zip(b.names, b.amp_fault))}, "
                     f"watchdog trips {b.watchdog_trips}\n")
    sys.stdout.flush()
    return 0


def register(parser, subparsers) -> None:
    """Add the ``emulate`` subcommand to the motorctl CLI."""
    e = subparsers.add_parser("emulate", help="run the gantry I/O emulator (device side of a bus driver)")
    e.add_argument("--transport", required=True, choices=TRANSPORTS)
    e.add_argument("config", help="the driver's YAML (plant under axes.NAME.driver.plant)")
    e.add_argument("--fault", action="append", metavar="KIND[:AXIS[:START[:COUNT]]]",
                   help="inject a fault (repeatable): drop, late, corrupt, stale, exception, "
                        "disconnect, bus_off")
    e.add_argument("--duration", type=float, help="stop after this many seconds")
    e.add_argument("--priority", type=int, default=90,
                   help="SCHED_FIFO priority of the emulator (0: normal scheduling); default 90, above the "
                        "loop's 80: it stands in for hardware, which never waits for the host")
    e.set_defaults(func=cmd_emulate)
