"""A CiA 402 drive as some come from the market: canopen's ``LocalNode`` with only the
mandatory objects (no 0x1005, 0x1006, 0x1016, 0x6007, 0x603F, 0x6072, 0x6076, 0x6077 and no PDO
parameter objects 0x1400-0x1A03) and a hard-wired PDO mapping, written here from
docs/drivers.md alone (not the project's emulator). The driver brings it up from a YAML config
that declares the fixed mapping and ``host_watchdog: none``, runs the closed loop through it and
confirms the stop; with the default ``host_watchdog: heartbeat`` the set-up is refused and what
it had changed on the drive (its producer heartbeat 0x1017) is put back. In-process, on
python-can's ``virtual`` bus (the drives in a thread)."""

from __future__ import annotations

import struct
from pathlib import Path

import can
import canopen
from canopen import objectdictionary as odm
from conftest import RIGID_PLANT

from motorctl.app.job import run_job
from motorctl.config import config_from_dict, load_yaml
from motorctl_drivers import cia402
from motorctl_emulators.cia402_drive import STATUSWORD, drive_transition
from motorctl_emulators.device import Device
from harness import device_thread
from motorctl_emulators.plant_bank import load_plant

CONFIGS = Path(__file__).resolve().parents[1] / "configs"
DRIVE_HEARTBEAT_MS = 100          # what the drive produces as delivered


def _dictionary(node_id: int):
    od = odm.ObjectDictionary()
    od.node_id = node_id

    def var(name, index, dtype, access="rw", default=0):
        v = odm.ODVariable(name, index, 0)
        v.data_type, v.access_type, v.default = dtype, access, default
        od.add_object(v)

    var("Device type", 0x1000, odm.UNSIGNED32, "ro", 0x00020192)
    var("Error register", 0x1001, odm.UNSIGNED8, "ro")
    var("Producer heartbeat time", 0x1017, odm.UNSIGNED16, "rw", DRIVE_HEARTBEAT_MS)
    ident = odm.ODRecord("Identity object", 0x1018)
    for sub, name in ((0, "Highest sub-index supported"), (1, "Vendor-ID")):
        v = odm.ODVariable(name, 0x1018, sub)
        v.data_type, v.access_type, v.default = odm.UNSIGNED32 if sub else odm.UNSIGNED8, "ro", 1 if not sub else 0x5A
        ident.add_member(v)
    od.add_object(ident)
    var("Controlword", 0x6040, odm.UNSIGNED16)
    var("Statusword", 0x6041, odm.UNSIGNED16, "ro")
    var("Modes of operation", 0x6060, odm.INTEGER8)
    var("Modes of operation display", 0x6061, odm.INTEGER8, "ro")
    var("Position actual value", 0x6064, odm.INTEGER32, "ro")
    var("Target torque", 0x6071, odm.INTEGER16)
    return od


class FixedPdoDrive(Device):
    """Two drives (node 1: X, node 2: Y) on a virtual bus: RPDO 0x200 + node = controlword,
    target torque; TPDO 0x180 + node = statusword, position; both answered at every SYNC (0x080)
    while Operational, the target torque applied (±1000 per mille ↔ ±10 V) only in Operation
    enabled."""

    def __init__(self, channel: str, bank):
        super().__init__(None, {}, bank)
        self.bus = can.Bus(interface="virtual", channel=channel)
        self.network = canopen.Network(self.bus)
        self.nodes, self.rx, self.state, self.cw_prev = [], [], [], []
        for i in range(len(bank.names)):
            node = canopen.LocalNode(i + 1, _dictionary(i + 1))
            self.network.add_node(node)
            node.add_read_callback(lambda index, subindex, od, i=i: self._read(i, index))
            self.nodes.append(node)
            self.rx.append(bytes(4))
            self.state.append(cia402.SWITCH_ON_DISABLED)
            self.cw_prev.append(0)
            self.network.subscribe(0x200 + i + 1, lambda cid, data, ts, i=i: self._rpdo(i, data))
        self.network.subscribe(0x80, self._sync)
        for node in self.nodes:
            node.nmt.send_command(0x81)
            node.nmt.send_command(0x80)

    def _read(self, i: int, index: int):
        if index == 0x6041:
            return STATUSWORD[self.state[i]]
        if index == 0x6064:
            return self.bank.counts(i, 0.5e-6)
        return None

    def _rpdo(self, i: int, data) -> None:
        self.rx[i] = bytes(data[:4])

    def _sync(self, cid, data, ts) -> None:
        for i, node in enumerate(self.nodes):
            if node.nmt.state != "OPERATIONAL":
                continue
            cw, target = struct.unpack("<Hh", self.rx[i])
            self.state[i] = drive_transition(self.state[i], cw, self.cw_prev[i])
            self.cw_prev[i] = cw
            on = self.state[i] == cia402.OPERATION_ENABLED
            self.bank.command(i, target / 100.0 if on else 0.0, on)
            pos = ((self.bank.counts(i, 0.5e-6) + (1 << 31)) % (1 << 32)) - (1 << 31)
            self.network.send_message(0x180 + i + 1, struct.pack("<Hi", STATUSWORD[self.state[i]], pos))

    def poll(self, timeout_s: float) -> None:
        msg = self.bus.recv(timeout=timeout_s)
        while msg is not None:
            if not msg.is_error_frame and not msg.is_remote_frame:
                self.network.notify(msg.arbitration_id, msg.data, msg.timestamp)
            msg = self.bus.recv(timeout=0)

    def close(self) -> None:
        for node in self.nodes:
            node.nmt.stop_heartbeat()
        self.bus.shutdown()


