"""Peer comparison: lidarcal against pairwise point-to-plane ICP (Open3D) on simulated missions.

What a user without a calibration tool reaches for is to register the strips to each other
with ICP. This benchmark runs both on the same simulated missions (known biases, known true
surface) and measures, in the same run:

- **remaining strip discrepancy**: per overlapping strip pair, the RMS point-to-plane distance
  (along the local surface normal) between the strips, on smooth surfaces only; and, from the
  truth, the RMS relative 3D misalignment of the two strips at the same places;
- **error against the true surface**: vertical distance ``dz`` of the points to the simulated
  DSM (median ``|dz|`` and RMS), the same along the true surface normal, and the 3D distance
  of each point to the true point its pulse hit (RMS);
- **time** (wall and CPU) of each method, from the delivered strips to corrected / aligned
  points.

Rows: ``none`` (the delivered, biased strips: the baseline of every ratio), ``lidarcal``
(calibrate, then correct every point, in process), ``lidarcal CLI`` (on the ``speed``
mission: ``lidarcal calibrate`` and ``lidarcal correct`` of its bag as a user runs them, two
processes timed end to end, the corrected points read back from the output bag), ``ICP-union``
and ``ICP-ref`` (rigid 6-DoF
point-to-plane ICP of each strip to the union of the strips already aligned, or to one
reference strip, then a vertical shift onto the control point), ``ICP-mean`` (ICP-union's
registration re-centred on the mean strip pose) and ``floor`` (the same mission simulated
without biases: the range noise alone, a reference, not a method).

Open3D is a dependency of this benchmark only, deliberately not in requirements.txt::

    apt-get update && apt-get install -y libusb-1.0-0   # as root: Open3D's wheel links it
    .venv/bin/pip install open3d==0.20.0                # (or open3d-cpu), Python 3.11

Run from the package root::

    .venv/bin/python bench/bench_peer_icp.py                   # three missions, ~6 min
    .venv/bin/python bench/bench_peer_icp.py --missions speed    # the goal: ~1.5 min
    .venv/bin/python bench/bench_peer_icp.py --quick           # small missions, ~40 s

See bench/README.md, section "Peer comparison", for what each figure means.
"""

from __future__ import annotations

import argparse
import copy
import math
import os
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import benchlib  # bench/benchlib.py: this script's folder is on sys.path
import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from lidarcal_ros.core.config import FlightConfig
from lidarcal_ros.core.flags import FLAG_NOT_CORRECTED
from lidarcal_ros.core.params import PARAMETER_NAMES, arcsec_to_rad, as_vector
from lidarcal_ros.core.simulation.simulate import SimulatedMission, simulate_mission
from lidarcal_ros.core.simulation.spec import DEFAULT_BIASES, SimulationSpec
from lidarcal_ros.core.simulation.surface import TREE
from lidarcal_ros.pipeline.calibration.procedure import calibrate_mission
from lidarcal_ros.pipeline.correction.apply import CorrectionSettings, correct_columns

ARCSEC = math.pi / 180.0 / 3600.0

#: Radii (m) around a point's true position at which the true surface must stay on the
#: point's tangent plane for the point to count as "smooth" (no edge, wall, ridge or crown).
SMOOTH_RADII_M = (2.5, 5.0)
#: Largest departure (m) of the true surface from that tangent plane at those radii (the
#: undulating ground bends by a few cm over 5 m; an edge or a ridge by metres).
SMOOTH_TOL_M = 0.10
#: Neighbours of the other strip that define the local plane of a discrepancy query.
PAIR_K = 8
#: The farthest of those neighbours must lie within this distance of the query point (m).
PAIR_MAX_RADIUS_M = 3.0
#: A neighbourhood is a plane if its RMS residual is below this (m, range noise 2 cm) ...
PAIR_MAX_RESIDUAL_M = 0.08
#: ... and it spreads in two directions (second principal spread above this, m).
PAIR_MIN_SPREAD_M = 0.3
#: A pair overlaps if this many smooth points of the later strip have a smooth point of the
#: earlier strip within ``OVERLAP_RADIUS_M`` (horizontal, true positions).
MIN_PAIR_POINTS = 1000
OVERLAP_RADIUS_M = 1.5


# ---------------------------------------------------------------------------- missions
@dataclass(frozen=True)
class MissionSpec:
    """One simulated mission of the comparison.

    Attributes
    ----------
    name : str
    seed : int
        Terrain and noise seed of :func:`simulate_mission`.
    density : float
        Points per m^2 at the highest line.
    line_length_m : float
        Length of every flight line, metres.
    biases : dict
        Simulated biases, SI (metres, radians, unitless scale).
    """

    name: str
    seed: int
    density: float
    line_length_m: float
    biases: dict[str, float]


def _strong_biases() -> dict[str, float]:
    """A second bias set: every bias large, of other signs than the paper's."""
    return {"dX": 0.12, "dY": -0.15, "dZ": 0.0, "domega": arcsec_to_rad(120.0),
            "dphi": arcsec_to_rad(-140.0), "dkappa": arcsec_to_rad(-100.0), "dr": -0.15,
            "dS": -1.5e-4}


