"""In-memory mission data: trajectory, strips, control points.

Every coordinate is float64 in the map frame (metres, Z up); every time is absolute seconds on
the trajectory's clock.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from lidarcal_ros.core.attitude import headings_from_quaternions, normalise_quaternions
from lidarcal_ros.errors import TrajectoryError


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
                     full_attitude: bool = True) -> Trajectory:
        """Build from unordered samples: sorts by time, drops non-finite and duplicate stamps
        (a sample's orientation may be NaN: it has none)."""
        t = np.asarray(t, dtype=np.float64)
        xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
        q = None if orientation is None else np.asarray(orientation,
                                                        dtype=np.float64).reshape(-1, 4)
        ok = np.isfinite(t) & np.isfinite(xyz).all(axis=1)
        order = np.flatnonzero(ok)
        order = order[np.argsort(t[order], kind="stable")]
        if order.size:
            ts = t[order]
            order = order[np.concatenate(([True], np.diff(ts) > 0))]
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
