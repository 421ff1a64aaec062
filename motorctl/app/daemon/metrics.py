"""Prometheus metrics of the daemon (docs/metrics.md), served from a process of their own.

The I/O process (:mod:`motorctl.app.daemon.io_side`) hands a small snapshot of figures it
already keeps (:func:`snapshot`: the drainer's turnaround histogram and counters, the status
block, the setpoint stream's counters) to the *metrics process* every :data:`SNAPSHOT_EVERY_S`
over a non-blocking socket pair (:class:`MetricsLink`; a send that would wait is dropped and
counted). The metrics process serves the newest snapshot at ``GET /metrics`` in Prometheus's
text exposition format (the ``prometheus-client`` library, the ``metrics`` extra). A scrape
reads nothing of the loop, the shared ring or the run log: its work is the conversion of one
snapshot (a few dozen samples), whatever the scrape rate.

The only rows the metrics look at are the ones the drainer already took: :class:`RowTap`, a
drainer tap, sums the following error's square per axis over enabled cycles and counts the
cycles in which the loop's missed-period counter rose (one overrun), a few numpy reductions per
drained batch.

The metrics process runs at nice :data:`METRICS_NICE` (0, as the I/O process: a scrape is
bounded work, and at +10 a loaded host starved it for minutes, docs/benchmarks.md) and ends
with the I/O process (EOF on the link, ``PR_SET_PDEATHSIG``).
"""

from __future__ import annotations

import math
import os
import pickle
import socket
import sys
import threading
import time

import numpy as np

from motorctl.app.daemon.forked import SnapshotLink, fork_helper, helper_started

#: the I/O process sends a snapshot this often [s]
SNAPSHOT_EVERY_S = 1.0
#: the metrics process's niceness (the I/O process's own)
METRICS_NICE = 0
#: upper bounds of the turnaround histogram's buckets [s] (then +Inf)
TURNAROUND_BUCKETS_S = (5e-6, 10e-6, 15e-6, 20e-6, 30e-6, 50e-6, 75e-6, 100e-6, 150e-6,
                        200e-6, 500e-6, 1e-3, 5e-3)


class RowTap:
    """A drainer tap (I/O process): per axis the sum of e² [m²] and the count of enabled
    cycles since the last :meth:`take`, and the overruns (cycles whose missed-period counter
    rose) since the start. Never raises.

    Args:
        layout: the run's :class:`~motorctl.loop.records.RecordLayout`. names: axis names.
    """

    def __init__(self, layout, names):
        self.c_e = np.asarray([layout.index(f"{a}.e") for a in names])
        self.c_en = np.asarray([layout.index(f"{a}.enabled") for a in names])
        self.c_ovr = layout.cycle("overruns")
        self.sq = np.zeros(len(names))
        self.n = np.zeros(len(names), dtype=np.int64)
        self.overruns = 0
        self._prev_ovr = None

    def __call__(self, rows: np.ndarray, start: int) -> None:
        try:
            if rows.shape[0] == 0:
                return
            en = rows[:, self.c_en] > 0
            e = np.where(en, rows[:, self.c_e], 0.0)
            self.sq += np.einsum("ij,ij->j", e, e)
            self.n += en.sum(axis=0)
            ovr = rows[:, self.c_ovr]
            prev = ovr[0] if self._prev_ovr is None else self._prev_ovr
            self.overruns += int(np.count_nonzero(np.diff(ovr, prepend=prev) > 0))
            self._prev_ovr = float(ovr[-1])
        except Exception:               # noqa: BLE001 - a metric must never touch the drain
            pass

    def take(self) -> list[float]:
        """RMS following error per axis [m] since the last call (NaN: no enabled cycle)."""
        out = [math.sqrt(s / n) if n else math.nan for s, n in zip(self.sq, self.n)]
        self.sq[:] = 0.0
        self.n[:] = 0
        return out


