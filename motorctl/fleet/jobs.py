"""Identification over many machines' run logs on Dask: ``motorctl fleet identify``.

The job, for SOURCES (run logs or folders of them, local paths or fsspec URLs):

1. :func:`collect_sources` lists the logs (a folder: every ``*.mclog`` and ``*.log`` file under
   it, recursively, in sorted order).
2. One **scan** task per log (:func:`scan_log`): the file's SHA-256 (its content hash, read in
   1 MiB blocks), its header (``machine_id``, ``started``, the axes) and its windows. A log
   whose hash is already in the output folder (or seen earlier in the same run) is skipped
   there: the job is idempotent.
3. One **window** task per axis and window of each new log (:func:`identify_window`): the
   record of ``motorctl identify`` (:func:`motorctl.ident.data.load_record`), cut to the
   window, through the same pipeline (:func:`motorctl.ident.pipeline.identify_record`), verdict
   included. Without ``window_s`` a log is one window (its longest run of enabled cycles, as
   ``identify`` takes it); with it, that run is split into ⌊T/window_s⌋ equal windows (each at
   least ``window_s`` long, shorter than 2·window_s), so an hour-long log gives many points in
   time and many tasks.
4. Results come back as they complete (``distributed.as_completed``); a log's rows are kept
   until all its windows are done, then written together with the other finished logs' as one
   Parquet file ``part-*.parquet`` (pyarrow; written to a temporary name and renamed, so a
   reader never sees half a file) every :data:`FLUSH_ROWS` rows or :data:`FLUSH_S` seconds,
   and at the end. A log is either wholly in the dataset or not at all.

Failures: a log that cannot be read or identified (a damaged file, a fit refused by the
pipeline: :class:`~motorctl.recorder.runlog.LogError`, :class:`~motorctl.inputs.InputError`,
``OSError``) is returned by its task as an error, reported by name and left out of the
dataset (so it is tried again by the next run); any other exception is retried by Dask
(``retries``), and a worker that dies mid-task (killed, out of memory) has its tasks
rescheduled on the others (the scheduler's ``allowed-failures``); a task that still fails is
reported by its log's name and skipped. The job itself is never lost to one log.

Dask: a ``LocalCluster`` (processes, one thread each, ``workers`` of them, each bounded by
``memory_limit``: the nanny restarts a worker beyond it) or an existing scheduler
(``scheduler="tcp://HOST:8786"``; its workers need motorctl installed and the logs' URLs
reachable). Inside a worker the effect search runs on one thread
(:data:`motorctl.ident.select.SEARCH_THREADS`; its result does not depend on it).
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import math
import os
import tempfile
import time
from contextlib import contextmanager
from pathlib import Path
from urllib.parse import urlsplit

# a parameter's interval: value ± Z95·σ̂, σ̂ identify's stated theta_std (sampling and model error)
from motorctl.ident.uncertainty import Z95
from motorctl.inputs import InputError

#: the nominal parameters written (physical name, index in θ): values g·θ with g the force gain
#: A1 [N/V] when the log's header gives it (else 1, the values in V: ``force_unit``)
PARAMETERS = (("mass_kg", 0), ("viscous_N_s_per_m", 1), ("coulomb_N", 2), ("offset_N", 3))
#: run-log file names looked for in a folder
LOG_SUFFIXES = (".mclog", ".log")
#: rows (windows) gathered before a part file is written, and the longest wait [s] between two
FLUSH_ROWS = 256
FLUSH_S = 10.0
#: retries of a task that raised (not a data error) or whose worker died
RETRIES = 2
#: URL schemes accepted for --scheduler
SCHEDULER_SCHEMES = ("tcp", "tls")


# ---------------------------------------------------------------------------- the schema
def schema():
    """The dataset's pyarrow schema: one row per log window (docs/fleet.md, "The dataset")."""
    import pyarrow as pa
    fields = [
        ("machine", pa.string()), ("axis", pa.string()),
        ("time", pa.timestamp("us", tz="UTC")), ("started", pa.timestamp("us", tz="UTC")),
        ("window", pa.int32()), ("window_t0_s", pa.float64()), ("window_t1_s", pa.float64()),
        ("samples", pa.int64()), ("force_unit", pa.string()), ("gain_N_per_V", pa.float64()),
    ]
    for name, _ in PARAMETERS:
        fields += [(name, pa.float64()), (f"{name}_lo", pa.float64()), (f"{name}_hi", pa.float64())]
    fields += [
        ("n_theta", pa.int32()),
        ("effects_named", pa.list_(pa.string())),
        ("effects", pa.list_(pa.struct([("name", pa.string()), ("parameter", pa.string()),
                                        ("value", pa.float64())]))),
        ("verdict_structured", pa.bool_()), ("verdict", pa.string()),
        ("heldout_rms_nominal", pa.float64()), ("heldout_rms", pa.float64()),
        ("log_path", pa.string()), ("log_sha256", pa.string()),
    ]
    return pa.schema(fields)


