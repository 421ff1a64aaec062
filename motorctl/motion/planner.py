"""The look-ahead path planner: a :class:`~motorctl.motion.gcode.Program` → a jerk-limited
:class:`Trajectory` of every axis (docs/motion.md, "The planner").

Interface (filled in below): :func:`plan`, :func:`point_to_point`, :func:`check_limits`,
:class:`Trajectory` (``duration``, ``sample``, ``sample_into``, ``line_at``, ``events``, ``stops``).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from motorctl.motion.gcode import AXES, Program


class LimitError(ValueError):
    """A program or move outside the soft limits: ``str()`` is one line naming the file:line, the
    axis, and how far outside [m]. Attributes: line (source line, 0 for a move), axis, excess_m."""

    def __init__(self, msg: str, line: int, axis: str, excess_m: float):
        self.line, self.axis, self.excess_m = line, axis, excess_m
        super().__init__(msg)


@dataclass(frozen=True)
class AxisLimits:
    """One axis's limits: v_max [m/s], a_max [m/s²], j_max [m/s³] (all > 0)."""

    v_max: float
    a_max: float
    j_max: float


class Trajectory:
    """Setpoints of n_axes axes over [0, duration].

    duration [s]; axes: the axis names (len n_axes); events: [(t [s], Event)] in time order (the
    time its output is set); stops: [(t [s], Pause)] (the trajectory is at rest at t: the caller
    holds its clock there until resume); end: the final position, shape (n_axes,) [m].
    """

    axes: tuple[str, ...]
    duration: float

    def sample(self, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(x [m], v [m/s], a [m/s²]) at time t [s], each shape (n_axes,); before 0 the start at
        rest, after ``duration`` the end at rest."""
        raise NotImplementedError

    def sample_into(self, t0: float, dt: float, out: np.ndarray) -> None:
        """Fill out[k, 0:3, i] = (x, v, a) of axis i at t0 + k·dt for k < out.shape[0]
        (out shape (n, 3, n_axes), float64); no allocation proportional to the program."""
        raise NotImplementedError

    def line_at(self, t: float) -> int:
        """The source line of the segment being run at time t [s] (0 before the first)."""
        raise NotImplementedError


def plan(program: Program, axes: Sequence[str], limits: Sequence[AxisLimits], *,
         feed_scale: float = 1.0, start: Sequence[float] | None = None) -> Trajectory:
    """Plan a parsed program for the machine's ``axes`` (letters among X Y Z, in the order of the
    arrays) with each axis's ``limits``. feed_scale multiplies every programmed feed (feed
    override, ≤ the axis limits always). start: the axes' positions [m] (None: program.start).
    Raises ValueError on an axis the program moves that is not in ``axes``."""
    raise NotImplementedError


def point_to_point(start: Sequence[float], goal: Sequence[float], limits: Sequence[AxisLimits], *,
                   feed: float | None = None, axes: Sequence[str] | None = None) -> Trajectory:
    """A coordinated straight move from rest at ``start`` to rest at ``goal`` (shape (n_axes,) [m])
    with synchronised arrival (Ruckig, Synchronization.Time), each axis within its own limits,
    the path speed ≤ ``feed`` [m/s] when given."""
    raise NotImplementedError


def check_limits(program: Program, soft_limits: Mapping[str, tuple[float, float]],
                 offsets: Mapping[str, float] | None = None) -> None:
    """Refuse a program that leaves the soft limits anywhere on its path (arcs included).

    soft_limits: axis letter → (soft_min, soft_max) [m]; offsets: axis letter → shift [m] added to
    the program's machine coordinates (None: 0). Raises :class:`LimitError` naming the first
    offending line, the axis and how far outside."""
    raise NotImplementedError
