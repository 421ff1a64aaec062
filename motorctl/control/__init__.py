"""The controllers, chosen by name from the ``motorctl.controllers`` entry-point group (as the
drivers are): C1 and C2 (the DCDIARC law of Chen, Yao & Wang 2013, with its projection-type
least-squares estimator and cubic input inversion) and LinuxCNC's PID with feedforward. Every
one implements :class:`motorctl.control.base.Controller`: its own settings model, its own
check, its linearisation (for autotune's margins) and the signals it records.

Adding a controller: one module with a ``Controller`` subclass and one entry point
(docs/architecture.md, "Adding a controller").
"""

from __future__ import annotations

from functools import cache
from importlib.metadata import EntryPoint, entry_points

ENTRY_POINT_GROUP = "motorctl.controllers"


@cache
def available_controllers() -> dict[str, EntryPoint]:
    """The installed controllers by name, sorted (classes load on first use: their kernels
    compile only when a controller is built)."""
    return {ep.name: ep for ep in sorted(entry_points(group=ENTRY_POINT_GROUP), key=lambda e: e.name)}


#: the registered names, sorted (the daemon's status encodes the active law by its index)
CONTROLLER_NAMES: tuple[str, ...] = tuple(available_controllers())


@cache
def controller_class(name: str):
    """The class registered as ``name``. Raises KeyError naming the known controllers."""
    eps = available_controllers()
    if name not in eps:
        raise KeyError(f"unknown controller {name!r}; allowed: {', '.join(eps) or 'none installed'}")
    cls = eps[name].load()
    if getattr(cls, "name", "") != name:
        raise KeyError(f"the entry point {name!r} loads {cls.__qualname__}, whose name is {cls.name!r}")
    return cls


def configured_controllers(section) -> list[str]:
    """Names of the controllers an axis's ``controller:`` section configures (sorted)."""
    return [n for n in CONTROLLER_NAMES if section.configures(n)]


def make_controller(section, name: str, ts: float):
    """Build controller ``name`` from an axis's ``controller:`` section (a checked
    :class:`~motorctl.control.params.ControllerConfig`) at sample period ts [s]: the class reads
    its own settings from the section (:meth:`~motorctl.control.base.Controller.from_config`).

    Raises:
        KeyError: unknown name. ValueError: the section does not configure it (the message
            names the configured ones).
    """
    if not section.configures(name):
        raise ValueError(f"controller {name!r} is not configured for this axis; configured: "
                         f"{', '.join(configured_controllers(section))}")
    return controller_class(name).from_config(section, ts)
