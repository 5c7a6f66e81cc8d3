"""The INS attitude of the trajectory: quaternions, rotations and their interpolation.

Conventions: docs/method.md section 10 (REP-103 quaternions, ``R_ins = R(q) P^T``). An absent
orientation (zero, not finite, or the identity where every pose is the identity) is a NaN row.
"""

from __future__ import annotations

import math

import numpy as np

from lidarcal_ros.core.jit import compiled, inlined

#: docs/method.md's body axes (right, forward, up) in REP-103's (forward, left, up):
#: ``v_rep = P v_method``.
P_BODY = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])

#: The identity quaternion, ``(x, y, z, w)``.
IDENTITY_XYZW = (0.0, 0.0, 0.0, 1.0)


def normalise_quaternions(q: np.ndarray, *, oriented: bool = False) -> np.ndarray:
    """Unit quaternions ``(n, 4)`` xyzw, NaN rows where absent (module docstring).

    The identity rows are absent unless another row, or an earlier part of the same trajectory
    (``oriented``), carries a rotation other than the identity. The sign is chosen so that
    consecutive rows lie in the same hemisphere (``q`` and ``-q`` are the same rotation;
    interpolation needs the shorter arc).
    """
    q = np.array(q, dtype=np.float64, copy=True).reshape(-1, 4)
    scale = np.abs(q).max(axis=1) if q.size else np.zeros(0)
    with np.errstate(invalid="ignore", divide="ignore", over="ignore", under="ignore"):
        # Rows far from unit length are scaled by their largest component first: squares of
        # 1e308 overflow and squares of a subnormal vanish (a rotation read as none). Others
        # are divided by their norm alone, so that every result stays bit for bit as before.
        extreme = ~((scale > 1e-100) & (scale < 1e100))
        q[extreme] /= scale[extreme, None]
        q /= np.sqrt(np.einsum("ij,ij->i", q, q))[:, None]
    absent = ~np.isfinite(q).all(axis=1) | ~(scale > 0.0)
    identity = (q[:, 0] == 0.0) & (q[:, 1] == 0.0) & (q[:, 2] == 0.0)
    if not oriented and not (~absent & ~identity).any():
        absent |= identity  # identity everywhere: the producer has no attitude
    q[absent] = np.nan
    _one_hemisphere(q)
    return q


def _one_hemisphere(q: np.ndarray) -> None:
    """Flip rows of ``q`` (n, 4) in place so that consecutive rows lie in one hemisphere (a
    NaN row breaks the chain: the row after it is not compared)."""
    if q.shape[0] > 1:
        flip = np.einsum("ij,ij->i", q[1:], q[:-1]) < 0.0
        # Cumulative parity: a row is flipped when an odd number of sign changes precede it.
        parity = np.concatenate(([False], np.logical_xor.accumulate(flip)))
        q[parity] = -q[parity]


def bridge_missing(t: np.ndarray, q: np.ndarray, *, max_gap_s: float
                   ) -> tuple[np.ndarray, int]:
    """Orientations for the samples that lack one between two that have one at most
    ``max_gap_s`` apart (an attitude field dropped from a message or two of an INS stream):
    spherical linear interpolation between those two.

    Parameters
    ----------
    t : (n,) float64
        Sample times, s, strictly increasing.
    q : (n, 4) float64
        Unit quaternions xyzw (:func:`normalise_quaternions`), NaN rows where absent.
    max_gap_s : float, keyword-only
        The longest time between the two samples with an orientation around a gap bridged, s.

    Returns
    -------
    (n, 4) float64
        ``q`` itself where nothing is bridged; else a copy with the bridged rows filled, the
        rows in one hemisphere across them.
    int
        The samples bridged.
    """
    missing = np.isnan(q[:, 0])
    has = np.flatnonzero(~missing)
    if not missing.any() or has.size < 2:
        return q, 0
    gaps = np.flatnonzero(missing)
    after = np.searchsorted(has, gaps)
    inside = (after > 0) & (after < has.size)
    before_t = t[has[np.clip(after - 1, 0, has.size - 1)]]
    after_t = t[has[np.clip(after, 0, has.size - 1)]]
    bridged = gaps[inside & (after_t - before_t <= max_gap_s * (1.0 + 1e-9))]  # (0.68-0.58)
    if not bridged.size:
        return q, 0
    known = q[has]
    _one_hemisphere(known)  # (the rows either side of a gap were not compared)
    out = q.copy()
    out[has] = known
    out[bridged] = slerp(t[has], known, t[bridged])
    return out, int(bridged.size)


