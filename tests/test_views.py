"""Views are guests: the scope page and Foxglove run in the view process, so a view that cannot
start (its library missing, or failing at import) is one warning line and the daemon records
every row; pages that never read lose frames (counted), never rows."""

from __future__ import annotations

import asyncio
import os
import time

from harness import free_port
from test_daemon_helpers import Daemon, ctl, make_config, status, wait_for


def _start(d: Daemon, axis: str) -> None:
    for _ in range(5):                  # bounded: a refusal that asks for a retry gets one
        r = ctl(d.sock, "start", axis)
        if r.returncode == 0 or "retry" not in r.stdout + r.stderr:
            break
        time.sleep(0.2)
    assert r.returncode == 0, r.stdout + r.stderr


def _axes_run_and_nothing_lost(d: Daemon, seconds: float) -> dict:
    _start(d, "X")
    _start(d, "Y")
    c0 = status(d.sock)["loop"]["cycles"]
    st = wait_for(lambda: (s := status(d.sock))["loop"]["cycles"] > c0 + seconds * 5000 and s,
                  120, f"{seconds} s of loop cycles")
    assert {a: s["fault"] for a, s in st["axes"].items()} == {"X": "", "Y": ""}
    assert st["log"]["lost_rows"] == 0 and st["log"]["recorder_fault"] == ""
    return st


def test_a_missing_or_broken_view_library_is_one_line_and_no_row_lost(tmp_path):
    # aiohttp "not installed" (None in sys.modules is how Python spells it), foxglove-sdk
    # installed but failing when imported (in the view process)
    stubs = tmp_path / "stubs"
    (stubs / "foxglove").mkdir(parents=True)
    (stubs / "sitecustomize.py").write_text("import sys\nsys.modules['aiohttp'] = None\n")
    (stubs / "foxglove" / "__init__.py").write_text("raise RuntimeError('broken build')\n")
    env = {**os.environ, "PYTHONPATH": str(stubs)}
    sp, fp = free_port(), free_port()
    cfg = make_config(tmp_path, extra_daemon={"scope": {"listen": f"127.0.0.1:{sp}"},
                                              "foxglove": {"listen": f"127.0.0.1:{fp}"}})
    d = Daemon(cfg, tmp_path / "motorctl.sock", env=env)
    try:
        d.wait_ready()
        _axes_run_and_nothing_lost(d, 3.0)
        # both views refused: the view process reports, then ends (status "views" None); on a
        # loaded host its niced start-up can take longer than the run, and a SIGTERM before its
        # report would leave the broken library's line unwritten
        wait_for(lambda: status(d.sock)["views"] is None, 60, "the view process's report")
        code, _, err = d.terminate()
    finally:
        d.kill()
    assert code == 0, err
    lines = [ln for ln in err.splitlines() if "scope" in ln or "foxglove" in ln]
    assert len(lines) == 2, err
    assert "Traceback" not in err and "scope on" not in err and "foxglove on" not in err, err
    assert sum("scope disabled: install motorctl[scope]" in ln for ln in lines) == 1, err
    assert sum("daemon.foxglove.listen" in ln and "RuntimeError: broken build" in ln
               for ln in lines) == 1, err


def test_a_view_s_report_is_read_after_a_frame_found_the_view_process_gone():
    """The view process reports what it could not serve, then ends. A frame sent after its end
    fails and marks the link gone (``alive`` False, the frame counted dropped); the report
    waiting on the socket is still read, then the EOF. (Before, a link marked gone read nothing,
    and the daemon's line for the broken view was lost: a race the test above lost once.)"""
    import pickle
    import socket

    from motorctl.app.daemon.views import ViewLink
    ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    ours.setblocking(False)
    link = ViewLink(ours, 0)
    report = ("started", {"foxglove": "RuntimeError: broken build"})
    theirs.send(pickle.dumps(report))
    theirs.close()
    link.on_frame({"t": 0.0})                # EPIPE (Python ignores SIGPIPE)
    assert not link.alive and link.dropped == 1 and link.sent == 0
    assert link.receive() == [report]
    assert link.receive() == []
    ours.close()


