"""GTCF (the contouring pair law, motorctl.control.gtcf) against per-axis C2 on the simulated gantry,
each with the gains ``motorctl autotune`` writes for it.

    .venv/bin/python benchmarks/bench_gtcf.py [--config configs/gantry.yaml] [--out DIR] [--skip-cut]
                                              [--no-autotune] [--sweep 1.5,2,2.5/1.5] [--seeds 2,3,4,5]
                                              [--plant X.stiction_N=20,Y.stiction_N=16] [--grid] [--no-causes]

0. (default) ``motorctl autotune CONFIG --axis X --axis Y --law c2 --virtual-clock --json --out
   DIR/autotune`` on a copy of the config (a subprocess): both axes' C2 gains by the rule, then
   GTCF's gain_n per axis on them by the same rule (motorctl.commission.gtcf_tune), written to
   DIR/autotune/autotuned.yaml; the rest runs that file, C2 and GTCF alike. ``--no-autotune``:
   the config's own gains.
1. The ISO 230-4 circle, R 50 mm at 50 and 100 mm/s, by the user's command:
   ``motorctl circle-test CONFIG --controller c2 --controller gtcf --feed 0.05 --feed 0.1 --json
   --log DIR/circle.log`` (a subprocess, bounded by a timeout). From each run log's header
   (``circle.figures_m``), per instrument: G (worse of cw/ccw), G(b) and, for the simulated
   ballbar (the plant's true carriage positions, which the simulated driver reads beside its
   encoders: no encoder floor), the largest contour error. From each run log's encoder rows,
   independently of motorctl's evaluation: the test circles' rows
   (the header's ``circle.rows``), an algebraic least-squares circle fit (Kåsa) of the measured
   X.y, Y.y per direction, and the largest |r − R_fit| (the largest contour error about the
   fitted circle); the saturated samples (|u| ≥ u_lim − 1 mV, either axis) in the test circles'
   rows and in the whole run (its rapid approach included) and their share of the run, the
   largest |u| in the test circles, the u RMS at rest (the dwells; the worse axis,
   motorctl.metrics.u_rest_rms), a fault (circle-test's exit).
2. A plasma cut path with lead-in arcs (benchmarks/bench_contour.py's CUT: lead-ins of 1-2 mm,
   R 3 mm corners, a slot, an R 8 mm hole; F5000) streamed through the same daemon motion path
   as the circle test (:func:`motorctl.app.circle_test.run_circle_test` with the program swapped
   for the cut path), the run log written; from the log: the largest distance of the measured
   path from the programmed path (:func:`motorctl.motion.path.contour_error`), separately while
   cutting (the setpoint moving at no more than F5000) and on the G0 rapids between the
   contours, the saturation as above in those rows; and the servo's own part, the distance of
   the measured path from the setpoints' path (the log's x_d, a polyline; the programmed path
   less the planner's G64 P0.01 blending, which alone departs up to ~9 µm from it:
   benchmarks/bench_contour.py).

3. ``--sweep``: GTCF again with each listed gain_n (X's/Y's; one number: both; gain_t and the
   low-pass as chosen) on the same circles and cut path, admitted by the rule or not, and a table of what each buys (the ratios of 1.) and
   costs: each axis's u RMS at rest on the circle and the cut (the cut's straight edges hold one
   axis still while the other moves: that axis is the contour direction, under gain_n), the
   saturated samples, and whether autotune found the margins holding for it.
4. ``--seeds``: the circles again with the simulated driver's seed set to each listed value (the
   encoder's and the force noise's realisation; the same gains, no new autotune), per seed the
   ratios of 1. and their median, by the encoders and by the ballbar, and the verdict: on how
   many draws and feeds GTCF's G and G(b) by the ballbar are ≥ 30 % below C2's; on a draw where
   they are not, C2's and GTCF's G against the 0.70 × C2 it needed and what bounds it: G(b) by
   the ballbar of both laws on that draw decomposed by cause (:func:`causes`: the circle again
   with each of :data:`CAUSES` removed from the plant alone, the stick (breakaway = Coulomb
   friction), the encoder's noise and interpolation error inside the loop, the force noise, and
   all three together: the loop's deterministic error), each with where G(b) is made (the
   radial deviation within ±10° of X's reversals, of Y's, elsewhere; 10 circle runs a missed
   draw, ``--no-causes``: the split alone). The largest figures are the axes' reversals, where the
   plant's stiction (1.25 × its Coulomb friction) holds an axis until the loop has built the
   breakaway force; the noise dithers that stick (and the Coulomb friction's reversal), C2's
   more than GTCF's, so one seed's ratio is one draw.
5. The encoder's floor: G of each test circle's own setpoints (the C2 log's x_d) as the config's
   simulated encoders read them (resolution, noise, interpolation error; 10 draws): the G of a
   motion without any error: what the measured positions show of a perfect law.
6. ``--plant``: the circles, the cut and the seeds on the simulated plant changed so (driver keys
   per axis; the gains as tuned on the config's plant): e.g. the breakaway force set to the
   Coulomb friction (no stick at the reversals), or the encoder without noise and interpolation
   error, to see which of the plant's effects a figure rests on.
7. ``--grid``: GTCF's circles with each of 60 settings (X gain_n 1.5-3 x lambda_n 1-2, Y gain_n
   1-2 x low-pass 500 Hz or none) on the config's seed and ``--seeds``, judged by G alone
   (autotune's rule not asked): the least G the law's settings reach on each draw (about 10
   minutes for five draws).

Prints the autotuned gains and a Markdown table with the ratio GTCF / C2 (below 0.70: the ≥ 30 %
target). Deterministic (the virtual clock, the simulated driver's seed): the same figures every
run.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import math
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

LAWS = ("c2", "gtcf")
FEEDS = (0.05, 0.1)
U_LIM = 10.0


def fit_circle(x: np.ndarray, y: np.ndarray) -> tuple[float, float, float]:
    """Kåsa's algebraic least-squares circle: (cx, cy, R) [m] minimising Σ(x² + y² + D x + E y + F)²."""
    A = np.column_stack([x, y, np.ones_like(x)])
    b = -(x * x + y * y)
    (D, E, F), *_ = np.linalg.lstsq(A, b, rcond=None)
    cx, cy = -D / 2.0, -E / 2.0
    return cx, cy, float(np.sqrt(cx * cx + cy * cy - F))


