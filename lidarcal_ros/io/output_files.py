"""Outputs that are either complete or absent, refused alike by every command.

docs/internals.md, "Bags" ("Outputs complete or absent").
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import os
import shutil
from collections.abc import Iterable, Sequence
from pathlib import Path

from lidarcal_ros.errors import OutputError, one_line

#: The refusal of an existing output, the same for every command.
EXISTS = "exists (use --overwrite to replace it)"
#: The refusal of an output another writer made while this command ran.
APPEARED = ("appeared while this command was writing it (another writer?); left as it is, "
            "this command's output discarded")


def os_reason(exc: BaseException) -> str:
    """The operating system's reason of an ``OSError`` (``No space left on device``), else
    the exception in one line."""
    if isinstance(exc, OSError) and exc.strerror:
        return exc.strerror
    return one_line(exc)


def overlapping(output: Path, source: Path) -> bool:
    """Whether writing ``output`` would replace or move ``source``: the same path (through
    links too), or one inside the other (a file in a bag directory)."""
    out, src = output.resolve(), source.resolve()
    return out == src or out in src.parents or src in out.parents


def check_output(path: str | os.PathLike[str], *, overwrite: bool,
                 directory: bool = False,
                 inputs: Iterable[str | os.PathLike[str]] = ()) -> Path:
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
    inputs : iterable of path-like, keyword-only
        The command's inputs (and its other outputs): an output that is one of them, or holds
        or lies inside one, is refused, whatever ``overwrite``.

    Returns
    -------
    pathlib.Path

    Raises
    ------
    OutputError
        The output is an input; it exists and ``overwrite`` is False; it is a directory where
        a file is written; it is a dangling symbolic link (whatever ``overwrite``); its name
        is longer than the file system takes; its parent directory is missing or not writable
        (the operating system's reason: permission denied, read-only file system...).
    """
    path = Path(path)
    name_max = _name_max(path.parent)
    if len(path.name.encode()) > name_max:  # else the OS's "File name too long" alone
        raise OutputError(f"{path}: name of {len(path.name.encode())} bytes; the file system "
                          f"takes at most {name_max}")
    for source in inputs:
        if overlapping(path, Path(source)):
            raise OutputError(f"{path}: is also an input ({source}); write the output "
                              "elsewhere")
    if path.is_dir() and not directory:
        raise OutputError(f"{path}: is a directory; -o/--output takes a file name here")
    if path.is_symlink() and not path.exists():
        # Refused, not written through: the target may lie anywhere (a file would appear
        # where the user did not name one); nor replaced: the link was put there for a reason.
        raise OutputError(f"{path}: is a symbolic link to {os.readlink(path)}, which does not "
                          "exist; remove the link or name the output itself")
    if (path.exists() or path.is_symlink()) and not overwrite:
        raise OutputError(f"{path}: {EXISTS}")
    parent = path.parent
    if not parent.is_dir():
        raise OutputError(f"{path}: {parent} is not a directory" if parent.exists() else
                          f"{path}: directory {parent} does not exist")
    # What creating the output will meet (permissions, a read-only file system...).
    probe = hidden_beside(path, "probe")
    try:
        probe.touch()
    except OSError as exc:
        raise OutputError(f"{path}: cannot write in {parent} ({os_reason(exc)})") from None
    finally:  # also when a signal arrives between the two
        remove_quietly(probe)
    return path


def _name_max(directory: Path) -> int:
    """The longest name, bytes, the file system of ``directory`` takes (255 if unsaid)."""
    try:
        return int(os.pathconf(directory, "PC_NAME_MAX"))
    except (OSError, ValueError):
        return 255


def hidden_beside(path: Path, kind: str) -> Path:
    """A hidden name of this process in ``path``'s directory: ``.NAME.lidarcal-KIND-PID``, or
    where that would pass the file system's 255 bytes (a legal long name), one with a digest
    of the name in its place."""
    name = f".{path.name}.lidarcal-{kind}-{os.getpid()}"
    if len(name.encode()) > 255:
        digest = hashlib.sha1(path.name.encode(), usedforsecurity=False).hexdigest()[:16]
        name = f".lidarcal-{kind}-{os.getpid()}-{digest}"
    return path.with_name(name)


