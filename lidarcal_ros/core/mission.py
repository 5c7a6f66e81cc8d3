"""In-memory mission data: trajectory, strips, control points.

Every coordinate is float64 in the map frame (metres, Z up); every time is absolute seconds on
the trajectory's clock.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from lidarcal_ros.core.attitude import headings_from_quaternions, normalise_quaternions
from lidarcal_ros.errors import TrajectoryError

logger = logging.getLogger(__name__)


@dataclass
class Trajectory:
    """Positions of the IMU origin over time, and its attitude where known.

    Attributes
    ----------
    t : (n,) float64
        Sample times, seconds, strictly increasing.
    xyz : (n, 3) float64
        Positions in the map frame, metres.
    orientation : (n, 4) float64 or None
        The INS attitude at each sample: unit quaternions ``(x, y, z, w)`` rotating REP-103's
        body frame (x forward, y left, z up) into the map frame
        (:mod:`lidarcal_ros.core.attitude`), a row of NaN where a sample has none (identity,
        zero or not finite); None when no sample has one (positions only, as the
        quasi-rigorous method needs). Normalised on construction, consecutive rows in one
        hemisphere.
    full_attitude : bool
        The orientation carries roll and pitch as measured (an INS); False where only a
        heading was known and the poses were levelled (an ASCII trajectory's heading column):
        the rigorous model (method.md section 10) then has nothing to add. Set False on
        construction, whatever was given, where every orientation is level to 1e-9 rad (no
        INS flies that level; a bag keeps no word of how its poses were made).
    """

    t: np.ndarray
    xyz: np.ndarray
    orientation: np.ndarray | None = None
    full_attitude: bool = True
    _heading: np.ndarray | None = field(default=None, init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        self.t = np.ascontiguousarray(self.t, dtype=np.float64)
        self.xyz = np.ascontiguousarray(self.xyz, dtype=np.float64).reshape(-1, 3)
        if self.t.shape[0] != self.xyz.shape[0]:
            raise TrajectoryError(
                f"trajectory has {self.t.shape[0]} stamps but {self.xyz.shape[0]} positions"
            )
        if self.orientation is not None:
            q = np.asarray(self.orientation, dtype=np.float64)
            if q.size != 4 * self.t.shape[0]:
                raise TrajectoryError(f"trajectory has {self.t.shape[0]} stamps but "
                                      f"{q.size / 4:g} orientations")
            q = normalise_quaternions(q)
            self.orientation = None if not q.size or np.isnan(q).all() else q
        if self.orientation is not None and self.full_attitude:
            # R(q)[2, 0], R(q)[2, 1]: the vertical components of the forward and left axes
            # (0: level), and R(q)[2, 2], the up axis's (1: upright)
            x, y, z, w = self.orientation.T
            tilt = np.abs(np.concatenate([x * z - y * w, y * z + x * w]))
            upright = 1.0 - 2.0 * (x * x + y * y)
            self.full_attitude = not bool(np.nanmax(tilt) < 0.5e-9
                                          and np.nanmin(upright) > 0.0)

    @property
    def heading(self) -> np.ndarray | None:
        """The body's heading ``kappa`` at each sample (rad, method.md's convention: the yaw
        of the forward axis, :func:`~lidarcal_ros.core.attitude.headings_from_quaternions`),
        NaN where a sample has no orientation; None without orientation."""
        if self.orientation is None:
            return None
        if self._heading is None:
            self._heading = headings_from_quaternions(self.orientation)
        return self._heading

    @classmethod
    def from_samples(cls, t: np.ndarray, xyz: np.ndarray,
                     orientation: np.ndarray | None = None, *,
                     full_attitude: bool = True, source: str | None = None) -> Trajectory:
        """Build from unordered samples: sorts by time, drops non-finite and duplicate stamps
        (the first sample of a stamp, in the given order, is kept; a sample's orientation may
        be NaN: it has none).

        ``source`` (e.g. ``"BAG: trajectory /lidar/trajectory"``): a reader's name for the
        samples. With it, what was dropped is logged as one warning line with the counts
        (:class:`SampleScreening`), and samples that all carry one stamp are refused.

        Raises
        ------
        TrajectoryError
            With ``source``: two or more samples, all at one stamp (no trajectory).
        """
        t = np.asarray(t, dtype=np.float64)
        xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
        q = None if orientation is None else np.asarray(orientation,
                                                        dtype=np.float64).reshape(-1, 4)
        ok = np.isfinite(t) & np.isfinite(xyz).all(axis=1)
        order = np.flatnonzero(ok)
        order = order[np.argsort(t[order], kind="stable")]
        first = np.ones(order.size, dtype=bool)
        if order.size:
            first[1:] = np.diff(t[order]) > 0
        if source is not None:
            screening = SampleScreening.of(t, xyz, order, first)
            if screening.one_stamp:
                raise TrajectoryError(
                    f"{source}: all {order.size} poses carry the same stamp "
                    f"({t[order[0]]:.3f} s), so they trace no path (is the driver stamping "
                    "its poses?)")
            text = screening.warning()
            if text:
                logger.warning("%s: %s", source, text)
        order = order[first]
        return cls(t[order], xyz[order], None if q is None else q[order],
                   full_attitude=full_attitude)

    def take(self, index: np.ndarray | slice) -> Trajectory:
        """The samples at ``index`` (a slice, or indices in time order)."""
        return Trajectory(self.t[index], self.xyz[index],
                          None if self.orientation is None else self.orientation[index],
                          full_attitude=self.full_attitude)

    def __len__(self) -> int:
        return int(self.t.shape[0])


@dataclass
class SampleScreening:
    """What :meth:`Trajectory.from_samples` leaves out of a reader's samples.

    Attributes
    ----------
    n_samples : int
        Samples given.
    non_finite_stamps, non_finite_positions : int
        Samples left out for a stamp, or else a position, that is not finite.
    repeated : int
        Samples at a stamp met before (after sorting; the first of each stamp is kept).
    conflicting : int
        Stamps repeated at positions more than 1 mm from the one kept.
    max_conflict_m : float
        Largest distance of a repeat from the position kept at its stamp, metres.
    one_stamp : bool
        Two or more finite samples, all at one stamp.
    """

    n_samples: int
    non_finite_stamps: int
    non_finite_positions: int
    repeated: int
    conflicting: int
    max_conflict_m: float
    one_stamp: bool

    @classmethod
    def of(cls, t: np.ndarray, xyz: np.ndarray, order: np.ndarray,
           first: np.ndarray) -> SampleScreening:
        """Screening of samples ``t, xyz`` of which ``order`` (finite, sorted by stamp) are
        kept where ``first`` (the first at their stamp)."""
        bad_t = int(np.count_nonzero(~np.isfinite(t)))
        bad_xyz = int(t.size - order.size - bad_t)
        kept_at = np.cumsum(first) - 1  # index among the kept of each sorted sample's stamp
        kept_xyz = xyz[order[first]]
        gap = np.linalg.norm(xyz[order] - kept_xyz[kept_at], axis=1)[~first]
        stamps_conflicting = np.unique(kept_at[~first][gap > 1e-3])
        return cls(n_samples=int(t.size), non_finite_stamps=bad_t, non_finite_positions=bad_xyz,
                   repeated=int(np.count_nonzero(~first)),
                   conflicting=int(stamps_conflicting.size),
                   max_conflict_m=float(gap.max()) if gap.size else 0.0,
                   one_stamp=bool(order.size >= 2 and np.count_nonzero(first) == 1))

    def warning(self) -> str:
        """One line with the counts of what was left out and why; empty when nothing was
        (exact repeats, a message recorded twice, are harmless and not mentioned alone)."""
        parts = []
        if self.non_finite_stamps:
            parts.append(f"{_poses(self.non_finite_stamps)} with non-finite stamps left out")
        if self.non_finite_positions:
            parts.append(f"{_poses(self.non_finite_positions)} with non-finite positions left "
                         "out")
        if self.conflicting:
            parts.append(f"{self.conflicting} stamp{'' if self.conflicting == 1 else 's'} "
                         "repeated at positions up to "
                         f"{self.max_conflict_m:.3g} m apart: the first kept")
        if parts:
            used = (self.n_samples - self.non_finite_stamps - self.non_finite_positions
                    - self.repeated)
            parts.append(f"{used} of {self.n_samples} poses used")
        return "; ".join(parts)


def _poses(n: int) -> str:
    return f"{n} pose{'' if n == 1 else 's'}"


@dataclass
class Strip:
    """The points of one flight line.

    Attributes
    ----------
    strip_id : int
        Flight-line id (``strip_id`` / ``point_source_id`` field).
    xyz : (n, 3) float64
        Points in the map frame as delivered (biased), metres.
    t : (n,) float64
        Firing times, seconds.
    intensity : (n,) float32 or None
        Recorded peak amplitude, if the cloud had it.
    """

    strip_id: int
    xyz: np.ndarray
    t: np.ndarray
    intensity: np.ndarray | None = None
    extra: dict[str, np.ndarray] = field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.t.shape[0])


@dataclass
class ControlPoints:
    """Vertical (or full) control points in the map frame.

    Attributes
    ----------
    ids : list of str
    xyz : (n, 3) float64, metres
    """

    ids: list[str]
    xyz: np.ndarray

    def __len__(self) -> int:
        return len(self.ids)


@dataclass
class Mission:
    """Everything one calibration needs, in memory."""

    trajectory: Trajectory
    strips: list[Strip]
    control: ControlPoints | None = None
    frame_id: str = "map"
    dropped_non_finite: int = 0
    #: Points left out by the thinning of ``calibration.thinning_cell_m``.
    thinned_points: int = 0

    @property
    def n_points(self) -> int:
        return sum(len(s) for s in self.strips)
