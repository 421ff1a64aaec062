"""Stage *fit*: joint least squares of the nominal model and a list of terms (IDIM-LS), its SSE,
BIC and 2-fold held-out RMS, the searches over a family's parameter and the split of the
coefficients into θ and each term's β."""

from __future__ import annotations

import math

import numpy as np

from motorctl.effects import family as effect_family
from motorctl.ident.idim import ls, unit_columns
from motorctl.ident.records import Evaluated, Term, _hold, _same_width

#: base term lists whose normal equations :meth:`Identifier.sse` keeps per thread
PARTIAL_CACHE = 4


def _cov(phi: np.ndarray, residual: np.ndarray) -> np.ndarray:
    """σ̂² (ΦᵀΦ)⁻¹ of an LS fit (p, p)."""
    m, k = phi.shape
    return float(residual @ residual) / max(m - k, 1) * np.linalg.pinv(phi.T @ phi)


def _sse_of(phi: np.ndarray, y: np.ndarray) -> float:
    """SSE of the LS fit of y (M,) on phi (M, p) (:func:`_coef`)."""
    r = y - phi @ _coef(phi, y)
    return float(r @ r)


def _coef(phi: np.ndarray, y: np.ndarray) -> np.ndarray:
    """LS coefficients by column-scaled normal equations (fast path; lstsq if singular)."""
    a, sc = unit_columns(phi)
    try:
        return np.linalg.solve(a.T @ a, a.T @ y) / sc
    except np.linalg.LinAlgError:
        return np.linalg.lstsq(phi, y, rcond=None)[0]


