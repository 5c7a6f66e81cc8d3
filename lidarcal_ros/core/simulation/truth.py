"""What a simulated mission records as its truth: each line flown, and the record of the whole.

Plain values only, map coordinates, angles in degrees where the key says so.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from lidarcal_ros.core.params import as_vector
from lidarcal_ros.core.simulation.flight_path import FlightLine, FlightState, RoughAir, Turbulence
from lidarcal_ros.core.simulation.scanning import INTENSITY_K, WAVELENGTH_NM, Scanner, swath_width
from lidarcal_ros.core.simulation.spec import LEAD_S, TURN_S, SimulationSpec
from lidarcal_ros.core.simulation.surface import Surface

#: The simulated biases' convention, recorded with them.
BIAS_CONVENTION = ("true system ideal (zero lever arm, identity boresight, S=1); "
                   "nominal = bias; R_B = Rz(dkappa) Ry(dphi) Rx(domega); "
                   "beta = (1 + dS) theta; r = r_true + dr; "
                   "R_ins = Rz(kappa) Rx(pitch) Ry(roll)")


def _span_deg(values: np.ndarray) -> list[float]:
    return [math.degrees(float(values.min())) + 0.0, math.degrees(float(values.max())) + 0.0]


def line_summary(flight: FlightLine, state: FlightState, over_line: np.ndarray,
                 pulses: tuple[float, float, int], origin: tuple[float, float], fov_deg: float
                 ) -> dict[str, Any]:
    """What was flown on a line (map coordinates): its geometry and manoeuvre, the times of its
    first and last pulses, and its attitude over them.

    Parameters
    ----------
    flight : FlightLine
    state : FlightState
        The flight at the trajectory's samples of the line.
    over_line : (n_samples,) bool
        The samples from the first pulse to the last.
    pulses : (t_first, t_last, n_pulses)
        The absolute firing times (s) of the first and last pulses, and their number.
    origin : (x0, y0)
        Local to map coordinates, metres.
    fov_deg : float
        Field of view, degrees (for the swath width).

    Returns
    -------
    dict
        ``id``, ``start``, ``end`` (map), ``height``, ``direction`` (unit, start to end),
        ``kappa`` (the track's heading at the first pulse, rad), ``crab_deg`` (mid-line),
        ``length_m``, ``swath_width_m``, ``t_first``, ``t_last``, ``n_pulses``,
        ``turn_deg_s``, ``bank_deg`` (the coordinated turn's), ``roll_offset_deg``,
        ``radius_m`` (None on a straight line), ``heading_change_deg`` and ``attitude``: the
        least and greatest roll, pitch, heading wobble and crab over its pulses (deg, from the
        trajectory's samples).
    """
    ox, oy = origin

    def on_line(values: np.ndarray) -> np.ndarray:
        return np.broadcast_to(values, over_line.shape)[over_line]

    kappa_track = on_line(state.kappa_track)
    crab = on_line(state.crab)
    wobble = on_line(state.kappa) - kappa_track - crab
    crab_mid = float(flight.state(np.array([0.5 * flight.duration])).crab[0])
    return {
        "id": flight.line_id,
        "start": (float(flight.start[0] + ox), float(flight.start[1] + oy)),
        "end": (float(flight.end[0] + ox), float(flight.end[1] + oy)),
        "height": float(flight.height),
        "direction": (float(flight.direction[0]), float(flight.direction[1])),
        "kappa": float(flight.kappa_start),
        "crab_deg": math.degrees(crab_mid),
        "length_m": float(flight.length),
        "swath_width_m": swath_width(flight.height, fov_deg),
        "t_first": float(pulses[0]),
        "t_last": float(pulses[1]),
        "n_pulses": int(pulses[2]),
        "turn_deg_s": math.degrees(flight.turn_rate),
        "bank_deg": math.degrees(flight.bank),
        "roll_offset_deg": math.degrees(flight.roll_offset),
        "radius_m": flight.radius,
        "heading_change_deg": math.degrees(flight.turn_rate * flight.duration),
        "attitude": {
            "roll_deg": _span_deg(on_line(state.roll)),
            "pitch_deg": _span_deg(on_line(state.pitch)),
            "yaw_wobble_deg": _span_deg(wobble),
            "crab_deg": _span_deg(crab),
        },
    }


def line_attitude_record(summary: dict[str, Any]) -> dict[str, Any]:
    """A line's manoeuvre and attitude for the truth file (from its :func:`line_summary`)."""
    return {"turn_deg_s": summary["turn_deg_s"], "bank_deg": summary["bank_deg"],
            "roll_offset_deg": summary["roll_offset_deg"], "radius_m": summary["radius_m"],
            "heading_change_deg": summary["heading_change_deg"],
            **{k: list(v) for k, v in summary["attitude"].items()}}


def rough_air_record(rough_air: RoughAir, spec: SimulationSpec, turbulence: Turbulence
                     ) -> dict[str, Any]:
    """The rough air flown: its settings, the INS rate, its seed and the disturbances drawn."""
    return {**rough_air.describe(), "ins_rate_hz": spec.trajectory_rate_hz,
            "seed": int(spec.seed if rough_air.seed is None else rough_air.seed),
            "disturbances": turbulence.describe()}


def truth_config(spec: SimulationSpec, scanner: Scanner, *, terrain: Surface,
                 lines: list[dict[str, Any]], attitude: bool, turbulence: Turbulence | None,
                 n_points: int) -> dict[str, Any]:
    """The record of a simulated mission: every option of ``spec`` as simulated, what follows
    from them (PRF, mirror rate, extinction, the terrain's summary) and the lines' crab and
    attitude.

    Parameters
    ----------
    spec : SimulationSpec
    scanner : Scanner
        The mission's scanner.
    terrain : Surface
        The surface scanned.
    lines : list of dict
        The :func:`line_summary` of every line, in flight order.
    attitude : bool
        Whether the trajectory carries the orientation.
    turbulence : Turbulence or None
        The rough air's disturbances, scaled (None in calm air).
    n_points : int
        Points of all strips.
    """
    flight, sensor, noise, site = spec.flight, spec.sensor, spec.noise, spec.site
    rough = None
    if flight.rough_air is not None and turbulence is not None:
        rough = rough_air_record(flight.rough_air, spec, turbulence)
    ox, oy = site.origin
    return {
        "scenario": flight.scenario, "seed": spec.seed, "density": float(sensor.density),
        "biases": dict(spec.biases), "bias_vector": [float(v) for v in as_vector(spec.biases)],
        "bias_convention": BIAS_CONVENTION,
        "range_noise_m": float(noise.range_noise_m),
        "line_length_m": float(flight.line_length_m),
        "speed_mps": float(flight.speed_mps), "fov_deg": float(sensor.fov_deg),
        "trajectory_rate_hz": spec.trajectory_rate_hz,
        "trajectory_noise_m": float(noise.trajectory_noise_m), "n_control": int(site.n_control),
        "t0": float(flight.t0), "origin": [ox, oy], "visibility_km": float(site.visibility_km),
        "intensity_noise": float(noise.intensity_noise), "terrain_kind": spec.terrain_kind,
        "lines_given": flight.lines is not None,
        "wind_mps": list(flight.wind_mps),
        "attitude": attitude,
        "rough_air": rough,
        "crab_deg": {int(li["id"]): li["crab_deg"] for li in lines},
        "line_attitude": {int(li["id"]): line_attitude_record(li) for li in lines},
        "prf_hz": scanner.prf_hz, "scan_rate_hz": scanner.scan_rate_hz,
        "density_reference_height_m": max(li["height"] for li in lines),
        "wavelength_nm": WAVELENGTH_NM,
        "atmospheric_alpha_per_m": scanner.atmospheric_alpha_per_m,
        "intensity_k": INTENSITY_K, "turn_s": TURN_S, "lead_s": LEAD_S,
        "class_reflectance": {"soil": 0.30, "grass": 0.45, "asphalt": 0.12, "roof": 0.25,
                              "tree": 0.50},
        "terrain": terrain.describe(),
        "n_points": n_points,
    }


__all__ = ["BIAS_CONVENTION", "line_attitude_record", "line_summary", "rough_air_record",
           "truth_config"]
