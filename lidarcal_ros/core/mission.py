"""In-memory mission data: trajectory, strips, control points.

Every coordinate is float64 in the map frame (metres, Z up); every time is absolute seconds on
the trajectory's clock.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from lidarcal_ros.core.georeferencing.attitude import (
    bridge_missing,
    headings_from_quaternions,
    normalise_quaternions,
)
from lidarcal_ros.errors import TrajectoryError

logger = logging.getLogger(__name__)


def _tilted(q: np.ndarray) -> bool:
    """Some of the unit quaternions ``q`` (n, 4), NaN rows ignored, is not level to 1e-9 rad
    or not upright: the poses carry roll and pitch, not a heading only."""
    # R(q)[2, 0], R(q)[2, 1]: the vertical components of the forward and left axes (0: level),
    # and R(q)[2, 2], the up axis's (1: upright)
    x, y, z, w = q.T
    tilt = np.abs(np.concatenate([x * z - y * w, y * z + x * w]))
    upright = 1.0 - 2.0 * (x * x + y * y)
    return not bool(np.nanmax(tilt) < 0.5e-9 and np.nanmin(upright) > 0.0)


def _usable_sigmas(sigma: np.ndarray, n: int) -> np.ndarray | None:
    """Position sigmas (n, 3) as a trajectory holds them: NaN where not finite or not above
    zero, None where none is left."""
    out = np.array(sigma, dtype=np.float64)
    if out.size != 3 * n:
        raise TrajectoryError(f"trajectory has {n} stamps but {out.size / 3:g} position sigmas")
    out = out.reshape(n, 3)
    with np.errstate(invalid="ignore"):
        out[~(out > 0.0) | ~np.isfinite(out)] = np.nan
    return None if not out.size or np.isnan(out).all() else out


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
        (:mod:`lidarcal_ros.core.georeferencing.attitude`), a row of NaN where a sample has none
        (identity, zero or not finite); None when no sample has one (positions only, as the
        quasi-rigorous method needs). Normalised on construction, consecutive rows in one
        hemisphere.
    full_attitude : bool
        The orientation carries roll and pitch as measured (an INS); False where only a
        heading was known and the poses were levelled (an ASCII trajectory's heading column):
        the rigorous model (docs/method.md section 10) then has nothing to add. Set False on
        construction, whatever was given, where every orientation is level to 1e-9 rad (no
        INS flies that level; a bag keeps no word of how its poses were made).
    position_sigma : (n, 3) float64 or None
        The navigation solution's one-sigma accuracy of each position along map x, y, z (E, N,
        U), metres (an SBET's ``smrmsg``, a PoseWithCovarianceStamped's covariance), NaN
        where a sample has none (not finite, or not above zero); None when no sample has one.
        The priors of the strips' trajectory errors come from it where given
        (docs/method.md section 11).
    """

    t: np.ndarray
    xyz: np.ndarray
    orientation: np.ndarray | None = None
    full_attitude: bool = True
    position_sigma: np.ndarray | None = None
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
            self.full_attitude = _tilted(self.orientation)
        if self.position_sigma is not None:
            self.position_sigma = _usable_sigmas(self.position_sigma, self.t.shape[0])

    @property
    def heading(self) -> np.ndarray | None:
        """The body's heading ``kappa`` at each sample (rad, docs/method.md's convention: the yaw
        of the forward axis,
        :func:`~lidarcal_ros.core.georeferencing.attitude.headings_from_quaternions`), NaN where a
        sample has no orientation; None without orientation."""
        if self.orientation is None:
            return None
        if self._heading is None:
            self._heading = headings_from_quaternions(self.orientation)
        return self._heading

    @classmethod
    def from_samples(cls, t: np.ndarray, xyz: np.ndarray,
                     orientation: np.ndarray | None = None, *,
                     full_attitude: bool = True, source: str | None = None,
                     position_sigma: np.ndarray | None = None) -> Trajectory:
        """Build from unordered samples: sorts by time, drops non-finite stamps or positions
        and repeated stamps (the first sample of a stamp, in the given order, is kept; a
        sample's orientation, or its ``position_sigma`` row, may be NaN: it has none).

        ``source`` (a reader's name for the samples, e.g. ``"BAG: trajectory /lidar/trajectory"``)
        screens the samples of a file as a whole (:func:`screen_samples`): every sample of a
        stamp repeated at positions more than :data:`CONFLICT_M` apart is dropped (which one
        is right is unknown), what is dropped is counted in one warning line, and samples
        that cannot make a trajectory are refused.

        Raises
        ------
        TrajectoryError
            With ``source``: two or more samples all at one stamp, or fewer than two usable
            samples at distinct stamps.
        """
        t = np.asarray(t, dtype=np.float64)
        xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
        q = None if orientation is None else np.asarray(orientation,
                                                        dtype=np.float64).reshape(-1, 4)
        ok = (np.isfinite(t) & np.isfinite(xyz).all(axis=1) & ~beyond_map(xyz)
              if source is None else screen_samples(t, xyz, source))
        said = screen_orientations(q[ok]) if source is not None and q is not None else []
        order = np.flatnonzero(ok)
        order = order[np.argsort(t[order], kind="stable")]
        if order.size:
            ts = t[order]
            order = order[np.concatenate(([True], np.diff(ts) > 0))]
        sigma = (None if position_sigma is None
                 else np.asarray(position_sigma, dtype=np.float64).reshape(-1, 3)[order])
        traj = cls(t[order], xyz[order], None if q is None else q[order],
                   full_attitude=full_attitude, position_sigma=sigma)
        if source is not None and traj.orientation is not None:
            traj.orientation, bridged = bridge_missing(traj.t, traj.orientation,
                                                       max_gap_s=BRIDGE_S)
            if bridged:
                said.append(f"{bridged} poses without one between poses with one at most "
                            f"{BRIDGE_S:g} s apart: their orientation interpolated")
        if said:
            logger.warning("%s: of %d orientation quaternions, %s", source,
                           0 if q is None else int(ok.sum()), "; ".join(said))
        return traj

    @classmethod
    def of_normalised(cls, t: np.ndarray, xyz: np.ndarray, orientation: np.ndarray | None,
                      full_attitude: bool, heading: np.ndarray | None = None, *,
                      position_sigma: np.ndarray | None = None) -> Trajectory:
        """A trajectory of arrays already as construction makes them (times (n,) and
        positions (n, 3) contiguous float64; unit quaternions in one hemisphere from row to
        row, or None; ``full_attitude`` decided; the headings of the quaternions if known),
        taken as they are: no copy, no check. For a keeper of samples that derives each
        sample's values once (:class:`~lidarcal_ros.core.trajectory.buffer.TrajectoryBuffer`)
        rather than all of them at every new sample."""
        traj = cls.__new__(cls)
        traj.t, traj.xyz, traj.orientation = t, xyz, orientation
        traj.full_attitude = full_attitude
        traj.position_sigma = position_sigma
        traj._heading = heading
        return traj

    def take(self, index: np.ndarray | slice) -> Trajectory:
        """The samples at ``index`` (a slice, or indices in time order)."""
        t = np.ascontiguousarray(self.t[index])
        xyz = np.ascontiguousarray(self.xyz[index])
        sigma = None
        if self.position_sigma is not None:
            sigma = np.ascontiguousarray(self.position_sigma[index])
            sigma = None if not sigma.size or np.isnan(sigma).all() else sigma
        if self.orientation is None:
            return Trajectory.of_normalised(t, xyz, None, self.full_attitude,
                                            position_sigma=sigma)
        # Taken as normalised: an identity row of this trajectory is a level pose heading
        # east even where the part taken holds nothing else.
        q = np.ascontiguousarray(self.orientation[index])
        if not q.size or np.isnan(q).all():
            return Trajectory.of_normalised(t, xyz, None, self.full_attitude,
                                            position_sigma=sigma)
        return Trajectory.of_normalised(t, xyz, q, self.full_attitude and _tilted(q),
                                        position_sigma=sigma)

    def __len__(self) -> int:
        return int(self.t.shape[0])


