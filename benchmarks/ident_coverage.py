"""Coverage of ``motorctl identify``'s 95 % intervals: the share of fits whose interval contains
the truth, per parameter, for the stated intervals identify reports (theta_ci95,
parameters_ci95: the Newey-West σ and the model error the record shows in quadrature;
motorctl.ident.uncertainty), for the Newey-West sandwich's σ alone (theta_std_sampling,
parameters_std_sampling) and for the white least-squares formula's σ̂²(ΦᵀΦ)⁻¹ ± 1.96σ on the
same fits.

Rerun:
    python benchmarks/ident_coverage.py --jobs 2                 # 2 plants x 6 cases x 2 sizes x 5 seeds, ~6 min
    python benchmarks/ident_coverage.py --seeds 2 --plant rigid  # a quick look
    python benchmarks/ident_coverage.py --pairs --jobs 2         # two effects at once: the joint fits' errors

The fits: a 20 s log of the simulated X axis (C2, virtual clock; :func:`motorctl.commission.tune.
make_log`, :func:`motorctl.ident.synth.gantry_dict`) on two plants, ``rigid``
(configs/gantry-rigid.yaml, the paper's model, with a 1 N white force noise) and ``default``
(configs/gantry.yaml: structural mode, current loop, stiction, encoder and force noise), with no
added effect or one of :data:`EFFECTS` at the sizes ``--sizes`` (the family's ``example`` with
its forces scaled, :func:`tune_families.scaled`), for the driver seeds 1..``--seeds``; then
``motorctl identify``'s pipeline (:func:`motorctl.ident.pipeline.identify_record`). Compared:
θ1..θ4 (and θ5, θ6 when fitted) of the values the effects come from against the plant's
M/A1, B/A1, Af/A1, offset/A1, A2/A1, A3/A1 (not where the added effect changes what a θ means:
:data:`THETA_SKIP`), and each named effect's simulator options identify reports under the same
name (:func:`ident_families.compared`; phases and references left out), when the effect is named.

Prints per plant and parameter: fits, coverage of the white, the Newey-West and the stated
interval, the median error / σ of each, the seeds' spread and the bias against the Newey-West σ
(per case, the standard deviation and the mean of the error over the seeds, divided by the
case's median σ, then the median over the cases: a spread / σ near or below 1 with a bias / σ
well above 2 is an error the same on every seed, which no variance from the record's own
residual covers), and the median width of the stated interval relative to the value; then the
totals per plant and over all, and identify's CPU time per log.
Exit 0 always (a measurement).
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from ident_families import compared  # noqa: E402
from tune_families import scaled  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
#: plant name -> (config, force noise [N]: None the config's own)
PLANTS = {"rigid": (str(ROOT / "configs" / "gantry-rigid.yaml"), 1.0),
          "default": (str(ROOT / "configs" / "gantry.yaml"), None)}
EFFECTS = ("cogging", "spring", "periodic_disturbance", "asymmetric_friction", "force_constant_drift")
#: θ indexes not compared beside a family: the spring moves the offset to its rest position, an
#: asymmetric friction splits the viscous and Coulomb terms by direction, a drifting force
#: constant makes every θ = ·/A1 a function of time
THETA_SKIP = {"spring": (3,), "asymmetric_friction": (1, 2, 3), "force_constant_drift": (0, 1, 2, 3, 4, 5)}
#: pairs of families on one plant (their examples at ×1): the joint fits (``--pairs``)
PAIRS = (("cogging", "asymmetric_friction"), ("cogging", "force_constant_drift"),
         ("periodic_disturbance", "spring"), ("cogging", "spring"))
#: cogging of one harmonic at a 17 mm period (beside the drift it came out 17.80 mm, −12 %, with a
#: second harmonic never injected)
COGGING_17 = {"cogging": {"amplitudes_N": [12.0], "period_m": 0.017, "phases_rad": [0.3]}}


def run_all(fn, items: list, jobs: int) -> list:
    """``fn(*item)`` for each tuple of ``items``, in order, in ``jobs`` processes (1: here)."""
    if jobs > 1 and items:
        with ProcessPoolExecutor(max_workers=jobs) as ex:
            return list(ex.map(fn, *zip(*items)))
    return [fn(*item) for item in items]


def covered(ci: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """(n,) bool: the intervals ``ci`` (n, 2) that hold ``truth`` (n,)."""
    return (ci[:, 0] <= truth) & (truth <= ci[:, 1])


def true_theta(config: str) -> list[float]:
    """θ1..θ6 of the X axis of ``config``: M/A1, B/A1, Af/A1, offset/A1, A2/A1, A3/A1."""
    from motorctl.config import load_yaml
    d = load_yaml(config)["axes"]["X"]["driver"]
    a1 = float(d["a1_N_per_V"])
    return [d["mass_kg"] / a1, d["viscous_N_s_per_m"] / a1, d["coulomb_N"] / a1, d.get("offset_N", 0.0) / a1,
            d.get("a2_N_per_V2", 0.0) / a1, d.get("a3_N_per_V3", 0.0) / a1]


def _at(v, name: str):
    """The entry of a parameter's list value for a compared name ``k[i]`` (or the value)."""
    if name.endswith("]"):
        i = int(name[name.rindex("[") + 1:-1])
        return v[i] if isinstance(v, list) and i < len(v) else None
    return v