#: The mission of the speed goal: bench/benchlib.py's ~1M-point mission (its cached bag is
#: the one ``lidarcal calibrate`` and ``lidarcal correct`` read).
SPEED = benchlib.MISSION_1M


def mission_specs(quick: bool) -> list[MissionSpec]:
    """The missions of a run: the ~1M-point mission of the speed goal, the paper scenario
    with the paper's biases, and a second seed with large biases (``quick``: small versions
    of the last two)."""
    speed = MissionSpec("speed", SPEED.seed, SPEED.density, SPEED.line_length_m,
                        dict(DEFAULT_BIASES))
    if quick:
        return [speed, MissionSpec("paper", 7, 0.15, 400.0, dict(DEFAULT_BIASES)),
                MissionSpec("strong", 102, 0.15, 400.0, _strong_biases())]
    return [speed, MissionSpec("paper", 7, 0.4, 800.0, dict(DEFAULT_BIASES)),
            MissionSpec("strong", 102, 0.3, 1000.0, _strong_biases())]


def simulate(spec: MissionSpec, *, biased: bool = True) -> SimulatedMission:
    """The paper scenario (six strips at 1150 m and 540 m, built-up terrain, one control
    point) with the spec's biases, or without any (the noise floor: same terrain, same noise)."""
    return simulate_mission(SimulationSpec.from_options(
        scenario="paper", seed=spec.seed, density=spec.density,
        line_length_m=spec.line_length_m, biases=spec.biases if biased else {}))


# ---------------------------------------------------------------------------- truth
def smooth_mask(sim: SimulatedMission, k: int) -> np.ndarray:
    """Points of strip ``k`` that lie on a smooth part of the true surface.

    A point qualifies if its pulse hit the height field (not a wall), not a tree crown, and the
    true surface at 16 points on circles of :data:`SMOOTH_RADII_M` around its true position
    stays within :data:`SMOOTH_TOL_M` of the tangent plane there. Decided from the simulated
    truth alone, so every method is evaluated on the same points.

    Returns
    -------
    (n,) bool
    """
    terrain = sim.terrain
    xyz = sim.true_xyz[k]
    ok = (sim.surface_class[k] != TREE) & ~sim.on_wall[k]
    idx = np.flatnonzero(ok)
    x, y = xyz[idx, 0], xyz[idx, 1]
    h0 = terrain.height(x, y)
    n = terrain.normal(x, y)
    gx, gy = -n[:, 0] / n[:, 2], -n[:, 1] / n[:, 2]
    good = np.abs(h0 - xyz[idx, 2]) < 0.01
    for r in SMOOTH_RADII_M:
        for a in np.arange(8) * (math.pi / 4.0):
            dx, dy = r * math.cos(a), r * math.sin(a)
            good &= np.abs(terrain.height(x + dx, y + dy) - (h0 + gx * dx + gy * dy)) \
                < SMOOTH_TOL_M
    ok[idx] = good
    return ok


@dataclass
class TruthPair:
    """An overlapping strip pair and the points it is measured on.

    Attributes
    ----------
    a, b : int
        Strip indices (into the mission's strip list), ``a < b``.
    query : (m,) int
        Points of strip ``b`` whose distance to strip ``a``'s local plane is measured: smooth
        points with a smooth point of strip ``a`` within :data:`OVERLAP_RADIUS_M` (horizontal,
        true positions), at most ``--pair-points`` of them, drawn at random once.
    partner : (m,) int
        For each query, that nearest smooth point of strip ``a`` (true positions).
    """

    a: int
    b: int
    query: np.ndarray
    partner: np.ndarray


@dataclass
class Truth:
    """What every method is measured on (chosen from the simulated truth, once per mission).

    Attributes
    ----------
    smooth : list of (n_k,) bool
        :func:`smooth_mask` of each strip.
    pairs : list of TruthPair
        Overlapping strip pairs and their query points.
    surface : list of (m_k,) int
        Per strip, the points whose error against the true surface is measured: smooth
        points, at most ``--surface-points`` per strip, drawn at random once.
    """

    smooth: list[np.ndarray]
    pairs: list[TruthPair]
    surface: list[np.ndarray]


def build_truth(sim: SimulatedMission, pair_points: int, surface_points: int,
                seed: int = 0) -> Truth:
    """Choose the evaluation points of a mission (see :class:`Truth`)."""
    rng = np.random.default_rng(seed)
    n_strips = len(sim.mission.strips)
    smooth = [smooth_mask(sim, k) for k in range(n_strips)]
    surface = []
    for k in range(n_strips):
        idx = np.flatnonzero(smooth[k])
        if idx.size > surface_points:
            idx = np.sort(rng.choice(idx, surface_points, replace=False))
        surface.append(idx)
    pairs = []
    for a in range(n_strips):
        smooth_a = np.flatnonzero(smooth[a])
        tree = cKDTree(sim.true_xyz[a][smooth_a, :2])
        for b in range(a + 1, n_strips):
            cand = np.flatnonzero(smooth[b])
            d, j = tree.query(sim.true_xyz[b][cand, :2], k=1,
                              distance_upper_bound=OVERLAP_RADIUS_M)
            near = np.isfinite(d)
            cand, j = cand[near], j[near]
            if cand.size < MIN_PAIR_POINTS:
                continue
            if cand.size > pair_points:
                pick = np.sort(rng.choice(cand.size, pair_points, replace=False))
                cand, j = cand[pick], j[pick]
            pairs.append(TruthPair(a, b, cand, smooth_a[j]))
    return Truth(smooth, pairs, surface)


