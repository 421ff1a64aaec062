"""Position-shaped friction: a Coulomb level that varies along the stroke in any smooth shape
(a worn rail section, waviness of a guide, a bearing preload that changes along the stroke).

Physical model (the paper's smooth friction shape S_f(ẋ) = (2/π) atan(900 ẋ), eq. 1):

    F_eff(x, ẋ) = −g(x) S_f(ẋ)                                                       [N]

Identification: g is a clamped uniform cubic B-spline over the record's position range
[x_lo, x_hi] with n segments, g(x) = Σ_j c_j B_j(x), j = 1..n+3 (de Boor, *A Practical Guide to
Splines*, 2001, ch. IX), constant beyond the range. The columns are B_j(x)·S_f(ẋ) for
j = 2..n+3: B_1 is left out because Σ_j B_j = 1, so the mean level of g is θ3's (only the
shape of g is identifiable). The searched parameter h is the knot grid (:class:`KnotGrid`, a
float equal to the knot spacing [m] that also carries x_lo, x_hi and n); n is chosen by the
identifier's held-out rule (:meth:`PositionFrictionShapeFamily.search`):

* the baseline is the linear family, ``position_dependent_friction`` (column x·S_f(ẋ)), which
  stays the one-term case of this family: a cubic spline contains every straight line;
* n runs over :data:`SEGMENTS`; a count is kept only when its 2-fold held-out residual RMS is at
  least :data:`TERM_GAIN` (3 %, the identifier's MIN_HELDOUT_GAIN) below that of the count kept
  before (the linear baseline at first);
* when no count beats the straight line, the candidate carries a note that makes it
  implausible: a linear slope is ``position_dependent_friction``'s, whose one column is
  preferred. When both are accepted this family's held-out gain is the larger (by the rule
  above), so forward selection takes it; when the linear family was selected first, the grid
  also leaves out the last B-spline (``drop_linear``), whose direction x·S_f(ẋ) then has.

The search uses ``ctx.heldout_rms(terms)`` (:meth:`motorctl.ident.fit.Fits.heldout_rms`),
the identifier's own 2-fold block cross-validation.

Plausibility: the Coulomb level θ3 + g(x) stays positive over the range, and the shape is
friction: a friction force changes sign with the direction of motion, so the same basis as a
direction-independent force f(x) (columns B_j(x), as a spring or cogging would need) must lower
the SSE by less than :data:`MAX_FORCE_SHARE` of what the friction columns do. (The per-direction
agreement the position-periodic families use needs 4 × the columns in samples per direction,
more than a 6 s record of the gantry has with 10 columns.)

Compensation: d̂_eff(x_d, ẋ_d) = −(g_V(x_d) − offset_V) S_f(ẋ_d) [V], g_V = g / A1 evaluated as
a piecewise cubic on precomputed per-segment coefficients (no scipy call in the cycle), plus the
exact raised-cosine bumps of the simulator's form (:meth:`~PositionFrictionShapeFamily.compensation_for`).
The emitted offset_V is the mean of g_V over the record weighted by |S_f(ẋ)| (where friction
acts), so the term has zero mean over the identified motion; the θ̂(0) written with it is the
fitted θ3 + offset_V (:meth:`~PositionFrictionShapeFamily.theta_shift`).
"""

from __future__ import annotations

import math
from typing import ClassVar

import numpy as np
from pydantic import Field, model_validator

from motorctl.effects.base import CompTerm, EffectFamily, PlantTerm
from motorctl.effects.periodic import SHAPE_POINTS
from motorctl.effects.position_dependent_friction import FAMILY as LINEAR, direction_check
from motorctl.jit import njit
from motorctl.model import s_f
from motorctl.schema import Pos, StrictModel

