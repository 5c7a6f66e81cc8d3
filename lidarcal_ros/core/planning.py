"""Flight planning: which parameters a planned flight will be able to calibrate.

The planned lines simulated and matched as ``lidarcal calibrate`` would, the normal matrix
analysed (docs/method.md section 7; docs/internals.md, "Flight planning").
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from lidarcal_ros.core.adjustment.least_squares import (
    NormalEquations,
    ObservabilityLimits,
    ParameterState,
    solve,
)
from lidarcal_ros.core.adjustment.strip_blocks import StripBlocks
from lidarcal_ros.core.calibration.calibrate import CalibrationSettings, Calibrator
from lidarcal_ros.core.calibration.pairs import outside_strips
from lidarcal_ros.core.georeferencing.laser_geometry import PositioningModel
from lidarcal_ros.core.georeferencing.rigorous import describe_models
from lidarcal_ros.core.mission import Strip
from lidarcal_ros.core.params import PARAMETER_NAMES
from lidarcal_ros.core.simulation.raster_terrain import RasterTerrain
from lidarcal_ros.core.simulation.scanning import swath_width
from lidarcal_ros.core.simulation.simulate import simulate_mission
from lidarcal_ros.core.simulation.spec import (
    FlightSpec,
    NoiseSpec,
    SensorSpec,
    SimulationSpec,
    SiteSpec,
    normalise_lines,
)
from lidarcal_ros.core.trajectory.strip_errors import TrajectoryErrorSettings, TrajectoryModel
from lidarcal_ros.errors import CalibrationError, ConfigError

logger = logging.getLogger(__name__)

TERRAINS = ("built-up", "flat")
#: The keys of a plan file, and of its ``sensor`` mapping (docs/interface.md "Flight plan").
PLAN_KEYS = ("sensor", "terrain", "terrain_cell_m", "terrain_origin", "lines", "control",
             "model")
SENSOR_KEYS = ("fov_deg", "range_noise_m", "density", "speed_mps")
#: Planning simulates at most this density (points/m^2) and scales the predicted sigmas.
MAX_SIMULATED_DENSITY = 0.3
#: Most points a plan's simulation may hold (about 650 bytes each in the calibration's
#: matching: some 13 GB); a larger block is planned by a representative part of it.
MAX_SIMULATED_POINTS = 20_000_000


@dataclass
class FlightPlan:
    """A flight plan (docs/interface.md "Flight plan"); map frame, metres."""

    lines: list[dict[str, Any]]
    terrain: str = "built-up"
    fov_deg: float = 50.0
    range_noise_m: float = 0.03
    density: float = 1.0
    speed_mps: float = 60.0
    control: list[tuple[float, float, float]] = field(default_factory=list)
    #: ``terrain`` names a DSM file: its grid, once read (:func:`lidarcal_ros.io.survey.plan_file.
    #: read_flight_plan`), and the ``.npy`` georeference options of the plan.
    dsm: RasterTerrain | None = None
    terrain_cell_m: float | None = None
    terrain_origin: tuple[float, float] | None = None
    #: ``matching.model`` the calibration will run with (:mod:`lidarcal_ros.core.
    #: georeferencing`): ``auto`` (the default) and ``rigorous`` plan for poses that carry
    #: the INS attitude the lines are flown with (a real INS never records an exactly level
    #: flight, so ``auto`` will run the rigorous model on every strip), ``level`` for
    #: positions only.
    model: PositioningModel = PositioningModel.AUTO

    @property
    def uses_dsm(self) -> bool:
        """``terrain`` is a DSM file rather than ``built-up`` or ``flat``."""
        return self.terrain not in TERRAINS

    def centre(self) -> tuple[float, float]:
        """Centre of the planned lines' bounding box, map frame, metres."""
        pts = np.array([p for ln in self.lines for p in (ln["start"], ln["end"])])
        return (float(pts[:, 0].min() + pts[:, 0].max()) / 2,
                float(pts[:, 1].min() + pts[:, 1].max()) / 2)

    @classmethod
    def from_mapping(cls, doc: Any, *, source: str = "plan") -> FlightPlan:
        """Validate a parsed plan document.

        Raises
        ------
        ConfigError
            One line naming the key at fault.
        """
        if not isinstance(doc, Mapping):
            raise ConfigError(f"{source}: expected a mapping with 'lines'")
        sensor = doc.get("sensor", {}) or {}
        if not isinstance(sensor, Mapping):
            raise ConfigError(f"{source}: 'sensor' must be a mapping")
        # a misspelt key would otherwise plan without what it meant (control, a sensor value)
        for where, keys, known in ((source, doc, PLAN_KEYS),
                                   (f"{source}: sensor", sensor, SENSOR_KEYS)):
            unknown = [str(k) for k in keys if k not in known]
            if unknown:
                raise ConfigError(f"{where}: unknown key{'s' if len(unknown) > 1 else ''} "
                                  f"{', '.join(unknown)} (known: {', '.join(known)})")

        def number(where: Mapping[str, Any], key: str, default: float, lo: float,
                   hi: float) -> float:
            value = where.get(key, default)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or \
                    not math.isfinite(value) or not lo < value <= hi:
                raise ConfigError(f"{source}: {key} must be a number in ({lo}, {hi}], "
                                  f"got {value!r}")
            return float(value)

        fov = number(sensor, "fov_deg", 50.0, 0.0, 120.0)
        noise = number(sensor, "range_noise_m", 0.03, 0.0, 1.0)
        density = number(sensor, "density", 1.0, 0.0, 100.0)
        speed = number(sensor, "speed_mps", 60.0, 0.0, 500.0)
        terrain = doc.get("terrain", "built-up")
        if not isinstance(terrain, str) or not terrain.strip():
            raise ConfigError(f"{source}: terrain must be built-up, flat or a DSM path")
        cell_m = doc.get("terrain_cell_m")
        if cell_m is not None:
            cell_m = number(doc, "terrain_cell_m", 1.0, 0.0, 1000.0)
        origin = doc.get("terrain_origin")
        if origin is not None:
            try:
                origin = (float(origin[0]), float(origin[1]))
                if not all(math.isfinite(v) for v in origin):
                    raise ValueError("not finite")
            except (TypeError, ValueError, IndexError, KeyError):
                raise ConfigError(f"{source}: terrain_origin must be [west, north] in metres, "
                                  f"got {doc.get('terrain_origin')!r}") from None
        raw_lines = doc.get("lines")
        if not isinstance(raw_lines, Sequence) or isinstance(raw_lines, str) or not raw_lines:
            raise ConfigError(f"{source}: 'lines' must be a non-empty list")
        for i, ln in enumerate(raw_lines):
            if not isinstance(ln, Mapping) or not all(k in ln for k in ("start", "end",
                                                                         "height")):
                raise ConfigError(f"{source}: line {i + 1} needs id, start [x, y], end [x, y] "
                                  "and height (optional: turn_deg_s, bank_deg, roll_deg)")
        try:
            lines = normalise_lines([dict(ln) for ln in raw_lines])
        except ConfigError as exc:
            raise ConfigError(f"{source}: {exc}") from None
        given = doc.get("model", PositioningModel.AUTO.value)
        try:
            model = PositioningModel(given)
        except ValueError:
            raise ConfigError(f"{source}: model must be one of {', '.join(PositioningModel)}, "
                              f"got {given!r}") from None
        top = max(ln["height"] for ln in lines)
        points = sum(math.dist(ln["start"], ln["end"]) for ln in lines) * \
            swath_width(top, fov) * min(density, MAX_SIMULATED_DENSITY)
        if points > MAX_SIMULATED_POINTS:
            raise ConfigError(
                f"{source}: the {len(lines)} lines would simulate about {points / 1e6:.0f}M "
                f"points, more than the {MAX_SIMULATED_POINTS / 1e6:.0f}M planning holds in "
                "memory; plan a representative part of the block")
        raw_control = doc.get("control") or []
        if not isinstance(raw_control, Sequence) or isinstance(raw_control, str):
            raise ConfigError(f"{source}: 'control' must be a list of [x, y, z], got "
                              f"{raw_control!r}")
        control = []
        for i, c in enumerate(raw_control):
            try:
                x, y = float(c[0]), float(c[1])
                z = float(c[2]) if len(c) > 2 else 0.0
            except (TypeError, ValueError, IndexError):
                raise ConfigError(f"{source}: control point {i + 1} must be [x, y, z]") from None
            if not all(math.isfinite(v) for v in (x, y, z)):
                raise ConfigError(f"{source}: control point {i + 1} must be finite numbers "
                                  f"[x, y, z], got {c!r}")
            control.append((x, y, z))
        return cls(lines, terrain, fov, noise, density, speed, control,
                   terrain_cell_m=cell_m, terrain_origin=origin, model=model)


