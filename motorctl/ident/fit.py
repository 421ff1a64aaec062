"""Stage *fit*: joint least squares of the nominal model and a list of terms (IDIM-LS), its SSE,
BIC and 2-fold held-out RMS (an :class:`~motorctl.ident.records.Evaluated` record), the
searches over a family's parameter and the split of the coefficients into θ and each term's β.

:class:`Fits` is also what a family's search and checks are handed
(:class:`motorctl.effects.base.SearchContext`): the fits, the terms of the candidates stage
(:class:`~motorctl.ident.columns.Columns`) and the read-outs of :mod:`motorctl.ident.probes`.
It holds no selection: what was chosen is in the records the other stages pass around.
"""

from __future__ import annotations

import math
import threading
from dataclasses import replace

import numpy as np

from motorctl.effects import family as effect_family
from motorctl.ident import probes
from motorctl.ident.columns import Columns
from motorctl.ident.idim import ls, ls_coef as _coef, ls_sse as _sse_of, unit_columns
from motorctl.ident.records import Evaluated, Structure, Term, hold, same_width

#: base term lists whose normal equations :meth:`Fits.sse` keeps per thread
PARTIAL_CACHE = 4


class Fits:
    """Joint LS fits of the nominal model plus terms on one record at one structure.

    Args:
        columns: the candidates stage on the record (:class:`~motorctl.ident.columns.Columns`).
    """

    def __init__(self, columns: Columns):
        self.columns = columns
        self.setup = columns.setup
        self._local = threading.local()

    def at(self, structure: Structure, fresh: bool = False) -> "Fits":
        """The fits of the same record at another nominal structure (:meth:`Columns.at`)."""
        return Fits(self.columns.at(structure, fresh))

    def with_structure(self, fresh: bool = False, **changes) -> "Fits":
        """:meth:`at` the structure with ``changes`` (its fields)."""
        return self.at(replace(self.structure, **changes), fresh)

    def __getstate__(self) -> dict:
        """Pickled without the per-thread normal equations of :meth:`sse` (rebuilt on demand)."""
        state = self.__dict__.copy()
        state.pop("_local", None)
        return state

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self._local = threading.local()

    # what the families read (motorctl.effects.base.SearchContext)
    structure = property(lambda self: self.columns.structure)
    p = property(lambda self: self.columns.p)
    n_theta = property(lambda self: self.columns.structure.n_theta)
    zoh = property(lambda self: self.columns.structure.zoh)
    nuisance = property(lambda self: self.columns.structure.nuisance)
    rec = property(lambda self: self.setup.rec)
    stroke = property(lambda self: self.setup.stroke)
    moving = property(lambda self: self.setup.moving)
    fold = property(lambda self: self.setup.fold)
    m = property(lambda self: self.setup.m)
    memo = property(lambda self: self.setup.memo)
    families = property(lambda self: self.setup.families)
    friction = property(lambda self: self.setup.friction)
    current_loop = property(lambda self: self.setup.current_loop)
    loop_filter = property(lambda self: self.setup.loop_filter)
    modelled_lag = property(lambda self: self.setup.modelled_lag)

    def term(self, family: str, h) -> Term:
        """The term of ``family`` at h (:meth:`Columns.term`)."""
        return self.columns.term(family, h)

    def dec_cols(self, family: str, h) -> np.ndarray | None:
        return self.columns.dec_cols(family, h)

    def target(self, delay: float = 0.0) -> np.ndarray:
        return self.columns.target(delay)

    def delayed_u(self, delay: float) -> np.ndarray:
        return self.columns.delayed_u(delay)

    def input_columns(self, delay: float) -> np.ndarray:
        return self.columns.input_columns(delay)

    def design(self, terms) -> tuple[np.ndarray, np.ndarray]:
        """Regressor (M, p) and target (M,) of the nominal model plus ``terms``. A term whose
        family holds the carriage at rest (stiction, :meth:`~motorctl.effects.base.EffectFamily.
        other_weight`) weighs the other terms' columns: a force the carriage does not feel while
        it is held is fitted on the samples in motion only. The structure's ``nuisance`` (when
        set) last, weighed the same."""
        delay = self.zoh + sum(t.delay for t in terms)
        weight = hold(terms)[0]
        cols = [self.columns.nominal_phi(delay)]
        for t in terms:
            if t.cols is not None:
                own = weight is None or effect_family(t.family).other_weight(t) is not None
                cols.append(t.cols if own else t.cols * weight[:, None])
        nuisance = self.nuisance
        if nuisance is not None:
            cols.append(nuisance if weight is None else nuisance * weight[:, None])
        return np.column_stack(cols), self.columns.target(delay)

    def heldout(self, phi: np.ndarray, y: np.ndarray) -> float:
        """2-fold cross-validated residual RMS over the interleaved blocks."""
        sse = 0.0
        fold = self.setup.fold
        for k in (0, 1):
            tr, te = fold == k, fold != k
            coef = _coef(phi[tr], y[tr])
            r = y[te] - phi[te] @ coef
            sse += float(r @ r)
        return math.sqrt(sse / len(y))

    def evaluate(self, terms) -> Evaluated:
        """The joint LS fit of the nominal model plus ``terms``, its held-out RMS and BIC."""
        terms = list(terms)
        phi, y = self.design(terms)
        fit = ls(phi, y)
        m = self.setup.m
        k = phi.shape[1] + sum(1 for t in terms if t.h is not None)
        sse = float(fit.residual @ fit.residual)
        bic = m * math.log(sse / m) + k * math.log(m)
        return Evaluated(term=terms[-1] if terms else None, heldout_rms=self.heldout(phi, y), fit=fit, bic=bic)

    def sse(self, terms) -> float:
        """SSE of the joint LS fit of the nominal model plus ``terms`` (decimated, V²).

        The same fit as :func:`_coef` on :meth:`design`: when the last term adds columns and
        neither shifts the input nor weighs the others, the normal equations of the model
        without it (:meth:`_partial`, kept per thread for the last few term lists: a grid or
        Brent search fits many candidates on one base) are bordered with its columns, so only
        the new columns' products are computed (M·k·(p + k) instead of M·(p + k)²)."""
        terms = list(terms)
        last = terms[-1] if terms else None
        if last is None or last.cols is None or last.delay or effect_family(last.family).other_weight(last) is not None:
            return _sse_of(*self.design(terms))
        return self.sse_with(terms[:-1], last.cols)

    def sse_with(self, terms, cols: np.ndarray) -> float:
        """SSE of the joint LS fit of the nominal model plus ``terms`` plus the decimated columns
        ``cols`` (M, k), weighed like a term's by a holding family's weight (:meth:`design`):
        the normal equations of ``terms`` (:meth:`_partial`) bordered with ``cols``."""
        a0, y, weight, g, b = self._partial(list(terms))
        c = cols if weight is None else cols * weight[:, None]
        a1 = unit_columns(c)[0]
        cross = a0.T @ a1
        n0 = g.shape[0]
        gram = np.empty((n0 + c.shape[1],) * 2)
        gram[:n0, :n0], gram[:n0, n0:], gram[n0:, :n0], gram[n0:, n0:] = g, cross, cross.T, a1.T @ a1
        rhs = np.concatenate([b, a1.T @ y])
        try:
            coef = np.linalg.solve(gram, rhs)
        except np.linalg.LinAlgError:
            full = np.column_stack([a0, a1])
            coef = np.linalg.lstsq(full, y, rcond=None)[0]
            r = y - full @ coef
            return float(r @ r)
        r = y - a0 @ coef[:n0] - a1 @ coef[n0:]
        return float(r @ r)

    def _partial(self, base: list):
        """(Φ with its columns scaled to unit norm, y, the weight base puts on an added term's
        columns or None, the scaled Gram matrix, the scaled Φᵀy) of the nominal model plus ``base``, for
        :meth:`sse`; the last :data:`PARTIAL_CACHE` per thread, keyed by the terms and their
        columns (held, so that their ids stay theirs)."""
        key = tuple((id(t), id(t.cols)) for t in base)
        cache = getattr(self._local, "partial", None)
        if cache is None:
            cache = self._local.partial = {}
        hit = cache.get(key)
        if hit is not None:
            return hit[1]
        phi, y = self.design(base)
        weight = hold(base)[0]
        a = unit_columns(phi)[0]
        out = (a, y, weight, a.T @ a, a.T @ y)
        if len(cache) >= PARTIAL_CACHE:
            cache.pop(next(iter(cache)))
        cache[key] = ([(t, t.cols) for t in base], out)
        return out

    def heldout_with(self, terms, cols: np.ndarray) -> float:
        """Held-out RMS (:meth:`heldout`) of the nominal model plus ``terms`` plus the decimated
        columns ``cols`` (M, k), weighed like a term's (:meth:`sse_with`): an account that is
        not a family's term (:mod:`motorctl.ident.accounts`) judged as a candidate is."""
        terms = list(terms)
        phi, y = self.design(terms)
        weight = hold(terms)[0]
        c = cols if weight is None else cols * weight[:, None]
        return self.heldout(np.column_stack([phi, c]), y)

    def hold_weight(self, terms) -> np.ndarray | None:
        """The weight (M,) a holding family among ``terms`` puts on the other columns
        (:meth:`design`), None when none holds the carriage."""
        return hold(terms)[0]

    def heldout_rms(self, terms) -> float:
        """2-fold cross-validated residual RMS (:meth:`heldout`, decimated, V) of the joint LS fit
        of the nominal model plus ``terms``: the held-out rule a family may apply inside its
        search (e.g. to choose a number of terms)."""
        return self.heldout(*self.design(list(terms)))

    def best_over(self, family, grid, base, cols_fn=None):
        """Searched parameter by joint LS over a grid (all data); ``cols_fn`` may give cheap
        approximate columns (e.g. on the decimated signals), the best one then gets its exact
        columns. Returns (Term, SSE per grid value (K,))."""
        base = list(base)
        best = None
        sses = []
        if cols_fn is None:
            self.columns.decimate_ahead(family, grid)
        for h in grid:
            term = Term(family, float(h), cols_fn(h) if cols_fn else self.columns.dec_cols(family, h))
            sse = self.sse(base + [term])
            sses.append(sse)
            if best is None or sse < best[0]:
                best = (sse, term)
        term = best[1]
        return replace(term, cols=self.columns.dec_cols(family, term.h)), np.array(sses)

    def best_between(self, family, lo: float, hi: float, base, xatol: float):
        """The term of ``family`` minimising the joint-LS SSE (exact columns) for h in
        [lo, hi], to within ``xatol`` (:func:`scipy.optimize.minimize_scalar`, bounded Brent:
        golden sections and parabolic steps, about 10 fits where a grid of the same resolution
        takes 20 or more). For an SSE with one minimum in the interval. Returns the Term."""
        from scipy.optimize import minimize_scalar
        base = list(base)

        def sse(h):
            return self.sse(base + [self.term(family, float(h))])
        res = minimize_scalar(sse, bounds=(lo, hi), method="bounded", options={"xatol": xatol})
        return self.term(family, float(res.x))

    def best_delay(self, grid) -> float:
        """The input delay [samples] in ``grid`` (K,) minimising the nominal model's SSE."""
        sses = self.delay_sses([], np.asarray(grid, dtype=float))
        return float(grid[int(np.argmin(sses))]) + self.zoh

    def coef_split(self, ev: Evaluated, terms) -> tuple[np.ndarray, list]:
        """(θ (n_theta,), [β of each term]) of the fit ``ev`` of the nominal model plus ``terms``."""
        nt = self.n_theta
        th = ev.fit.coef[:nt]
        out, i = [], nt
        for t in terms:
            k = 0 if t.cols is None else t.cols.shape[1]
            out.append(ev.fit.coef[i:i + k])
            i += k
        return th, out

    def residual_on(self, other: "Fits", terms, ev: Evaluated) -> np.ndarray:
        """Residual (M2,) on another record's fits ``other`` of the model fitted here (nominal
        + ``terms``, the fit ``ev``), nothing fitted again there: ``other`` is taken at this
        structure with the thrust shape of ``ev``'s θ on its own input."""
        th, betas = self.coef_split(ev, terms)
        other = other.with_structure(fresh=True, n_theta=self.n_theta, fu=self.columns.thrust_shape(other.p.u, th))
        new_terms = []
        for t in terms:
            cols = other.dec_cols(t.family, t.h) if t.cols is not None else None
            new_terms.append(same_width(Term(t.family, t.h, cols, t.delay), t))
        phi, y = other.design(new_terms)
        coef = np.concatenate([th] + [b for b in betas])
        return y - phi @ coef

    # the read-outs the families' checks use (motorctl.ident.probes)
    def delay_sses(self, base, grid, band=None, rows=None) -> np.ndarray:
        return probes.delay_sses(self, list(base), grid, band, rows)

    def explained_shares(self, term: Term, base, *rows: np.ndarray) -> tuple[float, ...]:
        return probes.explained_shares(self, term, list(base), *rows)

    def direction_agreement(self, term: Term, base) -> float:
        return probes.direction_agreement(self, term, list(base))

    def direction_split_gain(self, term: Term, base) -> float:
        return probes.direction_split_gain(self, term, list(base))

    def speed_growth(self, term: Term, base, period: float) -> float:
        return probes.speed_growth_interval(self, term, list(base), period)[0]

    def speed_growth_interval(self, term: Term, base, period: float) -> tuple[float, float, float]:
        return probes.speed_growth_interval(self, term, list(base), period)

    def rows_std(self, phi: np.ndarray, y: np.ndarray, rows: np.ndarray, combos: np.ndarray):
        return probes.rows_std(self, phi, y, rows, combos)


