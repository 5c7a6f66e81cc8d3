"""The grid normals' cell size against the simulation's truth (reflectance, incidence).

The corrected reflectance and incidence with cells of the shipped rule and of fixed numbers of
point spacings:

    .venv/bin/python bench/normals_cells.py                   # four missions, five rules (minutes)
    .venv/bin/python bench/normals_cells.py --lookahead       # the offline (look-ahead) path
    .venv/bin/python bench/normals_cells.py --quick           # one small mission
    .venv/bin/python bench/normals_cells.py --scenarios paper:4:11 --rules shipped 1.5

Each mission (``SimulationSpec.from_options(scenario=S, density=D, seed=N,
line_length_m=L)``; ``--scenarios`` takes ``S:D:N``) is simulated once and corrected once
per cell rule with its true biases and the simulator's calibration constant (reflectance
absolute), through :class:`~lidarcal_ros.pipeline.correction.stream.StreamCorrector` in clouds
of 50 ms of scanning pushed one at a time, as the corrector node receives them: without
look-ahead (each cloud's normals from the points up to it, the live path) unless
``--lookahead``.

Rules (``--rules``): ``shipped`` is :func:`lidarcal_ros.core.normals.grid_normals.cell_size` as it
is (:data:`~lidarcal_ros.core.normals.grid_normals.CELL_SPACINGS` spacings while the cell side stays
within a metre, 1.5 where sparser); a number is that many point spacings along and across track
whatever the cell's size.

Figures per mission and rule (bench/README.md, "Normals: cell size against truth")
--------------------------------------------------------------------------------------
- **cell**: the rule's cell side for each strip's points (``cell_size``, the geometric mean
  of along and across track), m, smallest to largest strip (the paper scenario flies lines at
  1150 m and 540 m);
- **reflectance error**: ``|rho / rho_true - 1|``, %, median / p90 / p99, over the corrected
  points whose true incidence is below 60 deg; **roof**: the same on roofs only, median / p90;
- **incidence error**: ``|incidence - incidence_true|``, deg, median / p90, over the points
  given a normal;
- **rough**, **no normal**: % of all points flagged ``FLAG_ROUGH`` / ``FLAG_NO_NORMAL``.

The corrections run in this process, one thread (``nice`` it on a shared machine).
"""

from __future__ import annotations

import argparse
import itertools
import math
import os
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

import machine  # bench/machine.py: this script's folder is on sys.path
import numpy as np

import lidarcal_ros.core.normals.grid_normals as normals
from lidarcal_ros.core.config import FlightConfig
from lidarcal_ros.core.flags import FLAG_NO_NORMAL, FLAG_ROUGH
from lidarcal_ros.core.params import as_vector
from lidarcal_ros.core.simulation.scanning import INTENSITY_K
from lidarcal_ros.core.simulation.simulate import SimulatedMission, simulate_mission
from lidarcal_ros.core.simulation.spec import SCENARIOS, SimulationSpec
from lidarcal_ros.core.simulation.surface import ROOF
from lidarcal_ros.io.bag.mission_bag import strip_point_array
from lidarcal_ros.pipeline.correction.apply import CorrectionSettings, trajectory_heading
from lidarcal_ros.pipeline.correction.stream import StreamCorrector

SHIPPED = "shipped"
DEFAULT_RULES = [SHIPPED, "1.5", "2.0", "2.5", "3.0"]
#: Built-up terrain dense (two seeds) and sparse, and flat terrain dense.
DEFAULT_SCENARIOS = ["paper:4:5", "paper:4:7", "flat:4:5", "paper:0.5:3"]
QUICK_SCENARIOS = ["paper:4:5"]
#: Scanning time per cloud, s (a live sensor's cloud).
CLOUD_S = 0.05
#: The simulator's amplitude for reflectance 1 at the reference range (1000 m), normal
#: incidence and clear air: the calibration constant that makes the reflectance absolute.
SIMULATOR_CONSTANT = INTENSITY_K / 1000.0**2
MAX_INCIDENCE_DEG = 60.0


