"""Reading identification data: motorctl run logs, CSV files and MATLAB files.

All readers return a :class:`Record` (SI units: t [s], y [m], u [V], optional yd [m]) after the
same checks (:func:`check_record`); bad data raise :class:`motorctl.recorder.runlog.LogError` (or
:class:`motorctl.inputs.InputError` for the file itself) with one line naming the file, the column
or variable (and the CSV line) and what is allowed.

The input boundary: every DATA file goes through :func:`motorctl.inputs.regular_file` first (no
FIFO, device or directory; at most :data:`MAX_DATA_BYTES`); CSV text through
:func:`motorctl.inputs.read_text` (UTF-8, a byte-order mark accepted). Values must be finite and
of physical magnitude (:data:`MAX_ABS`); time in ms or µs is refused with a message saying so
(never converted silently).
"""

from __future__ import annotations

import csv
import io
import math
from dataclasses import dataclass, field

import numpy as np

from motorctl.inputs import InputError, read_text, regular_file, summarize
from motorctl.metrics import runs
from motorctl.recorder.runlog import LogError, MAGIC, read_log

#: Largest DATA file read (run log, CSV or MATLAB) [bytes]: 2 GiB, hours of a 1 kHz axis.
MAX_DATA_BYTES = 2 << 30
#: Largest magnitude allowed per column (SI): time [s], positions [m], input [V, or N without
#: --gain]. Beyond these the record is not a measurement of a machine axis (or not in SI units).
MAX_ABS = {"t": 1e10, "y": 1e3, "yd": 1e3, "u": 1e4}
#: Force gain A1 allowed (--gain, run-log header) [N/V]: (0, MAX_GAIN].
MAX_GAIN = 1e6
#: Sample period allowed [s]: 1 µs .. 0.1 s (1 MHz .. 10 Hz).
MIN_PERIOD_S, MAX_PERIOD_S = 1e-6, 0.1
#: Smallest input range (peak-to-peak) counted as a varying input [V].
MIN_INPUT_RANGE = 1e-6

#: Shortest record accepted [s] and fewest samples (the IDIM filters need some length).
MIN_DURATION_S = 1.0
MIN_SAMPLES = 200
#: Relative tolerance on the sample period (uniform sampling).
PERIOD_RTOL = 1e-3
#: Smallest position travel (peak-to-peak) counted as motion [m].
MIN_TRAVEL_M = 1e-5


@dataclass
class Record:
    """One axis's identification data.

    Attributes:
        t: time [s], shape (N,), uniform and increasing. y: measured position [m], (N,).
        u: drive input [V] (or the force channel when ``gain`` is None and the file is in N), (N,).
        yd: reference position [m], (N,) or None. gain: force per input unit A1 [N/V] or None.
        source: file name (for messages and the report). axis: axis name for run logs.
        header: the run log header (run logs only; holds the config and the simulated truth).
    """

    t: np.ndarray
    y: np.ndarray
    u: np.ndarray
    yd: np.ndarray | None = None
    gain: float | None = None
    source: str = ""
    axis: str = ""
    header: dict = field(default_factory=dict)
    #: how messages name each channel, e.g. {"y": "variable 'qm' (y)"} (default "column 'y'")
    labels: dict = field(default_factory=dict)

    def label(self, name: str) -> str:
        return self.labels.get(name, f"column {name!r}")

    @property
    def period_s(self) -> float:
        return float((self.t[-1] - self.t[0]) / (len(self.t) - 1))

    @property
    def n(self) -> int:
        return len(self.t)

    @property
    def u_limit(self) -> float | None:
        """The input's limit [V] the run log's config declares for the axis (its controller's
        ``u_lim``); None for a CSV/MAT record or a missing or malformed entry."""
        lim = _dig(self.header, "config", "axes", self.axis, "controller", "u_lim")
        ok = isinstance(lim, (int, float)) and not isinstance(lim, bool) and math.isfinite(lim) and lim > 0
        return float(lim) if ok else None


