"""The fleet's report: ``motorctl fleet report``. Each machine's and axis's parameters over
time, their trend, the changes that are wear and not noise, and the machines outside the
fleet's spread.

The series (:func:`series_of`): per machine and axis, the nominal parameters of the dataset
(:data:`motorctl.fleet.jobs.PARAMETERS`, each with its 95 % interval) and the amplitude of each
named effect (an effect parameter whose name has ``amplitude`` in it, the first harmonic:
``cogging.amplitudes_N[0]``, ...); a window where the effect is not named counts as 0 (below
what the identification can tell), with no interval of its own.

**Noise** of a point i: v_i = σ_i² + s², with σ_i the fit's own standard deviation (its interval
/ 2·1.96) and s the larger of (a) the series' own scatter, 1.4826·MAD of its first differences
/ √2 (robust to one step and to a steady trend), (b) the fleet's scatter: the median of (a)
over the fleet's machines and axes for that parameter, (c) :data:`REL_FLOOR` of the series'
typical magnitude (the median |value| of its non-zero points).

**Change points** (:func:`change_point`): a two-segment fit over every split τ at the points'
times leaving :data:`MIN_SEG` points on each side, two shapes: a **step** y = a + b·[t ≥ τ] (a
cogging force that appears, a changed payload) and a **hinge** y = a + b·max(0, t − τ) (wear
that grows from an onset: friction, an encoder's error). Each is fitted by Huber's M-estimator
(P. J. Huber, "Robust estimation of a location parameter", Ann. Math. Statist. 35, 1964;
iteratively reweighted least squares, weights h_i/v_i with h_i = min(1, c/|r_i/√v_i|),
c = :data:`HUBER_C`), so that a bad day's points weigh as a few σ and do not drag a level as
they drag a mean. The shape and τ with the least Huber loss Σρ(r_i/√v_i) win; the change Δ is b
(step) or b·(t_last − τ) (hinge, the growth so far), its standard error from (XᵀWX)⁻¹ with the
final weights (not rescaled), z = |Δ|/se. The scan over τ is a multiple test, hence the high
:data:`Z_ALARM`.

**Persistence** (:func:`days_held`): a point holds the new level when its interval (± Z95·√v_i:
the fit's own widened by the series' noise) lies wholly beyond the level before the change, in
the change's direction; a day holds it when the median of its points' margins does. One bad
day holds it on one day only.

**Alarm** (wear, not noise), all of: z ≥ :data:`Z_ALARM`; |Δ| ≥ :data:`K_FLEET` × the fleet's
scatter of that parameter; |Δ| ≥ :data:`MIN_REL_CHANGE` of the series' typical magnitude; the new
level held on at least :data:`MIN_DAYS_HELD` days after τ, one of them among the latest
:data:`MIN_DAYS_HELD` days (wear that stays: one bad day neither raises an alarm nor, as one
dip, clears it; a machine back for that many days does); for an effect's amplitude, the effect named in at least
:data:`MIN_SEG` windows and :data:`MIN_NAMED_SHARE` of those after τ (a one-off phantom effect
is not wear).

**Trend**: the Theil–Sen slope (the median of the pairwise slopes; H. Theil 1950, P. K. Sen
1968) with its 95 % confidence interval (``scipy.stats.theilslopes``), per day, over the whole
series and, for an alarm of the hinge shape, from τ on: reported, never an alarm on its own.

**Outside the fleet's spread** (:func:`fleet_outliers`): a machine whose median value of a
nominal parameter lies more than :data:`Z_FLEET` robust standard deviations (1.4826·MAD over
the machines) from the fleet's median, with at least :data:`MIN_FLEET` machines: a plant that
differs, reported beside the alarms, not one of them.
"""

from __future__ import annotations

import datetime as _dt
import json
import math
import re
from pathlib import Path

import numpy as np

from motorctl.fleet.jobs import PARAMETERS, Z95
from motorctl.inputs import InputError

