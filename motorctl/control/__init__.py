"""The controllers, chosen by name: C1 and C2 (the DCDIARC law of Chen, Yao & Wang 2013, with its
projection-type least-squares estimator and cubic input inversion) and LinuxCNC's PID with
feedforward. Every one implements :class:`motorctl.control.base.Controller`.

Adding a controller: a module with a ``Controller`` subclass, an entry in :data:`CONTROLLERS`,
and (if it has settings) a key in :class:`motorctl.control.params.ControllerConfig`.
"""

from __future__ import annotations

from importlib import import_module

#: name -> ("module:Class", the key of the ``controller:`` section it needs, or None when the
#: top-level keys suffice). Classes load on first use (the kernels compile only when needed).
CONTROLLERS: dict[str, tuple[str, str | None]] = {
    "c1": ("motorctl.control.dcdiarc:DCDIARC", None),
    "c2": ("motorctl.control.dcdiarc:DCDIARC", None),
    "pid": ("motorctl.control.pid:PID", "pid"),
}
CONTROLLER_NAMES: tuple[str, ...] = tuple(CONTROLLERS)


def controller_class(name: str):
    """The class registered as ``name``. Raises KeyError naming the known controllers."""
    try:
        target, _ = CONTROLLERS[name]
    except KeyError:
        raise KeyError(f"unknown controller {name!r}; allowed: {', '.join(CONTROLLER_NAMES)}") from None
    module, cls = target.split(":")
    return getattr(import_module(module), cls)


def configured_controllers(section) -> list[str]:
    """Names of the controllers an axis's ``controller:`` section configures (in registry
    order): those whose settings key is present (C1 and C2 always; a PID with ``pid``)."""
    return [n for n, (_, key) in CONTROLLERS.items() if key is None or getattr(section, key) is not None]


def make_controller(section, name: str, ts: float):
    """Build controller ``name`` from an axis's ``controller:`` section at sample period ts [s].

    Raises:
        KeyError: unknown name. ValueError: the section does not configure it.
    """
    return controller_class(name).from_config(section, ts, name)
