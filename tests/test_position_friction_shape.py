"""The ``position_friction_shape`` effect family (docs/identification.md): friction that varies with
position in any smooth shape, F_eff = −g(x) S_f(ẋ), g a cubic B-spline whose segment count is
chosen by the identifier's held-out rule.

A synthetic log of the rigid X axis with a friction bump (the family's example: 15 N more Coulomb
friction over 0.17 … 0.33 m) is named as this family with the bump's shape; a linear c·x friction
is still ``position_dependent_friction``; the true bump compensated removes the closed-loop damage.
Logs and closed-loop runs are made once per module on two worker processes (virtual clock).
"""

from __future__ import annotations

import dataclasses

import json
import math
import os
from concurrent.futures import ProcessPoolExecutor

import numpy as np
import pytest
from scipy.interpolate import BSpline

from motorctl.commission.tune import make_log
from motorctl.cli import main
from motorctl.config import ConfigError, config_from_dict, load_yaml
from motorctl.effects import FAMILIES, family
from motorctl.effects import position_friction_shape as pfs
from motorctl.effects.base import Signals
from motorctl.effects.compensation import Compensation, CompensationConfig
from motorctl.ident.data import load_record
from motorctl.ident.report import effect_shape
from motorctl.ident.select import MIN_HELDOUT_GAIN, Identifier
from motorctl.ident.synth import EXAMPLES, gantry_dict
from motorctl.model import s_f, s_f_scalar

NAME = "position_friction_shape"
LINEAR = "position_dependent_friction"
A1 = 80.0
BUMP = EXAMPLES[NAME]
IDENT_S = 8.0
#: closed loop: as docs/identification.md ("Compensation counted once") but 12 s, L2 over 4-12 s
#: (the first program period excluded); 16 s gives the same figure (1.02)
CLOSED_LOOP_S = 12.0


def _bump_truth(x):
    """g(x) of the example [N] (N,)."""
    return sum(pfs.bump_value(x, b["center_m"], b["width_m"], b["amplitude_N"]) for b in BUMP[NAME]["bumps"])


def _job(args):
    """Worker: one simulated run (and its identification when asked)."""
    path, effect, duration, compensation, identify = args
    make_log(path, effect, duration_s=duration, seed=1, compensation=compensation)
    return path, (Identifier(load_record(path)).run() if identify else None)


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    d = tmp_path_factory.mktemp("pfs")
    fam = family(NAME)
    comp = {NAME: fam.compensation_for(fam.sim_options.model_validate(BUMP[NAME]), A1)}
    jobs = [(str(d / "cl_before.mclog"), BUMP, CLOSED_LOOP_S, None, False),      # longest first
            (str(d / "cl_after.mclog"), BUMP, CLOSED_LOOP_S, comp, False),
            (str(d / "bump.mclog"), BUMP, IDENT_S, None, True),
            (str(d / "linear.mclog"), EXAMPLES[LINEAR], IDENT_S, None, True),
            (str(d / "cl_floor.mclog"), None, CLOSED_LOOP_S, None, False)]
    with ProcessPoolExecutor(max_workers=2) as ex:
        return {os.path.basename(p).split(".")[0]: (p, idf) for p, idf in ex.map(_job, jobs)}


def _found(idf, name):
    """(term, β) of family ``name`` in the final model."""
    names = [t.family for t in idf.terms]
    i = names.index(name)
    return idf.terms[i], idf.coef_split(idf.final, idf.terms)[1][i]


