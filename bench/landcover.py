"""The paper's Tables 6 and 7 on simulated missions: land-cover classification (Gaussian
maximum likelihood) of normalised DSM + raw intensity against normalised DSM + reflectance.

    .venv/bin/python bench/landcover.py                  # density 0.5, seeds 3 and 4
    .venv/bin/python bench/landcover.py --seeds 3 --cell 2

Each mission (``SimulationSpec.from_options(scenario="paper", density=D, line_length_m=250)``:
six strips at 1150 m and 540 m over built-up terrain whose surface classes are known) is
corrected with its true biases (geometry and reflectance, as ``lidarcal correct`` does); the
classifier is trained on the simulator's five surfaces (30% of each class's cells) and scored
on the other cells as the paper's four classes (tree, built-up = roofs + asphalt, grass,
soil). Both radiometries use the same cells and the same training split.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from lidarcal_ros.core.config import FlightConfig
from lidarcal_ros.core.params import as_vector
from lidarcal_ros.core.qa.landcover import classify_cells
from lidarcal_ros.core.simulation.simulate import simulate_mission
from lidarcal_ros.core.simulation.spec import SimulationSpec
from lidarcal_ros.pipeline.correction.apply import CorrectionSettings, NormalsFit, correct_columns

NAMES = ["soil", "grass", "asphalt", "roof", "tree"]
MERGE = [3, 2, 1, 1, 0]
MERGED = ["tree", "built-up", "grass", "soil"]


def main() -> None:
    """Correct and classify each mission of the command line and print both confusion tables."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", default="3,4", help="simulation seeds, comma-separated")
    ap.add_argument("--density", type=float, default=0.5, help="points per m^2 at 1150 m")
    ap.add_argument("--cell", type=float, default=2.0, help="raster cell, m")
    args = ap.parse_args()
    for seed in (int(s) for s in args.seeds.split(",")):
        started = time.perf_counter()
        sim = simulate_mission(SimulationSpec.from_options(
            scenario="paper", density=args.density, line_length_m=250.0, seed=seed))
        settings = CorrectionSettings.from_config(FlightConfig(), as_vector(sim.biases))
        xyz, rho, raw, labels = [], [], [], []
        for strip, cls in zip(sim.mission.strips, sim.surface_class, strict=True):
            res = correct_columns(strip.xyz, strip.t, strip.intensity,
                                  sim.mission.trajectory, settings,
                                  normals=NormalsFit(group=np.full(len(strip),
                                                                   strip.strip_id)))
            xyz.append(res.xyz)
            rho.append(res.reflectance)
            raw.append(strip.intensity)
            labels.append(cls)
        pts = np.concatenate(xyz)
        print(f"seed {seed}: {pts.shape[0]} points, {args.cell:g} m cells")
        for name, values in (("raw intensity (Table 6)", raw),
                             ("reflectance (Table 7)", rho)):
            acc = classify_cells(pts, np.concatenate(values).astype(np.float64),
                                 np.concatenate(labels), names=NAMES, merge=MERGE,
                                 merged_names=MERGED, cell_m=args.cell, seed=seed)
            print(f"  nDSM + {name}")
            print("\n".join("    " + line for line in acc.lines()))
        print(f"  ({time.perf_counter() - started:.1f} s)")


if __name__ == "__main__":
    main()
