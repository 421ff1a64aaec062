"""Library of named physical effect families (issue 5, item 3).

Every family adds columns C(h) to the nominal IDIM regressor, u = Φθ + Cβ (input units, V), with
at most one searched hyper-parameter h (period, Stribeck velocity, change time, delay,
frequency). The force the effect adds to the plant is then F_eff = −A1·Cβ (N), the form of
``motorctl_drivers.sim`` (module docstring there):

==============================  ===================================  ======================
family                          plant force F_eff [N]                columns C (u = Φθ + Cβ)
==============================  ===================================  ======================
cogging                         Σ A_k sin(2πkx/P + φ_k)              sin, cos(2πkx/P), k ≤ K
force_ripple                    F_m Σ r_k sin(2πkx/P + φ_k)          f_u(u)·sin, ·cos(2πkx/P)
stribeck                        −F_s exp(−(ẋ/v_s)²) S_f(ẋ)           exp(−(ẋ/v_s)²) S_f(ẋ)
asymmetric_friction             −(ΔF_c S_f(ẋ) + ΔB ẋ), ẋ > 0 only    S_f(ẋ)·[ẋ>0], ẋ·[ẋ>0]
position_dependent_friction     −c (x − x_ref) S_f(ẋ)                x·S_f(ẋ)
spring                          −k (x − x_0)                         x
payload_change                  Δm ẍ from t_c on (mass step)         ẍ·[t ≥ t_c]
periodic_disturbance            A sin(2πft + φ)                      sin, cos(2πft)
input_delay                     u acts τ later                       target u(t − τ) instead of u
==============================  ===================================  ======================

x_ref, x_0 are absorbed by θ3, θ4 (only the slope/stiffness is identifiable).
"""

from __future__ import annotations

import math

import numpy as np
from scipy.signal import lombscargle

from motorctl.model import s_f

FAMILIES = ("cogging", "force_ripple", "stribeck", "asymmetric_friction", "position_dependent_friction",
            "spring", "payload_change", "input_delay", "periodic_disturbance")
#: Harmonics fitted for position- and time-periodic families.
N_HARMONICS = 2


class Candidate:
    """One family at one value of its searched parameter: full-rate columns and/or delayed input."""

    def __init__(self, family: str, h: float | None, cols: np.ndarray | None, delay: int = 0):
        self.family, self.h, self.cols, self.delay = family, h, cols, delay


# ---------------------------------------------------------------------------- column builders
def _fourier(z: np.ndarray, period: float, k: int, scale=None) -> np.ndarray:
    ph = (2.0 * np.pi / period) * z
    s1, c1 = np.sin(ph), np.cos(ph)
    out = np.empty((len(z), 2 * k))
    s, c = s1, c1
    for j in range(k):
        if j:  # angle addition: sin((j+1)φ), cos((j+1)φ) from sin(jφ), cos(jφ)
            s, c = s * c1 + c * s1, c * c1 - s * s1
        out[:, 2 * j], out[:, 2 * j + 1] = s, c
    if scale is not None:
        out *= scale[:, None]
    return out


def columns(family: str, h, p) -> np.ndarray | None:
    """Full-rate columns (N, k) of ``family`` at hyper-parameter h on prepared data ``p``."""
    x, v, a, u, t = p.x, p.v, p.a, p.u, p.t
    if family == "cogging":
        return _fourier(x, h, N_HARMONICS)
    if family == "force_ripple":
        # ripple multiplies the thrust F_m(u)/A1 = f_u(u) (nominal θ5, θ6 when fitted)
        return _fourier(x, h, N_HARMONICS, scale=getattr(p, "fu", None) if getattr(p, "fu", None) is not None else u)
    if family == "stribeck":
        return (np.exp(-(v / h) ** 2) * s_f(v))[:, None]
    if family == "asymmetric_friction":
        pos = (v > 0).astype(float)
        return np.column_stack([s_f(v) * pos, v * pos])
    if family == "position_dependent_friction":
        return (x * s_f(v))[:, None]
    if family == "spring":
        return x[:, None]
    if family == "payload_change":
        return (a * (t >= h))[:, None]
    if family == "periodic_disturbance":
        return _fourier(t, 1.0 / h, 1)
    if family == "input_delay":
        return None
    raise ValueError(f"unknown effect family {family!r}; families: {', '.join(FAMILIES)}")


def columns_fast(family: str, h, p) -> np.ndarray | None:
    """The columns of :func:`columns` evaluated on the *decimated* signals (M, k): a cheap
    approximation for the grid searches (the exact columns are filtered at full rate)."""
    from types import SimpleNamespace
    q = SimpleNamespace(x=p.x_d, v=p.v_d, a=p.a_d, u=p.u_d, t=p.t_d)
    return columns(family, h, q)


def delayed(u: np.ndarray, d: int) -> np.ndarray:
    """u(t − d·Ts), shape (N,), first d samples held at u[0]."""
    if d <= 0:
        return u
    return np.concatenate([np.full(d, u[0]), u[:-d]])