def parse_map(text: str | None) -> dict:
    """``"t=t,y=qm,u=vir,yd=qg"`` → {"t": "t", "y": "qm", "u": "vir", "yd": "qg"}.

    Raises:
        LogError: a malformed item or an unknown key (allowed: t, y, u, yd).
    """
    if not text:
        return {}
    out = {}
    for item in text.split(","):
        if "=" not in item:
            raise LogError(f"--map: item {item!r} is not KEY=NAME (keys: t, y, u, yd)")
        k, v = (s.strip() for s in item.split("=", 1))
        if k not in ("t", "y", "u", "yd") or not v:
            raise LogError(f"--map: key {k!r} not allowed (keys: t, y, u, yd, each =VARIABLE)")
        out[k] = v
    return out


def check_record(rec: Record) -> Record:
    """Validate a record: shapes, finite values of physical magnitude (:data:`MAX_ABS`), time
    strictly increasing, uniform, in seconds (ms/µs detected), length, motion, input, gain.

    Raises:
        LogError: naming the file and the column (or variable), what was wrong and what is allowed.
    """
    src = rec.source or "data"
    n = len(rec.t) if getattr(rec.t, "ndim", 0) == 1 else None
    for name in ("t", "y", "u", "yd"):
        a = getattr(rec, name)
        if a is None:
            continue
        lab = rec.label(name)
        if a.ndim != 1:
            raise LogError(f"{src}: {lab} has shape {'x'.join(map(str, a.shape))}; a vector is required")
        if len(a) != n:
            raise LogError(f"{src}: {lab} has {a.size} values, expected {n} (same as {rec.label('t')})")
        bad = ~np.isfinite(a)
        if bad.any():
            i = int(np.argmax(bad))
            raise LogError(f"{src}: {lab} has {int(bad.sum())} non-finite value(s) "
                           f"(first at sample {i}{_where(rec, i)}); only finite numbers are allowed")
        lim = MAX_ABS[name]
        big = np.abs(a) >= lim
        if big.any():
            i = int(np.argmax(big))
            unit = {"t": "s", "y": "m", "yd": "m", "u": "V (N without --gain)"}[name]
            raise LogError(f"{src}: {lab} = {a[i]:.6g} at sample {i}{_where(rec, i)} is not a physical value; "
                           f"|{name}| < {lim:g} {unit} is allowed (SI units: s, m, V)")
    if n < MIN_SAMPLES:
        raise LogError(f"{src}: only {n} samples; at least {MIN_SAMPLES} and {MIN_DURATION_S:g} s are needed")
    dt = np.diff(rec.t)
    if np.any(dt <= 0):
        i = int(np.argmax(dt <= 0))
        raise LogError(f"{src}: {rec.label('t')} is not increasing at sample {i + 1}{_where(rec, i + 1)} "
                       f"(t = {rec.t[i]:.6g} then {rec.t[i + 1]:.6g} s); time must strictly increase")
    ts = float(np.median(dt))
    span = float(rec.t[-1] - rec.t[0])
    if ts > 0.5 and span > 1000:
        raise LogError(f"{src}: {rec.label('t')} looks like milliseconds or microseconds, not seconds "
                       f"(median step {ts:.6g}, span {span:.6g}); give t in seconds "
                       "(divide by 1000 for ms, by 1e6 for µs)")
    if ts > MAX_PERIOD_S or ts < MIN_PERIOD_S:
        raise LogError(f"{src}: {rec.label('t')} has a median step of {ts:.6g} s; a sample period within "
                       f"{MIN_PERIOD_S:g}..{MAX_PERIOD_S:g} s is required (is t in seconds?)")
    if np.max(np.abs(dt - ts)) > PERIOD_RTOL * ts + 1e-12:
        i = int(np.argmax(np.abs(dt - ts)))
        raise LogError(f"{src}: {rec.label('t')} is not uniformly sampled (step {dt[i]:.6g} s at sample "
                       f"{i + 1}{_where(rec, i + 1)}, median {ts:.6g} s); a constant sample period is required")
    if span < MIN_DURATION_S:
        raise LogError(f"{src}: record lasts {span:.3g} s; at least {MIN_DURATION_S:g} s is needed")
    if np.ptp(rec.y) < MIN_TRAVEL_M:
        raise LogError(f"{src}: {rec.label('y')} shows no motion (travel {np.ptp(rec.y):.3g} m < "
                       f"{MIN_TRAVEL_M:g} m); identification needs the axis to move")
    if np.ptp(rec.u) < MIN_INPUT_RANGE:
        raise LogError(f"{src}: {rec.label('u')} is constant (range {np.ptp(rec.u):.3g} < "
                       f"{MIN_INPUT_RANGE:g}); identification needs a varying input")
    if rec.gain is not None and not (isinstance(rec.gain, (int, float)) and math.isfinite(rec.gain)
                                     and 0 < rec.gain <= MAX_GAIN):
        raise LogError(f"{src}: gain {summarize(rec.gain)} N/V is not a positive number up to {MAX_GAIN:g} N/V")
    return rec


