"""The ISO 230-4 circular test of the simulated gantry on the daemon's motion path.

The test program (:func:`motorctl.motion.circle.circle_program`: CCW then CW full circles in XY,
entered and left on tangential half circles, with 90° overshoot arcs of the circle before and
after each measured turn) is read, checked and planned by the daemon's
:class:`~motorctl.app.daemon.motion_side.MotionSide`, streamed through the setpoint ring into
the compiled cycle's STREAM mode (:mod:`motorctl.loop.stream`) with both axes in command mode,
all in one process on the virtual clock (the simulated plant advances one period per cycle, so
the figures are those of a wall-clock run, and the same every run). The measured path of each
test circle (the rows whose setpoint belongs to its G-code line) is evaluated by
:func:`motorctl.motion.circle.evaluate`: circular deviation G per direction and both (G(b)),
circular hysteresis H, radial deviation F about the nominal centre; and the largest contour
error, the largest radial distance of either test circle from its own least-squares circle.

Two instruments read the test circles (ISO 230-4 measures the path with an instrument apart from
the machine's own feedback, a ballbar):

- ``encoder``: the axes' own encoders (the log's ``AXIS.y``, what the loop controls on). Their
  steps, noise and interpolation error are in every figure: on the simulated gantry (0.5 µm
  steps, 0.1 µm noise, ±0.15 µm interpolation error) a path without any motion error reads G
  1.4-1.5 µm at R 50 mm (docs/control-law.md, "What the ratio rests on");
- ``ballbar``: the carriages' true positions, read through the driver's ``true_position_m``
  where it has one (:attr:`motorctl_drivers.sim.SimDriver.true_position_m`, the simulated plant's
  x at each read; a simulated ballbar without an error of its own). A real drive has only its
  encoders: the run then says so (:attr:`CircleRun.no_ballbar`) and reports the encoders alone.
  The ballbar is sampled between cycles (the loop's ``on_slack``), not inside the timed cycle.

The figures are the same bit for bit on every run of one config: the virtual clock, the
simulated driver's noise drawn from its ``seed`` (the config's ``driver.seed``), the filler
called at fixed cycles. With ``log_path`` the run's every cycle is written as a run log (the
format of ``motorctl run --log``: ``motorctl plot``, ``motorctl export`` read it); its header
adds ``kind: "circle-test"`` and ``circle``: the program, radius, feed, centre, the log rows
``[first, end)`` of each test circle (``rows``) and each instrument's figures (``figures_m``:
``{"encoder": {...}, "ballbar": {...} or null}``, :func:`figures`; ``no_ballbar``: why there is
none). The log's rows hold the encoders' positions; the ballbar's are in the header's figures
only (the record's columns are the loop's, :mod:`motorctl.loop.records`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from motorctl.app.build import build, log_header, shutdown, start
from motorctl.app.daemon.motion_side import AxisLimits, MotionSide
from motorctl.config import LoadedConfig
from motorctl.loop.stream import SetpointRing
from motorctl.motion.circle import CircleResult, circle_program, evaluate, fit_circle, radial
from motorctl.recorder.runlog import LogWriter

#: seconds of setpoints in the ring (as the daemon's)
RING_S = 1.0
#: header bytes kept free for what is known at the end (the circles' rows, the figures)
HEADER_RESERVE = 64 << 10
#: the instruments (module docstring), in the order they are reported
ENCODER, BALLBAR = "encoder", "ballbar"
#: what each instrument is, one line (the command's legend)
INSTRUMENTS = {ENCODER: "the axes' own encoders (the position the loop controls on)",
               BALLBAR: "the carriages' true positions from the driver (a simulated ballbar; real drives have none)"}


@dataclass(frozen=True)
class Reading:
    """One instrument's reading of the test circles: ``instrument`` (:data:`ENCODER` or
    :data:`BALLBAR`), the ISO 230-4 figures ``result`` [m], ``e_max`` the largest contour error
    [m] (:func:`largest_contour_error`), the test circles' ``paths`` ({"cw": (x, y), "ccw": (x,
    y)}, arrays (n,) [m])."""

    instrument: str
    result: CircleResult
    e_max: float
    paths: dict


@dataclass
class CircleRun:
    """One circular test: its controller, feed [m/s], radius [m], centre (x, y) [m], each
    instrument's reading ({"encoder": Reading, "ballbar": Reading}; no "ballbar" where the driver
    reads no true position, ``no_ballbar`` then says why), the underruns (0 unless the planner
    fell behind), the run log's path (None: not written) and the log rows of each test circle
    ({"cw": (first, end), ...}, row indexes of the log). ``result`` and ``paths``: the encoders'."""

    controller: str
    feed: float
    radius: float
    center: tuple[float, float]
    readings: dict
    underruns: int
    log_path: str | None = None
    rows: dict | None = None
    no_ballbar: str = ""

    @property
    def result(self) -> CircleResult:
        """The encoders' ISO 230-4 figures [m]."""
        return self.readings[ENCODER].result

    @property
    def paths(self) -> dict:
        """The test circles as the encoders read them ({"cw": (x, y), "ccw": (x, y)} [m])."""
        return self.readings[ENCODER].paths


