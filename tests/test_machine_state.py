"""The daemon's state machine (motorctl/app/daemon/machine.py) on its own: the state computed from
what is observed, the refusals, and docs/daemon.md's table being the module's. The daemon driven
through it, with faults injected: tests/test_daemon_stateful.py."""

from __future__ import annotations

from pathlib import Path

import pytest

from motorctl.app.daemon.machine import (ACCEPTS, REQUESTS, MachineState, Observed, axis_state,
                                         machine_state, refusal, table_markdown)

S = MachineState


def ob(modes=("command", "command"), faults=("", ""), busy=False, held=False, aborting=False,
       depth=0, braking=False):
    return Observed(tuple(modes), tuple(faults), busy, held, aborting, depth, braking)


@pytest.mark.parametrize("o, state", [
    (ob(modes=("disabled", "disabled")), S.STOPPED),
    (ob(modes=("tracking", "disabled")), S.STOPPED),        # an axis's own program: per axis
    (ob(), S.IDLE),
    (ob(busy=True), S.EXECUTE),
    (ob(busy=True, held=True), S.HELD),
    (ob(held=True), S.IDLE),                                 # a hold with nothing to hold
    (ob(busy=True, aborting=True), S.ABORTING),
    (ob(modes=("stopping", "command")), S.STOPPING),
    (ob(modes=("disabled", "command"), faults=("following error", "")), S.ABORTED),
    (ob(modes=("disabled", "command"), faults=("following error", ""), braking=True), S.ABORTING),
    (ob(modes=("disabled", "disabled"), faults=("x", "y"), depth=625, busy=True), S.ABORTED),
])
def test_the_state_follows_what_is_observed(o, state):
    assert machine_state(o) is state


def test_a_faulted_machine_refuses_motion_and_names_the_way_out():
    o = ob(modes=("disabled", "disabled"), faults=("following error (value 0.003, limit 0.001)",
                                                   "recorder: recorder stalled"))
    st = machine_state(o)
    assert st is S.ABORTED
    for req in ("resume", "move", "gcode", "jog", "home"):
        line = refusal(st, req, o, ("X", "Y"))
        assert line.startswith(f"{req}: refused in state aborted")
        assert "X: following error" in line and "motorctl fault-reset X" in line
    for req in ("abort", "fault-reset", "stop", "status", "upload"):
        assert refusal(st, req, o, ("X", "Y")) == ""


def test_abort_stop_and_fault_reset_are_accepted_in_every_state():
    for st in MachineState:
        for req in ("abort", "stop", "fault-reset"):
            assert req in ACCEPTS[st]
        assert set(ACCEPTS[st]) <= set(REQUESTS)


def test_no_motion_is_accepted_unless_idle_or_running():
    for st in (S.STOPPED, S.HELD, S.ABORTING, S.ABORTED, S.STOPPING):
        for req in ("move", "gcode", "jog", "home"):
            assert req not in ACCEPTS[st], (st, req)


def test_axis_states_are_cia402s():
    assert axis_state("disabled", "") == "switch_on_disabled"
    assert axis_state("command", "") == "command"
    assert axis_state("tracking", "") == "operation_enabled"
    assert axis_state("stopping", "") == "quick_stop_active"
    assert axis_state("command", "soft limit") == "fault"


def test_the_docs_table_is_the_modules():
    doc = (Path(__file__).resolve().parents[1] / "docs" / "daemon.md").read_text(encoding="utf-8")
    assert table_markdown() in doc