#: segment counts n tried, in increasing order (n + 2 columns each). At most 12: on the gantry's
#: 8-20 s records 16 segments (18 columns) of a narrow bump fail the identifier's mean Wald per
#: column (most columns are flat), and the 0.25 s held-out blocks leave parts of the stroke unseen
#: by one fold, so finer grids cannot be judged (their held-out RMS blows up)
SEGMENTS = (1, 2, 3, 4, 6, 8, 12)
#: least relative drop of the held-out residual RMS for a larger segment count to be kept
#: (equal to ``motorctl.ident.rules.MIN_HELDOUT_GAIN``; checked by the tests)
TERM_GAIN = 0.03
#: largest SSE reduction of the same basis as a direction-independent force, relative to the
#: friction shape's, for the friction shape to be plausible
MAX_FORCE_SHARE = 0.5
#: largest SSE reduction of the same basis over the speed |ẋ| (a friction that varies with the
#: speed: :meth:`KnotGrid.as_speed`), relative to the friction shape's, for the shape to be
#: told from it: a program that passes each position at the same speed makes a speed's
#: friction a shape of position (an encoder's interpolation error on the default plant left
#: ±0.5 N at cruise and ∓1 N at 0.2-1 m/s, taken as an 8-segment shape of 27 N; its speed basis
#: explains 1.0× as much, a 15 N bump in the cruise 0.0x)
MAX_SPEED_SHARE = 0.7
#: shortest position range [m] a shape is looked for over
MIN_RANGE_M = 0.01
DEGREE = 3
#: share of the viscous column ẋ the shape's columns must explain (R² over the moving samples)
#: for the record to be taken as unable to tell a friction shape from viscous friction
#: (:func:`viscous_span`)
VISCOUS_R2 = 0.9


# ---------------------------------------------------------------------------- YAML
class FrictionBump(StrictModel):
    """One raised-cosine bump of the Coulomb level [N]: a (cos(π (x − c)/w))² for |x − c| < w/2,
    0 elsewhere. center_m: c [m]. width_m: w, the full width of the bump [m]. amplitude_N: a,
    the extra Coulomb force at the centre [N] (negative: less friction there)."""

    center_m: float
    width_m: Pos
    amplitude_N: float


class PositionFrictionShape(StrictModel):
    """Simulated position-shaped friction, ``axes.NAME.driver.effects.position_friction_shape``:
    −g(x) S_f(ẋ) [N], g(x) = Σ of the ``bumps`` (at least one)."""

    bumps: list[FrictionBump] = Field(min_length=1)


class FrictionBumpComp(StrictModel):
    """A bump of the compensated Coulomb level [V]: as :class:`FrictionBump`, amplitude_V = a / A1."""

    center_m: float
    width_m: Pos
    amplitude_V: float


class PositionFrictionShapeComp(StrictModel):
    """Compensation, ``axes.NAME.controller.compensation.position_friction_shape``:
    −(g_V(x) − offset_V) S_f(ẋ) [V], g_V(x) = spline(x) + Σ bumps(x).

    start_m, end_m: the range [x_lo, x_hi] of the spline [m] (x_lo < x_hi); coefficients_V: its
    clamped uniform cubic B-spline coefficients c_j [V] (n + 3 of them for n segments, at least
    4), g constant beyond the range; bumps: raised-cosine bumps (:class:`FrictionBumpComp`);
    offset_V: subtracted from g_V (the record's mean level, carried by θ̂3) [V].
    At least one of the spline and the bumps.
    """

    start_m: float | None = None
    end_m: float | None = None
    coefficients_V: list[float] = Field(default_factory=list)
    bumps: list[FrictionBumpComp] = Field(default_factory=list)
    offset_V: float = 0.0

    @model_validator(mode="after")
    def _check(self):
        if self.coefficients_V:
            if self.start_m is None or self.end_m is None or not self.end_m > self.start_m:
                raise ValueError("coefficients_V needs start_m < end_m")
            if len(self.coefficients_V) < DEGREE + 1:
                raise ValueError(f"coefficients_V: at least {DEGREE + 1} (one segment)")
        elif not self.bumps:
            raise ValueError("needs coefficients_V (with start_m, end_m) or bumps")
        return self