#: fewest points on each side of a change
MIN_SEG = 2
#: the change's z (|Δ| over its standard error) from which it is an alarm
Z_ALARM = 6.0
#: |Δ| at least this many times the fleet's scatter of the parameter
K_FLEET = 4.0
#: |Δ| at least this share of the series' typical magnitude (a nominal parameter moving less
#: than 2 % is no wear worth a visit)
MIN_REL_CHANGE = 0.02
#: the series' noise floor: this share of its typical magnitude
REL_FLOOR = 0.005
#: an effect must be named in this share of the windows after τ
MIN_NAMED_SHARE = 2.0 / 3.0
#: the new level must be held on at least this many days after the change, one of them among
#: this many latest days
MIN_DAYS_HELD = 2
#: Huber's constant [standard deviations]: 95 % efficiency at Gaussian noise (Huber 1964)
HUBER_C = 1.345
#: iterations of the reweighted fit at most, and the change in a weight below which it stops
HUBER_ITER = 50
HUBER_TOL = 1e-6
#: robust z beyond which a machine is outside the fleet's spread, and the fewest machines for it
Z_FLEET = 3.5
MIN_FLEET = 5
#: confidence of the Theil–Sen interval
TREND_CONFIDENCE = 0.95
DAY_S = 86400.0

_AMPLITUDE = re.compile(r"amplitude[^\[]*(\[0\])?$")


def monitored_effect(parameter: str) -> bool:
    """An effect parameter followed over time: an amplitude, its first harmonic when a list."""
    return bool(_AMPLITUDE.search(parameter)) and ("[" not in parameter or parameter.endswith("[0]"))


# ---------------------------------------------------------------------------- the series
def load_rows(out_dir) -> list[dict]:
    """The dataset's rows (dicts, :func:`motorctl.fleet.jobs.schema`). Raises InputError: no
    such folder, or no dataset in it."""
    from motorctl.fleet.jobs import read_dataset
    d = Path(out_dir)
    if not d.is_dir():
        raise InputError(f"{out_dir}: no such folder (the --out of `motorctl fleet identify`)")
    t = read_dataset(d)
    if t is None or t.num_rows == 0:
        raise InputError(f"{out_dir}: no fleet dataset here (machine=*/month=*/part-*.parquet); run `motorctl fleet identify` first")
    return t.to_pylist()


def series_of(rows: list[dict]) -> dict:
    """{(machine, axis): {"t": days (n,), "day": calendar days (n,) int, "time": datetimes,
    "logs": paths, "params": {name: {"y": (n,), "sigma": (n,) (NaN: none), "named": (n,) bool
    or None}}}}, points in time order; t counts days from the fleet's first window, day the
    UTC calendar days from its date."""
    if not rows:
        return {}
    t0 = min(r["time"] for r in rows)
    d0 = t0.astimezone(_dt.timezone.utc).date()
    effects = sorted({f"{e['name']}.{e['parameter']}" for r in rows for e in (r["effects"] or [])
                      if monitored_effect(e["parameter"])})
    groups: dict = {}
    for r in rows:
        groups.setdefault((r["machine"], r["axis"]), []).append(r)
    out = {}
    for key, rs in sorted(groups.items()):
        rs.sort(key=lambda r: (r["time"], r["log_path"]))
        s = {"t": np.array([(r["time"] - t0).total_seconds() / DAY_S for r in rs]),
             "day": np.array([(r["time"].astimezone(_dt.timezone.utc).date() - d0).days for r in rs], int),
             "time": [r["time"] for r in rs], "logs": [r["log_path"] for r in rs],
             "unit": rs[0]["force_unit"], "params": {}}
        for name, _ in PARAMETERS:
            y = np.array([r[name] for r in rs], float)
            sig = np.array([(r[f"{name}_hi"] - r[f"{name}_lo"]) / (2 * Z95) for r in rs], float)
            s["params"][name] = {"y": y, "sigma": sig, "named": None}
        for eff in effects:
            fam, par = eff.split(".", 1)
            y, named = np.zeros(len(rs)), np.zeros(len(rs), bool)
            for i, r in enumerate(rs):
                for e in r["effects"] or []:
                    if e["name"] == fam and e["parameter"] == par:
                        y[i], named[i] = e["value"], True
            if named.any():
                s["params"][eff] = {"y": y, "sigma": np.full(len(rs), np.nan), "named": named}
        out[key] = s
    return out


