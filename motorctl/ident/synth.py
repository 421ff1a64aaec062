"""Synthetic logs for tests, benchmark and the closed-loop check: the simulated gantry with one
effect the controller's config does not declare.

The configs come from ``configs/gantry-rigid.yaml`` (the paper's rigid plant: no structural mode,
ideal amplifier, quantisation-only encoder; one axis, virtual clock), so that the one effect
added is the only thing the paper's model lacks; ``configs/gantry.yaml`` when that file is absent. Effect parameters are
in the simulator's YAML form (``motorctl_drivers.sim``, ``axes.NAME.driver.effects``); the
examples are the families' own (:attr:`motorctl.effects.base.EffectFamily.example`).
"""

from __future__ import annotations

import copy
import math
from pathlib import Path

import numpy as np

from motorctl.config import load_yaml
from motorctl.effects import FAMILIES
from motorctl.ident.data import Record

_CONFIGS = Path(__file__).resolve().parents[2] / "configs"
GANTRY = _CONFIGS / "gantry-rigid.yaml" if (_CONFIGS / "gantry-rigid.yaml").is_file() else _CONFIGS / "gantry.yaml"

#: One example per family (X axis of the gantry: M = 12.8 kg, A1 = 80 N/V, stroke 0.4 m), a
#: fragment of ``axes.NAME.driver``: {"cogging": {...}} (an ``effects:`` entry) or
#: {"input_delay_s": τ} (an axis-level driver key).
EXAMPLES = {name: copy.deepcopy(fam.example) for name, fam in FAMILIES.items()}


def gantry_dict(axis: str = "X", effect: dict | None = None, seed: int = 1, noise_N: float | None = 1.0,
                compensation: dict | None = None, trajectory: dict | None = None,
                base: str | Path | None = None) -> dict:
    """Config dict of one gantry axis with ``effect`` on the plant (undeclared to the controller).

    Args:
        axis: 'X' or 'Y'. effect: {"cogging": {...}} (an entry of ``effects:``, a key naming a
            family with simulator options) or {"input_delay_s": τ} (any other key: an axis-level
            driver option). seed: driver seed. noise_N: plant force noise std [N] (None: the
            config's own).
        compensation: the controller's ``compensation`` dict (None: none).
        trajectory: keys of the axis's ``trajectory:`` section to override (e.g. a gentler
            ``a_max``; None: the config's program).
        base: the sim-driver config file the axis comes from (default :data:`GANTRY`, the
            rigid plant; e.g. ``configs/gantry.yaml`` for the default plant with its mode,
            current loop, noise and stiction).
    """
    d = copy.deepcopy(load_yaml(str(base or GANTRY)))
    d["axes"] = {axis: d["axes"][axis]}
    d["loop"]["clock"] = "virtual"
    d["loop"]["realtime"]["policy"] = "off"
    d["driver"]["seed"] = int(seed)
    drv = d["axes"][axis]["driver"]
    if noise_N is not None:
        drv["force_noise_N"] = float(noise_N)
    # an undeclared effect can raise the tracking error well above the production limits:
    # widen the following-error window so the supervisor does not cut the record short
    lim = d["axes"][axis]["limits"]
    lim["following_error_m"] = max(lim["following_error_m"], 0.01)
    lim["min_following_error_m"] = max(lim["min_following_error_m"], 0.005)
    for k, v in (effect or {}).items():
        if k in FAMILIES and FAMILIES[k].sim_options is not None:
            drv.setdefault("effects", {})[k] = copy.deepcopy(v)
        else:
            drv[k] = copy.deepcopy(v)
    if compensation:
        d["axes"][axis]["controller"]["compensation"] = copy.deepcopy(compensation)
    if trajectory:
        d["axes"][axis]["trajectory"].update(copy.deepcopy(trajectory))
    return d



#: the numpy axis of :func:`numpy_axis` (SI): carriage mass M [kg], force gain A1 [N/V], viscous
#: friction B [N·s/m], Coulomb friction F_c [N] as the model's S_f(ẋ) = (2/π)atan(900ẋ) (no
#: stiction: the carriage is not held at rest), offset F_0 [N] (a force on the carriage)
NUMPY_AXIS = {"mass_kg": 12.8, "gain_N_per_V": 80.0, "viscous_N_s_per_m": 17.6, "coulomb_N": 20.0, "offset_N": -4.0}


def numpy_axis_theta(axis: dict | None = None) -> np.ndarray:
    """The true θ1..θ4 (4,) [V s²/m, V s/m, V, V] of :func:`numpy_axis`'s plant in the model
    u = θ1ẍ + θ2ẋ + θ3 S_f(ẋ) − θ4 (paper eq. 9 without the force curve): M/A1, B/A1, F_c/A1, F_0/A1."""
    a = {**NUMPY_AXIS, **(axis or {})}
    g = a["gain_N_per_V"]
    return np.array([a["mass_kg"], a["viscous_N_s_per_m"], a["coulomb_N"], a["offset_N"]]) / g


