"""GTCF, the contouring law of a pair of axes (motorctl.control.gtcf; docs/control-law.md, "GTCF:
the contouring law of a pair of axes"), against a plain numpy reference of its equations.

The reference builds the task frame as an explicit rotation matrix T = [tᵀ; nᵀ] and the
feedback as the matrix product −D^½ (g_t t tᵀ + N^½ n nᵀ N^½) D^½ p, N = diag(g_n,X, g_n,Y)
(numpy, no numba, nothing of the law's arithmetic); the law computes it as a scalar formula in
compiled code. Everything
else of a GTCF sample is C2's per-axis law, checked against its own reference in
tests/test_law_reference.py, so one GTCF sample is compared with one C2 sample from the same
state: v must differ by the reference's feedback minus C2's −k_s p, and e, p, d̂0, θ̂ must be
C2's. Tolerance as there: RTOL times the sum of the magnitudes of the terms.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from conftest import examples
from hypothesis import given, settings
from hypothesis import strategies as st

from motorctl.control.dcdiarc import C2, P_K1, P_KS, S_Y_PREV  # the law's layout (to set a state), no arithmetic
from motorctl.control.gtcf import G_ALPHA, G_GN, G_GT, G_LN, G_VFB, G_VMIN, G_YJ, GTCF, gtcf_feedback, gtcf_step
from motorctl.control.params import ControllerConfig
from motorctl.control.signals import SIG_D0, SIG_E, SIG_P, SIG_THETA, SIG_V

TS = 2e-4
RTOL = 1e-9
X_MIN = [0.05, 0.08, 0.05, -0.5, -0.015, -0.002]
X_MAX = [0.3, 0.5, 0.5, 0.5, 0.0, 0.0]


def _section(partner: str, g_t: float = 1.0, g_n: float = 3.0, v_min: float = 0.002) -> ControllerConfig:
    return ControllerConfig.model_validate(dict(
        type="gtcf", u_lim=10.0, theta_min=X_MIN, theta_max=X_MAX, theta_hat0=[0.2, 0.2, 0.1, 0.0, -0.01, -0.001],
        gamma0=[2.0, 50.0, 100.0, 500.0, 0.05, 0.005], k_s=50.0, k1=500.0, gamma_d=500.0, d_hat_max=1.0,
        gtcf=dict(partner=partner, gain_t=g_t, gain_n=g_n, v_min=v_min)))


def reference_feedback(p, v, ks, g_t, g_n, v_min):
    """−D^½ (g_t' t tᵀ + N'^½ n nᵀ N'^½) D^½ p (2,), t = v/|v|, n = t rotated +90°, N' =
    diag(g_n') (g_n: both axes'), the gains blended to 1 below v_min [V]."""
    s = float(np.hypot(v[0], v[1]))
    w = min(1.0, s / v_min)
    gt, gn = 1.0 + w * (g_t - 1.0), 1.0 + w * (np.asarray(g_n, float) - 1.0)
    t = np.asarray(v, float) / s if s > 0 else np.array([1.0, 0.0])
    n = np.array([-t[1], t[0]])
    Nh = np.diag(np.sqrt(gn))
    Dh = np.diag(np.sqrt(ks))
    K = Dh @ (gt * np.outer(t, t) + Nh @ np.outer(n, n) @ Nh) @ Dh
    return -K @ np.asarray(p, float), np.abs(K) @ np.abs(p)


@pytest.fixture(scope="module")
def laws():
    gx = GTCF.from_config(_section("Y"), TS)
    gy = GTCF.from_config(_section("X"), TS)
    gx.link_axes(["X", "Y"], 0)
    gy.link_axes(["X", "Y"], 1)
    c2 = C2.from_config(_section("Y"), TS)
    return gx, gy, c2


finite = dict(allow_nan=False, allow_infinity=False)


@settings(max_examples=examples(60), deadline=None)
@given(y=st.lists(st.floats(-0.02, 0.42, **finite), min_size=2, max_size=2),
       dy=st.lists(st.floats(-2e-4, 2e-4, **finite), min_size=2, max_size=2),
       err=st.lists(st.floats(-1e-4, 1e-4, **finite), min_size=2, max_size=2),
       v=st.lists(st.floats(-1.0, 1.0, **finite), min_size=2, max_size=2),
       ad=st.floats(-10.0, 10.0, **finite),
       ks=st.lists(st.floats(5.0, 500.0, **finite), min_size=2, max_size=2),
       k1=st.lists(st.floats(50.0, 2000.0, **finite), min_size=2, max_size=2),
       g=st.lists(st.floats(0.2, 8.0, **finite), min_size=3, max_size=3),
       v_min=st.sampled_from([1e-3, 0.002, 0.5]))
def test_one_sample_against_reference(laws, y, dy, err, v, ad, ks, k1, g, v_min):
    """One GTCF sample from a drawn state (g: g_t, X's g_n, Y's g_n): v = C2's v + (reference
    feedback + k_s p), the rest C2's."""
    gx, gy, c2 = laws
    yp = [y[0] - dy[0], y[1] - dy[1]]
    xd = [y[0] - err[0], y[1] - err[1]]
    for c in (gx, c2):
        c.reset(yp[0], keep_theta=False)
        c._prm[P_KS] = ks[0]
        c._prm[P_K1] = k1[0]
    gy._prm[P_KS] = ks[1]
    gy._prm[P_K1] = k1[1]
    tab = gx._span[6:]                              # GTCF's numbers follow the span of the θ box
    tab[G_GT], tab[G_GN], tab[G_VMIN] = g[0], g[1], v_min
    tab[G_YJ] = yp[1]
    gy._span[6 + G_GN] = g[2]                       # the partner's contour gain comes from its block
    u = gtcf_step(y[0], xd[0], v[0], ad, xd[0], v[0], ad, 0.0, y[1], xd[1], v[1], True, gx.signals, gx._F, gx._I,
                  gx._L, gy._F, gy._L)
    u_c2 = c2.update(y[0], xd[0], v[0], ad)
    p = [(y[i] - yp[i]) / TS - v[i] + k1[i] * (y[i] - xd[i]) for i in range(2)]
    ref, scale = reference_feedback(p, v, np.array(ks), g[0], g[1:], v_min)
    want = c2.v + ref[0] + ks[0] * p[0]
    tol = RTOL * (abs(c2.v) + 2.0 * ks[0] * abs(p[0]) + scale[0]) + 1e-300
    assert abs(gx.signals[SIG_V] - want) <= tol, (gx.signals[SIG_V], want)
    assert abs(gx.v_fb - (ref[0] + ks[0] * p[0])) <= tol
    for s in (SIG_E, SIG_P, SIG_D0):
        assert gx.signals[s] == c2.signals[s]
    assert np.array_equal(gx.signals[SIG_THETA:SIG_THETA + 6], c2.signals[SIG_THETA:SIG_THETA + 6])
    assert abs(u) <= 10.0 and abs(u_c2) <= 10.0


