"""Simulated airborne linear-scanner LiDAR missions with known system biases.

The simulator uses *exact* geometry (rotations, ranges, mirror angles, ray casting into an
analytic DSM), not the linearised bias model of method.md section 3, so that it tests the
calibration rather than agreeing with it by construction.

Bias convention (pinned by ``vectors/method_vectors.json``)
-----------------------------------------------------------
A bias is ``nominal - true``. The simulated *true* system is the ideal one: zero lever arm,
identity boresight, mirror scale 1, no range offset. The system georeferences with the
*nominal* values, which are therefore the biases themselves:

- a pulse fired at time ``t`` with physical mirror angle ``theta`` leaves the IMU origin ``X_o``
  along ``R_kappa [-sin theta, 0, -cos theta]`` and meets the terrain at ``P`` (true point) after
  ``r_true`` metres;
- the system records ``r = r_true + dr (+ noise)`` and ``beta = (1 + dS) * theta`` and reports
  ``X_b = X_o + R_kappa [dX, dY, dZ] + R_kappa R_B rho``, ``rho = -r [sin beta, 0, cos beta]``,
  with the exact boresight ``R_B = Rz(dkappa) Ry(dphi) Rx(domega)``
  (``scipy Rotation.from_euler("xyz", [domega, dphi, dkappa])``), whose small-angle form is
  method.md's ``I + skew``.

``R_kappa = [[c, -s, 0], [s, c, 0], [0, 0, 1]]`` (body right-forward-up to map), flight
direction ``(-sin kappa, cos kappa)``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from lidarcal_ros.core.attitude import quaternions_from_headings
from lidarcal_ros.core.mission import ControlPoints, Mission, Strip, Trajectory
from lidarcal_ros.core.model import boresight_matrix
from lidarcal_ros.core.params import PARAMETER_NAMES, arcsec_to_rad, as_vector
from lidarcal_ros.core.radiometry import atmospheric_alpha
from lidarcal_ros.core.terrain import Terrain, cast_rays
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
TURN_S = 30.0  # time between the end of one line's trajectory and the start of the next
LEAD_S = 2.0  # trajectory before the first and after the last pulse of a line
_BLOCK = 262_144


@dataclass
class SimulatedMission:
    """A simulated mission and its truth.

    Per-strip lists are in the order of ``mission.strips``; local truths are in map
    coordinates (``origin`` added) like the mission.
    """

    mission: Mission
    biases: dict[str, float]
    true_xyz: list[np.ndarray]
    surface_class: list[np.ndarray]
    incidence_true: list[np.ndarray]
    reflectance_true: list[np.ndarray]
    range_true: list[np.ndarray]
    terrain: Terrain
    lines: list[dict[str, Any]]
    config: dict[str, Any]
    scan_angle_true: list[np.ndarray] = field(default_factory=list)
    on_wall: list[np.ndarray] = field(default_factory=list)


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


def biased_from_pulse(
    trajectory_position: np.ndarray,
    kappa: np.ndarray | float,
    range_true: np.ndarray | float,
    theta: np.ndarray | float,
    biases: dict[str, float],
    range_noise: np.ndarray | float = 0.0,
) -> np.ndarray:
    """Point reported by the biased system for a pulse of known true geometry.

    Parameters
    ----------
    trajectory_position : (n, 3) or (3,)
        IMU origin at the firing time, map frame.
    kappa : heading(s), rad.
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
    delta = as_vector(biases)
    rb = boresight_matrix(delta[3], delta[4], delta[5])
    r = np.asarray(range_true, dtype=np.float64) + delta[6] + np.asarray(range_noise)
    beta = (1.0 + delta[7]) * np.asarray(theta, dtype=np.float64)
    sb, cb = np.sin(beta), np.cos(beta)
    # v = dL + R_B rho, rho = -r [sin beta, 0, cos beta]
    vx = delta[0] - r * (rb[0, 0] * sb + rb[0, 2] * cb)
    vy = delta[1] - r * (rb[1, 0] * sb + rb[1, 2] * cb)
    vz = delta[2] - r * (rb[2, 0] * sb + rb[2, 2] * cb)
    c, s = np.cos(kappa), np.sin(kappa)
    n = int(np.broadcast(xo[:, 0], vx, c).size)
    out = np.empty((n, 3))
    out[:, 0] = xo[:, 0] + c * vx - s * vy
    out[:, 1] = xo[:, 1] + s * vx + c * vy
    out[:, 2] = xo[:, 2] + vz
    return out[0] if single and n == 1 else out


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


