"""Stiction: a carriage at rest stays at rest until the applied force exceeds the breakaway force
(static friction above the Coulomb level; linear guides typically 1.1-1.5 × Coulomb).

Physical model (Karnopp): while |ẋ| is below a small band and |F_applied| ≤ F_s the carriage
does not move, whatever the input; the friction then holds exactly the applied force. Seen from
the nominal model (eq. 4: ẍ = 0 at rest, S_f(0) = 0) the input at rest is unexplained:

    F_eff = −w(ẋ)·(A1 u + F_0)        with w(ẋ) ≈ 1 at rest, 0 in motion                  [N]

Simulator: the plant's own Karnopp stiction, ``axes.NAME.driver.stiction_N`` (it needs the total
force at rest, which no :class:`~motorctl.effects.base.PlantTerm` hook sees, so it lives in
:class:`motorctl_drivers.sim.AxisPlant`; this family only switches it on). Identification:
columns u·w(ẋ), w(ẋ) with w(ẋ) = exp(−(ẋ/h)²), the band h searched on a log grid from 0.01 mm/s
to 3 mm/s (a band at its upper edge is low-speed friction, Stribeck's, and refused); β1 is the share of the input held at rest (1: fully held), β2 the constant it holds
against. Plausible when β1 is near 1 and the largest force held at rest (99th percentile of
|Cβ|) reaches half the Coulomb level θ3 (a record need not push to the breakaway).
While stiction is in the model the other effects' columns are weighed by 1 − w(ẋ): the
carriage held at rest feels no other force either (a periodic disturbance below the breakaway
force leaves no trace in the input at rest), so they are fitted on the samples in motion.
For the values only (a dead-zone selected beside it: :func:`motorctl.ident.values.
refit`), w(ẋ) is multiplied by the stick state measured from the encoder's reading
(:class:`StickState`, :func:`held_by_reading`).
Not compensable here: stiction is fought with the robust feedback (or a dither / breakaway kick
that needs the law's own output), not with an additive term in (x_d, ẋ_d, t).
"""

from __future__ import annotations

import math
from typing import ClassVar

import numpy as np

from motorctl.effects.base import EffectFamily
from motorctl.effects.stribeck import velocity_grid
from motorctl.metrics import runs

#: searched velocity band h [m/s]: "at rest" is a fraction of a millimetre per second of the
#: filtered velocity; a band of several mm/s is low-speed friction (Stribeck's), not a carriage held
BAND_GRID = np.exp(np.linspace(math.log(1e-5), math.log(3e-3), 20))
#: a band at least this wide [m/s] may hold part of a low-speed friction (:meth:`StictionFamily.joint_values`;
#: the clean default plant's band 0.3-0.45 mm/s)
WIDE_BAND = 1e-3
#: plausible share of the input held at rest (β1)
HELD_RANGE = (0.7, 1.3)
#: the largest input held at rest must reach this share of the Coulomb level θ3 (static
#: friction is at least the kinetic one; a record may not push to the breakaway, and the loop
#: holds the carriage with what its error asks for: on the default plant the 25 N stiction
#: holds at most 0.51-0.53 of θ3, 0.43-0.46 where a Stribeck hump, a position-dependent
#: friction or an encoder error raises θ3 before it is modelled, 0.30 beside a 0.6 ms delay)
MIN_HELD_COULOMB = 0.35
#: ... unless the reading shows a friction holding the carriage (:func:`dwell_spread`; for a band
#: narrower than :data:`WIDE_BAND`: a wider one, taken before a Stribeck hump of 20 N was
#: modelled on a plant with 12 / 15 N Coulomb / static friction, held 2.2 mm/s of it, and the
#: hump's rest went to a position-periodic friction and a ripple): the mean
#: input of the stretches the reading stands still differs from one dwell to the next at one
#: position by at least this share of θ3 (RMS). A carriage the loop holds in place (no static
#: friction: the rigid plant, its 0.5 and 5 µm encoders) needs the same force in every dwell,
#: the one that balances the constant forces there: 0.001 and 0.007-0.008 of θ3; a dead-zone
#: without stiction (the loop holds at the band's edge) 0.017; a friction holds what the loop
#: applied when it stopped, anything up to the breakaway: 0.20-0.21 on the default plant, 0.075-0.094
#: on a plant whose loop holds only 0.2 θ3 at rest (12/15 N Coulomb/static, a +2 N offset;
#: docs/identification.md, "Stiction: the hold the reading shows")
MIN_DWELL_SPREAD = 0.035
#: least duration of a dwell [s] (:func:`dwell_spread`) and the least degrees of freedom of
#: the spread (dwells beyond the first at each position)
MIN_DWELL_S, MIN_DWELL_DOF = 0.05, 3
#: dwells within this distance [m] of each other are at one position (a program's dwells
#: repeat their positions to within the stop's error, µm)
DWELL_POSITION_TOL = 1e-3