def own_scatter(y: np.ndarray) -> float:
    """1.4826·MAD of the first differences / √2 (y (n,)): a point's scatter, robust to one step
    and to a steady trend; 0 for fewer than 3 points."""
    if len(y) < 3:
        return 0.0
    d = np.diff(y)
    return float(1.4826 * np.median(np.abs(d - np.median(d))) / math.sqrt(2))


def typical(y: np.ndarray) -> float:
    nz = np.abs(y[y != 0])
    return float(np.median(nz)) if nz.size else 0.0


def fleet_scatter(series: dict) -> dict:
    """{parameter: the median over machines and axes of :func:`own_scatter`} (0 where every
    series is flat)."""
    per: dict = {}
    for s in series.values():
        for name, p in s["params"].items():
            per.setdefault(name, []).append(own_scatter(p["y"]))
    return {name: float(np.median(v)) for name, v in per.items()}


# ---------------------------------------------------------------------------- the tests
def _huber_rho(u: np.ndarray) -> np.ndarray:
    """Huber's loss of standardized residuals u: u²/2 within ±c, c·|u| − c²/2 beyond."""
    a = np.abs(u)
    return np.where(a <= HUBER_C, 0.5 * u * u, HUBER_C * a - 0.5 * HUBER_C * HUBER_C)


def change_point(t: np.ndarray, y: np.ndarray, v: np.ndarray, min_seg: int = MIN_SEG) -> dict | None:
    """The best two-segment model of a series, fitted by Huber's M-estimator (module docstring,
    "Change points"). Every split and shape is fitted at once (arrays of splits × points).

    Args:
        t: times [days] (n,), increasing. y: values (n,). v: each point's variance (n,) [y²].
        min_seg: fewest points on each side.
    Returns:
        {"shape": "step"|"hinge", "k": index of the first point after the change, "tau" [days],
        "delta" (the change, y's unit), "se", "z", "before" (the fitted value before),
        "after" (the fitted value at the last point), "loss" (Huber's), "downweighted"
        (points with a Huber weight below 1/2)}, or None (too few points).
    """
    t, y, v = (np.asarray(x, float) for x in (t, y, v))
    n = len(t)
    if n < 2 * min_seg:
        return None
    ks = np.arange(min_seg, n - min_seg + 1)
    step = (np.arange(n)[None, :] >= ks[:, None]).astype(float)
    tau_h = t[ks - 1]                          # the hinge starts at the last point before
    hinge = np.maximum(0.0, t[None, :] - tau_h[:, None])
    Z = np.concatenate([step, hinge])          # (2K, n): the second column of each fit's X
    shapes = ["step"] * len(ks) + ["hinge"] * len(ks)
    taus = np.concatenate([t[ks], tau_h])
    valid = np.concatenate([np.ones(len(ks), bool), np.count_nonzero(hinge, axis=1) >= min_seg])
    w0, sw = 1.0 / v, 1.0 / np.sqrt(v)
    h = np.ones_like(Z)
    for _ in range(HUBER_ITER):
        w = w0[None, :] * h
        wz = w * Z
        s0, s1, s11 = w.sum(1), wz.sum(1), (wz * Z).sum(1)
        sy, s1y = w @ y, wz @ y
        det = s0 * s11 - s1 * s1
        ok = valid & (det > 1e-12 * s0 * s11)
        det = np.where(ok, det, 1.0)
        a, b = (s11 * sy - s1 * s1y) / det, (s0 * s1y - s1 * sy) / det
        u = (y[None, :] - a[:, None] - b[:, None] * Z) * sw[None, :]
        h_new = np.minimum(1.0, HUBER_C / np.maximum(np.abs(u), 1e-300))
        done = float(np.max(np.abs(h_new - h))) < HUBER_TOL
        h = h_new
        if done:
            break
    loss = np.where(ok, _huber_rho(u).sum(1), np.inf)
    if not np.isfinite(loss).any():
        return None
    j = int(np.argmin(loss))
    scale = 1.0 if shapes[j] == "step" else float(t[-1] - taus[j])
    delta = float(b[j] * scale)
    se = math.sqrt(max(float(s0[j] / det[j]), 0.0)) * abs(scale)
    return {"shape": shapes[j], "k": int(ks[j % len(ks)]), "tau": float(taus[j]), "delta": delta, "se": se,
            "z": abs(delta) / se if se > 0 else math.inf, "before": float(a[j]), "after": float(a[j]) + delta,
            "loss": float(loss[j]), "downweighted": int(np.count_nonzero(h[j] < 0.5))}


