"""The bias model of docs/method.md sections 2-3 and 10: design matrix and point correction.

Vectorised over points; ``x``, ``z`` in metres (laser frame, ``z`` negative), ``kappa`` and
``beta`` in radians; parameters in :data:`lidarcal_ros.core.params.PARAMETER_NAMES` order.
"""

from __future__ import annotations

import numpy as np

from lidarcal_ros.core.georeferencing import bias_model_kernels as calibration_kernels
from lidarcal_ros.core.georeferencing.correction_kernels import bias_offsets
from lidarcal_ros.core.georeferencing.laser_geometry import LaserGeometry, ScannerKind
from lidarcal_ros.core.params import N_PARAMETERS

#: Empty arrays: no rotation per point (the level model), no column per point.
_NO_ROTATION = np.zeros((0, 3, 3))
_NO_COLUMN = np.zeros(0)


def design_matrix(
    x: np.ndarray, z: np.ndarray, kappa: np.ndarray, beta: np.ndarray
) -> np.ndarray:
    """Impact of the eight biases on each point, docs/method.md eq. [8].

    Parameters
    ----------
    x, z, kappa, beta : (n,) float64
        Laser-frame lateral/vertical coordinate (m), heading (rad), mirror angle (rad).

    Returns
    -------
    (n, 3, 8) float64
        ``A`` such that ``X_biased = X_true + A @ delta`` (rows X, Y, Z of the map frame).
    """
    x = np.asarray(x, dtype=np.float64)
    z = np.asarray(z, dtype=np.float64)
    c = np.cos(kappa)
    s = np.sin(kappa)
    sb = np.sin(beta)
    cb = np.cos(beta)
    a = np.zeros((*x.shape, 3, N_PARAMETERS))
    a[..., 0, 0] = c
    a[..., 0, 1] = -s
    a[..., 0, 3] = z * s
    a[..., 0, 4] = z * c
    a[..., 0, 5] = -x * s
    a[..., 0, 6] = -c * sb
    a[..., 0, 7] = z * beta * c
    a[..., 1, 0] = s
    a[..., 1, 1] = c
    a[..., 1, 3] = -z * c
    a[..., 1, 4] = z * s
    a[..., 1, 5] = x * c
    a[..., 1, 6] = -s * sb
    a[..., 1, 7] = z * beta * s
    a[..., 2, 2] = 1.0
    a[..., 2, 4] = -x
    a[..., 2, 6] = -cb
    a[..., 2, 7] = -x * beta
    return a


def normal_design_rows(
    normal: np.ndarray, x: np.ndarray, z: np.ndarray, kappa: np.ndarray, beta: np.ndarray
) -> np.ndarray:
    """``n^T A`` for each point: the design row of a point-to-patch observation, without
    materialising the (n, 3, 8) matrix (level model).

    Parameters
    ----------
    normal : (n, 3) float64
        Unit patch normals in the map frame.
    x, z, kappa, beta : (n,) float64
        As in :func:`design_matrix`.

    Returns
    -------
    (n, 8) float64
    """
    nx, ny = normal[:, 0], normal[:, 1]
    c = np.cos(kappa)
    s = np.sin(kappa)
    # The normal along the body's right (c, s) and forward (-s, c) axes, and up.
    body = np.column_stack([nx * c + ny * s, -nx * s + ny * c, normal[:, 2]])
    return body_normal_rows(body, x, z, beta, np.sin(beta), np.cos(beta))


