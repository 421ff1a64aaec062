"""The operator page in a real browser (docs/operator-page.md): the daemon on the simulated gantry
with a scope and a users file; headless Chromium (Debian's, driven by Playwright with that
executable) logs in as an operator, enables the axes, jogs X by a step and continuously (the DRO
and ``status`` follow), runs a program sent from a file to its end and sees a wrong one refused
with the daemon's line; as a viewer and logged out the jog button is disabled and a direct POST
is refused (403), as is a POST without the CSRF token or from another origin. Skips only when no
``chromium`` is on PATH, as tests/test_scope.py (``.ci/run`` installs it; the skip table allows no
skip on CI)."""

from __future__ import annotations

import json
import shutil
import time
import urllib.error
import urllib.request

import pytest
import yaml

from harness import free_port
from test_daemon_helpers import running_daemon, status, wait_for

CHROMIUM = shutil.which("chromium")   # .ci/run: `command -v chromium`, else apt-get install
ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
        "--disable-background-networking", "--disable-component-update", "--disable-sync"]

pytestmark = pytest.mark.skipif(CHROMIUM is None,
                                reason="no chromium on PATH (apt-get install chromium)")

OP_PASSWORD = "op-secret-7f3a"       # looked for in the run logs afterwards: never written
VIEW_PASSWORD = "viewer-secret-19c2"
#: every wait in the browser [ms]
WAIT_MS = 15000


def _get(url: str):
    try:
        return urllib.request.urlopen(url, timeout=5).read()
    except OSError:              # the view process binds its port a moment after the start
        return None


def _post(url: str, body: dict, headers: dict | None = None) -> int:
    """The HTTP status of a POST (urllib: no browser, no cookie unless given)."""
    req = urllib.request.Request(url, data=json.dumps(body).encode(), method="POST",
                                 headers={"Content-Type": "application/json", **(headers or {})})
    try:
        with urllib.request.urlopen(req, timeout=5) as r:
            return r.status
    except urllib.error.HTTPError as exc:
        return exc.code


def _users_file(tmp_path):
    from motorctl.app.users import hash_password
    p = tmp_path / "users.yaml"
    p.write_text(yaml.safe_dump({"users": {
        "op": {"password": hash_password(OP_PASSWORD), "roles": ["operator"]},
        "vw": {"password": hash_password(VIEW_PASSWORD), "roles": ["viewer"]}}}))
    return p


def _login(page, name: str, password: str) -> None:
    page.fill("#login-name", name)
    page.fill("#login-password", password)
    page.click("#login")
    page.wait_for_function(f"window.op.session.user === {name!r}", timeout=WAIT_MS)