# ---------------------------------------------------------------------------- measures
@dataclass
class PairFigure:
    """Remaining discrepancy of one strip pair (metres), and how many queries were used."""

    a: int
    b: int
    rms: float
    used: int
    queried: int
    relative_3d_rms: float


def pair_discrepancy(xyz: Sequence[np.ndarray], true_xyz: Sequence[np.ndarray],
                     truth: Truth) -> list[PairFigure]:
    """Remaining strip-to-strip discrepancy, per overlapping pair.

    For each query point of strip ``b``: its :data:`PAIR_K` nearest neighbours (3D) in strip
    ``a`` (the method's coordinates), a least-squares plane through them (principal components),
    and the query's distance to that plane along its normal. A query is used if its neighbours
    are all smooth (truth), lie within :data:`PAIR_MAX_RADIUS_M`, fit a plane to
    :data:`PAIR_MAX_RESIDUAL_M` and spread in two directions. Independent of lidarcal's own QA
    (which measures point to TIN patch).

    Also, from the truth, the *relative 3D error* of the pair: for each query point and its
    partner in strip ``a`` (the nearest true point), the difference of their 3D errors
    ``(p_b - p_b,true) - (p_a - p_a,true)``; its RMS length. This sees the horizontal
    misalignment that a distance along the normal misses on flat ground.

    Parameters
    ----------
    xyz : list of (n_k, 3) float64
        Every strip's points as the method leaves them, map frame, metres.
    true_xyz : list of (n_k, 3) float64
        The true points of the same pulses, metres.
    truth : Truth

    Returns
    -------
    list of PairFigure
        RMS of the point-to-plane distances and of the relative 3D errors, metres.
    """
    trees: dict[int, cKDTree] = {}
    out = []
    for pair in truth.pairs:
        a, b, query = pair.a, pair.b, pair.query
        if a not in trees:
            trees[a] = cKDTree(xyz[a])
        p = xyz[b][query]
        d, nb = trees[a].query(p, k=PAIR_K)
        ok = np.isfinite(d[:, -1]) & (d[:, -1] <= PAIR_MAX_RADIUS_M)
        ok[ok] = truth.smooth[a][nb[ok]].all(axis=1)
        pts = xyz[a][nb[ok]]
        centre = pts.mean(axis=1)
        dev = pts - centre[:, None, :]
        cov = np.einsum("mki,mkj->mij", dev, dev) / PAIR_K
        w, v = np.linalg.eigh(cov)
        normal = v[:, :, 0]
        planar = (np.sqrt(np.maximum(w[:, 0], 0.0)) < PAIR_MAX_RESIDUAL_M) & \
            (np.sqrt(np.maximum(w[:, 1], 0.0)) > PAIR_MIN_SPREAD_M)
        dist = np.einsum("mi,mi->m", p[ok] - centre, normal)[planar]
        rms = float(np.sqrt(np.mean(dist**2))) if dist.size else math.nan
        rel = (p - true_xyz[b][query]) - (xyz[a][pair.partner] - true_xyz[a][pair.partner])
        rel_rms = float(np.sqrt(np.mean(np.einsum("ij,ij->i", rel, rel))))
        out.append(PairFigure(a, b, rms, int(dist.size), int(query.size), rel_rms))
    return out


@dataclass
class SurfaceFigure:
    """Error of the points against the simulated truth (metres), over the chosen points."""

    dz_median_abs: float
    dz_rms: float
    normal_rms: float
    err3d_rms: float
    n: int


def surface_error(sim: SimulatedMission, xyz: Sequence[np.ndarray],
                  truth: Truth) -> SurfaceFigure:
    """Error of the points against the true surface and the true points.

    ``dz = z - H(x, y)`` with ``H`` the simulated DSM at the point's own (corrected) planimetric
    position; the normal distance is ``dz * n_z`` with ``n_z`` the vertical component of the
    true surface normal there (exact on planes); the 3D error is ``|p - p_true|``, the distance
    to the (noise-free) point the pulse really hit. Over :attr:`Truth.surface` of every strip.

    Returns
    -------
    SurfaceFigure
        Metres.
    """
    dz_all, dn_all, e3_all = [], [], []
    for k, idx in enumerate(truth.surface):
        p = xyz[k][idx]
        h = sim.terrain.height(p[:, 0], p[:, 1])
        nz = sim.terrain.normal(p[:, 0], p[:, 1])[:, 2]
        dz = p[:, 2] - h
        dz_all.append(dz)
        dn_all.append(dz * nz)
        e3_all.append(np.linalg.norm(p - sim.true_xyz[k][idx], axis=1))
    dz = np.concatenate(dz_all)
    dn = np.concatenate(dn_all)
    e3 = np.concatenate(e3_all)
    return SurfaceFigure(float(np.median(np.abs(dz))), float(np.sqrt(np.mean(dz**2))),
                         float(np.sqrt(np.mean(dn**2))), float(np.sqrt(np.mean(e3**2))),
                         int(dz.size))


