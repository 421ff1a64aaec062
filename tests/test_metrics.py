"""Prometheus metrics (docs/metrics.md): one daemon on the simulated gantry with
``daemon.metrics`` on a loopback port, read through a real HTTP GET and parsed with
prometheus-client's own parser; every value checked against ``motorctl status --json`` of the
same daemon (counts and the daemon's own figures, never the host's wall time)."""

from __future__ import annotations

import json
import time
import urllib.request

import pytest

from harness import free_port
from test_daemon_helpers import ctl, make_config, running_daemon, wait_for

parser = pytest.importorskip("prometheus_client.parser")

#: GETs of /metrics a wait may spend (the I/O process sends a snapshot every second)
MAX_SCRAPES = 300


@pytest.fixture(scope="module")
def daemon(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("metrics")
    port = free_port()
    with running_daemon(tmp, fault_axis=True,
                        extra_daemon={"metrics": {"listen": f"127.0.0.1:{port}"}}) as d:
        d.url = f"http://127.0.0.1:{port}/metrics"
        yield d


def _scrape(url: str) -> dict | None:
    """{(name, labels...): value} of one GET (None while the metrics process is not listening)."""
    try:
        text = urllib.request.urlopen(url, timeout=10).read().decode()
    except OSError:
        return None
    out = {}
    for fam in parser.text_string_to_metric_families(text):
        for s in fam.samples:
            out[(s.name, *sorted(s.labels.items()))] = s.value
        out[("type", fam.name)] = fam.type
    return out


def _status(d) -> dict:
    r = ctl(d.sock, "status", "--json")
    assert r.returncode == 0, r.stderr
    return json.loads(r.stdout)


def _until(d, pred, what: str) -> dict:
    """Scrape until ``pred(metrics)`` holds, at most MAX_SCRAPES GETs."""
    last = None
    for _ in range(MAX_SCRAPES):
        last = _scrape(d.url)
        if last is not None and pred(last):
            return last
        time.sleep(0.1)                             # pace the GETs
    raise AssertionError(f"{what}: not seen in {MAX_SCRAPES} scrapes (last: {last!r})")


def test_metrics_parse_and_agree_with_status(daemon):
    d = daemon
    assert ctl(d.sock, "start", "Y").returncode == 0
    assert ctl(d.sock, "start", "X").returncode == 0
    wait_for(lambda: _status(d)["axes"]["X"]["phase"] == "tracking", 20, "X tracking")
    r = ctl(d.sock, "inject", "X", "push", "--force-n", "1500", "--cycles", "20")
    assert r.returncode == 0, r.stderr
    wait_for(lambda: _status(d)["axes"]["X"]["fault_bits"], 20, "X faulted")
    st0 = _status(d)
    fault = st0["axes"]["X"]["fault"]
    cause = fault.split(" (")[0]                   # e.g. "following error"
    key = ("motorctl_faults_total", ("axis", "X"), ("cause", cause))
    m = _until(d, lambda m: m.get(key, 0) >= 1
               and m.get(("motorctl_loop_cycles_total",), 0) > st0["loop"]["cycles"],
               f"the fault {fault!r} in /metrics")
    st = _status(d)                               # after the scrape: its counters are >= the scrape's

    # names and units by the conventions
    assert m[("type", "motorctl_loop_turnaround_seconds")] == "histogram"
    for name in ("motorctl_loop_cycles", "motorctl_loop_missed_periods", "motorctl_loop_overruns",
                 "motorctl_faults", "motorctl_stream_underruns", "motorctl_recorder_rows_lost"):
        assert m[("type", name)] == "counter", name
    for name in ("motorctl_following_error_rms_meters", "motorctl_i2t_level_ratio",
                 "motorctl_stream_ring_depth_rows", "motorctl_recorder_lag_rows",
                 "motorctl_recorder_lag_seconds", "motorctl_axis_fault_latched"):
        assert m[("type", name)] == "gauge", name

    # the fault: one onset, by its cause, the same one status names; X latched, Y not
    assert m[key] == 1 and sum(v for k, v in m.items() if k[0] == "motorctl_faults_total") == 1
    assert st["axes"]["X"]["fault"] == fault and not st["axes"]["Y"]["fault_bits"]
    assert m[("motorctl_axis_fault_latched", ("axis", "X"))] == 1
    assert m[("motorctl_axis_fault_latched", ("axis", "Y"))] == 0

    # counters: the scrape's snapshot precedes the status read
    cycles = m[("motorctl_loop_cycles_total",)]
    assert st0["loop"]["cycles"] < cycles <= st["loop"]["cycles"]
    assert m[("motorctl_loop_missed_periods_total",)] <= st["loop"]["overruns"]
    assert m[("motorctl_loop_overruns_total",)] <= m[("motorctl_loop_missed_periods_total",)]
    assert m[("motorctl_recorder_rows_lost_total",)] == st["log"]["lost_rows"] == 0
    assert m[("motorctl_stream_underruns_total",)] == st["motion"]["underruns"] == 0
    assert m[("motorctl_stream_ring_depth_rows",)] == st["motion"]["ring_depth"] == 0
    lag = m[("motorctl_recorder_lag_rows",)]
    assert 0 <= lag <= cycles
    assert m[("motorctl_recorder_lag_seconds",)] == pytest.approx(lag / st["loop"]["rate_hz"])

    # the turnaround histogram: cumulative, +Inf = count = the cycles drained (<= published);
    # status's turnaround_p50_us (read after the scrape, over N >= n cycles) lies in the buckets
    # of the scrape's quantiles (0.5 N - (N - n)) / n and 0.5 N / n: the p50 of N samples, n of
    # them the scrape's, whatever the other N - n were
    h = sorted(((float(dict(k[1:])["le"]), v) for k, v in m.items()
                if k[0] == "motorctl_loop_turnaround_seconds_bucket"))
    assert h[-1][0] == float("inf") and len(h) >= 10
    counts = [v for _, v in h]
    assert counts == sorted(counts)
    n = m[("motorctl_loop_turnaround_seconds_count",)]
    assert counts[-1] == n and 0 < n <= cycles
    mean = m[("motorctl_loop_turnaround_seconds_sum",)] / n
    assert 0 < mean < 1.0 / st["loop"]["rate_hz"] * 10
    p50, n_st = st["loop"]["turnaround_p50_us"] * 1e-6, st["loop"]["cycles"]
    assert n <= n_st
    hi_le = next(le for le, c in h if c >= 0.5 * n_st)
    lo_le = next(le for le, c in h if c >= 0.5 * n_st - (n_st - n))
    below = [le for le, _ in h if le < lo_le]
    assert p50 <= hi_le * (1 + 1e-9) and (not below or p50 > below[-1] * 0.9)

    # per axis: Y tracks (an RMS error below its peak), X faulted (no enabled cycle: NaN)
    rms_y = m[("motorctl_following_error_rms_meters", ("axis", "Y"))]
    assert 0 < rms_y <= st["axes"]["Y"]["following_error_peak_m"]
    for a in ("X", "Y"):
        lvl = m[("motorctl_i2t_level_ratio", ("axis", a))]
        assert 0 <= lvl < 1 and 0 <= st["axes"][a]["i2t_level"] < 1


def test_a_bad_metrics_address_is_one_line_and_exit_2(tmp_path, capsys):
    import yaml

    from motorctl.cli import main
    cfg = make_config(tmp_path)
    d = yaml.safe_load(cfg.read_text())
    d["daemon"]["metrics"] = {"listen": "127.0.0.1:http"}
    cfg.write_text(yaml.safe_dump(d))
    assert main(["check-config", str(cfg)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "daemon.metrics.listen" in err and str(cfg) in err, err


def test_a_view_process_behind_handles_a_bounded_number_of_messages_per_wake():
    """The view process's reader takes at most LINK_MESSAGES_PER_WAKE messages of the link per
    wake, so requests get their turn however much waits (docs/daemon.md, Views are guests)."""
    import pickle
    import socket

    from motorctl.app.daemon.views import LINK_MESSAGES_PER_WAKE, VIEW_NICE, Views

    class _Scope:
        def meta(self):
            return {}

    class _Loop:
        stopped = False

        def stop(self):
            self.stopped = True

    assert VIEW_NICE == 0
    a, b = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    with a, b:
        n = 3 * LINK_MESSAGES_PER_WAKE + 5
        for j in range(n):
            a.send(pickle.dumps(("frame", {"seq": j})))
        b.setblocking(False)
        v, loop = Views(_Scope()), _Loop()
        seen = []
        v.on_frame = seen.append
        calls = 0
        while len(seen) < n:
            v.on_readable(b, loop)
            calls += 1
            assert len(seen) <= calls * LINK_MESSAGES_PER_WAKE
        assert calls == 4 and [f["seq"] for f in seen] == list(range(n)) and not loop.stopped
