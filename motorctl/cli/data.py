"""``motorctl data``: the public data sets the examples use, fetched and checked by SHA-256.

    motorctl data fetch NAME [--url URL] [--validation-url URL]
                                             download into the data directory (the `data` extra)
    motorctl data path NAME [--validation]   print the checked local path
    motorctl data list                       the known data sets and where each is kept

The data directory is ``$MOTORCTL_DATA_DIR``, else the user cache directory
(:mod:`motorctl.datasets`). Exit codes: 0 done, 1 the source could not be reached, 2 bad input
(unknown name, a download whose SHA-256 differs: nothing kept; a file not fetched yet; pooch
missing): one line on stderr.

A set's further files (EMPS: the validation record ``DATA_EMPS_PULSES.mat``) are fetched with
it from their own pinned sources; with ``--url`` (a mirror of the main file) only from
``--validation-url`` when that is given, else not (the mirror may hold the main file only).
"""

from __future__ import annotations

import logging
import sys

from motorctl import datasets


def register(parser, subparsers) -> None:
    """Add the ``data`` subcommand (called by :func:`motorctl.cli.build_parser`)."""
    p = subparsers.add_parser("data", help="fetch the public data sets the examples use (EMPS), "
                                           "SHA-256 checked, into MOTORCTL_DATA_DIR")
    sub = p.add_subparsers(dest="data_command", metavar="ACTION", help="fetch, path or list")
    sub.required = True
    names = sorted(datasets.DATASETS)
    f = sub.add_parser("fetch", help="download a data set unless it is already there with the right SHA-256")
    f.add_argument("name", choices=names, help="data set")
    f.add_argument("--url", default=None,
                   help="download from this http(s) or file URL instead (a mirror); the SHA-256 is still checked")
    f.add_argument("--validation-url", default=None,
                   help="download the set's validation record (EMPS: DATA_EMPS_PULSES.mat) from this "
                        "http(s) or file URL instead; with --url and without this, it is not fetched")
    f.set_defaults(func=cmd_fetch)
    q = sub.add_parser("path", help="print the local path of a fetched data set (its SHA-256 checked)")
    q.add_argument("name", choices=names, help="data set")
    q.add_argument("--validation", action="store_true", help="the set's validation record instead")
    q.set_defaults(func=cmd_path)
    ls = sub.add_parser("list", help="the known data sets, where each is kept and whether it is there")
    ls.set_defaults(func=cmd_list)


def _usage(fn):
    """Run ``fn``, turning a :class:`motorctl.datasets.DataError` into the CLI's one-line bad input."""
    from motorctl.cli import UsageError
    try:
        return fn()
    except datasets.DataError as exc:
        raise UsageError(f"data: {exc}") from None


def cmd_fetch(args) -> int:
    import pooch
    pooch.get_logger().setLevel(logging.WARNING)    # this command prints its own line
    path, downloaded = _usage(lambda: datasets.fetch(args.name, url=args.url))
    print(f"{args.name}: {path} ({'downloaded' if downloaded else 'already there'}, SHA-256 "
          f"{datasets.DATASETS[args.name].sha256[:12]}... checked)")
    vurl = getattr(args, "validation_url", None)
    for f in datasets.DATASETS[args.name].extra:
        if args.url is not None and vurl is None:
            continue
        fpath, got = _usage(lambda f=f: datasets.fetch_extra(args.name, f.role, url=vurl))
        print(f"{args.name} ({f.role}): {fpath} ({'downloaded' if got else 'already there'}, SHA-256 "
              f"{f.sha256[:12]}... checked)")
    return 0


def cmd_path(args) -> int:
    if getattr(args, "validation", False):
        print(_usage(lambda: datasets.verified_extra_path(args.name, "validation")))
    else:
        print(_usage(lambda: datasets.verified_path(args.name)))
    return 0


def cmd_list(args) -> int:
    root = datasets.data_dir()
    for name, d in sorted(datasets.DATASETS.items()):
        path = datasets.local_path(name, root)
        sys.stdout.write(f"{name}: {d.about}\n  {path} ({'present' if path.is_file() else 'not fetched'})\n")
        for f in d.extra:
            fp = datasets.extra_path(name, f.role, root)
            sys.stdout.write(f"  {fp} ({f.role}; {'present' if fp.is_file() else 'not fetched'})\n")
    return 0
