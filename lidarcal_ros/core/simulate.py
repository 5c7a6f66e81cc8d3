"""Simulated airborne linear-scanner LiDAR missions with known system biases.

The simulator uses *exact* geometry (rotations, ranges, mirror angles, ray casting into an
analytic DSM), not the linearised bias model of method.md section 3, so that it tests the
calibration rather than agreeing with it by construction.

Bias convention (pinned by ``vectors/method_vectors.json``)
-----------------------------------------------------------
A bias is ``nominal - true``. The simulated *true* system is the ideal one: zero lever arm,
identity boresight, mirror scale 1, no range offset. The system georeferences with the
*nominal* values, which are therefore the biases themselves:

- a pulse fired at time ``t`` with physical mirror angle ``theta`` leaves the IMU origin
  ``X_o(t)`` along ``R_ins(t) [-sin theta, 0, -cos theta]`` and meets the terrain at ``P`` (true
  point) after ``r_true`` metres;
- the system records ``r = r_true + dr (+ noise)`` and ``beta = (1 + dS) * theta`` and reports
  ``X_b = X_o + R_ins [dX, dY, dZ] + R_ins R_B rho``, ``rho = -r [sin beta, 0, cos beta]``,
  with the exact boresight ``R_B = Rz(dkappa) Ry(dphi) Rx(domega)``
  (``scipy Rotation.from_euler("xyz", [domega, dphi, dkappa])``), whose small-angle form is
  method.md's ``I + skew``.

``R_ins = Rz(kappa) Rx(pitch) Ry(roll)`` (body right-forward-up to map, method.md section 10,
:mod:`lidarcal_ros.core.attitude`) and ``X_o`` are the exact attitude and position of the
flight at the firing time (:mod:`lidarcal_ros.core.flight_path`: straight lines or turns,
crabbed into the wind, banked, in rough air), not interpolated from the trajectory's samples.
A level flight has ``R_ins = R_kappa = [[c, -s, 0], [s, c, 0], [0, 0, 1]]``, flight direction
``(-sin kappa, cos kappa)``: sections 2-4's model.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from lidarcal_ros.core.attitude import body_rotations_from_attitude, quaternions_from_attitude
from lidarcal_ros.core.flight_path import (
    FlightLine,
    FlightState,
    RoughAir,
    Turbulence,
    crosswind_for_crab,
)
from lidarcal_ros.core.mission import ControlPoints, Mission, Strip, Trajectory
from lidarcal_ros.core.model import boresight_matrix
from lidarcal_ros.core.params import PARAMETER_NAMES, arcsec_to_rad, as_vector
from lidarcal_ros.core.radiometry import atmospheric_alpha
from lidarcal_ros.core.ray_casting import cast_rays
from lidarcal_ros.core.surface import Surface
from lidarcal_ros.core.terrain import Terrain
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
WAVELENGTH_NM = 1064.0
#: Radiometric constant: I = K rho cos(inc) exp(-2 alpha r) / r^2. About 3800 for a 0.5
#: reflectance at normal incidence from 1150 m, about 17000 from 540 m: fits uint16.
INTENSITY_K = 1.0e10
#: Default ground speed (m/s) and field of view (deg) of the simulated system.
SPEED_MPS, FOV_DEG = 60.0, 50.0
TURN_S = 30.0  # time between the end of one line's trajectory and the start of the next
LEAD_S = 2.0  # trajectory before the first and after the last pulse of a line
_BLOCK = 262_144


@dataclass
class SimulatedMission:
    """A simulated mission and its truth.

    Per-strip lists are in the order of ``mission.strips``; local truths are in map
    coordinates (``origin`` added) like the mission. ``lines`` says what each line flew:
    ``start``, ``end`` (map), ``height``, ``direction`` (unit, start to end), ``kappa`` (the
    track's heading at the first pulse), ``crab_deg`` (mid-line), ``length_m``, ``t_first``,
    ``t_last``, ``n_pulses``, ``turn_deg_s``, ``bank_deg`` (the coordinated turn's),
    ``roll_offset_deg``, ``radius_m`` (None on a straight line), ``heading_change_deg`` and
    ``attitude``: the least and greatest roll, pitch, heading wobble and crab over its pulses
    (deg, from the trajectory's samples). ``flight_lines`` are the flights themselves
    (:meth:`pose`).
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


# ---------------------------------------------------------------------- exact bias model


def _check_biases(biases: dict[str, float] | None) -> dict[str, float]:
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


def georeference(
    trajectory_position: np.ndarray,
    rotation: np.ndarray,
    range_true: np.ndarray | float,
    theta: np.ndarray | float,
    biases: dict[str, float],
    range_noise: np.ndarray | float = 0.0,
) -> np.ndarray:
    """Point reported by the biased system for a pulse of known true geometry (method.md
    section 10: ``X_b = X_o + R_ins [dX, dY, dZ] + R_ins R_B rho``,
    ``rho = -(r_true + dr + noise) [sin((1 + dS) theta), 0, cos((1 + dS) theta)]``).

    Parameters
    ----------
    trajectory_position : (n, 3) or (3,)
        IMU origin at the firing time, map frame.
    rotation : (n, 3, 3), (1, 3, 3) or (3, 3)
        ``R_ins``, body (right, forward, up) to map, at the firing time
        (:func:`~lidarcal_ros.core.attitude.body_rotations_from_attitude`).
    range_true, theta : true range (m) and physical mirror angle (rad).
    biases : dict
        Bias values (nominal - true), SI; missing keys are 0.
    range_noise : additive range noise, metres.

    Returns
    -------
    (n, 3) or (3,) float64
    """
    xo = np.asarray(trajectory_position, dtype=np.float64)
    single = xo.ndim == 1
    xo = xo.reshape(-1, 3)
    r_ins = np.asarray(rotation, dtype=np.float64).reshape(-1, 3, 3)
    delta = as_vector(biases)
    rb = boresight_matrix(delta[3], delta[4], delta[5])
    r = np.asarray(range_true, dtype=np.float64) + delta[6] + np.asarray(range_noise)
    beta = (1.0 + delta[7]) * np.asarray(theta, dtype=np.float64)
    sb, cb = np.sin(beta), np.cos(beta)
    # v = dL + R_B rho, rho = -r [sin beta, 0, cos beta]
    vx = delta[0] - r * (rb[0, 0] * sb + rb[0, 2] * cb)
    vy = delta[1] - r * (rb[1, 0] * sb + rb[1, 2] * cb)
    vz = delta[2] - r * (rb[2, 0] * sb + rb[2, 2] * cb)
    n = int(np.broadcast(xo[:, 0], vx, r_ins[:, 0, 0]).size)
    out = np.empty((n, 3))
    for i in range(3):
        # X_o first, then term by term: a level R_ins (zeros and ones off the heading's
        # cosines and sines) gives the same bits as R_kappa written out.
        out[:, i] = xo[:, i] + r_ins[:, i, 0] * vx + r_ins[:, i, 1] * vy + r_ins[:, i, 2] * vz
    return out[0] if single and n == 1 else out


def biased_from_pulse(
    trajectory_position: np.ndarray,
    kappa: np.ndarray | float,
    range_true: np.ndarray | float,
    theta: np.ndarray | float,
    biases: dict[str, float],
    range_noise: np.ndarray | float = 0.0,
) -> np.ndarray:
    """:func:`georeference` from a level platform of heading(s) ``kappa`` (rad):
    ``R_ins = R_kappa``."""
    return georeference(trajectory_position, body_rotations_from_attitude(0.0, 0.0, kappa),
                        range_true, theta, biases, range_noise)


def true_pulse(
    trajectory_position: np.ndarray, kappa: np.ndarray | float, true_point: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Range and physical mirror angle of the pulse of the (ideal) true system that hit a point.

    The true point must lie in the true scan plane through ``trajectory_position`` (its
    along-track laser coordinate, ignored here, is then zero).
    """
    xo = np.asarray(trajectory_position, dtype=np.float64).reshape(-1, 3)
    p = np.asarray(true_point, dtype=np.float64).reshape(-1, 3)
    c, s = np.cos(kappa), np.sin(kappa)
    dx, dy, dz = (p - xo).T
    rx = c * dx + s * dy  # R_kappa^T (P - X_o)
    rz = dz
    theta = np.arctan2(-rx, -rz)
    return np.hypot(rx, rz), theta


def biased_point_exact(
    trajectory_position: np.ndarray,
    kappa: np.ndarray | float,
    true_point: np.ndarray,
    biases: dict[str, float],
) -> np.ndarray:
    """Exact biased point for a true point observed from ``trajectory_position`` at ``kappa``.

    Inverts the true pulse (``rho = R_kappa^T (P - X_o)``, ``theta = atan2(-rho_x, -rho_z)``,
    ``r = |rho|``) and re-georeferences it with the biased system (module docstring).
    Vectorised: ``(3,)`` or ``(n, 3)`` points, scalar or ``(n,)`` kappa.
    """
    single = np.asarray(true_point).ndim == 1
    r, theta = true_pulse(trajectory_position, kappa, true_point)
    out = biased_from_pulse(
        np.asarray(trajectory_position, dtype=np.float64).reshape(-1, 3), kappa, r, theta,
        biases,
    )
    return out.reshape(3) if single else out


# ---------------------------------------------------------------------- sensor and atmosphere


def swath_width(height: float, fov_deg: float) -> float:
    """Swath width on flat ground at ``height`` metres below the sensor."""
    return 2.0 * height * math.tan(math.radians(fov_deg) / 2.0)


def pulse_and_scan_rates(
    density: float, speed_mps: float, fov_deg: float, height: float = HIGH
) -> tuple[float, float]:
    """PRF (Hz) and mirror frequency (full zig-zag periods per second) for a mean point density.

    ``density`` is the mean over the swath at ``height`` on flat ground:
    ``PRF = density * speed * swath``; the mirror frequency ``speed * sqrt(density) / 2`` makes
    the mean along-track spacing of sweeps equal to the mean across-track spacing of points.
    """
    prf = density * speed_mps * swath_width(height, fov_deg)
    scan = speed_mps * math.sqrt(density) / 2.0
    return prf, scan


def _triangle(phase: np.ndarray) -> np.ndarray:
    """Triangle wave of period 1 in [-1, 1], -1 at phase 0."""
    frac = np.mod(phase, 1.0)
    return 1.0 - 4.0 * np.abs(frac - 0.5)


# ---------------------------------------------------------------------- flight plans


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


#: Optional attitude keys of a line spec (:func:`normalise_lines`), degrees or deg/s.
LINE_ATTITUDE_KEYS = ("turn_deg_s", "bank_deg", "roll_deg")


def normalise_lines(lines: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """Validated line specs ``{id, start: (x, y), end: (x, y), height}`` with the optional
    attitude keys ``turn_deg_s``, ``bank_deg``, ``roll_deg`` (None where absent; their meaning:
    :meth:`~lidarcal_ros.core.flight_path.FlightLine.from_spec`). ConfigError names the line at
    fault."""
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
    end) that crabs it by ``crab_deg`` (:func:`~lidarcal_ros.core.flight_path.crosswind_for_crab`;
    the other lines are crabbed as their directions make it)."""
    (x0, y0), (x1, y1) = lines[0]["start"], lines[0]["end"]
    return crosswind_for_crab(crab_deg, speed_mps, math.atan2(x0 - x1, y1 - y0))


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


# ---------------------------------------------------------------------- simulation


@dataclass(frozen=True)
class _LineTimes:
    """When a line is flown: its trajectory starts at ``t_line`` (absolute, s), its ``n``
    pulses are fired from ``t_line + LEAD_S`` to ``t_line + t_last_rel``, its samples are at
    ``t_line + tr``."""

    t_line: float
    n: int
    t_last_rel: float
    tr: np.ndarray


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
    samples, :class:`~lidarcal_ros.core.flight_path.RoughAir`)."""
    flights = [replace(fl, time_offset=(tm.t_line - t0) + LEAD_S)
               for fl, tm in zip(flights, times, strict=True)]
    if rough_air is None:
        return flights, None
    raw = Turbulence.draw(rough_air, seed if rough_air.seed is None else rough_air.seed)
    sample_times = np.concatenate([fl.time_offset + (tm.tr - LEAD_S)
                                   for fl, tm in zip(flights, times, strict=True)])
    turbulence = raw.scaled(rough_air.peaks, sample_times)
    return [replace(fl, turbulence=turbulence) for fl in flights], turbulence


@dataclass(frozen=True)
class _Sensor:
    """The scanner, the atmosphere and the noise of one mission."""

    prf: float
    scan_hz: float
    half_fov: float
    bias: dict[str, float]
    alpha: float
    range_noise_m: float
    intensity_noise: float


@dataclass
class _LineScan:
    """One line's pulses: what the biased system delivers and the truth."""

    xyz_b: np.ndarray
    xyz_t: np.ndarray
    cls: np.ndarray
    incidence: np.ndarray
    reflectance: np.ndarray
    range_true: np.ndarray
    theta: np.ndarray
    on_wall: np.ndarray
    intensity: np.ndarray

    @classmethod
    def empty(cls, n: int) -> _LineScan:
        return cls(np.empty((n, 3)), np.empty((n, 3)), np.empty(n, dtype=np.int8),
                   np.empty(n, dtype=np.float32), np.empty(n, dtype=np.float32), np.empty(n),
                   np.empty(n, dtype=np.float32), np.empty(n, dtype=bool),
                   np.empty(n, dtype=np.float32))


def _scan_line(fl: FlightLine, n: int, terrain: Surface, sensor: _Sensor,
               rng: np.random.Generator) -> _LineScan:
    """Fire the line's ``n`` pulses: each leaves the IMU origin at its exact (analytic) pose
    along ``R_ins [-sin theta, 0, -cos theta]``, meets the terrain, and is georeferenced by
    the biased system (:func:`georeference`). Local coordinates."""
    out = _LineScan.empty(n)
    for i0 in range(0, n, _BLOCK):
        i1 = min(i0 + _BLOCK, n)
        trel = np.arange(i0, i1, dtype=np.float64) / sensor.prf
        theta = sensor.half_fov * _triangle(trel * sensor.scan_hz)
        m = i1 - i0
        state = fl.state(trel)
        r_ins = state.rotation()
        st, ct = np.sin(theta), np.cos(theta)
        d = np.empty((m, 3))
        for j in range(3):  # R_ins times the body's beam (-sin theta, 0, -cos theta)
            d[:, j] = r_ins[:, j, 0] * -st + r_ins[:, j, 2] * -ct
        hits = cast_rays(terrain, state.position, d)
        noise = rng.normal(0.0, sensor.range_noise_m, m) if sensor.range_noise_m > 0 else 0.0
        xb = georeference(state.position, r_ins, hits.t, theta, sensor.bias, noise)
        cl, rho = terrain.class_and_reflectance_local(hits.inside[:, 0], hits.inside[:, 1])
        nrm = terrain.normal_local(hits.xyz[:, 0], hits.xyz[:, 1])
        if hits.on_wall.any():
            w = hits.on_wall
            nrm[w] = terrain.wall_normal_local(hits.inside[w, 0], hits.inside[w, 1])
        cos_inc = np.clip(np.abs(np.einsum("ij,ij->i", nrm, d)), 0.0, 1.0)
        amp = INTENSITY_K * rho * cos_inc * np.exp(-2.0 * sensor.alpha * hits.t) / hits.t**2
        if sensor.intensity_noise > 0:
            amp *= 1.0 + sensor.intensity_noise * rng.standard_normal(m)
        sl = slice(i0, i1)
        out.xyz_b[sl] = xb
        out.xyz_t[sl] = hits.xyz
        out.cls[sl] = cl
        out.incidence[sl] = np.arccos(cos_inc)
        out.reflectance[sl] = rho
        out.range_true[sl] = hits.t
        out.theta[sl] = theta
        out.on_wall[sl] = hits.on_wall
        out.intensity[sl] = np.maximum(amp, 0.0)
    return out


def _span_deg(values: np.ndarray) -> list[float]:
    return [math.degrees(float(values.min())) + 0.0, math.degrees(float(values.max())) + 0.0]


def _line_summary(fl: FlightLine, times: _LineTimes, state: FlightState, t_abs: np.ndarray,
                  origin: tuple[float, float], fov_deg: float) -> dict[str, Any]:
    """What was flown on a line (map coordinates), its attitude over its pulses from the
    trajectory's samples between the first and the last."""
    ox, oy = origin
    on = (times.tr >= LEAD_S) & (times.tr <= times.t_last_rel)

    def over_line(values: np.ndarray) -> np.ndarray:
        return np.broadcast_to(values, times.tr.shape)[on]

    kappa_track = over_line(state.kappa_track)
    crab = over_line(state.crab)
    wobble = over_line(state.kappa) - kappa_track - crab
    crab_mid = float(fl.state(np.array([0.5 * fl.duration])).crab[0])
    return {
        "id": fl.line_id,
        "start": (float(fl.start[0] + ox), float(fl.start[1] + oy)),
        "end": (float(fl.end[0] + ox), float(fl.end[1] + oy)),
        "height": float(fl.height),
        "direction": (float(fl.direction[0]), float(fl.direction[1])),
        "kappa": float(fl.kappa_start),
        "crab_deg": math.degrees(crab_mid),
        "length_m": float(fl.length),
        "swath_width_m": swath_width(fl.height, fov_deg),
        "t_first": float(t_abs[0]),
        "t_last": float(t_abs[-1]),
        "n_pulses": int(times.n),
        "turn_deg_s": math.degrees(fl.turn_rate),
        "bank_deg": math.degrees(fl.bank),
        "roll_offset_deg": math.degrees(fl.roll_offset),
        "radius_m": fl.radius,
        "heading_change_deg": math.degrees(fl.turn_rate * fl.duration),
        "attitude": {
            "roll_deg": _span_deg(over_line(state.roll)),
            "pitch_deg": _span_deg(over_line(state.pitch)),
            "yaw_wobble_deg": _span_deg(wobble),
            "crab_deg": _span_deg(crab),
        },
    }


def simulate_mission(
    *,
    scenario: str = "paper",
    seed: int = 0,
    density: float = 1.0,
    biases: dict[str, float] | None = None,
    range_noise_m: float = 0.02,
    line_length_m: float = 1000.0,
    speed_mps: float = SPEED_MPS,
    fov_deg: float = FOV_DEG,
    trajectory_rate_hz: float | None = None,
    trajectory_noise_m: float = 0.0,
    n_control: int = 1,
    t0: float = 1.7e9,
    lines: Sequence[dict[str, Any]] | None = None,
    origin: Sequence[float] = (0.0, 0.0),
    visibility_km: float = 48.3,
    intensity_noise: float = 0.02,
    terrain_kind: str | None = None,
    noise_seed: int | None = None,
    control_xy: Sequence[Sequence[float]] | None = None,
    terrain: Surface | None = None,
    wind_mps: Sequence[float] = (0.0, 0.0),
    attitude: bool | None = None,
    rough_air: RoughAir | None = None,
) -> SimulatedMission:
    """Simulate a linear-scanner mission with known biases (module docstring for the model).

    Parameters
    ----------
    scenario : ``"paper"`` (six strips: 1 N / 2 S at 1150 m on one track, 3 N / 4 S at 540 m
        on the same track, 5 and 6 both north at 1150 m, 0.56 swath apart), ``"flat"`` (the
        same lines over flat ground) or ``"one_track"`` (strips 1-4 only).
    seed : everything random (terrain, noise, rough air) derives from it.
    density : mean points per m^2 over the swath of the highest line; the same PRF and mirror
        rate serve every line (about 2.1x the density at 540 m).
    biases : bias values, SI (nominal - true); missing keys are 0; None = paper-like defaults.
    range_noise_m : Gaussian range noise, metres.
    line_length_m, speed_mps, fov_deg : flight and sensor geometry.
    trajectory_rate_hz, trajectory_noise_m : trajectory sampling (Hz; default: the rough air's
        INS rate, else 50) and Gaussian noise added to the published samples (the points are
        georeferenced with the noiseless positions).
    n_control : vertical control points on open ground seen by every strip (centre first).
    t0 : absolute time of the first trajectory sample, seconds.
    lines : explicit lines ``{id, start: (x, y), end: (x, y), height}`` in local coordinates
        (the area's centre at (0, 0), before ``origin`` is added), overriding the scenario's;
        each may be a turn (``turn_deg_s``, the track's heading rate, positive left, or
        ``bank_deg``, the coordinated turn's bank, right wing down positive) flown as the arc
        from ``start`` to ``end``, and may carry a constant ``roll_deg`` (a sideslip)
        (:meth:`~lidarcal_ros.core.flight_path.FlightLine.from_spec`).
    origin : added to every map X/Y (e.g. (500000, 5000000) for projected-CRS magnitudes).
    visibility_km : for the atmospheric attenuation of the intensities.
    intensity_noise : relative (multiplicative) Gaussian noise of the intensities.
    terrain_kind : ``"built-up"`` or ``"flat"``; default from the scenario.
    noise_seed : seed of the range, intensity and trajectory noise alone (default: ``seed``),
        for Monte Carlo runs over one terrain.
    control_xy : explicit control point locations (local X, Y), instead of ``n_control``
        placed automatically; kept clear of buildings and trees, Z from the terrain.
    terrain : Surface, optional
        The surface to scan (e.g. a :class:`~lidarcal_ros.core.raster_terrain.RasterTerrain` of the
        site), instead of one generated from ``seed`` and ``terrain_kind``.
    wind_mps : (east, north)
        Where the air moves, m/s. To hold its track the aircraft turns its nose into the
        crosswind: on each line the sensor's heading is the track's plus the crab angle
        ``asin(w_right / speed_mps)`` (``w_right`` the wind's component to the right of the
        track), opposite on lines flown the other way. The points are georeferenced with that
        heading, as the system's IMU gives it; the trajectory's positions do not show it,
        and the quasi-rigorous method takes the heading from the track (method.md section 4),
        so without ``attitude`` a crab it cannot see is what this simulates.
    attitude : bool, optional
        Give the trajectory the sensor's orientation at each sample (``R_ins`` as a REP-103
        quaternion, ``Trajectory.orientation``, written to a bag as the pose's orientation),
        as an INS would; False: positions only (the contract's identity orientation). Default:
        with rough air or banked or turning lines, else positions only.
    rough_air : RoughAir, optional
        Fly in turbulence (:class:`~lidarcal_ros.core.flight_path.RoughAir`: roll, pitch and
        heading wobble, heave and sway); its ``ins_rate_hz`` is the trajectory's sample rate.
        Every pulse is georeferenced with the exact attitude and position at its firing time,
        not with the trajectory's samples.

    Returns
    -------
    SimulatedMission
    """
    if scenario not in SCENARIOS:
        raise ConfigError(f"scenario {scenario!r} unknown; known: {', '.join(SCENARIOS)}")
    if rough_air is not None and not isinstance(rough_air, RoughAir):
        raise ConfigError(f"rough_air must be a RoughAir, got {type(rough_air).__name__}")
    ins_rate = None if rough_air is None else rough_air.ins_rate_hz
    if trajectory_rate_hz is None:
        rate = 50.0 if ins_rate is None else float(ins_rate)
    elif ins_rate is not None and trajectory_rate_hz != ins_rate:
        raise ConfigError(f"trajectory_rate_hz ({trajectory_rate_hz:g} Hz) differs from the "
                          f"rough air's INS rate ({ins_rate:g} Hz): give one")
    else:
        rate = float(trajectory_rate_hz)
    for name, value, lo in (("density", density, 0.0), ("line_length_m", line_length_m, 0.0),
                            ("speed_mps", speed_mps, 0.0), ("trajectory_rate_hz", rate, 0.0)):
        if not (math.isfinite(value) and value > lo):
            raise ConfigError(f"{name} must be positive, got {value}")
    if not 0.0 < fov_deg < 120.0:
        raise ConfigError(f"fov_deg must be in (0, 120), got {fov_deg}")
    if range_noise_m < 0 or trajectory_noise_m < 0 or intensity_noise < 0:
        raise ConfigError("noise levels must be non-negative")
    if n_control < 0:
        raise ConfigError(f"n_control must be >= 0, got {n_control}")
    wind = np.asarray(wind_mps, dtype=np.float64).reshape(-1)
    if wind.shape != (2,) or not np.isfinite(wind).all():
        raise ConfigError(f"wind_mps must be two finite numbers (east, north), got {wind_mps}")
    bias = _check_biases(biases)
    kind = terrain_kind or ("flat" if scenario == "flat" else "built-up")
    plan = normalise_lines(
        lines if lines is not None else scenario_lines(scenario, line_length_m, fov_deg)
    )
    ox, oy = float(origin[0]), float(origin[1])
    ref_height = max(ln["height"] for ln in plan)
    prf, scan_hz = pulse_and_scan_rates(density, speed_mps, fov_deg, ref_height)
    half_fov = math.radians(fov_deg) / 2.0
    alpha = atmospheric_alpha(visibility_km)
    flights = [FlightLine.from_spec(ln, speed_mps=speed_mps, wind=(wind[0], wind[1]),
                                    half_fov=half_fov, rough_air=rough_air) for ln in plan]

    extent = _terrain_extent(flights, half_fov)
    if control_xy is not None:
        ctrl_xy = np.asarray(control_xy, dtype=np.float64).reshape(-1, 2)
    else:
        ctrl_xy = _control_locations(flights, half_fov, n_control, extent)
    if terrain is None:
        terrain = Terrain(extent, seed=seed, kind=kind, keep_clear=ctrl_xy, clear_radius=15.0,
                          origin=(ox, oy))
    elif (ox, oy) != terrain.origin:
        raise ConfigError(f"origin {(ox, oy)} differs from the given terrain's "
                          f"{terrain.origin}")
    delta = as_vector(bias)
    times = _schedule(flights, prf, rate, t0)
    flights, turbulence = _into_the_air(flights, times, t0, rough_air, seed)
    manoeuvres = any(fl.turn_rate != 0.0 or fl.roll_offset != 0.0 for fl in flights)
    with_attitude = (rough_air is not None or manoeuvres) if attitude is None else bool(attitude)
    sensor = _Sensor(prf, scan_hz, half_fov, bias, alpha, range_noise_m, intensity_noise)

    noise_key = int(seed if noise_seed is None else noise_seed)
    rng_noise = np.random.default_rng([noise_key, 0x5EED])
    scans: list[_LineScan] = []
    strips: list[Strip] = []
    traj_t: list[np.ndarray] = []
    traj_xyz: list[np.ndarray] = []
    traj_q: list[np.ndarray] = []
    line_info: list[dict[str, Any]] = []
    for fl, tm in zip(flights, times, strict=True):
        scan = _scan_line(fl, tm.n, terrain, sensor, rng_noise)
        for arr in (scan.xyz_b, scan.xyz_t):
            arr[:, 0] += ox
            arr[:, 1] += oy
        t_abs = (tm.t_line + LEAD_S) + np.arange(tm.n, dtype=np.float64) / prf
        strips.append(Strip(strip_id=fl.line_id, xyz=scan.xyz_b, t=t_abs,
                            intensity=scan.intensity))
        scans.append(scan)
        # trajectory: LEAD_S before the first pulse to LEAD_S after the last, exact samples
        state = fl.state(tm.tr - LEAD_S)
        pos = state.position
        pos[:, 0] += ox
        pos[:, 1] += oy
        if trajectory_noise_m > 0:
            pos += rng_noise.normal(0.0, trajectory_noise_m, pos.shape)
        traj_t.append(tm.t_line + tm.tr)
        traj_xyz.append(pos)
        if with_attitude:
            traj_q.append(quaternions_from_attitude(
                *(np.broadcast_to(v, tm.tr.shape) for v in (state.roll, state.pitch,
                                                             state.kappa))))
        line_info.append(_line_summary(fl, tm, state, t_abs, (ox, oy), fov_deg))

    trajectory = Trajectory(np.concatenate(traj_t), np.concatenate(traj_xyz),
                            np.concatenate(traj_q) if with_attitude else None)
    control = None
    if ctrl_xy.shape[0]:
        cz = terrain.height_local(ctrl_xy[:, 0], ctrl_xy[:, 1])
        cxyz = np.column_stack([ctrl_xy[:, 0] + ox, ctrl_xy[:, 1] + oy, cz])
        control = ControlPoints([f"C{i + 1}" for i in range(len(cxyz))], cxyz)
    mission = Mission(trajectory=trajectory, strips=strips, control=control)
    rough: dict[str, Any] | None = None
    if rough_air is not None and turbulence is not None:
        rough = {**rough_air.describe(), "ins_rate_hz": rate,
                 "seed": int(seed if rough_air.seed is None else rough_air.seed),
                 "disturbances": turbulence.describe()}
    config: dict[str, Any] = {
        "scenario": scenario, "seed": int(seed), "density": float(density),
        "biases": dict(bias), "bias_vector": [float(v) for v in delta],
        "bias_convention": "true system ideal (zero lever arm, identity boresight, S=1); "
                           "nominal = bias; R_B = Rz(dkappa) Ry(dphi) Rx(domega); "
                           "beta = (1 + dS) theta; r = r_true + dr; "
                           "R_ins = Rz(kappa) Rx(pitch) Ry(roll)",
        "range_noise_m": float(range_noise_m), "line_length_m": float(line_length_m),
        "speed_mps": float(speed_mps), "fov_deg": float(fov_deg),
        "trajectory_rate_hz": rate,
        "trajectory_noise_m": float(trajectory_noise_m), "n_control": int(n_control),
        "t0": float(t0), "origin": [ox, oy], "visibility_km": float(visibility_km),
        "intensity_noise": float(intensity_noise), "terrain_kind": kind,
        "lines_given": lines is not None,
        "wind_mps": [float(wind[0]), float(wind[1])],
        "attitude": with_attitude,
        "rough_air": rough,
        "crab_deg": {int(li["id"]): li["crab_deg"] for li in line_info},
        "line_attitude": {int(li["id"]): _line_attitude_record(li) for li in line_info},
        "prf_hz": prf, "scan_rate_hz": scan_hz, "density_reference_height_m": ref_height,
        "wavelength_nm": WAVELENGTH_NM, "atmospheric_alpha_per_m": alpha,
        "intensity_k": INTENSITY_K, "turn_s": TURN_S, "lead_s": LEAD_S,
        "class_reflectance": {"soil": 0.30, "grass": 0.45, "asphalt": 0.12, "roof": 0.25,
                              "tree": 0.50},
        "terrain": terrain.describe(),
        "n_points": int(sum(len(st) for st in strips)),
    }
    return SimulatedMission(
        mission=mission, biases=dict(bias), true_xyz=[s.xyz_t for s in scans],
        surface_class=[s.cls for s in scans], incidence_true=[s.incidence for s in scans],
        reflectance_true=[s.reflectance for s in scans],
        range_true=[s.range_true for s in scans], terrain=terrain, lines=line_info,
        config=config, scan_angle_true=[s.theta for s in scans],
        on_wall=[s.on_wall for s in scans], flight_lines=flights,
    )


def _line_attitude_record(info: dict[str, Any]) -> dict[str, Any]:
    """A line's manoeuvre and attitude for the truth file (plain values)."""
    return {"turn_deg_s": info["turn_deg_s"], "bank_deg": info["bank_deg"],
            "roll_offset_deg": info["roll_offset_deg"], "radius_m": info["radius_m"],
            "heading_change_deg": info["heading_change_deg"],
            **{k: list(v) for k, v in info["attitude"].items()}}
