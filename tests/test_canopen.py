"""CANopen CiA 402: the profile logic (cia402.py) and the driver against drives built on canopen's
own device side (``canopen.LocalNode``, motorctl_emulators/cia402_device.py), on python-can's
``virtual`` bus in this process (the drives in a thread; functional, no timing)."""

from __future__ import annotations

import contextlib
import re
import time
from pathlib import Path

import numpy as np
import pytest
import yaml
from conftest import RIGID_PLANT

from motorctl.app.job import run_job
from motorctl.config import ConfigError, config_from_dict, load_yaml
from motorctl.loop.records import MODE_APPROACH, MODE_HOLD, MODE_IDLE, MODE_PROGRAM
from motorctl.recorder.runlog import read_log
from motorctl_drivers import cia402
from motorctl_emulators.device import build_device
from harness import device_thread, exchange
from motorctl_emulators.plant_bank import FaultSpec

CONFIGS = Path(__file__).resolve().parents[1] / "configs"
PLANT = RIGID_PLANT


# --------------------------------------------------------------------------- profile logic
@pytest.mark.parametrize("sw, state", [(0x0000, cia402.NOT_READY), (0x0250, cia402.SWITCH_ON_DISABLED),
                                       (0x0231, cia402.READY_TO_SWITCH_ON), (0x0233, cia402.SWITCHED_ON),
                                       (0x0237, cia402.OPERATION_ENABLED), (0x0217, cia402.QUICK_STOP_ACTIVE),
                                       (0x021F, cia402.FAULT_REACTION_ACTIVE), (0x0208, cia402.FAULT),
                                       (0x0228, cia402.FAULT)])
def test_statusword_decoding(sw, state):
    assert cia402.decode_state(sw) == state


def test_power_state_machine_enables_step_by_step_and_resets_faults_only_when_asked():
    sm = cia402.PowerStateMachine()
    assert sm.step(0x0250, True) == cia402.CW_SHUTDOWN and not sm.enabled
    assert sm.step(0x0250, True) == cia402.CW_SHUTDOWN          # not confirmed yet: asked again
    assert sm.step(0x0231, True) == cia402.CW_SWITCH_ON
    assert sm.step(0x0233, True) == cia402.CW_ENABLE_OPERATION and not sm.enabled
    assert sm.step(0x0237, True) == cia402.CW_ENABLE_OPERATION and sm.enabled
    assert sm.step(0x0237, False) == cia402.CW_DISABLE_VOLTAGE and sm.enabled   # the drive has not left yet
    assert sm.step(0x0208, True) == cia402.CW_DISABLE_VOLTAGE and sm.fault      # enabled: never reset
    # disabled: the fault stays latched in the drive, bit 7 low, for as long as nobody asks
    assert all(sm.step(0x0208, False) == cia402.CW_DISABLE_VOLTAGE for _ in range(10 * sm.RESET_RETRY_CYCLES))
    sm.request_reset()                                                          # the operator's fault-reset
    cws = [sm.step(0x0208, False) for _ in range(2 * sm.RESET_TRIES * sm.RESET_RETRY_CYCLES)]
    edges = [k for k in range(1, len(cws)) if cws[k] & 0x80 and not cws[k - 1] & 0x80]
    assert len(edges) == sm.RESET_TRIES and all(c in (0, 0x80) for c in cws)   # rising edges of bit 7, bounded
    sm.request_reset()
    assert [sm.step(0x0208, False) for _ in range(2)] == [0, cia402.CW_FAULT_RESET]
    assert sm.step(0x0250, False) == cia402.CW_DISABLE_VOLTAGE and not sm.fault  # left Fault: done
    assert sm.step(0x0208, False) == cia402.CW_DISABLE_VOLTAGE                   # a new fault: latched again
    assert sm.step(0x0208, False) == cia402.CW_DISABLE_VOLTAGE


def test_error_codes_and_scaling():
    assert cia402.describe_error(0x2310) == "0x2310 continuous over-current"
    assert cia402.error_meaning(0x8130) == "life guard error or heartbeat error"
    assert cia402.error_meaning(0x2311) == "continuous over-current (group)"
    assert cia402.error_meaning(0xFF42) == "device specific"
    assert cia402.volts_to_permille(10.0, 10.0, 1000) == 1000
    assert cia402.volts_to_permille(-25.0, 10.0, 1000) == -1000          # saturates
    assert cia402.volts_to_permille(float("nan"), 10.0, 1000) == 0
    assert cia402.permille_to_volts(-500, 10.0, 1000) == -5.0