def saturation(log, mask=None) -> tuple[int, float, int]:
    """(samples with |u| ≥ u_lim − 1 mV on either axis and the largest |u| [V] among the rows of
    ``mask`` (None: all), the saturated samples of the whole run) of a run log."""
    u = np.column_stack([log.col(f"{a}.u") for a in ("X", "Y")])
    sat = np.any(np.abs(u) >= U_LIM - 1e-3, axis=1)
    m = np.ones(len(u), bool) if mask is None else mask
    return int(sat[m].sum()), float(np.max(np.abs(u[m]))), int(sat.sum())


def rest_by_axis(log) -> dict:
    """Each axis's u RMS at rest [V] over a run log's enabled rows ({"X": .., "Y": ..}):
    :func:`motorctl.metrics.u_rest_rms`, u about its mean where the axis's command has not moved
    for 0.3 s (on the rectangle's and the cut's straight edges too, where the partner moves); nan
    with no rest."""
    from motorctl.metrics import REST_AFTER_S, rest_mask, u_rest_rms
    out = {}
    ts = float(log.col("t")[1] - log.col("t")[0]) if len(log.col("t")) > 1 else 2e-4
    for a in ("X", "Y"):
        on = log.col(f"{a}.enabled") > 0.5
        rest = rest_mask(log.col(f"{a}.xd_dot")[on], log.col(f"{a}.xd_ddot")[on], ts, REST_AFTER_S)
        out[a] = u_rest_rms(log.col(f"{a}.u")[on], rest)
    return out


def rest_noise(log) -> float:
    """The larger of the two axes' u RMS at rest [V] (:func:`rest_by_axis`); nan with no rest."""
    out = list(rest_by_axis(log).values())
    return max(out) if all(v == v for v in out) else math.nan


def circles(config: str, out: Path, timeout_s: float, laws=LAWS) -> list[dict]:
    from motorctl.recorder.runlog import read_log
    base = out / "circle.log"
    cmd = [sys.executable, "-m", "motorctl", "circle-test", config, "--json", "--log", str(base)]
    for c in laws:
        cmd += ["--controller", c]
    for f in FEEDS:
        cmd += ["--feed", str(f)]
    print("$ " + " ".join(cmd[2:]).replace("-m motorctl", "motorctl"), file=sys.stderr)
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s, cwd=REPO)
    if res.returncode != 0:
        raise SystemExit(f"circle-test failed ({res.returncode}): {res.stderr[-2000:]}")
    rows = []
    for r in json.loads(res.stdout):
        log = read_log(r["log"])
        figs = log.header["circle"]["figures_m"]
        enc, bb = figs["encoder"], figs["ballbar"]
        xs, ys = log.col("X.y"), log.col("Y.y")
        worst = 0.0
        mask = np.zeros(len(xs), bool)
        for d, (a, b) in log.header["circle"]["rows"].items():
            mask[a:b] = True
            x, y = xs[a:b], ys[a:b]
            cx, cy, R = fit_circle(x, y)
            worst = max(worst, float(np.max(np.abs(np.hypot(x - cx, y - cy) - R))))
        sat, umax, sat_all = saturation(log, mask)
        rows.append({"path": f"circle R50 {r['feed_m_s'] * 1e3:.0f} mm/s", "law": r["controller"],
                     "G": max(enc["G_cw"], enc["G_ccw"]) * 1e6, "Gb": enc["G_b"] * 1e6, "emax": worst * 1e6,
                     "bb": None if bb is None else {"G": max(bb["G_cw"], bb["G_ccw"]) * 1e6, "Gb": bb["G_b"] * 1e6,
                                                    "emax": bb["e_max"] * 1e6},
                     "sat": sat, "umax": umax, "sat_all": sat_all, "share": sat_all / len(xs),
                     "rest": rest_noise(log), "rest_axes": rest_by_axis(log), "fault": "-", "log": r["log"]})
    return rows


def encoder_floor(config: str, log_path: str, seeds=range(1, 11)) -> list[float]:
    """G [um] of the test circles' own setpoints (the log's X.x_d, Y.x_d in the header's
    ``circle.rows``, the worse of cw and ccw) as the config's simulated encoders read them, one
    per seed: a motion without any error, each sample read by the simulated axis's own
    :meth:`motorctl_drivers.sim.AxisPlant.measured` (the carriage put at the setpoint, the
    period's encoder noise drawn as the driver draws it: 0.5 um steps, noise, interpolation
    error, each axis's ``encoder_*`` keys), its Kasa circle and its roundness as G is taken.
    What a G computed on measured positions shows of a perfect law (a loop can take out only
    the part of the encoder's error inside its bandwidth, near the reversals)."""
    import yaml
    from motorctl.recorder.runlog import read_log
    from motorctl_drivers.sim import AxisPlant, SimAxisOptions
    raw = yaml.safe_load(Path(config).read_text())
    log = read_log(log_path)
    ts = float(log.col("t")[1] - log.col("t")[0])
    plants = {a: AxisPlant(SimAxisOptions(**raw["axes"][a]["driver"]), ts, np.random.default_rng(0), 1)
              for a in ("X", "Y")}
    out = []
    for seed in seeds:
        rng = np.random.default_rng(seed)
        g = 0.0
        for a, b in log.header["circle"]["rows"].values():
            m = []
            for ax in ("X", "Y"):
                plant, x = plants[ax], log.col(f"{ax}.x_d")[a:b]
                noise = plant.enc_sigma * rng.standard_normal(len(x))
                read = np.empty(len(x))
                for k in range(len(x)):
                    plant.x, plant.enc_noise = x[k], noise[k]
                    read[k] = plant.measured()
                m.append(read)
            cx, cy, _ = fit_circle(*m)
            r = np.hypot(m[0] - cx, m[1] - cy)
            g = max(g, float(r.max() - r.min()) * 1e6)
        out.append(g)
    return out


