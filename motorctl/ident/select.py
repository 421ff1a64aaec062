"""Nominal fit, effect search and forward selection.

Decision rule (docs/identification.md, "Decision rule"): a candidate effect, re-fitted *jointly*
with the nominal θ, is accepted only when all three agree:

1. held-out gain: the RMS of the 2-fold cross-validated residual over interleaved blocks
   (blocks of :data:`BLOCK_S`, assigned to the two folds by a fixed pseudo-random draw so that no
   periodic trajectory lands in one fold) drops by at least :data:`MIN_HELDOUT_GAIN`;
2. information criterion: BIC = M ln(SSE/M) + k ln M drops by at least :data:`MIN_BIC_DROP`
   (k counts the columns and the searched parameter);
3. plausibility: the effect's coefficients are significant (Wald statistic per column ≥
   :data:`MIN_WALD`), its force is of a physical size worth naming (the 99th percentile of
   |A1·Cβ| at least :data:`MIN_SIZE_SHARE` of the RMS input force and, when the gain A1 is known,
   :data:`MIN_SIZE_N`), its parameters are inside their physical range (searched parameter not at
   the edge of its grid, amplitudes below half the input range, a position-periodic force the
   same in both directions of motion, ...), and the nominal θ stay physical (θ1 > 0, θ2, θ3
   not significantly negative).

Accepted effects are added one at a time (the best held-out gain first) and everything is
re-fitted, until no candidate passes (at most :data:`MAX_EFFECTS`). Then each selected effect is
judged again in the final model (backward elimination: plausible there, and a held-out gain of
:data:`MIN_HELDOUT_GAIN` against the model without it); the weakest that fails is dropped, and
the forward selection resumes without it (:data:`STEPWISE_ROUNDS` rounds at most). When a passing candidate of a family that looks alike
(:attr:`~motorctl.effects.base.EffectFamily.look_alike`) gains at least :data:`LOOK_ALIKE_SHARE`
of the selected one's held-out gain, the one kept is the one that leaves the lower held-out RMS
with the step's other candidates taken beside it greedily (:data:`LOOK_AHEAD_DEPTH` steps of
look-ahead), and it carries the other in ``rivals``: the report says the record cannot tell them
apart on their own.

The candidate families come from the registry :data:`motorctl.effects.FAMILIES`; each family's
columns, search over its parameter and its own plausibility checks are in its module
(``motorctl/effects/<name>.py``). The :class:`Identifier` is the context those use
(:class:`motorctl.effects.base.SearchContext`: ``term``, ``best_over``, ``best_between``, ``sse``,
``heldout_rms``, ``delay_sses``, ``direction_agreement``, ``target``).

The stages (docs/identification.md, "The stages in the code"), each a module of its own:
candidates (:mod:`motorctl.ident.columns`: the nominal regressor and each registry family's
columns) → fit (:mod:`motorctl.ident.fit`: joint IDIM-LS, SSE, BIC, held-out RMS) → select
(:meth:`Identifier._select` here, :mod:`motorctl.ident.stepwise`, :mod:`motorctl.ident.prune`) →
judge (:mod:`motorctl.ident.checks` per candidate, with :mod:`motorctl.ident.accounts`; after
the selection :mod:`motorctl.ident.refine`, :mod:`motorctl.ident.values` and
:mod:`motorctl.ident.judge`) → explain (:mod:`motorctl.ident.verdict`,
:mod:`motorctl.ident.ambiguity`, :mod:`motorctl.ident.pipeline`). The records between them are
:class:`~motorctl.ident.records.Term` and :class:`~motorctl.ident.records.Evaluated`; every
threshold is in :mod:`motorctl.ident.rules`. :class:`Identifier` joins the stages' parts on one
record and drives the forward selection.
"""

from __future__ import annotations

import os
import threading
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np
from scipy.fft import irfft

from motorctl.effects import FAMILIES, family as effect_family
from motorctl.effects.input_delay import (HOLD_TOLERANCE, amplifier_loop, current_loop_filter,  # noqa: F401
                                          is_hold, loop_lag)
