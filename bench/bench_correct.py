"""Benchmark of ``lidarcal correct``: end to end against the I/O floor of the same output,
the numerics in memory against a straightforward baseline, and memory.

    .venv/bin/python bench/bench_correct.py                  # everything (~6 min on 2 cores)
    .venv/bin/python bench/bench_correct.py --only floor     # end to end vs the I/O floor
    .venv/bin/python bench/bench_correct.py --quick          # the 1M-point mission only

Every figure is measured in this run, on missions simulated once and cached under
``bench/.cache/`` (bench/benchlib.py). Each measured program runs in a fresh process; its
wall time includes the process start.

Figures (bench/README.md, "Correction")
---------------------------------------
- **end to end against the I/O floor** (the goals: within 2x of the floor for MCAP and LAZ,
  on missions of about 1M and 10M points; at least 3M points/s to MCAP on the 10M one):
  ``lidarcal correct BAG --calibration CAL -o OUT.mcap|.laz`` as a user runs it (process
  start, imports, the trajectory, reading and decoding every cloud, normals, correction,
  encoding, compression, writing), against ``bench/io_floor.py`` (the same bag read and the
  same number of points and fields written to the same format with the same libraries, no
  correction, one thread), alternately, ``--repeats`` times each; min and median.
- **the numerics in memory** (stage figures, not goals): points per second of the whole
  per-point correction on the clouds of a mission already in memory
  (:class:`~lidarcal_ros.pipeline.correction.stream.StreamCorrector`: column extraction, local
  trajectory, eq. [13], normals with the look-ahead, incidence, radar equation, the
  corrected arrays), in one thread, with two worker threads, and as the corrector node runs
  it (one cloud at a time), against a baseline doing the same steps the obvious way
  (``cKDTree`` k = 10 + PCA normals); the median reflectance error against the simulated
  truth beside each, so that a speed-up that loses accuracy shows.
- **peak memory** of ``lidarcal correct`` (the goal: flat with mission length, under 1 GB)
  on two missions of the same density (2.6M and 10.3M points; ``--quick``: 1.3M and 5.1M),
  both formats, ``--workers`` 1 and 2: the peak resident set of the process tree.

The machine should be otherwise idle (the load average is printed before and after).
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
import shutil
import statistics
import sys
import time
from pathlib import Path
from typing import Any

import benchlib  # bench/benchlib.py: this script's folder is on sys.path
import machine
from benchlib import PYTHON, MissionSpec, run_child, tail

GOAL_RATIO_TO_FLOOR = 2.0
GOAL_POINTS_PER_S_10M_MCAP = 3.0e6
GOAL_PEAK_MIB = 1024.0
WORK = benchlib.CACHE / "correct_work"


# ---------------------------------------------------------------------------- missions
def calibration_of(meta: dict[str, Any]) -> Path:
    """A calibration file of the mission's true biases (beside its bag)."""
    import yaml

    path = Path(meta["bag"]).parent / "calibration_truth.yaml"
    if not path.exists():
        path.write_text(yaml.safe_dump({"lidarcal_calibration": {"biases": {
            k: {"value": float(v), "sigma": None, "estimated": True}
            for k, v in meta["biases"].items()}}}))
    return path


def output_size_mib(path: Path) -> float:
    """The size of an output file, or of the files of a bag directory, MiB."""
    if path.is_file():
        return path.stat().st_size / 2**20
    return sum(f.stat().st_size for f in path.iterdir()) / 2**20


def remove(path: Path) -> None:
    """Delete an output file or directory, if there is one."""
    if path.is_dir():
        shutil.rmtree(path)
    elif path.exists():
        path.unlink()


# ---------------------------------------------------------------------------- end to end
def run_correct(meta: dict[str, Any], out: Path, workers: int = 2,
                log: Path | None = None) -> dict[str, Any]:
    """Time ``lidarcal correct`` of the mission ``meta`` to ``out`` (its suffix says the format)
    in a child process: its figures (s, MiB), with the output's size; the output is deleted."""
    remove(out)
    log = log or WORK / f"correct{out.suffix}.log"
    res = run_child([benchlib.LIDARCAL, "correct", meta["bag"], "--calibration",
                     str(calibration_of(meta)), "-o", str(out), "--workers", str(workers)],
                    log=log)
    if res["rc"] != 0:
        raise SystemExit(f"lidarcal correct failed (exit {res['rc']}):\n{tail(log)}")
    res["size_mib"] = output_size_mib(out)
    remove(out)
    return res


