"""``motorctl identify`` at its input boundary: every malformed DATA (CSV, MATLAB, run log, not a
file at all) and every physically meaningless fit exits 2 with ONE line on stderr
(``motorctl: error: ...``), no traceback, quickly; valid records still exit 0.

All runs are in-process through :func:`motorctl.cli.main`.
"""

from __future__ import annotations

import json
import os
import struct
import time
import warnings

import numpy as np
import pytest

from motorctl.cli import main
from motorctl.recorder.runlog import MAGIC, LogWriter
from harness import emps_path

#: the EMPS record: $MOTORCTL_DATA_DIR, else the shared data directory beside the clone (or None)
EMPS = emps_path()
#: each malformed case must be refused within this much CPU time of this process [s]
MAX_CASE_S = 5.0


# ---------------------------------------------------------------------------- synthetic records
def _clean(n=3000, ts=1e-3, sign=1.0):
    """t, y, u of a mass with viscous and Coulomb friction driven by a multisine (SI units):
    M = 10 kg, A1 = 50 N/V, Fv = 20 N s/m, Fc = 5 N. ``sign`` = -1 flips u (wrong sign)."""
    t = np.arange(n) * ts
    u = 2.0 * np.sin(2 * np.pi * t) + np.sin(2 * np.pi * 3.7 * t + 1) + 0.5 * np.sin(2 * np.pi * 11 * t)
    M, A1, Fv, Fc = 10.0, 50.0, 20.0, 5.0
    x = v = 0.0
    y = np.empty(n)
    for k in range(n):
        y[k] = x
        v += (A1 * u[k] - Fv * v - Fc * np.tanh(v / 1e-3)) / M * ts
        x += v * ts
    y = y + 1e-7 * np.random.default_rng(0).standard_normal(n)
    return t, y, sign * u


def _csv_text(cols, header="t,y,u"):
    rows = np.column_stack(cols)
    return header + "\n" + "\n".join(",".join(f"{v:.10g}" for v in r) for r in rows) + "\n"


def _write(path, data):
    if isinstance(data, str):
        data = data.encode()
    path.write_bytes(data)
    return str(path)


def _savemat(path, **vars_):
    from scipy.io import savemat
    savemat(str(path), vars_)
    return str(path)


def _runlog(path, header=None, drop=(), raw_header=None):
    """A run log of the clean record on axis X (enabled throughout); ``header`` updates the
    header, ``drop`` leaves columns out, ``raw_header`` writes that JSON text as the header."""
    if raw_header is not None:
        blob = raw_header.encode()
        blob += b" " * ((-(len(MAGIC) + 8 + len(blob))) % 8)
        path.write_bytes(MAGIC + struct.pack("<Q", len(blob)) + blob + b"\0" * 64)
        return str(path)
    t, y, u = _clean()
    cols = {"t": t, "X.y": y, "X.u": u, "X.x_d": y, "X.enabled": np.ones_like(t)}
    for c in drop:
        cols.pop(c)
    h = {"columns": list(cols), "axes": ["X"], "period_s": 1e-3}
    h.update(header or {})
    with LogWriter(str(path), h) as w:
        w.append(np.column_stack(list(cols.values())))
    return str(path)


