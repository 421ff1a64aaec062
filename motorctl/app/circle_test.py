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
circular hysteresis H, radial deviation F about the nominal centre.

The figures are the same bit for bit on every run of one config: the virtual clock, the
simulated driver's noise drawn from its ``seed`` (the config's ``driver.seed``), the filler
called at fixed cycles. With ``log_path`` the run's every cycle is written as a run log (the
format of ``motorctl run --log``: ``motorctl plot``, ``motorctl export`` read it); its header
adds ``kind: "circle-test"`` and ``circle``: the program, radius, feed, centre, the log rows
``[first, end)`` of each test circle (``rows``) and the figures.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from motorctl.app.build import build, log_header, shutdown, start
from motorctl.app.daemon.motion_side import AxisLimits, MotionSide
from motorctl.config import LoadedConfig
from motorctl.loop.stream import SetpointRing
from motorctl.motion.circle import CircleResult, circle_program, evaluate
from motorctl.recorder.runlog import LogWriter

#: seconds of setpoints in the ring (as the daemon's)
RING_S = 1.0
#: header bytes kept free for what is known at the end (the circles' rows, the figures)
HEADER_RESERVE = 64 << 10


@dataclass
class CircleRun:
    """One circular test: its controller, feed [m/s], radius [m], centre (x, y) [m], the ISO
    230-4 figures, the underruns (0 unless the planner fell behind), the measured paths
    ({"cw": (x, y), "ccw": (x, y)}, [m]), the run log's path (None: not written) and the log
    rows of each test circle ({"cw": (first, end), ...}, row indexes of the log)."""

    controller: str
    feed: float
    radius: float
    center: tuple[float, float]
    result: CircleResult
    underruns: int
    paths: dict
    log_path: str | None = None
    rows: dict | None = None


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
        step = max(1, motion.lead // 2)
        state = {"k0": 0, "first": 0, "queued": False}

        def between_cycles(loop) -> None:
            # the daemon's filler, every `step` cycles (one run() call: a run() ends at 0 V)
            k = loop.k
            if k % step:
                return
            to_log(loop, k)                              # (step < the buffer's capacity)
            if not state["queued"]:
                if k < tb.cycles(0.05):                  # hold a moment first
                    return
                motion.gcode(text, "circle-test")
                state["queued"], state["k0"], state["first"] = True, k, k
            else:
                ys.append(loop.buf[np.arange(state["k0"], k) % loop.capacity][:, iy].copy())
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
        paths = {d: (y[line == where[d], 0], y[line == where[d], 1]) for d in ("cw", "ccw")}
        res = evaluate(paths["cw"], paths["ccw"], center, radius)
        # the i-th streamed row is the loop's row of cycle k0 + i, the log's row k0 + i
        rows = {}
        for d in ("cw", "ccw"):
            i = np.flatnonzero(line == where[d])
            rows[d] = (int(state["first"] + i[0]), int(state["first"] + i[-1] + 1))
        run = CircleRun(controller or asm.active[0], feed, radius, center, res, ring.underruns(), paths,
                        str(log_path) if log_path else None, rows)
        if writer is not None:
            writer.update_header(log_header(asm, kind="circle-test", circle={
                "standard": "ISO 230-4", "radius_m": radius, "feed_m_s": feed, "center_m": list(center),
                "program": text, "lines": where, "rows": rows, "underruns": run.underruns,
                "figures_m": figures(res)}))
        return run
    finally:
        shutdown(asm)
        if writer is not None:
            writer.close()


def figures(res: CircleResult) -> dict:
    """The ISO 230-4 figures of one test as {name: value [m]} (G_cw, G_ccw, G_b, H, F_max,
    F_min, radius_lsc) and center_lsc [x, y] [m]."""
    return {"G_cw": res.G_cw, "G_ccw": res.G_ccw, "G_b": res.G_b, "H": res.H, "F_max": res.F_max,
            "F_min": res.F_min, "radius_lsc": res.radius_lsc, "center_lsc": list(res.center_lsc)}