#: the band about each axis's reversal on the test circle (0°, 90°, 180°, 270°: where X's or Y's
#: velocity changes sign) that :func:`reversal_split` sets apart [rad]
REVERSAL_BAND = math.radians(10.0)


def reversal_split(config: str, feed: float, law: str) -> dict:
    """Where the simulated ballbar's G(b) of one circle test is made (R 50 mm at ``feed`` [m/s]
    with ``law``, run in this process by :func:`motorctl.app.circle_test.run_circle_test`, the
    command's own runner): the radial deviations [um] of both test circles about their
    bidirectional least-squares circle, as (largest, smallest) in three regions: "X" within
    :data:`REVERSAL_BAND` of X's reversals (0°, 180°: X's velocity changes sign, the normal is
    X), "Y" of Y's (90°, 270°), "off" the rest (the loop's own scatter, which a contour gain at
    the reversals does not take out); and "all", G(b) [um]."""
    from motorctl.app.circle_test import run_circle_test
    from motorctl.config import load_config
    from motorctl.motion.circle import radial
    run = run_circle_test(load_config(config), 0.05, feed, law)
    bb = run.readings["ballbar"]
    xc, yc = bb.result.center_lsc
    ang, rad = [np.concatenate(v) for v in zip(*(radial(*bb.paths[d], (xc, yc)) for d in ("cw", "ccw")))]
    dev = (rad - bb.result.radius_lsc) * 1e6
    qx = np.abs((ang + np.pi / 2) % np.pi - np.pi / 2)           # the angle to X's nearest reversal
    qy = np.abs(ang % np.pi - np.pi / 2)                         # ... to Y's
    out = {"all": bb.result.G_b * 1e6}
    for name, m in (("X", qx <= REVERSAL_BAND), ("Y", qy <= REVERSAL_BAND),
                    ("off", (qx > REVERSAL_BAND) & (qy > REVERSAL_BAND))):
        out[name] = (float(dev[m].max()), float(dev[m].min()))
    return out


#: the causes of a circle's G(b) that :func:`causes` removes from the simulated plant, one at a
#: time on the same draw: (what it is, the axis's driver keys that remove it, from the axis's
#: driver mapping). A noise's deviation is set to 1e-15 (1 fm, 1 fN: the least the config takes),
#: not 0, so that the plant still draws it and the other noise keeps its realisation (the draws of
#: one Generator, interleaved)
CAUSES = {
    "stick": ("the breakaway above the Coulomb friction (stiction_N = coulomb_N): the stick at a "
              "reversal, which the law's friction model theta3 S_f(xd_d) has not",
              lambda d: {"stiction_N": float(d.get("coulomb_N", 0.0))} if d.get("stiction_N") else {}),
    "encoder": ("the encoder's noise and interpolation error inside the loop",
                lambda d: ({"encoder_noise_m": 1e-15} if d.get("encoder_noise_m") else {})
                | ({"encoder_interpolation_m": 0.0} if d.get("encoder_interpolation_m") else {})),
    "force": ("the force noise", lambda d: {"force_noise_N": 1e-15} if d.get("force_noise_N") else {}),
}


def causes(config: str, feed: float, out: Path) -> dict:
    """What the simulated ballbar's G(b) of one draw is made of: C2's and GTCF's circle (R 50 mm at
    ``feed`` [m/s]) on ``config``'s plant as configured and with each of :data:`CAUSES` removed
    alone and all together ("all": the loop's own deterministic error, what no contour gain of the
    law's removes), copies of the config in ``out`` (the gains and the seed kept); each run's G(b)
    [um] and where it is made (:func:`reversal_split`). Returns {law: {"as configured", a cause or
    "all": reversal_split's dict}}."""
    import yaml
    variants = {"as configured": config}
    for name in [*CAUSES, "all"]:
        c = yaml.safe_load(Path(config).read_text())
        changed = False
        for ax in c["axes"].values():
            for cause in (CAUSES if name == "all" else [name]):
                ch = CAUSES[cause][1](ax.get("driver", {}))
                ax.setdefault("driver", {}).update(ch)
                changed |= bool(ch)
        if changed:
            out.mkdir(parents=True, exist_ok=True)
            p = out / f"without_{name}.yaml"
            p.write_text(yaml.safe_dump(c, sort_keys=False))
            variants[name] = str(p)
    return {law: {v: reversal_split(cfg, feed, law) for v, cfg in variants.items()} for law in LAWS}


