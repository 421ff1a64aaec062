"""Run logs: an append-only binary file of fixed-size float64 records with a JSON header.

Layout::

    b"MOTORCTL-RUNLOG\\n"                magic (16 bytes)
    uint64 little-endian                 header length H (bytes, padded so records are 8-aligned)
    H bytes                              UTF-8 JSON header, space-padded
    N × W float64 little-endian          records, W = len(header["columns"])

The header holds ``columns`` (names), ``period_s``, ``axes``, the config, the software version,
the start time and what the driver reports (e.g. the simulated truth). Records are only ever
appended, so a reader of a file that was cut short (a crash, ``kill -9``) drops at most the one
partial record at the end and keeps everything flushed before.

Columns: the record layout of :mod:`motorctl.loop.records` (names in ``columns``, units in
``units``); readers index by name.
"""

from __future__ import annotations

import json
import os
import struct
from dataclasses import dataclass

import numpy as np

from motorctl.loop.records import AXIS_FIELDS

MAGIC = b"MOTORCTL-RUNLOG\n"


class LogError(ValueError):
    """A file is not a readable motorctl run log (the message says why)."""


class LogWriter:
    """Append records to a run log. Not for the 5 kHz cycle: call it from outside the cycle.

    Args:
        path: file to create (truncated if it exists).
        header: JSON-able dict; ``columns`` is required.
        reserve: extra header bytes (spaces after the JSON) so that :meth:`update_header`
            can later add facts known only after the start (the flight recorder's real-time
            report, the end of the run) without moving the records.
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
        self._fd = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        os.write(self._fd, MAGIC + struct.pack("<Q", len(blob)) + blob)
        self.rows_written = 0

    def update_header(self, header: dict) -> bool:
        """Rewrite the JSON header in place (same columns). Returns False, leaving the file
        unchanged, when the new header does not fit in the space reserved at creation."""
        if list(header.get("columns", [])) != self._columns:
            raise ValueError("update_header cannot change the columns")
        blob = json.dumps(header).encode()
        if len(blob) > self._hlen:
            return False
        os.pwrite(self._fd, blob + b" " * (self._hlen - len(blob)), len(MAGIC) + 8)
        return True

    def append(self, rows: np.ndarray) -> None:
        """Append records, shape (k, W) float64 (C-contiguous)."""
        if rows.ndim != 2 or rows.shape[1] != self.width:
            raise ValueError(f"rows must have shape (k, {self.width}), got {rows.shape}")
        data = np.ascontiguousarray(rows, dtype="<f8").tobytes()
        view = memoryview(data)
        while view:
            n = os.write(self._fd, view)
            view = view[n:]
        self.rows_written += rows.shape[0]

    def flush(self) -> None:
        """Push written records to the storage device (fdatasync)."""
        os.fdatasync(self._fd)

    def release(self) -> None:
        """Close this process's descriptor without syncing (after ``fork``, in the process
        that will not write; the other process keeps appending)."""
        if self._fd >= 0:
            os.close(self._fd)
            self._fd = -1

    def close(self) -> None:
        if self._fd >= 0:
            os.fsync(self._fd)
            os.close(self._fd)
            self._fd = -1

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


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


def read_log(path: str) -> RunLog:
    """Read a run log; a partial last record (crash mid-write) is dropped.

    Raises:
        LogError: not a run log, or a damaged header.
        OSError: the file cannot be read.
    """
    with open(path, "rb") as fh:
        raw = fh.read()
    if not raw.startswith(MAGIC):
        raise LogError(f"{path}: not a motorctl run log (bad magic)")
    if len(raw) < len(MAGIC) + 8:
        raise LogError(f"{path}: header cut short")
    (hlen,) = struct.unpack_from("<Q", raw, len(MAGIC))
    start = len(MAGIC) + 8
    if len(raw) < start + hlen:
        raise LogError(f"{path}: header cut short")
    try:
        header = json.loads(raw[start:start + hlen].decode())
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise LogError(f"{path}: damaged header ({exc})") from None
    cols = header.get("columns")
    if not isinstance(cols, list) or not cols:
        raise LogError(f"{path}: header has no column list")
    body = raw[start + hlen:]
    rec = 8 * len(cols)
    n = len(body) // rec
    data = np.frombuffer(body[: n * rec], dtype="<f8").reshape(n, len(cols)).copy()
    return RunLog(header=header, columns=cols, data=data, truncated_bytes=len(body) - n * rec)
