"""Benchmark of the correction (``lidarcal correct``) against a straightforward baseline.

    .venv/bin/python bench/bench_correct.py                # throughput (~3M points) + memory
    .venv/bin/python bench/bench_correct.py --quick        # ~0.8M points, 2.6M for memory
    .venv/bin/python bench/bench_correct.py --no-memory    # throughput only

Every figure is measured in this run, the baseline too. Each measured program runs in a fresh
subprocess, so its peak memory is its own (``os.wait4`` gives the child's own ``ru_maxrss``).

Figures
-------
- **correction throughput** (the goal: 5M points/s or more on the 2-core machine): points per
  second of the whole per-point correction, in memory, on a simulated mission cut into 0.1 s
  clouds: column extraction, local trajectory (``laser_geometry``), eq. [13]
  (``correct_points``), range and scan angle, grid normals with the look-ahead context,
  incidence, atmosphere and radar equation, and the corrected structured arrays -- i.e.
  :class:`lidarcal_ros.pipeline.correction.StreamCorrector` in one thread, with 2 worker
  threads (what ``lidarcal correct`` uses by default, ``--workers 2``), and as the corrector
  node runs it: one cloud at a time (``batch_points=0``), with and without look-ahead, one
  thread. Median of ``--repeats`` runs after a warm-up, with the allocator tuning of
  ``lidarcal correct`` (``tune_allocator``).
- **baseline**: the same steps done the obvious way: per strip, ``laser_geometry`` +
  ``correct_points`` (the same), normals by ``scipy.spatial.cKDTree`` k-nearest neighbours
  (k = 10, ``workers=-1``: both cores) and PCA (``numpy.linalg.eigh`` on the 3x3
  covariances), the same radar equation. Its accuracy is printed beside lidarcal's (median
  relative reflectance error against the simulated truth, incidence < 60 deg, one global
  scale), so that a speed-up that loses accuracy shows.
- **end to end**: ``lidarcal correct BAG --calibration CAL -o OUT`` for ``.mcap`` and ``.laz``
  outputs, ``--workers 1`` and ``2``, wall time of the process (start, imports, both passes
  over the bag, CDR decoding, zstd / LAZ compression and writing included).
- **peak memory** (the goal: flat with mission length, under 1 GB): peak RSS of ``lidarcal
  correct`` on two missions of the same density, about 2.6M and 10.3M points (``--quick``:
  1.3M and 5.1M), to ``.mcap`` and ``.laz``, ``--workers 1`` and ``2``. Every strip of both
  holds more points than a correction batch (200k), so a flat peak shows that memory is
  bounded by the batch, not by the strip or the mission. The peak is that of the whole
  process tree (the worker processes and their forkserver included), sampled every 50 ms
  from /proc, or the process's own ``ru_maxrss`` if larger.

The machine should be otherwise idle: on a 2-core machine any other process shows directly
in the figures (the load average is printed first).

Missions are ``simulate_mission(scenario="paper", density=D, line_length_m=L, seed=7)``: six
strips at 1150 m and 540 m, built-up terrain; a strip holds about ``D * 1072.5 * L`` points.
They are written once as bags under ``bench/.cache/`` (git-ignored) with a calibration file of
the true biases; delete the directory to simulate again.
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
import os
import shutil
import signal
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import machine  # bench/machine.py: this script's folder is on sys.path

BENCH = Path(__file__).resolve().parent
ROOT = BENCH.parent
CACHE = BENCH / ".cache"
PYTHON = sys.executable
SEED = 7
SWATH_HIGH_M = 2.0 * 1150.0 * math.tan(math.radians(25.0))
N_STRIPS = 6

GOAL_POINTS_PER_S = 5.0e6
GOAL_PEAK_MIB = 1024.0


# ---------------------------------------------------------------------------- missions
def mission_points(density: float, line_length: float) -> int:
    return int(N_STRIPS * density * SWATH_HIGH_M * line_length)


def prepare_mission(density: float, line_length: float) -> dict[str, Any]:
    """A cached mission bag and calibration file (simulated in a child process)."""
    key = f"correct_paper_d{density:g}_L{line_length:g}_s{SEED}"
    where = CACHE / key
    meta_path = where / "meta.json"
    if meta_path.exists():
        return json.loads(meta_path.read_text())
    if where.exists():
        shutil.rmtree(where)
    where.mkdir(parents=True)
    print(f"  simulating {key} (~{mission_points(density, line_length) / 1e6:.1f}M points)...",
          flush=True)
    res = run_child([PYTHON, __file__, "_prepare", str(density), str(line_length), str(where)],
                    log=where / "prepare.log")
    if res["rc"] != 0 or not meta_path.exists():
        raise SystemExit(f"simulation failed:\n{tail(where / 'prepare.log')}")
    return json.loads(meta_path.read_text())


def prepare_worker(density: float, line_length: float, where: Path) -> None:
    import yaml

    from lidarcal_ros.core.simulate import simulate_mission
    from lidarcal_ros.core.simulation_spec import SimulationSpec
    from lidarcal_ros.io.bag import write_mission_bag

    started = time.perf_counter()
    sim = simulate_mission(SimulationSpec.from_options(
        scenario="paper", density=density, line_length_m=line_length, seed=SEED))
    bag = where / "mission"
    write_mission_bag(bag, sim.mission)
    cal = where / "calibration.yaml"
    cal.write_text(yaml.safe_dump({"lidarcal_calibration": {"biases": {
        k: {"value": float(v), "sigma": None, "estimated": True}
        for k, v in sim.biases.items()}}}))
    meta = {"bag": str(bag), "calibration": str(cal), "n_points": int(sim.mission.n_points),
            "density": density, "line_length_m": line_length,
            "prepare_s": time.perf_counter() - started}
    (where / "meta.json").write_text(json.dumps(meta, indent=1))


# ---------------------------------------------------------------------------- children
def _tree_rss_mib(root: int) -> float:
    """Resident memory of a process and all its descendants (worker processes, the
    forkserver), MiB, from /proc."""
    parent: dict[int, int] = {}
    rss: dict[int, int] = {}
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/stat", "rb") as f:
                fields = f.read().rsplit(b")", 1)[1].split()
            parent[int(entry)] = int(fields[1])
            rss[int(entry)] = int(fields[21])  # pages
        except (OSError, IndexError, ValueError):
            continue
    tree = {root}
    grew = True
    while grew:
        grew = False
        for pid, ppid in parent.items():
            if ppid in tree and pid not in tree:
                tree.add(pid)
                grew = True
    return sum(rss.get(pid, 0) for pid in tree) * os.sysconf("SC_PAGE_SIZE") / 2**20


def run_child(cmd: list[str], *, log: Path | None = None, limit_s: float | None = None,
              env: dict[str, str] | None = None) -> dict[str, Any]:
    """Run ``cmd``; its wall time, peak RSS (MiB) of the process itself (``wait4``) and of its
    whole process tree (sampled every 50 ms), and exit status."""
    out = open(log, "wb") if log else subprocess.DEVNULL
    tree_peak = 0.0
    try:
        started = time.perf_counter()
        proc = subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT, cwd=ROOT,
                                env={**os.environ, **(env or {})}, start_new_session=True)
        last_sample = 0.0
        while True:
            pid, status, usage = os.wait4(proc.pid, os.WNOHANG)
            if pid:
                break
            if limit_s is not None and time.perf_counter() - started > limit_s:
                os.killpg(proc.pid, signal.SIGKILL)
                pid, status, usage = os.wait4(proc.pid, 0)
                break
            now = time.perf_counter()
            if now - last_sample >= 0.05:
                tree_peak = max(tree_peak, _tree_rss_mib(proc.pid))
                last_sample = now
            time.sleep(0.01)
        wall = time.perf_counter() - started
    finally:
        if log:
            out.close()
    return {"wall_s": wall, "peak_mib": max(usage.ru_maxrss / 1024.0, tree_peak),
            "self_peak_mib": usage.ru_maxrss / 1024.0, "tree_peak_mib": tree_peak,
            "rc": os.waitstatus_to_exitcode(status)}


def tail(path: Path, n: int = 15) -> str:
    try:
        return "\n".join(path.read_text(errors="replace").splitlines()[-n:])
    except OSError:
        return ""


# ---------------------------------------------------------------------------- throughput
def throughput_worker(density: float, line_length: float, repeats: int,
                      baseline_points: int) -> None:
    """In a child: lidarcal's correction (1 and 2 threads) and the baseline, in memory.
    Prints one JSON line."""
    import numpy as np

    from lidarcal_ros.core.allocator import tune_allocator
    from lidarcal_ros.core.config import FlightConfig
    from lidarcal_ros.core.params import as_vector
    from lidarcal_ros.core.simulate import simulate_mission
    from lidarcal_ros.core.simulation_spec import SimulationSpec
    from lidarcal_ros.io.bag import _chunk_bounds, _strip_points
    from lidarcal_ros.pipeline.correction import (
        DEFAULT_BATCH_POINTS,
        CorrectionSettings,
        StreamCorrector,
    )

    tune_allocator()  # as `lidarcal correct` does
    sim = simulate_mission(SimulationSpec.from_options(
        scenario="paper", density=density, line_length_m=line_length, seed=SEED))
    mission = sim.mission
    settings = CorrectionSettings.from_config(FlightConfig(), as_vector(sim.biases))
    clouds: list[tuple[int, int, np.ndarray]] = []
    for k, strip in enumerate(mission.strips):
        pts = _strip_points(strip, {}, "bench")
        b = _chunk_bounds(pts["t"], 0.1)
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

    # Baseline on whole strips up to baseline_points.
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

    from lidarcal_ros.core.local_trajectory import laser_geometry
    from lidarcal_ros.core.model import correct_points

    strip = mission.strips[k]
    xyz, t = strip.xyz, strip.t
    geo = laser_geometry(t, xyz, mission.trajectory, window_s=settings.window_s)
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


# ---------------------------------------------------------------------------- driver
def end_to_end(meta: dict[str, Any], work: Path, suffix: str, workers: int = 2
               ) -> dict[str, Any]:
    out = work / f"corrected_{Path(meta['bag']).parent.name}{suffix}"
    if out.exists():
        shutil.rmtree(out) if out.is_dir() else out.unlink()
    log = work / f"correct_{Path(meta['bag']).parent.name}{suffix}.log"
    res = run_child([PYTHON, "-m", "lidarcal_ros", "correct", meta["bag"], "--calibration",
                     meta["calibration"], "-o", str(out), "--workers", str(workers)], log=log)
    if res["rc"] != 0:
        raise SystemExit(f"lidarcal correct failed (exit {res['rc']}):\n{tail(log)}")
    res["points_per_s"] = meta["n_points"] / res["wall_s"]
    res["size_mib"] = out.stat().st_size / 2**20 if out.is_file() else sum(
        f.stat().st_size for f in out.iterdir()) / 2**20
    print(f"  lidarcal correct -> {suffix} (--workers {workers}): "
          f"{meta['n_points'] / 1e6:.2f}M points, {res['wall_s']:.1f} s "
          f"({res['points_per_s'] / 1e6:.2f}M points/s), peak {res['peak_mib']:.0f} MiB "
          f"(process tree; main process {res['self_peak_mib']:.0f} MiB), output "
          f"{res['size_mib']:.0f} MiB", flush=True)
    out.unlink() if out.is_file() else shutil.rmtree(out)
    return res


def main() -> None:
    if len(sys.argv) > 1 and sys.argv[1] == "_prepare":
        prepare_worker(float(sys.argv[2]), float(sys.argv[3]), Path(sys.argv[4]))
        return
    if len(sys.argv) > 1 and sys.argv[1] == "_throughput":
        throughput_worker(float(sys.argv[2]), float(sys.argv[3]), int(sys.argv[4]),
                          int(sys.argv[5]))
        return
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="smaller missions")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--no-memory", action="store_true", help="skip the memory missions")
    ap.add_argument("--no-throughput", action="store_true",
                    help="skip the in-memory throughput comparison")
    ap.add_argument("--no-end-to-end", action="store_true", help="skip lidarcal correct runs")
    ap.add_argument("--baseline-points", type=int, default=1_000_000,
                    help="points the baseline corrects (whole strips; default 1M)")
    args = ap.parse_args()

    density = 0.5 if args.quick else 1.0
    line = 250.0 if args.quick else 500.0
    # Strips longer than a batch (200k points) in both missions: the peak must not grow.
    mem_density = 0.8 if args.quick else 1.6
    mem_lines = (250.0, 1000.0)
    work = CACHE / "correct_work"
    work.mkdir(parents=True, exist_ok=True)
    print(f"machine: {machine.describe()}", flush=True)

    if not args.no_throughput:
        throughput(args, density, line, work)

    if not args.no_end_to_end:
        meta = prepare_mission(density, line)
        for suffix in (".mcap", ".laz"):
            for workers in (1, 2):
                end_to_end(meta, work, suffix, workers)

    if not args.no_memory:
        memory(mem_density, mem_lines, work)


def throughput(args: argparse.Namespace, density: float, line: float, work: Path) -> None:
    print(f"throughput: mission density {density}, lines {line:g} m "
          f"(~{mission_points(density, line) / 1e6:.1f}M points)", flush=True)
    log = work / "throughput.log"
    res = run_child([PYTHON, __file__, "_throughput", str(density), str(line),
                     str(args.repeats), str(args.baseline_points)], log=log)
    if res["rc"] != 0:
        raise SystemExit(f"throughput worker failed:\n{tail(log)}")
    tp = json.loads(log.read_text().strip().splitlines()[-1])
    rows = [
        (label, tp[key]["points_per_s"], tp[key]["error"]) for label, key in (
            ("correction, 1 thread", "lidarcal_1"),
            ("correction, 2 worker threads", "lidarcal_2"),
            ("one cloud at a time (node), 1 thread", "node_mode"),
            ("one cloud at a time, no look-ahead", "node_mode_no_lookahead"))] + [
        (f"baseline (cKDTree k=10 + PCA), {tp['baseline']['points'] / 1e6:.2f}M points",
         tp["baseline"]["points_per_s"], tp["baseline_error"]),
    ]
    print(f"\n{'':48s} {'M points/s':>10s} {'refl. error':>11s}")
    for name, rate, err in rows:
        print(f"{name:48s} {rate / 1e6:10.2f} {100 * err:10.2f}%")
    best = max(tp[k]["points_per_s"] for k in ("lidarcal_1", "lidarcal_2"))
    met = "met" if best >= GOAL_POINTS_PER_S else "NOT met"
    print(f"ratio lidarcal / baseline: {best / tp['baseline']['points_per_s']:.1f}x; goal "
          f"{GOAL_POINTS_PER_S / 1e6:.0f}M points/s: {met} "
          f"({tp['n_points'] / 1e6:.2f}M points in {tp['n_clouds']} clouds)\n", flush=True)



def memory(mem_density: float, mem_lines: tuple[float, float], work: Path) -> None:
    print("\npeak memory of lidarcal correct, same density, two mission lengths:", flush=True)
    peaks = []
    for length in mem_lines:
        meta = prepare_mission(mem_density, length)
        for suffix in (".mcap", ".laz"):
            for workers in (1, 2):
                r = end_to_end(meta, work, suffix, workers)
                peaks.append((meta["n_points"], f"{suffix} -w{workers}", r["peak_mib"]))
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


if __name__ == "__main__":
    main()
