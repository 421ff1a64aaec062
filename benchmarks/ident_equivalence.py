"""Same results from ``motorctl identify`` before and after a change of its speed: a set of 20 s
logs of the default plant, identified by two source trees, compared.

Rerun:
    git archive main | tar -x -C /tmp/motorctl-main                  # the reference tree, once
    python benchmarks/ident_equivalence.py --ref-src /tmp/motorctl-main
    python benchmarks/ident_equivalence.py --src /tmp/motorctl-main --save /tmp/ref.json  # or: saved once ...
    python benchmarks/ident_equivalence.py --against /tmp/ref.json    # ... and compared later

The logs (built once into ``--logs``, default /tmp/motorctl-ident-equivalence): the simulated X
axis of ``configs/gantry.yaml`` (structural mode, current loop, encoder noise, stiction; C2,
virtual clock, seed 1), 20 s, clean and with each of :data:`FAMILIES` at its family's
``example`` size (undeclared to the controller). Each is identified by
``motorctl identify LOG --axis X --json --no-closed-loop`` as a new process with this tree's
code and with the reference (``--ref-src``: that tree first on PYTHONPATH; ``--against``: a
file of a ``--save``). Verdict per log: the same effect families named, in the same order;
every fitted parameter within :data:`REL_TOL` (phases within :data:`PHASE_TOL_RAD`); the
nominal θ within :data:`REL_TOL` or a tenth of its standard deviation; the residual verdict
(structured or not) the same.

Exit 0 when every log agrees, 1 otherwise.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path

#: the families whose example is put on the plant, one log each (plus a clean log)
FAMILIES = ("cogging", "spring", "stribeck", "asymmetric_friction", "input_delay", "periodic_disturbance")
#: largest relative difference of a fitted value [-]
REL_TOL = 0.01
#: largest difference of a fitted phase [rad]
PHASE_TOL_RAD = 0.01
#: a nominal θ_i may also differ by this share of its standard deviation
THETA_STD_SHARE = 0.1


def build_logs(folder: Path, duration_s: float, config: str) -> dict[str, Path]:
    """{name: log path}: the clean log and one per family of :data:`FAMILIES`, built when missing."""
    from motorctl.commission.tune import make_log
    from motorctl.effects import FAMILIES as REGISTRY
    folder.mkdir(parents=True, exist_ok=True)
    out = {}
    for name in ("clean",) + FAMILIES:
        path = folder / f"{name}_{duration_s:g}s.mclog"
        if not path.exists():
            t0 = time.perf_counter()
            make_log(str(path), None if name == "clean" else REGISTRY[name].example, duration_s=duration_s,
                     seed=1, axis="X", noise_N=None, base=config)
            print(f"built {path} in {time.perf_counter() - t0:.1f} s", flush=True)
        out[name] = path
    return out


#: the source tree this script belongs to
HERE = Path(__file__).resolve().parents[1]


def identify(log: Path, src: str | Path = HERE) -> dict:
    """The JSON summary of ``motorctl identify LOG --axis X --json --no-closed-loop`` run as a
    new process on the source tree ``src`` (its working directory and first on PYTHONPATH:
    ``python -c`` puts the working directory first on sys.path)."""
    src = Path(src).resolve()
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(src)] + [p for p in [env.get("PYTHONPATH")] if p])
    cmd = [sys.executable, "-c", "import sys; from motorctl.cli import main; sys.exit(main())", "identify",
           str(log), "--axis", "X", "--json", "--no-closed-loop"]
    out = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=str(src), check=False)
    if out.returncode != 0:
        raise RuntimeError(f"identify {log} failed (exit {out.returncode}): {out.stderr.strip()[-300:]}")
    return json.loads(out.stdout)


def essentials(s: dict) -> dict:
    """What is compared of a summary: effects (name, parameters), nominal θ and std, verdict."""
    return {"effects": [{"name": e["name"], "parameters": e["parameters"]} for e in s["effects"]],
            "theta": s["nominal"]["theta"], "theta_std": s["nominal"]["theta_std"],
            "structured": bool(s["residual"]["structured"])}


def _values(key: str, a, b, out: list) -> None:
    """Append (key, a, b, ok) for every numeric leaf of parameters a (reference) and b."""
    if isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            out.append((key, len(a), len(b), False))
            return
        for i, (x, y) in enumerate(zip(a, b)):
            _values(f"{key}[{i}]", x, y, out)
        return
    if isinstance(a, (int, float)) and isinstance(b, (int, float)):
        tol = PHASE_TOL_RAD if "phase" in key else REL_TOL * abs(a)
        d = abs(b - a)
        if "phase" in key:
            d = abs(math.remainder(b - a, 2 * math.pi))
        out.append((key, a, b, d <= tol))
        return
    out.append((key, a, b, a == b))


def compare(ref: dict, new: dict) -> tuple[bool, list[str]]:
    """(agree, lines): the verdict of one log (module docstring) and what differs."""
    lines = []
    rn, nn = [e["name"] for e in ref["effects"]], [e["name"] for e in new["effects"]]
    ok = rn == nn
    if not ok:
        lines.append(f"effects named: {rn or 'none'} -> {nn or 'none'}")
    vals: list = []
    if ok:
        for er, en in zip(ref["effects"], new["effects"]):
            for k in er["parameters"]:
                _values(f"{er['name']}.{k}", er["parameters"][k], en["parameters"].get(k), vals)
    for i, (a, b, sd) in enumerate(zip(ref["theta"], new["theta"], ref["theta_std"])):
        d = abs(b - a)
        vals.append((f"theta{i + 1}", a, b, d <= REL_TOL * abs(a) or d <= THETA_STD_SHARE * sd))
    worst = 0.0
    for key, a, b, good in vals:
        if isinstance(a, (int, float)) and isinstance(b, (int, float)) and a:
            worst = max(worst, abs(b - a) / abs(a)) if "phase" not in key else worst
        if not good:
            ok = False
            lines.append(f"{key}: {a!r} -> {b!r}")
    if ref["structured"] != new["structured"]:
        ok = False
        lines.append(f"residual structured: {ref['structured']} -> {new['structured']}")
    lines.insert(0, f"{len(vals)} values, largest relative change {100 * worst:.3f} %")
    return ok, lines


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--logs", default="/tmp/motorctl-ident-equivalence", help="folder of the logs (built once)")
    ap.add_argument("--duration", type=float, default=20.0, help="log length [s] (default 20)")
    ap.add_argument("--config", default=str(HERE / "configs" / "gantry.yaml"),
                    help="the plant (default configs/gantry.yaml)")
    ap.add_argument("--ref-src", default=None, help="source tree of the reference (e.g. an export of main)")
    ap.add_argument("--against", default=None, help="compare with the results of an earlier --save")
    ap.add_argument("--src", default=str(HERE), help="source tree compared (default: this script's)")
    ap.add_argument("--save", default=None, help="write --src's results here (JSON)")
    ap.add_argument("--only", action="append", default=None, help="only this log (clean or a family; repeatable)")
    args = ap.parse_args(argv)
    for opt, d in (("--ref-src", args.ref_src), ("--src", args.src)):
        if d and not (Path(d) / "motorctl").is_dir():
            ap.error(f"{opt} {d}: no motorctl package there")
    if args.against and not Path(args.against).is_file():
        ap.error(f"--against {args.against}: no such file")
    logs = build_logs(Path(args.logs), args.duration, args.config)
    if args.only:
        logs = {k: v for k, v in logs.items() if k in args.only}
    ref = json.loads(Path(args.against).read_text()) if args.against else {}
    mine, cpu = {}, {}
    for name, path in logs.items():
        r0 = os.times()
        mine[name] = essentials(identify(path, args.src))
        r1 = os.times()
        cpu[name] = (r1.children_user - r0.children_user) + (r1.children_system - r0.children_system)
        if args.ref_src:
            ref[name] = essentials(identify(path, args.ref_src))
    if args.save:
        Path(args.save).write_text(json.dumps(mine, indent=1))
        print(f"saved {len(mine)} results to {args.save}")
    if not ref:
        return 0
    bad = 0
    print(f"identify --no-closed-loop on {len(logs)} logs of {args.duration:g} s ({args.config}, axis X, seed 1); "
          f"load average {os.getloadavg()[0]:.2f}")
    for name in logs:
        if name not in ref:
            print(f"  {name}: no reference result")
            bad += 1
            continue
        ok, lines = compare(ref[name], mine[name])
        bad += not ok
        named = ", ".join(e["name"] for e in mine[name]["effects"]) or "no effect"
        print(f"  {name}: {'SAME' if ok else 'DIFFERENT'} ({named}; {lines[0]}; {cpu[name]:.2f} s CPU)")
        for line in lines[1:]:
            print(f"      {line}")
    print(f"{len(logs) - bad} of {len(logs)} logs give the same result")
    print("rerun: python benchmarks/ident_equivalence.py --ref-src DIR | --against FILE [--save FILE]")
    return 0 if bad == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