from motorctl.ident.checks import Checks, _fall_share  # noqa: F401
from motorctl.ident.columns import COLS_CACHE_MAX, DECIMATE_BATCH, Columns  # noqa: F401
from motorctl.ident.data import Record
from motorctl.ident.fit import PARTIAL_CACHE, Fits, _coef, _cov, _sse_of  # noqa: F401
from motorctl.ident.idim import choose_n_theta, input_reach, prepare, unit_columns
from motorctl.ident.prune import Prune
from motorctl.ident.records import (Evaluated, Term, _found_in_measurement, _force, _h_key, _hold,  # noqa: F401
                                    _plain, _r_h, _same_width, _searchable)
from motorctl.ident.refine import Refine
from motorctl.ident.rules import *  # noqa: F401,F403  (the decision rule's thresholds, re-exported)
from motorctl.ident.rules import BLOCK_S, FRICTION_SHAPES, HOLD_GRID, STEPWISE_ROUNDS
from motorctl.ident.stepwise import Stepwise
from motorctl.ident.values import Values

#: threads searching the families of one selection step (each family's search is independent
#: of the others' and its numpy/scipy work releases the GIL, so the result does not depend on it;
#: the searches are handed out longest first, by the CPU time of each family's last search or,
#: at the first step, by its :attr:`~motorctl.effects.base.EffectFamily.search_cost`)
SEARCH_THREADS = min(2, os.cpu_count() or 1)
#: elements of the shifted input columns :meth:`Identifier.delay_sses` holds at once (delays x
#: samples x 3; 2 M: 16 MB, a 20 s record's whole grid)
DELAY_CHUNK_ELEMENTS = 2_000_000