def rotation_matrices(q: np.ndarray) -> np.ndarray:
    """``R(q)`` (n, 3, 3) of unit quaternions ``(n, 4)`` xyzw (REP-103 body -> map)."""
    q = np.asarray(q, dtype=np.float64).reshape(-1, 4)
    x, y, z, w = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    r = np.empty((q.shape[0], 3, 3))
    r[:, 0, 0] = 1.0 - 2.0 * (y * y + z * z)
    r[:, 0, 1] = 2.0 * (x * y - z * w)
    r[:, 0, 2] = 2.0 * (x * z + y * w)
    r[:, 1, 0] = 2.0 * (x * y + z * w)
    r[:, 1, 1] = 1.0 - 2.0 * (x * x + z * z)
    r[:, 1, 2] = 2.0 * (y * z - x * w)
    r[:, 2, 0] = 2.0 * (x * z - y * w)
    r[:, 2, 1] = 2.0 * (y * z + x * w)
    r[:, 2, 2] = 1.0 - 2.0 * (x * x + y * y)
    return r


def body_rotations(q: np.ndarray) -> np.ndarray:
    """``R_ins = R(q) P^T`` (n, 3, 3): docs/method.md's body frame (right, forward, up) -> map.

    Its columns are the body's right, forward and up axes in the map frame: ``R(q)``'s
    columns are REP-103's forward, left and up, and right = -left.
    """
    r = rotation_matrices(q)
    out = np.empty_like(r)
    out[:, :, 0] = -r[:, :, 1]
    out[:, :, 1] = r[:, :, 0]
    out[:, :, 2] = r[:, :, 2]
    return out


def quaternions_from_attitude(roll: np.ndarray | float, pitch: np.ndarray | float,
                              kappa: np.ndarray | float) -> np.ndarray:
    """Quaternions ``(n, 4)`` xyzw of poses with ``R_ins = Rz(kappa) Rx(pitch) Ry(roll)``
    (radians, arrays of one length or scalars; docs/method.md section 10).

    ``R(q) = R_ins P = Rz(kappa + pi/2) Ry'(...)``: in REP-103's axes the roll is about x
    (forward) and the pitch about -y (the left axis: nose up is a negative rotation about it),
    so ``R(q) = Rz(kappa + pi/2) Ry(-pitch) Rx(roll)``.
    """
    roll, pitch, kappa = (np.atleast_1d(np.asarray(a, dtype=np.float64)).reshape(-1)
                          for a in np.broadcast_arrays(roll, pitch, kappa))
    yaw = kappa + 0.5 * math.pi
    cr, sr = np.cos(0.5 * roll), np.sin(0.5 * roll)
    cp, sp = np.cos(-0.5 * pitch), np.sin(-0.5 * pitch)
    cy, sy = np.cos(0.5 * yaw), np.sin(0.5 * yaw)
    # q = qz(yaw) * qy(-pitch) * qx(roll)
    q = np.empty((roll.shape[0], 4))
    q[:, 0] = cy * cp * sr - sy * sp * cr
    q[:, 1] = cy * sp * cr + sy * cp * sr
    q[:, 2] = sy * cp * cr - cy * sp * sr
    q[:, 3] = cy * cp * cr + sy * sp * sr
    return q


