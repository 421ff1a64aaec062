"""Clean logs of plants nobody tuned for: what ``motorctl identify`` says of each.

    python benchmarks/ident_random_plants.py                          # X, seeds 11-16, 8 plants each
    python benchmarks/ident_random_plants.py --axis Y --seeds 31,32 --modes 80-200

Each seed draws ``--plants`` plants (``numpy.random.default_rng(seed)``, in this order: Coulomb
friction uniform in 8-30 N, static friction 1.05-1.5 × it, an offset of ±5 N, viscous 10-40 N s/m,
a structural mode at ``--modes`` Hz (default 150-500) with damping 0.02-0.06, a current loop at
0.8-3 kHz; each rounded as printed) into the axis's ``driver:`` section of ``--config`` (default
configs/gantry.yaml; the mode's load fraction and everything else the config's), runs it 20 s on
the virtual clock under C2 (:func:`motorctl.commission.tune.make_log`, the driver's seed 1, no
extra force noise), and identifies the log by the user's command, ``python -m motorctl identify
LOG --axis A --json --no-closed-loop`` (a subprocess). Nothing is injected: every plant's own
effects are stiction, the current loop's delay and, where its antiresonance lies in the record's
band, the mode.

Prints per plant the draw, the effects named, "ambiguous" pairs, and the verdict (WARNING and its
first words, or clean); then the count of clean logs (no warning) and of logs that name a family
beyond stiction, the input delay and the structural mode (a **wrong name**). Deterministic: the
same lines every run. The logs go to ``--dir`` and are reused when present.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from multiprocessing import Pool
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
#: what a clean plant may be named for: its own effects
OWN = {"stiction", "input_delay", "structural_mode"}


def draws(seed: int, n: int, modes: tuple[float, float]) -> list[dict]:
    """The ``n`` plants of ``seed`` (the module docstring's ranges, rounded)."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        fc = float(rng.uniform(8, 30))
        ratio = float(rng.uniform(1.05, 1.5))
        out.append({"coulomb_N": round(fc, 1), "stiction_N": round(fc * ratio, 1),
                    "offset_N": round(float(rng.uniform(-5, 5)), 1),
                    "viscous_N_s_per_m": round(float(rng.uniform(10, 40)), 1),
                    "mode_hz": round(float(rng.uniform(*modes))),
                    "mode_damping": round(float(rng.uniform(0.02, 0.06)), 3),
                    "current_loop_hz": round(float(rng.uniform(800, 3000)))})
    return out


def one(job: tuple) -> tuple:
    """Simulate (unless the log exists) and identify one plant; returns (seed, k, plant, summary
    or the error text)."""
    seed, k, plant, axis, config, out = job
    from motorctl.commission.tune import make_log
    path = Path(out) / f"{Path(config).stem}_{axis}_seed{seed}_{k}.mclog"
    if not path.exists():
        make_log(str(path), plant, duration_s=20.0, seed=1, axis=axis, noise_N=None, base=config)
    r = subprocess.run([sys.executable, "-m", "motorctl", "identify", str(path), "--axis", axis, "--json",
                        "--no-closed-loop"], capture_output=True, text=True, timeout=900)
    if r.returncode != 0:
        return seed, k, plant, r.stderr.strip()[-300:]
    return seed, k, plant, json.loads(r.stdout)


def _range(text: str) -> tuple[float, float]:
    lo, _, hi = text.partition("-")
    try:
        return float(lo), float(hi)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: expected LO-HI, e.g. 150-500") from None


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--axis", default="X")
    ap.add_argument("--config", default=str(ROOT / "configs" / "gantry.yaml"))
    ap.add_argument("--seeds", default="11,12,13,14,15,16", help="comma list (default 11-16)")
    ap.add_argument("--plants", type=int, default=8, help="plants per seed (default 8)")
    ap.add_argument("--modes", type=_range, default=(150.0, 500.0), help="the mode's range [Hz] (default 150-500)")
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--dir", default="/tmp/motorctl_ident_random", help="where the logs go (reused)")
    args = ap.parse_args(argv)
    Path(args.dir).mkdir(parents=True, exist_ok=True)
    jobs = [(s, k, p, args.axis, args.config, args.dir)
            for s in (int(v) for v in args.seeds.split(",")) for k, p in enumerate(draws(s, args.plants, args.modes))]
    with Pool(args.jobs) as pool:
        done = pool.map(one, jobs, chunksize=1)
    clean = wrong = failed = 0
    for seed, k, plant, s in done:
        if isinstance(s, str):
            failed += 1
            print(f"seed {seed} #{k} {json.dumps(plant)}: identify failed: {s}")
            continue
        names = [e["name"] for e in s["effects"]]
        amb = [a.get("families") for a in s["ambiguous"]]
        res = s["residual"]
        clean += not res["structured"]
        wrong += bool(set(names) - OWN)
        print(f"seed {seed} #{k} {json.dumps(plant)}: {', '.join(names) or 'none'}"
              + (f"; ambiguous {amb}" if amb else "")
              + ("; WARNING " + res["text"][:150] if res["structured"] else "; clean"), flush=True)
    n = len(done)
    print(f"\n{args.axis} of {Path(args.config).name}, {n} plants: {clean} of {n} without a warning, "
          f"{wrong} naming a family beyond {', '.join(sorted(OWN))}, {failed} failed")
    print(f"rerun: python benchmarks/ident_random_plants.py --axis {args.axis} --seeds {args.seeds} "
          f"--plants {args.plants} --modes {args.modes[0]:g}-{args.modes[1]:g}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
