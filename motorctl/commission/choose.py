"""Step 3 of ``motorctl autotune``: every law's gain family on the measured response, the
members whose margins hold at every rung of the verification ladder."""

from __future__ import annotations

import math

import numpy as np

from motorctl.commission.loopshape import loop_margins, plant_model_frf
from motorctl.commission.rule import (BACKOFF, COH_USED, EDGE_SPAN, EDGE_TOL, F_TRACK_HZ, FRF_SIGMAS, PERIODS, RULE,
                                      Rule, SCALES, ZETA_RIGID)
from motorctl.control import configured_controllers, controller_class


# ================================================================ the rule
OMEGA = tuple(float(x) for x in np.geomspace(30.0, 3000.0, 49))   #: [rad/s]


RAYLEIGH_MEDIAN = math.sqrt(2.0 * math.log(2.0))   #: median of a Rayleigh variable of scale 1


def loop_frf(meas: dict, model: dict, ts: float, periods: int = PERIODS):
    """(w (K,) [rad/s] of :func:`grid_w`, the fitted model's FRF (K,), the FRF the rule runs on
    (K,)) [m/V]: the fitted model, times the measured FRF's departure from it where the
    measurement shows one: at the lines of coherence ≥ :data:`COH_USED` whose departure
    |G_meas/G_model − 1| exceeds :data:`FRF_SIGMAS` times the line's own random error
    ε = √(1 − γ²)/(γ √(2 n)) (γ²: the coherence, n: the measured periods; Bendat & Piersol,
    Random Data, 4th ed., eq. 9.90) scaled by the lines' own scatter about the model (the indirect
    closed-loop estimate scatters about twice that: on configs/gantry-rigid.yaml Y 15 % of the
    lines were beyond 3 ε), the ratio interpolated between the lines (1 at the others);
    the model alone below the first and above the last such line. On a rigid axis the lines of
    coherence 0.5-0.9 (30-60 Hz on configs/gantry-rigid.yaml Y) scatter ±10 % and ±7° about
    the model: taken as measured, one of them set the peak sensitivity of the 50 % rung
    (18.0 dB against 12.5 dB on the model) and the margins' edge went up and down with ω.
    The measured FRF is taken divided by the model's "input_gain" κ (:func:`motorctl.commission.
    fit.input_gain`): the plant at u ≈ 0, where the force gain f_u'(0) = 1 is its highest for
    θ5, θ6 ≤ 0 (the multisine's own amplitude measured it κ times lower), as the model is."""
    w = grid_w(ts)
    G_fit = plant_model_frf(model, ts, w)
    G_w = G_fit.copy()
    fm, Gm, ch = meas["f_hz"], meas["G"] / model.get("input_gain", 1.0), meas["coherence"]
    good = ch >= COH_USED
    f_w = w / (2.0 * math.pi)
    if good.sum() > 10:
        ratio = Gm / plant_model_frf(model, ts, 2.0 * math.pi * fm)
        gam2 = np.clip(ch, 1e-6, 1.0)
        eps = np.sqrt((1.0 - gam2) / (2.0 * max(periods, 1) * gam2))
        # the scale of that error from the lines' own scatter about the model: the median of a
        # Rayleigh variable (the complex departure) is 1.177 σ; not below the formula's. A line
        # of coherence 1 (a noise-free measurement: ε = 0) has no scatter to scale and counts as
        # measured wherever it departs at all
        scaled = good & (eps > 0.0)
        scale = max(1.0, float(np.median(np.abs(ratio[scaled] - 1.0) / eps[scaled])) / RAYLEIGH_MEDIAN) \
            if scaled.any() else 1.0
        ratio = np.where(good & (np.abs(ratio - 1.0) > FRF_SIGMAS * scale * eps), ratio, 1.0)
        inside = (f_w >= fm[good][0]) & (f_w <= fm[good][-1])
        re = np.interp(f_w, fm, ratio.real)
        im = np.interp(f_w, fm, ratio.imag)
        G_w[inside] = G_fit[inside] * (re[inside] + 1j * im[inside])
    return w, G_fit, G_w


