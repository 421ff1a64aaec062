"""Reading identification data: motorctl run logs, CSV files and MATLAB files (issue 5, item 1).

All readers return a :class:`Record` (SI units: t [s], y [m], u [V], optional yd [m]) after the
same checks (:func:`check_record`); bad data raise :class:`motorctl.recorder.runlog.LogError` with one line
naming the file, the column and what is allowed.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass, field

import numpy as np

from motorctl.recorder.runlog import LogError, MAGIC, read_log

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

    @property
    def period_s(self) -> float:
        return float((self.t[-1] - self.t[0]) / (len(self.t) - 1))

    @property
    def n(self) -> int:
        return len(self.t)


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
    """Validate a record: lengths, finite values, uniform increasing time, length, motion.

    Raises:
        LogError: naming the file and the column, what was wrong and what is allowed.
    """
    src = rec.source or "data"
    n = len(rec.t)
    for name in ("t", "y", "u", "yd"):
        a = getattr(rec, name)
        if a is None:
            continue
        if a.ndim != 1 or len(a) != n:
            raise LogError(f"{src}: column {name!r} has {a.size} values, expected {n} (same as 't')")
        bad = ~np.isfinite(a)
        if bad.any():
            i = int(np.argmax(bad))
            raise LogError(f"{src}: column {name!r} has {int(bad.sum())} non-finite value(s) "
                           f"(first at sample {i}); only finite numbers are allowed")
    if n < MIN_SAMPLES:
        raise LogError(f"{src}: only {n} samples; at least {MIN_SAMPLES} and {MIN_DURATION_S:g} s are needed")
    dt = np.diff(rec.t)
    if np.any(dt <= 0):
        i = int(np.argmax(dt <= 0))
        raise LogError(f"{src}: column 't' is not increasing at sample {i + 1} "
                       f"(t = {rec.t[i]:.6g} then {rec.t[i + 1]:.6g} s); time must strictly increase")
    ts = float(np.median(dt))
    if np.max(np.abs(dt - ts)) > PERIOD_RTOL * ts + 1e-12:
        i = int(np.argmax(np.abs(dt - ts)))
        raise LogError(f"{src}: column 't' is not uniformly sampled (step {dt[i]:.6g} s at sample {i + 1}, "
                       f"median {ts:.6g} s); a constant sample period is required")
    if rec.t[-1] - rec.t[0] < MIN_DURATION_S:
        raise LogError(f"{src}: record lasts {rec.t[-1] - rec.t[0]:.3g} s; at least {MIN_DURATION_S:g} s is needed")
    if np.ptp(rec.y) < MIN_TRAVEL_M:
        raise LogError(f"{src}: column 'y' shows no motion (travel {np.ptp(rec.y):.3g} m < {MIN_TRAVEL_M:g} m); "
                       "identification needs the axis to move")
    if np.ptp(rec.u) == 0.0:
        raise LogError(f"{src}: column 'u' is constant; identification needs a varying input")
    if rec.gain is not None and not (np.isfinite(rec.gain) and rec.gain > 0):
        raise LogError(f"{src}: gain {rec.gain!r} N/V is not a positive number")
    return rec


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
    if log.data.shape[0] == 0:
        raise LogError(f"{path}: the run log has no records")
    # keep the cycles where the amplifier was enabled (the start-up/shut-down cycles are not dynamics)
    on = a["enabled"] > 0.5
    if on.sum() < MIN_SAMPLES:
        raise LogError(f"{path}: axis {name!r} has only {int(on.sum())} enabled cycles "
                       f"(column '{name}.enabled'); at least {MIN_SAMPLES} are needed")
    idx = _longest_run(on)
    sim = log.header.get("driver", {}).get("simulated", {}).get(name, {})
    gain = sim.get("a1_N_per_V")
    if gain is None:
        try:
            gain = log.header["config"]["axes"][name]["driver"].get("a1_N_per_V")
        except (KeyError, TypeError, AttributeError):
            gain = None
    return Record(t=t[idx].copy(), y=a["y"][idx].copy(), u=a["u"][idx].copy(), yd=a["x_d"][idx].copy(),
                  gain=float(gain) if gain else None, source=str(path), axis=name, header=log.header)


def _longest_run(mask: np.ndarray) -> np.ndarray:
    """Indices of the longest run of True in a boolean array (N,)."""
    m = np.concatenate(([False], mask, [False])).astype(np.int8)
    d = np.diff(m)
    starts, ends = np.flatnonzero(d == 1), np.flatnonzero(d == -1)
    k = int(np.argmax(ends - starts))
    return np.arange(starts[k], ends[k])


def _read_csv(path: str, mapping: dict) -> Record:
    with open(path, newline="") as fh:
        reader = csv.reader(fh)
        try:
            head = [h.strip() for h in next(reader)]
        except StopIteration:
            raise LogError(f"{path}: empty CSV file; a header line with t,y,u (optional yd) is required") from None
        rows = [r for r in reader if r and any(c.strip() for c in r)]
    names = {k: mapping.get(k, k) for k in ("t", "y", "u", "yd")}
    for k in ("t", "y", "u"):
        if names[k] not in head:
            raise LogError(f"{path}: missing column {names[k]!r}; header is {','.join(head)}; "
                           "required: t,y,u (SI units), optional yd, or --map")
    try:
        data = np.array([[float(c) if c.strip() else np.nan for c in r] for r in rows], dtype=float)
    except ValueError as exc:
        raise LogError(f"{path}: a value is not a number ({exc})") from None
    if data.ndim != 2 or data.shape[1] != len(head):
        raise LogError(f"{path}: rows do not all have {len(head)} fields like the header")
    col = {h: data[:, i] for i, h in enumerate(head)}
    yd = col.get(names["yd"])
    return Record(t=col[names["t"]], y=col[names["y"]], u=col[names["u"]], yd=yd, source=str(path))


def _read_mat(path: str, mapping: dict, gain_spec: str | None) -> Record:
    from scipy.io import loadmat
    try:
        mat = loadmat(path)
    except Exception as exc:  # scipy raises several types for damaged files
        raise LogError(f"{path}: not a readable MATLAB file ({exc})") from None
    names = {k: mapping.get(k, k) for k in ("t", "y", "u", "yd")}
    avail = sorted(k for k in mat if not k.startswith("__"))
    out = {}
    for k, v in names.items():
        if v not in mat:
            if k == "yd" and "yd" not in mapping:
                continue
            raise LogError(f"{path}: no variable {v!r} for {k!r}; variables: {', '.join(avail)}; "
                           "use --map t=..,y=..,u=..[,yd=..]")
        out[k] = np.asarray(mat[v], dtype=float).ravel()
    gain = _gain(gain_spec, path, mat, avail)
    return Record(t=out["t"], y=out["y"], u=out["u"], yd=out.get("yd"), gain=gain, source=str(path))


def _gain(spec, path, mat=None, avail=()):
    if spec is None:
        return None
    try:
        return float(spec)
    except ValueError:
        pass
    if mat is not None and spec in mat:
        g = np.asarray(mat[spec], dtype=float).ravel()
        if g.size != 1:
            raise LogError(f"{path}: gain variable {spec!r} has {g.size} values; one number (N/V) is required")
        return float(g[0])
    raise LogError(f"{path}: --gain {spec!r} is neither a number (N/V) nor a variable of the file"
                   + (f" ({', '.join(avail)})" if avail else ""))


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
        LogError: unreadable or bad data (see :func:`check_record`). FileNotFoundError.
    """
    mp = parse_map(mapping) if isinstance(mapping, (str, type(None))) else dict(mapping)
    with open(path, "rb") as fh:
        head = fh.read(128)
    if head.startswith(MAGIC):
        rec = _read_runlog(path, axis)
        if gain is not None:
            rec.gain = _gain(gain, path)
    elif str(path).lower().endswith(".mat") or head.startswith(b"MATLAB"):
        rec = _read_mat(path, mp, gain)
    else:
        rec = _read_csv(path, mp)
        rec.gain = _gain(gain, path)
    return check_record(rec)
