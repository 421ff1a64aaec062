"""C1, C2 and PID+FF against a second, plain implementation (docs/control-law.md, Checked
against a second implementation).

The reference below is written from the paper (Chen, Yao & Wang 2013, equation numbers in the
comments; /work/shared/spec/paper-spec.md for the reconstructed ones) and from LinuxCNC's pid
component, in numpy and plain Python: no numba and nothing of motorctl's law code for the
arithmetic. Where the paper leaves a choice to the implementation it follows the project's
documented choice (docs/control-law.md, Discrete-time implementation) but computes it another
way:

* H_f's exact ZOH in closed form (the double pole), not by a matrix exponential;
* the freeze of eq. (27) by an eigenvalue, not by a Cholesky factorisation;
* the Γ-weighted projection of eq. (7)-(8) on the box as the projection onto the tangent cone
  in the Γ⁻¹ metric (the rule that is eq. (8) on a single face and keeps P1, P2 at edges and
  corners), found by trying every set of closed faces, not by an active-set iteration;
* the input inversion of eq. (9) by bisection, not by Newton or a closed-form root.

What is compared is the compiled step the servo loop runs (``dcdiarc_block_step``, ``pid_step``)
called through the public :class:`motorctl.control.base.Controller` interface, ``update``: a
controller is built from a ``controller:`` section (so the config -> law mapping is checked as
well), its state is set (θ̂, Γ, the H_f states through their live arrays; y[k−1], u[k−1], d̂0
through the law's state vector, the only thing imported from the law's module besides the
class), one sample is run and every output of the sample (u, v, e, p, x2, d̂0, θ̂, Γ, ε, the
freeze, k_s) is compared with the reference's. The states and parameter sets are drawn by
hypothesis (derandomized: tests/conftest.py) and by branch: parameters on the faces, edges and
corners of the box with a diagonal and a coupled Γ, the freeze of Γ, d̂0 at its bound, θ̂5 =
θ̂6 = 0, θ̂6 = 0 ≠ θ̂5, the saturated inversion, theory mode. A closed-loop run on a simulated
plant checks every sample of a realistic state sequence against the reference from the law's
state before it.

Tolerance (RTOL): a quantity may differ from the reference by RTOL = 1e-9 times the sum of the
magnitudes of the terms that make it up (a floating-point error bound, not a pinned value). The
two compute the same formulas in another order and by other algorithms (a closed form against
expm, an eigenvalue against a Cholesky test, subset enumeration against elimination, bisection
against Newton), each exact to a few ulp times the condition of what it solves: over 800 draws
they differed by at most 5e-14 of that sum (Γ's update), so RTOL leaves four orders of margin
for worse-conditioned Γ blocks, while a wrong sign or gain in any term moves the result by a
sizable fraction of that term, many orders beyond it.

Mutation check (docs/control-law.md): ``.venv/bin/python tests/test_law_reference.py --mutants``
runs this file against copies of the law with one term made wrong at a time (:data:`MUTANTS`)
and reports which the file catches.
"""

from __future__ import annotations

import math
import os
import shutil
import subprocess
import sys
import tempfile
from itertools import combinations
from pathlib import Path

import numpy as np
import pytest
from conftest import examples
from hypothesis import given, settings
from hypothesis import strategies as st

from motorctl.control.dcdiarc import DCDIARC
from motorctl.control.dcdiarc import S_D0, S_U, S_Y_PREV  # the law's state layout (to set a state), no arithmetic
from motorctl.control.params import ControllerConfig
from motorctl.control.pid import PID
from motorctl.control.signals import SIG

TS = 2e-4                    # the paper's sample period, 0.2 ms
RTOL = 1e-9                  # see the module docstring
G_MAX = 1800.0 / math.pi     # bound of S_f's slope, g in eq. (12)-(16)
# the X axis of the paper (Section VI, spec §6-7): the base the draws vary around
X_MIN = np.array([0.05, 0.08, 0.05, -0.5, -0.015, -0.002])
X_MAX = np.array([0.3, 0.5, 0.5, 0.5, 0.0, 0.0])
X_GAMMA0 = np.array([2.0, 50.0, 100.0, 500.0, 0.05, 0.005])


# ---------------------------------------------------------------------------------------------
# the reference: one sample of C1 / C2, written from the paper
# ---------------------------------------------------------------------------------------------

def s_f(x: float) -> float:
    """Friction shape S_f(x) = (2/π) arctan(900 x) (paper, after eq. 4)."""
    return 2.0 / math.pi * math.atan(900.0 * x)


def hf_zoh(omega: float, ts: float):
    """H_f(s) = ω²/(s + ω)² with states (x_f, ẋ_f), discretised exactly under a ZOH (spec §5.3).
    A = [[0, 1], [−ω², −2ω]] has the double eigenvalue −ω, so e^{AT} = e^{−ωT}(I + (A + ωI)T)
    and B_d = ∫e^{Aτ}B dτ = [1 − e^{−ωT}(1 + ωT), ω²T e^{−ωT}] (the step response and its slope)."""
    e = math.exp(-omega * ts)
    a = np.array([[e * (1.0 + omega * ts), e * ts], [-omega * omega * ts * e, e * (1.0 - omega * ts)]])
    b = np.array([1.0 - e * (1.0 + omega * ts), omega * omega * ts * e])
    return a, b


def tangent_cone_projection(zeta, th, tmin, tmax, gam):
    """Proj_θ̂(ζ) of eq. (7)-(8) on the box Ω_θ (eq. 5) for an SPD Γ.

    Eq. (8) on one face, outward normal n: ζ − Γn nᵀζ/(nᵀΓn) when nᵀζ > 0, else ζ. On a box the
    normals are ±e_i, and at an edge or corner the projection that keeps P1 and P2 is the
    closest point to ζ, in the Γ⁻¹ metric, of the tangent cone {z: z_i ≤ 0 on an upper face,
    z_i ≥ 0 on a lower one}: z = ζ − Γ[:, A] λ with λ = Γ[A, A]⁻¹ ζ[A] for its set A of closed
    faces (on one face, eq. 8). Found by trying every A among the faces θ̂ is on (at most 2⁶):
    the feasible candidate of least distance λᵀΓ[A, A]λ.

    Returns (z, A, λ) with A a tuple of indices."""
    n = len(th)
    on = [i for i in range(n) if th[i] >= tmax[i] or th[i] <= tmin[i]]
    up = {i: th[i] >= tmax[i] for i in on}
    tol = 1e-12 * (1.0 + float(np.abs(zeta).max()))
    best = None
    for size in range(len(on) + 1):
        for a in combinations(on, size):
            if a:
                ia = list(a)
                lam = np.linalg.solve(gam[np.ix_(ia, ia)], zeta[ia])
                z = zeta - gam[:, ia] @ lam
                z[ia] = 0.0
                dist = float(lam @ gam[np.ix_(ia, ia)] @ lam)
            else:
                lam = np.zeros(0)
                z = zeta.copy()
                dist = 0.0
            if all((z[i] <= tol) if up[i] else (z[i] >= -tol) for i in on):
                if best is None or dist < best[3] * (1.0 - 1e-12) - 1e-300:
                    best = (z, a, lam, dist)
    return best[0], best[1], best[2]