def temporary_beside(path: str | os.PathLike[str]) -> Path:
    """A hidden name in ``path``'s directory (same file system: the rename is atomic) under
    which the output is written until it is complete."""
    return hidden_beside(Path(path), "tmp")


def remove_quietly(path: Path) -> None:
    """Remove a file or directory tree if it exists (cleaning up after a failure)."""
    with contextlib.suppress(OSError):
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path, ignore_errors=True)
        else:
            path.unlink(missing_ok=True)


def install(new: Path, path: Path, *, overwrite: bool) -> None:
    """Move the complete output ``new`` (a file or a directory) to ``path``.

    Without ``overwrite`` an output that appeared at ``path`` while the command ran (a second
    writer of the same output) is left as it is and the move refused (``FileExistsError``),
    where a plain rename would silently replace it; with ``overwrite`` what is there is
    replaced only now, and put back if the move fails.
    """
    if not overwrite:
        if new.is_dir():
            if path.exists() or path.is_symlink():
                raise FileExistsError(errno.EEXIST, "appeared while writing", str(path))
            new.rename(path)  # a non-empty directory there since the check: refused too
        else:
            os.link(new, path)  # refuses an existing path, unlike rename
            new.unlink()
        return
    old = None
    if path.is_dir() and not path.is_symlink():
        old = hidden_beside(path, "old")
        path.rename(old)
    try:
        new.replace(path)
    except OSError:
        if old is not None:
            old.rename(path)
        raise
    if old is not None:
        remove_quietly(old)


def write_text(path: str | os.PathLike[str], text: str, *, what: str,
               overwrite: bool = True) -> Path:
    """Write a text file completely or not at all (UTF-8; :func:`write_bytes`)."""
    return write_bytes(path, text.encode("utf-8"), what=what, overwrite=overwrite)


def write_bytes(path: str | os.PathLike[str], data: bytes, *, what: str,
                overwrite: bool = True) -> Path:
    """Write a file completely or not at all (:func:`write_together` of one file)."""
    write_together([(Path(path), data, what)], overwrite=overwrite)
    return Path(path)


def write_together(files: Sequence[tuple[Path, bytes, str]], *, overwrite: bool = True) -> None:
    """Write files that belong together (a calibration and its URDF joint beside it) all or
    none: each to its temporary first, then, every one complete, each moved in place.

    Parameters
    ----------
    files : sequence of (path, data, what)
        Each file's path, bytes and what it is, for the error line (``calibration``,
        ``report``...).
    overwrite : bool, keyword-only
        Replace a file at a path; otherwise one that appeared since the command checked its
        output is refused (:func:`install`).

    Raises
    ------
    OutputError
        ``"<path>: cannot write <what> (<OS reason>)"``: no new file nor a partial one is
        left (a disk filling up at the second file takes the first one's temporary away
        too), and the previous files are untouched.
    """
    temporaries = [temporary_beside(path) for path, _, _ in files]
    path, what = files[0][0], files[0][2]  # the file being written or moved
    try:
        for entry, tmp in zip(files, temporaries, strict=True):
            path, data, what = entry
            with open(tmp, "wb") as stream:
                stream.write(data)
        for entry, tmp in zip(files, temporaries, strict=True):
            path, _, what = entry
            install(tmp, path, overwrite=overwrite)
    except FileExistsError:
        raise OutputError(f"{path}: {APPEARED}") from None
    except OSError as exc:
        raise OutputError(f"{path}: cannot write {what} ({os_reason(exc)})") from None
    finally:  # also on Ctrl-C or SIGTERM; an installed temporary is gone already
        for tmp in temporaries:
            remove_quietly(tmp)


__all__ = [
    "APPEARED", "EXISTS", "check_output", "hidden_beside", "install", "os_reason", "overlapping",
    "remove_quietly", "temporary_beside", "write_bytes", "write_text", "write_together",
]
