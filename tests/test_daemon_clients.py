"""No client can take the daemon down through its control socket: half lines, oversized lines,
garbage, idle connections beyond the cap, descriptor exhaustion, 40 operators at once. The
daemon answers ``status`` throughout and afterwards, and no axis faults."""

from __future__ import annotations

import resource
import socket
import threading
import time

from test_daemon_helpers import running_daemon, status

from motorctl.app.daemon.io_side import MAX_CLIENTS
from motorctl.cli.operator import call


def _connect(path) -> socket.socket:
    """A raw client; a full listen queue is waited out (bounded), as the CLI does."""
    for _ in range(200):
        s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        s.settimeout(5.0)
        try:
            s.connect(str(path))
            return s
        except BlockingIOError:
            s.close()
            time.sleep(0.01)
    raise AssertionError("the daemon's connection queue stayed full for 2 s")


def _healthy(d) -> dict:
    st = status(d.sock)
    assert d.proc.poll() is None
    assert all(a["fault_bits"] == 0 for a in st["axes"].values()), st["axes"]
    return st


def test_partial_oversized_and_garbage_requests(tmp_path):
    with running_daemon(tmp_path) as d:
        s = _connect(d.sock)                    # half a JSON object, then hang up
        s.sendall(b'{"cmd": "sta')
        s.close()
        _healthy(d)
        s = _connect(d.sock)                    # garbage without a newline, then hang up
        s.sendall(b"\x00\xff garbage " * 100)
        s.close()
        _healthy(d)
        s = _connect(d.sock)                    # a 10 MB line: refused with an answer, closed
        try:
            chunk = b"x" * 65536
            for _ in range(160):
                s.sendall(chunk)
        except OSError:
            pass                                # the daemon closed the connection: expected
        try:
            ans = s.recv(4096)
        except OSError:
            ans = b""
        s.close()
        assert ans == b"" or b"longer than" in ans
        _healthy(d)
        s = _connect(d.sock)                    # a request split over two reads is answered
        s.sendall(b'{"cmd": "st')
        _healthy(d)
        s.sendall(b'atus"}\n')
        assert b'"ok": true' in s.recv(1 << 20)
        s.close()
        assert call(str(d.sock), {"cmd": "bogus"})["usage"] is True
        _healthy(d)


def test_idle_connections_beyond_the_cap_and_40_operators_at_once(tmp_path):
    with running_daemon(tmp_path) as d:
        idle = [_connect(d.sock) for _ in range(MAX_CLIENTS + 40)]
        st = _healthy(d)                        # answered while 100+ connections are held
        assert st["clients"]["refused"] >= 40
        results, errors = [], []

        def one():
            try:
                results.append(call(str(d.sock), {"cmd": "status"}, timeout_s=20.0)["ok"])
            except Exception as exc:            # noqa: BLE001 - collected and asserted below
                errors.append(repr(exc))
        threads = [threading.Thread(target=one) for _ in range(40)]
        for t in threads:
            t.start()
        for t in threads:
            t.join(30)
        for s in idle:
            s.close()
        assert not errors and results == [True] * 40, errors[:3]
        _healthy(d)


def test_descriptor_exhaustion_does_not_kill_the_io_process(tmp_path):
    def low_nofile():
        resource.setrlimit(resource.RLIMIT_NOFILE, (48, 48))
    from test_daemon_helpers import Daemon, make_config
    d = Daemon(make_config(tmp_path), tmp_path / "motorctl.sock", preexec=low_nofile)
    try:
        d.wait_ready()
        held = []
        for _ in range(120):
            try:
                held.append(_connect(d.sock))
            except OSError:
                break
        for s in held[:60]:
            s.close()
        _healthy(d)
        for s in held[60:]:
            s.close()
        _healthy(d)
    finally:
        d.kill()
