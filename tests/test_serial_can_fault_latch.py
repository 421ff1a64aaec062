"""A fault the device latched stays latched across runs on the serial and CAN buses, reset only by
the operator (revision 2 of docs/serial-protocol.md and of the CAN frames, docs/drivers.md "CAN").

Each driver against its emulated device in a thread of this process (serial over a pty, CAN on
python-can's ``virtual`` bus; the helpers of tests/test_drivers_inprocess.py), as the CANopen
tests do (tests/test_canopen.py, whose daemon-side helpers are reused here). The fault is latched
by the device's command watchdog: a host falls silent while both axes drive, then its stop
comes (enable 0, no reset). Then: ``motorctl run`` (``run_job``) is refused naming each
channel's status and the command that clears it, the device still latched; ``motorctl
fault-reset --config CFG X`` (``reset_drive_faults``) clears X alone, then Y; a run works. The
daemon's ``fault-reset`` (the loop's ``begin_fault_reset`` / ``poll_fault_reset`` between cycles)
likewise. A device playing revision 1 is named as such at set-up.
"""

from __future__ import annotations

import contextlib
import sys

import pytest
import yaml
from test_drivers_inprocess import ANSWER_WAIT_S, _config, _serving

from harness import exchange, wait_for
from motorctl.config import config_from_dict
from motorctl_drivers.split_phase import SplitPhaseDriver

AXES = ("X", "Y")
#: the runs' duration [s] (lockstep at 1 kHz: 50 cycles of the program)
RUN_S = 0.05


def _words(transport: str, channel: str, axis: str, fault: bool) -> str:
    """What the driver says of ``axis``'s channel (its ``fault_state`` / ``drive_state``)."""
    k = AXES.index(axis)
    if transport == "serial":
        return (f"serial device 1 node {k + 1}: amplifier fault latched, amplifier off (status 0x05)" if fault
                else f"serial device 1 node {k + 1}: no fault, amplifier off (status 0x04)")
    return (f"CAN virtual {channel} feedback 0x180 (axis {axis}): "
            + (f"amplifier fault latched (byte 8 bit {k} set)" if fault else f"no fault (byte 8 bit {k} clear)"))


@contextlib.contextmanager
def _latched(transport: str, tmp_path, monkeypatch, revision: int = 2):
    """The emulated device of ``transport`` (shipped config, lockstep at 1 kHz) served from a
    thread, playing ``revision``, with its amplifier fault latched on X and Y by its command
    watchdog after a host fell silent while both drove (revision 1: its stop clears it, the
    watchdog latches the disabled channels again). Yields (loaded config, device, CAN channel
    name)."""
    channel = f"latch-{tmp_path.name}"
    driver = {"port": str(tmp_path / "ttyEMU")} if transport == "serial" else \
        {"interface": "virtual", "channel": channel}
    d = _config(f"gantry-{transport}.yaml", tmp_path, **driver)
    cfg = tmp_path / f"{transport}.yaml"
    cfg.write_text(yaml.safe_dump(d, sort_keys=False))
    loaded = config_from_dict(d, str(cfg), check_budget=False)
    # every set-up here (run_job's, reset_drive_faults') waits for the device thread's first
    # answer far beyond a loaded host's stall of it (an answer ends the wait at once)
    monkeypatch.setattr(SplitPhaseDriver, "CONFIGURE_TIMEOUT_S", ANSWER_WAIT_S)
    # the loop's read spins (python-can's virtual bus has no descriptor) while the device thread
    # waits for the GIL: a 0.5 ms switch interval instead of 5 ms hands it over as two processes
    # would be scheduled (measured on the loaded 2-core VM, CAN: 18 -> 5 ms a cycle; no verdict depends on it)
    interval = sys.getswitchinterval()
    sys.setswitchinterval(5e-4)
    with contextlib.ExitStack() as undo:
        undo.callback(sys.setswitchinterval, interval)
        dev = undo.enter_context(_serving(loaded))
        dev.play_revision(revision)
        drv = loaded.make_driver()
        try:
            drv.open()
            exchange(drv, [0.5, -0.5], [True, True], 5)
            assert dev.bank.enabled == [True, True]
            # the host falls silent while driving: the watchdog latches both (bounded wait)
            assert wait_for(lambda: all(dev.bank.amp_fault), 10.0), dev.bank.amp_fault
        finally:
            drv.close()                        # its stop comes later: enable 0, no reset
        assert dev.bank.enabled == [False, False]
        if revision == 2:                      # the stop's enable 0 left it latched
            assert dev.bank.amp_fault == [True, True]
        else:                                  # cleared by the stop, latched again by the watchdog
            assert wait_for(lambda: all(dev.bank.amp_fault), 10.0), dev.bank.amp_fault
        yield loaded, dev, channel


