"""What a fit gives the controller: the identifier whose fit gives the effects' values
(:func:`~motorctl.ident.values.values_from`, re-exported here), the compensation and θ̂(0) of the found effects
(:func:`compensation_from_fit`) and the tuned config (:func:`tuned_config`,
:func:`write_tuned_config`)."""

from __future__ import annotations

import numpy as np

from motorctl.ident import effects as fx
from motorctl.ident.explain import _flow, fig, saturation_note
from motorctl.ident.values import values_from


def values_and_parameters(idf, gain: float):
    """(:func:`values_from` of ``idf``, its ``params_of(term, h, beta)``: an effect's named
    parameters in physical units, :func:`motorctl.effects.parameters` on the values' fit, with
    the record's ``gain`` [N/V])); what :func:`~motorctl.ident.uncertainty.fit_uncertainty`
    takes as ``params_of`` (:func:`motorctl.ident.judge.parameters_of`)."""
    from motorctl.ident.judge import parameters_of
    src = values_from(idf)
    return src, parameters_of(src, gain)


def _split_std(idf, ev, terms) -> list:
    """The fit's standard deviations of each term's β (the layout of ``coef_split``)."""
    i, out = idf.n_theta, []
    for t in terms:
        k = 0 if t.cols is None else t.cols.shape[1]
        out.append(np.asarray(ev.fit.std[i:i + k], dtype=float))
        i += k
    return out


def compensation_from_fit(idf, final=None, terms=None) -> tuple[dict, np.ndarray, list]:
    """The ``controller.compensation`` of the found effects and the θ̂(0) that goes with it.

    ``final`` and ``terms``: the evaluated model and its effect terms (default: those of the
    values' model, :func:`values_from`: the selection's, or its refit's when one ran).

    An adaptable family's entry carries ``adapt: false`` and its projection box from the fit's
    confidence interval (β ∓ 3σ, at least the default margin): a user only flips ``adapt``.

    A found effect the record cannot tell from a look-alike family (``cannot_be_told_from`` in
    the summary: cogging or an encoder's interpolation error, stiction or a dead-zone) is not
    compensated: a compensation is only written for an effect the identification names.

    Returns:
        (compensation {family: options} (V units, d̂_eff = −Cβ), θ (n_theta,) = the jointly
        fitted nominal θ re-expressed about each term's reference
        (:meth:`motorctl.effects.base.EffectFamily.theta_shift`), names of found families that
        have no compensation term or are not told from a look-alike).
    """
    unnamed = {ev.term.family for ev, _ in getattr(idf, "accepted", []) if ev.rivals}
    if final is None and terms is None:
        idf = values_from(idf)
    final = idf.final if final is None else final
    terms = idf.terms if terms is None else terms
    th, betas = idf.coef_split(final, terms)
    stds = _split_std(idf, final, terms)
    theta = np.array(th, dtype=float)
    comp, skipped = {}, []
    for t, b, sd in zip(terms, betas, stds):
        c = None if t.family in unnamed else fx.compensation(t.family, t.h, b, idf.p, beta_std=sd)
        if c:
            comp.update(c)
            theta = theta + fx.family(t.family).theta_shift(c[t.family], idf.n_theta)
        else:
            skipped.append(t.family)
    return comp, theta, skipped

#: margin added beyond a fitted θ that lies outside the configured box (fraction of |θ|, and
#: at least this fraction of the box's width)
BOX_MARGIN = 0.2


