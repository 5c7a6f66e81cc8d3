"""How `lidarcal simulate` and `lidarcal calibrate` grow with the mission (bench/README.md,
"Scaling to large missions"; issue 31).

    .venv/bin/python bench/bench_scale.py                     # 1M and 4M points
    .venv/bin/python bench/bench_scale.py --max-points 100e6  # 1M, 4M, 16M, 64M, 100M
    .venv/bin/python bench/bench_scale.py --stages BAG        # calibrate's memory per stage
    .venv/bin/python bench/bench_scale.py --stages BAG --memory bounded  # the same, bounded
    .venv/bin/python bench/bench_scale.py --memory whole,bounded  # both calibration.memory
    .venv/bin/python bench/bench_scale.py --correct           # lidarcal correct of each too
    .venv/bin/python bench/bench_scale.py --points 1e6,100e6 --memory bounded --dask local:2

``--memory`` runs each size with each ``calibration.memory`` mode named and, with both,
prints the bounded estimate's difference from the whole one in the whole one's sigmas.

Each size is the paper's six strips at 0.5 points/m^2 (the 1150 m lines), lines as long as
the size needs, written by ``lidarcal simulate`` (cached under bench/.cache/scale/). Each
``lidarcal calibrate`` runs in a fresh process, as a user runs it (after one unmeasured run
that compiles the per-point loops); time per point and peak resident memory are printed
with their ratios to the 1M-point run of the same invocation. ``--correct`` also runs
``lidarcal correct`` of each size with its calibration (to an MCAP bag, removed after: the
output is as large as the input). ``--stages`` runs the calibration in this process and
samples its resident memory every 20 ms, per stage of its progress (what grows with the
points). ``--dask SPEC`` also runs each calibration with ``--dask SPEC`` and prints its
speed-up, the peak of its process tree and of its largest process, and its estimate against
the serial one's (byte-identical files, or the largest difference in sigmas); ``--points``
names the sizes instead of 1M, x4, ... ``--max-points``.
"""

from __future__ import annotations

import argparse
import os
import threading
import time
from pathlib import Path
from typing import Any

import machine
from benchlib import BENCH, PYTHON, ROOT, read_estimate, run_child, tail

DENSITY = 0.5
#: Points of the six strips per metre of line at DENSITY (measured: 6.435M points a km of
#: line at 1 point/m^2).
POINTS_PER_M = 6435.0 * DENSITY
CACHE = BENCH / ".cache" / "scale"


def mission(points: float) -> Path:
    """The bag of about ``points`` points (simulated once, streaming, then cached)."""
    length = round(points / POINTS_PER_M)
    bag = CACHE / f"paper_d{DENSITY:g}_L{length}"
    if not (bag / "metadata.yaml").is_file():
        CACHE.mkdir(parents=True, exist_ok=True)
        run = run_child([PYTHON, "-m", "lidarcal_ros", "simulate", "-o", str(bag),
                         "--density", str(DENSITY), "--line-length", str(length),
                         "--overwrite"], log=CACHE / f"{bag.name}.simulate.log")
        if run["rc"]:
            raise SystemExit(f"simulate failed:\n{tail(CACHE / f'{bag.name}.simulate.log')}")
        print(f"  simulated {bag.name}: {run['wall_s']:.0f} s, peak {run['peak_mib']:.0f} MiB")
    return bag


def n_points(bag: Path) -> int:
    """The points of a simulated bag, from its truth file."""
    import yaml

    truth = yaml.safe_load(Path(f"{bag}_truth.yaml").read_text())
    return int(truth["simulation"]["n_points"])


def output(bag: Path, memory: str, dask: str | None = None) -> Path:
    """The calibration file of ``bag`` calibrated with ``calibration.memory`` ``memory``
    (on ``--dask dask``: another file)."""
    return CACHE / f"{bag.name}.{memory}{_on(dask)}.calibration.yaml"


def _on(dask: str | None) -> str:
    """What the names of a run's files add with ``--dask``."""
    return "" if dask is None else ".dask"


def calibrate(bag: Path, memory: str = "whole", dask: str | None = None) -> dict[str, Any]:
    """``lidarcal calibrate`` of ``bag`` in a fresh process, ``calibration.memory``
    ``memory`` (with ``--dask dask``: the memory of its process tree too)."""
    log = CACHE / f"{bag.name}.{memory}{_on(dask)}.calibrate.log"
    config = CACHE / f"memory_{memory}.yaml"
    config.write_text(f"/**:\n  ros__parameters:\n    calibration:\n      memory: {memory}\n")
    cmd = [PYTHON, "-m", "lidarcal_ros", "calibrate", str(bag), "-o",
           str(output(bag, memory, dask)), "--overwrite", "--config", str(config),
           "--control", f"{bag}_control.csv"]
    run = run_child(cmd + ([] if dask is None else ["--dask", dask]), log=log,
                    tree_memory=dask is not None)
    if run["rc"]:
        raise SystemExit(f"calibrate failed:\n{tail(log)}")
    return run