def _key(fitted: dict, k: str) -> str | None:
    """The fitted parameter's name for the compared simulator option ``k`` (as compared() finds)."""
    from ident_families import ALIASES
    base = k.split("[")[0]
    return ALIASES.get(base) or next((f for f in fitted if f == base or f.endswith("_" + base)), None)


def one(plant: str, fragment: dict, label: str, seed: int, out: str) -> dict:
    """Log, identify and compare one fit; returns its rows (parameter, truth, value, old and
    new interval) and identify's CPU time."""
    from motorctl.commission.tune import make_log
    from motorctl.ident.data import load_record
    from motorctl.ident.pipeline import identify_record, values_and_parameters
    from motorctl.ident.uncertainty import ci95, fit_uncertainty
    from motorctl.recorder.runlog import LogError

    config, noise = PLANTS[plant]
    log = Path(out) / f"{plant}_{label}_s{seed}.mclog"
    make_log(str(log), fragment, duration_s=20.0, seed=seed, axis="X", noise_N=noise, base=config)
    t0 = time.process_time()
    try:
        rec = load_record(str(log), axis="X")
        idf, s = identify_record(rec)
    except LogError as exc:
        return {"plant": plant, "label": label, "seed": seed, "rows": [], "error": str(exc), "cpu_s": 0.0,
                "effects": []}
    cpu = time.process_time() - t0
    src, params_of = values_and_parameters(idf, rec.gain)
    white = fit_uncertainty(src, src.final, src.terms, params_of, white=True)
    a = s["augmented"]
    truth = true_theta(config)
    skip = set()
    for name in fragment:
        skip |= set(THETA_SKIP.get(name, ()))
    rows = []
    for i, v in enumerate(a["theta_values"]):
        if i in skip:
            continue
        rows.append((f"theta{i + 1}", truth[i], v, ci95(v, a["theta_std_white"][i]), a["theta_ci95"][i],
                     ci95(v, a.get("theta_std_sampling", a["theta_std"])[i])))
    by_name = {t.family: k for k, t in enumerate(src.terms)}
    for name, opts in fragment.items():
        found = next((e for e in s["effects"] if e["name"] == name), None)
        if found is None or not isinstance(opts, dict):
            continue
        k = by_name.get(name)
        for pname, tv, fv in compared(opts, found["parameters"]):
            key = _key(found["parameters"], pname)
            new = _at(found["parameters_ci95"].get(key), pname)
            old = _at(white["effects"][k]["ci95"].get(key), pname) if k is not None else None
            samp = _at(found.get("parameters_std_sampling", found["parameters_std"]).get(key), pname)
            if new is None or old is None or new[0] is None or samp is None:
                continue
            rows.append((f"{name}.{pname}", tv, fv, old, new, ci95(fv, samp)))
    return {"plant": plant, "label": label, "seed": seed, "rows": rows, "cpu_s": cpu,
            "effects": [e["name"] for e in s["effects"]], "lag": s["uncertainty"]["lag_samples"]}


