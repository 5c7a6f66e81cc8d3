"""Compiled per-point loops of the correction: biases removed, beam quantities, reflectance, rows.

Eq. [13] of docs/method.md is defined here once, also for
:func:`lidarcal_ros.core.georeferencing.bias_model.point_offsets`. Why in blocks and without
branches: docs/correction.md, "Per point".
"""

from __future__ import annotations

import math

import numpy as np

from lidarcal_ros.core.flags import (
    FLAG_GRAZING,
    FLAG_NO_INTENSITY,
    FLAG_NO_NORMAL,
    FLAG_NOT_CORRECTED,
    FLAG_ROUGH,
    FLAG_VOLUME,
)
from lidarcal_ros.core.georeferencing.attitude import pose_on_segment, segment_spline
from lidarcal_ros.core.jit import compiled, inlined


@inlined
def _body_offset(d: tuple[float, float, float, float, float, float, float, float], x: float,
                 z: float, beta: float, sin_beta: float, cos_beta: float
                 ) -> tuple[float, float, float]:
    """``C @ delta`` of one point: the displacement the biases cause in the body frame
    (right, forward, up), m; the columns ``C`` of docs/method.md section 10, as
    :func:`lidarcal_ros.core.georeferencing.bias_model.point_offsets` documents."""
    right = d[0] + z * d[4] - sin_beta * d[6] + z * beta * d[7]
    fwd = d[1] - z * d[3] + x * d[5]
    up = d[2] - x * d[4] - cos_beta * d[6] - x * beta * d[7]
    return right, fwd, up


@inlined
def _general_body_offset(d: tuple[float, float, float, float, float, float, float, float],
                         x: float, y: float, z: float, beta: float, sin_beta: float,
                         cos_beta: float, along: float) -> tuple[float, float, float]:
    """:func:`_body_offset` with a general laser vector's ``y`` (docs/method.md section 12:
    ``domega [0, -z, y]``, ``dkappa [-y, x, 0]``, ``dr`` along ``rho``, ``along = y / |rho|``),
    its terms added last so that ``y = 0`` gives :func:`_body_offset` to the bit."""
    right, fwd, up = _body_offset(d, x, z, beta, sin_beta, cos_beta)
    return right - y * d[5], fwd + along * d[6], up + y * d[3]


@inlined
def _bias_offset(d: tuple[float, float, float, float, float, float, float, float], x: float,
                 z: float, beta: float, sin_beta: float, cos_beta: float, c: float, s: float
                 ) -> tuple[float, float, float]:
    """``A @ delta`` of one point (docs/method.md eq. [8], map frame, m): the body-frame
    displacement rotated by the heading ``(c, s)``."""
    right, fwd, up = _body_offset(d, x, z, beta, sin_beta, cos_beta)
    return c * right - s * fwd, s * right + c * fwd, up


@compiled
def bias_offsets(delta: np.ndarray, x: np.ndarray, y: np.ndarray, z: np.ndarray,
                 beta: np.ndarray, cos_kappa: np.ndarray, sin_kappa: np.ndarray,
                 sin_beta: np.ndarray, cos_beta: np.ndarray, base: np.ndarray,
                 rotation: np.ndarray) -> np.ndarray:
    """``A @ delta`` of each point (map frame, m), or ``base - A @ delta`` (eq. [13]) when
    ``base`` has a row per point (an empty ``base``: the offsets).

    The body-frame displacement (right, forward, up), rotated by kappa (docs/method.md eq. [8]),
    or by each point's ``rotation`` (n, 3, 3; section 10) when it has a row per point, as
    :func:`lidarcal_ros.core.georeferencing.bias_model.point_offsets` documents. ``y`` with a
    row per point (rigorous): a general scanner's forward coordinate (section 12's columns,
    :func:`_general_body_offset`); empty: 0.
    """
    n = x.shape[0]
    out = np.empty((n, 3))
    d = (delta[0], delta[1], delta[2], delta[3], delta[4], delta[5], delta[6], delta[7])
    corrected = base.shape[0] == n and n > 0
    rigorous = rotation.shape[0] == n and n > 0
    general = rigorous and y.shape[0] == n
    for i in range(n):
        if rigorous:
            if general:
                yi = y[i]
                along = yi / math.sqrt(x[i] * x[i] + yi * yi + z[i] * z[i])
                right, fwd, up = _general_body_offset(d, x[i], yi, z[i], beta[i],
                                                      sin_beta[i], cos_beta[i], along)
            else:
                right, fwd, up = _body_offset(d, x[i], z[i], beta[i], sin_beta[i],
                                              cos_beta[i])
            r = rotation[i]
            ox = r[0, 0] * right + r[0, 1] * fwd + r[0, 2] * up
            oy = r[1, 0] * right + r[1, 1] * fwd + r[1, 2] * up
            oz = r[2, 0] * right + r[2, 1] * fwd + r[2, 2] * up
        else:
            ox, oy, oz = _bias_offset(d, x[i], z[i], beta[i], sin_beta[i], cos_beta[i],
                                      cos_kappa[i], sin_kappa[i])
        if corrected:
            out[i, 0] = base[i, 0] - ox
            out[i, 1] = base[i, 1] - oy
            out[i, 2] = base[i, 2] - oz
        else:
            out[i, 0], out[i, 1], out[i, 2] = ox, oy, oz
    return out