def days_held(day: np.ndarray, y: np.ndarray, v: np.ndarray, cp: dict) -> dict:
    """Whether the change ``cp`` (:func:`change_point`) persists (module docstring,
    "Persistence").

    Args:
        day: each point's calendar day (n,) int. y: values (n,). v: each point's variance (n,).
        cp: the change.
    Returns:
        {"held": days after the change that hold the new level, "days": days after the change,
        "recent": whether one of the latest :data:`MIN_DAYS_HELD` days after the change holds it}.
    """
    after = np.arange(len(y)) >= cp["k"]
    margin = np.sign(cp["delta"]) * (y - cp["before"]) - Z95 * np.sqrt(v)
    days = np.unique(day[after])
    holds = [bool(np.median(margin[after & (day == d)]) > 0) for d in days]
    return {"held": int(sum(holds)), "days": int(len(days)), "recent": any(holds[-MIN_DAYS_HELD:])}


def theil_sen(t: np.ndarray, y: np.ndarray, confidence: float = TREND_CONFIDENCE) -> dict | None:
    """Theil–Sen slope per day with its confidence interval (``scipy.stats.theilslopes``;
    Theil 1950, Sen 1968). t [days] (n,), y (n,). None for fewer than 3 points or no spread
    in time."""
    from scipy.stats import theilslopes
    if len(t) < 3 or np.ptp(t) <= 0:
        return None
    r = theilslopes(y, t, alpha=confidence)
    return {"slope_per_day": float(r.slope), "lo": float(r.low_slope), "hi": float(r.high_slope),
            "intercept": float(r.intercept), "confidence": confidence}


