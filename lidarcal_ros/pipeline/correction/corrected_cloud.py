"""The corrected cloud: its layout, its rows built from the correction's columns, its tallies.

Every input field, ``x, y, z`` corrected, and the :data:`ADDED_FIELDS` (docs/interface.md,
"Corrected clouds").
"""

from __future__ import annotations

import functools
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from lidarcal_ros.core.flags import (
    FLAG_GRAZING,
    FLAG_NO_INTENSITY,
    FLAG_NO_NORMAL,
    FLAG_NOT_CORRECTED,
    FLAG_ROUGH,
    FLAG_VOLUME,
)
from lidarcal_ros.core.georeferencing import correction_kernels
from lidarcal_ros.core.georeferencing.rigorous import ModelChoice

__all__ = [
    "ADDED_FIELDS", "INCIDENCE_RULES", "NO_ROWS", "CloudTally", "CorrectedColumns",
    "CorrectionStats", "RowTarget", "build_corrected", "corrected_dtype", "row_target",
]

#: Fields added to the corrected clouds (name, numpy type).
ADDED_FIELDS: tuple[tuple[str, str], ...] = (
    ("reflectance", "<f4"),
    ("range", "<f4"),
    ("incidence", "<f4"),
    ("scan_angle", "<f4"),
    ("correction_flags", "u1"),
)


@dataclass
class CorrectionStats:
    """Counts over everything corrected so far."""

    clouds: int = 0
    points: int = 0
    not_corrected: int = 0
    grazing: int = 0
    no_normal: int = 0
    no_intensity: int = 0
    rough: int = 0
    volume: int = 0
    #: Corrected points by the incidence their reflectance took (:data:`INCIDENCE_RULES`).
    incidence_rules: dict[str, int] = field(default_factory=dict)
    seconds: float = 0.0
    non_finite: int = 0  # points with a non-finite coordinate (also not corrected)
    #: Points corrected by each point-positioning model, and the latest reason each was
    #: chosen (:mod:`lidarcal_ros.core.georeferencing.rigorous`).
    model_points: dict[str, int] = field(default_factory=dict)
    model_reason: dict[str, str] = field(default_factory=dict)

    def add_model(self, model: str, reason: str, points: int) -> None:
        """Count ``points`` corrected by ``model`` (chosen for ``reason``)."""
        self.model_points[model] = self.model_points.get(model, 0) + points
        self.model_reason[model] = reason

    def describe_models(self) -> str:
        """One line on the models the points got, e.g. ``"rigorous (INS attitude at 50 Hz)
        for 100% of the points"``."""
        total = sum(self.model_points.values())
        if not total:
            return "no point corrected"
        return "; ".join(f"{m} ({self.model_reason[m]}) for "
                         f"{100.0 * k / total:.0f}% of the points"
                         for m, k in sorted(self.model_points.items(), key=lambda kv: -kv[1]))

    def describe_incidence(self) -> str:
        """One line on the incidence each corrected point's reflectance took, e.g.
        ``"surface normal for 71% of the points, none for volume (canopy) returns 27%,
        clamped grazing 2%"`` (the rules: :data:`INCIDENCE_RULES`)."""
        total = sum(self.incidence_rules.values())
        if not total:
            return "no point corrected"
        shares = [(name, 100.0 * k / total) for name, _, _ in INCIDENCE_RULES
                  if (k := self.incidence_rules.get(name, 0))]
        (first, share), rest = shares[0], shares[1:]
        return ", ".join([f"{first} for {_percent(share)} of the points",
                          *(f"{name} {_percent(share)}" for name, share in rest)])

    def merge(self, other: CorrectionStats) -> None:
        """Add the counts of ``other`` (a later part of the same stream)."""
        for name in ("clouds", "points", "not_corrected", "grazing", "no_normal",
                     "no_intensity", "rough", "volume", "non_finite", "seconds"):
            setattr(self, name, getattr(self, name) + getattr(other, name))
        for name, k in other.incidence_rules.items():
            self.incidence_rules[name] = self.incidence_rules.get(name, 0) + k
        for model, k in other.model_points.items():
            self.add_model(model, other.model_reason[model], k)

    def add(self, tally: CloudTally) -> None:
        """Count a corrected cloud (or several: tallies add up)."""
        for name, any_of, none_of in INCIDENCE_RULES:
            self.incidence_rules[name] = (self.incidence_rules.get(name, 0)
                                          + tally.matching(any_of, none_of))
        self.volume += tally.flagged(FLAG_VOLUME)
        self.points += tally.points
        self.non_finite += int(tally.counts[256])
        self.not_corrected += tally.flagged(FLAG_NOT_CORRECTED)
        self.grazing += tally.flagged(FLAG_GRAZING)
        self.no_normal += tally.flagged(FLAG_NO_NORMAL)
        self.no_intensity += tally.flagged(FLAG_NO_INTENSITY)
        self.rough += tally.flagged(FLAG_ROUGH)


def _percent(share: float) -> str:
    """A share in per cent for a summary: whole per cents, ``<1%`` below one."""
    return f"{share:.0f}%" if share >= 1.0 or share == 0.0 else "<1%"