def run_floor(meta: dict[str, Any], out: Path) -> dict[str, Any]:
    """Time bench/io_floor.py on the mission ``meta`` to ``out`` in a child process: its figures
    (s, MiB), with the output's size; the output is deleted."""
    from lidarcal_ros.io.bag.chunk_writer import ZSTD_LEVEL

    remove(out)
    log = WORK / f"floor{out.suffix}.log"
    res = run_child([PYTHON, str(benchlib.BENCH / "io_floor.py"), meta["bag"], str(out),
                     str(ZSTD_LEVEL)], log=log)
    if res["rc"] != 0:
        raise SystemExit(f"io_floor failed (exit {res['rc']}):\n{tail(log)}")
    res["size_mib"] = output_size_mib(out)
    remove(out)
    return res


def floor_comparison(specs: list[MissionSpec], repeats: int) -> list[dict[str, Any]]:
    """``lidarcal correct`` and the I/O floor, alternately, per mission and output format."""
    rows = []
    for spec in specs:
        meta = benchlib.prepare_mission(spec)
        for suffix in (".mcap", ".laz"):
            floor, lidarcal = [], []
            for r in range(repeats):
                floor.append(run_floor(meta, WORK / f"floor{suffix}"))
                lidarcal.append(run_correct(meta, WORK / f"corrected{suffix}"))
                print(f"  {spec.key} {suffix} run {r + 1}/{repeats}: floor "
                      f"{floor[-1]['wall_s']:.2f} s, lidarcal correct "
                      f"{lidarcal[-1]['wall_s']:.2f} s ({lidarcal[-1]['cpu_s']:.2f} s CPU, "
                      f"peak {lidarcal[-1]['peak_mib']:.0f} MiB)", flush=True)
            rows.append({"mission": spec.key, "points": meta["n_points"],
                         "clouds": meta.get("approx_clouds"), "format": suffix,
                         "floor": floor, "lidarcal": lidarcal})
    return rows


def print_floor_table(rows: list[dict[str, Any]]) -> list[str]:
    """The table of record; returns the goals not met."""
    def walls(runs: list[dict[str, Any]]) -> list[float]:
        return [r["wall_s"] for r in runs]

    print(f"\n{'mission':>24} {'points':>11} {'out':>5} {'floor s':>13} {'correct s':>13} "
          f"{'ratio':>12} {'correct M pts/s':>15} {'CPU s':>6} {'peak':>8} {'MiB out':>15}")
    print(f"{'':>24} {'':>11} {'':>5} {'min / med':>13} {'min / med':>13} "
          f"{'min / med':>12} {'(min wall)':>15} {'':>6} {'':>8} {'floor / ours':>15}")
    failed = []
    for row in rows:
        f, c = walls(row["floor"]), walls(row["lidarcal"])
        ratio_min = min(c) / min(f)
        ratio_med = statistics.median(c) / statistics.median(f)
        rate = row["points"] / min(c)
        cpu = statistics.median(r["cpu_s"] for r in row["lidarcal"])
        peak = max(r["peak_mib"] for r in row["lidarcal"])
        sizes = (f"{row['floor'][0]['size_mib']:.0f} / "
                 f"{row['lidarcal'][0]['size_mib']:.0f}")
        print(f"{row['mission']:>24} {row['points']:>11,} {row['format']:>5} "
              f"{benchlib.median_min(f):>13} {benchlib.median_min(c):>13} "
              f"{ratio_min:>5.2f} / {ratio_med:<4.2f} {rate / 1e6:>15.2f} {cpu:>6.2f} "
              f"{peak:>4.0f} MiB {sizes:>15}")
        if ratio_min > GOAL_RATIO_TO_FLOOR:
            failed.append(f"{row['mission']} {row['format']}: {ratio_min:.2f}x the I/O floor "
                          f"(goal <= {GOAL_RATIO_TO_FLOOR:g}x)")
        if row["format"] == ".mcap" and row["points"] >= 9e6 and \
                rate < GOAL_POINTS_PER_S_10M_MCAP:
            failed.append(f"{row['mission']} .mcap: {rate / 1e6:.2f}M points/s (goal >= "
                          f"{GOAL_POINTS_PER_S_10M_MCAP / 1e6:g}M)")
    print("ratio: lidarcal correct's wall time over the floor's (min over min, median over "
          "median); both include the process start")
    return failed


