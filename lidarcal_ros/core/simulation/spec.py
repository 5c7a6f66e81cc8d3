"""What a simulated mission is: every option of ``simulate_mission``, in five parts.

:class:`SimulationSpec` holds the seed, the biases, a :class:`FlightSpec`, :class:`SensorSpec`,
:class:`NoiseSpec`, :class:`SiteSpec` and :class:`TrajectoryErrorSpec`; build one from its parts
or with :meth:`SimulationSpec.from_options`. Local coordinates until ``SiteSpec.origin``.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, fields
from typing import Any

import numpy as np

from lidarcal_ros.core.params import PARAMETER_NAMES, arcsec_to_rad
from lidarcal_ros.core.simulation.flight_path import RoughAir, crosswind_for_crab
from lidarcal_ros.core.simulation.scanning import swath_width
from lidarcal_ros.core.simulation.surface import Surface
from lidarcal_ros.core.simulation.terrain import TERRAIN_KINDS
from lidarcal_ros.errors import ConfigError

SCENARIOS = ("paper", "flat", "one_track")

#: Paper-like biases (Habib et al. 2011, experiment II, plus a small lever-arm bias).
DEFAULT_BIASES: dict[str, float] = {
    "dX": 0.05,
    "dY": -0.04,
    "dZ": 0.0,
    "domega": arcsec_to_rad(-29.0),
    "dphi": arcsec_to_rad(-91.0),
    "dkappa": arcsec_to_rad(45.0),
    "dr": 0.118,
    "dS": 1.0e-4,
}

#: Flying heights of the paper's two blocks (above the ground datum), metres.
HIGH, LOW = 1150.0, 540.0
#: Default ground speed (m/s) and field of view (deg) of the simulated system.
SPEED_MPS, FOV_DEG = 60.0, 50.0
TURN_S = 30.0  # time between the end of one line's trajectory and the start of the next
LEAD_S = 2.0  # trajectory before the first and after the last pulse of a line
#: Optional attitude keys of a line spec (:func:`normalise_lines`), degrees or deg/s.
LINE_ATTITUDE_KEYS = ("turn_deg_s", "bank_deg", "roll_deg")


@dataclass(frozen=True)
class FlightSpec:
    """What is flown.

    Attributes
    ----------
    scenario : str
        ``"paper"`` (six strips: 1 N / 2 S at 1150 m on one track, 3 N / 4 S at 540 m on the
        same track, 5 and 6 both north at 1150 m, 0.56 swath apart), ``"flat"`` (the same lines
        over flat ground) or ``"one_track"`` (strips 1-4 only): its lines
        (:func:`scenario_lines`) unless ``lines`` is given.
    lines : sequence of dict, optional
        Explicit lines ``{id, start: (x, y), end: (x, y), height}`` (local coordinates,
        metres), overriding the scenario's; each may be a turn (``turn_deg_s``, the track's
        heading rate, positive left, or ``bank_deg``, the coordinated turn's bank, right wing
        down positive) flown as the arc from ``start`` to ``end``, and may carry a constant
        ``roll_deg`` (a sideslip)
        (:meth:`~lidarcal_ros.core.simulation.flight_path.FlightLine.from_spec`). Kept as validated
        by
        :func:`normalise_lines`.
    line_length_m : float
        Length of the scenario's lines, metres.
    speed_mps : float
        Ground speed, m/s.
    wind_mps : (east, north)
        Where the air moves, m/s. To hold its track the aircraft turns its nose into the
        crosswind: on each line the sensor's heading is the track's plus the crab angle
        ``asin(w_right / speed_mps)`` (``w_right`` the wind's component to the right of the
        track), opposite on lines flown the other way. The points are georeferenced with that
        heading, as the system's IMU gives it; the trajectory's positions do not show it, and
        the quasi-rigorous method takes the heading from the track (docs/method.md section 4), so
        without the attitude on the trajectory (``SensorSpec.attitude``) a crab it cannot see
        is what this simulates.
    rough_air : RoughAir, optional
        Fly in turbulence (:class:`~lidarcal_ros.core.simulation.flight_path.RoughAir`: roll, pitch
        and heading wobble, heave and sway); its ``ins_rate_hz`` is the trajectory's sample rate.
        Every pulse is georeferenced with the exact attitude and position at its firing time,
        not with the trajectory's samples.
    t0 : float
        Absolute time of the first trajectory sample, seconds.
    """

    scenario: str = "paper"
    lines: Sequence[dict[str, Any]] | None = None
    line_length_m: float = 1000.0
    speed_mps: float = SPEED_MPS
    wind_mps: tuple[float, float] = (0.0, 0.0)
    rough_air: RoughAir | None = None
    t0: float = 1.7e9

    def __post_init__(self) -> None:
        if self.scenario not in SCENARIOS:
            raise ConfigError(f"scenario {self.scenario!r} unknown; known: "
                              f"{', '.join(SCENARIOS)}")
        if self.rough_air is not None and not isinstance(self.rough_air, RoughAir):
            raise ConfigError(f"rough_air must be a RoughAir, got "
                              f"{type(self.rough_air).__name__}")
        _require_positive(line_length_m=self.line_length_m, speed_mps=self.speed_mps)
        wind = np.asarray(self.wind_mps, dtype=np.float64).reshape(-1)
        if wind.shape != (2,) or not np.isfinite(wind).all():
            raise ConfigError(f"wind_mps must be two finite numbers (east, north), got "
                              f"{self.wind_mps}")
        object.__setattr__(self, "wind_mps", (float(wind[0]), float(wind[1])))
        if self.lines is not None:
            object.__setattr__(self, "lines", tuple(normalise_lines(self.lines)))


@dataclass(frozen=True)
class SensorSpec:
    """The scanner and the trajectory it records.

    Attributes
    ----------
    density : float
        Mean points per m^2 over the swath of the highest line; the same PRF and mirror rate
        serve every line (about 2.1x the density at 540 m under 1150 m lines).
    fov_deg : float
        Full field of view of the scanner, degrees, in (0, 120).
    trajectory_rate_hz : float, optional
        Trajectory sampling, Hz (default: the rough air's INS rate, else 50).
    attitude : bool, optional
        Give the trajectory the sensor's orientation at each sample (``R_ins`` as a REP-103
        quaternion, ``Trajectory.orientation``, written to a bag as the pose's orientation),
        as an INS would; False: positions only (the contract's identity orientation). Default:
        with rough air or banked or turning lines, else positions only.
    """

    density: float = 1.0
    fov_deg: float = FOV_DEG
    trajectory_rate_hz: float | None = None
    attitude: bool | None = None

    def __post_init__(self) -> None:
        _require_positive(density=self.density)
        if self.trajectory_rate_hz is not None:
            _require_positive(trajectory_rate_hz=self.trajectory_rate_hz)
        if not 0.0 < self.fov_deg < 120.0:
            raise ConfigError(f"fov_deg must be in (0, 120), got {self.fov_deg}")


@dataclass(frozen=True)
class NoiseSpec:
    """The noise of the measurements.

    Attributes
    ----------
    range_noise_m : float
        Gaussian range noise, metres.
    intensity_noise : float
        Relative (multiplicative) Gaussian noise of the intensities.
    trajectory_noise_m : float
        Gaussian noise added to the published trajectory samples, metres (the points are
        georeferenced with the noiseless positions).
    noise_seed : int, optional
        Seed of the range, intensity and trajectory noise alone (default: the spec's seed),
        for Monte Carlo runs over one terrain.
    """

    range_noise_m: float = 0.02
    intensity_noise: float = 0.02
    trajectory_noise_m: float = 0.0
    noise_seed: int | None = None

    def __post_init__(self) -> None:
        if self.range_noise_m < 0 or self.trajectory_noise_m < 0 or self.intensity_noise < 0:
            raise ConfigError("noise levels must be non-negative")


@dataclass(frozen=True)
class SiteSpec:
    """Where the mission is flown.

    Attributes
    ----------
    terrain_kind : str, optional
        ``"built-up"`` or ``"flat"`` (:class:`~lidarcal_ros.core.simulation.terrain.Terrain`,
        generated from the spec's seed over the lines' footprint); default from the scenario.
    terrain : Surface, optional
        The surface to scan (e.g. a
        :class:`~lidarcal_ros.core.simulation.raster_terrain.RasterTerrain` of the site), instead of
        one generated; its origin must be ``origin``.
    origin : (x0, y0)
        Added to every map X/Y, metres (e.g. (500000, 5000000) for projected-CRS magnitudes).
    n_control : int
        Vertical control points on open ground seen by every strip (centre first), placed
        automatically.
    control_xy : sequence of (x, y), optional
        Explicit control point locations (local, metres), instead of ``n_control`` placed
        automatically; kept clear of buildings and trees, Z from the terrain.
    visibility_km : float
        Meteorological visibility, km: the atmospheric attenuation of the intensities.
    """

    terrain_kind: str | None = None
    terrain: Surface | None = None
    origin: tuple[float, float] = (0.0, 0.0)
    n_control: int = 1
    control_xy: Sequence[Sequence[float]] | None = None
    visibility_km: float = 48.3

    def __post_init__(self) -> None:
        if self.n_control < 0:
            raise ConfigError(f"n_control must be >= 0, got {self.n_control}")
        origin = (float(self.origin[0]), float(self.origin[1]))
        object.__setattr__(self, "origin", origin)
        if self.control_xy is not None:
            xy = np.asarray(self.control_xy, dtype=np.float64).reshape(-1, 2)
            object.__setattr__(self, "control_xy", tuple(map(tuple, xy.tolist())))
        if self.terrain is None:
            if self.terrain_kind and self.terrain_kind not in TERRAIN_KINDS:
                raise ConfigError(f"terrain kind {self.terrain_kind!r} unknown; known: "
                                  f"{', '.join(TERRAIN_KINDS)}")
        elif origin != self.terrain.origin:
            raise ConfigError(f"origin {origin} differs from the given terrain's "
                              f"{self.terrain.origin}")


@dataclass(frozen=True)
class TrajectoryErrorSpec:
    """The errors of the delivered trajectory (GNSS/INS), drawn per strip (docs/method.md section
    11).

    Strip ``s`` is georeferenced with ``X_o,true(t) + e_s(t)``, so its points and its
    trajectory carry, per map axis ``k`` (metres, delivered - true),

    ``e_s,k(t) = o_s,k + (t - t_s) v_s,k + a sin(2 pi (t - t_s) / P + phi_s,k)``

    with ``t_s`` the strip's mid time (between its first and last pulse), ``o_s,k`` and
    ``v_s,k`` normal with the sigmas below, ``phi_s,k`` uniform in ``[0, 2 pi)``, independent
    from strip to strip. The default is no error at all (a mission as without this part, to the
    bit); :data:`TYPICAL_TRAJECTORY_ERRORS` is a typical post-processed solution's.

    Attributes
    ----------
    offset_horizontal_m : float
        Sigma of the offset along each of map X and Y, metres.
    offset_vertical_m : float
        Sigma of the offset along map Z, metres.
    drift_m_per_s : float
        Sigma of the drift rate along each axis, m/s (1 cm per 10 s: 0.001).
    oscillation_m : float
        Amplitude ``a`` of the slow oscillation along each axis, metres (random phase).
    oscillation_period_s : float
        Its period ``P``, seconds.
    trajectory_error_seed : int, optional
        Seed of the draws (default: the spec's seed); they come from a generator of their own,
        so the rest of the mission is the same with or without them.
    """

    offset_horizontal_m: float = 0.0
    offset_vertical_m: float = 0.0
    drift_m_per_s: float = 0.0
    oscillation_m: float = 0.0
    oscillation_period_s: float = 60.0
    trajectory_error_seed: int | None = None

    def __post_init__(self) -> None:
        for name in ("offset_horizontal_m", "offset_vertical_m", "drift_m_per_s",
                     "oscillation_m"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not (
                    math.isfinite(value) and value >= 0.0):
                raise ConfigError(f"trajectory errors: {name} must be a finite number >= 0, "
                                  f"got {value!r}")
            object.__setattr__(self, name, float(value))
        period = self.oscillation_period_s
        if isinstance(period, bool) or not isinstance(period, (int, float)) or not (
                math.isfinite(period) and period > 0.0):
            raise ConfigError(f"trajectory errors: oscillation_period_s must be positive, "
                              f"got {period!r}")
        object.__setattr__(self, "oscillation_period_s", float(period))
        seed = self.trajectory_error_seed
        if seed is not None and (isinstance(seed, bool)
                                 or not isinstance(seed, numbers.Integral) or seed < 0):
            raise ConfigError(f"trajectory errors: trajectory_error_seed must be an integer "
                              f">= 0, got {seed!r}")
        if seed is not None:
            object.__setattr__(self, "trajectory_error_seed", int(seed))

    @property
    def active(self) -> bool:
        """Whether any error is drawn (a sigma or the amplitude above 0)."""
        return any(v > 0.0 for v in (self.offset_horizontal_m, self.offset_vertical_m,
                                     self.drift_m_per_s, self.oscillation_m))

    def describe(self) -> dict[str, Any]:
        """The settings as plain values (for a truth file)."""
        return {"offset_horizontal_m": self.offset_horizontal_m,
                "offset_vertical_m": self.offset_vertical_m,
                "drift_m_per_s": self.drift_m_per_s, "oscillation_m": self.oscillation_m,
                "oscillation_period_s": self.oscillation_period_s,
                "seed": self.trajectory_error_seed}


#: A typical post-processed GNSS/INS solution (issue 29): offsets of 4 cm horizontal and 5 cm
#: vertical (sigma per axis), a drift of 1 cm per 10 s (sigma per axis), a 1 cm oscillation of
#: period 60 s.
TYPICAL_TRAJECTORY_ERRORS = TrajectoryErrorSpec(
    offset_horizontal_m=0.04, offset_vertical_m=0.05, drift_m_per_s=0.001, oscillation_m=0.01,
    oscillation_period_s=60.0)


@dataclass(frozen=True)
class SimulationSpec:
    """Every option of a simulated mission (module docstring).

    Attributes
    ----------
    seed : int
        Everything random (terrain, noise, rough air) derives from it.
    biases : dict
        Bias values (nominal - true), SI, of every name of
        :data:`~lidarcal_ros.core.params.PARAMETER_NAMES` (kept as :func:`check_biases` gives
        them: names left out are 0); default :data:`DEFAULT_BIASES`.
    flight, sensor, noise, site, trajectory_errors : the parts (their classes)
    """

    seed: int = 0
    biases: dict[str, float] = field(default_factory=lambda: dict(DEFAULT_BIASES))
    flight: FlightSpec = field(default_factory=FlightSpec)
    sensor: SensorSpec = field(default_factory=SensorSpec)
    noise: NoiseSpec = field(default_factory=NoiseSpec)
    site: SiteSpec = field(default_factory=SiteSpec)
    trajectory_errors: TrajectoryErrorSpec = field(default_factory=TrajectoryErrorSpec)

    def __post_init__(self) -> None:
        object.__setattr__(self, "seed", int(self.seed))
        ins_rate = None if self.flight.rough_air is None else self.flight.rough_air.ins_rate_hz
        rate = self.sensor.trajectory_rate_hz
        if rate is not None and ins_rate is not None and rate != ins_rate:
            raise ConfigError(f"trajectory_rate_hz ({rate:g} Hz) differs from the "
                              f"rough air's INS rate ({ins_rate:g} Hz): give one")
        object.__setattr__(self, "biases", check_biases(self.biases))

    @classmethod
    def from_options(cls, **options: Any) -> SimulationSpec:
        """The spec of flat keywords: ``seed``, ``biases`` and the fields of the parts (each
        name belongs to one part; unset ones keep their defaults).

        Raises
        ------
        TypeError
            A keyword that is no option (the known ones listed).
        """
        parts: dict[str, Any] = {}
        for name, part in _PARTS.items():
            names = {f.name for f in fields(part)}
            parts[name] = part(**{k: options.pop(k) for k in list(options) if k in names})
        unknown = sorted(set(options) - {"seed", "biases"})
        if unknown:
            raise TypeError(f"SimulationSpec.from_options: unknown option(s) "
                            f"{', '.join(unknown)}; known: {', '.join(OPTION_NAMES)}")
        return cls(**options, **parts)

    # ------------------------------------------------------------------ resolved defaults

    @property
    def trajectory_rate_hz(self) -> float:
        """The trajectory's sample rate, Hz: the sensor's, the rough air's INS rate, or 50."""
        if self.sensor.trajectory_rate_hz is not None:
            return float(self.sensor.trajectory_rate_hz)
        rough = self.flight.rough_air
        return 50.0 if rough is None or rough.ins_rate_hz is None else float(rough.ins_rate_hz)

    @property
    def terrain_kind(self) -> str:
        """The kind of the terrain to generate: the site's, else the scenario's."""
        return self.site.terrain_kind or ("flat" if self.flight.scenario == "flat"
                                          else "built-up")

    @property
    def noise_seed(self) -> int:
        """Seed of the measurement noise: the noise's, else the spec's."""
        return int(self.seed if self.noise.noise_seed is None else self.noise.noise_seed)

    @property
    def trajectory_error_seed(self) -> int:
        """Seed of the trajectory errors: theirs, else the spec's."""
        seed = self.trajectory_errors.trajectory_error_seed
        return int(self.seed if seed is None else seed)

    def line_specs(self) -> list[dict[str, Any]]:
        """The validated lines to fly (:func:`normalise_lines`): the given ones, else the
        scenario's."""
        if self.flight.lines is not None:
            return [dict(ln) for ln in self.flight.lines]
        return normalise_lines(scenario_lines(self.flight.scenario, self.flight.line_length_m,
                                              self.sensor.fov_deg))


_PARTS: dict[str, type] = {"flight": FlightSpec, "sensor": SensorSpec, "noise": NoiseSpec,
                           "site": SiteSpec, "trajectory_errors": TrajectoryErrorSpec}
#: The keywords of :meth:`SimulationSpec.from_options`.
OPTION_NAMES: tuple[str, ...] = ("seed", "biases", *(f.name for part in _PARTS.values()
                                                    for f in fields(part)))


def check_biases(biases: Mapping[str, float] | None) -> dict[str, float]:
    """Every bias of :data:`~lidarcal_ros.core.params.PARAMETER_NAMES` as a float (missing
    names 0; None: :data:`DEFAULT_BIASES`). ConfigError for an unknown name or a value that is
    not finite."""
    if biases is None:
        return dict(DEFAULT_BIASES)
    unknown = [k for k in biases if k not in PARAMETER_NAMES]
    if unknown:
        raise ConfigError(
            f"unknown bias name(s) {', '.join(unknown)}; known: {', '.join(PARAMETER_NAMES)}"
        )
    out = {name: float(biases.get(name, 0.0)) for name in PARAMETER_NAMES}
    bad = [k for k, v in out.items() if not math.isfinite(v)]
    if bad:
        raise ConfigError(f"bias(es) {', '.join(bad)} not finite")
    return out


def _require_positive(**values: float) -> None:
    for name, value in values.items():
        if not (math.isfinite(value) and value > 0.0):
            raise ConfigError(f"{name} must be positive, got {value}")


# ---------------------------------------------------------------------- flight lines


def scenario_lines(scenario: str, line_length_m: float, fov_deg: float) -> list[dict[str, Any]]:
    """Lines of a named scenario, local coordinates (the area's centre at (0, 0))."""
    if scenario not in SCENARIOS:
        raise ConfigError(f"scenario {scenario!r} unknown; known: {', '.join(SCENARIOS)}")
    h = 0.5 * line_length_m

    def line(i: int, x: float, northward: bool, height: float) -> dict[str, Any]:
        a, b = (x, -h), (x, h)
        return {"id": i, "start": a if northward else b, "end": b if northward else a,
                "height": height}

    lines = [line(1, 0.0, True, HIGH), line(2, 0.0, False, HIGH),
             line(3, 0.0, True, LOW), line(4, 0.0, False, LOW)]
    if scenario in ("paper", "flat"):
        off = round(0.28 * swath_width(HIGH, fov_deg))  # 55-56% of the swath apart
        lines += [line(5, -off, True, HIGH), line(6, off, True, HIGH)]
    return lines


def normalise_lines(lines: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """Validated line specs ``{id, start: (x, y), end: (x, y), height}`` with the optional
    attitude keys ``turn_deg_s``, ``bank_deg``, ``roll_deg`` (None where absent; their meaning:
    :meth:`~lidarcal_ros.core.simulation.flight_path.FlightLine.from_spec`). ConfigError names the
    line at fault."""
    out = []
    seen = set()
    for i, ln in enumerate(lines):
        try:
            lid = int(ln.get("id", i + 1))
            start = (float(ln["start"][0]), float(ln["start"][1]))
            end = (float(ln["end"][0]), float(ln["end"][1]))
            height = float(ln["height"])
        except (AttributeError, KeyError, TypeError, ValueError, IndexError) as exc:
            raise ConfigError(
                f"line {i}: needs id, start (x, y), end (x, y), height ({exc})"
            ) from exc
        if lid in seen:
            raise ConfigError(f"line id {lid} repeated")
        seen.add(lid)
        if not all(math.isfinite(v) for v in (*start, *end, height)):
            raise ConfigError(f"line {lid}: start, end and height must be finite")
        if math.hypot(end[0] - start[0], end[1] - start[1]) < 1.0:
            raise ConfigError(f"line {lid}: start and end coincide")
        if not height > 50.0:
            raise ConfigError(f"line {lid}: height {height} m too low (must exceed 50 m)")
        spec: dict[str, Any] = {"id": lid, "start": start, "end": end, "height": height}
        for key in LINE_ATTITUDE_KEYS:
            value = ln.get(key)
            if value is not None:
                if isinstance(value, bool) or not isinstance(value, (int, float)) or not (
                        math.isfinite(value)):
                    raise ConfigError(f"line {lid}: {key} must be a finite number, got "
                                      f"{value!r}")
                value = float(value)
            spec[key] = value
        out.append(spec)
    if not out:
        raise ConfigError("no flight lines")
    return out


def crab_wind(crab_deg: float, lines: Sequence[dict[str, Any]],
              speed_mps: float = SPEED_MPS) -> tuple[float, float]:
    """The wind (east, north, m/s) blowing across the first of ``lines`` (from its start to its
    end) that crabs it by ``crab_deg``
    (:func:`~lidarcal_ros.core.simulation.flight_path.crosswind_for_crab`; the other lines are
    crabbed as their directions make it)."""
    (x0, y0), (x1, y1) = lines[0]["start"], lines[0]["end"]
    return crosswind_for_crab(crab_deg, speed_mps, math.atan2(x0 - x1, y1 - y0))


__all__ = ["DEFAULT_BIASES", "FOV_DEG", "HIGH", "LEAD_S", "LINE_ATTITUDE_KEYS", "LOW",
           "OPTION_NAMES", "SCENARIOS", "SPEED_MPS", "TURN_S", "TYPICAL_TRAJECTORY_ERRORS",
           "FlightSpec", "NoiseSpec", "SensorSpec", "SimulationSpec", "SiteSpec",
           "TrajectoryErrorSpec", "check_biases", "crab_wind", "normalise_lines",
           "scenario_lines"]
