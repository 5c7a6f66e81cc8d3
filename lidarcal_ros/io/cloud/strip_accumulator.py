"""The points of a mission's cloud messages gathered into strips.

Grouped by strip id, time-sorted, non-finite points dropped and counted; metres in the clouds'
frame, times absolute seconds.
"""

from __future__ import annotations

import itertools
import logging
from collections.abc import Iterator, Sequence
from typing import Any

import numpy as np

from lidarcal_ros.core.calibration.thinning import first_per_cell
from lidarcal_ros.core.mission import Strip
from lidarcal_ros.errors import CloudFormatError
from lidarcal_ros.io.cloud.columns import (
    DEFAULT_COORDINATE_TOLERANCE_M,
    CloudColumns,
    extract_columns,
)
from lidarcal_ros.io.cloud.pointcloud import cloud_to_array

logger = logging.getLogger(__name__)


class StripAccumulator:
    """Collects columns of cloud chunks; groups them into strips once at the end.

    Optional columns (``intensity`` and extra fields) may be missing from some chunks; a
    strip keeps such a column only if every one of its points had it.

    Parameters
    ----------
    topic : str
        The points topic, named in error and warning lines.
    time_field : str
        Time field of the clouds (:func:`~lidarcal_ros.io.cloud.columns.extract_columns`).
    thinning_cell_m : float
        Keep only the first point of each square cell of this size (m) per strip in each
        cloud (counted in ``thinned``); 0 keeps every point.
    box : (xmin, ymin, xmax, ymax) or None
        Keep only the points inside this box of the map frame (m; counted in
        ``outside_box``).
    coordinate_tolerance_m : float
        The coarsest rounding step of FLOAT32 ``x, y, z`` accepted (m).
    """

    def __init__(self, topic: str, time_field: str, thinning_cell_m: float = 0.0,
                 box: tuple[float, float, float, float] | None = None,
                 coordinate_tolerance_m: float = DEFAULT_COORDINATE_TOLERANCE_M) -> None:
        self.topic = topic
        self.box = box
        self.time_field = time_field
        self.thinning_cell_m = float(thinning_cell_m)
        self.coordinate_tolerance_m = coordinate_tolerance_m
        self.coordinate_step_m = 0.0  # the coarsest FLOAT32 step met
        self.outside_box = 0  # points left out by the box
        self.thinned = 0
        self.frames: set[str] = set()
        self.xyz: list[np.ndarray] = []
        self.t: list[np.ndarray] = []
        self.sid: list[np.ndarray] = []
        self.optional: dict[str, dict[int, np.ndarray]] = {}  # name -> message index -> col
        self.n_messages = 0

    def add(self, msg: Any) -> None:
        """Take the points of one ``PointCloud2`` message (its frame noted in ``frames``).

        Raises
        ------
        CloudFormatError
            The cloud lacks a required field (``strip_id`` or ``point_source_id`` among
            them) or has one of an unsupported type.
        """
        index = self.n_messages
        self.n_messages += 1
        self.frames.add(msg.header.frame_id)
        arr = cloud_to_array(msg, source=self.topic)
        cols = extract_columns(arr, time_field=self.time_field, source=self.topic,
                               coordinate_tolerance_m=self.coordinate_tolerance_m)
        self.coordinate_step_m = max(self.coordinate_step_m, cols.coordinate_step_m)
        if cols.strip_id is None:
            raise CloudFormatError(
                f"{self.topic}: cloud lacks field 'strip_id' (or 'point_source_id'); "
                f"fields present: {', '.join(arr.dtype.names or ())}"
            )
        if self.box is not None:
            x0, y0, x1, y1 = self.box
            x, y = cols.xyz[:, 0], cols.xyz[:, 1]
            inside = (x >= x0) & (x <= x1) & (y >= y0) & (y <= y1)
            self.outside_box += int(inside.size - np.count_nonzero(inside))
            cols, arr = cols.take(inside), arr[inside]
        if self.thinning_cell_m > 0:
            cols, arr = self._thinned(cols, arr)
        strip_id = cols.strip_id
        assert strip_id is not None  # (checked above; thinning keeps it)
        self.xyz.append(cols.xyz)
        self.t.append(cols.t)
        self.sid.append(strip_id)
        if cols.intensity is not None:
            self.optional.setdefault("intensity", {})[index] = cols.intensity
        names = arr.dtype.names or ()
        sid_name = "strip_id" if "strip_id" in names else "point_source_id"
        core = {"x", "y", "z", "intensity", cols.time_field, sid_name}
        for name in names:
            if name in core:
                continue
            col = arr[name]
            self.optional.setdefault("extra:" + name, {})[index] = col.astype(
                col.dtype.newbyteorder("=")
            )

    def _thinned(self, cols: CloudColumns, arr: np.ndarray
                 ) -> tuple[CloudColumns, np.ndarray]:
        """The cloud's points thinned
        (:func:`~lidarcal_ros.core.calibration.thinning.first_per_cell` among the finite ones, as
        the calibrator node does); the non-finite ones stay, to be dropped and counted with the
        others."""
        assert cols.strip_id is not None
        finite = cols.finite()
        keep = first_per_cell(cols.xyz, cols.strip_id, self.thinning_cell_m, valid=finite)
        keep |= ~finite
        left_out = int(keep.size - np.count_nonzero(keep))
        if not left_out:
            return cols, arr
        self.thinned += left_out
        return cols.take(keep), arr[keep]

    def _optional_column(
        self, name: str, parts: dict[int, np.ndarray]
    ) -> tuple[np.ndarray, np.ndarray | None] | None:
        """Concatenated column and per-point presence mask (None: present everywhere)."""
        first = next(iter(parts.values()))
        if any(p.shape[1:] != first.shape[1:] for p in parts.values()):
            logger.warning("%s: field '%s' changes shape between clouds; ignored",
                           self.topic, name.removeprefix("extra:"))
            return None
        dtype = np.result_type(*{p.dtype for p in parts.values()})
        if len(parts) == self.n_messages:
            return np.concatenate([parts[i] for i in range(self.n_messages)]), None
        chunks, mask = [], []
        for i, t in enumerate(self.t):
            got = parts.get(i)
            chunks.append(got if got is not None else np.zeros((t.size, *first.shape[1:]), dtype))
            mask.append(np.full(t.size, got is not None))
        return np.concatenate(chunks).astype(dtype, copy=False), np.concatenate(mask)

    def strips(self) -> tuple[list[Strip], int]:
        """The points taken so far as strips sorted by ``strip_id``, each in time order, and
        the number of points dropped for a non-finite ``x, y, z`` or ``t``; the accumulator
        is emptied."""
        xyz = np.concatenate(self.xyz) if len(self.xyz) > 1 else self.xyz[0]
        t = np.concatenate(self.t) if len(self.t) > 1 else self.t[0]
        sid = np.concatenate(self.sid) if len(self.sid) > 1 else self.sid[0]
        columns: dict[str, np.ndarray] = {}
        masks: dict[str, np.ndarray] = {}
        for name, parts in self.optional.items():
            got = self._optional_column(name, parts)
            if got is not None:
                columns[name] = got[0]
                if got[1] is not None:
                    masks[name] = got[1]
        self.xyz, self.t, self.sid, self.optional = [], [], [], {}

        ok = np.isfinite(xyz).all(axis=1) & np.isfinite(t)
        dropped = int(ok.size - np.count_nonzero(ok))
        if dropped:
            xyz, t, sid = xyz[ok], t[ok], sid[ok]
            columns = {k: v[ok] for k, v in columns.items()}
            masks = {k: v[ok] for k, v in masks.items()}

        perm, bounds = _strip_order(sid, t)
        if perm is not None:
            xyz, t, sid = xyz[perm], t[perm], sid[perm]
            columns = {k: v[perm] for k, v in columns.items()}
            masks = {k: v[perm] for k, v in masks.items()}
        strips = []
        for a, b in _pairs(bounds):
            sid_a = int(sid[a])
            keep: dict[str, np.ndarray] = {}
            for name, col in columns.items():
                mask = masks.get(name)
                if mask is not None and not mask[a:b].all():
                    if mask[a:b].any():
                        logger.warning("%s: field '%s' missing from some clouds of strip %d; "
                                       "ignored for that strip", self.topic,
                                       name.removeprefix("extra:"), sid_a)
                    continue
                keep[name] = col[a:b]
            intensity = keep.pop("intensity", None)
            extra = {k.removeprefix("extra:"): v for k, v in keep.items()}
            strips.append(Strip(sid_a, xyz[a:b], t[a:b], intensity, extra))
        return strips, dropped