def largest_contour_error(paths: dict) -> float:
    """The largest contour error [m] of the test circles ``paths`` ({"cw": (x, y), "ccw": (x, y)},
    arrays (n,) [m]): the largest |r − R| of either circle about its own least-squares circle
    (:func:`motorctl.motion.circle.fit_circle`; ISO 230-4's radial deviation about the LSC
    centre, the worse side). Raises ValueError: fewer than 3 points in a circle."""
    worst = 0.0
    for x, y in paths.values():
        xc, yc, r = fit_circle(x, y)
        _, rad = radial(x, y, (xc, yc))
        worst = max(worst, float(np.max(np.abs(rad - r))))
    return worst


def ballbar_of(driver, n: int) -> tuple[np.ndarray | None, str]:
    """The driver's true positions of its ``n`` axes as a ballbar reads them: (its
    ``true_position_m`` array (n,) [m], refreshed by each read, ""), or (None, why not: the
    driver reads none, e.g. a bus driver to a real drive)."""
    truth = getattr(driver, "true_position_m", None)
    if isinstance(truth, np.ndarray) and truth.shape == (n,):
        return truth, ""
    return None, (f"no ballbar: the {type(driver).__name__} driver reads no true position (a real drive "
                  "has only its encoders); the figures are the encoders'")


def _reading(instrument: str, paths: dict, center, radius: float) -> Reading:
    return Reading(instrument, evaluate(paths["cw"], paths["ccw"], center, radius),
                   largest_contour_error(paths), paths)