def analyse(rows: list[dict]) -> dict:
    """The whole fleet's findings from the dataset's rows.

    Returns:
        {"series": :func:`series_of`, "fleet_scatter", "findings": [one per machine, axis and
        parameter: {"machine", "axis", "parameter", "n", "noise", "trend", "change", "alarm"
        (bool), "why" (the rule that held it back, or ""), "when" (ISO time of the first point
        after the change), "logs" (those after the change)}], "outliers":
        :func:`fleet_outliers`}.
    """
    series = series_of(rows)
    fleet = fleet_scatter(series)
    findings = []
    for (machine, axis), s in series.items():
        t = s["t"]
        for name, p in s["params"].items():
            y, sig = p["y"], p["sigma"]
            scale = typical(y)
            s_extra = max(own_scatter(y), fleet.get(name, 0.0), REL_FLOOR * scale)
            if s_extra == 0.0:
                s_extra = 1e-12 * max(scale, 1.0)
            v = np.where(np.isfinite(sig), sig, 0.0) ** 2 + s_extra ** 2
            cp = change_point(t, y, v)
            held = days_held(s["day"], y, v, cp) if cp is not None else None
            f = {"machine": machine, "axis": axis, "parameter": name, "unit": s["unit"], "n": int(len(y)),
                 "noise": s_extra, "fit_sigma": float(np.nanmedian(sig)) if np.isfinite(sig).any() else None,
                 "trend": theil_sen(t, y), "change": cp, "alarm": False, "why": "", "when": None, "logs": [],
                 "trend_after": None, "held": held}
            if cp is not None:
                reasons = []
                if cp["z"] < Z_ALARM:
                    reasons.append(f"z {cp['z']:.1f} < {Z_ALARM:g}")
                if abs(cp["delta"]) < K_FLEET * fleet.get(name, 0.0):
                    reasons.append(f"|change| below {K_FLEET:g}x the fleet's scatter")
                if abs(cp["delta"]) < MIN_REL_CHANGE * scale:
                    reasons.append(f"|change| below {100 * MIN_REL_CHANGE:g} % of the value")
                if held["held"] < MIN_DAYS_HELD or not held["recent"]:
                    reasons.append(f"new level held on {held['held']} of {held['days']} days after the change "
                                   f"({MIN_DAYS_HELD} needed, one among the latest {MIN_DAYS_HELD})")
                if p["named"] is not None:
                    after = p["named"][cp["k"]:]
                    if after.sum() < MIN_SEG or after.mean() < MIN_NAMED_SHARE:
                        reasons.append(f"named in {int(after.sum())} of {after.size} windows after the change")
                f["alarm"] = not reasons
                f["why"] = "; ".join(reasons)
                k = cp["k"] if cp["shape"] == "step" else max(cp["k"] - 1, 0)
                f["when"] = (s["time"][cp["k"]] if cp["shape"] == "step" else s["time"][k]).isoformat()
                f["logs"] = list(dict.fromkeys(s["logs"][cp["k"]:]))
                if cp["shape"] == "hinge":
                    f["trend_after"] = theil_sen(t[k:], y[k:])
            findings.append(f)
    return {"series": series, "fleet_scatter": fleet, "findings": findings, "outliers": fleet_outliers(series)}


def fleet_outliers(series: dict) -> list[dict]:
    """Machines (and axes) whose median of a nominal parameter is more than :data:`Z_FLEET`
    robust standard deviations from the fleet's median (at least :data:`MIN_FLEET` series):
    [{"machine", "axis", "parameter", "median", "fleet_median", "z"}]."""
    out = []
    for name, _ in PARAMETERS:
        meds = {k: float(np.median(s["params"][name]["y"])) for k, s in series.items()}
        if len(meds) < MIN_FLEET:
            continue
        vals = np.array(list(meds.values()))
        mid = float(np.median(vals))
        mad = 1.4826 * float(np.median(np.abs(vals - mid)))
        if mad <= 0:
            continue
        for (machine, axis), m in meds.items():
            z = (m - mid) / mad
            if abs(z) > Z_FLEET:
                out.append({"machine": machine, "axis": axis, "parameter": name, "median": m,
                            "fleet_median": mid, "z": z})
    return out


# ---------------------------------------------------------------------------- writing
def _num(x: float) -> str:
    if x == 0 or not math.isfinite(x):
        return f"{x:g}"
    return f"{x:.4g}" if 1e-3 <= abs(x) < 1e5 else f"{x:.3e}"