# --------------------------------------------------------------------------- driver and drives
def _config(tmp_path, **driver) -> dict:
    """Lockstep with the drives (the thread shares the GIL): 0.5 s for an answer, and both
    heartbeat watches (the drives' consumer of the host, the host's watch of the drives) at
    1 s, far above a loaded host's stall of either thread; the tests of those watches set
    their own."""
    d = load_yaml(CONFIGS / "gantry-canopen.yaml")
    d["loop"]["rate_hz"] = 500
    d["loop"]["clock"] = "virtual"
    d["driver"].update(interface="virtual", channel=f"co-{tmp_path.name}", timeout_s=0.5, wait="spin",
                       round_trip_exchanges=20, heartbeat_consumer_ms=1000, drive_heartbeat_timeout_ms=1000)
    d["driver"].update(driver)
    return d


@contextlib.contextmanager
def _drives(loaded, faults=(), **device):
    """The emulated CiA 402 drives of ``loaded`` (canopen's device side, in a thread) and a
    driver for them, closed on exit (before the drives stop): yields (devices, driver).
    ``device``: more options of :func:`build_device` (e.g. ``late_s``)."""
    with device_thread(build_device(loaded, PLANT, faults=list(faults), **device)) as dev:
        drv = loaded.make_driver()
        try:
            yield dev, drv
        finally:
            drv.close()


def test_configure_maps_pdos_checks_scales_and_measures_the_round_trip(tmp_path):
    loaded = config_from_dict(_config(tmp_path), "<co>", check_budget=False)
    with _drives(loaded) as (dev, drv):
        drv.configure()
        d = drv.describe()
        x = d["drives"]["X"]
        assert x["device_type"] == "0x00020192" and x["state"] == "Switch on disabled"
        assert x["rpdo"] == {"cob_id": "0x201", "map": ["0x6040:00/16", "0x6071:00/16"], "transmission_type": 1}
        assert x["tpdo"] == {"cob_id": "0x181", "map": ["0x6041:00/16", "0x6064:00/32"], "transmission_type": 1}
        assert x["scale"] == {"permille_per_V": 100.0, "m_per_count": 0.5e-6}
        rt = d["round_trip"]
        assert rt["n"] == 20 and 0 < rt["median_us"] <= rt["max_us"] and rt["budget_source"] == "configured"
        node = dev.drives[0].node                    # what the drive holds, read on its side
        assert node.sdo[0x6060].raw == 10 and node.sdo[0x1017].raw == 10
        assert node.sdo[0x6007].raw == 1 and node.sdo[0x1006].raw == 2000
        assert node.sdo[0x1800][1].raw == 0x40000181            # TPDO valid, no RTR
        drv.activate()
        consumer_ms = loaded.driver_options.heartbeat_consumer_ms          # what the config says
        assert node.nmt.state == "OPERATIONAL" and node.sdo[0x1016][1].raw == (127 << 16) | consumer_ms
    # closed: heartbeat consumer off and pre-operational on the drive's side
    assert node.nmt.state == "PRE-OPERATIONAL" and node.sdo[0x1016][1].raw == 0