class Identifier(Columns, Fits, Checks, Stepwise, Prune, Refine, Values):
    """IDIM-LS identification of one record (see the module docstring).

    Args:
        rec: a checked :class:`~motorctl.ident.data.Record`.
        n_theta: 4 or 6 to force the nominal structure (default: :func:`choose_n_theta`).
        friction: 'sf' (the paper's S_f(ẋ) = (2/π)atan(900ẋ)) or 'sign' (the EMPS reference
            model's sign(ẋ)) for the Coulomb column.
        fq, nd: position cut-off [Hz] and decimation factor (default: idim.default_filters).
        families: effect family names to search (default: all of the registry, in its order).
        zoh_delay: delay [samples] between the logged input and the acceleration it causes
            (default 0.5 for motorctl run logs, whose input is a zero-order hold, 0 otherwise).
        on_nominal: called with the nominal θ̂ (n_theta,) each time the nominal model is
            fitted, before the effect search starts (e.g. to start a closed-loop run with it
            meanwhile); None: nothing.
        current_loop: model the amplifier's current loop the run log's config declares in every
            input column (:meth:`input_columns`), search stiction's band again after each
            effect taken (:meth:`_polish_at_rest`) and take Stribeck's S_f on the nominal
            column's velocity; off (default): the loop is fitted as an input delay, as before.
            On, Stribeck's F_s and v_s come within 10 % on the default plant, but the residual
            verdict, calibrated on the model without it, warns on clean logs (a 0.25 N
            structure at the slowest speeds) and no longer flags a 50 µm backlash
            (docs/identification.md, "Stribeck: the velocity of its column"); so the
            selection runs without it and, when Stribeck is selected, :meth:`refit` takes
            the values on it.

    Raises:
        ValueError: unknown friction shape or effect family.
    """

    def __init__(self, rec: Record, n_theta: int | None = None, friction: str = "sf",
                 fq: float | None = None, nd: int | None = None, families=None, seed: int = 0,
                 zoh_delay: float | None = None, on_nominal=None, current_loop: bool = False):
        if friction not in FRICTION_SHAPES:
            raise ValueError(f"friction shape {friction!r}; allowed: {', '.join(FRICTION_SHAPES)}")
        self.rec = rec
        self.friction = friction
        self.p: Prepared = prepare(rec.t, rec.y, rec.u, fq, nd)
        self.n_theta, self.n_theta_reason = choose_n_theta(rec.u, n_theta)
        #: the record's largest input |u|max [V] (:func:`~motorctl.ident.idim.input_reach`)
        self.u_reach = input_reach(self.p.u)
        self._n_theta_forced = n_theta is not None
        self.families = list(families or FAMILIES)
        for name in self.families:
            effect_family(name)   # ValueError naming the known families
        p = self.p
        m = len(p.t_d)
        blk = np.floor((p.t_d - p.t_d[0]) / BLOCK_S).astype(int)
        nb = blk.max() + 1
        rng = np.random.default_rng(seed)
        assign = np.zeros(nb, dtype=int)
        assign[rng.permutation(nb)[: nb // 2]] = 1
        self.fold = assign[blk]
        self.m = m
        self._phi_cache = {}
        self._cols_cache = {}
        self._local = threading.local()
        self.on_nominal = on_nominal
        #: on an identifier :meth:`refit` returns: the families searched again there (sorted),
        #: whether on the declared current loop's model, whether with the stick state measured
        self.refit_families: list = []
        #: (family, searched parameter before, after) of each effect :meth:`joint_refit` moved
        self.joint_moved: list = []
        #: (family, harmonics kept, held-out gain of the ones left out) per effect whose higher
        #: harmonics the held-out data did not support (:meth:`_prune_harmonics`)
        self.harmonics_cut: list = []
        self.loop_refit = False
        self.stick_measured = False
        #: decimated columns (M, k) appended to every regressor of :meth:`design` after the
        #: effects' (weighed like theirs by a holding family's weight), not an effect of the
        #: model's: the broadband force of a structural mode above the record's band that
        #: :meth:`refit` puts into the values' model (:meth:`mode_above_band`); None: none
        self.nuisance = None
        #: on an identifier :meth:`refit` returns with :attr:`nuisance`: {"columns_at_Hz": the
        #: antiresonance of its columns, "heldout_gain": the held-out RMS's relative fall they
        #: gave the selection's final model}; else None
        self.band_mode = None
        #: the identifier whose fit gives the values of this one's effects, when :meth:`refit`
        #: made one (the caller keeps it here: motorctl.ident.pipeline.values_from); else None
        self.refitted = None
        #: the last selection step's candidates on the final model (:meth:`_on_final`), which
        #: the residual verdict reads (:func:`motorctl.ident.pipeline.add_refused`)
        self.verdict_step: list = []
        #: effects the record cannot tell from a refused structure (:meth:`_ambiguities`):
        #: named neither, compensated neither
        self.ambiguous: list = []
        #: in a motorctl run log u_k is written after y_k is read and held over the period (ZOH):
        #: seen from the central-difference acceleration at t_k it acts half a sample late
        #: (u_{k-1}, u_k weigh equally). Other files: timing unknown, 0 unless told.
        self.moving = np.abs(p.v_d) > 0.02 * np.max(np.abs(p.v_d))
        #: the amplifier's current loop the run log's config declares (f_c [Hz], d_c [s]), modelled
        #: in every input column (:meth:`input_columns`): its first-order lag is not a delay
        #: within the few ms after each start, where a fitted pure delay left a difference that
        #: Stribeck's hump took up. ``modelled_lag``: its lag d_c + 1/(2π f_c) [samples] (0: none)
        self.current_loop = bool(current_loop)
        fc, dc = amplifier_loop(rec.header or {}, rec.axis) if current_loop else (0.0, 0.0)
        self.loop_filter = current_loop_filter(fc, dc, p.fs) if fc > 0 or dc > 0 else None
        self.modelled_lag = loop_lag(fc, dc) * p.fs
        if self.current_loop:
            p.v_sf = p.v            # Stribeck's S_f on the nominal column's velocity
        self.stroke = float(np.ptp(p.x_d))
        #: the hold is estimated from the data (CSV/MAT without --zoh-delay): run() checks it
        #: again with the selected effects
        self.hold_estimated = zoh_delay is None and not rec.header
        if zoh_delay is not None:
            self.zoh, self.zoh_source = float(zoh_delay), "given (--zoh-delay)"
        elif rec.header:
            self.zoh, self.zoh_source = 0.5, "run log: the input is a zero-order hold"
        else:
            # a CSV/MAT record of a sampled-data loop carries the same hold; find it in the data
            self.zoh = 0.0
            best = self.best_delay(HOLD_GRID)
            if is_hold(best):
                self.zoh = 0.5
                self.zoh_source = (f"detected: the best input delay of the nominal model, {best:.2f} sample, "
                                   "is the zero-order hold of a sampled-data loop")
            else:
                self.zoh_source = f"none detected (best input delay of the nominal model in 0..1.5 sample: {best:.2f})"

    def __getstate__(self) -> dict:
        """Pickled without the per-thread normal equations of :meth:`sse` (rebuilt on demand):
        an identifier goes back from a worker process whole."""
        state = self.__dict__.copy()
        state.pop("_local", None)
        return state

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self._local = threading.local()

    def _select(self, nominal: Evaluated, max_effects: int) -> "Identifier":
        self._cols_cache.clear()          # the thrust shape p.fu (ripple, drift columns) changes
        # thrust shape f_u(u) = u + θ5 u|u| + θ6 u³ for the ripple family
        self.p.fu = self.thrust_shape(self.p.u, nominal.fit.coef)
        if self.on_nominal is not None:
            self.on_nominal(nominal.fit.coef[:self.n_theta])
        base: list = []
        current = nominal
        #: (family, why it failed in the final model, searched parameter before, after) of each
        #: effect that backward elimination searched again and kept (:meth:`_eliminate`)
        self.researched = []
        steps = []
        accepted = []
        pool = ThreadPoolExecutor(max_workers=SEARCH_THREADS) if SEARCH_THREADS > 1 else None
        eliminated: list = []
        searched_with: dict = {}     # id(term) -> the terms selected when it was searched
        # family -> CPU seconds of its last search and judgement (at first: its search_cost)
        cost = {name: effect_family(name).search_cost for name in self.families}
        step_base: list = []         # the terms in the model when the last step was searched
        for _ in range(STEPWISE_ROUNDS):
            out = {n for n, _ in eliminated}        # never taken again once dropped
            while len(base) < max_effects:
                residual = current.fit.residual
                step_base = list(base)
                todo = [fam for fam in self.families if fam not in out and _searchable(fam, base)]

                def one(fam, base=base, residual=residual, current=current):
                    t0 = time.thread_time()
                    ev = self.search(fam, base, residual)
                    ev = None if ev is None else self.judge(ev, current, base)
                    cost[fam] = time.thread_time() - t0
                    return ev
                if pool:
                    # longest first (the CPU time of the family's last search; its search_cost at
                    # the first step), so that the threads end together; the results keep todo's order
                    order = sorted(range(len(todo)), key=lambda i: -cost[todo[i]])
                    futures = {i: pool.submit(one, todo[i]) for i in order}
                    found = [futures[i].result() for i in range(len(todo))]
                else:
                    found = [one(f) for f in todo]
                cands = [c for c in found if c is not None]
                steps.append(cands)
                good = [c for c in cands if c.ok]
                if not good:
                    break
                best = self._look_ahead(max(good, key=lambda c: c.gain), good, cands, base)
                accepted.append((best, current.heldout_rms))
                searched_with[id(best.term)] = list(base)
                base = base + [best.term]
                current = best
                base, current = self._polish_at_rest(base, current, searched_with)
            base, accepted, current, dropped = self._eliminate(base, accepted, current, searched_with)
            if not dropped:
                break
            eliminated += dropped
        base, accepted, current, replaced = self._simplify(base, accepted, current)
        eliminated += replaced
        base, current = self._polish(base, current, searched_with)
        last = steps[-1] if steps else []
        fresh = self._on_final(last, step_base, base, current)
        # the strong-effects rule reads the step as searched too: a structure refused on its
        # physics that the model's last change took away may be what that change is fitting
        base, accepted, current, doubted = self._doubt(base, accepted, current,
                                                       last if fresh is last else last + fresh)
        if doubted:
            fresh = self._on_final(last, step_base, base, current)
        eliminated += doubted
        base, accepted, current, fresh = self._ambiguities(base, accepted, current, fresh, last, step_base)
        base, current = self._refit_thrust_shape(base, current)
        if pool:
            pool.shutdown()
        self.verdict_step = fresh
        self.eliminated = eliminated
        self.nominal, self.final, self.terms, self.steps, self.accepted = nominal, current, base, steps, accepted
        return self

    def delay_sses(self, base: list, grid: np.ndarray, band: tuple[float, float] | None = None,
                   rows: np.ndarray | None = None) -> np.ndarray:
        """Joint-LS SSE for extra input delays ``grid`` [samples]: the decimated u, u|u|, u³ are
        shifted by a fractional number of decimated samples (FFT phase shift of band-limited
        signals) instead of being re-filtered for every candidate. ``band`` (lo, hi) [Hz]: the
        fit on that band of every column and of the target only (their FFT outside it zeroed),
        the delay one band's phase says; None: all of the record's band. ``rows`` (M,) bool: the
        fit and its SSE on those decimated samples only (e.g. :attr:`moving`); None: all."""
        p = self.p
        key = ("u3", self.zoh)
        if key not in self._phi_cache:
            self._phi_cache[key] = p.dec(self.input_columns(self.zoh))
        ud = self._phi_cache[key]
        spec = np.fft.rfft(ud, axis=0)
        w = 2 * np.pi * np.fft.rfftfreq(ud.shape[0])
        phi0, _ = self.design(base)
        if band is not None:
            f = np.fft.rfftfreq(ud.shape[0], p.nd / p.fs)
            keep = ((f >= band[0]) & (f < band[1])).astype(float)[:, None]
            spec = spec * keep
            phi0 = np.fft.irfft(np.fft.rfft(phi0, axis=0) * keep, n=ud.shape[0], axis=0)
        if rows is None:
            fit, scored = slice(None), slice(4, -4)
        else:
            fit = rows.copy()
            fit[:4] = fit[-4:] = False
            scored = slice(None)
        # the columns that do not move with the delay (all but θ5, θ6's) scaled and their Gram
        # matrix formed once; every delay of a chunk of the grid shifted and fitted at once,
        # its Gram matrix bordered with the moving columns (as in :meth:`sse`)
        moving = [4, 5] if self.n_theta == 6 else []
        a_f = phi0[fit][:, [j for j in range(phi0.shape[1]) if j not in moving]]
        a_f = unit_columns(a_f)[0]
        g_ff = a_f.T @ a_f
        grid = np.asarray(grid, dtype=float)
        chunk = max(1, DELAY_CHUNK_ELEMENTS // (3 * ud.shape[0]))
        return np.concatenate([self._delay_chunk(spec, w, ud.shape[0], grid[i:i + chunk], a_f, g_ff, len(moving),
                                                 fit, scored) for i in range(0, len(grid), chunk)])

    def _delay_chunk(self, spec, w, m, delays, a_f, g_ff, k, fit, scored) -> np.ndarray:
        """SSEs (G,) of :meth:`delay_sses` for ``delays`` (G,) [samples]: spec (F, 3) the
        spectrum of the decimated u, u|u|, u³ (m samples); w (F,) its bins [rad/sample]; a_f
        (m', q) the scaled columns that do not move with the delay on the fitted rows ``fit``,
        g_ff their Gram matrix; k the moving columns (0, or 2: θ5, θ6's −u|u|, −u³); the SSE on
        the rows ``scored`` of the fitted ones."""
        shift = np.exp(np.multiply.outer(delays / self.p.nd, -1j * w))               # (G, F)
        used = spec.T[:1 + k]                                          # u, and u|u|, u³ when they move
        sh = irfft(used[None, :, :] * shift[:, None, :], n=m, axis=-1)[:, :, fit]     # (G, 1 + k, m')
        y = sh[:, 0, :]
        n_g, q = len(delays), a_f.shape[1]
        gram = np.empty((n_g, q + k, q + k))
        gram[:, :q, :q] = g_ff
        rhs = np.empty((n_g, q + k))
        rhs[:, :q] = y @ a_f
        if k:
            a_s = -sh[:, 1:3, :]                                                      # (G, 2, m')
            sc_s = np.sqrt(np.einsum("gji,gji->gj", a_s, a_s))
            sc_s[sc_s == 0] = 1.0
            a_s /= sc_s[:, :, None]
            cross = a_s @ a_f                                                         # (G, 2, q)
            gram[:, q:, :q] = cross
            gram[:, :q, q:] = cross.transpose(0, 2, 1)
            gram[:, q:, q:] = a_s @ a_s.transpose(0, 2, 1)
            rhs[:, q:] = (a_s @ y[:, :, None])[:, :, 0]
        try:
            coef = np.linalg.solve(gram, rhs[:, :, None])[:, :, 0]
        except np.linalg.LinAlgError:        # a singular fit: its least-norm coefficients
            coef = (np.linalg.pinv(gram) @ rhs[:, :, None])[:, :, 0]
        r = y - coef[:, :q] @ a_f.T
        if k:
            r -= (coef[:, None, q:] @ a_s)[:, 0, :]
        r = r[:, scored]
        return np.einsum("gi,gi->g", r, r)
