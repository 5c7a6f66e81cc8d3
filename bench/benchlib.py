"""What the benchmarks share: the simulated missions (cached as bags), measured child
processes, and the reference estimates the accuracy is held to.

Missions are simulated once and cached under ``bench/.cache/`` (git-ignored) as a mission
bag, a control CSV and a ``meta.json`` (points, clouds, biases); delete the directory to
simulate again, e.g. after a change of the simulator.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

BENCH = Path(__file__).resolve().parent
ROOT = BENCH.parent
CACHE = BENCH / ".cache"
PYTHON = sys.executable
LIDARCAL = str(Path(PYTHON).with_name("lidarcal"))
#: The estimates of the benchmark missions that every version is held to (bench/README.md,
#: "Accuracy"): written by ``bench_calibrate.py --write-reference``.
REFERENCE = BENCH / "reference_estimates.json"
#: Points per metre of line per unit density: the swath at 1150 m (50 deg field of view).
SWATH_HIGH_M = 2.0 * 1150.0 * math.tan(math.radians(25.0))
N_STRIPS = 6
ARCSEC = 180.0 / math.pi * 3600.0
ANGLES = ("domega", "dphi", "dkappa")


@dataclass(frozen=True)
class MissionSpec:
    """A simulated paper mission (six strips at 1150 m and 540 m, built-up terrain, one
    control point, the paper's biases; clouds of 0.1 s of scanning).

    Attributes
    ----------
    density : float
        Points per m^2 at the 1150 m lines (a strip holds about ``density * 1072.5 * L``
        points, and the sensor fires ``density * 1072.5 * 60`` pulses a second).
    line_length_m : float
    seed : int
    rough_air : bool
        Flown in the simulator's rough air (``RoughAir()``: roll +-4 deg, pitch +-2.5 deg, 1
        deg of heading wobble) with a 5 deg crab (``crosswind_for_crab(5, 60)``), the INS
        attitude on the trajectory: the calibration chooses the rigorous model.
    """

    density: float
    line_length_m: float
    seed: int = 7
    rough_air: bool = False

    @property
    def key(self) -> str:
        """The mission's name in the cache and the reference: density, line length (m), seed,
        rough air."""
        return (f"paper_d{self.density:g}_L{self.line_length_m:g}_s{self.seed}"
                + ("_rough" if self.rough_air else ""))

    @property
    def approx_points(self) -> int:
        """About how many points the mission holds (six strips as wide as the 1150 m swath)."""
        return int(N_STRIPS * self.density * SWATH_HIGH_M * self.line_length_m)

    def describe(self) -> str:
        """The mission in words, for the benchmarks' output."""
        return (f"paper scenario, density {self.density:g}, {self.line_length_m:g} m lines, "
                f"seed {self.seed}" + (", rough air + 5 deg crab, INS attitude"
                                       if self.rough_air else ""))


#: The ~1M-point mission of the goals (the issue's 1.16M-point mission).
MISSION_1M = MissionSpec(0.3, 600.0)
#: The same in rough air (the rigorous model).
MISSION_1M_ROUGH = MissionSpec(0.3, 600.0, rough_air=True)
#: Ten times as many points, ten times as long (the calibration's scaling).
MISSION_10M_LONG = MissionSpec(0.3, 6000.0)
#: About 10M points at a denser sensor (103k pulses a second, clouds of 10k points): the
#: correction's throughput.
MISSION_10M_DENSE = MissionSpec(1.6, 1000.0)


def simulate(spec: MissionSpec) -> Any:
    """The simulated mission of a spec, in memory (:mod:`lidarcal_ros.core.simulation`)."""
    from lidarcal_ros.core.simulation.flight_path import RoughAir, crosswind_for_crab
    from lidarcal_ros.core.simulation.simulate import simulate_mission
    from lidarcal_ros.core.simulation.spec import SimulationSpec

    extra: dict[str, Any] = {}
    if spec.rough_air:
        extra = {"rough_air": RoughAir(), "attitude": True,
                 "wind_mps": crosswind_for_crab(5.0, 60.0)}
    return simulate_mission(SimulationSpec.from_options(
        scenario="paper", density=spec.density, line_length_m=spec.line_length_m,
        seed=spec.seed, **extra))