def test_enable_walks_the_state_machine_and_torque_flows_only_in_operation_enabled(tmp_path):
    loaded = config_from_dict(_config(tmp_path), "<co>", check_budget=False)
    with _drives(loaded) as (dev, drv):
        drv.open()
        y0 = drv.position_m.copy()
        seen = []
        for _ in range(12):
            exchange(drv, [3.0, -3.0], [True, True])
            seen.append((drv.describe()["drives"]["X"]["state"], dev.bank.applied_V[0]))
            if drv._sm[0].enabled:
                break
        assert [s for s, _ in seen][-1] == "Operation enabled"
        assert all(v == 0.0 for s, v in seen[:-1]), seen        # no torque before Operation enabled
        exchange(drv, [3.0, -3.0], [True, True], n=30)
        assert dev.bank.applied_V[0] == pytest.approx(3.0, abs=0.02)     # 300 per mille <-> 3 V
        moved = drv.position_m - y0
        assert moved[0] > 0 and moved[1] < 0, moved
        assert not drv.read_error.any() and not drv.amp_fault.any()
        trace = [t.split(" ", 1)[1] for t in drv.describe()["drives"]["X"]["statusword_trace"]]
        assert trace[:4] == ["Switch on disabled", "Ready to switch on", "Switched on", "Operation enabled"]
        exchange(drv, [3.0, 3.0], [False, True], n=3)             # X disabled: Disable voltage
        assert drv.describe()["drives"]["X"]["state"] == "Switch on disabled" and dev.bank.applied_V[0] == 0.0
    assert dev.bank.applied_V == [0.0, 0.0]                          # closed: 0 V on both drives


def test_emcy_latches_an_amplifier_fault_naming_the_code_until_the_operators_reset(tmp_path):
    """An EMCY (over-current) latches X's amplifier fault, named by its code. The drive stays in
    Fault, the axis disabled, for as long as nobody resets it (the host sends no controlword
    bit 7 of its own: before, 4.8 ms after the EMCY the drive had left Fault); the operator's
    reset (``Driver.reset_fault``, what ``motorctl fault-reset`` calls) takes it out."""
    loaded = config_from_dict(_config(tmp_path), "<co>", check_budget=False)
    with _drives(loaded, [FaultSpec.parse("emcy=0x2310:X:20")]) as (dev, drv):
        drv.open()
        for _ in range(40):
            exchange(drv, [1.0, 1.0], [True, True])
            if drv.amp_fault[0]:
                break
        assert drv.amp_fault[0] and not drv.amp_fault[1]
        reason = drv.fault_reason(0)
        assert "0x2310 continuous over-current" in reason and "node 1 (axis X)" in reason
        exchange(drv, [1.0, 1.0], [True, True], n=3)               # still requested: stays latched
        assert drv.amp_fault[0] and dev.bank.applied_V[0] == 0.0
        exchange(drv, [0.0, 1.0], [False, True], n=50)            # the supervisor disables the axis
        assert drv.amp_fault[0] and dev.drives[0].state == cia402.FAULT, cia402.STATE_NAMES[dev.drives[0].state]
        assert "0x2310 continuous over-current" in drv.fault_reason(0)
        assert drv.reset_fault(0)                                 # the operator's fault-reset
        for _ in range(20):
            exchange(drv, [0.0, 1.0], [False, True])
            if not drv.amp_fault[0]:
                break
        # the latch is reset; the reason still names the EMCY for the report of the fault
        assert not drv.amp_fault[0] and "0x2310" in drv.fault_reason(0)
        assert drv.describe()["emcy"] == {"X": "0x2310 continuous over-current"}   # the history stays
        trace = [t.split(" ", 1)[1] for t in drv.describe()["drives"]["X"]["statusword_trace"]]
        assert "Fault" in trace and trace[-1] == "Switch on disabled"
        for _ in range(20):                                       # enabled again (a new start)
            exchange(drv, [0.0, 1.0], [True, True])
            if drv.fault_reason(0) == "":
                break
        assert drv.fault_reason(0) == "" and not drv.amp_fault[0]


def test_a_lost_tpdo_costs_two_reads_then_the_count_is_realigned(tmp_path):
    """The driver counts SYNCs and TPDOs to tell the TPDO of the latest SYNC from a late one (the
    late burst is tests/test_canopen_e2e.py). X's TPDO of SYNC 30 is lost: every later one is
    one behind the count, so it is set aside; two reads with that same lag mean lost, not
    late, and the count is realigned. Every position taken as fresh answers the latest SYNC.
    The lost and the set-aside reads each wait out the read timeout: 50 ms here (a loaded host's
    late answers only add errors, which the bounds below allow)."""
    loaded = config_from_dict(_config(tmp_path, timeout_s=0.05), "<co>", check_budget=False)
    with _drives(loaded, [FaultSpec.parse("drop:X:30:1")]) as (dev, drv):
        drv.open()
        errors, behind = [], []
        for k in range(1, 61):                     # k SYNCs sent
            exchange(drv, [2.0, 1.0], [True, True], sleep_s=0.002)
            errors.append(bool(drv.read_error[0]))
            if not drv.read_error[0]:              # taken as fresh: it answers SYNC k
                behind.append(k - dev.syncs)       # SYNCs the drive had not served yet
        c = drv.counters
    assert max(behind) == 0, (behind, c)
    lost = [k for k, e in enumerate(errors, 1) if e]
    # the loss and the two set aside (a loaded host adds late ones: in-process, the drive needs the GIL)
    assert {31, 32, 33} <= set(lost) and c["tpdo_resyncs"] >= 1 and c["stale"] >= 2, (lost, c)
    assert sum(errors[-20:]) <= 5, (lost, c)                            # the count is right again


