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

What is compared is the compiled step the servo loop runs (``dcdiarc_block_step``,
``dcdiarc_comp_step``, ``pid_step``) called through the public
:class:`motorctl.control.base.Controller` interface, ``update`` (GTCF's ``gtcf_step`` directly,
as the cycle calls it with the partner's block): a controller is built from a ``controller:``
section (so the config -> law mapping is checked as well), its state is set (θ̂, Γ, the H_f
states through their live arrays; y[k−1], u[k−1], d̂0, the input ring, GTCF's partner position
and low-pass state through the law's state vector and block layout, the only things imported
from the laws' modules besides the classes and the pair's step), one sample is run and every output of the sample (u, v, e, p, x2, d̂0, θ̂, Γ, ε, the
freeze, k_s) is compared with the reference's. The states and parameter sets are drawn by
hypothesis (derandomized: tests/conftest.py) and by branch: parameters on the faces, edges and
corners of the box with a diagonal and a coupled Γ, the freeze of Γ, d̂0 at its bound, θ̂5 =
θ̂6 = 0, θ̂6 = 0 ≠ θ̂5, the saturated inversion, theory mode. A closed-loop run on a simulated
plant checks every sample of a realistic state sequence against the reference from the law's
state before it.

The compiled step's other branches, each switched on by the ``controller:`` section, are
modelled too, from the docs of the families and of the laws (motorctl/effects/*.py's docstrings,
motorctl/control/dcdiarc.py's, docs/control-law.md "GTCF"), not from their kernels: the
identified-effect compensation (fixed terms, cogging, spring, Stribeck on the reference velocity
ẋ_r = ẋ_d − k1 e and a time-periodic term, evaluated at the desired point, subtracted in v_a1 and
added to the estimator's input u; adapted terms, their columns at the interval's mean position,
velocity and mid time for the estimator and at the desired point for v_a1, β̂ in θ̂ with its box,
on C1 and C2 and in theory mode), the force ripple (v divided by 1 + r̂(x_d), the thrust channels
times 1 + r̂ at the measured mean), the input delay (v_a1 and d̂_eff at t + τ from the preview, the
estimator fed the input applied over the interval from a chronological history) and GTCF (the
task-frame feedback in the docs' matrix form v_s = −D^½ K D^½ p̃, K = g_t' t tᵀ + N'^½ n nᵀ N'^½,
the contour error's λ_n within and beyond its band, the blend below v_min, the low-pass, the
uncoupled and first-sample cases, over a compensation), the pair's step called as the servo
cycle calls it (``gtcf_step`` with the partner's block). Each branch: a few samples one after
the other, each checked against the reference from the law's state before it.

Tolerance (RTOL): a quantity may differ from the reference by RTOL = 1e-9 times the sum of the
magnitudes of the terms that make it up (a floating-point error bound, not a pinned value). The
two compute the same formulas in another order and by other algorithms (a closed form against
expm, an eigenvalue against a Cholesky test, subset enumeration against elimination, bisection
against Newton), each exact to a few ulp times the condition of what it solves: over 800 draws
they differed by at most 5e-14 of that sum (Γ's update), so RTOL leaves four orders of margin
for worse-conditioned Γ blocks, while a wrong sign or gain in any term moves the result by a
sizable fraction of that term, many orders beyond it.

Mutation check (docs/control-law.md): ``.venv/bin/python tests/test_law_reference.py --mutants``
runs this file against copies of the law with one term made wrong at a time (:data:`MUTANTS`,
at least one per branch above) and reports which the file catches (``--nojit``: the kernels as
Python; ``--jobs=N``: N mutants at once; ``--only=TEXT``: the mutants whose term holds TEXT).
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
from hypothesis import Phase, given, settings
from hypothesis import strategies as st

from motorctl.control.dcdiarc import DCDIARC
# the law's state layout (to set a state; B_*: where GTCF keeps its numbers), no arithmetic
from motorctl.control.dcdiarc import B_N, B_SPAN, S_D0, S_DC, S_RI, S_U, S_Y_PREV
from motorctl.control.gtcf import G_VFB, G_YJ, GTCF, gtcf_step
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
#: hypothesis's phases: in a mutant's run (:func:`run_mutants`) the first failing example is
#: enough (no shrinking)
PHASES = tuple(p for p in Phase if p is not Phase.shrink) if os.environ.get("LAW_REFERENCE_MUTANT") else tuple(Phase)


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


def reference_step(prm: dict, state: dict, y: float, xd: float, vd: float, ad: float, freeze=None, *,
                   comp: "RefComp | None" = None, t: float = 0.0, ahead=None, v_fb: float = 0.0,
                   v_fb_scale: float = 0.0) -> dict:
    """One sample k of C1 (n = 4) or C2 (n = 6) in the order of docs/control-law.md (spec §5.2).

    prm: the law's settings (kind, k1, k_s, gamma_d, d_hat_max, u_lim, omega_f, mu, nu, rho_M,
    mode, k2, eta, delta_d, k_s1, tmin, tmax). state (before the sample): y_prev, u_prev [V],
    d0, theta (n,), gamma (n, n), zf, zd (n,) the H_f states of the channels (x2, S_f(x2), 1, u,
    u|u|, u³) (C1: the first four). freeze: None (decide by eq. 27) or True/False (forced: for a
    sample whose λ_max is within rounding of ρ_M). Returns the outputs and what was hit.

    With an identified-effect compensation ``comp`` (:class:`RefComp`, module motorctl.effects'
    docs): θ (n + k,) then holds β̂, Γ and the H_f states the k basis channels; the state has d_prev
    (d̂_eff held with u[k−1]) and, with an input delay, hist: the last m (u, d̂_eff) pairs, oldest
    first. t [s]: the sample's time; ahead: (x_d, ẋ_d, ẍ_d) at t + τ (the preview; None: this
    sample's). v_fb [V]: GTCF's feedback beyond −k_s p (v_fb_scale: the magnitude of its terms)."""
    nn = 6 if prm["kind"] == "c2" else 4
    k = comp.k if comp is not None else 0
    n = nn + k
    tmin = np.concatenate([prm["tmin"][:nn], comp.beta_min if k else []])
    tmax = np.concatenate([prm["tmax"][:nn], comp.beta_max if k else []])
    th = state["theta"].astype(float).copy()
    gam = state["gamma"].astype(float).copy()
    out: dict = {}
    xf, vf, af = (xd, vd, ad) if ahead is None else ahead
    tau = comp.tau if comp is not None else 0.0

    # 1. the velocity: backward difference of two readings (spec §5.1)
    x2 = (y - state["y_prev"]) / TS

    # 2. the estimator with time-aligned inputs: the pair (x2[k], u[k−1]) of the interval just ended
    # (with an input delay τ = n Ts the input applied over it, u[k−1−n]; with a compensation the
    # model's input is u + d̂_eff, the thrust channels times 1 + r̂(x) at the interval's mean position)
    hist = state.get("hist")
    up, dp = (state["u_prev"], state.get("d_prev", 0.0)) if hist is None else hist[0]
    xm = 0.5 * (y + state["y_prev"])
    gm = 1.0 + comp.ripple(xm) if comp is not None else 1.0
    cols_m = comp.columns(xm, x2, t - 0.5 * TS) if k else np.zeros(0)
    inp = np.concatenate([[x2, s_f(x2), 1.0, gm * up + dp, gm * up * abs(up), gm * up ** 3][:nn], cols_m])
    a, b = hf_zoh(prm["omega_f"], TS)
    zf = a[0, 0] * state["zf"] + a[0, 1] * state["zd"] + b[0] * inp
    zd = a[1, 0] * state["zf"] + a[1, 1] * state["zd"] + b[1] * inp
    out["zf_scale"] = np.abs(a[0, 0] * state["zf"]) + np.abs(a[0, 1] * state["zd"]) + np.abs(b[0] * inp)
    out["zd_scale"] = np.abs(a[1, 0] * state["zf"]) + np.abs(a[1, 1] * state["zd"]) + np.abs(b[1] * inp)
    # eq. (25): u_f = −φ_fᵀθ, φ_f = [−ẋ2f, −x2f, −S_ff, 1_f, (u|u|)_f, (u³)_f], then the basis's c_f
    phi = np.array([-zd[0], -zf[0], -zf[1], zf[2]] + ([zf[4], zf[5]] if nn == 6 else []) + list(zf[nn:]))
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
    tau_ = phi * eps / nk                                      # eq. (28)
    zeta = g_new @ tau_
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

    # 5. v = v_a1 + v_a2 + v_s (eq. 13, 18, 22): model compensation on the DESIRED trajectory (at
    # t + τ with an input delay), less the effects' d̂_eff on (x_d, ẋ_r = ẋ_d − k1 e, t + τ)
    sfd = s_f(vf)
    vr = vf - prm["k1"] * e
    d_eff = comp.fixed(xf, vr, t + tau) if comp is not None else 0.0
    cols_d = comp.columns(xf, vr, t + tau) if k else np.zeros(0)
    va1 = th[0] * af + th[1] * vf + th[2] * sfd - th[3] - d_eff - float(th[nn:] @ cols_d)
    if prm["mode"] == "theory":
        # v_s = −(k_s1 + k_s2) p, k_s2 = (d̂_max + Σ θ_Mi |φ_di| + δ_d)²/(4η) (eq. 22), the
        # componentwise bound; φ_d = [−ẍ_d, −ẋ_d, −S_f(ẋ_d), 1, u|u|, u³, c(x_d)] with the last u
        span = tmax - tmin
        u_last = state["u_prev"]
        phid = np.concatenate([[-af, -vf, -sfd, 1.0, u_last * abs(u_last), u_last ** 3][:nn], cols_d])
        h = prm["d_hat_max"] + float(span @ np.abs(phid)) + prm["delta_d"]
        ks1 = prm["k_s1"] if prm["k_s1"] is not None else theory_ks1(tmin, tmax, prm["k1"], prm["k2"])
        ks = ks1 + h * h / (4.0 * prm["eta"])
    else:
        ks = prm["k_s"]                                        # experiment mode: v_s = −k_s p
    v = va1 - d0 - ks * p + v_fb
    ts_ = out["theta_scale"]
    v_scale = (ts_[0] * abs(af) + ts_[1] * abs(vf) + ts_[2] * abs(sfd) + ts_[3] + abs(d0) + abs(ks * p)
               + out["d0_scale"] + abs(d_eff) + float(ts_[nn:] @ np.abs(cols_d)) + v_fb_scale)

    # 6. u from v: C2 by the inversion of eq. (9) of v / (1 + r̂(x_d)) (the thrust F_m(u)(1 + r)),
    # C1 u = v / (1 + r̂); then the actuator's ±u_lim
    gd = 1.0 + comp.ripple(xf) if comp is not None else 1.0
    w = v / gd
    if nn == 6:
        u, case = invert(w, th[4], th[5], prm["u_lim"])
        slope = 1.0 + 2.0 * th[4] * abs(u) + 3.0 * th[5] * u * u
        u_scale = (v_scale / gd + ts_[4] * u * u + ts_[5] * abs(u) ** 3) / slope
    else:
        u, case = w, "none"
        u_scale = v_scale / gd
    u_clip = min(max(u, -prm["u_lim"]), prm["u_lim"])
    out["u_clipped"] = u_clip != u
    if hist is not None:
        out["hist"] = hist[1:] + [(u_clip, d_eff)]
    out.update(u=u_clip, v=v, e=e, p=p, x2=x2, d0=d0, theta=th, gamma=g_new, eps=eps, frozen=frozen,
               ks=ks, zf=zf, zd=zd, closed=closed, inversion=case, v_scale=v_scale, u_scale=u_scale,
               p_scale=abs(x2) + abs(vd) + prm["k1"] * abs(e), e_scale=abs(y) + abs(xd),
               x2_scale=(abs(y) + abs(state["y_prev"])) / TS, d_eff=d_eff, cols_m=cols_m, cols_d=cols_d,
               g_meas=gm, g_des=gd, delayed=(up, dp))
    return out


# ---------------------------------------------------------------------------------------------
# the law under test, through its Controller interface
# ---------------------------------------------------------------------------------------------

def section(prm: dict, theta0=None, **more) -> ControllerConfig:
    """The axis's ``controller:`` section of the settings ``prm`` (``more``: further keys, e.g.
    ``compensation``, ``gtcf``)."""
    data = dict(type=prm["kind"], u_lim=prm["u_lim"], theta_min=list(prm["tmin"]), theta_max=list(prm["tmax"]),
                theta_hat0=list(theta0 if theta0 is not None else 0.5 * (prm["tmin"] + prm["tmax"])),
                gamma0=list(prm["gamma0"]), k_s=prm["k_s"], k1=prm["k1"], gamma_d=prm["gamma_d"],
                d_hat_max=prm["d_hat_max"], filter={"omega_f": prm["omega_f"]}, mu=prm["mu"], nu=prm["nu"],
                rho_M=prm["rho_M"], mode=prm["mode"],
                theory={"k2": prm["k2"], "eta": prm["eta"], "delta_d": prm["delta_d"], "k_s1": prm["k_s1"]},
                **more)
    return ControllerConfig.model_validate(data)


def ring_history(c: DCDIARC) -> list[tuple[float, float]]:
    """The law's input ring (an input delay's (u, d̂_eff) pairs) as a history, oldest first."""
    m, ri = c._ring.shape[1], int(c._st[S_RI])
    return [(float(c._ring[0, (ri + j) % m]), float(c._ring[1, (ri + j) % m])) for j in range(m)]


def snapshot(c: DCDIARC, y_prev: float) -> dict:
    """The state of the law before its next sample, read from the controller (θ̂ with β̂; with
    a compensation the d̂_eff held with u, with an input delay the ring as a history, oldest first)."""
    est = c.estimator
    out = dict(y_prev=y_prev, u_prev=c.u, d0=c.d_hat0, theta=est.theta_hat.copy(),
               gamma=est.gamma.copy(), zf=est.zf.copy(), zd=est.zd.copy(), d_prev=float(c._st[S_DC]))
    if c._ring.shape[1] > 1:
        out["hist"] = ring_history(c)
    return out


def law_outputs(c: DCDIARC, u: float) -> dict:
    est = c.estimator
    n = c.n_theta
    sig = c.signals
    out = dict(u=u, v=c.v, e=c.e, p=c.p, x2=c.x2, d0=c.d_hat0, theta=est.theta_hat.copy(), gamma=est.gamma.copy(),
               eps=est.epsilon, frozen=est.frozen, ks=c.k_s_eff, zf=est.zf.copy(), zd=est.zd.copy(),
               sig_v=sig[SIG["v"]], sig_d0=sig[SIG["d_hat0"]], sig_p=sig[SIG["p"]],
               sig_theta=sig[SIG["theta_hat1"]:SIG["theta_hat1"] + n].copy(), d_eff=float(c._st[S_DC]),
               cols_m=est.cols.copy(), cols_d=c._cd.copy())
    if c._ring.shape[1] > 1:
        out["hist"] = ring_history(c)
    return out


def set_state(c: DCDIARC, state: dict) -> None:
    """Reset ``c`` at y[k−1] and set the law's state to ``state`` (:func:`snapshot`'s keys)."""
    c.reset(state["y_prev"])
    c._st[S_Y_PREV] = state["y_prev"]
    c._st[S_U] = state["u_prev"]
    c._st[S_D0] = state["d0"]
    c._st[S_DC] = state.get("d_prev", 0.0)
    c.estimator.theta_hat[:] = state["theta"]
    c.estimator.gamma[:] = state["gamma"]
    c.estimator.zf[:] = state["zf"]
    c.estimator.zd[:] = state["zd"]
    if "hist" in state:                      # the ring, oldest first from index 0
        c._ring[:] = np.array(state["hist"]).T
        c._st[S_RI] = 0.0


def run_law(prm: dict, state: dict, y: float, xd: float, vd: float, ad: float, c: DCDIARC | None = None,
            t: float = 0.0, ahead=None) -> dict:
    """One sample of the project's law from ``state``: a controller built from the section (or
    ``c``, built from it before), reset at y[k−1], its state set, then ``update`` (after
    ``preview`` with ``ahead``, the desired sample at t + τ, when given)."""
    if c is None:
        c = DCDIARC(section(prm), TS, prm["kind"])
    set_state(c, state)
    if ahead is not None:
        c.preview(*ahead)
    return law_outputs(c, c.update(y, xd, vd, ad, t))


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
    nn = len(law["sig_theta"])
    _close("theta_hat signals", law["sig_theta"], ref["theta"][:nn], ref["theta_scale"][:nn], where)
    _close("d_hat0 (eq. 19)", law["d0"], ref["d0"], ref["d0_scale"], where)
    _close("d_hat0 signal", law["sig_d0"], ref["d0"], ref["d0_scale"], where)
    _close("k_s", law["ks"], ref["ks"], abs(ref["ks"]), where)
    _close("v (eq. 13, 18, 22)", law["v"], ref["v"], ref["v_scale"], where)
    _close("v signal", law["sig_v"], ref["v"], ref["v_scale"], where)
    _close("u (eq. 9)", law["u"], ref["u"], ref["u_scale"], where)
    if len(ref["cols_m"]):
        _close("adapted basis at the interval's mean", law["cols_m"], ref["cols_m"], 1.0, where)
        _close("adapted basis at the desired point", law["cols_d"], ref["cols_d"], 1.0, where)
    _close("d_eff held with u", law["d_eff"], ref["d_eff"], abs(ref["d_eff"]), where)
    if "hist" in ref:
        _close("input ring (u, d_eff), oldest first", law["hist"], ref["hist"],
               np.abs(ref["hist"]) + ref["u_scale"], where)


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
@settings(max_examples=examples(60), deadline=None, phases=PHASES)
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
# the compiled step's other branches: identified-effect compensation (fixed and adapted terms),
# force ripple, input delay (motorctl/control/dcdiarc.py's module docstring, the families'
# docstrings in motorctl/effects/, docs/control-law.md) and the GTCF pair (docs/control-law.md,
# "GTCF: the contouring law of a pair of axes")
# ---------------------------------------------------------------------------------------------

class RefComp:
    """A ``compensation:`` mapping as the families' docs write it, evaluated in plain Python:

    * cogging: d(x) = Σ_k a_k sin(2πk x/P) + b_k cos(2πk x/P) [V]; adapted: the columns
      sin(2πk x/P) (k = 1..), then cos(...), β = (a, b);
    * spring: d(x) = −k (x − x_0); adapted: the column x_0 − x, β = k;
    * stribeck: d(v) = −F exp(−(v/v_s)²) S_f(v); adapted: the column −exp(−(v/v_s)²) S_f(v), β = F;
    * periodic_disturbance: Σ_k a_k sin(2πk f t) + b_k cos(2πk f t); adapted as cogging, on t;
    * force_ripple: the thrust fraction r(x) = Σ_k a_k sin(2πk x/P) + b_k cos(2πk x/P);
    * input_delay: τ [s], m = 1 + round(τ/Ts) (the ring of the inputs held).

    ``names``: the law's β names ("family.key[j]", :attr:`DCDIARC.beta_names`), which fix the
    order of the adapted coefficients in θ̂ (the reference maps each name to its own column)."""

    def __init__(self, spec: dict, names: list[str]):
        self.spec = spec
        self.names = list(names)
        self.k = len(self.names)
        adapted = {f for f, o in spec.items() if o.get("adapt")}
        assert {n.split(".")[0] for n in self.names} == adapted, (self.names, adapted)
        lo, hi = [], []
        for name in self.names:
            fam, key, j = self._parse(name)
            o = spec[fam]
            at = self._beta_keys(fam).index((key, j))
            lo.append(o["beta_min"][at])
            hi.append(o["beta_max"][at])
        self.beta_min, self.beta_max = np.array(lo), np.array(hi)
        self.tau = spec.get("input_delay", {}).get("delay_s", 0.0)
        self.m = 1 + int(round(self.tau / TS))

    @staticmethod
    def _parse(name):
        fam, rest = name.split(".", 1)
        key, j = (rest[:-1].split("[") if rest.endswith("]") else (rest, "0"))
        return fam, key, int(j)

    def _beta_keys(self, fam):
        o = self.spec[fam]
        if fam in ("cogging", "periodic_disturbance"):
            n = max(len(o.get("sin_V", [])), len(o.get("cos_V", [])))
            return [("sin_V", j) for j in range(n)] + [("cos_V", j) for j in range(n)]
        return [({"spring": "stiffness_V_per_m", "stribeck": "force_V"}[fam], 0)]

    @staticmethod
    def value(o: dict, key: str, j: int) -> float:
        """Coefficient j of an entry's key (a list padded with zeros, or a number)."""
        v = o[key]
        return (v[j] if j < len(v) else 0.0) if isinstance(v, list) else v

    def beta0(self) -> np.ndarray:
        """β of the entries as configured, in the order of ``names``."""
        return np.array([self.value(self.spec[fam], key, j) for fam, key, j in map(self._parse, self.names)])

    @staticmethod
    def _fourier(a, b, w, z):
        return sum(a[j] * math.sin((j + 1) * w * z) for j in range(len(a))) + \
            sum(b[j] * math.cos((j + 1) * w * z) for j in range(len(b)))

    def _term(self, fam, x, v, t):
        o = self.spec[fam]
        if fam == "cogging":
            return self._fourier(o.get("sin_V", []), o.get("cos_V", []), 2 * math.pi / o["period_m"], x)
        if fam == "periodic_disturbance":
            return self._fourier(o.get("sin_V", []), o.get("cos_V", []), 2 * math.pi * o["frequency_Hz"], t)
        if fam == "spring":
            return -o["stiffness_V_per_m"] * (x - o.get("rest_position_m", 0.0))
        if fam == "stribeck":
            return -o["force_V"] * math.exp(-(v / o["velocity_m_per_s"]) ** 2) * s_f(v)
        raise KeyError(fam)

    def fixed(self, x, v, t) -> float:
        """d̂_eff [V] of the fixed (not adapted) terms at x [m], v [m/s], t [s]."""
        return sum(self._term(f, x, v, t) for f, o in self.spec.items()
                   if f in ("cogging", "spring", "stribeck", "periodic_disturbance") and not o.get("adapt"))

    def columns(self, x, v, t) -> np.ndarray:
        """The adapted terms' columns c (k,) at x, v, t, in the order of ``names``."""
        out = []
        for name in self.names:
            fam, key, j = self._parse(name)
            o = self.spec[fam]
            if fam in ("cogging", "periodic_disturbance"):
                z, w = (x, 2 * math.pi / o["period_m"]) if fam == "cogging" else (t, 2 * math.pi * o["frequency_Hz"])
                out.append((math.sin if key == "sin_V" else math.cos)((j + 1) * w * z))
            elif fam == "spring":
                out.append(o.get("rest_position_m", 0.0) - x)
            else:
                out.append(-math.exp(-(v / o["velocity_m_per_s"]) ** 2) * s_f(v))
        return np.array(out)

    def ripple(self, x) -> float:
        o = self.spec.get("force_ripple")
        return 0.0 if o is None else self._fourier(o.get("sin", []), o.get("cos", []), 2 * math.pi / o["period_m"], x)


def draw_compensation(rng, fixed=(), adapted=(), ripple=False, delay=False, beta_face=False) -> dict:
    """A ``compensation:`` mapping: the families of ``fixed`` with fixed amplitudes, of ``adapted``
    adapted (β box and Γ(0) given; β̂ on a face of its box with ``beta_face``), a force ripple, an
    input delay of 1-4 samples (not a whole number of them: τ/Ts rounds)."""
    spec: dict = {}
    for fam in list(fixed) + list(adapted):
        if fam == "cogging":
            o = dict(period_m=rng.uniform(0.004, 0.05), sin_V=list(rng.uniform(-0.3, 0.3, 2)),
                     cos_V=list(rng.uniform(-0.3, 0.3, int(rng.integers(1, 3)))))
        elif fam == "periodic_disturbance":
            o = dict(frequency_Hz=rng.uniform(5.0, 120.0), sin_V=list(rng.uniform(-0.3, 0.3, 1)),
                     cos_V=list(rng.uniform(-0.3, 0.3, 2)))
        elif fam == "spring":
            o = dict(stiffness_V_per_m=rng.uniform(0.5, 5.0), rest_position_m=rng.uniform(-0.1, 0.1))
        else:
            o = dict(force_V=rng.uniform(0.05, 0.5), velocity_m_per_s=rng.uniform(0.002, 0.03))
        if fam in adapted:
            b = RefComp({fam: o}, [])._beta_keys(fam)
            vals = [RefComp.value(o, key, j) for key, j in b]
            w = [rng.uniform(0.05, 0.5) for _ in vals]
            o.update(adapt=True, beta_min=[v - a for v, a in zip(vals, w)], beta_max=[v + a for v, a in zip(vals, w)],
                     gamma0=[float(g) for g in rng.uniform(1.0, 50.0, len(vals))])
            if beta_face:                    # the entries on a face: β(0) = β_min or β_max
                for j, (key, i) in enumerate(b):
                    edge = o["beta_max"][j] if rng.random() < 0.5 else o["beta_min"][j]
                    if isinstance(o[key], list):
                        o[key] = list(o[key]) + [0.0] * (i + 1 - len(o[key]))
                        o[key][i] = edge
                    else:
                        o[key] = edge
        spec[fam] = o
    if ripple:
        spec["force_ripple"] = dict(period_m=rng.uniform(0.01, 0.05), sin=list(rng.uniform(-0.12, 0.12, 2)),
                                    cos=list(rng.uniform(-0.12, 0.12, 1)))
    if delay:
        spec["input_delay"] = dict(delay_s=TS * (int(rng.integers(1, 5)) + rng.uniform(-0.4, 0.4)))
    return spec


def feature_state(rng, prm: dict, comp: RefComp, state: dict) -> dict:
    """``state`` (:func:`draw_state`'s) extended by the compensation's: β̂ (its θ̂(0) or inside
    its box), Γ with the β rows (coupled to θ), the basis channels' H_f states, the d̂_eff held
    with u[k−1] and the input ring's history."""
    n0, k = len(state["theta"]), comp.k
    st_ = dict(state)
    if k:
        inside = rng.random() < 0.5
        beta = rng.uniform(comp.beta_min, comp.beta_max) if inside else comp.beta0()
        st_["theta"] = np.concatenate([state["theta"], beta])
        gam = np.zeros((n0 + k, n0 + k))
        gam[:n0, :n0] = state["gamma"]
        d = rng.uniform(1.0, 50.0, k)
        gam[n0:, n0:] = np.diag(d)
        c = rng.uniform(-0.3, 0.3, (k, n0)) * np.sqrt(np.outer(d, np.diag(state["gamma"])))
        gam[n0:, :n0], gam[:n0, n0:] = c, c.T
        lam = np.linalg.eigvalsh(gam)
        if lam.min() <= 1e-9 * lam.max():    # keep it SPD: pull the coupling in
            gam[n0:, :n0] *= 0.3
            gam[:n0, n0:] *= 0.3
        lmax = float(np.linalg.eigvalsh(gam).max())
        if lmax > 0.8 * prm["rho_M"]:
            gam *= 0.8 * prm["rho_M"] / lmax
        st_["gamma"] = gam
        st_["zf"] = np.concatenate([state["zf"], rng.uniform(-1, 1, k)])
        st_["zd"] = np.concatenate([state["zd"], rng.normal(0, 0.3 * prm["omega_f"], k)])
    st_["d_prev"] = comp.fixed(state["y_prev"], rng.uniform(-0.02, 0.02), rng.uniform(0, 5)) if comp.spec else 0.0
    if comp.m > 1:
        u_lim = prm["u_lim"]
        st_["hist"] = [(float(rng.uniform(-u_lim, u_lim)), float(rng.uniform(-0.5, 0.5))) for _ in range(comp.m - 1)]
        st_["hist"].append((state["u_prev"], st_["d_prev"]))
    return st_


def feature_inputs(rng, prm: dict, state: dict, slow: bool, steps: int):
    """``steps`` samples after ``state``: (y, x_d, ẋ_d, ẍ_d, t, the desired sample at t + τ),
    the velocities small with ``slow`` (where a Stribeck term and ẋ_r matter), the desired
    trajectory a smooth one."""
    u_lim, ks = prm["u_lim"], (prm["k_s"] if prm["mode"] == "experiment" else 2e3)
    th1 = float(state["theta"][0])
    y_prev = state["y_prev"]
    x2 = rng.uniform(-0.02, 0.02) if slow else rng.uniform(-1.0, 1.0)
    t = rng.uniform(0.0, 10.0)
    out = []
    for _ in range(steps):
        x2 += rng.normal(0, 0.004 if slow else 0.05)
        y = y_prev + x2 * TS
        e = rng.normal(0, 2e-5)
        p = rng.normal(0, 0.1 * u_lim / ks)
        vd = x2 - (p - prm["k1"] * e)
        ad = rng.normal(0, 0.2 * u_lim / th1)
        t += TS
        ahead = (y - e + rng.normal(0, 1e-5), vd + rng.normal(0, 0.002 if slow else 0.02), ad + rng.normal(0, 0.5))
        out.append((y, y - e, vd, ad, t, ahead))
        y_prev = y
    return out


#: the compensation's branches of the compiled step (dcdiarc_comp_step, dcdiarc_block_step,
#: ls_update): the families of each case (fixed, adapted), a ripple, a delay, the law, and the
#: reference's word that the branch was hit over the samples
FEATURES = {
    "fixed terms (cogging, spring, Stribeck on the reference velocity, time-periodic): v_a1 and u + d_eff":
        (dict(kind="c2", fixed=("cogging", "spring", "stribeck", "periodic_disturbance"), slow=True),
         lambda rs: all(abs(r["d_eff"]) > 1e-3 for r in rs)),
    "adapted terms (C2): beta in theta_hat, columns at the interval's mean and at the desired point":
        (dict(kind="c2", adapted=("cogging", "spring", "stribeck", "periodic_disturbance"), slow=True),
         lambda rs: all(np.abs(r["cols_m"]).max() > 1e-3 for r in rs)),
    "adapted terms (C1): their channels after the fourth, with a fixed term":
        (dict(kind="c1", fixed=("cogging",), adapted=("spring", "periodic_disturbance")), lambda rs: True),
    "adapted coefficients on the faces of their box (projection with beta)":
        (dict(kind="c2", adapted=("cogging", "spring"), beta_face=True),
         lambda rs: any(any(i >= 6 for i in r["closed"]) for r in rs)),
    "adapted terms in theory mode (beta's span in k_s2, eq. 22)":
        (dict(kind="c2", theory=True, adapted=("spring", "stribeck"), slow=True), lambda rs: True),
    "force ripple: v / (1 + r(x_d)), the thrust channels times 1 + r(x)":
        (dict(kind="c2", ripple=True), lambda rs: all(abs(r["g_des"] - 1.0) > 1e-3 for r in rs)),
    "force ripple with a fixed term (d_eff not scaled), C1":
        (dict(kind="c1", ripple=True, fixed=("spring",)), lambda rs: True),
    "input delay: v_a1 and d_eff at t + tau, the estimator on u[k-1-n]":
        (dict(kind="c2", delay=True, fixed=("periodic_disturbance", "stribeck"), slow=True),
         lambda rs: all("hist" in r for r in rs) and len(rs) > len(rs[0]["hist"])),   # the ring wrapped
    "input delay, ripple, adapted and fixed terms together":
        (dict(kind="c2", delay=True, ripple=True, adapted=("cogging",), fixed=("spring",)), lambda rs: True),
}
FEATURE_STEPS = 6


def feature_case(name: str, seed: int):
    """Parameters, the compensation's mapping and the law built from its section, a state and
    the samples of ``FEATURES[name]`` from ``seed``."""
    flags = dict(FEATURES[name][0])
    kind, slow = flags.pop("kind"), flags.pop("slow", False)
    theory = flags.pop("theory", False)
    rng = np.random.default_rng(seed)
    prm = draw_params(rng, kind, theory)
    spec = draw_compensation(rng, **flags)
    c = DCDIARC(section(prm, compensation=spec), TS, kind)
    comp = RefComp(spec, c.beta_names)
    assert c.preview_s == comp.tau and c._ring.shape[1] == comp.m, "the law's delay is not the documented one"
    state, _ = draw_state(rng, prm, bounds=("in",) * 6 if kind == "c2" else ("in",) * 4, coupled=rng.random() < 0.5,
                          freeze=False, hold56=False, d0_edge=False, big=False)
    state = feature_state(rng, prm, comp, state)
    return prm, comp, c, state, feature_inputs(rng, prm, state, slow, FEATURE_STEPS)


def feature_run(prm, comp, c, state, samples) -> list[dict]:
    """The samples one after the other on the law from ``state``; each compared with the
    reference from the law's own state before it. Returns the references."""
    set_state(c, state)
    refs = []
    y_prev = state["y_prev"]
    for j, (y, xd, vd, ad, t, ahead) in enumerate(samples):
        before = snapshot(c, y_prev) if j else state
        c.preview(*ahead)
        law = law_outputs(c, c.update(y, xd, vd, ad, t))
        ref = reference_step(prm, before, y, xd, vd, ad, comp=comp, t=t, ahead=ahead if comp.tau > 0 else None)
        if ref["freeze_ambiguous"] and law["frozen"] != ref["frozen"]:
            ref = reference_step(prm, before, y, xd, vd, ad, freeze=law["frozen"], comp=comp, t=t,
                                 ahead=ahead if comp.tau > 0 else None)
        compare(law, ref, f" at sample {j + 1}")
        refs.append(ref)
        y_prev = y
    return refs


FEATURE_SEEDS = 40


@pytest.mark.parametrize("name", list(FEATURES))
def test_each_compensation_branch_is_visited_and_matches(name):
    """Each of the compensation's branches (fixed and adapted terms, on C1 and C2, in theory mode,
    on the faces of β's box; force ripple; input delay; all together) on a law built from a
    section that configures it: FEATURE_STEPS samples one after the other, each against the
    reference from the law's state before it; the first of FEATURE_SEEDS draws that hits the
    branch counts (none: the draws lost it)."""
    want = FEATURES[name][1]
    for seed in range(FEATURE_SEEDS):
        refs = feature_run(*feature_case(name, 30_000 + seed))
        if want(refs):
            return
    raise AssertionError(f"no draw of {FEATURE_SEEDS} hits {name!r}")


def reference_gtcf(gi: dict, gj: dict, p_i: float, p_j: float, e_i: float, e_j: float, vd_i: float, vd_j: float,
                   vfb_prev: float) -> dict:
    """GTCF's feedback for axis i beyond C2's own −k_s,i p_i (docs/control-law.md, "GTCF"), in the
    docs' matrix form: the task frame t = ẋ_d/|ẋ_d|, n = t turned +90°, ε_n = nᵀe;
    p̃ = p + (λ' − 1) k1 n sat_b(ε_n) per axis; K = g_t' t tᵀ + N'^½ n nᵀ N'^½; v_s = −D^½ K D^½ p̃,
    D = diag(k_s); v_fb,raw = v_s,i + k_s,i p_i; g' = 1 + min(1, |ẋ_d|/v_min)(g − 1), λ' alike;
    then the first-order low-pass v_fb = v_fb[k−1] + α (v_fb,raw − v_fb[k−1]) (α < 1).

    gi: axis i's {ks, k1, g_t, g_n, v_min, lam, band, alpha}; gj: the partner's {ks, k1, g_n, lam,
    band}. Returns v_fb [V], its terms' magnitude, ε_n [m] (NaN at rest: no path direction)."""
    s = math.hypot(vd_i, vd_j)
    w = min(1.0, s / gi["v_min"])
    if s > 0.0:
        t = np.array([vd_i, vd_j]) / s
        e_n = float(np.array([-t[1], t[0]]) @ np.array([e_i, e_j]))
    else:                                   # at rest every gain is 1: K = I in any frame
        t, e_n = np.array([1.0, 0.0]), math.nan
    nrm = np.array([-t[1], t[0]])
    pt = np.array([p_i, p_j], dtype=float)
    if s > 0.0:
        for a, g in enumerate((gi, gj)):
            lam = 1.0 + w * (g["lam"] - 1.0)
            pt[a] += (lam - 1.0) * g["k1"] * nrm[a] * min(max(e_n, -g["band"]), g["band"])
    blend = lambda g: 1.0 + w * (g - 1.0)   # noqa: E731
    nh = np.sqrt([blend(gi["g_n"]), blend(gj["g_n"])])
    K = blend(gi["g_t"]) * np.outer(t, t) + np.outer(nh * nrm, nh * nrm)
    dh = np.sqrt([gi["ks"], gj["ks"]])
    terms = -dh[0] * K[0] * dh * pt
    raw = float(terms.sum()) + gi["ks"] * p_i
    scale = float(np.abs(terms).sum()) + abs(gi["ks"] * p_i)
    if gi["alpha"] < 1.0:
        v_fb = vfb_prev + gi["alpha"] * (raw - vfb_prev)
        scale = abs(vfb_prev) + gi["alpha"] * (scale + abs(vfb_prev))
    else:
        v_fb = raw
    return dict(v_fb=v_fb, scale=scale, e_n=e_n, w=w, ptilde=pt)


def gtcf_settings(rng, flags: dict) -> tuple[dict, dict]:
    """The pair's ``gtcf:`` mappings (X, Y): g_t shared, g_n, λ_n, band per axis; X low-passed
    with ``lowpass``; λ_n > 1 with ``lam``, its band wide with ``wide_band``."""
    g_t = rng.uniform(0.5, 2.0)
    out = []
    for ax, partner in (("X", "Y"), ("Y", "X")):
        b = dict(partner=partner, gain_t=g_t, gain_n=rng.uniform(1.0, 4.0), v_min=rng.uniform(0.001, 0.01),
                 lambda_n=rng.uniform(1.2, 2.5) if flags.get("lam") else 1.0,
                 lambda_band=rng.uniform(2e-4, 1e-3) if flags.get("wide_band") else rng.uniform(1e-6, 8e-6))
        if ax == "X" and flags.get("lowpass"):
            b["lowpass_hz"] = rng.uniform(100.0, 2000.0)
        out.append(b)
    return out[0], out[1]


#: GTCF's branches (gtcf_step): the draw's flags and the reference's word that the branch was hit
GTCF_BRANCHES = {
    "uncoupled (the partner not on GTCF): C2 alone": (dict(coupled=False), lambda rs: True),
    "the partner's first sample (its y[k-1] NaN): C2 alone": (dict(yj_nan=True), lambda rs: True),
    "at rest (no path direction): every gain 1, the low-pass decays": (dict(rest=True, lowpass=True),
                                                                        lambda rs: all(r["w"] == 0.0 for r in rs)),
    "below v_min: the gains and lambda_n blended": (dict(slow=True, lam=True, wide_band=True),
                                                    lambda rs: all(0.0 < r["w"] < 1.0 for r in rs)),
    "the task frame: g_t, each axis's g_n and their cross term": (dict(), lambda rs: all(r["w"] == 1.0 for r in rs)),
    "lambda_n within its band": (dict(lam=True, wide_band=True),
                                 lambda rs: any(abs(r["e_n"]) < 2e-4 and r["w"] == 1.0 for r in rs)),
    "lambda_n beyond its band (the contour error saturated)": (dict(lam=True),
                                                               lambda rs: any(abs(r["e_n"]) > 8e-6 for r in rs)),
    "low-pass on the feedback beyond C2's": (dict(lowpass=True, lam=True), lambda rs: True),
    "GTCF over a compiled compensation (dcdiarc_comp_step under v_fb)": (
        dict(comp=True, lam=True), lambda rs: all(abs(r["d_eff"]) > 1e-3 for r in rs)),
}


def gtcf_case(name: str, seed: int):
    """Axis i (X) and its partner j (Y) of a GTCF pair built from their sections, i's state and
    the samples of both for ``GTCF_BRANCHES[name]`` from ``seed``."""
    flags = GTCF_BRANCHES[name][0]
    rng = np.random.default_rng(seed)
    prm_i, prm_j = draw_params(rng, "c2", False), draw_params(rng, "c2", False)
    gx, gy = gtcf_settings(rng, flags)
    spec = draw_compensation(rng, fixed=("cogging", "stribeck"), delay=True) if flags.get("comp") else {}
    ci = GTCF(section(prm_i, gtcf=gx, compensation=spec), TS)
    cj = GTCF(section(prm_j, gtcf=gy), TS)
    comp = RefComp(spec, ci.beta_names)
    state, _ = draw_state(rng, prm_i, bounds=("in",) * 6, coupled=rng.random() < 0.5, freeze=False,
                          hold56=False, d0_edge=False, big=False)
    state = feature_state(rng, prm_i, comp, state)
    state["yj_prev"] = math.nan if flags.get("yj_nan") else rng.uniform(-0.3, 0.3)
    state["vfb_prev"] = rng.uniform(-1.0, 1.0) if flags.get("lowpass") else 0.0
    slow, rest = flags.get("slow"), flags.get("rest")
    mine = feature_inputs(rng, prm_i, state, False, FEATURE_STEPS)
    yj = state["yj_prev"] if state["yj_prev"] == state["yj_prev"] else 0.0
    part = feature_inputs(rng, prm_j, dict(theta=prm_j["tmin"], y_prev=yj), False, FEATURE_STEPS)
    samples = []
    for (y, xd, vd, ad, t, ahead), (y_j, xd_j, vd_j, *_) in zip(mine, part):
        if rest:
            vd = vd_j = ad = 0.0
        elif slow:
            f = gx["v_min"] * rng.uniform(0.2, 0.9) / math.hypot(vd, vd_j)
            vd, vd_j = vd * f, vd_j * f
        samples.append((y, xd, vd, ad, t, ahead, y_j, xd_j, vd_j))
    pair = [{"ks": prm["k_s"], "k1": prm["k1"], "g_t": g["gain_t"], "g_n": g["gain_n"], "v_min": g["v_min"],
             "lam": g["lambda_n"], "band": g["lambda_band"],
             "alpha": 1.0 - math.exp(-2 * math.pi * g["lowpass_hz"] * TS) if g.get("lowpass_hz") else 1.0}
            for prm, g in ((prm_i, gx), (prm_j, gy))]
    return prm_i, comp, ci, cj, pair, state, samples, flags.get("coupled", True)


def gtcf_run(prm, comp, ci, cj, pair, state, samples, coupled) -> list[dict]:
    """The samples one after the other on axis i's compiled step (gtcf_step, as the servo cycle
    calls it, with the partner's block), each compared with the reference (GTCF's feedback, then
    C2's sample with it) from the law's own state before it. Returns the references."""
    set_state(ci, state)
    g0 = ci._L[B_SPAN] + ci._L[B_N]          # GTCF's numbers after the span (gtcf.py's layout)
    ci._F[g0 + G_YJ] = state["yj_prev"]
    ci._F[g0 + G_VFB] = state["vfb_prev"]
    refs = []
    y_prev = state["y_prev"]
    for j, (y, xd, vd, ad, t, ahead, y_j, xd_j, vd_j) in enumerate(samples):
        before = snapshot(ci, y_prev) if j else state
        yj_prev, vfb_prev = float(ci._F[g0 + G_YJ]), float(ci._F[g0 + G_VFB])
        u = gtcf_step(y, xd, vd, ad, *(ahead if comp.tau > 0 else (xd, vd, ad)), t, y_j, xd_j, vd_j, coupled,
                      ci.signals, ci._F, ci._I, ci._L, cj._F, cj._L)
        law = law_outputs(ci, u)
        p_i = (y - y_prev) / TS - vd + prm["k1"] * (y - xd)
        p_j = (y_j - yj_prev) / TS - vd_j + pair[1]["k1"] * (y_j - xd_j)
        if coupled and math.isfinite(p_j):
            g = reference_gtcf(pair[0], pair[1], p_i, p_j, y - xd, y_j - xd_j, vd, vd_j, vfb_prev)
        else:                                # C2 alone for the sample
            g = dict(v_fb=0.0, scale=0.0, e_n=math.nan, w=math.nan)
        ref = reference_step(prm, before, y, xd, vd, ad, comp=comp if comp.spec else None, t=t,
                             ahead=ahead if comp.tau > 0 else None, v_fb=g["v_fb"], v_fb_scale=g["scale"])
        if ref["freeze_ambiguous"] and law["frozen"] != ref["frozen"]:
            ref = reference_step(prm, before, y, xd, vd, ad, freeze=law["frozen"], comp=comp if comp.spec else None,
                                 t=t, ahead=ahead if comp.tau > 0 else None, v_fb=g["v_fb"], v_fb_scale=g["scale"])
        where = f" at sample {j + 1}"
        _close("GTCF's feedback beyond C2's (v_fb)", ci.v_fb, g["v_fb"], g["scale"], where)
        assert (ci.e_n != ci.e_n) == (g["e_n"] != g["e_n"]), f"contour error{where}: law {ci.e_n}, reference {g['e_n']}"
        if g["e_n"] == g["e_n"]:
            _close("contour error e_n", ci.e_n, g["e_n"], abs(y - xd) + abs(y_j - xd_j), where)
        compare(law, ref, where)
        refs.append({**ref, **g})
        y_prev = y
    return refs


@pytest.mark.parametrize("name", list(GTCF_BRANCHES))
def test_each_gtcf_branch_is_visited_and_matches(name):
    """GTCF's branches (uncoupled, the partner's first sample, at rest, below v_min, the task
    frame with per-axis gains, λ_n within and beyond its band, the low-pass, over a compensation)
    on the compiled pair step with the partner's block: FEATURE_STEPS samples one after the other,
    each against the reference (the docs' matrix form of the task-frame feedback, then C2's sample)
    from the law's state before it."""
    want = GTCF_BRANCHES[name][1]
    for seed in range(FEATURE_SEEDS):
        refs = gtcf_run(*gtcf_case(name, 40_000 + seed))
        if want(refs):
            return
    raise AssertionError(f"no draw of {FEATURE_SEEDS} hits {name!r}")


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


@settings(max_examples=examples(100), deadline=None, phases=PHASES)
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

#: where each mutant's term is checked first (a -k expression of this file's tests; the whole file
#: after, when those pass): the law's core, the PID, the compensation's branches, GTCF's
CORE = "one_sample or each_branch or closed_loop"
AREA_PID = "pid"
AREA_COMP = "compensation_branch"
AREA_GTCF = "gtcf_branch"
DC, EST, INV, PIDF, GT = ("motorctl/control/dcdiarc.py", "motorctl/control/estimator.py",
                          "motorctl/control/inversion.py", "motorctl/control/pid.py", "motorctl/control/gtcf.py")

#: (term, file, the line's text, the wrong text, where it is checked first): one deliberate error
#: in the law at a time
MUTANTS = [
    ("u_a: sign of theta1 xdd_d", DC, "va1 = th[0] * af + th[1] * vf", "va1 = -th[0] * af + th[1] * vf", CORE),
    ("u_a: gain x2 on theta2 xd_d", DC,
     "va1 = th[0] * af + th[1] * vf", "va1 = th[0] * af + 2.0 * th[1] * vf", CORE),
    ("u_a: S_f(x2) for S_f(xd_d)", DC, "sfd = s_f_jit(vf)", "sfd = s_f_jit(x2)", CORE),
    ("u_a: sign of theta4", DC, "th[2] * sfd - th[3] - v_comp", "th[2] * sfd + th[3] - v_comp", CORE),
    ("u_s1: sign of k_s p", DC, "v = va1 - d0 - ks * p", "v = va1 - d0 + ks * p", CORE),
    ("u_s1: sign of k1 e in p", DC,
     "p = (x2 - xd_dot) + prm[P_K1] * e", "p = (x2 - xd_dot) - prm[P_K1] * e", CORE),
    ("u_s1: theory k_s2 /2", DC,
     "ks = prm[P_KS1] + hb * hb / prm[P_ETA4]", "ks = prm[P_KS1] + hb * hb / (2.0 * prm[P_ETA4])", CORE),
    ("d0: sign of gamma_d p", DC,
     "d0 = st[S_D0] + ts * prm[P_GD] * p", "d0 = st[S_D0] - ts * prm[P_GD] * p", CORE),
    ("d0: sign in v", DC, "v = va1 - d0 - ks * p", "v = va1 + d0 - ks * p", CORE),
    ("d0: no clip at -d_max", DC,
     "    elif d0 < -dmax:\n        d0 = -dmax\n    st[S_D0] = d0",
     "    elif d0 < -dmax:\n        d0 = d0\n    st[S_D0] = d0", CORE),
    ("adaptation: sign of epsilon", EST, "eps = pred - u_f", "eps = u_f - pred", CORE),
    ("adaptation: rate x2 (Ts)", EST, "val = th[i] + ts * z[i]", "val = th[i] + 2.0 * ts * z[i]", CORE),
    ("adaptation: Gamma downdate sign", EST,
     "val = scale * gam[i, j] - cgi * g[j]", "val = scale * gam[i, j] + cgi * g[j]", CORE),
    ("adaptation: tau without 1/n_k", EST, "    k = eps / nk\n", "    k = eps\n", CORE),
    ("adaptation: forgetting squared", EST,
     "c = h * scale * scale / (1.0 + h * scale * quad)", "c = h * scale / (1.0 + h * scale * quad)", CORE),
    ("adaptation: phi_1 sign (xdd_2f)", EST, "phi[0] = -zd[0]", "phi[0] = zd[0]", CORE),
    ("adaptation: u|u| channel as u^2", EST,
     "inp[4] = u_prev * abs(u_prev)", "inp[4] = u_prev * u_prev", CORE),
    ("adaptation: freeze never", EST,
     "frozen = lambda_max_exceeds(gam, g, scale, c, rho, piv)", "frozen = False", CORE),
    ("projection: none (clip only)", EST,
     "    project_box(z, th, tmin, tmax, gam, piv, coef, vec, pividx, active)\n", "    pass\n", CORE),
    ("projection: wrong multiplier sign test", EST,
     "bad = -lam[mm] if th[j] >= tmax[j] else lam[mm]", "bad = lam[mm] if th[j] >= tmax[j] else -lam[mm]", CORE),
    ("projection: faces never opened (add-only)", EST,
     "        if worst >= 0:\n            active[worst] = False\n            continue\n",
     "        worst = -1\n", CORE),
    ("projection: Gamma-weighting dropped", EST,
     "                z[a] -= piv[m, a] * f\n", "                z[a] -= (piv[m, a] * f if a == j else 0.0)\n", CORE),
    ("inversion: sign of theta5 in Newton", INV,
     "g = r + theta5 * r * r + theta6 * r * r * r - w", "g = r - theta5 * r * r + theta6 * r * r * r - w", CORE),
    ("inversion: quadratic root 4 -> 2", INV, "disc = 1.0 + 4.0 * theta5 * w", "disc = 1.0 + 2.0 * theta5 * w", CORE),
    ("inversion: saturates at 0.9 f(u_M)", INV,
     "    if w >= f_max:\n        return s * u_max\n", "    if w >= 0.9 * f_max:\n        return s * u_max\n", CORE),
    ("inversion: odd symmetry lost", INV, "        s = -1.0\n        w = -v", "        s = 1.0\n        w = -v", CORE),
    ("pid: FF2 on xd_dot", PIDF, "prm[P_FF2] * xd_ddot", "prm[P_FF2] * xd_dot", AREA_PID),
    ("pid: anti-windup reversed", PIDF, "if t * st[S_LIMIT] <= 0.0:", "if t * st[S_LIMIT] >= 0.0:", AREA_PID),
    ("pid: deadband zeroes only", PIDF, "    if t > db:\n        t -= db\n", "    if t > db:\n        t = t\n", AREA_PID),
    ("pid: D on the feedback only", PIDF, "ed = xd_dot - x2", "ed = -x2", AREA_PID),
    # the compensation's fixed terms (dcdiarc_comp_step, dcdiarc_block_step, ls_update)
    ("fixed: +d_eff in v_a1", DC, "th[3] - v_comp  ", "th[3] + v_comp  ", AREA_COMP),
    ("fixed: d_eff not held with u (estimator on u alone)", DC, "    st[S_DC] = v_comp\n", "    st[S_DC] = 0.0\n",
     AREA_COMP),
    ("fixed: the estimator's input u without d_eff", EST, "inp[3] = u_prev + d_prev", "inp[3] = u_prev", AREA_COMP),
    ("fixed: d_eff on xd_dot, not the reference velocity", DC,
     "vr = vf - F[L[B_PRM] + P_K1] * (y - x_d)", "vr = vf", AREA_COMP),
    # adapted terms
    ("adapted: +beta c in v_a1", DC, "va1 -= th[n + j] * cd[j]", "va1 += th[n + j] * cd[j]", AREA_COMP),
    ("adapted: columns at the interval's end, not its mean", DC,
     "\n        xm = 0.5 * (y + y_prev)", "\n        xm = y", AREA_COMP),
    ("adapted: columns at the sample's time, not mid-interval", DC,
     "L[B_CM] + k]), xm, (y - y_prev) / ts, t - 0.5 * ts)", "L[B_CM] + k]), xm, (y - y_prev) / ts, t)", AREA_COMP),
    ("adapted: sign of the basis in phi", EST, "phi[nn + j] = zf[nn + j]", "phi[nn + j] = -zf[nn + j]", AREA_COMP),
    ("adapted: theory k_s2 without beta's span", DC,
     "hb += span[n + j] * abs(cd[j])", "hb += 0.0 * abs(cd[j])", AREA_COMP),
    # force ripple
    ("ripple: v times 1 + r, not divided", DC,
     "w = v / g_des if g_des != 1.0 else v", "w = v * g_des if g_des != 1.0 else v", AREA_COMP),
    ("ripple: the estimator's factor at x_d, not the measured mean", DC,
     "g_meas = 1.0 + comp_thrust(tab, xm)", "g_meas = 1.0 + comp_thrust(tab, xf)", AREA_COMP),
    ("ripple: u|u| channel not scaled", EST, "inp[4] = ug * abs(u_prev)", "inp[4] = u_prev * abs(u_prev)",
     AREA_COMP),
    ("ripple: d_eff scaled with u", EST, "inp[3] = ug + d_prev", "inp[3] = (u_prev + d_prev) * g_prev", AREA_COMP),
    # input delay
    ("delay: the estimator on u[k-1], not the input applied", DC,
     "ls_update(x2, ring[0, ri], ring[1, ri],", "ls_update(x2, st[S_U], st[S_DC],", AREA_COMP),
    ("delay: the ring's index not advanced", DC, "st[S_RI] = float((ri + 1) % m)", "st[S_RI] = float(ri)", AREA_COMP),
    ("delay: v_a1 on this sample, not t + tau", DC,
     "return dcdiarc_block_step(y, x_d, xd_dot, xd_ddot, xf, vf, af, v_comp,",
     "return dcdiarc_block_step(y, x_d, xd_dot, xd_ddot, x_d, xd_dot, xd_ddot, v_comp,", AREA_COMP),
    ("delay: d_eff at t, not t + tau", DC, "tf = t + tab[T_PREVIEW]", "tf = t", AREA_COMP),
    # GTCF (gtcf_step, gtcf_feedback)
    ("gtcf: sign of the contour error", GT, "e_n = (xd_dot * (y_j - x_dj) - xd_dot_j * (y - x_d)) / s",
     "e_n = (xd_dot_j * (y - x_d) - xd_dot * (y_j - x_dj)) / s", AREA_GTCF),
    ("gtcf: g_t's term with t_j q_j of the wrong sign", GT,
     "(gt - 1.0) * ti * (ti * qi + tj * qj)", "(gt - 1.0) * ti * (ti * qi - tj * qj)", AREA_GTCF),
    ("gtcf: cross term with this axis's g_n alone", GT, "math.sqrt(gni * gnj)", "gni", AREA_GTCF),
    ("gtcf: the blend not held at 1 above v_min", GT, "    if w > 1.0:\n        w = 1.0\n",
     "    if w > 1.0:\n        w = w\n", AREA_GTCF),
    ("gtcf: lambda_n not blended below v_min", GT, "(lambda_n - 1.0) * w * k1", "(lambda_n - 1.0) * k1", AREA_GTCF),
    ("gtcf: the contour error not held to its band", GT, "min(max(e_n, -band), band)", "e_n", AREA_GTCF),
    ("gtcf: C2's k_s times lambda_n's term kept in v_fb", GT,
     "- F[prm + P_KS] * dp_i", "+ F[prm + P_KS] * dp_i", AREA_GTCF),
    ("gtcf: the partner's lambda_n from this axis's block", GT,
     "p_j += _contour_dp(Fj[gj + G_LN], Fj[gj + G_LB]", "p_j += _contour_dp(F[g + G_LN], F[g + G_LB]", AREA_GTCF),
    ("gtcf: low-pass without its state", GT,
     "v_fb = F[g + G_VFB] + F[g + G_ALPHA] * (v_fb - F[g + G_VFB])", "v_fb = F[g + G_ALPHA] * v_fb", AREA_GTCF),
    ("gtcf: low-pass skipped when the feedback is 0 (at rest)", GT,
     "if F[g + G_ALPHA] < 1.0:", "if F[g + G_ALPHA] < 1.0 and v_fb != 0.0:", AREA_GTCF),
    ("gtcf: the partner's y[k-1] read after it is replaced", GT,
     "    y_jp = F[g + G_YJ]\n    F[g + G_YJ] = y_j\n", "    F[g + G_YJ] = y_j\n    y_jp = F[g + G_YJ]\n", AREA_GTCF),
    ("gtcf: coupled when the partner is not on GTCF", GT, "    if coupled:\n", "    if True:\n", AREA_GTCF),
    ("gtcf: a NaN partner sample not refused", GT, "if p_j == p_j and abs(p_j) < math.inf:", "if True:", AREA_GTCF),
    ("gtcf: the compensation dropped under GTCF", GT, "if F[g + G_COMP] != 0.0:", "if False:", AREA_GTCF),
]


def run_mutants(jit: bool = True, jobs: int = 1, only: str = "") -> int:
    """Copy the law into a scratch tree, make one term wrong at a time (:data:`MUTANTS`), run
    this file there, and report whether it fails (caught) or passes (missed): first the tests of
    the mutant's area (its -k expression), then, when those pass, the whole file. Hypothesis does
    not shrink a failure here (``LAW_REFERENCE_MUTANT``: the first failing example is enough).
    The repository is not touched; numba's cache of each copy lives in its scratch tree and goes
    with it (a mutant compiles the kernels afresh: 1-3 min each on 2 cores; ``jit`` False runs
    them as Python, NUMBA_DISABLE_JIT). ``jobs``: mutants run at once (a scratch tree each);
    ``only``: the mutants whose term contains it. Prints a line per mutant, then the counts and
    the time. Returns 0 when every mutant is caught and the unmutated copy passes."""
    import time
    from concurrent.futures import ThreadPoolExecutor
    repo = Path(__file__).resolve().parents[1]
    t0 = time.monotonic()
    chosen = [m for m in MUTANTS if only in m[0]]

    def tree() -> Path:
        scratch = Path(tempfile.mkdtemp(prefix="law-mutants-"))
        for part in ("motorctl", "motorctl_drivers", "tests", "pyproject.toml"):
            src = repo / part
            if src.is_dir():
                shutil.copytree(src, scratch / part, ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
            else:
                shutil.copy2(src, scratch / part)
        return scratch

    def env_of(scratch: Path) -> dict:
        env = dict(os.environ, PYTHONPATH=str(scratch), MOTORCTL_CACHE_DIR=str(scratch / ".cache"),
                   LAW_REFERENCE_MUTANT="1")
        env.pop("NUMBA_DISABLE_JIT", None)
        env.pop("NUMBA_CACHE_DIR", None)
        if not jit:
            env["NUMBA_DISABLE_JIT"] = "1"
        return env

    def run(scratch: Path, area: str | None) -> tuple[int, str]:
        argv = [sys.executable, "-m", "pytest", "-q", "-x", "-n", "0", "--noconftest", "-p", "no:cacheprovider",
                "-p", "no:randomly", "tests/test_law_reference.py"] + (["-k", area] if area else [])
        p = subprocess.run(argv, cwd=scratch, env=env_of(scratch), capture_output=True, text=True)
        failed = [ln for ln in p.stdout.splitlines() if ln.startswith(("FAILED", "ERROR"))]
        return p.returncode, (failed[0] if failed else (p.stdout.strip().splitlines() or ["(no output)"])[-1])

    def one(mutant) -> tuple[str, bool, str]:
        term, rel, old, new, area = mutant
        scratch = tree()
        try:
            path = scratch / rel
            orig = path.read_text()
            if orig.count(old) != 1:
                return term, False, f"NOT APPLIED: the mutant's text is in {rel} {orig.count(old)} times, not once"
            path.write_text(orig.replace(old, new))
            rc, last = run(scratch, area)
            if rc == 0:                      # its area's tests pass: the whole file
                rc, last = run(scratch, None)
            caught = rc != 0 and "FAILED" in last
            return term, caught, (f"caught: {last}" if caught else f"MISSED (rc {rc}): {last}")
        finally:
            shutil.rmtree(scratch, ignore_errors=True)

    base = tree()
    try:
        which = subprocess.run([sys.executable, "-c", "import motorctl; print(motorctl.__file__)"], cwd=base,
                               env=env_of(base), capture_output=True, text=True).stdout.strip()
        assert which.startswith(str(base)), f"the copy is not the one imported: {which}"
        rc, last = run(base, None)
    finally:
        shutil.rmtree(base, ignore_errors=True)
    ok = rc == 0
    print(f"{'(none: the law as it is)':62s} {'passes' if ok else 'FAILS: ' + last}", flush=True)
    caught = 0
    with ThreadPoolExecutor(max(1, jobs)) as ex:
        for term, hit, line in ex.map(one, chosen):
            caught += hit
            ok &= hit
            print(f"{term:62s} {line}", flush=True)
    print(f"\n{len(chosen)} mutants, {caught} caught, {len(chosen) - caught} missed; "
          f"{time.monotonic() - t0:.0f} s ({'compiled' if jit else 'NUMBA_DISABLE_JIT'}, {max(1, jobs)} at a time)")
    return 0 if ok else 1


if __name__ == "__main__":
    if "--mutants" in sys.argv:
        sys.path.insert(0, str(Path(__file__).resolve().parent))
        jobs = next((int(a.split("=", 1)[1]) for a in sys.argv if a.startswith("--jobs=")), 1)
        only = next((a.split("=", 1)[1] for a in sys.argv if a.startswith("--only=")), "")
        raise SystemExit(run_mutants(jit="--nojit" not in sys.argv, jobs=jobs, only=only))
    raise SystemExit(pytest.main(["-q", "-n", "0", __file__]))
