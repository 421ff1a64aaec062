"""The effect-free floor of ``motorctl tune`` on the simulated driver, and the damage removed.

On the sim driver the plant's unmodelled effects are known: the floor is the same config and
seed with every effect family switched off, the best a compensation can do. The families are
found through the registry :data:`motorctl.effects.FAMILIES` (no list here): a family with an
``effects:`` entry (``sim_options``) is switched off by removing that entry; one whose simulator
option is an axis-level driver key (e.g. ``input_delay_s``) by removing the keys of its
``example`` (the fragment of ``axes.NAME.driver`` that switches it on), which restores the
option's default (off). :func:`effect_free` then checks through each family's ``sim_config``
that nothing is left on.

    damage removed = (L2_before − L2_after) / (L2_before − L2_floor)

1 means the tuned run tracks like the effect-free plant; 0 means nothing was gained.
"""

from __future__ import annotations

import copy

from motorctl.config import LoadedConfig, config_from_dict
from motorctl.effects import FAMILIES

#: ``driver.type`` of the simulated driver (its plant and effects are in the config)
SIM_DRIVER = "sim"


def is_simulated(loaded: LoadedConfig) -> bool:
    """True when the config runs the simulated driver (whose plant is in the config)."""
    return loaded.cfg.driver.type == SIM_DRIVER


def effects_on(loaded: LoadedConfig, axis: str) -> list[str]:
    """Names of the effect families switched on in the simulated plant of ``axis``, in registry
    order (each family's ``sim_config`` is not None). Empty for a driver other than sim."""
    if not is_simulated(loaded):
        return []
    opts = loaded.axis_driver_options[axis]
    return [name for name, fam in FAMILIES.items() if fam.sim_config(opts) is not None]


def effect_free(cfg: dict, source: str = "<effect-free config>") -> dict:
    """A copy of the sim-driver config dict ``cfg`` with every effect family switched off on
    every axis; everything else (plant, force noise, seed, controllers, programs) unchanged.

    Args:
        cfg: a config dict (parsed YAML) of the sim driver. source: its name in errors.
    Returns:
        The new config dict (``cfg`` is not modified).
    Raises:
        ConfigError: ``cfg`` is not a valid config.
        ValueError: the driver is not sim, or a family is still on after its entry and keys
            were removed (a family whose switch this rule does not find).
    """
    d = copy.deepcopy(cfg)
    for ax in d.get("axes", {}).values():
        drv = ax.get("driver")
        if not isinstance(drv, dict):
            continue
        effects = drv.get("effects")
        for fam in FAMILIES.values():
            if fam.sim_options is not None:
                if isinstance(effects, dict):
                    effects.pop(fam.name, None)
            else:
                for key in fam.example:
                    drv.pop(key, None)
        if isinstance(effects, dict) and not effects:
            drv.pop("effects")
    loaded = config_from_dict(d, source, check_budget=False)
    if not is_simulated(loaded):
        raise ValueError(f"{source}: driver {loaded.cfg.driver.type!r} has no simulated plant to switch "
                         f"effects off in (driver type {SIM_DRIVER!r} only)")
    for a in loaded.axes:
        left = effects_on(loaded, a)
        if left:
            raise ValueError(f"{source}: axes.{a}.driver: {', '.join(left)} still on after removing "
                             f"its effects entry and the keys of its example")
    return d


def damage_removed(l2_before: float, l2_after: float, l2_floor: float) -> float | None:
    """(L2_before − L2_after) / (L2_before − L2_floor) [-], or None when the effect does no
    damage (L2_before ≤ L2_floor: nothing to remove). L2 in any one unit (e.g. µm)."""
    damage = l2_before - l2_floor
    if not damage > 0:
        return None
    return (l2_before - l2_after) / damage


__all__ = ["SIM_DRIVER", "damage_removed", "effect_free", "effects_on", "is_simulated"]
