"""Run logs: an append-only binary file of fixed-size float64 records with a JSON header.

Layout::

    b"MOTORCTL-RUNLOG\\n"                magic (16 bytes)
    uint64 little-endian                 header length H (bytes, padded so records are 8-aligned)
    H bytes                              UTF-8 JSON header, space-padded
    N × W float64 little-endian          records, W = len(header["columns"])

The header is a JSON object holding ``columns`` (names, a non-empty list of distinct strings),
``period_s``, ``axes`` (a list of names), the config, the software version, the start time and
what the driver reports (e.g. the simulated truth). Records are only ever appended, so a reader
of a file that was cut short (a crash, ``kill -9``) drops at most the one partial record at the
end and keeps everything flushed before; a failed append (a full disk) is cut back to the last
whole record, so the file stays readable.

One file here; a daemon's run is a numbered set of such files that share the header
(:mod:`motorctl.recorder.segments` writes and reads the set as one run).

Columns: the record layout of :mod:`motorctl.loop.records` (names in ``columns``, units in
``units``); readers index by name.
"""

from __future__ import annotations

import json
import math
import os
import struct
from dataclasses import dataclass

import numpy as np

from motorctl.inputs import InputError, regular_file
from motorctl.loop.records import AXIS_FIELDS, MODE_PROGRAM

MAGIC = b"MOTORCTL-RUNLOG\n"
#: a header longer than this is refused as damaged [bytes]
MAX_HEADER_BYTES = 16 << 20
#: rows per chunk of :meth:`LogFile.chunks` (64 Ki rows x 43 columns = 22 MB)
CHUNK_ROWS = 65536


class LogError(ValueError):
    """A file is not a readable motorctl run log (the message says why: ``FILE: ...``)."""


class LogWriter:
    """Append records to a run log. Not for the 5 kHz cycle: call it from outside the cycle.

    Args:
        path: file to create (truncated if it exists).
        header: JSON-able dict; ``columns`` is required.
        reserve: extra header bytes (spaces after the JSON) so that :meth:`update_header`
            can later add facts known only after the start (the flight recorder's real-time
            report, the end of the run) without moving the records.
    Attributes:
        rows_written: records in the file. data_offset: byte offset of the first record.
    Raises:
        ValueError: no ``columns``. OSError: the file cannot be created or written.
    """

    def __init__(self, path: str, header: dict, reserve: int = 0):
        if "columns" not in header:
            raise ValueError("header needs 'columns'")
        self.path = str(path)
        self.width = len(header["columns"])
        self._columns = list(header["columns"])
        blob = json.dumps(header).encode()
        blob += b" " * int(reserve)
        pad = (-(len(MAGIC) + 8 + len(blob))) % 8
        blob += b" " * pad
        self._hlen = len(blob)
        self.data_offset = len(MAGIC) + 8 + self._hlen
        self._fd = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        try:
            _write_all(self._fd, MAGIC + struct.pack("<Q", len(blob)) + blob)
        except OSError:                    # (a full disk) no half-written file stays behind
            os.close(self._fd)
            self._fd = -1
            try:
                os.unlink(self.path)
            except OSError:
                pass
            raise
        self.rows_written = 0

    @classmethod
    def reopen(cls, path: str) -> tuple["LogWriter", dict]:
        """Open an existing run log to append to and to update its header (after the process
        that wrote it died). A partial last record is cut off. Returns (writer, header).

        Raises:
            LogError: not a readable run log. OSError: it cannot be opened for writing.
        """
        lf = open_log(path)
        self = cls.__new__(cls)
        self.path, self.width, self._columns = lf.path, len(lf.columns), list(lf.columns)
        self.data_offset = lf.data_offset
        self._hlen = lf.data_offset - len(MAGIC) - 8
        self.rows_written = lf.n_rows
        self._fd = os.open(self.path, os.O_WRONLY)
        try:
            os.ftruncate(self._fd, self.size)
            os.lseek(self._fd, self.size, os.SEEK_SET)
        except OSError:
            self.release()
            raise
        return self, lf.header

    @property
    def size(self) -> int:
        """Bytes in the file (header and whole records)."""
        return self.data_offset + 8 * self.width * self.rows_written

    def update_header(self, header: dict) -> bool:
        """Rewrite the JSON header in place (same columns). Returns False, leaving the file
        unchanged, when the new header does not fit in the space reserved at creation.
        Raises OSError (the write failed)."""
        if list(header.get("columns", [])) != self._columns:
            raise ValueError("update_header cannot change the columns")
        blob = json.dumps(header).encode()
        if len(blob) > self._hlen:
            return False
        os.pwrite(self._fd, blob + b" " * (self._hlen - len(blob)), len(MAGIC) + 8)
        return True

    def append(self, rows: np.ndarray) -> None:
        """Append records, shape (k, W) float64 (C-contiguous).

        Raises:
            OSError: the write failed (ENOSPC, EIO ...); the file is cut back to its last whole
            record first, so it stays readable and a later append continues it.
        """
        if rows.ndim != 2 or rows.shape[1] != self.width:
            raise ValueError(f"rows must have shape (k, {self.width}), got {rows.shape}")
        data = np.ascontiguousarray(rows, dtype="<f8").tobytes()
        try:
            _write_all(self._fd, data)
        except OSError:
            try:                           # no partial record may stay behind
                os.ftruncate(self._fd, self.size)
                os.lseek(self._fd, self.size, os.SEEK_SET)
            except OSError:
                pass
            raise
        self.rows_written += rows.shape[0]

    def flush(self) -> None:
        """Push written records to the storage device (fdatasync). Raises OSError."""
        os.fdatasync(self._fd)

    def release(self) -> None:
        """Close this process's descriptor without syncing (after ``fork``, in the process
        that will not write; the other process keeps appending)."""
        if self._fd >= 0:
            os.close(self._fd)
            self._fd = -1

    def close(self) -> None:
        """fsync and close (the descriptor is closed even when the fsync fails: OSError)."""
        if self._fd >= 0:
            fd, self._fd = self._fd, -1
            try:
                os.fsync(fd)
            finally:
                os.close(fd)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def _write_all(fd: int, data: bytes) -> None:
    view = memoryview(data)
    while view:
        n = os.write(fd, view)
        view = view[n:]