# ---------------------------------------------------------------------------- the basis
class KnotGrid(float):
    """The searched parameter h: a clamped uniform cubic knot grid over [start_m, end_m] with
    ``segments`` segments. Its float value is the knot spacing [m] (what ``identify --json``
    reports as "searched"); the attributes define the basis, so the same columns are built on
    any record (validation, compensation).

    Raises:
        ValueError: end_m ≤ start_m or segments < 1.
    """

    def __new__(cls, start_m: float, end_m: float, segments: int, drop_linear: bool = False,
                force: bool = False, span=None, speed_max: float | None = None):
        start_m, end_m, segments = float(start_m), float(end_m), int(segments)
        if not end_m > start_m or segments < 1:
            raise ValueError(f"knot grid {start_m:g}..{end_m:g} m with {segments} segments")
        obj = super().__new__(cls, (end_m - start_m) / segments)
        obj.start_m, obj.end_m, obj.segments = start_m, end_m, segments
        obj.drop_linear, obj.force = bool(drop_linear), bool(force)
        #: None, or the (k, k − 1) map Q (a tuple of rows) from the fitted β to the free
        #: B-splines' coefficients: the shape is fitted without the direction viscous friction
        #: takes on this record (:func:`viscous_span`)
        obj.span = None if span is None else tuple(tuple(float(v) for v in row) for row in span)
        #: None, or the speed [m/s] mapped to end_m: the basis is then one of the speed
        #: (:meth:`as_speed`)
        obj.speed_max = None if speed_max is None else float(speed_max)
        return obj

    def __reduce__(self):
        return KnotGrid, (self.start_m, self.end_m, self.segments, self.drop_linear, self.force, self.span,
                          self.speed_max)

    def __repr__(self) -> str:
        flags = ((", drop_linear" if self.drop_linear else "") + (", force" if self.force else "")
                 + (", without the viscous direction" if self.span is not None else "")
                 + (f", over the speed up to {self.speed_max:.4g} m/s" if self.speed_max is not None else ""))
        return f"KnotGrid({self.start_m:.6g}, {self.end_m:.6g}, {self.segments}{flags})"

    def as_force(self) -> KnotGrid:
        """The same basis as a direction-independent force f(x) (columns B_j(x), no S_f(ẋ)):
        the alternative :meth:`PositionFrictionShapeFamily.plausible` compares with."""
        return KnotGrid(self.start_m, self.end_m, self.segments, self.drop_linear, force=True, span=self.span)

    def as_speed(self, speed_max: float) -> KnotGrid:
        """The same basis over the speed: columns B_j(z)·S_f(ẋ) with z = start_m + (end_m −
        start_m)·min(|ẋ|/speed_max, 1) (a Coulomb level that varies with the speed, e.g. a
        Stribeck hump or a speed-dependent error of the model), the alternative
        :meth:`PositionFrictionShapeFamily.plausible` compares with; speed_max [m/s] > 0."""
        return KnotGrid(self.start_m, self.end_m, self.segments, self.drop_linear, span=self.span,
                        speed_max=speed_max)

    def with_span(self, span) -> KnotGrid:
        """The same grid with the coefficient map ``span`` (k, k − 1) (None: all directions)."""
        return KnotGrid(self.start_m, self.end_m, self.segments, self.drop_linear, self.force, span, self.speed_max)

    @property
    def n_columns(self) -> int:
        """Number of regressor columns (fitted β)."""
        return len(self.free()) - (0 if self.span is None else 1)

    @property
    def knots(self) -> np.ndarray:
        """The clamped knot vector (segments + 7,) [m]."""
        inner = np.linspace(self.start_m, self.end_m, self.segments + 1)
        return np.r_[[self.start_m] * DEGREE, inner, [self.end_m] * DEGREE]

    @property
    def n_basis(self) -> int:
        """Number of B-splines K = segments + 3."""
        return self.segments + DEGREE

    def free(self) -> np.ndarray:
        """Indices (k,) of the B-splines that are columns: all but the first (θ3 has the mean),
        and but the last when the linear family's column x·S_f(ẋ) is in the model too."""
        return np.arange(1, self.n_basis - (1 if self.drop_linear else 0))

    def basis(self, x) -> np.ndarray:
        """B_j(x) (N, K) at positions x (N,) [m], x clamped into [start_m, end_m].

        The clamped x lies within the knots' base interval, where ``extrapolate=True`` gives the
        same matrix and skips scipy's bounds check (Python's min and max over the N samples,
        half of the call's time on a 100 000-sample record)."""
        from scipy.interpolate import BSpline     # identification only (not the loop process)
        xc = np.clip(np.asarray(x, dtype=float), self.start_m, self.end_m)
        return BSpline.design_matrix(xc, self.knots, DEGREE, extrapolate=True).toarray()

    def coefficients(self, beta) -> np.ndarray:
        """All K spline coefficients c_j from the fitted column coefficients β (k,)
        (0 for the B-splines left out)."""
        c = np.zeros(self.n_basis)
        b = np.asarray(beta, dtype=float)
        c[self.free()] = b if self.span is None else np.asarray(self.span) @ b
        return c