def test_uncoupled_sample_is_c2(laws):
    """A partner that does not run GTCF (coupled False) or has no y[k−1] yet (NaN): C2's sample."""
    gx, gy, c2 = laws
    for coupled, yjp in ((False, 0.1), (True, math.nan)):
        for c in (gx, c2):
            c.reset(0.1, keep_theta=False)
        gx._span[6 + G_YJ] = yjp
        u = gtcf_step(0.10001, 0.1, 0.05, 1.0, 0.1, 0.05, 1.0, 0.0, 0.2, 0.2, 0.05, coupled, gx.signals, gx._F, gx._I,
                      gx._L, gy._F, gy._L)
        assert u == c2.update(0.10001, 0.1, 0.05, 1.0)
        assert gx.v_fb == 0.0


@pytest.mark.parametrize("phi", np.linspace(0.0, 2 * np.pi, 9)[:-1] + 0.3)
def test_task_frame_rotation(phi):
    """On a circle, equal k_s: a purely radial (normal) error gives only the contour gain's force
    −g_n k_s p, a purely tangential one only −g_t k_s p; both directions, both axes."""
    ks, gt, gn, v_min = 80.0, 0.7, 4.0, 1e-3
    t = np.array([-math.sin(phi), math.cos(phi)])      # CCW: the desired velocity's direction
    n = np.array([math.cos(phi), math.sin(phi)])       # radial
    vd = 0.1 * t
    for d, gain in ((n, gn), (t, gt)):
        p = 3e-3 * d
        total = [-ks * p[i] + gtcf_feedback(p[i], p[1 - i], vd[i], vd[1 - i], ks, ks, gt, gn, gn, v_min)
                 for i in range(2)]
        np.testing.assert_allclose(total, -gain * ks * p, rtol=1e-12, atol=1e-15)
    # at rest the gains blend to 1: C2's −k_s p in every direction
    p = np.array([1e-3, -2e-3])
    assert all(gtcf_feedback(p[i], p[1 - i], 0.0, 0.0, ks, ks, gt, gn, 2.0, v_min) == 0.0 for i in range(2))