def check_header(header, path: str) -> dict:
    """The header of ``path`` if it is one a reader can use, else :class:`LogError` (one line).

    Checked: a JSON object; ``columns`` a non-empty list of distinct strings; ``axes`` (if
    present) a list of strings; ``period_s`` (if present) a positive finite number.
    """
    if not isinstance(header, dict):
        raise LogError(f"{path}: damaged header (a JSON {type(header).__name__}, not an object)")
    cols = header.get("columns")
    if not isinstance(cols, list) or not cols or not all(isinstance(c, str) for c in cols):
        raise LogError(f"{path}: damaged header ('columns' is not a non-empty list of names)")
    if len(set(cols)) != len(cols):
        dup = next(c for c in cols if cols.count(c) > 1)
        raise LogError(f"{path}: damaged header (column {dup!r} appears twice)")
    axes = header.get("axes", [])
    if not isinstance(axes, list) or not all(isinstance(a, str) for a in axes):
        raise LogError(f"{path}: damaged header ('axes' is not a list of names)")
    p = header.get("period_s")
    if p is not None and not (isinstance(p, (int, float)) and not isinstance(p, bool)
                              and math.isfinite(p) and p > 0):
        raise LogError(f"{path}: damaged header ('period_s' is not a positive number)")
    return header


@dataclass
class LogFile:
    """One run log opened for reading: the header checked, the records not read yet.

    Attributes:
        path; header (dict); columns (list[str]); n_rows (whole records at open time);
        data_offset (byte offset of the first record); truncated_bytes (a partial last
        record, ignored).
    """

    path: str
    header: dict
    columns: list
    n_rows: int
    data_offset: int
    truncated_bytes: int = 0

    @property
    def axes(self) -> list:
        return list(self.header.get("axes", []))

    def chunks(self, rows: int = CHUNK_ROWS):
        """The records in order as arrays of at most ``rows`` rows, shape (k, W) float64:
        read from the file chunk by chunk (memory bounded by ``rows``, whatever the length).

        Raises:
            LogError: the file shrank while it was read. OSError: a read failed.
        """
        w = len(self.columns)
        rec = 8 * w
        with open(self.path, "rb") as fh:
            fh.seek(self.data_offset)
            left = self.n_rows
            while left > 0:
                k = min(rows, left)
                buf = fh.read(k * rec)
                if len(buf) < k * rec:
                    raise LogError(f"{self.path}: the file shrank while it was read")
                block = np.frombuffer(buf, dtype="<f8").reshape(k, w)
                self.check_records(block, self.n_rows - left)
                yield block
                left -= k

    def read(self) -> np.ndarray:
        """Every record, (n_rows, W) float64 (in memory)."""
        w = len(self.columns)
        with open(self.path, "rb") as fh:
            fh.seek(self.data_offset)
            buf = fh.read(self.n_rows * 8 * w)
        n = len(buf) // (8 * w)
        data = np.frombuffer(buf[: n * 8 * w], dtype="<f8").reshape(n, w).copy()
        self.check_records(data, 0)
        return data

    def check_records(self, block: np.ndarray, first: int) -> None:
        """Records that do not fit the header (its ``columns`` count differs from what was
        written, or the file was overwritten) raise :class:`LogError`: the cycle time ``t``
        (the first column, k·Ts) must be finite, increasing and a whole number of periods.
        ``block``: records (k, W) from record index ``first``."""
        if block.shape[0] == 0 or not self.columns or self.columns[0] != "t":
            return
        t = block[:, 0]
        ts = self.header.get("period_s")
        bad = ~np.isfinite(t) | (t < 0)
        if block.shape[0] > 1:
            bad[1:] |= np.diff(t) <= 0
        if ts:
            k = t / ts
            with np.errstate(invalid="ignore"):
                bad |= np.abs(k - np.round(k)) > 1e-6 * np.maximum(1.0, np.abs(k))
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise LogError(f"{self.path}: damaged records (record {first + i}: t = {t[i]!r} is not "
                           f"the next cycle's time; does the header's {len(self.columns)} columns "
                           f"match what was written?)")