@dataclass
class ParameterPrediction:
    """What the plan predicts for one parameter."""

    estimable: bool
    sigma: float | None
    max_correlation: float | None
    correlated_with: str | None
    reason: str = ""


@dataclass
class PlanReport:
    """Predictions per parameter plus advice in words."""

    parameters: dict[str, ParameterPrediction]
    advice: list[str]
    strip_pairs: int
    correspondences: int
    #: The model the predictions are of, and why (``describe_models`` of the strips).
    model: str = ""
    #: The same predictions where each strip's trajectory drift is estimated with the biases
    #: (docs/method.md section 11; priors of 5 cm and 2 mm/s), empty without correspondences.
    with_trajectory_errors: dict[str, ParameterPrediction] = field(default_factory=dict)

    def to_json_dict(self) -> dict[str, Any]:
        """docs/interface.md's ``lidarcal plan --json``, plus ``with_trajectory_errors``."""
        out: dict[str, Any] = {"parameters": _json_parameters(self.parameters),
                               "advice": list(self.advice)}
        out["strip_pairs"] = self.strip_pairs
        out["correspondences"] = self.correspondences
        out["model"] = self.model
        out["with_trajectory_errors"] = {
            "model": "drift", "parameters": _json_parameters(self.with_trajectory_errors)}
        return out