# ---------------------------------------------------------------------------- throughput
def throughput_worker(spec: MissionSpec, repeats: int, baseline_points: int) -> None:
    """In a child: lidarcal's correction (1 and 2 threads, node mode) and the baseline, in
    memory. Prints one JSON line."""
    import numpy as np

    from lidarcal_ros.core.allocator import tune_allocator
    from lidarcal_ros.core.config import FlightConfig
    from lidarcal_ros.core.params import as_vector
    from lidarcal_ros.io.bag.mission_bag import strip_point_array, time_chunk_bounds
    from lidarcal_ros.pipeline.correction.apply import CorrectionSettings
    from lidarcal_ros.pipeline.correction.stream import DEFAULT_BATCH_POINTS, StreamCorrector

    tune_allocator()  # as `lidarcal correct` does
    sim = benchlib.simulate(spec)
    mission = sim.mission
    settings = CorrectionSettings.from_config(FlightConfig(), as_vector(sim.biases))
    clouds: list[tuple[int, int, np.ndarray]] = []
    for k, strip in enumerate(mission.strips):
        pts = strip_point_array(strip, {}, "bench")
        b = time_chunk_bounds(pts["t"], 0.1)
        clouds.extend((k, lo, pts[lo:hi]) for lo, hi in itertools.pairwise(b))
    n = mission.n_points

    def run_lidarcal(workers: int, batch_points: int = DEFAULT_BATCH_POINTS,
                     lookahead: bool = True) -> tuple[float, dict[int, np.ndarray]]:
        corr = StreamCorrector(mission.trajectory, settings, workers=workers,
                               batch_points=batch_points, lookahead=lookahead)
        corr.start()
        started = time.perf_counter()
        out = []
        for k, lo, c in clouds:
            out.extend(corr.push(c, (k, lo)))
        out.extend(corr.flush())
        wall = time.perf_counter() - started
        per: dict[int, list[np.ndarray]] = {}
        for (k, _lo), arr in out:
            per.setdefault(k, []).append(arr["reflectance"])
        return wall, {k: np.concatenate(v) for k, v in per.items()}

    result: dict[str, Any] = {"n_points": n, "n_clouds": len(clouds)}
    run_lidarcal(1)  # warm-up
    for name, workers, batch, lookahead in (
            ("lidarcal_1", 1, DEFAULT_BATCH_POINTS, True),
            ("lidarcal_2", 2, DEFAULT_BATCH_POINTS, True),
            ("node_mode", 1, 0, True),
            ("node_mode_no_lookahead", 1, 0, False)):
        walls = []
        refl: dict[int, np.ndarray] = {}
        for _ in range(repeats):
            wall, refl = run_lidarcal(workers, batch, lookahead)
            walls.append(wall)
        result[name] = {"wall_s": statistics.median(walls), "walls": walls,
                        "points_per_s": n / statistics.median(walls)}
        result[name]["error"] = reflectance_error(sim, refl, range(len(mission.strips)))

    strips = []
    total = 0
    for k, strip in enumerate(mission.strips):
        if total and total + len(strip) > baseline_points:
            break
        strips.append(k)
        total += len(strip)
    started = time.perf_counter()
    refl_b = {k: baseline_strip(mission, k, settings) for k in strips}
    wall_b = time.perf_counter() - started
    result["baseline"] = {"wall_s": wall_b, "points": total, "points_per_s": total / wall_b,
                          "strips": [mission.strips[k].strip_id for k in strips]}
    result["baseline_error"] = reflectance_error(sim, refl_b, strips)
    print(json.dumps(result))


