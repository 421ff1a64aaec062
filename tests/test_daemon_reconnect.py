"""The daemon reconnects a drive that disappears and comes back, without re-enabling anything.

``motorctl daemon`` drives X and Y over the serial protocol (``socket://127.0.0.1``) against
``motorctl emulate`` in its own process. X is tracking when the emulator is killed: both axes
fault (the lost link fills the error bucket: 0 V, amplifier off), ``status`` says the link is
down. A new emulator on the same port: the daemon reconnects by itself (outside the cycle,
every axis idle), ``status`` says the link is back, and every axis is still faulted with its
amplifier off. Then ``fault-reset`` and ``start`` work and X tracks again.
"""

from __future__ import annotations

from pathlib import Path

import yaml
from conftest import RIGID_PLANT
from test_daemon_helpers import Daemon, as_test_daemon, ctl, status, wait_for

from harness import Emulator, loopback_e2e_config

CONFIGS = Path(__file__).resolve().parents[1] / "configs"
#: the emulated drive's command watchdog [s] (its protection when the host stops commanding)
DEVICE_WATCHDOG_S = 5.0


def _config(tmp: Path) -> tuple[Path, Path]:
    d, cfg, _rate = loopback_e2e_config("serial", CONFIGS, tmp)
    # the device's command watchdog (set by the driver in configure()) far beyond a loaded
    # host's stall: the host never dies here, and at 0.2 s a stall of the daemon (wall clock)
    # faulted the tracking axis through the device, a verdict of the host's load
    d["driver"]["watchdog_s"] = DEVICE_WATCHDOG_S
    sock = as_test_daemon(d, tmp)
    # the loopback on a loaded machine loses bursts, and a starved emulator loses plant time (1 mm
    # a cycle at 2 m/s, 2 kHz): the subject here is the link. The bucket (+10 an error, -1 an
    # exchange) holds 300 lost exchanges in a row, a 0.15 s stall of the emulator (at 300, 30 of
    # them, 15 ms: X faulted once while it followed through the new link, in a fresh-clone suite)
    for ax in d["axes"].values():
        ax["limits"]["error_bucket_limit"] = 3000
        ax["limits"]["following_error_m"] = 0.01
    cfg.write_text(yaml.safe_dump(d, sort_keys=False))
    return cfg, sock


def test_a_drive_that_comes_back_is_reconnected_and_nothing_is_re_enabled(tmp_path):
    cfg, sock = _config(tmp_path)
    emu = Emulator("serial", cfg, plant=RIGID_PLANT, watchdog_s=DEVICE_WATCHDOG_S).__enter__()
    daemon = Daemon(cfg, sock)
    try:
        daemon.wait_ready()
        assert status(sock)["link"]["connected"] is True
        assert ctl(sock, "start", "X").returncode == 0
        wait_for(lambda: status(sock)["axes"]["X"]["phase"] == "tracking", 30, "X tracking")

        emu.__exit__(None, None, None)      # the drive disappears (SIGKILL) while X tracks
        st = wait_for(lambda: (s := status(sock))["axes"]["X"]["state"] == "fault"
                      and not s["link"]["connected"] and s, 20, "X fault and the link down")
        assert "I/O error" in st["axes"]["X"]["fault"] or "driver" in st["axes"]["X"]["fault"], st["axes"]["X"]
        down = st["link"]
        # tries go on while nobody answers, each a short pause of the loop
        wait_for(lambda: status(sock)["link"]["attempts"] > down["attempts"] + 1, 20, "reconnection attempts")
        st = status(sock)
        # the attempt is bounded by RECONNECT_TIMEOUT_S (0.25 s), not by the driver's set-up timeout
        # (1 s): below 0.9 s, with room for a loaded host
        assert st["link"]["last_error"] and st["link"]["last_pause_s"] < 0.9, st["link"]

        emu = Emulator("serial", cfg, plant=RIGID_PLANT, watchdog_s=DEVICE_WATCHDOG_S).__enter__()
        st = wait_for(lambda: (s := status(sock))["link"]["connected"] and s, 30, "the link back")
        assert st["link"]["reconnects"] == 1 and st["link"]["last_error"] == "", st["link"]
        # nothing was re-enabled: both axes still faulted, 0 V and amplifier off
        for a in ("X", "Y"):
            ax = st["axes"][a]
            assert ax["state"] == "fault" and not ax["amplifier_enabled"] and ax["u_V"] == 0.0, ax
        # start is refused until an operator resets the fault
        r = ctl(sock, "start", "X")
        assert r.returncode != 0 and "fault" in r.stderr, r
        # the exchanges work again: the error bucket drains, then the reset is accepted
        r = wait_for(lambda: (r := ctl(sock, "fault-reset", "X")).returncode == 0 and r, 10, "fault-reset X")
        assert ctl(sock, "start", "X").returncode == 0
        st = wait_for(lambda: (s := status(sock))["axes"]["X"]["phase"] == "tracking" and s, 30,
                      "X tracking again")
        assert st["axes"]["X"]["amplifier_enabled"] and st["axes"]["Y"]["state"] == "fault"
        # ... and it follows: no fault while it runs a while through the new link
        wait_for(lambda: status(sock)["loop"]["cycles"] > st["loop"]["cycles"] + 2000, 30, "cycles")
        st = status(sock)
        assert st["axes"]["X"]["state"] == "enabled", st["axes"]["X"]
        assert abs(st["axes"]["X"]["following_error_m"]) < 1e-3, st["axes"]["X"]
    finally:
        daemon.kill()
        emu.__exit__(None, None, None)