def add_only_projection(zeta, th, tmin, tmax, gam):
    """The add-only rule of docs/control-law.md, Box projection (spec §2.2): close every face on
    which the step points outward, repeat, never open one. Used only to tell apart the corner
    cases where it and the tangent-cone projection differ (a branch the tests must visit)."""
    n = len(th)
    act: list[int] = []
    z = zeta.copy()
    for _ in range(n):
        new = [i for i in range(n) if i not in act and
               ((th[i] >= tmax[i] and z[i] > 0.0) or (th[i] <= tmin[i] and z[i] < 0.0))]
        if not new:
            break
        act += new
        z = zeta - gam[:, act] @ np.linalg.solve(gam[np.ix_(act, act)], zeta[act])
        z[act] = 0.0
    return z


def f_u(u: float, t5: float, t6: float) -> float:
    """v = u + θ5 u|u| + θ6 u³ (eq. 9)."""
    return u + t5 * u * abs(u) + t6 * u ** 3


def invert(v: float, t5: float, t6: float, u_m: float) -> tuple[float, str]:
    """u with f_u(u) = v, |u| ≤ u_M (eq. 9): f_u is odd and strictly increasing on |u| ≤ u_M
    (Assumption 2), so sign(u) = sign(v) and |u| is the one root on [0, u_M] of
    r + θ5 r² + θ6 r³ = |v|, found by bisection; |v| ≥ f_u(u_M) (beyond the actuator): |u| = u_M.
    Returns (u, the case of spec §3.4 it falls in)."""
    s = 1.0 if v >= 0.0 else -1.0
    w = abs(v)
    case = "linear" if t5 == 0.0 and t6 == 0.0 else ("quadratic" if t6 == 0.0 else "cubic")
    if w >= f_u(u_m, t5, t6):
        return s * u_m, "saturated"
    lo, hi = 0.0, u_m
    while True:
        mid = 0.5 * (lo + hi)
        if mid <= lo or mid >= hi:
            break
        if f_u(mid, t5, t6) < w:
            lo = mid
        else:
            hi = mid
    return s * 0.5 * (lo + hi), case


def theory_ks1(tmin, tmax, k1: float, k2: float) -> float:
    """Smallest k_s1 making the matrix of eq. (14)-(15) PSD over Ω_θ and 0 ≤ g ≤ 1800/π:
    k_s1 ≥ k2 + θ1 k1 − θ2 − θ3 g + (θ2 + θ3 g)²/(2 θ1 k1) (spec §3.3). The right side is convex
    in θ1 (θ1 k1 + c/θ1), in (θ2, θ3) and in g, so its maximum is at a corner and at g = 0 or
    g = 1800/π."""
    worst = -math.inf
    for t1 in (tmin[0], tmax[0]):
        for t2 in (tmin[1], tmax[1]):
            for t3 in (tmin[2], tmax[2]):
                for g in (0.0, G_MAX):
                    worst = max(worst, k2 + t1 * k1 - t2 - t3 * g + (t2 + t3 * g) ** 2 / (2.0 * t1 * k1))
    return worst


def reference_step(prm: dict, state: dict, y: float, xd: float, vd: float, ad: float, freeze=None) -> dict:
    """One sample k of C1 (n = 4) or C2 (n = 6) in the order of docs/control-law.md (spec §5.2).

    prm: the law's settings (kind, k1, k_s, gamma_d, d_hat_max, u_lim, omega_f, mu, nu, rho_M,
    mode, k2, eta, delta_d, k_s1, tmin, tmax). state (before the sample): y_prev, u_prev [V],
    d0, theta (n,), gamma (n, n), zf, zd (n,) the H_f states of the channels (x2, S_f(x2), 1, u,
    u|u|, u³) (C1: the first four). freeze: None (decide by eq. 27) or True/False (forced: for a
    sample whose λ_max is within rounding of ρ_M). Returns the outputs and what was hit."""
    n = 6 if prm["kind"] == "c2" else 4
    tmin, tmax = prm["tmin"][:n], prm["tmax"][:n]
    th = state["theta"].astype(float).copy()
    gam = state["gamma"].astype(float).copy()
    out: dict = {}

    # 1. the velocity: backward difference of two readings (spec §5.1)
    x2 = (y - state["y_prev"]) / TS

    # 2. the estimator with time-aligned inputs: the pair (x2[k], u[k−1]) of the interval just ended
    up = state["u_prev"]
    inp = np.array([x2, s_f(x2), 1.0, up, up * abs(up), up ** 3])[:n]
    a, b = hf_zoh(prm["omega_f"], TS)
    zf = a[0, 0] * state["zf"] + a[0, 1] * state["zd"] + b[0] * inp
    zd = a[1, 0] * state["zf"] + a[1, 1] * state["zd"] + b[1] * inp
    out["zf_scale"] = np.abs(a[0, 0] * state["zf"]) + np.abs(a[0, 1] * state["zd"]) + np.abs(b[0] * inp)
    out["zd_scale"] = np.abs(a[1, 0] * state["zf"]) + np.abs(a[1, 1] * state["zd"]) + np.abs(b[1] * inp)
    # eq. (25): u_f = −φ_fᵀθ, φ_f = [−ẋ2f, −x2f, −S_ff, 1_f, (u|u|)_f, (u³)_f]
    phi = np.array([-zd[0], -zf[0], -zf[1], zf[2]] + ([zf[4], zf[5]] if n == 6 else []))
    u_f = zf[3]
    eps = float(-phi @ th - u_f)                               # eq. (26): ε = û_f − u_f
    out["eps_scale"] = float(np.abs(phi * th).sum() + abs(u_f))
    # eq. (27), information form with forgetting μ and normalisation ν (spec §5.4)
    quad = float(phi @ gam @ phi)
    nk = 1.0 + prm["nu"] * quad
    gp = gam / (1.0 - prm["mu"] * TS)                          # Γ' = Γ/(1 − μTs)
    gpp = gp @ np.outer(phi, phi) @ gp
    den = 1.0 + TS / nk * float(phi @ gp @ phi)
    g_new = gp - TS / nk * gpp / den
    g_new = 0.5 * (g_new + g_new.T)
    lmax = float(np.linalg.eigvalsh(g_new).max())
    out["freeze_ambiguous"] = abs(lmax - prm["rho_M"]) <= 1e-9 * prm["rho_M"]
    frozen = lmax > prm["rho_M"] if freeze is None else freeze   # "0 otherwise": Γ kept
    if frozen:
        g_new = gam
        out["gamma_scale"] = np.abs(gam)
    else:
        out["gamma_scale"] = np.abs(gp) + TS / nk * np.abs(gpp) / den
    tau = phi * eps / nk                                       # eq. (28)
    zeta = g_new @ tau
    z, closed, lam = tangent_cone_projection(zeta, th, tmin, tmax, g_new)   # eq. (7)-(8)
    out["kkt_differs"] = bool(np.abs(z - add_only_projection(zeta, th, tmin, tmax, g_new)).max()
                              > 1e-6 * (1.0 + np.abs(zeta).max()))
    corr = np.abs(g_new[:, list(closed)]) @ np.abs(lam) if closed else np.zeros(n)
    out["theta_scale"] = np.abs(th) + TS * (np.abs(zeta) + corr)
    th = np.clip(th + TS * z, tmin, tmax)                      # the clip: overshoot within one step

    # 3. errors (eq. 11): e = x1 − x_d, p = ė + k1 e
    e = y - xd
    p = (x2 - vd) + prm["k1"] * e

    # 4. fast dynamic compensation (eq. 18-19), projected onto |d̂0| ≤ d̂_max
    d0_raw = state["d0"] + TS * prm["gamma_d"] * p
    d0 = min(max(d0_raw, -prm["d_hat_max"]), prm["d_hat_max"])
    out["d0_clipped"] = d0 != d0_raw
    out["d0_scale"] = abs(state["d0"]) + TS * prm["gamma_d"] * abs(p)

    # 5. v = v_a1 + v_a2 + v_s (eq. 13, 18, 22): model compensation on the DESIRED trajectory
    sfd = s_f(vd)
    va1 = th[0] * ad + th[1] * vd + th[2] * sfd - th[3]
    if prm["mode"] == "theory":
        # v_s = −(k_s1 + k_s2) p, k_s2 = (d̂_max + Σ θ_Mi |φ_di| + δ_d)²/(4η) (eq. 22), the
        # componentwise bound; φ_d = [−ẍ_d, −ẋ_d, −S_f(ẋ_d), 1, u|u|, u³] with the last u
        span = tmax - tmin
        phid = np.array([-ad, -vd, -sfd, 1.0, up * abs(up), up ** 3])[:n]
        h = prm["d_hat_max"] + float(span @ np.abs(phid)) + prm["delta_d"]
        ks1 = prm["k_s1"] if prm["k_s1"] is not None else theory_ks1(tmin, tmax, prm["k1"], prm["k2"])
        ks = ks1 + h * h / (4.0 * prm["eta"])
    else:
        ks = prm["k_s"]                                        # experiment mode: v_s = −k_s p
    v = va1 - d0 - ks * p
    ts_ = out["theta_scale"]
    v_scale = (ts_[0] * abs(ad) + ts_[1] * abs(vd) + ts_[2] * abs(sfd) + ts_[3] + abs(d0) + abs(ks * p)
               + out["d0_scale"])

    # 6. u from v: C2 by the inversion of eq. (9), C1 u = v; then the actuator's ±u_lim
    if n == 6:
        u, case = invert(v, th[4], th[5], prm["u_lim"])
        slope = 1.0 + 2.0 * th[4] * abs(u) + 3.0 * th[5] * u * u
        u_scale = (v_scale + ts_[4] * u * u + ts_[5] * abs(u) ** 3) / slope
    else:
        u, case = v, "none"
        u_scale = v_scale
    u_clip = min(max(u, -prm["u_lim"]), prm["u_lim"])
    out["u_clipped"] = u_clip != u
    out.update(u=u_clip, v=v, e=e, p=p, x2=x2, d0=d0, theta=th, gamma=g_new, eps=eps, frozen=frozen,
               ks=ks, zf=zf, zd=zd, closed=closed, inversion=case, v_scale=v_scale, u_scale=u_scale,
               p_scale=abs(x2) + abs(vd) + prm["k1"] * abs(e), e_scale=abs(y) + abs(xd),
               x2_scale=(abs(y) + abs(state["y_prev"])) / TS)
    return out


