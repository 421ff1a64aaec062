"""The protection's margins on a config (docs/protection.md): every controller ``compare``
runs (C1, C2 and the PID when configured), on the virtual clock, and per axis the I²t
accumulator's peak and the largest RMS of u in a window at rest, each as the ratio of the
trip level to it (14x: the run stays 14 times below the trip); then an unstable gain (X on C2,
k_s 250, k1 1800: a limit cycle at rest) and when its fault latched after the reference came
to rest; and Y on the PID at ω_n 1400 rad/s (integral corner ω_n/3) for every ζ of the PID's
family, 20 s each: the largest RMS of u in a window at rest, the fault and when it latched.

    python benchmarks/protection_margins.py [configs/gantry.yaml] [duration_s (40)]

Prints the table; the last figures are quoted in docs/protection.md.
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import numpy as np

from motorctl.app.job import run_job
from motorctl.cli.run import compared_controllers
from motorctl.config import config_from_dict, load_yaml
from motorctl.recorder.runlog import read_log

UNSTABLE = {"k_s": 250.0, "k1": 1800.0}


def margins(path: str, duration_s: float) -> None:
    loaded = config_from_dict(load_yaml(path), path)
    print(f"{path}, {duration_s:g} s per controller (virtual clock)")
    print(f"{'axis':4} {'ctrl':5} {'e_M um':>8} {'e_F um':>8} {'L2 um':>7} {'I2t peak V2s':>13} "
          f"{'limit/peak':>10} {'rest RMS V':>10} {'limit/RMS':>9}  fault")
    for kind in compared_controllers(loaded):
        res = run_job(loaded, controller=kind, duration_s=duration_s, clock="virtual")
        for a, r in res.axes.items():
            ri = r["i2t_limit_V2s"] / r["i2t_peak_V2s"] if r["i2t_peak_V2s"] > 0 else float("inf")
            ro = r["rest_rms_limit_V"] / r["rest_rms_peak_V"] if r["rest_rms_peak_V"] > 0 else float("inf")
            print(f"{a:4} {kind:5} {r['e_M_um']:8.2f} {r['e_F_um']:8.2f} {r['L2_um']:7.3f} "
                  f"{r['i2t_peak_V2s']:13.3f} {ri:9.1f}x {r['rest_rms_peak_V']:10.3f} {ro:8.1f}x  "
                  f"{r['fault'] or '-'}")


def unstable(path: str, duration_s: float) -> None:
    data = load_yaml(path)
    data["axes"]["X"]["controller"].update(UNSTABLE)
    loaded = config_from_dict(data, path)
    with tempfile.TemporaryDirectory() as tmp:
        log = str(Path(tmp) / "unstable.log")
        res = run_job(loaded, axes=["X"], controller="c2", duration_s=duration_s, clock="virtual", log_path=log)
        rl = read_log(log)
    t, fb, u, en, vd = (rl.col(c) for c in ("t", "X.fault_bits", "X.u", "X.enabled", "X.xd_dot"))
    k = int(np.argmax(fb != 0))
    moving = np.nonzero(vd[:k] != 0.0)[0]
    rest = t[moving[-1] + 1] if moving.size else t[0]
    print(f"X on C2 k_s {UNSTABLE['k_s']:g}, k1 {UNSTABLE['k1']:g}: {res.axes['X']['fault']}; latched at "
          f"t = {t[k]:.4f} s, {t[k] - rest:.4f} s after the reference came to rest; after it |u| <= "
          f"{np.abs(u[k:]).max():g} V, enable {en[k:].max():g}")


def pid_at(path: str, axis: str = "Y", w_n: float = 1400.0, r: float = 3.0, duration_s: float = 20.0) -> None:
    from motorctl.commission.verify import apply_gains
    from motorctl.control.pid import PID
    data = load_yaml(path)
    theta1 = float(data["axes"][axis]["controller"]["theta_hat0"][0])
    for g in PID.gain_family(theta1, None, [w_n]):
        if g["_r"] != r:
            continue
        loaded = config_from_dict(apply_gains(data, axis, "pid", g), path)
        with tempfile.TemporaryDirectory() as tmp:
            log = str(Path(tmp) / "pid.log")
            res = run_job(loaded, axes=[axis], controller="pid", duration_s=duration_s, clock="virtual",
                          log_path=log)
            fb, t = read_log(log).col(f"{axis}.fault_bits"), read_log(log).col("t")
        a = res.axes[axis]
        k = int(np.argmax(fb != 0))
        when = f" at t = {t[k]:.2f} s" if fb[k] else ""
        print(f"{axis} on PID w_n {w_n:g}, zeta {g['_zeta']:g}, r {r:g} ({duration_s:g} s): largest u RMS in a "
              f"window at rest {a['rest_rms_peak_V']:.2f} V; {a['fault'] or 'no fault'}{when}")


if __name__ == "__main__":
    cfg = sys.argv[1] if len(sys.argv) > 1 else "configs/gantry.yaml"
    dur = float(sys.argv[2]) if len(sys.argv) > 2 else 40.0
    unstable(cfg, 20.0)
    pid_at(cfg)
    margins(cfg, dur)
