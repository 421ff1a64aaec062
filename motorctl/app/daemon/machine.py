"""The daemon's machine state: one table that every request, fault and helper event goes through.

The field's models, as this daemon maps them:

* **PackML** (ISA-TR88.00.02) for the machine's commanded motion (the axes in command mode,
  which follow the setpoint stream together): ``STOPPED`` (no axis in command mode, none
  faulted; an axis may run its own program, a per-axis state), ``IDLE`` (axes in command mode,
  nothing commanded), ``EXECUTE`` (a G-code program, a move, a jog or homing runs), ``HELD`` (a feed hold, a programmed pause M0/M1, or a pause after an underrun:
  the motion is kept, ``resume`` goes on), ``ABORTING`` (an abort, a stop or a fault is bringing
  the commanded motion to rest: the queue dropped, the setpoint ring drained), ``ABORTED`` (a
  fault is latched on an axis: nothing moves until ``fault-reset``), ``STOPPING`` (an axis's
  ``stop`` or the signal's category-1 stop runs).
* **CiA 402** for each axis (:func:`axis_state`): ``switch_on_disabled`` (0 V, amplifier off),
  ``operation_enabled`` (its own program, an approach or a jog), ``command`` (operation enabled,
  following the setpoint stream), ``quick_stop_active`` (a stop's brake), ``fault``.
* **LinuxCNC's task/motion split**: the I/O process is *task* (it takes requests, plans, and
  keeps this table), the loop process is *motion* (it applies what task sends at a cycle
  boundary, and on a fault puts the axis at 0 V with its amplifier off in that cycle and drains
  the setpoint ring; :mod:`motorctl.app.daemon.loop_side`).

The machine state is not a variable that can drift from the truth: :func:`machine_state`
computes it from what the loop published (each axis's mode and latched fault bits) and from the
motion side (queue, hold, abort, pause, homing), at every request and every wake of the I/O
process. What the table decides is which request is accepted in which state
(:data:`ACCEPTS`, :func:`refusal`) and what every event does (:data:`REACTIONS`): a fault, an
abort and a stop all end in the state the table names, with the ring drained, ``idle`` true and
every waiter answered with the cause. ``docs/daemon.md`` shows the same table and diagram
(a test compares them).
"""

from __future__ import annotations

import enum
from dataclasses import dataclass


class MachineState(str, enum.Enum):
    """PackML's machine states as this daemon has them (module docstring)."""

    STOPPED = "stopped"
    IDLE = "idle"
    EXECUTE = "execute"
    HELD = "held"
    ABORTING = "aborting"
    ABORTED = "aborted"
    STOPPING = "stopping"


#: the per-axis states (CiA 402's drive state machine names) by the loop's sequencing mode name
#: (:data:`motorctl.loop.servo.MODE_NAMES`)
AXIS_STATES = {"disabled": "switch_on_disabled", "approach": "operation_enabled",
               "tracking": "operation_enabled", "jog": "operation_enabled",
               "command": "command", "stopping": "quick_stop_active"}

#: every request of the control socket the table rules on: ``jog`` is a jog of an axis in command
#: mode (a move of the stream), ``jog-disabled`` one of a disabled axis (the loop's own jog, also
#: the way back inside the soft limits after a soft-limit fault)
REQUESTS = ("start", "stop", "switch", "fault-reset", "move", "gcode", "jog", "jog-disabled", "home",
            "hold", "resume", "abort", "override", "optional-stop")

_S = MachineState
#: which request each state accepts; a request not listed is refused with :func:`refusal`'s line.
#: Requests not ruled here (``status``, ``upload``, ``inject``) are accepted in every state;
#: ``start``, ``stop``, ``switch``, ``fault-reset`` are further checked per axis by the loop
#: (the one place that sees the live state).
ACCEPTS: dict[MachineState, frozenset] = {
    _S.STOPPED: frozenset({"start", "stop", "switch", "fault-reset", "jog-disabled", "hold", "abort",
                           "override", "optional-stop"}),
    _S.IDLE: frozenset({"start", "stop", "switch", "fault-reset", "move", "gcode", "jog",
                        "jog-disabled", "home", "hold", "resume", "abort", "override", "optional-stop"}),
    _S.EXECUTE: frozenset({"start", "stop", "switch", "fault-reset", "move", "gcode", "jog-disabled",
                           "hold", "resume", "abort", "override", "optional-stop"}),
    _S.HELD: frozenset({"start", "stop", "switch", "fault-reset", "jog-disabled", "hold", "resume",
                        "abort", "override", "optional-stop"}),
    _S.ABORTING: frozenset({"stop", "switch", "fault-reset", "abort", "override", "optional-stop"}),
    _S.ABORTED: frozenset({"start", "stop", "switch", "fault-reset", "jog-disabled", "abort",
                           "override", "optional-stop"}),
    _S.STOPPING: frozenset({"start", "stop", "switch", "fault-reset", "jog-disabled", "abort",
                            "override", "optional-stop"}),
}