@pytest.mark.parametrize("phi", [0.0, 0.5 * math.pi, math.pi, 1.5 * math.pi, 0.7])
def test_contour_gain_per_axis(phi):
    """Each axis its own contour gain: on a circle (CCW, equal k_s) where the normal is an axis
    (the other axis's reversal), a radial error meets that axis's g_n alone; between, a radial
    p = |p| n meets −k_s a |p| N^½ n, a = nᵀ N^½ n = √g_nX n_X² + √g_nY n_Y² (so nᵀ of it is
    −k_s a² |p|, and with unequal gains a part along the path: N^½ n is not n)."""
    ks, gt, gx, gy, v_min = 60.0, 1.0, 2.5, 1.5, 1e-3
    t = np.array([-math.sin(phi), math.cos(phi)])
    n = np.array([math.cos(phi), math.sin(phi)])
    vd = 0.1 * t
    p = 2e-3 * n
    g = (gx, gy)
    total = np.array([-ks * p[i] + gtcf_feedback(p[i], p[1 - i], vd[i], vd[1 - i], ks, ks, gt, g[i], g[1 - i], v_min)
                      for i in range(2)])
    a = math.sqrt(gx) * n[0] ** 2 + math.sqrt(gy) * n[1] ** 2
    assert float(n @ total) == pytest.approx(-ks * a * a * 2e-3, rel=1e-12)
    np.testing.assert_allclose(total, -ks * a * 2e-3 * np.array([math.sqrt(gx) * n[0], math.sqrt(gy) * n[1]]),
                               rtol=1e-12, atol=1e-15)
    if abs(n[1]) < 1e-12:                                        # X's reversal: the normal is X
        assert total[0] == pytest.approx(-gx * ks * p[0], rel=1e-12)


def test_lowpass_on_the_task_frame_feedback(laws):
    """With ``lowpass_hz`` the feedback beyond C2's is the first-order low-pass of the raw one:
    v_fb[k] = v_fb[k−1] + α (raw − v_fb[k−1]), α = 1 − exp(−2π f_c Ts); the same sample with
    α = 1 gives the raw feedback."""
    gx, gy, c2 = laws
    gy._span[6 + G_GN] = 2.0
    args = (0.10001, 0.1, 0.05, 0.0, 0.1, 0.05, 0.0, 0.0, 0.2, 0.2, 0.05, True)
    raw = []
    for alpha in (1.0, 1.0 - math.exp(-2 * math.pi * 500.0 * TS)):
        gx.reset(0.1, keep_theta=False)
        tab = gx._span[6:]                               # (the reset rebinds the block)
        tab[G_GT], tab[G_GN], tab[G_VMIN] = 1.0, 2.0, 1e-3
        tab[G_ALPHA] = alpha
        tab[G_YJ] = 0.2
        tab[G_VFB] = 0.3                                 # the filter's state from a sample before
        gtcf_step(*args, gx.signals, gx._F, gx._I, gx._L, gy._F, gy._L)
        raw.append(gx.v_fb)
    assert raw[0] != 0.0
    assert raw[1] == pytest.approx(0.3 + (1.0 - math.exp(-2 * math.pi * 500.0 * TS)) * (raw[0] - 0.3), rel=1e-12)
    tab[G_ALPHA] = 1.0


