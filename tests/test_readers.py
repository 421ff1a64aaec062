"""Readers never harm a run log and never leave half a file: ``export`` and ``plot`` refuse an
output that is the log (or any run log), a damaged log is one line and exit 2 with nothing
written, and a write that fails (a file-size limit, as a full disk fails) leaves no partial
output and names the file."""

from __future__ import annotations

import json
import resource
import struct
import subprocess

import numpy as np
import pytest

from conftest import MOTORCTL, REPO
from motorctl.loop.records import RecordLayout
from motorctl.recorder.runlog import MAGIC, LogWriter

TS = 2e-4


def _write_log(path, rows: int = 3000) -> bytes:
    lay = RecordLayout(["X"])
    header = {"columns": lay.columns, "units": lay.units, "axes": ["X"], "period_s": TS}
    data = np.zeros((rows, len(lay.columns)))
    data[:, lay.cycle("t")] = np.arange(rows) * TS
    data[:, lay.index("X.e")] = 1e-6 * np.sin(np.arange(rows) / 50)
    with LogWriter(str(path), header) as w:
        w.append(data)
    return path.read_bytes()


@pytest.fixture(scope="module")
def logs(tmp_path_factory):
    d = tmp_path_factory.mktemp("readers")
    good = d / "run.mclog"
    _write_log(good)
    # the same records under a header that lists one column fewer than each row holds
    bad = d / "damaged.mclog"
    blob = good.read_bytes()
    (hlen,) = struct.unpack_from("<Q", blob, len(MAGIC))
    start = len(MAGIC) + 8
    header = json.loads(blob[start:start + hlen])
    header["columns"] = header["columns"][:-1]
    header["units"] = header["units"][:-1]
    new = json.dumps(header).encode()
    bad.write_bytes(blob[:start] + new + b" " * (hlen - len(new)) + blob[start + hlen:])
    return good, bad


def _cli(*args, limit_bytes: int | None = None):
    def preexec():
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit_bytes, limit_bytes))
    return subprocess.run([*MOTORCTL, *map(str, args)], capture_output=True, text=True, cwd=REPO,
                          timeout=120, preexec_fn=preexec if limit_bytes else None)


def _one_error_line(r, *words):
    assert r.returncode == 2, (r.returncode, r.stderr)
    assert "Traceback" not in r.stderr and r.stderr.count("\n") == 1, r.stderr
    for w in words:
        assert w in r.stderr, r.stderr


def test_export_onto_its_own_log_or_another_run_log_is_refused(logs, tmp_path):
    good, _ = logs
    before = good.read_bytes()
    r = _cli("export", good, "--mcap", good)
    _one_error_line(r, str(good), "is the run log being read")
    other = tmp_path / "other.mclog"
    other_bytes = _write_log(other, rows=10)
    link = tmp_path / "link.csv"
    link.symlink_to(good)
    _one_error_line(_cli("export", good, "--csv", link), "is the run log being read")
    _one_error_line(_cli("export", good, "--csv", other), str(other), "never overwrites one")
    assert good.read_bytes() == before and other.read_bytes() == other_bytes


def test_a_damaged_log_is_one_line_and_nothing_written(logs, tmp_path):
    _, bad = logs
    for flag, out in (("--mcap", tmp_path / "x.mcap"), ("--csv", tmp_path / "x.csv"),
                      ("--mat", tmp_path / "x.mat")):
        _one_error_line(_cli("export", bad, flag, out), str(bad), "damaged records")
    r = _cli("plot", bad, "--out", tmp_path / "plots")
    _one_error_line(r, str(bad), "damaged records")
    assert sorted(p.name for p in tmp_path.rglob("*") if p.is_file()) == []


def test_a_write_that_fails_names_the_file_and_leaves_nothing(logs, tmp_path):
    good, _ = logs
    out = tmp_path / "x.csv"
    r = _cli("export", good, "--csv", out, limit_bytes=64 << 10)   # the CSV is ~1 MB
    _one_error_line(r, str(out), "cannot write the export")
    assert list(tmp_path.iterdir()) == []
    # without the limit the same export completes, and replaces an older output whole
    out.write_text("old\n")
    r = _cli("export", good, "--csv", out)
    assert r.returncode == 0, r.stderr
    assert out.read_text().count("\n") == 3001 and [p.name for p in tmp_path.iterdir()] == ["x.csv"]


def test_plot_writes_whole_pngs_and_refuses_a_run_log_in_their_place(logs, tmp_path):
    good, _ = logs
    out = tmp_path / "plots"
    out.mkdir()
    _write_log(out / "X_error.png", rows=10)         # a run log where a figure would go
    r = _cli("plot", good, "--out", out)
    _one_error_line(r, "X_error.png", "never overwrites one")
    assert not [p for p in out.iterdir() if p.name.endswith(".part")]
    assert (out / "X_error.png").read_bytes()[:len(MAGIC)] == MAGIC


def test_a_full_disk_names_the_file_and_leaves_nothing(logs, tmp_path):
    """A real ENOSPC: a 256 KiB tmpfs mounted in a private mount namespace of this test's
    child (gone with it); skipped where unshare(1) may not create one."""
    import shutil
    good, _ = logs
    unshare = shutil.which("unshare")
    if unshare is None or subprocess.run([unshare, "-m", "true"], capture_output=True).returncode:
        pytest.skip("no private mount namespace here (unshare -m)")
    disk = tmp_path / "disk"
    disk.mkdir()
    cmd = " ".join(map(str, MOTORCTL))
    script = (f"mount -t tmpfs -o size=256k tmpfs {disk} && {cmd} export {good} --csv {disk}/x.csv; "
              f"echo rc=$?; ls -A {disk}")
    r = subprocess.run([unshare, "-m", "sh", "-c", script], capture_output=True, text=True,
                       cwd=REPO, timeout=120)
    assert "rc=2" in r.stdout, r.stdout + r.stderr
    assert r.stdout.strip().endswith("rc=2"), r.stdout          # nothing left on the full disk
    assert "Traceback" not in r.stderr and r.stderr.count("\n") == 1, r.stderr
    assert f"{disk}/x.csv: cannot write the export (No space left on device)" in r.stderr
