"""How well a UAV payload's mounting is calibrated, by the INS's grade (issue 33's bars).

    .venv/bin/python bench/bench_uav_accuracy.py                      # vlp16 and os1-32, seeds 1-3
    .venv/bin/python bench/bench_uav_accuracy.py --ins exact,tactical --seeds 1 --layouts vlp16

Each run simulates a payload (``lidarcal simulate --uav``'s, ``--columns`` firings a
revolution, in memory), calibrates its mounting as ``lidarcal calibrate`` does (the flight
configuration's defaults, ``--models`` the trajectory models tried) and prints against the
truth: the rotation's error (arcsec), the lever arm's x and y (mm; z is held without
control), ``dr`` (mm), the largest |error / sigma| of an estimated bias, and how far the
calibration's error moves the points (median, mm: the points georeferenced with the
calibrated mounting against the true one, through the same delivered trajectory; and the same
with the lever arm's z given its true value, as control points or a survey would). The INS
grades: ``exact``; ``attitude`` (the tactical unit's attitude errors only); ``position``
(its position errors only); ``tactical`` (both: position 2, 2, 3 cm, attitude 18, 18, 36
arcsec, first-order Gauss-Markov over 30 s and 20 s). The baseline is the exact INS of the
same seed and layout: the ratio of each grade's rotation error to it is printed too.
The bars of issue 33 (tactical INS): 30 arcsec, 8 mm, dr 4 mm, honest sigmas (within 2-3).
``--set`` passes flight configuration values (e.g. the trajectory model's priors),
``--strips turns`` cuts the flight in the middle of each turn instead of leaving the turns
out, ``--nominal truth`` starts from the true mounting, ``--position-correlation-s`` and
``--attitude-correlation-s`` set how long the INS's position and attitude errors stay alike
(0.01: white noise, each 100 Hz pose its own), ``--told`` gives the calibration the INS's
errors (``ins.*``) so that its sigmas allow for them.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import time
from dataclasses import dataclass

import machine  # bench/machine.py: this script's folder is on sys.path
import numpy as np
import yaml

from lidarcal_ros.core.calibration.extrinsic import MountingCalibration, calibrate_mounting
from lidarcal_ros.core.config import FlightConfig
from lidarcal_ros.core.georeferencing.sensor_frame import Mounting, georeference
from lidarcal_ros.core.mission import Trajectory
from lidarcal_ros.core.simulation.uav_payload import (
    UavPayloadMission,
    UavPayloadSpec,
    simulate_uav_payload,
)
from lidarcal_ros.core.trajectory.lines import straight_lines
from lidarcal_ros.errors import LidarcalError
from lidarcal_ros.pipeline.calibration.sensor_frame import sensor_calibration_settings

ARCSEC = math.degrees(1.0) * 3600.0
#: The INS grades: UavPayloadSpec's options (none: the tactical unit's defaults).
GRADES: dict[str, dict[str, tuple[float, float, float]]] = {
    "exact": {"ins_position_sigma_m": (0.0, 0.0, 0.0),
              "ins_attitude_sigma_deg": (0.0, 0.0, 0.0)},
    "attitude": {"ins_position_sigma_m": (0.0, 0.0, 0.0)},
    "position": {"ins_attitude_sigma_deg": (0.0, 0.0, 0.0)},
    "tactical": {},
}


@dataclass
class Outcome:
    """One calibration against the truth."""

    rotation_arcsec: float
    lever_mm: tuple[float, float]
    dr_mm: float
    worst_sigmas: float
    moved_mm: float
    moved_z_given_mm: float
    seconds: float


def _rotation_error(a: np.ndarray, b: np.ndarray) -> float:
    return math.degrees(math.acos(min(1.0, (float(np.trace(a.T @ b)) - 1.0) / 2.0))) * 3600.0


def assess(m: UavPayloadMission, cal: MountingCalibration, seconds: float) -> Outcome:
    """The calibration ``cal`` of ``m`` against its truth."""
    true = m.truth_mounting
    error = cal.delta - m.biases
    used = np.isfinite(cal.sigma)
    t = m.clouds.absolute_times()
    pick = np.random.default_rng(0).choice(t.size, min(t.size, 200_000), replace=False)
    xyz = m.clouds.xyz[pick]
    # the true range bias is in the ranges: the same points as the true mounting puts them
    truth = georeference(xyz, t[pick], m.trajectory, true,
                         range_offset=float(m.biases[6])).xyz

    def moved(mounting: Mounting) -> float:
        calibrated = georeference(xyz, t[pick], m.trajectory, mounting,
                                  range_offset=cal.range_offset_m).xyz
        return float(np.median(np.linalg.norm(calibrated - truth, axis=1))) * 1e3

    lever = (cal.mounting.translation - true.translation) * 1e3
    return Outcome(_rotation_error(true.rotation, cal.mounting.rotation),
                   (float(lever[0]), float(lever[1])), float(error[6]) * 1e3,
                   float(np.max(np.abs(error[used] / cal.sigma[used]))), moved(cal.mounting),
                   moved(Mounting(cal.mounting.rotation, np.array(
                       [*cal.mounting.translation[:2], true.translation[2]]))), seconds)


def told(spec: UavPayloadSpec) -> dict[str, float]:
    """The flight configuration's ``ins.*`` values of the payload's INS (its errors)."""
    position, attitude = spec.ins_position_sigma_m, spec.ins_attitude_sigma_deg
    return {"ins__position_sigma_m": max(position[:2]), "ins__height_sigma_m": position[2],
            "ins__attitude_sigma_arcsec": max(attitude[:2]) * 3600.0,
            "ins__heading_sigma_arcsec": attitude[2] * 3600.0,
            "ins__position_correlation_s": spec.ins_correlation_s[0],
            "ins__attitude_correlation_s": spec.ins_correlation_s[1]}


def strip_spans(trajectory: Trajectory, *, through_turns: bool) -> np.ndarray:
    """The strips' time spans (k, 2), s: the straight lines, or (``through_turns``) the
    flight cut in the middle of each turn."""
    lines = straight_lines(trajectory)
    if not through_turns:
        return lines
    middle = 0.5 * (lines[1:, 0] + lines[:-1, 1])
    return np.column_stack([np.r_[lines[0, 0], middle + 1e-3], np.r_[middle, lines[-1, 1]]])


def main() -> None:
    """Run the grid the options give and print a row a run."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--layouts", default="vlp16,os1-32")
    ap.add_argument("--seeds", default="1,2,3")
    ap.add_argument("--ins", default="exact,attitude,position,tactical")
    ap.add_argument("--models", default="none",
                    help="calibration.trajectory.model values tried (default none)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="a flight configuration value for every calibration (repeatable), "
                    "e.g. calibration.trajectory.correlation_s=30")
    ap.add_argument("--strips", choices=("lines", "turns"), default="lines",
                    help="lines: each line a strip, the turns left out (lidarcal calibrate's "
                    "way); turns: the flight cut in the middle of each turn, each strip a "
                    "line with the halves of the turns beside it")
    ap.add_argument("--position-correlation-s", type=float, default=30.0,
                    help="correlation time of the INS's position errors, s")
    ap.add_argument("--attitude-correlation-s", type=float, default=20.0,
                    help="correlation time of the INS's attitude errors, s")
    ap.add_argument("--nominal", choices=("robot", "truth"), default="robot",
                    help="robot: the mounting off by tenths of a degree and centimetres (the "
                    "robot description's); truth: the true mounting, whose estimate should "
                    "be zero within 2 sigma (dr the true range bias)")
    ap.add_argument("--told", action="store_true",
                    help="give the calibration each grade's INS errors (ins.* of the flight "
                    "configuration: sigmas and correlation times), as a user would from the "
                    "unit's datasheet; without, the INS is taken as exact")
    ap.add_argument("--columns", type=int, default=360)
    ap.add_argument("--lines", type=int, default=4)
    args = ap.parse_args()
    print(machine.describe())
    print(f"{'layout':7s} {'seed':>4s} {'INS':9s} {'model':6s} {'rot':>7s} {'x':>7s} "
          f"{'y':>7s} {'dr':>6s} {'|e|/s':>6s} {'moved':>6s} {'z given':>7s} {'x exact':>8s} "
          f"{'time':>6s}")
    for layout in args.layouts.split(","):
        for seed in (int(s) for s in args.seeds.split(",")):
            floor: dict[str, float] = {}
            for grade in args.ins.split(","):
                spec = UavPayloadSpec(layout=layout, seed=seed, columns=args.columns,
                                      n_lines=args.lines, ins_correlation_s=(
                                          args.position_correlation_s,
                                          args.attitude_correlation_s),
                                      **GRADES[grade])  # type: ignore[arg-type]
                m = simulate_uav_payload(spec)
                if args.nominal == "truth":
                    m = dataclasses.replace(m, nominal=m.truth_mounting, biases=np.r_[
                        np.zeros(6), m.biases[6:]])
                spans = strip_spans(m.trajectory, through_turns=args.strips == "turns")
                for model in args.models.split(","):
                    config = FlightConfig().with_values(**{
                        k.replace(".", "__"): yaml.safe_load(v) for k, v in
                        (item.split("=", 1) for item in args.set)},
                        calibration__trajectory__model=model,
                        **(told(spec) if args.told else {}))
                    started = time.perf_counter()
                    try:
                        cal = calibrate_mounting(
                            m.clouds.xyz, m.clouds.absolute_times(), m.trajectory, m.nominal,
                            settings=sensor_calibration_settings(config=config), lines=spans)
                    except LidarcalError as exc:
                        print(f"{layout:7s} {seed:4d} {grade:9s} {model:6s} failed: {exc}")
                        continue
                    o = assess(m, cal, time.perf_counter() - started)
                    base = floor.setdefault(model, o.rotation_arcsec) if grade == "exact" \
                        else floor.get(model)
                    ratio = f"{o.rotation_arcsec / base:8.1f}" if base else f"{'-':>8s}"
                    print(f"{layout:7s} {seed:4d} {grade:9s} {model:6s} "
                          f"{o.rotation_arcsec:6.1f}\" {o.lever_mm[0]:+7.1f} "
                          f"{o.lever_mm[1]:+7.1f} {o.dr_mm:+6.1f} {o.worst_sigmas:6.1f} "
                          f"{o.moved_mm:6.1f} {o.moved_z_given_mm:7.1f} {ratio} {o.seconds:5.1f}s",
                          flush=True)


if __name__ == "__main__":
    main()
