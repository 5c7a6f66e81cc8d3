"""A mission bag read for a bounded-memory calibration (``calibration.memory: bounded``).

Three passes over the bag (:mod:`lidarcal_ros.core.calibration.bounded`): the strips'
footprints, sizes and spans; each pair's candidate points; the surface strips' points near
the candidates and every strip's points near a control point. What is held does not grow with
the mission beyond ``matching.max_candidates_per_pair`` candidates a pair and their
neighbourhoods. Map frame, metres; seconds.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from lidarcal_ros.core.calibration.bounded import (
    LowestPriority,
    NearCandidates,
    StripExtent,
    control_cells,
    neighbourhood_radius,
    plan_pairs,
)
from lidarcal_ros.core.calibration.calibrate import Progress, WholeStrips
from lidarcal_ros.core.calibration.pairs import FootprintGrid
from lidarcal_ros.core.config import FlightConfig
from lidarcal_ros.core.georeferencing.heading import HeadingSource, check_orientation
from lidarcal_ros.core.georeferencing.laser_geometry import PositioningModel
from lidarcal_ros.core.georeferencing.rigorous import check_model_setting
from lidarcal_ros.core.mission import Mission, Strip
from lidarcal_ros.errors import InputError
from lidarcal_ros.io.bag.mission_blocks import MissionBlocks
from lidarcal_ros.io.survey.control import read_control_csv

logger = logging.getLogger(__name__)

#: Radius of the surface strip's points held around a candidate, in its point spacings
#: (the candidate's patch, its neighbours for the bend test and Delaunay's reach beyond
#: them), plus ``matching.max_normal_distance_m`` for how far the estimate moves it.
NEIGHBOURHOOD_SPACINGS = 8.0


@dataclass
class ReducedMission(Mission):
    """A mission whose strips hold only the points a calibration matches (``whole``: by strip
    id, the whole strip's extent and the sampling priority of each point held)."""

    whole: WholeStrips = field(default_factory=dict)

    @property
    def n_points(self) -> int:
        """The points of the whole strips (not those held)."""
        return sum(extent.n_points for extent, _ in self.whole.values())

    @property
    def n_held(self) -> int:
        """The points held."""
        return sum(len(s) for s in self.strips)


def load_reduced_mission(
    bag: str | Path, config: FlightConfig, *, control_csv: str | Path | None = None,
    progress: Progress | None = None, spacings: float = NEIGHBOURHOOD_SPACINGS,
    margin_m: float | None = None,
) -> ReducedMission:
    """Read ``bag`` in three passes into the reduced mission of a bounded-memory calibration
    (:func:`~lidarcal_ros.pipeline.calibration.procedure.load_mission`'s topics, control
    points and checks). The surface strip's points are held within ``spacings`` of its point
    spacings plus ``margin_m`` (m; None: ``matching.max_normal_distance_m``) of a candidate
    (:data:`NEIGHBOURHOOD_SPACINGS`).

    Raises
    ------
    BagError, CloudFormatError, InputError, ConfigError
        As ``load_mission``.
    """
    report = progress or (lambda stage, frac: None)
    settings = config.calibration_settings()
    cell = settings.overlap_cell_m
    blocks = MissionBlocks(
        bag, points_topic=config["topics.points"], trajectory_topic=config["topics.trajectory"],
        control_topic=config["topics.control_points"], time_field=config["time_field"],
        thinning_cell_m=config["calibration.thinning_cell_m"],
        coordinate_tolerance_m=config["sensor.range_noise_m"])

    # pass 1: footprints, sizes, spans
    report("reading the bag (1/3: footprints)", 0.0)
    extents: dict[int, StripExtent] = {}
    last_t: dict[int, float] = {}
    unordered: set[int] = set()
    for piece in _pieces(blocks):
        ext = extents.setdefault(piece.strip_id, StripExtent(piece.strip_id, cell))
        if piece.t.size and piece.t[0] < last_t.get(piece.strip_id, -np.inf):
            unordered.add(piece.strip_id)
        ext.add(piece.xyz, piece.t)
        if piece.t.size:
            last_t[piece.strip_id] = float(piece.t[-1])
    if not extents:
        raise InputError(f"{bag}: no finite point on {config['topics.points']}")
    if unordered:
        logger.warning("%s: the clouds of strips %s come out of time order: their sample "
                       "points differ from those of calibration.memory whole", bag,
                       ", ".join(map(str, sorted(unordered))))
    trajectory = blocks.trajectory
    assert trajectory is not None
    check_orientation(HeadingSource(config["matching.heading_source"]), trajectory, str(bag))
    check_model_setting(PositioningModel(config["matching.model"]), trajectory, str(bag))
    control = blocks.control
    csv = control_csv or config["calibration.control_points_file"] or None
    if csv:
        control = read_control_csv(csv)
    ids = sorted(extents)
    ordered = [extents[sid].finish() for sid in ids]
    plans = plan_pairs(ordered, footprint=FootprintGrid(cell),
                       min_overlap_cells=settings.min_overlap_cells)

    # pass 2: each pair's candidates (the points of lowest priority in its zone)
    report("reading the bag (2/3: candidates)", 1 / 3)
    lowest = [LowestPriority(settings.max_candidates_per_pair) for _ in plans]
    for k, piece, index, priority in _numbered(blocks, ids, settings.seed):
        keys = FootprintGrid(cell).keys(piece.xyz)
        for plan, lowest_k in zip(plans, lowest, strict=True):
            if plan.a == k:
                inside = np.isin(keys, plan.zone)
                lowest_k.add(priority[inside], index[inside], piece.xyz[inside, :2])
    chosen = [lowest_k.result() for lowest_k in lowest]

    # pass 3: the candidates, the surface strips' points near them, the points near control
    report("reading the bag (3/3: neighbourhoods)", 2 / 3)
    near_control = control_cells(control.xyz[:, :2], cell) if control is not None and \
        len(control) else np.empty(0, np.int64)
    own: list[np.ndarray] = []
    near: list[NearCandidates] = []
    for k, ext in enumerate(ordered):
        own.append(np.unique(np.concatenate(
            [np.empty(0, np.int64)] + [idx for plan, (idx, _) in zip(plans, chosen, strict=True)
                                       if plan.a == k])))
        xy = [xy for plan, (_, xy) in zip(plans, chosen, strict=True) if plan.b == k]
        radius = neighbourhood_radius(ext.density, spacings=spacings,
                                      margin_m=settings.max_normal_distance_m
                                      if margin_m is None else margin_m)
        near.append(NearCandidates(np.concatenate([np.empty((0, 2)), *xy]), radius,
                                   near_control, cell))
    held: dict[int, list[tuple[np.ndarray, np.ndarray, np.ndarray]]] = {k: [] for k in
                                                                         range(len(ids))}
    for k, piece, index, priority in _numbered(blocks, ids, settings.seed):
        keep = near[k](piece.xyz[:, :2]) | np.isin(index, own[k])
        if keep.any():
            held[k].append((piece.xyz[keep], piece.t[keep], priority[keep]))
    strips, whole = [], {}
    for k, sid in enumerate(ids):
        parts = held.pop(k)
        xyz = np.concatenate([np.empty((0, 3))] + [p[0] for p in parts])
        t = np.concatenate([np.empty(0)] + [p[1] for p in parts])
        strips.append(Strip(sid, xyz, t))
        whole[sid] = (ordered[k], np.concatenate([np.empty(0)] + [p[2] for p in parts]))
    report("reading the bag", 1.0)
    mission = ReducedMission(trajectory, strips, control, blocks.frame,
                             blocks.dropped_non_finite, 0, whole=whole)
    logger.info("%s: %d of %d points held for %d strip pairs", bag, mission.n_held,
                mission.n_points, len(plans))
    return mission


def _pieces(blocks: MissionBlocks) -> Iterator[Strip]:
    """Every cloud's points by strip, in the bag's order (one pass)."""
    for pieces in blocks.clouds():
        yield from pieces


def _numbered(blocks: MissionBlocks, ids: list[int], seed: int
              ) -> Iterator[tuple[int, Strip, np.ndarray, np.ndarray]]:
    """One pass: each piece with its strip's position in ``ids``, the index of each point in
    its strip (in the bag's order, which is the strip's time order) and its sampling
    priority (one PCG64 draw a point, seeded as ``PairMatcher`` seeds a whole strip's)."""
    position = {sid: k for k, sid in enumerate(ids)}
    rngs = {sid: np.random.default_rng([seed, sid]) for sid in ids}
    counts = dict.fromkeys(ids, 0)
    for piece in _pieces(blocks):
        sid, n = piece.strip_id, len(piece)
        index = np.arange(counts[sid], counts[sid] + n, dtype=np.int64)
        counts[sid] += n
        yield position[sid], piece, index, rngs[sid].random(n)


__all__ = ["NEIGHBOURHOOD_SPACINGS", "ReducedMission", "load_reduced_mission"]