# ---------------------------------------------------------------------------- methods
@dataclass
class MethodResult:
    """Points a method leaves, its wall time (s) and notes to print."""

    name: str
    xyz: list[np.ndarray]
    seconds: float
    notes: list[str] = field(default_factory=list)
    cpu_seconds: float = math.nan


def run_lidarcal(sim: SimulatedMission) -> MethodResult:
    """``lidarcal calibrate`` + ``lidarcal correct`` in memory: the project API with the default
    flight configuration (``calibrate_mission``), then every point of every strip corrected with
    the estimate (``correct_columns``: eq. [13], range, incidence, reflectance)."""
    mission = sim.mission
    config = FlightConfig()
    c0 = time.process_time()
    t0 = time.perf_counter()
    result = calibrate_mission(mission, config)
    t1 = time.perf_counter()
    settings = CorrectionSettings.from_config(config, result.solution.delta)
    xyz = []
    not_corrected = 0
    for strip in mission.strips:
        cols = correct_columns(strip.xyz, strip.t, strip.intensity, mission.trajectory,
                               settings, source=f"strip {strip.strip_id}")
        not_corrected += int(np.count_nonzero(cols.flags & FLAG_NOT_CORRECTED))
        xyz.append(cols.xyz)
    t2 = time.perf_counter()
    cpu = time.process_time() - c0
    sol = result.solution
    truth = as_vector(sim.biases)
    errs = []
    for i, name in enumerate(PARAMETER_NAMES):
        if name not in sol.estimated:
            continue
        e = sol.delta[i] - truth[i]
        if name in ("domega", "dphi", "dkappa"):
            errs.append(f"{name} {e / ARCSEC:+.2f}\"")
        elif name == "dS":
            errs.append(f"{name} {e:+.1e}")
        else:
            errs.append(f"{name} {e * 1000:+.1f} mm")
    qa = [p.rms_after for p in result.pairs]
    notes = [
        f"calibrate {t1 - t0:.1f} s ({result.iterations} iterations, "
        f"{'converged' if result.converged else 'NOT converged'}), correct every point "
        f"{t2 - t1:.1f} s ({not_corrected} points left uncorrected)",
        "estimate - truth: " + ", ".join(errs),
        f"its own QA (point to TIN patch), RMS after: median {np.median(qa) * 100:.1f} cm, "
        f"worst {max(qa) * 100:.1f} cm over {len(qa)} pairs",
    ]
    return MethodResult("lidarcal", xyz, t2 - t0, notes, cpu)


def run_lidarcal_cli(sim: SimulatedMission) -> MethodResult:
    """``lidarcal calibrate`` and ``lidarcal correct`` of the :data:`SPEED` mission's bag as a
    user runs them (two processes, each timed from its start to its end: imports, reading the
    bag, writing the calibration file / the corrected bag), the corrected points read back
    from the output bag (``/lidar/points_corrected``) and put in the simulation's order."""
    meta = benchlib.prepare_mission(SPEED)
    if meta["n_points"] != sim.mission.n_points:
        raise SystemExit(f"the cached bag of {SPEED.key} holds {meta['n_points']} points, the "
                         f"simulation {sim.mission.n_points}: delete bench/.cache")
    with tempfile.TemporaryDirectory(prefix="lidarcal-peer-") as tmp:
        cal, out = Path(tmp) / "calibration.yaml", Path(tmp) / "corrected.mcap"
        steps = {}
        for name, cmd in (("calibrate", [benchlib.LIDARCAL, "calibrate", meta["bag"],
                                         "--control", meta["control"], "-o", str(cal)]),
                          ("correct", [benchlib.LIDARCAL, "correct", meta["bag"],
                                       "--calibration", str(cal), "-o", str(out)])):
            log = Path(tmp) / f"{name}.log"
            res = benchlib.run_child(cmd, log=log)
            if res["rc"] != 0:
                raise SystemExit(f"lidarcal {name} failed:\n{benchlib.tail(log)}")
            steps[name] = res
        estimate = benchlib.read_estimate(cal)
        xyz = corrected_points(out, sim)
    seconds = sum(r["wall_s"] for r in steps.values())
    same, lines = benchlib.compare_with_reference(SPEED.key, estimate)
    cal_s, cor_s = steps["calibrate"], steps["correct"]
    notes = [f"lidarcal calibrate {cal_s['wall_s']:.2f} s ({cal_s['cpu_s']:.1f} s CPU, peak "
             f"{cal_s['peak_mib']:.0f} MiB) + lidarcal correct {cor_s['wall_s']:.2f} s "
             f"({cor_s['cpu_s']:.1f} s CPU, peak {cor_s['peak_mib']:.0f} MiB) = "
             f"{seconds:.2f} s end to end",
             "estimate against the reference (bench/reference_estimates.json): "
             + {True: "every estimate within 0.1 sigma", False: "MOVED by more than 0.1 sigma",
                None: "no reference"}[same]]
    notes += [f"  {line}" for line in lines]
    return MethodResult("lidarcal CLI", xyz, seconds, notes,
                        sum(r["cpu_s"] for r in steps.values()))