@pytest.mark.parametrize("phi", [0.0, 0.5 * math.pi, 0.7, 4.0])
def test_contour_error_gain_in_the_sliding_variable(laws, phi):
    """λ_n: with ė = ẋ_d (p = k1 e), equal k_s and k1 and one g_n, a position error δ along the
    normal meets −g_n λ_n k_s k1 δ (the contour entry of Λ is λ_n k1), one along the tangent
    −g_t k_s k1 δ, as without λ_n; beyond the band b (5 µm), −g_n k_s k1 (δ + (λ_n − 1) b). The
    samples' v_fb are the totals less C2's −k_s p."""
    gx, gy, c2 = laws
    ks, k1, gt, gn, lam, v_min, d = 50.0, 500.0, 1.0, 2.0, 1.5, 1e-3, 2e-6
    t = np.array([-math.sin(phi), math.cos(phi)])
    n = np.array([math.cos(phi), math.sin(phi)])
    vd = 0.1 * t
    xd = np.array([0.1, 0.2])
    try:
        for a in (gx, gy):
            a.reset(0.0, keep_theta=False)
            a._span[6 + G_GT], a._span[6 + G_GN], a._span[6 + G_VMIN], a._span[6 + G_LN] = gt, gn, v_min, lam
            a._prm[P_KS], a._prm[P_K1] = ks, k1
        big = 4e-5                                            # beyond the 5 µm band: λ_n's part stops there
        for dirn, d, want in ((n, d, -gn * lam * ks * k1 * d), (t, d, -gt * ks * k1 * d),
                              (n, big, -gn * ks * k1 * (big + (lam - 1.0) * 5e-6))):
            y = xd + d * dirn
            yp = y - vd * TS                                  # (y − y[k−1]) / Ts = ẋ_d: p = k1 e
            tot = []
            for i, (a, b) in enumerate(((gx, gy), (gy, gx))):
                a._st[S_Y_PREV] = yp[i]
                a._span[6 + G_YJ] = yp[1 - i]
                gtcf_step(y[i], xd[i], vd[i], 0.0, xd[i], vd[i], 0.0, 0.0, y[1 - i], xd[1 - i], vd[1 - i], True,
                          a.signals, a._F, a._I, a._L, b._F, b._L)
                tot.append(a.v_fb - ks * k1 * d * dirn[i])
            np.testing.assert_allclose(tot, want * dirn, rtol=1e-9, atol=1e-12)
    finally:
        for a in (gx, gy):
            a._span[6 + G_LN] = 1.0


@pytest.mark.parametrize("phi", [0.3, 0.9, 1.3])
def test_the_margins_take_lambda_at_the_share_the_axis_carries(laws, phi):
    """autotune's margins at a point of the span (gtcf_tune.span_lambda): where the contour
    direction's share of X is s = n_X², X's own stiffness in the law (X's error alone, Y's λ_n 1)
    is k_s g k1 λ' with g = g_t + (g_n − g_t) s and λ' = span_lambda(g, g_t, g_n, λ_n)."""
    from motorctl.commission.gtcf_tune import span_lambda
    gx, gy, c2 = laws
    ks, k1, gn, lam, d = 50.0, 500.0, 2.0, 1.5, 1e-6
    t = np.array([-math.sin(phi), math.cos(phi)])
    vd = 0.1 * t
    xd = np.array([0.1, 0.2])
    try:
        for a, la in ((gx, lam), (gy, 1.0)):
            a.reset(0.0, keep_theta=False)
            a._span[6 + G_GT], a._span[6 + G_GN], a._span[6 + G_VMIN], a._span[6 + G_LN] = 1.0, gn, 1e-3, la
            a._prm[P_KS], a._prm[P_K1] = ks, k1
        y = xd + np.array([d, 0.0])
        yp = y - vd * TS
        gx._st[S_Y_PREV], gx._span[6 + G_YJ] = yp[0], yp[1]
        gtcf_step(y[0], xd[0], vd[0], 0.0, xd[0], vd[0], 0.0, 0.0, y[1], xd[1], vd[1], True,
                  gx.signals, gx._F, gx._I, gx._L, gy._F, gy._L)
        s = math.cos(phi) ** 2
        g = 1.0 + (gn - 1.0) * s
        assert gx.v_fb - ks * k1 * d == pytest.approx(-ks * g * k1 * span_lambda(g, 1.0, gn, lam) * d, rel=1e-9)
    finally:
        for a in (gx, gy):
            a._span[6 + G_LN] = 1.0


