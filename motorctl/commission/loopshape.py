"""Frequency-domain commissioning tools: the physical plant model's discrete frequency response,
each controller's linearisation C(e^{jωTs}) and the margins of a loop L = C·G.

Conventions (the servo loop's row k holds y[k], read before u[k] is computed and held over the
next period): G(z) maps u to y through the zero-order hold, G_zoh(z) = (1 − z⁻¹) Z{G(s)/s}
(so it carries the one-period delay of the read → write order); C(z) maps −y to u, so the loop
gain is L = C G and the sensitivity S = 1/(1 + L).

Each law gives its own linearisation (:meth:`motorctl.control.base.Controller.linearise`:
PID in motorctl/control/pid.py, C1/C2 in motorctl/control/dcdiarc.py); :func:`c_frf` looks it
up by name.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

#: the physical model's parameters, in order (SI; θ1 = M/A1 and θ2 = B/A1 as in paper eq. 4)
MODEL_KEYS = ("theta1", "theta2", "load_fraction", "mode_hz", "mode_damping", "current_loop_hz",
              "delay_s")


def plant_model_frf(p: dict, ts: float, w: np.ndarray, n_alias: int = 12) -> np.ndarray:
    """Discrete FRF G_zoh(e^{jωTs}) [m/V] of the physical model ``p`` (:data:`MODEL_KEYS`).

    The continuous model is the collocated two-mass axis of ``motorctl_drivers/sim.py`` scaled
    by the force constant: carriage (1 − f)θ1 and load f θ1 [V s²/m] coupled by a spring and
    damper with free-free mode ``mode_hz`` (damping ``mode_damping``; ``mode_hz`` = 0: rigid),
    viscous θ2 [V s/m] on the carriage, a first-order current loop of bandwidth
    ``current_loop_hz`` (0: none) and a transport delay ``delay_s``; sampled under the ZOH with
    ``n_alias`` aliases each side.

    Args:
        p: parameters (:data:`MODEL_KEYS`). ts: period [s]. w: frequencies [rad/s], shape (K,),
            0 < w < π/ts.
    Returns:
        complex (K,).
    """
    th1, th2 = p["theta1"], p["theta2"]
    ws = 2.0 * math.pi / ts
    tau_i = 1.0 / (2.0 * math.pi * p["current_loop_hz"]) if p["current_loop_hz"] > 0 else 0.0
    a = np.arange(-n_alias, n_alias + 1)[:, None]
    s = 1j * (w[None, :] + a * ws)
    if p["mode_hz"] > 0.0:
        f = p["load_fraction"]
        mc, ml = (1.0 - f) * th1, f * th1
        mu = mc * ml / th1
        wm = 2.0 * math.pi * p["mode_hz"]
        k, c = wm * wm * mu, 2.0 * p["mode_damping"] * wm * mu
        load = ml * s * s + c * s + k
        g = load / ((mc * s * s + th2 * s) * load + (c * s + k) * ml * s * s)
    else:
        g = 1.0 / (th1 * s * s + th2 * s)
    g = g * np.exp(-s * p["delay_s"]) / (1.0 + s * tau_i)
    acc = np.sum(g / (s * ts), axis=0)
    return acc * (1.0 - np.exp(-1j * w * ts))


def c_frf(law: str, g: dict, ts: float, w: np.ndarray, theta_hat=None, u0: float = 0.0) -> np.ndarray:
    """C(e^{jωTs}) (K,) of controller ``law`` with gains ``g`` at w (K,) [rad/s], linearised at
    u0 [V] with θ̂ (6,) where the law needs them. Raises KeyError for an unknown law,
    NotImplementedError for a law without a linearisation."""
    from motorctl.control import controller_class

    return controller_class(law).linearise(g, ts, w, theta_hat, u0)


@dataclass(frozen=True)
class Margins:
    """Stability margins of a loop L = C G sampled on an increasing frequency grid.

    Attributes:
        gm_db: gain margin [dB] (least over the −180° crossings with |L| < 1; inf: none).
        gm_hz: where it is taken [Hz] (nan: none).
        pm_deg: phase margin [deg] (least over the |L| = 1 crossings; inf: none).
        wc_hz: the first (lowest) |L| = 1 crossing [Hz]: the loop's bandwidth (a resonance
            that lifts |L| above 1 again further up does not count as bandwidth; nan: none).
        ms_db: peak sensitivity max |1/(1 + L)| [dB]; ms_hz where it peaks [Hz].
    """

    gm_db: float
    gm_hz: float
    pm_deg: float
    wc_hz: float
    ms_db: float
    ms_hz: float

    def meets(self, gm_min_db: float, pm_min_deg: float, ms_max_db: float) -> bool:
        return self.gm_db >= gm_min_db and self.pm_deg >= pm_min_deg and self.ms_db <= ms_max_db


def loop_margins(L: np.ndarray, f_hz: np.ndarray) -> Margins:
    """:class:`Margins` of the loop FRF ``L`` (K,) at frequencies ``f_hz`` (K,), increasing.
    Crossings are located between grid points by linear interpolation."""
    mag = np.abs(L)
    gm, gm_hz = math.inf, math.nan
    # −180° crossings: the imaginary part changes sign where the real part is negative
    for i in np.flatnonzero((np.sign(L.imag[:-1]) != np.sign(L.imag[1:])) & (L.real[:-1] < 0)):
        a = L.imag[i] / (L.imag[i] - L.imag[i + 1])
        m = mag[i] + a * (mag[i + 1] - mag[i])
        if m < 1.0 and -20.0 * math.log10(m) < gm:
            gm, gm_hz = -20.0 * math.log10(m), f_hz[i] + a * (f_hz[i + 1] - f_hz[i])
    # phase unwrapped along the grid, starting in (−360°, 0]: a crossing beyond −180° (a delay
    # or a lag past the mode) counts as a negative margin, not as its wrapped image
    ph = np.degrees(np.unwrap(np.angle(L)))
    ph -= 360.0 * math.ceil(ph[0] / 360.0)
    pm, wc = math.inf, math.nan
    ldb = np.log(mag)
    for i in np.flatnonzero(np.sign(ldb[:-1]) != np.sign(ldb[1:])):
        a = ldb[i] / (ldb[i] - ldb[i + 1])
        pm = min(pm, 180.0 + ph[i] + a * (ph[i + 1] - ph[i]))
        if math.isnan(wc):
            wc = f_hz[i] + a * (f_hz[i + 1] - f_hz[i])
    sens = 1.0 / np.abs(1.0 + L)
    j = int(np.argmax(sens))
    return Margins(gm, gm_hz, pm, wc, 20.0 * math.log10(sens[j]), float(f_hz[j]))
