"""``motorctl identify``: residual analysis of measured data (issue 5).

    motorctl identify DATA [--axis A] [--map t=..,y=..,u=..,yd=..] [--gain G] [--config CFG]
                      [--validate DATA2] [--json] [--report DIR] [--n-theta 4|6]
                      [--friction sf|sign] [--no-closed-loop] [--closed-loop-duration S]

Exit codes: 0 done (with or without an effect found), 2 bad input (one line on stderr).
"""

from __future__ import annotations

import json
import math
import sys

import numpy as np

from motorctl.ident import effects as fx
from motorctl.ident.data import load_record
from motorctl.ident.select import Identifier
from motorctl.model import THETA_NAMES

#: Horizon of the simulated-position fit % (motorctl.ident.simfit) [s].
SIM_WINDOW_S = 0.2


def register(parser, subparsers) -> None:
    """Add the ``identify`` subcommand (called by :func:`motorctl.cli.build_parser`)."""
    p = subparsers.add_parser("identify", help="fit the model to measured data, trace the residual to "
                                               "a missing effect, report before/after")
    p.add_argument("data", help="run log, CSV (t,y,u[,yd], SI) or MATLAB file")
    p.add_argument("--axis", default=None, help="axis of a run log (default: the first)")
    p.add_argument("--map", dest="mapping", default=None,
                   help="column/variable names, e.g. t=t,y=qm,u=vir,yd=qg")
    p.add_argument("--gain", default=None, help="force gain A1 in N/V: a number or a MATLAB variable")
    p.add_argument("--config", default=None,
                   help="config of the simulated plant for the closed-loop before/after "
                        "(default: the config in a run log's header)")
    p.add_argument("--validate", default=None, help="second record (same format options) for validation")
    p.add_argument("--json", action="store_true", help="one JSON object on stdout")
    p.add_argument("--report", default=None, metavar="DIR", help="write report.txt and PNG figures here")
    p.add_argument("--n-theta", type=int, choices=(4, 6), default=None,
                   help="force theta1..theta4 or theta1..theta6 (default: chosen from the input range)")
    p.add_argument("--friction", choices=("sf", "sign"), default="sf",
                   help="Coulomb shape: the paper's S_f (default) or sign() as in the EMPS reference model")
    p.add_argument("--zoh-delay", type=float, default=None, metavar="SAMPLES",
                   help="input-to-acceleration delay of the logged input (default 0.5 for run logs: "
                        "zero-order hold; 0 for CSV/MAT)")
    p.add_argument("--no-closed-loop", action="store_true", help="skip the closed-loop before/after runs")
    p.add_argument("--closed-loop-duration", type=float, default=8.0, help="seconds per closed-loop run")
    p.set_defaults(func=cmd_identify)


# ---------------------------------------------------------------------------- summary
def _r(x):
    return float(x) if x is not None and math.isfinite(float(x)) else None


def summarise(idf: Identifier) -> dict:
    """The JSON object of ``identify`` (issue 5, item 5); residuals in N when a gain is known."""
    rec = idf.rec
    g = rec.gain or 1.0
    unit = "N" if rec.gain else "V"
    nt = idf.n_theta
    nom = idf.nominal
    out = {
        "source": rec.source,
        "axis": rec.axis or None,
        "samples": int(rec.n),
        "period_s": rec.period_s,
        "filters": {"position_lowpass_Hz": idf.p.fq, "decimation": idf.p.nd, "zoh_delay_samples": idf.zoh,
                    "block_s": 0.25, "friction_shape": idf.friction},
        "residual_unit": unit,
        "gain_N_per_V": rec.gain,
        "nominal": {
            "theta": [float(v) for v in nom.fit.coef[:nt]],
            "theta_std": [float(v) for v in nom.fit.std[:nt]],
            "theta_names": list(THETA_NAMES[:nt]),
            "n_theta": nt,
            "n_theta_reason": idf.n_theta_reason,
            "condition_number": nom.fit.cond,
            "residual_rms": g * nom.fit.rms,
            "heldout_rms": g * nom.heldout_rms,
        },
    }
    if rec.gain:
        th = nom.fit.coef
        out["nominal"]["physical"] = {"mass_kg": g * th[0], "viscous_N_s_per_m": g * th[1],
                                      "coulomb_N": g * th[2], "offset_N": g * th[3]}
    th, betas = idf.coef_split(idf.final, idf.terms)
    effects = []
    for (ev, before), term, beta in zip(idf.accepted, idf.terms, betas):
        effects.append({
            "name": term.family,
            "parameters": fx.parameters(term.family, term.h, beta, rec.gain, idf.p.fs),
            "heldout_rms_before": g * before,
            "heldout_rms_after": g * ev.heldout_rms,
        })
    out["effects"] = effects
    out["augmented"] = {"theta": [float(v) for v in th], "residual_rms": g * idf.final.fit.rms,
                        "heldout_rms": g * idf.final.heldout_rms}
    from motorctl.ident.simfit import simulation_fit
    out["nominal"]["simulation_fit_percent"] = simulation_fit(idf, [], idf.nominal, SIM_WINDOW_S)
    out["augmented"]["simulation_fit_percent"] = simulation_fit(idf, idf.terms, idf.final, SIM_WINDOW_S)
    out["simulation_window_s"] = SIM_WINDOW_S
    chosen = [ev for ev, _ in idf.accepted]
    out["candidates"] = [
        [{"name": c.term.family, "searched": _r(c.term.h), "heldout_gain_percent": 100 * c.gain,
          "accepted": c.ok, "selected": any(c is e for e in chosen), "reasons": c.reasons} for c in step]
        for step in idf.steps]
    return out


