"""The strip surface under each control point: a least-squares plane through its neighbours.

A TIN facet carries the noise of its three vertices; the plane of ``k`` neighbours carries
about ``1/sqrt(k)`` of one point's, so a few control points fix the block's common vertical
shift (docs/method.md section 11's datum) to a fraction of the range noise.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: A neighbourhood whose points stray further than this from their plane (RMS, m) is not a
#: plane (an edge, vegetation): its control point keeps the TIN facet.
PLANE_MAX_RMS_M = 0.05


@dataclass(frozen=True)
class ControlSurface:
    """Planes fitted under control points (arrays over the control points).

    Attributes
    ----------
    valid : (m,) bool
        A plane was fitted: ``k`` neighbours within the radius, residual RMS within
        :data:`PLANE_MAX_RMS_M`.
    neighbours : (m, k) int64
        The points of the strip the plane rests on (-1 where not valid).
    weights : (m, k) float64
        The plane's point above the control point as a combination of its neighbours (sums
        to one; ``sum w_i X_i`` is the foot in x, y).
    normal : (m, 3) float64
        Upward unit normal of the plane, map frame.
    distance : (m,) float64
        Signed normal distance, control point minus plane, metres.
    """

    valid: np.ndarray
    neighbours: np.ndarray
    weights: np.ndarray
    normal: np.ndarray
    distance: np.ndarray

    def take(self, index: np.ndarray) -> ControlSurface:
        """The planes of the control points ``index`` (indices or a mask)."""
        return ControlSurface(self.valid[index], self.neighbours[index], self.weights[index],
                              self.normal[index], self.distance[index])


def fit_control_planes(control: np.ndarray, points: np.ndarray, candidates: np.ndarray, *,
                       k: int, max_radius: float) -> ControlSurface:
    """The plane under each control point through its ``k`` nearest points (horizontally).

    Parameters
    ----------
    control : (m, 3) float64
        Control points, map frame, metres.
    points : (n, 3) float64
        The strip's points in their current (corrected) coordinates, map frame, metres.
    candidates : (c,) int64
        The points that may be neighbours (those near any control point).
    k : int
        Neighbours of each plane (at least 3).
    max_radius : float
        Farthest neighbour accepted, metres: beyond it the control point has no plane.
    """
    from scipy.spatial import cKDTree

    m = control.shape[0]
    out = ControlSurface(np.zeros(m, dtype=bool), np.full((m, k), -1, dtype=np.int64),
                         np.zeros((m, k)), np.zeros((m, 3)), np.full(m, np.nan))
    if candidates.size < k or m == 0:
        return out
    near = points[candidates]
    dist, nearest = cKDTree(near[:, :2]).query(control[:, :2], k=k)
    dist, nearest = dist.reshape(m, k), nearest.reshape(m, k)
    inside = dist[:, -1] <= max_radius
    dxy = near[nearest, :2] - control[:, None, :2]  # (m, k, 2), about each control point
    design = np.concatenate([np.ones((m, k, 1)), dxy], axis=2)  # (m, k, 3)
    normal_matrix = np.einsum("mki,mkj->mij", design, design)
    solvable = inside & (np.abs(np.linalg.det(normal_matrix)) > 1e-12)
    normal_matrix[~solvable] = np.eye(3)
    inverse = np.linalg.inv(normal_matrix)
    weights = np.einsum("mj,mkj->mk", inverse[:, 0, :], design)  # first row of (A^T A)^-1 A^T
    z = near[nearest, 2]
    coef = np.einsum("mij,mkj,mk->mi", inverse, design, z)
    residual = np.einsum("mkj,mj->mk", design, coef) - z
    rms = np.sqrt((residual**2).sum(axis=1) / max(k - 3, 1))
    valid = solvable & (rms <= PLANE_MAX_RMS_M)
    tilt = np.hypot(np.hypot(coef[:, 1], coef[:, 2]), 1.0)
    normal = np.column_stack([-coef[:, 1], -coef[:, 2], np.ones(m)]) / tilt[:, None]
    out.valid[:] = valid
    out.neighbours[valid] = candidates[nearest[valid]]
    out.weights[valid] = weights[valid]
    out.normal[valid] = normal[valid]
    out.distance[valid] = (control[valid, 2] - coef[valid, 0]) * normal[valid, 2]
    return out


__all__ = ["PLANE_MAX_RMS_M", "ControlSurface", "fit_control_planes"]
