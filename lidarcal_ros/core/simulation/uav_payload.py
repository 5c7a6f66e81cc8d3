"""A simulated UAV payload: a spinning multi-beam lidar on a multirotor, sensor-frame clouds.

A VLP-16 or OS1-32-like scanner (:data:`LAYOUTS`) tilted on a multirotor flying lines 55-80 m
over the analytic terrain, joined by turns: clouds of one revolution with the drivers' time
fields, the INS's noisy poses of ``base_link`` at 100 Hz, the nominal mounting and the truth
(docs/method.md section 12). Map frame local to the terrain, metres; mountings REP-103.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.signal import lfilter
from scipy.spatial.transform import Rotation

from lidarcal_ros.core.georeferencing.sensor_frame import Mounting, mounting_from_biases
from lidarcal_ros.core.mission import ControlPoints, Trajectory
from lidarcal_ros.core.params import N_PARAMETERS
from lidarcal_ros.core.simulation.flight_path import G_MPS2, RoughAir, Turbulence
from lidarcal_ros.core.simulation.ray_casting import cast_rays
from lidarcal_ros.core.simulation.terrain import Terrain
from lidarcal_ros.errors import ConfigError

#: Farthest a beam is cast from the vertical, deg (the ray caster's reach; beyond it, at
#: 55-80 m, the range exceeds the scanners' anyway).
MAX_OFF_NADIR_DEG = 60.0
#: Time field units of the drivers (docs/interface.md): FLOAT32 seconds, UINT32 nanoseconds.
SECONDS_FLOAT32 = "s_float32"
NANOSECONDS_UINT32 = "ns_uint32"


@dataclass(frozen=True)
class ScannerLayout:
    """A spinning multi-beam scanner as its driver publishes it.

    Attributes
    ----------
    name : str
    frame_id : str
        The clouds' ``header.frame_id``.
    elevations_deg : tuple of float
        Each beam's elevation above the sensor's x-y plane (the ``ring`` order), deg.
    rate_hz : float
        Revolutions per second; one cloud per revolution.
    columns : int
        Firings of each beam per revolution.
    beam_delay_s : float
        Between the firings of consecutive beams of a column, s (0: all at once).
    spin : float
        +1 counterclockwise about the sensor's z axis, -1 clockwise.
    time_field, time_units : str
        The per-point time field's name and units (:data:`SECONDS_FLOAT32` or
        :data:`NANOSECONDS_UINT32`), relative to the cloud's stamp.
    max_range_m, range_noise_m : float
        Farthest return, m, and the range noise (1 sigma), m.
    """

    name: str
    frame_id: str
    elevations_deg: tuple[float, ...]
    rate_hz: float
    columns: int
    beam_delay_s: float
    spin: float
    time_field: str
    time_units: str
    max_range_m: float
    range_noise_m: float


#: Velodyne VLP-16: 16 beams from -15 to +15 deg every 2 deg, fired 2.304 us apart in cycles
#: of 55.296 us (1808 per revolution at 10 Hz), spinning clockwise; ``time`` FLOAT32 s.
VLP16 = ScannerLayout("vlp16", "velodyne", tuple(float(e) for e in range(-15, 16, 2)), 10.0,
                      1808, 2.304e-6, -1.0, "time", SECONDS_FLOAT32, 100.0, 0.02)
#: An Ouster OS1-32-like scanner: 32 beams evenly over 45 deg, 1024 columns at 10 Hz, a
#: column's beams fired together, counterclockwise; ``t`` UINT32 ns.
OS1_32 = ScannerLayout("os1-32", "os_sensor", tuple(float(e) for e in np.linspace(-22.5, 22.5, 32)),
                       10.0, 1024, 0.0, 1.0, "t", NANOSECONDS_UINT32, 120.0, 0.015)
LAYOUTS: dict[str, ScannerLayout] = {VLP16.name: VLP16, OS1_32.name: OS1_32}


@dataclass(frozen=True)
class UavPayloadSpec:
    """Everything a UAV payload mission depends on (it is deterministic from ``seed``).

    Attributes
    ----------
    layout : ``vlp16`` or ``os1-32`` (:data:`LAYOUTS`).
    seed : int
    n_lines, line_length_m, line_spacing_m : the lines: parallel, north-south, alternating in
        direction, ``line_spacing_m`` apart, centred on the map's origin.
    heights_m : the lines' heights above the terrain's mean ground, cycled, m (55-80).
    speed_mps : ground speed, m/s.
    tilt_deg : the spin axis pitched up from the forward axis, so that the scan plane looks
        forward of nadir by as much, deg.
    lever_arm_m : the nominal ``t_bs``, m.
    biases : (8,) or None
        The mounting's error ``nominal - true`` (docs/method.md section 1, SI; ``dS`` must be
        0); None draws it from the seed: boresight 0.1-0.4 deg, lever arm 2-5 cm, range
        0.5-2 cm, signs at random.
    columns : firings per revolution (None: the layout's; fewer make a lighter mission).
    range_noise_m : None: the layout's.
    trajectory_rate_hz : the INS's output rate.
    ins_position_sigma_m, ins_attitude_sigma_deg : the INS's errors (east, north, up; roll,
        pitch, heading), 1 sigma, first-order Gauss-Markov with ``ins_correlation_s``
        (position, attitude).
    wobble_deg : the multirotor's peak roll and pitch wobble (half of it in heading), deg.
    drag_tilt_deg : nose-down pitch of cruise (the thrust against drag), deg.
    terrain_kind : ``built-up`` or ``flat``.
    start_time_s : the time of the first cloud, s (absolute, the trajectory's clock).
    n_control : vertical control points surveyed on open ground under the lines (0-100; the
        terrain keeps its objects 15 m from them), which make ``dZ`` observable.
    time_offset_s : the timing bias ``dt`` of the clouds' times (delivered - true, s; at most
        0.1 s; docs/method.md section 12): every stamp, and so every point's time, is ``dt``
        late on the trajectory's clock.
    """

    layout: str = "vlp16"
    seed: int = 0
    n_lines: int = 4
    line_length_m: float = 200.0
    line_spacing_m: float = 40.0
    heights_m: tuple[float, ...] = (55.0, 80.0, 65.0, 72.0)
    speed_mps: float = 8.0
    tilt_deg: float = 20.0
    lever_arm_m: tuple[float, float, float] = (0.12, 0.0, -0.18)
    biases: tuple[float, ...] | None = None
    columns: int | None = None
    range_noise_m: float | None = None
    trajectory_rate_hz: float = 100.0
    ins_position_sigma_m: tuple[float, float, float] = (0.02, 0.02, 0.03)
    ins_attitude_sigma_deg: tuple[float, float, float] = (0.005, 0.005, 0.01)
    ins_correlation_s: tuple[float, float] = (30.0, 20.0)
    wobble_deg: float = 1.0
    drag_tilt_deg: float = 4.0
    terrain_kind: str = "built-up"
    start_time_s: float = 1_700_000_000.0
    n_control: int = 0
    time_offset_s: float = 0.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.time_offset_s) and abs(self.time_offset_s) <= 0.1):
            raise ConfigError(f"uav payload: time_offset_s must be within +-0.1 s, got "
                              f"{self.time_offset_s}")
        if self.layout not in LAYOUTS:
            raise ConfigError(f"uav payload: layout {self.layout!r} unknown; known: "
                              f"{', '.join(LAYOUTS)}")
        if not (isinstance(self.n_lines, int) and 1 <= self.n_lines <= 50):
            raise ConfigError(f"uav payload: n_lines must be 1-50, got {self.n_lines!r}")
        for name in ("line_length_m", "line_spacing_m", "speed_mps", "trajectory_rate_hz"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0.0):
                raise ConfigError(f"uav payload: {name} must be positive, got {value}")
        if not self.heights_m or not all(20.0 <= h <= 300.0 for h in self.heights_m):
            raise ConfigError(f"uav payload: heights_m must be 20-300 m, got {self.heights_m}")
        if not (isinstance(self.n_control, int) and 0 <= self.n_control <= 100):
            raise ConfigError(f"uav payload: n_control must be 0-100, got {self.n_control!r}")
        if self.columns is not None and not (isinstance(self.columns, int)
                                             and 16 <= self.columns <= 4096):
            raise ConfigError(f"uav payload: columns must be 16-4096, got {self.columns!r}")
        if self.biases is not None and (len(self.biases) != N_PARAMETERS
                                        or self.biases[-1] != 0.0):
            raise ConfigError(f"uav payload: biases must be {N_PARAMETERS} numbers with dS 0 "
                              f"(a spinning scanner has no mirror scale), got {self.biases}")

    @property
    def scanner(self) -> ScannerLayout:
        """The layout, with ``columns`` and ``range_noise_m`` as this spec sets them."""
        base = LAYOUTS[self.layout]
        return ScannerLayout(
            base.name, base.frame_id, base.elevations_deg, base.rate_hz,
            base.columns if self.columns is None else self.columns, base.beam_delay_s,
            base.spin, base.time_field, base.time_units, base.max_range_m,
            base.range_noise_m if self.range_noise_m is None else self.range_noise_m)


def nominal_mounting(spec: UavPayloadSpec) -> Mounting:
    """The mounting as designed: the sensor's z (spin) axis forward, pitched up by
    ``tilt_deg``, its x axis down (forward of nadir by ``tilt_deg``), its y axis left."""
    s, c = math.sin(math.radians(spec.tilt_deg)), math.cos(math.radians(spec.tilt_deg))
    rotation = np.column_stack([[s, 0.0, -c], [0.0, 1.0, 0.0], [c, 0.0, s]])
    return Mounting(rotation, np.asarray(spec.lever_arm_m, dtype=np.float64))


def draw_biases(seed: int) -> np.ndarray:
    """The mounting error of a seed (``nominal - true``, SI; :class:`UavPayloadSpec`)."""
    rng = np.random.default_rng([int(seed), 0x5E45])
    sign = rng.choice([-1.0, 1.0], 7)
    magnitude = np.concatenate([rng.uniform(0.02, 0.05, 3),
                                np.radians(rng.uniform(0.1, 0.4, 3)), rng.uniform(0.005, 0.02, 1)])
    return np.concatenate([sign * magnitude, [0.0]])


# ------------------------------------------------------------------ the flight

def _cycloid(u: np.ndarray) -> np.ndarray:
    """``u - sin(2 pi u) / 2 pi``: 0 to 1 over ``u`` in [0, 1] with zero first and second
    derivative at both ends (a turn's heading and a climb start and end smoothly)."""
    return u - np.sin(2.0 * math.pi * u) / (2.0 * math.pi)


#: Gauss-Legendre nodes and weights on [0, 1] (a turn's position: the integral of its
#: heading's direction, exact to well below a micrometre).
_GL_X, _GL_W = np.polynomial.legendre.leggauss(24)
_GL_X, _GL_W = 0.5 * (_GL_X + 1.0), 0.5 * _GL_W
#: ``int_0^1 sin(pi cycloid(u)) du``: a 180-degree turn of duration T moves the path
#: sideways by ``speed T`` times this.
_TURN_SIDEWAYS = float(np.sum(_GL_W * np.sin(math.pi * _cycloid(_GL_X))))
#: Straight flight before the first and after the last line, s (the trajectory covers it).
LEAD_S = 2.0


@dataclass
class UavFlight:
    """The multirotor's path and attitude as functions of the time ``tau`` since the first
    line's start, s (negative in the lead-in).

    Segments alternate line, turn, line, ...: a line flies straight and level at its height;
    a turn reverses the heading by 180 degrees (``psi`` growing as :func:`_cycloid`) while
    climbing or descending to the next line's height, moving one line spacing sideways. The
    attitude tilts the thrust against the acceleration and the drag (a multirotor's), the
    heading along the track, with wobble (sinusoids of 0.5-8 s).
    """

    spec: UavPayloadSpec
    t0: np.ndarray = field(init=False)
    kind: np.ndarray = field(init=False)  # 0 line, 1 turn
    duration: np.ndarray = field(init=False)
    start: np.ndarray = field(init=False)  # (k, 2) xy
    psi0: np.ndarray = field(init=False)  # REP-103 yaw at the segment's start
    turn: np.ndarray = field(init=False)  # heading change, rad
    z0: np.ndarray = field(init=False)
    z1: np.ndarray = field(init=False)
    line: np.ndarray = field(init=False)  # line index, -1 for turns
    turbulence: Turbulence = field(init=False)

    def __post_init__(self) -> None:
        s = self.spec
        v, length = s.speed_mps, s.line_length_m
        turn_s = s.line_spacing_m / (v * _TURN_SIDEWAYS)
        x0 = -0.5 * (s.n_lines - 1) * s.line_spacing_m
        rows = []
        t = 0.0
        for i in range(s.n_lines):
            north = i % 2 == 0
            psi = 0.5 * math.pi if north else -0.5 * math.pi
            y_start = -0.5 * length if north else 0.5 * length
            z = s.heights_m[i % len(s.heights_m)]
            lead = LEAD_S if i == 0 else 0.0
            tail = LEAD_S if i == s.n_lines - 1 else 0.0
            sign = 1.0 if north else -1.0
            rows.append((t - lead, 0, (length + v * (lead + tail)) / v, x0 + i * s.line_spacing_m,
                         y_start - sign * v * lead, psi, 0.0, z, z, i))
            t += length / v
            if i + 1 < s.n_lines:
                z_next = s.heights_m[(i + 1) % len(s.heights_m)]
                rows.append((t, 1, turn_s, x0 + i * s.line_spacing_m, y_start + sign * length,
                             psi, -math.pi if north else math.pi, z, z_next, -1))
                t += turn_s
        a = np.array(rows, dtype=np.float64)
        self.t0, self.kind, self.duration = a[:, 0], a[:, 1].astype(np.int64), a[:, 2]
        self.start, self.psi0, self.turn = a[:, 3:5], a[:, 5], a[:, 6]
        self.z0, self.z1, self.line = a[:, 7], a[:, 8], a[:, 9].astype(np.int64)
        air = RoughAir(roll_deg=s.wobble_deg, pitch_deg=s.wobble_deg,
                       yaw_deg=0.5 * s.wobble_deg, heave_m=0.05, sway_m=0.05,
                       min_period_s=0.5, max_period_s=8.0, components=4, ins_rate_hz=None)
        span = np.arange(self.t0[0], self.end, 0.05)
        self.turbulence = Turbulence.draw(air, s.seed).scaled(air.peaks, span)

    @property
    def end(self) -> float:
        """The flight's last time, s (after the last line's lead-out)."""
        return float(self.t0[-1] + self.duration[-1])

    @property
    def recording(self) -> tuple[float, float]:
        """Start and end of the lines' flight (the clouds'), s."""
        return 0.0, self.end - LEAD_S

    def segment(self, tau: np.ndarray) -> np.ndarray:
        """The segment of each time (int64)."""
        return np.clip(np.searchsorted(self.t0, tau, side="right") - 1, 0, self.t0.size - 1)

    def pose(self, tau: np.ndarray) -> tuple[np.ndarray, Rotation]:
        """The true pose of ``base_link`` at times ``tau`` (s): position (n, 3), map frame,
        m, and the rotation ``R_mb`` (REP-103's body to map)."""
        tau = np.asarray(tau, dtype=np.float64).reshape(-1)
        k = self.segment(tau)
        v = self.spec.speed_mps
        dt = tau - self.t0[k]
        turning = self.kind[k] == 1
        u = np.where(turning, np.clip(dt / self.duration[k], 0.0, 1.0), 0.0)
        psi = self.psi0[k] + self.turn[k] * _cycloid(u)
        # heading rate (rad/s) and vertical acceleration of the turn's cycloids
        wave = 1.0 - np.cos(2.0 * math.pi * u)
        psi_dot = np.where(turning, self.turn[k] / self.duration[k] * wave, 0.0)
        climb = (self.z1[k] - self.z0[k])
        z_acc = np.where(turning, climb * 2.0 * math.pi * np.sin(2.0 * math.pi * u)
                         / self.duration[k] ** 2, 0.0)
        xyz = np.empty((tau.size, 3))
        xyz[:, 0] = self.start[k, 0] + v * dt * np.cos(psi)
        xyz[:, 1] = self.start[k, 1] + v * dt * np.sin(psi)
        xyz[:, 2] = self.z0[k] + climb * _cycloid(u)
        if turning.any():
            i = np.flatnonzero(turning)
            # int_0^dt (cos, sin)(psi(s)) ds by Gauss-Legendre on [0, dt]
            nodes = _GL_X[None, :] * u[i, None]
            ang = self.psi0[k[i], None] + self.turn[k[i], None] * _cycloid(nodes)
            span = dt[i]
            xyz[i, 0] = self.start[k[i], 0] + v * span * (np.cos(ang) @ _GL_W)
            xyz[i, 1] = self.start[k[i], 1] + v * span * (np.sin(ang) @ _GL_W)
        forward = np.column_stack([np.cos(psi), np.sin(psi), np.zeros_like(psi)])
        left = np.column_stack([-np.sin(psi), np.cos(psi), np.zeros_like(psi)])
        wobble = self.turbulence(tau)  # roll, pitch, yaw (rad), heave, sway (m)
        xyz += wobble[3][:, None] * [0.0, 0.0, 1.0] - wobble[4][:, None] * left
        # thrust along the body's up axis: against gravity, the turn's centripetal and
        # vertical accelerations and the drag of cruise
        drag = G_MPS2 * math.tan(math.radians(self.spec.drag_tilt_deg))
        thrust = (forward * drag + left * (v * psi_dot)[:, None]
                  + np.column_stack([np.zeros((tau.size, 2)), G_MPS2 + z_acc]))
        up = thrust / np.linalg.norm(thrust, axis=1, keepdims=True)
        fwd = forward - np.einsum("ij,ij->i", forward, up)[:, None] * up
        fwd /= np.linalg.norm(fwd, axis=1, keepdims=True)
        frame = Rotation.from_matrix(np.stack([fwd, np.cross(up, fwd), up], axis=2))
        return xyz, frame * Rotation.from_rotvec(wobble[:3].T)

    def line_of(self, tau: np.ndarray) -> np.ndarray:
        """The line flown at each time (int64; -1 in a turn)."""
        return self.line[self.segment(np.asarray(tau, dtype=np.float64))]


def _gauss_markov(rng: np.random.Generator, n: int, sigma: float, correlation_s: float,
                  step_s: float) -> np.ndarray:
    """A stationary first-order Gauss-Markov series of ``n`` samples ``step_s`` apart."""
    if sigma == 0.0 or n == 0:
        return np.zeros(n)
    a = math.exp(-step_s / correlation_s)
    w = rng.standard_normal(n)
    x0 = sigma * rng.standard_normal()
    out, _ = lfilter([sigma * math.sqrt(1.0 - a * a)], [1.0, -a], w, zi=[a * x0])
    return np.asarray(out)


# ------------------------------------------------------------------ the clouds

@dataclass
class SensorClouds:
    """Clouds in the sensor's frame, as a driver publishes them, concatenated.

    Attributes
    ----------
    frame_id : str
    time_field : str
        The time field's name (``time``, ``t``).
    time_units : :data:`SECONDS_FLOAT32` or :data:`NANOSECONDS_UINT32`.
    stamps : (k,) float64
        Each cloud's ``header.stamp``, absolute s (its first firing).
    offsets : (k + 1,) int64
        Cloud ``i`` holds points ``offsets[i]:offsets[i + 1]``.
    xyz : (n, 3) float32
        The points in the sensor's frame, m.
    time : (n,) float32 s or uint32 ns
        Each point's time after its cloud's stamp.
    ring : (n,) uint16
        The beam.
    """

    frame_id: str
    time_field: str
    time_units: str
    stamps: np.ndarray
    offsets: np.ndarray
    xyz: np.ndarray
    time: np.ndarray
    ring: np.ndarray

    def __len__(self) -> int:
        return int(self.stamps.shape[0])

    def cloud(self, i: int) -> slice:
        """The points of cloud ``i``."""
        return slice(int(self.offsets[i]), int(self.offsets[i + 1]))

    def absolute_times(self) -> np.ndarray:
        """Each point's absolute time, s, as a reader of the driver's fields computes it."""
        counts = np.diff(self.offsets)
        scale = 1e-9 if self.time_units == NANOSECONDS_UINT32 else 1.0
        return np.repeat(self.stamps, counts) + self.time.astype(np.float64) * scale


@dataclass
class UavPayloadMission:
    """A simulated UAV payload mission (:func:`simulate_uav_payload`).

    Attributes
    ----------
    spec : UavPayloadSpec
    scanner : ScannerLayout
    clouds : SensorClouds
    trajectory : Trajectory
        The INS's poses of ``base_link`` (with its noise), map frame.
    nominal : Mounting
        ``base_link -> clouds.frame_id`` as the robot's description has it.
    truth_mounting : Mounting
    biases : (8,) float64
        ``nominal - true`` (SI; ``dr`` the range bias, ``dS`` 0).
    truth_trajectory : Trajectory
        The noise-free poses at the same times.
    truth_xyz : (n, 3) float64
        Where each point's ray met the terrain, map frame, m.
    on_wall : (n,) bool
        The ray stopped on a wall.
    line : (n,) int64
        The line each point was recorded on (-1 in a turn).
    terrain : Terrain
    control : ControlPoints or None
        The vertical control points (``spec.n_control``; map frame), None without.
    """

    spec: UavPayloadSpec
    scanner: ScannerLayout
    clouds: SensorClouds
    trajectory: Trajectory
    nominal: Mounting
    truth_mounting: Mounting
    biases: np.ndarray
    truth_trajectory: Trajectory
    truth_xyz: np.ndarray
    on_wall: np.ndarray
    line: np.ndarray
    terrain: Terrain
    control: ControlPoints | None = None


def _control_points(spec: UavPayloadSpec) -> np.ndarray:
    """``spec.n_control`` places (k, 2), m, spread over the area every line sees: across
    the middle half of the lines' span, along their middle 70%, drawn from the seed."""
    if not spec.n_control:
        return np.zeros((0, 2))
    rng = np.random.default_rng([spec.seed, 0xC0])
    across = 0.25 * max(spec.n_lines - 1, 1) * spec.line_spacing_m
    return np.column_stack([rng.uniform(-across, across, spec.n_control),
                            rng.uniform(-0.35, 0.35, spec.n_control) * spec.line_length_m])


def _firings(scanner: ScannerLayout, stamp_tau: float
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One revolution's firings from ``stamp_tau``: their offsets from the stamp (s, as the
    driver stores them and read back: float32 s or whole ns), beams and unit directions in the
    sensor's frame (azimuth turning with the firing time)."""
    beams = len(scanner.elevations_deg)
    column = np.arange(scanner.columns, dtype=np.float64) / (scanner.rate_hz * scanner.columns)
    offset = column[:, None] + np.arange(beams)[None, :] * scanner.beam_delay_s
    if scanner.time_units == NANOSECONDS_UINT32:
        offset = np.round(offset * 1e9) * 1e-9
    else:
        offset = offset.astype(np.float32).astype(np.float64)
    ring = np.broadcast_to(np.arange(beams), offset.shape)
    azimuth = scanner.spin * 2.0 * math.pi * scanner.rate_hz * (stamp_tau + offset)
    elevation = np.radians(np.asarray(scanner.elevations_deg))[ring]
    u = np.stack([np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth),
                  np.sin(elevation)], axis=-1)
    return offset.ravel(), ring.ravel(), u.reshape(-1, 3)