#: The incidence a corrected point's reflectance took (:mod:`lidarcal_ros.core.radiometry`),
#: each as (name in the summary, flags of which one must be set (0: none needed), flags none
#: of which may be): the surface normal's; none, for volume returns (canopy: ``cos`` 1);
#: bounded at ``radiometry.uncertain_incidence_max_deg``, for rough neighbourhoods; clamped
#: at ``radiometry.min_cos_incidence``, grazing (then bounded too); none known (no normal:
#: reflectance NaN).
INCIDENCE_RULES: tuple[tuple[str, int, int], ...] = (
    ("surface normal", 0,
     FLAG_NOT_CORRECTED | FLAG_VOLUME | FLAG_GRAZING | FLAG_ROUGH | FLAG_NO_NORMAL),
    ("none for volume (canopy) returns", FLAG_VOLUME, FLAG_NOT_CORRECTED),
    ("bounded (rough)", FLAG_ROUGH,
     FLAG_NOT_CORRECTED | FLAG_VOLUME | FLAG_GRAZING | FLAG_NO_NORMAL),
    ("clamped grazing", FLAG_GRAZING, FLAG_NOT_CORRECTED | FLAG_VOLUME | FLAG_NO_NORMAL),
    ("no normal", FLAG_NO_NORMAL, FLAG_NOT_CORRECTED | FLAG_VOLUME),
)

#: Each possible ``correction_flags`` byte, the index of :attr:`CloudTally.counts`.
_FLAG_BYTES = np.arange(256)


@dataclass(frozen=True)
class CloudTally:
    """What a corrected cloud holds, counted while it was built (:func:`build_corrected`).

    Attributes
    ----------
    counts : (257,) int64
        ``counts[f]``: the points whose ``correction_flags`` byte is ``f``; ``counts[256]``:
        the points with a non-finite coordinate (kept from the input: such a point cannot
        be corrected).
    """

    counts: np.ndarray

    @classmethod
    def empty(cls) -> CloudTally:
        """A tally of no point."""
        return cls(np.zeros(257, dtype=np.int64))

    @property
    def points(self) -> int:
        """The points of the cloud (each has a ``correction_flags`` byte), non-finite ones
        included."""
        return int(self.counts[:256].sum())

    @property
    def dense(self) -> bool:
        """Every coordinate finite (PointCloud2's ``is_dense``)."""
        return int(self.counts[256]) == 0

    def flagged(self, mask: int) -> int:
        """Points with any of the bits of ``mask`` set."""
        return int(self.counts[:256][(_FLAG_BYTES & mask) != 0].sum())

    def matching(self, any_of: int, none_of: int) -> int:
        """Points with one of the bits of ``any_of`` set (0: any point) and none of
        ``none_of``."""
        hit = (_FLAG_BYTES & none_of) == 0
        if any_of:
            hit &= (_FLAG_BYTES & any_of) != 0
        return int(self.counts[:256][hit].sum())

    def __add__(self, other: CloudTally) -> CloudTally:
        return CloudTally(self.counts + other.counts)


@dataclass
class CorrectedColumns:
    """Per-point results of :func:`~lidarcal_ros.pipeline.correction.apply.correct_columns`.

    Attributes
    ----------
    xyz : (n, 3) float64
        Corrected points (delivered ones where not corrected), map frame, m.
    range, incidence, scan_angle, reflectance : (n,) float32
        m, rad, rad, and the reflectance of :mod:`lidarcal_ros.core.radiometry` (Lambertian
        with a calibration constant, else relative in intensity units); NaN where unknown.
    flags : (n,) uint8
        ``FLAG_*`` bits.
    cell_m : (float, float)
        Grid cell ``(along, across)`` of the normals, m.
    """

    xyz: np.ndarray
    range: np.ndarray
    incidence: np.ndarray
    scan_angle: np.ndarray
    reflectance: np.ndarray
    flags: np.ndarray
    cell_m: tuple[float, float] = (math.nan, math.nan)
    #: The point-positioning model of the served points, and why
    #: (:func:`~lidarcal_ros.core.georeferencing.rigorous.choose_model`); None where none was
    #: served.
    choice: ModelChoice | None = None

    def __len__(self) -> int:
        return int(self.flags.shape[0])


#: The rows of a corrected cloud as the compiled loops write them
#: (:func:`row_target`): the output and input rows as words, the output's fields ``x, y, z,
#: reflectance, range, incidence, scan_angle, correction_flags`` and the tally's counts.
RowTarget = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                  np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]
#: "None" of the compiled correction's ``rows`` (it then writes the columns).
NO_ROWS: RowTarget = (np.zeros((0, 1), np.uint64), np.zeros((0, 1), np.uint64), np.zeros(0),
                      np.zeros(0), np.zeros(0), np.zeros(0, np.float32),
                      np.zeros(0, np.float32), np.zeros(0, np.float32),
                      np.zeros(0, np.float32), np.zeros(0, np.uint8),
                      np.zeros(257, np.int64))