def corrected_points(bag: Path, sim: SimulatedMission) -> list[np.ndarray]:
    """The corrected x, y, z of every strip of ``sim`` read back from a corrected bag, in the
    simulation's order (each strip's clouds in log-time order, which is its time order)."""
    from lidarcal_ros.io.bag.reader import open_bag
    from lidarcal_ros.io.cloud.pointcloud import cloud_to_array

    parts: dict[int, list[np.ndarray]] = {}
    times: dict[int, list[np.ndarray]] = {}
    with open_bag(bag) as reader:
        for _topic, msgtype, _ns, raw in reader.messages(["/lidar/points_corrected"]):
            pts = cloud_to_array(reader.deserialize(memoryview(raw), msgtype))
            for sid in np.unique(pts["strip_id"]):
                sel = pts[pts["strip_id"] == sid]
                parts.setdefault(int(sid), []).append(
                    np.column_stack([sel["x"], sel["y"], sel["z"]]))
                times.setdefault(int(sid), []).append(np.asarray(sel["t"]))
    out = []
    for strip in sim.mission.strips:
        t = np.concatenate(times[strip.strip_id])
        if not np.array_equal(t, strip.t):
            raise SystemExit(f"strip {strip.strip_id} of the corrected bag is not the "
                             "simulation's (delete bench/.cache)")
        out.append(np.concatenate(parts[strip.strip_id]))
    return out


def _overlap_cells(xyz: np.ndarray, cell: float = 10.0) -> set[int]:
    """Occupied horizontal grid cells of a strip (keys of ``cell``-metre cells)."""
    ij = np.floor(xyz[:, :2] / cell).astype(np.int64)
    return set(np.unique(ij[:, 0] * 1_000_003 + ij[:, 1]).tolist())


def registration_order(xyz: Sequence[np.ndarray]) -> list[int]:
    """Strip order for ICP: the reference first (largest overlap with all others), then
    greedily the strip overlapping the already-ordered ones most."""
    cells = [_overlap_cells(p) for p in xyz]
    n = len(cells)
    total = [sum(len(cells[i] & cells[j]) for j in range(n) if j != i) for i in range(n)]
    order = [int(np.argmax(total))]
    union = set(cells[order[0]])
    while len(order) < n:
        rest = [i for i in range(n) if i not in order]
        nxt = max(rest, key=lambda i: len(cells[i] & union))
        order.append(nxt)
        union |= cells[nxt]
    return order


def datum_shift(xyz: Sequence[np.ndarray], control: np.ndarray,
                radius_m: float = 3.0) -> float:
    """Vertical shift (m) that puts the strips on the control points: per control point, a
    least-squares plane ``z = a + b dx + c dy`` through all points within ``radius_m``
    (horizontal) of it, and ``z_control - a``; the mean over the control points."""
    shifts = []
    for cx, cy, cz in control:
        pts = []
        for p in xyz:
            near = np.hypot(p[:, 0] - cx, p[:, 1] - cy) <= radius_m
            pts.append(p[near])
        q = np.concatenate(pts)
        if q.shape[0] < 3:
            continue
        a = np.column_stack([np.ones(q.shape[0]), q[:, 0] - cx, q[:, 1] - cy])
        coef = np.linalg.lstsq(a, q[:, 2], rcond=None)[0]
        shifts.append(cz - coef[0])
    return float(np.mean(shifts)) if shifts else 0.0