def body_rotations_from_attitude(roll: np.ndarray | float, pitch: np.ndarray | float,
                                 kappa: np.ndarray | float) -> np.ndarray:
    """``R_ins = Rz(kappa) Rx(pitch) Ry(roll)`` (n, 3, 3) straight from the angles (radians,
    broadcast against each other; docs/method.md section 10): the rotation of the poses of
    :func:`quaternions_from_attitude`, without the round trip through a quaternion, so that a
    level pose (roll = pitch = 0) gives exactly docs/method.md's ``R_kappa``."""
    roll, pitch, kappa = np.broadcast_arrays(
        *(np.asarray(a, dtype=np.float64).reshape(-1) for a in (roll, pitch, kappa)))
    cr, sr = np.cos(roll), np.sin(roll)
    cp, sp = np.cos(pitch), np.sin(pitch)
    ck, sk = np.cos(kappa), np.sin(kappa)
    # Rx(pitch) Ry(roll) = [[cr, 0, sr], [sp sr, cp, -sp cr], [-cp sr, sp, cp cr]], then Rz.
    r = np.empty((roll.shape[0], 3, 3))
    r[:, 0, 0] = ck * cr - sk * sp * sr
    r[:, 0, 1] = -sk * cp
    r[:, 0, 2] = ck * sr + sk * sp * cr
    r[:, 1, 0] = sk * cr + ck * sp * sr
    r[:, 1, 1] = ck * cp
    r[:, 1, 2] = sk * sr - ck * sp * cr
    r[:, 2, 0] = -cp * sr
    r[:, 2, 1] = sp
    r[:, 2, 2] = cp * cr
    return r


def quaternions_from_headings(kappa: np.ndarray) -> np.ndarray:
    """Level quaternions ``(n, 4)`` xyzw of headings ``kappa`` (rad); NaN rows for NaN."""
    kappa = np.asarray(kappa, dtype=np.float64).reshape(-1)
    q = quaternions_from_attitude(np.zeros_like(kappa), np.zeros_like(kappa), kappa)
    q[~np.isfinite(kappa)] = np.nan
    return q