def body_normal_rows(normal_body: np.ndarray, x: np.ndarray, z: np.ndarray, beta: np.ndarray,
                     sin_beta: np.ndarray, cos_beta: np.ndarray, *,
                     y: np.ndarray | None = None) -> np.ndarray:
    """``n_b^T C`` for each point, ``C`` the (3, 8) columns of docs/method.md section 10 in the
    body frame and ``n_b = R^T n`` the patch normal in it: the design row of a point-to-patch
    observation in either model (``A = R C``, so ``n^T A = (R^T n)^T C``).

    With ``y`` (a general scanner's forward coordinate, m), section 12's columns:
    ``domega [0, -z, y]``, ``dkappa [-y, x, 0]``, ``dr rho / |rho|`` and no ``dS`` (0).

    Parameters
    ----------
    normal_body : (n, 3) float64
        Unit normals in the body frame (right, forward, up).
    x, z, beta : (n,) float64
        Body-frame lateral and vertical coordinates (m) and mirror angle (rad).
    sin_beta, cos_beta : (n,) float64
        ``sb``, ``cb`` of the ``dr`` column (section 10: ``-x / r``, ``-z / r``).

    Returns
    -------
    (n, 8) float64
    """
    n_right, n_fwd, n_up = normal_body[:, 0], normal_body[:, 1], normal_body[:, 2]
    rows = np.empty((normal_body.shape[0], N_PARAMETERS))
    rows[:, 0] = n_right
    rows[:, 1] = n_fwd
    rows[:, 2] = n_up
    rows[:, 3] = -z * n_fwd
    rows[:, 4] = z * n_right - x * n_up
    rows[:, 5] = x * n_fwd
    rows[:, 6] = -sin_beta * n_right - cos_beta * n_up
    rows[:, 7] = beta * (z * n_right - x * n_up)
    if y is not None:  # (added last: y = 0 leaves the rows above to the bit)
        rows[:, 3] += y * n_up
        rows[:, 5] -= y * n_right
        rows[:, 6] += y / np.sqrt(x * x + y * y + z * z) * n_fwd
        rows[:, 7] = 0.0
    return rows


def body_columns(x: np.ndarray, z: np.ndarray, beta: np.ndarray, sin_beta: np.ndarray,
                 cos_beta: np.ndarray, *, y: np.ndarray | None = None) -> np.ndarray:
    """The derivative of a point with respect to the biases in the body frame (right,
    forward, up), docs/method.md section 10: (n, 3, 8), ``A = R @ columns``; with ``y`` (a
    general scanner's forward coordinate, m) section 12's (as :func:`body_normal_rows`)."""
    n = np.shape(x)[0]
    cols = np.zeros((n, 3, N_PARAMETERS))
    cols[:, 0, 0] = cols[:, 1, 1] = cols[:, 2, 2] = 1.0
    cols[:, 1, 3] = -z
    cols[:, 0, 4] = z
    cols[:, 2, 4] = -x
    cols[:, 1, 5] = x
    cols[:, 0, 6] = -sin_beta
    cols[:, 2, 6] = -cos_beta
    cols[:, 0, 7] = beta * z
    cols[:, 2, 7] = -beta * x
    if y is not None:
        cols[:, 2, 3] = y
        cols[:, 0, 5] = -y
        cols[:, 1, 6] = y / np.sqrt(x * x + y * y + z * z)
        cols[:, :, 7] = 0.0
    return cols


def geometry_design_matrix(geometry: LaserGeometry) -> np.ndarray:
    """``A`` (n, 3, 8) of each point of ``geometry`` in either model: ``R`` times the body
    columns (:func:`body_columns`)."""
    _, _, sb, cb = geometry.trig()
    cols = body_columns(geometry.x, geometry.z, geometry.beta, sb, cb, y=_general_y(geometry))
    if geometry.rotation is None:  # R_kappa: the rows of eq. [8]
        return design_matrix(geometry.x, geometry.z, geometry.kappa, geometry.beta)
    a = np.einsum("nij,njk->nik", geometry.rotation, cols)
    if geometry.timing is not None:  # dS's place holds the timing bias dt (section 12)
        a[:, :, 7] = geometry.timing
    return a