@dataclass(frozen=True)
class Scenario:
    """One simulated mission: ``scenario:density:seed`` and the length of its lines."""

    scenario: str
    density: float
    seed: int
    line_length_m: float

    @classmethod
    def parse(cls, text: str, line_length_m: float) -> Scenario:
        """The mission of ``scenario:density:seed`` with lines of ``line_length_m`` (m); a usage
        error names what is wrong."""
        try:
            scenario, density, seed = text.split(":")
            parsed = cls(scenario, float(density), int(seed), line_length_m)
        except ValueError:
            raise SystemExit(f"--scenarios: {text!r} is not SCENARIO:DENSITY:SEED "
                             "(e.g. paper:4:5)") from None
        if not parsed.density > 0:
            raise SystemExit(f"--scenarios: {text!r}: the density must be positive")
        if scenario not in SCENARIOS:
            raise SystemExit(f"--scenarios: {text!r}: scenario {scenario!r} unknown; known: "
                             f"{', '.join(SCENARIOS)}")
        return parsed

    def describe(self) -> str:
        """The mission in words, for the output."""
        return (f"{self.scenario} scenario, density {self.density:g}, seed {self.seed}, "
                f"{self.line_length_m:g} m lines")

    def simulate(self) -> SimulatedMission:
        """The simulated mission."""
        return simulate_mission(SimulationSpec.from_options(
            scenario=self.scenario, density=self.density, seed=self.seed,
            line_length_m=self.line_length_m))


@contextmanager
def cell_rule(rule: str) -> Iterator[None]:
    """Grids made meanwhile (offline and streamed) have cells of ``rule``: :data:`SHIPPED`,
    or a fixed number of point spacings."""
    if rule == SHIPPED:
        yield
        return
    spacings = float(rule)

    def fixed_side(spacing: float) -> float:
        return spacings * spacing

    # Every grid takes its cell side from normals._cell_side (through cell_size); no setting
    # chooses the rule, as a user has no reason to (it is the subject of this study), so it is
    # swapped here for the duration of one correction.
    shipped = normals._cell_side
    normals._cell_side = fixed_side
    try:
        yield
    finally:
        normals._cell_side = shipped


def cell_sides(sim: SimulatedMission) -> list[float]:
    """The cell side (m, geometric mean of along and across track) of each strip's points
    under the rule in force."""
    sides = []
    for strip in sim.mission.strips:
        heading = trajectory_heading(sim.mission.trajectory, float(np.median(strip.t)))
        along, across = normals.cell_size(strip.xyz, heading, strip.t)
        sides.append(math.sqrt(along * across))
    return sides


def correct_stream(sim: SimulatedMission, settings: CorrectionSettings,
                   lookahead: bool) -> np.ndarray:
    """The mission's strips, one after the other, corrected as clouds of :data:`CLOUD_S`
    pushed one at a time; the corrected points in the strips' order."""
    corrector = StreamCorrector(sim.mission.trajectory, settings, batch_points=0,
                                lookahead=lookahead)
    out: list[np.ndarray] = []
    for strip in sim.mission.strips:
        points = strip_point_array(strip, {}, f"strip {strip.strip_id}")
        t = points["t"]
        edges = np.unique(np.concatenate((
            [0], np.searchsorted(t, np.arange(t[0], t[-1], CLOUD_S)), [len(points)])))
        for a, b in itertools.pairwise(edges):
            out.extend(cloud for _tag, cloud in corrector.push(points[a:b]))
    out.extend(cloud for _tag, cloud in corrector.flush())
    return np.concatenate(out)


def percent(values: np.ndarray, *qs: float) -> list[float]:
    """Percentiles ``qs`` of fractions, in %; NaN for none."""
    if values.size == 0:
        return [math.nan] * len(qs)
    return [100.0 * float(v) for v in np.percentile(values, qs)]


def score(sim: SimulatedMission, corrected: np.ndarray) -> dict[str, Any]:
    """Errors of a corrected mission against the simulation's truth (module docstring)."""
    true_rho = np.concatenate(sim.reflectance_true).astype(np.float64)
    true_inc = np.concatenate(sim.incidence_true).astype(np.float64)
    roof = np.concatenate(sim.surface_class) == ROOF
    if corrected.shape[0] != true_rho.shape[0]:
        raise SystemExit(f"the corrector returned {corrected.shape[0]} points for "
                         f"{true_rho.shape[0]}")
    rho = corrected["reflectance"].astype(np.float64)
    inc = corrected["incidence"].astype(np.float64)
    flags = corrected["correction_flags"]
    scored = np.isfinite(rho) & (true_inc < math.radians(MAX_INCIDENCE_DEG))
    rho_err = np.abs(rho / true_rho - 1.0)
    given = np.isfinite(inc)
    inc_err = np.degrees(np.abs(inc[given] - true_inc[given]))
    return {
        "refl": percent(rho_err[scored], 50, 90, 99),
        "roof": percent(rho_err[scored & roof], 50, 90),
        "inc": [float(v) for v in np.percentile(inc_err, (50, 90))] if inc_err.size
        else [math.nan, math.nan],
        "rough": 100.0 * float(np.mean((flags & FLAG_ROUGH) != 0)),
        "no_normal": 100.0 * float(np.mean((flags & FLAG_NO_NORMAL) != 0)),
    }