def summary_markdown(res: dict, out_dir) -> str:
    """The Markdown summary: alarms (what changed, when, by how much, the logs), held-back
    changes, trends, machines outside the fleet's spread, the quiet machines."""
    series, findings = res["series"], res["findings"]
    n_rows = sum(len(s["t"]) for s in series.values())
    machines = sorted({m for m, _ in series})
    lines = [f"# Fleet report: {out_dir}", "",
             f"{len(machines)} machines, {len(series)} machine axes, {n_rows} windows"
             + (f", {min(min(s['time']) for s in series.values()):%Y-%m-%d} to "
                f"{max(max(s['time']) for s in series.values()):%Y-%m-%d}" if series else "") + ".",
             "", f"Rules: a change (Huber's robust two-segment fit) is an alarm when z ≥ {Z_ALARM:g} against "
             f"each fit's own interval and the series' noise, |change| ≥ {K_FLEET:g}× the fleet's scatter and "
             f"≥ {100 * MIN_REL_CHANGE:g} % of the value, and the new level is held beyond the points' intervals "
             f"on ≥ {MIN_DAYS_HELD} days, one among the latest {MIN_DAYS_HELD} (docs/fleet.md).", "", "## Alarms", ""]
    alarms = [f for f in findings if f["alarm"]]
    if not alarms:
        lines.append("None: no parameter of any machine changed beyond its noise and the fleet's spread.")
    else:
        lines += ["| machine | axis | parameter | shape | from | before | now | change | z | logs |",
                  "|---|---|---|---|---|---|---|---|---|---|"]
        for f in alarms:
            c = f["change"]
            rel = (f" ({100 * c['delta'] / abs(c['before']):+.1f} %)"
                   if abs(c["before"]) > 0.05 * abs(c["after"]) else " (from none)")
            logs = f["logs"]
            shown = ", ".join(Path(p).name for p in logs[:3]) + (f" … {Path(logs[-1]).name} ({len(logs)} logs)"
                                                                  if len(logs) > 3 else "")
            before = c["before"] if abs(c["before"]) > 1e-9 * abs(c["after"]) else 0.0    # round-off of a zero
            lines.append(f"| {f['machine']} | {f['axis']} | {f['parameter']} | {c['shape']} | {f['when'][:10]} | "
                         f"{_num(before)} | {_num(c['after'])} | {_num(c['delta'])}{rel} | {c['z']:.1f} | {shown} |")
        lines.append("")
        for f in alarms:
            ta = f["trend_after"]
            if ta:
                lines.append(f"- {f['machine']} {f['axis']} {f['parameter']}: since {f['when'][:10]} "
                             f"{_num(ta['slope_per_day'])}/day (Theil–Sen, 95 % CI {_num(ta['lo'])} .. {_num(ta['hi'])})")
    held = [f for f in findings if not f["alarm"] and f["change"] and f["change"]["z"] >= Z_ALARM]
    lines += ["", "## Changes held back as noise", ""]
    if not held:
        lines.append("None.")
    for f in held:
        lines.append(f"- {f['machine']} {f['axis']} {f['parameter']}: {_num(f['change']['delta'])} "
                     f"(z {f['change']['z']:.1f}) from {f['when'][:10]}: {f['why']}")
    lines += ["", "## Trends (Theil–Sen, 95 % CI excluding zero; not alarms by themselves)", ""]
    trends = [f for f in findings if f["trend"] and (f["trend"]["lo"] > 0 or f["trend"]["hi"] < 0)]
    if not trends:
        lines.append("None.")
    for f in trends:
        tr = f["trend"]
        lines.append(f"- {f['machine']} {f['axis']} {f['parameter']}: {_num(tr['slope_per_day'])}/day "
                     f"(CI {_num(tr['lo'])} .. {_num(tr['hi'])})" + (" — alarm" if f["alarm"] else ""))
    lines += ["", "## Outside the fleet's spread", ""]
    if not res["outliers"]:
        lines.append(f"None (or fewer than {MIN_FLEET} machine axes to judge).")
    for o in res["outliers"]:
        lines.append(f"- {o['machine']} {o['axis']} {o['parameter']}: median {_num(o['median'])}, fleet "
                     f"{_num(o['fleet_median'])} (robust z {o['z']:+.1f})")
    quiet = sorted({(f["machine"], f["axis"]) for f in findings} - {(f["machine"], f["axis"]) for f in alarms})
    lines += ["", "## Quiet", "", ", ".join(f"{m} {a}" for m, a in quiet) or "None.", ""]
    return "\n".join(lines)