def geometry_normal_rows(normal: np.ndarray, geometry: LaserGeometry) -> np.ndarray:
    """``n^T A`` of each point of ``geometry`` (either model) and its patch normal ``normal``
    (n, 3, map frame): :func:`body_normal_rows` of the normal turned into the body frame."""
    _, _, sb, cb = geometry.trig()
    rows = body_normal_rows(geometry.to_body(normal), geometry.x, geometry.z, geometry.beta,
                            sb, cb, y=_general_y(geometry))
    if geometry.timing is not None:  # dS's place holds the timing bias dt (section 12)
        rows[:, 7] = np.einsum("ij,ij->i", normal, geometry.timing)
    return rows


def _general_y(geometry: LaserGeometry) -> np.ndarray | None:
    """A general scanner's ``y`` (section 12's columns), or None (section 10's)."""
    return geometry.y if geometry.scanner is ScannerKind.GENERAL else None


Trig = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]


def point_offsets(
    delta: np.ndarray, x: np.ndarray, z: np.ndarray, kappa: np.ndarray, beta: np.ndarray,
    *, trig: Trig | None = None,
) -> np.ndarray:
    """``A @ delta`` for each point: the displacement the biases cause, map frame, metres.

    Parameters
    ----------
    trig : (cos kappa, sin kappa, sin beta, cos beta), keyword-only, optional
        Known already
        (:meth:`~lidarcal_ros.core.georeferencing.local_trajectory.LaserGeometry.trig`); computed
        from ``kappa`` and ``beta`` otherwise.

    Returns
    -------
    (n, 3) float64
    """
    return _offsets(delta, x, z, kappa, beta, trig, np.empty((0, 3)))


def _offsets(delta: np.ndarray, x: np.ndarray, z: np.ndarray, kappa: np.ndarray,
             beta: np.ndarray, trig: Trig | None, base: np.ndarray,
             rotation: np.ndarray | None = None, y: np.ndarray = _NO_COLUMN) -> np.ndarray:
    """:func:`point_offsets`, or ``base - `` them (one pass:
    :func:`~lidarcal_ros.core.georeferencing.correction_kernels.bias_offsets`).

    Body frame: the displacement to the right is ``dX + z dphi - sin(beta) dr + z beta dS``,
    forward ``dY - z domega + x dkappa``, up ``dZ - x dphi - cos(beta) dr - x beta dS``;
    rotated into the map frame by the heading kappa (level) or ``rotation`` (rigorous); a
    general scanner's ``y`` (rigorous) adds section 12's terms.
    """
    if trig is None:
        trig = (np.cos(kappa), np.sin(kappa), np.sin(beta), np.cos(beta))
    c, s, sb, cb = (np.asarray(a, dtype=np.float64) for a in trig)
    rot = _NO_ROTATION if rotation is None else np.ascontiguousarray(rotation,
                                                                     dtype=np.float64)
    return bias_offsets(np.asarray(delta, dtype=np.float64),
                        np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64),
                        np.asarray(z, dtype=np.float64),
                        np.asarray(beta, dtype=np.float64), c, s, sb, cb, base, rot)


def geometry_offsets(delta: np.ndarray, geometry: LaserGeometry) -> np.ndarray:
    """``A @ delta`` (n, 3, map frame, m) of each point of ``geometry``, either model (with
    the timing bias where ``geometry.timing`` is given)."""
    d, moved = _split_timing(delta, geometry)
    out = _offsets(d, geometry.x, geometry.z, geometry.kappa, geometry.beta,
                   geometry.trig(), np.empty((0, 3)), geometry.rotation, geometry.general_y)
    return out if moved is None else out + moved


def _split_timing(delta: np.ndarray, geometry: LaserGeometry
                  ) -> tuple[np.ndarray, np.ndarray | None]:
    """``delta`` without the timing bias, and what the timing bias moves each point (``dt``
    times the timing column, (n, 3) m): the eighth bias where ``geometry`` carries a timing
    column (docs/method.md section 12), else ``(delta, None)``."""
    d = np.asarray(delta, dtype=np.float64)
    if geometry.timing is None or not d[7]:
        return d, None
    rest = d.copy()
    rest[7] = 0.0
    return rest, d[7] * geometry.timing


