"""Commissioning of C1/C2 (k_s, k1) and of the PID+FF (P, I, D) on a config, the same way for
each controller: the gains in configs/gantry.yaml come from this script.

Rerun:  python benchmarks/tune_gains.py [--config configs/gantry.yaml] [--seconds 4] [--axis X]

What the commissioning engineer knows: the plant's frequency response (FRF) from u [V] to the
encoder, as a sine sweep on the machine would measure it (here computed from the simulated
plant's linear part: A1, the viscous B, the structural mode, the current loop and its delay,
the zero-order hold with its aliases; Coulomb friction and quantisation left out), the
catalogue model θ̂(0) for the PID's feedforward (as benchmarks/tune_pid.py), Ts, u_lim.

The linear feedback of each law, z = e^{jωTs}, Δ = (1 − z⁻¹)/Ts (backward difference):

    PID     C(z) = P + I Ts/(1 − z⁻¹) + D Δ                         (motorctl/control/pid.py)
    C1, C2  C(z) = (k_s + γ_d Ts/(1 − z⁻¹)) (k1 + Δ)                 v_s = −k_s p, d̂0 += Ts γ_d p
                                                                    (motorctl/control/dcdiarc.py;
                                                                    adaptation left out: slow)

Acceptance rule (every line), loop L = C(z) G_zoh(z):

    M1 margins      gain margin ≥ 6 dB, phase margin ≥ 30°, sensitivity peak |S|max ≤ 6 dB
                    (GM over the −180° crossings where |L| < 1, PM over all |L| = 1 crossings)
    M2 closed loop  a run of --seconds of the axis's program on the simulated plant (virtual
                    clock, the seed of ``motorctl compare``): no fault (following error, limits)
    M3 rest noise   u at rest (command still ≥ 0.3 s): RMS about its mean ≤ 2 % of u_lim (0.2 V: the D term sees
                    one-count toggles of the noisy encoder as D q/Ts; no limit cycle)
    choice          the admissible candidate of least L2[e] on that run; C1 and C2 share one
                    (k_s, k1) per axis (one ``controller:`` section, as in the paper): chosen on
                    C2, and C1 must pass M2-M3 with it too (else the next candidate)

Grid: C1/C2 k_s × k1 below with γ_d = the config's; PID ω_n × ζ × r as tune_pid.py
(P = θ̂1 ω_n², D = 2 ζ ω_n θ̂1, I = P ω_n / r, maxerror_i = 1 V / I).
"""

from __future__ import annotations

import argparse
import copy
import itertools
import math
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from tune_pid import candidate as pid_candidate  # noqa: E402
from tune_pid import catalogue_ff, run_axis  # noqa: E402

from motorctl.config import config_from_dict, load_yaml  # noqa: E402

KS = (50.0, 95.0, 150.0, 200.0, 300.0, 400.0)                 # [V s/m]
K1 = (100.0, 250.0, 500.0, 1000.0, 2000.0, 3333.0)            # [1/s]
OMEGA_N = (100.0, 150.0, 200.0, 300.0, 400.0, 500.0, 600.0, 800.0, 1000.0)   # [rad/s]
ZETA = (0.5, 0.7, 1.0)
R_INT = (3.0, 5.0, 10.0)
GM_MIN_DB, PM_MIN_DEG, MS_MAX_DB = 6.0, 30.0, 6.0
REST_FRACTION = 0.02