def test_a_missing_drive_heartbeat_is_an_amplifier_fault_naming_it_at_the_read_that_sees_it(tmp_path):
    """Y's heartbeat producer stops: the read that first finds it overdue (CiA 301 §7.2.8.3.2,
    the host's heartbeat consumer) makes it an amplifier fault named "heartbeat lost", not an
    I/O error the bucket would count for ten cycles and name "driver error bucket full"
    (judged on the driver's own count of reads that found it lost: 1 at the fault)."""
    # the host's watch: 300 ms (the drives produce every 10 ms from a thread of this process:
    # far above a loaded host's stall of it, so X's heartbeat is never missed)
    loaded = config_from_dict(_config(tmp_path, drive_heartbeat_timeout_ms=300), "<co>", check_budget=False)
    with _drives(loaded) as (dev, drv):
        drv.open()
        exchange(drv, [0, 0], [False, False], n=10, sleep_s=0.002)
        assert not drv.read_error.any() and not drv.amp_fault.any()
        dev.drives[1].node.nmt.stop_heartbeat()                   # Y's heartbeat producer stops
        t_stop = time.monotonic()
        seen = []
        while not drv.amp_fault[1] and time.monotonic() - t_stop < 5.0:   # bounded
            exchange(drv, [0, 0], [False, False], sleep_s=0.002)
            seen.append((bool(drv.read_error[1]), drv.counters["heartbeat_lost"]))
        assert drv.amp_fault[1] and not drv.amp_fault[0], seen[-5:]
        assert not any(e for e, _ in seen) and seen[-1][1] == 1, seen[-5:]     # named at the first read
        assert re.fullmatch(r"canopen node 2 \(axis Y\): heartbeat lost, none for \d+ ms "
                            r"\(drive_heartbeat_timeout_ms 300\)", drv.fault_reason(1)), drv.fault_reason(1)
        # not before the timeout: 300 ms after Y's last heartbeat, which came before t_stop (by
        # its 10 ms period, or a loaded thread's stall of up to 200 ms)
        assert time.monotonic() - t_stop >= 0.3 - 0.2
        exchange(drv, [0, 0], [False, False], n=3, sleep_s=0.002)
        assert drv.amp_fault[1] and not drv.read_error[1] and "heartbeat lost" in drv.fault_reason(1)


def test_a_drive_leaving_operational_is_an_amplifier_fault_naming_its_nmt_state(tmp_path):
    """Y's drive goes pre-operational (its heartbeat says 0x7F): an amplifier fault at the next
    read, not an I/O error the bucket would count for ten cycles; X is untouched."""
    loaded = config_from_dict(_config(tmp_path), "<co>", check_budget=False)
    with _drives(loaded) as (dev, drv):
        drv.open()
        exchange(drv, [0, 0], [False, False], n=10, sleep_s=0.002)
        assert not drv.amp_fault.any() and drv.fault_reason(1) == ""
        dev.drives[1].node.nmt.state = "PRE-OPERATIONAL"     # its next heartbeat (10 ms) says so
        t0 = time.monotonic()
        while not drv.amp_fault[1] and time.monotonic() - t0 < 5.0:       # bounded
            exchange(drv, [0, 0], [False, False], sleep_s=0.002)
            assert not drv.read_error[1] or not drv.amp_fault[1]
        assert drv.amp_fault[1] and not drv.read_error[1] and not drv.amp_fault[0]
        assert drv.fault_reason(1) == ("canopen node 2 (axis Y) left NMT Operational: its heartbeat says "
                                       "pre-operational (0x7F)")
        assert drv.counters["nmt_left"] >= 1


