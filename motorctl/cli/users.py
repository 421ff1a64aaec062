"""``motorctl users add|remove|list|unlock``: the accounts of the users file
(``daemon.users_file``, :mod:`motorctl.app.users`) that the operator page and the OPC UA server
check, and the lockouts of their logins (:mod:`motorctl.app.login`: ``unlock NAME`` clears a
name locked after failed logins; ``list`` shows the locked ones).

A password is never an argument (the process list shows arguments): it is asked on the
terminal (twice) or read as the first line of stdin (``--password-stdin``), and only its scrypt
hash is written. The file is written whole to a temporary file beside it, then renamed over it
(a reader sees the old file or the new one); a new file is created with mode 0600. The daemon's
page reads the file again when it changes (no restart).
"""

from __future__ import annotations

import getpass
import os
import sys
import tempfile

import yaml

from motorctl.cli import DEFAULT_CONFIG, UsageError


def register(parser, subparsers) -> None:
    """Add the ``users`` subcommand (called by :func:`motorctl.cli.build_parser`)."""
    p = subparsers.add_parser("users", help="add, remove or list the operator page's accounts "
                                            "(the users file: scrypt-hashed passwords, roles)")
    p.add_argument("action", choices=("add", "remove", "list", "unlock"),
                   help="add (or with --replace: change) a user, remove one, list them (and the locked "
                        "names), or unlock a name locked after failed logins")
    p.add_argument("name", nargs="?", default=None, help="the user's name (add, remove, unlock)")
    p.add_argument("--role", action="append", choices=("operator", "viewer"), default=None,
                   help="the user's role (repeatable; default viewer): operator may command")
    p.add_argument("--file", default=None, metavar="USERS_YAML",
                   help="the users file (default: daemon.users_file of --config)")
    p.add_argument("--config", default=DEFAULT_CONFIG, help=f"the daemon's config (default {DEFAULT_CONFIG})")
    p.add_argument("--replace", action="store_true", help="add: replace an existing user's password and roles")
    p.add_argument("--password-stdin", action="store_true",
                   help="add: read the password from the first line of stdin instead of asking")
    p.set_defaults(func=cmd_users)


def users_path(args) -> str:
    """The users file of the command: ``--file``, else the config's ``daemon.users_file``.
    Raises UsageError (one line)."""
    if args.file:
        return args.file
    from motorctl.config import load_yaml
    try:
        d = load_yaml(args.config)
    except Exception as exc:                       # noqa: BLE001 - one line, exit 2
        raise UsageError(f"{args.config}: {exc}") from None
    path = (d.get("daemon") or {}).get("users_file") if isinstance(d, dict) else None
    if not path:
        raise UsageError(f"{args.config}: daemon.users_file is not set; give --file USERS_YAML")
    return str(path)


def login_guard(args):
    """The log-in guard of the daemon (its state file beside its control socket: the global
    ``--socket``, else ``$MOTORCTL_SOCKET``, else ``daemon.socket`` of ``--config``). Raises
    UsageError (one line)."""
    from motorctl.app.login import LoginGuard, state_path
    sock = getattr(args, "socket", None) or os.environ.get("MOTORCTL_SOCKET")
    if not sock:
        from motorctl.config import ConfigError, load_config
        try:
            sock = load_config(args.config).cfg.daemon.socket
        except ConfigError as exc:
            raise UsageError(f"{exc}; or give --socket PATH") from None
    return LoginGuard(state_path(sock))


def _read(path: str) -> dict:
    if not os.path.exists(path):
        return {"users": {}}
    from motorctl.app.users import UsersError, load_users
    try:
        load_users(path)                           # the same checks as the daemon's
    except UsersError as exc:
        raise UsageError(str(exc)) from None
    with open(path, encoding="utf-8") as f:
        return yaml.safe_load(f)


def _write(path: str, data: dict) -> None:
    """Write ``data`` to ``path`` atomically (temporary file, fsync, rename); mode 0600 for a new
    file, the old file's mode otherwise. Raises UsageError (one line)."""
    mode = os.stat(path).st_mode & 0o777 if os.path.exists(path) else 0o600
    d = os.path.dirname(os.path.abspath(path))
    try:
        fd, tmp = tempfile.mkstemp(prefix=".users-", dir=d)
        try:
            with os.fdopen(fd, "w", encoding="utf-8") as f:
                yaml.safe_dump(data, f, sort_keys=True)
                f.flush()
                os.fsync(f.fileno())
            os.chmod(tmp, mode)
            os.replace(tmp, path)
        except BaseException:
            os.unlink(tmp)
            raise
    except OSError as exc:
        raise UsageError(f"{path}: cannot write the users file ({exc.strerror})") from None


def _password(args) -> str:
    if args.password_stdin:
        pw = sys.stdin.readline().rstrip("\r\n")
    else:
        pw = getpass.getpass(f"password for {args.name}: ")
        if getpass.getpass("again: ") != pw:
            raise UsageError("the two passwords differ; nothing written")
    if len(pw) < 8:
        raise UsageError("the password is shorter than 8 characters; nothing written")
    return pw


def cmd_users(args) -> int:
    """The ``users`` command: exit 0, or 2 with one line (UsageError)."""
    if args.action == "unlock":
        if not args.name:
            raise UsageError("users unlock: the NAME to unlock is needed")
        try:
            was = login_guard(args).unlock(args.name)
        except OSError as exc:
            raise UsageError(f"users unlock: the daemon's login state: {exc.strerror or exc}") from None
        print(f"{args.name}: unlocked" if was else f"{args.name}: was not locked (failed logins cleared)")
        return 0
    path = users_path(args)
    data = _read(path)
    users = data.setdefault("users", {}) or {}
    data["users"] = users
    if args.action == "list":
        locked = _locked(args)
        for name, entry in sorted(users.items()):
            lock = f"\tlocked until {_utc(locked[name])}" if name in locked else ""
            print(f"{name}\t{','.join(entry.get('roles', ['viewer']))}{lock}")
        return 0
    if not args.name or any(c.isspace() for c in args.name):
        raise UsageError(f"users {args.action}: a NAME without spaces is needed")
    if args.action == "remove":
        if users.pop(args.name, None) is None:
            raise UsageError(f"{path}: no user {args.name!r}")
        _write(path, data)
        print(f"{path}: {args.name} removed")
        return 0
    if args.name in users and not args.replace:
        raise UsageError(f"{path}: {args.name!r} exists; --replace changes the password and roles")
    from motorctl.app.users import hash_password
    roles = sorted(set(args.role or ["viewer"]))
    users[args.name] = {"password": hash_password(_password(args)), "roles": roles}
    _write(path, data)
    print(f"{path}: {args.name} ({', '.join(roles)})")
    return 0


def _locked(args) -> dict:
    """The locked names of the daemon of ``--config`` ({} when the config or its state cannot
    be read: ``list`` of a bare ``--file`` shows the accounts only)."""
    try:
        return login_guard(args).locked()
    except (UsageError, OSError):
        return {}


def _utc(t: float) -> str:
    import time
    return time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime(t))
