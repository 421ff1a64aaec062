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
        (self._gs0, self._glen, self._kind, self._p0, self._p1, self._u, arc) = geo
        self._ix, self._iy = ix, iy
        self.n1, self.n2, self.period = n1, n2, period
        self._m = n1 + n2 - 2
        self.delay = 0.5 * self._m * period
        self.t_profile = phases.duration
        self.duration = self.t_profile + (n1 + n2 + 1) * period
        self.start, self.end = start, end
        self.events, self.stops = events, stops
        self._tail = None                 # (next time, s, ṡ, x, v tails) of the last grid call
        self._k1 = np.full(n1, 1.0 / n1)
        # the arcs per piece (0 on lines): centre, radius and angle at the start and their rates
        # per metre of path; the shrink's compensation (0: none) and the rates of its fades in
        # and out with an offset (0 and 2 where it does not fade: the same circle goes on)
        self._any_arc = bool(np.any(self._kind == 1))
        cx, cy, r0, r1, phi0, sweep, fi, fo = arc.T
        safe = np.where(self._glen > 0, self._glen, 1.0)
        self._arc_tab = (cx, cy, r0, (r1 - r0) / safe, phi0, sweep / safe, np.abs(sweep) / safe,
                         ((fi >= 0) & (fo >= 0)).astype(float),
                         np.where(fi > 0, 1.0 / np.where(fi > 0, fi, 1.0), 0.0), np.where(fi > 0, 0.0, 2.0),
                         np.where(fo > 0, 1.0 / np.where(fo > 0, fo, 1.0), 0.0), np.where(fo > 0, 0.0, 2.0))

    def __getstate__(self):
        d = dict(self.__dict__)
        d["_tail"] = None
        d.pop("_cache", None)
        return d

    def _path(self, s: np.ndarray, sd: np.ndarray, lead: np.ndarray,
              rising: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The blended path's point and velocity at path length s moving at ṡ (shape (k,) each;
        returns shape (k, n_axes) each); arcs on the radius the short filter shrinks back onto
        theirs (the radius over S(ω), S the moving average's gain sin(n₂ωh/2)/(n₂ sin(ωh/2)) at
        the angular rate ω, faded in and out by a smoothstep of the path where the circle changes).
        ``lead``: the unfiltered path length at the newest sample of each point's window, and
        ``rising``: whether the unfiltered speed rises there (shape (k,) each): at a join (within
        BOUNDARY_M, the averages' rounding) the point is on the piece it is leaving while the
        newest sample is not beyond the join and not speeding up from it, else on the next one
        (arriving at a stop the velocity keeps the direction it came from, to its last sample;
        leaving a stop it takes the next piece's from the first sample that moves, however little
        that sample has moved: a point kept on the last piece there moves the wrong axis)."""
        gs0, glen = self._gs0, self._glen
        k = np.searchsorted(gs0, s, side="right") - 1
        np.maximum(k, 0, out=k)
        d0 = s - gs0[k]
        lk = glen[k]
        eps = self.BOUNDARY_M
        near = (d0 <= eps) | (lk - d0 <= eps)
        if len(gs0) > 1 and near.any():
            last = len(gs0) - 1
            back = (d0 <= eps) & (k > 0) & (lead <= gs0[k] + eps) & ~rising
            k[back] -= 1
            kn = np.minimum(k + 1, last)
            ahead = (k < last) & (gs0[kn] - s <= eps) & ((lead > gs0[kn] + eps)
                                                         | (rising & (lead >= gs0[kn] - eps)))
            k[ahead] += 1
            d0 = s - gs0[k]
            lk = glen[k]
        sig = np.minimum(np.maximum(d0, 0.0), lk)
        u = self._u[k]
        x = self._p0[k] + sig[:, None] * u
        v = sd[:, None] * u
        if self._any_arc:
            sel = np.flatnonzero(self._kind[k])
            if sel.size:
                self._arcs(sel, k[sel], sig[sel], sd[sel], lk[sel], x, v)
        return x, v

    def _arcs(self, sel, ka, sg, sda, la, x, v) -> None:
        """The arcs' rows ``sel`` of x and v (in place): pieces ka at sg along them at ṡ sda."""
        cx, cy, r0, drds, phi0, dphids, adphi, comp, fi_inv, fi_off, fo_inv, fo_off = (c[ka] for c in self._arc_tab)
        phi = phi0 + dphids * sg
        r = r0 + drds * sg
        xh = (0.5 * self.period) * sda * adphi + 1e-300
        g = comp * (self.n2 * np.sin(xh) / np.sin(self.n2 * xh) - 1.0)      # 1/S − 1
        wi = sg * fi_inv + fi_off
        wo = (la - sg) * fo_inv + fo_off
        w = np.minimum(np.minimum(wi, wo), 1.0)
        dw = np.where(w < 1.0, np.where(wi < wo, fi_inv, -fo_inv), 0.0) * (6.0 * w * (1.0 - w))
        w *= w * (3.0 - 2.0 * w)
        gw = g * w
        rr = r * (1.0 + gw)
        radial = sda * (drds * (1.0 + gw) + r * g * dw)
        tang = sda * rr * dphids
        c, sn = np.cos(phi), np.sin(phi)
        ax, ay = self._ix, self._iy
        x[sel, ax] = cx + rr * c
        x[sel, ay] = cy + rr * sn
        v[sel, ax] = radial * c - tang * sn
        v[sel, ay] = radial * sn + tang * c

    def _grid(self, t0: float, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """x, v, a (each (n, n_axes)) at t0 + i·h, i < n: s and ṡ through the moving average of
        n1, the path at s, x and v through the moving average of n2, a the backward difference
        of v over n2. Keeps the windows' tails for a call that goes on at t0 + n·h."""
        n1, n2, h = self.n1, self.n2, self.period
        tail = self._tail
        k1 = self._k1
        if tail is not None and abs(tail[0] - t0) <= 1e-9 * h:
            _, s_t, sd_t, x_t, v_t = tail
            s_new, sd_new = self._ph.at(t0 + np.arange(n) * h)
            s = np.concatenate([s_t, s_new])                 # n1 + n2 + n samples of the profile
            sd = np.concatenate([sd_t, sd_new])
            sl, sdl = s[n2 + 1:], sd[n2 + 1:]                # the windows ending at the new points
            xn, vn = self._path(np.convolve(sl, k1, "valid"), np.convolve(sdl, k1, "valid"), s_new,
                                sd_new > sd[-n - 1:-1])
            xr = np.concatenate([x_t, xn])                   # n2 + 1 + n samples of the path
            vr = np.concatenate([v_t, vn])
        else:
            s, sd = self._ph.at(t0 + np.arange(-(n1 + n2), n) * h)
            xr, vr = self._path(np.convolve(s, k1, "valid"), np.convolve(sd, k1, "valid"), s[n1 - 1:],
                                sd[n1 - 1:] > sd[n1 - 2:-1])
        c = np.cumsum(xr - xr[0], axis=0)                  # the n2-averages ending at the n points
        x = (c[n2 + 1:] - c[1:-n2]) / n2 + xr[0]
        c = np.cumsum(vr, axis=0)
        v = (c[n2 + 1:] - c[1:-n2]) / n2
        a = (vr[n2 + 1:] - vr[1:-n2]) / (n2 * h)
        self._tail = (t0 + n * h, s[-(n1 + n2):], sd[-(n1 + n2):], xr[-(n2 + 1):], vr[-(n2 + 1):])
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
        xr, vr = self._path(sf.ravel(), sdf.ravel(), s[:, n1 - 1:].ravel(),
                            (sd[:, n1 - 1:] > sd[:, n1 - 2:-1]).ravel())
        na = xr.shape[1]
        xr = xr.reshape(len(t), n2 + 2, na)
        vr = vr.reshape(len(t), n2 + 2, na)
        x = xr[:, 2:].mean(axis=1)
        v = vr[:, 2:].mean(axis=1)
        a = (vr[:, -1] - vr[:, 1]) / (n2 * h)
        return x, v, a

    def sample_into(self, t0: float, dt: float, out: np.ndarray) -> None:
        """Fill out[k, 0:3, i] = (x, v, a) of axis i at t0 + k·dt (out shape (n, 3, n_axes)):
        at the planner's period the filters on the grid through t0 (a block at a time, the
        windows of a call that goes on where the last ended reused), at another the filters
        anchored at each time."""
        n = out.shape[0]
        h = self.period
        if abs(dt - h) <= 1e-12 * h:
            for lo in range(0, n, self.BLOCK):
                m = min(self.BLOCK, n - lo)
                out[lo:lo + m, 0], out[lo:lo + m, 1], out[lo:lo + m, 2] = self._grid(t0 + lo * h, m)
        else:
            t = t0 + np.arange(n) * dt
            for lo in range(0, n, 256):
                x, v, a = self._window(t[lo:lo + 256])
                out[lo:lo + len(x), 0], out[lo:lo + len(x), 1], out[lo:lo + len(x), 2] = x, v, a
        if t0 + (n - 1) * dt >= self.duration:
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
