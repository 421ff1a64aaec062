"""Fitted values against the truth for every effect family at two sizes: ``motorctl identify`` on
the default plant.

Rerun:
    python benchmarks/ident_families.py                               # every family, 2 sizes, 20 s logs
    python benchmarks/ident_families.py --family stribeck --family asymmetric_friction --jobs 2
    python benchmarks/ident_families.py --family stribeck --tune      # and tune's damage removed
    python benchmarks/ident_families.py --family stribeck --current-loop   # the loop modelled

For each family of :data:`motorctl.effects.FAMILIES` (registry order) and each size (the
family's ``example`` with its force-valued options × ``--sizes``, default 0.5 and 1;
:func:`tune_families.scaled`): a 20 s log of the simulated X axis of ``--config`` (default
``configs/gantry.yaml``: structural mode, current loop, encoder noise, stiction; C2, virtual
clock, ``--seed``, default 1: the simulated driver's noise) with the effect on the plant,
undeclared to the controller; then identify on it
(:func:`motorctl.ident.pipeline.identify_record`). Every simulator option of the effect that
identify reports under the same name (or a name ending in it, e.g. ``velocity_m_per_s`` in
``stribeck_velocity_m_per_s``) is compared: true → fitted and the relative error; phases,
references and shapes are not compared. A row meets the bar when the family is named and every
compared value is within 10 %; "warns unexplained" is identify's verdict on the residual left
(with the effect named right, a warning is a false alarm); "also" lists the other effects named
beyond the plant's own (those identify names on a log of the same plant and seed without the
effect: the default plant's stiction and current-loop delay), phantoms beside the right name.
``--tune`` adds tune's damage removed (:func:`tune_families.tune_family`: before run, identify,
after run, floor; compensable families only), which takes about a minute of CPU per row more.

Exit 0 when every row meets the bar.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from tune_families import scaled  # noqa: E402

#: the issue's bar on a fitted value: within this share of the truth
TOLERANCE = 0.10
#: simulator option -> identify's parameter, where the names differ
ALIASES = {"input_delay_s": "delay_s", "encoder_interpolation_m": "amplitudes_m",
           "encoder_signal_period_m": "signal_period_m"}
#: options not compared (references, phases, shapes: not identifiable or not a size)
SKIP = ("phase", "reference_m", "rest_position_m", "bumps")


def compared(truth: dict, fitted: dict) -> list[tuple[str, float, float]]:
    """(name, true, fitted) for every numeric simulator option of ``truth`` (an effect's options,
    lists element-wise) that identify's ``fitted`` parameters carry under the same name, a name
    ending in it, or :data:`ALIASES`' name; phases and references are left out."""
    out = []
    for k, v in truth.items():
        if any(s in k for s in SKIP):
            continue
        key = ALIASES.get(k) or next((f for f in fitted if f == k or f.endswith("_" + k)), None)
        if key is None or key not in fitted:
            continue
        tv = v if isinstance(v, list) else [v]
        fv = fitted[key] if isinstance(fitted[key], list) else [fitted[key]]
        for i, (a, b) in enumerate(zip(tv, fv)):
            if isinstance(a, (int, float)) and a != 0:
                out.append((k if len(tv) == 1 else f"{k}[{i}]", float(a), float(b)))
    return out


def one(name: str, factor: float, out: str, duration_s: float, config: str, tune: bool,
        current_loop: bool = False, seed: int = 1, also: str | None = None) -> dict:
    """Log, identify and (``tune``) tune one family at one size; returns the row's figures."""
    from motorctl.commission.tune import make_log
    from motorctl.effects import FAMILIES
    from motorctl.ident.data import load_record
    from motorctl.ident.pipeline import identify_record
    from motorctl.recorder.runlog import LogError

    if name is None:                    # the plant's own: no effect on it
        fragment, did_scale, also = {}, False, None
    else:
        fam = FAMILIES[name]
        fragment, did_scale = scaled(fam.example, factor, fam.size_options)
    if also == name:
        also = None
    plant = {**FAMILIES[also].example, **fragment} if also else fragment
    d = Path(out) / f"{name or 'plant'}_x{factor:g}{'+' + also if also else ''}_s{seed}"
    d.mkdir(parents=True, exist_ok=True)
    log = d / "before.mclog"
    make_log(str(log), plant, duration_s=duration_s, seed=seed, axis="X", noise_N=None, base=config)
    t0 = time.process_time()
    try:
        rec = load_record(str(log), axis="X")
        _, s = identify_record(rec, current_loop=current_loop)
    except LogError as exc:          # e.g. a delay so long that the run faulted at once
        return {"name": name, "factor": factor, "scaled": did_scale, "named": False, "effects": [],
                "values": [], "cpu_s": time.process_time() - t0, "unexplained": False,
                "damage_removed": None, "also": also, "logged_s": duration_s,
                "duration_s": duration_s, "error": str(exc)}
    cpu = time.process_time() - t0
    truth = next(iter(fragment.values())) if name in fragment else fragment
    found = next((e for e in s["effects"] if e["name"] == name), None)
    rows = compared(truth if isinstance(truth, dict) else fragment, found["parameters"]) if found else []
    res = {"name": name, "factor": factor, "scaled": did_scale, "named": found is not None,
           "effects": [e["name"] for e in s["effects"]], "values": rows, "cpu_s": cpu,
           "unexplained": bool(s["residual"]["structured"]), "damage_removed": None,
           "also": also, "logged_s": float(rec.t[-1] - rec.t[0]),
           "duration_s": duration_s}
    if tune and name is not None and fam.has_compensation:
        from tune_families import tune_family
        r = tune_family(name, fragment, d / "tune", duration_s, base=config)
        res["damage_removed"] = r.get("damage_removed")
    return res


