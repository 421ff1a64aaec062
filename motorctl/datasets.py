"""Public data sets the project works with, fetched on demand and checked by SHA-256.

A data set lives in ``<data dir>/<name>/<file>``; the data directory is the environment variable
``MOTORCTL_DATA_DIR`` when set, else the user cache directory of ``pooch.os_cache("motorctl")``
(e.g. ``~/.cache/motorctl`` on Linux). With the file already there and its SHA-256 right, nothing
is downloaded, so a machine without network works from a directory holding a copy (CI and the
tests point ``MOTORCTL_DATA_DIR`` at one). Downloads go through pooch (the ``data`` extra): the
file is streamed to a temporary name beside its target and moved into place only when its
SHA-256 matches the pinned one.

* ``emps``: ``DATA_EMPS.mat``, the estimation record of the EMPS benchmark (Electro-Mechanical
  Positioning System, ONERA / LS2N; A. Janot, M. Gautier, M. Brunot, "Data Set and Reference
  Models of EMPS", Workshop on Nonlinear System Identification Benchmarks, Eindhoven, 2019,
  nonlinearbenchmark.org). A MATLAB 5 file (``scipy.io.loadmat``): ``t``, ``qm``, ``qg``, ``vir``
  of shape (24841, 1) (s, m, m, V) sampled at 1 kHz, and the drive gain ``gtau`` (N/V). The
  official distribution is a zip archive; the single file is fetched from a public copy of it
  pinned to one commit, and its SHA-256 pins the bytes whatever the source.
  Beside it, ``DATA_EMPS_PULSES.mat`` (the ``validation`` file, :func:`extra_path`), the
  benchmark's validation record: the same variables of shape (24841, 1) and ``pulses_N`` (N,
  force pulses applied to the load, not in ``vir``), from the same copy, SHA-256 pinned too.
  ``motorctl identify DATA_EMPS.mat ... --validate DATA_EMPS_PULSES.mat`` judges the models
  fitted on the first record on it (the description's cross-test validation).
"""

from __future__ import annotations

import hashlib
import os
import re
import shutil
import urllib.request
from dataclasses import dataclass
from pathlib import Path

#: environment variable naming the data directory (offline use: a directory holding copies)
DATA_DIR_ENV = "MOTORCTL_DATA_DIR"


class DataError(Exception):
    """A data set that is unknown, not fetched, or whose download failed its SHA-256 check."""


@dataclass(frozen=True)
class DataFile:
    """A further file of a data set, kept beside its main one: ``role`` (what it is for, e.g.
    ``"validation"``), ``fname``, ``url``, ``sha256`` (hex digest of its bytes)."""

    role: str
    fname: str
    url: str
    sha256: str


@dataclass(frozen=True)
class DataSet:
    """One downloadable file: ``name`` (the command's argument and the sub-directory), ``fname``
    (the file name), ``url`` (where it is downloaded from), ``sha256`` (hex digest of its bytes),
    ``about`` (one line for the listing); ``extra``: further files fetched with it
    (:class:`DataFile`, e.g. a validation record)."""

    name: str
    fname: str
    url: str
    sha256: str
    about: str
    extra: tuple = ()


DATASETS: dict[str, DataSet] = {d.name: d for d in (
    DataSet("emps", "DATA_EMPS.mat",
            "https://raw.githubusercontent.com/forgi86/sysid-neural-continuous/"
            "956aa7ecd73061b0321c6f6098d74c9e4a7ce67a/examples/EMPS/data/DATA_EMPS.mat",
            "6cf6814ae14618795da0101aae2bb97ff0c6351b0501b5492751b02b07facf7e",
            "EMPS benchmark: a real positioning axis in closed loop, 1 kHz, 24.8 s (Janot, Gautier, "
            "Brunot 2019); with its validation record DATA_EMPS_PULSES.mat",
            extra=(DataFile("validation", "DATA_EMPS_PULSES.mat",
                            "https://raw.githubusercontent.com/forgi86/sysid-neural-continuous/"
                            "956aa7ecd73061b0321c6f6098d74c9e4a7ce67a/examples/EMPS/data/DATA_EMPS_PULSES.mat",
                            "0eab75bb1f6b16228ee78791343a88bf9bfd9a51036ac9807d7b5fc11c0e1704"),)),
)}


def dataset(name: str) -> DataSet:
    """The data set called ``name``. Raises :class:`DataError` naming the known ones."""
    try:
        return DATASETS[name]
    except KeyError:
        raise DataError(f"{name!r}: no such data set (known: {', '.join(sorted(DATASETS))})") from None


def data_dir() -> Path:
    """``$MOTORCTL_DATA_DIR`` when set and not empty, else ``pooch.os_cache("motorctl")``
    (raises ModuleNotFoundError without pooch)."""
    env = os.environ.get(DATA_DIR_ENV)
    if env:
        return Path(env).expanduser()
    import pooch
    return Path(pooch.os_cache("motorctl"))