def test_close_restores_every_object_the_set_up_changed(tmp_path):
    """The drives' objects as found before the set-up (X's producer heartbeat 0x1017 at its own
    100 ms), changed for the run, and the same again after close."""
    loaded = config_from_dict(_config(tmp_path), "<co>", check_budget=False)
    objects = [(0x1005, 0), (0x1006, 0), (0x1016, 1), (0x1017, 0), (0x6007, 0), (0x6060, 0)]
    objects += [(c + k, sub) for c in (0x1400, 0x1600, 0x1800, 0x1A00) for k in range(4) for sub in (0, 1, 2)]
    with device_thread(build_device(loaded, PLANT)) as dev:
        node = dev.drives[0].node
        node.sdo.download(0x1017, 0, (100).to_bytes(2, "little"))
        before = {key: bytes(node.sdo.upload(*key)) for key in objects}
        drv = loaded.make_driver()
        try:
            drv.open()
            exchange(drv, [0, 0], [False, False], n=5)
            during = {key: bytes(node.sdo.upload(*key)) for key in objects}
        finally:
            drv.close()
        after = {key: bytes(node.sdo.upload(*key)) for key in objects}
    assert during[(0x1017, 0)] == (10).to_bytes(2, "little") and during[(0x6060, 0)] == b"\x0a"
    assert after == before, {k: (before[k].hex(), after[k].hex()) for k in objects if after[k] != before[k]}
    assert drv.counters["restored"] >= 10, drv.counters


def test_the_drives_heartbeat_consumer_stops_the_motor_when_the_host_goes_silent(tmp_path):
    # a consumer of 300 ms: a loaded host's stall between two exchanges does not reach it
    loaded = config_from_dict(_config(tmp_path, abort_connection_option=2, heartbeat_consumer_ms=300), "<co>",
                              check_budget=False)
    with _drives(loaded) as (dev, drv):
        drv.open()
        for _ in range(40):
            exchange(drv, [2.0, 2.0], [True, True], sleep_s=0.002)
        assert dev.bank.applied_V[0] != 0.0
        lines = []
        dev.bank.log = lines.append                              # the drives' messages, kept
        t0 = time.monotonic()                                    # the host stops cycling
        # both drives' consumers trip; the emulator handles one drive after the other, so wait
        # for both (a wait on X alone could look at Y in the microseconds between the two)
        while time.monotonic() - t0 < 2.0 and any(v != 0.0 for v in dev.bank.applied_V):
            time.sleep(0.005)
        assert dev.bank.applied_V == [0.0, 0.0]
        assert dev.drives[0].state == cia402.SWITCH_ON_DISABLED   # option 2: disable voltage
    trips = [re.search(r"^heartbeat consumer (\w): no heartbeat from node 127 for 300 ms "
                       r"\(last at t=([\d.]+), now t=([\d.]+)\)", ln) for ln in lines]
    trips = [m.groups() for m in trips if m]
    assert sorted(a for a, _, _ in trips) == ["X", "Y"], lines
    for axis, last, now in trips:
        # on the drive's own clock: no sooner than its consumer time after the host's last
        # heartbeat, and within it plus its 10 ms poll, but for the emulator thread's scheduling
        assert 0.300 <= float(now) - float(last) <= 0.300 + 0.010 + 0.200, (axis, float(now) - float(last))


def test_configure_refuses_a_wrong_scale_and_releases_the_bus(tmp_path):
    d = _config(tmp_path)
    d["axes"]["X"]["driver"]["rated_torque"] = 1234                  # the drive says 100000
    loaded = config_from_dict(d, "<co>", check_budget=False)
    with _drives(loaded) as (_, drv):
        with pytest.raises(OSError, match=r"rated torque 0x6076 is 100000, the config says 1234"):
            drv.configure()
        assert drv.state == "unconfigured" and drv.bus is None
        d["axes"]["X"]["driver"].pop("rated_torque")
        d["axes"]["X"]["driver"]["full_scale_permille"] = 3500      # above max torque 0x6072 = 3000
        drv = config_from_dict(d, "<co>", check_budget=False).make_driver()
        with pytest.raises(OSError, match="above the drive's max torque 0x6072 = 3000"):
            drv.configure()
        d["axes"]["X"]["driver"]["sdo"] = [{"index": 0x6072, "value": 4000, "size": 2}]   # raise it by SDO
        drv = config_from_dict(d, "<co>", check_budget=False).make_driver()
        try:
            drv.configure()
            assert drv.describe()["drives"]["X"]["max_torque_permille"] == 4000
        finally:
            drv.close()


