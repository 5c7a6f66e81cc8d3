"""The trajectory errors of a simulated mission: each strip's ``e_s(t)``, drawn and recorded.

docs/method.md section 11.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from lidarcal_ros.core.simulation.spec import TrajectoryErrorSpec
from lidarcal_ros.errors import ConfigError

#: The model the truth file's ``trajectory_errors`` block records, in words.
TRAJECTORY_ERROR_MODEL = (
    "delivered - true, map frame, metres: per axis k, e_s,k(t) = offset_k + (t - t_ref) drift_k "
    "+ oscillation_amplitude_k sin(2 pi (t - t_ref) / oscillation_period_s + "
    "oscillation_phase_rad_k)")
#: What the trajectory carries outside the strips' pulses, in words.
BETWEEN_STRIPS = (
    "each line's trajectory samples (lead_s before its first pulse to lead_s after its last, "
    "t_span) carry its strip's e_s(t); the turns between lines have no samples, so a reader "
    "interpolating the trajectory across a turn blends one strip's error linearly into the "
    "next's")

Vector = tuple[float, float, float]


def _vector(values: Any) -> Vector:
    x, y, z = (float(v) + 0.0 for v in values)  # + 0.0: no -0.0 in the truth
    return (x, y, z)


@dataclass(frozen=True)
class StripTrajectoryError:
    """The error ``e_s(t)`` of one strip's delivered trajectory (delivered - true, map frame,
    metres), per axis ``k``:
    ``offset_k + (t - t_ref) drift_k + amplitude_k sin(2 pi (t - t_ref) / period_s + phase_k)``.

    Attributes
    ----------
    strip_id : int
    t_ref : float
        The strip's mid time (between its first and last pulse), absolute seconds.
    t_span : (float, float)
        The first and last trajectory sample of its line (absolute seconds), which carry it.
    offset : (3,) float
        Metres.
    drift : (3,) float
        m/s about ``t_ref``.
    amplitude : (3,) float
        Of the oscillation, metres.
    period_s : float
        Of the oscillation, seconds.
    phase : (3,) float
        Of the oscillation at ``t_ref``, radians.
    """

    strip_id: int
    t_ref: float
    t_span: tuple[float, float]
    offset: Vector
    drift: Vector
    amplitude: Vector
    period_s: float
    phase: Vector

    def at(self, t: np.ndarray | float) -> np.ndarray:
        """``e_s`` at absolute times ``t`` (s): (n, 3) float64, map frame, metres."""
        dt = np.asarray(t, dtype=np.float64).reshape(-1, 1) - self.t_ref
        return (np.asarray(self.offset) + dt * np.asarray(self.drift)
                + np.asarray(self.amplitude)
                * np.sin((2.0 * math.pi / self.period_s) * dt + np.asarray(self.phase)))

    def record(self) -> dict[str, Any]:
        """The strip's entry of the truth file's ``trajectory_errors.strips``."""
        return {"t_ref": self.t_ref, "t_span": list(self.t_span), "offset": list(self.offset),
                "drift": list(self.drift), "oscillation_amplitude": list(self.amplitude),
                "oscillation_period_s": self.period_s,
                "oscillation_phase_rad": list(self.phase)}

    @classmethod
    def from_record(cls, strip_id: int, record: Any) -> StripTrajectoryError:
        """The error of a truth file's strip entry (:meth:`record`); ConfigError naming the
        strip and the key that is missing or not numbers."""
        if not isinstance(record, Mapping):
            raise ConfigError(f"trajectory_errors: strip {strip_id}: expected a mapping")

        def numbers(key: str, n: int) -> list[float]:
            value = record.get(key)
            values = value if isinstance(value, (list, tuple)) else [value]
            out = [float(v) for v in values if isinstance(v, (int, float))
                   and not isinstance(v, bool) and math.isfinite(v)]
            if len(out) != len(values) or len(out) != n:
                raise ConfigError(f"trajectory_errors: strip {strip_id}: {key} must be "
                                  f"{n} finite number{'s' if n > 1 else ''}, got {value!r}")
            return out

        period = numbers("oscillation_period_s", 1)[0]
        if not period > 0.0:
            raise ConfigError(f"trajectory_errors: strip {strip_id}: oscillation_period_s "
                              f"must be positive, got {period}")
        span = numbers("t_span", 2)
        return cls(int(strip_id), numbers("t_ref", 1)[0], (span[0], span[1]),
                   _vector(numbers("offset", 3)), _vector(numbers("drift", 3)),
                   _vector(numbers("oscillation_amplitude", 3)), period,
                   _vector(numbers("oscillation_phase_rad", 3)))


def draw_trajectory_errors(spec: TrajectoryErrorSpec, seed: int,
                           strips: Sequence[tuple[int, float, tuple[float, float]]]
                           ) -> list[StripTrajectoryError]:
    """Each strip's error, drawn in flight order from a generator of its own (seeded by
    ``seed``), strip by strip (offset, drift, phases), so a strip's draws do not depend on the
    lines after it nor on the sigmas (standard normals scaled).

    Parameters
    ----------
    spec : TrajectoryErrorSpec
    seed : int
    strips : sequence of (strip_id, t_ref, t_span)
        Per strip in flight order: its id, mid time and trajectory span (absolute seconds).
    """
    rng = np.random.default_rng([seed, 0x7E55])
    offset_sigma = np.array([spec.offset_horizontal_m, spec.offset_horizontal_m,
                             spec.offset_vertical_m])
    amplitude = _vector([spec.oscillation_m] * 3)
    out = []
    for strip_id, t_ref, span in strips:
        offset = rng.standard_normal(3) * offset_sigma
        drift = rng.standard_normal(3) * spec.drift_m_per_s
        phase = rng.uniform(0.0, 2.0 * math.pi, 3)
        out.append(StripTrajectoryError(int(strip_id), float(t_ref),
                                        (float(span[0]), float(span[1])), _vector(offset),
                                        _vector(drift), amplitude,
                                        spec.oscillation_period_s, _vector(phase)))
    return out


def trajectory_errors_record(spec: TrajectoryErrorSpec, seed: int,
                             errors: Sequence[StripTrajectoryError]) -> dict[str, Any]:
    """The truth file's ``trajectory_errors`` block: the settings, the seed used, the model in
    words and each strip's parameters (by strip id)."""
    return {**spec.describe(), "seed": int(seed), "model": TRAJECTORY_ERROR_MODEL,
            "between_strips": BETWEEN_STRIPS,
            "strips": {err.strip_id: err.record() for err in errors}}


def read_trajectory_errors(block: Any) -> dict[int, StripTrajectoryError]:
    """Each strip's error from a truth file's ``trajectory_errors`` block
    (:func:`trajectory_errors_record`); ConfigError naming what is wrong."""
    strips = block.get("strips") if isinstance(block, Mapping) else None
    if not isinstance(strips, Mapping):
        raise ConfigError("trajectory_errors: expected a mapping with 'strips'")
    out = {}
    for key, record in strips.items():
        try:
            strip_id = int(key)
        except (TypeError, ValueError):
            raise ConfigError(f"trajectory_errors: strip id {key!r} is not an integer") from None
        out[strip_id] = StripTrajectoryError.from_record(strip_id, record)
    return out


__all__ = ["BETWEEN_STRIPS", "TRAJECTORY_ERROR_MODEL", "StripTrajectoryError",
           "draw_trajectory_errors", "read_trajectory_errors", "trajectory_errors_record"]
