"""Benchmark of ``lidarcal correct``, ``calibrate``, ``evaluate`` and ``report`` with ``--dask
local:N`` against the serial runs of the same mission.

    .venv/bin/python bench/bench_dask.py                        # the ~6M-point mission, .mcap
    .venv/bin/python bench/bench_dask.py --density 0.3 --line-length 600 --format laz
    .venv/bin/python bench/bench_dask.py --workers 2 --repeats 3
    .venv/bin/python bench/bench_dask.py --commands calibrate --density 0.3 --line-length 500
    .venv/bin/python bench/bench_dask.py --commands evaluate,report --density 0.3 --line-length 500

Each run is ``lidarcal correct BAG --calibration CAL -o OUT`` (or ``lidarcal calibrate BAG
--control CSV -o CAL``, ``lidarcal evaluate BAG --calibration CAL --check-points CSV --json``,
``lidarcal report BAG --calibration CAL --check-points CSV -o OUT.html``; CAL: the true
biases) in a fresh process (its wall time includes the process start and, with ``--dask``,
the local cluster's start), serial and ``--dask local:N`` alternately, ``--repeats`` times
each; printed per command: the wall times (min, median), the speed-up (serial / Dask, of the
minima), the peak resident memory of each process tree, and whether the two outputs are byte
for byte the same (each run writes an output of the same name in its own folder: a bag's
metadata holds its file name; a calibration file holds no time; a report's time and command
line are left out of the comparison).
The mission is simulated once and cached under ``bench/.cache/`` (bench/benchlib.py).
"""

from __future__ import annotations

import argparse
import filecmp
import re
import shutil
import sys
from pathlib import Path
from typing import Any

import benchlib  # bench/benchlib.py: this script's folder is on sys.path
from bench_correct import calibration_of
from benchlib import PYTHON, MissionSpec, median_min, run_child, tail

WORK = benchlib.CACHE / "dask_work"
#: The commands benchmarked and the name of each one's output.
NAMES = {"correct": "out.mcap", "calibrate": "calibration.yaml", "evaluate": "evaluation.json",
         "report": "report.html"}


def _page(path: Path) -> str:
    """A report's page without what differs from run to run: its time and command line."""
    page = re.sub(r"\d{4}-\d\d-\d\d \d\d:\d\d:\d\d UTC", "", path.read_text())
    return re.sub(r"<td>lidarcal report [^<]*</td>", "", page)


def _same(a: Path, b: Path) -> bool:
    """The two outputs (files, or bag directories) hold the same bytes."""
    if a.suffix == ".html":
        return _page(a) == _page(b)
    if a.is_file():
        return filecmp.cmp(a, b, shallow=False)
    names = sorted(p.name for p in a.iterdir())
    return names == sorted(p.name for p in b.iterdir()) and all(
        filecmp.cmp(a / n, b / n, shallow=False) for n in names)


def _run(meta: dict[str, Any], command: str, out: Path, dask: str | None) -> dict[str, Any]:
    """One ``lidarcal COMMAND`` of the mission ``meta`` to ``out``: its figures."""
    if out.parent.exists():
        shutil.rmtree(out.parent)
    out.parent.mkdir(parents=True)
    log = WORK / "last.log"
    calibration = ["--calibration", str(calibration_of(meta))]
    checks = ["--check-points", meta["control"]]
    inputs = {"correct": [*calibration, "-o", str(out), "-q"],
              "calibrate": ["--control", meta["control"], "-o", str(out), "-q"],
              # (evaluate's output is what it prints: the log)
              "evaluate": [*calibration, *checks, "--json"],
              "report": [*calibration, *checks, "-o", str(out), "-q"]}[command]
    if command == "evaluate":
        log = out
    cmd = [PYTHON, "-m", "lidarcal_ros", command, meta["bag"], *inputs]
    if dask is not None:
        cmd += ["--dask", dask]
    res = run_child(cmd, log=log, tree_memory=True)
    if res["rc"] != 0:
        raise SystemExit(f"lidarcal {command} failed (exit {res['rc']}):\n{tail(log)}")
    return res


def _compare(meta: dict[str, Any], command: str, name: str, dask: str, repeats: int) -> bool:
    """``command`` serial and with ``--dask`` alternately, ``repeats`` times: print the
    figures; whether the outputs are the same bytes."""
    times: dict[str, list[float]] = {"serial": [], dask: []}
    peaks: dict[str, list[float]] = {"serial": [], dask: []}
    for _ in range(repeats):
        for label, option in (("serial", None), (dask, dask)):
            res = _run(meta, command, WORK / command / label / name, option)
            times[label].append(res["wall_s"])
            peaks[label].append(res["peak_mib"])
    same = _same(WORK / command / "serial" / name, WORK / command / dask / name)
    print(f"lidarcal {command}:")
    for label in times:
        print(f"  {label:>8}: wall {median_min(times[label])} s (min/median), peak "
              f"{max(peaks[label]):.0f} MiB (process tree)")
    speedup = min(times["serial"]) / min(times[dask])
    print(f"  speed-up of --dask {dask}: {speedup:.2f}x; outputs byte-identical: {same}; "
          f"load average {benchlib.load_average():.2f}", flush=True)
    return same


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark; print its figures."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--density", type=float, default=1.0)
    ap.add_argument("--line-length", type=float, default=1000.0)
    ap.add_argument("--format", choices=("mcap", "laz", "las"), default="mcap")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--commands", default="correct,calibrate",
                    help="comma-separated: correct, calibrate, evaluate, report")
    args = ap.parse_args(argv)
    commands = [c.strip() for c in args.commands.split(",") if c.strip()]
    if not commands or set(commands) - set(NAMES):
        ap.error(f"--commands: expected some of {', '.join(NAMES)}, got {args.commands!r}")
    spec = MissionSpec(args.density, args.line_length)
    meta = benchlib.prepare_mission(spec)
    print(f"mission: {spec.describe()}: {meta['n_points'] / 1e6:.2f}M points; load average "
          f"{benchlib.load_average():.2f}", flush=True)
    dask = f"local:{args.workers}"
    names = {**NAMES, "correct": f"out.{args.format}"}
    same = [_compare(meta, c, names[c], dask, args.repeats) for c in commands]
    shutil.rmtree(WORK, ignore_errors=True)
    return 0 if all(same) else 1


if __name__ == "__main__":
    sys.exit(main())