def test_contour_error_gain_in_the_linearisation():
    """GTCF.linearise with λ_n: C2's loop at k_s (1 + (g − 1) F) plus F k_s g (λ_n − 1) k1
    (unfiltered: F = 1), λ_n = 1 the same as without."""
    gains = {"k_s": 48.0, "k1": 1067.0, "gamma_d": 500.0, "g": 2.0, "lowpass_hz": None}
    w = np.array([10.0, 600.0, 3000.0])
    base = GTCF.linearise(gains, TS, w)
    assert np.array_equal(GTCF.linearise(dict(gains, lambda_n=1.0), TS, w), base)
    np.testing.assert_allclose(GTCF.linearise(dict(gains, lambda_n=1.5), TS, w) - base,
                               48.0 * 2.0 * 0.5 * 1067.0, rtol=1e-12)


def test_closed_loop_circle_beats_c2():
    """A short circle (R 10 mm, 100 mm/s) through circle-test's own path on the simulated gantry,
    virtual clock: GTCF's largest radial deviation and G(b) are below C2's, no fault."""
    from motorctl.app.circle_test import run_circle_test
    from motorctl.config import load_config
    from conftest import REPO
    loaded = load_config(str(REPO / "configs" / "gantry.yaml"))
    res = {c: run_circle_test(loaded, 0.01, 0.1, c) for c in ("c2", "gtcf")}
    for r in res.values():
        assert r.underruns == 0
    f = {c: max(r.result.F_max, -r.result.F_min) for c, r in res.items()}
    assert f["gtcf"] < f["c2"], f
    assert res["gtcf"].result.G_b < res["c2"].result.G_b


# ---------------------------------------------------------------- autotune of the pair's gains
def _measured(loaded, raw, axis):
    """An axis's result of autotune's steps 1-2 (:func:`motorctl.commission.autotune.autotune`
    with measure_only) as a noise-free measurement would give it: the "measured" response is the
    simulated plant's own model (its driver section: mass, force constant, viscous friction, the
    structural mode, the current loop, the delay; :func:`motorctl.commission.loopshape.plant_model_frf`)
    and the rest spectrum the encoder's white noise. The measurement and the fit are
    tests/test_autotune.py's; here only the GTCF step, deterministic and fast."""
    from motorctl.commission.choose import grid_w
    from motorctl.commission.loopshape import plant_model_frf
    from motorctl.commission.rule import RULE
    d = raw["axes"][axis]["driver"]
    sec = loaded.axes[axis].controller
    ts = loaded.period_s
    model = {"theta1": d["mass_kg"] / d["a1_N_per_V"], "theta2": d["viscous_N_s_per_m"] / d["a1_N_per_V"],
             "load_fraction": d["mode_load_fraction"], "mode_hz": d["mode_hz"], "mode_damping": d["mode_damping"],
             "current_loop_hz": d["current_loop_hz"], "delay_s": d["current_loop_delay_s"],
             "theta3": d["coulomb_N"] / d["a1_N_per_V"], "theta4": d["offset_N"] / d["a1_N_per_V"]}
    model["sigma"] = {k: 0.0 for k in model}
    w = grid_w(ts)
    G = plant_model_frf(model, ts, w)
    f = np.fft.rfftfreq(1024, ts)
    rest_psd = (f, np.full(f.size, 2.0 * d["encoder_noise_m"] ** 2 * ts))
    return {"axis": axis, "measure": {"rest_psd": rest_psd}, "model": model,
            "theta_hat0": [float(x) for x in sec.theta_hat0], "w": w, "G_fit": G, "G_w": G, "choice": {},
            "verify": {}, "reference": None, "gains": {}, "extra": {}, "ts": ts, "section": sec, "rule": RULE}