def run_icp(o3d: Any, sim: SimulatedMission, mode: str, args: argparse.Namespace
            ) -> list[MethodResult]:
    """Rigid pairwise point-to-plane ICP (Open3D), then one vertical datum shift.

    Each strip is voxel-downsampled (``--icp-voxel``), its normals estimated by Open3D (hybrid
    radius / k search, oriented up) from its own points. The reference strip (largest overlap
    with the others) stays; every other strip, in :func:`registration_order`, is registered
    rigidly (6 DoF) to the *union* of the strips already aligned (``mode="union"``, cropped to
    the source's extent) or to the reference strip alone (``mode="ref"``), coarse to fine: the
    correspondence distances of ``--icp-distances`` with a Tukey robust kernel (``--icp-tukey``)
    on the point-to-plane residual. The transforms are applied to every point, then all strips
    are shifted vertically onto the control point (:func:`datum_shift`), as lidarcal also
    gets that control point. Coordinates are centred on the mission's mean for conditioning.

    With ``mode="union"`` and ``args.icp_mean``, a second result ``ICP-mean``: the same
    registration, then the whole block moved by the inverse of the mean strip pose (mean
    rotation and mean translation of all strips' transforms, the reference's identity
    included), so that no strip's own error is taken as the frame, then the datum shift.
    Its time is that of the registration (the re-centring costs milliseconds).

    Returns
    -------
    list of MethodResult
    """
    reg = o3d.pipelines.registration
    strips = [s.xyz for s in sim.mission.strips]
    c0 = time.process_time()
    t0 = time.perf_counter()
    centre = np.mean([p.mean(axis=0) for p in strips], axis=0)
    clouds = []
    for p in strips:
        pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(p - centre))
        if args.icp_voxel > 0:
            pc = pc.voxel_down_sample(args.icp_voxel)
        pc.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=args.icp_normal_radius,
                                                                 max_nn=args.icp_normal_nn))
        pc.orient_normals_to_align_with_direction(np.array([0.0, 0.0, 1.0]))
        clouds.append(pc)
    order = registration_order(strips)
    ref = order[0]
    transforms: dict[int, np.ndarray] = {ref: np.eye(4)}
    fits = []
    for i in order[1:]:
        source = clouds[i]
        if mode == "ref":
            target = clouds[ref]
        else:
            target = o3d.geometry.PointCloud()
            for j in transforms:
                target += copy.deepcopy(clouds[j]).transform(transforms[j])
            margin = 2.0 * max(args.icp_distances)
            box = o3d.geometry.AxisAlignedBoundingBox(
                source.get_min_bound() - margin, source.get_max_bound() + margin)
            target = target.crop(box)
        t = np.eye(4)
        res = None
        for dist, k in zip(args.icp_distances, args.icp_tukey):
            res = reg.registration_icp(
                source, target, dist, t,
                reg.TransformationEstimationPointToPlane(reg.TukeyLoss(k=k)),
                reg.ICPConvergenceCriteria(max_iteration=args.icp_iterations))
            t = np.asarray(res.transformation)
        transforms[i] = t
        assert res is not None
        rv = Rotation.from_matrix(t[:3, :3]).as_rotvec() / ARCSEC
        fits.append(f"{sim.mission.strips[i].strip_id}: t=({t[0, 3] * 100:+.0f}, "
                    f"{t[1, 3] * 100:+.0f}, {t[2, 3] * 100:+.0f}) cm, rot=({rv[0]:+.0f}, "
                    f"{rv[1]:+.0f}, {rv[2]:+.0f})\", fitness {res.fitness:.2f}")
    t_reg = time.perf_counter() - t0
    cpu_reg = time.process_time() - c0
    notes = [f"reference strip {sim.mission.strips[ref].strip_id}, order "
             + " ".join(str(sim.mission.strips[i].strip_id) for i in order)
             + f"; registration {t_reg:.1f} s",
             "transforms (translation at the mission centre; rotation vector, arcsec): "
             + "; ".join(fits)]
    variants: list[tuple[str, dict[int, np.ndarray]]] = [(f"ICP-{mode}", transforms)]
    if mode == "union" and args.icp_mean:
        keys = sorted(transforms)
        mean = np.eye(4)
        mean[:3, :3] = Rotation.from_matrix([transforms[k][:3, :3] for k in keys]).mean() \
            .as_matrix()
        mean[:3, 3] = np.mean([transforms[k][:3, 3] for k in keys], axis=0)
        back = np.linalg.inv(mean)
        variants.append(("ICP-mean", {k: back @ transforms[k] for k in keys}))
    out = []
    for name, tf in variants:
        t1 = time.perf_counter()
        c1 = time.process_time()
        xyz = []
        for k, p in enumerate(strips):
            t = tf[k]
            xyz.append((p - centre) @ t[:3, :3].T + t[:3, 3] + centre)
        shift = 0.0
        if sim.mission.control is not None and len(sim.mission.control):
            shift = datum_shift(xyz, sim.mission.control.xyz)
            for p in xyz:
                p[:, 2] += shift
        seconds = t_reg + time.perf_counter() - t1
        cpu = cpu_reg + time.process_time() - c1
        extra = f"datum shift to the control point {shift * 100:+.1f} cm"
        if name == "ICP-mean":
            r = tf[ref]
            rv = Rotation.from_matrix(r[:3, :3]).as_rotvec() / ARCSEC
            extra = (f"the registration of ICP-union, re-centred on the mean pose (moves the "
                     f"reference strip by ({r[0, 3] * 100:+.0f}, {r[1, 3] * 100:+.0f}, "
                     f"{r[2, 3] * 100:+.0f}) cm, ({rv[0]:+.0f}, {rv[1]:+.0f}, {rv[2]:+.0f})\"); "
                     + extra)
            out.append(MethodResult(name, xyz, seconds, [extra], cpu))
        else:
            out.append(MethodResult(name, xyz, seconds, [*notes, extra], cpu))
    return out


# ---------------------------------------------------------------------------- report
@dataclass
class Row:
    """One line of the table (distances in metres, times in seconds)."""

    name: str
    seconds: float
    cpu_seconds: float
    pair_median: float
    pair_worst: float
    rel3d_median: float
    rel3d_worst: float
    dz_median_abs: float
    dz_rms: float
    normal_rms: float
    err3d_rms: float
    used: int
    worst_pair: str