def open_log(path: str) -> LogFile:
    """Open a run log: check that it is a regular file with the magic and a usable header
    (:func:`check_header`), count its whole records; nothing else is read.

    Raises:
        LogError: missing, not a regular file (a FIFO, device or directory), not a run log,
        or a damaged header; one line naming the file. OSError: a read failed.
    """
    path = str(path)
    try:
        st = regular_file(path, "run log", 1 << 62)
    except InputError as exc:
        raise LogError(str(exc)) from None
    with open(path, "rb") as fh:
        head = fh.read(len(MAGIC) + 8)
        if not head.startswith(MAGIC):
            raise LogError(f"{path}: not a motorctl run log (bad magic)")
        if len(head) < len(MAGIC) + 8:
            raise LogError(f"{path}: header cut short")
        (hlen,) = struct.unpack_from("<Q", head, len(MAGIC))
        start = len(MAGIC) + 8
        if hlen > MAX_HEADER_BYTES or st.st_size < start + hlen:
            raise LogError(f"{path}: header cut short" if hlen <= MAX_HEADER_BYTES
                           else f"{path}: damaged header (length {hlen} bytes)")
        blob = fh.read(hlen)
    if len(blob) < hlen:
        raise LogError(f"{path}: header cut short")
    try:
        header = json.loads(blob.decode())
    except (UnicodeDecodeError, json.JSONDecodeError, RecursionError) as exc:
        raise LogError(f"{path}: damaged header ({exc})") from None
    check_header(header, path)
    cols = list(header["columns"])
    rec = 8 * len(cols)
    body = st.st_size - start - hlen
    return LogFile(path, header, cols, body // rec, start + hlen, body % rec)


@dataclass
class RunLog:
    """A run log read back: ``header`` (dict), ``columns`` (list[str]), ``data`` (N, W) float64."""

    header: dict
    columns: list
    data: np.ndarray
    truncated_bytes: int = 0

    def col(self, name: str) -> np.ndarray:
        """One column, shape (N,). Raises KeyError naming the available columns."""
        try:
            return self.data[:, self.columns.index(name)]
        except ValueError:
            raise KeyError(f"no column {name!r} in the log; columns: {', '.join(self.columns)}") from None

    @property
    def axes(self) -> list:
        return list(self.header.get("axes", []))

    def axis(self, name: str) -> dict:
        """All columns of one axis as {field: array (N,)} (fields the log lacks are left out)."""
        if name not in self.axes:
            raise KeyError(f"no axis {name!r} in the log; axes: {', '.join(self.axes)}")
        return {f: self.col(f"{name}.{f}") for f in AXIS_FIELDS if f"{name}.{f}" in self.columns}

    def program_rows(self, name: str) -> np.ndarray | None:
        """Axis ``name``'s rows of the program (its ``mode`` column equal to MODE_PROGRAM: not
        the idle read at 0 V nor the approach a run starts with) as a bool mask (N,); None for a
        log without the column (written before runs had a start sequence: every row is the
        program's)."""
        col = f"{name}.mode"
        return self.col(col) == MODE_PROGRAM if col in self.columns else None


def read_log(path: str) -> RunLog:
    """Read one run-log file into memory; a partial last record (crash mid-write) is dropped.
    (A daemon's whole run, a set of segments: :func:`motorctl.recorder.segments.read_run`.)

    Raises:
        LogError: missing, not a regular file, not a run log, or a damaged header (one line).
        OSError: the file cannot be read.
    """
    lf = open_log(path)
    data = lf.read()
    return RunLog(header=lf.header, columns=lf.columns, data=data,
                  truncated_bytes=lf.truncated_bytes + 8 * len(lf.columns) * (lf.n_rows - data.shape[0]))