def snapshot(io, tap: RowTap) -> dict:
    """The figures the metrics serve, from the I/O process's own state (``io``: its
    :class:`~motorctl.app.daemon.io_side.IOSide`): nothing is read from the loop but what the
    status block and the drained rows already hold. Units: seconds, metres, rows."""
    from motorctl.app.daemon.status import ST
    from motorctl.loop.safety import FAULT_NAMES
    from motorctl.recorder.flight import _HIST_BIN_NS

    dr, ring = io.drainer, io.plan.ring
    hist = dr.loop_stats.turn
    cum = np.cumsum(hist)
    edges = [min(int(round(b * 1e9 / _HIST_BIN_NS)), hist.size) for b in TURNAROUND_BUCKETS_S]
    buckets = [int(cum[i - 1]) if i > 0 else 0 for i in edges]
    centres = (np.arange(hist.size) + 0.5) * (_HIST_BIN_NS * 1e-9)
    faults: dict[tuple[str, str], int] = {}
    for onset in dr.fault_onsets:
        for bit, name in FAULT_NAMES.items():
            if onset["bits"] & bit:
                key = (onset["axis"], name)
                faults[key] = faults.get(key, 0) + 1
    stream = io.motion.stream
    published = ring.published()
    return {
        "names": list(io.names),
        "cycles": int(published),
        "turnaround": {"buckets": buckets, "count": int(cum[-1]) if cum.size else 0,
                       "sum_s": float(np.dot(hist, centres))},
        "missed_periods": int(dr.overruns),
        "overruns": int(tap.overruns),
        "faults": faults,
        "fault_latched": [int(ring.status[i, ST["fault"]]) for i in range(len(io.names))],
        "fe_rms_m": tap.take(),
        "i2t_level": [float(ring.status[i, ST["i2t"]]) for i in range(len(io.names))],
        "underruns": int(stream.underruns()),
        "ring_depth": int(stream.depth()),
        "recorder_lag_rows": int(max(0, published - dr.written)),
        "rows_lost": int(dr.lost_rows),
        "period_s": float(io.plan.asm.loaded.period_s),
    }


def families(snap: dict) -> list:
    """The metric families of one snapshot (prometheus-client objects; empty before the first)."""
    from prometheus_client.core import (
        CounterMetricFamily,
        GaugeMetricFamily,
        HistogramMetricFamily,
    )
    if not snap:
        return []
    out = []
    t = snap["turnaround"]
    h = HistogramMetricFamily("motorctl_loop_turnaround_seconds",
                              "Time from the start of a cycle's read to the end of its write "
                              "(0.25 us bins, every drained cycle)")
    h.add_metric([], [(repr(b), c) for b, c in zip(TURNAROUND_BUCKETS_S, t["buckets"])]
                 + [("+Inf", t["count"])], t["sum_s"])
    out.append(h)
    out.append(CounterMetricFamily("motorctl_loop_cycles", "Cycles the loop has published",
                                   value=snap["cycles"]))
    out.append(CounterMetricFamily("motorctl_loop_missed_periods",
                                   "Loop periods skipped because a cycle ran late",
                                   value=snap["missed_periods"]))
    out.append(CounterMetricFamily("motorctl_loop_overruns",
                                   "Cycles after which one or more periods were skipped",
                                   value=snap["overruns"]))
    f = CounterMetricFamily("motorctl_faults", "Fault onsets by axis and cause",
                            labels=["axis", "cause"])
    for (axis, cause), n in sorted(snap["faults"].items()):
        f.add_metric([axis, cause], n)
    out.append(f)
    latched = GaugeMetricFamily("motorctl_axis_fault_latched",
                                "1 while the axis has a latched fault", labels=["axis"])
    rms = GaugeMetricFamily("motorctl_following_error_rms_meters",
                            "RMS following error over the enabled cycles of the last snapshot "
                            "interval (NaN: not enabled)", labels=["axis"])
    i2t = GaugeMetricFamily("motorctl_i2t_level_ratio",
                            "I2t accumulator over its trip level (1 trips)", labels=["axis"])
    for j, a in enumerate(snap["names"]):
        latched.add_metric([a], 1.0 if snap["fault_latched"][j] else 0.0)
        rms.add_metric([a], snap["fe_rms_m"][j])
        i2t.add_metric([a], snap["i2t_level"][j])
    out += [latched, rms, i2t]
    out.append(CounterMetricFamily("motorctl_stream_underruns",
                                   "Setpoint stream underruns (the loop ran dry and braked)",
                                   value=snap["underruns"]))
    out.append(GaugeMetricFamily("motorctl_stream_ring_depth_rows",
                                 "Setpoint rows written and not yet read by the loop",
                                 value=snap["ring_depth"]))
    out.append(GaugeMetricFamily("motorctl_recorder_lag_rows",
                                 "Cycles published by the loop and not yet in the run log",
                                 value=snap["recorder_lag_rows"]))
    out.append(GaugeMetricFamily("motorctl_recorder_lag_seconds",
                                 "The recorder's lag in loop time",
                                 value=snap["recorder_lag_rows"] * snap["period_s"]))
    out.append(CounterMetricFamily("motorctl_recorder_rows_lost",
                                   "Published rows overwritten in the ring before they were written",
                                   value=snap["rows_lost"]))
    return out