def correct_geometry(xyz: np.ndarray, delta: np.ndarray, geometry: LaserGeometry
                     ) -> np.ndarray:
    """Eq. [13] in either model: ``X_corrected = X_biased - A @ delta_hat`` (n, 3, m)."""
    xyz = np.asarray(xyz, dtype=np.float64)
    if xyz.shape != (np.shape(geometry.x)[0], 3):
        raise ValueError(f"xyz of shape {xyz.shape} for {np.shape(geometry.x)[0]} points")
    d, moved = _split_timing(delta, geometry)
    if moved is not None:
        xyz = xyz - moved
    return _offsets(d, geometry.x, geometry.z, geometry.kappa, geometry.beta,
                    geometry.trig(), xyz, geometry.rotation, geometry.general_y)


def correct_points(
    xyz: np.ndarray,
    delta: np.ndarray,
    x: np.ndarray,
    z: np.ndarray,
    kappa: np.ndarray,
    beta: np.ndarray,
    *,
    trig: Trig | None = None,
) -> np.ndarray:
    """docs/method.md eq. [13]: ``X_corrected = X_biased - A @ delta_hat``.

    Parameters
    ----------
    xyz : (n, 3) float64
        Biased points, map frame, metres.
    delta : (8,) float64
        Estimated biases, SI units.
    trig : keyword-only, optional
        As in :func:`point_offsets`.

    Returns
    -------
    (n, 3) float64
        New array of corrected points.
    """
    xyz = np.asarray(xyz, dtype=np.float64)
    if xyz.shape != (np.shape(x)[0], 3):
        raise ValueError(f"xyz of shape {xyz.shape} for {np.shape(x)[0]} points")
    return _offsets(delta, x, z, kappa, beta, trig, xyz)


def boresight_matrix(domega: float, dphi: float, dkappa: float) -> np.ndarray:
    """Exact boresight rotation ``Rz(dkappa) Ry(dphi) Rx(domega)`` (body frame).

    Its small-angle form is docs/method.md's ``R_B = I + skew(domega, dphi, dkappa)``; this order is
    the one that reproduces the ``exact_offset`` of the shared test vectors.
    """
    cw, sw = np.cos(domega), np.sin(domega)
    cp, sp = np.cos(dphi), np.sin(dphi)
    ck, sk = np.cos(dkappa), np.sin(dkappa)
    rx = np.array([[1.0, 0.0, 0.0], [0.0, cw, -sw], [0.0, sw, cw]])
    ry = np.array([[cp, 0.0, sp], [0.0, 1.0, 0.0], [-sp, 0.0, cp]])
    rz = np.array([[ck, -sk, 0.0], [sk, ck, 0.0], [0.0, 0.0, 1.0]])
    return rz @ ry @ rx


def correct_points_exact(
    xyz: np.ndarray, frame: LaserGeometry, delta: np.ndarray
) -> np.ndarray:
    """Remove the biases exactly: invert the biased georeferencing of docs/method.md eq. [1]-[2]
    (section 10's form in the rigorous model).

    The delivered point is ``X_b = X_o + R d + R R_B rho_b`` with the recorded range and
    mirror angle inside ``rho_b = -r [sin beta, 0, cos beta]``, ``R`` the body frame
    (``R_kappa`` level, ``R_ins`` rigorous); the system used the biased (nominal) values
    ``d = (dX, dY, dZ)``, ``R_B(domega, dphi, dkappa)``, range offset ``dr`` and mirror scale
    ``1 + dS``. Undoing them: ``rho_b = R_B^T (R^T (X_b - X_o) - d)``,
    ``r_true = |rho_b| - dr``, ``theta = beta / (1 + dS)``, and the true point is
    ``X_o + R (-r_true) [sin theta, 0, cos theta]``, keeping the (small) along-track
    component of ``rho_b``. A general scanner's (``frame.scanner``; section 12) laser vector
    is any direction: ``rho_b = R_B^T R^T (X_b - X_o)``, the true point ``X_o + R (rho_b (1 -
    dr / |rho_b|) - d)``, no ``dS``.

    Agrees with eq. [13] to second order in the biases; used while iterating so that large
    biases (150 arcsec, 0.2 m) leave no linearisation error.

    Parameters
    ----------
    xyz : (n, 3) float64
        Delivered points, map frame, metres.
    frame : LaserGeometry
        The firing positions and body frames of the points (their geometry as delivered).
    delta : (8,) float64
        Biases, SI.
    """
    return _exact(xyz, frame, delta, with_geometry=False)[0]


