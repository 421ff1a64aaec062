"""``motorctl data fetch|path`` (docs/identification.md): the EMPS record downloaded with its
SHA-256 checked, never twice, never kept when its bytes differ. Nothing here leaves this machine:
the source is a copy served by an HTTP server on loopback (a thread of this process) or a
``file:`` URL, and the data directory is a temporary one."""

from __future__ import annotations

import functools
import hashlib
import http.server
import os
import subprocess
import sys
import threading
from pathlib import Path

import pytest

from harness import emps_path, motorctl_cmd
from motorctl.datasets import DATASETS

EMPS = emps_path()
needs_emps = pytest.mark.skipif(EMPS is None, reason="EMPS data not available")


def _cli(data_dir: Path, *args: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "MOTORCTL_DATA_DIR": str(data_dir)}
    return subprocess.run(motorctl_cmd("data", *args), capture_output=True, text=True, timeout=120, env=env)


class _Server:
    """An HTTP server on 127.0.0.1 serving ``root`` from a thread; ``requests`` lists the paths asked."""

    def __init__(self, root: Path):
        requests = self.requests = []

        class Handler(http.server.SimpleHTTPRequestHandler):
            def do_GET(self):
                requests.append(self.path)
                super().do_GET()

            def log_message(self, *a):
                pass

        self.httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0),
                                                     functools.partial(Handler, directory=str(root)))
        self.url = f"http://127.0.0.1:{self.httpd.server_address[1]}"
        self.thread = threading.Thread(target=self.httpd.serve_forever, daemon=True)
        self.thread.start()

    def close(self):
        self.httpd.shutdown()
        self.httpd.server_close()
        self.thread.join(5)


@pytest.fixture
def served(tmp_path):
    """An HTTP server on loopback serving the EMPS copy as ``good.mat`` and one byte changed as
    ``bad.mat``."""
    root = tmp_path / "www"
    root.mkdir()
    data = Path(EMPS).read_bytes()
    (root / "good.mat").write_bytes(data)
    (root / "bad.mat").write_bytes(data[:-1] + bytes([data[-1] ^ 1]))
    srv = _Server(root)
    yield srv
    srv.close()


def test_the_local_copy_is_the_pinned_one():
    """The SHA-256 the command pins is the one of the copy the tests use (so the tests below
    exercise the real check)."""
    if EMPS is None:
        pytest.skip("EMPS data not available")
    assert hashlib.sha256(Path(EMPS).read_bytes()).hexdigest() == DATASETS["emps"].sha256


@needs_emps
def test_fetch_downloads_once_then_finds_it_there(tmp_path, served):
    data_dir = tmp_path / "data"
    r = _cli(data_dir, "fetch", "emps", "--url", f"{served.url}/good.mat")
    assert r.returncode == 0, r.stderr
    target = data_dir / "emps" / "DATA_EMPS.mat"
    assert target.read_bytes() == Path(EMPS).read_bytes()
    assert "downloaded" in r.stdout and served.requests == ["/good.mat"]
    assert sorted(p.name for p in (data_dir / "emps").iterdir()) == ["DATA_EMPS.mat"]   # no temporary left

    again = _cli(data_dir, "fetch", "emps", "--url", f"{served.url}/good.mat")
    assert again.returncode == 0, again.stderr
    assert "already there" in again.stdout and served.requests == ["/good.mat"]      # not asked again

    path = _cli(data_dir, "path", "emps")
    assert path.returncode == 0 and path.stdout.strip() == str(target)


@needs_emps
def test_a_download_with_another_hash_is_refused_and_nothing_kept(tmp_path, served):
    data_dir = tmp_path / "data"
    r = _cli(data_dir, "fetch", "emps", "--url", f"{served.url}/bad.mat")
    assert r.returncode == 2, r.stderr
    assert served.requests == ["/bad.mat"]
    assert len(r.stderr.splitlines()) == 1 and "Traceback" not in r.stderr
    assert r.stderr.startswith("motorctl: error: data: ") and DATASETS["emps"].sha256 in r.stderr
    assert not data_dir.exists()                                   # no file, no directory


@needs_emps
def test_a_changed_local_copy_is_replaced_from_a_file_url(tmp_path):
    """A copy whose bytes differ is not accepted by `path` and is replaced by `fetch`; a
    ``file:`` URL (a copy on a mounted disk) is a source like any other."""
    data_dir = tmp_path / "data"
    (data_dir / "emps").mkdir(parents=True)
    (data_dir / "emps" / "DATA_EMPS.mat").write_bytes(b"partial")
    p = _cli(data_dir, "path", "emps")
    assert p.returncode == 2 and "SHA-256" in p.stderr and len(p.stderr.splitlines()) == 1
    r = _cli(data_dir, "fetch", "emps", "--url", Path(EMPS).resolve().as_uri())
    assert r.returncode == 0, r.stderr
    assert (data_dir / "emps" / "DATA_EMPS.mat").read_bytes() == Path(EMPS).read_bytes()


def test_path_of_a_data_set_not_fetched(tmp_path):
    r = _cli(tmp_path, "path", "emps")
    assert r.returncode == 2
    assert r.stderr == (f"motorctl: error: data: {tmp_path / 'emps' / 'DATA_EMPS.mat'}: not fetched yet: "
                        "motorctl data fetch emps\n")


def test_an_unreachable_source_is_one_line(tmp_path):
    """A source nobody serves (a loopback port just closed): one line, exit 1, nothing kept."""
    srv = _Server(tmp_path)
    url = srv.url
    srv.close()
    r = _cli(tmp_path / "data", "fetch", "emps", "--url", f"{url}/DATA_EMPS.mat")
    assert r.returncode == 1 and len(r.stderr.splitlines()) == 1 and "download failed" in r.stderr
    assert not (tmp_path / "data").exists()


def test_fetch_without_pooch_names_the_extra(tmp_path):
    code = ("import sys; sys.modules['pooch'] = None; from motorctl.cli import main; "
            "sys.exit(main(['data', 'fetch', 'emps']))")
    env = {**os.environ, "MOTORCTL_DATA_DIR": str(tmp_path)}
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, env=env)
    assert r.returncode == 2, r.stderr
    assert r.stderr == ("motorctl: error: data: needs the 'data' extra (pooch is not installed): "
                        "pip install 'motorctl[data]'\n")
    assert list(tmp_path.iterdir()) == []