# ---------------------------------------------------------------------------- identification
def test_bump_is_named_with_its_shape(runs):
    _, idf = runs["bump"]
    assert [t.family for t in idf.terms] == [NAME], [(c.term.family, c.reasons) for c in idf.steps[0]]
    ev, before = idf.accepted[0]
    assert ev.heldout_rms < 0.6 * before                # measured 1.99 -> 0.90 N
    # not cogging, Stribeck or the linear family: each judged and refused at the first step
    verdicts = {c.term.family: c.ok for c in idf.steps[0]}
    assert not verdicts["cogging"] and not verdicts["stribeck"] and not verdicts[LINEAR]
    # the fitted shape against the truth over the stroke covered, both about their mean
    # (θ3 carries the mean level): measured correlation 0.998, RMS error 2.3 % of the bump
    term, beta = _found(idf, NAME)
    xs, y, xl, yl = effect_shape(idf, term, beta)
    assert xl == "position [m]" and "UNIT" in yl
    assert xs.min() == pytest.approx(idf.p.x.min()) and xs.max() == pytest.approx(idf.p.x.max())
    g = _bump_truth(xs)
    yc, gc = y - y.mean(), g - g.mean()
    amp = BUMP[NAME]["bumps"][0]["amplitude_N"]
    assert np.corrcoef(yc, gc)[0, 1] > 0.95
    assert math.sqrt(np.mean((yc - gc) ** 2)) < 0.1 * amp
    p = family(NAME).parameters(term.h, beta, idf.rec.gain, idf.p.fs)
    assert abs(p["extremum_position_m"] - BUMP[NAME]["bumps"][0]["center_m"]) < 0.01
    assert p["peak_to_peak_N"] == pytest.approx(amp, rel=0.15)


def test_segment_count_is_chosen_by_the_heldout_rule(runs):
    """Replays the rule: from the linear family's held-out RMS, a count is kept only when it
    lowers the held-out RMS by TERM_GAIN (= the identifier's MIN_HELDOUT_GAIN) below the count
    kept before; the selected term has the last count kept."""
    assert pfs.TERM_GAIN == MIN_HELDOUT_GAIN
    _, idf = runs["bump"]
    term, _ = _found(idf, NAME)
    kept, kept_rms = None, idf.heldout_rms([idf.term(LINEAR, None)])
    rms = {}
    for n in pfs.SEGMENTS:
        h = pfs.KnotGrid(term.h.start_m, term.h.end_m, n)
        rms[n] = idf.heldout_rms([idf.term(NAME, h)])
        if rms[n] <= (1 - pfs.TERM_GAIN) * kept_rms:
            kept, kept_rms = n, rms[n]
    assert kept == term.h.segments, rms
    assert 1 < kept < max(pfs.SEGMENTS), rms           # a shape, not a straight line; measured 8
    assert term.cols.shape[1] == kept + 2               # B_2 .. B_{n+3}: B_1 is θ3's mean level


def test_linear_friction_is_still_the_linear_family(runs):
    _, idf = runs["linear"]
    assert [t.family for t in idf.terms] == [LINEAR]
    (mine,) = [c for c in idf.steps[0] if c.term.family == NAME]
    assert not mine.ok and any("no shape beyond a linear slope" in r for r in mine.reasons), mine.reasons


def test_identify_json_report_and_write_config(runs, tmp_path, capsys):
    """The CLI end to end: JSON (the knot grid as a float), the report figure, and a tuned config
    whose compensation has zero mean over the record and θ̂3 re-expressed (passes check-config)."""
    path, idf = runs["bump"]
    rep, out = tmp_path / "rep", tmp_path / "tuned.yaml"
    assert main(["identify", path, "--json", "--no-closed-loop", "--report", str(rep),
                 "--write-config", str(out)]) == 0
    s = json.loads(capsys.readouterr().out)
    (e,) = s["effects"]
    assert e["name"] == NAME and e["parameters"]["segments"] == idf.terms[0].h.segments
    (cand,) = [c for c in s["candidates"][0] if c["name"] == NAME]
    assert cand["selected"] and cand["searched"] == pytest.approx(e["parameters"]["knot_spacing_m"])
    assert (rep / "effect_shape.png").stat().st_size > 0
    ctl = load_yaml(out)["axes"]["X"]["controller"]
    entry = ctl["compensation"][NAME]
    cfg = CompensationConfig.model_validate({NAME: entry})
    c = Compensation(cfg)
    x, v = idf.p.x, idf.p.v
    d = np.array([c.value(float(a), float(b), 0.0) for a, b in zip(x, v)])
    # d̂_eff = −(g − offset) S_f: zero mean over the motion weighted by |S_f| (its sign is S_f's)
    w = np.abs(s_f(v))
    assert abs(np.sum(d * np.sign(v)) / np.sum(w)) < 1e-9
    theta, _ = idf.coef_split(idf.final, idf.terms)
    assert ctl["theta_hat0"][2] == pytest.approx(theta[2] + entry["offset_V"], rel=1e-5)
    # θ̂3 = the plant's Coulomb level plus the bump's mean over the motion: (20 N + ḡ) / A1
    g_mean = np.sum(w * _bump_truth(x)) / np.sum(w)
    assert ctl["theta_hat0"][2] == pytest.approx((20.0 + g_mean) / A1, abs=0.015)