def viscous_span(h: KnotGrid, p, moving) -> np.ndarray | None:
    """The coefficient map (k, k − 1) that leaves out of the shape the direction viscous
    friction takes on this record, or None when the record separates the two.

    On a program that passes each position at the same speed in each direction, the speed is
    a function of position, |ẋ| = s(x), so B ẋ = B s(x) S_f(ẋ) is a friction shape too: the
    viscous column is (nearly) in the span of the shape's columns [S_f(ẋ), B_j(x) S_f(ẋ)] and a
    joint fit can trade B against g(x) = −B s(x) (a negative θ2 or a Coulomb level that turns
    negative at the ends). When the shape's columns explain at least :data:`VISCOUS_R2` of the
    viscous column over the moving samples (R², least squares), the direction a they do it
    with is left out: the shape is fitted on the β with (C̃ a)ᵀ(C̃ β) = 0 (C̃ the shape's
    columns less their projection on θ3's S_f(ẋ)), so the part of the record viscous friction
    explains stays θ2's (the nominal model's).

    Args:
        h: the knot grid (its ``span`` is ignored). p: the prepared record (decimated x_d, v_d
            (M,) [m, m/s]). moving: bool (M,), the samples in motion.
    Returns:
        Q (k, k − 1) with orthonormal columns, k = len(h.free()), or None.
    """
    from scipy.linalg import null_space
    mv = np.asarray(moving, dtype=bool)
    if mv.sum() < 4 * (len(h.free()) + 1):
        return None
    v = p.v_d[mv]
    sf = s_f(v)
    c = h.basis(p.x_d[mv])[:, h.free()] * sf[:, None]
    a_full = np.column_stack([sf, c])
    coef = np.linalg.lstsq(a_full, v, rcond=None)[0]
    r = v - a_full @ coef
    if 1.0 - float(r @ r) / float(v @ v) < VISCOUS_R2:
        return None
    # θ3's column S_f(ẋ) is in every model: the direction is taken on the columns without it
    ct = c - np.outer(sf, (sf @ c) / float(sf @ sf))
    w = ct.T @ (ct @ coef[1:])
    if not np.any(w):
        return None
    return null_space(w[None, :])


def knot_grid(start_m: float, end_m: float, segments: int) -> KnotGrid:
    """A knot grid h for :meth:`PositionFrictionShapeFamily.columns` (public helper for tests
    and tools)."""
    return KnotGrid(start_m, end_m, segments)


def bump_value(x, center: float, width: float, amplitude: float):
    """a (cos(π (x − c)/w))² for |x − c| < w/2, else 0, vectorised over x (N,) [m]."""
    z = (np.asarray(x, dtype=float) - center) / width
    return np.where(np.abs(z) < 0.5, amplitude * np.cos(np.pi * z) ** 2, 0.0)


def spline_pieces(start_m: float, end_m: float, coefficients) -> tuple:
    """Per-segment power coefficients of a clamped uniform cubic B-spline, for the cycle.

    Returns:
        (lo [m], 1/Δ [1/m], n, a0, a1, a2, a3, g_lo, g_hi): on segment i (u = (x − lo)/Δ − i in
        [0, 1]) g = a0[i] + u (a1[i] + u (a2[i] + u a3[i])); tuples of n floats; g_lo, g_hi
        the values at the ends (g is constant beyond them).
    """
    from scipy.interpolate import BSpline, PPoly  # at build time, only for a config that uses it
    c = np.asarray(coefficients, dtype=float)
    n = len(c) - DEGREE
    h = KnotGrid(start_m, end_m, n)
    pp = PPoly.from_spline(BSpline(h.knots, c, DEGREE))
    keep = np.flatnonzero(np.diff(pp.x) > 0)[:n]          # the n segments of non-zero length
    dx = h.real
    # PPoly: g = Σ_m c[m] s^(3−m), s = x − x_i  ->  u = s/Δ: a_k = c[3−k] Δ^k
    a = [tuple(float(v) for v in pp.c[DEGREE - k, keep] * dx ** k) for k in range(DEGREE + 1)]
    spl = BSpline(h.knots, c, DEGREE)
    return (start_m, 1.0 / dx, n, *a, float(spl(start_m)), float(spl(end_m)))