#: ``(atan(x) - x) / x^3`` as a polynomial in ``x^2`` on ``0 <= x <= tan(pi/8)`` (lowest
#: order first): a Chebyshev least-squares fit to numpy's arctan on that interval, degree 5;
#: :func:`atan_poly` is within 4e-11 rad of it everywhere (test_kernels).
_ATAN_COEFFS = (-0.33333333309346724, 0.19999982577414943, -0.14284358755605978,
                0.11074431763228341, -0.08643818118436813, 0.050907470841734664)

#: ``(asin(x) - x) / x^3`` as a polynomial in ``x^2`` on ``0 <= x <= 1/2``, fitted alike
#: (degree 6); :func:`acos_poly` is within 1e-10 rad of numpy's arccos on [0, 1].
_ASIN_COEFFS = (0.1666666667454038, 0.07499994167680879, 0.04464702851563003,
                0.03027839999860813, 0.02354782561152891, 0.010783899233701058,
                0.030712755360604242)

_TAN_PI_8 = math.tan(math.pi / 8.0)
_TAN_3PI_8 = math.tan(3.0 * math.pi / 8.0)


@inlined
def atan_poly(q: float) -> float:
    """``atan(q)`` (rad) to 4e-11 from a polynomial after the classic range reduction
    (``atan(a) = pi/4 + atan((a - 1) / (a + 1)) = pi/2 + atan(-1 / a)``): a few
    multiply-adds that vectorise, where libm's scalar arctangent is a call per point, the
    dearest step of :func:`correct_returns`. NaN gives NaN."""
    a = abs(q)
    base = 0.0
    x = a
    if a > _TAN_3PI_8:
        base, x = 0.5 * math.pi, -1.0 / a
    elif a > _TAN_PI_8:
        base, x = 0.25 * math.pi, (a - 1.0) / (a + 1.0)
    z = x * x
    c = _ATAN_COEFFS
    poly = c[0] + z * (c[1] + z * (c[2] + z * (c[3] + z * (c[4] + z * c[5]))))
    return math.copysign(base + (x + x * z * poly), q)


@inlined
def _asin_half(x: float) -> float:
    """``asin(x)`` for ``0 <= x <= 1/2`` (:data:`_ASIN_COEFFS`)."""
    z = x * x
    c = _ASIN_COEFFS
    poly = c[0] + z * (c[1] + z * (c[2] + z * (c[3] + z * (c[4] + z * (c[5] + z * c[6])))))
    return x + x * z * poly


@inlined
def acos_poly(c: float) -> float:
    """``acos(c)`` (rad) for ``0 <= c <= 1`` to 1e-10 (``acos c = 2 asin(sqrt((1 - c) / 2))``
    above 1/2, ``pi/2 - asin c`` below; :func:`atan_poly` says why). NaN gives NaN."""
    if c > 0.5:
        return 2.0 * _asin_half(math.sqrt((1.0 - c) * 0.5))
    return 0.5 * math.pi - _asin_half(c)