# ---------------------------------------------------------------------------------------------
# the law under test, through its Controller interface
# ---------------------------------------------------------------------------------------------

def section(prm: dict, theta0=None) -> ControllerConfig:
    """The axis's ``controller:`` section of the settings ``prm``."""
    data = dict(type=prm["kind"], u_lim=prm["u_lim"], theta_min=list(prm["tmin"]), theta_max=list(prm["tmax"]),
                theta_hat0=list(theta0 if theta0 is not None else 0.5 * (prm["tmin"] + prm["tmax"])),
                gamma0=list(prm["gamma0"]), k_s=prm["k_s"], k1=prm["k1"], gamma_d=prm["gamma_d"],
                d_hat_max=prm["d_hat_max"], filter={"omega_f": prm["omega_f"]}, mu=prm["mu"], nu=prm["nu"],
                rho_M=prm["rho_M"], mode=prm["mode"],
                theory={"k2": prm["k2"], "eta": prm["eta"], "delta_d": prm["delta_d"], "k_s1": prm["k_s1"]})
    return ControllerConfig.model_validate(data)


def snapshot(c: DCDIARC, y_prev: float) -> dict:
    """The state of the law before its next sample, read from the controller."""
    est = c.estimator
    return dict(y_prev=y_prev, u_prev=c.u, d0=c.d_hat0, theta=c.theta_hat.copy(),
                gamma=est.gamma.copy(), zf=est.zf.copy(), zd=est.zd.copy())


def law_outputs(c: DCDIARC, u: float) -> dict:
    est = c.estimator
    n = c.n_theta
    sig = c.signals
    return dict(u=u, v=c.v, e=c.e, p=c.p, x2=c.x2, d0=c.d_hat0, theta=c.theta_hat.copy(), gamma=est.gamma.copy(),
                eps=est.epsilon, frozen=est.frozen, ks=c.k_s_eff, zf=est.zf.copy(), zd=est.zd.copy(),
                sig_v=sig[SIG["v"]], sig_d0=sig[SIG["d_hat0"]], sig_p=sig[SIG["p"]],
                sig_theta=sig[SIG["theta_hat1"]:SIG["theta_hat1"] + n].copy())


def run_law(prm: dict, state: dict, y: float, xd: float, vd: float, ad: float, c: DCDIARC | None = None) -> dict:
    """One sample of the project's law from ``state``: a controller built from the section (or
    ``c``, built from it before), reset at y[k−1], its state set, then ``update``."""
    if c is None:
        c = DCDIARC(section(prm), TS, prm["kind"])
    c.reset(state["y_prev"])
    c._st[S_Y_PREV] = state["y_prev"]
    c._st[S_U] = state["u_prev"]
    c._st[S_D0] = state["d0"]
    c.theta_hat[:] = state["theta"]
    c.estimator.gamma[:] = state["gamma"]
    c.estimator.zf[:] = state["zf"]
    c.estimator.zd[:] = state["zd"]
    return law_outputs(c, c.update(y, xd, vd, ad))


def _close(name, got, want, scale, where=""):
    got, want, scale = np.asarray(got, float), np.asarray(want, float), np.asarray(scale, float)
    bad = ~(np.abs(got - want) <= RTOL * scale + 1e-15)
    assert not bad.any(), (f"{name}{where}: law {got!r} vs reference {want!r}, |diff| "
                           f"{np.abs(got - want)!r} > {RTOL:g} x {scale!r}")