def numpy_axis(duration_s: float = 5.0, seed: int = 1, *, fs: float = 5000.0, cycle_s: float = 1.63,
               input_noise_V: float = 0.3, force_noise_N: float = 0.0, axis: dict | None = None,
               kf_drift: tuple | None = None, step: tuple | None = None, cogging: tuple | None = None,
               spring_N_per_m: float = 0.0, vibration: tuple | None = None) -> Record:
    """A record of a rigid axis simulated in numpy (not motorctl's simulator): the model of paper
    eq. 9 without its force curve, M ẍ = A1 u − B ẋ − F_c S_f(ẋ) + F_0 + the effect injected
    (:data:`NUMPY_AXIS`, ``axis`` overriding its keys), under a PD loop with feedforward
    (4000 V/m, 40 V·s/m) and ``input_noise_V`` [V RMS] of white noise on its input, u held over
    each period 1/fs (read y_k, then write u_k: a run log's zero-order hold, so identify it with
    ``zoh_delay=0.5``), integrated exactly for the acceleration held over four substeps. The
    program: 0 ↔ 0.2 m raised-cosine moves of 0.25 s with dwells, period ``cycle_s`` [s].

    Effects (each off unless given): ``kf_drift`` (a, τ [s]): the force constant × 1 − a(1 −
    e^(−t/τ)) (a coil warming towards a level); ``step`` (F [N], t [s]): a constant force from t
    on; ``cogging`` (A [N], P [m]): A sin(2πx/P + 0.5); ``spring_N_per_m`` k: −k(x − 0.1 m);
    ``vibration`` (A [N], f [Hz]): A sin(2πft + 0.3); ``force_noise_N``: a white force [N RMS]
    held over each period. Returns a :class:`~motorctl.ident.data.Record` (t, y [m], u [V],
    gain A1), shapes (N,) with N = duration_s·fs."""
    a = {**NUMPY_AXIS, **(axis or {})}
    m, a1, b, fc, f0 = (a[k] for k in ("mass_kg", "gain_N_per_V", "viscous_N_s_per_m", "coulomb_N", "offset_N"))
    n = int(round(duration_s * fs))
    t_all = np.arange(n) / fs
    tc = np.mod(t_all, cycle_s)
    half, move, stroke = cycle_s / 2, 0.25, 0.2
    xr, vr, ar = np.zeros(n), np.zeros(n), np.zeros(n)
    for start, sign, base in ((0.0, 1.0, 0.0), (half, -1.0, stroke)):
        sel = (tc >= start) & (tc < start + move)
        s = (tc[sel] - start) / move
        xr[sel] = base + sign * stroke * 0.5 * (1 - np.cos(np.pi * s))
        vr[sel] = sign * stroke * 0.5 * np.pi / move * np.sin(np.pi * s)
        ar[sel] = sign * stroke * 0.5 * (np.pi / move) ** 2 * np.cos(np.pi * s)
    xr[(tc >= move) & (tc < half)] = stroke
    rng = np.random.default_rng(seed)
    u_noise = input_noise_V * rng.standard_normal(n)
    f_noise = force_noise_N * rng.standard_normal(n)
    sub = 4
    h = 1.0 / (fs * sub)
    x = v = 0.0
    ys, us = np.empty(n), np.empty(n)
    for k in range(n):
        t = k / fs
        ys[k] = x
        u = 4000.0 * (xr[k] - x) + 40.0 * (vr[k] - v) + (m * ar[k] + b * vr[k]) / a1 + u_noise[k]
        u = min(max(u, -10.0), 10.0)
        us[k] = u
        f_m = a1 * u * (1.0 - kf_drift[0] * (1.0 - math.exp(-t / kf_drift[1])) if kf_drift else 1.0) + f_noise[k]
        if step is not None and t >= step[1]:
            f_m += step[0]
        for j in range(sub):
            f = f_m - spring_N_per_m * (x - 0.1)
            if cogging:
                f += cogging[0] * math.sin(2 * math.pi * x / cogging[1] + 0.5)
            if vibration:
                f += vibration[0] * math.sin(2 * math.pi * vibration[1] * (t + j * h) + 0.3)
            acc = (f - b * v - fc * (2 / math.pi) * math.atan(900.0 * v) + f0) / m
            x += h * v + 0.5 * h * h * acc
            v += h * acc
    return Record(t=t_all, y=ys, u=us, gain=a1, source="<numpy axis>", axis="X")