def start(rec, n_theta: int | None = None, friction: str = "sf", fq: float | None = None, nd: int | None = None,
          families=None, seed: int = 0, zoh_delay: float | None = None, current_loop: bool = False) -> Fits:
    """The record opened for the stages: prepared (:func:`~motorctl.ident.idim.prepare`), its
    held-out folds drawn, the nominal structure chosen (:func:`~motorctl.ident.idim.
    choose_n_theta`) and the zero-order hold set or found; the fits at that first structure.

    Args:
        rec: a checked :class:`~motorctl.ident.data.Record`.
        n_theta: 4 or 6 to force the nominal structure (None: chosen from the input range).
        friction: 'sf' (the paper's S_f(ẋ) = (2/π)atan(900ẋ)) or 'sign' (the EMPS reference
            model's sign(ẋ)) for the Coulomb column.
        fq, nd: position cut-off [Hz] and decimation factor (default: idim.default_filters).
        families: effect family names to search (default: all of the registry, in its order).
        seed: the draw of the held-out folds' blocks.
        zoh_delay: delay [samples] between the logged input and the acceleration it causes
            (None: 0.5 for motorctl run logs, whose input is a zero-order hold; found in the
            data for other files, ``setup.hold_estimated``).
        current_loop: model the amplifier's current loop the run log's config declares in every
            input column (Stribeck's S_f then on the nominal column's velocity).
    Raises:
        ValueError: unknown friction shape or effect family.
    """
    from motorctl.effects import FAMILIES
    from motorctl.effects.input_delay import amplifier_loop, current_loop_filter, is_hold, loop_lag
    from motorctl.ident.idim import choose_n_theta, input_reach, prepare
    from motorctl.ident.records import Setup
    from motorctl.ident.rules import BLOCK_S, FRICTION_SHAPES, HOLD_GRID

    if friction not in FRICTION_SHAPES:
        raise ValueError(f"friction shape {friction!r}; allowed: {', '.join(FRICTION_SHAPES)}")
    names = tuple(families or FAMILIES)
    for name in names:
        effect_family(name)   # ValueError naming the known families
    p = prepare(rec.t, rec.y, rec.u, fq, nd)
    nt, reason = choose_n_theta(rec.u, n_theta)
    blk = np.floor((p.t_d - p.t_d[0]) / BLOCK_S).astype(int)
    nb = blk.max() + 1
    assign = np.zeros(nb, dtype=int)
    assign[np.random.default_rng(seed).permutation(nb)[: nb // 2]] = 1
    # the amplifier's current loop the run log's config declares (f_c [Hz], d_c [s]), modelled
    # in every input column: its first-order lag is not a delay within the few ms after each
    # start, where a fitted pure delay left a difference that Stribeck's hump took up
    fc, dc = amplifier_loop(rec.header or {}, rec.axis) if current_loop else (0.0, 0.0)
    if current_loop:
        p.v_sf = p.v            # Stribeck's S_f on the nominal column's velocity
    setup = Setup(rec=rec, p=p, friction=friction, families=names, current_loop=bool(current_loop),
                  loop_filter=current_loop_filter(fc, dc, p.fs) if fc > 0 or dc > 0 else None,
                  modelled_lag=loop_lag(fc, dc) * p.fs, fold=assign[blk],
                  moving=np.abs(p.v_d) > 0.02 * np.max(np.abs(p.v_d)), stroke=float(np.ptp(p.x_d)),
                  u_reach=input_reach(p.u), m=len(p.t_d), hold_estimated=zoh_delay is None and not rec.header)
    if zoh_delay is not None:
        zoh, source = float(zoh_delay), "given (--zoh-delay)"
    elif rec.header:
        zoh, source = 0.5, "run log: the input is a zero-order hold"
    else:
        zoh, source = 0.0, ""
    fits = Fits(Columns(setup, Structure(n_theta=nt, n_theta_reason=reason, zoh=zoh, zoh_source=source,
                                         n_theta_forced=n_theta is not None)))
    if setup.hold_estimated:
        # a CSV/MAT record of a sampled-data loop carries the same hold; find it in the data
        best = fits.best_delay(HOLD_GRID)
        if is_hold(best):
            source = (f"detected: the best input delay of the nominal model, {best:.2f} sample, "
                      "is the zero-order hold of a sampled-data loop")
            fits = fits.with_structure(zoh=0.5, zoh_source=source)
        else:
            fits = fits.with_structure(zoh_source=f"none detected (best input delay of the nominal model in "
                                                  f"0..1.5 sample: {best:.2f})")
    return fits