def _where(rec: Record, i: int) -> str:
    """`, line L` for CSV records (their line numbers are in ``rec.header['_lines']``)."""
    lines = rec.header.get("_lines") if isinstance(rec.header, dict) else None
    return f", line {int(lines[i])}" if lines is not None and 0 <= i < len(lines) else ""


AXIS_NEEDED = ("y", "u", "enabled")


def _read_runlog(path: str, axis: str | None) -> Record:
    log = read_log(path)
    axes = log.axes
    if not axes:
        raise LogError(f"{path}: the run log header lists no axes")
    name = axis or axes[0]
    if name not in axes:
        raise LogError(f"{path}: no axis {name!r} in the log; axes: {', '.join(axes)}")
    try:
        a = log.axis(name)
        t = log.col("t")
    except KeyError as exc:
        raise LogError(f"{path}: {exc.args[0]}") from None
    missing = [f"{name}.{f}" for f in AXIS_NEEDED if f not in a]
    if missing:
        raise LogError(f"{path}: no column {missing[0]!r} in the log; identification needs "
                       f"t, {name}.y, {name}.u and {name}.enabled")
    if log.data.shape[0] == 0:
        raise LogError(f"{path}: the run log has no records")
    # keep the cycles where the amplifier was enabled (the start-up/shut-down cycles are not dynamics),
    # up to the run's duration (a run's end is a controlled stop: its tail is not the program's)
    on = a["enabled"] > 0.5
    end = log.header.get("program_end_s")
    if isinstance(end, (int, float)) and not isinstance(end, bool):
        on &= t < end
    if on.sum() < MIN_SAMPLES:
        raise LogError(f"{path}: axis {name!r} has only {int(on.sum())} enabled cycles "
                       f"(column '{name}.enabled'); at least {MIN_SAMPLES} are needed")
    idx = _longest_run(on)
    gain = _dig(log.header, "driver", "simulated", name, "a1_N_per_V")
    if gain is None:
        gain = _dig(log.header, "config", "axes", name, "driver", "a1_N_per_V")
    if gain is not None:
        if isinstance(gain, bool) or not isinstance(gain, (int, float)):
            raise LogError(f"{path}: the header's a1_N_per_V of axis {name!r} is {summarize(gain)}; "
                           "a positive number (N/V) is required")
        gain = float(gain)
    yd = a["x_d"][idx].copy() if "x_d" in a else None
    return Record(t=t[idx].copy(), y=a["y"][idx].copy(), u=a["u"][idx].copy(), yd=yd,
                  gain=gain if gain else None, source=str(path), axis=name, header=log.header,
                  labels={k: f"column '{name}.{c}'" for k, c in (("y", "y"), ("u", "u"), ("yd", "x_d"))}
                  | {"t": "column 't'"})


def _dig(d, *keys):
    """d[k1][k2]... or None when a level is missing or not a mapping."""
    for k in keys:
        if not isinstance(d, dict):
            return None
        d = d.get(k)
    return d


def _longest_run(mask: np.ndarray) -> np.ndarray:
    """Indices of the longest run of True in a boolean array (N,)."""
    starts, ends = runs(mask)
    k = int(np.argmax(ends - starts))
    return np.arange(starts[k], ends[k])


