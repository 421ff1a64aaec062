"""Identification over many machines' run logs on Dask: ``motorctl fleet identify``.

The job, for SOURCES (run logs or folders of them, local paths or fsspec URLs):

1. :func:`collect_sources` lists the logs (a folder: every ``*.mclog`` and ``*.log`` file under
   it, recursively, in sorted order).
2. One **scan** task per log (:func:`scan_log`): the file's SHA-256 (its content hash, read in
   1 MiB blocks), its header (``machine_id``, ``started``, the axes), its run (:func:`run_id`:
   the header's machine, start and axes with the hash of its first records) and its windows.
   A log whose hash is already in the output folder (or seen earlier in the same run) is
   skipped: the job is idempotent. Of the logs of one run (a log cut mid-run, copied before
   its end, beside the whole one) only the one with the most records counts: a cut copy of a
   run already counted is skipped, and a longer log of a run supersedes the shorter one's rows.
3. One **window** task per axis and window of each new log (:func:`identify_window`): the
   record of ``motorctl identify`` (:func:`motorctl.ident.data.load_record`), cut to the
   window, through the same pipeline (:func:`motorctl.ident.pipeline.identify_record`), verdict
   included. Without ``window_s`` a log is one window (its longest run of enabled cycles, as
   ``identify`` takes it); with it, that run is split into ⌊T/window_s⌋ equal windows (each at
   least ``window_s`` long, shorter than 2·window_s), so an hour-long log gives many points in
   time and many tasks.
4. Results come back as they complete (``distributed.as_completed``); a log's rows are kept
   until all its windows are done, then written together with the other finished logs' every
   :data:`FLUSH_ROWS` rows or :data:`FLUSH_S` seconds, and at the end: one Parquet file per
   partition, ``machine=<machine>/month=<YYYY-MM>/part-*.parquet`` (hive style; written to a
   temporary name and renamed, so a reader never sees half a file). A log is either wholly in
   the dataset or not at all.
5. At the end the job compacts each partition that holds more than one file, or rows of a
   superseded log, into one file (:func:`compact`).

The dataset reads as ``pyarrow.dataset.dataset(DIR, partitioning="hive")`` (the report folder
``_report`` and temporary files, named with a leading ``_`` or ``.``, are not part of it) or
:func:`read_dataset`, which also leaves out a superseded log's rows (a crash between a write
and the compaction leaves them on disk) and an exact repeat of a row.

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
import secrets
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
#: records hashed into a log's run (:func:`run_id`): a log cut within its first 256 cycles
#: (50 ms at 5 kHz) has fewer and counts as a run of its own (too short to identify anyway)
HEAD_RECORDS = 256
#: the hive partitions of the dataset, each a string: the machine and the month (UTC) of the row's time
PARTITIONS = ("machine", "month")


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
        ("run_id", pa.string()), ("log_records", pa.int64()),
    ]
    return pa.schema(fields)


def partitioning():
    """The dataset's hive partitioning (``machine=.../month=...``), both keys strings (a
    machine named ``17`` stays the string "17")."""
    import pyarrow as pa
    import pyarrow.dataset as ds
    return ds.partitioning(pa.schema([(k, pa.string()) for k in PARTITIONS]), flavor="hive")


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


def run_id(machine: str, started: str, axes: list, head: bytes) -> str:
    """The identity of a run (SHA-256, hex): the header's machine, ``started`` (as written) and
    axes, and the bytes of its first :data:`HEAD_RECORDS` records. Two logs with the same run
    are one run at two lengths: records are only appended, so a log copied or cut mid-run has
    the whole log's first records, while its header (rewritten at the end) and its content
    hash differ."""
    h = hashlib.sha256()
    h.update(repr((str(machine), str(started), [str(a) for a in axes])).encode())
    h.update(head)
    return h.hexdigest()


def scan_log(url: str, window_s: float | None = None) -> dict:
    """Task: a log's content hash, machine, start time, axes, run (:func:`run_id`), whole
    records and windows (:func:`windows_of`).

    Returns:
        {"url", "sha256", "machine", "started" (ISO, UTC), "axes", "run_id", "records",
        "windows": [(t0, t1)]} or {"url", "error"} when the file cannot be read or is not a
        run log.
    """
    from motorctl.recorder.runlog import LogError, open_log
    try:
        sha = content_hash(url)
        with local_copy(url) as path:
            lf = open_log(path)
            with open(path, "rb") as fh:
                fh.seek(lf.data_offset)
                head = fh.read(8 * len(lf.columns) * min(lf.n_rows, HEAD_RECORDS))
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
            "axes": list(lf.axes), "run_id": run_id(str(machine), h.get("started"), lf.axes, head),
            "records": int(lf.n_rows), "windows": windows_of(h, lf.n_rows, window_s)}


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
        url: the log. sha256: its content hash. machine, started (ISO): from its header
            (the job adds the log's run and records to the row, :func:`scan_log`).
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
    """The dataset's Parquet files: ``machine=*/month=*/part-*.parquet``, and the top-level
    ``part-*.parquet`` of a dataset written before it was partitioned (moved into the
    partitions by the next job's :func:`compact`)."""
    d = Path(out_dir)
    return sorted(d.glob("machine=*/month=*/part-*.parquet")) + sorted(d.glob("part-*.parquet"))


def partition_dir(out_dir, machine: str, time: _dt.datetime) -> Path:
    """The folder of a row's partition: ``machine=<machine>/month=<YYYY-MM>`` (the machine
    percent-encoded, as ``pyarrow.dataset``'s hive partitioning decodes it; the month of
    ``time`` in UTC)."""
    from urllib.parse import quote
    month = time.astimezone(_dt.timezone.utc).strftime("%Y-%m")
    return Path(out_dir) / f"machine={quote(str(machine), safe='')}" / f"month={month}"


def _read_part(f: Path):
    """One part file as a Table of :func:`schema`: ``machine`` from its partition's path, a
    column a part written by an older version lacks as nulls. Raises InputError naming it."""
    import pyarrow as pa
    import pyarrow.parquet as pq
    from urllib.parse import unquote
    sc = schema()
    try:
        t = pq.read_table(f)
        cols = {name: t.column(name) for name in t.column_names}
        if f.parent.name.startswith("month="):
            cols["machine"] = pa.array([unquote(f.parent.parent.name.split("=", 1)[1])] * t.num_rows, pa.string())
        return pa.table([cols[n] if n in cols else pa.nulls(t.num_rows, sc.field(n).type) for n in sc.names],
                        names=sc.names).cast(sc)
    except (OSError, pa.ArrowException) as exc:
        raise InputError(f"{f}: not a readable Parquet part of a fleet dataset "
                         f"({' '.join(str(exc).split())[:200]})") from None


def _best_logs(runs, records, hashes) -> set:
    """The content hashes of the logs that count: of the logs of one run (``runs``, None: a
    log of its own), the one with the most ``records`` (ties: the smallest hash)."""
    best: dict = {}
    for run, n, sha in zip(runs, records, hashes):
        key = run if run is not None else ("log", sha)
        cand = (-(n if n is not None else 0), sha)
        if key not in best or cand < best[key]:
            best[key] = cand
    return {sha for _, sha in best.values()}


def _counted(t, keep: set | None = None):
    """The rows of Table ``t`` that count: those of the logs in ``keep`` (default: the
    :func:`_best_logs` of ``t``), each (log, axis, window) once."""
    import pyarrow as pa
    import pyarrow.compute as pc
    hashes = t.column("log_sha256").to_pylist()
    if keep is None:
        keep = _best_logs(t.column("run_id").to_pylist(), t.column("log_records").to_pylist(), hashes)
    seen, mask = set(), []
    for key in zip(hashes, t.column("axis").to_pylist(), t.column("window").to_pylist()):
        mask.append(key[0] in keep and key not in seen)
        seen.add(key)
    del pc
    return t if all(mask) else t.filter(pa.array(mask, pa.bool_()))


def read_dataset(out_dir, counted: bool = True):
    """The dataset in ``out_dir`` as one pyarrow Table (:func:`schema`), or None when it holds
    no part file. ``counted``: only the rows that count (a log superseded by a longer log of
    its run, or a row repeated, left out); else every row on disk.

    Raises:
        InputError: a part file that cannot be read (one line naming it).
    """
    import pyarrow as pa
    files = part_files(out_dir)
    if not files:
        return None
    t = pa.concat_tables([_read_part(f) for f in files])
    return _counted(t) if counted else t


def known_logs(out_dir) -> dict:
    """What the dataset in ``out_dir`` holds: {"hashes": content hashes of its logs, "runs":
    {run_id: (records, log_path)} of the logs that count}."""
    t = read_dataset(out_dir, counted=False)
    if t is None:
        return {"hashes": set(), "runs": {}}
    cols = [t.column(c).to_pylist() for c in ("log_sha256", "run_id", "log_records", "log_path")]
    keep = _best_logs(cols[1], cols[2], cols[0])
    runs = {run: (n or 0, path) for sha, run, n, path in zip(*cols) if run is not None and sha in keep}
    return {"hashes": set(cols[0]), "runs": runs}


def _write_part(table, folder: Path, name: str) -> Path:
    """Write ``table`` (:func:`schema`) as ``folder/name`` without its ``machine`` column:
    under a temporary name, then renamed."""
    import pyarrow.parquet as pq
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / name
    tmp = folder / f".{name}.tmp"
    pq.write_table(table.drop_columns(["machine"]), tmp)
    os.replace(tmp, path)
    return path


class PartWriter:
    """Rows to Parquet part files in ``out_dir``: :meth:`add` gathers a finished log's rows,
    :meth:`flush` writes them as one file per partition (:func:`partition_dir`; temporary name,
    then renamed)."""

    def __init__(self, out_dir, flush_rows: int = FLUSH_ROWS, flush_s: float = FLUSH_S):
        self.dir = Path(out_dir)
        self.rows: list[dict] = []
        self.flush_rows, self.flush_s = int(flush_rows), float(flush_s)
        self.last = time.monotonic()
        # unique among writers, also two in one process and second (a job's and its compaction's)
        self.stamp = (_dt.datetime.now(_dt.timezone.utc).strftime("%Y%m%dT%H%M%S")
                      + f"-{os.getpid()}-{secrets.token_hex(3)}")
        self.n = 0
        self.written = 0
        self.files: list[str] = []

    def add(self, rows: list[dict]) -> None:
        self.rows.extend(rows)
        if len(self.rows) >= self.flush_rows or time.monotonic() - self.last >= self.flush_s:
            self.flush()

    def name(self) -> str:
        self.n += 1
        return f"part-{self.stamp}-{self.n - 1:05d}.parquet"

    def write(self, table, folder: Path) -> None:
        self.files.append(str(_write_part(table, folder, self.name())))

    def flush(self) -> None:
        import pyarrow as pa
        self.last = time.monotonic()
        if not self.rows:
            return
        groups: dict = {}
        for r in self.rows:
            groups.setdefault(partition_dir(self.dir, r["machine"], r["time"]), []).append(r)
        for folder, rows in sorted(groups.items()):
            self.write(pa.Table.from_pylist(rows, schema=schema()), folder)
        self.written += len(self.rows)
        self.rows = []


def compact(out_dir, writer: PartWriter | None = None) -> dict:
    """Compact the dataset in ``out_dir``: each partition holding more than one part file, or
    rows that do not count (a superseded log, a repeated row: :func:`read_dataset`), is
    rewritten as one file of its counted rows in time order (written, then the old files
    removed: a crash in between leaves rows twice on disk, which :func:`read_dataset` counts
    once). Parts from before the partitions: the whole dataset is rewritten into partitions.

    Returns:
        {"partitions": partitions written, "files_before", "files_after", "rows_dropped"}.
    Raises:
        InputError: a part file that cannot be read.
    """
    import pyarrow as pa
    d = Path(out_dir)
    writer = writer or PartWriter(d)
    files = part_files(d)
    tables = {f: _read_part(f) for f in files}
    every = pa.concat_tables(tables.values()) if tables else None
    keep = set() if every is None else _best_logs(every.column("run_id").to_pylist(),
                                                  every.column("log_records").to_pylist(),
                                                  every.column("log_sha256").to_pylist())
    by_dir: dict = {}
    for f in files:
        by_dir.setdefault(f.parent, []).append(f)
    legacy = d in by_dir
    old = []
    for folder, fs in by_dir.items():
        n = sum(tables[f].num_rows for f in fs)
        if legacy or len(fs) > 1 or _counted(pa.concat_tables([tables[f] for f in fs]), keep).num_rows < n:
            old += fs
    if not old:
        return {"partitions": 0, "files_before": len(files), "files_after": len(files), "rows_dropped": 0}
    rows = _counted(pa.concat_tables([tables[f] for f in old]), keep)
    rows = rows.sort_by([("time", "ascending"), ("axis", "ascending"), ("window", "ascending")])
    groups: dict = {}
    for i, (m, t) in enumerate(zip(rows.column("machine").to_pylist(), rows.column("time").to_pylist())):
        groups.setdefault(partition_dir(d, m, t), []).append(i)
    n_before = len(writer.files)
    for folder, idx in sorted(groups.items()):
        writer.write(rows.take(pa.array(idx)), folder)
    written = set(writer.files[n_before:])
    for f in old:
        if str(f) not in written:
            f.unlink(missing_ok=True)
    return {"partitions": len(groups), "files_before": len(files), "files_after": len(part_files(d)),
            "rows_dropped": int(sum(tables[f].num_rows for f in old) - rows.num_rows)}


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
        {"logs", "identified", "skipped" (already in the dataset, or cut), "failed": [(url,
        message)], "cut": [(url, the log of its run that counts, its records, that log's)],
        "superseded": [(a log in the dataset, the longer log of its run now counted, records,
        records)], "rows" (written), "files" (the part files written and still there after the
        compaction), "compaction" (:func:`compact`), "seconds"}.
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
    known = known_logs(out)
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
    stats = {"logs": len(urls), "identified": 0, "skipped": 0, "failed": [], "cut": [], "superseded": []}

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

    def outcome(fut, url):
        try:
            res = fut.result()
        except (Exception, FutureCancelledError) as exc:       # retries spent, or a killed worker
            res = {"url": url, "error": f"{url}: {type(exc).__name__}: {' '.join(str(exc).split())[:200]}"}
        fut.release()
        return res

    # every log scanned first: of the logs of one run, only the longest is identified
    scans: dict = {}                       # url -> scan_log's result
    ac = as_completed()
    keyed = {}
    for url in urls:
        f = client.submit(scan_log, url, window_s, retries=retries, pure=False)
        keyed[f.key] = url
        ac.add(f)
    for fut in ac:
        url = keyed.pop(fut.key)
        res = outcome(fut, url)
        if "error" in res:
            fail(url, res["error"])
        else:
            scans[url] = res
    seen = set(known["hashes"])
    best = {run: {"records": n, "url": path, "new": False} for run, (n, path) in known["runs"].items()}
    for url in urls:
        res = scans.get(url)
        if res is None:
            continue
        if res["sha256"] in seen:
            stats["skipped"] += 1
            del scans[url]
            continue
        seen.add(res["sha256"])
        prev = best.get(res["run_id"])
        if prev is not None and prev["records"] >= res["records"]:
            stats["cut"].append((url, prev["url"], res["records"], prev["records"]))
            stats["skipped"] += 1
            del scans[url]
            continue
        if prev is not None:
            if prev["new"]:
                stats["cut"].append((prev["url"], url, prev["records"], res["records"]))
                stats["skipped"] += 1
                del scans[prev["url"]]
            else:
                stats["superseded"].append((prev["url"], url, prev["records"], res["records"]))
        best[res["run_id"]] = {"records": res["records"], "url": url, "new": True}
    tick()

    ac = as_completed()
    what: dict = {}                        # future key -> url
    pending: dict = {}                     # url -> {"left": n, "rows": [], "error": None}
    for url in urls:
        res = scans.get(url)
        if res is None:
            continue
        jobs = [(ax, i, w0, w1) for ax in res["axes"] for i, (w0, w1) in enumerate(res["windows"])]
        pending[url] = {"left": len(jobs), "rows": [], "error": None}
        for ax, i, w0, w1 in jobs:
            f = client.submit(task, url, res["sha256"], res["machine"], res["started"], ax, i, w0, w1,
                              retries=retries, pure=False)
            what[f.key] = url
            ac.add(f)
    for fut in ac:
        url = what.pop(fut.key)
        res = outcome(fut, url)
        p = pending[url]
        p["left"] -= 1
        if "error" in res:
            p["error"] = p["error"] or res["error"]
        else:
            p["rows"].append(res | {"run_id": scans[url]["run_id"], "log_records": scans[url]["records"]})
        if p["left"] == 0:
            del pending[url]
            if p["error"]:
                fail(url, p["error"])
            else:
                writer.add(p["rows"])
                stats["identified"] += 1
                tick()
    writer.flush()
    written = writer.written
    stats["compaction"] = compact(out, writer)
    stats.update(rows=written, files=[f for f in writer.files if os.path.exists(f)],
                 seconds=time.monotonic() - t_start)
    return stats


__all__ = ["FLUSH_ROWS", "FLUSH_S", "HEAD_RECORDS", "LOG_SUFFIXES", "PARAMETERS", "PARTITIONS", "PartWriter", "RETRIES",
           "Z95", "check_scheduler", "collect_sources", "compact", "content_hash", "default_workers",
           "fleet_client", "identify_window", "known_logs", "local_copy", "part_files", "partition_dir",
           "partitioning", "read_dataset", "run_fleet", "run_id", "scan_log", "schema", "windows_of"]
