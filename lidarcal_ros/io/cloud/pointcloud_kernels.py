"""Compiled scans of the fields of a structured point cloud, each in one pass over the rows."""

from __future__ import annotations

import math

import numpy as np

from lidarcal_ros.core.jit import compiled, inlined


@compiled
def all_finite_xyz(x: np.ndarray, y: np.ndarray, z: np.ndarray) -> bool:
    """``np.isfinite(x).all() and np.isfinite(y).all() and np.isfinite(z).all()`` in one pass
    over the rows (the fields of a structured cloud, strided), stopping at the first
    non-finite value."""
    for i in range(x.shape[0]):
        if not (math.isfinite(x[i]) and math.isfinite(y[i]) and math.isfinite(z[i])):
            return False
    return True


@inlined
def _low_high(v: float, lo: float, hi: float) -> tuple[float, float]:
    """``lo, hi`` widened to ``v`` (a NaN ``v`` leaves them), without a branch."""
    return (v if v < lo else lo), (v if v > hi else hi)


@compiled
def finite_range(values: np.ndarray) -> tuple[float, float]:
    """``(np.fmin.reduce(values), np.fmax.reduce(values))`` in one pass (a field of a
    structured cloud, strided): the least and greatest values ignoring NaN, ``(nan, nan)``
    when all are NaN or there are none. Four running extremes, not one: one is a chain of
    dependent comparisons a value long, four overlap (the corrector reads the times of
    every cloud it receives this way)."""
    n = values.shape[0]
    lo0 = lo1 = lo2 = lo3 = math.inf
    hi0 = hi1 = hi2 = hi3 = -math.inf
    body = n - n % 4
    for i in range(0, body, 4):
        lo0, hi0 = _low_high(values[i], lo0, hi0)
        lo1, hi1 = _low_high(values[i + 1], lo1, hi1)
        lo2, hi2 = _low_high(values[i + 2], lo2, hi2)
        lo3, hi3 = _low_high(values[i + 3], lo3, hi3)
    for i in range(body, n):
        lo0, hi0 = _low_high(values[i], lo0, hi0)
    lo = min(min(lo0, lo1), min(lo2, lo3))
    hi = max(max(hi0, hi1), max(hi2, hi3))
    if not lo <= hi:  # nothing but NaN (an infinite value counts: inf <= inf)
        return math.nan, math.nan
    return float(lo), float(hi)


@compiled
def gather_columns(x: np.ndarray, y: np.ndarray, z: np.ndarray, t: np.ndarray,
                   intensity: np.ndarray, strip_id: np.ndarray, xyz_out: np.ndarray,
                   t_out: np.ndarray, intensity_out: np.ndarray, strip_id_out: np.ndarray
                   ) -> tuple[float, float, int]:
    """:func:`gather_xyz` plus ``t_out[:] = t``, ``intensity_out[:] = intensity`` and
    ``strip_id_out[:] = strip_id`` (each converted to the output's type), in one pass over
    the rows of a structured cloud instead of one per field. An empty ``intensity`` or
    ``strip_id`` (the cloud has none) is skipped.

    Returns
    -------
    t_lo, t_hi : float
        :func:`finite_range` of ``t``, found in the same pass.
    non_finite : int
        Rows with a non-finite ``x``, ``y``, ``z`` or ``t`` (none: the checks for them can
        be skipped).
    """
    has_intensity = intensity.shape[0] == x.shape[0]
    has_strip_id = strip_id.shape[0] == x.shape[0]
    lo = math.inf
    hi = -math.inf
    seen = False
    non_finite = 0
    for i in range(x.shape[0]):
        xi, yi, zi, ti = x[i], y[i], z[i], t[i]
        xyz_out[i, 0] = xi
        xyz_out[i, 1] = yi
        xyz_out[i, 2] = zi
        t_out[i] = ti
        if has_intensity:
            intensity_out[i] = intensity[i]
        if has_strip_id:
            strip_id_out[i] = strip_id[i]
        if ti == ti:  # (not NaN)
            seen = True
            lo = min(lo, ti)
            hi = max(hi, ti)
        if not (math.isfinite(xi) and math.isfinite(yi) and math.isfinite(zi)
                and math.isfinite(ti)):
            non_finite += 1
    if not seen:
        return math.nan, math.nan, non_finite
    return float(lo), float(hi), non_finite


@compiled
def gather_xyz(x: np.ndarray, y: np.ndarray, z: np.ndarray, out: np.ndarray) -> None:
    """``out[:, 0], out[:, 1], out[:, 2] = x, y, z`` (float64; FLOAT32 fields widened
    exactly) in one pass over the rows of a structured cloud."""
    for i in range(x.shape[0]):
        out[i, 0] = x[i]
        out[i, 1] = y[i]
        out[i, 2] = z[i]


__all__ = ["all_finite_xyz", "finite_range", "gather_columns", "gather_xyz"]