def _json_parameters(parameters: dict[str, ParameterPrediction]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for name, p in parameters.items():
        entry: dict[str, Any] = {
            "estimable": p.estimable, "sigma": p.sigma,
            "max_correlation": p.max_correlation, "correlated_with": p.correlated_with,
        }
        if p.reason:
            entry["reason"] = p.reason
        out[name] = entry
    return out


def predict(plan: FlightPlan, *, seed: int = 0) -> PlanReport:
    """Predict which parameters ``plan`` can calibrate (all eight are asked for)."""
    simulated_density = min(plan.density, MAX_SIMULATED_DENSITY)
    if plan.uses_dsm:
        if plan.dsm is None:
            raise ConfigError(f"terrain '{plan.terrain}': the DSM has not been read "
                              "(read the plan with lidarcal_ros.io.survey.plan_file"
                               ".read_flight_plan)")
        _check_dsm_covers(plan, plan.dsm)
    sim = simulate_mission(SimulationSpec(
        seed=seed, biases={},
        flight=FlightSpec(lines=plan.lines, speed_mps=plan.speed_mps),
        sensor=SensorSpec(density=simulated_density, fov_deg=plan.fov_deg,
                          attitude=plan.model != PositioningModel.LEVEL),
        noise=NoiseSpec(range_noise_m=0.0, intensity_noise=0.0),
        site=SiteSpec(terrain_kind=None if plan.uses_dsm else plan.terrain,
                      terrain=plan.dsm if plan.uses_dsm else None, n_control=0,
                      control_xy=[(c[0], c[1]) for c in plan.control] if plan.control else None),
    ))
    # Level lines all flown due east are poses of the identity, which alone read as "no
    # attitude": the level model is then the same geometry.
    level = plan.model == PositioningModel.LEVEL or sim.mission.trajectory.orientation is None
    # The correspondences carry their trajectory terms: the same matches serve the analysis
    # with the trajectory as exact and with each strip's drift (docs/method.md section 11).
    drift = TrajectoryErrorSettings(TrajectoryModel.DRIFT)
    settings = CalibrationSettings(solve_for=PARAMETER_NAMES, limits=ObservabilityLimits(),
                                   model=(PositioningModel.LEVEL if level
                                          else PositioningModel.RIGOROUS), fov_deg=plan.fov_deg,
                                   trajectory=drift)
    unseen = _unseen_control(plan, sim.mission.strips, settings.overlap_cell_m)
    cal = Calibrator.from_mission(sim.mission, settings)
    model = describe_models({ps.strip_id: ps.choice for ps in cal.strips})
    obs = cal.observations_at(np.zeros(len(PARAMETER_NAMES)))
    # A correspondence compares a point with a patch interpolated from three noisy vertices;
    # the calibration samples a fixed share of the points, so sigmas scale with density.
    sigma_obs = plan.range_noise_m * math.sqrt(1.5)
    sigma_obs *= math.sqrt(simulated_density / plan.density)
    parameters = _predictions(NormalEquations.from_observations(obs), sigma_obs, settings.limits)
    with_errors: dict[str, ParameterPrediction] = {}
    if obs.trajectory is not None and len(obs):
        blocks = StripBlocks(obs, obs.trajectory, cal.trajectory, drift, sigma_obs)
        with_errors = _predictions(blocks.reduced, sigma_obs, settings.limits)
    advice = _advice(plan, parameters, unseen)
    lost = [n for n in PARAMETER_NAMES if parameters[n].estimable and n in with_errors
            and not with_errors[n].estimable]
    lever = [n for n in lost if n in ("dX", "dY", "dZ")]
    if lever:
        advice.append(f"{', '.join(lever)}: with each strip's trajectory error estimated, the "
                      "lever arm is a constant shift of each straight strip, as the strip's "
                      "offset is: hold it at its surveyed value, or fly banked turns within "
                      "the lines")
    if "dkappa" in lost:
        advice.append("dkappa: with each strip's trajectory error estimated, its along-track "
                      "shift is a strip's offset: add crossing lines")
    return PlanReport(parameters, advice, len(cal.pairs), len(obs), model, with_errors)


def _predictions(neq: NormalEquations, sigma_obs: float,
                 limits: ObservabilityLimits) -> dict[str, ParameterPrediction]:
    """Per parameter what the normal equations ``neq`` predict with correspondences of sigma
    ``sigma_obs`` (m)."""
    try:
        sol = solve(neq, solve_for=PARAMETER_NAMES, sigma0_apriori=sigma_obs, limits=limits)
    except CalibrationError as exc:
        return {n: ParameterPrediction(False, None, None, None, str(exc))
                for n in PARAMETER_NAMES}
    parameters: dict[str, ParameterPrediction] = {}
    est = list(sol.estimated)
    for i, name in enumerate(PARAMETER_NAMES):
        st = sol.status[name]
        if st.state != ParameterState.ESTIMATED:
            parameters[name] = ParameterPrediction(False, None, None, None, st.reason)
            continue
        j = est.index(name)
        corr = np.abs(sol.correlation[j]).copy()
        corr[j] = -1.0
        k = int(np.argmax(corr)) if len(est) > 1 else -1
        parameters[name] = ParameterPrediction(
            True, float(sol.sigma[i]),
            round(float(corr[k]), 3) if k >= 0 else None, est[k] if k >= 0 else None)
    return parameters


def _check_dsm_covers(plan: FlightPlan, dsm: RasterTerrain) -> None:
    """Every line's swath (at the DSM's lowest height) must lie on the DSM."""
    xmin, xmax, ymin, ymax = dsm.extent
    for ln in plan.lines:
        half = 0.5 * swath_width(ln["height"] - dsm.height_range[0], plan.fov_deg)
        xs = [ln["start"][0], ln["end"][0]]
        ys = [ln["start"][1], ln["end"][1]]
        if (min(xs) - half < xmin or max(xs) + half > xmax or min(ys) - half < ymin
                or max(ys) + half > ymax):
            raise ConfigError(
                f"terrain '{plan.terrain}': line {ln['id']}'s swath reaches beyond the DSM "
                f"(x {xmin:.0f}..{xmax:.0f}, y {ymin:.0f}..{ymax:.0f} m); a larger DSM, or "
                "terrain_origin to place it")


def _unseen_control(plan: FlightPlan, strips: Sequence[Strip], cell_m: float) -> list[int]:
    """The control points of ``plan`` (indices) that no line's swath covers, each said in a
    warning line: the plan cannot use them."""
    if not plan.control:
        return []
    outside = outside_strips(strips, np.array(plan.control), cell_m)
    unseen = [int(i) for i in np.flatnonzero(outside)]
    for i in unseen:
        x, y, _ = plan.control[i]
        logger.warning("control point %d at (%.0f, %.0f) lies outside every line's swath: "
                       "no line sees it, the plan does not use it", i + 1, x, y)
    return unseen


def _advice(plan: FlightPlan, parameters: dict[str, ParameterPrediction],
            unseen_control: Sequence[int] = ()) -> list[str]:
    """Words on what line or control would fix what the plan cannot see (control points
    ``unseen_control`` lie outside every swath)."""
    blind = {n for n, p in parameters.items() if not p.estimable}
    advice = [f"control point {i + 1}: outside every line's swath, unused; move it under the "
              "overlaps of the lines" for i in unseen_control]
    geometry = _line_geometry(plan)
    if "dZ" in blind:
        advice.append("dZ: not observable from strips alone; add a vertical control point "
                      "seen by several strips" if len(plan.control) <= len(unseen_control) else
                      "dZ: the control cannot separate dZ from dr; fix dZ to its surveyed "
                      "value (the default) or add lines at another height")
    if "dkappa" in blind:
        if not geometry["offset_same_direction"] and not geometry["crossing"]:
            advice.append("dkappa: every line is on one track; add a line flown in the same "
                          "direction, offset by at least 40% of the swath (or a crossing line)")
        else:
            advice.append("dkappa: needs sloped features in the overlap of the same-direction "
                          "offset lines; widen their overlap or move it over buildings")
    if "dr" in blind:
        advice.append("dr: fly a second pair at another height or add vertical control")
    horizontal = {"dX", "dY", "domega"} & blind
    if horizontal and plan.terrain == "flat":
        advice.append(f"{', '.join(sorted(horizontal))}: the terrain is flat; horizontal "
                      "biases need sloped features (buildings, gable roofs) in the overlaps")
    elif horizontal and plan.uses_dsm:
        advice.append(f"{', '.join(sorted(horizontal))}: the site's surface offers too few "
                      "sloped features in the overlaps; move the overlaps over buildings or "
                      "relief")
    elif {"dY", "domega"} <= blind:
        advice.append("dY, domega: they act alike at one flying height; fly the opposite pair "
                      "at two heights")
    elif "dX" in blind:
        advice.append("dX: fly opposite lines with full overlap over sloped features")
    if "dS" in blind:
        advice.append("dS: needs data spread across the swath; fly lines whose overlaps cover "
                      "the swath edges")
    if "dphi" in blind:
        advice.append("dphi: fly opposite lines with full overlap")
    for name, p in parameters.items():
        if p.estimable and p.max_correlation is not None and p.max_correlation > 0.95:
            advice.append(f"{name}: strongly correlated with {p.correlated_with} "
                          f"({p.max_correlation:.2f}); its estimate will be weak")
    return advice


def _line_geometry(plan: FlightPlan) -> dict[str, bool]:
    """Which line arrangements the plan holds (docs/method.md section 7)."""
    dirs = []
    for ln in plan.lines:
        d = np.subtract(ln["end"], ln["start"])
        dirs.append((d / np.linalg.norm(d), np.array(ln["start"], dtype=float), ln["height"]))
    offset_same = crossing = False
    for i in range(len(dirs)):
        for j in range(i + 1, len(dirs)):
            (ui, pi, hi), (uj, pj, _) = dirs[i], dirs[j]
            cos = float(ui @ uj)
            if abs(cos) < math.cos(math.radians(30)):
                crossing = True
            elif cos > 0:
                lateral = abs(float((pj - pi) @ np.array([-ui[1], ui[0]])))
                if lateral >= 0.2 * swath_width(hi, plan.fov_deg):
                    offset_same = True
    return {"offset_same_direction": offset_same, "crossing": crossing}


__all__ = [
    "MAX_SIMULATED_DENSITY",
    "MAX_SIMULATED_POINTS",
    "PLAN_KEYS",
    "SENSOR_KEYS",
    "TERRAINS",
    "FlightPlan",
    "ParameterPrediction",
    "PlanReport",
    "predict",
]
