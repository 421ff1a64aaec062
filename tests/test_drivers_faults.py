"""Fault injection per transport, through ``motorctl run`` against ``motorctl emulate --fault``
(one run per transport):

* dropped, corrupted, late and stale replies and exception responses below the leaky-bucket
  limit keep both axes running, and each kind is counted by the driver (run-log header);
* then a lasting loss (serial: the link is disconnected; CAN: the node goes bus-off; Modbus:
  the TCP connection is dropped) fills the bucket: the axis faults and its output is 0 V with
  the amplifier disabled in the very cycle the fault latches, and nothing re-enables it.

The run is in lockstep with the device (``loop.clock: virtual``) with a 0.1 s read timeout,
late answers 0.2 s late and a 5 s command watchdog in the device, so that what the test counts
is what the emulator was told to do, not the host's scheduling: a loaded host holds either
process off for tens of milliseconds at times (now and then for more: a read timed out by the
host adds 10 to the error bucket of 100 and stays below it), and never for the 5 s the device
waits for a command before it faults its amplifier.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml
from conftest import RIGID_PLANT

from motorctl.loop.records import MODE_IDLE
from motorctl.loop.safety import FAULT_IO_ERROR
from motorctl.recorder.runlog import read_log
from harness import (
    Emulator,
    NetNamespace,
    loopback_e2e_config,
    parse_run_table,
    run_cli,
)

CONFIGS = Path(__file__).resolve().parents[1] / "configs"
PLANT = RIGID_PLANT

#: Below the limit: each burst adds ≤ 10 × (cycles lost) to a bucket of 100, which drains by 1
#: per clean cycle between bursts (60 ms apart: ≥ 60 cycles). Then a lasting loss from
#: LASTING_T on (serial: the link is disconnected; CAN: the node goes bus-off;
#: Modbus: the TCP connection is dropped).
#: All of it happens while both axes are at rest (the first move starts at 0.5 s), so the
#: tracking of the moves plays no part. (kind, time [s], count): the start in commands is
#: time × rate.
TRANSIENT = [("drop", 0.10, 3), ("corrupt", 0.16, 3), ("stale", 0.22, 2), ("exception", 0.28, 2),
             ("late", 0.34, 1)]
#: the read timeout of the lockstep run [s]: longer than any scheduling hiccup of a loaded host
READ_TIMEOUT_S = 0.1
LATE_S = 2 * READ_TIMEOUT_S     # later than the read timeout on every transport
#: the device's command watchdog [s]: far beyond the longest wait of the run (a read timeout),
#: so only the lasting loss stops the axes
WATCHDOG_S = 5.0
LASTING_T = 0.42
#: the run goes on this long after the lasting loss starts [s]: past the bucket's fill (10
#: cycles at ≥ 1 kHz) and short, as every cycle after the loss waits out the read timeout
AFTER_LASTING_S = 0.03
#: the axes' error bucket limit: the driver's default (+10 per failed exchange, −1 per clean
#: one); the planned transient bursts (≤ 3 exchanges, 60 ms apart) stay far below it
BUCKET_LIMIT = 100
LASTING = {"serial": ("disconnect", 1), "can": ("bus_off", 100000), "modbus": ("disconnect", 1)}


def _faults(transport: str, rate: float) -> tuple[list[str], int]:
    out = [f"{kind}:*:{round(t * rate)}:{n}" for kind, t, n in TRANSIENT]
    kind, n = LASTING[transport]
    start = round(LASTING_T * rate)
    return out + [f"{kind}:*:{start}:{n}"], start


@pytest.mark.parametrize("transport", ["serial", "can", "modbus"])
def test_transient_faults_keep_running_and_a_lasting_loss_faults_to_0V_in_the_same_cycle(transport, tmp_path):
    d, cfg, rate = loopback_e2e_config(transport, CONFIGS, tmp_path)
    d["loop"]["clock"] = "virtual"
    d["driver"]["timeout_s"] = READ_TIMEOUT_S
    if "watchdog_s" in d["driver"]:      # serial: the driver sets the device's watchdog
        d["driver"]["watchdog_s"] = WATCHDOG_S
    for ax in d["axes"].values():
        assert ax["limits"].get("error_bucket_limit", BUCKET_LIMIT) == BUCKET_LIMIT
    cfg.write_text(yaml.safe_dump(d, sort_keys=False))
    log_path = tmp_path / "run.log"
    ns = NetNamespace() if transport == "can" else None
    prefix = ns.__enter__().prefix if ns else ()
    try:
        faults, lasting_start = _faults(transport, rate)
        with Emulator(transport, cfg, plant=PLANT, faults=faults, watchdog_s=WATCHDOG_S,
                      late_s=LATE_S, prefix=prefix) as emu:
            duration = f"{LASTING_T + AFTER_LASTING_S:.3f}"
            r = run_cli(["run", str(cfg), "--controller", "c2", "--duration", duration, "--log", str(log_path)],
                        prefix=prefix, timeout_s=90)
            err = emu.stderr()
    finally:
        if ns:
            ns.__exit__(None, None, None)
    assert log_path.exists(), f"{r.stdout}\n{r.stderr}\n{err}"
    log = read_log(str(log_path))
    # the job ran and the axes faulted; the link is gone at the end, so no device confirms the
    # stop: exit 3 and one line per axis saying so (never the "at 0 V, amplifiers off" line)
    assert r.returncode == 3, r.stdout + r.stderr
    assert all(f"axis {a}: the stop is NOT confirmed by the device" in r.stderr for a in "XY"), r.stderr
    assert "amplifiers off" not in r.stdout, r.stdout
    table = parse_run_table(r.stdout)
    c = log.header["driver"]["counters"]
    # every transient kind was seen and counted by the driver ...
    assert c["timeouts"] >= 3 + 1, c                         # the drops and the late answer
    assert c["bad_frames"] >= 3, c                           # corrupted: bad CRC / short / undecodable
    assert c["stale"] >= 2 + 1, c                            # stale answers and the late one arriving
    assert c["exceptions"] >= 2, c                           # exception responses / error frames
    for a in ("X", "Y"):
        assert "driver error bucket full" in table[a]["fault"], r.stdout
        bits = log.col(f"{a}.fault_bits").astype(int)
        enabled = log.col(f"{a}.enabled")
        u = log.col(f"{a}.u")
        k = int(np.argmax(bits != 0))
        # the run starts with idle cycles (0 V, amplifier off) that read where the axis stands
        mode = log.col(f"{a}.mode")
        k0 = int(np.argmax(mode != MODE_IDLE))
        assert k0 >= 1 and (enabled[:k0] == 0.0).all() and (u[:k0] == 0.0).all(), (a, mode[:k0 + 1])
        # ... without stopping the axis: no fault, never disabled, until the lasting loss
        why = f"{a}: first fault {bits[k]} at cycle {k}, lasting loss from command {lasting_start}; {c}"
        assert bits[k] == FAULT_IO_ERROR and not bits[:k].any() and enabled[k0:k].min() == 1.0, why
        # the loss starts with command `lasting_start` (answered in the next cycle); the bucket
        # (+10 per failed exchange, limit BUCKET_LIMIT) is full after BUCKET_LIMIT / 10 cycles
        assert lasting_start + 1 <= k <= lasting_start + 1 + BUCKET_LIMIT // 10 + 5, why
        # 0 V and amplifier off in the very cycle the fault latches, and from then on
        assert u[k] == 0.0 and enabled[k] == 0.0
        assert (u[k:] == 0.0).all() and (enabled[k:] == 0.0).all()
