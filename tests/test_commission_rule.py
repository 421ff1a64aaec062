"""The commissioning rule's pieces that read the plant and the runs, without running the machine:
the short runs' saturation bound (the full run's allowed rate, stated statistically), the family's
damping ratios on a rigid plant, and the verification's step up where the margins allow."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import stats

from motorctl.commission import verify as V
from motorctl.commission.choose import choose_gains, family_zetas, grid_w
from motorctl.commission.evaluate import sat_dispersion
from motorctl.commission.loopshape import plant_model_frf
from motorctl.commission.rule import SAT_ALPHA, ZETA_RIGID
from motorctl.config import load_yaml
from motorctl.control import controller_class
from motorctl.control.base import Controller

TS = 2e-4
REF_FULL = {"saturated": 18, "samples": 200000, "u_rest_rms_V": 0.04}    # rigid Y's shipped C2, 40 s
PSD = (np.arange(1.0, 100.0), np.ones(99))
REF_SHORT = {"saturated": 0, "samples": 40000, "u_rest_rms_V": 0.04, "e_psd": PSD}     # its first 8 s


def test_sat_dispersion_counts_episodes_not_samples():
    sat = np.zeros(100, bool)
    assert sat_dispersion(sat) == 1.0
    sat[[3, 50]] = True                      # two single samples: Poisson-like
    assert sat_dispersion(sat) == 1.0
    sat[10:14] = True                        # and one episode of 4: (1 + 1 + 16) / 6
    assert sat_dispersion(sat) == pytest.approx(18.0 / 6.0)


def test_a_full_run_is_held_to_the_constraint_itself():
    """40 s against the configured controller's 40 s: 1.5 x max(its count, 10), as the search's
    constraint (rigid Y: 27)."""
    assert V.limits(REF_FULL, 10.0, 200000, REF_FULL)[0] == 27
    assert V.limits(None, 10.0, 200000)[0] == 15          # no reference: the floor share alone


def test_a_short_run_is_judged_by_the_full_runs_rate():
    """An 8 s screen of rigid Y: the configured C2 saturated 0 times in its first 8 s, which
    allowed 3 (a count of one window); at the full run's allowed rate (27 in 40 s: 5.4 in 8 s)
    a run fails only above the 95 % quantile, and a bursty run (episodes of 4) gets its
    dispersion's room."""
    n = REF_SHORT["samples"]
    sat, _ = V.limits(REF_SHORT, 10.0, n, REF_FULL)
    assert sat == stats.poisson.ppf(1.0 - SAT_ALPHA, 27 * n / 200000) == 9
    bursty, _ = V.limits(REF_SHORT, 10.0, n, REF_FULL, dispersion=4.0)
    assert bursty == int(4.0 * stats.poisson.ppf(1.0 - SAT_ALPHA, 5.4 / 4.0)) > sat
    # never below the same-window allowance of a configured controller that saturated more
    busy = dict(REF_SHORT, saturated=344)
    assert V.limits(busy, 10.0, n, REF_FULL)[0] == 516
    # the verdict says so; a run at the rate passes, one far above it does not
    run = {"fault": "", "samples": n, "saturated": 8, "sat_dispersion": 1.0, "u_rest_rms_V": 0.03,
           "osc_ratio": 2.0, "e_psd": PSD}
    assert V.admissible(run, 10.0, REF_SHORT, full_ref=REF_FULL) == ""
    assert "saturated" in V.admissible(dict(run, saturated=10), 10.0, REF_SHORT, full_ref=REF_FULL)
    assert "saturated" in V.admissible(run, 10.0, REF_SHORT)      # without the full run: the window's 3


RIGID = {"theta1": 0.69, "theta2": 0.25, "mode_hz": 0.0, "mode_damping": 0.0, "load_fraction": 0.0,
         "current_loop_hz": 1e9, "delay_s": 0.0, "mode": False}