def exact_correction(
    xyz: np.ndarray, frame: LaserGeometry, delta: np.ndarray
) -> tuple[np.ndarray, np.ndarray, LaserGeometry]:
    """:func:`correct_points_exact` and the laser geometry of the corrected points seen from
    the same firing positions and body frames
    (:func:`~lidarcal_ros.core.georeferencing.laser_geometry.geometry_at`, with its sines and
    cosines of ``beta``), in one compiled pass
    (:func:`~lidarcal_ros.core.georeferencing.bias_model_kernels.exact_correction_and_geometry`).

    Returns
    -------
    corrected : (n, 3) float64
        The points without the biases, map frame, m.
    shift : (n, 3) float64
        ``xyz - corrected``, m.
    geometry : LaserGeometry
        Of the corrected points (``kappa``, ``origin`` and ``rotation`` shared with
        ``frame``).
    """
    corrected, shift, geometry = _exact(xyz, frame, delta, with_geometry=True)
    assert geometry is not None
    return corrected, shift, geometry


def corrected_geometry(corrected: np.ndarray, frame: LaserGeometry,
                       index: np.ndarray | None) -> LaserGeometry:
    """The geometry :func:`exact_correction` gives the points ``index`` of ``corrected``
    (from :func:`correct_points_exact` of the same ``frame``), the same bits, without computing it
    for the others: ``geometry.take(index)``; ``index`` None: every point, ``frame``'s own
    arrays shared (no copy of them)."""
    every = index is None
    index = np.arange(corrected.shape[0]) if index is None else \
        np.ascontiguousarray(index, dtype=np.int64)
    k = index.shape[0]
    rigorous = frame.rotation is not None
    c, s = frame.cos_kappa, frame.sin_kappa
    if c is None or s is None:
        c, s, _, _ = frame.trig()
    x, z, beta, sb, cb = (np.empty(k) for _ in range(5))
    y = np.empty(k) if rigorous else _NO_COLUMN
    calibration_kernels.corrected_geometry(
        np.ascontiguousarray(corrected, dtype=np.float64),
        np.ascontiguousarray(frame.origin, dtype=np.float64),
        np.ascontiguousarray(c, dtype=np.float64), np.ascontiguousarray(s, dtype=np.float64),
        _NO_ROTATION if frame.rotation is None else np.ascontiguousarray(frame.rotation),
        index, x, y, z, beta, sb, cb)
    part = frame if every else frame.take(index)
    return LaserGeometry(x=x, z=z, kappa=part.kappa, beta=beta, origin=part.origin,
                         cos_kappa=c if every else c[index],
                         sin_kappa=s if every else s[index], sin_beta=sb, cos_beta=cb,
                         heading_from=frame.heading_from, crab_deg=frame.crab_deg,
                         rotation=part.rotation, y=y if rigorous else None,
                         model=frame.model, scanner=frame.scanner, timing=part.timing)


