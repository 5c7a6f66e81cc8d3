"""Inputs named by URL (``s3://``, ``https://``, ...): fetched through fsspec, kept in a cache.

A bag or LAS file given as a URL is copied, in the process that reads it (the CLI's, each
Dask worker's), into a directory of the URL's own under the cache (``$LIDARCAL_URL_CACHE``,
else ``~/.cache/lidarcal/urls``), its files under their own names, so that a rosbag2
directory keeps its layout. A copy is fetched again only when the source's size or stamp
(ETag, modification time) changed; processes on one machine share it (a lock per URL).
"""

from __future__ import annotations

import fcntl
import hashlib
import json
import os
import posixpath
import re
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

from lidarcal_ros.errors import InputError, one_line

#: The environment variable naming the cache directory.
CACHE_ENV = "LIDARCAL_URL_CACHE"

#: ``protocol://`` at the start of a URL (not a Windows drive, not a relative path).
_URL = re.compile(r"^([A-Za-z][A-Za-z0-9+.-]+)://")

#: What of a file's listing says it changed (whichever its filesystem gives).
_STAMP_KEYS = ("size", "ETag", "etag", "mtime", "LastModified", "Last-Modified",
               "last_modified", "updated", "md5Hash", "created")


def is_url(source: str | os.PathLike[str]) -> bool:
    """``source`` is a URL with a protocol (``s3://...``), not a path."""
    return isinstance(source, str) and _URL.match(source) is not None


def source_of(value: str | os.PathLike[str]) -> str | Path:
    """An input as held: a URL as given (each process reading it fetches it), else a path."""
    return value if isinstance(value, str) and is_url(value) else Path(value)


def cache_root() -> Path:
    """Where copies of URLs are kept."""
    configured = os.environ.get(CACHE_ENV)
    if configured:
        return Path(configured)
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "lidarcal" / "urls"


def local_source(source: str | os.PathLike[str], *, what: str) -> Path:
    """The local path of ``source``: itself if a path (or a ``file://`` URL), else its copy in
    the cache, fetched now where missing or stale. ``what`` (e.g. ``"bag"``) names it in
    errors.

    Raises
    ------
    InputError
        No filesystem for the URL's protocol here (its fsspec package not installed), the
        URL names nothing, or fetching it failed.
    """
    if not is_url(source):
        return Path(source)
    url = str(source)
    try:
        import fsspec
    except ImportError:
        raise InputError(f"{what} {url}: a URL needs fsspec (pip install fsspec)") from None
    try:
        fs, path = fsspec.core.url_to_fs(url)
    except (ImportError, ValueError) as exc:
        raise InputError(f"{what} {url}: no filesystem for this URL here "
                         f"({one_line(exc)})") from None
    if "file" in _protocols(fs):
        return Path(path)
    name = _name_of(path) or "source"
    home = cache_root() / hashlib.sha256(url.encode()).hexdigest()[:16]
    try:
        with _locked(home):
            if fs.isdir(path):
                files = [entry for entry in fs.ls(path, detail=True)
                         if entry.get("type") == "file"]
                if not files:
                    raise InputError(f"{what} {url}: an empty directory")
                for entry in files:
                    base = _name_of(entry["name"])
                    _fetch(fs, entry, home / name / base, home / f".{name}.{base}.stamp")
            else:
                _fetch(fs, fs.info(path), home / name, home / f".{name}.stamp")
    except FileNotFoundError:
        _forget_if_empty(home)
        raise InputError(f"{what} {url}: not found") from None
    except InputError:
        _forget_if_empty(home)
        raise
    except Exception as exc:  # (the filesystem's own: network, credentials, permissions)
        _forget_if_empty(home)
        raise InputError(f"{what} {url}: cannot be fetched ({one_line(exc)})") from None
    return home / name


def _forget_if_empty(home: Path) -> None:
    """``home`` removed where nothing was fetched into it (its lock only): a URL refused
    leaves no trace in the cache."""
    try:
        if [p.name for p in home.iterdir()] == [".lock"]:
            (home / ".lock").unlink()
            home.rmdir()
    except OSError:  # (another process fetching it now, or already gone)
        pass


def _name_of(path: str) -> str:
    """The last part of a filesystem's path or URL, without its query (a signed link's
    signature is no part of the name, whose suffix the readers go by)."""
    return posixpath.basename((urlsplit(path).path if is_url(path) else path).rstrip("/"))


def _protocols(fs: Any) -> tuple[str, ...]:
    protocol = fs.protocol
    return (protocol,) if isinstance(protocol, str) else tuple(protocol)


@contextmanager
def _locked(home: Path) -> Iterator[None]:
    """``home`` created and held by this process alone (other processes wait)."""
    home.mkdir(parents=True, exist_ok=True)
    with open(home / ".lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)


def _fetch(fs: Any, entry: dict[str, Any], target: Path, stamp_file: Path) -> None:
    """The file of listing ``entry`` copied to ``target``, unless the copy there is of the
    same stamp (kept in ``stamp_file``; a file whose filesystem tells no stamp is fetched
    every time)."""
    stamp = _stamp(entry) or _stamp(fs.info(entry["name"]))
    if stamp and target.is_file() and stamp_file.is_file() and stamp_file.read_text() == stamp:
        return
    target.parent.mkdir(parents=True, exist_ok=True)
    partial = target.with_name(f".{target.name}.partial")
    fs.get_file(entry["name"], str(partial))
    os.replace(partial, target)
    stamp_file.write_text(stamp)


def _stamp(entry: dict[str, Any]) -> str:
    """What of a listing's entry tells a change, as text ('' where nothing does)."""
    known = {k: str(entry[k]) for k in _STAMP_KEYS if entry.get(k) is not None}
    return json.dumps(known, sort_keys=True) if known else ""


__all__ = ["CACHE_ENV", "cache_root", "is_url", "local_source", "source_of"]