@njit
def plant_force(f, x, v, t, sf, p):
    """f + F_eff [N] at position x [m] with sf = S_f(v) (v, t unused): f − g(x) sf, g the sum of
    raised-cosine bumps a cos²(k (x − c)) for |x − c| < h (:func:`bump_value`); the row
    p = (c_1 [m], h_1 = w_1/2 [m], k_1 = π/w_1 [rad/m], a_1 [N], c_2, ...)."""
    g = 0.0
    for j in range(0, p.shape[0], 4):
        s = x - p[j]
        if -p[j + 1] < s < p[j + 1]:
            q = math.cos(p[j + 2] * s)
            g += p[j + 3] * q * q
    return f - g * sf


def _spline_row(pieces) -> list[float]:
    """The row of :func:`_spline_at` for :func:`spline_pieces`' result: (lo, 1/Δ, n, g_lo, g_hi,
    a0[0..n), a1[0..n), a2[0..n), a3[0..n))."""
    lo, inv, n, a0, a1, a2, a3, g_lo, g_hi = pieces
    return [lo, inv, float(n), g_lo, g_hi, *a0, *a1, *a2, *a3]


@njit
def _spline_at(x, p, at):
    """g(x) of the spline whose :func:`_spline_row` starts at p[at]: constant beyond the ends,
    else a0[i] + u (a1[i] + u (a2[i] + u a3[i])) on segment i, u = (x − lo)/Δ − i."""
    n = int(p[at + 2])
    z = (x - p[at]) * p[at + 1]
    if z <= 0.0:
        return p[at + 3]
    if z >= n:
        return p[at + 4]
    i = int(z)
    u = z - i
    a = at + 5 + i
    return p[a] + u * (p[a + n] + u * (p[a + 2 * n] + u * p[a + 3 * n]))


def _spline_fn(pieces):
    """g(x) [same unit as the coefficients] of :func:`spline_pieces` as a scalar function."""
    row = np.array(_spline_row(pieces))
    return lambda x: _spline_at(x, row, 0)


@njit
def _bumps_at(x, p, at):
    """Σ a cos²(k (x − c)) over the bumps with |x − c| < h; p[at] = the count, then (c [m], h [m],
    k [rad/m], a) per bump."""
    g = 0.0
    for j in range(at + 1, at + 1 + 4 * int(p[at]), 4):
        s = x - p[j]
        if -p[j + 1] < s < p[j + 1]:
            q = math.cos(p[j + 2] * s)
            g += p[j + 3] * q * q
    return g


@njit
def comp_add(d, x, v, t, sf, p):
    """d − (g(x_d) − offset) S_f(ẋ_d) [V], g = the spline (when p[0] != 0) plus the bumps; the
    row p = (has spline, :func:`_spline_row` (when it has), the bump count, (c, h = w/2,
    k = π/w, a) per bump, offset [V])."""
    at = 1
    if p[0] != 0.0:
        g = _spline_at(x, p, 1)
        at = 6 + 4 * int(p[3])
        if p[at] > 0.0:
            g = g + _bumps_at(x, p, at)
    else:
        g = _bumps_at(x, p, at)
    return d - (g - p[p.shape[0] - 1]) * sf


