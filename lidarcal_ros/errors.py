"""Exceptions of lidarcal_ros.

Every error the package raises on bad input derives from :class:`LidarcalError`, whose message
is one line naming the file, topic, field or parameter at fault. The CLI prints that line and
exits non-zero; nodes log it and keep running.
"""

from __future__ import annotations


def one_line(err: BaseException) -> str:
    """An exception's message as one line (its type's name when it has none): what a
    library's error adds to a :class:`LidarcalError` message."""
    text = " ".join(str(err).split())
    return text or type(err).__name__


#: Longest message a user is shown; the rest of a longer one (a megabyte topic name, fifty
#: thousand unknown keys) is cut, its length said.
MAX_MESSAGE_CHARS = 2000


def brief(text: str, limit: int = MAX_MESSAGE_CHARS) -> str:
    """``text`` as one line of at most about ``limit`` characters."""
    text = " ".join(text.split())
    if len(text) <= limit:
        return text
    return f"{text[:limit]}... ({len(text)} characters)"


class LidarcalError(Exception):
    """Root of every lidarcal_ros error."""


class InputError(LidarcalError):
    """Input data is malformed or inconsistent (cloud fields, frames, bags, files)."""


class CloudFormatError(InputError):
    """A PointCloud2 lacks a required field, has an unsupported type or an inconsistent layout."""


class BagError(InputError):
    """A bag cannot be opened or read (missing, truncated, wrong storage, missing topic)."""


class TrajectoryError(InputError):
    """The trajectory does not cover a point's time or is otherwise unusable."""


class ConfigError(LidarcalError):
    """A flight configuration, calibration file or parameter value is invalid."""


class OutputError(LidarcalError):
    """An output cannot be written: it exists (without ``--overwrite``), its directory is
    missing or not writable, or writing failed (disk full, I/O error). Nothing partial is left
    behind."""


class CalibrationError(LidarcalError):
    """The adjustment cannot proceed (no overlap, no correspondences, nothing to estimate)."""


__all__ = [
    "MAX_MESSAGE_CHARS",
    "BagError",
    "CalibrationError",
    "CloudFormatError",
    "ConfigError",
    "InputError",
    "LidarcalError",
    "OutputError",
    "TrajectoryError",
    "brief",
    "one_line",
]