def plant_frf(opt, ts: float, w: np.ndarray, n_alias: int = 60) -> np.ndarray:
    """Discrete FRF G_zoh(e^{jωTs}) [m/V] of the axis plant (linear part) under the ZOH.

    Args: opt: the axis's SimAxisOptions. ts: period [s]. w: frequencies [rad/s] (< π/ts).
    """
    mc, ml, k, c = opt.mode_coefficients()
    b = opt.viscous_N_s_per_m
    ti = 1.0 / (2 * math.pi * opt.current_loop_hz) if opt.current_loop_hz > 0 else 0.0
    tot = opt.current_loop_delay_s + opt.input_delay_s
    ws = 2 * math.pi / ts
    acc = np.zeros_like(w, dtype=complex)
    for a in range(-n_alias, n_alias + 1):
        s = 1j * (w + a * ws)
        if ml > 0:
            den = (mc * s * s + b * s) * (ml * s * s + c * s + k) + (c * s + k) * ml * s * s
            g = (ml * s * s + c * s + k) / den
        else:
            g = 1.0 / (opt.mass_kg * s * s + b * s)
        g = g * opt.a1_N_per_V * np.exp(-s * tot) / (1.0 + s * ti)
        acc += g / (s * ts)
    return acc * (1.0 - np.exp(-1j * w * ts))


def margins(L: np.ndarray) -> tuple[float, float, float]:
    """(GM [dB], PM [deg], |S|max [dB]) of a loop FRF sampled on an increasing grid."""
    mag, ph = np.abs(L), np.angle(L)
    gm = math.inf
    cross = np.where((np.sign(L.imag[:-1]) != np.sign(L.imag[1:])) & (L.real[:-1] < 0))[0]
    for i in cross:
        if mag[i] < 1.0:
            gm = min(gm, -20 * math.log10(mag[i]))
    pm = math.inf
    for i in np.where(np.sign(mag[:-1] - 1.0) != np.sign(mag[1:] - 1.0))[0]:
        pm = min(pm, 180.0 + math.degrees(ph[i]) if ph[i] <= 0 else 180.0 - math.degrees(ph[i]))
    ms = 20 * math.log10(np.max(1.0 / np.abs(1.0 + L)))
    return gm, pm, ms


def c_frf(kind: str, g: dict, ts: float, w: np.ndarray) -> np.ndarray:
    zi = np.exp(-1j * w * ts)
    delta = (1.0 - zi) / ts
    integ = ts / (1.0 - zi)
    if kind == "pid":
        return g["P"] + g["I"] * integ + g["D"] * delta
    return (g["k_s"] + g["gamma_d"] * integ) * (g["k1"] + delta)


def run_c(raw, source, axis, kind, seconds, g):
    raw = copy.deepcopy(raw)
    raw["axes"][axis]["controller"].update({"k_s": g["k_s"], "k1": g["k1"]})
    return run_axis(raw, source, axis, kind, seconds)


