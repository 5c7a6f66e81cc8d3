"""Outputs that are either complete or absent, refused alike by every command.

docs/internals.md, "Bags" ("Outputs complete or absent").
"""

from __future__ import annotations

import contextlib
import os
import shutil
from pathlib import Path

from lidarcal_ros.errors import OutputError, one_line

#: The refusal of an existing output, the same for every command.
EXISTS = "exists (use --overwrite to replace it)"


def os_reason(exc: BaseException) -> str:
    """The operating system's reason of an ``OSError`` (``No space left on device``), else
    the exception in one line."""
    if isinstance(exc, OSError) and exc.strerror:
        return exc.strerror
    return one_line(exc)


def check_output(path: str | os.PathLike[str], *, overwrite: bool,
                 directory: bool = False) -> Path:
    """Refuse, before any work, an output that cannot be written.

    Parameters
    ----------
    path : path-like
        The output (a file, or a directory when ``directory``).
    overwrite : bool, keyword-only
        Whether an existing output may be replaced.
    directory : bool, keyword-only
        The output is a directory (a rosbag2 bag); otherwise an existing directory there is
        refused.

    Returns
    -------
    pathlib.Path

    Raises
    ------
    OutputError
        The output exists and ``overwrite`` is False; it is a directory where a file is
        written; its parent directory is missing or not writable (the operating system's
        reason: permission denied, read-only file system...).
    """
    path = Path(path)
    if path.is_dir() and not directory:
        raise OutputError(f"{path}: is a directory; -o/--output takes a file name here")
    if (path.exists() or path.is_symlink()) and not overwrite:
        raise OutputError(f"{path}: {EXISTS}")
    parent = path.parent
    if not parent.is_dir():
        raise OutputError(f"{path}: {parent} is not a directory" if parent.exists() else
                          f"{path}: directory {parent} does not exist")
    # What creating the output will meet (permissions, a read-only file system...).
    probe = path.with_name(f".{path.name}.lidarcal-probe-{os.getpid()}")
    try:
        probe.touch()
    except OSError as exc:
        raise OutputError(f"{path}: cannot write in {parent} ({os_reason(exc)})") from None
    remove_quietly(probe)
    return path


def temporary_beside(path: str | os.PathLike[str]) -> Path:
    """A hidden name in ``path``'s directory (same file system: the rename is atomic) under
    which the output is written until it is complete."""
    path = Path(path)
    return path.with_name(f".{path.name}.lidarcal-tmp-{os.getpid()}")


def remove_quietly(path: Path) -> None:
    """Remove a file or directory tree if it exists (cleaning up after a failure)."""
    with contextlib.suppress(OSError):
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path, ignore_errors=True)
        else:
            path.unlink(missing_ok=True)


def write_text(path: str | os.PathLike[str], text: str, *, what: str) -> Path:
    """Write a text file completely or not at all (UTF-8; :func:`write_bytes`)."""
    return write_bytes(path, text.encode("utf-8"), what=what)


def write_bytes(path: str | os.PathLike[str], data: bytes, *, what: str) -> Path:
    """Write a file completely or not at all.

    Parameters
    ----------
    path : path-like
    data : bytes
    what : str
        What the file is, for the error line (``calibration``, ``report``...).

    Raises
    ------
    OutputError
        ``"<path>: cannot write <what> (<OS reason>)"``; neither the new file nor a partial
        one is left, and a previous file at ``path`` is untouched.
    """
    path = Path(path)
    tmp = temporary_beside(path)
    try:
        with open(tmp, "wb") as stream:
            stream.write(data)
        tmp.replace(path)
    except OSError as exc:
        remove_quietly(tmp)
        raise OutputError(f"{path}: cannot write {what} ({os_reason(exc)})") from None
    return path


__all__ = [
    "EXISTS", "check_output", "os_reason", "remove_quietly", "temporary_beside", "write_bytes",
    "write_text",
]
