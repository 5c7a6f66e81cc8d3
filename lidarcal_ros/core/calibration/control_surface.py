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


def plane_weights(dxy: np.ndarray) -> np.ndarray:
    """The weights ``w`` (k,) with ``sum w_i z_i`` the height at the origin of the plane
    fitted to points at horizontal offsets ``dxy`` (k, 2) from it: the first row of the
    least-squares solution ``(A^T A)^-1 A^T``, ``A = [1, dx, dy]``."""
    design = np.column_stack([np.ones(len(dxy)), dxy])
    return np.linalg.solve(design.T @ design, design.T)[0]


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
    m = control.shape[0]
    out = ControlSurface(np.zeros(m, dtype=bool), np.full((m, k), -1, dtype=np.int64),
                         np.zeros((m, k)), np.zeros((m, 3)), np.full(m, np.nan))
    if candidates.size < k:
        return out
    near = points[candidates]
    for i in range(m):
        d2 = ((near[:, :2] - control[i, :2]) ** 2).sum(axis=1)
        nearest = np.argpartition(d2, k - 1)[:k]
        if d2[nearest].max() > max_radius**2:
            continue
        dxy = near[nearest, :2] - control[i, :2]
        z = near[nearest, 2]
        design = np.column_stack([np.ones(k), dxy])
        coef, *_ = np.linalg.lstsq(design, z, rcond=None)
        rms = float(np.sqrt(((design @ coef - z) ** 2).sum() / max(k - 3, 1)))
        if rms > PLANE_MAX_RMS_M:
            continue
        normal = np.array([-coef[1], -coef[2], 1.0]) / np.hypot(np.hypot(coef[1], coef[2]), 1.0)
        out.valid[i] = True
        out.neighbours[i] = candidates[nearest]
        out.weights[i] = plane_weights(dxy)
        out.normal[i] = normal
        out.distance[i] = (control[i, 2] - coef[0]) * normal[2]
    return out


__all__ = ["PLANE_MAX_RMS_M", "ControlSurface", "fit_control_planes", "plane_weights"]