def pair_errors(plant: str, fragment: dict, label: str, seed: int, out: str) -> dict:
    """Log with two effects, identify; each family's named values against the truth."""
    from motorctl.commission.tune import make_log
    from motorctl.ident.data import load_record
    from motorctl.ident.pipeline import identify_record
    config, noise = PLANTS[plant]
    log = Path(out) / f"pair_{plant}_{label}_s{seed}.mclog"
    make_log(str(log), fragment, duration_s=20.0, seed=seed, axis="X", noise_N=noise, base=config)
    _, s = identify_record(load_record(str(log), axis="X"))
    res = []
    for name, opts in fragment.items():
        found = next((e for e in s["effects"] if e["name"] == name), None)
        if found is None:
            res.append((name, None, None, None))
            continue
        for pname, tv, fv in compared(opts, found["parameters"]):
            res.append((f"{name}.{pname}", tv, fv, 100.0 * (fv - tv) / abs(tv)))
    extra = [e["name"] for e in s["effects"] if e["name"] not in fragment]
    return {"plant": plant, "label": label, "seed": seed, "rows": res, "also": extra}


def work(args) -> list[tuple]:
    from motorctl.effects import FAMILIES
    out = []
    for plant in args.plant:
        for seed in range(1, args.seeds + 1):
            out.append((plant, {}, "none", seed))
            for name in EFFECTS:
                fam = FAMILIES[name]
                for f in args.sizes:
                    frag, _ = scaled(fam.example, f, fam.size_options)
                    out.append((plant, frag, f"{name}x{f:g}", seed))
    return out


