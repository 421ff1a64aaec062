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


def closed_loop(idf, cfg: dict, axis: str, duration_s: float) -> dict | None:
    """C2 alone vs C2 with the found effects compensated, both on the plant of ``cfg`` (``motorctl
    identify``'s closed-loop before/after; ``idf``: a :class:`motorctl.ident.select.Identifier`
    after its run).

    Args:
        cfg: a config dict whose simulated plant carries the effect (e.g. the run log's header).
        axis: the axis to run. duration_s: run length [s].
    Returns:
        {"before": {...}, "after": {...}, "compensation": {...}} with e_M_um, e_F_um, L2_um, or
        None when no found effect maps to a compensation term.
    """
    import copy

    from motorctl.app.job import run_job
    from motorctl.ident.pipeline import compensation_from_fit, set_theta0
    comp, theta_aug, _skipped = compensation_from_fit(idf)
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
    # each run starts from its own fitted model: the nominal θ alone, the augmented θ (about
    # the emitted references) with the compensation
    set_theta0(base["axes"][axis]["controller"], idf.nominal.fit.coef[:idf.n_theta])
    set_theta0(after["axes"][axis]["controller"], theta_aug)
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


def make_log(path: str, effect: dict | None = None, duration_s: float = 8.0, seed: int = 1,
             axis: str = "X", noise_N: float = 1.0, compensation: dict | None = None,
             trajectory: dict | None = None):
    """Run the simulated axis of :func:`motorctl.ident.synth.gantry_dict` (C2, virtual clock)
    and write the run log to ``path`` (arguments as ``gantry_dict``): the synthetic logs of the
    identification's tests and benchmarks.

    Returns:
        The :class:`motorctl.app.job.JobResult`.
    """
    from motorctl.app.job import run_job
    from motorctl.ident.synth import gantry_dict
    loaded = config_from_dict(gantry_dict(axis, effect, seed, noise_N, compensation, trajectory),
                              f"<synthetic {axis}>")
    return run_job(loaded, duration_s=duration_s, clock="virtual", log_path=str(path))


__all__ = ["SIM_DRIVER", "closed_loop", "damage_removed", "effect_free", "effects_on", "is_simulated", "make_log"]
