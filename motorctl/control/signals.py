"""The signals every controller publishes after each sample, declared once by name and unit.

A law writes them into its :attr:`motorctl.control.base.Controller.signals` block, shape
(N_SIGNALS,) float64; a signal the law does not have (θ̂5/θ̂6 for C1, θ̂ and d̂0 for a PID) is
NaN, never a stale value of another law. The servo loop copies the block into the cycle record
(:mod:`motorctl.loop.records` lays it out per axis) and reads ``e`` for the following-error
check. Symbols are the paper's (Chen, Yao & Wang 2013, eq. 11-19).
"""

from __future__ import annotations

#: what a controller publishes after each sample: name -> unit
CONTROLLER_SIGNALS: dict[str, str] = {
    "v": "V",                  # the law's output before the input inversion
    "e": "m",                  # tracking error y − x_d
    "p": "m/s",                # p = ė + k1 e (eq. 11); PID: the derivative of the error
    "x2": "m/s",               # velocity estimate (backward difference)
    "theta_hat1": "V s^2/m",
    "theta_hat2": "V s/m",
    "theta_hat3": "V",
    "theta_hat4": "V",
    "theta_hat5": "1/V",
    "theta_hat6": "1/V^2",
    "d_hat0": "V",             # fast disturbance compensation (eq. 19)
}
N_SIGNALS = len(CONTROLLER_SIGNALS)
#: the most adapted parameters a law publishes (theta_hat1..theta_hat6)
N_THETA_MAX = 6

#: offsets into the signals block
SIG = {name: j for j, name in enumerate(CONTROLLER_SIGNALS)}
SIG_V, SIG_E, SIG_P, SIG_X2 = SIG["v"], SIG["e"], SIG["p"], SIG["x2"]
SIG_THETA = SIG["theta_hat1"]
SIG_D0 = SIG["d_hat0"]
