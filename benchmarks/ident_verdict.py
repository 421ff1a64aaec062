"""What ``motorctl identify`` says on the default plant when nothing is added and when the
plant has something no force family models: false alarms, misses and wrong names over seeds.

Rerun:
    python benchmarks/ident_verdict.py                          # 3 seeds, 20 s logs, X axis
    python benchmarks/ident_verdict.py --seeds 5 --dir /tmp/iv  # logs kept (and reused) in DIR

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
#: effects the clean plant has and identify may name
CLEAN_NAMES = {"stiction", "input_delay"}
#: names that are wrong for each case
WRONG = {"encoder": {"cogging", "force_ripple", "periodic_disturbance", "periodic_friction"},
         "mode150": {"periodic_disturbance", "force_ripple", "cogging", "periodic_friction"},
         "backlash50": {"input_delay"}, "backlash200": {"input_delay"}}
#: the family that names each case rightly (besides the warning)
RIGHT = {"encoder": "encoder_interpolation", "mode150": "structural_mode"}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", type=int, default=3, help="seeds per case (default 3)")
    ap.add_argument("--duration", type=float, default=20.0, help="log length [s] (default 20)")
    ap.add_argument("--dir", default="/tmp/motorctl_ident_verdict", help="where the logs go (reused)")
    ap.add_argument("--case", action="append", choices=list(CASES), help="only these cases (repeatable)")
    args = ap.parse_args(argv)

    from motorctl.commission.tune import make_log
    from motorctl.ident.data import load_record
    from motorctl.ident.pipeline import identify_record

    base = Path(__file__).resolve().parents[1] / "configs" / "gantry.yaml"
    out = Path(args.dir)
    out.mkdir(parents=True, exist_ok=True)
    counts = {}
    for case in args.case or list(CASES):
        c = counts.setdefault(case, {"logs": 0, "warned": 0, "wrong": 0, "right": 0, "named": 0, "other": 0})
        for seed in range(1, args.seeds + 1):
            path = out / f"{case}_seed{seed}_{args.duration:g}s.mclog"
            if not path.exists():
                make_log(str(path), CASES[case], duration_s=args.duration, seed=seed, base=str(base))
            _, s = identify_record(load_record(str(path), None, None, axis="X"))
            names = {e["name"] for e in s["effects"]}
            warned = bool(s["residual"]["structured"])
            wrong = (names - CLEAN_NAMES) if case == "clean" else (names & WRONG[case])
            right = warned or RIGHT.get(case) in names
            other = names - CLEAN_NAMES - WRONG.get(case, set()) - {RIGHT.get(case)}
            c["logs"] += 1
            c["named"] += RIGHT.get(case) in names
            c["other"] += bool(other) and case != "clean"
            c["warned"] += warned
            c["wrong"] += bool(wrong)
            c["right"] += right
            print(f"{case} seed {seed}: effects {', '.join(sorted(names)) or 'none'}; "
                  f"{'WARNING ' if warned else ''}{s['residual']['text'][:160]}", flush=True)
    print()
    ok = True
    for case, c in counts.items():
        if case == "clean":
            print(f"clean: false alarms {c['warned']}/{c['logs']}, wrong names {c['wrong']}/{c['logs']}")
            ok &= c["warned"] == 0 and c["wrong"] == 0
        else:
            fam = f", named by {RIGHT[case]} {c['named']}/{c['logs']}" if case in RIGHT else ""
            print(f"{case}: told (the family or the warning) {c['right']}/{c['logs']}{fam}, misses "
                  f"{c['logs'] - c['right']}/{c['logs']}, wrong names {c['wrong']}/{c['logs']}, "
                  f"other names beside the plant's stiction and delay {c['other']}/{c['logs']}")
            ok &= c["right"] == c["logs"] and c["wrong"] == 0
    clean = counts.get("clean")
    effect = [c for k, c in counts.items() if k != "clean"]
    if clean:
        print(f"verdict false-alarm rate: {clean['warned']}/{clean['logs']} clean logs warned")
    if effect:
        n = sum(c["logs"] for c in effect)
        print(f"verdict miss rate: {sum(c['logs'] - c['right'] for c in effect)}/{n} logs with an effect neither "
              f"named by its family nor warned; warned alone: {sum(c['warned'] for c in effect)}/{n}")
    print(f"load average {os.getloadavg()[0]:.2f}; rerun: python benchmarks/ident_verdict.py --seeds {args.seeds}")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