class MetricsLink(SnapshotLink):
    """The I/O process's end of the metrics process (:class:`.forked.SnapshotLink`: pid, sent,
    dropped, alive)."""

    def __init__(self, sock: socket.socket, pid: int, listen: str, tap: RowTap):
        super().__init__(sock, pid, SNAPSHOT_EVERY_S)
        self.listen, self.tap = listen, tap

    def snapshot(self, io, now: float) -> dict:
        return snapshot(io, self.tap)

    def report_line(self, text: str) -> str:
        if text == "ok":
            return f"motorctl: metrics on http://{self.listen}/metrics"
        return f"motorctl: warning: daemon.metrics.listen {self.listen}: not served ({text})"


def start_metrics(listen: str, layout, names, drainer) -> MetricsLink | None:
    """Fork the metrics process (I/O process, before its threads start) serving ``listen``
    ("host:port"); None with one warning line when the ``metrics`` extra is missing or the
    fork fails. The line saying it serves comes later (:meth:`MetricsLink.poll`)."""
    from motorctl.app.daemon.views import exposure_warning, missing_extra
    from motorctl.config import parse_listen
    line = missing_extra("prometheus_client", "metrics", "metrics")
    if line:
        sys.stderr.write(line + "\n")
        return None
    host, port = parse_listen(listen)
    if line := exposure_warning("daemon.metrics.listen", host):
        sys.stderr.write(line + "\n")
    forked = fork_helper("metrics", lambda sock, parent: metrics_main(sock, host, port, parent))
    if forked is None:
        return None
    tap = RowTap(layout, names)
    drainer.taps.append(tap)
    return MetricsLink(*forked, listen, tap)


class _Collector:
    """prometheus-client's collector over the newest snapshot (swapped whole, never mutated)."""

    def __init__(self):
        self.snap: dict = {}

    def collect(self):
        return iter(families(self.snap))


def metrics_main(sock: socket.socket, host: str, port: int, parent_pid: int) -> int:
    """The metrics process: serve ``/metrics`` on host:port until the link closes."""
    helper_started(parent_pid, METRICS_NICE)
    collector = _Collector()
    try:
        from prometheus_client import CollectorRegistry, start_http_server
        registry = CollectorRegistry(auto_describe=False)
        registry.register(collector)
        start_http_server(port, addr=host, registry=registry)
    except BaseException as exc:              # noqa: BLE001 - one line, no metrics
        sock.send((f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__).encode())
        return 0
    sock.send(b"ok")
    while True:
        try:
            data = sock.recv(1 << 20)
        except InterruptedError:
            continue
        except OSError:
            data = b""
        if not data:
            return 0
        collector.snap = pickle.loads(data)


__all__ = ["MetricsLink", "RowTap", "snapshot", "families", "start_metrics", "SNAPSHOT_EVERY_S"]