def weight(v: np.ndarray, h: float) -> np.ndarray:
    """w(ẋ) = exp(−(ẋ/h)²) (N,): 1 at rest, 0 in motion; v [m/s], h [m/s]."""
    return np.exp(-(v / h) ** 2)


#: half-window [samples] of the measured stick state (:func:`held_by_reading`)
STICK_WINDOW = 10


class StickState(float):
    """Stiction's parameter h with the stick state taken from the measurement: its float value
    is the velocity band h [m/s] the selection found (reported); ``window``: the half-window
    [samples] of :func:`held_by_reading`. The columns' weight is then w(ẋ)·s(t), s the
    measured stick state: the Karnopp model holds the carriage exactly still (x constant), so
    a sample is held only where the encoder's reading stands still too; w(ẋ) on the filtered
    velocity alone is a smooth stand-in for that switch which also weighs the samples just
    before a stop and after a breakaway (moving, less than a count yet), and a dead-zone's
    offset, seen mostly on the samples crossing its band at those instants, follows the band
    h of w (default plant, ×1: 0.10 / 0.25 mm/s give −0.5 / 24 mV for 20 mV). The product
    keeps w's exclusion of those instants (the reading lags the motion by up to a count) and
    takes the stick itself from the reading; the offset then no longer depends on the window
    (19.8, 19.7 mV for 20 at 10, 20 samples)."""

    def __new__(cls, h: float, window: int = STICK_WINDOW):
        obj = super().__new__(cls, float(h))
        obj.window = int(window)
        return obj


def encoder_count(y: np.ndarray) -> float:
    """The encoder's count [m] of the raw reading y (N,) [m]: its smallest step, when every
    reading lies on that grid (within 1 % of a count); 0 when y is not quantized (a filtered
    or interpolated record) or does not change."""
    dy = np.abs(np.diff(y))
    dy = dy[dy > 1e-12]
    if not dy.size:
        return 0.0
    q = float(dy.min())
    k = (y - y[0]) / q
    return q if float(np.max(np.abs(k - np.round(k)))) < 0.01 else 0.0


def held_by_reading(y: np.ndarray, window: int) -> np.ndarray:
    """The measured stick state (N,) in {0, 1}: 1 where the raw encoder reading y [m] stays
    within one count (a carriage held by Karnopp stiction does not move; the reading flickers
    by at most one count with the encoder's noise) over a stretch of 2·window + 1 samples that
    contains t (flat stretches, then widened back by the window: a morphological opening, so
    the motion's edges are not moved by the window), 0 elsewhere. All 0 when the reading is not
    quantized (:func:`encoder_count` 0)."""
    # imported here: the effect families are imported with every config (the daemon's too),
    # scipy.ndimage costs 0.16 s of start-up and only identification needs it
    from scipy.ndimage import maximum_filter1d, minimum_filter1d

    q = encoder_count(y)
    if q <= 0.0:
        return np.zeros_like(y)
    size = 2 * int(window) + 1
    spread = maximum_filter1d(y, size, mode="nearest") - minimum_filter1d(y, size, mode="nearest")
    flat = (spread <= 1.5 * q).astype(float)
    return maximum_filter1d(flat, size, mode="nearest")