def compare(law: dict, ref: dict, where: str = "") -> None:
    """Every output of the sample against the reference, within RTOL of its own scale."""
    _close("x2", law["x2"], ref["x2"], ref["x2_scale"], where)
    _close("e", law["e"], ref["e"], ref["e_scale"], where)
    _close("p (eq. 11)", law["p"], ref["p"], ref["p_scale"], where)
    _close("p signal", law["sig_p"], ref["p"], ref["p_scale"], where)
    _close("H_f states x_f", law["zf"], ref["zf"], ref["zf_scale"], where)
    _close("H_f states dx_f/dt", law["zd"], ref["zd"], ref["zd_scale"], where)
    _close("epsilon (eq. 26)", law["eps"], ref["eps"], ref["eps_scale"], where)
    assert law["frozen"] == ref["frozen"], (f"freeze of Gamma (eq. 27){where}: law {law['frozen']}, "
                                            f"reference {ref['frozen']}")
    _close("Gamma (eq. 27)", law["gamma"], ref["gamma"], ref["gamma_scale"], where)
    _close("theta_hat (eq. 7-8, 28)", law["theta"], ref["theta"], ref["theta_scale"], where)
    _close("theta_hat signals", law["sig_theta"], ref["theta"], ref["theta_scale"], where)
    _close("d_hat0 (eq. 19)", law["d0"], ref["d0"], ref["d0_scale"], where)
    _close("d_hat0 signal", law["sig_d0"], ref["d0"], ref["d0_scale"], where)
    _close("k_s", law["ks"], ref["ks"], abs(ref["ks"]), where)
    _close("v (eq. 13, 18, 22)", law["v"], ref["v"], ref["v_scale"], where)
    _close("v signal", law["sig_v"], ref["v"], ref["v_scale"], where)
    _close("u (eq. 9)", law["u"], ref["u"], ref["u_scale"], where)


def check(prm, state, y, xd, vd, ad, c: DCDIARC | None = None, where: str = "") -> dict:
    """Run the law and the reference on one sample and compare; returns the reference's."""
    law = run_law(prm, state, y, xd, vd, ad, c)
    ref = reference_step(prm, state, y, xd, vd, ad)
    if ref["freeze_ambiguous"] and law["frozen"] != ref["frozen"]:
        ref = reference_step(prm, state, y, xd, vd, ad, freeze=law["frozen"])   # λ_max = ρ_M to rounding
    compare(law, ref, where)
    return ref


# ---------------------------------------------------------------------------------------------
# the draws: a parameter set and a state, by seed and by the branches to aim at
# ---------------------------------------------------------------------------------------------

def assumption2_ok(t5r, t6r, u_m, margin=0.05) -> bool:
    """Assumption 2 with a margin: f_u' = 1 + 2θ5 r + 3θ6 r² ≥ margin for 0 ≤ r ≤ u_M at every
    (θ5, θ6) of the box (affine in (θ5, θ6): the corners; in r: the ends and the vertex)."""
    for t5 in t5r:
        for t6 in t6r:
            rs = [0.0, u_m] + ([-t5 / (3 * t6)] if t6 > 0 > t5 and -t5 / (3 * t6) < u_m else [])
            if min(1 + 2 * t5 * r + 3 * t6 * r * r for r in rs) < margin:
                return False
    return True


def draw_params(rng, kind: str, theory: bool) -> dict:
    """A parameter set: the box Ω_θ (Assumption 2 on θ5, θ6 with a margin), the gains, H_f, the
    LS settings, the mode."""
    u_lim = rng.uniform(3.0, 12.0)
    lo = np.array([rng.uniform(0.03, 0.3), rng.uniform(0.0, 0.2), rng.uniform(0.0, 0.2), rng.uniform(-1.0, -0.01)])
    hi = np.array([lo[0] * rng.uniform(1.5, 6.0), lo[1] + rng.uniform(0.1, 0.8), lo[2] + rng.uniform(0.1, 0.8),
                   rng.uniform(0.01, 1.0)])
    while True:
        a5 = -rng.uniform(0.0, 0.5) / u_lim
        a6 = -rng.uniform(0.0, 0.25) / u_lim ** 2
        b5 = a5 + rng.uniform(0.05, 1.0) * (-a5 + 0.1 / u_lim)
        b6 = a6 + rng.uniform(0.05, 1.0) * (-a6 + 0.02 / u_lim ** 2)
        if assumption2_ok((a5, b5), (a6, b6), u_lim):
            break
    tmin = np.concatenate([lo, [a5, a6]])
    tmax = np.concatenate([hi, [b5, b6]])
    rho = math.exp(rng.uniform(math.log(50.0), math.log(5000.0)))
    return dict(kind=kind, u_lim=u_lim, tmin=tmin, tmax=tmax,
                gamma0=np.minimum(X_GAMMA0 * rng.uniform(0.2, 5.0, 6), rho),      # ‖Γ(0)‖ ≤ ρ_M (eq. 27)
                k1=math.exp(rng.uniform(math.log(20), math.log(2000))),
                k_s=math.exp(rng.uniform(math.log(5), math.log(300))),
                gamma_d=0.0 if rng.random() < 0.05 else math.exp(rng.uniform(math.log(10), math.log(5000))),
                d_hat_max=rng.uniform(0.2, 3.0), omega_f=math.exp(rng.uniform(math.log(50), math.log(800))),
                mu=0.0 if rng.random() < 0.5 else rng.uniform(0.01, 5.0),
                nu=0.0 if rng.random() < 0.5 else math.exp(rng.uniform(math.log(1e-6), math.log(1e-1))),
                rho_M=rho, mode="theory" if theory else "experiment", k2=rng.uniform(1.0, 30.0),
                eta=math.exp(rng.uniform(math.log(0.01), math.log(1.0))), delta_d=rng.uniform(0.0, 0.5),
                k_s1=None if rng.random() < 0.5 else rng.uniform(10.0, 500.0))