def test_the_family_reads_the_plant():
    """A fitted mode: each law's own damping ratios; none: lower ones too, for every law."""
    assert family_zetas("c2", dict(RIGID, mode=True, mode_hz=120.0)) is None
    for law in ("c1", "c2", "pid"):
        z = family_zetas(law, RIGID)
        assert set(ZETA_RIGID) | set(controller_class(law).ZETA) == set(z) and min(z) < 0.3
    fam = controller_class("pid").gain_family(0.69, None, [400.0], zetas=(0.15,))
    assert {g["_zeta"] for g in fam} == {0.15} and len(fam) == len(controller_class("pid").R_INT)

    class Keeps(Controller):            # a law that keeps the base's family: none, with or without zetas
        name = "keeps"

    assert Keeps.gain_family(1.0, None, [100.0]) == [] == Keeps.gain_family(1.0, None, [100.0], zetas=(0.2,))


def test_on_a_rigid_plant_lightly_damped_members_are_admissible(repo):
    """On the rigid Y axis's response (configs/gantry-rigid.yaml's parameters) the margin floor
    admits C2 members below the law's own least ζ (0.3), over a range of ω; with a mode
    (the same axis at 120 Hz) the family stays the law's own."""
    from motorctl.config import config_from_dict
    raw = load_yaml(repo / "configs" / "gantry-rigid.yaml")
    section = config_from_dict(raw, "gantry-rigid.yaml").axes["Y"].controller
    w = grid_w(TS)
    f = np.linspace(0.0, 2500.0, 257)
    rest_psd = (f, np.full(f.size, 1e-16))
    ch = choose_gains("c2", plant_model_frf(RIGID, TS, w), w, TS, 0.69, section, rest_psd,
                      zetas=family_zetas("c2", RIGID))
    low = [g["_w"] for s, gs in ch["admissible"].items() if dict(s)["_zeta"] < 0.3 for g in gs]
    assert len(low) > 10 and max(low) > 1000.0
    flexible = dict(RIGID, mode=True, mode_hz=120.0, mode_damping=0.03, load_fraction=0.5)
    ch = choose_gains("c2", plant_model_frf(flexible, TS, w), w, TS, 0.69, section, rest_psd,
                      zetas=family_zetas("c2", flexible))
    assert min(dict(s)["_zeta"] for s in ch["admissible"]) >= 0.3


class _Machine:
    """A stand-in for the runs: L2[e] falls as k_s rises, and saturation above ``k_sat``."""

    def __init__(self, k_sat: float):
        self.k_sat, self.calls = k_sat, []

    def __call__(self, raw, source, axis, law, seconds, clock):
        k = raw["axes"][axis]["controller"][law]["k_s"]
        self.calls.append((k, seconds))
        n = int(seconds * 5000)
        return {"fault": "", "samples": n, "saturated": 1000 if k > self.k_sat else 0, "sat_dispersion": 1.0,
                "u_rest_rms_V": 0.01, "osc_ratio": 2.0, "L2_um": 100.0 / k, "e_M_um": 1.0,
                "e_psd": PSD}


@pytest.mark.parametrize("k_sat, k_up", [(1e9, 100.0 * 1.25 ** 3), (130.0, 125.0), (110.0, 100.0 * 1.25 ** 0.25),
                                          (100.0, 100.0)])
def test_the_confirmed_gains_step_up_where_the_runs_allow(repo, monkeypatch, k_sat, k_up):
    """From confirmed gains k_s 100, each step up (x 1.25) is screened, run in full and on its
    rungs; a step that saturates halves the factor (in log), down to STEP_UP_MIN, for at most
    STEP_UP_TRIES steps; what failed is never kept."""
    machine = _Machine(k_sat)
    monkeypatch.setattr(V, "evaluate", machine)
    raw = load_yaml(repo / "configs" / "gantry-rigid.yaml")
    ref = {"saturated": 0, "samples": 200000, "u_rest_rms_V": 0.05, "e_psd": PSD}
    choice = {"holds": lambda g: True}
    v = V._Verification(raw, "gantry-rigid.yaml", "Y", "c2", choice, 8.0, "virtual", dict(ref, samples=40000),
                        None, None, ref)
    g = {"k_s": 100.0, "k1": 500.0, "gamma_d": 500.0}
    l2, got, sc, _ = v.climb((1.0, g, 1.0, "search"), 40.0, ref)
    assert got["k_s"] == pytest.approx(k_up) and sc == pytest.approx(k_up / 100.0)
    assert l2 == pytest.approx(100.0 / k_up) if k_up > 100.0 else l2 == 1.0
    assert got["k_s"] <= k_sat
    # margins that fail at the raised gains: no run at all
    machine.calls.clear()
    v.choice = {"holds": lambda g: g["k_s"] <= 100.0}
    assert v.climb((1.0, g, 1.0, "search"), 40.0, ref)[1] is g and machine.calls == []
    assert math.isfinite(l2)