def test_no_drive_is_a_one_line_connection_error(tmp_path):
    drv = config_from_dict(_config(tmp_path, sdo_timeout_s=0.05), "<co>", check_budget=False).make_driver()
    with pytest.raises(ConnectionError) as exc:
        drv.configure()
    assert "\n" not in str(exc.value) and "canopen node 1 (axis X): no SDO answer reading 0x1000:00" in str(exc.value)
    assert drv.bus is None


def test_config_checks(tmp_path):
    d = _config(tmp_path)
    d["axes"]["Y"]["driver"]["node_id"] = 1
    with pytest.raises(ConfigError, match="share a node_id"):
        config_from_dict(d, "<co>", check_budget=False)
    d = _config(tmp_path, heartbeat_consumer_ms=15)
    with pytest.raises(ConfigError, match="at least twice"):
        config_from_dict(d, "<co>", check_budget=False)


def test_runs_after_a_drive_left_standing_at_half_a_millimetre_and_a_run_cut_mid_program(tmp_path):
    """The issue's CiA 402 case: the drives' carriages stand at 0.5 mm (X) and -0.3 mm (Y), not at
    the program's first point 0 (a 0.3 mm following-error limit at rest: without the approach the
    first cycle faults). Run 1 approaches from there and runs 1.2 s of the program (both axes end at
    0.4 m, mid-program); run 2 (0.2 s), on the same drives, approaches from 0.4 m. Both without a fault,
    the rows: idle reads, the approach, the program."""
    plant = load_yaml(PLANT)
    for a, x in (("X", 0.0005), ("Y", -0.0003)):
        plant["axes"][a]["driver"]["initial_position_m"] = x
    plant_path = tmp_path / "plant.yaml"
    plant_path.write_text(yaml.safe_dump(plant))
    loaded = config_from_dict(_config(tmp_path), "<co>", check_budget=False)
    results = []
    with device_thread(build_device(loaded, plant_path)):
        for k, seconds in enumerate((1.2, 0.2)):
            res = run_job(loaded, duration_s=seconds, clock="virtual", log_path=str(tmp_path / f"run{k}.mlog"))
            assert all(not r["fault"] for r in res.axes.values()), {a: r["fault"] for a, r in res.axes.items()}
            results.append(res)
    for a, first in (("X", 0.0005), ("Y", -0.0003)):
        assert results[0].approach[a]["from_m"] == pytest.approx(first, abs=1e-6)
        assert results[1].approach[a]["from_m"] == pytest.approx(0.4, abs=2e-4)
        for k in range(2):
            mode = read_log(str(tmp_path / f"run{k}.mlog")).col(f"{a}.mode")
            i, j = int(np.argmax(mode != MODE_IDLE)), int(np.argmax(mode == MODE_PROGRAM))
            assert i >= 2 and (mode[i:j] == MODE_APPROACH).all() and j - i >= 2
            assert np.isin(mode[j:], (MODE_PROGRAM, MODE_HOLD)).all() and mode[-1] == MODE_HOLD   # then the stop


def _loop_on_drives(loaded):
    """The loop of ``loaded`` built and started on the drives (virtual clock): (assembly, loop)."""
    from motorctl.app.build import build, start
    asm = build(loaded, clock="virtual", capacity=1000)
    start(asm, "off")
    return asm, asm.loop


def _reset_between_cycles(lp, n: int) -> dict:
    """The operator's fault-reset of X as the daemon's loop process makes it: the drive's reset
    sent between two cycles (``begin_fault_reset``), then looked at between every later cycle
    (``poll_fault_reset``) until done, at most ``n`` cycles. Returns what it saw (cycles counted
    by the loop, never wall time)."""
    seen: dict = {}

    def slack(loop):
        if "k0" not in seen:
            seen["k0"] = loop.k
            seen["pending"], ok, why = loop.begin_fault_reset(0)
            if not seen["pending"]:
                seen.update(done_k=loop.k, ok=ok, why=why)
                loop.request_stop()
            return
        done, ok, why = loop.poll_fault_reset(0)
        if done:
            seen.update(done_k=loop.k, ok=ok, why=why)
            loop.request_stop()

    lp.on_slack = slack
    lp.run(n)
    lp.on_slack = None
    return seen


