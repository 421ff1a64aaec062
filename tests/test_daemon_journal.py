"""The daemon's journal (its stderr) against a reader that falls behind: the I/O process's lines
are written by a thread of their own (motorctl.app.daemon.journal), so the run log and the
control socket go on whatever the reader does."""

from __future__ import annotations

import fcntl
import os

from test_daemon_helpers import Daemon, make_config, status, wait_for

from motorctl.client import call

#: Linux's fcntl to set a pipe's buffer (not in Python's fcntl module before 3.10 on every libc)
F_SETPIPE_SZ = getattr(fcntl, "F_SETPIPE_SZ", 1031)
#: fault onsets sent: each writes one journal line of about 150 bytes, several times the pipe
FAULTS = 60


def test_a_journal_nobody_reads_never_holds_the_run_log_or_the_socket(tmp_path):
    """The daemon's stdout and stderr on a pipe of 4 KiB that is not read while 60 amplifier
    faults latch and are reset (a line each: several times the pipe): every request is answered
    (within the client's 5 s), the run log's rows go on, no recorder fault; then the pipe read
    holds the daemon's lines, and ``status`` counts what was dropped. Before, the line that found
    the pipe full blocked the I/O process's main thread for good: the run log stopped at that
    fault and the socket went unanswered (the state machine's soak, after 29 minutes)."""
    cfg = make_config(tmp_path)
    r, w = os.pipe()
    fcntl.fcntl(w, F_SETPIPE_SZ, 4096)
    dmn = Daemon(cfg, tmp_path / "motorctl.sock", output=w)
    os.close(w)
    try:
        dmn.wait_ready(120)
        sock = str(dmn.sock)
        rows0 = status(sock)["log"]["rows"]
        for k in range(FAULTS):
            axis = "XY"[k % 2]
            assert call(sock, {"cmd": "inject", "axis": axis, "kind": "amp_fault", "cycles": 3}, timeout_s=5.0)["ok"]
            wait_for(lambda: call(sock, {"cmd": "status"}, timeout_s=5.0)["status"]["axes"][axis]["fault"],
                     10, f"fault {k} latched")

            def cleared():
                call(sock, {"cmd": "fault-reset", "axis": axis}, timeout_s=5.0)
                return not call(sock, {"cmd": "status"}, timeout_s=5.0)["status"]["axes"][axis]["fault"]
            wait_for(cleared, 10, f"fault {k} reset", interval=0.05)
        st = call(sock, {"cmd": "status"}, timeout_s=5.0)["status"]
        assert st["log"]["rows"] > rows0 and st["log"]["recorder_fault"] == "", st["log"]
        dropped = st["log"]["journal_dropped"]
        os.set_blocking(r, False)
        text = b""
        while True:                           # what the pipe holds, then what the journal writes on
            try:
                chunk = os.read(r, 1 << 16)
            except BlockingIOError:
                break
            text += chunk
        assert b"amplifier fault" in text, text[-2000:]
        assert dropped >= 0
    finally:
        dmn.kill()
        os.close(r)


def test_a_journal_write_never_waits_and_counts_what_it_drops():
    """The Journal on a stream whose writes block (a reader that stopped): writes return at once,
    at most max_lines wait, the rest are counted; once the reader goes on, the waiting lines and
    one line saying how many were dropped are written, in order."""
    import io
    import threading

    from motorctl.app.daemon.journal import Journal

    gate = threading.Event()

    class Held(io.StringIO):
        def write(self, s):
            gate.wait(30)
            return super().write(s)

    real = Held()
    j = Journal(real, max_lines=5)
    for k in range(20):
        assert j.write(f"line {k}\n") == len(f"line {k}\n")
    assert not j.drain(0.2)                   # held: nothing could be written
    gate.set()
    assert j.drain(10)
    text = real.getvalue()
    lines = text.splitlines()
    # the lines written are the first ones in order (the writer may have taken one batch before
    # the reader held it up: at most max_lines + the batch's), the rest counted, then said
    written = lines[:-1]
    assert written == [f"line {k}" for k in range(len(written))] and 5 <= len(written) <= 10, text
    assert j.dropped == 20 - len(written)
    assert lines[-1] == f"motorctl daemon: {j.dropped} journal lines dropped (the journal's reader fell behind)"