def baseline_strip(mission: Any, k: int, settings: Any) -> Any:
    """The obvious implementation for one strip: k-NN (cKDTree) + PCA normals."""
    import numpy as np
    from scipy.spatial import cKDTree

    from lidarcal_ros.core.georeferencing.bias_model import correct_points
    from lidarcal_ros.core.georeferencing.local_trajectory import laser_geometry

    strip = mission.strips[k]
    xyz, t = strip.xyz, strip.t
    geo = laser_geometry(t, xyz, mission.trajectory, window=settings.window)
    xc = correct_points(xyz, settings.delta, geo.x, geo.z, geo.kappa, geo.beta)
    rel = xc - geo.origin
    r = np.linalg.norm(rel, axis=1)
    direction = rel / r[:, None]
    tree = cKDTree(xyz)
    _, nn = tree.query(xyz, k=10, workers=-1)
    nb = xyz[nn]  # (n, 10, 3)
    nb = nb - nb.mean(axis=1, keepdims=True)
    cov = np.einsum("nki,nkj->nij", nb, nb) / 10.0
    _, vec = np.linalg.eigh(cov)
    normal = vec[:, :, 0]
    cos_t = np.abs(np.einsum("ij,ij->i", normal, direction))
    rho, _ = settings.radiometry.reflectance(strip.intensity, r, cos_t)
    return rho


def reflectance_error(sim: Any, refl: dict[int, Any], strips: Any) -> float:
    """Median |g rho / rho_true - 1| over points with true incidence < 60 deg."""
    import numpy as np

    est = np.concatenate([np.asarray(refl[k], dtype=np.float64) for k in strips])
    truth = np.concatenate([sim.reflectance_true[k] for k in strips]).astype(np.float64)
    inc = np.concatenate([sim.incidence_true[k] for k in strips])
    sel = (inc < math.radians(60)) & np.isfinite(est)
    g = np.median(truth[sel] / est[sel])
    return float(np.median(np.abs(g * est[sel] / truth[sel] - 1.0)))


def throughput(spec: MissionSpec, repeats: int, baseline_points: int) -> None:
    """Measure and print the numerics in memory (points a second and reflectance error of
    lidarcal's corrector and of the baseline) on the mission ``spec``, in a child process."""
    print(f"\nthe numerics in memory (stage figures): {spec.describe()} "
          f"(~{spec.approx_points / 1e6:.1f}M points)", flush=True)
    log = WORK / "throughput.log"
    res = run_child([PYTHON, __file__, "_throughput", json.dumps(spec.__dict__),
                     str(repeats), str(baseline_points)], log=log)
    if res["rc"] != 0:
        raise SystemExit(f"throughput worker failed:\n{tail(log)}")
    tp = json.loads(log.read_text().strip().splitlines()[-1])
    rows = [
        (label, tp[key]["points_per_s"], tp[key]["error"]) for label, key in (
            ("StreamCorrector, 1 thread", "lidarcal_1"),
            ("StreamCorrector, 2 worker threads", "lidarcal_2"),
            ("one cloud at a time (node), 1 thread", "node_mode"),
            ("one cloud at a time, no look-ahead", "node_mode_no_lookahead"))] + [
        (f"baseline (cKDTree k=10 + PCA), {tp['baseline']['points'] / 1e6:.2f}M points",
         tp["baseline"]["points_per_s"], tp["baseline_error"]),
    ]
    print(f"{'':48s} {'M points/s':>10s} {'refl. error':>11s}")
    for name, rate, err in rows:
        print(f"{name:48s} {rate / 1e6:10.2f} {100 * err:10.2f}%")
    best = max(tp[k]["points_per_s"] for k in ("lidarcal_1", "lidarcal_2"))
    print(f"ratio lidarcal / baseline: {best / tp['baseline']['points_per_s']:.1f}x "
          f"({tp['n_points'] / 1e6:.2f}M points in {tp['n_clouds']} clouds)", flush=True)