def text(res: dict, own=()) -> list[str]:
    """The row of the table: family, size, true → fitted (error), verdict, damage removed;
    ``own``: the plant's own effects (named on its log without the effect), not listed as others."""
    vals = "; ".join(f"{k} {a:.4g} → {b:.4g} ({100 * (b - a) / abs(a):+.1f} %)" for k, a, b in res["values"])
    ok = res["named"] and all(abs(b - a) <= TOLERANCE * abs(a) for _, a, b in res["values"])
    named = "named" if res["named"] else f"NOT named (found {', '.join(res['effects']) or 'nothing'})"
    if res.get("error"):
        named = f"not identified: {res['error']}"
    if res["logged_s"] < 0.95 * res["duration_s"]:
        named += f" (the log ends at {res['logged_s']:.2f} s: the run faulted)"
    if res["also"]:
        named += f"; {res['also']} " + ("named" if res["also"] in res["effects"] else "NOT named")
    if res["named"] or res["also"]:
        others = [e for e in res["effects"] if e not in (res["name"], res["also"], *own)]
        named += f"; also {', '.join(others)}" if others else ""
    d = res["damage_removed"]
    return [res["name"], f"×{res['factor']:g}" + ("" if res["scaled"] else " (no force option)"),
            vals or "—", "yes" if ok else "no", named, "yes" if res["unexplained"] else "no",
            "—" if d is None else f"{d:.2f}"]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--family", action="append", default=None, help="only this family (repeatable)")
    ap.add_argument("--sizes", default="0.5,1", help="factors on the example's forces (default 0.5,1)")
    ap.add_argument("--duration", type=float, default=20.0, help="log length [s] (default 20)")
    ap.add_argument("--config", default="configs/gantry.yaml", help="the plant (default configs/gantry.yaml)")
    ap.add_argument("--tune", action="store_true", help="also tune's damage removed (compensable families)")
    ap.add_argument("--jobs", type=int, default=min(2, os.cpu_count() or 1), help="processes (default 2)")
    ap.add_argument("--out", default=None, help="keep logs here (default: a temporary folder)")
    ap.add_argument("--seed", type=int, default=1,
                    help="the simulated driver's seed: its force and encoder noise (default 1)")
    ap.add_argument("--with", dest="also", default=None, metavar="FAMILY",
                    help="also this family's example (x1) on every row's plant: two effects at once "
                         "(the row's family is judged; the table says what else was named)")
    ap.add_argument("--current-loop", action="store_true",
                    help="identify with the declared current loop modelled (Identifier current_loop)")
    args = ap.parse_args(argv)
    from motorctl.effects import FAMILIES
    names = args.family or list(FAMILIES)
    unknown = [n for n in names + ([args.also] if args.also else []) if n not in FAMILIES]
    if unknown:
        ap.error(f"unknown family {', '.join(unknown)}; families: {', '.join(FAMILIES)}")
    if not Path(args.config).is_file():
        ap.error(f"--config {args.config}: no such file")
    if args.also and args.tune:
        ap.error("--with and --tune: tune's damage removed is measured for one effect at a time")
    sizes = [float(x) for x in args.sizes.split(",")]
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="motorctl-ident-families-") as tmp:
        out = args.out or tmp
        work = [(None, 1.0)] + [(n, f) for n in names for f in sizes]
        job = (out, args.duration, args.config, args.tune, args.current_loop, args.seed, args.also)
        if args.jobs > 1 and len(work) > 1:
            with ProcessPoolExecutor(max_workers=args.jobs) as ex:
                done = list(ex.map(one, *zip(*work), *([j] * len(work) for j in job)))
        else:
            done = [one(n, f, *job) for n, f in work]
    own, done = done[0]["effects"], done[1:]
    header = ["family", "size (example ×)", "true → fitted (error)", "within 10 %", "identify",
              "warns unexplained", "damage removed by tune"]
    print(f"identify{' (current loop modelled)' if args.current_loop else ''} on {args.config}"
          + (f" with {args.also} (its example) on every plant" if args.also else "") + ", axis X, "
          f"{args.duration:g} s logs (virtual clock, seed {args.seed}); "
          f"load average {os.getloadavg()[0]:.2f}; the plant's own effects (named without one): "
          f"{', '.join(own) or 'none'}\n")
    print("| " + " | ".join(header) + " |")
    print("|" + "---|" * len(header))
    met = 0
    for r in done:
        row = text(r, own)
        met += row[3] == "yes"
        print("| " + " | ".join(row) + " |")
    cpu = [r["cpu_s"] for r in done]
    print(f"\n{met} of {len(done)} rows named with every compared value within {100 * TOLERANCE:g} %; "
          f"identify {min(cpu):.1f}-{max(cpu):.1f} s CPU per log")
    print(f"rerun: python benchmarks/ident_families.py [--family NAME] [--sizes 0.5,1] [--tune] "
          f"({time.perf_counter() - t0:.0f} s here)")
    return 0 if met == len(done) else 1


if __name__ == "__main__":
    sys.exit(main())
