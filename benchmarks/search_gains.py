"""An independent search over each law's gains, by the user's own path (``motorctl run --json``,
40 s = ten program periods on the virtual clock), to judge ``motorctl autotune``'s choice.

Independent of autotune: no autotune module is imported, its gain family, grid and pass rule
are not used, and its own point is not among the searched ones. Per law and axis, in log space
(C1/C2: k_s, k1 with γ_d as configured; PID+FF: P, D and the integral corner ω_i = I/P, the
integral clamp 1 V / I, FF as in the compared config): a scrambled Sobol design
(scipy.stats.qmc.Sobol, fixed seed) over a wide box, then Nelder-Mead (scipy.optimize.minimize)
from the best point that met the constraints, L2[e] plus a penalty for a violation; with
``--rounds 2`` once more, a Sobol design in a box of ±0.3 decade around the best so far and
Nelder-Mead from its best.

The constraints (the shipped C2's 40 s run on the same axis as the reference): no fault, u RMS
at rest ≤ 1.5× the reference's, saturated samples ≤ 1.5 × max(the reference's, 10); with
``--floor`` also the margin floor (GM ≥ 6 dB, PM ≥ 10°, |S| ≤ 16 dB at 100, 75 and 50 % of the
loop gain) on the true plant, the simulated axis's own parameters (not autotune's
measurement), as a constraint of the search itself: the Sobol design is drawn from the points
that hold it (a cheap check before any run) and a Nelder-Mead step onto a point that fails it
is not run (it scores as a violation). Without it the search may find gains with smaller
margins than autotune admits.

Run (about 7 s per run on an idle core; --sobol 16 --nm 24: 40 runs per law and axis):
    python benchmarks/search_gains.py configs/gantry.yaml --axis X --axis Y \
        --autotuned runs/autotune-gantry/autotuned.yaml --json runs/search_gains.json
It prints, per law and axis: autotune's L2[e] and constraints (its written gains, run the same
way), the search's best, the ratio autotune / search.
"""

from __future__ import annotations

import argparse
import contextlib
import copy
import io
import itertools
import json
import math
import os
import sys
import tempfile

import numpy as np
import yaml
from scipy import optimize
from scipy.stats import qmc

LAWS = ("c1", "c2", "pid")
#: log10 box per law: (key, low, high); PID's "wi" is I/P [rad/s]
BOX = {"c1": (("k_s", 0.5, 3.5), ("k1", 1.7, 3.8)),
       "c2": (("k_s", 0.5, 3.5), ("k1", 1.7, 3.8)),
       "pid": (("P", 3.5, 6.0), ("D", 0.7, 3.0), ("wi", 1.0, 3.0))}
PENALTY = 100.0
FLOOR = (6.0, 10.0, 16.0)   #: GM >= [dB], PM >= [deg], |S| <= [dB] (--floor)


def run(raw: dict, axis: str, law: str, seconds: float) -> dict:
    """``motorctl run CONFIG --axis A --controller LAW --duration S --virtual-clock --json`` on the
    config dict (a temporary file), through the CLI's own entry point in this process (the
    same code as the command, without a Python start-up per run)."""
    from motorctl.cli import main as motorctl_main
    with tempfile.NamedTemporaryFile("w", suffix=".yaml", delete=False) as f:
        yaml.safe_dump(raw, f)
        path = f.name
    buf = io.StringIO()
    try:
        with contextlib.redirect_stdout(buf):
            motorctl_main(["run", path, "--axis", axis, "--controller", law, "--duration", str(seconds),
                           "--virtual-clock", "--json"])
    except SystemExit:
        pass
    finally:
        os.unlink(path)
    try:
        return json.loads(buf.getvalue().strip().splitlines()[-1])["axes"][axis]
    except (ValueError, KeyError, IndexError):
        return {"fault": "run failed", "L2_um": math.nan}


def with_gains(raw: dict, axis: str, law: str, x: np.ndarray) -> dict:
    raw = copy.deepcopy(raw)
    sec = raw["axes"][axis]["controller"]
    v = {k: float(10.0 ** xi) for (k, _, _), xi in zip(BOX[law], x)}
    if law == "pid":
        pid = sec["pid"]
        pid.update(P=v["P"], D=v["D"], I=v["P"] * v["wi"], maxerror_i=1.0 / (v["P"] * v["wi"]))
    else:
        own = dict(sec.get(law) or {})
        own.update(k_s=v["k_s"], k1=v["k1"])
        sec[law] = own
    return raw