#: 8-byte words of a row of the points lidarcal writes
#: (:func:`~lidarcal_ros.io.cloud.pointcloud.make_point_dtype`: 40 bytes) and of their corrected
#: rows (64 bytes): for these :func:`correct_returns` copies a row with counts known when it
#: is compiled (unrolled, a tenth of its time less than a loop over counts read at run time).
_USUAL_IN_WORDS = 5
_USUAL_OUT_WORDS = 8

#: Points per block of :func:`correct_returns`: its columns (some 40 values a point) stay
#: in the first caches between the block's loops.
_RETURNS_BLOCK = 256


@inlined
def _return_beam(px: float, py: float, pz: float, ox: float, oy: float, oz: float,
                 r00: float, r01: float, r02: float, r10: float, r11: float, r12: float,
                 r20: float, r21: float, r22: float,
                 d: tuple[float, float, float, float, float, float, float, float],
                 n0: float, n1: float, n2: float, rigorous: bool
                 ) -> tuple[float, float, float, float, float, float, float]:
    """One return from its firing point ``o`` and body frame ``R`` (row by row): ``beta``
    (NaN at or above the firing point), the corrected point (eq. [13]), the range, the scan
    angle and the incidence cosine (NaN without a normal) as :func:`correct_returns`
    documents; no branch but selects, so that a loop over it runs in vector registers."""
    dx, dy, dz = px - ox, py - oy, pz - oz
    x = r00 * dx + r10 * dy + r20 * dz
    z = r02 * dx + r12 * dy + r22 * dz
    q = x / z
    b = atan_poly(q) if z < 0.0 else np.nan
    r2 = x * x + z * z
    if rigorous:  # section 10's r = |rho_hat|; section 4 recovers no along-track part
        y = r01 * dx + r11 * dy + r21 * dz
        r2 += y * y
    inv_r = 1.0 / math.sqrt(r2)
    right, fwd, up = _body_offset(d, x, z, b, -x * inv_r, -z * inv_r)
    cx = px - (r00 * right + r01 * fwd + r02 * up)  # eq. [13]
    cy = py - (r10 * right + r11 * fwd + r12 * up)
    cz = pz - (r20 * right + r21 * fwd + r22 * up)
    # The beam from the firing point to the corrected return.
    rx, ry, rz = cx - ox, cy - oy, cz - oz
    r = math.sqrt(rx * rx + ry * ry + rz * rz)
    # the tangent's change, ``d`` in correct_returns' docstring
    dtan = (r00 * rx + r10 * ry + r20 * rz) / (r02 * rx + r12 * ry + r22 * rz) - q
    g = 1.0 / (1.0 + q * q)
    scan = b + dtan * g - q * dtan * dtan * g * g
    cos_t = abs((n0 * rx + n1 * ry + n2 * rz) * (1.0 / r))
    return b, cx, cy, cz, r, scan, 1.0 if cos_t > 1.0 else cos_t  # (NaN stays NaN)


