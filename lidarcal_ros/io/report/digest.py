"""Size and SHA-256 of input files and directories, for the provenance of a report."""

from __future__ import annotations

import hashlib
from collections.abc import Callable
from pathlib import Path

#: Bytes read at a time.
_CHUNK = 1 << 20


def digest(path: str | Path, *, progress: Callable[[int], None] | None = None
           ) -> tuple[int, str]:
    """``(size in bytes, SHA-256 hex)`` of a file's content, or of a directory's: its files'
    relative paths (UTF-8, NUL-terminated) and contents, in path order, so that a renamed
    or a changed file changes it.

    ``progress`` is called with the bytes read so far.

    Raises
    ------
    OSError
        The path cannot be read.
    """
    path = Path(path)
    files = sorted(p for p in path.rglob("*") if p.is_file()) if path.is_dir() else [path]
    sha = hashlib.sha256()
    size = 0
    for file in files:
        if path.is_dir():
            sha.update(file.relative_to(path).as_posix().encode("utf-8") + b"\0")
        with file.open("rb") as f:
            while chunk := f.read(_CHUNK):
                sha.update(chunk)
                size += len(chunk)
                if progress is not None:
                    progress(size)
    return size, sha.hexdigest()


def total_size(path: str | Path) -> int:
    """Bytes in a file, or in every file under a directory."""
    path = Path(path)
    if path.is_dir():
        return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())
    return path.stat().st_size


__all__ = ["digest", "total_size"]
