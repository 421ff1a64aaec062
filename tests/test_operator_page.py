"""The operator page in a real browser (docs/operator-page.md): the daemon on the simulated gantry
with a scope and a users file; headless Chromium (Debian's, driven by Playwright with that
executable) logs in as an operator, enables the axes, jogs X by a step and continuously (the DRO
and ``status`` follow), runs a program sent from a file to its end and sees a wrong one refused
with the daemon's line; as a viewer and logged out the jog button is disabled and a direct POST
is refused (403), as is a POST without the CSRF token or from another origin. Skips only when no
``chromium`` is on PATH, as tests/test_scope.py (``.ci/run`` installs it; the skip table allows no
skip on CI). The screenshot after the program goes to ``$MOTORCTL_ARTEFACTS/operator.png`` when set."""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import time
import urllib.error
import urllib.request
from pathlib import Path

import pytest
import yaml

from harness import free_port
from test_daemon_helpers import Daemon, make_config, status, wait_for

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


@contextlib.contextmanager
def _daemon_and_browser(tmp_path, extra_daemon: dict):
    """A daemon on ``make_config(tmp_path, extra_daemon=...)``, ready, and headless Chromium,
    launched while the daemon starts (the two start-ups overlap); both ended after (bounded)."""
    from playwright.sync_api import sync_playwright
    d = Daemon(make_config(tmp_path, extra_daemon=extra_daemon), tmp_path / "motorctl.sock")
    try:
        with sync_playwright() as pw:
            browser = pw.chromium.launch(executable_path=CHROMIUM, args=ARGS)
            try:
                d.wait_ready()
                yield d, browser
            finally:
                browser.close()
    finally:
        d.kill()


def test_operator_page_jogs_runs_a_program_and_refuses_viewers(tmp_path):
    port = free_port()
    base = f"http://127.0.0.1:{port}"
    users = _users_file(tmp_path)
    prog = tmp_path / "square.ngc"
    prog.write_text("G21 G90\nG1 X20 Y10 F6000\nG1 X25 Y15\nM2\n")
    bad = tmp_path / "too-far.ngc"
    bad.write_text("G21 G90\nG1 X900 F6000\nM2\n")
    with _daemon_and_browser(tmp_path, {"scope": {"listen": f"127.0.0.1:{port}"},
                                        "users_file": str(users)}) as (d, browser):
        sock = d.sock
        wait_for(lambda: _get(base + "/operator/session"), 30, "the view process to serve")
        # ---- logged out: read only, the DRO shows, a direct POST is refused
        anon = browser.new_context().new_page()
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
        page.click("#enable-X")
        page.click("#enable-Y")
        page.wait_for_function("['X', 'Y'].every((a) => document.getElementById('state-' + a).textContent"
                               " === 'enabled / command')", timeout=WAIT_MS)
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
        wait_for(lambda: status(sock)["axes"]["X"]["y_m"] > x1 + 0.001, 10, "X moving on")
        page.mouse.up()
        wait_for(lambda: status(sock)["motion"]["idle"], 10, "the jog to stop")
        x2 = status(sock)["axes"]["X"]["y_m"]
        assert x1 + 0.001 < x2 < x1 + 0.3, (x1, x2)        # stopped well before the soft limit (0.42 m)

        # ---- a program sent from a file, run to its end
        page.set_input_files("#program-file", str(prog))
        page.click("#program-run")
        page.wait_for_function("window.op.program === 'finished'", timeout=WAIT_MS)
        ax = status(sock)["axes"]
        assert abs(ax["X"]["y_m"] - 0.025) < 5e-5 and abs(ax["Y"]["y_m"] - 0.015) < 5e-5, ax
        page.wait_for_function(
            "Math.abs(parseFloat(document.getElementById('pos-X').textContent) - 25) < 0.05",
            timeout=WAIT_MS)
        if os.environ.get("MOTORCTL_ARTEFACTS"):          # the page as the operator saw it
            dest = Path(os.environ["MOTORCTL_ARTEFACTS"])
            dest.mkdir(parents=True, exist_ok=True)
            page.screenshot(path=str(dest / "operator.png"), full_page=True)
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

        # ---- a viewer (the first page, logged in now): read only; its session's POST is refused
        _login(anon, "vw", VIEW_PASSWORD)
        anon.wait_for_function("window.op.session.roles.join() === 'viewer'", timeout=WAIT_MS)
        assert anon.is_disabled("#jog-plus-X") and anon.is_disabled("#abort")
        vcookie = next(c for c in anon.context.cookies() if c["name"] == "motorctl_session")
        vcsrf = anon.evaluate("window.op.session.csrf")
        x3 = status(sock)["axes"]["X"]["y_m"]
        assert _post(base + "/operator/cmd/jog", jog, {"Cookie": f"motorctl_session={vcookie['value']}",
                                                       "X-CSRF-Token": vcsrf}) == 403
        # a wrong password: no session (answered after LOGIN_FAIL_DELAY_S: X had time to move)
        assert _post(base + "/login", {"name": "op", "password": "wrong"}) == 403
        assert status(sock)["axes"]["X"]["y_m"] == pytest.approx(x3, abs=1e-6)
    # no password in anything the daemon wrote
    for f in (tmp_path / "logs").rglob("*"):
        if f.is_file():
            data = f.read_bytes()
            assert OP_PASSWORD.encode() not in data and VIEW_PASSWORD.encode() not in data, f