#: Samples at one stamp further apart than this (m) conflict: which one is right is unknown.
CONFLICT_M = 0.001
#: No map coordinate (projected, or geocentric: 6.4e6 m) reaches this (m); one beyond is a
#: corrupt value, left out with the non-finite (and its square stays far from overflow).
MAX_COORDINATE_M = 1e9
#: An orientation whose quaternion's norm is this far from 1 is said once (then normalised).
UNIT_TOLERANCE = 0.01
#: Poses of a file without an orientation (zero, not finite) between two with one at most
#: this far apart (s) get theirs by slerp between them, said once: an attitude field dropped
#: from a message or two of an INS stream (at 50 Hz, 4 missing). Slerp misses a turbulent
#: attitude (0.5 rad/s^2) by ``a h^2 / 8``: 6e-4 rad over 0.1 s at worst, at one pose.
BRIDGE_S = 0.1
#: A stamp up to this much (s) earlier than one read before it is sorted into place (messages
#: reordered or late on their way, as live samples can be); more is a clock that stepped back
#: (a reset, a leap second of 1 s, two sources on one topic), after which two paths share
#: the same times. Half a second: the default trajectory window, and half a leap second.
REORDER_S = 0.5
#: A pose read after later ones but within this (m) of the path the others draw at its stamp
#: was only logged late; a clock that stepped back puts it on another stretch of flight.
LATE_POSE_M = 1.0