def print_header() -> None:
    """Print the two header lines of the results table."""
    print(f"\n{'rule':>8} {'cell m':>10} {'reflectance error %':>20} {'roof %':>12} "
          f"{'incidence deg':>13} {'rough':>6} {'no':>6}")
    print(f"{'':>8} {'':>10} {'med / p90 / p99':>20} {'med / p90':>12} {'med / p90':>13} "
          f"{'%':>6} {'normal':>6}")


def print_row(rule: str, sides: list[float], s: dict[str, Any]) -> None:
    """Print one rule's row: its cell sides (m) and its error figures ``s`` (percent, degrees)."""
    name = rule if rule == SHIPPED else f"{float(rule):g} sp"
    cell = f"{min(sides):.2f}-{max(sides):.2f}"
    refl = " / ".join(f"{v:.2f}" for v in s["refl"])
    roof = " / ".join(f"{v:.2f}" for v in s["roof"])
    inc = " / ".join(f"{v:.2f}" for v in s["inc"])
    print(f"{name:>8} {cell:>10} {refl:>20} {roof:>12} {inc:>13} {s['rough']:>6.2f} "
          f"{s['no_normal']:>6.2f}", flush=True)


def main() -> None:
    """Correct each mission of the command line with each cell rule and print the errors against
    the truth."""
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    ap.add_argument("--scenarios", nargs="+", default=None, metavar="S:D:N",
                    help="missions as scenario:density:seed (default: "
                         + " ".join(DEFAULT_SCENARIOS) + ")")
    ap.add_argument("--rules", nargs="+", default=DEFAULT_RULES,
                    help="'shipped' and/or numbers of point spacings (default: "
                         + " ".join(DEFAULT_RULES) + ")")
    ap.add_argument("--line-length", type=float, default=None,
                    help="length of the missions' lines, m (default 150; --quick 60)")
    ap.add_argument("--lookahead", action="store_true",
                    help="fit each cloud's normals once the points after it are there (the "
                         "offline path) instead of at once (the live path)")
    ap.add_argument("--quick", action="store_true",
                    help=f"{' '.join(QUICK_SCENARIOS)} with 60 m lines, unless given")
    args = ap.parse_args()
    for rule in args.rules:
        if rule != SHIPPED:
            try:
                ok = float(rule) > 0
            except ValueError:
                ok = False
            if not ok:
                raise SystemExit(f"--rules: {rule!r} is neither 'shipped' nor a positive "
                                 "number of spacings")
    line_length = args.line_length or (60.0 if args.quick else 150.0)
    scenarios = [Scenario.parse(text, line_length) for text in
                 args.scenarios or (QUICK_SCENARIOS if args.quick else DEFAULT_SCENARIOS)]

    load_start = os.getloadavg()[0]
    print(f"machine: {machine.describe()}", flush=True)
    print(f"path: {'look-ahead (offline)' if args.lookahead else 'live (no look-ahead)'}, "
          f"clouds of {CLOUD_S * 1000:g} ms; reflectance errors over true incidence < "
          f"{MAX_INCIDENCE_DEG:g} deg", flush=True)
    config = FlightConfig.from_mapping({"radiometry.calibration_constant": SIMULATOR_CONSTANT})
    for scenario in scenarios:
        started = time.perf_counter()
        sim = scenario.simulate()
        settings = CorrectionSettings.from_config(config, as_vector(sim.biases))
        print(f"\n{scenario.describe()}: {sim.mission.n_points:,} points in "
              f"{len(sim.mission.strips)} strips (simulated in "
              f"{time.perf_counter() - started:.0f} s)", flush=True)
        print_header()
        for rule in args.rules:
            with cell_rule(rule):
                sides = cell_sides(sim)
                corrected = correct_stream(sim, settings, args.lookahead)
            print_row(rule, sides, score(sim, corrected))
        print(f"({time.perf_counter() - started:.0f} s)", flush=True)
    print(f"\nload average (1 min) before / after: {load_start:.2f} / "
          f"{os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