def _read_csv(path: str, mapping: dict) -> Record:
    text = read_text(path, "CSV data file", MAX_DATA_BYTES)
    if "\x00" in text:
        line = text[: text.index("\x00")].count("\n") + 1
        raise LogError(f"{path}: line {line}: a NUL byte; DATA must be a CSV text file (t,y,u[,yd])")
    reader = csv.reader(io.StringIO(text, newline=""))
    try:
        head = None
        for row in reader:
            if row and any(c.strip() for c in row):
                head = [h.strip() for h in row]
                head_line = reader.line_num
                break
        if head is None:
            raise LogError(f"{path}: empty CSV file; a header line with t,y,u (optional yd) is required")
        names = {k: mapping.get(k, k) for k in ("t", "y", "u", "yd")}
        for k in ("t", "y", "u"):
            if names[k] not in head:
                shown = summarize(",".join(head), 80)
                hint = ("; the first line holds numbers: a header line is needed" if _numeric(head) else "")
                raise LogError(f"{path}: missing column {names[k]!r}; header (line {head_line}) is {shown}"
                               f"{hint}; required: t,y,u (SI units), optional yd, or --map")
        dup = next((h for h in head if head.count(h) > 1), None)
        if dup is not None and dup in names.values():
            raise LogError(f"{path}: column {dup!r} appears twice in the header")
        use = {k: head.index(v) for k, v in names.items() if v in head}
        cols = {k: [] for k in use}
        lines = []
        for row in reader:
            if not row or not any(c.strip() for c in row):
                continue
            ln = reader.line_num
            if len(row) != len(head):
                raise LogError(f"{path}: line {ln}: ragged row of {len(row)} field(s), the header has "
                               f"{len(head)}; every row needs one value per header column")
            for k, j in use.items():
                c = row[j].strip()
                if not c:
                    raise LogError(f"{path}: line {ln}: column {names[k]!r} is empty; a number is required")
                try:
                    v = float(c)
                except ValueError:
                    raise LogError(f"{path}: line {ln}: column {names[k]!r} value {summarize(c, 40)} "
                                   "is not a number") from None
                cols[k].append(v)
            lines.append(ln)
    except csv.Error as exc:
        raise LogError(f"{path}: line {reader.line_num}: not valid CSV ({exc})") from None
    if not lines:
        raise LogError(f"{path}: the CSV file has a header ({','.join(head)[:80]}) but no data rows")
    arr = {k: np.asarray(v, dtype=float) for k, v in cols.items()}
    return Record(t=arr["t"], y=arr["y"], u=arr["u"], yd=arr.get("yd"), source=str(path),
                  header={"_lines": np.asarray(lines)},
                  labels={k: f"column {names[k]!r}" for k in names})


def _numeric(fields) -> bool:
    try:
        [float(f) for f in fields]
        return True
    except ValueError:
        return False


def _mat_vector(path: str, mat: dict, var: str, what: str) -> np.ndarray:
    """A MATLAB variable as a real float vector (N,), or LogError naming the variable."""
    v = mat[var]
    lab = f"variable {var!r}" + (f" ({what})" if what else "")
    if not isinstance(v, np.ndarray):
        raise LogError(f"{path}: {lab} is a {type(v).__name__} (sparse or not an array); "
                       "a real numeric vector is required")
    kind = v.dtype.kind
    if v.dtype.names:
        kind_s = "a struct"
    elif kind == "O":
        kind_s = "a cell array or struct"
    elif kind in "US":
        kind_s = "a string"
    elif kind == "c":
        kind_s = "complex"
    elif kind not in "biuf":
        kind_s = f"of type {v.dtype}"
    else:
        kind_s = None
    if kind_s:
        raise LogError(f"{path}: {lab} is {kind_s}; a real numeric vector is required")
    if v.ndim > 2 or (v.ndim == 2 and min(v.shape) > 1):
        raise LogError(f"{path}: {lab} has shape {'x'.join(map(str, v.shape))}; a vector (Nx1 or 1xN) "
                       "is required")
    return np.asarray(v, dtype=float).ravel()