# ---------------------------------------------------------------------------- closed loop
def test_true_bump_compensated_removes_the_damage(runs):
    """(L2_before − L2_after)/(L2_before − L2_floor) ≥ 0.8: C2 on the rigid X axis, seed 1, the
    true bump compensated (compensation_for); floor: the same plant without it. Measured (12 s,
    L2 over 4-12 s): 3.597 → 3.488 µm, floor 3.491 µm: 1.03 (16 s: 3.594 → 3.486, 3.488: 1.02)."""
    from motorctl.commission.compare import compare_logs
    before, after, floor = (runs[k][0] for k in ("cl_before", "cl_after", "cl_floor"))
    ba = compare_logs(before, after)["axes"]["X"]
    bf = compare_logs(before, floor)["axes"]["X"]
    assert ba["window_s"] == [4.0, CLOSED_LOOP_S] and bf["window_s"] == ba["window_s"]
    l2_b, l2_a, l2_f = ba["before"]["L2_um"], ba["after"]["L2_um"], bf["after"]["L2_um"]
    assert l2_b > l2_f * 1.01, (l2_b, l2_f)             # the bump does damage
    assert (l2_b - l2_a) / (l2_b - l2_f) >= 0.8, (l2_b, l2_a, l2_f)


# ---------------------------------------------------------------------------- the terms themselves
POINTS = [(x, v) for x in (-0.05, 0.0, 0.013, 0.1, 0.17, 0.2, 0.25, 0.3, 0.3299, 0.37, 0.45)
          for v in (-0.8, -0.01, 0.0, 0.004, 0.05, 0.8)]


def test_compensation_for_cancels_the_plant_force():
    fam = FAMILIES[NAME]
    two = {"bumps": [{"center_m": 0.1, "width_m": 0.1, "amplitude_N": 8.0},
                     {"center_m": 0.3, "width_m": 0.12, "amplitude_N": -6.0}]}
    for opts in (BUMP[NAME], two):
        sim = fam.sim_options.model_validate(opts)
        force = fam.plant_term(sim, 2e-4).force
        c = Compensation(CompensationConfig.model_validate({NAME: fam.compensation_for(sim, A1)}))
        forces = []
        for x, v in POINTS:
            f = force(0.0, x, v, 0.0, s_f_scalar(v))
            forces.append(f)
            assert f == pytest.approx(-_g(opts, x) * s_f_scalar(v), rel=1e-12, abs=1e-12)
            assert -c.value(x, v, 0.0) == pytest.approx(-f / A1, rel=1e-9, abs=1e-12)
        assert max(abs(f) for f in forces) > 5.0


def _g(opts, x):
    return float(sum(pfs.bump_value(x, b["center_m"], b["width_m"], b["amplitude_N"]) for b in opts["bumps"]))