def attitude_from_quaternions(q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``roll, pitch, kappa`` (rad, each (n,)) of quaternions (n, 4) xyzw, inverse of
    :func:`quaternions_from_attitude` (pitch within +-90 deg). NaN rows give NaN."""
    r = body_rotations(np.asarray(q, dtype=np.float64).reshape(-1, 4))
    # R_ins = Rz(k) Rx(p) Ry(r): third row (-cp sr, sp, cp cr), first column's ... see below.
    # Rx(p) Ry(r) = [[cr, 0, sr], [sp sr, cp, -sp cr], [-cp sr, sp, cp cr]].
    pitch = np.arcsin(np.clip(r[:, 2, 1], -1.0, 1.0))
    roll = np.arctan2(-r[:, 2, 0], r[:, 2, 2])
    # The forward column is Rz(k) (0, cp, sp): its horizontal part points along the heading.
    kappa = np.arctan2(-r[:, 0, 1], r[:, 1, 1])
    return roll, pitch, kappa


def headings_from_quaternions(q: np.ndarray) -> np.ndarray:
    """``kappa`` (rad, in ``(-pi, pi]``) of quaternions (n, 4) xyzw: the yaw of the body's
    forward axis projected on the horizontal, whatever the roll and pitch; NaN for NaN rows
    or a forward axis straight up or down."""
    q = np.asarray(q, dtype=np.float64).reshape(-1, 4)
    x, y, z, w = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    fx = w * w + x * x - y * y - z * z  # R(q) (1, 0, 0), horizontal part, times |q|^2
    fy = 2.0 * (x * y + w * z)
    with np.errstate(invalid="ignore"):
        kappa = np.arctan2(fy, fx) - 0.5 * math.pi
    kappa = np.where(kappa <= -math.pi, kappa + 2.0 * math.pi, kappa)
    return np.where((fx == 0.0) & (fy == 0.0), np.nan, kappa)


def slerp(t_samples: np.ndarray, q_samples: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Quaternions ``(n, 4)`` at times ``t`` by spherical linear interpolation between the
    samples bracketing each time (clamped to the first and last sample outside them).

    Parameters
    ----------
    t_samples : (m,) float64
        Sample times, s, strictly increasing.
    q_samples : (m, 4) float64
        Unit quaternions xyzw in one hemisphere from sample to sample
        (:func:`normalise_quaternions`); NaN rows give NaN.
    t : (n,) float64
        Times, s.
    """
    t = np.asarray(t, dtype=np.float64).reshape(-1)
    m = t_samples.shape[0]
    if m == 0:
        return np.full((t.shape[0], 4), np.nan)
    if m == 1:
        return np.repeat(q_samples[:1], t.shape[0], axis=0)
    i = np.clip(np.searchsorted(t_samples, t, side="right") - 1, 0, m - 2)
    t0, t1 = t_samples[i], t_samples[i + 1]
    f = np.clip((t - t0) / (t1 - t0), 0.0, 1.0)
    q0, q1 = q_samples[i], q_samples[i + 1]
    cos_theta = np.clip(np.einsum("ij,ij->i", q0, q1), -1.0, 1.0)
    theta = np.arccos(cos_theta)
    sin_theta = np.sin(theta)
    small = sin_theta < 1e-9
    with np.errstate(invalid="ignore", divide="ignore"):
        w0 = np.where(small, 1.0 - f, np.sin((1.0 - f) * theta) / sin_theta)
        w1 = np.where(small, f, np.sin(f * theta) / sin_theta)
    out = w0[:, None] * q0 + w1[:, None] * q1
    out /= np.sqrt(np.einsum("ij,ij->i", out, out))[:, None]
    return out


#: Below this rotation angle (rad) the quaternion exponential and logarithm take their
#: series: an INS turns by well under a degree between samples.
_SERIES_ANGLE = 0.02


@inlined
def _qmul(a0: float, a1: float, a2: float, a3: float, b0: float, b1: float, b2: float,
          b3: float) -> tuple[float, float, float, float]:
    """Hamilton product ``a b`` of quaternions ``(x, y, z, w)``."""
    return (a3 * b0 + a0 * b3 + a1 * b2 - a2 * b1,
            a3 * b1 - a0 * b2 + a1 * b3 + a2 * b0,
            a3 * b2 + a0 * b1 - a1 * b0 + a2 * b3,
            a3 * b3 - a0 * b0 - a1 * b1 - a2 * b2)


@inlined
def _relative_rotation(q: np.ndarray, j: int, k: int) -> tuple[float, float, float]:
    """The rotation vector (rad) of ``q_j^-1 q_k``: sample ``k`` seen from sample ``j``'s
    body frame; NaN where either has no orientation."""
    x, y, z, w = _qmul(-q[j, 0], -q[j, 1], -q[j, 2], q[j, 3], q[k, 0], q[k, 1], q[k, 2],
                       q[k, 3])
    if w < 0.0:
        x, y, z, w = -x, -y, -z, -w
    v = math.sqrt(x * x + y * y + z * z)
    if v < 0.5 * _SERIES_ANGLE:
        u2 = v * v / (w * w)  # 2 atan(v / w) / v = (2 / w)(1 - u^2/3 + u^4/5), u = v / w
        scale = 2.0 / w * (1.0 - u2 / 3.0 + u2 * u2 / 5.0)
    else:
        scale = 2.0 * math.atan2(v, w) / v
    return x * scale, y * scale, z * scale


@inlined
def segment_spline(j: int, traj_t: np.ndarray, traj_q: np.ndarray
                    ) -> tuple[float, float, float, float, float, float, float, float, float,
                               float]:
    """The cubic of the attitude between samples ``j`` and ``j + 1``, in the chart of
    sample ``j`` (rotation vectors ``phi`` of ``q_j^-1 q(t)``): ``phi_1`` (of sample
    ``j + 1``) and the Hermite tangents ``m_0``, ``m_1`` (rad/s) from central differences
    over the neighbouring samples, one-sided (a slerp) where a neighbour lacks.

    Returns ``p1x, p1y, p1z, m0x, m0y, m0z, m1x, m1y, m1z, h`` (``h`` the interval, s).
    """
    m = traj_t.shape[0]
    t0, t1 = traj_t[j], traj_t[j + 1]
    h = t1 - t0
    p1x, p1y, p1z = _relative_rotation(traj_q, j, j + 1)
    m0x, m0y, m0z = p1x / h, p1y / h, p1z / h
    m1x, m1y, m1z = m0x, m0y, m0z
    if j >= 1 and not math.isnan(traj_q[j - 1, 0]):
        ax, ay, az = _relative_rotation(traj_q, j, j - 1)
        d = t1 - traj_t[j - 1]
        m0x, m0y, m0z = (p1x - ax) / d, (p1y - ay) / d, (p1z - az) / d
    if j + 2 < m and not math.isnan(traj_q[j + 2, 0]):
        bx, by, bz = _relative_rotation(traj_q, j, j + 2)
        d = traj_t[j + 2] - t0
        m1x, m1y, m1z = bx / d, by / d, bz / d
    return p1x, p1y, p1z, m0x, m0y, m0z, m1x, m1y, m1z, h


@inlined
def pose_on_segment(ti: float, j: int, spline: tuple[float, float, float, float, float,
                                                      float, float, float, float, float],
                     traj_t: np.ndarray, traj_xyz: np.ndarray, traj_q: np.ndarray
                     ) -> tuple[float, float, float, float, float, float, float, float,
                                float, float, float, float]:
    """The firing position (linear interpolation) and ``R_ins`` (the segment's cubic,
    :func:`segment_spline`) at time ``ti`` between samples ``j`` and ``j + 1``.

    Returns ``ox, oy, oz`` (m) and ``R_ins`` row by row: ``r00, r01, r02, r10, ..., r22``.
    """
    p1x, p1y, p1z, m0x, m0y, m0z, m1x, m1y, m1z, h = spline
    f = (ti - traj_t[j]) / h
    g = 1.0 - f
    ox = g * traj_xyz[j, 0] + f * traj_xyz[j + 1, 0]
    oy = g * traj_xyz[j, 1] + f * traj_xyz[j + 1, 1]
    oz = g * traj_xyz[j, 2] + f * traj_xyz[j + 1, 2]
    # Hermite basis with phi(0) = 0: h10 h m0 + h01 phi1 + h11 h m1.
    f2 = f * f
    b10 = (f2 * f - 2.0 * f2 + f) * h
    b01 = 3.0 * f2 - 2.0 * f2 * f
    b11 = (f2 * f - f2) * h
    px = b10 * m0x + b01 * p1x + b11 * m1x
    py = b10 * m0y + b01 * p1y + b11 * m1y
    pz = b10 * m0z + b01 * p1z + b11 * m1z
    angle = math.sqrt(px * px + py * py + pz * pz)
    if angle < _SERIES_ANGLE:
        a2 = angle * angle  # sin(a/2)/a and cos(a/2) by their series
        s = 0.5 - a2 / 48.0 + a2 * a2 / 3840.0
        c = 1.0 - a2 / 8.0 + a2 * a2 / 384.0
    else:
        s = math.sin(0.5 * angle) / angle
        c = math.cos(0.5 * angle)
    x, y, z, w = _qmul(traj_q[j, 0], traj_q[j, 1], traj_q[j, 2], traj_q[j, 3],
                       px * s, py * s, pz * s, c)
    inv = 1.0 / math.sqrt(x * x + y * y + z * z + w * w)
    x, y, z, w = x * inv, y * inv, z * inv, w * inv
    # R(q)'s columns are REP-103's forward, left, up; R_ins's are right (= -left),
    # forward, up.
    f0 = 1.0 - 2.0 * (y * y + z * z)
    f1 = 2.0 * (x * y + z * w)
    f2_ = 2.0 * (x * z - y * w)
    l0 = 2.0 * (x * y - z * w)
    l1 = 1.0 - 2.0 * (x * x + z * z)
    l2 = 2.0 * (y * z + x * w)
    u0 = 2.0 * (x * z + y * w)
    u1 = 2.0 * (y * z - x * w)
    u2 = 1.0 - 2.0 * (x * x + y * y)
    return ox, oy, oz, -l0, f0, u0, -l1, f1, u1, -l2, f2_, u2


@compiled
def interpolated_frames(t: np.ndarray, xyz: np.ndarray, segment: np.ndarray,
                        traj_t: np.ndarray, traj_xyz: np.ndarray, traj_q: np.ndarray
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Firing position, ``R_ins`` and the laser vector ``rho_hat = R_ins^T (X - X_o)`` of
    each point (docs/method.md section 10) from the trajectory samples around its time.

    The position is interpolated linearly (an aircraft's acceleration moves it by well under
    a millimetre from the chord between samples 20 ms apart), the attitude by a cubic
    Hermite in the rotation vectors of the sample before (:func:`pose_on_segment`): in
    turbulence the attitude's angular acceleration reaches some 0.5 rad/s^2, and slerp, a
    constant rate between samples, misses it by ``a h^2 / 8``, 2.5e-5 rad (2.5 cm at 1 km)
    at 50 Hz, where the cubic's error, of order ``h^3`` (its tangents are central
    differences), is some 3e-7 rad. Where a neighbouring sample is missing the segment is a
    slerp.

    Parameters
    ----------
    t : (n,) float64
        Firing times, s.
    xyz : (n, 3) float64
        Points, map frame, m.
    segment : (n,) int64
        The sample ``j`` of each point, ``traj_t[j] <= t < traj_t[j + 1]`` (``0 <= j < m - 1``).
    traj_t, traj_xyz, traj_q : (m,), (m, 3), (m, 4) float64
        Sample times (s), positions (m) and unit quaternions (xyzw, one hemisphere).

    Returns
    -------
    origin : (n, 3) firing positions, m
    rotation : (n, 3, 3) ``R_ins``
    rho : (n, 3) ``(x, y, z)`` body-frame coordinates of the points, m
    """
    n = t.shape[0]
    origin = np.empty((n, 3))
    rotation = np.empty((n, 3, 3))
    rho = np.empty((n, 3))
    current = -1
    spline = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)
    for i in range(n):
        j = segment[i]
        if j != current:  # points come in time order: a segment serves thousands
            spline = segment_spline(j, traj_t, traj_q)
            current = j
        ox, oy, oz, r00, r01, r02, r10, r11, r12, r20, r21, r22 = pose_on_segment(
            t[i], j, spline, traj_t, traj_xyz, traj_q)
        origin[i, 0], origin[i, 1], origin[i, 2] = ox, oy, oz
        r = rotation[i]
        r[0, 0], r[0, 1], r[0, 2] = r00, r01, r02
        r[1, 0], r[1, 1], r[1, 2] = r10, r11, r12
        r[2, 0], r[2, 1], r[2, 2] = r20, r21, r22
        dx, dy, dz = xyz[i, 0] - ox, xyz[i, 1] - oy, xyz[i, 2] - oz
        rho[i, 0] = r00 * dx + r10 * dy + r20 * dz
        rho[i, 1] = r01 * dx + r11 * dy + r21 * dz
        rho[i, 2] = r02 * dx + r12 * dy + r22 * dz
    return origin, rotation, rho


__all__ = [
    "IDENTITY_XYZW",
    "P_BODY",
    "attitude_from_quaternions",
    "body_rotations",
    "body_rotations_from_attitude",
    "bridge_missing",
    "headings_from_quaternions",
    "interpolated_frames",
    "normalise_quaternions",
    "pose_on_segment",
    "quaternions_from_attitude",
    "quaternions_from_headings",
    "rotation_matrices",
    "segment_spline",
    "slerp",
]
