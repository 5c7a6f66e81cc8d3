"""The point records of a LAS/LAZ chunk in one compiled pass (for the LAS writer).

The same arithmetic as the numpy it replaces; the tests compare the records byte for byte.
"""

from __future__ import annotations

import math

import numpy as np

from lidarcal_ros.core.jit import compiled

#: How the intensity field becomes LAS's 16-bit one (:meth:`LasChunkWriter._intensity16`).
INTENSITY_NONE, INTENSITY_U16, INTENSITY_U8, INTENSITY_FLOAT = 0, 1, 2, 3
_DEGREES = 180.0 / math.pi  # numpy's degrees()


@compiled
def rows_to_write(x: np.ndarray, y: np.ndarray, z: np.ndarray, offsets: np.ndarray,
                  scales: np.ndarray, max_scaled: float) -> tuple[np.ndarray, int, int]:
    """The rows LAS can store: finite ``x, y, z`` within ``max_scaled`` steps of the offsets
    (``|(v - offset) / scale| < max_scaled``); and how many are left out for each reason
    (non-finite, out of range)."""
    n = x.shape[0]
    rows = np.empty(n, np.int64)
    k = non_finite = out_of_range = 0
    for i in range(n):
        xi, yi, zi = x[i], y[i], z[i]
        if not (math.isfinite(xi) and math.isfinite(yi) and math.isfinite(zi)):
            non_finite += 1
        elif (abs((xi - offsets[0]) / scales[0]) < max_scaled
              and abs((yi - offsets[1]) / scales[1]) < max_scaled
              and abs((zi - offsets[2]) / scales[2]) < max_scaled):
            rows[k] = i
            k += 1
        else:
            out_of_range += 1
    return rows[:k], non_finite, out_of_range


@compiled
def _clip(v: float, lo: float, hi: float) -> float:
    return min(max(v, lo), hi)


@compiled
def fill_records(rows: np.ndarray, x: np.ndarray, y: np.ndarray, z: np.ndarray,
                 t: np.ndarray, adjusted_gps: bool, gps_offset: float, leap_t: np.ndarray,
                 leap_n: np.ndarray, intensity: np.ndarray, intensity_mode: int,
                 source: np.ndarray, return_number: np.ndarray, returns: np.ndarray,
                 scan_angle: np.ndarray, reflectance: np.ndarray, rng: np.ndarray,
                 incidence: np.ndarray, flags: np.ndarray, not_corrected: int,
                 offsets: np.ndarray, scales: np.ndarray,
                 out_x: np.ndarray, out_y: np.ndarray, out_z: np.ndarray,
                 out_intensity: np.ndarray, out_bits: np.ndarray, out_class_flags: np.ndarray,
                 out_scan: np.ndarray, out_source: np.ndarray, out_gps: np.ndarray,
                 out_reflectance: np.ndarray, out_range: np.ndarray,
                 out_incidence: np.ndarray, out_flags: np.ndarray) -> tuple[int, int]:
    """Point format 6 records (and the extra bytes) of the points ``rows``, as
    :meth:`lidarcal_ros.io.survey.las_writer.LasChunkWriter.write` sets laspy's fields: X, Y, Z
    ``round((v - offset) / scale)`` (half to even); GPS time
    ``t - gps_offset + leap_n[searchsorted(leap_t, t, 'right')]`` (adjusted standard) or
    ``t``; the intensity per ``intensity_mode``; point source the strip clipped to
    0..65535; return number and count clipped to 1..15 (1 when absent); scan angle
    ``rint(degrees(-scan) / 0.006)`` (NaN: 0) clipped to +-30000; the extra bytes (NaN for an
    absent float); withheld where ``flags & not_corrected``. Optional inputs are empty
    arrays when absent; the other fields of the outputs are left as they are (zero).

    Returns
    -------
    (int, int)
        Intensities clipped to 0..65535; points withheld.
    """
    clipped = withheld = 0
    for j in range(rows.shape[0]):
        i = rows[j]
        out_x[j] = np.int32(np.rint((x[i] - offsets[0]) / scales[0]))
        out_y[j] = np.int32(np.rint((y[i] - offsets[1]) / scales[1]))
        out_z[j] = np.int32(np.rint((z[i] - offsets[2]) / scales[2]))
        ti = t[i]
        if adjusted_gps:
            k = 0
            while k < leap_t.shape[0] and leap_t[k] <= ti:
                k += 1
            out_gps[j] = (ti - gps_offset) + leap_n[k]
        else:
            out_gps[j] = ti
        if intensity_mode == INTENSITY_U16:
            out_intensity[j] = intensity[i]
        elif intensity_mode == INTENSITY_U8:
            out_intensity[j] = np.uint16(intensity[i]) * np.uint16(257)
        elif intensity_mode == INTENSITY_FLOAT:
            v = np.rint(np.float64(intensity[i]))
            if math.isnan(v):
                v = 0.0
            elif math.isinf(v):
                v = 1.7976931348623157e308 if v > 0 else -1.7976931348623157e308
            if v < 0.0 or v > 65535.0:
                clipped += 1
            out_intensity[j] = np.uint16(_clip(v, 0.0, 65535.0))
        if source.shape[0]:
            out_source[j] = min(max(np.int64(source[i]), 0), 65535)
        rn = np.uint8(min(max(return_number[i], 1), 15)) if return_number.shape[0] else 1
        nr = np.uint8(min(max(returns[i], 1), 15)) if returns.shape[0] else 1
        out_bits[j] = np.uint8(rn | (nr << 4))
        if scan_angle.shape[0]:
            steps = np.rint((-np.float64(scan_angle[i])) * _DEGREES / 0.006)
            if math.isnan(steps):
                steps = 0.0
            out_scan[j] = np.int16(_clip(steps, -30000.0, 30000.0))
        out_reflectance[j] = reflectance[i] if reflectance.shape[0] else np.nan
        out_range[j] = rng[i] if rng.shape[0] else np.nan
        out_incidence[j] = incidence[i] if incidence.shape[0] else np.nan
        if flags.shape[0]:
            f = flags[i]
            out_flags[j] = f
            if f & not_corrected:
                out_class_flags[j] = 4  # the withheld bit
                withheld += 1
    return clipped, withheld


__all__ = ["INTENSITY_FLOAT", "INTENSITY_NONE", "INTENSITY_U8", "INTENSITY_U16",
           "fill_records", "rows_to_write"]
