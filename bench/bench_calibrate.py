"""Benchmark of ``lidarcal calibrate`` (bench/README.md, "Calibration").

    .venv/bin/python bench/bench_calibrate.py            # end to end, scaling to 10M, matching
    .venv/bin/python bench/bench_calibrate.py --quick    # end to end and matching only
    .venv/bin/python bench/bench_calibrate.py --baseline # + the straightforward baseline

Every figure is measured in this run. Each measured program runs in a fresh process, so its
peak memory is its own (``os.wait4`` gives the child's own resource usage). The estimates are
held to the reference of bench/reference_estimates.json (every one within 0.1 of its sigma).
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import benchlib  # bench/benchlib.py: this script's folder is on sys.path
from benchlib import BENCH, LIDARCAL, PYTHON, ROOT, MissionSpec, run_child, tail

#: Goals of the issue for a mission of about 1M points on the 2-core machine.
GOAL_WALL_S = 10.0
GOAL_PEAK_MIB = 1024.0
GOAL_SIGMA = 0.1  # every estimate within this many of its sigmas of the reference
#: The matching's throughput goal of an earlier issue (a stage figure now).
GOAL_POINTS_PER_S_PER_CORE = 1.0e6
ARCSEC = 180.0 / math.pi * 3600.0

SINGLE_THREAD_ENV = {"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1",
                     "MKL_NUM_THREADS": "1", "NUMEXPR_NUM_THREADS": "1"}


def run_lidarcal(meta: dict, repeats: int, work: Path) -> dict[str, Any]:
    """``lidarcal calibrate`` end to end, ``repeats`` times."""
    import yaml

    runs = []
    doc = None
    out = work / "lidarcal.yaml"
    for r in range(repeats):
        log = work / f"lidarcal_{meta['key']}_{r}.log"
        res = run_child([LIDARCAL, "calibrate", meta["bag"], "--control", meta["control"],
                         "-o", str(out), "--overwrite"], log=log)
        if res["rc"] != 0:
            raise SystemExit(f"lidarcal calibrate failed (exit {res['rc']}):\n{tail(log)}")
        runs.append(res)
        print(f"  {meta['key']} run {r + 1}/{repeats}: {res['wall_s']:.2f} s wall, "
              f"{res['cpu_s']:.2f} s CPU, peak {res['peak_mib']:.0f} MiB", flush=True)
        doc = yaml.safe_load(out.read_text())["lidarcal_calibration"]
    assert doc is not None
    return {
        "runs": runs,
        "walls": [r["wall_s"] for r in runs],
        "wall_s": statistics.median(r["wall_s"] for r in runs),
        "cpu_s": statistics.median(r["cpu_s"] for r in runs),
        "peak_mib": max(r["peak_mib"] for r in runs),
        "iterations": int(doc["iterations"]),
        "converged": bool(doc["converged"]),
        "model": str(doc.get("model", "")),
        "estimate": benchlib.read_estimate(out),
        "delta": {k: float(v["value"]) for k, v in doc["biases"].items()},
        "estimated": {k: bool(v["estimated"]) for k, v in doc["biases"].items()},
    }


# ---------------------------------------------------------------------------- scaling
def scaling_worker(spec: MissionSpec) -> None:
    """In a child: bag reading and the calibration of one mission in process, the CPU
    seconds of each stage (:class:`~lidarcal_ros.core.calibration.threads.StageClock`). One
    JSON line."""
    import resource

    from lidarcal_ros.io.config_file import load_flight_config
    from lidarcal_ros.pipeline.calibration.procedure import calibrate_mission, load_mission

    meta = benchlib.prepare_mission(spec, quiet=True)
    config = load_flight_config(None)
    w0, c0 = time.perf_counter(), time.thread_time()
    mission = load_mission(meta["bag"], config, control_csv=meta["control"])
    w1, c1 = time.perf_counter(), time.thread_time()
    result = calibrate_mission(mission, config)
    w2 = time.perf_counter()
    print(json.dumps({
        "points": mission.n_points, "read_wall_s": w1 - w0, "read_cpu_s": c1 - c0,
        "calibrate_wall_s": w2 - w1, "stages": result.stage_seconds,
        "iterations": result.iterations,
        "peak_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0}))


def run_scaling(specs: list[MissionSpec], work: Path) -> list[dict[str, Any]]:
    """The in-process calibration (bag read + calibrate) of each mission, each in a fresh
    process: its figures (points, s, MiB) and the process's wall time."""
    out = []
    for spec in specs:
        benchlib.prepare_mission(spec)
        log = work / f"scaling_{spec.key}.log"
        res = run_child([PYTHON, str(Path(__file__).resolve()), "_scaling",
                         json.dumps(spec.__dict__)], log=log)
        if res["rc"] != 0:
            raise SystemExit(f"scaling worker failed (exit {res['rc']}):\n{tail(log)}")
        line = [ln for ln in log.read_text().splitlines() if ln.startswith("{")][-1]
        out.append({"spec": spec, "wall_s": res["wall_s"], **json.loads(line)})
        print(f"  {spec.key}: {out[-1]['points']:,} points, {res['wall_s']:.1f} s", flush=True)
    return out


