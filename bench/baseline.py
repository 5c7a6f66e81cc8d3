"""Baseline for the benchmarks: a straightforward implementation of the same method.

Same data, same local trajectories, same design rows (evaluated at the corrected points), same
exact bias removal between iterations (Gauss-Newton: each iteration solves for the increment
that removes the normal discrepancies left by the current estimate), same least-squares solver
and robust re-weighting as ``lidarcal calibrate`` (it imports
:mod:`lidarcal_ros.core.georeferencing.local_trajectory`,
:mod:`lidarcal_ros.core.georeferencing.bias_model` and
:func:`lidarcal_ros.core.adjustment.least_squares.solve`), but the matching is done the obvious way:

- every iteration, every strip's TIN is rebuilt from the *corrected* coordinates with
  ``scipy.spatial.Delaunay`` (qhull), and its triangles are judged again (edge length, slope,
  bend against the neighbours);
- points are located with ``Delaunay.find_simplex`` and matched to that one triangle only (no
  neighbour candidates, no vertex shift);
- there is no sample stratification: every iteration matches all candidates of every pair (up
  to ``max_candidates_per_pair``, the same random subset ``lidarcal`` starts from);
- ``find_simplex`` walks from the triangle found for the previous query, so it is fed the
  candidates in acquisition order (sorted indices), as ``lidarcal`` matches them;
- it runs a fixed number of iterations (``--iterations``, the count ``lidarcal`` reported), then
  rebuilds once more for the QA figures (RMS before / after per pair), as ``lidarcal`` does.

Run on its own (the benchmark runs it in a subprocess with a time limit)::

    .venv/bin/python bench/baseline.py BAG --control CSV --iterations 5 -o result.json

The JSON result holds the estimate (SI), timings per phase (seconds) and counts.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy import ndimage
from scipy.spatial import Delaunay

from lidarcal_ros.core.adjustment.least_squares import (
    NormalEquations,
    Observations,
    Solution,
    solve,
)
from lidarcal_ros.core.calibration.calibrate import CalibrationSettings
from lidarcal_ros.core.georeferencing.bias_model import correct_points_exact, normal_design_rows
from lidarcal_ros.core.georeferencing.laser_geometry import LaserGeometry
from lidarcal_ros.core.georeferencing.local_trajectory import laser_geometry
from lidarcal_ros.core.mission import Mission
from lidarcal_ros.core.params import N_PARAMETERS, PARAMETER_NAMES

# ---------------------------------------------------------------------------- TIN, matching


@dataclass
class BaselineTin:
    """A qhull Delaunay triangulation of one strip's (corrected) XY and its usable triangles."""

    tri: Delaunay
    origin: np.ndarray
    usable: np.ndarray


def _normals(local: np.ndarray, simplices: np.ndarray) -> np.ndarray:
    v0 = local[simplices[:, 0]]
    nrm = np.cross(local[simplices[:, 1]] - v0, local[simplices[:, 2]] - v0)
    length = np.linalg.norm(nrm, axis=1)
    length[length == 0] = np.inf
    nrm /= length[:, None]
    nrm[nrm[:, 2] < 0] *= -1.0
    return nrm


def build_tin(xyz: np.ndarray, max_edge_m: float, max_slope_deg: float,
              max_bend_deg: float) -> BaselineTin:
    """Delaunay over XY (about a local origin) and the same triangle quality rules."""
    origin = xyz.mean(axis=0)
    local = xyz - origin
    tri = Delaunay(local[:, :2], qhull_options="Qbb Qc Qz")
    # The barycentric transforms find_simplex needs (scipy computes them on first use, one
    # small LAPACK solve per triangle): part of building a TIN that can locate points.
    tri.transform  # noqa: B018
    simp = tri.simplices
    corners = local[simp]
    edges = corners[:, [1, 2, 0], :2] - corners[:, :, :2]
    max_edge = np.sqrt((edges**2).sum(axis=2)).max(axis=1)
    nrm = _normals(local, simp)
    ok = (max_edge <= max_edge_m) & (nrm[:, 2] >= np.cos(np.radians(max_slope_deg)))
    cos_bend = np.cos(np.radians(max_bend_deg))
    for k in range(3):
        nb = tri.neighbors[:, k]
        has = nb >= 0
        agree = np.ones_like(ok)
        agree[has] = (nrm[has] * nrm[nb[has]]).sum(axis=1) >= cos_bend
        ok &= agree
    return BaselineTin(tri, origin, ok)