#: Clouds whose rays are cast together (the ray caster's cost is per call as much as per ray).
_BATCH_CLOUDS = 10


def _scan(flight: UavFlight, scanner: ScannerLayout, true: Mounting, terrain: Terrain,
          biases: np.ndarray, rng: np.random.Generator
          ) -> tuple[SensorClouds, np.ndarray, np.ndarray]:
    """Every revolution of the lines' flight: each firing cast from the true pose and
    mounting at its time, the returns within the scanner's range recorded as the driver
    reports them (range plus the bias ``dr`` and noise, along the beam's direction in the
    sensor's frame). Stamps are relative to the flight's time origin here.

    Returns the clouds, each point's true position (map) and whether it lies on a wall.
    """
    offset, ring, u = _firings(scanner, 0.0)  # whole revolutions: the same every cloud
    u_base = u @ true.rotation.T
    lever = np.array(true.translation)
    cos_limit = math.cos(math.radians(MAX_OFF_NADIR_DEG))
    lo, hi = flight.recording
    period = 1.0 / scanner.rate_hz
    stamps = lo + period * np.arange(int(math.floor((hi - lo) / period)))
    counts, xyz_s, times, rings, truth, walls = [], [], [], [], [], []
    for b in range(0, stamps.size, _BATCH_CLOUDS):
        batch = stamps[b:b + _BATCH_CLOUDS]
        tau = (batch[:, None] + offset[None, :]).ravel()
        position, attitude = flight.pose(tau)
        direction = attitude.apply(np.tile(u_base, (batch.size, 1)))
        down = np.flatnonzero(direction[:, 2] < -cos_limit)
        origin = position[down] + attitude[down].apply(lever)
        hits = cast_rays(terrain, origin, direction[down])
        keep = (hits.t <= scanner.max_range_m) & (hits.t >= 1.0)
        sel = down[keep]
        firing = sel % offset.size
        r = hits.t[keep] + biases[6] + rng.normal(0.0, scanner.range_noise_m, sel.size)
        counts.append(np.bincount(sel // offset.size, minlength=batch.size))
        xyz_s.append((r[:, None] * u[firing]).astype(np.float32))
        times.append(offset[firing])
        rings.append(ring[firing].astype(np.uint16))
        truth.append(hits.xyz[keep])
        walls.append(hits.on_wall[keep])
    offset_all = np.concatenate(times)
    time = (np.round(offset_all * 1e9).astype(np.uint32)
            if scanner.time_units == NANOSECONDS_UINT32 else offset_all.astype(np.float32))
    offsets = np.concatenate([[0], np.cumsum(np.concatenate(counts))]).astype(np.int64)
    clouds = SensorClouds(scanner.frame_id, scanner.time_field, scanner.time_units, stamps,
                          offsets, np.concatenate(xyz_s), time, np.concatenate(rings))
    return clouds, np.concatenate(truth), np.concatenate(walls)


def simulate_uav_payload(spec: UavPayloadSpec | None = None) -> UavPayloadMission:
    """Fly the mission of ``spec`` (module docstring); the same spec gives the same mission
    to the bit."""
    spec = spec or UavPayloadSpec()
    scanner = spec.scanner
    flight = UavFlight(spec)
    biases = (draw_biases(spec.seed) if spec.biases is None
              else np.asarray(spec.biases, dtype=np.float64))
    nominal = nominal_mounting(spec)
    true = mounting_from_biases(nominal, biases)
    half = 0.5 * spec.line_length_m + 150.0
    across = 0.5 * (spec.n_lines - 1) * spec.line_spacing_m + 150.0
    control_xy = _control_points(spec)
    terrain = Terrain((-across, across, -half, half), seed=spec.seed, kind=spec.terrain_kind,
                      keep_clear=control_xy)
    control = ControlPoints(
        [f"C{i + 1}" for i in range(len(control_xy))],
        np.column_stack([control_xy, terrain.height_local(control_xy[:, 0], control_xy[:, 1])])
    ) if len(control_xy) else None
    rng = np.random.default_rng([spec.seed, 0x0AF1])

    clouds, truth_xyz, on_wall = _scan(flight, scanner, true, terrain, biases, rng)
    clouds.stamps += spec.start_time_s + spec.time_offset_s

    # The INS at its rate over the whole flight, and its errors.
    step = 1.0 / spec.trajectory_rate_hz
    tau_s = flight.t0[0] + step * np.arange(int(math.floor((flight.end - flight.t0[0]) / step)) + 1)
    position, attitude = flight.pose(tau_s)
    t_abs = spec.start_time_s + tau_s
    truth_trajectory = Trajectory(t_abs, position, attitude.as_quat())
    noise_rng = np.random.default_rng([spec.seed, 0x1E5])
    tau_p, tau_a = spec.ins_correlation_s
    dpos = np.column_stack([_gauss_markov(noise_rng, tau_s.size, s, tau_p, step)
                            for s in spec.ins_position_sigma_m])
    datt = np.column_stack([_gauss_markov(noise_rng, tau_s.size, math.radians(s), tau_a, step)
                            for s in spec.ins_attitude_sigma_deg])
    delivered = attitude * Rotation.from_rotvec(datt)
    trajectory = Trajectory(t_abs, position + dpos, delivered.as_quat())
    point_tau = clouds.absolute_times() - spec.start_time_s - spec.time_offset_s
    return UavPayloadMission(
        spec=spec, scanner=scanner, clouds=clouds, trajectory=trajectory, nominal=nominal,
        truth_mounting=true, biases=biases, truth_trajectory=truth_trajectory,
        truth_xyz=truth_xyz, on_wall=on_wall,
        line=flight.line_of(point_tau), terrain=terrain, control=control)


__all__ = [
    "LAYOUTS", "LEAD_S", "MAX_OFF_NADIR_DEG", "NANOSECONDS_UINT32", "OS1_32", "SECONDS_FLOAT32",
    "VLP16", "ScannerLayout", "SensorClouds", "UavFlight", "UavPayloadMission",
    "UavPayloadSpec", "draw_biases", "nominal_mounting",
    "simulate_uav_payload",
]