def print_scaling(rows: list[dict[str, Any]]) -> None:
    """Per stage: CPU seconds at each size, ns a point, and the growth."""
    order = sorted({k for r in rows for k in r["stages"]},
                   key=lambda k: -rows[0]["stages"].get(k, 0.0))
    stages = ["bag reading", *order]

    def seconds(row: dict[str, Any], stage: str) -> float:
        return row["read_cpu_s"] if stage == "bag reading" else row["stages"].get(stage, 0.0)

    head = f"{'stage (CPU s of its threads)':32s}" + "".join(
        f"{r['points'] / 1e6:>9.2f}M {'ns/pt':>6s}" for r in rows)
    if len(rows) > 1:
        head += f" {'growth':>7s} (points x{rows[-1]['points'] / rows[0]['points']:.1f})"
    print(head)
    for stage in stages:
        line = f"{stage:32s}" + "".join(
            f"{seconds(r, stage):>10.2f} {1e9 * seconds(r, stage) / r['points']:>6.0f}"
            for r in rows)
        if len(rows) > 1 and seconds(rows[0], stage) > 0:
            line += f" {seconds(rows[-1], stage) / seconds(rows[0], stage):>7.1f}x"
        print(line)
    print(f"{'calibration, wall':32s}" + "".join(
        f"{r['calibrate_wall_s']:>10.2f} {1e9 * r['calibrate_wall_s'] / r['points']:>6.0f}"
        for r in rows))
    print(f"{'process, wall / peak RSS':32s}" + "".join(
        f"{r['wall_s']:>8.1f} s {r['peak_mib']:>5.0f} MiB" for r in rows))
    print("stage figures: CPU seconds the calibration's threads spent in each stage (bag "
          "reading: the reading thread); matching: point location and candidate tests; "
          "corrections: the exact correction of every strip at each estimate; design rows: "
          "n^T A of the matches; normal equations: accumulation, solution, robust weights")


def run_baseline(meta: dict, iterations: int, limit_s: float, work: Path,
                 single_thread_blas: bool = True) -> dict[str, Any]:
    """bench/baseline.py in a subprocess with a time limit."""
    tag = "1" if single_thread_blas else "default"
    out = work / f"baseline_{tag}.json"
    log = work / f"baseline_{tag}.log"
    res = run_child([PYTHON, str(BENCH / "baseline.py"), meta["bag"], "--control",
                     meta["control"], "--iterations", str(iterations), "-o", str(out)],
                    limit_s=limit_s, log=log, cwd=ROOT,
                    env=SINGLE_THREAD_ENV if single_thread_blas else None)
    label = "1 BLAS thread" if single_thread_blas else "default BLAS threads"
    if res["timed_out"]:
        print(f"  baseline ({label}): over the {limit_s:.0f} s limit, stopped", flush=True)
        return {**res, "wall_s": limit_s}
    if res["rc"] != 0:
        raise SystemExit(f"baseline failed (exit {res['rc']}):\n{tail(log)}")
    body = json.loads(out.read_text())
    print(f"  baseline ({label}): {res['wall_s']:.1f} s wall, {res['cpu_s']:.1f} s CPU, "
          f"peak {res['peak_mib']:.0f} MiB", flush=True)
    body["inner_wall_s"] = body.pop("wall_s", None)  # measured inside, after imports
    return {**body, **res}  # wall time, CPU and memory as measured from outside