# ---------------------------------------------------------------------------- search grids
def spatial_periodogram(x: np.ndarray, r: np.ndarray, periods: np.ndarray) -> np.ndarray:
    """Least-squares (Lomb-Scargle) periodogram of r against position x (uneven abscissa).

    Args:
        x [m], r: shape (M,), samples with the axis moving. periods [m]: shape (K,).
    Returns:
        Normalised power (K,) (:func:`scipy.signal.lombscargle`, angular frequencies 2π/P).
    """
    return lombscargle(x, r - r.mean(), 2.0 * np.pi / periods, normalize=True)


def peak_periods(x, r, periods, n_peaks=3) -> list:
    """The ``n_peaks`` highest local maxima of the spatial periodogram, as periods [m]."""
    pw = spatial_periodogram(x, r, periods)
    loc = np.flatnonzero((pw[1:-1] > pw[:-2]) & (pw[1:-1] >= pw[2:])) + 1
    loc = loc[np.argsort(pw[loc])[::-1]][:n_peaks]
    return [float(periods[i]) for i in loc]


def period_grid(stroke: float) -> np.ndarray:
    """Plausible cogging / ripple periods [m]: 1 mm .. min(0.1 m, stroke/3), 0.2 % steps."""
    hi = min(0.1, stroke / 3.0)
    lo = 1e-3
    if hi <= lo * 1.5:
        return np.array([])
    return np.exp(np.arange(math.log(lo), math.log(hi), 0.002))


def refine(center: float, rel: float, n: int) -> np.ndarray:
    """n values from center·(1 − rel) to center·(1 + rel)."""
    return center * (1.0 + np.linspace(-rel, rel, n))


# ---------------------------------------------------------------------------- physical read-out
def parameters(family: str, h, beta: np.ndarray, gain: float | None, fs: float) -> dict:
    """Physical parameters of a fitted candidate, names ending in their unit.

    Forces are in N when the gain A1 [N/V] is known, otherwise in V (force / A1).
    """
    g = gain if gain else 1.0
    fu = "N" if gain else "V"
    out: dict = {}
    if family in ("cogging", "force_ripple", "periodic_disturbance"):
        s, c = beta[0::2], beta[1::2]
        # F_eff = −A1 (s sin + c cos) = A sin(· + φ) with A = A1·|(s, c)|, φ = atan2(−c, −s)
        amp = g * np.hypot(s, c)
        ph = np.arctan2(-c, -s)
        if family == "periodic_disturbance":
            out["frequency_Hz"] = float(h)
            out[f"amplitude_{fu}"] = float(amp[0])
            out["phase_rad"] = float(ph[0])
        elif family == "cogging":
            out["period_m"] = float(h)
            out[f"amplitudes_{fu}"] = [float(a) for a in amp]
            out["phases_rad"] = [float(p) for p in ph]
        else:
            out["period_m"] = float(h)
            out["fractions"] = [float(a) for a in np.hypot(s, c)]
            out["phases_rad"] = [float(p) for p in ph]
    elif family == "stribeck":
        out["stribeck_velocity_m_per_s"] = float(h)
        out[f"force_{fu}"] = float(g * beta[0])
    elif family == "asymmetric_friction":
        out[f"coulomb_{fu}"] = float(g * beta[0])
        out[f"viscous_{fu}_s_per_m"] = float(g * beta[1])
    elif family == "position_dependent_friction":
        out[f"coulomb_slope_{fu}_per_m"] = float(g * beta[0])
    elif family == "spring":
        out[f"stiffness_{fu}_per_m"] = float(g * beta[0])
    elif family == "payload_change":
        out["t_change_s"] = float(h)
        out["mass_kg" if gain else "theta1_step_V_s2_per_m"] = float(g * beta[0])
    elif family == "input_delay":
        out["delay_samples"] = float(h)
        out["delay_s"] = float(h) / fs
    return out


def compensation(family: str, h, beta: np.ndarray) -> dict | None:
    """The ``controller.compensation`` YAML entry for a found effect (V units), or None when the
    family cannot be compensated by a term d̂_eff(x_d, ẋ_d, t) (force ripple needs u, a payload
    change or an input delay are not additive forces)."""
    # d_eff = −Cβ (see the module docstring)
    if family == "cogging":
        return {"cogging": {"period_m": float(h), "sin_V": [float(-b) for b in beta[0::2]],
                            "cos_V": [float(-b) for b in beta[1::2]]}}
    if family == "periodic_disturbance":
        return {"periodic_disturbance": {"frequency_Hz": float(h), "sin_V": [float(-beta[0])],
                                         "cos_V": [float(-beta[1])]}}
    if family == "spring":
        return {"spring": {"stiffness_V_per_m": float(beta[0]), "rest_position_m": 0.0}}
    if family == "stribeck":
        return {"stribeck": {"force_V": float(beta[0]), "velocity_m_per_s": float(h)}}
    if family == "asymmetric_friction":
        return {"asymmetric_friction": {"coulomb_V": float(beta[0]), "viscous_V_s_per_m": float(beta[1])}}
    if family == "position_dependent_friction":
        return {"position_dependent_friction": {"coulomb_slope_V_per_m": float(beta[0]), "reference_m": 0.0}}
    return None
