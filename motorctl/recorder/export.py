"""``motorctl export``: a run (one run log, or a daemon's set of segments read as one run) as CSV
or as a MATLAB .mat file, streamed: the records are read and written chunk by chunk, so memory
stays bounded (a few tens of MB) whatever the length of the log.

The input is a :class:`motorctl.recorder.segments.Run` (:func:`~motorctl.recorder.segments.
open_run`), or anything with ``columns``, ``header``, ``axes``, ``n_rows`` and ``chunks(rows)``.
"""

from __future__ import annotations

import csv
import os
import struct

import numpy as np

#: rows per chunk written to CSV (the csv module turns each chunk into Python floats)
CSV_CHUNK_ROWS = 4096
#: rows per chunk written to .mat
MAT_CHUNK_ROWS = 65536
#: largest variable of a MAT v5 file [bytes] (MATLAB's limit for -v6/-v7 files)
MAT5_MAX_VAR_BYTES = (1 << 31) - 1

# MAT v5 element types and the double class (MATLAB "MAT-File Format", 2023)
_MI_INT8, _MI_INT32, _MI_UINT32, _MI_DOUBLE, _MI_MATRIX = 1, 5, 6, 9, 14
_MX_DOUBLE_CLASS = 6


def export_csv(run, out: str, chunk_rows: int = CSV_CHUNK_ROWS) -> int:
    """Write a run as CSV (one header line with the column names, then one line per record,
    floats as Python writes them). Returns the rows written.

    Raises:
        LogError: the log changed while it was read. OSError: reading or writing failed.
    """
    n = 0
    with open(out, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(run.columns)
        for chunk in run.chunks(chunk_rows):
            w.writerows(chunk.tolist())
            n += chunk.shape[0]
    return n


def mat_name(column: str) -> str:
    """MATLAB variable name of a column: 'X.theta_hat1' → 'X_theta_hat1'."""
    name = "".join(ch if ch.isalnum() or ch == "_" else "_" for ch in column)
    return name if name[:1].isalpha() else "v_" + name


def _pad8(n: int) -> int:
    return (n + 7) & ~7


def _double_matrix_head(name: str, rows: int, cols: int) -> bytes:
    """The MAT v5 element of a real double matrix up to its data: miMATRIX tag, array flags,
    dimensions, name, miDOUBLE tag (the rows·cols float64 in column-major order follow)."""
    nm = name.encode("ascii")
    nbytes = rows * cols * 8
    body = (struct.pack("<II", _MI_UINT32, 8) + struct.pack("<II", _MX_DOUBLE_CLASS, 0)
            + struct.pack("<II", _MI_INT32, 8) + struct.pack("<ii", rows, cols)
            + struct.pack("<II", _MI_INT8, len(nm)) + nm + b"\0" * (_pad8(len(nm)) - len(nm))
            + struct.pack("<II", _MI_DOUBLE, nbytes))
    return struct.pack("<II", _MI_MATRIX, len(body) + nbytes) + body


def export_mat(run, out: str, chunk_rows: int = MAT_CHUNK_ROWS) -> tuple[int, list[str]]:
    """Write a run as a MATLAB .mat file (format 5, uncompressed), streamed.

    Variables: ``columns`` (cell array of names), ``period_s``, ``axes`` (scipy.io.savemat),
    then one (N, 1) column vector per column named by :func:`mat_name`, and ``data`` (N, W)
    when it fits a MAT v5 variable (2 GB; else it is left out and a note says so). The
    vectors are laid out first and filled chunk by chunk (one pass over the log).

    Returns:
        (rows written, notes). Raises: LogError, OSError; ValueError (a column is too long
        for a MAT v5 variable: use CSV).
    """
    from scipy.io import savemat
    n, cols = int(run.n_rows), list(run.columns)
    w = len(cols)
    notes = []
    if n * 8 > MAT5_MAX_VAR_BYTES:
        raise ValueError(f"{n} records are too many for a .mat (v5) file: a column would "
                         f"exceed 2 GB; export to CSV instead")
    big = [(mat_name(c), 1) for c in cols]
    with_data = n * w * 8 <= MAT5_MAX_VAR_BYTES
    if with_data:
        big.append(("data", w))
    else:
        notes.append(f"the (N, W) 'data' matrix ({n * w * 8 / 1e9:.2f} GB) is over the MAT v5 "
                     f"limit of 2 GB and is left out; every column is in its own variable")
    period = run.header.get("period_s", 0.0) or 0.0
    with open(out, "wb") as fh:
        savemat(fh, {"columns": np.array(cols, dtype=object), "period_s": float(period),
                     "axes": np.array(run.axes, dtype=object)},
                do_compression=False, oned_as="column")
        fh.flush()
        fd = fh.fileno()
        pos = fh.tell()
        data_at = []                         # file offset of each variable's data
        for name, width in big:
            head = _double_matrix_head(name, n, width)
            os.pwrite(fd, head, pos)
            data_at.append(pos + len(head))
            pos += len(head) + n * width * 8
        os.ftruncate(fd, pos)
        i0 = 0
        for chunk in run.chunks(chunk_rows):
            k = chunk.shape[0]
            if i0 + k > n:
                break
            for j in range(w):
                col = np.ascontiguousarray(chunk[:, j], dtype="<f8").tobytes()
                os.pwrite(fd, col, data_at[j] + 8 * i0)
                if with_data:                # column-major: column j holds rows 0..N-1
                    os.pwrite(fd, col, data_at[w] + 8 * (j * n + i0))
            i0 += k
    return i0, notes


#: rows per chunk read for MCAP
MCAP_CHUNK_ROWS = 8192
#: MCAP topics: the run header, the cycle-wide columns, one per axis, the faults
MCAP_RUN_TOPIC = "/motorctl/run"
MCAP_CYCLE_TOPIC = "/motorctl/cycle"
MCAP_FAULT_TOPIC = "/motorctl/faults"


def mcap_axis_topic(axis: str) -> str:
    """The MCAP topic of one axis's columns: ``/motorctl/axis/X``."""
    return f"/motorctl/axis/{axis}"


def _json_schema(title: str, fields, units) -> bytes:
    import json
    props = {f: {"type": "number", "description": f"[{u}]"} for f, u in zip(fields, units)}
    return json.dumps({"title": title, "type": "object", "properties": props}).encode()


def export_mcap(run, out: str, chunk_rows: int = MCAP_CHUNK_ROWS) -> dict:
    """Write a run as an MCAP file (the container of ROS 2 bags and Foxglove), streamed with the
    ``mcap`` library: JSON messages with a JSON schema on each channel, log time = the record's
    ``t`` [ns].

    Channels: ``/motorctl/run`` (one message: the run header), ``/motorctl/cycle`` (the
    cycle-wide columns, one message per record), ``/motorctl/axis/<A>`` (the axis's columns
    without the prefix, one message per record), ``/motorctl/faults`` (a message when an axis's
    latched fault bits change: axis, bits, names, t). Units are in each schema's descriptions.

    Returns:
        {topic: messages written}.
    Raises:
        ImportError: the ``mcap`` package is not installed (the ``mcap`` extra). LogError,
        OSError: reading or writing failed.
    """
    import json

    from mcap.writer import Writer

    from motorctl.loop.safety import describe_faults
    cols = list(run.columns)
    units = list(run.header.get("units") or [""] * len(cols))
    axes = list(run.axes)
    cycle_idx = [j for j, c in enumerate(cols) if "." not in c]
    axis_idx = {a: [j for j, c in enumerate(cols) if c.startswith(f"{a}.")] for a in axes}
    t_j = cols.index("t")
    fb_j = {a: cols.index(f"{a}.fault_bits") for a in axes if f"{a}.fault_bits" in cols}
    counts: dict[str, int] = {}
    with open(out, "wb") as fh:
        w = Writer(fh)
        w.start(profile="", library="motorctl")

        def channel(topic: str, title: str, schema: bytes) -> int:
            sid = w.register_schema(name=title, encoding="jsonschema", data=schema)
            counts[topic] = 0
            return w.register_channel(topic=topic, message_encoding="json", schema_id=sid)

        run_ch = channel(MCAP_RUN_TOPIC, "motorctl.RunHeader", b'{"type": "object"}')
        cyc_ch = channel(MCAP_CYCLE_TOPIC, "motorctl.Cycle",
                         _json_schema("motorctl.Cycle", [cols[j] for j in cycle_idx], [units[j] for j in cycle_idx]))
        ax_ch = {a: channel(mcap_axis_topic(a), "motorctl.Axis",
                            _json_schema("motorctl.Axis", [cols[j].split(".", 1)[1] for j in axis_idx[a]],
                                         [units[j] for j in axis_idx[a]])) for a in axes}
        fault_ch = channel(MCAP_FAULT_TOPIC, "motorctl.Fault", json.dumps(
            {"title": "motorctl.Fault", "type": "object",
             "properties": {"axis": {"type": "string"}, "bits": {"type": "integer"},
                            "faults": {"type": "string"}, "t": {"type": "number", "description": "[s]"}}}).encode())
        first = True
        bits_prev = {a: 0 for a in fb_j}
        cyc_names = [cols[j] for j in cycle_idx]
        ax_names = {a: [cols[j].split(".", 1)[1] for j in axis_idx[a]] for a in axes}
        for chunk in run.chunks(chunk_rows):
            for row in chunk.tolist():
                ns = int(round(row[t_j] * 1e9))
                if first:
                    w.add_message(run_ch, ns, json.dumps(run.header, default=str).encode(), ns)
                    counts[MCAP_RUN_TOPIC] += 1
                    first = False
                w.add_message(cyc_ch, ns, json.dumps(dict(zip(cyc_names, [row[j] for j in cycle_idx]))).encode(), ns)
                counts[MCAP_CYCLE_TOPIC] += 1
                for a in axes:
                    msg = dict(zip(ax_names[a], [row[j] for j in axis_idx[a]]))
                    w.add_message(ax_ch[a], ns, json.dumps(msg).encode(), ns)
                    counts[mcap_axis_topic(a)] += 1
                    if a in fb_j:
                        bits = int(row[fb_j[a]])
                        if bits != bits_prev[a]:
                            w.add_message(fault_ch, ns, json.dumps(
                                {"axis": a, "bits": bits, "faults": describe_faults(bits), "t": row[t_j]}).encode(), ns)
                            counts[MCAP_FAULT_TOPIC] += 1
                            bits_prev[a] = bits
        w.finish()
    return counts
