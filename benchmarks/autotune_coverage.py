"""Whether the intervals ``motorctl autotune`` states for its fitted model hold the plant's true
values: each parameter's 95 % interval (the JSON's ``model.ci95``; for a motorctl without it, θ ±
1.96 σ of ``model.sigma`` or ``theta1_small_signal_range`` where the JSON has it) against the simulated plant's own parameters, over driver seeds and plants.

Run (about 9 s a run of both axes on 2 shared cores; 3 plants x 6 seeds: under 3 minutes):

    python benchmarks/autotune_coverage.py                          # 3 plants, seeds 1-6
    python benchmarks/autotune_coverage.py --seeds 1-10 --config configs/gantry.yaml
    python benchmarks/autotune_coverage.py --jobs 1 --keep /tmp/atc  # keep each run's JSON
    python benchmarks/autotune_coverage.py --random 6 --seeds 1-3    # 6 plants no config has

``--random K``: K plants drawn as ``benchmarks/ident_random_plants.py`` draws them (X: its seed 11,
modes 150-500 Hz; Y: its seed 31, modes 80-200 Hz; Coulomb, static, offset, viscous, mode and
current loop each), the k-th X and Y draws in a copy of configs/gantry.yaml (its masses, force
constants, input nonlinearity, load fractions, encoder and noise), written beside the runs.

The user's path: each run is ``sys.executable -m motorctl autotune CFG --axis X --axis Y
--virtual-clock --measure-only --json`` in a subprocess on a copy of the config whose
``driver.seed`` is the seed (the multisine and the friction passes, the model's fit; no gains).
The ``motorctl`` measured is the one ``python -m motorctl`` imports from the working directory;
to measure a snapshot, export it (``git archive HEAD motorctl motorctl_drivers
motorctl_emulators | tar -x -C DIR``) and run from outside the repository with
``PYTHONPATH=DIR``.

The truth, from each axis's ``driver:`` section (the simulated plant, motorctl_drivers/sim.py,
the model of motorctl/commission/loopshape.py has the same structure): θ1 = M/A1, θ2 = B/A1,
θ3 = F_c/A1, θ4 = F_offset/A1 (the paper's θ, eq. 4; A1 ``a1_N_per_V``), ``current_loop_hz``,
``delay_s`` = ``current_loop_delay_s``, and where the plant has a structural mode and the fit
kept one: ``mode_hz``, ``mode_damping``, ``load_fraction`` = ``mode_load_fraction``. A
parameter the fit does not hold (the rigid plant's mode) is not counted.

Prints one line per run and parameter outside its interval, then per plant and parameter the
count inside of those counted, and the total. Exit 1 when a run failed.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from multiprocessing import Pool
from pathlib import Path

import yaml

REPO = Path(__file__).resolve().parents[1]
CONFIGS = ["configs/gantry.yaml", "configs/gantry-rigid.yaml", "configs/gantry-half-mode.yaml"]
#: the normal quantile of a two-sided 95 % interval
Z95 = 1.959964
#: the parameters compared: name -> the truth from the axis's driver section (None: not counted)
TRUTH = {
    "theta1": lambda d: d["mass_kg"] / d["a1_N_per_V"],
    "theta2": lambda d: d.get("viscous_N_s_per_m", 0.0) / d["a1_N_per_V"],
    "theta3": lambda d: d.get("coulomb_N", 0.0) / d["a1_N_per_V"],
    "theta4": lambda d: d.get("offset_N", 0.0) / d["a1_N_per_V"],
    "current_loop_hz": lambda d: d.get("current_loop_hz") or None,
    "delay_s": lambda d: d.get("current_loop_delay_s", 0.0),
    "mode_hz": lambda d: d.get("mode_hz") or None,
    "mode_damping": lambda d: d.get("mode_damping") if d.get("mode_hz") else None,
    "load_fraction": lambda d: d.get("mode_load_fraction") if d.get("mode_hz") else None,
}


def _seeds(text: str) -> list[int]:
    out: list[int] = []
    for part in text.split(","):
        a, _, b = part.partition("-")
        out += list(range(int(a), int(b or a) + 1))
    return out


def interval(model: dict, name: str) -> tuple[float, float] | None:
    """The stated 95 % interval of ``name`` in autotune's JSON ``model`` (None: not fitted):
    ``model.ci95`` where the JSON has it, else (an older motorctl) θ ± 1.96 σ."""
    if "ci95" in model:
        iv = model["ci95"].get(name)
        return None if iv is None else (float(iv[0]), float(iv[1]))
    if name == "theta1" and model.get("theta1_small_signal_range"):
        lo, hi = model["theta1_small_signal_range"]
        return float(lo), float(hi)
    if name not in model or name not in model.get("sigma", {}):
        return None
    if name in ("mode_hz", "mode_damping", "load_fraction") and not model.get("mode"):
        return None
    v, s = float(model[name]), float(model["sigma"][name])
    return v - Z95 * s, v + Z95 * s


def random_configs(k: int, folder: Path) -> list[str]:
    """``k`` copies of configs/gantry.yaml with X's and Y's driver sections drawn as
    ``benchmarks/ident_random_plants.py`` draws them (module docstring), written to ``folder``."""
    import importlib.util
    spec = importlib.util.spec_from_file_location("ident_random_plants", REPO / "benchmarks" / "ident_random_plants.py")
    rp = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(rp)
    xs, ys = rp.draws(11, k, (150.0, 500.0)), rp.draws(31, k, (80.0, 200.0))
    folder.mkdir(parents=True, exist_ok=True)
    out = []
    for i in range(k):
        cfg = yaml.safe_load((REPO / "configs" / "gantry.yaml").read_text())
        cfg["axes"]["X"]["driver"].update(xs[i])
        cfg["axes"]["Y"]["driver"].update(ys[i])
        path = folder / f"random_{i + 1}.yaml"
        path.write_text(yaml.safe_dump(cfg, sort_keys=False))
        out.append(str(path))
    return out


def run_one(job: tuple[str, int, str | None]) -> dict:
    """Autotune's measurement of both axes of ``config`` at driver seed ``seed``; the rows."""
    config, seed, keep = job
    cfg = yaml.safe_load((REPO / config).read_text())
    cfg.setdefault("driver", {})["seed"] = seed
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / Path(config).name
        path.write_text(yaml.safe_dump(cfg, sort_keys=False))
        p = subprocess.run([sys.executable, "-m", "motorctl", "autotune", str(path), "--axis", "X", "--axis", "Y",
                            "--virtual-clock", "--measure-only", "--json", "--out", str(Path(tmp) / "out")],
                           capture_output=True, text=True, cwd=str(REPO), timeout=600)
    if p.returncode != 0:
        return {"config": config, "seed": seed, "error": (p.stderr.strip().splitlines() or ["?"])[-1]}
    out = json.loads(p.stdout)
    if keep:
        Path(keep).mkdir(parents=True, exist_ok=True)
        (Path(keep) / f"{Path(config).stem}_seed{seed}.json").write_text(p.stdout)
    rows = []
    for axis, res in out["axes"].items():
        drv = cfg["axes"][axis]["driver"]
        for name, truth_of in TRUTH.items():
            truth = truth_of(drv)
            iv = interval(res["model"], name)
            if truth is None or iv is None:
                continue
            rows.append({"axis": axis, "name": name, "truth": float(truth), "value": float(res["model"][name]),
                         "lo": iv[0], "hi": iv[1], "inside": iv[0] <= truth <= iv[1]})
    return {"config": config, "seed": seed, "rows": rows}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", action="append", help="plant config (repeatable; default: the three plants)")
    ap.add_argument("--seeds", default="1-6", help="driver seeds: N, N-M or a comma list (default 1-6)")
    ap.add_argument("--jobs", type=int, default=2, help="processes (default 2)")
    ap.add_argument("--keep", help="keep each run's JSON in this folder")
    ap.add_argument("--random", type=int, default=0, metavar="K",
                    help="K plants no config has instead (module docstring; configs written to --keep or a temporary folder)")
    a = ap.parse_args(argv)
    configs = a.config or CONFIGS
    if a.random:
        configs = random_configs(a.random, Path(a.keep or tempfile.mkdtemp(prefix="atc-random-")))
    jobs = [(c, s, a.keep) for c in configs for s in _seeds(a.seeds)]
    with Pool(max(1, a.jobs)) as pool:
        results = pool.map(run_one, jobs)
    failed = 0
    table: dict[tuple[str, str, str], list[int]] = {}
    for r in results:
        if "error" in r:
            failed += 1
            print(f"{r['config']} seed {r['seed']}: failed: {r['error']}")
            continue
        for row in r["rows"]:
            t = table.setdefault((r["config"], row["axis"], row["name"]), [0, 0])
            t[0] += row["inside"]
            t[1] += 1
            if not row["inside"]:
                print(f"{r['config']} seed {r['seed']} {row['axis']} {row['name']}: {row['value']:.6g} in "
                      f"[{row['lo']:.6g}, {row['hi']:.6g}], truth {row['truth']:.6g}: outside")
    print("\n| plant | axis | parameter | inside / counted |\n|---|---|---|---|")
    total = [0, 0]
    for (config, axis, name), (k, n) in table.items():
        print(f"| {Path(config).stem} | {axis} | {name} | {k} / {n} |")
        total[0] += k
        total[1] += n
    pct = 100.0 * total[0] / max(total[1], 1)
    print(f"\n95 % intervals holding the truth: {total[0]} of {total[1]} ({pct:.1f} %), "
          f"{len(jobs) - failed} runs of {len(jobs)}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