def test_operator_page_jogs_runs_a_program_and_refuses_viewers(tmp_path):
    from playwright.sync_api import sync_playwright

    port = free_port()
    base = f"http://127.0.0.1:{port}"
    users = _users_file(tmp_path)
    with running_daemon(tmp_path, extra_daemon={"scope": {"listen": f"127.0.0.1:{port}"},
                                                "users_file": str(users)}) as d:
        sock = d.sock
        wait_for(lambda: _get(base + "/operator/session"), 30, "the view process to serve")
        prog = tmp_path / "square.ngc"
        prog.write_text("G21 G90\nG1 X20 Y10 F6000\nG1 X25 Y15\nM2\n")
        bad = tmp_path / "too-far.ngc"
        bad.write_text("G21 G90\nG1 X900 F6000\nM2\n")
        with sync_playwright() as pw:
            browser = pw.chromium.launch(executable_path=CHROMIUM, args=ARGS)
            try:
                # ---- logged out: read only, the DRO shows, a direct POST is refused
                anon = browser.new_page()
                anon.goto(base + "/operator")
                anon.wait_for_function("window.op.polls > 0 && document.getElementById('jog-plus-X')",
                                       timeout=WAIT_MS)
                assert anon.is_disabled("#jog-plus-X") and anon.is_disabled("#program-run")
                assert _post(base + "/operator/cmd/jog", {"axis": "X", "by": 0.001}) == 403

                # ---- the operator: enable both axes in command mode, then jog X by 1 mm
                page = browser.new_context().new_page()
                page.goto(base + "/operator")
                _login(page, "op", OP_PASSWORD)
                page.wait_for_function("!document.getElementById('jog-plus-X').disabled", timeout=WAIT_MS)
                for a in ("X", "Y"):
                    page.click(f"#enable-{a}")
                    page.wait_for_function(f"document.getElementById('state-{a}').textContent"
                                           f" === 'enabled / command'", timeout=WAIT_MS)
                x0 = status(sock)["axes"]["X"]["y_m"]
                page.select_option("#jog-step", "0.001")
                page.click("#jog-plus-X")
                def jogged():
                    s = status(sock)
                    return s if abs(s["axes"]["X"]["y_m"] - x0 - 0.001) < 2e-5 and s["motion"]["idle"] else None
                st = wait_for(jogged, 10, "X 1 mm further", detail=lambda: status(sock)["axes"]["X"]["y_m"] - x0)
                shown = float(page.inner_text("#pos-X"))          # [mm], polled every 0.2 s
                page.wait_for_function(
                    f"Math.abs(parseFloat(document.getElementById('pos-X').textContent) - "
                    f"{(x0 + 0.001) * 1000}) < 0.02", timeout=WAIT_MS)
                assert "jog X: ok" in page.inner_text("#answer"), (shown, st["axes"]["X"])

                # ---- a continuous jog: held down it moves, released it stops
                x1 = status(sock)["axes"]["X"]["y_m"]
                page.fill("#jog-speed", "20")
                page.hover("#jogc-plus-X")
                page.mouse.down()
                wait_for(lambda: status(sock)["axes"]["X"]["y_m"] > x1 + 0.002, 10, "X moving on")
                page.mouse.up()
                wait_for(lambda: status(sock)["motion"]["idle"], 10, "the jog to stop")
                x2 = status(sock)["axes"]["X"]["y_m"]
                assert x1 + 0.002 < x2 < x1 + 0.05, (x1, x2)

                # ---- a program sent from a file, run to its end
                page.set_input_files("#program-file", str(prog))
                page.click("#program-run")
                page.wait_for_function("window.op.program === 'finished'", timeout=WAIT_MS)
                ax = status(sock)["axes"]
                assert abs(ax["X"]["y_m"] - 0.025) < 5e-5 and abs(ax["Y"]["y_m"] - 0.015) < 5e-5, ax
                page.wait_for_function(
                    "Math.abs(parseFloat(document.getElementById('pos-X').textContent) - 25) < 0.05",
                    timeout=WAIT_MS)
                # a program the daemon refuses: its one line on the page, nothing moves
                page.set_input_files("#program-file", str(bad))
                page.click("#program-run")
                page.wait_for_function("window.op.program.startsWith('refused: ')", timeout=WAIT_MS)
                refused = page.inner_text("#program-state")
                assert "too-far.ngc:2" in refused and "\n" not in refused, refused
                assert abs(status(sock)["axes"]["X"]["y_m"] - 0.025) < 5e-5

                # ---- the operator's session without its CSRF token, or from another origin: 403
                cookie = next(c for c in page.context.cookies() if c["name"] == "motorctl_session")
                assert cookie["httpOnly"] and cookie["sameSite"] == "Strict"
                jar = {"Cookie": f"motorctl_session={cookie['value']}"}
                csrf = page.evaluate("window.op.session.csrf")
                jog = {"axis": "X", "by": 0.001}
                assert _post(base + "/operator/cmd/jog", jog, jar) == 403
                assert _post(base + "/operator/cmd/jog", jog, {**jar, "X-CSRF-Token": csrf,
                                                               "Origin": "http://evil.example"}) == 403
                assert _post(base + "/operator/cmd/override", {"value": 0.9},
                             {**jar, "X-CSRF-Token": csrf}) == 200
                assert status(sock)["motion"]["override"] == pytest.approx(0.9)

                # ---- a viewer: read only; its own session's POST is refused
                viewer = browser.new_context().new_page()
                viewer.goto(base + "/operator")
                _login(viewer, "vw", VIEW_PASSWORD)
                viewer.wait_for_function("window.op.polls > 0", timeout=WAIT_MS)
                assert viewer.is_disabled("#jog-plus-X") and viewer.is_disabled("#abort")
                vcookie = next(c for c in viewer.context.cookies() if c["name"] == "motorctl_session")
                vcsrf = viewer.evaluate("window.op.session.csrf")
                x3 = status(sock)["axes"]["X"]["y_m"]
                assert _post(base + "/operator/cmd/jog", jog, {"Cookie": f"motorctl_session={vcookie['value']}",
                                                               "X-CSRF-Token": vcsrf}) == 403
                # a wrong password: no session
                assert _post(base + "/login", {"name": "op", "password": "wrong"}) == 403
            finally:
                browser.close()
        time.sleep(0.3)
        assert status(sock)["axes"]["X"]["y_m"] == pytest.approx(x3, abs=1e-6)
    # no password in anything the daemon wrote
    for f in (tmp_path / "logs").rglob("*"):
        if f.is_file():
            data = f.read_bytes()
            assert OP_PASSWORD.encode() not in data and VIEW_PASSWORD.encode() not in data, f