def test_one_fault_reset_takes_the_drive_out_of_fault_and_clears_the_latch(tmp_path):
    """An EMCY latches X's amplifier fault; ONE operator's fault-reset (the daemon's: the drive's
    reset, CiA 402 transition 15, then the supervisor's latch once the drive reports it left
    Fault) clears it, answered within the bound (``FAULT_RESET_WAIT_S`` of cycles) and without
    blocking a cycle: the loop ran every cycle in between. Before, the first fault-reset was
    refused with 'run fault-reset again once the drive has left its fault'."""
    from motorctl.app.build import shutdown
    from motorctl.loop.servo import FAULT_RESET_WAIT_S
    loaded = config_from_dict(_config(tmp_path), "<co>", check_budget=False)
    with device_thread(build_device(loaded, PLANT, faults=[FaultSpec.parse("emcy=0x2310:X:20")])) as dev:
        asm, lp = _loop_on_drives(loaded)
        try:
            lp.run(60)
            assert asm.supervisor.fault[0] and asm.driver.amp_fault[0], asm.supervisor.reason(0)
            assert dev.drives[0].state == cia402.FAULT                  # latched in the drive
            bound = round(FAULT_RESET_WAIT_S * loaded.cfg.loop.rate_hz)
            assert lp.fault_reset_cycles == bound == 50
            seen = _reset_between_cycles(lp, 3 * bound)
            assert seen["pending"] and seen["ok"] and seen["why"] == "", seen
            assert 1 <= seen["done_k"] - seen["k0"] <= bound, seen     # within 100 ms of cycles
            assert not asm.supervisor.fault[0] and not asm.driver.amp_fault[0]
            assert dev.drives[0].state == cia402.SWITCH_ON_DISABLED
        finally:
            shutdown(asm)


def test_a_drive_that_stays_in_fault_refuses_the_reset_naming_its_state_after_the_bound(tmp_path):
    """The drive keeps faulting (the EMCY injected at every SYNC): the fault-reset sends the
    drive's reset, waits ``FAULT_RESET_WAIT_S`` of cycles (50 at 500 Hz), and is refused then,
    naming the drive's CiA 402 state and statusword; the latch stays."""
    from motorctl.app.build import shutdown
    loaded = config_from_dict(_config(tmp_path), "<co>", check_budget=False)
    with device_thread(build_device(loaded, PLANT, faults=[FaultSpec.parse("emcy=0x2310:X:20:100000")])):
        asm, lp = _loop_on_drives(loaded)
        try:
            lp.run(60)
            assert asm.supervisor.fault[0] and asm.driver.amp_fault[0]
            seen = _reset_between_cycles(lp, 200)
            assert seen["pending"] and not seen["ok"], seen
            assert seen["done_k"] - seen["k0"] == lp.fault_reset_cycles == 50, seen
            assert "did not leave its fault within 100 ms" in seen["why"], seen
            assert "canopen node 1 (axis X) is in Fault reaction active (statusword 0x" in seen["why"], seen
            assert asm.supervisor.fault[0]
        finally:
            shutdown(asm)


