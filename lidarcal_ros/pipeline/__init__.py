"""The procedures the CLI and the nodes both drive.

Batch (``lidarcal calibrate``, ``lidarcal correct``) and streaming (the nodes) call the same
functions here, which call :mod:`lidarcal_ros.core` for numerics and :mod:`lidarcal_ros.io` for
data, so the two cannot drift apart.

Calibration: :mod:`.calibration` (load a mission, calibrate, summaries, simulate to files),
:mod:`.streaming` (strip by strip, with :mod:`.stream_inputs` and :mod:`.stream_checkpoint`),
:mod:`.calibration_service` and :mod:`.calibrator_statuses` (the calibrator node's jobs and
statuses, ROS-free). Correction: :mod:`.correction` (a set of points), :mod:`.corrected_cloud`
(the corrected rows), :mod:`.correction_batch` and :mod:`.stream_corrector` (chunk by chunk),
:mod:`.bag_correction` (``lidarcal correct``) and :mod:`.trajectory_gate`,
:mod:`.live_corrector`, :mod:`.cloud_backlog`, :mod:`.correction_service` and
:mod:`.correction_process` (the corrector node's side, ROS-free),
:mod:`.reflectance`. Import: :mod:`.importer` and its ``import_*`` parts. QA:
:mod:`.evaluation`, :mod:`.report` and its ``report_*`` parts. :mod:`.replay` paces a bag.
"""

# --- exports (generated from the modules' __all__; test/test_exports.py checks) ---
from lidarcal_ros.exports import lazy_exports