# ---------------------------------------------------------------------------- sources
def _is_url(s: str) -> bool:
    return "://" in s


def collect_sources(sources) -> list[str]:
    """The run logs named by ``sources`` (files, folders, fsspec URLs of either), each once, in
    the order given (a folder's logs sorted).

    Raises:
        InputError: a source that does not exist (or a folder holding no log).
    """
    import fsspec
    out, seen = [], set()
    for src in sources:
        src = str(src)
        try:
            fs, path = fsspec.core.url_to_fs(src)
        except (ValueError, ImportError) as exc:
            raise InputError(f"{src}: cannot open this source ({exc})") from None
        try:
            if fs.isdir(path):
                found = sorted(p for p in fs.find(path) if p.endswith(LOG_SUFFIXES))
                if not found:
                    raise InputError(f"{src}: no run log (*.mclog, *.log) in this folder")
                names = [fs.unstrip_protocol(p) if _is_url(src) else p for p in found]
            elif fs.isfile(path):
                names = [src]
            else:
                raise InputError(f"{src}: no such file or folder")
        except OSError as exc:
            raise InputError(f"{src}: cannot list this source ({exc})") from None
        for n in names:
            if n not in seen:
                seen.add(n)
                out.append(n)
    return out


@contextmanager
def local_copy(url: str):
    """A local path for ``url``: the path itself for a local file, else a temporary copy
    (removed on exit). Raises OSError: it cannot be read."""
    if not _is_url(url) or url.startswith("file://"):
        yield url[len("file://"):] if url.startswith("file://") else url
        return
    import fsspec
    fd, tmp = tempfile.mkstemp(suffix=".mclog", prefix="fleet-")
    try:
        with os.fdopen(fd, "wb") as out, fsspec.open(url, "rb") as src:
            while block := src.read(1 << 20):
                out.write(block)
        yield tmp
    finally:
        os.unlink(tmp)


def content_hash(url: str) -> str:
    """SHA-256 (hex) of the file's bytes, read in 1 MiB blocks. Raises OSError."""
    import fsspec
    h = hashlib.sha256()
    with fsspec.open(url, "rb") as fh:
        while block := fh.read(1 << 20):
            h.update(block)
    return h.hexdigest()


# ---------------------------------------------------------------------------- tasks
def _iso_utc(text) -> _dt.datetime | None:
    if not isinstance(text, str):
        return None
    try:
        t = _dt.datetime.fromisoformat(text)
    except ValueError:
        return None
    return (t if t.tzinfo else t.replace(tzinfo=_dt.timezone.utc)).astimezone(_dt.timezone.utc)


