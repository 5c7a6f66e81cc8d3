"""Simulated airborne linear-scanner LiDAR missions with known system biases.

:func:`simulate_mission` assembles a mission from the modules beside it; how it stays
reproducible to the bit: docs/internals.md, "The simulator".
"""

from __future__ import annotations

import copy
import functools
import math
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from lidarcal_ros.core.georeferencing.attitude import (
    normalise_quaternions,
    quaternions_from_attitude,
)
from lidarcal_ros.core.mission import ControlPoints, Mission, Strip, Trajectory
from lidarcal_ros.core.radiometry import atmospheric_alpha
from lidarcal_ros.core.simulation.flight_path import FlightLine, RoughAir, Turbulence
from lidarcal_ros.core.simulation.scanning import (
    LineScan,
    Scanner,
    pulse_and_scan_rates,
    scan_blocks,
    scan_line,
    skip_noise,
)
from lidarcal_ros.core.simulation.spec import LEAD_S, TURN_S, SimulationSpec
from lidarcal_ros.core.simulation.surface import Surface
from lidarcal_ros.core.simulation.terrain import Terrain
from lidarcal_ros.core.simulation.trajectory_errors import (
    StripTrajectoryError,
    draw_trajectory_errors,
    trajectory_errors_record,
)
from lidarcal_ros.core.simulation.truth import line_summary, truth_config
from lidarcal_ros.errors import ConfigError

#: How far (m) the terrain's objects stay from a control point.
CONTROL_CLEAR_RADIUS_M = 15.0


