"""Operators' accounts: who may command the machine from the OPC UA server and the operator page.

The file (``daemon.users_file``) is YAML::

    users:
      alice: {password: "scrypt$16384$8$1$<salt>$<hash>", roles: [operator]}
      bob:   {password: "scrypt$16384$8$1$<salt>$<hash>", roles: [viewer]}

Passwords are stored only as scrypt hashes (RFC 7914, :func:`hashlib.scrypt`; salt and hash
base64). Roles: ``operator`` (commands: start, hold, resume, abort, home, jog, program load,
fault reset) and ``viewer`` (read only, as an anonymous session when that is allowed).
:func:`hash_password` makes an entry's ``password`` value.
"""

from __future__ import annotations

import base64
import hashlib
import hmac
import os
from dataclasses import dataclass

import yaml

ROLES = ("operator", "viewer")
#: scrypt's cost parameters (RFC 7914 section 2: N = 2^14, r = 8, p = 1, 16 MiB per check)
SCRYPT_N, SCRYPT_R, SCRYPT_P = 1 << 14, 8, 1


class UsersError(ValueError):
    """The users file is missing or wrong: one line naming the file, the key and what is allowed."""


def hash_password(password: str, salt: bytes | None = None) -> str:
    """The ``password`` value of a users-file entry: ``scrypt$N$r$p$salt$hash`` (base64)."""
    salt = os.urandom(16) if salt is None else salt
    h = hashlib.scrypt(password.encode(), salt=salt, n=SCRYPT_N, r=SCRYPT_R, p=SCRYPT_P, dklen=32)
    b = base64.b64encode
    return f"scrypt${SCRYPT_N}${SCRYPT_R}${SCRYPT_P}${b(salt).decode()}${b(h).decode()}"


def _verify(stored: str, password: str) -> bool:
    _, n, r, p, salt, want = stored.split("$")
    got = hashlib.scrypt(password.encode(), salt=base64.b64decode(salt), n=int(n), r=int(r), p=int(p),
                         dklen=len(base64.b64decode(want)), maxmem=256 << 20)
    return hmac.compare_digest(got, base64.b64decode(want))


@dataclass(frozen=True)
class Users:
    """The accounts of one users file: name -> (password hash, roles)."""

    path: str
    accounts: dict

    def roles(self, name: str, password: str) -> frozenset[str] | None:
        """The roles of ``name`` when ``password`` is right, else None (unknown name or wrong
        password alike). The same work whatever the name: an unknown name is checked against a
        dummy hash with the cost parameters of the file's first account (one scrypt, as for a
        known name), so the time of a refusal does not tell whether the name exists; the
        comparison is constant-time (:func:`hmac.compare_digest`)."""
        if not isinstance(password, str):
            return None
        entry = self.accounts.get(name) if isinstance(name, str) else None
        if entry is None:
            _verify(self._dummy(), password)
            return None
        stored, roles = entry
        return frozenset(roles) if _verify(stored, password) else None

    def _dummy(self) -> str:
        """A hash no password matches, with the cost (N, r, p, salt and hash lengths) of the
        file's first account (the module's defaults for an empty file)."""
        first = next(iter(self.accounts.values()), None)
        if first is None:
            b = base64.b64encode
            return f"scrypt${SCRYPT_N}${SCRYPT_R}${SCRYPT_P}${b(bytes(16)).decode()}${b(bytes(32)).decode()}"
        _, n, r, p, salt, want = first[0].split("$")
        return f"scrypt${n}${r}${p}${salt}${base64.b64encode(bytes(len(base64.b64decode(want)))).decode()}"


def load_users(path: str) -> Users:
    """Read and check a users file. Raises UsersError (file, key, what is allowed)."""
    try:
        with open(path, encoding="utf-8") as f:
            data = yaml.safe_load(f)
    except OSError as exc:
        raise UsersError(f"{path}: cannot read the users file ({exc.strerror})") from None
    except yaml.YAMLError as exc:
        raise UsersError(f"{path}: not valid YAML ({exc})") from None
    if not isinstance(data, dict) or not isinstance(data.get("users"), dict):
        raise UsersError(f"{path}: users: missing; allowed: a mapping of user names to "
                         "{password: scrypt$..., roles: [operator|viewer]}")
    accounts = {}
    for name, entry in data["users"].items():
        key = f"{path}: users.{name}"
        if not isinstance(entry, dict) or set(entry) - {"password", "roles"}:
            raise UsersError(f"{key}: allowed keys: password, roles")
        pw, roles = entry.get("password"), entry.get("roles", ["viewer"])
        if not isinstance(pw, str) or pw.count("$") != 5 or not pw.startswith("scrypt$"):
            raise UsersError(f"{key}.password: not an scrypt hash; allowed: the output of "
                             "motorctl.app.users.hash_password (scrypt$N$r$p$salt$hash)")
        if not isinstance(roles, list) or not roles or any(r not in ROLES for r in roles):
            raise UsersError(f"{key}.roles: {roles!r}; allowed: a list of {', '.join(ROLES)}")
        accounts[str(name)] = (pw, tuple(roles))
    return Users(path, accounts)