# ---------------------------------------------------------------------------- matching worker
def throughput_worker(args: argparse.Namespace) -> None:
    """In a single-threaded child: TIN build and matching of N queries, lidarcal vs baseline.

    Prints one JSON line. The TIN is strip 1's (1150 m, the widest); the queries are points of
    the other strips inside its footprint, in their acquisition order (as lidarcal matches its
    candidates), drawn to N.
    """
    import numpy as np
    from scipy import ndimage

    sys.path.insert(0, str(BENCH))
    import baseline

    from lidarcal_ros.core.calibration.tin import Tin, TinQuality, match_to_tin
    from lidarcal_ros.core.georeferencing.bias_model import point_offsets
    from lidarcal_ros.core.georeferencing.local_trajectory import laser_geometry
    from lidarcal_ros.core.params import as_vector
    from lidarcal_ros.io.config_file import load_flight_config
    from lidarcal_ros.pipeline.calibration.procedure import load_mission

    meta = json.loads(Path(args.meta).read_text())
    config = load_flight_config(None)
    s = config.calibration_settings()
    mission = load_mission(meta["bag"], config, control_csv=meta["control"])
    # Footprints on a grid of overlap cells, as the calibration finds overlaps.
    cell = s.overlap_cell_m
    allxy = np.concatenate([st.xyz[:, :2] for st in mission.strips])
    lo = allxy.min(axis=0)
    shape = tuple(int(v) + 1 for v in np.ceil((allxy.max(axis=0) - lo) / cell))

    def index(xy):
        ix = np.clip(np.floor((xy[:, 0] - lo[0]) / cell).astype(np.int64), 0, shape[0] - 1)
        iy = np.clip(np.floor((xy[:, 1] - lo[1]) / cell).astype(np.int64), 0, shape[1] - 1)
        return ix, iy

    b = 0  # strip 1: 1150 m, the widest footprint
    strip = mission.strips[b]
    xyz = strip.xyz
    raster = np.zeros(shape, dtype=bool)
    raster[index(xyz[:, :2])] = True
    density = len(strip) / max(float(raster.sum()) * cell**2, 1.0)
    spacing = 1.0 / np.sqrt(max(density, 1e-6))
    qd = dict(max_edge_m=s.max_edge_factor * spacing, max_slope_deg=s.max_slope_deg,
              max_bend_deg=s.max_bend_deg)
    inner = ndimage.binary_erosion(raster, structure=np.ones((3, 3), dtype=bool))
    pool = [other.xyz[inner[index(other.xyz[:, :2])]]
            for k, other in enumerate(mission.strips) if k != b]
    pool_xyz = np.concatenate(pool)
    rng = np.random.default_rng(0)
    n = args.n
    pick = (np.sort(rng.choice(len(pool_xyz), n, replace=False)) if n <= len(pool_xyz)
            else np.sort(rng.integers(0, len(pool_xyz), n)))
    queries = np.ascontiguousarray(pool_xyz[pick])
    threshold = s.max_normal_distance_m
    repeats = args.repeats

    def timed(fn, reps: int, budget_s: float = 60.0):
        """Median CPU time of this (single-threaded) process over ``reps`` calls: seconds of
        one core, unaffected by other processes waiting for it; and the median wall time."""
        cpu, wall, out = [], [], None
        for _ in range(reps):
            w0, c0 = time.perf_counter(), time.process_time()
            out = fn()
            cpu.append(time.process_time() - c0)
            wall.append(time.perf_counter() - w0)
            if sum(wall) > budget_s:
                break
        walls.append(statistics.median(wall))
        return statistics.median(cpu), len(cpu), out

    walls: list[float] = []

    # TIN builds (lidarcal: triangulation + quality + grid locator; baseline: qhull + quality).
    build_l, _, tin = timed(lambda: Tin(xyz, TinQuality(**qd)), repeats)
    build_b, _, btin = timed(lambda: baseline.build_tin(xyz, **qd), repeats)

    # Warm-up (first-touch of arrays, caches), not timed.
    match_to_tin(queries[:10_000], tin, xyz, max_normal_distance=threshold)
    baseline.locate(btin, queries[:10_000, :2])

    t_l, reps_l, m = timed(
        lambda: match_to_tin(queries, tin, xyz, max_normal_distance=threshold), repeats)
    # Later iterations: vertices corrected by the simulated biases, queries located through
    # the vertex shift (two point locations per query).
    delta = as_vector(meta["biases"])
    g = laser_geometry(strip.t, xyz, mission.trajectory, window=s.window)
    shift = point_offsets(delta, g.x, g.z, g.kappa, g.beta)
    corrected = xyz - shift
    t_ls, reps_ls, m_s = timed(
        lambda: match_to_tin(queries, tin, corrected, max_normal_distance=threshold,
                             vertex_shift=shift), repeats)

    def base_match():
        tri = baseline.locate(btin, queries[:, :2])
        return baseline.plane_match(queries, btin.tri.simplices, xyz, tri, btin.usable,
                                    threshold)

    t_b, reps_b, mb = timed(base_match, repeats)
    t_loc, _, _ = timed(lambda: baseline.locate(btin, queries[:, :2]), 1)
    t_lloc, _, _ = timed(lambda: tin.locate(queries[:, :2]), 1)
    # Queries in random order (a walk cannot start next to the answer): a subset.
    n_rand = min(n, args.random_n)
    shuffled = np.ascontiguousarray(queries[rng.permutation(n)[:n_rand]])
    t_lr, _, _ = timed(
        lambda: match_to_tin(shuffled, tin, xyz, max_normal_distance=threshold), 1)

    def base_match_random():
        tri = baseline.locate(btin, shuffled[:, :2])
        return baseline.plane_match(shuffled, btin.tri.simplices, xyz, tri, btin.usable,
                                    threshold)

    t_br, _, _ = timed(base_match_random, 1)
    print(json.dumps({
        "n_queries": n, "tin_points": int(len(xyz)),
        "tin_build_s": {"lidarcal": build_l, "baseline": build_b},
        "match_s": {"lidarcal": t_l, "lidarcal_shift": t_ls, "baseline": t_b,
                    "baseline_locate_only": t_loc, "lidarcal_locate_only": t_lloc},
        "match_wall_s": {"lidarcal": walls[2], "lidarcal_shift": walls[3],
                         "baseline": walls[4]},
        "random_order": {"n": n_rand, "lidarcal_s": t_lr, "baseline_s": t_br},
        "repeats": {"lidarcal": reps_l, "lidarcal_shift": reps_ls, "baseline": reps_b},
        "matched_fraction": {"lidarcal": float(m.valid.mean()),
                             "lidarcal_shift": float(m_s.valid.mean()),
                             "baseline": float(mb[0].mean())},
    }))


