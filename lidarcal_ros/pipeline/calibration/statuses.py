"""What the live calibrator reports about itself on ``/diagnostics``, beside each estimate's QA.

The statuses: docs/nodes.md, "``lidarcal_calibrator``".
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from lidarcal_ros.core.adjustment.least_squares import ParameterState
from lidarcal_ros.core.calibration.extrinsic import timing_text
from lidarcal_ros.core.calibration.result import CalibrationResult
from lidarcal_ros.core.trajectory.strip_errors import StripError, TrajectoryErrorSettings
from lidarcal_ros.io.calibration_file import Extrinsic
from lidarcal_ros.io.cloud.messages import ERROR, OK, WARN, StatusSpec
from lidarcal_ros.pipeline.calibration.streaming import StreamingCalibration

__all__ = ["TRAJECTORY_ERROR_FACTOR", "TRAJECTORY_WARN_FACTOR", "InputCounts", "ServiceCounts",
           "operating_statuses", "refinement_status", "timing_status_text", "trajectory_status",
           "with_timing_bias"]

#: A strip's estimated trajectory offset (horizontal or vertical) or drift rate beyond this
#: many times its configured a-priori sigma is a WARN: a 3-sigma event of a navigation solution
#: as accurate as configured (about 1 % of strips horizontally), worth a look at its GNSS.
TRAJECTORY_WARN_FACTOR = 3.0
#: Beyond this many times, an ERROR: the navigation solution is not what is configured (a lost
#: fix, a wrong antenna height, a float solution); corrected points are only as good as the
#: estimate, and the priors, sized for the configured accuracy, hold it back.
TRAJECTORY_ERROR_FACTOR = 6.0


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


def timing_status_text(extrinsic: Extrinsic | None) -> str:
    """The timing bias ``dt`` of a mounting's calibration (``extrinsic``: its block, with the
    timing bias) as the estimate's line says it: ``dt +3.01 +- 0.09 ms`` where estimated,
    ``dt held at 0`` where asked for and the flight could not see it, '' where not asked for
    (or no mounting)."""
    if extrinsic is None or (extrinsic.time_offset_sigma_s is None
                             and not extrinsic.time_offset_note):
        return ""
    return "dt " + timing_text(extrinsic.time_offset_s, extrinsic.time_offset_sigma_s,
                               extrinsic.time_offset_note)


def with_timing_bias(status: StatusSpec, extrinsic: Extrinsic | None) -> StatusSpec:
    """``status`` (``lidarcal: estimate`` or ``lidarcal: sensor frame``) with the timing bias
    of ``extrinsic`` (:func:`timing_status_text`) after its message and in its values
    (``dt``; ``time_offset_s`` and ``time_offset_sigma_s``, s, '' where not estimated;
    ``time_offset_not_estimable``); unchanged where the calibration did not try."""
    text = timing_status_text(extrinsic)
    if not text or extrinsic is None:
        return status
    sep = "; " if status.name == "lidarcal: sensor frame" else ", "
    sigma = extrinsic.time_offset_sigma_s
    return replace(status, message=f"{status.message}{sep}{text}", values={
        **status.values, "dt": text, "time_offset_s": repr(float(extrinsic.time_offset_s)),
        "time_offset_sigma_s": "" if sigma is None else repr(float(sigma)),
        "time_offset_not_estimable": extrinsic.time_offset_note})


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
    steps, last_step = s.clock_steps
    level = WARN if inp.skipped or uncovered or rejected or late or partial or steps else OK
    message = f"{inp.clouds} clouds, {inp.points} points, {inp.poses} poses"
    if steps:
        message += (f"; pose {last_step} ({steps} step(s) back; the old clock's poses "
                    "dropped)")
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
        "poses_left_out": str(s.poses_left_out), "clock_steps_back": str(steps),
        "clouds": str(inp.clouds), "points": str(inp.points),
        "poses": str(inp.poses), "skipped_clouds": str(inp.skipped),
        "last_error": inp.last_error, "queued_jobs": str(queued_jobs),
        "uncovered_points": str(uncovered),
        "uncovered_strips": ",".join(str(i) for i in left_out),
        "late_points": str(late),
        "rejected_strips": ",".join(str(i) for i, _ in rejected),
        "partial_strips": "; ".join(f"{i}: {text}" for i, text in partial.items()),
        "last_rejection": rejected[-1][1] if rejected else ""})


def trajectory_status(result: CalibrationResult,
                      settings: TrajectoryErrorSettings) -> StatusSpec:
    """``lidarcal: trajectory``: the trajectory model (and why, where ``auto`` chose it) and
    each strip's estimated error (docs/method.md section 11), its horizontal and vertical offset
    and drift rate against ``settings``' a-priori sigmas (the navigation accuracy configured):
    WARN beyond :data:`TRAJECTORY_WARN_FACTOR` times, ERROR beyond
    :data:`TRAJECTORY_ERROR_FACTOR` times, naming the strip (and the biases not estimated,
    which the strips' offsets take up where they are flagged). OK with the trajectory as
    exact."""
    values = {"model": result.trajectory_choice,
              "warn_factor": f"{TRAJECTORY_WARN_FACTOR:g}",
              "error_factor": f"{TRAJECTORY_ERROR_FACTOR:g}"}
    est = result.trajectory
    if est is None:
        return StatusSpec(OK, "lidarcal: trajectory",
                          f"taken as exact ({result.trajectory_choice})", values)
    level, worst, flagged = OK, 0.0, []
    for sid in sorted(est.strips):
        se = est.strips[sid]
        values[f"strip_{sid}"] = _strip_error_text(se)
        for what, size, sigma, key in _strip_error_sizes(se, settings):
            ratio = size / sigma
            worst = max(worst, ratio)
            if ratio > TRAJECTORY_WARN_FACTOR:
                error = ratio > TRAJECTORY_ERROR_FACTOR
                level = max(level, ERROR if error else WARN)
                unit = "cm/s" if what == "drift" else "cm"
                flagged.append(
                    f"strip {sid}: trajectory {what} {size * 100:.1f} {unit}, more than "
                    f"{TRAJECTORY_ERROR_FACTOR if error else TRAJECTORY_WARN_FACTOR:g}x the "
                    f"{sigma * 100:g} {unit} configured ({key}): a GNSS problem?")
    values["largest_ratio"] = f"{worst:.2f}"
    values["largest_offset_m"] = f"{est.largest_offset_m():.4f}"
    if flagged:
        message = "; ".join(flagged)
        held = [name for name, st in result.solution.status.items()
                if st.state == ParameterState.NOT_ESTIMABLE]
        if held:  # (docs/method.md section 11: a lever arm held fixed is a shift of each strip)
            message += (f" (or the biases not estimated, {', '.join(held)}, held at their "
                        "fixed values and taken up by the strips' offsets)")
    else:
        message = (f"{len(est.strips)} strips' errors within {TRAJECTORY_WARN_FACTOR:g}x the "
                   f"navigation accuracy configured (largest offset "
                   f"{est.largest_offset_m() * 100:.1f} cm; {result.trajectory_choice})")
    return StatusSpec(level, "lidarcal: trajectory", message, values)


def _strip_error_sizes(se: StripError, settings: TrajectoryErrorSettings
                       ) -> list[tuple[str, float, float, str]]:
    """(what, size, a-priori sigma, configuration key) of a strip's horizontal offset, vertical
    offset and drift rate (m, m/s)."""
    key = "calibration.trajectory."
    out = [("horizontal offset", float(np.hypot(se.offset[0], se.offset[1])),
            settings.offset_sigma_horizontal_m, key + "offset_sigma_horizontal_m"),
           ("vertical offset", abs(float(se.offset[2])), settings.offset_sigma_vertical_m,
            key + "offset_sigma_vertical_m")]
    if se.drift is not None:
        out.append(("drift", float(np.max(np.abs(se.drift))), settings.drift_sigma_m_per_s,
                    key + "drift_sigma_m_per_s"))
    return out


def _strip_error_text(se: StripError) -> str:
    """A strip's error in words: offset E N U +- sigma (cm), drift (cm/s)."""
    o, s = se.offset * 100, se.offset_sigma * 100
    text = (f"offset E {o[0]:+.1f} N {o[1]:+.1f} U {o[2]:+.1f} cm (+- {s[0]:.1f} {s[1]:.1f} "
            f"{s[2]:.1f}) at t {se.t_ref:.1f} s")
    if se.drift is not None:
        d = se.drift * 100
        text += f", drift {d[0]:+.2f} {d[1]:+.2f} {d[2]:+.2f} cm/s"
    return text