def validation(idf: Identifier, rec2) -> dict:
    """Residual RMS on a second record of the nominal and the augmented model fitted on DATA."""
    other = Identifier(rec2, n_theta=idf.n_theta, friction=idf.friction, zoh_delay=idf.zoh)
    g = idf.rec.gain or 1.0
    r0 = idf.predict_on(other, [], idf.nominal)
    r1 = idf.predict_on(other, idf.terms, idf.final)
    return {"source": rec2.source, "residual_rms_before": g * float(np.sqrt(np.mean(r0 ** 2))),
            "residual_rms_after": g * float(np.sqrt(np.mean(r1 ** 2)))}


# ---------------------------------------------------------------------------- closed loop
def closed_loop(idf: Identifier, cfg: dict, axis: str, duration_s: float) -> dict | None:
    """C2 alone vs C2 with the found effects compensated, both on the plant of ``cfg``.

    Args:
        cfg: a config dict whose simulated plant carries the effect (e.g. the run log's header).
        axis: the axis to run. duration_s: run length [s].
    Returns:
        {"before": {...}, "after": {...}, "compensation": {...}} with e_M_um, e_F_um, L2_um, or
        None when no found effect maps to a compensation term.
    """
    import copy

    from motorctl.app.job import run_job
    from motorctl.config import config_from_dict
    th, betas = idf.coef_split(idf.final, idf.terms)
    comp = {}
    for t, b in zip(idf.terms, betas):
        c = fx.compensation(t.family, t.h, b)
        if c:
            comp.update(c)
    if not comp:
        return None
    base = copy.deepcopy(cfg)
    base["axes"] = {axis: base["axes"][axis]}
    base["loop"]["clock"] = "virtual"
    base["loop"].setdefault("realtime", {})["policy"] = "off"
    ctl = base["axes"][axis]["controller"]
    ctl.pop("compensation", None)
    ctl["type"] = "c2"
    after = copy.deepcopy(base)
    after["axes"][axis]["controller"]["compensation"] = comp
    res = {}
    for name, d in (("before", base), ("after", after)):
        loaded = config_from_dict(d, f"<identify closed loop: {name}>")
        r = run_job(loaded, duration_s=duration_s, clock="virtual").axes[axis]
        res[name] = {k: float(r[k]) for k in ("e_M_um", "e_F_um", "L2_um", "u_peak_V")}
        res[name]["fault"] = r["fault"]
    res["compensation"] = comp
    res["controller"] = "c2"
    res["duration_s"] = duration_s
    return res