def run_throughput(meta_path: Path, n: int, repeats: int, work: Path) -> dict[str, Any]:
    """The matching microbenchmark on the mission of ``meta_path``, in a fresh single-threaded
    process: its figures (CPU s, matched fractions)."""
    log = work / "throughput.log"
    cmd = [PYTHON, str(Path(__file__).resolve()), "_throughput", "--meta", str(meta_path),
           "--n", str(n), "--repeats", str(repeats)]
    res = run_child(cmd, env=SINGLE_THREAD_ENV, log=log, cwd=ROOT)
    if res["rc"] != 0:
        raise SystemExit(f"matching benchmark failed (exit {res['rc']}):\n{tail(log)}")
    lines = [ln for ln in log.read_text().splitlines() if ln.startswith("{")]
    return json.loads(lines[-1])


# ---------------------------------------------------------------------------- profile worker
def profile_worker(args: argparse.Namespace) -> None:
    """Profile (cProfile) of the in-process calibration (bag read + calibrate), top functions."""
    import cProfile
    import io
    import pstats

    from lidarcal_ros.io.config_file import load_flight_config
    from lidarcal_ros.pipeline.calibration.procedure import calibrate_mission, load_mission

    meta = json.loads(Path(args.meta).read_text())
    config = load_flight_config(None)
    prof = cProfile.Profile()
    started = time.perf_counter()
    prof.enable()
    mission = load_mission(meta["bag"], config, control_csv=meta["control"])
    result = calibrate_mission(mission, config)
    prof.disable()
    wall = time.perf_counter() - started
    print(f"in-process calibrate under cProfile: {wall:.1f} s wall, {result.iterations} "
          f"iterations, {mission.n_points} points")
    for key in ("tottime", "cumulative"):
        buf = io.StringIO()
        st = pstats.Stats(prof, stream=buf).strip_dirs().sort_stats(key)
        st.print_stats(args.top)
        text = buf.getvalue()
        start = text.find("   ncalls")
        print(f"\n--- top {args.top} by {key} ---")
        print(text[start:].rstrip())