@compiled
def correct_returns(t: np.ndarray, xyz: np.ndarray, ok: np.ndarray, window: np.ndarray,
                    rigorous: bool,
                    lines: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray],
                    poses: tuple[np.ndarray, np.ndarray, np.ndarray],
                    delta: np.ndarray, normals: np.ndarray, rough: np.ndarray,
                    volume: np.ndarray, intensity: np.ndarray,
                    radiometry: tuple[np.float32, np.float32, np.float32, np.float32],
                    out: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                               np.ndarray],
                    rows: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                                np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                                np.ndarray]) -> None:
    """Correct each return and derive its beam quantities and reflectance, in one compiled
    call (:func:`lidarcal_ros.pipeline.correction.apply.correct_columns`; docs/correction.md,
    "Per point", gives the steps): the firing position and body frame of each point (a window's
    line and heading, docs/method.md section 4, or the INS attitude interpolated between samples,
    section 10, :func:`lidarcal_ros.core.georeferencing.attitude.interpolated_frames`),
    ``beta = atan(x / z)``, eq. [13] as :func:`bias_offsets`, then range, scan angle, incidence and
    :meth:`lidarcal_ros.core.radiometry.RadiometricModel.reflectance` (in float32, operation
    for operation) and the ``correction_flags`` bits (:mod:`lidarcal_ros.core.flags`).

    The arithmetic costs more than the memory traffic, and the libm arctangent and arc
    cosine of each point more than the rest of it. So ``beta`` and the incidence come from
    :func:`atan_poly` and :func:`acos_poly` (within 1e-10 rad; the incidence from the float64
    cosine, where a float32 one would lose up to 3e-4 rad near normal incidence), and the
    scan angle ``atan(x_c / z_c)`` of the corrected return from ``beta`` of the delivered
    one: their tangents differ by ``d``, of the order of the biases (below 1e-3), and
    ``atan(q + d) = atan(q) + d / (1 + q^2) - q d^2 / (1 + q^2)^2`` up to a ``d^3`` term
    below 1e-9 rad. The points go in blocks of :data:`_RETURNS_BLOCK`: each point's frame
    is looked up (level) or interpolated (rigorous) into columns of the block, then the
    arithmetic of the whole block runs without a branch, several points at a time in the
    processor's vector registers (:func:`_return_beam`), and the radiometry after it; the
    operations, and so the results, are those of a point at a time.

    Parameters
    ----------
    t, xyz : (n,), (n, 3) float64
        Firing times (s) and delivered points (map frame, m).
    ok : (n,) bool
        Points the trajectory serves (covered, finite, below it); the others, and any whose
        frame puts it at or above the firing point, are flagged not corrected.
    window : (m,) int64
        For each ``ok`` point in order (``m = ok.sum()``): its window (level) or the sample
        starting its trajectory segment (rigorous).
    rigorous : bool
        Which model: ``poses`` (section 10) or ``lines`` (section 4) give the frames.
    lines : (t_mean, p_mean, velocity, cos_w, sin_w)
        The windows' lines
        (:class:`~lidarcal_ros.core.georeferencing.local_trajectory.WindowLines`): (k,), (k, 3), (k,
        3), (k,), (k,) float64.
    poses : (traj_t, traj_xyz, traj_q)
        The trajectory's samples: (s,), (s, 3), (s, 4) float64 (unit quaternions in one
        hemisphere, :class:`~lidarcal_ros.core.mission.Trajectory`).
    delta : (8,) float64
        Biases to remove (docs/method.md order, SI).
    normals : (n, 3) float64
        Unit surface normals, map frame (NaN: none).
    rough : (n,) bool, or empty
        Uncertain normals (none when empty).
    volume : (n,) bool, or empty
        Volume returns (none when empty;
        :func:`~lidarcal_ros.core.radiometry.volume_returns`): no incidence correction
        (``cos`` 1, incidence NaN, no ``FLAG_NO_NORMAL``), flagged ``FLAG_VOLUME``.
    intensity : (n,) float32, or empty
        Recorded intensity (the cloud has none when empty).
    radiometry : (c_min, c_doubt, scale, two_alpha) float32
        :meth:`~lidarcal_ros.core.radiometry.RadiometricModel.kernel_constants`.
    out : (out_xyz, range_m, incidence, scan_angle, reflectance, flags)
        Written: corrected points (n, 3) float64 (the delivered ones where not corrected),
        m; range, incidence, scan angle, reflectance (n,) float32 (m, rad, rad, the
        reflectance's unit; NaN where unknown); the ``correction_flags`` bits (n,) uint8.
        Not written with ``rows`` (may be empty then).
    rows : (out_words, in_words, x, y, z, reflectance, range, incidence, scan_angle, flags,
        tally), or ``out_words`` empty
        The corrected cloud's rows to write instead of ``out``, as
        :func:`fill_corrected_rows` writes them from ``out`` (its arguments but for the
        columns): each block of points goes from the first-level cache into its rows, not
        through ``out`` and a second pass.
    """
    out_xyz, range_m, incidence, scan_angle, reflectance, flags = out
    (out_words, in_words, x_row, y_row, z_row, refl_row, range_row, inc_row, scan_row,
     flags_row, tally) = rows
    in_rows = out_words.shape[0] == t.shape[0]
    k_words, m_words = in_words.shape[1], out_words.shape[1]
    usual_rows = k_words == _USUAL_IN_WORDS and m_words == _USUAL_OUT_WORDS
    # The tally in four interleaved sets of counts (one counter incremented point after point
    # would make each increment wait for the one before); added up at the end.
    counts = np.zeros((4, 257), dtype=np.int64)
    c_min, c_doubt, scale, two_alpha = radiometry
    traj_t, traj_xyz, traj_q = poses
    t_mean, p_mean, velocity, cos_w, sin_w = lines
    n = t.shape[0]
    nan32 = np.float32(np.nan)
    has_rough = rough.shape[0] == n
    has_volume = volume.shape[0] == n
    has_intensity = intensity.shape[0] == n
    no_intensity = np.uint8(0 if has_intensity else FLAG_NO_INTENSITY)
    d = (delta[0], delta[1], delta[2], delta[3], delta[4], delta[5], delta[6], delta[7])
    size = _RETURNS_BLOCK
    # The block's columns: the point, its normal, firing point and frame (level: the
    # heading's cosine and sine in rows 9-10; rigorous: R row by row in rows 9-17), whether
    # it is served, its roughness and intensity; then what the beam gives.
    col = np.empty((18, size))
    served = np.empty(size, dtype=np.bool_)
    corrected = np.empty(size, dtype=np.bool_)
    flag_col = np.empty(size, dtype=np.uint8)
    rough_col = np.zeros(size, dtype=np.bool_)
    volume_col = np.zeros(size, dtype=np.bool_)
    level_col = np.full(size, np.nan, dtype=np.float32)
    beam = np.empty((8, size))
    gain = np.empty(size, dtype=np.float32)
    current = -1
    spline = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)
    j = 0
    # Every point served and the level model (the usual case): a point's window is its own
    # index, and the windows come in runs of thousands of points (a window changes with each
    # trajectory sample), over which the line's parameters are constants.
    runs = not rigorous and window.shape[0] == n
    for a in range(0, n, size):
        m = min(size, n - a)
        # 1. Each point's frame (the window's line, or the attitude's cubic between the
        #    samples around it: points come in time order, a segment serves thousands).
        pts, nrm = xyz[a:a + m], normals[a:a + m]
        for k in range(m):
            col[0, k], col[1, k], col[2, k] = pts[k, 0], pts[k, 1], pts[k, 2]
            col[3, k], col[4, k], col[5, k] = nrm[k, 0], nrm[k, 1], nrm[k, 2]
        if has_rough:
            rgh = rough[a:a + m]
            for k in range(m):
                rough_col[k] = rgh[k]
        if has_volume:
            vol = volume[a:a + m]
            for k in range(m):
                volume_col[k] = vol[k]
        if has_intensity:
            lvl = intensity[a:a + m]
            for k in range(m):
                level_col[k] = lvl[k]
        if runs:
            for k in range(m):
                served[k] = True
            # 2. The beam of every point of the block, run by run (in vector registers).
            k0 = 0
            while k0 < m:
                w = window[a + k0]
                k1 = k0 + 1
                while k1 < m and window[a + k1] == w:
                    k1 += 1
                tm, c, s = t_mean[w], cos_w[w], sin_w[w]
                p0, p1, p2 = p_mean[w, 0], p_mean[w, 1], p_mean[w, 2]
                v0, v1, v2 = velocity[w, 0], velocity[w, 1], velocity[w, 2]
                tt, cr, br = t[a + k0:a + k1], col[:, k0:k1], beam[:, k0:k1]
                for k in range(k1 - k0):
                    dt = tt[k] - tm
                    res = _return_beam(cr[0, k], cr[1, k], cr[2, k], p0 + v0 * dt,
                                       p1 + v1 * dt, p2 + v2 * dt, c, -s, 0.0, s, c, 0.0,
                                       0.0, 0.0, 1.0, d, cr[3, k], cr[4, k], cr[5, k], False)
                    for row in range(7):
                        br[row, k] = res[row]
                    br[7, k] = acos_poly(res[6])
                k0 = k1
        else:
            for k in range(m):
                i = a + k
                served[k] = ok[i]
                if not ok[i]:
                    for row in range(6, 18):
                        col[row, k] = 0.0
                    continue
                w = window[j]
                j += 1
                if rigorous:
                    if w != current:
                        spline = segment_spline(w, traj_t, traj_q)
                        current = w
                    f = pose_on_segment(t[i], w, spline, traj_t, traj_xyz, traj_q)
                    for row in range(12):
                        col[6 + row, k] = f[row]
                else:
                    dt = t[i] - t_mean[w]
                    col[6, k] = p_mean[w, 0] + velocity[w, 0] * dt
                    col[7, k] = p_mean[w, 1] + velocity[w, 1] * dt
                    col[8, k] = p_mean[w, 2] + velocity[w, 2] * dt
                    col[9, k], col[10, k] = cos_w[w], sin_w[w]
            # 2. The beam of every point of the block (in vector registers).
            if rigorous:
                for k in range(m):
                    res = _return_beam(col[0, k], col[1, k], col[2, k], col[6, k],
                                       col[7, k], col[8, k], col[9, k], col[10, k],
                                       col[11, k], col[12, k], col[13, k], col[14, k],
                                       col[15, k], col[16, k], col[17, k], d, col[3, k],
                                       col[4, k], col[5, k], True)
                    for row in range(7):
                        beam[row, k] = res[row]
                    beam[7, k] = acos_poly(res[6])
            else:
                for k in range(m):
                    c, s = col[9, k], col[10, k]
                    res = _return_beam(col[0, k], col[1, k], col[2, k], col[6, k],
                                       col[7, k], col[8, k], c, -s, 0.0, s, c, 0.0, 0.0,
                                       0.0, 1.0, d, col[3, k], col[4, k], col[5, k], False)
                    for row in range(7):
                        beam[row, k] = res[row]
                    beam[7, k] = acos_poly(res[6])
        # 3. The two-way attenuation (libm's exponential: a call per point).
        if has_intensity:
            for k in range(m):
                gain[k] = math.exp(two_alpha * np.float32(beam[4, k]))
        # 4. Reflectance and flags (without a branch, as step 2).
        for k in range(m):
            good = served[k] and not math.isnan(beam[0, k])
            cos_t = beam[6, k]
            r32 = np.float32(beam[4, k])
            fl = no_intensity
            # A volume return takes no incidence correction (cos 1) and has no incidence.
            in_volume = volume_col[k]
            if in_volume:
                fl |= FLAG_VOLUME
                cos_t = 1.0
                beam[7, k] = np.nan
            if math.isnan(cos_t):
                fl |= FLAG_NO_NORMAL
            uncertain = rough_col[k]
            if uncertain:
                fl |= FLAG_ROUGH
            # RadiometricModel.reflectance: the clamped cosine (NaN stays NaN), bounded
            # further where the normal is uncertain, then the radar equation.
            level = level_col[k]
            if has_intensity and not math.isfinite(level):
                fl |= FLAG_NO_INTENSITY
            cos32 = np.float32(cos_t)
            grazing = cos32 < c_min
            if has_intensity and grazing:
                fl |= FLAG_GRAZING
            cos_eff = c_min if grazing else cos32
            if (uncertain or grazing) and cos_eff < c_doubt:
                cos_eff = c_doubt
            g32 = gain[k]
            g32 *= r32
            g32 *= r32
            g32 *= scale
            g32 /= cos_eff
            g32 *= level
            gain[k] = g32 if good and has_intensity else nan32
            flag_col[k] = fl if good else FLAG_NOT_CORRECTED | no_intensity
            corrected[k] = good
        # 5. Written out (the points not corrected keep their coordinates, NaN in the derived
        #    fields): into the cloud's rows, or a field at a time.
        if in_rows:
            for k in range(m):
                i = a + k
                if usual_rows:  # (word counts the compiler knows: the copy unrolled)
                    for word in range(_USUAL_IN_WORDS):
                        out_words[i, word] = in_words[i, word]
                    for word in range(_USUAL_IN_WORDS, _USUAL_OUT_WORDS):
                        out_words[i, word] = 0
                else:
                    for word in range(k_words):
                        out_words[i, word] = in_words[i, word]
                    for word in range(k_words, m_words):
                        out_words[i, word] = 0
                good = corrected[k]
                px = beam[1, k] if good else col[0, k]
                py = beam[2, k] if good else col[1, k]
                pz = beam[3, k] if good else col[2, k]
                bits = flag_col[k]
                counts[k & 3, bits] += 1
                if not (math.isfinite(px) and math.isfinite(py) and math.isfinite(pz)):
                    counts[k & 3, 256] += 1
                x_row[i], y_row[i], z_row[i] = px, py, pz
                refl_row[i] = gain[k]
                range_row[i] = np.float32(beam[4, k]) if good else nan32
                inc_row[i] = np.float32(beam[7, k]) if good else nan32
                scan_row[i] = np.float32(beam[5, k]) if good else nan32
                flags_row[i] = bits
            continue
        for k in range(m):
            good = corrected[k]
            out_xyz[a + k, 0] = beam[1, k] if good else col[0, k]
            out_xyz[a + k, 1] = beam[2, k] if good else col[1, k]
            out_xyz[a + k, 2] = beam[3, k] if good else col[2, k]
        for k in range(m):
            range_m[a + k] = np.float32(beam[4, k]) if corrected[k] else nan32
        for k in range(m):
            scan_angle[a + k] = np.float32(beam[5, k]) if corrected[k] else nan32
        for k in range(m):
            incidence[a + k] = np.float32(beam[7, k]) if corrected[k] else nan32
        for k in range(m):
            reflectance[a + k] = gain[k]
        for k in range(m):
            flags[a + k] = flag_col[k]
    if in_rows:
        for lane in range(4):
            for bits in range(257):
                tally[bits] += counts[lane, bits]