def _cases():
    """name -> builder(tmp_path) returning (argv after 'identify', needle in the message)."""
    t, y, u = _clean()
    c = {}

    # --- CSV
    c["empty_file"] = lambda d: ([_write(d / "e.csv", "")], "empty")
    c["blank_lines_only"] = lambda d: ([_write(d / "b.csv", "\n \n\n")], "empty CSV")
    c["header_only"] = lambda d: ([_write(d / "h.csv", "t,y,u\n")], "no data rows")
    c["ragged_row"] = lambda d: ([_write(d / "r.csv", _csv_text((t, y, u)).replace("\n0.01,", "\n0.01,7,", 1))],
                                 "line 12: ragged row")
    c["time_in_ms"] = lambda d: ([_write(d / "ms.csv", _csv_text((t * 1e3, y, u)))], "milliseconds")
    c["time_in_us"] = lambda d: ([_write(d / "us.csv", _csv_text((t * 1e6, y, u)))], "microseconds")
    c["values_1e300"] = lambda d: ([_write(d / "big.csv", _csv_text((t, y * 1e300, u * 1e300)))], "not a physical")
    c["positions_1e200"] = lambda d: ([_write(d / "y200.csv", _csv_text((t, y * 1e200, u)))], "|y| < 1000 m")
    c["input_1e5_V"] = lambda d: ([_write(d / "u5.csv", _csv_text((t, y, u * 1e5)))], "|u| < 10000")
    c["time_1e300"] = lambda d: ([_write(d / "t300.csv", _csv_text((t + 1e300, y, u)))], "column 't'")

    def nan_row(d):
        yy = y.copy()
        yy[500] = np.nan
        return [_write(d / "nan.csv", _csv_text((t, yy, u)))], "line 502"
    c["nan_row"] = nan_row

    def inf_u(d):
        uu = u.copy()
        uu[7] = np.inf
        return [_write(d / "inf.csv", _csv_text((t, y, uu)))], "non-finite"
    c["inf_in_u"] = inf_u

    def non_monotonic(d):
        tt = t.copy()
        tt[300], tt[301] = tt[301], tt[300]
        return [_write(d / "nm.csv", _csv_text((tt, y, u)))], "not increasing"
    c["non_monotonic_time"] = non_monotonic
    c["repeated_time"] = lambda d: ([_write(d / "rep.csv", _csv_text((np.floor(t * 100) / 100, y, u)))],
                                    "not increasing")
    c["slow_sampling_1s"] = lambda d: ([_write(d / "slow.csv", _csv_text((np.arange(300.0), y[:300] * 1e3, u[:300])))],
                                       "median step")
    c["non_utf8"] = lambda d: ([_write(d / "l1.csv", ("t,y,u,note\n" + _csv_text((t, y, u), "x")[2:]
                                                       ).encode().replace(b"\n0.5,", b"\n0.5\xe9,", 1))],
                               "not UTF-8")
    c["utf16"] = lambda d: ([_write(d / "u16.csv", _csv_text((t, y, u)).encode("utf-16"))], "UTF-16")
    c["word_in_cell"] = lambda d: ([_write(d / "w.csv", "t,y,u\n" + "\n".join(
        f"{a:.6g},{'oops' if i == 3 else f'{b:.6g}'},{e:.6g}" for i, (a, b, e) in enumerate(zip(t, y, u))))],
        "line 5: column 'y' value 'oops' is not a number")
    c["empty_cell"] = lambda d: ([_write(d / "ec.csv", "t,y,u\n" + "\n".join(
        f"{a:.6g},{'' if i == 9 else f'{b:.6g}'},{e:.6g}" for i, (a, b, e) in enumerate(zip(t, y, u))))],
        "line 11: column 'y' is empty")
    c["no_header"] = lambda d: ([_write(d / "nh.csv", _csv_text((t, y, u)).split("\n", 1)[1])], "holds numbers")
    c["duplicate_column"] = lambda d: ([_write(d / "dup.csv", _csv_text((t, y, u, u), "t,y,u,u"))], "twice")
    c["binary_garbage"] = lambda d: ([_write(d / "g.csv", bytes(range(256)) * 10)], "")
    c["nul_bytes"] = lambda d: ([_write(d / "nul.csv", b"t,y,u\n0,0,\x00\x00\n")], "NUL")
    c["constant_input"] = lambda d: ([_write(d / "cu.csv", _csv_text((t, y, np.ones_like(u))))], "constant")
    c["no_motion"] = lambda d: ([_write(d / "nm0.csv", _csv_text((t, np.zeros_like(y), u)))], "no motion")
    c["gain_nan"] = lambda d: ([_write(d / "gn.csv", _csv_text((t, y, u))), "--gain", "nan"], "positive number")
    c["gain_negative"] = lambda d: ([_write(d / "gneg.csv", _csv_text((t, y, u))), "--gain", "-80"], "positive")
    c["wrong_sign_of_u"] = lambda d: ([_write(d / "neg.csv", _csv_text(_clean(sign=-1.0))), "--no-closed-loop"],
                                      "sign of u")

    def unrelated(seed, needle):
        def build(d):
            rng = np.random.default_rng(seed)
            yy = np.cumsum(rng.standard_normal(len(t))) * 1e-4
            return [_write(d / f"noise{seed}.csv", _csv_text((t, yy, rng.standard_normal(len(t))))),
                    "--no-closed-loop"], needle
        return build
    # a random walk against white noise: theta1 < 0 (seed 3), theta1 > 0 but a simulation fit
    # of -1500 % (seed 0), or a simulation that overflows (seed 7)
    c["unrelated_theta1_negative"] = unrelated(3, "theta1 = ")
    c["unrelated_simfit_negative"] = unrelated(0, "< 0 %")
    c["unrelated_simfit_diverges"] = unrelated(7, "diverges")

    # --- not a regular file
    def fifo(d):
        p = d / "pipe.csv"
        os.mkfifo(p)
        return [str(p)], "FIFO"
    c["fifo"] = fifo
    c["directory"] = lambda d: ([str(d)], "directory")
    c["dev_zero"] = lambda d: (["/dev/zero"], "device")
    c["missing_file"] = lambda d: ([str(d / "nope.csv")], "no such file")

    # --- MATLAB
    c["mat_string_var"] = lambda d: ([_savemat(d / "s.mat", t=t, y=y, u="volts")], "variable 'u' is a string")
    c["mat_struct_var"] = lambda d: ([_savemat(d / "st.mat", t=t, y={"a": y, "b": 1.0}, u=u)], "variable 'y' is a")
    c["mat_cell_var"] = lambda d: ([_savemat(d / "c.mat", t=t, y=y, u=np.array([u, "x"], dtype=object))],
                                   "variable 'u' is a cell")
    c["mat_complex"] = lambda d: ([_savemat(d / "cx.mat", t=t, y=y + 1j * y, u=u)], "variable 'y' is complex")
    c["mat_2d_t"] = lambda d: ([_savemat(d / "t2.mat", t=np.column_stack([t, t]), y=y, u=u)],
                               "variable 't' has shape 3000x2")
    c["mat_mapped_2d"] = lambda d: ([_savemat(d / "m2.mat", time=t, qm=np.column_stack([y, y]), vir=u),
                                     "--map", "t=time,y=qm,u=vir"], "variable 'qm' (y) has shape")
    c["mat_length_mismatch"] = lambda d: ([_savemat(d / "lm.mat", t=t, y=y[:-5], u=u)], "variable 'y' has 2995")
    c["mat_garbage"] = lambda d: ([_write(d / "gb.mat", b"MATLAB 5.0 MAT-file" + b"\xff" * 300)], "MATLAB")
    c["mat_text_named_mat"] = lambda d: ([_write(d / "txt.mat", _csv_text((t, y, u)))], "MATLAB")
    c["mat_gain_string"] = lambda d: ([_savemat(d / "gs.mat", t=t, y=y, u=u, g="abc"), "--gain", "g"],
                                      "variable 'g' (gain) is a string")
    c["mat_gain_vector"] = lambda d: ([_savemat(d / "gv.mat", t=t, y=y, u=u, g=[1.0, 2.0]), "--gain", "g"],
                                      "2 values")
    c["mat_ms_time"] = lambda d: ([_savemat(d / "ms.mat", t=t * 1e3, y=y, u=u)], "milliseconds")
    c["mat_missing_var"] = lambda d: ([_savemat(d / "mv.mat", t=t, y=y)], "no variable 'u'")

    # --- run logs
    c["log_header_list"] = lambda d: ([_runlog(d / "hl.log", raw_header="[1, 2, 3]")], "damaged header")
    c["log_axes_5"] = lambda d: ([_runlog(d / "a5.log", raw_header='{"columns": ["t"], "axes": 5}')],
                                 "'axes' is not a list")
    c["log_header_not_json"] = lambda d: ([_runlog(d / "nj.log", raw_header="{not json")], "damaged header")
    c["log_gain_negative"] = lambda d: ([_runlog(d / "gneg.log", {"driver": {"simulated": {"X": {"a1_N_per_V": -3}}}})],
                                        "positive")
    c["log_gain_arg_negative"] = lambda d: ([_runlog(d / "ga.log"), "--gain", "-1"], "positive")
    c["log_gain_text"] = lambda d: ([_runlog(d / "gt.log", {"driver": {"simulated": {"X": {"a1_N_per_V": "x"}}}})],
                                    "a1_N_per_V")
    c["log_no_enabled_column"] = lambda d: ([_runlog(d / "ne.log", drop=("X.enabled",))], "X.enabled")
    c["log_no_u_column"] = lambda d: ([_runlog(d / "nu.log", drop=("X.u",))], "X.u")
    c["log_no_axes"] = lambda d: ([_runlog(d / "na.log", {"axes": []})], "no axes")
    c["log_no_records"] = lambda d: ([_runlog(d / "nr.log", raw_header='{"columns": ["t", "X.y", "X.u", '
                                                                      '"X.enabled"], "axes": ["X"]}')], "")
    return c


