"""A planned program's setpoints: the path-speed profile through a moving average of T1, the
blended path at that length, the setpoints through a moving average of T2 (docs/motion.md, "The
planner", step 3; the FIR interpolators of L. Biagiotti, C. Melchiorri, "FIR filters for online
trajectory planning with time- and frequency-domain specifications", Control Engineering
Practice 20 (2012) 1385-1399).

On the planner's grid (period h) the setpoints are the filtered profile exactly, by cumulative
sums; a call that starts where the previous one ended (the setpoint filler's) reuses the last
call's windows, so its work is the rows it returns, not the windows' length.
"""

from __future__ import annotations

import math

import numpy as np

from motorctl.motion.profile import Phases
from motorctl.motion.trajectory import Trajectory


class PathTrajectory(Trajectory):
    """A planned program (see :class:`motorctl.motion.planner.Trajectory` for the interface).

    phases: the path-speed profile (:class:`~motorctl.motion.profile.Phases`); geo: the blended
    path's table (gs0, glen, kinds, p0s, p1s, us, arcs: per piece its start length [m], length
    [m], kind (0 line, 1 arc), start and end point and direction (shape (n, n_axes)), arc
    (cx, cy, r0, r1, phi0, sweep, fade_in, fade_out)); ix, iy: X and Y among the axes (−1:
    none); n1, n2: the moving averages' lengths [periods]; period [s]."""

    #: grid points computed at once by :meth:`sample` (the cache a streaming caller walks through)
    CACHE = 256
    #: rows computed at once by :meth:`sample_into` on the grid (the cumulative sums' rounding
    #: stays that of a block's travel, whatever the call's length)
    BLOCK = 2048
    #: a point this close to a join is at the join [m] (:meth:`_path`)
    BOUNDARY_M = 1e-9

    def __init__(self, axes, phases: Phases, geo, ix, iy, n1, n2, period, start, end, events, stops):
        self.axes = tuple(axes)
        self._ph = phases
        (self._gs0, self._glen, self._kind, self._p0, self._p1, self._u, self._arc) = geo
        self._any_arc = bool(np.any(self._kind == 1))
        self._ix, self._iy = ix, iy
        self.n1, self.n2, self.period = n1, n2, period
        self._m = n1 + n2 - 2
        self.delay = 0.5 * self._m * period
        self.t_profile = phases.duration
        self.duration = self.t_profile + (n1 + n2 + 1) * period
        self.start, self.end = start, end
        self.events, self.stops = events, stops
        self._tail = None                 # (next grid index, s, ṡ, x, v tails) of the last call

    def __getstate__(self):
        d = dict(self.__dict__)
        d["_tail"] = None
        d.pop("_cache", None)
        return d

    def _shrink(self, om: np.ndarray) -> np.ndarray:
        """1/S(ω) − 1: the relative radius the short moving average of n2 samples shrinks back
        to 0 on a circle run at angular rate ω [rad/s], S its gain sin(n ω h/2)/(n sin(ω h/2))
        (a moving average's frequency response)."""
        x = 0.5 * np.asarray(om, dtype=float) * self.period
        small = np.abs(x) < 1e-9
        xs = np.where(small, 1.0, x)
        s = np.where(small, 1.0, np.sin(self.n2 * xs) / (self.n2 * np.sin(xs)))
        return 1.0 / s - 1.0

    def _path(self, s: np.ndarray, sd: np.ndarray, lead: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The blended path's point and velocity at path length s moving at ṡ (shape (k,) each;
        returns shape (k, n_axes) each); arcs on the radius the short filter shrinks back onto
        theirs. ``lead``: the unfiltered path length at the newest sample of each point's window
        (shape (k,)): at a join (within BOUNDARY_M, the averages' rounding) the point is on the
        piece it is leaving while that is not beyond the join, else on the next one (arriving at a
        stop the velocity keeps the direction it came from, to its last sample)."""
        gs0 = self._gs0
        k = np.searchsorted(gs0, s, side="right") - 1
        np.clip(k, 0, len(gs0) - 1, out=k)
        if len(gs0) > 1:
            at = (s - gs0[k] <= self.BOUNDARY_M) & (k > 0)
            back = at & (lead <= gs0[k] + self.BOUNDARY_M)
            k[back] -= 1
            kn = np.minimum(k + 1, len(gs0) - 1)
            ahead = (k + 1 < len(gs0)) & (gs0[kn] - s <= self.BOUNDARY_M) & (lead > gs0[kn] + self.BOUNDARY_M)
            k[ahead] += 1
        length = self._glen[k]
        sig = np.clip(s - self._gs0[k], 0.0, length)
        u = self._u[k]
        x = self._p0[k] + sig[:, None] * u
        v = sd[:, None] * u
        if not self._any_arc:
            return x, v
        sel = np.flatnonzero(self._kind[k] == 1)
        if sel.size:                                       # the arcs' points only
            ka, sg, sda, la = k[sel], sig[sel], sd[sel], length[sel]
            cx, cy, r0, r1, phi0, sweep, fi, fo = self._arc[ka].T
            safe = np.where(la > 0, la, 1.0)
            f = sg / safe
            phi = phi0 + sweep * f
            r = r0 + (r1 - r0) * f
            dphi = sweep / safe
            dr = (r1 - r0) / safe
            rs = np.where(r > 0, r, 1.0)
            g = self._shrink(sda * np.abs(dphi))
            # the compensation faded in over fi of path at the arc's start and out over fo at
            # its end (0: none there, the same circle goes on; < 0: not compensated), by a
            # smoothstep of the path (the radial velocity it adds starts and ends at 0)
            fi_s = np.where(fi > 0, fi, 1.0)
            fo_s = np.where(fo > 0, fo, 1.0)
            wi = np.where(fi > 0, sg / fi_s, np.inf)
            wo = np.where(fo > 0, (la - sg) / fo_s, np.inf)
            u_ = np.clip(np.minimum(wi, wo), 0.0, 1.0)
            du = np.where((u_ > 0) & (u_ < 1), np.where(wi < wo, 1.0 / fi_s, -1.0 / fo_s), 0.0)
            w = u_ * u_ * (3.0 - 2.0 * u_)
            dw = 6.0 * u_ * (1.0 - u_) * du
            g = np.where((fi < 0) | (fo < 0), 0.0, g)
            rr = r + rs * g * w
            c, sn = np.cos(phi), np.sin(phi)
            radial = sda * (dr + rs * g * dw)
            ax, ay = self._ix, self._iy
            x[sel, ax] = cx + rr * c
            x[sel, ay] = cy + rr * sn
            v[sel, ax] = radial * c - sda * rr * dphi * sn
            v[sel, ay] = radial * sn + sda * rr * dphi * c
        return x, v

    def _grid(self, i0: int, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """x, v, a (each (n, n_axes)) at grid points i0 .. i0 + n − 1 (time i·h): s and ṡ through
        the moving average of n1, the path at s, x and v through the moving average of n2, a the
        backward difference of v over n2. Keeps the windows' tails for a call that goes on at
        i0 + n."""
        n1, n2, h = self.n1, self.n2, self.period
        tail = self._tail
        if tail is not None and tail[0] == i0:
            _, s_t, sd_t, x_t, v_t = tail
            t = (i0 + np.arange(n)) * h
            s_new, sd_new = self._ph.at(t)
            s = np.concatenate([s_t, s_new])                 # n1 + n2 + n samples of the profile
            sd = np.concatenate([sd_t, sd_new])
            ref = s[0]
            c = np.cumsum(np.concatenate([[0.0], s - ref]))
            sf = (c[n1:] - c[:-n1])[-n:] / n1 + ref          # the n1-averages ending at the new points
            c = np.cumsum(np.concatenate([[0.0], sd]))
            sdf = (c[n1:] - c[:-n1])[-n:] / n1
            xn, vn = self._path(sf, sdf, s[-n:])
            xr = np.concatenate([x_t, xn])                   # n2 + 1 + n samples of the path
            vr = np.concatenate([v_t, vn])
        else:
            t = (i0 + np.arange(-(n1 + n2), n)) * h
            s, sd = self._ph.at(t)
            ref = s[0]
            c = np.cumsum(np.concatenate([[0.0], s - ref]))
            sf = (c[n1:] - c[:-n1]) / n1 + ref               # n + n2 + 1
            c = np.cumsum(np.concatenate([[0.0], sd]))
            sdf = (c[n1:] - c[:-n1]) / n1
            xr, vr = self._path(sf, sdf, s[n1 - 1:])
        xref = xr[0]
        c = np.cumsum(np.concatenate([np.zeros((1, xr.shape[1])), xr - xref]), axis=0)
        x = (c[n2:] - c[:-n2])[-n:] / n2 + xref
        c = np.cumsum(np.concatenate([np.zeros((1, vr.shape[1])), vr]), axis=0)
        v = (c[n2:] - c[:-n2])[-n:] / n2
        a = (vr[n2:] - vr[:-n2])[-n:] / (n2 * h)
        self._tail = (i0 + n, s[-(n1 + n2):].copy(), sd[-(n1 + n2):].copy(), xr[-(n2 + 1):].copy(),
                      vr[-(n2 + 1):].copy())
        return x, v, a

    def _window(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """x, v, a (each (len(t), n_axes)) at arbitrary times t: the filters anchored at each."""
        n1, n2, h = self.n1, self.n2, self.period
        g = t[:, None] + np.arange(-(n1 + n2), 1) * h                 # (rows, n1 + n2 + 1)
        s, sd = self._ph.at(g)
        ref = s[:, :1]
        z = np.zeros((s.shape[0], 1))
        c = np.cumsum(np.concatenate([z, s - ref], axis=1), axis=1)
        sf = (c[:, n1:] - c[:, :-n1]) / n1 + ref                     # (rows, n2 + 2)
        c = np.cumsum(np.concatenate([z, sd], axis=1), axis=1)
        sdf = (c[:, n1:] - c[:, :-n1]) / n1
        xr, vr = self._path(sf.ravel(), sdf.ravel(), s[:, n1 - 1:].ravel())
        na = xr.shape[1]
        xr = xr.reshape(len(t), n2 + 2, na)
        vr = vr.reshape(len(t), n2 + 2, na)
        x = xr[:, 2:].mean(axis=1)
        v = vr[:, 2:].mean(axis=1)
        a = (vr[:, -1] - vr[:, 1]) / (n2 * h)
        return x, v, a

    def sample_into(self, t0: float, dt: float, out: np.ndarray) -> None:
        """Fill out[k, 0:3, i] = (x, v, a) of axis i at t0 + k·dt (out shape (n, 3, n_axes))."""
        n = out.shape[0]
        h = self.period
        q = t0 / h
        i0 = round(q)
        if abs(dt - h) <= 1e-12 * h and abs(q - i0) <= 1e-9:
            for lo in range(0, n, self.BLOCK):
                m = min(self.BLOCK, n - lo)
                x, v, a = self._grid(int(i0) + lo, m)
                out[lo:lo + m, 0], out[lo:lo + m, 1], out[lo:lo + m, 2] = x, v, a
        else:
            t = t0 + np.arange(n) * dt
            for lo in range(0, n, 256):
                x, v, a = self._window(t[lo:lo + 256])
                out[lo:lo + len(x), 0], out[lo:lo + len(x), 1], out[lo:lo + len(x), 2] = x, v, a
        t_last = t0 + (n - 1) * dt
        if t_last >= self.duration:
            late = t0 + np.arange(n) * dt >= self.duration
            out[late, 0] = self.end
            out[late, 1:3] = 0.0

    def sample(self, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(x, v, a) at t [s] (each shape (n_axes,)): on the planner's grid (within 1e-6 of a
        period) the grid's setpoints exactly; between two grid points x and v interpolated by
        cubic Hermite polynomials (from x, v and v, a at both ends) and a linearly. Grid points
        are computed a block of :data:`CACHE` at a time (the fast path of :meth:`sample_into`),
        so a caller walking forward pays about 1 µs a call."""
        if t >= self.duration:
            z = np.zeros(len(self.axes))
            return self.end.copy(), z, z.copy()
        h = self.period
        q = t / h
        k = math.floor(q)
        frac = q - k
        if frac > 1.0 - 1e-6:
            k, frac = k + 1, 0.0
        elif frac < 1e-6:
            frac = 0.0
        c = getattr(self, "_cache", None)
        need_hi = k + (1 if frac else 0)
        if c is None or not (self._c0 <= k and need_hi < self._c0 + self.CACHE):
            if c is None:
                c = self._cache = np.empty((self.CACHE, 3, len(self.axes)))
            self._c0 = k
            self.sample_into(k * h, h, c)
        i = k - self._c0
        if frac == 0.0:
            return c[i, 0].copy(), c[i, 1].copy(), c[i, 2].copy()
        x0, v0, a0 = c[i]
        x1, v1, a1 = c[i + 1]
        s = frac
        h00, h10, h01, h11 = (2 * s**3 - 3 * s**2 + 1, s**3 - 2 * s**2 + s, -2 * s**3 + 3 * s**2, s**3 - s**2)
        x = h00 * x0 + h10 * h * v0 + h01 * x1 + h11 * h * v1
        v = h00 * v0 + h10 * h * a0 + h01 * v1 + h11 * h * a1
        return x, v, a0 + (a1 - a0) * s

    def line_at(self, t: float) -> int:
        """The source line being run at t [s] (the filters' delay accounted)."""
        tu = t - self.delay
        ph = self._ph
        if tu < 0 or len(ph.t0) < 2:
            return 0
        k = int(np.searchsorted(ph.t0, tu, side="right") - 1)
        return int(ph.line[min(k, len(ph.line) - 1)])