MEASURES: tuple[tuple[str, str], ...] = (
    ("pair_median", "pair med"), ("pair_worst", "pair max"),
    ("rel3d_median", "rel3D med"), ("rel3d_worst", "rel3D max"),
    ("dz_median_abs", "|dz| med"), ("dz_rms", "dz RMS"), ("normal_rms", "dn RMS"),
    ("err3d_rms", "3D RMS"),
)
#: Two methods within this relative difference on a measure are reported as a tie.
TIE = 0.03


def measure(res: MethodResult, sim: SimulatedMission, truth: Truth) -> Row:
    """All figures of one method's points."""
    pairs = pair_discrepancy(res.xyz, sim.true_xyz, truth)
    rms = np.array([p.rms for p in pairs])
    rel = np.array([p.relative_3d_rms for p in pairs])
    worst = pairs[int(np.nanargmax(rms))]
    ids = [s.strip_id for s in sim.mission.strips]
    surf = surface_error(sim, res.xyz, truth)
    return Row(res.name, res.seconds, res.cpu_seconds, float(np.nanmedian(rms)),
               float(np.nanmax(rms)), float(np.median(rel)), float(np.max(rel)),
               surf.dz_median_abs, surf.dz_rms, surf.normal_rms,
               surf.err3d_rms, sum(p.used for p in pairs), f"{ids[worst.a]} & {ids[worst.b]}")


def _seconds(value: float) -> str:
    return "-" if math.isnan(value) else f"{value:.1f}"


def format_table(rows: Sequence[Row]) -> list[str]:
    """The figures (distances in cm, times in s) and the ratios to the ``none`` row."""
    head = (f"{'method':<10} {'wall s':>6} {'CPU s':>6}"
            + "".join(f" {label:>9}" for _, label in MEASURES))
    lines = [head + f" {'worst pair':>10} {'pair pts':>8}"]
    for r in rows:
        lines.append(f"{r.name:<10} {_seconds(r.seconds):>6} {_seconds(r.cpu_seconds):>6}"
                     + "".join(f" {getattr(r, key) * 100:>9.1f}" for key, _ in MEASURES)
                     + f" {r.worst_pair:>10} {r.used:>8}")
    base = next((r for r in rows if r.name == "none"), None)
    if base is not None:
        lines.append("")
        lines.append(f"{'ratio/none':<10} {'':>6} {'':>6}"
                     + "".join(f" {label:>9}" for _, label in MEASURES))
        for r in rows:
            if r is base:
                continue
            lines.append(f"{r.name:<10} {'':>6} {'':>6}" + "".join(
                f" {getattr(r, key) / getattr(base, key):>9.3f}" for key, _ in MEASURES))
    return lines


def best_per_measure(rows: Sequence[Row]) -> list[str]:
    """Per measure, which method (not ``none``, not the floor) is best, or which tie (within
    :data:`TIE`), and the next best."""
    methods = [r for r in rows if r.name not in ("none", "floor")]
    out = []
    for key, label in MEASURES:
        ranked = sorted(methods, key=lambda r: getattr(r, key))
        best = getattr(ranked[0], key)
        tied = [r for r in ranked if getattr(r, key) <= best * (1.0 + TIE)]
        rest = ranked[len(tied):]
        figures = ", ".join(f"{r.name} {getattr(r, key) * 100:.2f} cm" for r in ranked)
        verdict = (f"best: {tied[0].name}" if len(tied) == 1
                   else "tie: " + ", ".join(r.name for r in tied))
        if rest and len(tied) == 1:
            verdict += f", {getattr(rest[0], key) / best:.1f}x lower than {rest[0].name}"
        out.append(f"  {label:<13} {verdict}  ({figures})")
    return out


