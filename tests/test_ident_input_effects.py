"""Fitted values of the input-side families against the truth (docs/identification.md, "Fitted
values against the truth"): the input delay beyond the zero-order hold and the amplifier's
declared current loop, a fractional delay in the plant, the force-constant drift's exact column,
and the dead-zone's width from the force beyond its band.

Records are simulated here in numpy (a rigid axis under a PD loop with feedforward, 5 kHz, 8 s:
moves with dwells), not by the servo loop: each test runs in about a second and knows its truth.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from motorctl.effects import FAMILIES
from motorctl.effects.input_delay import amplifier_lag, delay_line, held_lag_response
from motorctl.ident.data import Record
from motorctl.ident.select import Identifier

FS = 5000.0
M, A1, A2, A3, B, FC, F0 = 12.8, 80.0, -1.04, -0.12, 17.6, 20.0, -4.0
SUB = 4
#: the input's broadband part [V] (a closed loop's noise: the delay shows in its phase)
NOISE_V = 0.3


def _reference(duration_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """x_r, ẋ_r, ẍ_r (N,): 0 ↔ 0.2 m raised-cosine moves of 0.25 s, 0.55 s dwells."""
    t = np.arange(int(duration_s * FS)) / FS
    cycle, move, stroke = 1.6, 0.25, 0.2
    tc = np.mod(t, cycle)
    x, v, a = np.zeros_like(t), np.zeros_like(t), np.zeros_like(t)
    for start, sign, base in ((0.0, 1.0, 0.0), (0.8, -1.0, stroke)):
        m = (tc >= start) & (tc < start + move)
        s = (tc[m] - start) / move
        x[m] = base + sign * stroke * 0.5 * (1 - np.cos(np.pi * s))
        v[m] = sign * stroke * 0.5 * np.pi / move * np.sin(np.pi * s)
        a[m] = sign * stroke * 0.5 * (np.pi / move) ** 2 * np.cos(np.pi * s)
    x[(tc >= move) & (tc < 0.8)] = stroke
    return x, v, a


def _simulate(duration_s=8.0, kappa=0.0, dz=(0.0, 0.0), delay_samples=0.0, tau_i=0.0, stiction_n=0.0,
              seed=0, noise_v=NOISE_V, stribeck=(0.0, 0.05)) -> Record:
    """A record of the rigid axis (module constants) under u = PD + feedforward + ``noise_v`` [V] of white noise,
    the input through a dead-zone dz = (d, o) [V], ``delay_samples`` of transport delay
    (:func:`delay_line`), a first-order current loop of time constant ``tau_i`` [s], a thrust
    (1 + κ t) F_m(u), Karnopp stiction ``stiction_n`` [N] and a Stribeck friction ``stribeck`` =
    (F_s [N], v_s [m/s]), F_s exp(−(ẋ/v_s)²) S_f(ẋ). u is held over each period
    (read y_k, then write u_k: the run log's zero-order hold)."""
    xr, vr, ar = _reference(duration_s)
    rng = np.random.default_rng(seed)
    noise = noise_v * rng.standard_normal(len(xr))
    n_whole = math.floor(delay_samples + 1e-9)
    line = delay_line(n_whole, delay_samples - n_whole) if delay_samples > 0 else (lambda u: u)
    h = 1.0 / (FS * SUB)
    x = v = f = 0.0
    d, o = dz
    ys, us = np.empty(len(xr)), np.empty(len(xr))
    for k in range(len(xr)):
        t = k / FS
        ys[k] = x
        u = 4000.0 * (xr[k] - x) + 40.0 * (vr[k] - v) + (M * ar[k] + B * vr[k]) / A1 + noise[k]
        u = min(max(u, -10.0), 10.0)
        us[k] = u
        z = line(u) + o
        ua = z - d if z > d else (z + d if z < -d else 0.0)
        fm = (A1 * ua + A2 * ua * abs(ua) + A3 * ua ** 3) * (1.0 + kappa * t)
        for _ in range(SUB):
            if tau_i > 0:       # the current loop: the mean of its exact response over the step
                f_mean = fm + (f - fm) * tau_i / h * (1.0 - math.exp(-h / tau_i))
                f = fm + (f - fm) * math.exp(-h / tau_i)
            else:
                f = f_mean = fm
            if stiction_n > 0 and abs(v) < 1e-4 and abs(f_mean + F0) <= stiction_n:
                v = 0.0
                continue
            fc = FC + stribeck[0] * math.exp(-(v / stribeck[1]) ** 2)
            acc = (f_mean - B * v - fc * (2 / math.pi) * math.atan(900.0 * v) + F0) / M
            x += h * v + 0.5 * h * h * acc        # exact for the acceleration held over h
            v += h * acc
    return Record(t=np.arange(len(xr)) / FS, y=ys, u=us, gain=A1, source="<numpy axis>", axis="X")


# ------------------------------------------------------------------------------- input delay
def test_fractional_delay_line_is_the_mean_of_the_delayed_held_input():
    step = [1.0] * 4
    d = delay_line(1, 0.5)
    assert [d(u) for u in step] == [0.0, 0.5, 1.0, 1.0]
    d = delay_line(0, 0.25)
    assert [d(u) for u in (1.0, 2.0, 3.0)] == pytest.approx([0.75, 1.75, 2.75])
    d = delay_line(2)
    assert [d(u) for u in (1.0, 2.0, 3.0, 4.0)] == [0.0, 0.0, 1.0, 2.0]
    with pytest.raises(ValueError):
        delay_line(0, 0.0)


def test_plant_applies_a_delay_between_whole_periods():
    fam = FAMILIES["input_delay"]
    half = fam.plant_term(0.0003, 0.0002)        # 1.5 periods (0.0003 / 0.0002 = 1.4999...)
    assert [half.input(1.0) for _ in range(4)] == pytest.approx([0.0, 0.5, 1.0, 1.0])
    whole = fam.plant_term(0.0006, 0.0002)       # 2.9999999999999996: three whole periods
    assert [whole.input(1.0) for _ in range(4)] == [0.0, 0.0, 0.0, 1.0]
    assert fam.plant_term(0.00001, 0.0002) is not None and fam.plant_term(0.0, 0.0002) is None


def test_amplifier_lag_is_what_the_config_declares():
    header = {"config": {"axes": {"X": {"driver": {"current_loop_hz": 1000.0, "current_loop_delay_s": 5e-5}}}}}
    lag, said = amplifier_lag(header, "X")
    assert lag == pytest.approx(1 / (2 * math.pi * 1000.0) + 5e-5)
    assert "1000 Hz current loop" in said
    assert amplifier_lag(header, "Y") == (0.0, "")
    assert amplifier_lag({}, "X") == (0.0, "")
    bad = {"config": {"axes": {"X": {"driver": {"current_loop_hz": "fast"}}}}}
    assert amplifier_lag(bad, "X") == (0.0, "")


def test_current_loop_filter_is_the_hold_then_the_lag():
    """Without a loop the held input is seen half a sample late, (0.5, 0.5); a loop passes the
    whole input (DC gain 1) d_c + 1/(2π f_c) later on average, its tail geometric."""
    h, r = held_lag_response(0.0, 0.0, FS)
    assert h[:2] == pytest.approx([0.5, 0.5]) and np.allclose(h[2:], 0.0) and r == 0.0
    h, r = held_lag_response(1000.0, 5e-5, FS)
    tail = r ** np.arange(1, 200)
    full = np.concatenate([h, h[-1] * tail])
    assert full.sum() == pytest.approx(1.0, abs=1e-9)
    mean = (np.arange(full.size) * full).sum()
    assert mean == pytest.approx(0.5 + 5e-5 * FS + FS / (2 * math.pi * 1000.0), abs=1e-6)


def test_with_the_declared_loop_modelled_the_delay_found_is_the_transport_delay_alone(delayed):
    """The 1 kHz loop in the nominal model (``current_loop``): the delay search starts beyond it
    and finds the 1.5 samples of transport delay; the report adds the loop back."""
    fam = FAMILIES["input_delay"]
    term, note = fam.search(Identifier(delayed, current_loop=True), [], None)
    assert note is None and float(term.h) == pytest.approx(1.5, abs=0.12)
    par = fam.parameters(term.h, None, A1, FS)
    assert par["delay_s"] * FS == pytest.approx(1.5, abs=0.12)
    assert par["total_delay_s"] * FS == pytest.approx(1.5 + FS / (2 * math.pi * 1000.0), abs=0.12)


@pytest.fixture(scope="module")
def delayed():
    """1.5 samples of transport delay behind a 1 kHz current loop the header declares."""
    rec = _simulate(delay_samples=1.5, tau_i=1 / (2 * math.pi * 1000.0))
    rec.header = {"config": {"axes": {"X": {"driver": {"current_loop_hz": 1000.0}}}}}
    return rec


def test_input_delay_found_is_the_transport_delay_beyond_the_current_loop(delayed):
    fam = FAMILIES["input_delay"]
    loop = FS / (2 * math.pi * 1000.0)           # the 1 kHz loop's lag: 0.80 sample
    term, note = fam.search(Identifier(delayed), [], None)
    assert note is None
    par = fam.parameters(term.h, None, A1, FS)
    assert par["delay_s"] * FS == pytest.approx(1.5, abs=0.12)
    assert par["amplifier_lag_s"] * FS == pytest.approx(loop)
    assert par["total_delay_s"] * FS == pytest.approx(1.5 + loop, abs=0.12)
    # undeclared, the loop's lag is part of the delay found
    bare = Record(delayed.t, delayed.y, delayed.u, gain=A1, axis="X", header={"run": 1})
    term, _ = fam.search(Identifier(bare), [], None)
    assert fam.parameters(term.h, None, A1, FS)["delay_s"] * FS == pytest.approx(1.5 + loop, abs=0.12)


# ------------------------------------------------------------------------------- drift
def test_force_constant_drift_is_exact_on_the_fits_own_thrust_shape():
    """κ = −0.02/s over 8 s (−16 %), inputs up to several volts: the column on the joint fit's
    θ5, θ6 gives κ relative to the record's start; the nominal fit's θ5, θ6 (biased by the drift)
    do not."""
    rec = _simulate(kappa=-0.02)
    idf = Identifier(rec, n_theta=6, zoh_delay=0.5)
    fam = FAMILIES["force_constant_drift"]
    term, _ = fam.search(idf, [], None)
    kappa = fam.parameters(term.h, idf.evaluate([term]).fit.coef[-1:], A1, FS)["drift_per_s"]
    assert kappa == pytest.approx(-0.02, rel=0.03)
    assert float(term.h) == pytest.approx(rec.t[0])
    # the column on the nominal fit's shape, about the same start
    from motorctl.effects.force_constant_drift import DriftReference
    th = idf.evaluate([]).fit.coef
    naive = idf.term(fam.name, DriftReference(rec.t[0], th[4], th[5]))
    k_naive = -float(idf.evaluate([naive]).fit.coef[-1])
    assert abs(k_naive / -0.02 - 1) > abs(kappa / -0.02 - 1)
    # the decimated column in closed form (three columns decimated once per record, combined)
    # is the decimated full-rate column to rounding, and the three are not decimated again
    for h in (term.h, naive.h):
        closed = fam.decimated_columns(h, idf.p)
        filtered = idf.p.dec(fam.columns(h, idf.p))
        assert closed.shape == filtered.shape == (len(idf.p.t_d), 1)
        assert np.max(np.abs(closed - filtered)) <= 1e-12 * np.max(np.abs(filtered))
    assert fam.decimated_columns(None, idf.p) is None      # the column on p.fu: decimated as it is
    kept = idf.p.derived[(fam.name, float(rec.t[0]))]
    assert not kept.flags.writeable
    fam.decimated_columns(term.h, idf.p)
    assert idf.p.derived[(fam.name, float(rec.t[0]))] is kept


# ------------------------------------------------------------------------------- dead-zone
@pytest.fixture(scope="module")
def dead_zone_run():
    """d = 0.15 V, o = 20 mV behind a 25 N stiction, the reading in 0.5 µm counts: the
    identifier, stiction's term, the dead-zone's term found beside it and its note."""
    rec = _simulate(dz=(0.15, 0.02), stiction_n=25.0, noise_v=0.02)
    rec.y = np.round(rec.y / 0.5e-6) * 0.5e-6
    idf = Identifier(rec, n_theta=6, zoh_delay=0.5)
    st, _ = FAMILIES["stiction"].search(idf, [], None)
    term, note = FAMILIES["amplifier_dead_zone"].search(idf, [st], None)
    return idf, st, term, note


def test_dead_zone_width_is_the_force_beyond_its_band_not_the_static_friction(dead_zone_run):
    """d = 0.15 V, o = 20 mV behind a 25 N stiction that holds the carriage through the dwells
    (its input band there is about ±0.3 V): the width comes from the motion, where the
    dead-zone takes A1·d against the sign of the input; the offset from the exact lost input
    f_u(u) − f_u(dz(u + o)) (where the band lies, and the force curve bending about u + o),
    which θ4 alone (F_0) cannot take."""
    idf, st, term, note = dead_zone_run
    fam = FAMILIES["amplifier_dead_zone"]
    assert note is None
    ev = idf.evaluate([st, term])
    par = fam.parameters(term.h, ev.fit.coef[-1:], A1, FS)
    assert par["dead_zone_V"] == pytest.approx(0.15, rel=0.05)
    assert par["lost_share"] == pytest.approx(1.0, abs=0.02)
    assert par["offset_V"] == pytest.approx(0.02, rel=0.1)
    assert not fam.plausible(idf, term, ev.fit.coef[-1:], ev.fit.coef[:6], [st])


def test_dead_zone_alone_at_rest_is_taken_with_its_exact_term():
    """d = 0.15 V, o = 20 mV on an axis without stiction (the dead-zone is what holds it at
    rest): the grid's width, then the exact lost input f_u(u) − f_u(dz(u + o)) refined from it
    (the linear columns, first order in o, leave the offset a third low on the rigid plant)."""
    rec = _simulate(dz=(0.15, 0.02), noise_v=0.02)
    idf = Identifier(rec, n_theta=6, zoh_delay=0.5)
    term, note = FAMILIES["amplifier_dead_zone"].search(idf, [], None)
    assert note is None and getattr(term.h, "offset", None) is not None, term.h
    assert float(term.h) == pytest.approx(0.15, rel=0.05)
    assert term.h.offset == pytest.approx(0.02, rel=0.1)


def test_stick_state_is_the_reading_standing_still_not_moved_by_the_window():
    """held_by_reading: 1 where the quantized reading stays within one count (the encoder's
    noise flickers it by one), 0 in motion, the motion's edges the same for any window; no
    stick state from a reading that is not quantized."""
    from motorctl.effects.stiction import encoder_count, held_by_reading
    q = 0.5e-6
    t = np.arange(4000) / FS
    x = np.where(t < 0.2, 0.0, np.where(t < 0.4, 0.05 * (t - 0.2), 0.01))    # 50 mm/s move
    noisy = x + 0.1e-6 * np.random.default_rng(1).standard_normal(len(t)) + 0.2e-6
    y = np.round(noisy / q) * q
    assert encoder_count(y) == pytest.approx(q)
    assert encoder_count(noisy) == 0.0 and not held_by_reading(noisy, 10).any()
    moving = (t >= 0.2) & (t < 0.4)
    for window in (5, 10, 20):
        s = held_by_reading(y, window)
        assert s[~moving][5:-5].all() and s[~moving].mean() > 0.99
        # the reading lags a start by less than a count (10 µs at 50 mm/s): a sample or so
        assert np.count_nonzero(s[moving]) <= 2


def test_dead_zone_values_taken_again_with_the_stick_state_from_the_reading(dead_zone_run):
    """With a dead-zone selected beside stiction on a quantized reading (0.5 µm counts) the
    refit re-weighs stiction by the measured stick state and searches the dead-zone again
    there: width and offset of d = 0.15 V, o = 20 mV within 10 %; the selection unchanged.
    An unquantized reading has no stick state to measure: no refit."""
    idf, st, dz, _ = dead_zone_run
    ref = _refit(idf.judge, [st, dz])
    assert ref is not None and ref.stick_measured and not ref.on_current_loop
    assert [t.family for t in ref.terms] == ["stiction", "amplifier_dead_zone"]
    got = ref.terms[1].h
    assert float(got) == pytest.approx(0.15, rel=0.1)
    assert got.offset == pytest.approx(0.02, rel=0.1)
    assert ref.families == ("amplifier_dead_zone", "stiction")
    # a reading that is not quantized shows no stick state: the selection's values stay
    import dataclasses

    from motorctl.ident.checks import Judge
    from motorctl.ident.columns import Columns
    from motorctl.ident.fit import Fits
    p = idf.setup.p
    unquantized = dataclasses.replace(idf.setup, p=dataclasses.replace(p, y=p.y + 1e-8 * np.sin(np.arange(len(p.y)))))
    assert _refit(Judge(Fits(Columns(unquantized, idf.structure))), [st, dz]) is None


# ------------------------------------------------------------------------------- the refit
def _refit(judge, terms):
    """The values' model :func:`motorctl.ident.values.refit` gives for a selection of ``terms``
    (no final model: no mode above the band looked for)."""
    from motorctl.ident.records import Selection
    from motorctl.ident.values import refit
    sel = Selection(structure=judge.fits.structure, nominal=None, final=None, terms=tuple(terms), accepted=(),
                    steps=())
    return refit(judge, sel)


@pytest.fixture(scope="module")
def stribeck_run():
    """10 N / 0.05 m/s Stribeck friction behind a 1 kHz current loop the header declares,
    identified as ``motorctl identify`` selects (the loop fitted as an input delay)."""
    rec = _simulate(tau_i=1 / (2 * math.pi * 1000.0), stribeck=(10.0, 0.05))
    rec.header = {"config": {"axes": {"X": {"driver": {"current_loop_hz": 1000.0}}}}}
    return Identifier(rec).run()


def _v_s(idf):
    i = next(k for k, t in enumerate(idf.terms) if t.family == "stribeck")
    return float(idf.terms[i].h)


def test_stribeck_velocity_is_taken_again_on_the_declared_current_loop(stribeck_run):
    """Fitted as a pure delay, the loop's lag trades against the hump within the few ms after
    each start (here 0.021 m/s beside a delay of 1.08 samples); the refit on the loop's model
    keeps the selection and takes v_s again there (0.053 m/s), the loop explaining the delay."""
    idf = stribeck_run
    ref = idf.refit()
    assert ref is not None and ref.on_current_loop and ref.fits.current_loop
    assert [t.family for t in ref.terms] == [t.family for t in idf.terms]
    assert "stribeck" in [t.family for t in idf.terms]
    assert _v_s(ref) == pytest.approx(0.05, rel=0.10)
    assert abs(_v_s(ref) - 0.05) < abs(_v_s(idf) - 0.05)
    delay = next((t for t in ref.terms if t.family == "input_delay"), None)
    assert delay is None or float(delay.h) < 0.3          # beyond the modelled loop: ~0
    # the values and the compensation written are the refit's; selection and verdict are not
    from motorctl.ident.pipeline import compensation_from_fit, values_from
    idf.refitted = ref
    try:
        assert values_from(idf) is ref
        comp, _, _ = compensation_from_fit(idf)
        assert comp["stribeck"]["velocity_m_per_s"] == pytest.approx(_v_s(ref))
        if delay is not None:       # 0 beyond the modelled loop: the preview is the loop's lag
            lag = 1 / (2 * math.pi * 1000.0)
            assert comp["input_delay"]["delay_s"] == pytest.approx(lag + float(delay.h) / FS)
        comp0, _, _ = compensation_from_fit(idf, idf.final, idf.terms)
        assert comp0["stribeck"]["velocity_m_per_s"] == pytest.approx(_v_s(idf))
    finally:
        idf.refitted = None


def test_refit_only_when_stribeck_is_selected_and_the_loop_not_yet_modelled(stribeck_run):
    idf = stribeck_run
    declared = Identifier(idf.rec)
    assert _refit(declared.judge, [t for t in idf.terms if t.family != "stribeck"]) is None   # nothing that takes it
    modelled = Identifier(idf.rec, current_loop=True)
    assert _refit(modelled.judge, idf.terms) is None        # the loop modelled already


def test_thrust_curve_columns_are_of_the_held_input():
    """u|u|, u³ are made of the held input, then delayed: a fractional delay's linear
    interpolation taken first would shrink a 2 kHz line at 5 kHz to cos(0.4π) = 0.31 and with it
    the curve's rectified part (the mean of u³ over U + a sin: U³ + 1.5 U a²), which a phantom
    force ripple then took (an encoder's 1 mm error at 2 m/s)."""
    n = int(2.0 * FS)
    t = np.arange(n) / FS
    u = 6.0 + 2.0 * np.sin(2 * np.pi * 2000.0 * t + 0.3)
    y = 0.1 * t + 1e-4 * np.sin(2 * np.pi * 3.0 * t)
    idf = Identifier(Record(t=t, y=y, u=u, gain=A1), zoh_delay=0.5)
    cols = idf.input_columns(0.5)
    mid = slice(100, n - 100)
    held = np.column_stack([u, u * np.abs(u), u ** 3])
    assert np.mean(cols[mid, 2]) == pytest.approx(np.mean(held[mid, 2]), rel=1e-3)   # 252, not 219.5
    assert np.mean(cols[mid, 1]) == pytest.approx(np.mean(held[mid, 1]), rel=1e-3)
    assert np.mean(cols[mid, 0]) == pytest.approx(6.0, rel=1e-3)


def test_an_effect_too_small_in_the_values_model_is_not_confirmed():
    """Every effect's values are the refit's (:meth:`Identifier.refit`): one whose force there is
    below the size an effect is named at is not confirmed and is dropped with that reason, even
    of a family whose values are not taken on the loop's or the stick state's model (a clean
    plant with a 269 Hz mode: a 3.8 N/m spring on the rigid model, 0.27 N/m with the mode's
    force above the band in the values' model). Here a spring put into the model of a plant
    that has none, its refit's stiffness ~0."""
    from dataclasses import replace

    from motorctl.ident.judge import confirm_values
    from motorctl.ident.values import ValuesModel
    idf = Identifier(_simulate(duration_s=4.0)).run()
    terms = idf.terms + [idf.term("spring", None)]
    final = idf.evaluate(terms)
    sel = replace(idf.selection, terms=tuple(terms), final=final,
                  accepted=idf.accepted + ((final, final.heldout_rms),))
    values = ValuesModel(fits=idf.fits, terms=sel.terms, final=final, band_mode={"columns_at_Hz": 150.0},
                         refitted=True)
    sel, _ = confirm_values(idf.judge, sel, values)
    assert "spring" not in [t.family for t in sel.terms]
    why = dict(sel.eliminated)["spring"]
    assert "not confirmed by the refit's model" in why and "too small to name" in why, why