def draw_state(rng, prm: dict, bounds: tuple, coupled: bool, freeze: bool, hold56: bool, d0_edge: bool,
               big: bool):
    """A state before the sample and the sample's inputs, for the parameter set ``prm``.

    bounds: per parameter 'in', 'lo' or 'hi' (θ̂ inside, on its lower or upper face); coupled: Γ
    with off-diagonal terms; freeze: λ_max(Γ) at or above ρ_M (eq. 27's freeze likely), else
    below it; hold56: u[k−1] = 0, zero (u|u|)_f, (u³)_f states and Γ uncoupled on θ5, θ6, so that
    θ̂5, θ̂6 stay exactly as drawn (0 on a face at 0: the inversion's C1-like and quadratic
    cases); d0_edge: d̂0 near its bound; big: large accelerations (the inversion saturates)."""
    n = 6 if prm["kind"] == "c2" else 4
    tmin, tmax = prm["tmin"][:n], prm["tmax"][:n]
    th = rng.uniform(tmin, tmax)
    for i in range(n):
        if bounds[i] == "lo":
            th[i] = tmin[i]
        elif bounds[i] == "hi":
            th[i] = tmax[i]
    if hold56 and n == 6:
        for i in (4, 5):
            # 0 where 0 is a face (θ5, θ6 ≤ 0 physically); else a face or an inner point
            th[i] = 0.0 if (bounds[i] != "in" and tmin[i] <= 0.0 <= tmax[i] and rng.random() < 0.7) else th[i]
    d = X_GAMMA0[:n] * np.exp(rng.uniform(-2.0, 2.0, n))
    if coupled:
        w = rng.normal(size=(n, n + 2))
        s = w @ w.T
        corr = s / np.sqrt(np.outer(np.diag(s), np.diag(s)))
        alpha = rng.uniform(0.3, 0.97)
        corr = (1 - alpha) * np.eye(n) + alpha * corr
        gam = np.sqrt(np.outer(d, d)) * corr
    else:
        gam = np.diag(d)
    if hold56 and n == 6:
        for i in (4, 5):
            gam[i, :] = 0.0
            gam[:, i] = 0.0
            gam[i, i] = d[i]
    lmax = float(np.linalg.eigvalsh(gam).max())
    if freeze:
        gam *= prm["rho_M"] * rng.uniform(0.98, 2.0) / lmax
    elif lmax > 0.8 * prm["rho_M"]:
        gam *= prm["rho_M"] * rng.uniform(0.05, 0.8) / lmax
    u_lim = prm["u_lim"]
    y_prev = rng.uniform(-0.3, 0.3)
    x2 = 0.0 if rng.random() < 0.15 else rng.uniform(-2.5, 2.5)
    y = y_prev + x2 * TS
    if hold56:
        u_prev = 0.0
    else:
        u_prev = [0.0, u_lim, -u_lim, rng.uniform(-u_lim, u_lim), rng.uniform(-u_lim, u_lim)][rng.integers(5)]
    dmax = prm["d_hat_max"]
    d0 = (rng.choice([-1.0, 1.0]) * dmax * rng.uniform(0.97, 1.0)) if d0_edge else rng.uniform(-dmax, dmax)
    om = prm["omega_f"]
    zf = np.array([x2 + rng.normal(0, 0.1), rng.uniform(-1, 1), rng.uniform(0, 1), rng.uniform(-u_lim, u_lim),
                   rng.uniform(-1, 1) * u_lim ** 2, rng.uniform(-1, 1) * u_lim ** 3])
    zd = np.array([rng.normal(0, 30), rng.normal(0, 0.3 * om), rng.uniform(0, 0.37 * om),
                   rng.normal(0, 0.3 * om * u_lim), rng.normal(0, 0.3 * om * u_lim ** 2),
                   rng.normal(0, 0.3 * om * u_lim ** 3)])
    if hold56:
        zf[4:] = 0.0
        zd[4:] = 0.0
    # the inputs at sizes that keep v mostly inside the actuator's range (big: mostly beyond)
    e = rng.normal(0, 2e-5) * (1.0 if rng.random() < 0.7 else 100.0)
    ks = prm["k_s"] if prm["mode"] == "experiment" else 2e3
    p = rng.normal(0, 0.2 * u_lim / ks) * (5.0 if big else 1.0)
    vd = x2 - (p - prm["k1"] * e)                              # ė = p − k1 e
    xd = y - e
    ad = rng.normal(0, 0.3 * u_lim / th[0]) * (4.0 if big else 1.0)
    state = dict(y_prev=y_prev, u_prev=u_prev, d0=d0, theta=th, gamma=gam, zf=zf[:n], zd=zd[:n])
    return state, (y, xd, vd, ad)


def draw_case(kind: str, seed: int, theory: bool = False, **flags):
    """A parameter set and one state (:func:`draw_params`, :func:`draw_state`) from ``seed``."""
    rng = np.random.default_rng(seed)
    prm = draw_params(rng, kind, theory)
    return (prm, *draw_state(rng, prm, **flags))


FACES = st.sampled_from(["in", "in", "lo", "hi"])
STATES_PER_SET = 3


@st.composite
def state_flags(draw, kind):
    n = 6 if kind == "c2" else 4
    return dict(bounds=tuple(draw(FACES) for _ in range(n)), coupled=draw(st.booleans()),
                freeze=draw(st.sampled_from([False, False, True])),
                hold56=kind == "c2" and draw(st.sampled_from([False, False, True])),
                d0_edge=draw(st.sampled_from([False, False, True])), big=draw(st.sampled_from([False, False, True])))


@pytest.mark.parametrize("kind", ["c1", "c2"])
@settings(max_examples=examples(60), deadline=None)
@given(seed=st.integers(0, 2 ** 32 - 1), theory=st.sampled_from([False, False, False, True]), data=st.data())
def test_one_sample_matches_the_reference(kind, seed, theory, data):
    """Random parameter sets (hypothesis), each with STATES_PER_SET random states: u, v, e, p, d̂0,
    θ̂, Γ, ε, the freeze and k_s of one sample of the compiled law agree with the reference. One
    controller per parameter set, built from its section; each state is set after a reset."""
    rng = np.random.default_rng(seed)
    prm = draw_params(rng, kind, theory)
    c = DCDIARC(section(prm), TS, kind)
    for j in range(STATES_PER_SET):
        state, inputs = draw_state(rng, prm, **data.draw(state_flags(kind)))
        check(prm, state, *inputs, c=c, where=f" (state {j})")


# the branches each kind must visit, with the draws that aim at them and the reference's word that
# they were hit; a branch no seed of BRANCH_SEEDS hits fails the test (the draws lost it)
BRANCH_SEEDS = 400
ALL_IN = ("in",) * 6


def _hit(kind, flags, want):
    n = 6 if kind == "c2" else 4
    for seed in range(BRANCH_SEEDS):
        rng = np.random.default_rng(10_000 + seed)
        fl = dict(flags)
        if fl.get("bounds") == "random":
            fl["bounds"] = tuple(rng.choice(["in", "lo", "hi"], n))
        fl.setdefault("bounds", ALL_IN)
        fl["bounds"] = tuple(fl["bounds"])[:n]
        for k in ("coupled", "freeze", "theory", "hold56", "d0_edge", "big"):
            fl.setdefault(k, False)
        prm, state, inputs = draw_case(kind, 10_000 + seed, **fl)
        ref = reference_step(prm, state, *inputs)
        if want(ref, prm, state) and not ref["freeze_ambiguous"]:
            return prm, state, inputs
    raise AssertionError(f"{kind}: no draw of {BRANCH_SEEDS} hits this branch")


BRANCHES = {
    "interior, no face closed": (dict(), lambda r, p, s: not r["closed"] and not r["frozen"]),
    "one upper face closed (eq. 8)": (dict(bounds=("hi",) + ALL_IN[1:]),
                                      lambda r, p, s: r["closed"] == (0,)),
    "one lower face closed, coupled Gamma": (dict(bounds=("in", "lo") + ALL_IN[2:], coupled=True),
                                             lambda r, p, s: r["closed"] == (1,)),
    "on a face, step inward (face stays open)": (dict(bounds=("in", "in", "hi") + ALL_IN[3:]),
                                                 lambda r, p, s: not r["closed"] and s["theta"][2] == p["tmax"][2]
                                                 and r["theta"][2] < p["tmax"][2]),
    "corner, two faces closed": (dict(bounds="random", coupled=True), lambda r, p, s: len(r["closed"]) >= 2),
    "corner where the add-only rule closes a face too many": (dict(bounds="random", coupled=True),
                                                             lambda r, p, s: r["kkt_differs"]),
    "Gamma frozen (lambda_max > rho_M, eq. 27)": (dict(freeze=True), lambda r, p, s: r["frozen"]),
    "Gamma updated with forgetting and normalisation (mu, nu > 0)": (
        dict(), lambda r, p, s: not r["frozen"] and p["mu"] > 0 and p["nu"] > 0),
    "d_hat0 at its bound (eq. 19)": (dict(d0_edge=True), lambda r, p, s: r["d0_clipped"]),
    "theory mode, k_s1 from eq. 14-15": (dict(theory=True), lambda r, p, s: p["k_s1"] is None and not r["u_clipped"]),
    "u clipped at u_lim": (dict(big=True), lambda r, p, s: r["u_clipped"] or r["inversion"] == "saturated"),
}
C2_BRANCHES = {
    "inversion: theta5 = theta6 = 0 (u = v)": (dict(hold56=True, bounds=("in",) * 4 + ("hi", "hi")),
                                              lambda r, p, s: r["inversion"] == "linear" and abs(r["v"]) > 0.5),
    "inversion: theta6 = 0 != theta5 (quadratic)": (dict(hold56=True, bounds=("in",) * 4 + ("in", "hi")),
                                                   lambda r, p, s: r["inversion"] == "quadratic" and abs(r["v"]) > 0.5),
    "inversion: cubic, |u| > 3 V": (dict(), lambda r, p, s: r["inversion"] == "cubic" and abs(r["u"]) > 3.0),
    "inversion: beyond f_u(u_M) (saturated)": (dict(big=True), lambda r, p, s: r["inversion"] == "saturated"),
    "inversion: just inside f_u(u_M)": (dict(big=True), lambda r, p, s: r["inversion"] == "cubic"
                                        and abs(r["v"]) > 0.93 * f_u(p["u_lim"], r["theta"][4], r["theta"][5])),
    "inversion: v < 0, cubic": (dict(), lambda r, p, s: r["inversion"] == "cubic" and r["v"] < -1.0),
}
BRANCH_CASES = ([("c1", b) for b in BRANCHES] + [("c2", b) for b in BRANCHES] + [("c2", b) for b in C2_BRANCHES])