CASES = _cases()


def test_corpus_is_large():
    assert len(CASES) >= 30


@pytest.mark.parametrize("name", sorted(CASES))
def test_malformed_input_exits_2_with_one_line(name, tmp_path, capsys):
    argv, needle = CASES[name](tmp_path)
    capsys.readouterr()
    t0 = time.process_time()          # CPU time of this process: not the loaded host's wall time
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        rc = main(["identify", *argv])
    dt = time.process_time() - t0
    assert not [w for w in caught if issubclass(w.category, RuntimeWarning)], (name, caught)
    out, err = capsys.readouterr()
    assert rc == 2, (name, rc, err)
    assert err.startswith("motorctl: error: ") and err.endswith("\n"), err
    assert err.count("\n") == 1, err
    assert "Traceback" not in err and out == ""
    assert needle in err, (name, err)
    assert dt < MAX_CASE_S, (name, dt)


def test_file_over_the_size_cap_is_refused_before_reading(tmp_path, capsys, monkeypatch):
    import motorctl.ident.data as data
    t, y, u = _clean()
    p = _write(tmp_path / "big.csv", _csv_text((t, y, u)))
    monkeypatch.setattr(data, "MAX_DATA_BYTES", 1000)
    assert main(["identify", p]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "too large" in err and "at most 1000 bytes" in err


def test_write_config_leaves_nothing_when_the_fit_is_refused(tmp_path, capsys):
    out = tmp_path / "tuned.yaml"
    p = _write(tmp_path / "neg.csv", _csv_text(_clean(sign=-1.0)))
    assert main(["identify", p, "--config", "configs/gantry.yaml", "--write-config", str(out),
                 "--no-closed-loop"]) == 2
    assert not out.exists()
    assert "theta1" in capsys.readouterr().err


# ---------------------------------------------------------------------------- valid input still works
def test_clean_csv_exits_0(tmp_path, capsys):
    p = _write(tmp_path / "clean.csv", _csv_text(_clean()))
    assert main(["identify", p, "--json", "--no-closed-loop"]) == 0
    s = json.loads(capsys.readouterr().out)
    assert abs(s["nominal"]["theta"][0] / 0.2 - 1) < 0.02        # M / A1 = 10 / 50
    assert s["nominal"]["simulation_fit_percent"] > 90


def test_csv_with_bom_crlf_and_extra_text_column_exits_0(tmp_path, capsys):
    t, y, u = _clean()
    text = "t,y,u,note\r\n" + "".join(f"{a:.10g},{b:.10g},{e:.10g},ok\r\n" for a, b, e in zip(t, y, u))
    p = _write(tmp_path / "bom.csv", b"\xef\xbb\xbf" + text.encode())
    assert main(["identify", p, "--json", "--no-closed-loop"]) == 0
    assert json.loads(capsys.readouterr().out)["samples"] == len(t)


def test_clean_runlog_and_mat_exit_0(tmp_path, capsys):
    t, y, u = _clean()
    assert main(["identify", _runlog(tmp_path / "ok.log"), "--json", "--no-closed-loop"]) == 0
    assert json.loads(capsys.readouterr().out)["axis"] == "X"
    # odd header sections the reader does not need are ignored, not a traceback
    odd = _runlog(tmp_path / "odd.log", {"driver": "sim", "config": 5, "driver_type": "sim"})
    assert main(["identify", odd, "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["gain_N_per_V"] is None
    p = _savemat(tmp_path / "ok.mat", time=t.reshape(1, -1), qm=y.reshape(-1, 1), vir=u, g=50.0)
    assert main(["identify", p, "--map", "t=time,y=qm,u=vir", "--gain", "g", "--json", "--no-closed-loop"]) == 0
    s = json.loads(capsys.readouterr().out)
    assert abs(s["nominal"]["physical"]["mass_kg"] / 10 - 1) < 0.02


def test_emps_still_exits_0(capsys):
    if EMPS is None:
        pytest.skip("EMPS data not available")
    assert main(["identify", EMPS, "--map", "t=t,y=qm,u=vir,yd=qg", "--gain", "gtau", "--json",
                 "--no-closed-loop"]) == 0
    s = json.loads(capsys.readouterr().out)
    assert abs(s["nominal"]["physical"]["mass_kg"] / 95.1 - 1) < 0.02