def dwell_spread(p) -> float:
    """The RMS difference [V] of the mean input u between dwells at one position: the stretches
    of at least :data:`MIN_DWELL_S` where the raw reading stands still (:func:`held_by_reading`,
    half-window :data:`STICK_WINDOW`), grouped by position (:data:`DWELL_POSITION_TOL`), each
    dwell's mean u less its group's mean, pooled over the groups (n − 1 per group); NaN with fewer
    than :data:`MIN_DWELL_DOF` degrees of freedom or an unquantized reading. p: a prepared record
    (full-rate ``y`` [m], ``u`` [V], (N,), sampled at ``fs`` [Hz]); kept in ``p.derived``.

    A carriage held by the loop alone needs the same force at every dwell at one position (the
    one that balances what acts there: an offset, a spring, cogging), so its dwells' means
    differ by the noise; one held by a friction keeps whatever the loop applied when it
    stopped, anything within the breakaway force (Karnopp), so they differ by a share of it."""
    got = p.derived.get("dwell_spread")
    if got is not None:
        return got
    dwells = [(float(np.mean(p.y[a:b])), float(np.mean(p.u[a:b])))
              for a, b in zip(*runs(held_by_reading(p.y, STICK_WINDOW) > 0.5)) if (b - a) >= MIN_DWELL_S * p.fs]
    dwells.sort()
    dev, dof, group = 0.0, 0, []
    for d in dwells + [(math.inf, 0.0)]:
        if group and d[0] - group[-1][0] > DWELL_POSITION_TOL:
            m = np.array([u for _, u in group])
            dev += float(np.sum((m - m.mean()) ** 2))
            dof += len(m) - 1
            group = []
        group.append(d)
    got = p.derived["dwell_spread"] = math.sqrt(dev / dof) if dof >= MIN_DWELL_DOF else math.nan
    return got


#: the measured stick state must hold at least this share of the samples the velocity weight
#: holds (w(ẋ) > 0.5) to be used (:func:`reading_shows_stick`)
MIN_STICK_AGREEMENT = 0.5


def reading_shows_stick(p, h: float) -> bool:
    """The encoder's reading shows the stick state (:func:`held_by_reading`, half-window
    :data:`STICK_WINDOW`) on at least :data:`MIN_STICK_AGREEMENT` of the samples the velocity
    weight of band h [m/s] holds: a quantized reading whose noise stays within a count at rest.
    p: a prepared record (raw reading ``p.y`` [m], filtered velocity ``p.v`` [m/s], (N,))."""
    at_rest = weight(p.v, h) > 0.5
    if not at_rest.any():
        return False
    return float(np.mean(held_by_reading(p.y, STICK_WINDOW)[at_rest])) >= MIN_STICK_AGREEMENT