def test_a_view_s_report_is_read_when_it_ended_with_frames_unread():
    """The view process reports what it could not serve and ends without reading the frames
    already sent to it (its start-up, niced, outlasted the first frames: a loaded host). The
    kernel then reports the reset on the link's first recv, before the report still queued
    (AF_UNIX SOCK_SEQPACKET); the report is read, then the EOF. (Before, the reset was taken for
    the EOF and the daemon's line for the broken view was lost: the race the daemon test above
    lost on a loaded host.)"""
    import pickle
    import socket

    from motorctl.app.daemon.views import ViewLink
    ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    ours.setblocking(False)
    link = ViewLink(ours, 0)
    link.on_frame({"t": 0.0})                 # queued at the view process, never read
    assert link.alive and link.sent == 1
    report = ("started", {"foxglove": "RuntimeError: broken build"})
    theirs.send(pickle.dumps(report))
    theirs.close()
    assert link.receive() == [report]
    assert not link.alive
    assert link.receive() == []
    ours.close()


def test_pages_that_never_read_drop_frames_not_rows(tmp_path):
    """Five WebSocket pages that connect and never read, and the view process is the one
    that falls behind: the run log loses nothing, no axis faults, and a page that reads is
    told how many frames it missed."""
    import aiohttp
    from aiohttp import WSCloseCode

    port = free_port()
    cfg = make_config(tmp_path, extra_daemon={"scope": {"listen": f"0.0.0.0:{port}"}})
    d = Daemon(cfg, tmp_path / "motorctl.sock")
    try:
        d.wait_ready()
        wait_for(lambda: _get(port), 30, "the scope page")

        async def pages():
            async with aiohttp.ClientSession() as s:
                stuck = [await s.ws_connect(f"ws://127.0.0.1:{port}/ws") for _ in range(5)]
                st = _axes_run_and_nothing_lost(d, 3.0)
                async with s.ws_connect(f"ws://127.0.0.1:{port}/ws") as ws:
                    meta = await ws.receive_json(timeout=10)
                    msg = await ws.receive_json(timeout=10)
                for w in stuck:
                    await w.close()
                # every close answered by the view process (1000), none left to the client's
                # own timeout (1006): a page's close is read while frames are queued for it
                return meta, msg, st, [w.close_code for w in (ws, *stuck)]
        meta, msg, st, closed = asyncio.run(pages())
        assert closed == [WSCloseCode.OK] * 6, closed
        assert st["views"]["frames_sent"] > 50, st["views"]     # 3 s at one frame per 20 ms
        assert "X.e" in meta["meta"]["channels"]
        assert set(msg) >= {"frames", "status", "dropped"} and msg["dropped"] >= 0
        code, _, err = d.terminate()
    finally:
        d.kill()
    assert code == 0, err
    # listening beyond loopback is allowed, with one line that says the page is open
    assert sum("no authentication" in ln and "daemon.scope.listen 0.0.0.0" in ln
               for ln in err.splitlines()) == 1, err
    assert f"motorctl: scope on http://0.0.0.0:{port}/" in err


def _get(port: int) -> bool:
    import urllib.request
    try:
        return urllib.request.urlopen(f"http://127.0.0.1:{port}/meta", timeout=2).status == 200
    except OSError:
        return False


def test_a_view_process_reaped_in_the_wake_its_report_came_still_has_its_line(capsys):
    """The view process reports a view it could not serve and ends by itself; the I/O process's
    supervision reaps it in the same wake, before the selector has handed it the report. The
    report is read before the link is dropped: the broken view's line is written. (Before, the
    link went with the report unread, and a CI run lost the foxglove line.)"""
    import pickle
    import selectors
    import socket
    from types import SimpleNamespace

    from motorctl.app.daemon.io_side import IOSide
    from motorctl.app.daemon.views import ViewLink
    ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    ours.setblocking(False)
    pid = os.fork()
    if pid == 0:                                 # the view process: its report, then its end
        theirs.send(pickle.dumps(("started", {"foxglove": "RuntimeError: broken build"})))
        os._exit(0)
    theirs.close()
    wait_for(lambda: open(f"/proc/{pid}/stat").read().split(")")[-1].split()[0] == "Z", 10, "the child's end")
    io = SimpleNamespace(views=ViewLink(ours, pid), fox_listen="127.0.0.1:1", sel=selectors.DefaultSelector(),
                         scope=SimpleNamespace(listeners=[], tap=None), drainer=SimpleNamespace(taps=[]),
                         helpers={"views": {"pid": pid, "starts": 1, "retry_at": 0.0, "ended": ""}})
    io.report_views = lambda: IOSide.report_views(io)
    io.drop_views = lambda: IOSide.drop_views(io)
    IOSide.supervise(io, time.monotonic())
    err = capsys.readouterr().err
    assert io.views is None and "ended by itself" in err, err
    assert "daemon.foxglove.listen 127.0.0.1:1: not served (RuntimeError: broken build)" in err, err