# ---------------------------------------------------------------------------- memory
def memory(specs: tuple[MissionSpec, MissionSpec]) -> list[str]:
    """Measure and print the peak memory of ``lidarcal correct`` on the two missions (MCAP and
    LAZ outputs, one and two workers); the goals not met, in words."""
    print("\npeak memory of lidarcal correct, same density, two mission lengths:", flush=True)
    peaks = []
    for spec in specs:
        meta = benchlib.prepare_mission(spec)
        for suffix in (".mcap", ".laz"):
            for workers in (1, 2):
                r = run_correct(meta, WORK / f"corrected{suffix}", workers)
                peaks.append((meta["n_points"], f"{suffix} -w{workers}", r["peak_mib"]))
                print(f"  {meta['n_points'] / 1e6:.2f}M points -> {suffix}, --workers "
                      f"{workers}: {r['wall_s']:.1f} s, peak {r['peak_mib']:.0f} MiB",
                      flush=True)
    print(f"\n{'mission':>14s} {'output':>11s} {'peak RSS':>10s}")
    for n, label, peak in peaks:
        print(f"{n / 1e6:11.2f}M pt {label:>11s} {peak:8.0f} MiB")
    big = max(p for _, _, p in peaks)
    small_n, big_n = min(q[0] for q in peaks), max(q[0] for q in peaks)
    growth = max(
        next(p for n, lb, p in peaks if n == big_n and lb == label)
        - next(p for n, lb, p in peaks if n == small_n and lb == label)
        for label in {lb for _, lb, _ in peaks})
    print(f"largest peak {big:.0f} MiB (goal < {GOAL_PEAK_MIB:.0f} MiB: "
          f"{'met' if big < GOAL_PEAK_MIB else 'NOT met'}); largest growth from the short "
          f"to the long mission {growth:+.0f} MiB")
    return [] if big < GOAL_PEAK_MIB else [f"peak memory {big:.0f} MiB"]


# ---------------------------------------------------------------------------- driver
def main() -> int:
    """Run the sections of the command line (or, with ``_throughput`` first, the child worker)
    and print their figures and goals; exit status 0."""
    if len(sys.argv) > 1 and sys.argv[1] == "_throughput":
        throughput_worker(MissionSpec(**json.loads(sys.argv[2])), int(sys.argv[3]),
                          int(sys.argv[4]))
        return 0
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    ap.add_argument("--quick", action="store_true",
                    help="the 1M-point mission only; smaller memory missions")
    ap.add_argument("--only", nargs="+", choices=("floor", "throughput", "memory"),
                    default=["floor", "throughput", "memory"])
    ap.add_argument("--repeats", type=int, default=3,
                    help="runs of each measured program (min and median reported)")
    ap.add_argument("--baseline-points", type=int, default=1_000_000,
                    help="points the in-memory baseline corrects (whole strips; default 1M)")
    args = ap.parse_args()
    WORK.mkdir(parents=True, exist_ok=True)
    load_start = benchlib.load_average()
    print(f"machine: {machine.describe()}", flush=True)
    failed: list[str] = []
    if "floor" in args.only:
        specs = [benchlib.MISSION_1M] + ([] if args.quick else [benchlib.MISSION_10M_DENSE])
        for spec in specs:
            print(f"mission {spec.key}: {spec.describe()}", flush=True)
        print("end to end, lidarcal correct against the I/O floor (bench/io_floor.py):",
              flush=True)
        failed += print_floor_table(floor_comparison(specs, args.repeats))
    if "throughput" in args.only:
        throughput(MissionSpec(0.5, 250.0) if args.quick else MissionSpec(1.0, 500.0),
                   args.repeats, args.baseline_points)
    if "memory" in args.only:
        density = 0.8 if args.quick else 1.6
        failed += memory((MissionSpec(density, 250.0), MissionSpec(density, 1000.0)))
    load_end = benchlib.load_average()
    print(f"\nload average (1 min) before / after: {load_start:.2f} / {load_end:.2f}")
    print("goals: " + ("all met" if not failed else "NOT met: " + "; ".join(failed)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