def tune_axis(raw: dict, source: str, axis: str, seconds: float) -> dict:
    loaded = config_from_dict(raw, source)
    sec, ts = loaded.axes[axis].controller, loaded.period_s
    opt = loaded.axis_driver_options[axis]
    w = np.logspace(math.log10(2 * math.pi * 0.5), math.log10(0.999 * math.pi / ts), 6000)
    G = plant_frf(opt, ts, w)
    u_rest = REST_FRACTION * sec.u_lim
    print(f"\n## axis {axis}: Ts = {ts * 1e3:g} ms, u_lim = {sec.u_lim:g} V, {seconds:g} s runs; "
          f"plant: mode {opt.mode_hz:g} Hz, current loop {opt.current_loop_hz:g} Hz, "
          f"delay {opt.current_loop_delay_s * 1e6:g} us")
    chosen = {}
    for kind in ("c2", "pid"):
        if kind == "c2":
            grid = [{"k_s": ks, "k1": k1, "gamma_d": sec.settings("c2").gamma_d} for ks, k1 in itertools.product(KS, K1)]
        else:
            grid = []
            for wn, z, r in itertools.product(OMEGA_N, ZETA, R_INT):
                g = pid_candidate(sec, wn, z, r)
                g["_label"] = f"w_n {wn:g} zeta {z:g} r {r:g}"
                grid.append(g)
        print(f"\n### {kind.upper()} ({len(grid)} candidates)")
        print(f"{'gains':<44} {'GM dB':>6} {'PM deg':>6} {'|S| dB':>6} {'e_M um':>7} {'L2 um':>7} "
              f"{'u_pk V':>6} {'rest mV':>7}  verdict")
        best = None
        for g in grid:
            label = (f"k_s {g['k_s']:g} k1 {g['k1']:g}" if kind == "c2"
                     else f"{g['_label']}: P {g['P']:.4g} I {g['I']:.4g} D {g['D']:.4g}")
            gm, pm, ms = margins(c_frf(kind, g, ts, w) * G)
            if gm < GM_MIN_DB or pm < PM_MIN_DEG or ms > MS_MAX_DB:
                print(f"{label:<44} {gm:6.1f} {pm:6.1f} {ms:6.1f} {'':>7} {'':>7} {'':>6} {'':>7}  fails M1")
                continue
            pid = {k: v for k, v in g.items() if not k.startswith("_")} if kind == "pid" else None
            res = (run_c(raw, source, axis, "c2", seconds, g) if kind == "c2"
                   else run_axis(raw, source, axis, "pid", seconds, pid))
            fails = []
            if res["fault"]:
                fails.append("M2")
            if not res["u_rest_rms_V"] <= u_rest:
                fails.append("M3")
            if kind == "c2" and not fails:
                r1 = run_c(raw, source, axis, "c1", seconds, g)
                if r1["fault"] or not r1["u_rest_rms_V"] <= u_rest:
                    fails.append("C1")
            print(f"{label:<44} {gm:6.1f} {pm:6.1f} {ms:6.1f} {res['e_M_um']:7.2f} {res['L2_um']:7.3f} "
                  f"{res['u_peak_V']:6.2f} {res['u_rest_rms_V'] * 1e3:7.1f}  "
                  f"{'ok' if not fails else 'fails ' + ','.join(fails)}", flush=True)
            if not fails and (best is None or (res["L2_um"], res["e_M_um"]) < best[0]):
                best = ((res["L2_um"], res["e_M_um"]), label, g, res, (gm, pm, ms))
        if best is None:
            print(f"no {kind} candidate passes on axis {axis}")
            continue
        _, label, g, res, (gm, pm, ms) = best
        print(f"chosen {kind.upper()} on {axis}: {label}; GM {gm:.1f} dB, PM {pm:.1f} deg, |S| {ms:.1f} dB; "
              f"e_M {res['e_M_um']:.2f} um, L2 {res['L2_um']:.3f} um, rest {res['u_rest_rms_V'] * 1e3:.1f} mV")
        chosen[kind] = g
    return chosen


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default="configs/gantry.yaml")
    ap.add_argument("--seconds", type=float, default=4.0, help="program seconds per run (one period)")
    ap.add_argument("--axis", action="append", help="tune only this axis (repeatable)")
    args = ap.parse_args()
    raw = load_yaml(args.config)
    axes = args.axis or list(raw["axes"])
    t0 = time.time()
    print(f"# gain commissioning, {time.strftime('%Y-%m-%d %H:%M:%S')}")
    print(f"# rerun: python benchmarks/tune_gains.py --config {args.config} --seconds {args.seconds:g}"
          + "".join(f" --axis {a}" for a in (args.axis or [])))
    print(__doc__[__doc__.index("Acceptance rule"):].rstrip())
    print(f"grid C1/C2: k_s {KS} x k1 {K1}; PID: w_n {OMEGA_N} x zeta {ZETA} x r {R_INT}")
    out = {a: tune_axis(raw, args.config, a, args.seconds) for a in axes}
    print("\n## chosen gains")
    for a, ch in out.items():
        if "c2" in ch:
            print(f"axes.{a}.controller: k_s: {ch['c2']['k_s']:g}, k1: {ch['c2']['k1']:g}")
        if "pid" in ch:
            g = ch["pid"]
            print(f"axes.{a}.controller.pid: " + ", ".join(
                f"{k}: {float(f'{g[k]:.4g}')!r}" for k in ("P", "I", "D", "FF1", "FF2", "bias", "maxerror_i")))
    print(f"# {time.time() - t0:.0f} s")


if __name__ == "__main__":
    main()