def test_autotune_writes_the_pairs_gains_by_the_rule(tmp_path, monkeypatch):
    """autotune's GTCF step on configs/gantry.yaml (its gtcf blocks; the configured C2 gains, the
    plant's own response as measured, a short test contour R 10 mm at 100 mm/s): each axis's
    gain_n of the grid and its low-pass (none or LOWPASS_HZ) written in its block with gain_t 1
    (partner and v_min kept); the margins reported at least the rule's on both axes (and found
    again from the measured response at each axis's choice at 100/75/50 %); the search started
    at each axis's first admissible option and moved only the axis a failed run named, to its
    next option (its low-pass after a failure on its rest noise, else its next lower g_n); then
    on that choice only an axis's λ_n raised, kept where its runs passed; the same margins and
    the same figures of the chosen gains' contour run a second time."""
    import yaml
    from motorctl.commission import gtcf_tune
    from motorctl.commission.autotune import write_config
    from motorctl.commission.loopshape import c_frf, loop_margins
    from motorctl.commission.rule import GM_MIN_DB, MS_MAX_DB, PM_MIN_DEG, RULE, SCALES
    from motorctl.config import config_from_dict, load_yaml
    from conftest import REPO
    src = str(REPO / "configs" / "gantry.yaml")
    raw = load_yaml(src)
    loaded = config_from_dict(raw, src)
    res = [_measured(loaded, raw, a) for a in ("X", "Y")]
    monkeypatch.setattr(gtcf_tune, "SIDE_S", 0.35)      # the rectangle's edges: 0.35 s (0.05 s of rest), for time
    kw = dict(full_periods=0, radius=0.01, feed=0.1, max_runs=5)
    tp = gtcf_tune.tune_pair(loaded, raw, *res, **kw)
    new = write_config(raw, res, src, tmp_path / "autotuned.yaml", [tp])
    g = tp["gains"]
    opt = {a: (g["gain_n"][a], g["lowpass_hz"][a], g["lambda_n"][a]) for a in ("X", "Y")}
    assert g["gain_t"] == 1.0
    assert all(opt[a][0] in gtcf_tune.GAIN_N and opt[a][1] in (None, gtcf_tune.LOWPASS_HZ)
               and opt[a][2] in gtcf_tune.LAMBDA_N for a in opt)
    text = (tmp_path / "autotuned.yaml").read_text()
    back = yaml.safe_load(text)
    assert "# " in text and f"gtcf X-Y: gain_t 1, gain_n {gtcf_tune._opts(opt)}" in text
    for a, b in (("X", "Y"), ("Y", "X")):
        blk = back["axes"][a]["controller"]["gtcf"]
        assert blk == new["axes"][a]["controller"]["gtcf"]
        assert (blk["gain_t"], blk["gain_n"], blk["lowpass_hz"], blk["lambda_n"]) == (1.0, *opt[a])
        assert blk["partner"] == b and blk["v_min"] == raw["axes"][a]["controller"]["gtcf"]["v_min"]
    config_from_dict(back, str(tmp_path / "autotuned.yaml"))          # the written file is a valid config
    for r in res:
        a = r["axis"]
        m = tp["margins"][a]
        assert m["gm_db"] >= GM_MIN_DB and m["pm_deg"] >= PM_MIN_DEG and m["ms_db"] <= MS_MAX_DB, m
        c2 = gtcf_tune.c2_gains(r)
        L = c_frf("gtcf", gtcf_tune.gtcf_gains(c2, *opt[a]), r["ts"], r["w"], r["theta_hat0"]) * r["G_w"]
        f = r["w"] / (2 * np.pi)
        assert all(RULE.holds(loop_margins(s * L, f)) for s in SCALES)
        assert (*opt[a][:2], 1.0) in tp["admissible"][a]
    # the search: from each axis's first admissible option, one axis to its next after each failure
    cands, raised = [], []
    for n, *_ in tp["runs"]:
        to = raised if any(o[2] != 1.0 for o in n.values()) else cands
        if not to or to[-1] != n:
            to.append(n)
    if cands:
        assert cands[0] == {a: tp["admissible"][a][0] for a in ("X", "Y")}
        for prev, nxt in zip(cands, cands[1:]):
            why = next(w for n, _, _, _, w in tp["runs"] if n == prev and w)
            named = why.split(":")[0]
            moved = [a for a in prev if prev[a] != nxt[a]]
            assert len(moved) == 1
            adm = tp["admissible"][moved[0]]
            i, j = adm.index(prev[moved[0]]), adm.index(nxt[moved[0]])
            # the next option: the same g_n low-passed after a failure on the rest noise, else
            # the next lower g_n
            lower = next(k for k in range(i + 1, len(adm)) if adm[k][0] < adm[i][0])
            assert j == lower or (j == i + 1 and f"{named}: u at rest" in why), (prev, nxt, why)
            assert moved[0] == named or prev[named][0] == 1.0
        base = cands[-1]
        if opt != {"X": (1.0, None, 1.0), "Y": (1.0, None, 1.0)}:
            assert {a: o[:2] for a, o in base.items()} == {a: o[:2] for a, o in opt.items()}
            assert not any(w for n, _, _, _, w in tp["runs"] if n == opt)
        # λ_n's step: each candidate the choice with one more axis's λ_n raised
        for n in raised:
            assert {a: o[:2] for a, o in n.items()} == {a: o[:2] for a, o in base.items()}
            assert any(n[a][2] > 1.0 and base[a][2] == 1.0 for a in n)
    # deterministic: the margins and the chosen's run on the test contour come out the same again
    pair = ("X", "Y")
    c2 = {r["axis"]: gtcf_tune.c2_gains(r) for r in res}
    for r in res:
        assert gtcf_tune.axis_margins(r, c2[r["axis"]], 1.0, *opt[r["axis"]])[0] == tp["margins"][r["axis"]]
    if tp["chosen"].get("contour") is not None:
        again = gtcf_tune.contour_run(gtcf_tune.with_gains(raw, pair, c2, 1.0, opt), src, pair, "gtcf", 0.01, 0.1)
        for a in pair:
            for k in ("saturated", "u_rest_rms_V", "u_peak_V", "osc_ratio", "fault"):
                x, y = again[a][k], tp["chosen"]["contour"][a][k]
                assert x == y or (x != x and y != y), (a, k, x, y)


def test_a_pair_with_two_tangential_gains_is_refused(tmp_path):
    """The pair's two gtcf blocks with different gain_t: `motorctl circle-test` exits 2 with the
    key and why, and starts nothing (no log written)."""
    import subprocess
    import sys

    import yaml
    from conftest import REPO
    raw = yaml.safe_load((REPO / "configs" / "gantry.yaml").read_text())
    raw["axes"]["Y"]["controller"]["gtcf"]["gain_t"] = 1.5
    cfg = tmp_path / "g.yaml"
    cfg.write_text(yaml.safe_dump(raw))
    log = tmp_path / "c.log"
    r = subprocess.run([sys.executable, "-m", "motorctl", "circle-test", str(cfg), "--controller", "gtcf",
                        "--radius", "0.01", "--log", str(log)], capture_output=True, text=True, timeout=300, cwd=REPO)
    assert r.returncode == 2, (r.returncode, r.stderr)
    assert "gtcf" in r.stderr and "gain_t" in r.stderr and "Traceback" not in r.stderr
    assert not any(tmp_path.glob("c*.log"))