# ---------------------------------------------------------------------------- text
def text_report(s: dict) -> str:
    u = s["residual_unit"]
    n = s["nominal"]
    lines = [f"motorctl identify: {s['source']}" + (f" (axis {s['axis']})" if s.get("axis") else ""),
             f"  {s['samples']} samples at {1 / s['period_s']:.0f} Hz; position low-pass "
             f"{s['filters']['position_lowpass_Hz']:g} Hz, decimation {s['filters']['decimation']}, "
             f"friction shape {s['filters']['friction_shape']}",
             f"nominal model: {n['n_theta_reason']}",
             f"  condition number {n['condition_number']:.1f}"]
    for name, v, sd in zip(n["theta_names"], n["theta"], n["theta_std"]):
        lines.append(f"  {name} = {v:.6g} +- {sd:.2g}")
    if "physical" in n:
        lines.append("  physical: " + ", ".join(f"{k} {v:.4g}" for k, v in n["physical"].items()))
    lines.append(f"  residual RMS {n['residual_rms']:.4g} {u}; held-out RMS {n['heldout_rms']:.4g} {u}")
    if not s["effects"]:
        lines.append("effects: no effect found (no candidate passed held-out gain, BIC and plausibility)")
    for e in s["effects"]:
        lines.append(f"effect found: {e['name']}: " + ", ".join(f"{k} {v}" for k, v in e["parameters"].items()))
        lines.append(f"  held-out RMS {e['heldout_rms_before']:.4g} -> {e['heldout_rms_after']:.4g} {u}")
    a = s["augmented"]
    lines.append(f"augmented model: residual RMS {a['residual_rms']:.4g} {u}, held-out RMS {a['heldout_rms']:.4g} {u}")
    if n.get("simulation_fit_percent") is not None:
        lines.append(f"simulated position fit ({s['simulation_window_s']:g} s windows from the measured state): "
                     f"nominal {n['simulation_fit_percent']:.3f} %, augmented {a['simulation_fit_percent']:.3f} %")
    lines.append("candidates per forward-selection step:")
    for i, step in enumerate(s["candidates"]):
        for c in sorted(step, key=lambda c: -c["heldout_gain_percent"]):
            verdict = ("SELECTED" if c.get("selected") else "passes (a better one was selected)") if c["accepted"] \
                else "rejected: " + "; ".join(c["reasons"])
            lines.append(f"  step {i + 1}: {c['name']:28s} held-out gain {c['heldout_gain_percent']:7.2f} % {verdict}")
    if s.get("validation"):
        v = s["validation"]
        lines.append(f"validation on {v['source']}: residual RMS {v['residual_rms_before']:.4g} -> "
                     f"{v['residual_rms_after']:.4g} {u}")
    cl = s.get("closed_loop")
    if cl:
        b, f = cl["before"], cl["after"]
        lines.append(f"closed loop ({cl['duration_s']:g} s, simulated plant with the effect):")
        lines.append(f"  C2 alone:            e_M {b['e_M_um']:.2f} um, e_F {b['e_F_um']:.2f} um, L2 {b['L2_um']:.3f} um")
        lines.append(f"  C2 + compensation:   e_M {f['e_M_um']:.2f} um, e_F {f['e_F_um']:.2f} um, L2 {f['L2_um']:.3f} um")
    elif s.get("closed_loop_note"):
        lines.append(f"closed loop: {s['closed_loop_note']}")
    return "\n".join(lines) + "\n"


# ---------------------------------------------------------------------------- command
def cmd_identify(args) -> int:
    from motorctl.cli import UsageError
    from motorctl.inputs import writable_dir
    if args.report:
        writable_dir(args.report, "report")        # before the (long) fit
    try:
        rec = load_record(args.data, args.mapping, args.gain, args.axis)
        rec2 = load_record(args.validate, args.mapping, args.gain, args.axis) if args.validate else None
    except IsADirectoryError as exc:
        raise UsageError(f"{exc.filename}: is a directory; DATA must be a file") from None
    if args.closed_loop_duration <= 0:
        raise UsageError(f"--closed-loop-duration {args.closed_loop_duration}: must be > 0 s")
    if args.zoh_delay is not None and not 0 <= args.zoh_delay <= 10:
        raise UsageError(f"--zoh-delay {args.zoh_delay}: must be within 0..10 samples")
    idf = Identifier(rec, n_theta=args.n_theta, friction=args.friction, zoh_delay=args.zoh_delay).run()
    s = summarise(idf)
    s["validation"] = validation(idf, rec2) if rec2 is not None else None
    s["closed_loop"] = None
    if not args.no_closed_loop and idf.terms:
        cfg = None
        if args.config:
            from motorctl.config import load_yaml
            cfg = load_yaml(args.config)
        elif rec.header.get("config") and rec.header.get("driver_type") == "sim":
            cfg = rec.header["config"]
        if cfg is None:
            s["closed_loop_note"] = "not run (no simulated plant: pass --config with the plant carrying the effect)"
        else:
            axis = rec.axis or args.axis or next(iter(cfg.get("axes", {})), None)
            if axis not in cfg.get("axes", {}):
                raise UsageError(f"{args.config or rec.source}: no axis {axis!r} in the config; "
                                 f"axes: {', '.join(cfg.get('axes', {}))}")
            s["closed_loop"] = closed_loop(idf, cfg, axis, args.closed_loop_duration)
            if s["closed_loop"] is None:
                s["closed_loop_note"] = "not run (the found effect has no additive compensation term)"
    if args.report:
        from motorctl.ident.report import write_report
        write_report(idf, s, args.report, text_report(s))
    if args.json:
        sys.stdout.write(json.dumps(s, default=_json_default) + "\n")
    else:
        sys.stdout.write(text_report(s))
    return 0


def _json_default(o):
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(type(o).__name__)


__all__ = ["register", "cmd_identify", "summarise", "validation", "closed_loop", "text_report"]