def margins_hold(law: str, g: dict, ts: float, w: np.ndarray, G_w: np.ndarray, theta_hat=None,
                 rule: Rule = RULE):
    """(:class:`Margins` of L = C G_w at 100 % of ``g``, whether the rule's margins hold at every
    rung of the verification ladder :data:`SCALES`). A loop with integral action can lose phase
    margin when its gain falls, and a heavier load lowers the loop gain the same way."""
    f = w / (2.0 * math.pi)
    L = controller_class(law).linearise(g, ts, w, theta_hat) * G_w
    mg = loop_margins(L, f)
    ok = rule.holds(mg) and all(rule.holds(loop_margins(sc * L, f)) for sc in SCALES[:-1])
    return mg, ok


def family_zetas(law: str, model: dict) -> tuple[float, ...] | None:
    """The damping ratios ζ of ``law``'s family on the fitted plant ``model``
    (:func:`motorctl.commission.fit.fit_plant`): the law's own (None) when the fit kept a
    structural mode; when it kept none (a rigid plant), the law's own and :data:`ZETA_RIGID`
    too. With a lightly damped mode the law's own ζ stay (on configs/gantry.yaml autotune comes
    within 15 % of an independent search with them); without one only the delay and the
    current loop limit the loop, and a lightly damped design pole pair at a higher ω (less D for the same P: less
    rest noise, less saturation) can be the best the program allows (on
    configs/gantry-rigid.yaml an independent search's best C1/C2 gains sit at ζ 0.17-0.26).
    The margins on the measured response still decide which members are admissible."""
    if model.get("mode", True):
        return None
    return tuple(sorted(set(ZETA_RIGID) | set(controller_class(law).ZETA)))


def tunable_laws(section) -> list[str]:
    """The laws an axis's section configures that give autotune a gain family and a
    linearisation (:class:`motorctl.control.base.Controller`), sorted."""
    out = []
    for name in configured_controllers(section):
        cls = controller_class(name)
        try:
            fam = cls.gain_family(1.0, section.settings(name), OMEGA[:1])
            if fam:
                cls.linearise(fam[0], 1e-4, np.array([1.0]))
                out.append(name)
        except NotImplementedError:
            continue
    return out


def shape_of(g: dict) -> tuple:
    """A candidate's shape: its design numbers other than ω ("_zeta", "_r", ...)."""
    return tuple(sorted((k, v) for k, v in g.items() if k.startswith("_") and k not in ("_w", "_rest_V")))


def design_of(g: dict) -> tuple:
    """A candidate's place in its law's family: all its design numbers, ω included
    ((("_r", r), ("_w", ω), ("_zeta", ζ)) for the PID)."""
    return tuple(sorted((k, v) for k, v in g.items() if k.startswith("_") and k != "_rest_V"))


def neighbours(g: dict, grid: dict, members: dict) -> list[dict]:
    """The members of ``members`` ({:func:`design_of`: gains}) one grid step from ``g`` in one
    design number, or in two at once (the diagonals: e.g. a higher ω with a lower ζ), on the
    family's grid ``grid`` ({design key: sorted values}, :func:`choose_gains`)."""
    here = dict(design_of(g))
    keys = [k for k in grid if k in here]
    steps = [((k, s),) for k in keys for s in (1, -1)]
    steps += [((a, sa), (b, sb)) for i, a in enumerate(keys) for b in keys[i + 1:]
              for sa in (1, -1) for sb in (1, -1)]
    out = []
    for step in steps:
        d = dict(here)
        for k, s in step:
            j = grid[k].index(here[k]) + s
            if not 0 <= j < len(grid[k]):
                break
            d[k] = grid[k][j]
        else:
            m = members.get(tuple(sorted(d.items())))
            if m is not None:
                out.append(m)
    return out