@pytest.mark.parametrize(("kind", "branch"), BRANCH_CASES)
def test_each_branch_is_visited_and_matches(kind, branch):
    """The branches of the step (faces, edges, corners of the box; the freeze; the bounds of d̂0
    and u; theory mode; the inversion's cases) each met by a draw, and matched there."""
    flags, want = {**BRANCHES, **C2_BRANCHES}[branch]
    prm, state, inputs = _hit(kind, flags, want)
    ref = check(prm, state, *inputs)
    assert want(ref, prm, state)


def plant_run(kind: str, seed: int, steps: int = 400):
    """C1/C2 closing the loop on eq. (4) (true θ of spec §7, 8 Euler substeps a sample, 0.5 µm
    encoder) on a sine; at every sample the law's step is checked against the reference from
    the law's own state before it. Returns the references (to count what they visited)."""
    rng = np.random.default_rng(seed)
    prm = dict(kind=kind, u_lim=10.0, tmin=X_MIN.copy(), tmax=X_MAX.copy(), gamma0=X_GAMMA0 * 20.0, k1=250.0,
               k_s=95.0, gamma_d=500.0, d_hat_max=1.0, omega_f=200.0, mu=rng.choice([0.0, 0.5]), nu=0.0,
               rho_M=1e4, mode="experiment", k2=10.0, eta=0.05, delta_d=0.3, k_s1=None)
    theta_true = np.array([0.16, 0.22, 0.25, -0.05, -0.013, -0.0015])
    theta0 = np.array([0.3, 0.08, 0.5, 0.0, 0.0, 0.0])          # on faces, far from the truth
    c = DCDIARC(section(prm, theta0), TS, kind)
    amp, w = rng.uniform(0.005, 0.02), rng.uniform(20.0, 40.0)
    x = np.zeros(2)
    y_prev = 0.0
    c.reset(0.0)
    refs = []
    for k in range(1, steps + 1):
        u = c.u
        for _ in range(8):      # eq. (4) under the held u
            dt = TS / 8
            force = (f_u(u, theta_true[4], theta_true[5]) - theta_true[1] * x[1]
                     - theta_true[2] * s_f(x[1]) + theta_true[3])
            x = x + dt * np.array([x[1], force / theta_true[0]])
        y = 0.5e-6 * round(x[0] / 0.5e-6)
        t = k * TS
        xd, vd, ad = amp * math.sin(w * t), amp * w * math.cos(w * t), -amp * w * w * math.sin(w * t)
        before = snapshot(c, y_prev)
        law = law_outputs(c, c.update(y, xd, vd, ad))
        ref = reference_step(prm, before, y, xd, vd, ad)
        if ref["freeze_ambiguous"] and law["frozen"] != ref["frozen"]:
            ref = reference_step(prm, before, y, xd, vd, ad, freeze=law["frozen"])
        compare(law, ref, f" at sample {k}")
        refs.append(ref)
        y_prev = y
    return refs


@pytest.mark.parametrize("kind", ["c1", "c2"])
def test_every_sample_of_a_closed_loop_run_matches(kind):
    """A closed loop on the simulated gantry from θ̂(0) on the faces of the box: every sample
    (the H_f states, Γ and θ̂ as the law evolved them) matches the reference, and the run does
    visit closed faces."""
    refs = plant_run(kind, 7)
    assert sum(1 for r in refs if r["closed"]) >= 10
    assert any(abs(r["u"]) > 1.0 for r in refs)


# ---------------------------------------------------------------------------------------------
# PID + feedforward against LinuxCNC's pid component
# ---------------------------------------------------------------------------------------------

class LinuxCncPid:
    """LinuxCNC's ``pid`` (manual page pid(9); hal/components/pid.c, calc_pid), one period:

        error = command − feedback; limited to ±maxerror; the deadband taken off it
        errorI += error·period unless the output is in its limit and error pushes further into
                  it; limited to ±maxerrorI
        errorD = commandD − feedbackD
        output = bias + Pgain·error + Igain·errorI + Dgain·errorD
                 + FF0·command + FF1·commandD + FF2·commandDD, limited to ±maxoutput

    with the project's documented choices (motorctl/control/pid.py): command = x_d with commandD
    = ẋ_d and commandDD = ẍ_d wired from the planner (LinuxCNC's command-deriv pin), feedbackD
    the backward difference of the feedback, and the output always limited, to ±u_lim when
    maxoutput is 0 and to ±min(maxoutput, u_lim) otherwise. A limit of 0 is none."""

    def __init__(self, g: dict, u_lim: float, y0: float):
        self.g = g
        self.limit = min(g["maxoutput"], u_lim) if g["maxoutput"] != 0.0 else u_lim
        self.error_i = 0.0
        self.limit_state = 0.0
        self.prev_fb = y0

    def step(self, command, feedback, command_d, command_dd):
        g = self.g
        error = command - feedback
        t = error
        if g["maxerror"] != 0.0:
            t = min(max(t, -g["maxerror"]), g["maxerror"])
        if t > g["deadband"]:
            t -= g["deadband"]
        elif t < -g["deadband"]:
            t += g["deadband"]
        else:
            t = 0.0
        held = t * self.limit_state > 0.0     # in the limit and pushing further: no wind-up
        if not held:
            self.error_i += t * TS
        raw_i = self.error_i
        if g["maxerror_i"] != 0.0:
            self.error_i = min(max(self.error_i, -g["maxerror_i"]), g["maxerror_i"])
        fb_d = (feedback - self.prev_fb) / TS
        self.prev_fb = feedback
        error_d = command_d - fb_d
        out = (g["bias"] + g["P"] * t + g["I"] * self.error_i + g["D"] * error_d
               + g["FF0"] * command + g["FF1"] * command_d + g["FF2"] * command_dd)
        pre = out
        if out > self.limit:
            out, self.limit_state = self.limit, 1.0
        elif out < -self.limit:
            out, self.limit_state = -self.limit, -1.0
        else:
            self.limit_state = 0.0
        scale = (abs(g["bias"]) + abs(g["P"] * t) + abs(g["I"] * self.error_i) + abs(g["D"] * error_d)
                 + abs(g["FF0"] * command) + abs(g["FF1"] * command_d) + abs(g["FF2"] * command_dd))
        return dict(u=out, v=pre, e=-error, p=-error_d, x2=fb_d, error_i=self.error_i,
                    saturated=self.limit_state != 0.0, scale=scale, t=t, raw=error, held=held,
                    i_limited=raw_i != self.error_i)


