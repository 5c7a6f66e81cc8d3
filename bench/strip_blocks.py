"""The adjustment with every strip's trajectory errors (docs/method.md section 11) against the
number of strips: time and memory of the reduced solve (core/adjustment/strip_blocks.py) for a block
of parallel lines in rows with cross lines, against the dense solve of the whole system measured
in the same run.

    .venv/bin/python bench/strip_blocks.py [--strips 10 30 100 300 1000] [--per-pair 2000]

Each strip overlaps its two neighbours in its row and every fourth strip is crossed by a
line of the next row, so a strip holds 2-3 overlaps as in a real block; each overlap gives
``--per-pair`` correspondences with random normals and design rows (the numbers of a solve
do not depend on the geometry). Prints per size: correspondences, unknowns, seconds and peak
memory of the reduced solve (normal equations, Schur complement, back-substitution, every
trajectory sigma), the dense solve's where it fits (<= 3000 unknowns), their ratio, and the
reduced solve's seconds per strip (linear: flat).
"""

from __future__ import annotations

import argparse
import sys
import time
import tracemalloc
from collections.abc import Callable
from functools import partial

import machine  # bench/machine.py: this script's folder is on sys.path
import numpy as np

from lidarcal_ros.core.adjustment.least_squares import ObservabilityLimits, Observations, solve
from lidarcal_ros.core.adjustment.strip_blocks import StripBlocks
from lidarcal_ros.core.params import PARAMETER_NAMES
from lidarcal_ros.core.trajectory.strip_errors import (
    TrajectoryErrorSettings,
    TrajectoryModel,
    TrajectoryRows,
    TrajectoryState,
    error_columns,
)

ROW = 20  # strips per row of the block
STRIP_S = 60.0  # seconds of a strip


def block(strips: int, per_pair: int, model: TrajectoryModel,
          seed: int = 0) -> tuple[Observations, TrajectoryState]:
    """Correspondences of a block of ``strips`` (module docstring)."""
    rng = np.random.default_rng(seed)
    state = TrajectoryState(model)
    for k in range(strips):
        state.add_strip(k * 90.0 - STRIP_S / 2, k * 90.0 + STRIP_S / 2)
    pairs = [(k, k + 1) for k in range(strips - 1) if (k + 1) % ROW]
    pairs += [(k, k + ROW) for k in range(0, strips - ROW, 4)]
    a = np.repeat([p[0] for p in pairs], per_pair)
    b = np.repeat([p[1] for p in pairs], per_pair)
    k = a.size
    n = rng.normal(size=(k, 3))
    n /= np.linalg.norm(n, axis=1)[:, None]
    t_a = a * 90.0 + rng.uniform(-STRIP_S / 2, STRIP_S / 2, k)
    t_b = b * 90.0 + rng.uniform(-STRIP_S / 2, STRIP_S / 2, k)
    rows = TrajectoryRows(a, t_a, b, t_b, n, np.zeros(k))
    design = rng.normal(size=(k, 8)) * 0.1
    y = rng.normal(0.0, 0.02, k)
    obs = Observations(design, y, np.ones(k), np.zeros(k, np.int64), np.zeros(k, np.int64),
                       rows)
    return obs, state


def measured(work: Callable[[], object]) -> tuple[float, float]:
    """Seconds and peak MiB (Python's allocations, numpy's included) of ``work()``."""
    tracemalloc.start()
    t0 = time.perf_counter()
    work()
    seconds = time.perf_counter() - t0
    peak = tracemalloc.get_traced_memory()[1] / 2**20
    tracemalloc.stop()
    return seconds, peak


def reduced_solve(obs: Observations, state: TrajectoryState) -> None:
    """The reduced solve with every trajectory sigma."""
    assert obs.trajectory is not None
    blocks = StripBlocks(obs, obs.trajectory, state, TrajectoryErrorSettings(state.model),
                         unit_sigma=0.02)
    sol = solve(blocks.reduced, solve_for=PARAMETER_NAMES,
                limits=ObservabilityLimits(max_sigma={}))
    blocks.tau_step(sol.delta)
    blocks.tau_sigma(sol)


def dense_solve(obs: Observations, state: TrajectoryState) -> None:
    """The same system solved densely, every sigma (the baseline)."""
    assert obs.trajectory is not None
    full_t = error_columns(state, obs.trajectory).toarray()
    top = obs.rows.T @ obs.rows
    side = obs.rows.T @ full_t
    prior = state.prior(TrajectoryErrorSettings(state.model)).toarray()
    corner = full_t.T @ full_t + prior * 0.02 ** 2
    n_mat = np.block([[top, side], [side.T, corner]])
    u = np.concatenate([obs.rows.T @ obs.y, full_t.T @ obs.y])
    np.linalg.inv(n_mat) @ u


def main() -> int:
    """Time the reduced and the dense solve for each number of strips of the command line and
    print them; exit status 0."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--strips", type=int, nargs="+", default=[10, 30, 100, 300, 1000])
    parser.add_argument("--per-pair", type=int, default=2000)
    parser.add_argument("--model", default="drift", choices=("offset", "drift", "spline"))
    args = parser.parse_args()
    print(f"machine: {machine.describe()}")
    print(f"{'strips':>6} {'corresp.':>9} {'unknowns':>8} {'reduced s':>9} {'MiB':>6} "
          f"{'dense s':>8} {'MiB':>6} {'dense/red.':>10} {'ms/strip':>8}")
    for strips in args.strips:
        obs, state = block(strips, args.per_pair, TrajectoryModel(args.model))
        unknowns = 8 + state.params.shape[0]
        red_s, red_mb = measured(partial(reduced_solve, obs, state))
        if unknowns <= 3000:
            den_s, den_mb = measured(partial(dense_solve, obs, state))
            dense = f"{den_s:8.2f} {den_mb:6.0f} {den_s / red_s:10.1f}"
        else:
            dense = f"{'-':>8} {'-':>6} {'-':>10}"
        print(f"{strips:6d} {len(obs):9d} {unknowns:8d} {red_s:9.2f} {red_mb:6.0f} {dense} "
              f"{1000 * red_s / strips:8.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
