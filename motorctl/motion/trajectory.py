"""The interface every planned motion offers the daemon's setpoint filler: setpoints of n axes
over [0, duration] (:class:`Trajectory`)."""

from __future__ import annotations

import numpy as np

from motorctl.motion.gcode import Event, Pause


class Trajectory:
    """Setpoints of n_axes axes over [0, duration].

    duration [s]; axes: the axis names (len n_axes); events: [(t [s], Event)] in time order (the
    time its output is set); stops: [(t [s], Pause)] (the trajectory is at rest at t: the caller
    holds its clock there until resume); start, end: the first and final positions, shape
    (n_axes,) [m].
    """

    axes: tuple[str, ...]
    duration: float
    start: np.ndarray
    end: np.ndarray
    events: list[tuple[float, Event]]
    stops: list[tuple[float, Pause]]

    def sample(self, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(x [m], v [m/s], a [m/s²]) at time t [s], each shape (n_axes,); before 0 the start at
        rest, after ``duration`` the end at rest."""
        out = np.empty((1, 3, len(self.axes)))
        self.sample_into(t, 1.0, out)
        return out[0, 0].copy(), out[0, 1].copy(), out[0, 2].copy()

    def sample_into(self, t0: float, dt: float, out: np.ndarray) -> None:
        """Fill out[k, 0:3, i] = (x, v, a) of axis i at t0 + k·dt for k < out.shape[0]
        (out shape (n, 3, n_axes), float64); the work is proportional to the block, not to the
        program."""
        raise NotImplementedError

    def line_at(self, t: float) -> int:
        """The source line of the segment being run at time t [s] (0 before the first)."""
        return 0


