"""Benchmark of ``motorctl fleet``: logs per second with 1 and 2 local workers of one thread
each (the speed-up), the per-log cost against ``identify``'s pipeline alone, and whether the
report flags each injected wear with the right parameter within 5 days of its onset and
nothing on the clean machines, even those given a single bad day.

Rerun:
    python benchmarks/bench_fleet.py                                  # 20 machines x 30 days x 1 log
    python benchmarks/bench_fleet.py --machines 20 --days 30 --logs-per-day 4   # the target, >= 2000 logs
    python benchmarks/bench_fleet.py --dir /tmp/fleet-bench --keep    # the logs kept for another run
    python benchmarks/bench_fleet.py --dir /tmp/fleet-bench --reuse --timing-only   # timings again on them
    python benchmarks/bench_fleet.py --machines 8 --days 20 --logs-per-day 2 --detection-only \
        --dir /tmp/fleet-bad --keep                                   # bad days and wear only (~3 min)
    python benchmarks/bench_fleet.py --dir /tmp/fleet-bad --reuse --detection-only  # the report again

Steps (each timed, wall and the load average printed, as other processes inflate wall time):

1. the simulated fleet (:func:`motorctl.fleet.simulate.simulate_fleet`: 3 s logs, 2
   processes; the first three machines worn: Coulomb friction +1 %/day, a 6 N cogging force,
   an encoder interpolation error growing 0.4 µm/day, from a third of the period on; the next
   three clean machines one bad day each (:func:`motorctl.fleet.simulate.default_bad_days`:
   Coulomb friction +25 %, viscous friction +25 %, mass +10 %, at 1/2, 2/3 and 5/6 of the
   period), unless ``--no-bad-days``);
2. ``identify``'s pipeline alone, in this process (:func:`motorctl.ident.data.load_record` +
   :func:`motorctl.ident.pipeline.identify_record`, as ``motorctl identify --no-closed-loop``
   after its start-up) on ``--sample`` logs: the median seconds per log;
3. ``--sample`` logs through ``run_fleet`` with 1, then 2, local workers (a fresh output
   folder each, the workers' imports done first): logs/s of the job, the workers' CPU seconds
   per log (``time.process_time`` of each worker process, before and after), the cluster's
   start-up;
4. the whole fleet with 2 workers (``--reuse``: only the logs not yet in the dataset), then the
   report: each worn machine's alarm (parameter, the change point's date against the onset)
   and the report replayed day by day (on the logs up to each day): the first day it raises
   each wear's alarm (the detection delay), and the days on which it raises any alarm on a
   clean machine (false alarms: with a bad day, and without).

``--detection-only`` skips steps 2 and 3.
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path


def _load() -> str:
    try:
        return "load %.1f %.1f %.1f" % os.getloadavg()
    except OSError:
        return "load ?"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--machines", type=int, default=20)
    ap.add_argument("--days", type=int, default=30)
    ap.add_argument("--logs-per-day", type=int, default=1)
    ap.add_argument("--duration", type=float, default=3.0, help="program seconds per log")
    ap.add_argument("--sample", type=int, default=40, help="logs for the per-log cost and the 1/2-worker runs")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--dir", default=None, help="working folder (default: a temporary one)")
    ap.add_argument("--keep", action="store_true", help="keep the logs and the dataset")
    ap.add_argument("--reuse", action="store_true", help="use the logs already in --dir (its fleet_truth.json)")
    ap.add_argument("--timing-only", action="store_true", help="steps 1-3 only (no whole-fleet run, no report)")
    ap.add_argument("--detection-only", action="store_true", help="steps 1 and 4 only (no timings)")
    ap.add_argument("--no-bad-days", action="store_true", help="no bad day on the clean machines")
    a = ap.parse_args(argv)

    from motorctl.fleet.simulate import simulate_fleet

    work = Path(a.dir or tempfile.mkdtemp(prefix="fleet-bench-"))
    logs_dir = work / "logs"
    t = time.monotonic()
    if a.reuse:
        import json
        truth = json.loads((logs_dir / "fleet_truth.json").read_text())
        a.machines, a.days, a.logs_per_day = len(truth["machines"]), truth["days"], truth["logs_per_day"]
        a.duration = truth["duration_s"]
    print(f"# bench_fleet: {a.machines} machines x {a.days} days x {a.logs_per_day} logs of {a.duration:g} s; "
          f"{os.cpu_count()} cores; {_load()}", flush=True)
    if not a.reuse:
        truth = simulate_fleet(logs_dir, a.machines, a.days, a.logs_per_day, duration_s=a.duration, seed=a.seed,
                               workers=2, bad_days=[] if a.no_bad_days else None)
    logs = truth["logs"]
    print(f"{'reused' if a.reuse else 'simulated'} {len(logs)} logs in {time.monotonic() - t:.1f} s (2 processes); "
          f"{_load()}", flush=True)

    if not a.detection_only:
        _timings(a, logs, work)
    if a.timing_only:
        return 0
    ok = _detection(a, truth, logs_dir, work)
    if not a.keep and a.dir is None:
        shutil.rmtree(work, ignore_errors=True)
    return 0 if ok else 1


def _timings(a, logs, work) -> None:
    """Steps 2 and 3: identify alone, then the sample through 1 and 2 workers."""
    from motorctl.fleet.jobs import fleet_client, run_fleet

    # the per-log cost of identify's pipeline alone (in this process, after its imports)
    from motorctl.ident.data import load_record
    from motorctl.ident.pipeline import identify_record
    step = max(1, len(logs) // a.sample)
    sample = logs[::step][: a.sample]
    identify_record(load_record(sample[0]))            # imports and first-call costs out of the timing
    per, cpu = [], []
    for p in sample:
        t, c = time.perf_counter(), time.process_time()
        identify_record(load_record(p))
        per.append(time.perf_counter() - t)
        cpu.append(time.process_time() - c)
    ident_s, ident_cpu = statistics.median(per), statistics.median(cpu)
    print(f"identify alone: median {ident_s:.3f} s/log wall, {ident_cpu:.3f} CPU-s/log, over {len(per)} logs "
          f"({1 / ident_s:.2f} logs/s); {_load()}", flush=True)

    rates, cpus = {}, {}
    for w in (1, 2):
        out = work / f"out-{w}w"
        shutil.rmtree(out, ignore_errors=True)
        t = time.monotonic()
        with fleet_client(workers=w) as client:
            up = time.monotonic() - t
            # the workers' imports out of the timing, as identify alone's first call is
            client.run(lambda: __import__("motorctl.ident.pipeline"))
            c0 = sum(client.run(time.process_time).values())
            s = run_fleet(sample, out, client=client)
            cpus[w] = (sum(client.run(time.process_time).values()) - c0) / max(s["identified"], 1)
        rates[w] = s["identified"] / s["seconds"]
        print(f"fleet identify, {w} worker(s): {s['identified']} logs in {s['seconds']:.1f} s = {rates[w]:.2f} logs/s, "
              f"{cpus[w]:.3f} worker CPU-s/log ({up:.1f} s cluster start); {_load()}", flush=True)
    print(f"speed-up 2 vs 1 worker: {rates[2] / rates[1]:.2f}x; per-log cost on 1 worker vs identify alone: "
          f"{(1 / rates[1]) / ident_s:.2f}x wall, {cpus[1] / ident_cpu:.2f}x CPU", flush=True)


def _detection(a, truth, logs_dir, work) -> bool:
    """Step 4: the whole fleet, the report, the replay day by day. True: every wear flagged
    within 5 days of its onset and no alarm on a clean machine on any day."""
    import datetime as dt

    from motorctl.fleet.jobs import run_fleet
    from motorctl.fleet.report import analyse, load_rows, write_report
    from motorctl.fleet.simulate import WEAR_PARAMETER
    out = work / "out"
    if not a.reuse:
        shutil.rmtree(out, ignore_errors=True)
    s = run_fleet([logs_dir], out, workers=2)
    print(f"whole fleet, 2 workers: {s['identified']} logs in {s['seconds']:.1f} s = "
          f"{s['identified'] / s['seconds']:.2f} logs/s ({s['skipped']} already in the dataset), "
          f"{len(s['failed'])} failed; {_load()}", flush=True)
    for u, m in s["failed"][:5]:
        print(f"  failed {u}: {m}")
    t = time.monotonic()
    r = write_report(out, work / "report")
    print(f"report: {time.monotonic() - t:.1f} s; {r['summary']}", flush=True)
    from motorctl.fleet.jobs import part_files
    parts = part_files(out)
    print(f"dataset: {len(parts)} part files in {len({p.parent for p in parts})} partitions (machine=/month=)", flush=True)

    worn = {w["machine"]: w for w in truth["wear"]}
    bad = {b["machine"]: b for b in truth.get("bad_days", [])}
    ok = True
    for f in r["alarms"]:
        if f["machine"] not in worn:
            ok = False
            print(f"FALSE ALARM {f['machine']} {f['axis']} {f['parameter']} from {f['when'][:10]} (z {f['change']['z']:.1f})")
    rows = load_rows(out)
    t0 = min(x["time"] for x in rows)
    # the report on the logs up to each day: {day: {(machine, parameter)}} of its alarms
    t = time.monotonic()
    day0 = dt.datetime.combine(t0.date(), dt.time(), t0.tzinfo)
    raised = {}
    for d in range(1, a.days):
        upto = day0 + dt.timedelta(days=d + 1)
        res = analyse([x for x in rows if x["time"] < upto])
        raised[d] = {(f["machine"], f["parameter"]) for f in res["findings"] if f["alarm"]}
    print(f"replay: the report on the logs up to each of days 1..{a.days - 1}: {time.monotonic() - t:.1f} s", flush=True)
    for m, w in worn.items():
        want = WEAR_PARAMETER[w["kind"]]
        got = [f for f in r["alarms"] if f["machine"] == m and f["parameter"] == want]
        other = [f["parameter"] for f in r["alarms"] if f["machine"] == m and f["parameter"] != want]
        if not got:
            ok = False
            print(f"MISSED {m} {w['kind']} ({want}) from day {w['onset_day']}; other alarms: {other}")
            continue
        day = (dt.datetime.fromisoformat(got[0]["when"]) - t0).total_seconds() / 86400
        # day by day from the onset: the first day the report on the logs so far raises it
        first = next((d for d in range(max(w["onset_day"], 1), a.days) if (m, want) in raised[d]), None)
        late = None if first is None else first - w["onset_day"]
        ok &= late is not None and late <= 5
        kept = [d for d in raised if first is not None and d >= first]
        on = sum((m, want) in raised[d] for d in kept)
        early = sorted(d for d in raised if d < w["onset_day"] and any(mm == m for mm, _ in raised[d]))
        print(f"{m} {w['kind']}: alarm on {want} ({got[0]['change']['shape']}, z {got[0]['change']['z']:.0f}), change "
              f"point day {day:.1f} (onset {w['onset_day']}); first raised on day {first} = onset + {late} days, "
              f"then on {on} of the {len(kept)} days from it; alarms before the onset: {early or 'none'}; "
              f"other alarms on it: {other or 'none'}")
    clean = sorted(set(truth["machines"]) - set(worn))
    print(f"clean machines with an alarm in the final report: "
          f"{sorted({f['machine'] for f in r['alarms'] if f['machine'] in clean}) or 'none'} of {len(clean)}")
    for m in clean:
        days_on = {d: sorted(p for mm, p in raised[d] if mm == m) for d in raised}
        days_on = {d: p for d, p in days_on.items() if p}
        ok &= not days_on
        b = bad.get(m)
        what = (f"bad day {b['day']} ({b['parameter']} x{b.get('factor', '?')})" if b else "no bad day")
        if b or days_on:
            shown = ", ".join(f"{d}: {'+'.join(p)}" for d, p in days_on.items())
            print(f"{m} {what}: alarm on {len(days_on)} of {len(raised)} replayed days" + (f" ({shown})" if shown else ""))
    n_clean_days = sum(1 for d in raised for m in clean if any(mm == m for mm, _ in raised[d]))
    print(f"false alarms: {n_clean_days} machine-days with an alarm on the {len(clean)} clean machines "
          f"({len(bad)} of them with a bad day) over {len(raised)} replayed days")
    print("RESULT:", "all wear flagged within 5 days of onset, no false alarm" if ok else "FAILED (see above)")
    return ok


if __name__ == "__main__":
    sys.exit(main())