def test_a_drive_fault_stays_latched_across_runs_until_the_operators_reset_without_a_daemon(tmp_path):
    """X's drive faults (EMCY 0x2310) in one session and is left in Fault. The next set-up does not
    reset it (before, it wrote controlword 0x0080 and said "cleared the Fault it was in at
    set-up"): it warns, and ``motorctl run`` is refused in one line naming the drive's CiA 402
    state, statusword, error code 0x603F and the command that clears it, nothing driven, the drive
    still in Fault. ``reset_drive_faults`` (``motorctl fault-reset --config CONFIG X``, no daemon)
    sends transition 15, reports Switch on disabled after, and the next set-up finds no fault."""
    from motorctl.app.build import StartRefused
    from motorctl.app.fault_reset import reset_drive_faults
    loaded = config_from_dict(_config(tmp_path), "<co>", check_budget=False)
    with _drives(loaded, [FaultSpec.parse("emcy=0x2310:X:20")]) as (dev, drv):
        drv.open()
        for _ in range(40):
            exchange(drv, [1.0, 1.0], [True, True])
            if drv.amp_fault[0]:
                break
        assert drv.amp_fault[0]
        drv.close()                                                    # the session ends, X in Fault
        assert dev.drives[0].state == cia402.FAULT
        notices = []
        with pytest.raises(StartRefused) as exc:
            run_job(loaded, duration_s=0.2, clock="virtual", on_notice=notices.append)
        why = str(exc.value)
        assert "\n" not in why and why.startswith("axis X's drive is in its fault (canopen node 1 (axis X) is in "
                                                  "Fault (statusword 0x"), why
        assert "error code 0x603F = 0x2310 continuous over-current" in why and "axis Y" not in why, why
        assert "'motorctl fault-reset --config <co> X' (no daemon running) or 'motorctl fault-reset X'" in why, why
        assert why.endswith("nothing was driven"), why
        assert any(n.startswith("warning: axis X: set-up found the drive in its fault") for n in notices), notices
        assert not any("cleared" in n for n in notices), notices
        assert dev.drives[0].state == cia402.FAULT                      # the set-up left it there
        rep = reset_drive_faults(loaded, ["X"])
        (x,) = rep.axes
        assert x.sent and x.cleared and "is in Fault (statusword 0x" in x.was and "0x2310" in x.was, x
        assert x.now.startswith("canopen node 1 (axis X) is in Switch on disabled (statusword 0x"), x
        assert rep.stop_confirmed and dev.drives[0].state == cia402.SWITCH_ON_DISABLED
        drv = loaded.make_driver()                                      # the next set-up finds no fault
        drv.open()
        exchange(drv, [0.0, 0.0], [False, False], n=5)
        assert not drv.amp_fault.any() and not any("found the drive" in n for n in drv.notices), drv.notices


def test_the_reset_without_a_daemon_is_refused_while_a_daemon_answers_on_its_socket(tmp_path):
    """``motorctl fault-reset --config CONFIG X`` must not open a bus a daemon holds: a control
    socket that answers (here a stand-in answering one status request) refuses it in one line
    naming the daemon's command, before the driver is made; a socket file nobody answers on (a
    dead daemon's) does not."""
    import json
    import socket
    import threading

    from motorctl.app.fault_reset import BusHeld, daemon_answering, reset_drive_faults
    path = str(tmp_path / "d.sock")
    srv = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    srv.bind(path)
    srv.listen(1)

    def answer():
        conn, _ = srv.accept()
        with conn:
            conn.recv(4096)
            conn.sendall((json.dumps({"ok": True, "status": {}}) + "\n").encode())

    th = threading.Thread(target=answer, daemon=True)
    th.start()
    loaded = config_from_dict(_config(tmp_path), "<co>", check_budget=False)
    with pytest.raises(BusHeld) as exc:
        reset_drive_faults(loaded, ["X", "Y"], [path])
    th.join(timeout=5)
    assert str(exc.value) == (f"a daemon answers on {path}: it holds the bus, nothing was opened; reset through "
                              f"it: 'motorctl --socket {path} fault-reset X Y'")
    srv.close()                                                  # the file stays, nobody answers
    assert daemon_answering([path]) is None
    # a master on the bus whose socket is not known (a daemon started with another --socket, a
    # run): its SYNC is heard before anything is sent
    import can
    stop = threading.Event()

    def master():
        with can.Bus(interface="virtual", channel=loaded.driver_options.channel) as bus:
            while not stop.is_set():
                bus.send(can.Message(arbitration_id=0x80, data=b"", is_extended_id=False))
                time.sleep(0.002)

    th = threading.Thread(target=master, daemon=True)
    th.start()
    try:
        with pytest.raises(BusHeld, match=r"^a SYNC \(0x080\) on CAN virtual co-\S+: another master drives this bus"):
            reset_drive_faults(loaded, ["X"])
    finally:
        stop.set()
        th.join(timeout=5)