#: what each event does, and the state it ends in (the docs' transition table)
REACTIONS: tuple[tuple[str, str, str, MachineState], ...] = (
    ("start AXIS --mode command", "STOPPED, IDLE, ABORTED (another axis)",
     "the axis holds where it stands; the setpoint ring is emptied when no other axis follows it",
     _S.IDLE),
    ("move / gcode / jog / home", "IDLE (move, gcode: EXECUTE too, queued after what runs)",
     "planned off the loop, streamed", _S.EXECUTE),
    ("hold, M0/M1, an underrun", "EXECUTE", "the feed scale ramps to 0 on the path (an underrun: the "
     "loop brakes on its own); the motion is kept", _S.HELD),
    ("resume", "HELD", "back onto the path where it stopped, the feed ramps up", _S.EXECUTE),
    ("the motion's end", "EXECUTE", "the queue is empty, the ring drained", _S.IDLE),
    ("abort", "any", "feed hold on the path, then the queue, the program being planned and homing are "
     "dropped; the ring holds only the stop", _S.ABORTING),
    ("the abort's rest", "ABORTING", "the ring drained, idle true, stopped_because 'aborted'", _S.IDLE),
    ("a fault on any axis", "any", "that axis 0 V and amplifier off in the cycle it is seen; the loop "
     "drains the ring and the other command-mode axes brake to rest (category 1); the queue, the "
     "program being planned and homing are dropped; every waiter is answered with the cause",
     _S.ABORTED),
    ("fault-reset AXIS", "ABORTED", "refused while the cause persists; the drive's own fault is "
     "reset only by this command", _S.STOPPED),
    ("stop AXIS", "any", "the axis comes to rest on its profile (category 1), then 0 V, amplifier "
     "off; commanded motion that moves it is dropped", _S.STOPPING),
    ("a helper dies (view, metrics, OPC UA, planner)", "any", "named in status and the journal, "
     "started again (bounded); the loop and the recorder go on", None),
)


@dataclass(frozen=True)
class Observed:
    """What the machine state is computed from (the I/O process's view at one instant).

    Attributes:
        modes: (n,) each axis's sequencing mode name (``MODE_NAMES``' values).
        faults: (n,) each axis's latched fault line ('' when none).
        busy: commanded motion is queued, streamed, being planned, or homing runs.
        held: the commanded motion is held (a feed hold, M0/M1, an underrun's pause).
        aborting: an abort is bringing the commanded motion to rest.
        ring_depth: setpoint rows not yet taken by the loop. braking: the loop's stream brake runs.
    """

    modes: tuple
    faults: tuple
    busy: bool
    held: bool
    aborting: bool
    ring_depth: int = 0
    braking: bool = False


def axis_state(mode: str, fault: str) -> str:
    """One axis's CiA 402 state name from its mode name and fault line."""
    return "fault" if fault else AXIS_STATES.get(mode, "switch_on_disabled")


def machine_state(ob: Observed) -> MachineState:
    """The machine's PackML state (module docstring) from what is observed now."""
    if any(ob.faults):
        # the commanded motion is still coming to rest (the other axes' brake, the ring) or not
        return _S.ABORTING if (ob.busy or ob.braking or ob.ring_depth) and any(
            m == "command" for m, f in zip(ob.modes, ob.faults) if not f) else _S.ABORTED
    if ob.aborting:
        return _S.ABORTING
    if any(m == "stopping" for m in ob.modes):
        return _S.STOPPING
    if ob.held and ob.busy:
        return _S.HELD
    if ob.busy:
        return _S.EXECUTE
    if not any(m == "command" for m in ob.modes):
        return _S.STOPPED
    return _S.IDLE


def refusal(state: MachineState, request: str, ob: Observed | None = None, names=()) -> str:
    """'' when ``state`` accepts ``request`` (:data:`ACCEPTS`), else the one line of the refusal:
    the state, why, and the command that gets out of it."""
    if request not in REQUESTS or request in ACCEPTS[state]:
        return ""
    if state is _S.ABORTED:
        faulted = [(a, f) for a, f in zip(names, ob.faults) if f] if ob is not None else []
        what = "; ".join(f"{a}: {f}" for a, f in faulted) or "an axis is faulted"
        first = faulted[0][0] if faulted else "AXIS"
        return (f"{request}: refused in state aborted ({what}); run 'motorctl fault-reset {first}' "
                f"and start the axis again")
    why = {
        _S.STOPPED: "no axis is enabled; run 'motorctl start AXIS --mode command' first",
        _S.IDLE: "nothing is held or running",
        _S.EXECUTE: "motion is running; wait for it, or hold / abort it",
        _S.HELD: "the motion is held; resume or abort it first",
        _S.ABORTING: "an abort or a fault is bringing the motion to rest; retry when it is idle",
        _S.STOPPING: "an axis is stopping; retry when it has stopped",
    }[state]
    return f"{request}: refused in state {state.value} ({why})"


def table_markdown() -> str:
    """The request table (:data:`ACCEPTS`) as the markdown rows of ``docs/daemon.md``."""
    states = list(MachineState)
    head = "| request | " + " | ".join(s.value for s in states) + " |\n"
    head += "| --- |" + " --- |" * len(states) + "\n"
    rows = "".join(f"| {r} | " + " | ".join("yes" if r in ACCEPTS[s] else "-" for s in states) + " |\n"
                   for r in REQUESTS)
    return head + rows


__all__ = ["ACCEPTS", "AXIS_STATES", "MachineState", "Observed", "REACTIONS",
           "REQUESTS", "axis_state", "machine_state", "refusal", "table_markdown"]