def stepped_back(t: np.ndarray, xyz: np.ndarray, source: str) -> None:
    """Refuse samples whose stamps step back, in the order read, by more than
    :data:`REORDER_S` (a sample read again at the same stamp and position, or one within
    :data:`LATE_POSE_M` of the path the others draw at its stamp, is no step).

    Sorting such samples would interleave two stretches of flight: the trajectory would zigzag
    between them and be reported, wrongly, as gaps or as points outside it.

    Raises
    ------
    TrajectoryError
        One line naming ``source``, the first stamp that went back, from what and by how
        much, and how many samples went back.
    """
    finite = np.flatnonzero(np.isfinite(t) & np.isfinite(xyz).all(axis=1))
    if finite.size < 2:
        return
    ts = t[finite]
    newest = np.maximum.accumulate(ts)
    back = np.concatenate(([False], ts[1:] < newest[:-1] - REORDER_S))
    if not back.any():
        return
    # a message recorded twice: the same stamp at the same place as an earlier sample
    at = finite[back]
    order = np.argsort(t[finite], kind="stable")
    first = order[np.searchsorted(t[finite][order], t[at])]
    repeat = (t[finite[first]] == t[at]) & (finite[first] < at) & (
        np.linalg.norm(xyz[finite[first]] - xyz[at], axis=1) <= CONFLICT_M)
    # a pose logged late where the path runs through it (a recorder's lag) is no step either
    ahead = finite[~back]
    at_t = np.column_stack([np.interp(t[at], t[ahead], xyz[ahead, c]) for c in range(3)])
    late = np.linalg.norm(at_t - xyz[at], axis=1) <= LATE_POSE_M
    repeat |= late
    if repeat.all():
        return
    i = int(np.flatnonzero(back)[~repeat][0])
    k = int(finite[i])
    raise TrajectoryError(
        f"{source}: stamps go backwards at pose {k + 1} of {t.size}: t={t[k]:.3f} s after "
        f"t={newest[i - 1]:.3f} s, {newest[i - 1] - t[k]:.3f} s back "
        f"({int(np.count_nonzero(~repeat))} poses earlier than one read before them); a "
        "trajectory's clock must run forward (clock reset, or two sources on one topic?)")