def _read_mat(path: str, mapping: dict, gain_spec: str | None) -> Record:
    from scipy.io import loadmat
    try:
        mat = loadmat(path)
    except NotImplementedError:
        raise LogError(f"{path}: a MATLAB v7.3 (HDF5) file; save it with -v7 or as CSV") from None
    except Exception as exc:  # scipy raises several types for damaged files
        msg = " ".join(str(exc).split())[:120] or type(exc).__name__
        raise LogError(f"{path}: not a readable MATLAB file ({msg})") from None
    names = {k: mapping.get(k, k) for k in ("t", "y", "u", "yd")}
    avail = sorted(k for k in mat if not k.startswith("__"))
    shown = summarize(", ".join(avail), 100)
    out = {}
    for k, v in names.items():
        if v not in avail:
            if k == "yd" and "yd" not in mapping:
                continue
            raise LogError(f"{path}: no variable {v!r} for {k!r}; variables: {shown}; "
                           "use --map t=..,y=..,u=..[,yd=..]")
        out[k] = _mat_vector(path, mat, v, k if v != k else "")
    gain = _gain(gain_spec, path, mat, avail)
    labels = {k: f"variable {v!r}" + (f" ({k})" if v != k else "") for k, v in names.items()}
    return Record(t=out["t"], y=out["y"], u=out["u"], yd=out.get("yd"), gain=gain, source=str(path),
                  labels=labels)


def _gain(spec, path, mat=None, avail=()):
    if spec is None:
        return None
    try:
        g = float(spec)
    except ValueError:
        g = None
    if g is None and mat is not None and spec in avail:
        a = _mat_vector(path, mat, spec, "gain")
        if a.size != 1:
            raise LogError(f"{path}: gain variable {spec!r} has {a.size} values; one number (N/V) is required")
        g = float(a[0])
    if g is None:
        raise LogError(f"{path}: --gain {summarize(spec, 40)} is neither a number (N/V) nor a variable of the file"
                       + (f" ({summarize(', '.join(avail), 100)})" if avail else ""))
    if not (math.isfinite(g) and 0 < g <= MAX_GAIN):
        raise LogError(f"{path}: gain {spec!r} = {g:g} N/V; a positive number up to {MAX_GAIN:g} N/V is required")
    return g


def load_record(path: str, mapping: str | dict | None = None, gain: str | None = None,
                axis: str | None = None) -> Record:
    """Read DATA for ``motorctl identify`` and check it.

    Args:
        path: a motorctl run log, a ``.csv`` (header with t,y,u[,yd]) or a ``.mat`` file.
        mapping: ``--map`` text or dict (keys t, y, u, yd → column/variable names).
        gain: ``--gain``: a number in N/V or a variable of the MATLAB file (force = gain·u).
        axis: axis of a run log (default: the first).
    Returns:
        A checked :class:`Record`.
    Raises:
        InputError: missing, not a regular file (FIFO, device, directory), larger than
        :data:`MAX_DATA_BYTES`, unreadable or not UTF-8 (CSV).
        LogError: bad data (see :func:`check_record`).
    """
    mp = parse_map(mapping) if isinstance(mapping, (str, type(None))) else dict(mapping)
    regular_file(path, "data", MAX_DATA_BYTES)     # before any open(): a FIFO would block
    try:
        with open(path, "rb") as fh:
            head = fh.read(128)
    except OSError as exc:
        raise InputError(f"{path}: cannot read the data file ({exc.strerror or exc})") from None
    if not head:
        raise LogError(f"{path}: empty file; DATA must be a run log, a CSV file (t,y,u[,yd]) or a MATLAB file")
    if head.startswith(MAGIC):
        rec = _read_runlog(path, axis)
        if gain is not None:
            rec.gain = _gain(gain, path)
    elif str(path).lower().endswith(".mat") or head.startswith(b"MATLAB"):
        rec = _read_mat(path, mp, gain)
    else:
        rec = _read_csv(path, mp)
        rec.gain = _gain(gain, path)
    check_record(rec)
    rec.header.pop("_lines", None)
    return rec