def print_causes(got: dict, need: float) -> None:
    """:func:`causes`'s runs of one draw as a Markdown table (G(b) by the ballbar and its largest /
    smallest radial deviation at X's reversals, at Y's and elsewhere, per law and variant), then
    the bound: GTCF's G(b) against the 0.7 x C2's a 30 % needs (``need``), as configured and with
    each cause removed."""
    variants = list(got["c2"])
    print("    G(b) by the ballbar, each cause removed alone on this draw (um; in brackets the radial deviation, "
          f"largest / smallest, within {math.degrees(REVERSAL_BAND):g} deg of X's reversals, of Y's, elsewhere):\n")
    print("    | law | " + " | ".join(v if v == "as configured" else f"without {v}" for v in variants) + " |")
    print("    |---|" + "---|" * len(variants))
    for law in LAWS:
        cells = [f"{s['all']:.2f} (X {s['X'][0]:+.2f} / {s['X'][1]:+.2f}, Y {s['Y'][0]:+.2f} / {s['Y'][1]:+.2f}, "
                 f"off {s['off'][0]:+.2f} / {s['off'][1]:+.2f})" for s in (got[law][v] for v in variants)]
        print(f"    | {law} | " + " | ".join(cells) + " |")
    g, c = got["gtcf"], got["c2"]
    parts = []
    for v in variants[1:]:
        parts.append(f"without {v}: GTCF {g[v]['all']:.2f} / C2 {c[v]['all']:.2f} = x{g[v]['all'] / c[v]['all']:.2f} "
                     f"(its part of G(b): C2 {c['as configured']['all'] - c[v]['all']:+.2f}, GTCF "
                     f"{g['as configured']['all'] - g[v]['all']:+.2f})")
    print(f"\n    the bound: GTCF's G(b) {g['as configured']['all']:.2f} against the {need:.2f} a 30 % needs; "
          + "; ".join(parts))
    for v in variants[1:]:
        print(f"      {v}: " + (CAUSES[v][0] if v in CAUSES else "every cause above removed"))


def setpoint_contour_error(pos: np.ndarray, des: np.ndarray, window: int = 250) -> np.ndarray:
    """The distance [m] of each measured point pos[k] (N, 2) from the setpoints' path des (N, 2),
    a polyline, searched over its segments within ``window`` samples of k: the servo's own
    contour error (the setpoints' departure from the programmed path, the planner's G64 P
    blending, left out)."""
    n = len(pos)
    best = np.full(n, np.inf)
    k = np.arange(n)
    for o in range(-window, window):
        a = np.clip(k + o, 0, n - 1)
        b = np.clip(k + o + 1, 0, n - 1)
        seg = des[b] - des[a]
        ll = np.einsum("ij,ij->i", seg, seg)
        t = np.where(ll > 0, np.einsum("ij,ij->i", pos - des[a], seg) / np.where(ll > 0, ll, 1.0), 0.0)
        t = np.clip(t, 0.0, 1.0)
        d = np.hypot(*(pos - des[a] - t[:, None] * seg).T)
        np.minimum(best, d, out=best)
    return best


def cut_path(config: str, out: Path, laws=LAWS) -> list[dict]:
    import motorctl.app.circle_test as ct
    from motorctl.config import load_config
    from motorctl.motion import GcodeSettings, parse
    from motorctl.motion.path import contour_error
    from motorctl.recorder.runlog import read_log
    spec = importlib.util.spec_from_file_location("bench_contour", REPO / "benchmarks" / "bench_contour.py")
    bc = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bc)
    # the torch words (M3/M5) left out: the gantry's config maps no outputs (motion is the same)
    text = "\n".join(ln for ln in bc.CUT.splitlines() if ln.strip() not in ("M3", "M5")) + "\n"
    lines = text.splitlines()
    hole = next(i for i, ln in enumerate(lines) if ln.startswith("G2 X58 Y50 I-8")) + 1
    orig = ct.circle_program
    ct.circle_program = lambda radius, feed, center: (text, {"cw": hole, "ccw": hole})
    rows = []
    try:
        loaded = load_config(config)
        gs = GcodeSettings(axes=["X", "Y"], words={"M3": "torch", "M5": "torch", "S": "ignore"})
        for c in laws:
            lp = out / f"cut_{c}.log"
            fault = "-"
            try:
                ct.run_circle_test(loaded, 0.008, 5000 / 60e3, c, center=(0.05, 0.05), log_path=str(lp))
            except ValueError as exc:            # a fault: the log keeps the rows up to it
                fault = str(exc)
            log = read_log(str(lp))
            # the program as the daemon planned it: from where the axes stood
            prog = parse(text, "cut", gs, start=(float(log.col("X.y")[0]), float(log.col("Y.y")[0]), 0.0))
            speed = np.hypot(log.col("X.xd_dot"), log.col("Y.xd_dot"))
            # the cut: the setpoint moving at no more than the programmed feed (the G0 rapids,
            # up to the axes' v_max, are the other moving rows)
            cutting = (speed > 1e-3) & (speed <= 5000 / 60e3 + 1e-6)
            pos = np.column_stack([log.col("X.y"), log.col("Y.y")])
            des = np.column_stack([log.col("X.x_d"), log.col("Y.x_d")])
            e_sp = setpoint_contour_error(pos, des)
            extra = {"share": saturation(log)[2] / len(pos), "rest": rest_noise(log), "rest_axes": rest_by_axis(log),
                     "fault": fault}
            for what, m in (("cutting", cutting), ("rapids", speed > 5000 / 60e3 + 1e-6)):
                e_prog = contour_error(prog, pos[m])
                sat, umax, sat_all = saturation(log, m)
                rows.append({"path": f"cut path F5000, {what}: from the setpoints' path", "law": c,
                             "G": float("nan"), "Gb": float("nan"), "emax": float(e_sp[m].max()) * 1e6, "sat": sat,
                             "umax": umax, "sat_all": sat_all} | extra)
                rows.append({"path": f"cut path F5000, {what}: from the programmed path", "law": c,
                             "G": float("nan"), "Gb": float("nan"), "emax": float(e_prog.max()) * 1e6, "sat": sat,
                             "umax": umax, "sat_all": sat_all} | extra)
    finally:
        ct.circle_program = orig
    return rows


