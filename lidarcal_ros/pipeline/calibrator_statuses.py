"""What the live calibrator reports about itself on ``/diagnostics``, beside each estimate's QA.

``lidarcal: memory`` (points held against the budget, thinning, strips released),
``lidarcal: input`` (clouds, points and poses received; what was skipped, left out or refused,
and why; the strips seen only in part), ``lidarcal: state`` (estimates, checkpoints, the
normal equations) and, while there is no estimate, ``lidarcal: convergence``; and the
convergence status of the latest estimate while the background refinement works on it
(:func:`refinement_status`). Levels and the status record are
:mod:`lidarcal_ros.io.ros_messages`'.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from lidarcal_ros.io.ros_messages import OK, WARN, StatusSpec
from lidarcal_ros.pipeline.streaming import StreamingCalibration

__all__ = ["InputCounts", "ServiceCounts", "operating_statuses", "refinement_status"]


@dataclass
class InputCounts:
    """What arrived: clouds and their points, poses, clouds skipped and the last reason."""

    clouds: int = 0
    points: int = 0
    poses: int = 0
    skipped: int = 0
    last_error: str = ""


@dataclass(frozen=True)
class ServiceCounts:
    """The calibrator's own counts: estimates published, the seconds the last took,
    checkpoints written, the checkpoint resumed from ('' = none) and jobs waiting."""

    solves: int
    last_solve_s: float
    checkpoints: int
    resumed_from: str
    queued_jobs: int


def refinement_status(stream: StreamingCalibration, status: StatusSpec) -> StatusSpec:
    """The convergence ``status`` of the latest estimate, saying whether the estimate is being
    converged on the strips now held."""
    if not stream.refinement_pending:
        return replace(status, values={**status.values, "refining": "false"})
    return replace(status, level=max(status.level, WARN), message=(
        f"converging: iteration {stream.refinement_iteration + 1} on the strips held (latest "
        f"estimate: {status.message})"), values={
            **status.values, "converged": "False", "refining": "true"})


def operating_statuses(stream: StreamingCalibration, received: InputCounts,
                       counts: ServiceCounts, *, no_estimate: bool) -> list[StatusSpec]:
    """Memory, input and state statuses, and the convergence status when ``no_estimate``
    has been published and the stream holds none."""
    out = [memory_status(stream), input_status(stream, received, counts.queued_jobs)]
    neq = stream.normal_equations
    resumed = counts.resumed_from
    out.append(StatusSpec(OK, "lidarcal: state", (
        f"{counts.solves} solves (last {counts.last_solve_s:.2f} s), {counts.checkpoints} "
        "checkpoints" + (f", resumed from {resumed}" if resumed else "")
        + ("" if stream.latest is not None else f"; waiting: {stream.waiting_for}")), {
        "solves": str(counts.solves), "last_solve_s": f"{counts.last_solve_s:.3f}",
        "checkpoints": str(counts.checkpoints), "resumed_from": resumed,
        "normal_equations_count": str(int(neq.count)),
        "normal_equations_trace": repr(float(np.trace(neq.n))),
        "normal_equations_yy": repr(float(neq.yy))}))
    if stream.latest is None and no_estimate:
        out.append(StatusSpec(OK if not stream.strip_ids else WARN, "lidarcal: convergence",
                              "no estimate yet: " + (stream.waiting_for or "no data")))
    return out


def memory_status(stream: StreamingCalibration) -> StatusSpec:
    """``lidarcal: memory``: points held against the budget (WARN once the budget released
    strips or forced a thinning)."""
    s = stream
    dropped = s.dropped_points
    level = WARN if dropped or s.auto_thinning_cell_m else OK
    message = f"{s.n_points} points held of a budget of {s.max_points}"
    cell = float(s.config["calibration.thinning_cell_m"])
    if s.thinned_points:
        message += f" ({s.thinned_points} left out by thinning)"
    if s.auto_thinning_cell_m:
        message += (f"; the strips being flown outgrew the budget: thinning at "
                    f"{s.thinning_cell_m:g} m")
    if dropped:
        message += (f"; released {dropped} points (strips "
                    f"{', '.join(str(i) for i in s.dropped_strips)}), oldest first")
        if cell <= 0:
            message += "; calibration.thinning_cell_m would keep more strips"
    return StatusSpec(level, "lidarcal: memory", message, {
        "points_held": str(s.n_points), "budget_points": str(s.max_points),
        "thinned_points": str(s.thinned_points), "thinning_cell_m": f"{cell:g}",
        "auto_thinning_cell_m": f"{s.auto_thinning_cell_m:g}",
        "dropped_points": str(dropped),
        "dropped_strips": ",".join(str(i) for i in s.dropped_strips),
        "strips": ",".join(str(i) for i in s.strip_ids),
        "open_strips": ",".join(str(i) for i in s.open_strip_ids)})


def input_status(stream: StreamingCalibration, received: InputCounts,
                 queued_jobs: int) -> StatusSpec:
    """``lidarcal: input``: what arrived, and what of it was skipped, left out or refused
    (WARN when anything was)."""
    s, inp = stream, received
    uncovered, left_out = s.uncovered_points, s.uncovered_strips
    rejected, late = s.rejected_strips, s.late_points
    partial = s.partial_strips
    level = WARN if inp.skipped or uncovered or rejected or late or partial else OK
    message = f"{inp.clouds} clouds, {inp.points} points, {inp.poses} poses"
    if inp.skipped:
        message += f"; {inp.skipped} malformed clouds skipped (last: {inp.last_error})"
    if uncovered:
        message += f"; {uncovered} points without trajectory left out" + (
            f" (strips {', '.join(str(i) for i in left_out)} wholly)" if left_out else "")
    if late:
        message += (f"; {late} points of strips already closed ignored (a pause longer than "
                    "strip_gap_s?)")
    if rejected:
        message += (f"; {len(rejected)} strip(s) refused by the calibration, left out "
                    f"(last: {rejected[-1][1]})")
    if partial:
        message += (f"; strips {', '.join(str(i) for i in partial)} seen in part (strip "
                    f"{next(iter(partial))}: {next(iter(partial.values()))})")
    if s.poses_left_out:
        message += (f"; {s.poses_left_out} poses left out (a non-finite stamp or position, or "
                    "a stamp already received)")
    return StatusSpec(level, "lidarcal: input", message, {
        "poses_left_out": str(s.poses_left_out),
        "clouds": str(inp.clouds), "points": str(inp.points),
        "poses": str(inp.poses), "skipped_clouds": str(inp.skipped),
        "last_error": inp.last_error, "queued_jobs": str(queued_jobs),
        "uncovered_points": str(uncovered),
        "uncovered_strips": ",".join(str(i) for i in left_out),
        "late_points": str(late),
        "rejected_strips": ",".join(str(i) for i, _ in rejected),
        "partial_strips": "; ".join(f"{i}: {text}" for i, text in partial.items()),
        "last_rejection": rejected[-1][1] if rejected else ""})
