"""What ``motorctl identify`` says on the default plant when nothing is added and when the
plant has something no force family models: false alarms, misses and wrong names over seeds.

Rerun:
    python benchmarks/ident_verdict.py                          # 3 seeds, 20 s logs, X axis
    python benchmarks/ident_verdict.py --seeds 5 --dir /tmp/iv  # logs kept (and reused) in DIR
    python benchmarks/ident_verdict.py --seed-from 4 --seeds 5  # seeds 4-8
    python benchmarks/ident_verdict.py --case sizes             # the other sizes of the same effects
    python benchmarks/ident_verdict.py --config configs/gantry-rigid.yaml --case all
    python benchmarks/ident_verdict.py --axis Y --trajectory a_max=5 --case clean --seeds 3

``--case`` takes a case's name or a group: ``default`` (the five below, the default run),
``sizes`` (the same effects at other sizes, below), ``holdout`` (sizes not looked at while the
checks were changed: ±2 µm at 1.5 mm, ±3 µm at 3 mm, ±4 µm at 2.5 mm, the mode at 100 and 175
Hz, the play at 30 and 150 µm), ``variants`` (the plant's other knobs: the mode's load
fraction and damping, a 250 Hz mode, the play on a lighter load, the encoder's error beside a
mode; clean plants with a 400 Hz current loop, a 5 µm encoder, 1 µm of encoder noise; see
``VARIANTS``), ``all``; repeatable. ``--config`` takes the
plant (default ``configs/gantry.yaml``); on a plant without a structural mode the backlash cases
are skipped (the play is in the mode's coupling). ``--axis Y`` takes the config's Y axis (the
configs/gantry.yaml one: 52 kg, its 120 Hz mode, a_max 10 m/s²) and ``--trajectory KEY=VALUE``
(repeatable) overrides a key of the axis's ``trajectory:`` section (e.g. a gentler ``a_max``):
plants and programs beyond the ones the checks were set on. Each log's identify summary is
written next to it as JSON (``<log>.json``: the verdict's shares, the candidates and their reasons).

Cases (``configs/gantry.yaml``, axis X, C2, virtual clock; :func:`motorctl.commission.tune.make_log`):

* ``clean``: the plant as it is (structural mode 350 Hz, current loop, encoder noise and its
  ±0.15 µm interpolation error at 20 µm, stiction). A warning "unexplained structured
  residual" is a **false alarm**; an effect named other than stiction and the input delay of
  the current loop (0.2 ms) is a **wrong name**.
* ``encoder``: an interpolation error of ±3 µm at a 2 mm signal period (a magnetic scale): the
  encoder_interpolation family or the warning is right; cogging, force ripple, a periodic
  disturbance or periodic friction is a **wrong name**; neither the family nor the warning is a
  **miss**.
* ``mode150``: the structural mode at 150 Hz instead of 350: the structural_mode family or the
  warning is right; a periodic disturbance, a force ripple, cogging or periodic friction is a
  **wrong name**; neither is a **miss**.
* ``backlash50``, ``backlash200``: the payload (the mode's load) held with a play of 50 µm and
  of 200 µm (``backlash_m``), an effect no family models: the warning is right; an input delay
  is a **wrong name** (the clean plant's current-loop delay included: with the play the band
  check refuses it); no warning is a **miss**.

Other sizes (``--case sizes``): the encoder's error of ±1.5 µm and ±5 µm at 1 mm and 4 mm
signal periods (``encoder1.5um1mm`` ...) and of ±2.5 µm at 0.8 mm (``encoder2.5um0.8mm``), the
mode at 120 and 200 Hz (``mode120``, ``mode200``), the play of 20 and 100 µm (``backlash20``,
``backlash100``); each judged as its kind above. A
200 Hz mode's antiresonance lies above the searched range (f_a 155 Hz on the default plant, 167
Hz on the rigid plant's load of 0.3): it is told as the plant's bandwidth limit (the family
refused at the grid's edge, with the load the band sees, m_l/M = (f_a/f_M)²; no warning when the
model with its force leaves no structure) or by the warning.

The clean plant's own names come from the axis's driver section with the case's changes (a
current loop a clean case adds is the plant's own): stiction (``stiction_N`` > 0), the
current loop's input delay (``current_loop_hz`` or ``current_loop_delay_s`` > 0) and, when its
antiresonance lies below the position filter's 250 Hz (``configs/gantry-half-mode.yaml``: 175
Hz, f_a 136 Hz), the structural mode; on such a plant the clean case is judged as a mode case
(the structural_mode family or the warning is right) and is not counted in the false alarms.

The verdict's rates: **false alarm** = a warning on a clean log; **miss** = no warning (and no
right family) on a log with an effect (backlash: no family models it, so only the warning is
right).

"Other names" counts the logs of a case that name a family neither right nor listed as wrong
nor the clean plant's (stiction, the current loop's delay): a phantom beside the effect.

Prints one line per log (the effects named, the verdict), the counts per case, and the verdict's
false-alarm and miss rates over all logs. A 20 s log takes 2-5 s to simulate once the numba
cache is warm (minutes the first time), identify 10-30 s on a 2-core machine.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
from pathlib import Path

CASES = {
    "clean": {},
    "encoder": {"encoder_interpolation_m": 3.0e-6, "encoder_signal_period_m": 2.0e-3},
    "mode150": {"mode_hz": 150.0},
    "backlash50": {"backlash_m": 5.0e-5},
    "backlash200": {"backlash_m": 2.0e-4},
}
#: the same effects at other sizes (``--case sizes``)
SIZES = {
    **{f"encoder{a:g}um{p:g}mm": {"encoder_interpolation_m": a * 1e-6, "encoder_signal_period_m": p * 1e-3}
       for a in (1.5, 5.0) for p in (1.0, 4.0)},
    "encoder2.5um0.8mm": {"encoder_interpolation_m": 2.5e-6, "encoder_signal_period_m": 0.8e-3},
    "mode120": {"mode_hz": 120.0},
    "mode200": {"mode_hz": 200.0},
    "backlash20": {"backlash_m": 2.0e-5},
    "backlash100": {"backlash_m": 1.0e-4},
}
#: sizes not used while the checks were changed (``--case holdout``; run on seeds 9-10)
HOLDOUT = {
    "encoder2um1.5mm": {"encoder_interpolation_m": 2.0e-6, "encoder_signal_period_m": 1.5e-3},
    "encoder3um3mm": {"encoder_interpolation_m": 3.0e-6, "encoder_signal_period_m": 3.0e-3},
    "encoder4um2.5mm": {"encoder_interpolation_m": 4.0e-6, "encoder_signal_period_m": 2.5e-3},
    "mode100": {"mode_hz": 100.0},
    "mode175": {"mode_hz": 175.0},
    "backlash30": {"backlash_m": 3.0e-5},
    "backlash150": {"backlash_m": 1.5e-4},
}
#: the plant's other knobs, never used while the checks were changed (``--case variants``; run
#: on seeds 21-22): the mode's load fraction and damping, a mode at 250 Hz, the play on a lighter
#: load, the encoder's error beside the 150 Hz mode; and clean plants (judged as ``clean``: the
#: plant's own names only) with a 400 Hz current loop, a 5 µm encoder, 1 µm of encoder noise
VARIANTS = {
    "mode150lf0.2": {"mode_hz": 150.0, "mode_load_fraction": 0.2},
    "mode150lf0.6": {"mode_hz": 150.0, "mode_load_fraction": 0.6},
    "mode150z0.01": {"mode_hz": 150.0, "mode_damping": 0.01},
    "mode150z0.08": {"mode_hz": 150.0, "mode_damping": 0.08},
    "mode250": {"mode_hz": 250.0},
    "backlash70lf0.2": {"backlash_m": 7.0e-5, "mode_load_fraction": 0.2},
    "encoder3um2mm_mode150": {"encoder_interpolation_m": 3.0e-6, "encoder_signal_period_m": 2.0e-3,
                              "mode_hz": 150.0},
    "clean_cl400": {"current_loop_hz": 400.0},
    "clean_encoder5um": {"encoder_resolution_m": 5.0e-6},
    "clean_noise1um": {"encoder_noise_m": 1.0e-6},
}
ALL = {**CASES, **SIZES, **HOLDOUT, **VARIANTS}
GROUPS = {"default": list(CASES), "sizes": list(SIZES), "holdout": list(HOLDOUT), "variants": list(VARIANTS),
          "all": list(ALL)}
#: names that are wrong for each kind of case
PERIODIC = {"cogging", "force_ripple", "periodic_disturbance", "periodic_friction"}
WRONG = {"encoder": PERIODIC, "mode": PERIODIC, "backlash": {"input_delay"}}
#: the family that names each kind rightly (besides the warning)
RIGHT = {"encoder": "encoder_interpolation", "mode": "structural_mode"}
#: the position filter's cut-off at 5 kHz [Hz]: a mode whose antiresonance lies above it is not seen
MODE_SEEN_HZ = 250.0


def kind(case: str) -> str:
    """'clean', 'encoder', 'mode' or 'backlash'."""
    return next(k for k in ("clean", "encoder", "mode", "backlash") if case.startswith(k))


def plant_names(drv: dict) -> set:
    """The effects the clean plant of an axis's driver section has and identify may name."""
    names = set()
    if drv.get("stiction_N", 0.0) > 0:
        names.add("stiction")
    if drv.get("current_loop_hz", 0.0) > 0 or drv.get("current_loop_delay_s", 0.0) > 0:
        names.add("input_delay")
    f, lf = drv.get("mode_hz", 0.0), drv.get("mode_load_fraction", 0.3)
    if 0 < f * math.sqrt(1.0 - lf) < MODE_SEEN_HZ:
        names.add("structural_mode")
    return names