def prepare_mission(spec: MissionSpec, *, quiet: bool = False) -> dict[str, Any]:
    """The cached bag, control CSV and meta of a mission (simulated in a child process the
    first time: the simulation's memory is not the benchmark's).

    Returns
    -------
    dict
        ``bag``, ``control`` (paths), ``n_points``, ``n_clouds``, ``biases`` (SI), the spec,
        ``cached``.
    """
    where = CACHE / spec.key
    meta_path = where / "meta.json"
    if meta_path.exists():
        meta = json.loads(meta_path.read_text())
        meta["cached"] = True
        return meta
    if where.exists():
        shutil.rmtree(where)
    where.mkdir(parents=True)
    if not quiet:
        print(f"  simulating {spec.key} (~{spec.approx_points / 1e6:.1f}M points)...",
              flush=True)
    log = where / "prepare.log"
    res = run_child([PYTHON, str(Path(__file__).resolve()), "_prepare",
                     json.dumps(asdict(spec)), str(where)], log=log)
    if res["rc"] != 0 or not meta_path.exists():
        raise SystemExit(f"simulation of {spec.key} failed:\n{tail(log)}")
    meta = json.loads(meta_path.read_text())
    meta["cached"] = False
    return meta


def _prepare_worker(spec: MissionSpec, where: Path) -> None:
    from lidarcal_ros.io.bag.mission_bag import write_mission_bag
    from lidarcal_ros.io.survey.control import write_control_csv

    started = time.perf_counter()
    sim = simulate(spec)
    bag = where / "mission"
    write_mission_bag(bag, sim.mission)
    control = where / "control.csv"
    assert sim.mission.control is not None
    write_control_csv(control, sim.mission.control)
    n_clouds = sum(int(math.ceil((s.t[-1] - s.t[0]) / 0.1)) for s in sim.mission.strips)
    meta = {"key": spec.key, "spec": asdict(spec), "bag": str(bag), "control": str(control),
            "n_points": int(sim.mission.n_points), "n_strips": len(sim.mission.strips),
            "approx_clouds": n_clouds, "biases": sim.biases,
            "simulate_s": time.perf_counter() - started}
    (where / "meta.json").write_text(json.dumps(meta, indent=1))  # last: marks it complete


# ---------------------------------------------------------------------------- children
def _tree_rss_mib(root: int) -> tuple[float, float]:
    """Resident memory of a process and all its descendants, MiB, from /proc: their sum and
    the largest one's."""
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
    page_mib = os.sysconf("SC_PAGE_SIZE") / 2**20
    sizes = [rss.get(pid, 0) for pid in tree]
    return sum(sizes) * page_mib, max(sizes) * page_mib


_compiled = False


def compile_package() -> None:
    """Byte-compile lidarcal_ros once per benchmark run, so that the timed processes load
    it as an installed package does (pip and colcon compile on install; an editable install
    compiles on first import, unless ``PYTHONDONTWRITEBYTECODE`` is set, as it is in some
    containers: then every process would compile the package's sources again)."""
    global _compiled
    if not _compiled:
        import compileall

        compileall.compile_dir(ROOT / "lidarcal_ros", quiet=1)
        _compiled = True


def run_child(cmd: list[str], *, log: Path | None = None, limit_s: float | None = None,
              env: dict[str, str] | None = None, cwd: Path | None = ROOT,
              tree_memory: bool = False) -> dict[str, Any]:
    """Run ``cmd`` in a fresh process (its output to ``log``), lidarcal_ros byte-compiled
    first (:func:`compile_package`).

    Returns
    -------
    dict
        ``wall_s`` (perf_counter around the process, its start included), ``cpu_s``
        (user + system of the child, ``wait4``), ``peak_mib`` (the child's own peak RSS: its
        ``VmHWM`` read every few ms, which a forked child does not inherit from the
        benchmark's process as ``ru_maxrss`` does; or with ``tree_memory`` that of its
        process tree sampled every 50 ms if larger), with ``tree_memory`` also
        ``largest_mib`` (the largest single process of the tree, sampled; at least the
        child's own peak), ``rc``, ``timed_out``.
    """
    compile_package()
    out = open(log, "wb") if log else subprocess.DEVNULL
    tree_peak = 0.0
    largest = 0.0
    own_peak = 0.0
    timed_out = False
    try:
        started = time.perf_counter()
        proc = subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT, cwd=cwd,
                                env={**os.environ, **(env or {})}, start_new_session=True)
        last_sample = 0.0
        while True:
            pid, status, usage = os.wait4(proc.pid, os.WNOHANG)
            if pid:
                break
            own_peak = max(own_peak, _hwm_mib(proc.pid))
            now = time.perf_counter()
            if limit_s is not None and now - started > limit_s:
                timed_out = True
                os.killpg(proc.pid, signal.SIGKILL)
                pid, status, usage = os.wait4(proc.pid, 0)
                break
            if tree_memory and now - last_sample >= 0.05:
                total, one = _tree_rss_mib(proc.pid)
                tree_peak, largest = max(tree_peak, total), max(largest, one)
                last_sample = now
            time.sleep(0.005)
        wall = time.perf_counter() - started
        proc.returncode = os.waitstatus_to_exitcode(status)  # already reaped
    finally:
        if log:
            out.close()
    own = own_peak or usage.ru_maxrss / 1024.0
    run = {"wall_s": wall, "cpu_s": usage.ru_utime + usage.ru_stime,
           "peak_mib": max(own, tree_peak), "rc": proc.returncode, "timed_out": timed_out}
    if tree_memory:
        run["largest_mib"] = max(own, largest)
    return run


