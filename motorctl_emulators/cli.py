"""``motorctl emulate``: the gantry I/O emulator, the device side of a bus driver in its own process.

    motorctl emulate --transport can|canopen|ethercat|serial|modbus CONFIG [--plant PLANT] [--watchdog S]
                     [--late S] [--fault KIND[:AXIS[:START[:COUNT]]]] [--duration S] [--priority N]

CONFIG is the driver's own YAML (``driver.type`` must be the ``--transport``): the device
listens where the driver connects and decodes its layout. PLANT is a simulated-gantry config
(default ``configs/gantry.yaml``, the one ``motorctl run`` uses): its ``driver:`` section (type
``sim``) gives seed, substeps and the watchdog, its ``axes.NAME.driver`` the plant of each axis
of CONFIG. The plant advances one loop period of CONFIG (``1/loop.rate_hz``) per valid command,
as an encoder-counter plus amplifier-input module paced by its master would; a run through the
emulator meets the same plant and noise as a run of PLANT's sim driver at that rate.

Watchdog: no valid command for ``--watchdog`` seconds (default: PLANT's ``driver.watchdog_s``
when > 0, else 0.05 s) → 0 V and an amplifier fault (reported in every answer, latched until the
device's reset: serial and CAN revision 2, a Modbus map's ``fault_reset``: the reset request's
rising edge with the amplifier disabled; otherwise a command with the amplifier disabled).

Fault injection: ``--fault KIND[:AXIS[:START[:COUNT]]]`` (repeatable), KIND one of drop, late
(answer after ``--late`` seconds and never before the host's next command to that device,
CANopen: the next SYNC; so it misses its cycle, and comes in a burst with the next answer),
corrupt, stale, exception, disconnect, bus_off, emcy[=CODE] (CANopen: the drive faults with
that EMCY error code); START counts the command frames the
device has received (CANopen: SYNCs; 0-based). A CANopen drive's watchdog is its heartbeat
consumer, set by the host (0x1016); ``--watchdog`` does not apply to it.

The first line on stdout is ``ready: ...`` once the device listens. SIGTERM/SIGINT end it with
a ``stopped: ...`` line. The device classes come from the ``motorctl.emulators`` entry points.
"""

from __future__ import annotations

import argparse
import signal
import sys
from importlib.metadata import entry_points

from motorctl.inputs import seconds_arg

#: the entry-point group of the emulated devices (motorctl_emulators.device.ENTRY_POINT_GROUP;
#: read here without importing the devices, so that the parser of every command stays light)
_DEVICES = "motorctl.emulators"

#: PLANT when ``--plant`` is not given (relative to the working directory, as ``motorctl run``'s CONFIG)
DEFAULT_PLANT = "configs/gantry.yaml"


def _fault(text: str):
    from motorctl_emulators.plant_bank import FaultSpec
    try:
        return FaultSpec.parse(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def cmd_emulate(args) -> int:
    from motorctl.config import ConfigError, load_config
    loaded = load_config(args.config, check_budget=False)
    if loaded.cfg.driver.type != args.transport:
        raise ConfigError(args.config, "driver.type", f"{loaded.cfg.driver.type!r} is not the "
                          f"--transport {args.transport!r}")
    try:
        from motorctl_emulators.device import build_device
        from motorctl_emulators.plant_bank import DEFAULT_LATE_S
        dev = build_device(loaded, args.plant, watchdog_s=args.watchdog,
                           late_s=DEFAULT_LATE_S if args.late is None else args.late,
                           faults=args.fault or ())
    except ConfigError:
        raise
    except ValueError as exc:     # a fault on an unknown axis, a layout the device cannot serve
        raise ConfigError(args.config, "", str(exc)) from None
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
    sys.stdout.write(f"ready: {args.transport} emulator, axes {', '.join(b.names)}, plant {args.plant}, "
                     f"{1 / loaded.period_s:g} Hz plant period, watchdog "
                     f"{b.watchdog_s * 1e3:g} ms, {len(b.faults)} faults scheduled, {rt}\n")
    sys.stdout.flush()
    dev.serve(stop=lambda: bool(stop), duration_s=args.duration)
    sys.stdout.write(f"stopped: commands {dict(zip(b.names, b.commands))}, "
                     f"applied_V {dict(zip(b.names, b.applied_V))}, "
                     f"amp_fault {dict(zip(b.names, b.amp_fault))}, "
                     f"watchdog trips {b.watchdog_trips}\n")
    sys.stdout.flush()
    return 0


def register(parser, subparsers) -> None:
    """Add the ``emulate`` subcommand to the motorctl CLI (entry point ``motorctl.commands``)."""
    e = subparsers.add_parser("emulate", help="run the gantry I/O emulator (device side of a bus driver)",
                              description=__doc__.split("\n\n")[2].replace("``", ""))
    e.add_argument("--transport", required=True, choices=sorted(ep.name for ep in entry_points(group=_DEVICES)),
                   help="the protocol of the device side (the driver.type of CONFIG)")
    e.add_argument("config", help="the bus driver's YAML (driver.type = --transport)")
    e.add_argument("--plant", default=DEFAULT_PLANT,
                   help=f"simulated-gantry config giving the plant of each axis, seed, substeps and "
                        f"watchdog (driver.type: sim); default {DEFAULT_PLANT}")
    e.add_argument("--watchdog", type=seconds_arg, metavar="S",
                   help="command watchdog [s]; default: the plant config's driver.watchdog_s, else 0.05")
    e.add_argument("--late", type=seconds_arg, default=None, metavar="S",
                   help="delay of a 'late' answer [s]; default: the plant bank's DEFAULT_LATE_S (2 ms)")
    e.add_argument("--fault", type=_fault, action="append", metavar="KIND[:AXIS[:START[:COUNT]]]",
                   help="inject a fault (repeatable): drop, late, corrupt, stale, exception, "
                        "disconnect, bus_off, emcy[=CODE] (CANopen)")
    e.add_argument("--duration", type=seconds_arg, metavar="S", help="stop after this many seconds")
    e.add_argument("--priority", type=int, default=90,
                   help="SCHED_FIFO priority of the emulator (0: normal scheduling); default 90, above the "
                        "loop's 80: it stands in for hardware, which never waits for the host")
    e.set_defaults(func=cmd_emulate)