def edge_member(make, holds, g: dict, u: float = 1.0) -> dict | None:
    """The family member with ``u`` times the damping gain of ``g`` (C1/C2: k_s = 2ζωθ1; PID:
    D, the same number) and the highest stiffness the margins allow (C1/C2: k1 = ω/2ζ; PID:
    P = θ1ω², the same r): the design (ω√u·s, ζ√u/s) with the largest s in [1/EDGE_SPAN,
    EDGE_SPAN] whose margins hold (``holds``), bracketed in log s to :data:`EDGE_TOL`;
    ``make(g, ω, ζ)``: the member of ``g``'s other design numbers at (ω, ζ) (off the family's
    grid). None when no s holds (on a scan of 13 points) or the edge is ``g`` itself.

    At a fixed damping gain a stiffer loop tracks better, and on a carriage held by stiction
    it is quieter at rest too (configs/gantry-rigid.yaml Y, C1 at k_s 132.5, 40 s runs: k1
    1200 0.758 µm and 59 mV, 1630 0.563 µm and 53 mV, 2200 0.417 µm and 47 mV): the margins
    bound it (the least ζ they allow at that ω lies between the family's damping ratios)."""
    w0, z0 = g["_w"] * math.sqrt(u), g["_zeta"] * math.sqrt(u)
    scan = np.geomspace(1.0 / EDGE_SPAN, EDGE_SPAN, 13)
    ok = [s for s in scan if holds(make(g, w0 * s, z0 / s))]
    if not ok:
        return None
    lo = max(ok)
    hi = next((s for s in scan if s > lo), None)
    while hi is not None and math.log(hi / lo) > EDGE_TOL:
        s = math.sqrt(lo * hi)
        if holds(make(g, w0 * s, z0 / s)):
            lo = s
        else:
            hi = s
    m = make(g, w0 * lo, z0 / lo)
    return None if u == 1.0 and lo < 1.0 + EDGE_TOL else m


def rest_noise(C: np.ndarray, rest_psd) -> float:
    """Predicted u RMS at rest [V]: the measured rest spectrum of y [m²/Hz] through |C| (a
    carriage held by stiction: the loop is open). C: C(e^{jωTs}) at the PSD's frequencies."""
    f, s = rest_psd
    df = f[1] - f[0]
    return float(math.sqrt(np.sum(np.abs(C[1:]) ** 2 * s[1:]) * df))


def grid_w(ts: float) -> np.ndarray:
    """The frequency grid of the margins [rad/s]: 1 Hz to 0.999 Nyquist, log-spaced."""
    return np.geomspace(2.0 * math.pi, 0.999 * math.pi / ts, 4000)


