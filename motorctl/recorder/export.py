"""``motorctl export``: a run log as CSV or as a MATLAB .mat file."""

from __future__ import annotations

import csv

import numpy as np

from motorctl.recorder.runlog import RunLog


def export_csv(log: RunLog, out: str) -> int:
    """Write a run log as CSV (one header line with the column names). Returns rows written."""
    with open(out, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(log.columns)
        w.writerows(log.data.tolist())
    return log.data.shape[0]


def mat_name(column: str) -> str:
    """MATLAB variable name of a column: 'X.theta_hat1' → 'X_theta_hat1'."""
    name = "".join(ch if ch.isalnum() or ch == "_" else "_" for ch in column)
    return name if name[:1].isalpha() else "v_" + name


def export_mat(log: RunLog, out: str) -> int:
    """Write a run log as a MATLAB .mat file (scipy.io.savemat, format 5).

    Variables: ``data`` (N, W), ``columns`` (cell array of names), ``period_s``, ``axes``, and
    one (N, 1) column vector per column named by :func:`mat_name`. Returns rows written.
    """
    from scipy.io import savemat
    d = {"data": log.data, "columns": np.array(log.columns, dtype=object),
         "period_s": float(log.header.get("period_s", 0.0)),
         "axes": np.array(log.axes, dtype=object)}
    for j, c in enumerate(log.columns):
        d[mat_name(c)] = log.data[:, j:j + 1]
    savemat(out, d, do_compression=False, oned_as="column")
    return log.data.shape[0]