def correct(bag: Path, memory: str) -> dict[str, Any]:
    """``lidarcal correct`` of ``bag`` with its ``memory`` calibration, in a fresh process
    (the corrected bag removed after)."""
    log = CACHE / f"{bag.name}.correct.log"
    out = CACHE / f"{bag.name}.corrected.mcap"
    try:
        run = run_child([PYTHON, "-m", "lidarcal_ros", "correct", str(bag), "--calibration",
                         str(output(bag, memory)), "-o", str(out), "--overwrite"], log=log)
    finally:
        out.unlink(missing_ok=True)
    if run["rc"]:
        raise SystemExit(f"correct failed:\n{tail(log)}")
    return run


def table(rows: dict[str, list[tuple[int, dict[str, Any]]]], first: str) -> None:
    """Time per point and peak memory of each run against the first (1M-point) run of
    its row group."""
    print(f"\n| {first} | points | wall | ns/point | x 1M | CPU | peak RSS | x 1M | bytes/point |")
    print("|---|---|---|---|---|---|---|---|---|")
    for name, runs in rows.items():
        n0, r0 = runs[0]
        for n, r in runs:
            per = r["wall_s"] / n * 1e9
            per0 = r0["wall_s"] / n0 * 1e9
            print(f"| {name} | {n:,} | {r['wall_s']:.1f} s | {per:.0f} | {per / per0:.2f} | "
                  f"{r['cpu_s']:.1f} s | {r['peak_mib']:.0f} MiB | "
                  f"{r['peak_mib'] / r0['peak_mib']:.2f} | {r['peak_mib'] * 2**20 / n:.0f} |")


def on_dask(bag: Path, memory: str, serial: dict[str, Any], dask: str) -> str:
    """``memory``'s calibration of ``bag`` on ``--dask dask`` against ``serial``'s run: one
    line of figures."""
    run = calibrate(bag, memory, dask)
    a, b = output(bag, memory), output(bag, memory, dask)
    same = a.read_bytes() == b.read_bytes()
    return (f"--dask {dask} ({memory}): {run['wall_s']:.1f} s wall against {serial['wall_s']:.1f}"
            f" s serial ({serial['wall_s'] / run['wall_s']:.2f}x), peak {run['peak_mib']:.0f} "
            f"MiB the process tree, {run['largest_mib']:.0f} MiB its largest process (serial "
            f"{serial['peak_mib']:.0f} MiB); the calibration file "
            + ("byte-identical" if same else "differs: " + differences(a, b, "serial", "dask")))


def differences(first: Path, second: Path, first_name: str, second_name: str) -> str:
    """The estimate of file ``second`` minus that of ``first``, in ``first``'s sigmas."""
    reference, other = read_estimate(first), read_estimate(second)
    worst = 0.0
    parts = []
    for name, w in reference.items():
        b = other.get(name)
        if b is None or not w["sigma"]:
            parts.append(f"{name} -")
            continue
        d = (b["value"] - w["value"]) / w["sigma"]
        worst = max(worst, abs(d))
        parts.append(f"{name} {d:+.4f}")
    return (f"{second_name} - {first_name}, sigmas: {' '.join(parts)} "
            f"(largest {worst:.4f})")


def sizes(max_points: float) -> list[float]:
    """1M, then x4 up to ``max_points`` (which is included)."""
    out = [1e6]
    while out[-1] * 4 < max_points:
        out.append(out[-1] * 4)
    if max_points > out[-1]:
        out.append(max_points)
    return out