@compiled
def fill_corrected_rows(out_words: np.ndarray, in_words: np.ndarray, x: np.ndarray,
                        y: np.ndarray, z: np.ndarray, xyz: np.ndarray, reflectance: np.ndarray,
                        range_m: np.ndarray, incidence: np.ndarray, scan_angle: np.ndarray,
                        flags: np.ndarray, reflectance_in: np.ndarray, range_in: np.ndarray,
                        incidence_in: np.ndarray, scan_angle_in: np.ndarray,
                        flags_in: np.ndarray, tally: np.ndarray) -> None:
    """Write corrected rows, one row at a time: the input row's words, zeros after them,
    then the corrected coordinates and the added fields (``rows[:, :k] = input rows;
    rows[:, k:] = 0; out[name] = column`` for each field, as numpy does it in nine passes
    over the output); and count, in the same pass, what the cloud's users ask of it
    (how many points are flagged, whether it is dense), which would otherwise take a pass
    each over the written rows.

    Parameters
    ----------
    out_words : (n, m) uint32 or uint64
        The output rows as 4- or 8-byte words (written whole).
    in_words : (n, k) of the same type, k <= m
        The input rows as words.
    x, y, z, reflectance, range_m, incidence, scan_angle, flags : (n,)
        Views of the output's fields (into ``out_words``' memory), written after the words
        of their row.
    xyz : (n, 3) float64
        Corrected coordinates, m.
    reflectance_in, range_in, incidence_in, scan_angle_in, flags_in : (n,)
        The added fields' values.
    tally : (257,) int64
        Added to: ``tally[f]``, the rows whose flags byte is ``f``
        (``np.bincount(flags_in, minlength=256)``); ``tally[256]``, the rows with a
        non-finite corrected coordinate.
    """
    n, m = out_words.shape
    k = in_words.shape[1]
    for i in range(n):
        f = flags_in[i]
        tally[f] += 1
        if not (math.isfinite(xyz[i, 0]) and math.isfinite(xyz[i, 1])
                and math.isfinite(xyz[i, 2])):
            tally[256] += 1
        for j in range(k):
            out_words[i, j] = in_words[i, j]
        for j in range(k, m):
            out_words[i, j] = 0
        x[i] = xyz[i, 0]
        y[i] = xyz[i, 1]
        z[i] = xyz[i, 2]
        reflectance[i] = reflectance_in[i]
        range_m[i] = range_in[i]
        incidence[i] = incidence_in[i]
        scan_angle[i] = scan_angle_in[i]
        flags[i] = f


@compiled
def byte_counts(values: np.ndarray) -> np.ndarray:
    """How many times each byte value occurs: ``np.bincount(values, minlength=256)`` for a
    uint8 array, in one pass and without the interpreter lock (bincount first widens the
    array to 8-byte integers).

    Parameters
    ----------
    values : (n,) uint8

    Returns
    -------
    (256,) int64
    """
    counts = np.zeros(256, dtype=np.int64)
    for i in range(values.shape[0]):
        counts[values[i]] += 1
    return counts


__all__ = ["acos_poly", "atan_poly", "bias_offsets", "byte_counts", "correct_returns",
           "fill_corrected_rows"]