def screen_samples(t: np.ndarray, xyz: np.ndarray, source: str) -> np.ndarray:
    """Which trajectory samples of a reader can be used, saying what is not.

    Samples with a non-finite stamp or position are left out, and so is every sample of a
    stamp repeated at positions more than :data:`CONFLICT_M` apart (two sources on one
    topic?); a stamp repeated at one position (a message recorded twice) is harmless.
    What is left out is counted in one warning line naming ``source``.

    Parameters
    ----------
    t : (n,) float64
        Stamps, seconds.
    xyz : (n, 3) float64
        Positions, metres.
    source : str
        The reader's name for the samples (file and topic), for the lines.

    Returns
    -------
    (n,) bool
        The samples kept.

    Raises
    ------
    TrajectoryError
        Two or more samples all at one stamp (the stamps were not set), stamps that step
        back in the order given (:func:`stepped_back`), or fewer than two usable samples at
        distinct stamps: one line naming ``source`` and the counts.
    """
    beyond = beyond_map(xyz)
    if beyond.any():  # as if not finite from here on (their squares would overflow)
        xyz = np.where(beyond[:, None], np.nan, xyz)
    finite = np.isfinite(t) & np.isfinite(xyz).all(axis=1)
    keep = finite.copy()
    order = np.flatnonzero(finite)
    order = order[np.argsort(t[order], kind="stable")]
    ts = t[order]
    if order.size > 1 and ts[0] == ts[-1]:
        raise TrajectoryError(
            f"{source}: all {order.size} poses carry the same stamp t={ts[0]:.3f} s; a "
            "trajectory needs each pose at its own time (header.stamp not set?)")
    stepped_back(t, xyz, source)
    # each sorted sample against the first of its stamp
    first = np.concatenate(([True], np.diff(ts) > 0)) if order.size else np.ones(0, bool)
    head = order[np.maximum.accumulate(np.where(first, np.arange(order.size), 0))]
    apart = np.linalg.norm(xyz[order] - xyz[head], axis=1)
    conflicting = np.unique(ts[apart > CONFLICT_M])
    if conflicting.size:
        keep[order[np.isin(ts, conflicting)]] = False
    n_bad, n_conflict = int(np.count_nonzero(~finite)), int(np.count_nonzero(finite & ~keep))
    n_beyond = int(np.count_nonzero(beyond & np.isfinite(t)))
    parts = [f"{n_bad - n_beyond} with a non-finite stamp or position"] if n_bad > n_beyond \
        else []
    if n_beyond:
        parts.append(f"{n_beyond} with a coordinate beyond {MAX_COORDINATE_M:g} m")
    if n_conflict:
        parts.append(f"{n_conflict} at {conflicting.size} stamp"
                     f"{'' if conflicting.size == 1 else 's'} repeated at positions up to "
                     f"{float(apart.max()):.3g} m apart (first at t={conflicting[0]:.3f} s; "
                     "which one is right is unknown)")
    distinct = int(np.unique(t[keep]).size)
    if distinct < 2:
        left_out = f" ({'; '.join(parts)})" if parts else ""
        raise TrajectoryError(f"{source}: {distinct} usable pose stamp"
                              f"{'' if distinct == 1 else 's'} among {t.size} poses{left_out}; "
                              "a trajectory needs at least 2 at distinct times")
    if parts:
        logger.warning("%s: %d of %d poses left out: %s", source, n_bad + n_conflict, t.size,
                       "; ".join(parts))
    return keep


def beyond_map(xyz: np.ndarray) -> np.ndarray:
    """(n,) bool: the rows of ``xyz`` (n, 3) with a finite coordinate beyond
    :data:`MAX_COORDINATE_M` (m)."""
    xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    with np.errstate(invalid="ignore"):
        return np.asarray((np.abs(xyz) > MAX_COORDINATE_M).any(axis=1))


def screen_orientations(q: np.ndarray) -> list[str]:
    """What to say of the quaternions ``q`` (n, 4) xyzw of a file: how many are far from unit
    length (normalised) or zero among others that are not (read as poses without
    orientation); the parts of one warning line."""
    q = np.asarray(q, dtype=np.float64).reshape(-1, 4)
    scale = np.abs(q).max(axis=1) if q.size else np.zeros(0)
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        norm = scale * np.sqrt(np.einsum("ij,ij->i", q / scale[:, None], q / scale[:, None]))
    given = np.isfinite(scale) & (scale > 0.0)  # (a norm past 1.8e308 overflows: far off)
    off = given & ~(np.abs(norm - 1.0) <= UNIT_TOLERANCE)
    zero = scale == 0.0
    parts = []
    if off.any():
        parts.append(f"{int(off.sum())} not of unit length (norms {norm[off].min():.3g} to "
                     f"{norm[off].max():.3g}): normalised")
    if zero.any() and given.any():
        parts.append(f"{int(zero.sum())} zero: read as poses without orientation")
    return parts


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
        """The number of points over all strips."""
        return sum(len(s) for s in self.strips)


__all__ = ["BRIDGE_S", "CONFLICT_M", "LATE_POSE_M", "MAX_COORDINATE_M", "REORDER_S",
           "UNIT_TOLERANCE", "ControlPoints", "Mission", "Strip", "Trajectory", "beyond_map",
           "screen_orientations", "screen_samples", "stepped_back"]