def test_compensation_from_a_fit_is_minus_the_fitted_columns_about_its_offset():
    """identify fits u = Φθ + Cβ: the emitted term is −(Cβ − offset S_f), the offset the mean of g
    over the record weighted by |S_f(ẋ)|, and θ3 moves by it (theta_shift)."""
    fam = FAMILIES[NAME]
    h = pfs.knot_grid(0.0, 0.4, 6)
    x, v = (np.array(a, dtype=float) for a in zip(*POINTS))
    sig = Signals(x, v, np.zeros_like(x), np.zeros_like(x), np.zeros_like(x))
    cols = fam.columns(h, sig)
    assert cols.shape == (len(x), 8)
    beta = np.random.default_rng(3).uniform(-0.3, 0.3, cols.shape[1])
    rec_x = np.linspace(0.0, 0.4, 801)
    rec_v = 0.5 * np.sin(np.linspace(0.0, 20.0, 801))
    entry = fam.compensation(h, beta, Signals(rec_x, rec_v, 0 * rec_x, 0 * rec_x, 0 * rec_x))
    c = Compensation(CompensationConfig.model_validate({NAME: entry}))
    got = np.array([c.value(a, b, 0.0) for a, b in zip(x, v)])
    assert np.allclose(got, -(cols @ beta) + entry["offset_V"] * s_f(v), rtol=1e-9, atol=1e-12)
    g_rec = h.basis(rec_x)[:, h.free()] @ beta
    w = np.abs(s_f(rec_v))
    assert entry["offset_V"] == pytest.approx(np.sum(w * g_rec) / np.sum(w), rel=1e-12)
    assert fam.theta_shift(entry, 6) == pytest.approx([0, 0, entry["offset_V"], 0, 0, 0])
    assert entry["offset_V"] != 0.0


def test_piecewise_cubic_matches_the_b_spline_and_is_constant_beyond():
    rng = np.random.default_rng(7)
    for n, lo, hi in ((1, 0.0, 0.4), (5, -0.02, 0.31), (12, 0.1, 0.2)):
        c = rng.normal(size=n + 3)
        g = pfs._spline_fn(pfs.spline_pieces(lo, hi, c))
        spl = BSpline(pfs.KnotGrid(lo, hi, n).knots, c, 3)
        xs = np.r_[np.linspace(lo, hi, 997), lo - 0.05, hi + 0.05, np.linspace(lo, hi, n + 1)]
        want = spl(np.clip(xs, lo, hi))
        got = np.array([g(float(x)) for x in xs])
        assert np.allclose(got, want, rtol=1e-11, atol=1e-11), n


def test_the_term_is_a_compiled_kernel_the_cycle_runs():
    """The compensation term is a compiled kernel listed for the cycle (no Python inside the
    5 kHz cycle), and its table evaluates as the term does."""
    from motorctl.effects.compensation import KERNELS
    fam = FAMILIES[NAME]
    entry = {"start_m": 0.0, "end_m": 0.4, "coefficients_V": [0.0, 0.1, -0.1, 0.2, 0.0, 0.05],
             "bumps": [{"center_m": 0.2, "width_m": 0.1, "amplitude_V": 0.1},
                       {"center_m": 0.3, "width_m": 0.1, "amplitude_V": -0.1}], "offset_V": 0.01}
    add = fam.compensator(fam.comp_options.model_validate(entry))
    assert any(k is add.kernel for k in KERNELS)
    c = Compensation(CompensationConfig.model_validate({NAME: entry}))
    assert c.table is not None
    for x, v in ((-0.1, 0.01), (0.05, -0.02), (0.2, 0.3), (0.27, 0.0), (0.5, 1.0)):
        assert c.value(x, v, 0.0) == add(0.0, x, v, 0.0, s_f_scalar(v))


def test_yaml_keys_and_refusals():
    d = gantry_dict("X", BUMP, compensation={NAME: {"start_m": 0.0, "end_m": 0.4,
                                                    "coefficients_V": [0.0, 0.1, 0.2, 0.0], "offset_V": 0.05}})
    cfg = config_from_dict(d, "<pfs>")
    assert getattr(cfg.axes["X"].controller.compensation, NAME).offset_V == 0.05
    for bad, needle in (({"coefficients_V": [0.0, 0.1, 0.2, 0.0]}, "start_m < end_m"),
                        ({"start_m": 0.0, "end_m": 0.4, "coefficients_V": [0.1, 0.2]}, "at least 4"),
                        ({"offset_V": 0.1}, "coefficients_V (with start_m, end_m) or bumps")):
        with pytest.raises(ConfigError, match="compensation") as exc:
            config_from_dict(gantry_dict("X", None, compensation={NAME: bad}), "<pfs>")
        assert needle in str(exc.value)
    with pytest.raises(ConfigError, match=NAME):
        config_from_dict(gantry_dict("X", {NAME: {"bumps": []}}), "<pfs>")