def _key_number(text: str) -> tuple[str, float]:
    """``--trajectory``'s KEY=NUMBER as (key, number)."""
    key, _, value = text.partition("=")
    try:
        return key, float(value)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: expected KEY=NUMBER, e.g. a_max=25") from None


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", type=int, default=3, help="seeds per case (default 3)")
    ap.add_argument("--seed-from", type=int, default=1, help="first seed (default 1): seeds N..N+seeds-1")
    ap.add_argument("--duration", type=float, default=20.0, help="log length [s] (default 20)")
    ap.add_argument("--dir", default="/tmp/motorctl_ident_verdict", help="where the logs go (reused)")
    ap.add_argument("--config", default=None, help="the plant (default configs/gantry.yaml)")
    ap.add_argument("--axis", default="X", help="the config's axis (default X)")
    ap.add_argument("--trajectory", action="append", default=[], metavar="KEY=VALUE", type=_key_number,
                    help="a key of the axis's trajectory: section to override, e.g. a_max=5 (repeatable)")
    ap.add_argument("--case", action="append", choices=list(ALL) + list(GROUPS),
                    help="only these cases or groups (default, sizes, holdout, variants, all; repeatable; "
                         "default: default)")
    args = ap.parse_args(argv)

    from motorctl.commission.tune import make_log
    from motorctl.config import load_yaml
    from motorctl.ident.data import load_record
    from motorctl.ident.pipeline import identify_record

    default = Path(__file__).resolve().parents[1] / "configs" / "gantry.yaml"
    base = Path(args.config).resolve() if args.config else default
    if not base.is_file():
        print(f"ident_verdict.py: --config {args.config}: no such file", file=sys.stderr)
        return 2
    axes = load_yaml(str(base))["axes"]
    if args.axis not in axes:
        print(f"ident_verdict.py: --axis {args.axis}: {base.name} has {', '.join(axes)}", file=sys.stderr)
        return 2
    trajectory = dict(args.trajectory)
    drv = axes[args.axis]["driver"]
    own = plant_names(drv)
    prefix = "" if base == default else base.stem + "_"
    prefix += "" if args.axis == "X" else f"{args.axis}_"
    prefix += "".join(f"{k}{v:g}_" for k, v in trajectory.items())
    cases = []
    for c in args.case or ["default"]:
        cases += [k for k in GROUPS.get(c, [c]) if k not in cases]
    if drv.get("mode_hz", 0.0) <= 0:
        skipped = [c for c in cases if kind(c) == "backlash"]
        if skipped:
            print(f"{base.name}: no structural mode, so no play in its coupling: {', '.join(skipped)} skipped")
        cases = [c for c in cases if kind(c) != "backlash"]
    out = Path(args.dir)
    out.mkdir(parents=True, exist_ok=True)
    seeds = range(args.seed_from, args.seed_from + args.seeds)
    counts = {}
    for case in cases:
        # the plant's own names with the case's changes (a current loop a clean case adds is its own);
        # a clean plant whose own mode the family can see is judged as a mode case
        mine = plant_names({**drv, **ALL[case]})
        kd = "mode" if kind(case) == "clean" and "structural_mode" in mine else kind(case)
        c = counts.setdefault(case, {"logs": 0, "warned": 0, "wrong": 0, "right": 0, "named": 0, "other": 0,
                                     "kind": kd})
        for seed in seeds:
            path = out / f"{prefix}{case}_seed{seed}_{args.duration:g}s.mclog"
            if not path.exists():
                make_log(str(path), ALL[case], duration_s=args.duration, seed=seed, base=str(base),
                         axis=args.axis, trajectory=trajectory or None)
            _, s = identify_record(load_record(str(path), None, None, axis=args.axis))
            Path(str(path) + ".json").write_text(json.dumps(s, default=float, indent=1))
            names = {e["name"] for e in s["effects"]}
            warned = bool(s["residual"]["structured"])
            # a mode above the band told as the plant's bandwidth limit (the residual without
            # structure beside its force): the structural mode's, not a warning
            limit = any(t.get("explained_by") == "structural_mode" for t in s["residual"]["tested"])
            wrong = (names - mine) if kd == "clean" else (names & WRONG[kd])
            right = warned or RIGHT.get(kd) in names or (kd == "mode" and limit)
            other = names - mine - WRONG.get(kd, set()) - {RIGHT.get(kd)}
            c["logs"] += 1
            c["named"] += RIGHT.get(kd) in names
            c["other"] += bool(other) and kd != "clean"
            c["warned"] += warned
            c["wrong"] += bool(wrong)
            c["right"] += right
            text = s["residual"]["text"]
            # a mode above the band: what the record says of it comes after the first 160 characters
            tail = text.find("a bandwidth limit", 160)
            more = f" [... {text[tail:tail + 160]}]" if tail > 0 else ""
            print(f"{case} seed {seed}: effects {', '.join(sorted(names)) or 'none'}; "
                  f"{'WARNING ' if warned else ''}{text[:160]}{more}", flush=True)
    print()
    ok = True
    own_text = " and ".join(sorted(own - {"structural_mode"})) or "nothing"
    for case, c in counts.items():
        if c["kind"] == "clean":
            print(f"{case}: false alarms {c['warned']}/{c['logs']}, wrong names {c['wrong']}/{c['logs']}")
            ok &= c["warned"] == 0 and c["wrong"] == 0
        else:
            fam = f", named by {RIGHT[c['kind']]} {c['named']}/{c['logs']}" if c["kind"] in RIGHT else ""
            plant = ("the plant's stiction and delay" if own == {"stiction", "input_delay"}
                     else f"the plant's {own_text}")
            print(f"{case}: told (the family or the warning) {c['right']}/{c['logs']}{fam}, misses "
                  f"{c['logs'] - c['right']}/{c['logs']}, wrong names {c['wrong']}/{c['logs']}, "
                  f"other names beside {plant} {c['other']}/{c['logs']}")
            ok &= c["right"] == c["logs"] and c["wrong"] == 0
    clean = [c for c in counts.values() if c["kind"] == "clean"]
    effect = [c for c in counts.values() if c["kind"] != "clean"]
    if clean:
        print(f"verdict false-alarm rate: {sum(c['warned'] for c in clean)}/{sum(c['logs'] for c in clean)} "
              "clean logs warned")
    if effect:
        n = sum(c["logs"] for c in effect)
        print(f"verdict miss rate: {sum(c['logs'] - c['right'] for c in effect)}/{n} logs with an effect neither "
              f"named by its family nor warned; warned alone: {sum(c['warned'] for c in effect)}/{n}")
    rerun = f"--seeds {args.seeds}"
    rerun += f" --seed-from {args.seed_from}" if args.seed_from != 1 else ""
    rerun += f" --config {args.config}" if args.config else ""
    rerun += f" --axis {args.axis}" if args.axis != "X" else ""
    rerun += "".join(f" --trajectory {k}={v:g}" for k, v in args.trajectory)
    rerun += "".join(f" --case {c}" for c in args.case or [])
    print(f"load average {os.getloadavg()[0]:.2f}; rerun: python benchmarks/ident_verdict.py {rerun}")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