def pair_work(args) -> list[tuple]:
    from motorctl.effects import FAMILIES
    out = []
    for plant in args.plant:
        for seed in range(1, args.seeds + 1):
            for a, b in PAIRS:
                frag = {**FAMILIES[a].example, **FAMILIES[b].example}
                out.append((plant, frag, f"{a}+{b}", seed))
            out.append((plant, {**COGGING_17, **FAMILIES["force_constant_drift"].example},
                        "cogging17mm+force_constant_drift", seed))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--jobs", type=int, default=min(2, os.cpu_count() or 1), help="processes (default 2)")
    ap.add_argument("--seeds", type=int, default=5, help="driver seeds 1..N (default 5)")
    ap.add_argument("--sizes", default="0.5,1", help="factors on the examples' forces (default 0.5,1)")
    ap.add_argument("--plant", action="append", choices=sorted(PLANTS), default=None,
                    help="rigid and/or default (default both)")
    ap.add_argument("--pairs", action="store_true", help="two effects at once: the values' errors")
    ap.add_argument("--out", default=None, help="keep the logs here (default: a temporary folder)")
    args = ap.parse_args(argv)
    args.plant = args.plant or ["rigid", "default"]
    args.sizes = [float(x) for x in args.sizes.split(",")]
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="motorctl-ident-coverage-") as tmp:
        out = args.out or tmp
        Path(out).mkdir(parents=True, exist_ok=True)
        items = pair_work(args) if args.pairs else work(args)
        done = run_all(pair_errors if args.pairs else one, [(*item, out) for item in items], args.jobs)
    wall = time.perf_counter() - t0
    if args.pairs:
        print("| plant | seed | effects | value: true → fitted (error) | also named |\n|---|---|---|---|---|")
        worst = 0.0
        for r in done:
            vals = "; ".join(f"{n} NOT named" if tv is None else f"{n} {tv:.4g} → {fv:.4g} ({e:+.1f} %)"
                             for n, tv, fv, e in r["rows"])
            worst = max([worst] + [abs(e) for *_, e in r["rows"] if e is not None])
            print(f"| {r['plant']} | {r['seed']} | {r['label']} | {vals} | {', '.join(r['also']) or '-'} |")
        print(f"\nlargest error {worst:.1f} %; {wall:.0f} s wall")
        print("rerun: python benchmarks/ident_coverage.py --pairs --jobs 2 [--seeds 2] [--plant rigid]")
        return 0
    per: dict = {}
    cases: dict = {}              # (plant, parameter) -> {case label: [(error, σ new)] over the seeds}
    for r in done:
        for name, tv, fv, old, new, samp in r["rows"]:
            per.setdefault((r["plant"], name), []).append((tv, fv, old, new, samp))
            cases.setdefault((r["plant"], name), {}).setdefault(r["label"], []).append(
                (fv - tv, (samp[1] - samp[0]) / (2.0 * 1.959963984540054)))
    print(f"identify's 95 % intervals against the truth: {len(done)} fits "
          f"({', '.join(args.plant)} plant; none + {', '.join(EFFECTS)} at x{', x'.join(f'{f:g}' for f in args.sizes)}; "
          f"seeds 1-{args.seeds}; 20 s logs); load average {os.getloadavg()[0]:.2f}\n")
    print("| plant | parameter | fits | white covers | Newey-West covers | stated (Newey-West + model error) covers | "
          "median abs(error)/σ white | median abs(error)/σ Newey-West | median abs(error)/σ stated | "
          "seeds' spread / σ NW | abs(bias) / σ NW | median stated width / abs(value) |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    tot_old = tot_new = tot_nw = tot = 0
    for (plant, name), rows in sorted(per.items()):
        tv = np.array([r[0] for r in rows])
        fv = np.array([r[1] for r in rows])
        old = np.array([r[2] for r in rows], dtype=float)
        new = np.array([r[3] for r in rows], dtype=float)
        nw = np.array([r[4] for r in rows], dtype=float)
        c_old, c_new, c_nw = (np.mean(covered(ci, tv)) for ci in (old, new, nw))
        z_old = np.abs(fv - tv) / np.maximum((old[:, 1] - old[:, 0]) / 3.919927969, 1e-300)
        z_new = np.abs(fv - tv) / np.maximum((new[:, 1] - new[:, 0]) / 3.919927969, 1e-300)
        z_nw = np.abs(fv - tv) / np.maximum((nw[:, 1] - nw[:, 0]) / 3.919927969, 1e-300)
        width = np.median((new[:, 1] - new[:, 0]) / np.maximum(np.abs(fv), 1e-300))
        tot_old += int(round(c_old * len(rows)))
        tot_new += int(round(c_new * len(rows)))
        tot_nw += int(round(c_nw * len(rows)))
        tot += len(rows)
        # per case (plant, effect, size) over its seeds: the spread of the errors and their mean
        # (the bias: the same on every seed), each against the case's median σ
        spread, bias = [], []
        for errs in cases[(plant, name)].values():
            if len(errs) >= 2:
                e = np.array([x for x, _ in errs])
                sd = float(np.median([y for _, y in errs]))
                spread.append(float(np.std(e, ddof=1)) / sd)
                bias.append(abs(float(np.mean(e))) / sd)
        sp = f"{np.median(spread):.2f}" if spread else "-"
        bi = f"{np.median(bias):.1f}" if bias else "-"
        print(f"| {plant} | {name} | {len(rows)} | {100 * c_old:.0f} % | {100 * c_nw:.0f} % | {100 * c_new:.0f} % | "
              f"{np.median(z_old):.1f} | {np.median(z_nw):.1f} | {np.median(z_new):.1f} | {sp} | {bi} | "
              f"{100 * width:.3g} % |")
    errs = [r for r in done if r.get("error")]
    cpu = [r["cpu_s"] for r in done if not r.get("error")]
    lags = [r["lag"] for r in done if r.get("lag") is not None]
    for plant in args.plant:
        pr = [(k, v) for k, v in per.items() if k[0] == plant]
        n_p = sum(len(v) for _, v in pr)
        cov_p = {j: sum(int(np.sum([(r[j][0] <= r[0] <= r[j][1]) for r in v])) for _, v in pr) for j in (2, 4, 3)}
        print(f"\n{plant}: white {cov_p[2]}/{n_p} ({100 * cov_p[2] / max(n_p, 1):.0f} %), Newey-West {cov_p[4]}/{n_p} "
              f"({100 * cov_p[4] / max(n_p, 1):.0f} %), stated {cov_p[3]}/{n_p} ({100 * cov_p[3] / max(n_p, 1):.0f} %)", end="")
    print(f"\nall parameters: white {tot_old}/{tot} ({100 * tot_old / max(tot, 1):.0f} %), Newey-West {tot_nw}/{tot} "
          f"({100 * tot_nw / max(tot, 1):.0f} %), stated {tot_new}/{tot} "
          f"({100 * tot_new / max(tot, 1):.0f} %); {len(errs)} fits refused; identify {min(cpu):.1f}-{max(cpu):.1f} s (median {np.median(cpu):.2f} s) "
          f"CPU per log; Newey-West bandwidth {min(lags)}-{max(lags)} decimated samples; {wall:.0f} s wall")
    print("rerun: python benchmarks/ident_coverage.py --jobs 2 [--seeds 5] [--plant rigid] [--sizes 0.5,1]")
    return 0


if __name__ == "__main__":
    sys.exit(main())