def scaling(points: list[float], modes: list[str], *, with_correct: bool = False,
            dask: str | None = None) -> None:
    """The table of time per point and peak memory against the first size's run of the
    same ``calibration.memory`` mode, for each of ``modes`` (and, ``with_correct``, of
    ``lidarcal correct`` with the first mode's calibration; with ``dask``, each
    calibration on ``--dask dask`` too)."""
    rows: dict[str, list[tuple[int, dict[str, Any]]]] = {m: [] for m in modes}
    corrections: dict[str, list[tuple[int, dict[str, Any]]]] = {"correct": []}
    notes = []
    # a first run unmeasured: it compiles the per-point loops (numba's cache), some 10 s
    calibrate(mission(1e6), modes[0])
    for size in points:
        bag = mission(size)
        n = n_points(bag)
        for memory in modes:
            run = calibrate(bag, memory)
            rows[memory].append((n, run))
            print(f"  {n / 1e6:7.2f}M points, {memory}: {run['wall_s']:7.1f} s wall, "
                  f"{run['cpu_s']:7.1f} s CPU, peak {run['peak_mib']:7.0f} MiB", flush=True)
            if dask is not None:
                notes.append(f"{n:,} points: {on_dask(bag, memory, run, dask)}")
                print(f"  {notes[-1]}", flush=True)
        if with_correct:
            run = correct(bag, modes[0])
            corrections["correct"].append((n, run))
            print(f"  {n / 1e6:7.2f}M points, correct: {run['wall_s']:7.1f} s wall, "
                  f"{run['cpu_s']:7.1f} s CPU, peak {run['peak_mib']:7.0f} MiB", flush=True)
        if {"whole", "bounded"} <= set(modes):
            notes.append(f"{n:,} points: "
                         + differences(output(bag, "whole"), output(bag, "bounded"), "whole",
                                       "bounded"))
            print(f"  {notes[-1]}", flush=True)
    table(rows, "memory")
    if with_correct:
        table(corrections, "command")
    for note in notes:
        print(note)


def stages(bag: Path, memory: str = "whole") -> None:
    """Resident memory per stage of one calibration of ``bag`` (in this process), the
    mission held as ``calibration.memory`` ``memory`` says."""
    from lidarcal_ros.core.config import FlightConfig
    from lidarcal_ros.pipeline.calibration.procedure import (
        calibrate_mission,
        load_for_calibration,
    )

    def rss_mib() -> float:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20

    stage = ["start"]
    peaks: dict[str, list[float]] = {}
    done = threading.Event()

    def sample() -> None:
        while not done.wait(0.02):
            entry = peaks.setdefault(stage[0], [time.perf_counter(), 0.0, 0.0])
            entry[1] = max(entry[1], rss_mib())
            entry[2] = time.perf_counter()

    def progress(name: str, _fraction: float) -> None:
        stage[0] = name.split(": ")[-1] if name.startswith("iteration") else name

    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    started = time.perf_counter()
    config = FlightConfig().with_values(calibration__memory=memory)
    stage[0] = "reading the bag"
    mission_ = load_for_calibration(bag, config, control_csv=f"{bag}_control.csv",
                                    progress=progress)
    n = mission_.n_points
    held = getattr(mission_, "n_held", n)
    calibrate_mission(mission_, config, progress=progress)
    done.set()
    sampler.join()
    print(f"{bag.name} ({memory}): {n:,} points, {held:,} held, "
          f"{time.perf_counter() - started:.1f} s")
    print("| stage (first seen in order) | seconds | peak RSS | added | added per held point |")
    print("|---|---|---|---|---|")
    before = 0.0
    for name, (t0, peak, t1) in peaks.items():
        added = max(peak - before, 0.0)
        print(f"| {name} | {t1 - t0:.1f} | {peak:.0f} MiB | {added:.0f} MiB | "
              f"{added * 2**20 / held:.0f} B |")
        before = max(before, peak)


def main() -> None:
    """Parse the options and run."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--max-points", type=float, default=4e6,
                        help="the largest mission (default 4e6)")
    parser.add_argument("--stages", type=Path, default=None, metavar="BAG",
                        help="calibrate's memory per stage of BAG, in this process")
    parser.add_argument("--memory", default="whole",
                        help="calibration.memory modes, comma-separated (default whole)")
    parser.add_argument("--correct", action="store_true",
                        help="also lidarcal correct of each size (the first mode's calibration)")
    parser.add_argument("--points", default=None,
                        help="the sizes, comma-separated, e.g. 1e6,100e6 (default: 1M, x4, "
                        "... --max-points)")
    parser.add_argument("--dask", default=None, metavar="SPEC",
                        help="also calibrate each size with --dask SPEC, e.g. local:2")
    args = parser.parse_args()
    modes = [m for m in args.memory.split(",") if m]
    if not modes or set(modes) - {"whole", "bounded"}:
        parser.error(f"--memory: whole and/or bounded, got {args.memory!r}")
    os.chdir(ROOT)
    print(machine.describe())
    print(f"load average (1 min): {os.getloadavg()[0]:.1f}")
    if args.stages is not None:
        stages(args.stages, modes[0])
    else:
        try:
            points = sizes(args.max_points) if args.points is None else \
                [float(p) for p in args.points.split(",") if p]
        except ValueError:
            parser.error(f"--points: numbers separated by commas, got {args.points!r}")
        scaling(points, modes, with_correct=args.correct, dask=args.dask)
    print(f"load average (1 min): {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