def plot_machine(res: dict, machine: str, path) -> None:
    """One PNG: each parameter of the machine's axes over time with its 95 % intervals, the
    Theil–Sen line and, for a change, its two-segment fit (red when an alarm)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    keys = [k for k in res["series"] if k[0] == machine]
    names = []
    for k in keys:
        names += [n for n in res["series"][k]["params"] if n not in names]
    by = {(f["machine"], f["axis"], f["parameter"]): f for f in res["findings"]}
    fig, axs = plt.subplots(len(names), 1, figsize=(7, 1.9 * len(names) + 0.6), sharex=True, squeeze=False)
    for ax, name in zip(axs[:, 0], names):
        for k in keys:
            s = res["series"][k]
            if name not in s["params"]:
                continue
            p, t = s["params"][name], s["t"]
            err = np.where(np.isfinite(p["sigma"]), Z95 * p["sigma"], 0.0)
            ax.errorbar(t, p["y"], yerr=err, fmt="o", ms=3, lw=0.8, label=f"axis {k[1]}")
            f = by.get((machine, k[1], name))
            if f and f["trend"]:
                tr = f["trend"]
                ax.plot(t, tr["intercept"] + tr["slope_per_day"] * t, "--", color="grey", lw=0.8)
            if f and f["change"]:
                c = f["change"]
                if c["shape"] == "step":
                    fit = np.where(t >= c["tau"], c["after"], c["before"])
                else:
                    fit = c["before"] + (c["after"] - c["before"]) * np.maximum(0, t - c["tau"]) / max(t[-1] - c["tau"], 1e-12)
                ax.plot(t, fit, color="red" if f["alarm"] else "tab:green", lw=1.2)
                if f["alarm"]:
                    ax.axvline(c["tau"], color="red", lw=0.8, ls=":")
        ax.set_ylabel(name, fontsize=7)
        ax.tick_params(labelsize=7)
    axs[-1, 0].set_xlabel("days since the fleet's first log")
    axs[0, 0].set_title(f"{machine}: parameters over time (95 % intervals; red: alarm)", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


def write_report(out_dir, report_dir=None, plots: bool = True) -> dict:
    """Analyse the dataset in ``out_dir`` and write ``summary.md``, ``findings.json`` and one
    ``<machine>.png`` per machine to ``report_dir`` (default ``out_dir/_report``: a leading ``_``,
    so that ``pyarrow.dataset`` does not take it for part of the dataset).

    Returns:
        {"summary": path, "findings": path, "plots": [paths], "alarms": [the alarm findings]}.
    Raises:
        InputError: no dataset in ``out_dir``, a report folder that cannot be written.
    """
    from motorctl.inputs import writable_dir
    rows = load_rows(out_dir)
    rdir = writable_dir(report_dir if report_dir is not None else Path(out_dir) / "_report", "fleet report")
    res = analyse(rows)
    (rdir / "summary.md").write_text(summary_markdown(res, out_dir), encoding="utf-8")
    findings = res["findings"]
    (rdir / "findings.json").write_text(json.dumps({"findings": findings, "outliers": res["outliers"],
                                                    "fleet_scatter": res["fleet_scatter"]},
                                                   indent=1, default=str), encoding="utf-8")
    pngs = []
    if plots:
        for machine in sorted({m for m, _ in res["series"]}):
            path = rdir / f"{machine}.png"
            plot_machine(res, machine, path)
            pngs.append(str(path))
    return {"summary": str(rdir / "summary.md"), "findings": str(rdir / "findings.json"), "plots": pngs,
            "alarms": [f for f in res["findings"] if f["alarm"]], "result": res}


__all__ = ["HUBER_C", "HUBER_ITER", "HUBER_TOL", "K_FLEET", "MIN_DAYS_HELD", "MIN_FLEET", "MIN_NAMED_SHARE",
           "MIN_REL_CHANGE", "MIN_SEG", "REL_FLOOR", "TREND_CONFIDENCE", "Z_ALARM", "Z_FLEET", "analyse",
           "change_point", "days_held", "fleet_outliers", "fleet_scatter", "load_rows",
           "monitored_effect", "own_scatter", "plot_machine", "series_of", "summary_markdown", "theil_sen",
           "typical", "write_report"]