# ---------------------------------------------------------------------------- report
def fmt_num(v: float | None, kind: str) -> str:
    """A figure for the tables by ``kind``: ``s`` seconds, ``mib`` MiB, ``rate`` million a
    second, else as it is; ``-`` for None or not finite."""
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "-"
    if kind == "s":
        return f"{v:.1f} s" if v >= 10 else f"{v:.2f} s"
    if kind == "mib":
        return f"{v:.0f} MiB"
    if kind == "rate":
        return f"{v / 1e6:.2f} M/s"
    return f"{v:g}"


def print_table(rows: list[list[str]], header: list[str]) -> None:
    """Print ``rows`` under ``header`` as a text table, columns padded to their widest cell."""
    widths = [max(len(str(r[i])) for r in [header, *rows]) for i in range(len(header))]
    line = " | ".join(h.ljust(w) for h, w in zip(header, widths))
    print(line)
    print("-+-".join("-" * w for w in widths))
    for r in rows:
        print(" | ".join(str(c).ljust(w) for c, w in zip(r, widths)))


def show_param(name: str, value: float | None) -> str:
    """A bias (SI) for the tables: arcsec for the boresight angles, ppm for dS, cm otherwise;
    ``-`` for None."""
    if value is None:
        return "-"
    if name in ("domega", "dphi", "dkappa"):
        return f"{value * ARCSEC:+.2f}\""
    if name == "dS":
        return f"{value * 1e6:+.1f} ppm"
    return f"{value * 100:+.2f} cm"


def machine() -> str:
    """The machine line of :mod:`machine`, and whether Triangle builds the TINs."""
    import machine as bench_machine

    try:
        import triangle  # noqa: F401

        tri = "yes"
    except ImportError:
        tri = "no"
    return f"{bench_machine.describe()}; triangle installed: {tri}"


