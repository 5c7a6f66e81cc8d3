"""Clouds in the sensor's frame: the mounting, direct georeferencing, the calibrated mounting.

docs/method.md section 12: a point ``p`` of the sensor frame is ``X = X_mb(t) + R_mb(t) (t_bs
+ R_bs p)`` with REP-103's mounting ``base_link -> sensor`` ``(R_bs, t_bs)``; in the method's
right-forward-up body frame the laser vector is ``rho = P R_bs p``, the lever arm ``P t_bs``,
and the biases move a point by ``R_ins C(rho) delta`` (:func:`general_columns`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import StrEnum

import numpy as np
from scipy.spatial.transform import Rotation

from lidarcal_ros.core.georeferencing.attitude import (
    P_BODY,
    interpolated_frames,
    rotation_matrices,
    segment_spline,
)
from lidarcal_ros.core.georeferencing.bias_model import boresight_matrix
from lidarcal_ros.core.georeferencing.rigorous import attitude_segments
from lidarcal_ros.core.jit import compiled
from lidarcal_ros.core.mission import Trajectory
from lidarcal_ros.core.params import N_PARAMETERS, PARAMETER_INDEX
from lidarcal_ros.errors import ConfigError, TrajectoryError

#: Largest departure of a mounting's rotation from orthonormal (``|R^T R - I|``, max entry).
ORTHONORMAL_TOLERANCE = 1e-6


class TimeConvention(StrEnum):
    """What a driver's per-point time is measured from: ``relative`` to the cloud's
    ``header.stamp``, ``absolute`` (the stamps' clock), or ``auto`` (decided from the first
    cloud's values against its stamp)."""

    AUTO = "auto"
    RELATIVE = "relative"
    ABSOLUTE = "absolute"


# ------------------------------------------------------------------ the mounting

def quaternion_from_matrix(rotation: np.ndarray) -> np.ndarray:
    """The unit quaternion ``(x, y, z, w)`` of a rotation matrix (3, 3), ``w >= 0``: the
    inverse of :func:`~lidarcal_ros.core.georeferencing.attitude.rotation_matrices` (Shepperd's
    method: the largest of ``w, x, y, z`` is taken from the diagonal, the others from it)."""
    r = np.asarray(rotation, dtype=np.float64).reshape(3, 3)
    trace = r[0, 0] + r[1, 1] + r[2, 2]
    k = int(np.argmax([trace, r[0, 0], r[1, 1], r[2, 2]]))
    if k == 0:
        s = 2.0 * math.sqrt(1.0 + trace)  # 4 w
        q = [(r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s,
             0.25 * s]
    elif k == 1:
        s = 2.0 * math.sqrt(1.0 + r[0, 0] - r[1, 1] - r[2, 2])  # 4 x
        q = [0.25 * s, (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s,
             (r[2, 1] - r[1, 2]) / s]
    elif k == 2:
        s = 2.0 * math.sqrt(1.0 + r[1, 1] - r[0, 0] - r[2, 2])  # 4 y
        q = [(r[0, 1] + r[1, 0]) / s, 0.25 * s, (r[1, 2] + r[2, 1]) / s,
             (r[0, 2] - r[2, 0]) / s]
    else:
        s = 2.0 * math.sqrt(1.0 + r[2, 2] - r[0, 0] - r[1, 1])  # 4 z
        q = [(r[0, 2] + r[2, 0]) / s, (r[1, 2] + r[2, 1]) / s, 0.25 * s,
             (r[1, 0] - r[0, 1]) / s]
    out = np.array(q)
    out /= np.linalg.norm(out)
    return -out if out[3] < 0.0 else out


@dataclass(frozen=True)
class Mounting:
    """The mounting ``base_link -> sensor`` (REP-103; module docstring): a point ``p`` of the
    sensor's frame is ``translation + rotation @ p`` in ``base_link``.

    Attributes
    ----------
    rotation : (3, 3) float64
        ``R_bs``, sensor axes to ``base_link`` axes (orthonormal, determinant +1).
    translation : (3,) float64
        ``t_bs``, the sensor's origin in ``base_link``, m.
    """

    rotation: np.ndarray
    translation: np.ndarray

    def __post_init__(self) -> None:
        r = np.array(self.rotation, dtype=np.float64)
        t = np.array(self.translation, dtype=np.float64).reshape(-1)
        if r.shape != (3, 3) or not np.isfinite(r).all():
            raise ConfigError(f"mounting rotation must be a finite 3x3 matrix, got shape "
                              f"{r.shape}")
        if t.shape != (3,) or not np.isfinite(t).all():
            raise ConfigError(f"mounting translation must be 3 finite numbers (m), got {t}")
        off = float(np.max(np.abs(r.T @ r - np.eye(3))))
        if off > ORTHONORMAL_TOLERANCE or np.linalg.det(r) < 0.0:
            raise ConfigError(f"mounting rotation is not a rotation (|R^T R - I| = {off:.1e}, "
                              f"det {np.linalg.det(r):+.3f})")
        r.setflags(write=False)
        t.setflags(write=False)
        object.__setattr__(self, "rotation", r)
        object.__setattr__(self, "translation", t)

    @classmethod
    def from_quaternion(cls, translation: np.ndarray | list[float],
                        quaternion: np.ndarray | list[float]) -> Mounting:
        """From a TF transform: ``translation`` (m) and ``quaternion`` ``(x, y, z, w)``
        (normalised here; zero or not finite: ConfigError)."""
        q = np.asarray(quaternion, dtype=np.float64).reshape(-1)
        norm = float(np.linalg.norm(q)) if q.shape == (4,) else 0.0
        if not (math.isfinite(norm) and norm > 0.0):
            raise ConfigError(f"mounting quaternion must be 4 finite numbers (x, y, z, w), "
                              f"not all zero, got {q}")
        return cls(rotation_matrices(q / norm)[0], np.asarray(translation, dtype=np.float64))

    @property
    def quaternion(self) -> np.ndarray:
        """``R_bs`` as a unit quaternion ``(x, y, z, w)``, ``w >= 0`` (a TF transform's)."""
        return quaternion_from_matrix(self.rotation)

    @property
    def body_rotation(self) -> np.ndarray:
        """``P R_bs``: sensor axes to docs/method.md's body frame (right, forward, up)."""
        return P_BODY @ self.rotation

    @property
    def lever_arm(self) -> np.ndarray:
        """``P t_bs``: the sensor's origin in docs/method.md's body frame, m."""
        return P_BODY @ self.translation

    def to_base(self, points: np.ndarray | list[list[float]]) -> np.ndarray:
        """Sensor-frame points (n, 3) in ``base_link``, m: ``t_bs + R_bs p``."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        return p @ self.rotation.T + self.translation


def _boresight(delta: np.ndarray) -> np.ndarray:
    """``P^T R_B P``: the boresight rotation of ``delta`` (method.md's body frame) in
    ``base_link``'s axes."""
    i = PARAMETER_INDEX
    r_b = boresight_matrix(delta[i["domega"]], delta[i["dphi"]], delta[i["dkappa"]])
    return P_BODY.T @ r_b @ P_BODY


def _biases(delta: np.ndarray | list[float]) -> np.ndarray:
    d = np.asarray(delta, dtype=np.float64).reshape(-1)
    if d.shape != (N_PARAMETERS,) or not np.isfinite(d).all():
        raise ConfigError(f"biases must be {N_PARAMETERS} finite numbers (dX ... dS), got {d}")
    return d


def mounting_from_biases(nominal: Mounting, delta: np.ndarray | list[float]) -> Mounting:
    """The calibrated (true) mounting from the nominal one and the biases ``delta`` (SI,
    ``nominal - true``; docs/method.md section 12):
    ``R_bs,true = P^T R_B^T P R_bs,nominal``, ``t_bs,true = t_bs,nominal - P^T [dX, dY, dZ]``.

    The range bias is not part of a transform: the true range is ``r - dr`` (the
    ``range_offset`` of :func:`georeference`); ``dS`` has no meaning here.
    """
    d = _biases(delta)
    rotation = _boresight(d).T @ nominal.rotation
    return Mounting(rotation, nominal.translation - P_BODY.T @ d[:3])


def biases_between(nominal: Mounting, mounting: Mounting) -> np.ndarray:
    """The biases (8,) SI, ``nominal - true``, that take ``nominal`` to ``mounting`` (the
    inverse of :func:`mounting_from_biases`: exact, the boresight's angles those of
    :func:`~lidarcal_ros.core.georeferencing.bias_model.boresight_matrix`); ``dr`` and ``dS``
    zero."""
    r_b = P_BODY @ (nominal.rotation @ mounting.rotation.T) @ P_BODY.T  # R_B (body frame)
    dkappa, dphi, domega = Rotation.from_matrix(r_b).as_euler("ZYX")
    d = np.zeros(N_PARAMETERS)
    d[:3] = P_BODY @ (nominal.translation - mounting.translation)
    d[3:6] = domega, dphi, dkappa
    return d


def mounting_with_biases(true: Mounting, delta: np.ndarray | list[float]) -> Mounting:
    """The nominal mounting a system would use whose error is ``delta`` (``nominal -
    true``): the inverse of :func:`mounting_from_biases` (for the simulator)."""
    d = _biases(delta)
    return Mounting(_boresight(d) @ true.rotation, true.translation + P_BODY.T @ d[:3])


# ------------------------------------------------------------------ direct georeferencing

@dataclass
class SensorGeoreference:
    """Sensor-frame points georeferenced (:func:`georeference`), with what the design rows
    need.

    Attributes
    ----------
    xyz : (n, 3) float64
        The points in the map frame, m.
    origin : (n, 3) float64
        ``X_mb(t)``, the ``base_link`` origin at each point's time, map frame, m.
    rotation : (n, 3, 3) float64
        ``R_ins(t) = R_mb(t) P^T``: docs/method.md's body frame (right, forward, up) to map.
    rho : (n, 3) float64
        The laser vector ``P R_bs p`` (sensor origin to point, body frame, m), range
        corrected by ``range_offset``.
    lever_arm : (3,) float64
        ``P t_bs``, body frame, m.
    """

    xyz: np.ndarray
    origin: np.ndarray
    rotation: np.ndarray
    rho: np.ndarray
    lever_arm: np.ndarray

    @property
    def range(self) -> np.ndarray:
        """``|rho|``, m."""
        return np.sqrt(np.einsum("ij,ij->i", self.rho, self.rho))

    @property
    def base_rotation(self) -> np.ndarray:
        """``R_mb(t) = R_ins(t) P`` (n, 3, 3): REP-103's ``base_link`` to map."""
        return self.rotation @ P_BODY


def _segments(t: np.ndarray, trajectory: Trajectory, source: str) -> np.ndarray:
    """The trajectory segment of each time (rigorous.attitude_segments), refusing times
    outside the trajectory's span (no extrapolation)."""
    if len(trajectory) >= 2 and t.size:
        outside = (t < trajectory.t[0]) | (t > trajectory.t[-1])
        if outside.any():
            k = int(np.argmax(outside))
            raise TrajectoryError(
                f"{source}: {int(outside.sum())} of {t.size} points lie outside the "
                f"trajectory's time span [{trajectory.t[0]:.3f}, {trajectory.t[-1]:.3f}] s "
                f"(first at t={t[k]:.3f} s)")
    return attitude_segments(t, trajectory, source=source)


def georeference(points: np.ndarray, t: np.ndarray, trajectory: Trajectory,
                 mounting: Mounting, *, range_offset: float = 0.0,
                 source: str = "points") -> SensorGeoreference:
    """Direct georeferencing (docs/method.md section 12):
    ``X = X_mb(t) + R_mb(t) (t_bs + R_bs p)``, the pose of ``base_link`` interpolated at each
    point's time as section 10 does (position linear, attitude a cubic in rotation vectors:
    :func:`~lidarcal_ros.core.georeferencing.attitude.interpolated_frames`).

    Parameters
    ----------
    points : (n, 3) float32 or float64
        ``p``, the points in the sensor's frame, m.
    t : (n,) float64
        Absolute firing times on the trajectory's clock, s.
    trajectory : Trajectory
        Poses of ``base_link``; an orientation is required.
    mounting : Mounting
        ``base_link -> sensor``.
    range_offset : float, keyword-only
        Subtracted from every range (``dr`` of a calibration: ``r_true = r - dr``), m.

    Raises
    ------
    TrajectoryError
        No orientation, a point outside the trajectory's time span, or between poses
        without orientation.
    """
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    t = np.ascontiguousarray(t, dtype=np.float64).reshape(-1)
    if t.shape[0] != p.shape[0]:
        raise ConfigError(f"{source}: {p.shape[0]} points but {t.shape[0]} times")
    q = trajectory.orientation
    if q is None:
        raise TrajectoryError(f"{source}: sensor-frame clouds need the orientation of "
                              "base_link on the trajectory; its poses carry none")
    segment = _segments(t, trajectory, source)
    rho = p @ mounting.body_rotation.T
    if range_offset:
        r = np.sqrt(np.einsum("ij,ij->i", rho, rho))
        with np.errstate(invalid="ignore", divide="ignore"):
            rho *= np.where(r > 0.0, 1.0 - range_offset / r, 1.0)[:, None]
    origin, rotation, _ = interpolated_frames(t, np.zeros((t.shape[0], 3)), segment,
                                              trajectory.t, trajectory.xyz, q)
    lever = mounting.lever_arm
    xyz = origin + np.einsum("nij,nj->ni", rotation, rho + lever)
    return SensorGeoreference(xyz=xyz, origin=origin, rotation=rotation, rho=rho,
                              lever_arm=lever)


# ------------------------------------------------------------------ design columns

def general_columns(rho: np.ndarray, *, linear_scanner: bool = False) -> np.ndarray:
    """The derivative of a point with respect to the biases in the body frame (right,
    forward, up) for a general laser vector ``rho = [x, y, z]`` (docs/method.md section 12):
    (n, 3, 8) in :data:`~lidarcal_ros.core.params.PARAMETER_NAMES` order, ``A = R_ins @
    columns``.

    ``dX, dY, dZ`` the unit vectors, ``domega [0, -z, y]``, ``dphi [z, 0, -x]``, ``dkappa
    [-y, x, 0]``, ``dr rho / |rho|``; ``dS`` zero unless ``linear_scanner`` (then section
    10's ``beta [z, 0, -x]``, ``beta = atan2(-x, -z)``). With ``y = 0`` these are section 10's
    columns.
    """
    rho = np.asarray(rho, dtype=np.float64).reshape(-1, 3)
    x, y, z = rho[:, 0], rho[:, 1], rho[:, 2]
    r = np.sqrt(x * x + y * y + z * z)
    cols = np.zeros((rho.shape[0], 3, N_PARAMETERS))
    cols[:, 0, 0] = cols[:, 1, 1] = cols[:, 2, 2] = 1.0
    cols[:, 1, 3], cols[:, 2, 3] = -z, y
    cols[:, 0, 4], cols[:, 2, 4] = z, -x
    cols[:, 0, 5], cols[:, 1, 5] = -y, x
    with np.errstate(invalid="ignore", divide="ignore"):
        cols[:, :, 6] = rho / r[:, None]
    if linear_scanner:
        beta = np.arctan2(-x, -z)
        cols[:, 0, 7], cols[:, 2, 7] = beta * z, -beta * x
    return cols


def design_matrix(geo: SensorGeoreference, *, linear_scanner: bool = False) -> np.ndarray:
    """``A = R_ins C(rho)`` (n, 3, 8) of each georeferenced point: ``X_b = X_true + A delta``
    to first order (map frame; :func:`general_columns`)."""
    return np.einsum("nij,njk->nik", geo.rotation,
                     general_columns(geo.rho, linear_scanner=linear_scanner))


# ------------------------------------------------------------------ timing bias

@compiled
def _segment_splines(traj_t: np.ndarray, traj_q: np.ndarray) -> np.ndarray:
    """:func:`~lidarcal_ros.core.georeferencing.attitude.segment_spline` of every segment,
    (m - 1, 10); NaN rows where an end sample has no orientation."""
    m = traj_t.shape[0]
    out = np.full((max(m - 1, 0), 10), np.nan)
    for j in range(m - 1):
        if math.isnan(traj_q[j, 0]) or math.isnan(traj_q[j + 1, 0]):
            continue
        out[j, :] = segment_spline(j, traj_t, traj_q)
    return out


def _skew(v: np.ndarray) -> np.ndarray:
    """``[v]x`` (n, 3, 3) of vectors (n, 3)."""
    s = np.zeros((v.shape[0], 3, 3))
    s[:, 0, 1], s[:, 0, 2] = -v[:, 2], v[:, 1]
    s[:, 1, 0], s[:, 1, 2] = v[:, 2], -v[:, 0]
    s[:, 2, 0], s[:, 2, 1] = -v[:, 1], v[:, 0]
    return s


def body_rates(t: np.ndarray, trajectory: Trajectory, *, source: str = "points"
               ) -> tuple[np.ndarray, np.ndarray]:
    """The velocity ``v_mb`` (m/s) and angular rate ``w_mb`` (rad/s) of ``base_link`` at times
    ``t``, both in the map frame: the exact time derivatives of the interpolation
    :func:`georeference` uses (position linear between samples; attitude ``R_mb = R_j
    Exp(phi(t))``, ``phi`` the cubic of
    :func:`~lidarcal_ros.core.georeferencing.attitude.segment_spline`, whose rate is ``R_mb
    J_r(phi) phi'`` with ``J_r`` the right Jacobian of SO(3)).

    Returns
    -------
    v, w : (n, 3) float64 each
    """
    t = np.ascontiguousarray(t, dtype=np.float64).reshape(-1)
    q = trajectory.orientation
    if q is None:
        raise TrajectoryError(f"{source}: the trajectory has no orientation")
    j = _segments(t, trajectory, source)
    spline = _segment_splines(trajectory.t, q)[j]
    p1, m0, m1, h = spline[:, 0:3], spline[:, 3:6], spline[:, 6:9], spline[:, 9]
    f = ((t - trajectory.t[j]) / h)[:, None]
    f2 = f * f
    hh = h[:, None]
    # Hermite basis (attitude.pose_on_segment) and its derivative in time.
    phi = (f2 * f - 2.0 * f2 + f) * hh * m0 + (3.0 * f2 - 2.0 * f2 * f) * p1 \
        + (f2 * f - f2) * hh * m1
    phi_dot = (3.0 * f2 - 4.0 * f + 1.0) * m0 + (6.0 * f - 6.0 * f2) / hh * p1 \
        + (3.0 * f2 - 2.0 * f) * m1
    theta2 = np.einsum("ij,ij->i", phi, phi)
    theta = np.sqrt(theta2)
    small = theta < 1e-3
    with np.errstate(invalid="ignore", divide="ignore"):
        a = np.where(small, 0.5 - theta2 / 24.0, (1.0 - np.cos(theta)) / theta2)
        b = np.where(small, 1.0 / 6.0 - theta2 / 120.0, (theta - np.sin(theta)) / (theta2 * theta))
    k = _skew(phi)
    jr = np.eye(3) - a[:, None, None] * k + b[:, None, None] * (k @ k)
    omega_body = np.einsum("nij,nj->ni", jr, phi_dot)  # REP-103 body frame
    # R_mb(t) = R_j Exp(phi): the rotation at t, in closed form (Rodrigues).
    with np.errstate(invalid="ignore", divide="ignore"):
        s = np.where(small, 1.0 - theta2 / 6.0, np.sin(theta) / theta)
    exp = np.eye(3) + s[:, None, None] * k + a[:, None, None] * (k @ k)
    r_mb = rotation_matrices(q[j]) @ exp
    w = np.einsum("nij,nj->ni", r_mb, omega_body)
    v = (trajectory.xyz[j + 1] - trajectory.xyz[j]) / h[:, None]
    return v, w


def timing_column(geo: SensorGeoreference, v: np.ndarray, w: np.ndarray) -> np.ndarray:
    """The column of the timing bias ``dt`` (delivered - true time, s; docs/method.md section
    12): ``v_mb + w_mb x (X - X_mb)`` (n, 3, map frame, m/s), with ``v, w`` of
    :func:`body_rates` at the points' times."""
    return np.asarray(v) + np.cross(np.asarray(w), geo.xyz - geo.origin)


def point_rates(t: np.ndarray, xyz: np.ndarray, origin: np.ndarray, trajectory: Trajectory,
                *, source: str = "points") -> np.ndarray:
    """:func:`timing_column` of points ``xyz`` (n, 3, map frame, m) at times ``t`` (s) seen
    from ``origin`` (n, 3: the trajectory's position at each time), the rates those of
    ``trajectory`` (:func:`body_rates`): ``v + w x (X - origin)``, m/s."""
    v, w = body_rates(t, trajectory, source=source)
    return v + np.cross(w, np.asarray(xyz, dtype=np.float64) - origin)


__all__ = [
    "ORTHONORMAL_TOLERANCE",
    "Mounting",
    "SensorGeoreference",
    "TimeConvention",
    "biases_between",
    "body_rates",
    "design_matrix",
    "general_columns",
    "georeference",
    "mounting_from_biases",
    "mounting_with_biases",
    "point_rates",
    "quaternion_from_matrix",
    "timing_column",
]
