"""The controller interface: what the servo loop and the recorder read from a controller.

A controller is one axis's control law. The loop calls :meth:`Controller.reset` when the axis
is enabled (bumpless start from the measured position) and :meth:`Controller.update` once per
sample; after each sample the controller's :attr:`Controller.signals` hold the values of
:data:`motorctl.control.signals.CONTROLLER_SIGNALS` (NaN for a signal the law does not have). The
loop copies that block into the cycle record and reads the tracking error ``e`` for the
following-error check; nothing else is read, so any law that fills these slots can be driven,
recorded, switched and compared. A law may declare signals of its own
(:attr:`Controller.own_signals`): they follow the common block in :attr:`Controller.signals`
and the run log has them as columns ``AXIS.<name>`` (:class:`motorctl.loop.records.RecordLayout`).

Controllers are chosen by name (the ``motorctl.controllers`` entry points,
:mod:`motorctl.control`); each class reads its own part of an axis's ``controller:`` config
section (Klipper's rule): its :attr:`Controller.Settings` model, checked by
:meth:`Controller.check`, built by :meth:`Controller.from_config`. For commissioning it gives
its linearisation (:meth:`Controller.linearise`) and its family of gains with one loop-gain
knob (:meth:`Controller.gain_family`, :meth:`Controller.scaled`).
"""

from __future__ import annotations

import abc
from typing import Any, ClassVar, Mapping

import numpy as np

# the signal names and offsets, re-exported: the laws import them with the interface
from motorctl.control.signals import CONTROLLER_SIGNALS, N_SIGNALS, SIG, SIG_D0, SIG_E, SIG_P  # noqa: F401
from motorctl.control.signals import SIG_THETA, SIG_V, SIG_X2  # noqa: F401

#: the compiled laws the servo cycle runs itself (:mod:`motorctl.control.kernels`): C1/C2,
#: PID+FF, C1/C2 with a compensation (its terms compiled, :mod:`motorctl.effects.compensation`);
#: LAW_PY: a law whose :meth:`Controller.update` the cycle calls from Python (any law without a
#: compiled step)
LAW_PY, LAW_DCDIARC, LAW_PID, LAW_DCDIARC_COMP = 0, 1, 2, 3
#: the coupled pair law (GTCF, :mod:`motorctl.control.gtcf`): C2 per axis whose robust feedback
#: is set in the task frame of two axes; the cycle hands it the partner axis's sample as well
LAW_GTCF = 4