class Fits:
    """Joint LS fits of the nominal model plus terms (a part of
    :class:`~motorctl.ident.select.Identifier`)."""

    def design(self, terms: list) -> tuple[np.ndarray, np.ndarray]:
        """Regressor (M, p) and target (M,) of the nominal model plus ``terms``. A term whose
        family holds the carriage at rest (stiction, :meth:`~motorctl.effects.base.EffectFamily.
        other_weight`) weighs the other terms' columns: a force the carriage does not feel while
        it is held is fitted on the samples in motion only. :attr:`nuisance` (when set) last,
        weighed the same."""
        delay = self.zoh + sum(t.delay for t in terms)
        weight = _hold(terms)[0]
        cols = [self.nominal_phi(delay)]
        for t in terms:
            if t.cols is not None:
                own = weight is None or effect_family(t.family).other_weight(t) is not None
                cols.append(t.cols if own else t.cols * weight[:, None])
        if self.nuisance is not None:
            cols.append(self.nuisance if weight is None else self.nuisance * weight[:, None])
        return np.column_stack(cols), self.target(delay)

    def heldout(self, phi: np.ndarray, y: np.ndarray) -> float:
        """2-fold cross-validated residual RMS over the interleaved blocks."""
        sse = 0.0
        for k in (0, 1):
            tr, te = self.fold == k, self.fold != k
            coef = _coef(phi[tr], y[tr])
            r = y[te] - phi[te] @ coef
            sse += float(r @ r)
        return math.sqrt(sse / len(y))

    def evaluate(self, terms: list) -> Evaluated:
        phi, y = self.design(terms)
        fit = ls(phi, y)
        k = phi.shape[1] + sum(1 for t in terms if t.h is not None)
        sse = float(fit.residual @ fit.residual)
        bic = self.m * math.log(sse / self.m) + k * math.log(self.m)
        return Evaluated(term=terms[-1] if terms else None, heldout_rms=self.heldout(phi, y), fit=fit, bic=bic)

    def sse(self, terms):
        """SSE of the joint LS fit of the nominal model plus ``terms`` (decimated, V²).

        The same fit as :func:`_coef` on :meth:`design`: when the last term adds columns and
        neither shifts the input nor weighs the others, the normal equations of the model
        without it (:meth:`_partial`, kept per thread for the last few term lists: a grid or
        Brent search fits many candidates on one base) are bordered with its columns, so only
        the new columns' products are computed (M·k·(p + k) instead of M·(p + k)²)."""
        last = terms[-1] if terms else None
        if last is None or last.cols is None or last.delay or effect_family(last.family).other_weight(last) is not None:
            return _sse_of(*self.design(terms))
        return self.sse_with(terms[:-1], last.cols)

    def sse_with(self, terms: list, cols: np.ndarray) -> float:
        """SSE of the joint LS fit of the nominal model plus ``terms`` plus the decimated columns
        ``cols`` (M, k), weighed like a term's by a holding family's weight (:meth:`design`):
        the normal equations of ``terms`` (:meth:`_partial`) bordered with ``cols``."""
        a0, y, weight, g, b = self._partial(terms)
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
        columns (held, so that their ids stay theirs), n_theta and the hold."""
        key = (self.n_theta, self.zoh, id(self.nuisance)) + tuple((id(t), id(t.cols)) for t in base)
        cache = getattr(self._local, "partial", None)
        if cache is None:
            cache = self._local.partial = {}
        hit = cache.get(key)
        if hit is not None:
            return hit[1]
        phi, y = self.design(base)
        weight = _hold(base)[0]
        a = unit_columns(phi)[0]
        out = (a, y, weight, a.T @ a, a.T @ y)
        if len(cache) >= PARTIAL_CACHE:
            cache.pop(next(iter(cache)))
        cache[key] = ([(t, t.cols) for t in base], out)
        return out

    def heldout_with(self, terms: list, cols: np.ndarray) -> float:
        """Held-out RMS (:meth:`heldout`) of the nominal model plus ``terms`` plus the decimated
        columns ``cols`` (M, k), weighed like a term's (:meth:`sse_with`): an account that is
        not a family's term (:mod:`motorctl.ident.accounts`) judged as a candidate is."""
        phi, y = self.design(terms)
        weight = self.hold_weight(terms)
        c = cols if weight is None else cols * weight[:, None]
        return self.heldout(np.column_stack([phi, c]), y)

    def hold_weight(self, terms: list) -> np.ndarray | None:
        """The weight (M,) a holding family among ``terms`` puts on the other columns
        (:meth:`design`), None when none holds the carriage."""
        return _hold(terms)[0]

    def heldout_rms(self, terms) -> float:
        """2-fold cross-validated residual RMS (:meth:`heldout`, decimated, V) of the joint LS fit
        of the nominal model plus ``terms``: the held-out rule a family may apply inside its
        search (e.g. to choose a number of terms)."""
        return self.heldout(*self.design(terms))

    def best_over(self, family, grid, base, cols_fn=None):
        """Searched parameter by joint LS over a grid (all data); ``cols_fn`` may give cheap
        approximate columns (e.g. on the decimated signals), the best one then gets its exact
        columns. Returns (Term, SSE per grid value (K,))."""
        best = None
        sses = []
        if cols_fn is None:
            self._decimate_ahead(family, grid)
        for h in grid:
            term = Term(family, float(h), cols_fn(h) if cols_fn else self.dec_cols(family, h))
            sse = self.sse(base + [term])
            sses.append(sse)
            if best is None or sse < best[0]:
                best = (sse, term)
        term = best[1]
        term.cols = self.dec_cols(family, term.h)
        return term, np.array(sses)

    def best_between(self, family, lo: float, hi: float, base, xatol: float):
        """The term of ``family`` minimising the joint-LS SSE (exact columns) for h in
        [lo, hi], to within ``xatol`` (:func:`scipy.optimize.minimize_scalar`, bounded Brent:
        golden sections and parabolic steps, about 10 fits where a grid of the same resolution
        takes 20 or more). For an SSE with one minimum in the interval. Returns the Term."""
        from scipy.optimize import minimize_scalar

        def sse(h):
            return self.sse(base + [self.term(family, float(h))])
        res = minimize_scalar(sse, bounds=(lo, hi), method="bounded", options={"xatol": xatol})
        return self.term(family, float(res.x))

    def best_delay(self, grid) -> float:
        """The input delay [samples] in ``grid`` (K,) minimising the nominal model's SSE."""
        sses = self.delay_sses([], np.asarray(grid, dtype=float))
        return float(grid[int(np.argmin(sses))]) + self.zoh

    def coef_split(self, ev: Evaluated, terms: list) -> tuple[np.ndarray, list]:
        nt = self.n_theta
        th = ev.fit.coef[:nt]
        out, i = [], nt
        for t in terms:
            k = 0 if t.cols is None else t.cols.shape[1]
            out.append(ev.fit.coef[i:i + k])
            i += k
        return th, out

    def predict_on(self, other: "Identifier", terms: list, ev: Evaluated) -> np.ndarray:
        """Residual on another record of the model fitted here (nominal + ``terms``), decimated (M2,)."""
        th, betas = self.coef_split(ev, terms)
        other.n_theta = self.n_theta
        other.p.fu = self.thrust_shape(other.p.u, th)
        new_terms = []
        for t, b in zip(terms, betas):
            cols = other.dec_cols(t.family, t.h) if t.cols is not None else None
            new_terms.append(_same_width(Term(t.family, t.h, cols, t.delay), t))
        other.n_theta = self.n_theta
        phi, y = other.design(new_terms)
        coef = np.concatenate([th] + [b for b in betas])
        return y - phi @ coef