def locate(tin: BaselineTin, xy: np.ndarray) -> np.ndarray:
    """Triangle containing each XY (map frame), -1 outside: ``Delaunay.find_simplex``."""
    return tin.tri.find_simplex(xy - tin.origin[:2])


def plane_match(points: np.ndarray, simplices: np.ndarray, vertices: np.ndarray,
                tri: np.ndarray, usable: np.ndarray, max_normal_distance: float
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per-triangle plane math for points already located in triangle ``tri`` (-1: none).

    Returns ``valid (k,)``, ``normal (k, 3)``, ``weights (k, 3)`` (barycentric coordinates of
    the foot of the normal) and ``distance (k,)`` (point minus patch along the normal).
    """
    found = tri >= 0
    found[found] = usable[tri[found]]
    t = np.where(found, tri, 0)
    tv = vertices[simplices[t]] - points[:, None, :]  # (k, 3, 3), point at the origin
    v0 = tv[:, 0]
    e1 = tv[:, 1] - v0
    e2 = tv[:, 2] - v0
    nrm = np.cross(e1, e2)
    length = np.linalg.norm(nrm, axis=1)
    found &= length > 0
    length[length == 0] = 1.0
    nrm /= length[:, None]
    nrm[nrm[:, 2] < 0] *= -1.0
    dist = -(nrm * v0).sum(axis=1)
    ep = -dist[:, None] * nrm - v0
    d00 = (e1 * e1).sum(axis=1)
    d01 = (e1 * e2).sum(axis=1)
    d11 = (e2 * e2).sum(axis=1)
    d20 = (ep * e1).sum(axis=1)
    d21 = (ep * e2).sum(axis=1)
    denom = d00 * d11 - d01 * d01
    denom[denom == 0] = np.inf
    wv = (d11 * d20 - d01 * d21) / denom
    ww = (d00 * d21 - d01 * d20) / denom
    wu = 1.0 - wv - ww
    eps = -1e-9
    valid = found & (wu >= eps) & (wv >= eps) & (ww >= eps)
    valid &= np.abs(dist) <= max_normal_distance
    return valid, nrm, np.stack([wu, wv, ww], axis=1), dist


# ---------------------------------------------------------------------------- calibration


@dataclass
class _Strip:
    xyz: np.ndarray
    geometry: LaserGeometry
    raster: np.ndarray
    density: float


class Timer:
    """Accumulated wall time per phase."""

    def __init__(self) -> None:
        self.total: dict[str, float] = {}

    def add(self, phase: str, started: float) -> None:
        """Add the wall time since ``started`` (``time.perf_counter``, s) to ``phase``."""
        self.total[phase] = self.total.get(phase, 0.0) + time.perf_counter() - started


def _robust_solve(obs: Observations, s: CalibrationSettings, delta: np.ndarray) -> Solution:
    """Solve for the increment to ``delta`` (Gauss-Newton), re-weighting outliers."""
    fixed_step = {name: float(s.fixed.get(name, 0.0) - delta[i])
                  for i, name in enumerate(PARAMETER_NAMES)}
    base_w = obs.weights.copy()
    sol = None
    for _ in range(6):
        sol = solve(NormalEquations.from_observations(obs), solve_for=s.solve_for,
                    fixed=fixed_step, limits=s.limits)
        v = obs.residuals(sol.delta)
        scale = 1.4826 * np.median(np.abs(v[base_w > 0]))
        new_w = np.where(np.abs(v) <= s.robust_k * max(scale, 1e-6), base_w, 0.0)
        if np.array_equal(new_w > 0, obs.weights > 0):
            break
        obs.weights = new_w
    assert sol is not None
    sol.delta = sol.delta + delta
    return sol


def _observations(rows: np.ndarray, y: np.ndarray, weights: np.ndarray,
                  group: np.ndarray) -> Observations:
    """Observations; extra per-observation fields the class may have (e.g. a spatial cluster
    for error statistics the baseline does not report) are filled with zeros."""
    extra = {f.name: np.zeros(y.size, dtype=np.int64) for f in dataclasses.fields(Observations)
             if f.name not in ("rows", "y", "weights", "group")}
    return Observations(rows, y, weights, group, **extra)


def _geometry_at(xyz: np.ndarray, g0: LaserGeometry) -> LaserGeometry:
    """Laser-frame x, z, beta of (corrected) points from the fixed firing positions and headings:
    the design rows are the Jacobian at the current estimate."""
    rel = xyz - g0.origin
    x = rel[:, 0] * np.cos(g0.kappa) + rel[:, 1] * np.sin(g0.kappa)
    z = rel[:, 2]
    return LaserGeometry(x=x, z=z, kappa=g0.kappa, beta=np.arctan(x / z), origin=g0.origin)


def _design_rows(n: np.ndarray, w: np.ndarray, verts: np.ndarray, ga: LaserGeometry | None,
                 sb: _Strip) -> np.ndarray:
    """``n^T (A_A - A_B)`` of matched points, ``A_B`` interpolated at the foot of the normal
    (``-n^T A_B`` for control points: ``ga`` None)."""
    rows = (normal_design_rows(n, ga.x, ga.z, ga.kappa, ga.beta) if ga is not None
            else np.zeros((n.shape[0], N_PARAMETERS)))
    for v in range(3):
        gv = sb.geometry.take(verts[:, v])
        rows -= w[:, v:v + 1] * normal_design_rows(n, gv.x, gv.z, gv.kappa, gv.beta)
    return rows


def run(mission: Mission, s: CalibrationSettings, iterations: int) -> dict:
    """Calibrate ``mission`` with ``iterations`` rebuild-everything iterations."""
    timer = Timer()
    t0 = time.perf_counter()
    allxy = np.concatenate([st.xyz[:, :2] for st in mission.strips])
    lo = allxy.min(axis=0)
    cell = s.overlap_cell_m
    shape = tuple(int(v) + 1 for v in np.ceil((allxy.max(axis=0) - lo) / cell))

    def index(xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        ix = np.clip(np.floor((xy[:, 0] - lo[0]) / cell).astype(np.int64), 0, shape[0] - 1)
        iy = np.clip(np.floor((xy[:, 1] - lo[1]) / cell).astype(np.int64), 0, shape[1] - 1)
        return ix, iy

    strips: list[_Strip] = []
    for st in mission.strips:
        geom = laser_geometry(st.t, st.xyz, mission.trajectory, window=s.window)
        raster = np.zeros(shape, dtype=bool)
        raster[index(st.xyz[:, :2])] = True
        strips.append(_Strip(st.xyz, geom, raster,
                             len(st) / max(float(raster.sum()) * cell**2, 1.0)))
    timer.add("local trajectories", t0)

    # Overlapping pairs and their candidate points: the same rule and random draw as lidarcal.
    t0 = time.perf_counter()
    pairs: list[tuple[int, int, np.ndarray]] = []
    for i in range(len(strips)):
        for j in range(i + 1, len(strips)):
            both = strips[i].raster & strips[j].raster
            if int(both.sum()) < s.min_overlap_cells:
                continue
            a, b = (i, j) if strips[i].density <= strips[j].density else (j, i)
            zone = strips[a].raster & ndimage.binary_erosion(
                strips[b].raster, structure=np.ones((3, 3), dtype=bool))
            cand = np.flatnonzero(zone[index(strips[a].xyz[:, :2])])
            if cand.size == 0:
                continue
            if cand.size > s.max_candidates_per_pair:
                ids = sorted((mission.strips[i].strip_id, mission.strips[j].strip_id))
                rng = np.random.default_rng([s.seed, *ids])
                cand = np.sort(rng.choice(cand, s.max_candidates_per_pair, replace=False))
            pairs.append((a, b, cand))
    timer.add("overlaps", t0)

    control = mission.control
    quality = [dict(max_edge_m=s.max_edge_factor / np.sqrt(max(st.density, 1e-6)),
                    max_slope_deg=s.max_slope_deg, max_bend_deg=s.max_bend_deg)
               for st in strips]

    geometry0 = [st.geometry for st in strips]

    def corrected(delta: np.ndarray) -> list[np.ndarray]:
        out = []
        for st, g0 in zip(strips, geometry0):
            xyz = correct_points_exact(st.xyz, g0, delta)
            st.geometry = _geometry_at(xyz, g0)
            out.append(xyz)
        return out

    def rebuild(xyz: list[np.ndarray]) -> list[BaselineTin]:
        t = time.perf_counter()
        tins = [build_tin(xyz[k], **quality[k]) for k in range(len(strips))]
        timer.add("TIN rebuild (qhull Delaunay + quality)", t)
        return tins

    def match(points: np.ndarray, tin: BaselineTin, vertices: np.ndarray, threshold: float):
        t = time.perf_counter()
        tri = locate(tin, points[:, :2])
        timer.add("locate (find_simplex)", t)
        t = time.perf_counter()
        out = plane_match(points, tin.tri.simplices, vertices, tri, tin.usable, threshold)
        timer.add("plane math", t)
        return tri, out

    delta = np.zeros(N_PARAMETERS)
    threshold = s.max_normal_distance_m
    history = []
    before: list[np.ndarray] = []
    sol: Solution | None = None
    obs = Observations.empty()
    n_matched = 0
    for iteration in range(1, iterations + 1):
        xyz = corrected(delta)
        tins = rebuild(xyz)
        parts = []
        for p_i, (a, b, cand) in enumerate(pairs):
            tri, (valid, n, w, dist) = match(xyz[a][cand], tins[b], xyz[b], threshold)
            n_matched += cand.size
            if iteration == 1:
                before.append(dist[valid])
            t = time.perf_counter()
            verts = tins[b].tri.simplices[tri[valid]]
            idx = cand[valid]
            rows = _design_rows(n[valid], w[valid], verts, strips[a].geometry.take(idx),
                                strips[b])
            # Observed: n . (X_A - X_B) left by the current estimate; solve the increment.
            y = dist[valid]
            parts.append(_observations(rows, y, np.ones(y.size), np.full(y.size, p_i)))
            timer.add("design rows", t)
        if control is not None and len(control):
            for k, st in enumerate(strips):
                inside = np.flatnonzero(st.raster[index(control.xyz[:, :2])])
                if not inside.size:
                    continue
                tri, (valid, n, w, dist) = match(control.xyz[inside], tins[k], xyz[k],
                                                 threshold)
                if not valid.any():
                    continue
                verts = tins[k].tri.simplices[tri[valid]]
                rows = _design_rows(n[valid], w[valid], verts, None, st)
                y = dist[valid]
                parts.append(_observations(rows, y, np.full(y.size, s.control_weight),
                                           -1 - inside[valid]))
        obs = Observations.concatenate(parts)
        t = time.perf_counter()
        sol = _robust_solve(obs, s, delta)
        timer.add("adjustment", t)
        step = sol.delta - delta
        delta = sol.delta.copy()
        history.append(delta.tolist())
        inl = obs.weights > 0
        scale = float(np.sqrt(np.mean(obs.residuals(step)[inl] ** 2)))
        threshold = float(np.clip(2.0 * s.robust_k * scale, s.min_normal_distance_m, threshold))
    assert sol is not None

    # QA as lidarcal reports it: re-match with the final estimate at the first threshold.
    xyz = corrected(delta)
    tins = rebuild(xyz)
    qa = []
    for (a, b, cand), bef in zip(pairs, before):
        _, (valid, _, _, dist) = match(xyz[a][cand], tins[b], xyz[b], s.max_normal_distance_m)
        n_matched += cand.size
        after = dist[valid]
        qa.append({"strips": [mission.strips[a].strip_id, mission.strips[b].strip_id],
                   "rms_before_m": float(np.sqrt(np.mean(bef**2))) if bef.size else None,
                   "rms_after_m": float(np.sqrt(np.mean(after**2))) if after.size else None})
    return {
        "delta": {name: float(v) for name, v in zip(PARAMETER_NAMES, delta)},
        "sigma": {name: float(v) for name, v in zip(PARAMETER_NAMES, sol.sigma)},
        "sigma0": float(sol.sigma0),
        "iterations": iterations,
        "history": history,
        "pairs": qa,
        "n_pairs": len(pairs),
        "n_candidates": int(sum(c.size for _, _, c in pairs)),
        "n_matched_total": int(n_matched),
        "n_observations": int(len(obs)),
        "phases_s": timer.total,
    }


def main(argv: list[str] | None = None) -> int:
    """Calibrate a bag with the baseline for a fixed number of iterations and write its estimate,
    phase times (s) and point count as JSON; exit status 0."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("bag", type=Path)
    ap.add_argument("--control", type=Path, help="control points CSV id,x,y,z")
    ap.add_argument("--iterations", type=int, required=True)
    ap.add_argument("-o", "--output", type=Path, required=True, help="result JSON")
    args = ap.parse_args(argv)

    from lidarcal_ros.io.config_file import load_flight_config
    from lidarcal_ros.pipeline.calibration.procedure import load_mission

    started = time.perf_counter()
    config = load_flight_config(None)
    mission = load_mission(args.bag, config, control_csv=args.control)
    load_s = time.perf_counter() - started
    result = run(mission, config.calibration_settings(), args.iterations)
    result["phases_s"] = {"read bag": load_s, **result["phases_s"]}
    result["wall_s"] = time.perf_counter() - started
    result["n_points"] = int(mission.n_points)
    args.output.write_text(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
