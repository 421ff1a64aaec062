"""Log-ins on the OPC UA server and the operator page: one check, one back-off, one lockout.

Both surfaces (:mod:`motorctl.app.daemon.opcua_server`, :mod:`motorctl.app.daemon.operator_page`)
check a name and a password through :meth:`LoginGuard.attempt`, which

* refuses in the same time whatever the name: :meth:`motorctl.app.users.Users.roles` runs one
  scrypt for an unknown name as for a known one (OWASP Authentication Cheat Sheet, "Login
  Throttling" and "Authentication Responses"; the time of a refusal does not enumerate users);
* backs off per user name and per client address: after :data:`FREE_FAILURES` failed logins
  within :data:`WINDOW_S`, the next attempt is refused unchecked until ``BACKOFF_BASE_S * 2 **
  (n - FREE_FAILURES)`` seconds (at most :data:`BACKOFF_MAX_S`) after the last failure
  (``n``: the failures in the window);
* locks a user name after its :data:`LOCK_AFTER`-th failed login within :data:`WINDOW_S` for
  ``lockout_s`` (``daemon.login_lockout_s``): every login of that name is refused, the right
  password too, until it expires or the operator clears it (``motorctl users unlock NAME``,
  :meth:`LoginGuard.unlock`);
* writes each refusal and each lockout to the journal (the logger :data:`JOURNAL`, one line on
  the daemon's stderr: the name, the address, the surface and why; never a password).

Unknown names are counted and locked as known ones are, so neither the answers nor the
lockouts tell whether a name exists. The counts live in a small JSON file beside the daemon's
control socket (:func:`state_path`), shared by both surfaces and the command line and locked
with :func:`fcntl.flock` for each update; the password check itself runs outside the lock.
Times are the wall clock (seconds since the epoch), so a lock means the same to every process.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import logging
import os
import sys
import time
from dataclasses import dataclass

#: failed logins are counted over this window [s]
WINDOW_S = 60.0
#: the failed login (within WINDOW_S) that locks a user name
LOCK_AFTER = 6
#: failed logins within WINDOW_S answered without a back-off (a mistyped password)
FREE_FAILURES = 3
#: the first back-off [s]; it doubles with each further failure in the window
BACKOFF_BASE_S = 1.0
#: the longest back-off [s]
BACKOFF_MAX_S = 60.0
#: how long a user name stays locked when the config does not say (daemon.login_lockout_s) [s]
LOCKOUT_S = 900.0
#: names and addresses the state file keeps at most (the least recently failed go first)
MAX_KEYS = 4096
#: the journal's logger
JOURNAL = logging.getLogger("motorctl.login")
#: a name as the journal and the state file keep it (an attacker's name is not a line of its own)
NAME_CHARS = 64


def state_path(socket_path: str) -> str:
    """The state file of the daemon whose control socket is ``socket_path``:
    ``<socket without its suffix>.logins.json`` (``/run/motorctl/motorctl.logins.json``)."""
    return os.path.splitext(socket_path)[0] + ".logins.json"


def journal_to_stderr() -> None:
    """Send the journal's lines to stderr (the daemon's journal) as ``motorctl: login: ...``;
    called once by each process that serves logins. Idempotent."""
    if not any(getattr(h, "_motorctl_login", False) for h in JOURNAL.handlers):
        h = logging.StreamHandler(sys.stderr)
        h.setFormatter(logging.Formatter("motorctl: login: %(message)s"))
        h._motorctl_login = True
        JOURNAL.addHandler(h)
    JOURNAL.setLevel(logging.INFO)
    JOURNAL.propagate = False


def backoff_s(n: int) -> float:
    """The back-off after ``n`` failed logins within WINDOW_S [s]: 0 up to FREE_FAILURES - 1,
    then BACKOFF_BASE_S doubling, at most BACKOFF_MAX_S."""
    if n < FREE_FAILURES:
        return 0.0
    return min(BACKOFF_BASE_S * 2.0 ** (n - FREE_FAILURES), BACKOFF_MAX_S)


@dataclass(frozen=True)
class Verdict:
    """The outcome of a login: ``roles`` (None: refused); ``why``: "" (logged in), "wrong"
    (name or password), "backoff" (too soon after failures of this name or address), "locked"
    (the name is locked); ``retry_s``: when a refused login may be tried again [s]."""

    roles: frozenset | None
    why: str = ""
    retry_s: float = 0.0

    @property
    def ok(self) -> bool:
        return self.roles is not None


def _clean(name: str) -> str:
    return repr(str(name)[:NAME_CHARS])


class LoginGuard:
    """The log-in check of one daemon (module docstring).

    Args:
        path: the state file (:func:`state_path`); its folder must exist; made with mode 0600.
        lockout_s: how long a locked name stays locked [s] (``daemon.login_lockout_s``).
        surface: the journal's name for the caller ("OPC UA", "operator page").
        clock: seconds since the epoch (:func:`time.time`; tests give their own).
    """

    def __init__(self, path: str, lockout_s: float = LOCKOUT_S, surface: str = "", clock=time.time):
        self.path, self.lockout_s, self.surface, self.clock = path, float(lockout_s), surface, clock

    # ------------------------------------------------------------------ the state file
    @contextlib.contextmanager
    def _state(self, write: bool = True):
        """The state ``{"users": {name: {"fail": [t, ...], "locked_until": t}}, "addresses":
        {addr: {"fail": [...]}}}`` under an exclusive lock; written back when ``write``. A file
        that cannot be parsed is taken as empty (counts lost, never a login let in by it)."""
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o600)
        with os.fdopen(fd, "r+", encoding="utf-8") as f:
            fcntl.flock(f, fcntl.LOCK_EX)
            try:
                st = json.loads(f.read() or "{}")
                if not isinstance(st, dict):
                    st = {}
            except ValueError:
                st = {}
            st.setdefault("users", {})
            st.setdefault("addresses", {})
            yield st
            if write:
                self._prune(st)
                f.seek(0)
                f.truncate()
                json.dump(st, f)
                f.flush()

    def _prune(self, st: dict) -> None:
        now = self.clock()
        for kind in ("users", "addresses"):
            keep = {}
            for k, e in st[kind].items():
                fails = [t for t in e.get("fail", []) if now - t < WINDOW_S]
                locked = e.get("locked_until", 0.0)
                if fails or locked > now:
                    keep[k] = {"fail": fails, **({"locked_until": locked} if locked > now else {})}
            if len(keep) > MAX_KEYS:
                recent = sorted(keep, key=lambda k: max(keep[k]["fail"] or [keep[k].get("locked_until", 0.0)]))
                for k in recent[:len(keep) - MAX_KEYS]:
                    del keep[k]
            st[kind] = keep

    def _fails(self, e: dict | None, now: float) -> list[float]:
        return [t for t in (e or {}).get("fail", []) if now - t < WINDOW_S]

    # ------------------------------------------------------------------ the check
    def attempt(self, users, name: str, password: str, address: str) -> Verdict:
        """Check ``name`` and ``password`` against ``users`` (:class:`motorctl.app.users.Users`)
        for a client at ``address`` (its IP address, as a string). Refused unchecked while the
        name is locked or the name or the address is backing off; else one scrypt (the same
        work for an unknown name). Journals every refusal and lockout. Raises OSError when the
        state file cannot be used (the caller refuses the login)."""
        name, address = str(name)[:256], str(address)
        now = self.clock()
        with self._state(write=False) as st:
            ue, ae = st["users"].get(name), st["addresses"].get(address)
            locked = (ue or {}).get("locked_until", 0.0)
            uf, af = self._fails(ue, now), self._fails(ae, now)
        if locked > now:
            return self._refused(name, address, "locked", locked - now,
                                 f"the name is locked until {_utc(locked)}")
        wait = max((uf[-1] + backoff_s(len(uf)) - now) if uf else 0.0,
                   (af[-1] + backoff_s(len(af)) - now) if af else 0.0)
        if wait > 0:
            return self._refused(name, address, "backoff", wait,
                                 f"backing off after {max(len(uf), len(af))} failed logins within "
                                 f"{WINDOW_S:g} s, retry in {wait:.1f} s")
        roles = users.roles(name, password)
        if roles is not None:
            with self._state() as st:
                st["users"].pop(name, None)
            JOURNAL.info("%s logged in from %s (%s)", _clean(name), address, self.surface)
            return Verdict(frozenset(roles))
        now = self.clock()
        with self._state() as st:
            ue = st["users"].setdefault(name, {})
            ue["fail"] = self._fails(ue, now) + [now]
            ae = st["addresses"].setdefault(address, {})
            ae["fail"] = self._fails(ae, now) + [now]
            n = len(ue["fail"])
            lock = n >= LOCK_AFTER
            if lock:
                ue["locked_until"] = now + self.lockout_s
                ue["fail"] = []
        known = name in getattr(users, "accounts", {})
        self._refused(name, address, "wrong", backoff_s(n),
                      f"{'wrong password' if known else 'unknown name'} ({n} failed within {WINDOW_S:g} s)")
        if lock:
            JOURNAL.warning("user %s locked for %g s after %d failed logins within %g s (the last from %s, "
                            "%s); `motorctl users unlock %s` clears it", _clean(name), self.lockout_s,
                            LOCK_AFTER, WINDOW_S, address, self.surface, _clean(name))
            return Verdict(None, "locked", self.lockout_s)
        return Verdict(None, "wrong", backoff_s(n))

    def _refused(self, name: str, address: str, why: str, retry_s: float, text: str) -> Verdict:
        JOURNAL.warning("login refused: %s from %s (%s): %s", _clean(name), address, self.surface, text)
        return Verdict(None, why, retry_s)

    # ------------------------------------------------------------------ the operator's view
    def locked(self) -> dict[str, float]:
        """The locked names and until when each [s since the epoch]."""
        if not os.path.exists(self.path):
            return {}
        now = self.clock()
        with self._state(write=False) as st:
            return {k: e["locked_until"] for k, e in st["users"].items() if e.get("locked_until", 0.0) > now}

    def unlock(self, name: str) -> bool:
        """Clear the lock and the failed logins of ``name``, and every address's back-off (the
        name's own computer may be one of them): its next login is checked at once. True when
        it was locked. Journaled."""
        if not os.path.exists(self.path):
            return False
        with self._state() as st:
            e = st["users"].pop(str(name)[:256], None)
            st["addresses"] = {}
        was = bool(e and e.get("locked_until", 0.0) > self.clock())
        if was:
            JOURNAL.warning("user %s unlocked by the operator", _clean(name))
        return was


def _utc(t: float) -> str:
    return time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime(t))