@pytest.mark.parametrize("transport", ["serial", "can"])
def test_a_latched_fault_stays_across_runs_until_the_operators_reset(transport, tmp_path, monkeypatch):
    """The run after the latch is refused in one line naming each channel's status and the
    command (before: its set-up sent enable 0, "cleared the amplifier fault latched on X, Y",
    and drove), nothing driven, the device still latched; the operator's reset of X with no
    daemon clears X alone (the request's rising edge, seen by the device once), then Y's; the
    next run has no fault and its stop is confirmed."""
    from motorctl.app.build import StartRefused
    from motorctl.app.fault_reset import reset_drive_faults
    from motorctl.app.job import run_job
    with _latched(transport, tmp_path, monkeypatch) as (loaded, dev, channel):
        notices = []
        with pytest.raises(StartRefused) as exc:
            run_job(loaded, duration_s=RUN_S, clock="virtual", on_notice=notices.append)
        cfg = loaded.path
        assert str(exc.value) == "; ".join(
            f"axis {a}'s drive is in its fault ({_words(transport, channel, a, True)}); it stays there until the "
            f"operator resets it: 'motorctl fault-reset --config {cfg} {a}' (no daemon running) or 'motorctl "
            f"fault-reset {a}' (through the daemon)" for a in AXES) + "; nothing was driven"
        assert [n for n in notices if n.startswith("warning: ")] == [
            f"warning: axis {a}: set-up found the drive in its fault ({_words(transport, channel, a, True)}); it "
            f"stays there until the operator's 'motorctl fault-reset'" for a in AXES], notices
        assert not any("cleared" in n for n in notices), notices
        assert dev.bank.amp_fault == [True, True] and dev.bank.enabled == [False, False]
        for k, a in enumerate(AXES):                     # motorctl fault-reset --config CFG X, then Y
            (r,) = reset_drive_faults(loaded, [a]).axes
            assert (r.sent, r.cleared) == (True, True), r
            assert (r.was, r.now) == (_words(transport, channel, a, True), _words(transport, channel, a, False))
            assert dev.bank.amp_fault == [False, k == 0], (a, dev.bank.amp_fault)
        res = run_job(loaded, duration_s=RUN_S, clock="virtual")
        assert [res.axes[a]["fault"] for a in AXES] == ["", ""], res.axes
        assert res.stop_confirmed and not [n for n in res.notices if n.startswith("warning: ")], res.notices