def run_mission(spec: MissionSpec, o3d: Any, args: argparse.Namespace) -> list[Row]:
    """Simulate one mission, run every method, print its tables; returns the rows."""
    t0 = time.perf_counter()
    sim = simulate(spec)
    t_sim = time.perf_counter() - t0
    truth = build_truth(sim, args.pair_points, args.surface_points)
    t_truth = time.perf_counter() - t0 - t_sim
    b = sim.biases
    print(f"\n=== mission {spec.name}: seed {spec.seed}, density {spec.density} pts/m^2, "
          f"{spec.line_length_m:.0f} m lines, {len(sim.mission.strips)} strips, "
          f"{sim.mission.n_points} points (simulated in {t_sim:.1f} s, evaluation points "
          f"chosen in {t_truth:.1f} s)")
    print("    biases: " + ", ".join(
        f"{n} {b[n] / ARCSEC:+.0f}\"" if n in ("domega", "dphi", "dkappa")
        else (f"{n} {b[n]:+.1e}" if n == "dS" else f"{n} {b[n] * 100:+.1f} cm")
        for n in PARAMETER_NAMES))
    n_smooth = sum(int(m.sum()) for m in truth.smooth)
    print(f"    smooth points {n_smooth} of {sim.mission.n_points}; {len(truth.pairs)} "
          f"overlapping pairs, up to {args.pair_points} queries each; "
          f"{sum(s.size for s in truth.surface)} points against the true surface")
    sys.stdout.flush()

    results: list[tuple[MethodResult, Row]] = []
    raw = MethodResult("none", [s.xyz for s in sim.mission.strips], 0.0, cpu_seconds=0.0)
    results.append((raw, measure(raw, sim, truth)))
    runners: list[Callable[[], list[MethodResult]]] = [lambda: [run_lidarcal(sim)]]
    if spec.name == "speed":
        runners.append(lambda: [run_lidarcal_cli(sim)])
    for mode in args.icp:
        runners.append(lambda mode=mode: run_icp(o3d, sim, mode, args))
    for run in runners:
        for res in run():
            results.append((res, measure(res, sim, truth)))
            print(f"    {res.name}: done in {res.seconds:.1f} s")
        sys.stdout.flush()
    if not args.no_floor:
        floor = MethodResult("floor", [s.xyz for s in simulate(spec, biased=False).mission.strips],
                             math.nan)
        results.append((floor, measure(floor, sim, truth)))
    rows = [r for _, r in results]
    print()
    for line in format_table(rows):
        print("  " + line)
    print("\n  per measure, among lidarcal and ICP (ties within "
          f"{TIE * 100:.0f}%):")
    for line in best_per_measure(rows):
        print("  " + line)
    cli = next((r for r, _ in results if r.name == "lidarcal CLI"), None)
    icp = next((r for r, _ in results if r.name == "ICP-union"), None)
    if cli is not None and icp is not None:
        ratio = cli.seconds / icp.seconds
        print(f"\n  speed: lidarcal calibrate + correct end to end {cli.seconds:.2f} s, "
              f"ICP-union {icp.seconds:.2f} s (in process, from strips in memory): "
              f"{ratio:.2f}x the peer's wall time (goal <= 1: "
              f"{'met' if ratio <= 1.0 else 'NOT met'})")
    print("\n  notes:")
    for res, _ in results:
        for note in res.notes:
            print(f"    {res.name}: {note}")
    sys.stdout.flush()
    return rows


def import_open3d() -> Any:
    """Open3D, quiet; exits with one line if it cannot be imported."""
    try:
        import open3d as o3d
    except Exception as exc:  # ImportError, or OSError for a missing shared library
        first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        print(f"bench_peer_icp: cannot import open3d ({first}); install it: as root "
              "`apt-get update && apt-get install -y libusb-1.0-0`, then "
              "`.venv/bin/pip install open3d==0.20.0`", file=sys.stderr)
        raise SystemExit(2) from None
    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    return o3d


def main(argv: Sequence[str] | None = None) -> int:
    """Run lidarcal and the ICP variants on the missions of the command line and print the
    comparison; exit status 0."""
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--quick", action="store_true",
                    help="small missions (density 0.15, 400 m lines)")
    ap.add_argument("--missions", nargs="+", choices=("speed", "paper", "strong"),
                    default=["speed", "paper", "strong"])
    ap.add_argument("--icp", nargs="+", choices=("union", "ref"), default=["union", "ref"],
                    help="ICP variants: to the union of the aligned strips, to the reference")
    ap.add_argument("--pair-points", type=int, default=30_000,
                    help="discrepancy queries per strip pair (at most)")
    ap.add_argument("--surface-points", type=int, default=150_000,
                    help="points per strip measured against the true surface (at most)")
    ap.add_argument("--icp-voxel", type=float, default=1.0,
                    help="voxel size of the ICP downsampling, m (0: none)")
    ap.add_argument("--icp-normal-radius", type=float, default=4.0,
                    help="radius of Open3D's normal estimation, m")
    ap.add_argument("--icp-normal-nn", type=int, default=20,
                    help="most neighbours of Open3D's normal estimation")
    ap.add_argument("--icp-distances", type=float, nargs="+", default=[3.0, 2.0, 1.5],
                    help="max correspondence distances of the coarse-to-fine stages, m")
    ap.add_argument("--icp-tukey", type=float, nargs="+", default=[1.0, 0.5, 0.25],
                    help="Tukey kernel width of each stage (point-to-plane residual), m")
    ap.add_argument("--icp-iterations", type=int, default=30,
                    help="ICP iterations per stage (at most)")
    ap.add_argument("--no-icp-mean", dest="icp_mean", action="store_false",
                    help="skip the ICP-mean row (union registration re-centred on the mean "
                         "strip pose)")
    ap.add_argument("--no-floor", action="store_true",
                    help="skip the unbiased (noise floor) simulation")
    args = ap.parse_args(argv)
    if len(args.icp_tukey) != len(args.icp_distances):
        ap.error("--icp-tukey needs one value per --icp-distances stage")
    o3d = import_open3d()
    t0 = time.perf_counter()
    load = os.getloadavg()[0]
    print(f"bench_peer_icp: open3d {o3d.__version__}, numpy {np.__version__}, "
          f"{os.cpu_count()} CPUs, load average {load:.2f}")
    print("all distances in cm; time = wall seconds from the delivered strips to the "
          "corrected / aligned points")
    for spec in mission_specs(args.quick):
        if spec.name in args.missions:
            run_mission(spec, o3d, args)
    print(f"\ntotal {time.perf_counter() - t0:.0f} s; load average at the end "
          f"{os.getloadavg()[0]:.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
