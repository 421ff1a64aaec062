"""motorctl.motion.ruckig_profile: a Ruckig trajectory's states from its profiles, all samples at
once, equal to Ruckig's own ``at_time`` sample by sample (the per-call loop it replaces in
``RuckigTrajectory.sample_into``)."""

from __future__ import annotations

import numpy as np
import pytest

from motorctl.motion import planner as P
from motorctl.motion import ruckig_profile

#: configs/gantry.yaml's X and Y limits: v_max [m/s], a_max [m/s²], j_max [m/s³]
LIMITS = [P.AxisLimits(2.0, 40.0, 4000.0), P.AxisLimits(1.0, 10.0, 1000.0)]


def at_time_loop(traj, t0: float, dt: float, n: int) -> np.ndarray:
    """The samples by Ruckig's at_time, one call each (before 0: the start; after the end: the end)."""
    out = np.empty((n, 3, len(traj.axes)))
    for k in range(n):
        t = t0 + k * dt
        if t >= traj.duration:
            out[k, 0], out[k, 1:3] = traj.end, 0.0
            continue
        p, v, a = traj._t.at_time(max(t, 0.0))
        if traj._u is None:
            out[k] = p, v, a
        else:
            out[k] = traj.start + p[0] * traj._u, v[0] * traj._u, a[0] * traj._u
    return out


@pytest.mark.parametrize("case", range(12))
def test_the_profiles_give_what_at_time_gives(case):
    rng = np.random.default_rng(case)                  # derandomized: one seed a case
    start, goal = rng.uniform(0.0, 0.4, 2), rng.uniform(0.0, 0.4, 2)
    feed = (None, 0.02, 0.2, 1.0)[case % 4]
    moving = {}
    if case % 3 == 0:                                  # a new target in mid-move: all axes synchronised
        moving = {"velocity": rng.uniform(-0.3, 0.3, 2), "acceleration": rng.uniform(-3.0, 3.0, 2)}
    traj = P.point_to_point(start, goal, LIMITS, feed=feed, axes=["X", "Y"], **moving)
    n = min(int(traj.duration / 2e-4) + 20, 20000)
    got = np.empty((n, 3, 2))
    traj.sample_into(-0.001, 2e-4, got)
    if not moving:                                     # from rest: the profiles' way, always
        assert ruckig_profile.evaluable(traj._t)
    np.testing.assert_allclose(got, at_time_loop(traj, -0.001, 2e-4, n), rtol=1e-9, atol=1e-12)


def test_a_trajectory_it_cannot_evaluate_is_refused():
    class Brake:
        duration = 0.01

    class Profile:
        brake, accel = Brake(), None

    class Traj:
        profiles = [[Profile()]]
        duration = 1.0

    assert not ruckig_profile.evaluable(Traj())
    with pytest.raises(ValueError, match="at_time"):
        ruckig_profile.states(Traj(), np.zeros(3))
