"""Synthetic logs for tests, benchmark and the closed-loop check: the simulated gantry with one
effect the controller's config does not declare (issue 5, "What it must show").

The configs come from ``configs/gantry.yaml`` (one axis, virtual clock). Effect parameters are
in the simulator's YAML form (``motorctl_drivers.sim``, ``axes.NAME.driver.effects``).
"""

from __future__ import annotations

import copy
from pathlib import Path

from motorctl.config import config_from_dict, load_yaml

GANTRY = Path(__file__).resolve().parents[2] / "configs" / "gantry.yaml"

#: One example per family (X axis of the gantry: M = 12.8 kg, A1 = 80 N/V, stroke 0.4 m).
EXAMPLES = {
    "cogging": {"cogging": {"amplitudes_N": [12.0, 4.0], "period_m": 0.032, "phases_rad": [0.3, 1.0]}},
    "force_ripple": {"force_ripple": {"fractions": [0.06], "period_m": 0.045, "phases_rad": [0.5]}},
    "stribeck": {"stribeck": {"force_N": 20.0, "velocity_m_per_s": 0.05}},
    "asymmetric_friction": {"asymmetric_friction": {"coulomb_N": 10.0, "viscous_N_s_per_m": 20.0}},
    "position_dependent_friction": {"position_dependent_friction": {"coulomb_slope_N_per_m": 40.0,
                                                                    "reference_m": 0.2}},
    "spring": {"spring": {"stiffness_N_per_m": 100.0, "rest_position_m": 0.1}},
    "payload_change": {"payload_change": {"t_change_s": 4.65, "mass_kg": 2.0}},
    "periodic_disturbance": {"periodic_disturbance": {"amplitude_N": 6.0, "frequency_Hz": 7.3,
                                                      "phase_rad": 0.4}},
    "input_delay": {"input_delay_s": 0.0006},
}


def gantry_dict(axis: str = "X", effect: dict | None = None, seed: int = 1, noise_N: float = 1.0,
                compensation: dict | None = None) -> dict:
    """Config dict of one gantry axis with ``effect`` on the plant (undeclared to the controller).

    Args:
        axis: 'X' or 'Y'. effect: {"cogging": {...}} (an entry of ``effects:``) or
            {"input_delay_s": τ}. seed: driver seed. noise_N: plant force noise std [N].
        compensation: the controller's ``compensation`` dict (None: none).
    """
    d = copy.deepcopy(load_yaml(str(GANTRY)))
    d["axes"] = {axis: d["axes"][axis]}
    d["loop"]["clock"] = "virtual"
    d["loop"]["realtime"]["policy"] = "off"
    d["driver"]["seed"] = int(seed)
    drv = d["axes"][axis]["driver"]
    drv["force_noise_N"] = float(noise_N)
    # an undeclared effect can raise the tracking error well above the production limits:
    # widen the following-error window so the supervisor does not cut the record short
    lim = d["axes"][axis]["limits"]
    lim["following_error_m"] = max(lim["following_error_m"], 0.01)
    lim["min_following_error_m"] = max(lim["min_following_error_m"], 0.005)
    for k, v in (effect or {}).items():
        if k == "input_delay_s":
            drv["input_delay_s"] = v
        else:
            drv.setdefault("effects", {})[k] = copy.deepcopy(v)
    if compensation:
        d["axes"][axis]["controller"]["compensation"] = copy.deepcopy(compensation)
    return d


def make_log(path: str, effect: dict | None = None, duration_s: float = 8.0, seed: int = 1,
             axis: str = "X", noise_N: float = 1.0, compensation: dict | None = None):
    """Run the simulated axis (C2, virtual clock) and write the run log to ``path``.

    Returns:
        The :class:`motorctl.app.job.JobResult`.
    """
    from motorctl.app.job import run_job
    loaded = config_from_dict(gantry_dict(axis, effect, seed, noise_N, compensation), f"<synthetic {axis}>")
    return run_job(loaded, duration_s=duration_s, clock="virtual", log_path=str(path))
