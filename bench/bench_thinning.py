"""What thinning before calibration (``calibration.thinning_cell_m``) buys and costs.

    .venv/bin/python bench/bench_thinning.py                      # ~3.2M points, 4 cells
    .venv/bin/python bench/bench_thinning.py --density 0.5 --line-length 300 --cells 0,1

``lidarcal calibrate`` runs on one simulated mission (the paper's six strips, built-up
terrain; cached under ``bench/.cache/`` by ``benchlib.py``, with the true biases) once
without thinning, the baseline of the same run, and once per cell size. Per run: wall time
and peak resident memory of the process (its own ``VmHWM``), points left out, and per
parameter the estimate's difference from the unthinned one (cm, arcsec, or the unit of dS)
and its error in its own sigmas against the simulated truth. Ratios are baseline / thinned.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from pathlib import Path
from typing import Any

import machine  # bench/machine.py: this script's folder is on sys.path
from benchlib import CACHE, PYTHON, MissionSpec, prepare_mission, run_child, tail

ARCSEC = 180.0 * 3600.0 / 3.141592653589793
#: Display scale and unit of each parameter.
UNITS = {"dX": (100.0, "cm"), "dY": (100.0, "cm"), "dZ": (100.0, "cm"), "domega": (ARCSEC, "''"),
         "dphi": (ARCSEC, "''"), "dkappa": (ARCSEC, "''"), "dr": (100.0, "cm"), "dS": (1.0, "")}


def read_biases(path: Path) -> dict[str, tuple[float, float | None]]:
    """Each bias of a calibration file: its value (SI) and its sigma (None where not estimated)."""
    import yaml

    biases = yaml.safe_load(path.read_text())["lidarcal_calibration"]["biases"]
    return {k: (float(v["value"]), v["sigma"]) for k, v in biases.items()}


def calibrate(bag: str, cell: float, work: Path) -> dict[str, Any]:
    """Run ``lidarcal calibrate`` on ``bag`` with ``calibration.thinning_cell_m`` = ``cell`` (m;
    0: no thinning) in a child process: its figures (s, MiB), the points left out and the biases."""
    config = work / f"thinning_{cell:g}.yaml"
    config.write_text("/**:\n  ros__parameters:\n    calibration:\n"
                      f"      thinning_cell_m: {cell!r}\n")
    out = work / f"calibration_{cell:g}.yaml"
    log = work / f"calibrate_{cell:g}.log"
    res = run_child([PYTHON, "-m", "lidarcal_ros", "calibrate", bag, "--config", str(config),
                     "-o", str(out), "--overwrite"], log=log)
    if res["rc"] != 0:
        raise SystemExit(f"lidarcal calibrate (cell {cell:g} m) failed:\n{tail(log)}")
    text = log.read_text(errors="replace")
    left_out = re.search(r"(\d+) points left out", text)
    res["left_out"] = int(left_out.group(1)) if left_out else 0
    res["biases"] = read_biases(out)
    return res


def main() -> int:
    """Calibrate the mission without thinning and with each cell size and print the comparison;
    exit status 0."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--density", type=float, default=1.0)
    ap.add_argument("--line-length", type=float, default=500.0)
    ap.add_argument("--cells", default="0.7,1,1.5", help="cell sizes, m (0, the baseline, "
                    "is always run)")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    print(machine.describe(), flush=True)
    meta = prepare_mission(MissionSpec(args.density, args.line_length))
    truth = {name: (float(value), None) for name, value in meta["biases"].items()}
    work = CACHE / "thinning_work"
    work.mkdir(parents=True, exist_ok=True)
    cells = [0.0] + [float(c) for c in args.cells.split(",") if float(c) > 0]
    print(f"mission: {meta['n_points']} points (density {args.density:g}, lines of "
          f"{args.line_length:g} m)", flush=True)
    runs = {}
    for cell in cells:
        runs[cell] = calibrate(meta["bag"], cell, work)
        r = runs[cell]
        print(f"  cell {cell:g} m: {r['wall_s']:.1f} s, {r['peak_mib']:.0f} MiB, "
              f"{r['left_out']} points left out", flush=True)
    base = runs[0.0]
    names = [n for n in UNITS if base["biases"][n][1] is not None]
    print()
    print(f"{'cell':>6} {'kept':>6} {'wall':>7} {'ratio':>6} {'peak MiB':>9} {'ratio':>6}  "
          + " ".join(f"{n + ' diff':>13}" for n in names) + "   worst |error|/sigma")
    for cell, r in runs.items():
        kept = 1.0 - r["left_out"] / meta["n_points"]
        diffs = []
        worst = 0.0
        for n in names:
            value, sigma = r["biases"][n]
            scale, unit = UNITS[n]
            diffs.append(f"{(value - base['biases'][n][0]) * scale:+10.3g} {unit:<2}")
            if sigma:
                worst = max(worst, abs(value - truth[n][0]) / float(sigma))
        print(f"{cell:>5g}m {kept:>6.0%} {r['wall_s']:>6.1f}s "
              f"{base['wall_s'] / r['wall_s']:>6.2f} {r['peak_mib']:>9.0f} "
              f"{base['peak_mib'] / r['peak_mib']:>6.2f}  " + " ".join(diffs)
              + f"   {worst:.1f}")
    if args.json:
        args.json.write_text(json.dumps({"meta": meta, "runs": {
            str(c): {k: v for k, v in r.items()} for c, r in runs.items()}}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
