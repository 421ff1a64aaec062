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
from pathlib import Path

from motorctl.config import load_yaml
from motorctl.effects import FAMILIES

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