class Controller(abc.ABC):
    """Base of every controller (C1, C2, PID, ...).

    Attributes:
        name (str): registry name, e.g. "c2".
        ts (float): sample period [s].
        u_lim (float): output limit [V]; :meth:`update` returns |u| ≤ u_lim.
        n_theta (int): number of adapted parameters θ̂ (0 for a fixed-gain law).
        theta_hat (np.ndarray): shape (n_theta,), live view of θ̂.
        signals (np.ndarray): shape (N_SIGNALS + len(own_signals),) float64, the published
            signals of the last sample (see the module docstring), then the law's own
            (:meth:`own_index`); NaN where the law has no such signal.
        preview_s (float): how far ahead [s] the law wants the desired trajectory (an input
            delay it predicts over); when > 0 the loop calls :meth:`preview` with the desired
            trajectory at t + preview_s before each :meth:`update`. 0 (default): never.
    """

    name: ClassVar[str] = ""
    #: the law's settings model (a :class:`motorctl.schema.StrictModel`; None: no settings),
    #: read from the section's mapping named like the law and, when :attr:`shared_keys`, from
    #: the section's top-level keys (:class:`motorctl.control.params.ControllerConfig`)
    Settings: ClassVar[type | None] = None
    shared_keys: ClassVar[bool] = False
    #: the entries of :data:`motorctl.control.signals.CONTROLLER_SIGNALS` this law fills (the
    #: others are recorded as NaN)
    records: ClassVar[tuple[str, ...]] = ("v", "e", "p", "x2")
    #: signals of the law's own beyond :data:`~motorctl.control.signals.CONTROLLER_SIGNALS`:
    #: name -> unit, recorded as run-log columns ``AXIS.<name>`` after the fixed ones (names
    #: other than the record's fixed axis fields). A law that runs from Python
    #: (:attr:`law_code` LAW_PY) writes them at :meth:`own_index`; empty (default): none
    own_signals: ClassVar[dict[str, str]] = {}
    #: the settings keys autotune writes (those :meth:`gain_family` sets)
    tuned_keys: ClassVar[tuple[str, ...]] = ()
    #: the damping ratios ζ of :meth:`gain_family`'s design pole pair when autotune states none
    ZETA: ClassVar[tuple[float, ...]] = ()
    preview_s: float = 0.0

    def __init__(self, ts: float, u_lim: float, n_theta: int = 0):
        self.ts = float(ts)
        self.u_lim = float(u_lim)
        self.n_theta = int(n_theta)
        self.signals = np.full(N_SIGNALS + len(self.own_signals), np.nan)
        self.theta_hat = np.zeros(self.n_theta)

    @classmethod
    def own_index(cls, name: str) -> int:
        """Offset of the own signal ``name`` (:attr:`own_signals`) in :attr:`signals`.

        Raises:
            KeyError: the law declares no such signal (the message lists those it declares).
        """
        try:
            return N_SIGNALS + list(cls.own_signals).index(name)
        except ValueError:
            raise KeyError(f"controller {cls.name!r} declares no signal {name!r}; own signals: "
                           f"{', '.join(cls.own_signals) or 'none'}") from None

    @classmethod
    @abc.abstractmethod
    def from_config(cls, section, ts: float) -> "Controller":
        """Build from an axis's ``controller:`` section (a checked
        :class:`~motorctl.control.params.ControllerConfig`) at sample period ts [s].

        Raises:
            ValueError: the section does not configure this controller.
        """

    @classmethod
    def check(cls, settings, section) -> list[tuple[str, str]]:
        """Cross-checks of the law's ``settings`` with the rest of its ``section`` that the
        settings model cannot make alone. Returns [(key, what is wrong and what is allowed)]
        (empty: fine); the key is relative to the section. Default: none."""
        return []

    @classmethod
    def check_axes(cls, axis: str, settings, sections: Mapping[str, Any], period_s: float) -> list[tuple[str, str]]:
        """Cross-checks of axis ``axis``'s ``settings`` with the other axes' ``controller:``
        sections (``sections``: axis name -> section) and the loop's period ``period_s`` [s]
        (a pair law's two halves; a filter below the Nyquist frequency). Returns as
        :meth:`check`. Default: none."""
        return []

    @classmethod
    def linearise(cls, gains: Mapping[str, Any], ts: float, w: np.ndarray, theta_hat=None,
                  u0: float = 0.0) -> np.ndarray:
        """The law's small-signal transfer function C(e^{jωTs}) from −y to u at the operating
        point u0 [V], with θ̂ (6,) where it matters: ``gains`` maps the settings keys (a
        settings model's ``model_dump()`` or a candidate of :meth:`gain_family`); w (K,)
        [rad/s]. Returns complex (K,). Raises NotImplementedError when the law has none
        (autotune then skips it)."""
        raise NotImplementedError(f"controller {cls.name!r} has no linearisation")

    @classmethod
    def gain_family(cls, theta1: float, settings, omegas, zetas=None) -> list[dict]:
        """Autotune's candidates: settings key -> value dicts (with the design numbers under
        keys that start with '_'), from the fitted θ1 = M/A1 [V s²/m], one or more per design
        pole ω in ``omegas`` [rad/s] and damping ratio in ``zetas`` (None: :attr:`ZETA`; the
        rule widens it on a plant without a structural mode). Default: none (autotune leaves
        the law as configured)."""
        return []

    @classmethod
    def model_settings(cls, theta) -> dict:
        """Settings the law takes from a fitted axis model θ (6,) (paper eq. 4), written with
        its autotuned gains (e.g. a feedforward). Default: none (an adaptive law starts from
        the section's θ̂(0))."""
        return {}

    @classmethod
    def scaled(cls, gains: Mapping[str, Any], s: float) -> dict:
        """``gains`` at share ``s`` of the loop gain (the verification ladder's knob)."""
        raise NotImplementedError(f"controller {cls.name!r} has no loop-gain knob")

    @abc.abstractmethod
    def reset(self, y0: float) -> None:
        """Start (or restart) from the measured position y0 [m] with zero output."""

    @abc.abstractmethod
    def update(self, y: float, x_d: float, xd_dot: float, xd_ddot: float, t: float) -> float:
        """One sample: measured position y [m], desired position [m], velocity [m/s] and
        acceleration [m/s²], time t [s]. Returns u [V], |u| ≤ u_lim; fills :attr:`signals`.
        Never allocates a container, blocks or logs (it runs inside the 5 kHz cycle)."""

    @property
    def law_code(self) -> int:
        """The compiled step the servo cycle runs for this controller (``LAW_*``); LAW_PY
        (default): none, the cycle calls :meth:`update` (and :meth:`reset`) from Python."""
        return LAW_PY

    def state_size(self) -> tuple[int, int]:
        """(floats, ints) of the state a compiled law keeps in the cycle's rows (:meth:`attach`)."""
        return 0, 0

    def attach(self, sig: np.ndarray, f: np.ndarray, ii: np.ndarray, lay: np.ndarray) -> None:
        """Move a compiled law's state into the servo cycle's rows for this axis (between
        cycles): ``sig`` (N_SIGNALS,) the published signals, ``f`` float64 and ``ii`` int64 rows
        of at least :meth:`state_size`, ``lay`` int64 (N_LAYOUT,) the law's layout; the law's
        arrays become views of them, with their values. Default (LAW_PY): nothing."""

    def detach(self) -> None:
        """Take the state back from the cycle's rows into arrays of the controller's own (when
        the loop lets go of it: a switch). Default: nothing."""

    def preview(self, x_d: float, xd_dot: float, xd_ddot: float) -> None:
        """The desired position [m], velocity [m/s] and acceleration [m/s²] at t + preview_s,
        for the next :meth:`update` (inside the cycle: store floats only). Default: ignored."""

    @property
    def e(self) -> float:
        """Tracking error of the last sample, y − x_d [m]."""
        return float(self.signals[SIG_E])

    def inherit(self, other: "Controller") -> None:
        """Take over what ``other`` has learned (called at a switch, between cycles): by
        default the common leading entries of θ̂."""
        n = min(self.n_theta, other.n_theta)
        if n:
            self.theta_hat[:n] = other.theta_hat[:n]

    def theta_vector(self) -> np.ndarray:
        """θ̂ padded with NaN to 6 entries (a new array; not for the cycle)."""
        out = np.full(6, np.nan)
        out[: self.n_theta] = self.theta_hat
        return out