def _hwm_mib(pid: int) -> float:
    """A running process's peak resident set so far (``VmHWM``), MiB; 0 if unreadable."""
    try:
        with open(f"/proc/{pid}/status", "rb") as f:
            for line in f:
                if line.startswith(b"VmHWM:"):
                    return int(line.split()[1]) / 1024.0
    except (OSError, ValueError, IndexError):
        pass
    return 0.0


def tail(path: Path, n: int = 15) -> str:
    """The last ``n`` lines of a log file (empty if it cannot be read)."""
    try:
        return "\n".join(path.read_text(errors="replace").splitlines()[-n:])
    except OSError:
        return ""


def median_min(values: list[float]) -> str:
    """``min / median`` of run figures, for the tables."""
    ordered = sorted(values)
    mid = ordered[len(ordered) // 2] if len(ordered) % 2 else \
        0.5 * (ordered[len(ordered) // 2 - 1] + ordered[len(ordered) // 2])
    return f"{ordered[0]:.2f} / {mid:.2f}"


def load_average() -> float:
    """The machine's load average over the last minute."""
    return os.getloadavg()[0]


# ---------------------------------------------------------------------------- accuracy
def read_estimate(calibration_yaml: Path) -> dict[str, dict[str, float | None]]:
    """``{name: {"value", "sigma"}}`` of a calibration file's estimated biases (SI)."""
    import yaml

    doc = yaml.safe_load(calibration_yaml.read_text())["lidarcal_calibration"]
    return {k: {"value": float(v["value"]),
                "sigma": None if v["sigma"] is None else float(v["sigma"])}
            for k, v in doc["biases"].items() if v.get("estimated")}


def reference_estimates() -> dict[str, Any]:
    """The stored reference (:data:`REFERENCE`), ``{}`` when there is none."""
    return json.loads(REFERENCE.read_text()) if REFERENCE.exists() else {}


def store_reference(key: str, estimate: dict[str, dict[str, float | None]],
                    source: str) -> None:
    """Keep ``estimate`` as the reference of mission ``key`` (``source``: what made it)."""
    ref = reference_estimates()
    ref[key] = {"source": source, "biases": estimate}
    REFERENCE.write_text(json.dumps(ref, indent=1, sort_keys=True) + "\n")


def compare_with_reference(key: str, estimate: dict[str, dict[str, float | None]],
                           tolerance_sigma: float = 0.1) -> tuple[bool | None, list[str]]:
    """Whether every estimate is within ``tolerance_sigma`` of the reference's sigma of it.

    Returns
    -------
    ok : bool or None
        None when there is no reference for ``key``.
    lines : list of str
        Per parameter: reference, now, difference in the reference's sigmas.
    """
    ref = reference_estimates().get(key)
    if ref is None:
        return None, [f"no reference estimate for {key} in {REFERENCE.name}"]
    ok = True
    lines = []
    for name, want in ref["biases"].items():
        got = estimate.get(name)
        sigma = want["sigma"]
        if got is None or sigma is None or not sigma > 0:
            ok = False
            lines.append(f"{name:7s} reference {show(name, want['value'])}, now "
                         f"{'not estimated' if got is None else show(name, got['value'])}")
            continue
        diff = (got["value"] - want["value"]) / sigma
        ok &= abs(diff) <= tolerance_sigma
        lines.append(f"{name:7s} reference {show(name, want['value']):>14s} "
                     f"+- {show(name, sigma, signed=False):>11s}   now "
                     f"{show(name, got['value']):>14s}   difference {diff:+.4f} sigma")
    extra = sorted(set(estimate) - set(ref["biases"]))
    if extra:
        ok = False
        lines.append(f"estimated now and not in the reference: {', '.join(extra)}")
    return ok, lines


def show(name: str, value: float | None, signed: bool = True) -> str:
    """A bias in display units (arcsec, cm, ppm)."""
    if value is None or not math.isfinite(value):
        return "-"
    sign = "+" if signed else ""
    if name in ANGLES:
        return f"{value * ARCSEC:{sign}.3f}\""
    if name == "dS":
        return f"{value * 1e6:{sign}.3f} ppm"
    return f"{value * 100:{sign}.3f} cm"


if __name__ == "__main__":
    if len(sys.argv) == 4 and sys.argv[1] == "_prepare":
        _prepare_worker(MissionSpec(**json.loads(sys.argv[2])), Path(sys.argv[3]))
    else:
        raise SystemExit("usage: benchlib.py _prepare SPEC_JSON DIR (internal)")