def _normalise_lines(lines: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    out = []
    seen = set()
    for i, ln in enumerate(lines):
        try:
            lid = int(ln.get("id", i + 1))
            start = (float(ln["start"][0]), float(ln["start"][1]))
            end = (float(ln["end"][0]), float(ln["end"][1]))
            height = float(ln["height"])
        except (KeyError, TypeError, ValueError, IndexError) as exc:
            raise ConfigError(
                f"line {i}: needs id, start (x, y), end (x, y), height ({exc})"
            ) from exc
        if lid in seen:
            raise ConfigError(f"line id {lid} repeated")
        seen.add(lid)
        if math.hypot(end[0] - start[0], end[1] - start[1]) < 1.0:
            raise ConfigError(f"line {lid}: start and end coincide")
        if not height > 50.0:
            raise ConfigError(f"line {lid}: height {height} m too low (must exceed 50 m)")
        out.append({"id": lid, "start": start, "end": end, "height": height})
    if not out:
        raise ConfigError("no flight lines")
    return out


def _line_frame(ln: dict[str, Any]) -> tuple[np.ndarray, np.ndarray, float, float]:
    a = np.array(ln["start"], dtype=np.float64)
    b = np.array(ln["end"], dtype=np.float64)
    length = float(np.hypot(*(b - a)))
    u = (b - a) / length
    kappa = math.atan2(-u[0], u[1])
    return a, u, length, kappa


def _in_footprints(
    x: np.ndarray, y: np.ndarray, lines: list[dict[str, Any]], fov_deg: float, margin: float
) -> np.ndarray:
    ok = np.ones(x.shape, dtype=bool)
    for ln in lines:
        a, u, length, _ = _line_frame(ln)
        along = (x - a[0]) * u[0] + (y - a[1]) * u[1]
        across = (x - a[0]) * u[1] - (y - a[1]) * u[0]
        half = 0.5 * swath_width(ln["height"], fov_deg)
        ok &= (along >= margin) & (along <= length - margin) & (np.abs(across) <= half - margin)
    return ok


def _control_locations(
    lines: list[dict[str, Any]], fov_deg: float, n: int, extent: Sequence[float]
) -> np.ndarray:
    if n <= 0:
        return np.zeros((0, 2))
    xmin, xmax, ymin, ymax = extent
    # a 5 m grid anchored at the local origin (the centre of the named scenarios)
    gx, gy = np.meshgrid(np.arange(math.ceil(xmin / 5.0), math.floor(xmax / 5.0) + 1) * 5.0,
                         np.arange(math.ceil(ymin / 5.0), math.floor(ymax / 5.0) + 1) * 5.0)
    gx, gy = gx.ravel(), gy.ravel()
    for margin in (60.0, 40.0, 25.0):
        ok = _in_footprints(gx, gy, lines, fov_deg, margin)
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


def _terrain_extent(lines: list[dict[str, Any]], fov_deg: float) -> tuple[float, ...]:
    xs, ys = [], []
    for ln in lines:
        a, u, length, _ = _line_frame(ln)
        half = 0.5 * swath_width(ln["height"], fov_deg) + 100.0
        n = np.array([u[1], -u[0]])
        for along in (-100.0, length + 100.0):
            for side in (-half, half):
                p = a + along * u + side * n
                xs.append(p[0])
                ys.append(p[1])
    return (math.floor(min(xs)), math.ceil(max(xs)), math.floor(min(ys)), math.ceil(max(ys)))


# ---------------------------------------------------------------------- simulation


def simulate_mission(
    *,
    scenario: str = "paper",
    seed: int = 0,
    density: float = 1.0,
    biases: dict[str, float] | None = None,
    range_noise_m: float = 0.02,
    line_length_m: float = 1000.0,
    speed_mps: float = 60.0,
    fov_deg: float = 50.0,
    trajectory_rate_hz: float = 50.0,
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
    terrain: Terrain | None = None,
    wind_mps: Sequence[float] = (0.0, 0.0),
    attitude: bool = False,
) -> SimulatedMission:
    """Simulate a linear-scanner mission with known biases (module docstring for the model).

    Parameters
    ----------
    scenario : ``"paper"`` (six strips: 1 N / 2 S at 1150 m on one track, 3 N / 4 S at 540 m
        on the same track, 5 and 6 both north at 1150 m, 0.56 swath apart), ``"flat"`` (the
        same lines over flat ground) or ``"one_track"`` (strips 1-4 only).
    seed : everything random (terrain, noise) derives from it.
    density : mean points per m^2 over the swath of the highest line; the same PRF and mirror
        rate serve every line (about 2.1x the density at 540 m).
    biases : bias values, SI (nominal - true); missing keys are 0; None = paper-like defaults.
    range_noise_m : Gaussian range noise, metres.
    line_length_m, speed_mps, fov_deg : flight and sensor geometry.
    trajectory_rate_hz, trajectory_noise_m : trajectory sampling and Gaussian noise added to
        the published samples (the points are georeferenced with the noiseless positions).
    n_control : vertical control points on open ground seen by every strip (centre first).
    t0 : absolute time of the first trajectory sample, seconds.
    lines : explicit lines ``{id, start: (x, y), end: (x, y), height}`` in local coordinates
        (the area's centre at (0, 0), before ``origin`` is added), overriding the scenario's.
    origin : added to every map X/Y (e.g. (500000, 5000000) for projected-CRS magnitudes).
    visibility_km : for the atmospheric attenuation of the intensities.
    intensity_noise : relative (multiplicative) Gaussian noise of the intensities.
    terrain_kind : ``"built-up"`` or ``"flat"``; default from the scenario.
    noise_seed : seed of the range, intensity and trajectory noise alone (default: ``seed``),
        for Monte Carlo runs over one terrain.
    control_xy : explicit control point locations (local X, Y), instead of ``n_control``
        placed automatically; kept clear of buildings and trees, Z from the terrain.
    terrain : Terrain, optional
        The surface to scan (e.g. a :class:`~lidarcal_ros.core.terrain.RasterTerrain` of the
        site), instead of one generated from ``seed`` and ``terrain_kind``.
    wind_mps : (east, north)
        Where the air moves, m/s. To hold its track the aircraft turns its nose into the
        crosswind: on each line the sensor's heading is the track's plus the crab angle
        ``asin(w_right / speed_mps)`` (``w_right`` the wind's component to the right of the
        track), opposite on lines flown the other way. The points are georeferenced with that
        heading, as the system's IMU gives it; the trajectory's positions do not show it,
        and the quasi-rigorous method takes the heading from the track (method.md section 4),
        so without ``attitude`` a crab it cannot see is what this simulates.
    attitude : bool
        Give the trajectory the sensor's heading at each sample (``Trajectory.heading``,
        written to a bag as the orientation), as an IMU would; by default positions only
        (the contract's identity orientation).

    Returns
    -------
    SimulatedMission
    """
    if scenario not in SCENARIOS:
        raise ConfigError(f"scenario {scenario!r} unknown; known: {', '.join(SCENARIOS)}")
    for name, value, lo in (("density", density, 0.0), ("line_length_m", line_length_m, 0.0),
                            ("speed_mps", speed_mps, 0.0),
                            ("trajectory_rate_hz", trajectory_rate_hz, 0.0)):
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
    plan = _normalise_lines(
        lines if lines is not None else scenario_lines(scenario, line_length_m, fov_deg)
    )
    ox, oy = float(origin[0]), float(origin[1])
    ref_height = max(ln["height"] for ln in plan)
    prf, scan_hz = pulse_and_scan_rates(density, speed_mps, fov_deg, ref_height)
    half_fov = math.radians(fov_deg) / 2.0
    alpha = atmospheric_alpha(visibility_km)

    extent = _terrain_extent(plan, fov_deg)
    if control_xy is not None:
        ctrl_xy = np.asarray(control_xy, dtype=np.float64).reshape(-1, 2)
    else:
        ctrl_xy = _control_locations(plan, fov_deg, n_control, extent)
    if terrain is None:
        terrain = Terrain(extent, seed=seed, kind=kind, keep_clear=ctrl_xy, clear_radius=15.0,
                          origin=(ox, oy))
    elif (ox, oy) != terrain.origin:
        raise ConfigError(f"origin {(ox, oy)} differs from the given terrain's "
                          f"{terrain.origin}")
    delta = as_vector(bias)

    noise_key = int(seed if noise_seed is None else noise_seed)
    rng_noise = np.random.default_rng([noise_key, 0x5EED])
    strips: list[Strip] = []
    true_xyz: list[np.ndarray] = []
    classes: list[np.ndarray] = []
    incidence: list[np.ndarray] = []
    refl: list[np.ndarray] = []
    ranges: list[np.ndarray] = []
    thetas: list[np.ndarray] = []
    walls: list[np.ndarray] = []
    traj_t: list[np.ndarray] = []
    traj_xyz: list[np.ndarray] = []
    traj_heading: list[np.ndarray] = []
    line_info: list[dict[str, Any]] = []
    t_line = float(t0)
    for ln in plan:
        a, u, length, kappa_track = _line_frame(ln)
        crosswind = float(wind[0] * math.cos(kappa_track) + wind[1] * math.sin(kappa_track))
        if abs(crosswind) >= 0.5 * speed_mps:
            raise ConfigError(f"line {ln['id']}: a crosswind of {crosswind:.1f} m/s is too "
                              f"strong for {speed_mps:g} m/s")
        kappa = kappa_track + math.asin(crosswind / speed_mps)  # the sensor's heading
        c, s = math.cos(kappa), math.sin(kappa)
        height = ln["height"]
        duration = length / speed_mps
        n = int(math.floor(duration * prf)) + 1
        t_first_rel = LEAD_S
        xyz_b = np.empty((n, 3))
        xyz_t = np.empty((n, 3))
        cls_a = np.empty(n, dtype=np.int8)
        inc_a = np.empty(n, dtype=np.float32)
        rho_a = np.empty(n, dtype=np.float32)
        rng_a = np.empty(n)
        th_a = np.empty(n, dtype=np.float32)
        wall_a = np.empty(n, dtype=bool)
        inten = np.empty(n, dtype=np.float32)
        for i0 in range(0, n, _BLOCK):
            i1 = min(i0 + _BLOCK, n)
            trel = np.arange(i0, i1, dtype=np.float64) / prf
            theta = half_fov * _triangle(trel * scan_hz)
            m = i1 - i0
            xo = np.empty((m, 3))
            xo[:, 0] = a[0] + speed_mps * trel * u[0]
            xo[:, 1] = a[1] + speed_mps * trel * u[1]
            xo[:, 2] = height
            st, ct = np.sin(theta), np.cos(theta)
            d = np.empty((m, 3))
            d[:, 0] = -c * st
            d[:, 1] = -s * st
            d[:, 2] = -ct
            hits = cast_rays(terrain, xo, d)
            noise = rng_noise.normal(0.0, range_noise_m, m) if range_noise_m > 0 else 0.0
            xb = biased_from_pulse(xo, kappa, hits.t, theta, bias, noise)
            cl, rho = terrain._class_and_reflectance_local(hits.inside[:, 0], hits.inside[:, 1])
            nrm = terrain._normal_local(hits.xyz[:, 0], hits.xyz[:, 1])
            if hits.on_wall.any():
                w = hits.on_wall
                nrm[w] = terrain._wall_normal_local(hits.inside[w, 0], hits.inside[w, 1])
            cos_inc = np.clip(np.abs(np.einsum("ij,ij->i", nrm, d)), 0.0, 1.0)
            amp = INTENSITY_K * rho * cos_inc * np.exp(-2.0 * alpha * hits.t) / hits.t**2
            if intensity_noise > 0:
                amp *= 1.0 + intensity_noise * rng_noise.standard_normal(m)
            sl = slice(i0, i1)
            xyz_b[sl] = xb
            xyz_t[sl] = hits.xyz
            cls_a[sl] = cl
            inc_a[sl] = np.arccos(cos_inc)
            rho_a[sl] = rho
            rng_a[sl] = hits.t
            th_a[sl] = theta
            wall_a[sl] = hits.on_wall
            inten[sl] = np.maximum(amp, 0.0)
        for arr in (xyz_b, xyz_t):
            arr[:, 0] += ox
            arr[:, 1] += oy
        t_abs = (t_line + t_first_rel) + np.arange(n, dtype=np.float64) / prf
        strips.append(Strip(strip_id=int(ln["id"]), xyz=xyz_b, t=t_abs, intensity=inten))
        true_xyz.append(xyz_t)
        classes.append(cls_a)
        incidence.append(inc_a)
        refl.append(rho_a)
        ranges.append(rng_a)
        thetas.append(th_a)
        walls.append(wall_a)
        # trajectory: LEAD_S before the first pulse to LEAD_S after the last
        t_last_rel = t_first_rel + (n - 1) / prf
        n_traj = int(math.floor((t_last_rel + LEAD_S) * trajectory_rate_hz)) + 1
        tr = np.arange(n_traj, dtype=np.float64) / trajectory_rate_hz
        along = speed_mps * (tr - t_first_rel)
        pos = np.empty((n_traj, 3))
        pos[:, 0] = a[0] + along * u[0] + ox
        pos[:, 1] = a[1] + along * u[1] + oy
        pos[:, 2] = height
        if trajectory_noise_m > 0:
            pos += rng_noise.normal(0.0, trajectory_noise_m, pos.shape)
        traj_t.append(t_line + tr)
        traj_xyz.append(pos)
        traj_heading.append(np.full(len(tr), kappa))
        line_info.append({
            "id": int(ln["id"]),
            "start": (float(a[0] + ox), float(a[1] + oy)),
            "end": (float(ln["end"][0] + ox), float(ln["end"][1] + oy)),
            "height": float(height),
            "direction": (float(u[0]), float(u[1])),
            "kappa": float(kappa_track),
            "crab_deg": math.degrees(kappa - kappa_track),
            "length_m": float(length),
            "swath_width_m": swath_width(height, fov_deg),
            "t_first": float(t_abs[0]),
            "t_last": float(t_abs[-1]),
            "n_pulses": int(n),
        })
        t_line = float(t_line + tr[-1] + TURN_S)

    trajectory = Trajectory(
        np.concatenate(traj_t), np.concatenate(traj_xyz),
        quaternions_from_headings(np.concatenate(traj_heading)) if attitude else None)
    control = None
    if ctrl_xy.shape[0]:
        cz = terrain._height_local(ctrl_xy[:, 0], ctrl_xy[:, 1])
        cxyz = np.column_stack([ctrl_xy[:, 0] + ox, ctrl_xy[:, 1] + oy, cz])
        control = ControlPoints([f"C{i + 1}" for i in range(len(cxyz))], cxyz)
    mission = Mission(trajectory=trajectory, strips=strips, control=control)
    config: dict[str, Any] = {
        "scenario": scenario, "seed": int(seed), "density": float(density),
        "biases": dict(bias), "bias_vector": [float(v) for v in delta],
        "bias_convention": "true system ideal (zero lever arm, identity boresight, S=1); "
                           "nominal = bias; R_B = Rz(dkappa) Ry(dphi) Rx(domega); "
                           "beta = (1 + dS) theta; r = r_true + dr",
        "range_noise_m": float(range_noise_m), "line_length_m": float(line_length_m),
        "speed_mps": float(speed_mps), "fov_deg": float(fov_deg),
        "trajectory_rate_hz": float(trajectory_rate_hz),
        "trajectory_noise_m": float(trajectory_noise_m), "n_control": int(n_control),
        "t0": float(t0), "origin": [ox, oy], "visibility_km": float(visibility_km),
        "intensity_noise": float(intensity_noise), "terrain_kind": kind,
        "lines_given": lines is not None,
        "wind_mps": [float(wind[0]), float(wind[1])],
        "attitude": bool(attitude),
        "crab_deg": {int(li["id"]): li["crab_deg"] for li in line_info},
        "prf_hz": prf, "scan_rate_hz": scan_hz, "density_reference_height_m": ref_height,
        "wavelength_nm": WAVELENGTH_NM, "atmospheric_alpha_per_m": alpha,
        "intensity_k": INTENSITY_K, "turn_s": TURN_S, "lead_s": LEAD_S,
        "class_reflectance": {"soil": 0.30, "grass": 0.45, "asphalt": 0.12, "roof": 0.25,
                              "tree": 0.50},
        "terrain": terrain.describe(),
        "n_points": int(sum(len(st) for st in strips)),
    }
    return SimulatedMission(
        mission=mission, biases=dict(bias), true_xyz=true_xyz, surface_class=classes,
        incidence_true=incidence, reflectance_true=refl, range_true=ranges, terrain=terrain,
        lines=line_info, config=config, scan_angle_true=thetas, on_wall=walls,
    )
