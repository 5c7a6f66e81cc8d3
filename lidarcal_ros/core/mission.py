"""In-memory mission data: trajectory, strips, control points.

Every coordinate is float64 in the map frame (metres, Z up); every time is absolute seconds on
the trajectory's clock.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from lidarcal_ros.errors import TrajectoryError


@dataclass
class Trajectory:
    """Positions of the IMU origin over time, and its heading where known.

    Attributes
    ----------
    t : (n,) float64
        Sample times, seconds, strictly increasing.
    xyz : (n, 3) float64
        Positions in the map frame, metres.
    heading : (n,) float64 or None
        The body's heading ``kappa`` at each sample (rad, method.md's convention; from the
        orientation, :mod:`lidarcal_ros.core.heading`), NaN where a sample has none; None
        when no sample has one (positions only, as the quasi-rigorous method needs).
    """

    t: np.ndarray
    xyz: np.ndarray
    heading: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.t = np.ascontiguousarray(self.t, dtype=np.float64)
        self.xyz = np.ascontiguousarray(self.xyz, dtype=np.float64).reshape(-1, 3)
        if self.t.shape[0] != self.xyz.shape[0]:
            raise TrajectoryError(
                f"trajectory has {self.t.shape[0]} stamps but {self.xyz.shape[0]} positions"
            )
        if self.heading is not None:
            self.heading = np.ascontiguousarray(self.heading, dtype=np.float64).reshape(-1)
            if self.heading.shape[0] != self.t.shape[0]:
                raise TrajectoryError(f"trajectory has {self.t.shape[0]} stamps but "
                                      f"{self.heading.shape[0]} headings")
            if not self.heading.size or np.isnan(self.heading).all():
                self.heading = None

    @classmethod
    def from_samples(cls, t: np.ndarray, xyz: np.ndarray,
                     heading: np.ndarray | None = None) -> Trajectory:
        """Build from unordered samples: sorts by time, drops non-finite and duplicate stamps
        (a sample's heading may be NaN: it has none)."""
        t = np.asarray(t, dtype=np.float64)
        xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
        h = None if heading is None else np.asarray(heading, dtype=np.float64).reshape(-1)
        ok = np.isfinite(t) & np.isfinite(xyz).all(axis=1)
        order = np.flatnonzero(ok)
        order = order[np.argsort(t[order], kind="stable")]
        if order.size:
            ts = t[order]
            order = order[np.concatenate(([True], np.diff(ts) > 0))]
        return cls(t[order], xyz[order], None if h is None else h[order])

    def take(self, index: np.ndarray | slice) -> Trajectory:
        """The samples at ``index`` (a slice, or indices in time order)."""
        return Trajectory(self.t[index], self.xyz[index],
                          None if self.heading is None else self.heading[index])

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