def _config(tmp_path, **driver) -> dict:
    d = load_yaml(CONFIGS / "gantry-canopen.yaml")
    d["loop"].update(rate_hz=500, clock="virtual")      # lockstep: a read waits up to 2 s for
    # the drive thread's answer, so a loaded host delays the run but never stales a reading (at
    # 0.2 s two spinning processes held the thread off long enough once: a 1 mm following error);
    # the host's watch of the drives' heartbeats (produced every 10 ms from a thread of this
    # process) at 1 s, not 50 ms: a loaded host's stall of that thread is no read error
    d["driver"].update(interface="virtual", channel=f"fixed-{tmp_path.name}", timeout_s=2.0, sync_cob_id=0x80,
                       round_trip_exchanges=5, drive_heartbeat_timeout_ms=1000, **driver)
    for k, a in enumerate(("X", "Y")):
        node = k + 1
        d["axes"][a]["driver"].update(node_id=node, fixed_pdos={
            "rpdo": {"cob_id": 0x200 + node, "map": [[0x6040, 0, 16], [0x6071, 0, 16]]},
            "tpdo": {"cob_id": 0x180 + node, "map": [[0x6041, 0, 16], [0x6064, 0, 32]]}})
        d["axes"][a]["driver"].pop("rated_torque", None)
        d["axes"][a]["driver"].pop("sdo", None)
    return d


#: the plant bank's command watchdog [s]: the runs are in lockstep (virtual clock), so a gap
#: between two commands is the host's stall, not the master's time; at the bank's default 50 ms
#: a loaded host (3 spinning processes) tripped it on 6 of 40 runs, and this drive, which does
#: not report the bank's amplifier fault, then held 0 V while the host drove on: a following
#: error. 1 s as the config's other watches (0 of 40 so)
BANK_WATCHDOG_S = 1.0


def _drives(loaded):
    bank = load_plant(RIGID_PLANT, list(loaded.axes), loaded.period_s, watchdog_s=BANK_WATCHDOG_S,
                      log=lambda msg: None)
    return device_thread(FixedPdoDrive(loaded.driver_options.channel, bank))


def test_a_drive_with_fixed_pdos_and_no_optional_objects_runs_the_closed_loop(tmp_path):
    loaded = config_from_dict(_config(tmp_path, host_watchdog="none"), "<fixed>", check_budget=False)
    notices = []
    with _drives(loaded) as dev:
        res = run_job(loaded, controller="c2", duration_s=1.0, clock="virtual", on_notice=notices.append)
        held = [n.sdo[0x1017].raw for n in dev.nodes]
    print("\n".join(notices))
    for a in ("X", "Y"):
        r = res.axes[a]
        assert r["fault"] == "", r
        assert r["e_M_um"] < 200.0, r                    # it tracks: 1 s of the first move, C2 at 500 Hz
    warnings = [n for n in notices if n.startswith("warning: ")]
    assert len(warnings) == 1 and "no device-side watchdog (driver.host_watchdog: none)" in warnings[0], notices
    assert any("no readable mapping" in n and "taken as declared" in n for n in notices), notices
    assert any("0x1006" in n and "optional, not set" in n for n in notices), notices
    assert res.stop_confirmed, res.stop
    assert all("Switch on disabled" in c.held and "no torque actual 0x6077" in c.held for c in res.stop), res.stop
    assert dev.bank.applied_V == [0.0, 0.0] and dev.bank.enabled == [False, False]
    assert held == [DRIVE_HEARTBEAT_MS, DRIVE_HEARTBEAT_MS]   # the driver set 10 for the run; close restores


def test_without_a_heartbeat_consumer_the_set_up_is_refused_and_restored(tmp_path):
    loaded = config_from_dict(_config(tmp_path), "<fixed>", check_budget=False)
    drv = loaded.make_driver()
    with _drives(loaded) as dev:
        try:
            drv.configure()
            raise AssertionError("configure() accepted a drive without a heartbeat consumer")
        except OSError as exc:
            msg = str(exc)
        finally:
            drv.close()
        held = [n.sdo[0x1017].raw for n in dev.nodes]
    assert "has no heartbeat consumer 0x1016" in msg and "host_watchdog: none" in msg, msg
    assert "restored" in msg, msg
    assert held == [DRIVE_HEARTBEAT_MS, DRIVE_HEARTBEAT_MS]   # 0x1017 is back at what it was
