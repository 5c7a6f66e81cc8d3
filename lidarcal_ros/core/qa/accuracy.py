"""The paper's accuracy measures: relative (strip-to-strip rigid fit) and absolute (check points).

The transformation and the residuals: docs/internals.md, "Quality measures".
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import numpy as np

from lidarcal_ros.core.calibration.tin import Tin, match_to_tin
from lidarcal_ros.core.georeferencing.bias_model import boresight_matrix

logger = logging.getLogger(__name__)

#: Names of the rigid transformation's parameters, in the order of :attr:`RigidFit.values`.
RIGID_NAMES = ("tx", "ty", "tz", "omega", "phi", "kappa")
#: A direction of the 6x6 normal matrix weaker than this fraction of the strongest (after
#: scaling rotations by the overlap's size) is not determined by the data.
_WEAK_EIGEN = 1e-6


@dataclass
class RigidFit:
    """Rigid transformation co-aligning one strip pair (docs/internals.md, "Quality measures").

    Attributes
    ----------
    values : (6,) float64
        ``tx, ty, tz`` (m) and ``omega, phi, kappa`` (rad); NaN where not determined.
    sigmas : (6,) float64
        Standard deviations from the residuals (same units); NaN where not determined.
    determined : (6,) bool
        Whether the overlap's shape lets the data fix each parameter.
    rms_before, rms_after : float
        RMS normal distance before the first and after the last step, metres.
    n_matches : int
        Correspondences used in the last step.
    iterations : int
    converged : bool
    centroid : (3,) float64
        Centre of rotation ``c``, map frame, metres.
    """

    values: np.ndarray
    sigmas: np.ndarray
    determined: np.ndarray
    rms_before: float
    rms_after: float
    n_matches: int
    iterations: int
    converged: bool
    centroid: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def as_dict(self) -> dict[str, float | None]:
        """``name -> value`` (None where undetermined), SI units."""
        return {n: (float(v) if d else None)
                for n, v, d in zip(RIGID_NAMES, self.values, self.determined, strict=True)}


def _rotation(omega: float, phi: float, kappa: float) -> np.ndarray:
    """``Rz(kappa) Ry(phi) Rx(omega)``."""
    return boresight_matrix(omega, phi, kappa)


def _angles(rot: np.ndarray) -> tuple[float, float, float]:
    """``omega, phi, kappa`` of ``Rz Ry Rx``."""
    phi = -math.asin(max(-1.0, min(1.0, float(rot[2, 0]))))
    omega = math.atan2(float(rot[2, 1]), float(rot[2, 2]))
    kappa = math.atan2(float(rot[1, 0]), float(rot[0, 0]))
    return omega, phi, kappa


def _robust_keep(d: np.ndarray, k: float = 3.0) -> np.ndarray:
    """Inliers: within ``k`` robust sigmas (1.4826 MAD) of the median, at least 1 cm."""
    med = float(np.median(d))
    sigma = max(1.4826 * float(np.median(np.abs(d - med))), 0.01 / k)
    return np.abs(d - med) <= k * sigma


def rigid_icp(
    points: np.ndarray,
    tin: Tin,
    vertices: np.ndarray,
    *,
    max_normal_distance: float,
    vertex_shift: np.ndarray | None = None,
    max_iterations: int = 20,
    tolerance_m: float = 1e-4,
    min_matches: int = 50,
) -> RigidFit | None:
    """Point-to-patch ICP of ``points`` (strip a) onto the patches of ``tin`` (strip b).

    Parameters
    ----------
    points : (k, 3) float64
        Points of strip a in their current coordinates, map frame, metres.
    tin : Tin
        Strip b's TIN (built on its delivered coordinates).
    vertices : (n, 3) float64
        Strip b's vertices in their current coordinates, map frame, metres.
    max_normal_distance : float
        Largest accepted normal distance of a match, metres.
    vertex_shift : (n, 3) float64, optional
        ``delivered - current`` per vertex (None: ``vertices`` are the delivered ones).
    max_iterations : int
        Most match-solve steps.
    tolerance_m : float
        Converged when the step moves no matched point by more than this, metres.
    min_matches : int
        Fewest correspondences for a fit.

    Returns
    -------
    RigidFit, or None where fewer than ``min_matches`` points find a patch.
    """
    pts = np.asarray(points, dtype=np.float64)
    rot = np.eye(3)
    shift = np.zeros(3)
    centroid = np.zeros(3)
    start: np.ndarray | None = None
    rms_before = math.nan
    determined = np.ones(6, dtype=bool)
    step = np.zeros(6)
    sigmas = np.full(6, math.nan)
    n_used = 0
    converged = False
    iteration = 0
    for iteration in range(1, max_iterations + 1):
        if iteration == 1:
            moved = pts
        else:
            moved = (pts - centroid) @ rot.T + centroid + shift
        m = match_to_tin(moved, tin, vertices, max_normal_distance=max_normal_distance,
                         vertex_shift=vertex_shift, start=start)
        start = m.triangle
        ok = m.valid
        if int(ok.sum()) < min_matches:
            return None
        if iteration == 1:
            centroid = moved[ok].mean(axis=0)
        normal = m.normal[ok].copy()
        flat = ~tin.sloped[m.triangle[ok]]
        # Flat patches observe along the vertical only (docs/internals.md); the distance
        # along the vertical is the normal distance over n_z.
        d = m.distance[ok].copy()
        d[flat] = d[flat] / normal[flat, 2]
        normal[flat] = (0.0, 0.0, 1.0)
        keep = _robust_keep(d)
        normal, d, p = normal[keep], d[keep], moved[ok][keep]
        if iteration == 1:
            rms_before = float(np.sqrt(np.mean(d * d)))
        n_used = int(d.size)
        # Rotations scaled by the overlap's size so that all six columns are metres.
        r = p - (centroid + shift)
        size = max(float(np.sqrt(np.mean(np.sum(r * r, axis=1)))), 1.0)
        jac = np.column_stack([normal, np.cross(r, normal) / size])
        neq = jac.T @ jac
        rhs = -jac.T @ d
        scale = np.sqrt(np.maximum(np.diag(neq), 1e-30))
        scaled = neq / np.outer(scale, scale)
        eigval, eigvec = np.linalg.eigh(scaled)
        strong = eigval > _WEAK_EIGEN * eigval.max()
        # A parameter is determined where the weak directions hardly involve it.
        weak_load = (eigvec[:, ~strong] ** 2).sum(axis=1)
        determined = weak_load < 0.5
        inv = (eigvec[:, strong] / eigval[strong]) @ eigvec[:, strong].T
        x = (inv @ (rhs / scale)) / scale
        x[~determined] = 0.0
        resid = d + jac @ x
        dof = max(n_used - int(determined.sum()), 1)
        # (numpy's pairwise sum: BLAS's dot splits a long sum among its threads, so its last
        # bits follow their number, which a Dask worker sets to one)
        sigma0 = math.sqrt(float(np.sum(resid * resid)) / dof)
        cov_diag = np.diag(inv) / scale**2 * sigma0**2
        step = x.copy()
        step[3:] /= size
        sigmas = np.sqrt(cov_diag)
        sigmas[3:] /= size
        shift = shift + step[:3]
        rot = _rotation(*step[3:]) @ rot
        moved_most = float(np.max(np.abs(jac @ x))) if n_used else 0.0
        if moved_most < tolerance_m:
            converged = True
            break
    # Final residuals at the final transformation.
    moved = (pts - centroid) @ rot.T + centroid + shift
    m = match_to_tin(moved, tin, vertices, max_normal_distance=max_normal_distance,
                     vertex_shift=vertex_shift, start=start)
    ok = m.valid
    d = m.distance[ok]
    flat = ~tin.sloped[m.triangle[ok]]
    d = np.where(flat, d / m.normal[ok][:, 2], d)
    d = d[_robust_keep(d)] if d.size else d
    rms_after = float(np.sqrt(np.mean(d * d))) if d.size else math.nan
    values = np.concatenate([shift, _angles(rot)])
    values[~determined] = math.nan
    sigmas = np.where(determined, sigmas, math.nan)
    return RigidFit(values=values, sigmas=sigmas, determined=determined,
                    rms_before=rms_before, rms_after=rms_after, n_matches=n_used,
                    iterations=iteration, converged=converged, centroid=centroid)


# ---------------------------------------------------------------------------- check points
def tin_heights(tin: Tin, vertices: np.ndarray, xy: np.ndarray, *,
                vertex_shift: np.ndarray | None = None) -> np.ndarray:
    """Height of a strip's surface at map positions, by barycentric interpolation.

    Parameters
    ----------
    tin : Tin
        The strip's TIN (built on its delivered coordinates).
    vertices : (n, 3) float64
        The TIN's vertices in their current coordinates, map frame, metres.
    xy : (k, 2) float64
        Map positions, metres.
    vertex_shift : (n, 3) float64, optional
        ``delivered - current`` per vertex (None: ``vertices`` are the delivered ones). Each
        position is located in the delivered triangulation moved by the shift of the
        triangle first found there (the correction is smooth: a triangle's neighbours move
        alike).

    Returns
    -------
    (k,) float64
        Heights, metres; NaN outside the TIN or on a triangle not usable as a patch (a wall,
        a long edge across a gap).
    """
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    tri = tin.locate(xy)
    if vertex_shift is not None:
        found = tri >= 0
        moved = xy.copy()
        moved[found] += vertex_shift[tin.simplices[tri[found]], :2].mean(axis=1)
        tri = tin.locate(moved, np.where(found, tri, -1))
    out = np.full(xy.shape[0], np.nan)
    ok = tri >= 0
    ok[ok] = tin.usable[tri[ok]]
    if not ok.any():
        return out
    v = vertices[tin.simplices[tri[ok]]]  # (m, 3 vertices, 3)
    a, b, c = v[:, 0], v[:, 1], v[:, 2]
    p = xy[ok]
    det = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (c[:, 0] - a[:, 0]) * (b[:, 1] - a[:, 1])
    with np.errstate(divide="ignore", invalid="ignore"):
        wb = ((p[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1])
              - (c[:, 0] - a[:, 0]) * (p[:, 1] - a[:, 1])) / det
        wc = ((b[:, 0] - a[:, 0]) * (p[:, 1] - a[:, 1])
              - (p[:, 0] - a[:, 0]) * (b[:, 1] - a[:, 1])) / det
    wa = 1.0 - wb - wc
    out[ok] = wa * a[:, 2] + wb * b[:, 2] + wc * c[:, 2]
    return out


@dataclass
class AccuracySummary:
    """Statistics of check-point residuals (metres)."""

    n: int
    mean: float
    std: float
    rmse: float
    max_abs: float

    @classmethod
    def of(cls, residuals: np.ndarray) -> AccuracySummary:
        """The statistics of the finite ``residuals`` (metres); n 0 and NaN statistics when none
        is finite, std 0 for one."""
        r = np.asarray(residuals, dtype=np.float64)
        r = r[np.isfinite(r)]
        if r.size == 0:
            return cls(0, math.nan, math.nan, math.nan, math.nan)
        return cls(int(r.size), float(r.mean()), float(r.std(ddof=1)) if r.size > 1 else 0.0,
                   float(np.sqrt(np.mean(r * r))), float(np.max(np.abs(r))))


__all__ = ["RIGID_NAMES", "AccuracySummary", "RigidFit", "rigid_icp", "tin_heights"]