@functools.lru_cache(maxsize=64)  # (a stream has one or two layouts; each cloud asks)
def corrected_dtype(dtype: np.dtype[Any]) -> np.dtype[Any]:
    """The layout of a corrected cloud: the input fields at their offsets (minus any named
    like an added one), then :data:`ADDED_FIELDS` (4-byte aligned)."""
    added = {name for name, _ in ADDED_FIELDS}
    fields: Mapping[str, Any] = dtype.fields or {}
    names: list[str] = []
    formats: list[Any] = []
    offsets: list[int] = []
    for name, (fdt, off, *_rest) in fields.items():
        if name in added:
            continue
        names.append(name)
        formats.append(fdt)
        offsets.append(int(off))
    pos = (dtype.itemsize + 3) // 4 * 4
    for name, kind in ADDED_FIELDS:
        k = np.dtype(kind)
        pos = (pos + k.itemsize - 1) // k.itemsize * k.itemsize
        names.append(name)
        formats.append(k)
        offsets.append(pos)
        pos += k.itemsize
    itemsize = (pos + 7) // 8 * 8
    return np.dtype({"names": names, "formats": formats, "offsets": offsets,
                     "itemsize": itemsize})


def build_corrected(points: np.ndarray, res: CorrectedColumns, a: int = 0,
                    b: int | None = None, *, out: np.ndarray | None = None,
                    tally: CloudTally | None = None) -> np.ndarray:
    """The corrected cloud of ``points`` from rows ``a:b`` of ``res``.

    Parameters
    ----------
    out : structured array, optional
        Where to build it: ``len(points)`` rows of ``corrected_dtype(points.dtype)`` (for
        instance in the buffer a message is serialised into); by default a new array.
        Every byte of it is written: the input's bytes, the added fields and zeros between
        them, so the bytes do not depend on what the buffer held. Its rows must be
        contiguous.
    tally : CloudTally, optional
        Counts of the cloud's flags and non-finite points to add to (in the same pass as
        the rows are written).
    """
    n = len(points)
    b = a + n if b is None else b
    dtype = corrected_dtype(points.dtype)
    fresh = out is None
    if out is None:
        out = np.zeros(n, dtype=dtype)  # (cheaper than zeroing the gaps between fields)
    elif out.dtype != dtype or out.shape != (n,):
        raise ValueError(f"output of {out.shape} {out.dtype} for {n} points of {dtype}")
    if n == 0:
        return out
    points = np.ascontiguousarray(points)
    counts = tally.counts if tally is not None else np.zeros(257, dtype=np.int64)
    target = row_target(points, out, counts)
    if target is not None:
        # The usual layout: one compiled pass row by row instead of nine over the output.
        (out_words, in_words, x, y, z, reflectance, range_m, incidence, scan_angle,
         flags, _) = target
        correction_kernels.fill_corrected_rows(
            out_words, in_words, x, y, z, res.xyz[a:b], reflectance, range_m, incidence,
            scan_angle, flags, res.reflectance[a:b], res.range[a:b], res.incidence[a:b],
            res.scan_angle[a:b], res.flags[a:b], counts)
        return out
    if tally is not None:
        counts[:256] += correction_kernels.byte_counts(np.ascontiguousarray(res.flags[a:b]))
        counts[256] += int(np.count_nonzero(~np.isfinite(res.xyz[a:b]).all(axis=1)))
    if not fresh:
        # A used buffer: zero the added part of each row (whole 8-byte words; the row size
        # is a multiple of 8) before the input's bytes go in front of it.
        words = out.view(np.uint64).reshape(n, dtype.itemsize // 8)
        words[:, points.dtype.itemsize // 8:] = 0
    rows = out.view(np.uint8).reshape(n, dtype.itemsize)
    rows[:, :points.dtype.itemsize] = points.view(np.uint8).reshape(n, points.dtype.itemsize)
    out["x"] = res.xyz[a:b, 0]
    out["y"] = res.xyz[a:b, 1]
    out["z"] = res.xyz[a:b, 2]
    out["reflectance"] = res.reflectance[a:b]
    out["range"] = res.range[a:b]
    out["incidence"] = res.incidence[a:b]
    out["scan_angle"] = res.scan_angle[a:b]
    out["correction_flags"] = res.flags[a:b]
    return out


def row_target(points: np.ndarray, out: np.ndarray, counts: np.ndarray) -> RowTarget | None:
    """Where the compiled loops write the corrected cloud of ``points`` (contiguous) into
    ``out`` (``len(points)`` rows of :func:`corrected_dtype`, contiguous) and count its flags
    into ``counts`` (a :class:`CloudTally`'s); None for a layout whose rows are not whole
    4-byte words. The rows are copied in 8-byte words where both layouts allow (the
    corrected rows always do)."""
    if points.dtype.itemsize % 4:
        return None
    n = len(points)
    word = np.dtype(np.uint64 if points.dtype.itemsize % 8 == 0 else np.uint32)
    return (out.view(word).reshape(n, out.dtype.itemsize // word.itemsize),
            points.view(word).reshape(n, points.dtype.itemsize // word.itemsize),
            out["x"], out["y"], out["z"], out["reflectance"], out["range"],
            out["incidence"], out["scan_angle"], out["correction_flags"], counts)