_EXPORTS = {
    "bag_correction": (
        "CorrectOptions", "CorrectionReport", "FOREIGN_OUTPUT_SUFFIXES", "LAS_RUN_POINTS",
        "correct_bag", "output_kind", "warm_up_compiled_loops",
    ),
    "calibration": (
        "Truth", "calibrate_mission", "convergence_warning", "format_agreement",
        "format_report", "load_mission", "parse_biases", "qa_level", "simulation_paths",
        "trajectory_lines", "truth_document", "unused_control", "write_simulation",
    ),
    "calibration_service": (
        "AddCloud", "AddPose", "CalibrationService", "CalibratorOptions", "Job",
        "REQUEST_TIMEOUT_S", "ReadControlFile", "Reset", "SAVE_CONVERGE_S",
        "SHUTDOWN_CONVERGE_S", "Save", "SetConfig", "SetControl", "SetOptions", "Solve",
        "UPDATE_PERIOD_S",
    ),
    "calibrator_statuses": (
        "InputCounts", "ServiceCounts", "TRAJECTORY_ERROR_FACTOR", "TRAJECTORY_WARN_FACTOR",
        "operating_statuses", "refinement_status", "trajectory_status",
    ),
    "cloud_backlog": (
        "MAX_PUSH_POINTS", "Region", "TRAJECTORY_MARGIN_S", "WaitingCloud", "WaitingClouds",
        "take_ready",
    ),
    "corrected_cloud": (
        "ADDED_FIELDS", "CloudTally", "CorrectedColumns", "CorrectionStats", "INCIDENCE_RULES",
        "NO_ROWS", "RowTarget", "build_corrected", "corrected_dtype", "row_target",
    ),
    "correction": (
        "CorrectionSettings", "NormalsFit", "ServedFrames", "UNCORRECTED_WARNINGS",
        "UNCORRECTED_WARNING_S", "UncorrectedWarnings", "correct_cloud", "correct_columns",
        "flagged_geometry", "served_frames", "surface_points", "trajectory_heading",
    ),
    "correction_batch": (
        "BatchResult", "CorrectionBatch", "HeldCloud", "OutputPlacer", "cloud_volume",
        "deliver_normals", "run_batch",
    ),
    "correction_process": ("CorrectionProcess", "InboundRegion"),
    "correction_service": (
        "CorrectedMessage", "CorrectionEngine", "ErrorHandler", "LocalCorrection",
        "MessagePlacer", "RING_BYTES", "ResultHandler", "ServiceOptions", "warm_up_engine",
    ),
    "evaluation": (
        "CheckPointResidual", "Evaluation", "PairAlignment", "corrected_strips",
        "evaluate_mission", "format_evaluation",
    ),
    "import_options": (
        "ImportOptions", "RETURNS", "Returns", "TRAJECTORY_TIMES", "TrajectoryTime",
    ),
    "import_points": (
        "POINT_DTYPE", "PointsFrame", "PointsRead", "Progress", "RunStore", "SourceSpan",
        "header_time_base", "merged_windows", "points_frame", "read_points",
    ),
    "import_report": ("ImportReport",),
    "import_strips": ("StripAssembly", "StripMap", "StripSummary", "assemble_strips"),
    "import_time_bases": (
        "TIME_BASE_NAMES", "TimeRule", "gps_week_of_creation", "points_time_base",
        "reconcile_times", "trajectory_readings", "unwrap_week",
    ),
    "import_trajectory": (
        "BagTrajectory", "DeliveredTrajectory", "check_coverage", "model_note",
        "read_delivered_trajectory", "trajectory_from_file", "trajectory_from_rays",
    ),
    "import_writer": ("BagWritten", "write_bag"),
    "importer": ("import_mission",),
    "live_corrector": (
        "CorrectorOptions", "CorrectorStats", "LiveCorrector", "POSES_PER_HANDOVER",
    ),
    "reflectance": (
        "TARGET_MARGIN_M", "TARGET_MAX_INCIDENCE_DEG", "TargetMeasurement", "measure_target",
        "measure_target_in_bag", "measure_target_on_mission", "relative_settings", "target_of",
        "trusted_in_box", "with_constant",
    ),
    "replay": (
        "Message", "Pacer", "ReplayStats", "ReplayWindow", "SubscriberWait", "iter_window",
        "replay_window", "wait_for_subscribers",
    ),
    "report": (
        "ReportInputs", "build_report", "evaluation_section", "geometric_sections",
        "quality_assessment", "read_evaluation", "report_mission", "trajectory_section",
    ),
    "report_block": (
        "BlockPass", "EXCLUDED_FLAGS", "FOOTPRINT_CELL_M", "MAP_MAX_CELLS",
        "MAP_STRIP_SPACINGS", "SWATH_CELL_SPACINGS", "SWATH_MAX_CELLS", "StripFootprint",
        "TRAJECTORY_MAP_POINTS", "block_grids", "block_pass", "cell_sums", "flight_map",
        "time_text",
    ),
    "report_calibration": ("ReportCalibration", "read_report_calibration"),
    "report_provenance": ("configuration_table", "describe_inputs"),
    "report_radiometry": (
        "MIN_CLASS_POINTS", "SLOPE_CLASS_EDGES_DEG", "mean_raster", "radiometry_section",
        "slope_class_statistics",
    ),
    "stream_checkpoint": (
        "CHECKPOINT_VERSION", "ModelState", "StreamCheckpoint", "read_checkpoint",
        "write_checkpoint",
    ),
    "stream_corrector": ("DEFAULT_BATCH_POINTS", "StreamCorrector", "iter_corrected"),
    "stream_inputs": (
        "BYTES_PER_HELD_POINT", "FIRST_AUTO_CELL_M", "MAX_AUTO_CELL_M", "OpenStrip",
        "OpenStrips", "TrajectorySamples", "default_point_budget",
    ),
    "stream_models": ("ModelCalibrators",),
    "streaming": ("StreamingCalibration",),
    "strip_coverage": ("HOLE_FRACTION", "JOIN_S", "MIN_HOLE_S", "StripCoverage"),
    "throttled_log": ("ThrottledLog",),
    "trajectory_gate": ("REACH_SAMPLES", "RereadBag", "TrajectoryGate"),
}
__getattr__, __dir__, __all__ = lazy_exports(__name__, _EXPORTS)
# --- end of exports ---