def pid_case(seed: int, deadband: bool, maxerror: bool, maxerror_i: bool, maxoutput: bool, steps: int = 40):
    rng = np.random.default_rng(seed)
    lg = lambda a, b: math.exp(rng.uniform(math.log(a), math.log(b)))   # noqa: E731
    g = dict(P=lg(1e3, 1e6), I=0.0 if rng.random() < 0.2 else lg(1e4, 1e8),
             D=0.0 if rng.random() < 0.2 else lg(1.0, 500.0),
             FF0=rng.uniform(-5, 5) if rng.random() < 0.3 else 0.0, FF1=rng.uniform(-1, 1), FF2=rng.uniform(-0.5, 0.5),
             bias=rng.uniform(-1, 1), deadband=rng.uniform(0, 3e-5) if deadband else 0.0,
             maxerror=lg(5e-6, 2e-4) if maxerror else 0.0, maxerror_i=lg(1e-9, 1e-6) if maxerror_i else 0.0,
             maxoutput=rng.uniform(1.0, 15.0) if maxoutput else 0.0)
    u_lim = rng.uniform(3.0, 12.0)
    amp, w = rng.uniform(1e-3, 2e-2), rng.uniform(5.0, 60.0)
    y0 = rng.uniform(-0.1, 0.1)
    seq = []
    err = rng.normal(0, 3e-5)
    for k in range(1, steps + 1):
        t = k * TS
        err += rng.normal(0, 1e-5)
        xd = y0 + amp * math.sin(w * t)
        seq.append((xd + err, xd, amp * w * math.cos(w * t), -amp * w * w * math.sin(w * t)))
    return g, u_lim, y0, seq


def pid_check(g, u_lim, y0, seq) -> list[dict]:
    gains = {k: v for k, v in g.items()}
    section_ = ControllerConfig.model_validate(dict(type="pid", u_lim=u_lim, theta_min=list(X_MIN),
                                                    theta_max=list(X_MAX), theta_hat0=list(0.5 * (X_MIN + X_MAX)),
                                                    pid=gains))
    c = PID.from_config(section_, TS)
    c.reset(y0)
    ref = LinuxCncPid(g, u_lim, y0)
    out = []
    for k, (y, xd, vd, ad) in enumerate(seq):
        u = c.update(y, xd, vd, ad)
        r = ref.step(xd, y, vd, ad)
        where = f" at sample {k + 1}"
        _close("PID output", u, r["u"], r["scale"], where)
        _close("PID v (before the limit)", c.v, r["v"], r["scale"], where)
        _close("PID v signal", c.signals[SIG["v"]], r["v"], r["scale"], where)
        _close("PID e signal", c.e, r["e"], abs(y) + abs(xd), where)
        _close("PID errorD (p signal)", c.p, r["p"], (abs(y) + abs(xd)) / TS + abs(vd), where)
        _close("PID errorI", c.error_i, r["error_i"], abs(r["error_i"]) + TS * abs(r["t"]) * (k + 1), where)
        assert c.saturated == r["saturated"], f"PID saturated{where}: law {c.saturated}, reference {r['saturated']}"
        out.append(r)
    return out


@settings(max_examples=examples(100), deadline=None)
@given(seed=st.integers(0, 2 ** 32 - 1), deadband=st.booleans(), maxerror=st.booleans(),
       maxerror_i=st.booleans(), maxoutput=st.booleans())
def test_pid_matches_linuxcnc_pid(seed, deadband, maxerror, maxerror_i, maxoutput):
    """Random gains, limits and command/feedback sequences: every period's output, the output
    before the limit, errorI, errorD and the limit state agree with LinuxCNC's pid."""
    pid_check(*pid_case(seed, deadband, maxerror, maxerror_i, maxoutput))


PID_BRANCHES = {
    "output limited, integrator held (anti-windup)": (dict(maxoutput=True), lambda rs: any(a["held"] for a in rs)),
    "output limited at u_lim (maxoutput 0)": (dict(), lambda rs: any(a["saturated"] for a in rs)),
    "deadband takes the error to 0": (dict(deadband=True),
                                      lambda rs: any(a["t"] == 0.0 and a["raw"] != 0.0 for a in rs)),
    "deadband reduces the error": (dict(deadband=True), lambda rs: any(0.0 < abs(a["t"]) < abs(a["raw"]) for a in rs)),
    "maxerror limits the error": (dict(maxerror=True), lambda rs: any(abs(a["raw"]) > 2 * abs(a["t"]) > 0 for a in rs)),
    "maxerrorI limits the integrator": (dict(maxerror_i=True), lambda rs: any(a["i_limited"] for a in rs)),
}


@pytest.mark.parametrize("branch", list(PID_BRANCHES))
def test_pid_limits_are_visited_and_match(branch):
    flags, want = PID_BRANCHES[branch]
    for seed in range(200):
        fl = {**dict(deadband=False, maxerror=False, maxerror_i=False, maxoutput=False), **flags}
        case = pid_case(20_000 + seed, **fl)
        if want(pid_check(*case)):
            return
    raise AssertionError(f"no PID draw of 200 hits {branch!r}")


# ---------------------------------------------------------------------------------------------
# the mutation check: `python tests/test_law_reference.py --mutants`
# ---------------------------------------------------------------------------------------------