def end_to_end(missions: list[tuple[str, MissionSpec]], repeats: int, work: Path,
               write_reference: bool) -> tuple[dict[str, dict[str, Any]], list[str]]:
    """``lidarcal calibrate`` of each mission; its table and the check of its estimate."""
    results: dict[str, dict[str, Any]] = {}
    metas = {}
    for name, spec in missions:
        meta = benchlib.prepare_mission(spec)
        metas[name] = meta
        print(f"mission {name}: {spec.describe()}, {meta['n_points']:,} points "
              f"({benchlib.CACHE / spec.key})", flush=True)
    for name, _spec in missions:
        results[name] = run_lidarcal(metas[name], repeats, work)
    failed = []
    print(f"\n{'mission':8s} {'points':>11s} {'model':>9s} {'wall s min / med':>17s} "
          f"{'CPU s':>6s} {'peak RSS':>9s} {'iter.':>5s}  goal <= {GOAL_WALL_S:g} s and "
          f"{GOAL_PEAK_MIB:g} MiB")
    for name, _spec in missions:
        lc, meta = results[name], metas[name]
        ok = min(lc["walls"]) <= GOAL_WALL_S and lc["peak_mib"] <= GOAL_PEAK_MIB
        print(f"{name:8s} {meta['n_points']:>11,} {lc['model']:>9s} "
              f"{benchlib.median_min(lc['walls']):>17s} {lc['cpu_s']:>6.2f} "
              f"{lc['peak_mib']:>5.0f} MiB {lc['iterations']:>5d}  {'met' if ok else 'NOT met'}")
        if not ok:
            failed.append(f"{name}: {min(lc['walls']):.1f} s, {lc['peak_mib']:.0f} MiB")
    print("\nestimates against the reference (bench/reference_estimates.json), in the "
          "reference's sigmas:")
    for name, spec in missions:
        lc = results[name]
        if write_reference:
            benchlib.store_reference(spec.key, lc["estimate"], "bench_calibrate.py "
                                     "--write-reference")
        same, lines = benchlib.compare_with_reference(spec.key, lc["estimate"], GOAL_SIGMA)
        verdict = {True: f"every estimate within {GOAL_SIGMA:g} sigma",
                   False: f"NOT within {GOAL_SIGMA:g} sigma", None: "no reference"}[same]
        print(f"  {name}: {verdict}")
        for line in lines:
            print(f"    {line}")
        if same is False:
            failed.append(f"{name}: estimate moved")
    return results, failed


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark (or, with ``_scaling``, ``_throughput`` or ``_profile`` first, one of
    its child workers) and print its figures; exit status 0."""
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv and argv[0] == "_scaling":
        scaling_worker(MissionSpec(**json.loads(argv[1])))
        return 0
    if argv and argv[0] in ("_throughput", "_profile"):
        wp = argparse.ArgumentParser()
        wp.add_argument("--meta", required=True)
        wp.add_argument("--n", type=int, default=1_000_000)
        wp.add_argument("--repeats", type=int, default=3)
        wp.add_argument("--top", type=int, default=15)
        wp.add_argument("--random-n", type=int, default=100_000)
        wargs = wp.parse_args(argv[1:])
        (throughput_worker if argv[0] == "_throughput" else profile_worker)(wargs)
        return 0

    ap = argparse.ArgumentParser(description="Benchmark lidarcal calibrate (bench/README.md).")
    ap.add_argument("--quick", action="store_true",
                    help="no scaling to 10M points (end to end and matching only)")
    ap.add_argument("--repeats", type=int, default=3, help="end-to-end runs per mission")
    ap.add_argument("--missions", nargs="+", choices=("level", "rough"),
                    default=["level", "rough"])
    ap.add_argument("--no-matching", action="store_true",
                    help="skip the matching microbenchmark")
    ap.add_argument("--match-points", type=int, default=None,
                    help="query points of the matching benchmark (default: mission size)")
    ap.add_argument("--baseline", action="store_true",
                    help="also run the straightforward baseline (bench/baseline.py, minutes)")
    ap.add_argument("--baseline-limit", type=float, default=600.0,
                    help="time limit of the baseline run, s (default 600)")
    ap.add_argument("--profile", action="store_true",
                    help="also print a cProfile of the in-process calibration")
    ap.add_argument("--top", type=int, default=15, help="profile lines (default 15)")
    ap.add_argument("--write-reference", action="store_true",
                    help="store this run's estimates as the reference (run it on main)")
    args = ap.parse_args(argv)

    print(f"machine: {machine()}")
    load_start = benchlib.load_average()
    missions = [(name, {"level": benchlib.MISSION_1M, "rough": benchlib.MISSION_1M_ROUGH}[name])
                for name in args.missions]
    failed: list[str] = []
    with tempfile.TemporaryDirectory(prefix="lidarcal-bench-") as tmp:
        work = Path(tmp)
        print("end to end: lidarcal calibrate BAG --control CSV -o OUT.yaml", flush=True)
        results, failed = end_to_end(missions, args.repeats, work, args.write_reference)
        if not args.quick:
            print("\nscaling: one mission of ~1M points and one ten times as long, in "
                  "process", flush=True)
            print_scaling(run_scaling([benchlib.MISSION_1M, benchlib.MISSION_10M_LONG], work))
        level = benchlib.prepare_mission(benchlib.MISSION_1M)
        level_meta_path = benchlib.CACHE / level["key"] / "meta.json"
        if not args.no_matching:
            n_q = args.match_points or level["n_points"]
            print(f"\nmatching (stage figure): {n_q:,} queries against one strip's TIN, one "
                  "thread", flush=True)
            print_matching(run_throughput(level_meta_path, n_q, 3, work))
        if args.baseline and "level" in results:
            print(f"\nbaseline ({results['level']['iterations']} iterations, as lidarcal; "
                  f"limit {args.baseline_limit:.0f} s)", flush=True)
            base = run_baseline(level, results["level"]["iterations"], args.baseline_limit,
                                work)
            print_baseline(results["level"], base, level, args.baseline_limit)
        if args.profile:
            prof_log = work / "profile.log"
            print("\nprofile: in-process calibrate under cProfile", flush=True)
            res = run_child([PYTHON, str(Path(__file__).resolve()), "_profile", "--meta",
                             str(level_meta_path), "--top", str(args.top)], log=prof_log,
                            cwd=ROOT)
            if res["rc"] != 0:
                raise SystemExit(f"profile failed:\n{tail(prof_log)}")
            print(prof_log.read_text().rstrip())
    load_end = benchlib.load_average()
    print(f"\nload average (1 min) before / after: {load_start:.2f} / {load_end:.2f}")
    print("goals: " + ("all met" if not failed else "NOT met: " + "; ".join(failed)))
    return 0


def print_matching(tp: dict[str, Any]) -> None:
    """Print the matching microbenchmark's figures ``tp``: points matched a second per core, TIN
    build times (s), matched fractions."""
    n_q = tp["n_queries"]
    rand = tp["random_order"]
    rows = [
        ["in acquisition order", fmt_num(n_q / tp["match_s"]["lidarcal"], "rate"),
         fmt_num(n_q / tp["match_s"]["baseline"], "rate")],
        ["later iterations (vertex shift)", fmt_num(n_q / tp["match_s"]["lidarcal_shift"],
                                                    "rate"), "-"],
        ["in random order", fmt_num(rand["n"] / rand["lidarcal_s"], "rate"),
         fmt_num(rand["n"] / rand["baseline_s"], "rate")],
        [f"TIN build, one strip ({tp['tin_points']:,} pts)",
         fmt_num(tp["tin_build_s"]["lidarcal"], "s"), fmt_num(tp["tin_build_s"]["baseline"],
                                                              "s")],
    ]
    print_table(rows, ["matching, per core (CPU time)", "lidarcal", "baseline find_simplex"])
    print(f"matched {tp['matched_fraction']['lidarcal']:.1%} (lidarcal), "
          f"{tp['matched_fraction']['baseline']:.1%} (baseline); point location alone "
          f"{fmt_num(tp['match_s']['lidarcal_locate_only'], 's')} of "
          f"{fmt_num(tp['match_s']['lidarcal'], 's')}")


def print_baseline(lc: dict[str, Any], base: dict[str, Any], meta: dict[str, Any],
                   limit: float) -> None:
    """Print the baseline's end-to-end time and peak memory beside lidarcal's (``> limit`` s if
    it timed out) and both estimates beside the truth of ``meta``."""
    timed_out = bool(base.get("timed_out"))
    wall = f"> {limit:.0f} s" if timed_out else fmt_num(base.get("wall_s"), "s")
    ratio = lc["wall_s"] and (limit if timed_out else base["wall_s"]) / lc["wall_s"]
    print(f"baseline end to end: {wall} (lidarcal {fmt_num(lc['wall_s'], 's')}: "
          f"{'>' if timed_out else ''}{ratio:.1f}x), peak "
          f"{fmt_num(base.get('peak_mib'), 'mib')}")
    if timed_out:
        return
    rows = []
    for name in ("dX", "dY", "domega", "dphi", "dkappa", "dr", "dS"):
        lv = lc["delta"][name] if lc["estimated"].get(name) else None
        bv = base.get("delta", {}).get(name)
        rows.append([name, show_param(name, meta["biases"][name]), show_param(name, lv),
                     show_param(name, bv)])
    print_table(rows, ["parameter", "truth", "lidarcal", "baseline"])


if __name__ == "__main__":
    sys.exit(main())
