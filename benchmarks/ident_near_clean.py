"""Coverage of ``motorctl identify``'s 95 % intervals of θ1..θ4 on records close to the nominal
model: the share of fits whose stated interval (``augmented.theta_ci95``: the Newey-West σ and
the model error the record shows, in quadrature; motorctl.ident.uncertainty) holds the true θ.

Rerun:
    python benchmarks/ident_near_clean.py                 # 100 fits, 2 jobs, about 3 min on 2 idle cores
    python benchmarks/ident_near_clean.py --fits 20 --jobs 1

The records: :func:`motorctl.ident.synth.numpy_axis` (a rigid axis simulated in numpy, not
motorctl's simulator: exactly the nominal model u = θ1ẍ + θ2ẋ + θ3 S_f(ẋ) − θ4 with M = 12.8 kg,
A1 = 80 N/V, B = 17.6 N·s/m, F_c = 20 N, F_0 = −4 N, under a PD loop with 0.3 V of input noise,
5 kHz), 5 s each, with a white force noise of ``--force-noise`` N RMS and, on every record, the
plant's M, B, F_c, F_0 drawn within ±``--spread`` of those (uniform; "close to the nominal
model"), seeds 1..``--fits``; each identified as ``motorctl identify`` does
(:func:`motorctl.ident.pipeline.identify_record`, zoh 0.5: the axis holds u over the period).
Prints per θ the fits, the coverage of the stated and of the Newey-West interval alone, the
median |error| / σ stated, the median relative error and the median stated half-width; the
total, the names given (a name on these records is a phantom) and identify's CPU time per record.
Exit 0 always (a measurement).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

from motorctl.ident.pipeline import identify_record
from motorctl.ident.synth import NUMPY_AXIS, numpy_axis, numpy_axis_theta

sys.path.insert(0, str(Path(__file__).resolve().parent))

from ident_coverage import covered, run_all  # noqa: E402

THETA = ("theta1", "theta2", "theta3", "theta4")


def one(seed: int, force_noise: float, spread: float, duration: float) -> dict:
    """identify on the record of ``seed``: the true θ (4,), the stated and Newey-West intervals,
    the names given, the CPU seconds of identify."""
    rng = np.random.default_rng(1000 + seed)
    axis = {k: v * (1.0 + spread * rng.uniform(-1.0, 1.0)) for k, v in NUMPY_AXIS.items() if k != "gain_N_per_V"}
    rec = numpy_axis(duration, seed, force_noise_N=force_noise, axis=axis)
    t0 = time.process_time()
    _, s = identify_record(rec, zoh_delay=0.5)
    cpu = time.process_time() - t0
    a = s["augmented"]
    nw = [[v - 1.959963984540054 * sd, v + 1.959963984540054 * sd]
          for v, sd in zip(a["theta_values"], a["theta_std_sampling"])]
    return {"true": numpy_axis_theta(axis).tolist(), "value": a["theta_values"][:4], "stated": a["theta_ci95"][:4],
            "nw": nw[:4], "names": [e["name"] for e in s["effects"]], "cpu": cpu}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--fits", type=int, default=100, help="records (seeds 1..N; default 100)")
    ap.add_argument("--jobs", type=int, default=min(2, os.cpu_count() or 1), help="processes (default 2)")
    ap.add_argument("--force-noise", type=float, default=1.0, help="white force noise [N RMS] (default 1)")
    ap.add_argument("--spread", type=float, default=0.1, help="plant parameters within +-this share (default 0.1)")
    ap.add_argument("--duration", type=float, default=5.0, help="record length [s] (default 5)")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    done = run_all(one, [(seed, args.force_noise, args.spread, args.duration) for seed in range(1, args.fits + 1)],
                   args.jobs)
    wall = time.perf_counter() - t0
    tv = np.array([d["true"] for d in done])
    fv = np.array([d["value"] for d in done])
    st = np.array([d["stated"] for d in done], dtype=float)
    nw = np.array([d["nw"] for d in done], dtype=float)
    print(f"identify's 95 % intervals of theta1..theta4 on {len(done)} records close to the nominal model "
          f"(numpy axis, {args.duration:g} s at 5 kHz, force noise {args.force_noise:g} N, parameters within "
          f"+-{100 * args.spread:g} %); load average {os.getloadavg()[0]:.2f}\n")
    print("| theta | fits | stated covers | Newey-West covers | median abs(error)/sigma stated | "
          "median abs(error)/abs(value) | median stated half-width/abs(value) |\n|---|---|---|---|---|---|---|")
    cov_tot = n_tot = 0
    for j, name in enumerate(THETA):
        c_st, c_nw = covered(st[:, j], tv[:, j]), covered(nw[:, j], tv[:, j])
        sig = (st[:, j, 1] - st[:, j, 0]) / (2 * 1.959963984540054)
        z = np.median(np.abs(fv[:, j] - tv[:, j]) / np.maximum(sig, 1e-300))
        rel = np.median(np.abs(fv[:, j] - tv[:, j]) / np.abs(tv[:, j]))
        hw = np.median((st[:, j, 1] - st[:, j, 0]) / 2 / np.abs(fv[:, j]))
        cov_tot += int(c_st.sum())
        n_tot += len(c_st)
        print(f"| {name} | {len(c_st)} | {c_st.mean():.0%} ({int(c_st.sum())}) | {c_nw.mean():.0%} | {z:.2f} | "
              f"{100 * rel:.3f} % | {100 * hw:.3f} % |")
    names = {}
    for d in done:
        for n in d["names"]:
            names[n] = names.get(n, 0) + 1
    cpu = np.array([d["cpu"] for d in done])
    print(f"\nstated intervals hold the truth in {cov_tot}/{n_tot} ({cov_tot / n_tot:.1%}); names given "
          f"(phantoms): {names or 'none'}; identify's CPU per record median {np.median(cpu):.2f} s; {wall:.0f} s wall")
    print("rerun: python benchmarks/ident_near_clean.py [--fits 100] [--jobs 2] [--force-noise 1] [--spread 0.1]")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