def windows_of(header: dict, n_rows: int, window_s: float | None) -> list[tuple[float | None, float | None]]:
    """The windows [t0, t1) [s of the log's time] a log is split into: [(None, None)] (the
    whole record) without ``window_s``; else ⌊T/window_s⌋ equal windows of the program's span
    T (the header's ``program_start_s`` .. ``program_end_s``, else the whole log)."""
    if not window_s:
        return [(None, None)]
    ts = float(header.get("period_s") or 0.0)
    t0 = header.get("program_start_s")
    t1 = header.get("program_end_s")
    t0 = float(t0) if isinstance(t0, (int, float)) and not isinstance(t0, bool) else 0.0
    t1 = float(t1) if isinstance(t1, (int, float)) and not isinstance(t1, bool) else n_rows * ts
    n = max(1, int((t1 - t0) // float(window_s)))
    w = (t1 - t0) / n
    return [(t0 + i * w, t0 + (i + 1) * w) for i in range(n)]


def scan_log(url: str, window_s: float | None = None) -> dict:
    """Task: a log's content hash, machine, start time, axes and windows (:func:`windows_of`).

    Returns:
        {"url", "sha256", "machine", "started" (ISO, UTC), "axes", "windows": [(t0, t1)]} or
        {"url", "error"} when the file cannot be read or is not a run log.
    """
    from motorctl.recorder.runlog import LogError, open_log
    try:
        sha = content_hash(url)
        with local_copy(url) as path:
            lf = open_log(path)
    except (LogError, InputError, OSError) as exc:
        return {"url": url, "error": _one_line(exc, url)}
    h = lf.header
    machine = h.get("machine_id") or (h.get("config") or {}).get("machine_id") or "unknown"
    started = _iso_utc(h.get("started"))
    if started is None:
        return {"url": url, "error": f"{url}: the header's 'started' is {h.get('started')!r}, not an ISO time"}
    if not lf.axes:
        return {"url": url, "error": f"{url}: the header lists no axes"}
    return {"url": url, "sha256": sha, "machine": str(machine), "started": started.isoformat(),
            "axes": list(lf.axes), "windows": windows_of(h, lf.n_rows, window_s)}


def _one_line(exc: BaseException, url: str) -> str:
    msg = " ".join(str(exc).split()) or type(exc).__name__
    return msg if url in msg else f"{url}: {msg}"


def _effect_values(effects: list) -> list[dict]:
    """identify's effects as (name, parameter, value) rows: scalars as they are, lists as
    ``key[i]``; anything not a finite number is left out."""
    out = []
    for e in effects:
        for key, v in (e.get("parameters") or {}).items():
            items = [(key, v)] if not isinstance(v, (list, tuple)) else [(f"{key}[{i}]", x) for i, x in enumerate(v)]
            for k, x in items:
                if isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(float(x)):
                    out.append({"name": e["name"], "parameter": k, "value": float(x)})
    return out


def identify_window(url: str, sha256: str, machine: str, started: str, axis: str, window: int,
                    t0: float | None, t1: float | None) -> dict:
    """Task: identify one axis and window of a log with ``motorctl identify``'s pipeline.

    Args:
        url: the log. sha256: its content hash. machine, started (ISO): from its header.
        axis: the axis. window: the window's index; t0, t1: its span [s of the log's time]
            (None: the whole record).
    Returns:
        One row of :func:`schema` (a dict), or {"url", "error"} when the record cannot be read
        or the pipeline refuses it (one line naming the log).
    """
    import numpy as np

    from motorctl.ident import select
    from motorctl.ident.data import Record, check_record, load_record
    from motorctl.ident.pipeline import identify_record, values_from
    from motorctl.recorder.runlog import LogError
    select.SEARCH_THREADS = 1          # one thread per worker (the result does not depend on it)
    try:
        with local_copy(url) as path:
            rec = load_record(path, axis=axis)
        rec.source = url
        if t0 is not None:
            keep = (rec.t >= t0) & (rec.t < t1)
            rec = Record(t=rec.t[keep], y=rec.y[keep], u=rec.u[keep],
                         yd=None if rec.yd is None else rec.yd[keep], gain=rec.gain,
                         source=f"{url} [{t0:.3f}, {t1:.3f}) s", axis=rec.axis, header=rec.header,
                         labels=rec.labels)
            check_record(rec)
        idf, s = identify_record(rec)
    except (LogError, InputError, OSError) as exc:
        return {"url": url, "error": _one_line(exc, url)}
    src = values_from(idf)
    nt = idf.n_theta
    coef, std = np.asarray(src.final.fit.coef[:nt], float), np.asarray(s["augmented"]["theta_std"], float)
    g = float(rec.gain) if rec.gain else 1.0
    start = _iso_utc(started)
    offset = float(rec.t[0]) if t0 is None else float(t0)
    row = {"machine": machine, "axis": rec.axis or axis,
           "time": start + _dt.timedelta(seconds=offset), "started": start,
           "window": int(window), "window_t0_s": float(rec.t[0]), "window_t1_s": float(rec.t[-1]),
           "samples": int(rec.n), "force_unit": "N" if rec.gain else "V", "gain_N_per_V": rec.gain,
           "n_theta": int(nt)}
    for name, i in PARAMETERS:
        v, e = g * coef[i], g * std[i]
        row[name], row[f"{name}_lo"], row[f"{name}_hi"] = float(v), float(v - Z95 * e), float(v + Z95 * e)
    row["effects_named"] = [e["name"] for e in s["effects"]]
    row["effects"] = _effect_values(s["effects"])
    res = s.get("residual") or {}
    row["verdict_structured"] = bool(res.get("structured"))
    row["verdict"] = str(res.get("text", ""))
    row["heldout_rms_nominal"] = float(s["nominal"]["heldout_rms"])
    row["heldout_rms"] = float(s["augmented"]["heldout_rms"])
    row["log_path"], row["log_sha256"] = url, sha256
    return row


# ---------------------------------------------------------------------------- the dataset
def part_files(out_dir) -> list[Path]:
    return sorted(Path(out_dir).glob("part-*.parquet"))


def read_dataset(out_dir, columns=None):
    """The dataset in ``out_dir`` as one pyarrow Table (:func:`schema`), or None when it holds
    no part file.

    Raises:
        InputError: a part file that cannot be read (one line naming it).
    """
    import pyarrow as pa
    import pyarrow.parquet as pq
    files = part_files(out_dir)
    if not files:
        return None
    tables = []
    for f in files:
        try:
            tables.append(pq.read_table(f, columns=columns, schema=schema()))
        except (OSError, pa.ArrowException) as exc:
            raise InputError(f"{f}: not a readable Parquet part of a fleet dataset ({exc})") from None
    return pa.concat_tables(tables)


def done_hashes(out_dir) -> set:
    """Content hashes of the logs already in the dataset in ``out_dir``."""
    t = read_dataset(out_dir, columns=["log_sha256"])
    return set() if t is None else set(t.column("log_sha256").to_pylist())


class PartWriter:
    """Rows to Parquet part files in ``out_dir``: :meth:`add` gathers a finished log's rows,
    :meth:`flush` writes them as one file (temporary name, then renamed)."""

    def __init__(self, out_dir, flush_rows: int = FLUSH_ROWS, flush_s: float = FLUSH_S):
        self.dir = Path(out_dir)
        self.rows: list[dict] = []
        self.flush_rows, self.flush_s = int(flush_rows), float(flush_s)
        self.last = time.monotonic()
        self.stamp = _dt.datetime.now(_dt.timezone.utc).strftime("%Y%m%dT%H%M%S") + f"-{os.getpid()}"
        self.n = 0
        self.written = 0
        self.files: list[str] = []

    def add(self, rows: list[dict]) -> None:
        self.rows.extend(rows)
        if len(self.rows) >= self.flush_rows or time.monotonic() - self.last >= self.flush_s:
            self.flush()

    def flush(self) -> None:
        import pyarrow as pa
        import pyarrow.parquet as pq
        self.last = time.monotonic()
        if not self.rows:
            return
        table = pa.Table.from_pylist(self.rows, schema=schema())
        name = self.dir / f"part-{self.stamp}-{self.n:05d}.parquet"
        tmp = self.dir / f".{name.name}.tmp"
        pq.write_table(table, tmp)
        os.replace(tmp, name)
        self.n += 1
        self.written += len(self.rows)
        self.files.append(str(name))
        self.rows = []


# ---------------------------------------------------------------------------- the job
def check_scheduler(url: str) -> str:
    """``tcp://HOST:PORT`` (or ``tls://``) checked. Raises InputError naming what is wrong."""
    try:
        parts = urlsplit(url)
        port = parts.port
    except ValueError as exc:
        raise InputError(f"--scheduler {url!r}: not a scheduler address ({exc}); e.g. tcp://host:8786") from None
    if parts.scheme not in SCHEDULER_SCHEMES or not parts.hostname or port is None or parts.path not in ("", "/"):
        raise InputError(f"--scheduler {url!r}: not a scheduler address; "
                         f"{' or '.join(s + '://HOST:PORT' for s in SCHEDULER_SCHEMES)}, e.g. tcp://host:8786")
    return url


def default_workers() -> int:
    """The cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:
        return os.cpu_count() or 1


@contextmanager
def fleet_client(scheduler: str | None = None, workers: int | None = None, processes: bool = True,
                 memory_limit="auto"):
    """A ``distributed.Client``: of the scheduler at ``scheduler``, else of a LocalCluster of
    ``workers`` (default: the cores) single-thread workers (processes unless ``processes`` is
    False), each bounded by ``memory_limit`` ('auto': the machine's memory over the workers;
    bytes or '2GiB'), listening on 127.0.0.1 only, no dashboard.

    Raises:
        InputError: a bad scheduler address, or a scheduler that cannot be reached in 10 s.
    """
    import logging

    from distributed import Client, LocalCluster
    if scheduler:
        check_scheduler(scheduler)
        try:
            client = Client(scheduler, timeout="10s")
        except (OSError, TimeoutError) as exc:
            raise InputError(f"--scheduler {scheduler}: cannot reach the scheduler "
                             f"({' '.join(str(exc).split())[:160]})") from None
        try:
            yield client
        finally:
            client.close()
        return
    n = int(workers or default_workers())
    if n < 1:
        raise InputError(f"--workers {n}: at least 1")
    # processes: TCP on 127.0.0.1 only; threads (processes=False): in-process transport, no socket
    where = {"host": "127.0.0.1"} if processes else {}
    cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=processes, memory_limit=memory_limit,
                           dashboard_address=None, silence_logs=logging.ERROR, **where)
    client = Client(cluster)
    try:
        yield client
    finally:
        client.close()
        cluster.close()


def run_fleet(sources, out_dir, scheduler: str | None = None, workers: int | None = None,
              window_s: float | None = None, processes: bool = True, memory_limit="auto",
              retries: int = RETRIES, progress=None, task=None, client=None,
              flush_rows: int = FLUSH_ROWS, flush_s: float = FLUSH_S) -> dict:
    """Identify every new log of ``sources`` on Dask and add its rows to the Parquet dataset in
    ``out_dir`` (module docstring).

    Args:
        sources: run logs or folders (paths or fsspec URLs). out_dir: the dataset's folder
            (created; local). scheduler: ``tcp://HOST:PORT`` of a running scheduler (None: a
            LocalCluster, :func:`fleet_client`). workers, processes, memory_limit: the
            LocalCluster's. window_s: window length [s] (None: one window per log).
        retries: Dask retries of a task that raised or lost its worker.
        progress: called with {"done", "total", "identified", "skipped", "failed", "rate"}
            (logs; rate in logs/s) after each log (None: silent).
        task: the window task (default :func:`identify_window`; same signature).
        client: a ``distributed.Client`` to use instead of making one.
    Returns:
        {"logs", "identified", "skipped", "failed": [(url, message)], "rows", "files",
        "seconds"}.
    Raises:
        InputError: a missing source, an output folder that cannot be written or holds an
        unreadable part, a bad or unreachable scheduler, a window_s that is not a positive
        number.
    """
    from motorctl.inputs import writable_dir
    if window_s is not None and not (math.isfinite(float(window_s)) and float(window_s) > 0):
        raise InputError(f"--window-s {window_s}: a positive number of seconds")
    if scheduler:
        check_scheduler(scheduler)
    urls = collect_sources(sources)
    out = writable_dir(out_dir, "fleet output")
    known = done_hashes(out)
    if client is None:
        with fleet_client(scheduler, workers, processes, memory_limit) as c:
            return _run(c, urls, out, known, window_s, retries, progress, task or identify_window,
                        flush_rows, flush_s)
    return _run(client, urls, out, known, window_s, retries, progress, task or identify_window,
                flush_rows, flush_s)


def _run(client, urls, out, known, window_s, retries, progress, task, flush_rows, flush_s) -> dict:
    from distributed import as_completed
    from distributed.client import FutureCancelledError
    t_start = time.monotonic()
    writer = PartWriter(out, flush_rows, flush_s)
    stats = {"logs": len(urls), "identified": 0, "skipped": 0, "failed": []}
    what: dict = {}                        # future key -> ("scan", url) | ("window", url)
    pending: dict = {}                     # url -> {"left": n, "rows": [], "error": None}
    seen = set(known)

    def tick():
        if progress:
            done = stats["identified"] + stats["skipped"] + len(stats["failed"])
            dt = max(time.monotonic() - t_start, 1e-9)
            progress({"done": done, "total": len(urls), "identified": stats["identified"],
                      "skipped": stats["skipped"], "failed": len(stats["failed"]),
                      "rate": stats["identified"] / dt})

    def fail(url, msg):
        stats["failed"].append((url, msg))
        tick()

    ac = as_completed()
    for url in urls:
        f = client.submit(scan_log, url, window_s, retries=retries, pure=False)
        what[f.key] = ("scan", url)
        ac.add(f)
    for fut in ac:
        kind, url = what.pop(fut.key)
        try:
            res = fut.result()
        except (Exception, FutureCancelledError) as exc:       # retries spent, or a killed worker
            res = {"url": url, "error": f"{url}: {type(exc).__name__}: {' '.join(str(exc).split())[:200]}"}
        fut.release()
        if kind == "scan":
            if "error" in res:
                fail(url, res["error"])
                continue
            if res["sha256"] in seen:
                stats["skipped"] += 1
                tick()
                continue
            seen.add(res["sha256"])
            jobs = [(ax, i, w0, w1) for ax in res["axes"] for i, (w0, w1) in enumerate(res["windows"])]
            pending[url] = {"left": len(jobs), "rows": [], "error": None}
            for ax, i, w0, w1 in jobs:
                f = client.submit(task, url, res["sha256"], res["machine"], res["started"], ax, i, w0, w1,
                                  retries=retries, pure=False)
                what[f.key] = ("window", url)
                ac.add(f)
            continue
        p = pending[url]
        p["left"] -= 1
        if "error" in res:
            p["error"] = p["error"] or res["error"]
        else:
            p["rows"].append(res)
        if p["left"] == 0:
            del pending[url]
            if p["error"]:
                fail(url, p["error"])
            else:
                writer.add(p["rows"])
                stats["identified"] += 1
                tick()
    writer.flush()
    stats.update(rows=writer.written, files=writer.files, seconds=time.monotonic() - t_start)
    return stats


__all__ = ["FLUSH_ROWS", "FLUSH_S", "LOG_SUFFIXES", "PARAMETERS", "PartWriter", "RETRIES", "Z95", "check_scheduler",
           "collect_sources", "content_hash", "default_workers", "done_hashes", "fleet_client", "identify_window",
           "local_copy", "part_files", "read_dataset", "run_fleet", "scan_log", "schema", "windows_of"]
