"""A mission bag read for a bounded-memory calibration (``calibration.memory: bounded``).

Four passes over the bag (:mod:`lidarcal_ros.core.calibration.bounded`): the strips'
footprints, sizes and spans; each pair's candidate points; each pair's sample, chosen from
its candidates as the surface strip's points near them go by; the sample points, the surface
strips' points near them and every strip's points near a control point. What is held does
not grow with the mission beyond the pairs' samples and their neighbourhoods. Map frame,
metres; seconds.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from lidarcal_ros.core.calibration.bounded import (
    ChosenSamples,
    LowestPriority,
    NearCandidates,
    SampleChooser,
    StripExtent,
    control_cells,
    in_sorted,
    neighbourhood_radius,
    plan_pairs,
)
from lidarcal_ros.core.calibration.calibrate import CalibrationSettings, Progress, WholeStrips
from lidarcal_ros.core.calibration.pairs import FootprintGrid
from lidarcal_ros.core.config import FlightConfig
from lidarcal_ros.core.georeferencing.heading import HeadingSource, check_orientation
from lidarcal_ros.core.georeferencing.laser_geometry import PositioningModel
from lidarcal_ros.core.georeferencing.rigorous import check_model_setting
from lidarcal_ros.core.mission import Mission, Strip
from lidarcal_ros.errors import InputError
from lidarcal_ros.io.bag.mission_blocks import MissionBlocks
from lidarcal_ros.io.survey.control import read_control_csv
from lidarcal_ros.pipeline.executor import (
    CommandTasks,
    Executor,
    deal_heaviest_first,
    results_in_order,
)

logger = logging.getLogger(__name__)

#: Radius of the surface strip's points a candidate is matched to when the samples are
#: chosen (at zero correction: no margin), in its point spacings.
CHOICE_SPACINGS = 8.0

#: Radius of the surface strip's points held around a sample point, in its point spacings
#: (the patch under it and Delaunay's reach), plus :data:`NEIGHBOURHOOD_MARGIN_M` for how
#: far the estimate moves it: some 30-45 points a sample point at 0.1-0.5 points/m^2 (against
#: 8 spacings and 2 m, 280 points at 0.5 points/m^2, the estimate moves by 0.05 sigma at
#: most on the test and benchmark missions; 2 spacings and 1 m reach 0.13 sigma:
#: bench/README.md, "Scaling to large missions").
NEIGHBOURHOOD_SPACINGS = 3.0
#: See :data:`NEIGHBOURHOOD_SPACINGS`, m.
NEIGHBOURHOOD_MARGIN_M = 1.0


@dataclass
class ReducedMission(Mission):
    """A mission whose strips hold only the points a calibration matches (``whole``: by strip
    id, the whole strip's extent and the sampling priority of each point held)."""

    whole: WholeStrips = field(default_factory=dict)
    #: Each strip pair's sample points, chosen while reading (:class:`ChosenSamples`).
    samples: ChosenSamples = field(default_factory=dict)
    #: Most surface points held at once while the samples were chosen.
    held_choosing: int = 0

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
    margin_m: float = NEIGHBOURHOOD_MARGIN_M, executor: Executor | None = None,
) -> ReducedMission:
    """Read ``bag`` in four passes into the reduced mission of a bounded-memory calibration
    (:func:`~lidarcal_ros.pipeline.calibration.procedure.load_mission`'s topics, control
    points and checks). The surface strip's points are held within ``spacings`` of its point
    spacings plus ``margin_m`` (m) of a sample point (:data:`NEIGHBOURHOOD_SPACINGS`). With
    ``executor``, the pairs' samples are chosen on its workers, which read the bag by its
    path (the same samples).

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

    # pass 1: footprints (with the last cloud in each cell), sizes, spans
    report("reading the bag (1/4: footprints)", 0.0)
    extents: dict[int, StripExtent] = {}
    last_t: dict[int, float] = {}
    unordered: set[int] = set()
    for block, piece in _pieces(blocks):
        ext = extents.setdefault(piece.strip_id, StripExtent(piece.strip_id, cell))
        if piece.t.size and piece.t[0] < last_t.get(piece.strip_id, -np.inf):
            unordered.add(piece.strip_id)
        ext.add(piece.xyz, piece.t, block=block)
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
    report("reading the bag (2/4: candidates)", 1 / 4)
    lowest = [LowestPriority(settings.max_candidates_per_pair) for _ in plans]
    for k, piece, index, priority in _numbered(blocks, ids, settings.seed):
        keys = FootprintGrid(cell).keys(piece.xyz)
        for plan, lowest_k in zip(plans, lowest, strict=True):
            if plan.a == k:
                inside = in_sorted(plan.zone, keys)
                lowest_k.add(priority[inside], index[inside], piece.xyz[inside])
    choosers = [_chooser(lowest_k.result(), ordered[plan.b], settings)
                for plan, lowest_k in zip(plans, lowest, strict=True)]
    del lowest

    # pass 3: each pair's sample, its candidates matched at zero correction as the surface
    # strip's points near them go by (held only until the candidates near them are matched)
    report("reading the bag (3/4: samples)", 2 / 4)
    surfaces = [ids[plan.b] for plan in plans]
    chosen, peak_choosing = _choose_samples(blocks, choosers, surfaces, cell, executor)
    del choosers

    # pass 4: the sample points, the surface strips' points near them, the points near control
    report("reading the bag (4/4: neighbourhoods)", 3 / 4)
    near_control = control_cells(control.xyz[:, :2], cell) if control is not None and \
        len(control) else np.empty(0, np.int64)
    own: list[np.ndarray] = []
    near: list[NearCandidates] = []
    for k, ext in enumerate(ordered):
        own.append(np.unique(np.concatenate(
            [np.empty(0, np.int64)] + [sample for plan, (sample, _, _) in
                                       zip(plans, chosen, strict=True) if plan.a == k])))
        xy = [xyz[:, :2] for plan, (_, xyz, _) in zip(plans, chosen, strict=True)
              if plan.b == k]
        radius = neighbourhood_radius(ext.density, spacings=spacings, margin_m=margin_m)
        near.append(NearCandidates(np.concatenate([np.empty((0, 2)), *xy]), radius,
                                   near_control, cell))
    held: dict[int, list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]] = {
        k: [] for k in range(len(ids))}
    for k, piece, index, priority in _numbered(blocks, ids, settings.seed):
        keep = near[k](piece.xyz[:, :2]) | in_sorted(own[k], index)
        if keep.any():
            held[k].append((piece.xyz[keep], piece.t[keep], priority[keep], index[keep]))
    strips, whole, held_index = [], {}, []
    for k, sid in enumerate(ids):
        parts = held.pop(k)
        xyz = np.concatenate([np.empty((0, 3))] + [p[0] for p in parts])
        t = np.concatenate([np.empty(0)] + [p[1] for p in parts])
        strips.append(Strip(sid, xyz, t))
        whole[sid] = (ordered[k], np.concatenate([np.empty(0)] + [p[2] for p in parts]))
        held_index.append(np.concatenate([np.empty(0, np.int64)] + [p[3] for p in parts]))
    samples = {(ids[plan.a], ids[plan.b]): (np.searchsorted(held_index[plan.a], sample), before)
               for plan, (sample, _, before) in zip(plans, chosen, strict=True)}
    report("reading the bag", 1.0)
    mission = ReducedMission(trajectory, strips, control, blocks.frame,
                             blocks.dropped_non_finite, 0, whole=whole, samples=samples,
                             held_choosing=peak_choosing)
    logger.info("%s: %d of %d points held for %d strip pairs (%d held at most while "
                "choosing their samples)", bag, mission.n_held, mission.n_points, len(plans),
                peak_choosing)
    return mission


def _choose_samples(blocks: MissionBlocks, choosers: list[SampleChooser], surfaces: list[int],
                    cell: float, executor: Executor | None
                    ) -> tuple[list[tuple[np.ndarray, np.ndarray, np.ndarray]], int]:
    """Pass 3 (:func:`choose_in_pass`) here, or with ``executor`` in as many tasks as it has
    workers, each choosing some pairs' samples on its own pass over the bag (read from its
    path); the results in the order of ``choosers``, and the surface points held at most (with
    tasks: the sum of theirs)."""
    places = executor.places() if executor is not None else []
    if executor is None or len(places) < 2 or len(choosers) < 2:
        return choose_in_pass(blocks, choosers, surfaces, cell)
    # the pairs dealt to the tasks largest first, each to the one with the fewest
    # candidates (the matching's work grows with them)
    groups: list[list[int]] = [[] for _ in places[:len(choosers)]]
    for i, g in enumerate(deal_heaviest_first([(len(c.index),) for c in choosers],
                                              [(0,)] * len(groups))):
        groups[g].append(i)
    tasks = CommandTasks(executor, "calibrate")
    futures = [tasks.submit(choose_in_pass, blocks, [choosers[i] for i in group],
                            [surfaces[i] for i in group], cell, key=f"samples{g}", place=place)
               for g, (group, place) in enumerate(zip(groups, places, strict=False))]
    chosen: list[tuple[np.ndarray, np.ndarray, np.ndarray] | None] = [None] * len(choosers)
    peak = 0
    for group, (results, held) in zip(groups, results_in_order(futures), strict=True):
        for i, result in zip(group, results, strict=True):
            chosen[i] = result
        peak += held
    return [c for c in chosen if c is not None], peak


def choose_in_pass(blocks: MissionBlocks, choosers: list[SampleChooser], surfaces: list[int],
                   cell: float) -> tuple[list[tuple[np.ndarray, np.ndarray, np.ndarray]], int]:
    """One pass over the bag of ``blocks`` offering each chooser its surface strip's points
    (``surfaces``: that strip's id, by chooser; ``cell``: the footprint cell, m): each
    chooser's :meth:`~lidarcal_ros.core.calibration.bounded.SampleChooser.result`, and the
    surface points held at most (a task of :func:`load_reduced_mission` with an executor)."""
    users: dict[int, list[SampleChooser]] = {}
    for chooser, sid in zip(choosers, surfaces, strict=True):
        users.setdefault(sid, []).append(chooser)
    grid = FootprintGrid(cell)
    peak = 0
    for _, piece in _pieces(blocks, passed=choosers):
        offered = users.get(piece.strip_id)
        if offered:
            keys = grid.keys(piece.xyz)
            for chooser in offered:
                chooser.offer(piece.xyz, keys)
            peak = max(peak, sum(c.held for c in choosers))
    return [chooser.result() for chooser in choosers], peak


def _chooser(candidates: tuple[np.ndarray, np.ndarray, np.ndarray], surface: StripExtent,
             settings: CalibrationSettings) -> SampleChooser:
    """The :class:`SampleChooser` of a pair's ``candidates`` (strip indices, x y z,
    priorities) against the whole strip ``surface``, matching an eighth of them or 8192 at
    a time (one TIN each)."""
    index, xyz, priority = candidates
    radius = neighbourhood_radius(surface.density, spacings=CHOICE_SPACINGS, margin_m=0.0)
    return SampleChooser(
        index, xyz, priority, surface.last_block_near(xyz[:, :2], radius), radius=radius,
        quality=settings.tin_quality(surface.density), threshold=settings.max_normal_distance_m,
        per_class_cap=settings.per_class_cap, flat_class_factor=settings.flat_class_factor,
        cell=settings.overlap_cell_m, batch=min(8192, max(64, len(index) // 8)))


def _pieces(blocks: MissionBlocks, *, passed: Sequence[SampleChooser] = ()
            ) -> Iterator[tuple[int, Strip]]:
    """Every cloud's points by strip, in the bag's order, with the cloud's number (one pass);
    ``passed`` told of each cloud once all its pieces have gone by, and of the end."""
    block = -1
    for block, pieces in enumerate(blocks.clouds()):
        for piece in pieces:
            yield block, piece
        for chooser in passed:
            chooser.passed(block)


def _numbered(blocks: MissionBlocks, ids: list[int], seed: int
              ) -> Iterator[tuple[int, Strip, np.ndarray, np.ndarray]]:
    """One pass: each piece with its strip's position in ``ids``, the index of each point in
    its strip (in the bag's order, which is the strip's time order) and its sampling
    priority (one PCG64 draw a point, seeded as ``PairMatcher`` seeds a whole strip's)."""
    position = {sid: k for k, sid in enumerate(ids)}
    rngs = {sid: np.random.default_rng([seed, sid]) for sid in ids}
    counts = dict.fromkeys(ids, 0)
    for _, piece in _pieces(blocks):
        sid, n = piece.strip_id, len(piece)
        index = np.arange(counts[sid], counts[sid] + n, dtype=np.int64)
        counts[sid] += n
        yield position[sid], piece, index, rngs[sid].random(n)


__all__ = ["CHOICE_SPACINGS", "NEIGHBOURHOOD_MARGIN_M", "NEIGHBOURHOOD_SPACINGS", "ReducedMission",
           "choose_in_pass", "load_reduced_mission"]