def local_path(name: str, root: Path | None = None) -> Path:
    """Where data set ``name`` is (or would be) kept: ``root/<name>/<fname>``, ``root`` defaulting
    to :func:`data_dir`. Does not check that the file exists."""
    d = dataset(name)
    return (data_dir() if root is None else Path(root)) / d.name / d.fname


def extra_file(name: str, role: str) -> DataFile:
    """The further file ``role`` (e.g. ``"validation"``) of data set ``name``. Raises
    :class:`DataError` when the set has none of that role."""
    d = dataset(name)
    for f in d.extra:
        if f.role == role:
            return f
    raise DataError(f"{name}: no {role} file (known: {', '.join(f.role for f in d.extra) or 'none'})")


def extra_path(name: str, role: str, root: Path | None = None) -> Path:
    """Where the further file ``role`` of data set ``name`` is (or would be) kept: beside the
    main file, ``root/<name>/<its fname>``. Does not check that it exists."""
    return local_path(name, root).parent / extra_file(name, role).fname


def sha256_of(path: Path) -> str:
    """Hex SHA-256 of the file at ``path``."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _verified(path: Path, sha256: str, name: str) -> Path:
    """``path`` when present with the pinned ``sha256``; else DataError saying to fetch ``name``."""
    if not path.is_file():
        raise DataError(f"{path}: not fetched yet: motorctl data fetch {name}")
    if sha256_of(path) != sha256:
        raise DataError(f"{path}: SHA-256 differs from the pinned one (a changed or partial copy): "
                        f"motorctl data fetch {name}")
    return path


def verified_path(name: str) -> Path:
    """The local file of data set ``name``, present and with the pinned SHA-256. Raises
    :class:`DataError` when it is absent or its bytes differ (saying to fetch it)."""
    return _verified(local_path(name), dataset(name).sha256, name)


def verified_extra_path(name: str, role: str) -> Path:
    """:func:`verified_path` for the further file ``role`` of data set ``name``. Raises
    :class:`DataError` when it is absent, its bytes differ, or the set has no such file."""
    return _verified(extra_path(name, role), extra_file(name, role).sha256, name)


def fetch(name: str, url: str | None = None, timeout_s: float = 60.0) -> tuple[Path, bool]:
    """Make data set ``name`` present in :func:`data_dir` with its pinned SHA-256, downloading it
    from ``url`` (default: the data set's own) only when it is absent or differs.

    Returns (path, downloaded). Raises :class:`DataError` when the downloaded bytes do not have
    the pinned SHA-256 (nothing is kept: no file, no directory this call created), OSError when
    the source cannot be reached. ``url`` may be ``http:``, ``https:`` or ``file:`` (a mirror or
    a local copy); the pinned SHA-256 is checked whatever the source, ModuleNotFoundError without pooch (the ``data`` extra).
    """
    d = dataset(name)
    return _fetch_one(local_path(name), d.fname, url or d.url, d.sha256, timeout_s)


def fetch_extra(name: str, role: str, url: str | None = None, timeout_s: float = 60.0) -> tuple[Path, bool]:
    """:func:`fetch` for the further file ``role`` of data set ``name`` (e.g. EMPS's
    ``"validation"`` record), kept beside the main file, from ``url`` (default: its own).
    Returns (path, downloaded); raises as :func:`fetch` does, and :class:`DataError` for a role
    the set lacks."""
    f = extra_file(name, role)
    return _fetch_one(extra_path(name, role), f.fname, url or f.url, f.sha256, timeout_s)


def _fetch_one(path: Path, fname: str, src: str, sha256: str, timeout_s: float) -> tuple[Path, bool]:
    """Make ``path`` hold the bytes of SHA-256 ``sha256``, downloaded from ``src`` when absent or
    different (see :func:`fetch`)."""
    import pooch
    import requests

    if path.is_file() and sha256_of(path) == sha256:
        return path, False
    created = [p for p in (path.parent.parent, path.parent) if not p.exists()]
    downloader = (_copy_url if src.startswith("file:") else
                  pooch.HTTPDownloader(progressbar=False, timeout=timeout_s))
    try:
        pooch.retrieve(src, known_hash=f"sha256:{sha256}", fname=fname, path=path.parent,
                       downloader=downloader)
    except ValueError as exc:     # pooch's hash check: the temporary file is already removed
        _remove_empty(created)
        got = re.search(r"but got (\w+)", str(exc))
        raise DataError(f"{src}: SHA-256 of the download is {got.group(1) if got else 'another'}, not the "
                        f"pinned {sha256}: nothing kept") from None
    except requests.RequestException as exc:
        _remove_empty(created)
        raise OSError(f"{src}: download failed: {type(exc).__name__}: "
                      f"{' '.join(str(exc).split())[:200]}") from None
    return path, True


def _copy_url(url: str, output_file, pooch) -> None:
    """A pooch downloader for ``file:`` URLs (a copy on a local or mounted disk), by urllib."""
    with urllib.request.urlopen(url) as src, open(output_file, "wb") as dst:
        shutil.copyfileobj(src, dst)


def _remove_empty(dirs: list[Path]) -> None:
    for p in reversed(dirs):      # innermost first
        try:
            p.rmdir()
        except OSError:
            pass