def _exact(xyz: np.ndarray, frame: LaserGeometry, delta: np.ndarray, *, with_geometry: bool
           ) -> tuple[np.ndarray, np.ndarray, LaserGeometry | None]:
    """:func:`exact_correction`, its shift and geometry only ``with_geometry`` (else empty
    and None: 24 and 40-48 bytes a point not made)."""
    xyz = np.ascontiguousarray(xyz, dtype=np.float64)
    n = xyz.shape[0]
    if xyz.shape != (frame.origin.shape[0], 3):
        raise ValueError(f"xyz of shape {xyz.shape} for {frame.origin.shape[0]} points")
    d, moved = _split_timing(delta, frame)
    c, s = frame.cos_kappa, frame.sin_kappa
    if c is None or s is None:
        c, s, _, _ = frame.trig()
    rigorous = frame.rotation is not None
    general = frame.scanner is ScannerKind.GENERAL
    if general and not rigorous:
        raise ValueError("a general scanner's laser vectors need the rigorous model")
    corrected = np.empty((n, 3))
    shift = np.empty((n if with_geometry else 0, 3))
    m = n if with_geometry else 0
    x, z, beta, sb, cb = (np.empty(m) for _ in range(5))
    y = np.empty(m) if rigorous and with_geometry else _NO_COLUMN
    calibration_kernels.exact_correction_and_geometry(
        xyz, np.ascontiguousarray(frame.origin, dtype=np.float64),
        np.ascontiguousarray(c, dtype=np.float64), np.ascontiguousarray(s, dtype=np.float64),
        _NO_ROTATION if frame.rotation is None else np.ascontiguousarray(frame.rotation),
        d, boresight_matrix(d[3], d[4], d[5]), corrected, shift, x, y, z, beta, sb, cb, general,
        with_geometry)
    if moved is not None:
        # the pose looked up dt late moved the point by dt times its rate (section 12): the
        # mounting corrected in that pose, then the point moved back; the laser vector (the
        # geometry) is the mounting's, whatever the time
        corrected -= moved
        if with_geometry:
            shift += moved
    if not with_geometry:
        return corrected, shift, None
    geometry = LaserGeometry(x=x, z=z, kappa=frame.kappa, beta=beta, origin=frame.origin,
                             cos_kappa=c, sin_kappa=s, sin_beta=sb, cos_beta=cb,
                             heading_from=frame.heading_from, crab_deg=frame.crab_deg,
                             rotation=frame.rotation, y=y if rigorous else None,
                             model=frame.model, scanner=frame.scanner, timing=frame.timing)
    return corrected, shift, geometry


def add_geometry_normal_rows(out: np.ndarray, normal: np.ndarray, geometry: LaserGeometry,
                             index: np.ndarray, weight: np.ndarray | None = None) -> None:
    """``out += weight * n^T A`` of the points ``index`` of ``geometry`` (either model) and
    their patch normals ``normal`` (k, 3, map frame): :func:`geometry_normal_rows` of
    ``geometry.take(index)`` without the copy, in one compiled pass
    (:func:`~lidarcal_ros.core.georeferencing.bias_model_kernels.add_normal_rows`)."""
    c, s, sb, cb = geometry.trig()
    calibration_kernels.add_normal_rows(
        np.ascontiguousarray(normal, dtype=np.float64),
        np.ascontiguousarray(index, dtype=np.int64),
        _NO_COLUMN if weight is None else np.ascontiguousarray(weight, dtype=np.float64),
        geometry.x, geometry.general_y, geometry.z, geometry.beta, sb, cb, c, s,
        _NO_ROTATION if geometry.rotation is None else geometry.rotation, out)
    if geometry.timing is not None:  # dS's place holds the timing bias dt (section 12)
        rate = np.einsum("ij,ij->i", normal, geometry.timing[index])
        out[:, 7] += rate if weight is None else weight * rate


__all__ = [
    "Trig", "add_geometry_normal_rows", "body_columns", "body_normal_rows", "boresight_matrix",
    "correct_geometry", "correct_points", "correct_points_exact", "corrected_geometry",
    "design_matrix", "exact_correction", "geometry_design_matrix",
    "geometry_normal_rows", "geometry_offsets", "normal_design_rows", "point_offsets",
]
