"""A Ruckig trajectory's states at many times at once, from its profiles.

Ruckig's ``Trajectory.at_time`` answers one time per call (tens of µs each from Python): an 18 s
jog sampled at the loop's 0.2 ms period is 92 500 calls, seconds of the I/O process's time. A
Ruckig profile is up to seven phases of constant jerk per degree of freedom (Berscheid & Kröger
2021, "Jerk-limited real-time trajectory generation with arbitrary target states", RSS): each
phase k starts at time T_k with position p_k, velocity v_k, acceleration a_k and runs at jerk
j_k, so at τ = t − T_k into it

    p = p_k + v_k·τ + a_k·τ²/2 + j_k·τ³/6,   v = v_k + a_k·τ + j_k·τ²/2,   a = a_k + j_k·τ.

:func:`states` evaluates that for an array of times with numpy, for the trajectories it can
(one section, no brake or pre-acceleration phase: every move planned from rest, and from a
moving state within the limits); :func:`evaluable` says which.
"""

from __future__ import annotations

import numpy as np

__all__ = ["evaluable", "states"]


def _extra_phase(profile) -> float:
    """The duration [s] of the profile's phases ahead of its seven (a brake, a pre-acceleration)."""
    total = 0.0
    for name in ("brake", "accel"):
        part = getattr(profile, name, None)
        if part is not None:
            total += float(getattr(part, "duration", 0.0) or 0.0)
    return total


def evaluable(traj) -> bool:
    """Whether :func:`states` covers the Ruckig ``Trajectory`` ``traj``: one section, and no
    degree of freedom with a brake or pre-acceleration phase."""
    profiles = traj.profiles
    return len(profiles) == 1 and all(_extra_phase(p) == 0.0 for p in profiles[0])


def states(traj, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Position, velocity and acceleration of each degree of freedom of the Ruckig ``traj``
    (:func:`evaluable`) at the times ``t`` (shape (n,) [s]; clipped to [0, duration]). Returns
    three arrays of shape (n, dofs) [m, m/s, m/s²]. Raises ValueError for a trajectory
    :func:`evaluable` refuses."""
    if not evaluable(traj):
        raise ValueError("a Ruckig trajectory with several sections or a brake phase: use at_time")
    t = np.clip(np.asarray(t, dtype=float), 0.0, float(traj.duration))
    dofs = traj.profiles[0]
    p = np.empty((t.size, len(dofs)))
    v = np.empty_like(p)
    a = np.empty_like(p)
    for i, prof in enumerate(dofs):
        d = np.asarray(prof.t, dtype=float)
        ends = np.cumsum(d)
        k = np.minimum(np.searchsorted(ends, t, side="right"), d.size - 1)
        tau = t - (ends[k] - d[k])
        jk = np.asarray(prof.j, dtype=float)[k]
        ak = np.asarray(prof.a, dtype=float)[k]
        vk = np.asarray(prof.v, dtype=float)[k]
        pk = np.asarray(prof.p, dtype=float)[k]
        a[:, i] = ak + jk * tau
        v[:, i] = vk + tau * (ak + 0.5 * jk * tau)
        p[:, i] = pk + tau * (vk + tau * (0.5 * ak + jk * tau / 6.0))
    return p, v, a
