"""Law versus law with the gains ``motorctl autotune`` chose: C1, C2 and PID+FF on the nominal
plant and on scenarios run *without retuning*; and (``--search``) how close autotune's gains
come to the best a grid search over each law's gains finds under the same constraints.

Rerun:
    motorctl autotune configs/gantry.yaml --axis X --axis Y --out runs/autotune-gantry --virtual-clock
    python benchmarks/compare_laws.py runs/autotune-gantry/autotuned.yaml [--seconds 40] [--search]

Scenarios (the plant of the config's sim driver changed, the controller config untouched):

    u at its limit the plant and program as configured: X the paper's Fig. 3 program (2 m/s,
                   40 m/s²), Y the paper's Y-axis program (1 m/s, 10 m/s²); both need nearly
                   all of the 10 V (u_peak 10 V)
    nominal        the plant as configured, the program at half its acceleration and jerk
                   (X 20 m/s², Y 5 m/s²), so that the scenarios below remain feasible (at the
                   full program X with +5 kg needs 770 N where 10 V gives 576 N)
    (the next three on the half-acceleration program)
    payload +5 kg  mass_kg + 5, the extra mass beyond the structural joint (load share updated)
    Kf -20 %       a1, a2, a3 × 0.8 (a warm coil)
    Fig.2 x2       the force nonlinearity of the paper's Fig. 2 twice as strong (a2, a3 × 2)

Columns: e_M, e_F, L2[e] [µm], u_peak [V], u noise at rest [mV] (RMS of u about its mean where
the command has been still ≥ 0.3 s), saturated samples, fault. Virtual clock, seed of the
config (the same seeded plant for every law).

``--search``: per axis and law, the grid of :func:`motorctl.app.autotune.family` thinned (ω
every 3rd point, ζ ∈ {0.3, 0.5, 0.7}, r ∈ {3, 7}) is run on the nominal plant for ``--search-seconds``
under the rule's closed-loop constraints (no fault, saturation as autotune's verification allows
it: the configured controller of ``--reference`` on the same run + the share, u noise at rest,
no oscillation (u at rest, or e against that run's); margins not required), and the least L2[e] is compared with autotune's gains on the same run length.
"""

from __future__ import annotations

import argparse
import copy
import time

from motorctl.app.autotune import (
    OMEGA,
    admissible,
    apply_gains,
    evaluate,
)
from motorctl.config import config_from_dict, load_yaml

LAWS = (("c1", "C1"), ("c2", "C2"), ("pid", "PID+FF"))


def scenario(raw: dict, axis: str, name: str) -> dict:
    raw = copy.deepcopy(raw)
    d = raw["axes"][axis]["driver"]
    if name != "u at its limit":
        tr = raw["axes"][axis]["trajectory"]
        tr["a_max"] *= 0.5
        tr["j_max"] *= 0.5
    if name == "payload +5 kg":
        m = d["mass_kg"]
        if d.get("mode_hz", 0.0) > 0.0:
            f = d.get("mode_load_fraction", 0.3)
            d["mode_load_fraction"] = (f * m + 5.0) / (m + 5.0)
        d["mass_kg"] = m + 5.0
    elif name == "Kf -20 %":
        for k in ("a1_N_per_V", "a2_N_per_V2", "a3_N_per_V3"):
            d[k] = d.get(k, 0.0) * 0.8
    elif name == "Fig.2 x2":
        for k in ("a2_N_per_V2", "a3_N_per_V3"):
            d[k] = d.get(k, 0.0) * 2.0
    return raw


SCENARIOS = ("u at its limit", "nominal", "payload +5 kg", "Kf -20 %", "Fig.2 x2")


def table(raw, source, seconds):
    print("| axis | scenario | law | e_M µm | e_F µm | L2[e] µm | u_peak V | u noise at rest mV | sat | fault |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for axis in raw["axes"]:
        for sc in SCENARIOS:
            r = scenario(raw, axis, sc)
            for law, label in LAWS:
                res = evaluate(r, source, axis, law, seconds)
                print(f"| {axis} | {sc} | {label} | {res['e_M_um']:.2f} | {res['e_F_um']:.2f} | "
                      f"{res['L2_um']:.3f} | {res['u_peak_V']:.2f} | {res['u_rest_rms_V'] * 1e3:.0f} | "
                      f"{res['saturated']} | {res['fault'] or '-'} |", flush=True)


def search(raw, source, seconds, reference):
    """Grid search per axis and law (module docstring); the saturation allowance is the one of
    the autotune verification: the configured controller of ``reference`` on the same run."""
    print(f"\n## autotune vs grid search ({seconds:g} s runs, nominal plant)")
    ref_raw = load_yaml(reference)
    ref_raw["loop"]["realtime"]["policy"] = "off"
    print("| axis | law | autotune L2 µm | best grid L2 µm | best gains | ratio |")
    print("|---|---|---|---|---|---|")
    for axis in raw["axes"]:
        loaded = config_from_dict(raw, source)
        sec = loaded.axes[axis].controller
        th1 = float(raw["axes"][axis]["controller"]["pid"]["FF2"])   # autotune's fitted θ1
        u_lim = sec.u_lim
        ref = evaluate(ref_raw, reference, axis, ref_raw["axes"][axis]["controller"].get("type", "c2"),
                       seconds)
        for law, label in LAWS:
            mine = evaluate(raw, source, axis, law, seconds)
            best = None
            for w in OMEGA[::3]:
                for z in (0.3, 0.5, 0.7):
                    for r in ((3.0, 7.0) if law == "pid" else (None,)):
                        if law == "pid":
                            p = th1 * w * w
                            g = {"P": p, "I": p * w / r, "D": 2 * z * w * th1}
                        else:
                            g = {"k_s": 2 * z * w * th1, "k1": w / (2 * z)}
                        res = evaluate(apply_gains(raw, axis, law, g), source, axis, law, seconds)
                        if admissible(res, u_lim, ref):
                            continue
                        if best is None or res["L2_um"] < best[0]:
                            best = (res["L2_um"], g)
            why = admissible(mine, u_lim, ref)
            ok = f" ({why})" if why else ""
            gs = ", ".join(f"{k} {v:.4g}" for k, v in best[1].items()) if best else "-"
            bl = f"{best[0]:.3f}" if best else "-"
            ratio = f"{mine['L2_um'] / best[0]:.2f}" if best else "-"
            print(f"| {axis} | {label} | {mine['L2_um']:.3f}{ok} | {bl} | {gs} | {ratio} |", flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("config", help="the autotuned config (motorctl autotune ... --out DIR: DIR/autotuned.yaml)")
    ap.add_argument("--seconds", type=float, default=40.0)
    ap.add_argument("--search", action="store_true")
    ap.add_argument("--search-seconds", type=float, default=8.0)
    ap.add_argument("--no-table", action="store_true", help="with --search: only the search")
    ap.add_argument("--reference", default="configs/gantry.yaml",
                    help="with --search: the config autotune ran on (its controller's saturation is the allowance)")
    args = ap.parse_args()
    raw = load_yaml(args.config)
    raw["loop"]["realtime"]["policy"] = "off"
    t0 = time.time()
    print(f"# rerun: python benchmarks/compare_laws.py {args.config} --seconds {args.seconds:g}"
          + (f" --search --search-seconds {args.search_seconds:g}" if args.search else "")
          + (" --no-table" if args.no_table else ""))
    if not args.no_table:
        table(raw, args.config, args.seconds)
    if args.search:
        search(raw, args.config, args.search_seconds, args.reference)
    print(f"# {time.time() - t0:.0f} s")


if __name__ == "__main__":
    main()