def _pairs(bounds: Sequence[int]) -> Iterator[tuple[int, int]]:
    """Consecutive ``(start, stop)`` pairs of a boundary list."""
    return itertools.pairwise(bounds)


def is_nondecreasing(a: np.ndarray) -> bool:
    """Whether the values of ``a`` (1-D) never decrease (NaN compares false)."""
    return bool(a.size < 2 or np.all(a[1:] >= a[:-1]))


def _strip_order(sid: np.ndarray, t: np.ndarray) -> tuple[np.ndarray | None, list[int]]:
    """Permutation sorting by (strip id, time), or None if already sorted; strip bounds."""
    perm: np.ndarray | None = None
    if not is_nondecreasing(sid):
        perm = np.argsort(sid, kind="stable")
        sid = sid[perm]
    bounds = [0, *(np.flatnonzero(sid[1:] != sid[:-1]) + 1).tolist(), int(sid.size)]
    if sid.size == 0:
        return None, [0]
    for a, b in _pairs(bounds):
        seg = t[a:b] if perm is None else t[perm[a:b]]
        if not is_nondecreasing(seg):
            if perm is None:
                perm = np.arange(sid.size)
            sub = np.argsort(seg, kind="stable")
            perm[a:b] = perm[a:b][sub]
    return perm, bounds


# --------------------------------------------------------------------------------------
# Writing
# --------------------------------------------------------------------------------------


__all__ = ["StripAccumulator", "is_nondecreasing"]
