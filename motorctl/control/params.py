"""The ``controller:`` section of an axis: what every law shares (the active ``type``, the
output limit, the axis model θ̂(0) with its box, the identified compensation) and, by name,
each law's own settings (read by the law's own model: :attr:`motorctl.control.base.Controller.Settings`).

No compiled code here, so a config can be loaded and checked without the control kernels.

Layout (the paper's: C1 and C2 share one set of design numbers at the section's top level):

    controller:
      type: c2                      # the active law (a name in the registry)
      u_lim: 10.0                   # shared
      theta_min/theta_max/theta_hat0: [...]   # the axis model and its box (paper eq. 4, 6)
      k_s: 50.0                     # C1/C2's shared keys (their Settings)
      c1: {k_s: 90.0, k1: 1500.0}   # optional: one law's own values over the shared ones
      pid: {P: ..., I: ..., D: ...} # a law with no shared keys: only its own mapping
"""

from __future__ import annotations

from typing import Any

from pydantic import PrivateAttr

from motorctl.control import CONTROLLER_NAMES, controller_class
from motorctl.effects.compensation import CompensationSection
from motorctl.schema import StrictModel, Vec6, quantity


class ControllerConfig(StrictModel):
    """An axis's ``controller:`` section.

    Attributes:
        type: the active law (a name of :data:`motorctl.control.CONTROLLER_NAMES`); every
            configured law of the section can be switched to at run time.
        u_lim: output limit [V] (u_M of the paper's Assumption 2 and the output clamp).
        theta_min, theta_max, theta_hat0: the axis model θ = (M/A1 [V s²/m], B/A1 [V s/m],
            A_f/A1 [V], d_n/A1 [V], A2/A1 [1/V], A3/A1 [1/V²]) of paper eq. 4 and 6: its box Ω_θ
            and θ̂(0). C1 and C2 adapt within the box; identification, autotune and the PID's
            feedforward start from θ̂(0).
        compensation: identified effects (:data:`~motorctl.effects.compensation.CompensationSection`).
        Every other key belongs to a law: a mapping named like the law (``pid:``, ``c1:``) or,
        for a law whose ``shared_keys`` is set (C1 and C2), a top-level key of its settings.
        :meth:`settings` parses them with the law's own model.
    """

    model_config = StrictModel.model_config | {"extra": "allow"}

    type: str = "c2"
    u_lim: quantity(1e-3, 1e3, "V") = 10.0
    theta_min: Vec6
    theta_max: Vec6
    theta_hat0: Vec6
    compensation: CompensationSection = CompensationSection()
    # the laws' settings parsed so far, by name (:meth:`settings`: each parsed once per section)
    _settings: dict = PrivateAttr(default_factory=dict)

    def law_data(self, name: str) -> tuple[dict | None, dict]:
        """(the law's own mapping or None, the shared top-level keys it reads) for law ``name``.
        Raises KeyError for a name not in the registry."""
        cls = controller_class(name)
        extra = self.model_extra or {}
        own = extra.get(name)
        shared = ({k: v for k, v in extra.items() if k in cls.Settings.model_fields}
                  if cls.shared_keys and cls.Settings is not None else {})
        return own, shared

    def configures(self, name: str) -> bool:
        """True when the section holds settings of law ``name`` (its mapping, or for a law with
        shared keys any of them; a law without settings is always configured)."""
        if controller_class(name).Settings is None:
            return True
        own, shared = self.law_data(name)
        return own is not None or bool(shared)

    def settings(self, name: str) -> Any:
        """Law ``name``'s settings, parsed by its own model (the shared keys, then its own
        mapping over them) once per section: the loader's checks and the controller built from
        the section get the same object.

        Raises:
            KeyError: no such law. ValueError: the section does not configure it.
            pydantic.ValidationError: a value is wrong (the config loader reports it with its key).
        """
        if name in self._settings:
            return self._settings[name]
        cls = controller_class(name)
        if cls.Settings is None:
            return None
        if not self.configures(name):
            raise ValueError(f"the controller section does not configure {name!r}")
        own, shared = self.law_data(name)
        parsed = cls.Settings.model_validate(
            {**shared, **own} if isinstance(own, dict) else (own if own is not None else shared))
        self._settings[name] = parsed
        return parsed

    def model_copy(self, *, update=None, deep: bool = False):
        """A copy (pydantic's), whose laws' settings are parsed from its own keys when asked."""
        out = super().model_copy(update=update, deep=deep)
        object.__setattr__(out, "__pydantic_private__", {"_settings": {}})
        return out

    def unknown_keys(self) -> list[str]:
        """Keys of the section that no registered law reads."""
        known = set(type(self).model_fields) | set(CONTROLLER_NAMES)
        for n in CONTROLLER_NAMES:
            cls = controller_class(n)
            if cls.shared_keys and cls.Settings is not None:
                known |= set(cls.Settings.model_fields)
        return [k for k in (self.model_extra or {}) if k not in known]

    def allowed_keys(self) -> list[str]:
        """Every key a section may hold (the shared fields, the laws' names, their shared keys)."""
        out = list(type(self).model_fields) + list(CONTROLLER_NAMES)
        for n in CONTROLLER_NAMES:
            cls = controller_class(n)
            if cls.shared_keys and cls.Settings is not None:
                out += [k for k in cls.Settings.model_fields if k not in out]
        return out
