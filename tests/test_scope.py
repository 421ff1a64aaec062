"""The live scope in a real browser: the daemon on the simulated gantry serves the page; headless
Chromium (Debian's, driven by Playwright with that executable) shows the error trace moving
and a fault injected with ``motorctl inject`` with its reason; the screenshot is kept
(``$MOTORCTL_ARTEFACTS/scope.png`` when that is set). Skips only when no ``chromium`` is
on PATH (``shutil.which``, the lookup ``.ci/run``'s ``command -v chromium`` makes; it installs it)."""

from __future__ import annotations

import json
import os
import shutil
import time
import urllib.request
from pathlib import Path

import pytest

from harness import free_port
from test_daemon_helpers import ctl, running_daemon, status

CHROMIUM = shutil.which("chromium")   # .ci/run: `command -v chromium`, else apt-get install
ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
        "--disable-background-networking", "--disable-component-update", "--disable-sync"]

pytestmark = pytest.mark.skipif(CHROMIUM is None,
                                reason="no chromium on PATH (apt-get install chromium)")


def _wait(pred, timeout_s: float, what: str):
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        got = pred()
        if got:
            return got
        time.sleep(0.1)
    raise AssertionError(f"timed out waiting for {what}")


def _get(url: str):
    try:
        return urllib.request.urlopen(url, timeout=5).read()
    except OSError:              # the view process binds its port a moment after the start
        return None


def test_scope_page_shows_the_error_moving_and_a_fault_with_its_reason(tmp_path):
    from playwright.sync_api import sync_playwright

    port = free_port()
    with running_daemon(tmp_path, fault_axis=True, busy_y=True,
                        extra_daemon={"scope": {"listen": f"127.0.0.1:{port}"}}) as d:
        url = f"http://127.0.0.1:{port}/"
        meta = json.loads(_wait(lambda: _get(url + "meta"), 30, "the view process to serve"))
        assert "X.e" in meta["channels"] and meta["units"][meta["channels"].index("X.e")] == "m"
        assert ctl(d.sock, "start", "Y").returncode == 0
        with sync_playwright() as pw:
            browser = pw.chromium.launch(executable_path=CHROMIUM, args=ARGS)
            try:
                page = browser.new_page(viewport={"width": 1200, "height": 900})
                page.goto(url)
                page.wait_for_function("window.scope && window.scope.frames > 10", timeout=20000)
                # the error trace moves: Y tracks its program (moving most of the time), so its
                # envelope over the window spans more than 1 um, and the window scrolls
                page.wait_for_function(
                    "(() => { const hi = window.scope.max['Y.e'].filter((v) => v !== null);"
                    " const lo = window.scope.min['Y.e'].filter((v) => v !== null);"
                    " return hi.length > 100 && Math.max(...hi) - Math.min(...lo) > 1e-6; })()",
                    timeout=20000)
                t0 = page.evaluate("window.scope.t[window.scope.t.length - 1]")
                page.wait_for_function(f"window.scope.t[window.scope.t.length - 1] > {t0} + 0.5",
                                       timeout=20000)
                drawn = page.evaluate("window.scope.plots['Y.e'].data[0].length")
                assert drawn > 100
                # a fault injected through the CLI shows on the page with its reason
                assert ctl(d.sock, "start", "X").returncode == 0
                _wait(lambda: status(d.sock)["axes"]["X"]["phase"] == "tracking", 20, "X tracking")
                page.fill("#window", "1")        # the single shot freezes half a window after
                page.select_option("#trigger", "fault")
                r = ctl(d.sock, "inject", "X", "push", "--force-n", "1500", "--cycles", "20")
                assert r.returncode == 0, r.stderr
                page.wait_for_function(
                    "document.getElementById('fault-X') && "
                    "document.getElementById('fault-X').textContent.includes('following error')",
                    timeout=20000)
                reason = page.inner_text("#fault-X")
                assert reason == status(d.sock)["axes"]["X"]["fault"]
                # the single shot fired on the fault and froze the view
                page.wait_for_function("window.scope.paused === true", timeout=20000)
                assert "triggered: fault on X" in page.inner_text("#state")
                shot = tmp_path / "scope.png"
                page.screenshot(path=str(shot), full_page=True)
                assert shot.stat().st_size > 10_000
                if os.environ.get("MOTORCTL_ARTEFACTS"):
                    dest = Path(os.environ["MOTORCTL_ARTEFACTS"])
                    dest.mkdir(parents=True, exist_ok=True)
                    shutil.copy(shot, dest / "scope.png")
            finally:
                browser.close()
        # read-only: nothing but GET routes (a POST is refused)
        req = urllib.request.Request(url + "ws", data=b"{}", method="POST")
        with pytest.raises(urllib.error.HTTPError) as err:
            urllib.request.urlopen(req, timeout=5)
        assert err.value.code == 405


def test_a_bad_scope_address_is_a_config_error(tmp_path, capsys):
    import yaml

    from motorctl.cli import main
    from test_daemon_helpers import make_config
    cfg = make_config(tmp_path)
    d = yaml.safe_load(cfg.read_text())
    d["daemon"]["scope"] = {"listen": "localhost"}
    cfg.write_text(yaml.safe_dump(d))
    assert main(["check-config", str(cfg)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "daemon.scope.listen" in err and "host:port" in err, err


def test_a_slow_page_drops_frames_never_rows():
    """The scope's frames are bounded: however long nobody reads them, the list holds the
    newest BACKLOG_FRAMES and the tap returns (the drainer's rows are never held back: a page
    reads the list, it never blocks the tap)."""
    import numpy as np

    from motorctl.app.daemon.scope import BACKLOG_FRAMES, Scope
    from motorctl.loop.records import RecordLayout

    lay = RecordLayout(["X"])
    scope = Scope(None, lay, ["X"], 2e-4, {"X": 4.0})
    rows = np.zeros((100, len(lay.columns)))
    for k in range(3 * BACKLOG_FRAMES):          # 60 s of rows at 5 kHz, in 20 ms batches
        rows[:, lay.cycle("t")] = (k * 100 + np.arange(100)) * 2e-4
        rows[:, lay.index("X.e")] = np.sin(k + np.arange(100))
        scope.tap(rows, k * 100)
    assert scope.error == "" and scope.frames_made == 3 * BACKLOG_FRAMES
    assert len(scope.frames) == BACKLOG_FRAMES                  # bounded
    assert scope.frames[0]["seq"] == 2 * BACKLOG_FRAMES + 1     # the oldest went first
    f = scope.frames[-1]
    assert len(f["t"]) == 10 and all(lo <= hi for lo, hi in zip(f["min"]["X.e"], f["max"]["X.e"]))
    # a period start every 4 s of loop time is an event of the frame it falls in
    assert sum(ev["kind"] == "period" for fr in scope.frames for ev in fr["events"]) >= 1
