"""The circular test of ISO 230-4:2022 ("Circular tests for numerically controlled machine
tools"): a program that runs a circle in XY in both directions, and the evaluation of the measured
path - circular deviation G, circular hysteresis H and radial deviation F (the figures a ballbar
report shows).

Definitions (ISO 230-4, clause 3):

- radial deviation F: the measured radius minus the nominal radius about the *nominal* centre;
  reported as F_max (largest, outward) and F_min (smallest, inward);
- circular deviation G: the minimum radial separation of two concentric circles enveloping the
  measured path, centred here on the least-squares circle (the standard's LSC option); G(b), the
  bidirectional circular deviation, envelops the CW and CCW paths together;
- circular hysteresis H: the largest radial difference between the CW and the CCW path at one
  angle (about the common least-squares centre).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np


def fit_circle(x: np.ndarray, y: np.ndarray) -> tuple[float, float, float]:
    """Least-squares circle through points x, y (shape (n,), n ≥ 3) [m]: (x_c, y_c, r) [m].

    The algebraic fit (Kåsa): x² + y² = 2 x_c x + 2 y_c y + c solved by least squares, then
    r = sqrt(c + x_c² + y_c²); for the small deviations of a machine test it is the geometric
    fit to within nanometres. Raises ValueError for fewer than 3 points or collinear points."""
    x = np.asarray(x, dtype=float)
    y = np.asarray(y, dtype=float)
    if x.size < 3 or x.size != y.size:
        raise ValueError("fit_circle: need x and y of one length, at least 3 points")
    mx, my = x.mean(), y.mean()
    u, v = x - mx, y - my
    A = np.column_stack([2 * u, 2 * v, np.ones_like(u)])
    sol, _, rank, _ = np.linalg.lstsq(A, u * u + v * v, rcond=None)
    r2 = sol[2] + sol[0] ** 2 + sol[1] ** 2
    if rank < 3 or not np.isfinite(r2) or r2 <= 0:
        raise ValueError("fit_circle: the points do not lie on a circle")
    return float(sol[0] + mx), float(sol[1] + my), float(math.sqrt(r2))


def radial(x: np.ndarray, y: np.ndarray, center: Sequence[float]) -> tuple[np.ndarray, np.ndarray]:
    """(angle [rad] in (−π, π], radius [m]) of points x, y (shape (n,)) about ``center``."""
    dx = np.asarray(x, dtype=float) - center[0]
    dy = np.asarray(y, dtype=float) - center[1]
    return np.arctan2(dy, dx), np.hypot(dx, dy)


@dataclass(frozen=True)
class CircleResult:
    """One ISO 230-4 evaluation [m]: G_cw, G_ccw (circular deviation of each direction), G_b
    (bidirectional), H (circular hysteresis), F_max, F_min (radial deviation about the nominal
    centre), center_lsc (x, y) and radius_lsc of the least-squares circle of both paths."""

    G_cw: float
    G_ccw: float
    G_b: float
    H: float
    F_max: float
    F_min: float
    center_lsc: tuple[float, float]
    radius_lsc: float


def circular_deviation(x: np.ndarray, y: np.ndarray) -> float:
    """G [m] of one path (shape (n,) each): the radial span about its least-squares centre."""
    xc, yc, _ = fit_circle(x, y)
    _, r = radial(x, y, (xc, yc))
    return float(r.max() - r.min())


def _on_grid(angle: np.ndarray, r: np.ndarray, grid: np.ndarray) -> np.ndarray:
    order = np.argsort(angle)
    a, rr = angle[order], r[order]
    return np.interp(grid, np.concatenate([a - 2 * np.pi, a, a + 2 * np.pi]), np.tile(rr, 3))


def evaluate(cw: tuple[np.ndarray, np.ndarray], ccw: tuple[np.ndarray, np.ndarray],
             center: Sequence[float], radius: float, n_angles: int = 3600) -> CircleResult:
    """Evaluate a bidirectional circular test.

    cw, ccw: the measured (x, y) of each full circle (arrays of shape (n,) [m], the lead-in and
    lead-out arcs left out); center (x, y) and radius: the nominal circle [m]; n_angles: the
    angular grid on which H compares the two paths. Raises ValueError on fewer than 3 points."""
    xa = np.concatenate([cw[0], ccw[0]])
    ya = np.concatenate([cw[1], ccw[1]])
    xc, yc, rc = fit_circle(xa, ya)
    ang_cw, r_cw = radial(cw[0], cw[1], (xc, yc))
    ang_ccw, r_ccw = radial(ccw[0], ccw[1], (xc, yc))
    grid = np.linspace(-np.pi, np.pi, n_angles, endpoint=False)
    h = float(np.max(np.abs(_on_grid(ang_cw, r_cw, grid) - _on_grid(ang_ccw, r_ccw, grid))))
    r_all = np.concatenate([r_cw, r_ccw])
    _, rn = radial(xa, ya, center)
    return CircleResult(G_cw=circular_deviation(*cw), G_ccw=circular_deviation(*ccw),
                        G_b=float(r_all.max() - r_all.min()), H=h,
                        F_max=float((rn - radius).max()), F_min=float((rn - radius).min()),
                        center_lsc=(xc, yc), radius_lsc=rc)


def circle_program(radius: float, feed: float, center: Sequence[float] = (0.0, 0.0),
                   directions: Sequence[str] = ("ccw", "cw"), tolerance: float = 1e-5,
                   dwell: float = 0.5) -> tuple[str, dict[str, int]]:
    """The G-code of the test (ISO 230-4, 5.2: the full circle entered and left on tangential
    half-circle arcs of radius R/2 from and to the centre, so the test circle starts and ends
    at feed, without a reversal at its start point), with an overshoot arc of 90° on the test
    circle before and after the measured full circle, as a ballbar test runs them: where the
    R/2 arc joins the circle the curvature steps from 2/R to 1/R, and the planner's jerk-limited
    blend there (within the G64 tolerance) bends the setpoint off the circle for a few tens of
    ms (1.85 µm inside at R 50 mm, 100 mm/s); the overshoot arcs keep that join and the servo's
    settling after it out of the measured circle, which starts and ends at 90° (CCW) or −90°
    (CW), on the circle's own curvature both ways.

    radius [m], feed [m/s] (the path speed of the test), center (x, y) [m] (machine = program
    coordinates, G54 at 0), directions: "ccw" (G3) and/or "cw" (G2), run in that order with a
    ``dwell`` [s] between; tolerance: G64 P [m]. Returns (text, {direction: source line of its
    measured full circle}). Raises ValueError on a radius or feed ≤ 0 or an unknown direction."""
    if not radius > 0 or not feed > 0:
        raise ValueError(f"circle test: radius {radius} m and feed {feed} m/s must be > 0")
    mm = 1e3
    cx, cy, r = center[0] * mm, center[1] * mm, radius * mm
    lines = ["%", "(ISO 230-4 circular test: R %.4f mm, F %.1f mm/min)" % (r, feed * 60 * mm),
             f"G17 G21 G90 G94 G64 P{tolerance * mm:.4f}", f"G0 X{cx:.4f} Y{cy:.4f}", f"F{feed * 60 * mm:.1f}"]
    where: dict[str, int] = {}
    for d in directions:
        if d not in ("cw", "ccw"):
            raise ValueError(f"circle test: direction {d!r}: allowed cw, ccw")
        g, s = ("G2", -1.0) if d == "cw" else ("G3", 1.0)       # s: the side the circle turns to
        lines.append(f"{g} X{cx + r:.4f} Y{cy:.4f} I{r / 2:.4f} J0")              # lead-in, to 0°
        lines.append(f"{g} X{cx:.4f} Y{cy + s * r:.4f} I{-r:.4f} J0")            # overshoot, to ±90°
        lines.append(f"{g} X{cx:.4f} Y{cy + s * r:.4f} I0 J{-s * r:.4f}")        # the test circle
        where[d] = len(lines)
        lines.append(f"{g} X{cx - r:.4f} Y{cy:.4f} I0 J{-s * r:.4f}")            # overshoot, to 180°
        lines.append(f"{g} X{cx:.4f} Y{cy:.4f} I{r / 2:.4f} J0")                 # lead-out
        if dwell > 0:
            lines.append(f"G4 P{dwell:g}")
    lines += ["M2", "%"]
    return "\n".join(lines) + "\n", where