class StictionFamily(EffectFamily):
    name = "stiction"
    search_cost = 0.059
    plant_force = "holds the applied force at rest up to F_s (Karnopp)"
    searched = "velocity band h [m/s]"
    example: ClassVar[dict] = {"stiction_N": 25.0}
    look_alike: ClassVar[tuple[str, ...]] = ("amplifier_dead_zone",)
    acts_at_rest = True
    before_current_loop = True
    searched_on_current_loop = True

    # simulator: the plant core's Karnopp stiction (axis-level option, no hook)
    def sim_config(self, axis_options):
        return axis_options if getattr(axis_options, "stiction_N", 0.0) > 0.0 else None

    def plant_term(self, options, period_s):
        return None

    # identification
    def columns(self, h, p):
        """u·w(ẋ), w(ẋ), (N, 2); h: the velocity band [m/s] of w(ẋ) = exp(−(ẋ/h)²), or a
        :class:`StickState`: w the measured stick state (:func:`held_by_reading`)."""
        w = weight(p.v, h)
        if isinstance(h, StickState):
            w = w * held_by_reading(p.y, h.window)
        return np.column_stack([p.u * w, w])

    def stick_state(self, p, h, check: bool = True):
        """h as a :class:`StickState` (the stick state measured from the reading), when
        ``check`` is false or the reading of ``p`` shows it (:func:`reading_shows_stick`)."""
        if check and not reading_shows_stick(p, float(h)):
            return None
        return StickState(float(h))

    def other_weight(self, term):
        """1 − w(ẋ) (decimated): while the carriage is held, the other effects' forces are held
        too and leave no trace in the input; they are fitted on the samples in motion."""
        return 1.0 - term.cols[:, 1]

    def search(self, ctx, base, residual):
        p = ctx.p
        if np.mean(np.abs(p.v_d) < 2e-3) < 0.01:      # never at rest: nothing to see
            return None
        term, sses = ctx.best_over(self.name, BAND_GRID, base)
        i = int(np.argmin(sses))
        if i in (0, len(BAND_GRID) - 1):
            return term, f"velocity band {term.h:.3g} m/s at the edge of the searched range"
        fine = np.exp(np.linspace(math.log(BAND_GRID[i - 1]), math.log(BAND_GRID[i + 1]), 7))
        term, _ = ctx.best_over(self.name, fine, base)
        return term, None

    def joint_values(self, h):
        """A band of :data:`WIDE_BAND` or more may hold part of a low-speed friction taken up
        before that friction was modelled: the narrower bands of the grid (every other one) are
        tried with Stribeck searched beside each (default plant, Stribeck 30 N / 0.05 m/s: the
        selection's 2.0 mm/s band left F_s 24.6 N, v_s 0.058 m/s; beside 0.37 mm/s, 29.6 N and
        0.048 m/s with the lower SSE). Narrower bands: None."""
        return BAND_GRID[BAND_GRID < float(h)][::2] if float(h) >= WIDE_BAND else None

    def polish(self, ctx, term, others):
        """The band searched again (:meth:`search`) with the final model's other effects: taken
        first, before a low-speed friction was modelled, the band widens to take up part of it
        (default plant, Stribeck 20 N / 0.05 m/s: 1.65 mm/s, 0.33-0.41 mm/s beside the hump).
        None when the search's value sits at its grid's edge, or when the identifier does not
        model the current loop (its ``current_loop``: the selection as before)."""
        return self.searched_again(ctx, others) if getattr(ctx, "current_loop", False) else None

    def plausible(self, ctx, term, beta, theta, base):
        lo, hi = HELD_RANGE
        out = []
        if not lo <= beta[0] <= hi:
            out.append(f"share of the input held at rest {beta[0]:.2f} outside [{lo:g}, {hi:g}] "
                       "(stiction holds what is applied, no more)")
        held = float(np.percentile(np.abs(term.cols @ beta), 99))   # decimated, as the fit sees it
        if held < MIN_HELD_COULOMB * theta[2]:
            # the dwells speak for a hold at rest, not for a band of mm/s that takes part of a
            # low-speed friction too (WIDE_BAND): such a band keeps the held-force rule alone
            spread = dwell_spread(ctx.p) if float(term.h) < WIDE_BAND else math.nan
            if not spread >= MIN_DWELL_SPREAD * theta[2]:
                dwells = ("" if math.isnan(spread) else
                          f"; and the input held differs between dwells at one position by {spread:.3g} V RMS, below "
                          f"{MIN_DWELL_SPREAD:g} x theta3: the reading does not show a friction holding what the loop "
                          "applied either")
                out.append(f"holds at most {held:.3g} V at rest, below {MIN_HELD_COULOMB:g} x the Coulomb level "
                           f"theta3 {theta[2]:.3g} V: a static friction holds at least about that much{dwells}")
        return out

    def parameters(self, h, beta, gain, fs):
        return {"velocity_band_m_per_s": float(h), "held_share": float(beta[0])}

    # report
    def shape(self, ctx, h, beta, gain):
        vs = velocity_grid(ctx)
        vs = vs[np.abs(vs) <= 5 * h] if np.sum(np.abs(vs) <= 5 * h) > 10 else vs
        y = beta[0] * weight(vs, h)
        return vs, y, "velocity [m/s]", "share of the input held [-]"


FAMILY = StictionFamily()
