"""Log-ins (motorctl.app.login, motorctl.app.users): an unknown name costs the same scrypt as a
known one, back-off per name and per address, the 6th wrong password within a minute locks the
name, the operator unlocks it (``motorctl users unlock``), every refusal and lockout in the
journal. The clock is the test's own (no waiting); hashes are made with a small scrypt cost
(N = 2^10) so the checks are quick."""

from __future__ import annotations

import hashlib
import logging

import pytest
import yaml

from motorctl.app import users as users_mod
from motorctl.app.login import FREE_FAILURES, JOURNAL, LOCK_AFTER, LoginGuard, state_path
from motorctl.app.users import Users, hash_password, load_users


@pytest.fixture
def cheap_scrypt(monkeypatch):
    monkeypatch.setattr(users_mod, "SCRYPT_N", 1 << 10)


@pytest.fixture
def users(cheap_scrypt, tmp_path):
    p = tmp_path / "users.yaml"
    p.write_text(yaml.safe_dump({"users": {
        "olga": {"password": hash_password("op-secret"), "roles": ["operator"]},
        "victor": {"password": hash_password("view-secret"), "roles": ["viewer"]}}}))
    return load_users(str(p))


@pytest.fixture
def clock():
    class Clock:
        t = 1.8e9

        def __call__(self):
            return self.t
    return Clock()


@pytest.fixture
def journal():
    lines: list[str] = []

    class H(logging.Handler):
        def emit(self, record):
            lines.append(record.getMessage())
    h = H()
    JOURNAL.addHandler(h)
    level = JOURNAL.level
    JOURNAL.setLevel(logging.INFO)
    yield lines
    JOURNAL.removeHandler(h)
    JOURNAL.setLevel(level)


def _counting(monkeypatch) -> list:
    calls = []
    real = hashlib.scrypt

    def scrypt(pw, **kw):
        calls.append((kw["n"], kw["r"], kw["p"], len(kw["salt"]), kw["dklen"]))
        return real(pw, **kw)
    monkeypatch.setattr(users_mod.hashlib, "scrypt", scrypt)
    return calls


def test_an_unknown_name_costs_the_scrypt_of_a_known_one(users, monkeypatch):
    calls = _counting(monkeypatch)
    assert users.roles("olga", "op-secret") == frozenset({"operator"})
    assert users.roles("olga", "wrong") is None
    assert users.roles("nobody", "wrong") is None
    assert users.roles("nobody", "op-secret") is None
    assert len(calls) == 4 and len(set(calls)) == 1, calls      # one scrypt each, the same cost
    calls.clear()
    assert Users("none.yaml", {}).roles("nobody", "x") is None  # an empty file: the defaults' cost
    assert calls == [(users_mod.SCRYPT_N, users_mod.SCRYPT_R, users_mod.SCRYPT_P, 16, 32)]


def test_the_sixth_wrong_password_within_a_minute_locks_the_name(users, tmp_path, clock, journal, monkeypatch):
    g = LoginGuard(str(tmp_path / "m.logins.json"), lockout_s=300.0, surface="test", clock=clock)
    for name in ("olga", "nobody"):                       # an unknown name is locked as a known one
        for i in range(LOCK_AFTER):
            clock.t += 9.0                                # past each back-off, all within 60 s
            v = g.attempt(users, name, "wrong", f"192.0.2.{i}")
            assert v.why == ("locked" if i == LOCK_AFTER - 1 else "wrong"), (name, i, v)
    assert set(g.locked()) == {"olga", "nobody"}
    calls = _counting(monkeypatch)
    clock.t += 60.0
    v = g.attempt(users, "olga", "op-secret", "198.51.100.1")      # the right password: refused
    assert (v.ok, v.why) == (False, "locked") and not calls        # and not even checked
    clock.t += 300.0
    assert g.attempt(users, "olga", "op-secret", "198.51.100.1").roles == frozenset({"operator"})
    assert any("'olga' locked for 300 s" in ln for ln in journal)
    assert any("'nobody' from 192.0.2.0 (test): unknown name" in ln for ln in journal)
    assert any("'olga' from 192.0.2.1 (test): wrong password" in ln for ln in journal)
    assert not any("wrong" in ln.split(":")[-1] and "op-secret" in ln for ln in journal)
    assert not any("op-secret" in ln for ln in journal)