def autotune(config: str, out: Path, timeout_s: float) -> tuple[str, dict]:
    """``motorctl autotune`` of X and Y (C2, then the GTCF pair) on a copy of ``config`` in
    ``out``; (the autotuned config's path, its JSON summary)."""
    src = out / Path(config).name
    shutil.copyfile(REPO / config if not Path(config).is_absolute() else config, src)
    cmd = [sys.executable, "-m", "motorctl", "autotune", str(src), "--axis", "X", "--axis", "Y", "--law", "c2",
           "--virtual-clock", "--json", "--out", str(out / "autotune")]
    print("$ " + " ".join(cmd[2:]).replace("-m motorctl", "motorctl"), file=sys.stderr)
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s, cwd=REPO)
    if res.returncode != 0:
        raise SystemExit(f"autotune failed ({res.returncode}): {res.stderr[-2000:]}")
    got = json.loads(res.stdout)
    return got["config"], got


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default="configs/gantry.yaml")
    ap.add_argument("--out", default=None, help="where the run logs go (default: a temporary folder)")
    ap.add_argument("--skip-cut", action="store_true", help="the circles only")
    ap.add_argument("--no-autotune", action="store_true", help="the config's own gains (no autotune first)")
    ap.add_argument("--timeout", type=float, default=1800.0, help="circle-test's and autotune's time bound [s]")
    ap.add_argument("--sweep", default="", metavar="GX[/GY][,...]",
                    help="then GTCF again with these gain_n (X's/Y's; one number: both) on the same circles and "
                         "cut path, whether or not the rule admits them: what more contour gain buys, and what it costs")
    ap.add_argument("--seeds", default="", metavar="S[,S...]",
                    help="then the circles again with the simulated driver's seed set to each of these (the "
                         "noise realisation; the same gains): per seed and feed the ratios GTCF / C2, and their median")
    ap.add_argument("--plant", default="", metavar="AXIS.KEY=V[,...]",
                    help="the simulated plant changed so (the axes' driver keys, e.g. X.stiction_N=20) for the circles, "
                         "the cut and the seeds, after autotune (the gains tuned on the config's plant)")
    ap.add_argument("--no-causes", action="store_true",
                    help="with --seeds, on a draw that misses the 30 %%: only where G(b) is made, not its "
                         "decomposition by cause (10 circle runs a missed draw: each cause removed alone and all "
                         "together, both laws; 40 min in all for five missed draws beside other jobs)")
    ap.add_argument("--grid", action="store_true",
                    help="then GTCF's circles over a grid of its settings (X gain_n x lambda_n, Y gain_n x low-pass) "
                         "on the config's seed and --seeds, judged by G alone: the least G any setting reaches per draw")
    args = ap.parse_args(argv)
    try:
        plant = [(k.split(".", 1)[0], k.split(".", 1)[1], float(v))
                 for k, v in (p.split("=", 1) for p in args.plant.split(",") if p.strip())]
    except (ValueError, IndexError):
        ap.error(f"--plant: {args.plant!r} is not a comma-separated list of AXIS.KEY=NUMBER")
    from motorctl_drivers.sim import SimAxisOptions
    for ax, key, _ in plant:
        if key not in SimAxisOptions.model_fields:
            ap.error(f"--plant: {ax}.{key}: the simulated driver has no key {key!r}")
    try:
        seeds = [int(v) for v in args.seeds.split(",") if v.strip()]
    except ValueError:
        ap.error(f"--seeds: {args.seeds!r} is not a comma-separated list of integers")
    try:
        parts = [v.split("/") for v in args.sweep.split(",") if v.strip()]
        sweep = [tuple(float(x) for x in (p * 2)[:2]) for p in parts]          # one number: both axes
        if any(len(p) > 2 for p in parts) or any(min(g) <= 0 for g in sweep):
            raise ValueError
    except ValueError:
        ap.error(f"--sweep: {args.sweep!r} is not a comma-separated list of GX/GY or G (positive numbers)")
    out = Path(args.out or tempfile.mkdtemp(prefix="bench_gtcf_"))
    out.mkdir(parents=True, exist_ok=True)
    config = args.config
    got = None
    if not args.no_autotune:
        config, got = autotune(args.config, out, args.timeout)
        print(f"autotuned ({config}):")
        for a, s in got["axes"].items():
            g, m = s["gains"].get("c2", {}), s["margins"].get("c2", {})
            print(f"  {a} c2: k_s {g.get('k_s', math.nan):.4g} V s/m, k1 {g.get('k1', math.nan):.4g} 1/s, gamma_d "
                  f"{g.get('gamma_d', math.nan):.4g}: GM {m.get('gm_db') or math.inf:.1f} dB, PM "
                  f"{m.get('pm_deg', math.nan):.1f} deg, |S| {m.get('ms_db', math.nan):.1f} dB")
        for tp in got["gtcf"]:
            g = tp["gains"]
            print(f"  gtcf {'-'.join(tp['pair'])}: gain_t {g['gain_t']:g}; "
                  + "; ".join(f"{a} gain_n {g['gain_n'][a]:g}, lambda_n {g['lambda_n'][a]:g}, "
                              f"{_lp(g['lowpass_hz'][a])} (margins hold up to "
                              f"{tp['admissible'][a][0][0]:g}): GM {m['gm_db']:.1f} dB, PM {m['pm_deg']:.1f} deg, "
                              f"|S| {m['ms_db']:.1f} dB" for a, m in tp["margins"].items()))
            for r in tp["runs"]:
                print(f"    {r['run']} gain_n " + ", ".join(f"{a} {v:g} (lambda_n {r['lambda_n'][a]:g}, "
                                                         f"{_lp(r['lowpass_hz'][a])})"
                                                         for a, v in r['gain_n'].items())
                      + f" at {r['scale']:.0%}: {r['verdict']}")
        print()
    if plant:
        config = changed_plant(config, out, plant)
    rows = circles(config, out, args.timeout)
    if not args.skip_cut:
        rows += cut_path(config, out)
    print(f"GTCF against per-axis C2 ({config}, simulated, virtual clock; logs in {out})\n")
    print("| path | law | G um | G(b) um | largest contour error um (from the log) | ballbar: G / G(b) / largest "
          "contour error um | saturated samples: measured rows / whole run (share of the run) | max abs u V, "
          "measured rows | u RMS at rest mV (worse axis) | fault |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    base = {}
    for r in rows:
        if r["law"] == "c2":
            base[r["path"]] = r

        def rel(key):
            b = base.get(r["path"], {}).get(key)
            if r["law"] == "c2" or b is None or not np.isfinite(r[key]) or b == 0:
                return ""
            return f" (x{r[key] / b:.2f})"
        g = "–" if not np.isfinite(r["G"]) else f"{r['G']:.2f}{rel('G')}"
        gb = "–" if not np.isfinite(r["Gb"]) else f"{r['Gb']:.2f}{rel('Gb')}"
        rest = "–" if not np.isfinite(r["rest"]) else f"{r['rest'] * 1e3:.0f}"
        bb, bb0 = r.get("bb"), base.get(r["path"], {}).get("bb")
        if bb is None:
            bbs = "–"
        else:
            bbs = " / ".join(f"{bb[k]:.2f}" + ("" if r["law"] == "c2" or not bb0 else f" (x{bb[k] / bb0[k]:.2f})")
                             for k in ("G", "Gb", "emax"))
        print(f"| {r['path']} | {r['law']} | {g} | {gb} | {r['emax']:.2f}{rel('emax')} | {bbs} | {r['sat']} / "
              f"{r['sat_all']} ({r['share'] * 100:.3f} %) | {r['umax']:.2f} | {rest} | {r['fault']} |")
    floors = {r["path"]: encoder_floor(config, r["log"]) for r in rows if r["law"] == "c2" and "log" in r}
    print("\nThe encoder's floor: G of each test circle's setpoints as the simulated encoders read them (no "
          "motion error; 10 draws): " + ", ".join(f"{p} median {np.median(v):.2f} um ({min(v):.2f}-{max(v):.2f})"
                                                  for p, v in floors.items()))
    if sweep:
        print_sweep(config, out, rows, sweep, got, args)
    if seeds:
        print_seeds(config, out, seeds, args.timeout, rows, with_causes=not args.no_causes)
    if args.grid:
        print_grid(config, out, seeds, args.timeout)
    return 0


def changed_plant(config: str, out: Path, plant: list) -> str:
    """A copy of ``config`` in ``out`` with each (axis, driver key, value) of ``plant`` set (the
    simulated plant changed, the gains kept); its path. Raises SystemExit: an axis the config
    does not have."""
    import yaml
    raw = yaml.safe_load(Path(config).read_text())
    for ax, key, v in plant:
        if ax not in raw["axes"]:
            raise SystemExit(f"--plant: {ax}.{key}: the config has no axis {ax!r}")
        raw["axes"][ax]["driver"][key] = v
    cfg = out / ("plant_" + Path(config).name)
    cfg.write_text(yaml.safe_dump(raw, sort_keys=False))
    print("the plant changed: " + ", ".join(f"{a}.{k} = {v:g}" for a, k, v in plant))
    return str(cfg)


def print_seeds(config: str, out: Path, seeds: list, timeout_s: float, rows: list | None = None,
                with_causes: bool = True) -> None:
    """The circles (:func:`circles`) on copies of ``config`` whose ``driver.seed`` is each of
    ``seeds`` (the simulated encoder's and force noise's realisation; gains as ``config``'s), and
    ``rows``, :func:`circles`'s of ``config`` itself, as the draw of its own seed (first), a
    Markdown table of G, G(b) and the largest contour error of C2 and GTCF per seed and feed with
    the ratio GTCF / C2, and the median ratio per feed. A reversal's stick-slip (the plant's
    stiction above its Coulomb friction) comes and goes with the noise: one seed's ratio is one
    draw."""
    import statistics

    import yaml
    raw = yaml.safe_load(Path(config).read_text())
    own = int(raw["driver"].get("seed", 0))
    draws = list(dict.fromkeys(([own] if rows is not None else []) + list(seeds)))
    ratios: dict = {}
    verdict: list = []
    print("\nThe circles on other noise realisations (driver.seed), the same gains; each by the encoders "
          "and by the simulated ballbar (the carriages' true positions):\n")
    print("| seed | circle | instrument | C2: G / G(b) / largest contour error um | GTCF: G / G(b) / largest contour "
          "error um | ratio G / G(b) / largest |")
    print("|---|---|---|---|---|---|")
    for seed in draws:
        if seed == own and rows is not None:
            got = [r for r in rows if r["path"].startswith("circle")]
        else:
            d = out / f"seed{seed}"
            d.mkdir(parents=True, exist_ok=True)
            cfg = d / Path(config).name
            raw["driver"]["seed"] = seed
            cfg.write_text(yaml.safe_dump(raw, sort_keys=False))
            got = circles(str(cfg), d, timeout_s)
        by = {(r["path"], r["law"]): r for r in got}
        for path in dict.fromkeys(r["path"] for r in got):
            c, g = by.get((path, "c2")), by.get((path, "gtcf"))
            if c is None or g is None:
                continue
            for inst, cc, gg in (("encoder", c, g), ("ballbar", c.get("bb"), g.get("bb"))):
                if cc is None or gg is None:
                    print(f"| {seed} | {path} | {inst} | – | – | – |")
                    continue
                q = [gg[k] / cc[k] for k in ("G", "Gb", "emax")]
                ratios.setdefault((path, inst), []).append(q)
                if inst == "ballbar":
                    verdict.append((seed, path, cc, gg, q))
                print(f"| {seed} | {path} | {inst} | {cc['G']:.2f} / {cc['Gb']:.2f} / {cc['emax']:.2f} | {gg['G']:.2f} "
                      f"/ {gg['Gb']:.2f} / {gg['emax']:.2f} | x{q[0]:.2f} / x{q[1]:.2f} / x{q[2]:.2f} |")
    for (path, inst), qs in ratios.items():
        med = [statistics.median(q[i] for q in qs) for i in range(3)]
        worst = [max(q[i] for q in qs) for i in range(3)]
        print(f"\n{path}, by the {inst}: median ratio over {len(qs)} seeds G x{med[0]:.2f}, G(b) x{med[1]:.2f}, "
              f"largest x{med[2]:.2f}; the worst seed's x{worst[0]:.2f} / x{worst[1]:.2f} / x{worst[2]:.2f}", end="")
    print()
    if verdict:
        held = [v for v in verdict if v[4][0] <= 0.70 and v[4][1] <= 0.70]
        print(f"\nBy the ballbar, GTCF's G and G(b) >= 30 % below per-axis C2's on {len(held)} of {len(verdict)} "
              "draws (seed x feed)" + ("." if len(held) == len(verdict) else "; not on:"))
        for seed, path, cc, gg, q in verdict:
            if not (q[0] <= 0.70 and q[1] <= 0.70):
                print(f"  seed {seed}, {path}: G {gg['G']:.2f} against {0.7 * cc['G']:.2f} (C2 {cc['G']:.2f}), "
                      f"G(b) {gg['Gb']:.2f} against {0.7 * cc['Gb']:.2f} (C2 {cc['Gb']:.2f})")
                cfg = out / f"seed{seed}" / Path(config).name if seed != own else Path(config)
                feed = float(path.split()[-2]) * 1e-3
                if with_causes:
                    print_causes(causes(str(cfg), feed, out / f"causes_seed{seed}_{path.split()[-2]}"),
                                 0.7 * cc["Gb"])
                    continue
                sp = {law: reversal_split(str(cfg), feed, law) for law in LAWS}
                print(f"    where G(b) is made (the ballbar's radial deviation about the least-squares circle, "
                      f"largest / smallest um, within {math.degrees(REVERSAL_BAND):g} deg of X's reversals, of Y's, "
                      "elsewhere): " + "; ".join(f"{law} " + ", ".join(f"{k} {v[k][0]:+.2f} / {v[k][1]:+.2f}"
                                                                        for k in ("X", "Y", "off"))
                                                   for law, v in sp.items()))


GRID = {"X": [{"gain_n": g, "lambda_n": lam} for g in (1.5, 2.0, 2.5, 3.0) for lam in (1.0, 1.5, 2.0)],
        "Y": [{"gain_n": g, "lowpass_hz": fc} for g in (1.0, 1.5, 2.0) for fc in (500.0, None)
              if not (g == 1.0 and fc is None)]}


def print_grid(config: str, out: Path, seeds: list, timeout_s: float) -> None:
    """GTCF's circles (:func:`circles`, GTCF alone) with each combination of :data:`GRID`'s X and Y
    settings in the gtcf blocks (the rest as ``config``'s), on ``config``'s driver seed and each
    of ``seeds``, against per-axis C2 on the same draw; whether autotune's rule admits a setting
    is not asked (saturation, rest noise, margins): what the law's settings can do for G at
    best. Prints per setting the ratio GTCF / C2 of G per draw and feed, sorted by the worst,
    and per draw and feed the least GTCF G of any setting against the 0.7 x C2's a 30 % needs.
    Two circle-tests at a time (subprocesses)."""
    import copy
    from concurrent.futures import ThreadPoolExecutor

    import yaml
    raw = yaml.safe_load(Path(config).read_text())
    draws = list(dict.fromkeys([int(raw["driver"].get("seed", 0))] + list(seeds)))
    combos = [(x, y) for x in GRID["X"] for y in GRID["Y"]]

    def one(job):
        seed, k = job
        d = out / "grid" / f"seed{seed}" / ("c2" if k is None else f"v{k}")
        d.mkdir(parents=True, exist_ok=True)
        c = copy.deepcopy(raw)
        c["driver"]["seed"] = seed
        if k is not None:
            for ax, kv in zip(("X", "Y"), combos[k]):
                c["axes"][ax]["controller"]["gtcf"].update(kv)
        cfg = d / "config.yaml"
        cfg.write_text(yaml.safe_dump(c, sort_keys=False))
        return job, {r["path"]: r["G"] for r in circles(str(cfg), d, timeout_s, ("c2",) if k is None else ("gtcf",))}

    jobs = [(s, None) for s in draws] + [(s, k) for k in range(len(combos)) for s in draws]
    with ThreadPoolExecutor(2) as ex:
        got = dict(ex.map(one, jobs))
    paths = list(got[(draws[0], None)])
    cols = [(s, p) for s in draws for p in paths]
    ratio = {k: [got[(s, k)][p] / got[(s, None)][p] for s, p in cols] for k in range(len(combos))}

    def name(k):
        x, y = combos[k]
        return (f"X {x['gain_n']:g} (lambda_n {x['lambda_n']:g}) / Y {y['gain_n']:g} "
                f"({_lp(y['lowpass_hz'])})")
    print(f"\nGTCF's settings over a grid ({len(combos)}), G / C2's G per draw (seed) and circle, "
          "worst first:\n")
    print("| X gain_n (lambda_n) / Y gain_n (low-pass) | worst | "
          + " | ".join(f"seed {s}, {p.split()[-2]} mm/s" for s, p in cols) + " |")
    print("|---|---|" + "---|" * len(cols))
    for k in sorted(ratio, key=lambda k: max(ratio[k])):
        print(f"| {name(k)} | x{max(ratio[k]):.2f} | " + " | ".join(f"x{q:.2f}" for q in ratio[k]) + " |")
    print("\nThe least G of any setting per draw and circle, against 0.7 x C2's (um):")
    for s, p in cols:
        least = min(range(len(combos)), key=lambda k: got[(s, k)][p])
        print(f"  seed {s}, {p}: {got[(s, least)][p]:.2f} ({name(least)}) against {0.7 * got[(s, None)][p]:.2f}"
              f" (C2 {got[(s, None)][p]:.2f})")


def _lp(fc) -> str:
    return "unfiltered" if fc is None else f"low-pass {fc:g} Hz"


def print_sweep(config: str, out: Path, rows: list, sweep: list, got: dict | None, args) -> None:
    """GTCF with each (g_n,X, g_n,Y) of ``sweep`` in the gtcf blocks (gain_t and the low-pass as
    configured) on the circles and the cut path, as a Markdown table against per-axis C2's rows
    of ``rows``: the ratios of G, G(b), the largest contour error (the circles: the worse of the
    two feeds; the cut: from the setpoints' path while cutting), each axis's u RMS at rest on the
    circles' and the cut's runs (the contour direction's noise: on the cut's straight edges one
    axis stands still while the other moves), the whole runs' saturated samples, and whether
    autotune found each axis's margins holding for it with its configured low-pass ("?" without
    autotune)."""
    import yaml
    raw = yaml.safe_load(Path(config).read_text())
    blk = {a: raw["axes"][a]["controller"]["gtcf"] for a in ("X", "Y")}
    adm = {a: {g for g, fc in v if fc == blk[a].get("lowpass_hz")} for tp in (got or {}).get("gtcf", [])
           for a, v in tp["admissible"].items()}

    chosen = tuple(float(blk[a].get("gain_n", 2.0)) for a in ("X", "Y"))
    table = {chosen: [r for r in rows if r["law"] == "gtcf"]}
    for gn in sweep:
        if gn in table:
            continue
        for a, g in zip(("X", "Y"), gn):
            blk[a]["gain_n"] = g
        d = out / f"sweep_gain_n_{gn[0]:g}_{gn[1]:g}"
        d.mkdir(exist_ok=True)
        cfg = d / "config.yaml"
        cfg.write_text(yaml.safe_dump(raw, sort_keys=False))
        table[gn] = circles(str(cfg), d, args.timeout, ("gtcf",)) + ([] if args.skip_cut else cut_path(str(cfg), d, ("gtcf",)))
    base = {r["path"]: r for r in rows if r["law"] == "c2"}
    cut = "cut path F5000, cutting: from the setpoints' path"
    circ = [p for p in base if p.startswith("circle")]

    def worst(rs, key):
        return max((rs[p][key] / base[p][key] for p in circ if p in rs), default=math.nan)

    def rests(r):
        return " / ".join(f"{r['rest_axes'][a] * 1e3:.0f}" for a in ("X", "Y"))
    print(f"\nGTCF's contour gains swept (gain_t {blk['X'].get('gain_t', 1.0):g}; X {_lp(blk['X'].get('lowpass_hz'))}, "
          f"Y {_lp(blk['Y'].get('lowpass_hz'))}, as configured; x: GTCF / per-axis C2, "
          f"the worse of the circles at "
          f"{', '.join(p.split()[-2] for p in circ)} mm/s)\n")
    print("| gain_n X / Y | margins hold (autotune's rule) X / Y | G | G(b) | largest contour error, circles | cut, "
          "from the setpoints' path | u RMS at rest X / Y mV, circle 50 mm/s | the same, cut | saturated, whole runs "
          "| fault |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    c2c = base.get(circ[0]) if circ else None
    print(f"| c2 | – | 1 | 1 | 1 | 1 | {rests(c2c) if c2c else '–'} | {rests(base[cut]) if cut in base else '–'} | "
          f"{sum(r['sat_all'] for p, r in base.items() if p in circ or p == cut)} | – |")
    for gn in sorted(table):
        rs = {r["path"]: r for r in table[gn]}
        held = "?" if got is None else " / ".join("yes" if g in adm.get(a, ()) or g == 1.0 else "no"
                                                   for a, g in zip(("X", "Y"), gn))
        ce = f"x{rs[cut]['emax'] / base[cut]['emax']:.2f}" if cut in rs and cut in base else "–"
        faults = sorted({r["fault"] for r in table[gn] if r["fault"] != "-"}) or ["-"]
        print(f"| {gn[0]:g} / {gn[1]:g}{' (chosen)' if gn == chosen else ''} | {held} | x{worst(rs, 'G'):.2f} | "
              f"x{worst(rs, 'Gb'):.2f} | x{worst(rs, 'emax'):.2f} | {ce} | "
              f"{rests(rs[circ[0]]) if circ and circ[0] in rs else '–'} | {rests(rs[cut]) if cut in rs else '–'} | "
              f"{sum(r['sat_all'] for p, r in rs.items() if p in circ or p == cut)} | {'; '.join(faults)} |")


if __name__ == "__main__":
    sys.exit(main())