def true_plant(raw: dict, axis: str) -> dict:
    """The simulated axis's own parameters (its ``driver:`` section) as the plant model of
    :func:`motorctl.commission.loopshape.plant_model_frf`: the plant the search runs on, not
    autotune's measurement or fit."""
    d = raw["axes"][axis]["driver"]
    a1 = float(d["a1_N_per_V"])
    return {"theta1": float(d["mass_kg"]) / a1, "theta2": float(d.get("viscous_N_s_per_m", 0.0)) / a1,
            "mode_hz": float(d.get("mode_hz", 0.0)), "mode_damping": float(d.get("mode_damping", 0.0)),
            "load_fraction": float(d.get("mode_load_fraction", 0.0)),
            "current_loop_hz": float(d.get("current_loop_hz", 0.0)) or 1e9,
            "delay_s": float(d.get("current_loop_delay_s", 0.0))}


def floor_holds(raw: dict, axis: str, law: str, gains: dict) -> bool:
    """The margin floor (GM >= 6 dB, PM >= 10 deg, |S| <= 16 dB) at 100, 75 and 50 % of the
    loop gain, on the true plant (:func:`true_plant`) with the law's own linearisation."""
    from motorctl.commission.loopshape import c_frf, loop_margins, plant_model_frf
    ts = 1.0 / float(raw["loop"]["rate_hz"])
    w = np.geomspace(2.0 * math.pi, 0.999 * math.pi / ts, 4000)
    th = raw["axes"][axis]["controller"].get("theta_hat0")
    L = c_frf(law, gains, ts, w, th) * plant_model_frf(true_plant(raw, axis), ts, w)
    return all(loop_margins(sc * L, w / (2.0 * math.pi)).meets(*FLOOR) for sc in (1.0, 0.75, 0.5))


def gains_of(raw: dict, axis: str, law: str, x) -> dict:
    sec = with_gains(raw, axis, law, np.asarray(x))["axes"][axis]["controller"]
    return dict(sec["pid"]) if law == "pid" else {k: float(sec[law][k]) for k in ("k_s", "k1")} | {
        "gamma_d": float(sec[law].get("gamma_d", sec.get("gamma_d", 500.0)))}


def violation(res: dict, ref: dict) -> str:
    """'' when a run meets the constraints, else what failed."""
    if res.get("fault"):
        return f"fault: {res['fault']}"
    sat_max = int(1.5 * max(ref["saturated"], 10))
    if res["saturated"] > sat_max:
        return f"saturated {res['saturated']} > {sat_max}"
    rest_max = 1.5 * ref["u_rest_rms_V"]
    if not (res["u_rest_rms_V"] or 0.0) <= rest_max:
        return f"u rest {res['u_rest_rms_V'] * 1e3:.0f} > {rest_max * 1e3:.0f} mV"
    return ""


def design(raw, axis, law, lo, hi, n, seed, floor):
    """``n`` points of a scrambled Sobol sequence (fixed ``seed``) in the log box [lo, hi]; with
    ``floor``, the first ``n`` of the sequence whose margins hold the floor (:func:`floor_holds`,
    a cheap check on the true plant): the design's runs are all spent where the constraint
    holds (up to 64·n points are drawn; fewer than ``n`` when the floor admits so little)."""
    pts = lo + qmc.Sobol(len(lo), scramble=True, seed=seed).random(n if not floor else 64 * n) * (hi - lo)
    if not floor:
        return list(pts)
    return list(itertools.islice((x for x in pts if floor_holds(raw, axis, law, gains_of(raw, axis, law, x))), n))


