"""What ``lidarcal import`` can be told: :class:`ImportOptions`.

One frozen object for :func:`~lidarcal_ros.pipeline.importing.importer.import_mission`, built by the
CLI from its flags (the defaults are the CLI's); values that cannot work are refused when it is
made, each in one line naming the flag.
"""

from __future__ import annotations

import enum
import os
from dataclasses import dataclass, field

from lidarcal_ros.core.trajectory.rays import RayBudget
from lidarcal_ros.core.trajectory.segments import EstimateSettings
from lidarcal_ros.errors import ConfigError
from lidarcal_ros.io.survey.trajectory_files import TimeBase


class Returns(enum.StrEnum):
    """Which returns an import writes to the bag: the values of ``--returns``."""

    ALL = "all"
    #: The first return of each pulse (``return_number`` 1).
    FIRST = "first"
    #: The last return of each pulse (single returns included).
    LAST = "last"


#: ``--trajectory-time``'s word for None: the importer chooses the time base.
AUTO_TIME = "auto"


@dataclass(frozen=True)
class ImportOptions:
    """How LAS/LAZ strips and a trajectory become a mission bag.

    Attributes
    ----------
    crs : str or None
        CRS of the points (``EPSG:N``), overriding the LAS headers.
    returns : Returns
        Which returns go into the bag (all returns feed a trajectory estimate).
    strip_gap_s : float
        GPS-time gap that separates strips where point source ids do not, seconds.
    chunk_points : int
        Points decoded per LAS read.
    memory_points : int
        Points held in memory before spilling sorted runs to disk.
    qa_cell_m : float
        Cell of the overlap QA grid, metres (0: no QA). Per pair of strips, the mean heights
        of last returns in cells both strips cover and where both are smooth (standard
        deviation <= 15 cm) are compared
        (:class:`~lidarcal_ros.core.qa.overlap_grid.PairQA`). Its memory grows with the area
        flown over the cell's area (32 bytes a cell and strip), not with the points.
    trajectory : path-like, ``"estimate"`` or None
        SBET, ASCII trajectory, or ``"estimate"`` (also None) to rebuild it from multiple
        returns.
    trajectory_crs : str or None
        CRS of the trajectory positions (default EPSG:4979 for SBET and lat/lon columns, the
        points' CRS for ASCII x, y, z).
    trajectory_accuracy : path-like, ``"none"`` or None
        The trajectory file's accuracy file (Applanix ``smrmsg``: per-epoch position RMS, on
        the file's clock); None: ``smrmsg_NAME.out`` beside ``sbet_NAME.out`` where there is
        one (POSPac's names); ``"none"``: none.
    trajectory_time : TimeBase or None
        Time base of the trajectory file (None, ``--trajectory-time auto``: an SBET's week
        seconds, an ASCII file's by magnitude and overlap with the points).
    gps_week : int or None
        GPS week of week-second times.
    trajectory_rate_hz : float
        Trajectory file samples kept per second, Hz (0: all); an estimate is sampled at
        ``estimate.rate_hz``.
    estimate : EstimateSettings
        How a trajectory is rebuilt from multiple returns.
    ray_budget : RayBudget
        How many rays of multi-return pulses are kept for that estimate.
    frame_id : str
        Map frame name of clouds and poses.
    points_topic, trajectory_topic : str
    chunk_seconds : float
        Scanning time per PointCloud2 chunk, seconds.
    overwrite : bool
        Replace an existing output bag.

    Raises
    ------
    ConfigError
        An unknown ``returns`` or ``trajectory_time``, or a ``strip_gap_s`` or
        ``chunk_seconds`` that is not positive.
    """

    # the points
    crs: str | None = None
    returns: Returns = Returns.ALL
    strip_gap_s: float = 10.0
    chunk_points: int = 1_000_000
    memory_points: int = 2_000_000
    qa_cell_m: float = 2.0
    # the trajectory
    trajectory: str | os.PathLike[str] | None = "estimate"
    trajectory_crs: str | None = None
    trajectory_accuracy: str | os.PathLike[str] | None = None
    trajectory_time: TimeBase | None = None
    gps_week: int | None = None
    trajectory_rate_hz: float = 50.0
    estimate: EstimateSettings = field(default_factory=EstimateSettings)
    ray_budget: RayBudget = field(default_factory=RayBudget)
    # the bag
    frame_id: str = "map"
    points_topic: str = "/lidar/points"
    trajectory_topic: str = "/lidar/trajectory"
    chunk_seconds: float = 0.1
    overwrite: bool = False

    def __post_init__(self) -> None:
        # (the strings of the flags are taken too: the enums' values)
        try:
            object.__setattr__(self, "returns", Returns(self.returns))
        except ValueError:
            raise ConfigError(f"--returns must be one of {', '.join(Returns)}, "
                              f"got '{self.returns}'") from None
        if self.trajectory_time == AUTO_TIME:
            object.__setattr__(self, "trajectory_time", None)
        elif self.trajectory_time is not None:
            try:
                object.__setattr__(self, "trajectory_time", TimeBase(self.trajectory_time))
            except ValueError:
                raise ConfigError("--trajectory-time: unknown time base "
                                  f"'{self.trajectory_time}'") from None
        if not self.strip_gap_s > 0:
            raise ConfigError(f"--strip-gap must be positive, got {self.strip_gap_s}")
        if self.trajectory_accuracy is not None and self.estimates_trajectory and \
                str(self.trajectory_accuracy) != "none":
            raise ConfigError(f"--trajectory-accuracy {self.trajectory_accuracy}: needs a "
                              "trajectory file (--trajectory SBET), not an estimate")
        if not self.chunk_seconds > 0:
            raise ConfigError(f"chunk_seconds must be positive, got {self.chunk_seconds}")

    @property
    def estimates_trajectory(self) -> bool:
        """No trajectory file: the trajectory is rebuilt from multiple returns."""
        return self.trajectory is None or str(self.trajectory) == "estimate"


__all__ = ["AUTO_TIME", "ImportOptions", "Returns"]