def tuned_config(idf, s: dict, base: dict, axis: str, base_name: str) -> tuple[dict, str]:
    """The config ``base`` with axis ``axis`` tuned from the identification, and its YAML text.

    Changes, each commented in the text with its figure: ``controller.compensation`` = the found
    effects (:func:`compensation_from_fit`); ``theta_hat0`` = the fitted θ (θ1..θ4 only when the
    fit has four parameters; θ5, θ6 clipped into the box, which Assumption 2 checks); where a
    fitted θ_i (i ≤ 4) lies outside [theta_min, theta_max] the bound moves past it by
    :data:`BOX_MARGIN`. Nothing else changes.

    Args:
        s: the summary (:func:`summarise`). base: a config dict (parsed YAML). axis: its axis.
        base_name: where ``base`` came from (named in the header comment).
    Returns:
        (the new config dict, its YAML text with comments).
    """
    import copy

    import yaml

    cfg = copy.deepcopy(base)
    ctl = cfg["axes"][axis]["controller"]
    comp, theta, skipped = compensation_from_fit(idf)
    nt = idf.n_theta
    unit = s["residual_unit"]
    notes = set_theta0(ctl, theta[:nt])
    t0, lo, hi = ctl["theta_hat0"], ctl["theta_min"], ctl["theta_max"]
    if comp:
        ctl["compensation"] = copy.deepcopy(comp)
    else:
        ctl.pop("compensation", None)
    # YAML text: dump with placeholders, then put the commented sections in their place
    marks = {"theta_hat0": "@@T0@@", "theta_min": "@@TMIN@@", "theta_max": "@@TMAX@@", "compensation": "@@COMP@@"}
    draft = copy.deepcopy(cfg)
    dctl = draft["axes"][axis]["controller"]
    for k, m in marks.items():
        dctl[k] = m
    text = yaml.safe_dump(draft, sort_keys=False, default_flow_style=False, allow_unicode=True, width=100)
    std = s["nominal"]["theta_std"]
    fit_line = ", ".join(f"theta{i + 1} {theta[i]:.5g} +- {std[i]:.2g}" for i in range(nt))
    out = []
    for line in text.splitlines():
        stripped = line.strip()
        key = stripped.split(":", 1)[0]
        if key in marks and marks[key] in stripped:
            ind = line[: len(line) - len(line.lstrip())]
            if key == "theta_hat0":
                out.append(f"{ind}# motorctl identify: theta_hat0 from the joint fit ({fit_line}); "
                           f"{nt} parameters fitted")
                for i, n in sorted(notes.items()):
                    out.append(f"{ind}#   theta{i + 1}: {n}")
                out.append(f"{ind}theta_hat0: {_flow(t0)}")
            elif key == "theta_min":
                out.append(f"{ind}theta_min: {_flow(lo)}" + _changed(base, axis, "theta_min", lo))
            elif key == "theta_max":
                out.append(f"{ind}theta_max: {_flow(hi)}" + _changed(base, axis, "theta_max", hi))
            else:
                if not comp:
                    out.append(f"{ind}# motorctl identify: no compensable effect found"
                               + (f" ({', '.join(skipped)} has no compensation term)" if skipped else ""))
                    continue
                out.append(f"{ind}# motorctl identify: the found effects, compensated (an additive term in "
                           f"v_a1, eq. 13, told to the estimator; ripple: v / (1 + r(x)) before eq. 9; "
                           f"delay: v_a1 on the trajectory ahead)")
                for e in s["effects"]:
                    pars = ", ".join(f"{k} {fig(v)}" for k, v in e["parameters"].items())
                    tag = ("compensated" if e["name"] in comp else
                           "NOT compensated: the record cannot tell it from "
                           + ", ".join(r["name"] for r in e["cannot_be_told_from"])
                           if e.get("cannot_be_told_from") else "NOT compensable (no compensation term)")
                    out.append(f"{ind}#   {e['name']}: {pars}; held-out RMS {e['heldout_rms_before']:.4g} -> "
                               f"{e['heldout_rms_after']:.4g} {unit}; {tag}")
                body = yaml.safe_dump({"compensation": comp}, sort_keys=False, default_flow_style=False, width=100)
                out.extend(ind + b for b in body.splitlines())
        else:
            out.append(line)
    head = [f"# tuned by `motorctl identify {s['source']} --write-config` from {base_name}, axis {axis}",
            f"# nominal held-out residual RMS {s['nominal']['heldout_rms']:.4g} {unit}, augmented "
            f"{s['augmented']['heldout_rms']:.4g} {unit}"]
    if not s["effects"]:
        head.append("# no effect found: only theta_hat0 (and the box where needed) changed")
    note = saturation_note(s.get("input_saturation"))
    if note:
        head.append(f"# {note}")
    return cfg, "\n".join(head + out) + "\n"


def set_theta0(ctl: dict, theta) -> dict:
    """Set ``theta_hat0`` of a controller section (dict) to the fitted ``theta`` (4 or 6), with
    the rules of :func:`tuned_config` (θ5, θ6 clipped into the box, the box widened past a
    θ1..θ4 outside it). Returns {index: note}."""
    t0 = [float(v) for v in ctl["theta_hat0"]]
    lo = [float(v) for v in ctl["theta_min"]]
    hi = [float(v) for v in ctl["theta_max"]]
    notes = {}
    for i in range(min(len(theta), len(t0))):
        v = float(theta[i])
        if i >= 4:
            c = min(max(v, lo[i]), hi[i])
            notes[i] = f"fit {v:.5g}" + ("" if c == v else f", clipped into the box [{lo[i]:g}, {hi[i]:g}]")
            v = c
        else:
            w = BOX_MARGIN * max(abs(v), hi[i] - lo[i])
            if v < lo[i]:
                notes[i] = f"fit {v:.5g} < theta_min {lo[i]:g}: theta_min widened"
                lo[i] = max(v - w, 0.5 * v) if i == 0 else v - w
            elif v > hi[i]:
                notes[i] = f"fit {v:.5g} > theta_max {hi[i]:g}: theta_max widened"
                hi[i] = v + w
            else:
                notes[i] = f"fit {v:.5g}"
        t0[i] = round(v, 6)
    ctl["theta_hat0"] = t0
    ctl["theta_min"] = [round(v, 6) for v in lo]
    ctl["theta_max"] = [round(v, 6) for v in hi]
    return notes


def _changed(base: dict, axis: str, key: str, new: list) -> str:
    old = [float(v) for v in base["axes"][axis]["controller"][key]]
    if old == [float(v) for v in new]:
        return ""
    return f"  # motorctl identify: was {_flow(old)} (the fit lies outside)"


def write_tuned_config(idf, s: dict, base: dict, axis: str, base_name: str, path) -> dict:
    """Write the tuned config of :func:`tuned_config` to ``path`` after checking it as
    ``motorctl check-config`` does (the bus budget aside), and note it in ``s``
    (``written_config``).

    Returns:
        The new config dict.
    Raises:
        ConfigError: the tuned config does not pass the checks (nothing is written).
        OSError: ``path`` cannot be written.
    """
    from motorctl.config import config_from_dict
    new_cfg, text = tuned_config(idf, s, base, axis, base_name)
    config_from_dict(new_cfg, path, check_budget=False)   # what check-config checks
    with open(path, "w", encoding="utf-8") as fh:
        fh.write(text)
    s["written_config"] = str(path)
    return new_cfg
