"""``motorctl identify``: residual analysis of measured data.

    motorctl identify DATA [--axis A] [--map t=..,y=..,u=..,yd=..] [--gain G] [--config CFG]
                      [--validate DATA2] [--json] [--report DIR] [--n-theta 4|6]
                      [--friction sf|sign] [--no-closed-loop] [--closed-loop-duration S]
                      [--write-config OUT.yaml]

``--write-config`` writes the axis config (``--config``, or the config in a run log's header)
with the found effects as ``controller.compensation``, θ̂(0) from the fit and the box widened
where the fit lies outside it, every change commented with its figure
(:func:`motorctl.ident.pipeline.tuned_config`). The pipeline is :mod:`motorctl.ident.pipeline`,
the closed-loop before/after :class:`motorctl.commission.closed_loop.ClosedLoop`: this module parses and prints.

Exit codes: 0 done (with or without an effect found), 2 bad input (one line on stderr).
"""

from __future__ import annotations

import json
import math
import sys


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
    p.add_argument("--write-config", default=None, metavar="OUT.yaml",
                   help="write the config (--config, or the run log's) with the found effects compensated "
                        "and theta_hat0 from the fit, ready for `motorctl run`")
    p.set_defaults(func=cmd_identify)


# ---------------------------------------------------------------------------- command
def cmd_identify(args) -> int:
    from motorctl.cli import UsageError
    from motorctl.ident.data import load_record
    from motorctl.inputs import writable_dir, writable_file
    if args.report:
        writable_dir(args.report, "report")        # before reading DATA and the (long) fit
    if not (math.isfinite(args.closed_loop_duration) and 0 < args.closed_loop_duration <= 1e4):
        raise UsageError(f"--closed-loop-duration {args.closed_loop_duration}: must be within (0, 10000] s")
    if args.zoh_delay is not None and not (math.isfinite(args.zoh_delay) and 0 <= args.zoh_delay <= 10):
        raise UsageError(f"--zoh-delay {args.zoh_delay}: must be within 0..10 samples")
    try:
        rec = load_record(args.data, args.mapping, args.gain, args.axis)
        rec2 = load_record(args.validate, args.mapping, args.gain, args.axis) if args.validate else None
    except IsADirectoryError as exc:
        raise UsageError(f"{exc.filename}: is a directory; DATA must be a file") from None
    base_cfg, base_name = None, None
    if args.config:
        from motorctl.config import load_yaml
        base_cfg, base_name = load_yaml(args.config), args.config
    elif isinstance(rec.header.get("config"), dict) and isinstance(rec.header["config"].get("axes"), dict):
        base_cfg, base_name = rec.header["config"], f"the config in {rec.source}'s header"
    if args.write_config:
        if base_cfg is None:
            raise UsageError(f"--write-config {args.write_config}: needs a config to start from "
                             f"(--config BASE.yaml; {args.data} carries none)")
        w_axis = rec.axis or args.axis or next(iter(base_cfg.get("axes", {})), None)
        if w_axis not in base_cfg.get("axes", {}):
            raise UsageError(f"{base_name}: no axis {w_axis!r} in the config; "
                             f"axes: {', '.join(base_cfg.get('axes', {}))}")
        writable_file(args.write_config, "--write-config output")   # leaves no empty file behind
    cl_cfg, cl_axis = None, None
    if not args.no_closed_loop:
        if args.config:
            cl_cfg = base_cfg
        elif base_cfg is not None and rec.header.get("driver_type") == "sim":
            cl_cfg = rec.header["config"]
        if cl_cfg is not None:
            cl_axis = rec.axis or args.axis or next(iter(cl_cfg.get("axes", {})), None)
            if cl_axis not in cl_cfg.get("axes", {}):
                raise UsageError(f"{args.config or rec.source}: no axis {cl_axis!r} in the config; "
                                 f"axes: {', '.join(cl_cfg.get('axes', {}))}")

    # the closed loop's worker is forked before the identification is imported: it loads the
    # loop meanwhile and runs "before" and (the model found so far) "after" during the search
    cl = None
    if cl_cfg is not None:
        from motorctl.commission.closed_loop import ClosedLoop
        cl = ClosedLoop(cl_cfg, cl_axis, args.closed_loop_duration)
    try:
        from motorctl.ident.pipeline import (identify_record, json_default, text_report, validation,
                                             write_tuned_config)
        idf, s = identify_record(rec, n_theta=args.n_theta, friction=args.friction, zoh_delay=args.zoh_delay,
                                 on_nominal=cl and cl.before,
                                 after_fit=cl and (lambda idf: idf.terms and cl.after(idf)))
        s["validation"] = validation(idf, rec2) if rec2 is not None else None
        s["closed_loop"] = None
        if not args.no_closed_loop and idf.terms:
            if cl is None:
                s["closed_loop_note"] = "not run (no simulated plant: pass --config with the plant carrying the effect)"
            else:
                s["closed_loop"] = cl.result()
                if s["closed_loop"] is None:
                    s["closed_loop_note"] = "not run (the found effect has no additive compensation term)"
    finally:
        if cl is not None:
            cl.close()
    if args.write_config:
        write_tuned_config(idf, s, base_cfg, w_axis, base_name, args.write_config)
    if args.report:
        from motorctl.ident.report import write_report
        write_report(idf, s, args.report, text_report(s))
    if args.json:
        sys.stdout.write(json.dumps(s, default=json_default) + "\n")
    else:
        sys.stdout.write(text_report(s))
    return 0


#: causes to check when a fit is physically meaningless


__all__ = ["cmd_identify", "register"]