def choose_gains(law: str, G_w, w: np.ndarray, ts: float, theta1: float, section, rest_psd,
                 theta_hat=None, rule: Rule = RULE, zetas=None) -> dict | None:
    """Step 3 for one law on the plant FRF ``G_w`` (K,) at ``w`` (K,) [rad/s]: the family
    members whose margins hold at every step of the verification ladder (``zetas``: the
    family's damping ratios, :func:`family_zetas`; None: the law's own).

    Returns:
        None when no candidate passes, else {"gains" (the highest |L| at F_TRACK_HZ),
        "margins" (:class:`Margins`), "u_rest_pred_V", "candidates" (how many passed),
        "backoff", "admissible": {shape: [gains, ... by ω, highest first]},
        "members": {:func:`design_of`: gains} (the same candidates, by their place in the
        family), "grid": {design key: sorted values over the whole family},
        "l_track": {:func:`design_of`: |L| at F_TRACK_HZ}, "theta1" (the family's), "holds": gains
        -> whether the margins hold at 100, 75 and 50 % of those gains (a stepped-down candidate's
        own ladder), "edge": (gains, u=1) -> :func:`edge_member` (off the grid) or None,
        "sensitivity": (law, gains, f (M,) [Hz]) -> |S|² (M,) on the measured response}.
    """
    cls = controller_class(law)
    f = w / (2.0 * math.pi)
    wn = 2.0 * math.pi * rest_psd[0]
    best, n_ok, adm, members, l_track, grid = None, 0, {}, {}, {}, {}
    j_tr = int(np.argmin(np.abs(f - F_TRACK_HZ)))
    fam = (cls.gain_family(theta1, section.settings(law), OMEGA) if zetas is None else
           cls.gain_family(theta1, section.settings(law), OMEGA, zetas=zetas))
    for g in fam:
        for k, v in design_of(g):
            grid.setdefault(k, set()).add(v)
        mg, ok = margins_hold(law, g, ts, w, G_w, theta_hat, rule)
        if not ok:
            continue
        L = cls.linearise(g, ts, w, theta_hat) * G_w
        un = rest_noise(cls.linearise(g, ts, np.maximum(wn, 1e-9), theta_hat), rest_psd)
        n_ok += 1
        g["_rest_V"] = un
        adm.setdefault(shape_of(g), []).append(g)
        members[design_of(g)] = g
        l_track[design_of(g)] = float(abs(L[j_tr]))
        key = (abs(L[j_tr]), -mg.ms_db)
        if best is None or key > best[0]:
            best = (key, g, mg, un)
    if best is None:
        return None
    L = cls.linearise(best[1], ts, w, theta_hat) * G_w
    backoff = [b for b in BACKOFF if rule.holds(loop_margins(b * L, f))]
    for v in adm.values():
        v.sort(key=lambda g: -g["_w"])
    settings = section.settings(law)

    def make(like: dict, w_: float, z_: float) -> dict:
        """The member of ``like``'s other design numbers at (ω, ζ), its predicted rest noise
        and |L| at F_TRACK_HZ (in "l_track") noted."""
        g = next(m for m in cls.gain_family(theta1, settings, (w_,), zetas=(z_,))
                 if all(m.get(k) == v for k, v in shape_of(like) if k != "_zeta"))
        g["_rest_V"] = rest_noise(cls.linearise(g, ts, np.maximum(wn, 1e-9), theta_hat), rest_psd)
        l_track[design_of(g)] = float(abs(cls.linearise(g, ts, w[j_tr:j_tr + 1], theta_hat)[0] * G_w[j_tr]))
        return g

    def holds(g: dict) -> bool:
        return margins_hold(law, g, ts, w, G_w, theta_hat, rule)[1]
    return {"gains": best[1], "margins": best[2], "u_rest_pred_V": best[3], "candidates": n_ok,
            "backoff": backoff, "admissible": adm, "members": members, "l_track": l_track,
            "grid": {k: sorted(v) for k, v in grid.items()}, "theta1": theta1,
            "holds": holds, "edge": lambda g, u=1.0: edge_member(make, holds, g, u),
            "sensitivity": lambda law_, g, f_hz: _sensitivity2(law_, g, ts, w, G_w, theta_hat, f_hz)}


def _sensitivity2(law: str, g: dict, ts: float, w: np.ndarray, G_w: np.ndarray, theta_hat, f_hz) -> np.ndarray:
    """|S|² = |1 + C G|⁻² at f_hz (M,) [Hz] of ``law`` with gains ``g`` on the FRF ``G_w`` (K,)
    at w (K,) [rad/s] (interpolated in log f; G at the grid's ends outside it)."""
    f = np.maximum(np.asarray(f_hz, dtype=float), 1e-3)       # C has a pole at 0 Hz
    lf, lw = np.log(f), np.log(w / (2.0 * math.pi))
    G = np.interp(lf, lw, G_w.real) + 1j * np.interp(lf, lw, G_w.imag)
    C = controller_class(law).linearise(g, ts, 2.0 * math.pi * f, theta_hat)
    return 1.0 / np.maximum(np.abs(1.0 + C * G) ** 2, 1e-300)