def _fake_daemon(path: str, got: list):
    """A control socket answering as the daemon does (upload, gcode, jog, status): for the page's
    own bounds without a loop. ``got``: the requests, and each upload's byte count."""
    import asyncio

    async def handle(reader, writer):
        req = json.loads(await reader.readline())
        got.append(req)
        if req["cmd"] == "upload":
            writer.write(b'{"ok": true, "continue": true, "upload": "t1"}\n')
            await writer.drain()
            n = 0
            while n < req["bytes"]:
                chunk = await reader.read(1 << 16)
                assert chunk
                n += len(chunk)
            got.append({"uploaded": n})
            ans = {"ok": True, "upload": "t1", "bytes": n}
        elif req["cmd"] == "status":
            ans = {"ok": True, "status": {"axes": {"X": {"y_m": 0.001, "state": "enabled"}}, "motion": {"idle": True}}}
        elif req["cmd"] == "gcode":
            ans = {"ok": False, "error": "big.ngc:70000:1: G1: X 900 mm is beyond the soft limit", "usage": True}
        else:
            ans = {"ok": True}
        writer.write((json.dumps(ans) + "\n").encode())
        await writer.drain()
        writer.close()
    return asyncio.start_unix_server(handle, path)


def test_a_large_program_is_streamed_and_a_held_jog_not_kept_alive_stops(tmp_path):
    """Against a fake control socket (no browser): a 3 MB program (beyond aiohttp's 1 MiB body
    bound and the daemon's 64 KiB request line) goes to the socket as one ``upload`` of all its
    bytes, then ``gcode`` naming it, and the daemon's refusal comes back as the page's answer
    (409); a continuous jog nobody keeps alive is stopped within JOG_DEADMAN_S and a poll; a
    session's POST without its CSRF token is 403."""
    import asyncio

    from aiohttp import web
    from aiohttp.test_utils import TestClient, TestServer

    from motorctl.app.daemon.operator_page import JOG_DEADMAN_S, OperatorPage
    users = _users_file(tmp_path)
    sock = str(tmp_path / "fake.sock")
    got: list = []

    async def main():
        srv = await _fake_daemon(sock, got)
        page = OperatorPage(sock, str(users), ["X"], lambda name: b"<html></html>")
        app = web.Application()
        page.add_routes(app)
        try:
            async with TestClient(TestServer(app, host="127.0.0.1")) as c:
                r = await c.post("/operator/cmd/abort", json={})
                assert r.status == 403
                r = await c.post("/login", json={"name": "op", "password": OP_PASSWORD})
                assert r.status == 200, await r.text()
                csrf = (await r.json())["csrf"]
                assert (await c.post("/operator/cmd/abort", json={})).status == 403   # no token
                h = {"X-CSRF-Token": csrf}
                body = b"G1 X1 Y1 F600\n" * 220_000                                  # 3.1 MB
                r = await c.post("/operator/program?name=big.ngc", data=body, headers=h)
                ans = await r.json()
                assert r.status == 409 and ans["error"].startswith("big.ngc:70000:1: "), ans
                assert {"uploaded": len(body)} in got
                assert {"cmd": "gcode", "upload": "t1", "filename": "big.ngc"} in got
                st = await (await c.get("/operator/status")).json()
                assert st["axes"]["X"]["y_m"] == 0.001
                r = await c.post("/operator/cmd/jog", json={"axis": "X", "velocity": 0.01}, headers=h)
                assert r.status == 200
                t0 = time.monotonic()
                while {"cmd": "jog", "axis": "X", "stop": True} not in got:
                    assert time.monotonic() - t0 < JOG_DEADMAN_S + 2.0, got
                    await asyncio.sleep(0.02)
                assert time.monotonic() - t0 >= JOG_DEADMAN_S * 0.9
        finally:
            srv.close()
    asyncio.run(asyncio.wait_for(main(), 30))


def test_users_add_writes_a_hash_the_page_accepts(tmp_path, monkeypatch, capsys):
    """``motorctl users add NAME --role operator --password-stdin`` (motorctl.cli.users): the file
    holds the scrypt hash only (mode 0600), load_users gives the role; adding the name again
    without --replace is refused; remove takes it out."""
    import io

    from motorctl.app.users import load_users
    from motorctl.cli import Parser, UsageError
    from motorctl.cli import users as users_cli
    p = Parser(prog="motorctl")
    users_cli.register(p, p.add_subparsers(dest="command"))
    path = tmp_path / "u.yaml"

    def run(*argv, stdin=""):
        monkeypatch.setattr("sys.stdin", io.StringIO(stdin))
        args = p.parse_args(["users", *argv, "--file", str(path)])
        return args.func(args)
    assert run("add", "alice", "--role", "operator", "--password-stdin", stdin="correct horse\n") == 0
    assert path.stat().st_mode & 0o777 == 0o600 and "correct horse" not in path.read_text()
    assert load_users(str(path)).roles("alice", "correct horse") == frozenset({"operator"})
    with pytest.raises(UsageError, match="exists"):
        run("add", "alice", "--password-stdin", stdin="another one\n")
    assert run("add", "bob", "--password-stdin", stdin="bobs password\n") == 0
    assert run("remove", "alice") == 0
    assert run("list") == 0
    assert capsys.readouterr().out.splitlines()[-1] == "bob\tviewer"