def test_a_short_runs_rest_noise_is_judged_as_the_full_run_it_predicts():
    """Rigid Y's C1 (k_s 134, k1 1213): 8 s, first period 101 mV, second 61 mV: 84 mV over the
    run, which the configured C2's 8 s (61 mV, noisier in its own first period) let pass; the
    40 s run it predicts, 68 mV, is held to the 40 s limit (1.5 x 37 mV) and fails, as the 40 s
    run itself (60 mV) did."""
    short = {"fault": "", "samples": 40000, "saturated": 0, "sat_dispersion": 1.0, "u_rest_rms_V": 0.0835,
             "u_rest_first_V": 0.1011, "u_rest_later_V": 0.0611, "period_samples": 20000, "osc_ratio": 2.0,
             "e_psd": PSD}
    ref8 = dict(REF_SHORT, u_rest_rms_V=0.061)
    ref40 = dict(REF_FULL, u_rest_rms_V=0.0373)
    rest, predicted = V.rest_judged(short, ref40)
    assert predicted and rest == pytest.approx(math.sqrt((0.1011 ** 2 + 9 * 0.0611 ** 2) / 10))
    assert V.admissible(short, 10.0, ref8) == ""
    assert "predicted over 200000 samples (> 62 mV)" in V.admissible(short, 10.0, ref8, full_ref=ref40)
    # a full run, or one of a single period, is judged by its own figure
    assert V.rest_judged(dict(short, samples=200000), ref40) == (0.0835, False)
    assert V.rest_judged(dict(short, u_rest_later_V=math.nan), ref40) == (0.0835, False)


def test_a_full_run_failed_on_rest_noise_bars_the_candidates_as_noisy():
    short = {"saturated": 6, "samples": 40000, "u_rest_rms_V": 0.1}
    failed = {"saturated": 7, "samples": 40000, "u_rest_rms_V": 0.08}
    assert V._as_bad(short, failed, None) and not V._as_bad(failed, short, None)


def test_a_short_runs_saturation_after_its_first_period_stands_for_the_rest_of_the_full_run():
    """Gantry X's C2 saturated 6 times in its first period and 16 in its second (then 15-22 a
    period over 40 s, against a limit of 15): rejected on 8 s; 6 then 2 passes."""
    full = {"saturated": 7, "samples": 200000, "u_rest_rms_V": 0.1}
    ref8 = {"saturated": 2, "samples": 40000, "u_rest_rms_V": 0.1, "e_psd": PSD}
    run = {"fault": "", "samples": 40000, "period_samples": 20000, "saturated": 22, "sat_first": 6,
           "sat_dispersion": 1.0, "u_rest_rms_V": 0.05, "osc_ratio": 2.0, "e_psd": PSD}
    assert V.sat_later(run, ref8, full) == (16, stats.poisson.ppf(1.0 - SAT_ALPHA, (15 - 6) / 9.0))
    assert "16 after the first program period > 3" in V.admissible(run, 10.0, ref8, full_ref=full)
    assert V.sat_later(dict(run, saturated=8, sat_first=6), ref8, full) == (2, 3)
    assert V.admissible(dict(run, saturated=8, sat_first=6), 10.0, ref8, full_ref=full) == ""
    assert V.sat_later(dict(run, samples=20000), ref8, full) is None        # one period: the rate test
    assert V.sat_later(run, ref8, None) is None