@dataclass
class SimulatedMission:
    """A simulated mission and its truth.

    Per-strip lists are in the order of ``mission.strips``; local truths are in map
    coordinates (``origin`` added) like the mission. ``lines`` says what each line flew
    (:func:`~lidarcal_ros.core.simulation.truth.line_summary`), ``config`` is the record of
    the whole (:func:`~lidarcal_ros.core.simulation.truth.truth_config`). ``flight_lines``
    are the flights themselves (:meth:`pose`).

    The mission is as delivered: its points and trajectory carry each strip's trajectory error
    (``trajectory_errors``, by strip id; zero unless the spec asked for some), which
    ``true_trajectory`` (the same samples, trajectory noise included) does not.
    """

    mission: Mission
    biases: dict[str, float]
    true_xyz: list[np.ndarray]
    surface_class: list[np.ndarray]
    incidence_true: list[np.ndarray]
    reflectance_true: list[np.ndarray]
    range_true: list[np.ndarray]
    terrain: Surface
    lines: list[dict[str, Any]]
    config: dict[str, Any]
    scan_angle_true: list[np.ndarray] = field(default_factory=list)
    on_wall: list[np.ndarray] = field(default_factory=list)
    flight_lines: list[FlightLine] = field(default_factory=list)
    trajectory_errors: dict[int, StripTrajectoryError] = field(default_factory=dict)
    true_trajectory: Trajectory | None = None

    def trajectory_error(self, strip_id: int, t: np.ndarray | float) -> np.ndarray:
        """The true error ``e_s`` (delivered - true, map frame, metres; (n, 3)) of strip
        ``strip_id``'s trajectory at absolute times ``t`` (s): what its points carry at their
        firing times."""
        try:
            error = self.trajectory_errors[int(strip_id)]
        except KeyError:
            raise ConfigError(f"no strip {strip_id} in the simulated mission; strips: "
                              f"{', '.join(map(str, self.trajectory_errors))}") from None
        return error.at(t)

    def pose(self, index: int, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The exact IMU origin (n, 3, map frame) and ``R_ins`` (n, 3, 3) of strip ``index``
        at absolute times ``t`` (s), from the flight itself, not the trajectory's samples.

        The line's clock starts at its first pulse; absolute stamps near a GPS-like ``t0``
        resolve it to about 1e-7 s (some micrometres at flying speed): a mission simulated with
        a small ``t0`` gives poses exact to rounding.
        """
        fl = self.flight_lines[index]
        state = fl.state(np.asarray(t, dtype=np.float64) - self.lines[index]["t_first"])
        xyz = state.position
        xyz[:, 0] += self.config["origin"][0]
        xyz[:, 1] += self.config["origin"][1]
        return xyz, np.broadcast_to(state.rotation(), (xyz.shape[0], 3, 3))


def simulate_mission(spec: SimulationSpec) -> SimulatedMission:
    """Simulate the linear-scanner mission of ``spec`` with its known biases (the model:
    :mod:`~lidarcal_ros.core.simulation.exact_model`).

    Raises
    ------
    ConfigError
        What only the flight reveals: a line whose turn cannot join its ends, whose crosswind
        is too strong or whose beams would point too far from the vertical; control points
        that the strips cannot all see.
    """
    setup = _prepare(spec)
    recorder = _Recorder(setup.terrain, setup.scanner,
                         np.random.default_rng([spec.noise_seed, 0x5EED]), spec.site.origin,
                         spec.noise.trajectory_noise_m, setup.attitude, spec.sensor.fov_deg)
    for fl, tm, error in setup.lines():
        recorder.fly(fl, tm, error)
    mission = Mission(trajectory=recorder.trajectory(), strips=recorder.strips,
                      control=setup.control())
    true_trajectory = (recorder.trajectory(true=True) if spec.trajectory_errors.active
                       else mission.trajectory)
    scans = recorder.scans
    terrain, flights, errors = setup.terrain, setup.flights, setup.errors
    config = setup.truth(recorder.lines, int(sum(len(st) for st in recorder.strips)))
    return SimulatedMission(
        mission=mission, biases=dict(spec.biases), true_xyz=[s.xyz_t for s in scans],
        surface_class=[s.cls for s in scans], incidence_true=[s.incidence for s in scans],
        reflectance_true=[s.reflectance for s in scans],
        range_true=[s.range_true for s in scans], terrain=terrain, lines=recorder.lines,
        config=config, scan_angle_true=[s.theta for s in scans],
        on_wall=[s.on_wall for s in scans], flight_lines=flights,
        trajectory_errors={err.strip_id: err for err in errors}, true_trajectory=true_trajectory,
    )


# ---------------------------------------------------------------------- streaming


@dataclass
class StreamedLine:
    """One line of a :class:`MissionStream`, as delivered: its trajectory's samples
    (``trajectory``, map frame, its orientation where the mission has one) and its points,
    :meth:`blocks` at a time.

    ``t_first`` and ``t_last`` are the absolute times (s) of its first and last pulses,
    ``n_points`` their number.
    """

    strip_id: int
    trajectory: Trajectory
    t_first: float
    t_last: float
    n_points: int
    _blocks: Callable[[], Iterator[tuple[np.ndarray, np.ndarray, np.ndarray]]]

    def blocks(self) -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """The line's points in firing order, ``(t, xyz, intensity)`` a block of
        :data:`~lidarcal_ros.core.simulation.scanning.PULSE_BLOCK` pulses at a time (absolute
        s; map frame, m; float32): the values :func:`simulate_mission` gives the strip."""
        return self._blocks()


@dataclass
class MissionStream:
    """A simulated mission made a line at a time (:func:`stream_mission`): the control points
    and biases up front, :meth:`lines` in flight order, the truth's record (``config``, as
    :class:`SimulatedMission`'s) once every line has been made."""

    control: ControlPoints | None
    biases: dict[str, float]
    _setup: _Setup
    config: dict[str, Any] | None = None

    def lines(self) -> Iterator[StreamedLine]:
        """The lines in flight order; each line's :meth:`StreamedLine.blocks` may be read
        (once) at any time, and holds only its own generator's state."""
        setup = self._setup
        spec = setup.spec
        rng = np.random.default_rng([spec.noise_seed, 0x5EED])
        recorder = _Recorder(setup.terrain, setup.scanner, rng, spec.site.origin,
                             spec.noise.trajectory_noise_m, setup.attitude, spec.sensor.fov_deg)
        n_points = 0
        for fl, tm, error in setup.lines():
            # The points draw their noise before the line's trajectory does (simulate_mission's
            # order): the trajectory drawn after skipping the points' draws, the points later
            # from a copy of the generator where the line began; the same values, bit for bit.
            at_line = copy.deepcopy(rng.bit_generator.state)
            skip_noise(tm.n, setup.scanner, rng)
            trajectory = recorder.sample(fl, tm, error)
            summary = recorder.lines[-1]
            yield StreamedLine(fl.line_id, trajectory, summary["t_first"], summary["t_last"],
                               tm.n, functools.partial(recorder.points, fl, tm, error, at_line))
            n_points += tm.n
            recorder.forget_samples()
        self.config = setup.truth(recorder.lines, n_points)


def stream_mission(spec: SimulationSpec) -> MissionStream:
    """:func:`simulate_mission`'s mission made a line at a time, a block of points at a time,
    in memory that does not grow with the mission (the terrain and each line's trajectory
    samples aside): the same points, trajectory, control points and truth, bit for bit.

    Raises
    ------
    ConfigError
        As :func:`simulate_mission`.
    """
    setup = _prepare(spec)
    return MissionStream(setup.control(), dict(spec.biases), setup)


# ---------------------------------------------------------------------- the setup


@dataclass
class _Setup:
    """What a mission's flight needs before the first pulse: the scanner, the lines on the
    mission's clock, the site, the trajectory errors and the turbulence."""

    spec: SimulationSpec
    prf: float
    scanner: Scanner
    flights: list[FlightLine]
    terrain: Surface
    control_xy: np.ndarray
    times: list[_LineTimes]
    errors: list[StripTrajectoryError]
    turbulence: Turbulence | None
    attitude: bool

    def lines(self) -> Iterator[tuple[FlightLine, _LineTimes, StripTrajectoryError | None]]:
        """Each line, its times and its trajectory error (None where the spec has none)."""
        active = self.spec.trajectory_errors.active
        for fl, tm, error in zip(self.flights, self.times, self.errors, strict=True):
            yield fl, tm, error if active else None

    def control(self) -> ControlPoints | None:
        """The control points on the terrain (map frame), or None."""
        if not self.control_xy.shape[0]:
            return None
        ox, oy = self.spec.site.origin
        cxy = self.control_xy
        cz = self.terrain.height_local(cxy[:, 0], cxy[:, 1])
        cxyz = np.column_stack([cxy[:, 0] + ox, cxy[:, 1] + oy, cz])
        return ControlPoints([f"C{i + 1}" for i in range(len(cxyz))], cxyz)

    def truth(self, lines: list[dict[str, Any]], n_points: int) -> dict[str, Any]:
        """The truth's record (:func:`~lidarcal_ros.core.simulation.truth.truth_config`) of
        the lines flown."""
        spec = self.spec
        config = truth_config(spec, self.scanner, terrain=self.terrain, lines=lines,
                              attitude=self.attitude, turbulence=self.turbulence,
                              n_points=n_points)
        config["trajectory_errors"] = trajectory_errors_record(
            spec.trajectory_errors, spec.trajectory_error_seed, self.errors)
        return config


def _prepare(spec: SimulationSpec) -> _Setup:
    """The scanner, lines, site, schedule, trajectory errors and air of ``spec``."""
    flight, sensor = spec.flight, spec.sensor
    plan = spec.line_specs()
    ref_height = max(ln["height"] for ln in plan)
    prf, scan_hz = pulse_and_scan_rates(sensor.density, flight.speed_mps, sensor.fov_deg,
                                        ref_height)
    half_fov = math.radians(sensor.fov_deg) / 2.0
    scanner = Scanner(prf_hz=prf, scan_rate_hz=scan_hz, half_fov_rad=half_fov,
                      biases=dict(spec.biases),
                      atmospheric_alpha_per_m=atmospheric_alpha(spec.site.visibility_km),
                      range_noise_m=spec.noise.range_noise_m,
                      intensity_noise=spec.noise.intensity_noise)
    flights = [FlightLine.from_spec(ln, speed_mps=flight.speed_mps, wind=flight.wind_mps,
                                    half_fov=half_fov, rough_air=flight.rough_air)
               for ln in plan]
    terrain, control_xy = _site(spec, flights, half_fov)
    times = _schedule(flights, prf, spec.trajectory_rate_hz, flight.t0)
    errors = draw_trajectory_errors(spec.trajectory_errors, spec.trajectory_error_seed, [
        (fl.line_id, tm.t_mid(prf), (tm.t_line, tm.t_line + float(tm.tr[-1])))
        for fl, tm in zip(flights, times, strict=True)])
    flights, turbulence = _into_the_air(flights, times, flight.t0, flight.rough_air, spec.seed)
    manoeuvres = any(fl.turn_rate != 0.0 or fl.roll_offset != 0.0 for fl in flights)
    attitude = ((flight.rough_air is not None or manoeuvres) if sensor.attitude is None
                else bool(sensor.attitude))
    return _Setup(spec, prf, scanner, flights, terrain, control_xy, times, errors, turbulence,
                  attitude)


# ---------------------------------------------------------------------- the site


def _site(spec: SimulationSpec, flights: list[FlightLine], half_fov: float
          ) -> tuple[Surface, np.ndarray]:
    """The surface to scan (the given one, or a terrain generated over the lines' footprint,
    open ground kept around the control points) and the control points' local (x, y) (k, 2)."""
    extent = _terrain_extent(flights, half_fov)
    site = spec.site
    if site.control_xy is not None:
        control_xy = np.asarray(site.control_xy, dtype=np.float64).reshape(-1, 2)
    else:
        control_xy = _control_locations(flights, half_fov, site.n_control, extent)
    terrain = site.terrain
    if terrain is None:
        terrain = Terrain(extent, seed=spec.seed, kind=spec.terrain_kind, keep_clear=control_xy,
                          clear_radius=CONTROL_CLEAR_RADIUS_M, origin=site.origin)
    return terrain, control_xy


def _in_footprints(x: np.ndarray, y: np.ndarray, flights: list[FlightLine], half_fov: float,
                   margin: float) -> np.ndarray:
    ok = np.ones(x.shape, dtype=bool)
    for fl in flights:
        ok &= fl.covers(x, y, half_fov, margin)
    return ok


def _control_locations(
    flights: list[FlightLine], half_fov: float, n: int, extent: Sequence[float]
) -> np.ndarray:
    if n <= 0:
        return np.zeros((0, 2))
    xmin, xmax, ymin, ymax = extent
    # a 5 m grid anchored at the local origin (the centre of the named scenarios)
    gx, gy = np.meshgrid(np.arange(math.ceil(xmin / 5.0), math.floor(xmax / 5.0) + 1) * 5.0,
                         np.arange(math.ceil(ymin / 5.0), math.floor(ymax / 5.0) + 1) * 5.0)
    gx, gy = gx.ravel(), gy.ravel()
    for margin in (60.0, 40.0, 25.0):
        ok = _in_footprints(gx, gy, flights, half_fov, margin)
        if ok.any():
            break
    if not ok.any():
        raise ConfigError("control points: no area is seen by every strip")
    cx, cy = gx[ok], gy[ok]
    centre = np.array([cx.mean(), cy.mean()])
    d = np.hypot(cx - centre[0], cy - centre[1])
    chosen = [int(np.argmin(d))]
    dmin = np.hypot(cx - cx[chosen[0]], cy - cy[chosen[0]])
    while len(chosen) < n:
        j = int(np.argmax(dmin))
        if dmin[j] < 40.0:
            raise ConfigError(f"control points: the common area cannot hold {n} points 40 m apart")
        chosen.append(j)
        dmin = np.minimum(dmin, np.hypot(cx - cx[j], cy - cy[j]))
    return np.stack([cx[chosen], cy[chosen]], axis=1)


def _terrain_extent(flights: list[FlightLine], half_fov: float) -> tuple[float, ...]:
    pts = np.vstack([fl.outline(half_fov) for fl in flights])
    xs, ys = pts[:, 0].tolist(), pts[:, 1].tolist()
    return (math.floor(min(xs)), math.ceil(max(xs)), math.floor(min(ys)), math.ceil(max(ys)))


# ---------------------------------------------------------------------- the schedule


@dataclass(frozen=True)
class _LineTimes:
    """When a line is flown: its trajectory starts at ``t_line`` (absolute, s), its ``n``
    pulses are fired from ``t_line + LEAD_S`` to ``t_line + t_last_rel``, its samples are at
    ``t_line + tr``."""

    t_line: float
    n: int
    t_last_rel: float
    tr: np.ndarray

    def pulse_times(self, prf: float) -> np.ndarray:
        """The absolute firing times (s) at ``prf`` (Hz)."""
        return self.pulse_times_at(0, self.n, prf)

    def pulse_times_at(self, i0: int, i1: int, prf: float) -> np.ndarray:
        """The absolute firing times (s) at ``prf`` (Hz) of pulses ``i0`` to ``i1`` (excluded):
        the same values as those of :meth:`pulse_times`."""
        return (self.t_line + LEAD_S) + np.arange(i0, i1, dtype=np.float64) / prf

    def t_mid(self, prf: float) -> float:
        """Halfway between the first and the last pulse (absolute, s)."""
        first = self.t_line + LEAD_S
        return 0.5 * (first + (first + (self.n - 1) / prf))


def _schedule(flights: list[FlightLine], prf: float, rate: float, t0: float
              ) -> list[_LineTimes]:
    """One line after the other, ``TURN_S`` between the end of one trajectory and the next."""
    out = []
    t_line = float(t0)
    for fl in flights:
        n = int(math.floor(fl.duration * prf)) + 1
        t_last_rel = LEAD_S + (n - 1) / prf
        n_traj = int(math.floor((t_last_rel + LEAD_S) * rate)) + 1
        tr = np.arange(n_traj, dtype=np.float64) / rate
        out.append(_LineTimes(t_line, n, t_last_rel, tr))
        t_line = float(t_line + tr[-1] + TURN_S)
    return out


def _into_the_air(flights: list[FlightLine], times: list[_LineTimes], t0: float,
                  rough_air: RoughAir | None, seed: int) -> tuple[list[FlightLine],
                                                                  Turbulence | None]:
    """The lines on the mission's clock, in its rough air (scaled over the trajectory's
    samples, :class:`~lidarcal_ros.core.simulation.flight_path.RoughAir`)."""
    flights = [replace(fl, time_offset=(tm.t_line - t0) + LEAD_S)
               for fl, tm in zip(flights, times, strict=True)]
    if rough_air is None:
        return flights, None
    raw = Turbulence.draw(rough_air, seed if rough_air.seed is None else rough_air.seed)
    sample_times = np.concatenate([fl.time_offset + (tm.tr - LEAD_S)
                                   for fl, tm in zip(flights, times, strict=True)])
    turbulence = raw.scaled(rough_air.peaks, sample_times)
    return [replace(fl, turbulence=turbulence) for fl in flights], turbulence


# ---------------------------------------------------------------------- flying the lines


@dataclass
class _Recorder:
    """What the system records as the lines are flown one after the other, and the truth."""

    terrain: Surface
    scanner: Scanner
    rng: np.random.Generator
    origin: tuple[float, float]
    trajectory_noise_m: float
    attitude: bool
    fov_deg: float
    strips: list[Strip] = field(default_factory=list)
    scans: list[LineScan] = field(default_factory=list)
    lines: list[dict[str, Any]] = field(default_factory=list)
    _t: list[np.ndarray] = field(default_factory=list)
    _xyz: list[np.ndarray] = field(default_factory=list)
    _xyz_true: list[np.ndarray] = field(default_factory=list)
    _q: list[np.ndarray] = field(default_factory=list)
    _q_last: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))

    def fly(self, fl: FlightLine, tm: _LineTimes, error: StripTrajectoryError | None) -> None:
        """Scan a line, then sample its trajectory (:meth:`sample`); with an ``error``, the
        points as georeferenced with the delivered trajectory (+ ``e_s(t)``)."""
        scan = scan_line(fl, tm.n, self.terrain, self.scanner, self.rng)
        t_abs = tm.pulse_times(self.scanner.prf_hz)
        self._delivered(scan, t_abs, error)
        self.strips.append(Strip(strip_id=fl.line_id, xyz=scan.xyz_b, t=t_abs,
                                 intensity=scan.intensity))
        self.scans.append(scan)
        self.sample(fl, tm, error)

    def points(self, fl: FlightLine, tm: _LineTimes, error: StripTrajectoryError | None,
               state: Mapping[str, Any]) -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """:meth:`fly`'s points of a line a block at a time, ``(t, xyz, intensity)``, their
        noise drawn from a generator of the recorder's kind in ``state`` (where the line
        began)."""
        bit_generator = type(self.rng.bit_generator)()
        bit_generator.state = state
        rng = np.random.Generator(bit_generator)
        prf = self.scanner.prf_hz
        for i0, scan in scan_blocks(fl, tm.n, self.terrain, self.scanner, rng):
            t_abs = tm.pulse_times_at(i0, i0 + len(scan.intensity), prf)
            self._delivered(scan, t_abs, error)
            yield t_abs, scan.xyz_b, scan.intensity

    def _delivered(self, scan: LineScan, t_abs: np.ndarray,
                   error: StripTrajectoryError | None) -> None:
        """Move a scan (local) to the map; the delivered points with the trajectory error."""
        ox, oy = self.origin
        for arr in (scan.xyz_b, scan.xyz_t):
            arr[:, 0] += ox
            arr[:, 1] += oy
        if error is not None:
            # the system georeferences with X_o,true + e_s: each point moves with its position
            scan.xyz_b += error.at(t_abs)

    def sample(self, fl: FlightLine, tm: _LineTimes, error: StripTrajectoryError | None
               ) -> Trajectory:
        """Sample a line's trajectory (exact poses, ``LEAD_S`` before its first pulse to
        ``LEAD_S`` after its last, with the trajectory noise drawn from the recorder's
        generator; with an ``error``, + ``e_s(t)``, the samples without it kept for
        :meth:`trajectory` ``true``) and record what the line flew; the line's samples as
        delivered."""
        ox, oy = self.origin
        state = fl.state(tm.tr - LEAD_S)
        pos = state.position
        pos[:, 0] += ox
        pos[:, 1] += oy
        if self.trajectory_noise_m > 0:
            pos += self.rng.normal(0.0, self.trajectory_noise_m, pos.shape)
        t_samples = tm.t_line + tm.tr
        self._t.append(t_samples)
        self._xyz_true.append(pos)
        self._xyz.append(pos if error is None else pos + error.at(t_samples))
        if self.attitude:
            self._q.append(quaternions_from_attitude(
                *(np.broadcast_to(v, tm.tr.shape) for v in (state.roll, state.pitch,
                                                             state.kappa))))
        over_line = (tm.tr >= LEAD_S) & (tm.tr <= tm.t_last_rel)
        prf = self.scanner.prf_hz
        pulses = (float(tm.pulse_times_at(0, 1, prf)[0]),
                  float(tm.pulse_times_at(tm.n - 1, tm.n, prf)[0]), tm.n)
        self.lines.append(line_summary(fl, state, over_line, pulses, self.origin,
                                       self.fov_deg))
        q = None
        if self.attitude:
            # the sign the whole trajectory's normalisation gives the line (the previous line's
            # last orientation leads); the values normalised once, by Trajectory, as there
            q = self._q[-1]
            lead = normalise_quaternions(np.vstack([self._q_last, q[:1]]))[-1]
            q = -q if float(lead @ q[0]) < 0.0 else q
        trajectory = Trajectory(t_samples, self._xyz[-1], q)
        if trajectory.orientation is not None:
            self._q_last = trajectory.orientation[-1:]
        return trajectory

    def forget_samples(self) -> None:
        """Drop the trajectory samples kept for :meth:`trajectory` (a stream's lines carry
        their own)."""
        for kept in (self._t, self._xyz, self._xyz_true, self._q):
            kept.clear()

    def trajectory(self, *, true: bool = False) -> Trajectory:
        """The samples of every line flown so far, as delivered (``true``: without the
        trajectory errors)."""
        return Trajectory(np.concatenate(self._t),
                          np.concatenate(self._xyz_true if true else self._xyz),
                          np.concatenate(self._q) if self.attitude else None)


__all__ = ["CONTROL_CLEAR_RADIUS_M", "MissionStream", "SimulatedMission", "StreamedLine",
           "simulate_mission", "stream_mission"]
