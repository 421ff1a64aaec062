"""``motorctl opcua list|trust|untrust``: the OPC UA server's trust list of client certificates
(:class:`motorctl.app.daemon.opcua_server.TrustList`, ``daemon.opcua.pki_dir``, else
``LOG_DIR/opcua``): ``list`` shows the trusted and the rejected ones (a client refused for an
untrusted certificate is kept in ``rejected/``), ``trust CERT`` accepts a certificate file (DER
or PEM) or a rejected one by its thumbprint, ``untrust`` removes one. The server reads the list
again at the next connection: no restart.
"""

from __future__ import annotations

from motorctl.cli import DEFAULT_CONFIG, UsageError


def register(parser, subparsers) -> None:
    """Add the ``opcua`` subcommand (called by :func:`motorctl.cli.build_parser`)."""
    p = subparsers.add_parser("opcua", help="the OPC UA server's trust list of client certificates "
                                            "(list, trust, untrust)")
    p.add_argument("action", choices=("list", "trust", "untrust"),
                   help="list the trusted and rejected client certificates; trust one (a file, or a "
                        "rejected one's thumbprint); untrust one")
    p.add_argument("cert", nargs="?", default=None, metavar="CERT",
                   help="trust, untrust: a certificate file (DER or PEM) or a thumbprint (8+ hex digits, "
                        "as `list` shows)")
    p.add_argument("--config", default=DEFAULT_CONFIG, help=f"the daemon's config (default {DEFAULT_CONFIG})")
    p.add_argument("--pki-dir", default=None, metavar="DIR",
                   help="the trust list's folder (default: daemon.opcua.pki_dir of --config, else LOG_DIR/opcua)")
    p.set_defaults(func=cmd_opcua)


def _trust_list(args):
    from motorctl.app.daemon.opcua_server import TrustList, pki_dir
    if args.pki_dir:
        return TrustList(args.pki_dir)
    from motorctl.config import ConfigError, load_config
    try:
        cfg = load_config(args.config).cfg
    except ConfigError as exc:
        raise UsageError(f"{exc}; or give --pki-dir DIR") from None
    return TrustList(pki_dir(cfg))


def cmd_opcua(args) -> int:
    """The ``opcua`` command: exit 0, or 2 with one line (UsageError)."""
    tl = _trust_list(args)
    if args.action == "list":
        rows = tl.listing()
        if not rows:
            print(f"{tl.pki}: no client certificates trusted or rejected")
        for e in rows:
            print(f"{e['state']}\t{e['thumbprint']}\t{e['subject']}\t{e['uri']}\tuntil {e['not_after']}")
        return 0
    if not args.cert:
        raise UsageError(f"opcua {args.action}: a CERT (a certificate file or a thumbprint) is needed")
    try:
        if args.action == "trust":
            e = tl.trust(args.cert)
            print(f"trusted: {e['thumbprint']} {e['subject']} ({e['path']})")
        else:
            n = tl.untrust(args.cert)
            print(f"untrusted: {n} file(s) removed from {tl.trusted_dir}")
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    except OSError as exc:
        raise UsageError(f"{tl.pki}: {exc.strerror or exc}") from None
    return 0