# ---------------------------------------------------------------------------- the family
class PositionFrictionShapeFamily(EffectFamily):
    name = "position_friction_shape"
    search_cost = 0.12
    kernels = (("force", plant_force), ("add", comp_add))
    plant_force = "−g(x) S_f(ẋ), g a smooth shape (cubic B-spline)"
    searched = "knot spacing [m] (segment count chosen by the held-out rule)"
    sim_options = PositionFrictionShape
    #: a worn section of the X rail (M 12.8 kg, A1 80 N/V, stroke 0 … 0.4 m at 2 m/s): 15 N more
    #: Coulomb friction (20 N nominal) over 0.17 … 0.33 m, off-centre so it is not linear either
    example: ClassVar[dict] = {"position_friction_shape": {
        "bumps": [{"center_m": 0.25, "width_m": 0.16, "amplitude_N": 15.0}]}}
    comp_options = PositionFrictionShapeComp
    comp_needs_sf = True
    simpler = LINEAR.name

    # simulator
    def plant_term(self, o: PositionFrictionShape, period_s):
        row = []
        for b in o.bumps:
            row += [b.center_m, 0.5 * b.width_m, math.pi / b.width_m, b.amplitude_N]
        return PlantTerm.compiled("force", plant_force, row)

    # identification
    def columns(self, h, p):
        """B_j(x)·S_f(ẋ) for the free B-splines of the grid h (:meth:`KnotGrid.free`),
        (N, k) with k = segments + 2 (+ 1 without the linear family's column).

        Raises:
            TypeError: h is not a :class:`KnotGrid`.
        (``h.force``: B_j(x) alone, the direction-independent alternative of the plausibility check.)
        """
        if not isinstance(h, KnotGrid):
            raise TypeError(f"{self.name}: the searched parameter must be a KnotGrid, not {h!r}")
        z = p.x if h.speed_max is None else \
            h.start_m + (h.end_m - h.start_m) * np.minimum(np.abs(p.v) / h.speed_max, 1.0)
        b = h.basis(z)[:, h.free()]
        if h.span is not None:
            b = b @ np.asarray(h.span)
        return b if h.force else b * s_f(p.v)[:, None]

    def search(self, ctx, base, residual):
        """Segment count by the held-out rule (module docstring), over the record's position range."""
        x = ctx.p.x
        lo, hi = float(np.min(x)), float(np.max(x))
        if hi - lo < MIN_RANGE_M or ctx.moving.sum() < 50:
            return None
        has_linear = any(t.family == LINEAR.name for t in base)
        ref = base if has_linear else base + [ctx.term(LINEAR.name, None)]
        kept_rms = ctx.heldout_rms(ref)
        linear_rms = kept_rms
        kept = None
        first = None
        for n in SEGMENTS:
            term = ctx.term(self.name, KnotGrid(lo, hi, n, drop_linear=has_linear))
            first = first or term
            rms = ctx.heldout_rms(base + [term])
            if rms <= (1.0 - TERM_GAIN) * kept_rms:
                kept, kept_rms = term, rms
        if kept is None:
            gain = 1.0 - ctx.heldout_rms(base + [first]) / linear_rms
            return first, (f"no shape beyond a linear slope: {first.h.segments} segment(s) lower the held-out "
                           f"residual of {LINEAR.name} by {100 * gain:.1f} % (< {100 * TERM_GAIN:g} %)")
        if self._traded(ctx, kept, base):
            span = viscous_span(kept.h, ctx.p, ctx.moving)
            if span is not None:
                kept = ctx.term(self.name, kept.h.with_span(span))
        return kept, None

    def _traded(self, ctx, term, base) -> bool:
        """True when the joint fit with ``term`` is not physical in the way a shape traded
        against viscous friction is (θ2 significantly negative, or the Coulomb level θ3 + g(x)
        negative over the moving range): then :func:`viscous_span` decides the split."""
        ev = ctx.evaluate(base + [term])
        nt = ctx.n_theta
        th, sd = ev.fit.coef[:nt], ev.fit.std[:nt]
        k = term.cols.shape[1]
        beta = ev.fit.coef[-k:]
        return bool(th[1] < -3 * sd[1] or self._coulomb_min(ctx, term.h, beta, th) < 0)

    @staticmethod
    def _coulomb_min(ctx, h, beta, theta) -> float:
        """The least Coulomb level θ3 + g(x) over the positions the axis moved through."""
        xm = ctx.p.x_d[ctx.moving]
        lo, hi = (np.percentile(xm, [1.0, 99.0]) if xm.size else (h.start_m, h.end_m))
        xs = np.linspace(max(lo, h.start_m), min(hi, h.end_m), SHAPE_POINTS)
        return float(theta[2] + (h.basis(xs) @ h.coefficients(beta)).min())

    def plausible(self, ctx, term, beta, theta, base):
        reasons = []
        h = term.h
        # over the positions the axis moved through (1st..99th percentile): where it only rests
        # or turns round, friction is not seen and the spline is not held by data
        if self._coulomb_min(ctx, h, beta, theta) < 0:
            reasons.append("Coulomb level would turn negative over the stroke")
        # friction changes sign with the direction of motion: the same basis as a force f(x) that
        # does not (a spring, cogging, a magnet) must explain clearly less
        s0 = ctx.sse(base)
        d_fric = s0 - ctx.sse(base + [term])
        d_force = s0 - ctx.sse(base + [ctx.term(self.name, h.as_force())])
        if d_force > MAX_FORCE_SHARE * d_fric:
            reasons.append(f"not friction: the same shape as a direction-independent force f(x) explains "
                           f"{100 * d_force / max(d_fric, 1e-300):.0f} % as much (> {100 * MAX_FORCE_SHARE:g} %)")
        # a friction of position is the same at a position whatever the speed: the same basis over
        # |ẋ| must explain clearly less (else the record passes each position at one speed)
        v_max = float(np.max(np.abs(ctx.p.v_d)))
        if v_max > 0:
            d_speed = s0 - ctx.sse(base + [ctx.term(self.name, h.as_speed(v_max))])
            if d_speed > MAX_SPEED_SHARE * d_fric:
                reasons.append(f"not told from a friction that varies with the speed: the same basis over |v| "
                               f"explains {100 * d_speed / max(d_fric, 1e-300):.0f} % as much "
                               f"(> {100 * MAX_SPEED_SHARE:g} %)")
        return reasons + direction_check(ctx, term, base)

    def parameters(self, h, beta, gain, fs):
        """The knot grid (segments, spacing [m]) and the size of the shape: the peak-to-peak value
        of g over the record's range [N, or V without a gain] and the position of its extremum
        (largest |g − mean|) [m]. The shape itself (range, coefficients) is the compensation
        entry's spline and the report's figure."""
        g_, unit = (gain, "N") if gain else (1.0, "V")
        xs = np.linspace(h.start_m, h.end_m, SHAPE_POINTS)
        g = g_ * (h.basis(xs) @ h.coefficients(beta))
        g -= g.mean()
        return {"segments": int(h.segments), "knot_spacing_m": float(h), f"peak_to_peak_{unit}": float(np.ptp(g)),
                "extremum_position_m": float(xs[np.argmax(np.abs(g))])}

    # compensation
    def compensation(self, h, beta, signals=None):
        """The spline of the fit [V]; offset_V: the mean of g_V over ``signals`` weighted by
        |S_f(ẋ)| (0 without ``signals``)."""
        c = h.coefficients(beta)
        off = 0.0
        if signals is not None:
            w = np.abs(s_f(signals.v))
            g = h.basis(signals.x) @ c
            off = float(np.sum(w * g) / np.sum(w)) if np.sum(w) > 0 else float(np.mean(g))
        return {"start_m": h.start_m, "end_m": h.end_m, "coefficients_V": [float(v) for v in c],
                "offset_V": off}

    def theta_shift(self, entry, n_theta):
        """u = … + θ3 S_f + g_V S_f = … + (θ3 + offset_V) S_f + (g_V − offset_V) S_f:
        Δθ3 = offset_V."""
        d = np.zeros(n_theta)
        d[2] = entry.get("offset_V", 0.0)
        return d

    def compensation_for(self, o: PositionFrictionShape, a1):
        return {"bumps": [{"center_m": b.center_m, "width_m": b.width_m, "amplitude_V": b.amplitude_N / a1}
                          for b in o.bumps]}

    def compensator(self, o: PositionFrictionShapeComp):
        row = [0.0]
        if o.coefficients_V:
            row = [1.0, *_spline_row(spline_pieces(o.start_m, o.end_m, o.coefficients_V))]
        row.append(float(len(o.bumps)))
        for b in o.bumps:
            row += [b.center_m, 0.5 * b.width_m, math.pi / b.width_m, b.amplitude_V]
        return CompTerm("add", comp_add, row + [o.offset_V])

    # report
    def shape(self, ctx, h, beta, gain):
        """g(x) about its mean over the record (weighted by |S_f(ẋ)|, the level θ̂3 carries)
        against position over the knot grid's range."""
        xs = np.linspace(h.start_m, h.end_m, SHAPE_POINTS)
        c = h.coefficients(beta)
        w = np.abs(s_f(ctx.p.v))
        mean = float(np.sum(w * (h.basis(ctx.p.x) @ c)) / max(float(np.sum(w)), 1e-300))
        y = (gain or 1.0) * (h.basis(xs) @ c - mean)
        return xs, y, "position [m]", "g(x) − mean [UNIT]"


FAMILY = PositionFrictionShapeFamily()