def run_circle_test(loaded: LoadedConfig, radius: float, feed: float, controller: str | None = None,
                    center: tuple[float, float] | None = None, axes: tuple[str, str] = ("X", "Y"),
                    log_path: str | None = None) -> CircleRun:
    """Run the bidirectional circular test (module docstring) on ``axes`` of a simulated
    config with ``controller`` (None: each axis's configured one).

    radius [m], feed [m/s]; center: the circle's centre [m] (default: the middle of the soft
    limits); log_path: write the run log there (every cycle from the first, the header's
    ``circle`` section; the file is created before the first cycle). Raises ValueError: a radius
    or feed ≤ 0, a circle outside the soft limits (the planner's refusal with its line), a fault
    during the run (the log keeps the rows up to it). OSError: the log cannot be written.
    """
    names = list(axes)
    lims = [loaded.axes[a].limits for a in names]
    if center is None:
        center = tuple(0.5 * (lim.soft_min_m + lim.soft_max_m) for lim in lims)
    text, where = circle_program(radius, feed, center)
    tb = loaded.timebase
    ring = SetpointRing(tb.cycles(RING_S), len(names), shared=False)
    asm = build(loaded, names, controller, clock="virtual", capacity=tb.cycles(1.0), operated=True,
                stream=ring)
    writer = None
    if log_path:
        writer = LogWriter(str(log_path), log_header(asm, kind="circle-test"), reserve=HEADER_RESERVE)
    logged = [0]                                          # rows of the loop's buffer in the log

    def to_log(loop, k: int) -> None:
        if writer is not None and k > logged[0]:
            writer.append(loop.buf[np.arange(logged[0], k) % loop.capacity])
            logged[0] = k

    start(asm, "off")
    try:
        lp = asm.loop
        axis_limits = []
        for a, lim in zip(names, lims):
            tc = loaded.axes[a].trajectory
            axis_limits.append(AxisLimits(tc.v_max, tc.a_max, tc.j_max, lim.soft_min_m, lim.soft_max_m))
        for i, a in enumerate(names):
            lp.command_axis(i, axis_limits[i].a_max, axis_limits[i].j_max)
        motion = MotionSide(ring, lambda: lp.buf[(lp.k - 1) % lp.capacity], lp.layout, names, axis_limits,
                            lambda: lp.mode, tb.period_s, lead_s=RING_S / 2)
        motion.trace = []
        iy = [lp.layout.index(f"{a}.y") for a in names]
        ys: list = []
        truth, no_ballbar = ballbar_of(asm.driver, len(names))
        tbuf = np.zeros((lp.capacity, len(names)))        # the ballbar's rows, as the loop's buffer's
        ts: list = []
        step = max(1, motion.lead // 2)
        state = {"k0": 0, "first": 0, "queued": False}

        def between_cycles(loop) -> None:
            # the daemon's filler, every `step` cycles (one run() call: a run() ends at 0 V)
            k = loop.k
            if truth is not None:                        # the ballbar at the read of row k - 1
                tbuf[(k - 1) % loop.capacity] = truth
            if k % step:
                return
            to_log(loop, k)                              # (step < the buffer's capacity)
            if not state["queued"]:
                if k < tb.cycles(0.05):                  # hold a moment first
                    return
                motion.gcode(text, "circle-test")
                state["queued"], state["k0"], state["first"] = True, k, k
            else:
                rows_k = np.arange(state["k0"], k) % loop.capacity
                ys.append(loop.buf[rows_k][:, iy])
                if truth is not None:
                    ts.append(tbuf[rows_k])
                state["k0"] = k
                if motion.idle() or any(loop.supervisor.fault):
                    loop.request_stop()
                    return
            while motion.fill():                         # up to the lead, a block at a time
                pass

        lp.on_slack = between_cycles
        try:
            lp.run(1 << 40)
        finally:
            to_log(lp, lp.k)
        if any(lp.supervisor.fault):
            raise ValueError("circle test: fault during the run: " + "; ".join(
                lp.supervisor.reason(i) for i in range(len(names)) if lp.supervisor.fault[i]))
        y = np.concatenate(ys)
        line = np.asarray(motion.trace)
        # the trace holds the line of every streamed row; the loop took one per cycle from
        # the first row on (the ring never ran dry unless counted as an underrun)
        n = min(len(line), len(y))
        y, line = y[:n], line[:n]
        readings = {}
        for name, pos in ((ENCODER, y), (BALLBAR, np.concatenate(ts)[:n] if truth is not None else None)):
            if pos is not None:
                paths = {d: (pos[line == where[d], 0], pos[line == where[d], 1]) for d in ("cw", "ccw")}
                readings[name] = _reading(name, paths, center, radius)
        # the i-th streamed row is the loop's row of cycle k0 + i, the log's row k0 + i
        rows = {}
        for d in ("cw", "ccw"):
            i = np.flatnonzero(line == where[d])
            rows[d] = (int(state["first"] + i[0]), int(state["first"] + i[-1] + 1))
        run = CircleRun(controller or asm.active[0], feed, radius, center, readings, ring.underruns(),
                        str(log_path) if log_path else None, rows, no_ballbar)
        if writer is not None:
            writer.update_header(log_header(asm, kind="circle-test", circle={
                "standard": "ISO 230-4", "radius_m": radius, "feed_m_s": feed, "center_m": list(center),
                "program": text, "lines": where, "rows": rows, "underruns": run.underruns,
                "instruments": {k: INSTRUMENTS[k] for k in readings},
                "figures_m": {k: (figures(readings[k]) if k in readings else None) for k in INSTRUMENTS},
                "no_ballbar": no_ballbar}))
        return run
    finally:
        shutdown(asm)
        if writer is not None:
            writer.close()


def figures(reading: Reading) -> dict:
    """One instrument's figures as {name: value [m]}: ISO 230-4's G_cw, G_ccw, G_b, H, F_max,
    F_min, radius_lsc, center_lsc [x, y], and e_max (the largest contour error)."""
    res = reading.result
    return {"G_cw": res.G_cw, "G_ccw": res.G_ccw, "G_b": res.G_b, "H": res.H, "F_max": res.F_max,
            "F_min": res.F_min, "radius_lsc": res.radius_lsc, "center_lsc": list(res.center_lsc),
            "e_max": reading.e_max}


#: the figures of :func:`summary` and :func:`table`, per instrument: (name, CircleResult's field
#: or "e_max", column title)
_SHOWN = (("G_cw", "G cw um"), ("G_ccw", "G ccw um"), ("G_b", "G(b) um"), ("H", "H um"), ("F_max", "F max um"),
          ("F_min", "F min um"), ("e_max", "e max um"))


def _um(reading: Reading) -> dict:
    f = figures(reading)
    return {f"{k}_um": f[k] * 1e6 for k, _ in _SHOWN}


def summary(run: CircleRun) -> dict:
    """One run as JSON-able facts (``motorctl circle-test --json``): controller, feed_m_s,
    radius_m, center_m, underruns, log; each instrument's figures in µm ({"G_cw_um", "G_ccw_um",
    "G_b_um", "H_um", "F_max_um", "F_min_um", "e_max_um"}) under "encoder" and "ballbar" (null
    where the driver reads no true position, "no_ballbar" then says why)."""
    out = {"controller": run.controller, "feed_m_s": run.feed, "radius_m": run.radius, "center_m": list(run.center),
           "underruns": run.underruns, "log": run.log_path}
    for k in INSTRUMENTS:
        out[k] = _um(run.readings[k]) if k in run.readings else None
    out["no_ballbar"] = run.no_ballbar
    return out


def table(runs: list) -> list[list[str]]:
    """The runs as a table's rows (the header first): per run and instrument the controller,
    feed [mm/s], the instrument, the figures of :func:`summary` [µm], the underruns; a run
    without a ballbar has its ballbar row "none" (:attr:`CircleRun.no_ballbar` says why)."""
    rows = [["controller", "feed mm/s", "instrument"] + [t for _, t in _SHOWN] + ["underruns"]]
    for r in runs:
        for k in INSTRUMENTS:
            head = [r.controller, f"{r.feed * 1e3:.0f}", k]
            if k in r.readings:
                f = _um(r.readings[k])
                rows.append(head + [f"{f[n + '_um']:.2f}" for n, _ in _SHOWN] + [str(r.underruns)])
            else:
                rows.append(head[:2] + [k + ": none"] + ["-"] * len(_SHOWN) + [str(r.underruns)])
    return rows