@pytest.mark.parametrize("transport", ["serial", "can"])
def test_the_daemons_fault_reset_sends_the_request_between_cycles(transport, tmp_path, monkeypatch):
    """The daemon's path (as its loop process runs it, tests/test_canopen.py's helpers): the loop
    starts with X and Y faulted by the device's latch; one ``fault-reset X`` sends the request
    between cycles and clears the supervisor's latch once X's reply shows the fault gone, within
    the bound (``FAULT_RESET_WAIT_S`` of cycles), every cycle run; Y stays faulted."""
    from test_canopen import _loop_on_drives, _reset_between_cycles

    from motorctl.app.build import shutdown
    with _latched(transport, tmp_path, monkeypatch) as (loaded, dev, _channel):
        asm, lp = _loop_on_drives(loaded)
        try:
            lp.run(20)
            assert [bool(f) for f in asm.supervisor.fault] == [True, True] and asm.driver.amp_fault.all()
            bound = lp.fault_reset_cycles
            seen = _reset_between_cycles(lp, 3 * bound)
            assert seen["pending"] and seen["ok"] and seen["why"] == "", seen
            assert 1 <= seen["done_k"] - seen["k0"] <= bound, seen
            assert [bool(f) for f in asm.supervisor.fault] == [False, True]
            assert list(asm.driver.amp_fault) == [False, True]
            assert dev.bank.amp_fault == [False, True]
        finally:
            shutdown(asm)


@pytest.mark.parametrize("transport", ["serial", "can"])
def test_a_device_of_revision_1_is_named_it_cannot_keep_the_fault(transport, tmp_path, monkeypatch):
    """The emulated device playing revision 1 (enable 0 clears its latch; no revision bit): the
    driver does not pretend to keep the fault: a set-up warning names the revision and says the
    fault cannot stay latched, the old reset clears it with a notice, ``describe()`` says
    revision 1."""
    with _latched(transport, tmp_path, monkeypatch, revision=1) as (loaded, dev, channel):
        drv = loaded.make_driver()
        try:
            drv.open()
            (warn,) = [n for n in drv.notices if n.startswith("warning: ")]
            if transport == "serial":
                assert warn.startswith("warning: serial device 1 is of protocol revision 1 (its replies leave "
                                       "status bit 2 clear)"), warn
                assert drv.describe()["protocol_revision"] == 1
            else:
                assert warn.startswith(f"warning: CAN virtual {channel}: the drives of X (its drive leaves feedback "
                                       f"0x180 byte 8 bit 2, explicit_reset, clear), Y (its drive leaves feedback "
                                       f"0x180 byte 8 bit 3, explicit_reset, clear) are of revision 1"), warn
                assert drv.describe()["protocol_revision"] == {"X": 1, "Y": 1}
            assert "cannot stay latched until the operator's 'motorctl fault-reset'" in warn, warn
            assert any("at set-up, cleared the amplifier fault latched on X, Y" in n for n in drv.notices)
            assert not drv.amp_fault.any() and dev.bank.amp_fault == [False, False]
        finally:
            drv.close()


def test_can_layout_of_revision_2_is_checked():
    """``explicit_reset`` (a drive of revision 2) needs the ``fault_reset`` bit it is reset by; two
    bits of a frame may not share a position (each is checked against every other)."""
    from pydantic import ValidationError

    from motorctl_drivers import can_bus

    def axis(enable_bit, reset_bit, explicit=True):
        return can_bus.CanAxisOptions(
            command={"id": 0x200, "voltage": {"offset": 0, "size": 2}, "enable": {"byte": 4, "bit": enable_bit},
                     **({"fault_reset": {"byte": 4, "bit": reset_bit}} if reset_bit is not None else {})},
            feedback={"id": 0x180, "counts": {"offset": 0, "size": 4}, "fault": {"byte": 8, "bit": 0},
                      **({"explicit_reset": {"byte": 8, "bit": 2}} if explicit else {})})
    with pytest.raises(ValidationError, match="explicit_reset .* needs command.fault_reset"):
        axis(0, None)
    with pytest.raises(ValueError, match="command frame 0x200: byte 4 bit 0 used by X enable and X fault_reset"):
        can_bus.build_frames(["X"], {"X": axis(0, 0)}, "command", fd=False)
    (f,) = can_bus.build_frames(["X"], {"X": axis(0, 1)}, "command", fd=False)
    assert f.length == 5                                     # the bits share byte 4