def test_the_margin_edge_keeps_the_damping_gain_and_stiffens_to_where_the_margins_bind():
    """From a C1 member on the rigid Y axis's model (ω 330, ζ 0.25), the edge at the same k_s
    has the largest k1 whose margins hold (3 % above it they fail); at 1.2 x k_s the edge's
    k_s is 1.2 x; the edge of a member already on it is none."""
    from motorctl.commission.choose import edge_member, margins_hold
    w = grid_w(TS)
    G = plant_model_frf(RIGID, TS, w)
    cls = controller_class("c1")

    def make(like, w_, z_):
        return cls.gain_family(0.69, type("S", (), {"gamma_d": 500.0}), (w_,), zetas=(z_,))[0]

    def holds(g):
        return margins_hold("c1", g, TS, w, G)[1]

    g = make(None, 330.0, 0.25)
    assert holds(g)
    e = edge_member(make, holds, g)
    assert e["k_s"] == pytest.approx(g["k_s"]) and e["k1"] > 1.2 * g["k1"] and e["_zeta"] < g["_zeta"]
    assert holds(e) and not holds(dict(e, k1=e["k1"] * 1.03))
    up = edge_member(make, holds, g, 1.2)
    assert up["k_s"] == pytest.approx(1.2 * g["k_s"]) and holds(up)
    assert edge_member(make, holds, e) is None


def test_the_rule_takes_a_measured_line_only_where_it_departs_from_the_model():
    """Lines scattering about the model as their coherence says: the model; a line at twice
    the model's gain (far beyond its error): taken, the ratio interpolated to its neighbours."""
    from motorctl.commission.choose import loop_frf
    rng = np.random.default_rng(0)
    fm = np.arange(10.0, 1000.0)
    coh = np.full(fm.size, 0.8)
    G = plant_model_frf(RIGID, TS, 2 * math.pi * fm)
    eps = math.sqrt(0.2 / (2 * 32 * 0.8))
    Gm = G * (1.0 + eps * (rng.standard_normal(fm.size) + 1j * rng.standard_normal(fm.size)) / math.sqrt(2))
    Gm[490] = 2.0 * G[490]                             # 500 Hz
    w, G_fit, G_w = loop_frf({"f_hz": fm, "G": Gm, "coherence": coh}, RIGID, TS, 32)
    ratio = np.abs(G_w / G_fit)
    f = w / (2 * math.pi)
    assert np.allclose(ratio[(f < 498.0) | (f > 502.0)], 1.0)
    assert 1.7 < ratio.max() <= 2.0 + 1e-9                  # the grid's points beside the line


def test_the_error_spectrum_is_judged_beyond_what_the_sensitivities_predict():
    """Rigid Y's search best (k_s 132.5, k1 1630): its error 136x the configured C2's at 93 Hz,
    where its |S| peaks; not an oscillation when the sensitivities predict 50x there, one
    when they predict nothing."""
    f = np.arange(0.0, 200.0)
    ref = {"e_psd": (f, np.ones(f.size))}
    run = {"e_psd": (f, np.where(f == 93.0, 136.0, 1.0))}
    assert V.e_line_ratio(run, ref) == (136.0, 93.0)
    assert V.e_line_ratio(run, ref, lambda x: np.where(np.abs(x - 93.0) < 5, 50.0, 0.5))[0] == pytest.approx(2.72)
    res = {"fault": "", "samples": 200000, "saturated": 0, "u_rest_rms_V": 0.05, "osc_ratio": 2.0, **run}
    assert "oscillation at 93 Hz" in V.admissible(res, 10.0, dict(REF_FULL, **ref))
    assert V.admissible(res, 10.0, dict(REF_FULL, **ref), expect=lambda x: np.full(x.size, 50.0)) == ""


def test_lines_of_coherence_one_are_taken_where_they_depart_without_a_warning():
    """A noise-free measurement (coherence 1 at every line, or at some: ε = 0 there): no
    division by zero (numpy's RuntimeWarning is an error here); a line at the model stays the
    model, a departing one is taken."""
    import warnings

    from motorctl.commission.choose import loop_frf
    fm = np.arange(10.0, 1000.0)
    G = plant_model_frf(RIGID, TS, 2 * math.pi * fm)
    Gm = G.copy()
    Gm[490] = 1.5 * G[490]                             # 500 Hz
    for coh in (np.ones(fm.size), np.where(fm < 300.0, 1.0, 0.8)):
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            w, G_fit, G_w = loop_frf({"f_hz": fm, "G": Gm, "coherence": coh}, RIGID, TS, 32)
        ratio = np.abs(G_w / G_fit)
        f = w / (2 * math.pi)
        assert np.all(np.isfinite(G_w))
        assert np.allclose(ratio[(f < 498.0) | (f > 502.0)], 1.0)
        assert ratio.max() == pytest.approx(1.5, rel=0.2)