def test_knot_grid_pickles_and_validates():
    import pickle
    h = pfs.KnotGrid(0.01, 0.41, 8, drop_linear=True)
    h2 = pickle.loads(pickle.dumps(h))
    assert (h2.start_m, h2.end_m, h2.segments, h2.drop_linear, h2.force) == (0.01, 0.41, 8, True, False)
    assert float(h2) == pytest.approx(0.05)
    assert list(h2.free()) == list(range(1, 10))       # B_1 (θ3) and B_11 (the linear column) left out
    with pytest.raises(ValueError):
        pfs.KnotGrid(0.4, 0.0, 4)
    with pytest.raises(TypeError):
        FAMILIES[NAME].columns(None, Signals(*(np.zeros(3),) * 5))


def _strokes(speeds, n=4000):
    """Decimated-record stand-in: back-and-forth strokes over 0 … 0.4 m, one trapezoidal speed
    profile s(x) scaled by each of ``speeds`` in turn [m/s] (x_d, v_d (M,), all moving)."""
    from types import SimpleNamespace
    z = np.linspace(0.0, 1.0, n)
    x_up = 0.4 * z
    s = np.minimum(1.0, np.minimum(z, 1.0 - z) / 0.15) + 0.02
    xs, vs = [], []
    for k, sc in enumerate(speeds):
        xs.append(x_up if k % 2 == 0 else x_up[::-1])
        vs.append(sc * s if k % 2 == 0 else -sc * s[::-1])
    x, v = np.concatenate(xs), np.concatenate(vs)
    return SimpleNamespace(x_d=x, v_d=v), np.ones_like(x, dtype=bool)


def test_viscous_direction_is_left_out_only_when_the_record_cannot_tell():
    """One speed profile: |ẋ| is a function of x, so viscous friction is a friction shape and
    the shape is fitted without that direction (k − 1 coefficients mapped back to k); strokes
    at 1 and 0.3 of the speed separate them and the full basis is kept."""
    h = pfs.KnotGrid(0.0, 0.4, 8)
    k = len(h.free())
    p, mv = _strokes([2.0, 2.0, 2.0, 2.0])
    span = pfs.viscous_span(h, p, mv)
    assert span is not None and span.shape == (k, k - 1)
    hs = h.with_span(span)
    assert hs.n_columns == k - 1 and hs.as_force().span == hs.span
    # what is left out is the shape viscous friction takes: beyond θ3's S_f(ẋ), the fitted
    # shape explains almost nothing of ẋ (the full basis nearly all of it)
    sig = Signals(p.x_d, p.v_d, 0 * p.x_d, 0 * p.x_d, 0 * p.x_d)
    sf = s_f(p.v_d)

    def r2(*cols):
        a = np.column_stack(cols)
        r = p.v_d - a @ np.linalg.lstsq(a, p.v_d, rcond=None)[0]
        return 1 - (r @ r) / (p.v_d @ p.v_d)
    full = r2(sf, family(NAME).columns(h, sig)) - r2(sf)
    reduced = r2(sf, family(NAME).columns(hs, sig)) - r2(sf)
    assert full > 0.05 and reduced < 0.02 * full, (full, reduced)
    assert len(hs.coefficients(np.ones(k - 1))) == h.n_basis
    p2, mv2 = _strokes([2.0, 2.0, 0.6, 0.6])
    assert pfs.viscous_span(h, p2, mv2) is None


