"""Stage *candidates*: the model's columns. The nominal regressor of IDIM-LS (paper eq. 9 and
the input's force curve), the target, and each effect family's decimated columns at a searched
value (from the registry, :mod:`motorctl.effects`), as :class:`~motorctl.ident.records.Term`
records; cached for one selection.

A :class:`Columns` is the record (:class:`~motorctl.ident.records.Setup`) at one nominal
structure (:class:`~motorctl.ident.records.Structure`); another structure is another
:class:`Columns` (:meth:`Columns.at`), which shares the caches that do not depend on it.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy.signal import lfilter

from motorctl.effects import family as effect_family
from motorctl.effects.base import EffectFamily
from motorctl.effects.input_delay import delayed
from motorctl.ident.records import Setup, Structure, Term, h_key
from motorctl.ident.rules import MIN_THRUST_SHARE
from motorctl.model import f_u, s_f

#: decimated candidate columns kept per selection (about M·k·8 bytes each: 160 kB for a 20 s,
#: 5 kHz record with 4 columns)
COLS_CACHE_MAX = 1024
#: least number of full-rate columns decimated in one call when a grid's columns are decimated
#: ahead (:meth:`Columns.decimate_ahead`)
DECIMATE_BATCH = 16


class Columns:
    """The columns of the nominal model and of the families' terms on one record at one
    structure.

    Args:
        setup: the record (:class:`~motorctl.ident.records.Setup`). structure: the nominal
            model (:class:`~motorctl.ident.records.Structure`; its ``fu`` is the thrust shape
            the families' columns read as ``p.fu``).
        phi_cache: the nominal columns and targets by delay (shared by every structure of the
            record; None: a new one). cols_cache: the families' decimated columns by (family,
            h) (None: a new one).
    """

    def __init__(self, setup: Setup, structure: Structure, phi_cache: dict | None = None,
                 cols_cache: dict | None = None):
        self.setup = setup
        self.structure = structure
        self.p = setup.p if structure.fu is None else dataclasses.replace(setup.p, fu=structure.fu)
        self._phi_cache = {} if phi_cache is None else phi_cache
        self._cols_cache = {} if cols_cache is None else cols_cache

    def at(self, structure: Structure, fresh: bool = False) -> "Columns":
        """The same record at ``structure``: the nominal columns' cache shared; the families'
        columns shared when the thrust shape is the same (``fresh``: not at all), else those of
        the families that do not scale the thrust."""
        if fresh:
            cols = {}
        elif structure.fu is self.structure.fu:
            cols = self._cols_cache
        else:
            cols = {k: v for k, v in self._cols_cache.items() if not effect_family(k[0]).columns_on_thrust_shape}
        return Columns(self.setup, structure, self._phi_cache, cols)

    @property
    def n_theta(self) -> int:
        return self.structure.n_theta

    @property
    def zoh(self) -> float:
        return self.structure.zoh

    def nominal_phi(self, delay: float = 0.0) -> np.ndarray:
        """The decimated nominal regressor (M, n_theta) with the input delayed by ``delay``
        samples (paper eq. 9: ẍ, ẋ, the Coulomb shape, −1, and −u|u|, −u³ for θ5, θ6)."""
        key = (round(delay, 6), self.n_theta)
        if key not in self._phi_cache:
            if len(self._phi_cache) > 256:
                self._phi_cache.clear()
            p = self.p
            if "fixed" not in self._phi_cache:
                sf = np.sign(p.v) if self.setup.friction == "sign" else s_f(p.v)
                self._phi_cache["fixed"] = p.dec(np.column_stack([p.a, p.v, sf, -np.ones_like(p.v)]))
            phi = self._phi_cache["fixed"]
            if self.n_theta == 6:
                phi = np.column_stack([phi, -p.dec(self.input_columns(delay)[:, 1:])])
            self._phi_cache[key] = phi
        return self._phi_cache[key]

    def input_columns(self, delay: float) -> np.ndarray:
        """u, u|u|, u³ as the acceleration sees them ``delay`` samples after the logged input, at
        full rate (N, 3): without a declared current loop, of u(t − delay·Ts)
        (:meth:`delayed_u`) each column of the held input delayed (the force curve F_m(u) of
        eq. 3 acts on the held input, the delay on the force: a fractional delay's linear
        interpolation of u would shrink kilohertz content before the curve, 0.31 at 2 kHz for
        half a sample at 5 kHz, and leave the thrust the curve makes of it unmodelled); with one
        (``setup.loop_filter``), each column through the loop's exact filter (the force curve is
        what the loop lags) and shifted by delay − 0.5 (the filter holds the hold's half sample)."""
        raw = self._phi_cache.get("u_curve")
        if raw is None:
            u = self.p.u
            raw = self._phi_cache["u_curve"] = np.column_stack([u, u * np.abs(u), u ** 3])
        loop = self.setup.loop_filter
        if loop is None:
            return delayed(raw, delay) if delay > 0 else raw
        cols = self._phi_cache.get("loop")
        if cols is None:
            cols = self._phi_cache["loop"] = lfilter(*loop, raw, axis=0)
        return delayed(cols, delay - 0.5)

    def delayed_u(self, delay: float) -> np.ndarray:
        """The input the acceleration sees ``delay`` samples after the logged one, at full rate
        (N,): u(t − delay·Ts), fractional delays by linear interpolation; with a declared current
        loop, u through the loop's filter (:meth:`input_columns`)."""
        if self.setup.loop_filter is not None:
            return self.input_columns(delay)[:, 0]
        return delayed(self.p.u, delay) if delay > 0 else self.p.u

    def target(self, delay: float = 0.0) -> np.ndarray:
        """The decimated input u(t − delay·Ts) (M,): what the model is fitted to."""
        key = ("y", round(delay, 6))
        if key not in self._phi_cache:
            self._phi_cache[key] = (self.p.u_d if delay <= 0 and self.setup.loop_filter is None
                                    else self.p.dec(self.delayed_u(delay)))
        return self._phi_cache[key]

    def held_input(self) -> np.ndarray:
        """The decimated u, u|u|, u³ (M, 3) at the structure's hold (the input delay search's
        columns, :func:`motorctl.ident.probes.delay_sses`)."""
        key = ("u3", self.zoh)
        if key not in self._phi_cache:
            self._phi_cache[key] = self.p.dec(self.input_columns(self.zoh))
        return self._phi_cache[key]

    def dec_cols(self, family: str, h) -> np.ndarray | None:
        """Decimated columns (M, k) of ``family`` at h (None when it adds no columns).

        Cached per (family, h) for one selection: the later steps search the same grids again
        with another base, and decimating full-rate columns is most of identify's time; in
        single precision (:func:`~motorctl.ident.idim.parallel_decimate`: its round-off, 2e-6
        of a column's RMS, is far below the residual a candidate is fitted to). Read-only:
        callers never modify the array."""
        key = (family, h_key(h))
        c = self._cols_cache.get(key)
        if c is None:
            fam = effect_family(family)
            c = fam.decimated_columns(h, self.p)
            if c is None:
                full = self._through_loop(fam, fam.columns(h, self.p))
                c = False if full is None else self.p.dec(full, single=True)
            if len(self._cols_cache) < COLS_CACHE_MAX:
                self._cols_cache[key] = c
        return None if c is False else c

    def _through_loop(self, fam, full):
        """A family's full-rate columns (N,) or (N, k), through the declared current loop's
        filter (:meth:`input_columns`) when the family acts on the input before it
        (:attr:`~motorctl.effects.base.EffectFamily.before_current_loop`); else as they are."""
        loop = self.setup.loop_filter
        if full is None or loop is None or not fam.before_current_loop:
            return full
        return lfilter(*loop, np.asarray(full, dtype=float), axis=0)

    def decimate_ahead(self, family: str, grid) -> None:
        """Put the decimated columns of ``family`` at every h of ``grid`` (K,) into the cache of
        :meth:`dec_cols`, filtering the full-rate columns of several h in one call of at least
        :data:`DECIMATE_BATCH` columns, written as the rows of one block (each column is
        filtered on its own, so the numbers are those of one call per h; 20 columns of a
        100 000-sample record in single precision: 12 ms, 17 ms through a C-ordered (N, k)
        block). Families with closed-form decimated columns, values already cached, or a full
        cache: left to :meth:`dec_cols`."""
        fam = effect_family(family)
        if type(fam).decimated_columns is not EffectFamily.decimated_columns:
            return
        todo = []
        for h in grid:
            key = (family, h_key(h))
            if key not in self._cols_cache and all(key != k for k, _ in todo):
                todo.append((key, h))
        room = COLS_CACHE_MAX - len(self._cols_cache)
        todo = todo[:max(room, 0)]
        i = 0
        while i < len(todo):
            chunk, width = [], 0
            while i < len(todo) and width < DECIMATE_BATCH:
                key, h = todo[i]
                full = self._through_loop(fam, fam.columns(h, self.p))
                if full is None:
                    self._cols_cache[key] = False
                else:
                    chunk.append((key, full.ndim, full.reshape(len(full), -1)))
                    width += chunk[-1][2].shape[1]
                i += 1
            if not chunk:
                continue
            # the columns written as the rows of one block: parallel_decimate filters rows
            # (a C-ordered (N, k) block is copied into them column by column), and no hstack copy
            rows = np.empty((width, len(chunk[0][2])), dtype=np.float32)     # decimated in single precision
            j = 0
            for _, _, f in chunk:
                rows[j:j + f.shape[1]] = f.T
                j += f.shape[1]
            dec = self.p.dec(rows.T, single=True)
            j = 0
            for key, ndim, f in chunk:
                k = f.shape[1]
                self._cols_cache[key] = np.ascontiguousarray(dec[:, j] if ndim == 1 else dec[:, j:j + k])
                j += k

    def term(self, family: str, h) -> Term:
        """The term of ``family`` at h with its exact decimated columns and input shift."""
        return Term(family, h, self.dec_cols(family, h), effect_family(family).input_shift(h))

    def thrust_shape(self, u: np.ndarray, theta: np.ndarray) -> np.ndarray | None:
        """:func:`thrust_shape` at this structure and record."""
        return thrust_shape(self.n_theta, self.setup.u_reach, u, theta)


def thrust_shape(n_theta: int, u_reach: float, u: np.ndarray, theta: np.ndarray) -> np.ndarray | None:
    """The thrust shape f_u(u) = u + θ5 u|u| + θ6 u³ (paper eq. 9) of ``theta`` (θ̂ first,
    (n_theta + ...,)) at the inputs u [V] (N,), for the columns of the effects that scale the
    thrust (the ripple's, the drift's); None (the columns use u) with θ1..θ4 only
    (``n_theta`` 4), or when the curve keeps less than :data:`MIN_THRUST_SHARE` of the linear
    thrust at the record's largest input ``u_reach`` [V]: not a motor's saturation."""
    if n_theta != 6:
        return None
    r = u_reach
    if not r > 0.0 or float(f_u(r, theta[4], theta[5])) < MIN_THRUST_SHARE * r:
        return None
    return f_u(u, theta[4], theta[5])