def search(raw, axis, law, ref, seconds, n_sobol, n_nm, say, rounds=1, floor=False):
    box = BOX[law]
    lo, hi = np.array([b[1] for b in box]), np.array([b[2] for b in box])
    seen = []

    def f(x):
        x = np.clip(x, lo, hi)
        if floor and not floor_holds(raw, axis, law, gains_of(raw, axis, law, x)):
            return 2.0 * PENALTY                  # not run: the margins fail on the true plant
        res = run(with_gains(raw, axis, law, x), axis, law, seconds)
        why = violation(res, ref)
        l2 = res.get("L2_um", math.nan)
        seen.append((x.copy(), l2, why, res))
        say(f"  {axis} {law} " + " ".join(f"{k} {10 ** xi:.4g}" for (k, _, _), xi in zip(box, x))
            + f": L2 {l2:.3f} um, sat {res.get('saturated')}, rest {1e3 * (res.get('u_rest_rms_V') or 0):.0f} mV"
            + f" {why or 'ok'}")
        if why or not math.isfinite(l2):
            return PENALTY + (l2 if math.isfinite(l2) else PENALTY)
        return l2

    for x in design(raw, axis, law, lo, hi, n_sobol, 44, floor):
        f(x)
    ok = [s for s in seen if not s[2] and math.isfinite(s[1])]
    if ok and n_nm > 0:
        x0 = min(ok, key=lambda s: s[1])[0]
        simplex = [x0] + [x0 + np.eye(len(box))[j] * 0.15 * (hi - lo)[j] for j in range(len(box))]
        optimize.minimize(f, x0, method="Nelder-Mead",
                          options={"maxfev": n_nm, "initial_simplex": np.array(simplex), "xatol": 0.01})
    for _ in range(rounds - 1):      # a narrower design around the best so far, then Nelder-Mead again
        ok = [s for s in seen if not s[2] and math.isfinite(s[1])]
        if not ok:
            break
        c = min(ok, key=lambda s: s[1])[0]
        lo2, hi2 = np.maximum(lo, c - 0.3), np.minimum(hi, c + 0.3)
        for x in design(raw, axis, law, lo2, hi2, n_sobol, 45, floor):
            f(x)
        ok = [s for s in seen if not s[2] and math.isfinite(s[1])]
        x0 = min(ok, key=lambda s: s[1])[0]
        simplex = [x0] + [x0 + np.eye(len(box))[j] * 0.05 * (hi - lo)[j] for j in range(len(box))]
        optimize.minimize(f, x0, method="Nelder-Mead",
                          options={"maxfev": n_nm, "initial_simplex": np.array(simplex), "xatol": 0.005})
    ok = [s for s in seen if not s[2] and math.isfinite(s[1])]
    best = min(ok, key=lambda s: s[1]) if ok else None
    return best, len(seen)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("config")
    ap.add_argument("--axis", action="append", required=True)
    ap.add_argument("--law", action="append", choices=LAWS)
    ap.add_argument("--autotuned", help="autotune's written config: its gains are run the same way and "
                                        "its PID feedforward is used in the search")
    ap.add_argument("--seconds", type=float, default=40.0)
    ap.add_argument("--sobol", type=int, default=16)
    ap.add_argument("--nm", type=int, default=24)
    ap.add_argument("--floor", action="store_true",
                    help="only gains whose margins hold at 100/75/50 %% on the true plant (the sim's "
                         "parameters): GM >= 6 dB, PM >= 10 deg, |S| <= 16 dB")
    ap.add_argument("--rounds", type=int, default=1,
                    help="design + Nelder-Mead rounds; each after the first in a box of +-0.3 decade "
                         "around the best so far")
    ap.add_argument("--json", help="write the table here")
    a = ap.parse_args(argv)
    raw = yaml.safe_load(open(a.config))
    tuned = yaml.safe_load(open(a.autotuned)) if a.autotuned else None

    def say(s):
        print(s, flush=True)

    rows = []
    for axis in a.axis:
        ref = run(raw, axis, "c2", a.seconds)           # the shipped C2: the constraints' reference
        say(f"{axis}: shipped C2: L2 {ref['L2_um']:.3f} um, sat {ref['saturated']}, rest "
            f"{ref['u_rest_rms_V'] * 1e3:.0f} mV -> limits sat <= {int(1.5 * max(ref['saturated'], 10))}, "
            f"rest <= {1.5 * ref['u_rest_rms_V'] * 1e3:.0f} mV")
        base = copy.deepcopy(raw)
        if tuned:                                       # the PID's feedforward as autotune fitted it
            ff = {k: v for k, v in (tuned["axes"][axis]["controller"].get("pid") or {}).items()
                  if k.startswith("FF") or k == "bias"}
            base["axes"][axis]["controller"]["pid"].update(ff)
        for law in a.law or LAWS:
            at = None
            if tuned:
                r_at = run(tuned, axis, law, a.seconds)
                at = {"L2_um": r_at.get("L2_um"), "verdict": violation(r_at, ref) or "ok",
                      "saturated": r_at.get("saturated"), "u_rest_rms_V": r_at.get("u_rest_rms_V")}
                say(f"{axis} {law} autotune: L2 {at['L2_um']:.3f} um, sat {at['saturated']}, rest "
                    f"{1e3 * (at['u_rest_rms_V'] or 0):.0f} mV: {at['verdict']}")
            best, n = search(base, axis, law, ref, a.seconds, a.sobol, a.nm, say, a.rounds, a.floor)
            row = {"axis": axis, "law": law, "runs": n, "autotune": at,
                   "search_L2_um": best[1] if best else None,
                   "search_gains": ({k: float(10 ** xi) for (k, _, _), xi in zip(BOX[law], best[0])} if best else None)}
            if at and best and at["verdict"] == "ok":
                row["ratio"] = at["L2_um"] / best[1]
            rows.append(row)
            say(f"{axis} {law}: search best L2 {row['search_L2_um']} um in {n} runs; ratio {row.get('ratio')}")
    print("\n| law / axis | autotune L2[e] (um) | constraints | search best (um) | runs | ratio |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        at = r["autotune"] or {}
        print(f"| {r['axis']} {r['law']} | {at.get('L2_um', float('nan')):.3f} | {at.get('verdict', '-')} | "
              f"{(r['search_L2_um'] or float('nan')):.3f} | {r['runs']} | {r.get('ratio', float('nan')):.2f} |")
    if a.json:
        with open(a.json, "w") as f:
            json.dump(rows, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