#: (term, file, the line's text, the wrong text): one deliberate error in the law at a time
MUTANTS = [
    ("u_a: sign of theta1 xdd_d", "motorctl/control/dcdiarc.py",
     "va1 = th[0] * af + th[1] * vf", "va1 = -th[0] * af + th[1] * vf"),
    ("u_a: gain x2 on theta2 xd_d", "motorctl/control/dcdiarc.py",
     "va1 = th[0] * af + th[1] * vf", "va1 = th[0] * af + 2.0 * th[1] * vf"),
    ("u_a: S_f(x2) for S_f(xd_d)", "motorctl/control/dcdiarc.py",
     "sfd = s_f_jit(vf)", "sfd = s_f_jit(x2)"),
    ("u_a: sign of theta4", "motorctl/control/dcdiarc.py",
     "th[2] * sfd - th[3] - v_comp", "th[2] * sfd + th[3] - v_comp"),
    ("u_s1: sign of k_s p", "motorctl/control/dcdiarc.py",
     "v = va1 - d0 - ks * p", "v = va1 - d0 + ks * p"),
    ("u_s1: sign of k1 e in p", "motorctl/control/dcdiarc.py",
     "p = (x2 - xd_dot) + prm[P_K1] * e", "p = (x2 - xd_dot) - prm[P_K1] * e"),
    ("u_s1: theory k_s2 /2", "motorctl/control/dcdiarc.py",
     "ks = prm[P_KS1] + hb * hb / prm[P_ETA4]", "ks = prm[P_KS1] + hb * hb / (2.0 * prm[P_ETA4])"),
    ("d0: sign of gamma_d p", "motorctl/control/dcdiarc.py",
     "d0 = st[S_D0] + ts * prm[P_GD] * p", "d0 = st[S_D0] - ts * prm[P_GD] * p"),
    ("d0: sign in v", "motorctl/control/dcdiarc.py",
     "v = va1 - d0 - ks * p", "v = va1 + d0 - ks * p"),
    ("d0: no clip at -d_max", "motorctl/control/dcdiarc.py",
     "    elif d0 < -dmax:\n        d0 = -dmax\n    st[S_D0] = d0",
     "    elif d0 < -dmax:\n        d0 = d0\n    st[S_D0] = d0"),
    ("adaptation: sign of epsilon", "motorctl/control/estimator.py",
     "eps = pred - u_f", "eps = u_f - pred"),
    ("adaptation: rate x2 (Ts)", "motorctl/control/estimator.py",
     "val = th[i] + ts * z[i]", "val = th[i] + 2.0 * ts * z[i]"),
    ("adaptation: Gamma downdate sign", "motorctl/control/estimator.py",
     "val = scale * gam[i, j] - cgi * g[j]", "val = scale * gam[i, j] + cgi * g[j]"),
    ("adaptation: tau without 1/n_k", "motorctl/control/estimator.py",
     "    k = eps / nk\n", "    k = eps\n"),
    ("adaptation: forgetting squared", "motorctl/control/estimator.py",
     "c = h * scale * scale / (1.0 + h * scale * quad)", "c = h * scale / (1.0 + h * scale * quad)"),
    ("adaptation: phi_1 sign (xdd_2f)", "motorctl/control/estimator.py",
     "phi[0] = -zd[0]", "phi[0] = zd[0]"),
    ("adaptation: u|u| channel as u^2", "motorctl/control/estimator.py",
     "inp[4] = u_prev * abs(u_prev)", "inp[4] = u_prev * u_prev"),
    ("adaptation: freeze never", "motorctl/control/estimator.py",
     "frozen = lambda_max_exceeds(gam, g, scale, c, rho, piv)", "frozen = False"),
    ("projection: none (clip only)", "motorctl/control/estimator.py",
     "    project_box(z, th, tmin, tmax, gam, piv, coef, vec, pividx, active)\n",
     "    pass\n"),
    ("projection: wrong multiplier sign test", "motorctl/control/estimator.py",
     "bad = -lam[mm] if th[j] >= tmax[j] else lam[mm]", "bad = lam[mm] if th[j] >= tmax[j] else -lam[mm]"),
    ("projection: faces never opened (add-only)", "motorctl/control/estimator.py",
     "        if worst >= 0:\n            active[worst] = False\n            continue\n",
     "        worst = -1\n"),
    ("projection: Gamma-weighting dropped", "motorctl/control/estimator.py",
     "                z[a] -= piv[m, a] * f\n", "                z[a] -= (piv[m, a] * f if a == j else 0.0)\n"),
    ("inversion: sign of theta5 in Newton", "motorctl/control/inversion.py",
     "g = r + theta5 * r * r + theta6 * r * r * r - w", "g = r - theta5 * r * r + theta6 * r * r * r - w"),
    ("inversion: quadratic root 4 -> 2", "motorctl/control/inversion.py",
     "disc = 1.0 + 4.0 * theta5 * w", "disc = 1.0 + 2.0 * theta5 * w"),
    ("inversion: saturates at 0.9 f(u_M)", "motorctl/control/inversion.py",
     "    if w >= f_max:\n        return s * u_max\n", "    if w >= 0.9 * f_max:\n        return s * u_max\n"),
    ("inversion: odd symmetry lost", "motorctl/control/inversion.py",
     "        s = -1.0\n        w = -v", "        s = 1.0\n        w = -v"),
    ("pid: FF2 on xd_dot", "motorctl/control/pid.py",
     "prm[P_FF2] * xd_ddot", "prm[P_FF2] * xd_dot"),
    ("pid: anti-windup reversed", "motorctl/control/pid.py",
     "if t * st[S_LIMIT] <= 0.0:", "if t * st[S_LIMIT] >= 0.0:"),
    ("pid: deadband zeroes only", "motorctl/control/pid.py",
     "    if t > db:\n        t -= db\n", "    if t > db:\n        t = t\n"),
    ("pid: D on the feedback only", "motorctl/control/pid.py",
     "ed = xd_dot - x2", "ed = -x2"),
]


def run_mutants(jit: bool = True) -> int:
    """Copy the law into a scratch tree, make one term wrong at a time (:data:`MUTANTS`), run
    this file there, and report whether it fails (caught) or passes (missed). The repository is
    not touched; numba's cache of the copies lives in the scratch tree and goes with it.
    Returns 0 when every mutant is caught and the unmutated copy passes."""
    repo = Path(__file__).resolve().parents[1]
    scratch = Path(tempfile.mkdtemp(prefix="law-mutants-"))
    rows = []
    try:
        for part in ("motorctl", "motorctl_drivers", "tests", "pyproject.toml"):
            src = repo / part
            if src.is_dir():
                shutil.copytree(src, scratch / part, ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
            else:
                shutil.copy2(src, scratch / part)
        env = dict(os.environ, PYTHONPATH=str(scratch), MOTORCTL_CACHE_DIR=str(scratch / ".cache"))
        env.pop("NUMBA_CACHE_DIR", None)
        if not jit:
            env["NUMBA_DISABLE_JIT"] = "1"
        argv = [sys.executable, "-m", "pytest", "-q", "-x", "-n", "0", "--noconftest", "-p", "no:cacheprovider",
                "tests/test_law_reference.py"]
        which = subprocess.run([sys.executable, "-c", "import motorctl; print(motorctl.__file__)"], cwd=scratch,
                               env=env, capture_output=True, text=True).stdout.strip()
        assert which.startswith(str(scratch)), f"the copy is not the one imported: {which}"

        def run() -> tuple[int, str]:
            p = subprocess.run(argv, cwd=scratch, env=env, capture_output=True, text=True)
            failed = [ln for ln in p.stdout.splitlines() if ln.startswith(("FAILED", "ERROR"))]
            return p.returncode, (failed[0] if failed else p.stdout.strip().splitlines()[-1])

        rc, last = run()
        rows.append(("(none: the law as it is)", "passes" if rc == 0 else f"FAILS: {last}"))
        print(f"{'(none)':45s} {rows[-1][1]}", flush=True)
        ok = rc == 0
        for term, rel, old, new in MUTANTS:
            path = scratch / rel
            orig = path.read_text()
            assert orig.count(old) == 1, f"{rel}: the mutant's text for {term!r} is not there once"
            path.write_text(orig.replace(old, new))
            try:
                rc, last = run()
            finally:
                path.write_text(orig)
            caught = rc != 0 and "FAILED" in last
            ok &= caught
            rows.append((term, f"caught: {last}" if caught else f"MISSED (rc {rc}): {last}"))
            print(f"{term:45s} {rows[-1][1]}", flush=True)
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    return 0 if ok else 1


if __name__ == "__main__":
    if "--mutants" in sys.argv:
        sys.path.insert(0, str(Path(__file__).resolve().parent))
        raise SystemExit(run_mutants(jit="--nojit" not in sys.argv))
    raise SystemExit(pytest.main(["-q", "-n", "0", __file__]))