def test_a_shape_that_the_straight_line_does_as_well_is_replaced_by_it(runs):
    """After the selection, a friction shape whose simpler case (the linear slope) leaves a
    held-out RMS less than 3 % above in the final model is replaced by it, and the report says
    so; a shape that beats the line (the bump) stays."""
    _, idf = runs["linear"]
    grid = pfs.KnotGrid(float(idf.p.x.min()), float(idf.p.x.max()), 8)
    shape = idf.term(NAME, grid)
    ev = dataclasses.replace(idf.evaluate([shape]), term=shape, gain=0.5, rivals=())
    terms, accepted, final, replaced = idf._simplify([shape], [(ev, idf.nominal.heldout_rms)], ev)
    assert [t.family for t in terms] == [LINEAR] and [n for n, _ in replaced] == [NAME], replaced
    assert final.heldout_rms <= ev.heldout_rms / (1 - MIN_HELDOUT_GAIN)
    _, bump = runs["bump"]
    t, a, f, rep = bump._simplify(list(bump.terms), list(bump.accepted), bump.final)
    assert [x.family for x in t] == [x.family for x in bump.terms] and rep == []


def _one_speed_record(extra) -> "Record":
    """A hand-made 8 s, 5 kHz record of strokes 0 ↔ 0.4 m that pass each position at one speed
    (raised-cosine acceleration to 2 m/s over 0.1 m, cruise over 0.1 … 0.3 m): u = (M ẍ + B ẋ +
    F_c S_f(ẋ) + extra(x, ẋ) S_f(ẋ))/A1 plus seeded noise [V]."""
    from motorctl.ident.data import Record
    fs, vmax, ta = 5000.0, 2.0, 0.1
    ts = 1.0 / fs
    acc = vmax * (1 - np.cos(np.pi * np.arange(int(ta * fs)) / (ta * fs))) / 2
    v_up = np.concatenate([acc, np.full(int(0.1 * fs), vmax), acc[::-1], np.zeros(int(0.1 * fs))])
    v = np.tile(np.concatenate([v_up, -v_up]), 6)[: int(8 * fs)]
    x = np.cumsum(v) * ts
    a = np.gradient(v, ts)
    rng = np.random.default_rng(3)
    f = 10.0 * a + 20.0 * v + (20.0 + extra(x, v)) * s_f(v)
    t = np.arange(len(x)) * ts
    return Record(t=t, y=x + rng.normal(0, 1e-8, len(x)), u=f / A1 + rng.normal(0, 0.01, len(x)), gain=A1)


@pytest.mark.parametrize("case", ["speed", "bump"])
def test_a_shape_is_told_from_a_friction_of_the_speed(case):
    """On a program that passes each position at one speed, a friction that varies with the
    speed (a hump at 0.8 m/s, where the carriage accelerates) is a shape of position too: the
    same basis over |ẋ| explains as much, and the shape is refused for it. A bump in the cruise
    (constant speed) cannot be a friction of the speed and is not refused for it."""
    if case == "speed":
        rec = _one_speed_record(lambda x, v: 6.0 * np.exp(-((np.abs(v) - 0.8) / 0.2) ** 2))
    else:
        rec = _one_speed_record(lambda x, v: pfs.bump_value(x, 0.2, 0.08, 15.0))
    idf = Identifier(rec, zoh_delay=0.0)
    term = idf.term(NAME, pfs.KnotGrid(float(idf.p.x.min()), float(idf.p.x.max()), 8))
    ev = idf.evaluate([term])              # its term is the last of the model's
    k = term.cols.shape[1]
    reasons = FAMILIES[NAME].plausible(idf, term, ev.fit.coef[-k:], ev.fit.coef[:idf.n_theta], [])
    told = [r for r in reasons if r.startswith("not told from a friction that varies with the speed")]
    assert (len(told) == 1) if case == "speed" else not told, reasons
    # the shape does explain the effect either way (what is judged is what it is)
    assert ev.heldout_rms < 0.8 * idf.evaluate([]).heldout_rms
