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
    "BagError", "CalibrationError", "CloudFormatError", "ConfigError", "InputError",
    "LidarcalError", "OutputError", "TrajectoryError", "one_line",
]
