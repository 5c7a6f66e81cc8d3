"""The flight of a simulated line as analytic functions of time.

Attitude as docs/method.md section 10 (``R_ins = Rz(kappa) Rx(pitch) Ry(roll)``); positions in
local map coordinates, metres; ``tau`` seconds since the line's first pulse.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from lidarcal_ros.core.georeferencing.attitude import body_rotations_from_attitude
from lidarcal_ros.errors import ConfigError

#: Standard gravity, m/s^2 (the coordinated turn: ``tan(bank) = v omega / g``).
G_MPS2 = 9.80665
#: The disturbances of rough air, in the order of :class:`Turbulence`'s rows: roll, pitch and
#: heading wobble (rad), heave (up) and sway (to the right of the track) of the IMU origin (m).
AXES = ("roll", "pitch", "yaw", "heave", "sway")
#: Farthest a beam may point from the vertical (the ray caster's reach), degrees.
MAX_OFF_NADIR_DEG = 60.0
#: The crab of the rough-air report that :data:`REPORTED_ROUGH_AIR` reproduces, degrees.
REPORTED_CRAB_DEG = 5.0


@dataclass(frozen=True)
class RoughAir:
    """Turbulence: smooth random roll, pitch and heading wobble and small excursions of the
    flight path, and the INS that records them. The defaults are the rough air of a user's
    report (:data:`REPORTED_ROUGH_AIR`: roll +-4 deg, pitch +-2.5 deg, 1 deg heading wobble,
    the orientation on the trajectory at 50 Hz; its 5 deg crab is the wind's,
    :func:`crosswind_for_crab`).

    Each disturbance (:data:`AXES`) is a sum of ``components`` sinusoids, one period drawn
    log-uniformly in each of as many equal bands of log-period spanning
    ``[min_period_s, max_period_s]``, with amplitudes growing as the square root of the period
    and random phases, drawn from the mission's seed (or ``seed``); it is scaled so that its
    largest excursion over the mission's trajectory samples is the peak given here.

    Attributes
    ----------
    roll_deg, pitch_deg, yaw_deg : float
        Peak roll, pitch and heading wobble, degrees, about the attitude the line is flown with
        (its bank, zero pitch, its crabbed heading).
    heave_m, sway_m : float
        Peak excursions of the IMU origin up and to the right of the track, metres.
    min_period_s, max_period_s : float
        The band of periods, seconds.
    components : int
        Sinusoids per disturbance.
    ins_rate_hz : float or None
        The INS's output rate, the trajectory's sample rate (None: the simulator's
        ``trajectory_rate_hz``).
    seed : int or None
        Seed of the disturbances (None: the mission's).
    """

    roll_deg: float = 4.0
    pitch_deg: float = 2.5
    yaw_deg: float = 1.0
    heave_m: float = 0.5
    sway_m: float = 0.5
    min_period_s: float = 2.0
    max_period_s: float = 30.0
    components: int = 4
    ins_rate_hz: float | None = 50.0
    seed: int | None = None

    def __post_init__(self) -> None:
        for name, limit in (("roll_deg", 30.0), ("pitch_deg", 20.0), ("yaw_deg", 20.0),
                            ("heave_m", 50.0), ("sway_m", 50.0)):
            value = getattr(self, name)
            if not (math.isfinite(value) and 0.0 <= value <= limit):
                raise ConfigError(f"rough air: {name} must be in [0, {limit:g}], got {value}")
        lo, hi = self.min_period_s, self.max_period_s
        if not (math.isfinite(lo) and math.isfinite(hi) and 0.0 < lo <= hi):
            raise ConfigError(f"rough air: periods must satisfy 0 < min_period_s <= "
                              f"max_period_s, got {lo} and {hi}")
        if isinstance(self.components, bool) or not (
                isinstance(self.components, int) and 1 <= self.components <= 64):
            raise ConfigError(f"rough air: components must be an integer in [1, 64], got "
                              f"{self.components!r}")
        rate = self.ins_rate_hz
        if rate is not None and not (math.isfinite(rate) and rate > 0.0):
            raise ConfigError(f"rough air: ins_rate_hz must be positive, got {rate}")

    @property
    def peaks(self) -> np.ndarray:
        """Peak of each disturbance in :data:`AXES` order (rad, rad, rad, m, m)."""
        return np.array([math.radians(self.roll_deg), math.radians(self.pitch_deg),
                         math.radians(self.yaw_deg), self.heave_m, self.sway_m])

    def describe(self) -> dict[str, Any]:
        """The settings as plain values (for a truth file)."""
        return {"roll_deg": float(self.roll_deg), "pitch_deg": float(self.pitch_deg),
                "yaw_deg": float(self.yaw_deg), "heave_m": float(self.heave_m),
                "sway_m": float(self.sway_m), "min_period_s": float(self.min_period_s),
                "max_period_s": float(self.max_period_s), "components": int(self.components),
                "ins_rate_hz": None if self.ins_rate_hz is None else float(self.ins_rate_hz),
                "seed": None if self.seed is None else int(self.seed)}


#: The rough air of the report "roll +-4 deg, pitch +-2.5 deg, 5 deg crab, 1 deg yaw wobble,
#: the IMU's REP-103 orientation on the trajectory at 50 Hz" (the crab: the wind's,
#: :func:`crosswind_for_crab` of :data:`REPORTED_CRAB_DEG`).
REPORTED_ROUGH_AIR = RoughAir()


def crosswind_for_crab(crab_deg: float, speed_mps: float, kappa_track: float = 0.0
                       ) -> tuple[float, float]:
    """The wind (east, north, m/s) across a track of heading ``kappa_track`` (rad) that makes
    an aircraft holding it at ``speed_mps`` fly crabbed by ``crab_deg`` (its nose turned left,
    into a wind from the left, for a positive crab): ``speed sin(crab)`` towards the track's
    right."""
    w = speed_mps * math.sin(math.radians(crab_deg))
    return w * math.cos(kappa_track), w * math.sin(kappa_track)


@dataclass(frozen=True)
class Turbulence:
    """The disturbances of rough air as sums of sinusoids of the mission's time.

    Row ``j`` of each array belongs to ``AXES[j]``; ``value_j(t) = sum_k amplitudes[j, k]
    sin(2 pi t / periods_s[j, k] + phases[j, k])`` (rad or m).
    """

    periods_s: np.ndarray
    amplitudes: np.ndarray
    phases: np.ndarray

    @classmethod
    def draw(cls, rough_air: RoughAir, seed: int) -> Turbulence:
        """Unscaled disturbances of ``rough_air`` (class docstring there) from ``seed``."""
        rng = np.random.default_rng([int(seed), 0xA1B])
        k = rough_air.components
        lo, hi = math.log(rough_air.min_period_s), math.log(rough_air.max_period_s)
        band = (np.arange(k) + rng.uniform(0.0, 1.0, (len(AXES), k))) / k
        periods = np.exp(lo + (hi - lo) * band)
        amplitudes = np.sqrt(periods) * rng.uniform(0.5, 1.0, (len(AXES), k))
        phases = rng.uniform(0.0, 2.0 * math.pi, (len(AXES), k))
        return cls(periods, amplitudes, phases)

    def __call__(self, t: np.ndarray) -> np.ndarray:
        """``(5, n)`` disturbances at mission times ``t`` (s)."""
        t = np.asarray(t, dtype=np.float64).reshape(-1)
        out = np.zeros((len(AXES), t.shape[0]))
        for j in range(len(AXES)):
            for a, period, phase in zip(self.amplitudes[j], self.periods_s[j], self.phases[j],
                                        strict=True):
                if a != 0.0:
                    out[j] += a * np.sin((2.0 * math.pi / period) * t + phase)
        return out

    def scaled(self, peaks: np.ndarray, t: np.ndarray) -> Turbulence:
        """These disturbances scaled so that the largest of each over times ``t`` is
        ``peaks`` (in :data:`AXES` order)."""
        largest = np.abs(self(t)).max(axis=1) if np.size(t) else np.zeros(len(AXES))
        with np.errstate(divide="ignore", invalid="ignore"):
            factor = np.where(largest > 0.0, np.asarray(peaks) / largest, 0.0)
        return Turbulence(self.periods_s, self.amplitudes * factor[:, None], self.phases)

    def describe(self) -> dict[str, Any]:
        """Each disturbance's sinusoids as plain values (units: rad for roll, pitch and yaw,
        m for heave and sway)."""
        return {axis: {"periods_s": self.periods_s[j].tolist(),
                       "amplitudes": self.amplitudes[j].tolist(),
                       "phases_rad": self.phases[j].tolist()}
                for j, axis in enumerate(AXES)}


@dataclass(frozen=True)
class FlightState:
    """Where the IMU origin is and how the sensor is turned, at some times.

    Angles are (n,) arrays, or (1,) where they stay constant over the line.

    Attributes
    ----------
    position : (n, 3) float64
        The IMU origin, local map coordinates, metres.
    roll, pitch, kappa : ndarray
        The sensor's attitude (rad; ``R_ins = Rz(kappa) Rx(pitch) Ry(roll)``).
    kappa_track : ndarray
        Heading of the ground track (rad).
    crab : ndarray
        The heading turned into the crosswind, ``kappa`` less the track's and the wobble (rad).
    """

    position: np.ndarray
    roll: np.ndarray
    pitch: np.ndarray
    kappa: np.ndarray
    kappa_track: np.ndarray
    crab: np.ndarray

    def rotation(self) -> np.ndarray:
        """``R_ins`` (n, 3, 3), or (1, 3, 3) for a constant attitude: body to map."""
        return body_rotations_from_attitude(self.roll, self.pitch, self.kappa)


def _wrap(angle: np.ndarray) -> np.ndarray:
    """Angles wrapped into ``[-pi, pi)``."""
    return np.mod(angle + math.pi, 2.0 * math.pi) - math.pi


@dataclass(frozen=True)
class FlightLine:
    """One line's flight: a straight track from ``start`` to ``end``, or the arc of a
    constant-rate turn through them; build with :meth:`from_spec`.

    Attributes
    ----------
    line_id : int
    start, end : (2,) float64
        Where the first and last pulses are fired, local map coordinates, metres.
    height : float
        Height of the track above the ground datum, metres.
    speed : float
        Ground speed, m/s.
    turn_rate : float
        Rate of the track's heading, rad/s (positive: a left turn); 0 for a straight line.
    roll_offset : float
        A constant roll on top of the turn's bank (a sideslip on a straight line), rad.
    wind : (east, north)
        Where the air moves, m/s: the sensor's heading is the track's plus the crab
        ``asin(w_right / speed)``.
    length : float
        Distance flown from ``start`` to ``end``, metres (the arc's, on a turn).
    direction : (2,) float64
        Unit vector from ``start`` to ``end``.
    kappa_start : float
        Heading of the track at the first pulse, rad.
    peaks : (5,) float64
        The largest rough-air disturbances (:data:`AXES`), zeros in calm air.
    turbulence : Turbulence or None
        The rough air (scaled), None in calm air.
    time_offset : float
        Mission time of the first pulse, seconds (the rough air's clock).
    """

    line_id: int
    start: np.ndarray
    end: np.ndarray
    height: float
    speed: float
    turn_rate: float
    roll_offset: float
    wind: tuple[float, float]
    length: float
    direction: np.ndarray
    kappa_start: float
    peaks: np.ndarray = field(default_factory=lambda: np.zeros(len(AXES)))
    turbulence: Turbulence | None = None
    time_offset: float = 0.0

    # ------------------------------------------------------------------ construction

    @classmethod
    def from_spec(cls, spec: dict[str, Any], *, speed_mps: float, wind: tuple[float, float],
                  half_fov: float, rough_air: RoughAir | None = None) -> FlightLine:
        """The flight of a line spec ``{id, start, end, height, turn_deg_s, bank_deg,
        roll_deg}`` (validated start, end and height; the attitude keys may be absent or None).

        ``turn_deg_s`` (the track's heading rate, positive left) or ``bank_deg`` (the bank of
        a coordinated turn, right wing down positive: a right turn) makes the line the arc of
        that turn from ``start`` to ``end`` (the shorter one); ``roll_deg`` adds a constant
        roll. Raises ConfigError, naming the line, for a turn too tight for its ends, a
        crosswind too strong for the speed, or a swath that would reach more than
        :data:`MAX_OFF_NADIR_DEG` from the vertical.
        """
        lid = int(spec["id"])
        a = np.array(spec["start"], dtype=np.float64)
        b = np.array(spec["end"], dtype=np.float64)
        chord = float(np.hypot(*(b - a)))
        u = (b - a) / chord
        turn_deg_s, bank_deg = spec.get("turn_deg_s"), spec.get("bank_deg")
        if turn_deg_s is not None and bank_deg is not None:
            raise ConfigError(f"line {lid}: give turn_deg_s or bank_deg, not both")
        if bank_deg is not None:
            if not abs(bank_deg) < 60.0:
                raise ConfigError(f"line {lid}: bank_deg {bank_deg} must be within +-60")
            omega = -G_MPS2 * math.tan(math.radians(bank_deg)) / speed_mps
        else:
            omega = math.radians(turn_deg_s or 0.0)
        kappa_chord = math.atan2(-u[0], u[1])
        if omega == 0.0:
            length, kappa_start = chord, kappa_chord
        else:
            radius = speed_mps / abs(omega)
            if chord > 2.0 * radius:
                raise ConfigError(
                    f"line {lid}: a turn of {math.degrees(omega):.3g} deg/s at "
                    f"{speed_mps:g} m/s (radius {radius:.0f} m) cannot join start and end "
                    f"{chord:.0f} m apart")
            sweep = 2.0 * math.asin(chord / (2.0 * radius))
            length = radius * sweep
            kappa_start = kappa_chord - math.copysign(0.5 * sweep, omega)
        peaks = np.zeros(len(AXES)) if rough_air is None else rough_air.peaks
        line = cls(line_id=lid, start=a, end=b, height=float(spec["height"]),
                   speed=float(speed_mps), turn_rate=omega,
                   roll_offset=math.radians(spec.get("roll_deg") or 0.0),
                   wind=(float(wind[0]), float(wind[1])), length=length, direction=u,
                   kappa_start=kappa_start, peaks=peaks)
        line._check(half_fov)
        return line

    def _check(self, half_fov: float) -> None:
        kappa = self.kappa_start + self.turn_rate * np.linspace(0.0, self.duration, 65)
        crosswind = self.wind[0] * np.cos(kappa) + self.wind[1] * np.sin(kappa)
        worst = float(crosswind[np.argmax(np.abs(crosswind))])
        if abs(worst) >= 0.5 * self.speed:
            raise ConfigError(f"line {self.line_id}: a crosswind of {worst:.1f} m/s is too "
                              f"strong for {self.speed:g} m/s")
        rmin, rmax = self.roll_range
        reach = math.degrees(max(abs(rmin), abs(rmax)) + half_fov)
        if reach > MAX_OFF_NADIR_DEG:
            raise ConfigError(
                f"line {self.line_id}: a roll of up to "
                f"{math.degrees(max(abs(rmin), abs(rmax))):.1f} deg with half the field of "
                f"view ({math.degrees(half_fov):.1f} deg) points beams {reach:.1f} deg from "
                f"the vertical (at most {MAX_OFF_NADIR_DEG:g})")

    # ------------------------------------------------------------------ the line's figures

    @property
    def duration(self) -> float:
        """Seconds from the first pulse to ``end``."""
        return self.length / self.speed

    @property
    def bank(self) -> float:
        """The coordinated turn's bank, ``-atan(v omega / g)`` (rad; 0 on a straight line)."""
        return 0.0 if self.turn_rate == 0.0 else -math.atan(
            self.speed * self.turn_rate / G_MPS2)

    @property
    def radius(self) -> float | None:
        """The turn's radius, metres (None on a straight line)."""
        return None if self.turn_rate == 0.0 else self.speed / abs(self.turn_rate)

    @property
    def roll_range(self) -> tuple[float, float]:
        """Least and greatest roll over the line (rad): its bank and roll offset, +- the rough
        air's peak."""
        roll = self.bank + self.roll_offset
        return roll - float(self.peaks[0]), roll + float(self.peaks[0])

    def _crab(self, kappa_track: np.ndarray | float) -> np.ndarray | float:
        if self.turn_rate == 0.0:  # one heading: a scalar, as the level simulator always had
            crosswind = float(self.wind[0] * math.cos(self.kappa_start)
                              + self.wind[1] * math.sin(self.kappa_start))
            return math.asin(crosswind / self.speed)
        across = self.wind[0] * np.cos(kappa_track) + self.wind[1] * np.sin(kappa_track)
        return np.arcsin(across / self.speed)

    # ------------------------------------------------------------------ the flight

    def state(self, tau: np.ndarray) -> FlightState:
        """The IMU origin and the attitude at ``tau`` (s since the first pulse)."""
        tau = np.asarray(tau, dtype=np.float64).reshape(-1)
        pos = np.empty((tau.shape[0], 3))
        kappa_track: np.ndarray | float
        if self.turn_rate == 0.0:
            kappa_track = self.kappa_start
            pos[:, 0] = self.start[0] + self.speed * tau * self.direction[0]
            pos[:, 1] = self.start[1] + self.speed * tau * self.direction[1]
        else:
            # The arc: d/dt position = speed (-sin kappa, cos kappa), kappa = k0 + omega tau.
            kappa_track = self.kappa_start + self.turn_rate * tau
            signed_radius = self.speed / self.turn_rate
            pos[:, 0] = self.start[0] + signed_radius * (np.cos(kappa_track)
                                                         - math.cos(self.kappa_start))
            pos[:, 1] = self.start[1] + signed_radius * (np.sin(kappa_track)
                                                         - math.sin(self.kappa_start))
        pos[:, 2] = self.height
        crab = self._crab(kappa_track)
        roll: np.ndarray | float = self.bank + self.roll_offset
        pitch: np.ndarray | float = 0.0
        kappa = kappa_track + crab
        if self.turbulence is not None:
            d_roll, d_pitch, d_yaw, heave, sway = self.turbulence(self.time_offset + tau)
            roll = roll + d_roll
            pitch = d_pitch
            kappa = kappa + d_yaw
            pos[:, 0] += sway * np.cos(kappa_track)
            pos[:, 1] += sway * np.sin(kappa_track)
            pos[:, 2] += heave
        return FlightState(pos, *(np.asarray(v, dtype=np.float64).reshape(-1)
                                  for v in (roll, pitch, kappa, kappa_track, crab)))

    # ------------------------------------------------------------------ footprints

    def along_across(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Distance along the track from ``start`` and across it (positive to the right) of
        map points (local coordinates, metres)."""
        a, u = self.start, self.direction
        if self.turn_rate == 0.0:
            along = (x - a[0]) * u[0] + (y - a[1]) * u[1]
            across = (x - a[0]) * u[1] - (y - a[1]) * u[0]
            return along, across
        # Position - centre = signed_radius * right(kappa): the centre lies left of a left turn.
        signed_radius = self.speed / self.turn_rate
        cx = a[0] - signed_radius * math.cos(self.kappa_start)
        cy = a[1] - signed_radius * math.sin(self.kappa_start)
        sign = math.copysign(1.0, self.turn_rate)
        wx, wy = x - cx, y - cy
        dist = np.hypot(wx, wy)
        across = sign * (dist - abs(signed_radius))
        kappa = np.arctan2(sign * wy, sign * wx)  # heading where the point is abeam
        sweep = self.turn_rate * self.duration
        swept = _wrap(kappa - self.kappa_start - 0.5 * sweep) + 0.5 * sweep
        return signed_radius * swept, across

    def _bands(self, half_fov: float) -> tuple[float, float, float]:
        """Across-track band scanned whatever the roll (``lo``, ``hi``) and the farthest a beam
        reaches to either side, metres on flat ground at ``height`` below the track.

        A beam at mirror angle theta under a roll meets the ground at
        ``-height tan(theta + roll)`` to the right of the track.
        """
        rmin, rmax = self.roll_range
        h = self.height
        lo = -h * math.tan(half_fov + rmin)
        hi = h * math.tan(half_fov - rmax)
        reach = max(h * math.tan(half_fov + rmax), h * math.tan(half_fov - rmin))
        return lo, hi, reach

    def _along_pad(self, half_fov: float) -> float:
        """How far rough air's pitch and heading wobble may move the scan line along the track,
        metres (0 in calm air)."""
        if not self.peaks.any():
            return 0.0
        _, _, reach = self._bands(half_fov)
        return self.height * math.tan(self.peaks[1]) + reach * math.tan(self.peaks[2])

    def covers(self, x: np.ndarray, y: np.ndarray, half_fov: float, margin: float
               ) -> np.ndarray:
        """Whether the line's swath surely holds map points (local coordinates) ``margin``
        metres inside its edges, whatever the rough air does (on flat ground at ``height``
        below the track)."""
        along, across = self.along_across(x, y)
        lo, hi, _ = self._bands(half_fov)
        pad = self._along_pad(half_fov)
        side = margin + self.peaks[4]
        return ((along >= margin + pad) & (along <= self.length - margin - pad)
                & (across >= lo + side) & (across <= hi - side))

    def outline(self, half_fov: float, margin: float = 100.0) -> np.ndarray:
        """Points (k, 2, local coordinates) whose bounding box holds everything the line may
        scan, ``margin`` metres to spare."""
        _, _, reach = self._bands(half_fov)
        half = reach + margin + self.peaks[4]
        pad = self._along_pad(half_fov)
        a, u = self.start, self.direction
        if self.turn_rate == 0.0:
            n = np.array([u[1], -u[0]])
            return np.array([a + along * u + side * n
                             for along in (-margin - pad, self.length + margin + pad)
                             for side in (-half, half)])
        state = self.state(np.linspace(0.0, self.duration, 65))
        kt = state.kappa_track
        right = np.column_stack([np.cos(kt), np.sin(kt)])
        forward = np.column_stack([-np.sin(kt), np.cos(kt)])
        track = state.position[:, :2]
        track = np.vstack([track[:1] - (margin + pad) * forward[:1], track,
                           track[-1:] + (margin + pad) * forward[-1:]])
        right = np.vstack([right[:1], right, right[-1:]])
        return np.vstack([track - half * right, track + half * right])


__all__ = ["AXES", "G_MPS2", "MAX_OFF_NADIR_DEG", "REPORTED_CRAB_DEG", "REPORTED_ROUGH_AIR",
           "FlightLine", "FlightState", "RoughAir", "Turbulence", "crosswind_for_crab"]