def test_back_off_per_name_and_per_address(users, tmp_path, clock, monkeypatch):
    g = LoginGuard(str(tmp_path / "m.logins.json"), clock=clock)
    for i in range(FREE_FAILURES):                        # a few typos: answered at once
        assert g.attempt(users, "olga", "wrong", f"192.0.2.{i}").why == "wrong"
    calls = _counting(monkeypatch)
    v = g.attempt(users, "olga", "op-secret", "198.51.100.7")     # the name backs off, any address
    assert v.why == "backoff" and v.retry_s > 0 and not calls
    clock.t += v.retry_s + 0.01
    assert g.attempt(users, "olga", "op-secret", "198.51.100.7").ok
    for name in ("a", "b", "c"):                          # one address, several names
        clock.t += 0.1
        assert g.attempt(users, name, "x", "203.0.113.9").why == "wrong"
    assert g.attempt(users, "victor", "view-secret", "203.0.113.9").why == "backoff"
    assert g.attempt(users, "victor", "view-secret", "203.0.113.10").ok


def test_the_operator_unlocks_a_name_from_the_command_line(users, tmp_path, clock, capsys):
    from motorctl.cli import main as cli
    sock = tmp_path / "motorctl.sock"
    g = LoginGuard(state_path(str(sock)), clock=clock)
    for i in range(LOCK_AFTER):
        clock.t += 9.0
        g.attempt(users, "victor", "wrong", "192.0.2.1")
    assert "victor" in LoginGuard(state_path(str(sock))).locked()
    assert cli(["--socket", str(sock), "users", "list", "--file", users.path]) == 0
    out = capsys.readouterr().out
    assert "victor\tviewer\tlocked until" in out and "olga\toperator\n" in out, out
    assert cli(["--socket", str(sock), "users", "unlock", "victor"]) == 0
    assert "victor: unlocked" in capsys.readouterr().out
    clock.t += 1.0
    assert g.attempt(users, "victor", "view-secret", "192.0.2.1").ok
    assert cli(["--socket", str(sock), "users", "unlock"]) == 2
    assert capsys.readouterr().err.count("\n") == 1


def test_a_broken_state_file_is_taken_as_empty(users, tmp_path, clock):
    p = tmp_path / "m.logins.json"
    p.write_text("{not json")
    g = LoginGuard(str(p), clock=clock)
    assert g.attempt(users, "olga", "op-secret", "192.0.2.1").ok
    assert g.attempt(users, "olga", "wrong", "192.0.2.1").why == "wrong"


def test_the_operator_page_answers_a_refusal_alike_and_backs_off(users, tmp_path, journal, monkeypatch):
    """The page's /login (aiohttp's test client on loopback, no daemon: a login does not ask
    it): a wrong password and an unknown name get the same answer; after FREE_FAILURES
    failures from an address the next login is answered 429 with Retry-After, the right
    password too; each refusal is journaled with the client's address."""
    import asyncio

    from aiohttp import web
    from aiohttp.test_utils import TestClient, TestServer

    from motorctl.app.daemon import operator_page
    monkeypatch.setattr(operator_page, "LOGIN_FAIL_DELAY_S", 0.0)

    async def go():
        app = web.Application()
        operator_page.OperatorPage(str(tmp_path / "m.sock"), users.path, ["X"], lambda n: b"").add_routes(app)
        async with TestClient(TestServer(app, host="127.0.0.1")) as c:
            out = []
            for name in ("olga", "nobody", "victor"):
                r = await c.post("/login", json={"name": name, "password": "wrong"})
                out.append((r.status, await r.json()))
            r = await c.post("/login", json={"name": "olga", "password": "op-secret"})
            out.append((r.status, await r.json(), r.headers.get("Retry-After")))
            return out

    out = asyncio.run(go())
    assert out[0] == out[1] == out[2] == (403, {"ok": False, "error": "wrong name or password"}), out
    assert out[3][0] == 429 and int(out[3][2]) >= 1 and not out[3][1]["ok"], out
    assert any("'nobody' from 127.0.0.1 (operator page): unknown name" in ln for ln in journal)
    assert any("'olga' from 127.0.0.1 (operator page): backing off" in ln for ln in journal)
