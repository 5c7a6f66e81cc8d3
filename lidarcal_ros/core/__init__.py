"""Pure numeric core of lidarcal_ros: numpy and scipy only, never rclpy."""

# --- exports (generated from the modules' __all__; test/test_exports.py checks) ---
from lidarcal_ros.exports import lazy_exports

_EXPORTS = {
    "adjustment": (
        "DEFAULT_MAX_SIGMA", "NormalEquations", "ObservabilityLimits", "Observations",
        "ParameterStatus", "REFERENCE_MAGNITUDE", "Solution", "cluster_robust_sigma", "solve",
    ),
    "allocator": (
        "MMAP_THRESHOLD_BYTES", "NODE_TRIM_THRESHOLD_BYTES", "TRIM_THRESHOLD_BYTES",
        "populate_in_background", "tune_allocator",
    ),
    "attitude": (
        "IDENTITY_XYZW", "P_BODY", "attitude_from_quaternions", "body_rotations",
        "body_rotations_from_attitude", "headings_from_quaternions", "interpolated_frames",
        "normalise_quaternions", "pose_on_segment", "quaternions_from_attitude",
        "quaternions_from_headings", "rotation_matrices", "segment_spline", "slerp",
    ),
    "calibrate": (
        "CalibrationSettings", "Calibrator", "Progress", "choose_trajectory_model",
        "with_trajectory_model",
    ),
    "calibration_iteration": (
        "CYCLE_FACTOR", "Convergence", "Iteration", "MatchedSet", "NOISE_Z",
        "SETTLED_MAX_SIGMA", "TrajectoryTerms", "allow_for_shared_errors", "has_converged",
        "judge_convergence", "matching_cycle", "next_threshold", "reexpress_observations",
        "rematching_noise", "robust_solve",
    ),
    "calibration_kernels": ("add_normal_rows", "exact_correction_and_geometry"),
    "calibration_result": (
        "CalibrationResult", "ControlResidual", "NothingEstimated", "PairDiscrepancies",
        "PairStats", "robust_qa",
    ),
    "calibration_threads": ("StageClock", "WorkerPool"),
    "config": (
        "CALIBRATOR_NODE", "CORRECTOR_NODE", "FLIGHT_CONFIG_NODE", "FlightConfig",
        "NODE_PARAMETERS", "ParameterSpec", "ROS_PARAMETERS", "SCHEMA", "check_value",
        "coerce", "cross_check", "float_parameter", "int_parameter", "node_options",
        "parse_target_box", "undeclared",
    ),
    "correction_kernels": (
        "acos_poly", "atan_poly", "bias_offsets", "byte_counts", "correct_returns",
        "fill_corrected_rows",
    ),
    "evaluation": ("AccuracySummary", "RIGID_NAMES", "RigidFit", "rigid_icp", "tin_heights"),
    "exact_model": ("biased_from_pulse", "biased_point_exact", "georeference", "true_pulse"),
    "flags": (
        "FLAG_GRAZING", "FLAG_NOT_CORRECTED", "FLAG_NO_INTENSITY", "FLAG_NO_NORMAL",
        "FLAG_ROUGH", "FLAG_VOLUME",
    ),
    "flight_path": (
        "AXES", "FlightLine", "FlightState", "G_MPS2", "MAX_OFF_NADIR_DEG",
        "REPORTED_CRAB_DEG", "REPORTED_ROUGH_AIR", "RoughAir", "Turbulence",
        "crosswind_for_crab",
    ),
    "geometry": ("LEVEL", "LaserGeometry", "RIGOROUS", "geometry_at"),
    "georeferencing": (
        "LaserVectorQA", "MAX_TILT_DEG", "MIN_ATTITUDE_RATE_HZ", "MODELS", "MODEL_SPAN_PAD_S",
        "ModelChoice", "attitude_segments", "check_model_setting", "choose_model",
        "describe_model_policy", "describe_models", "laser_vector_qa", "models_summary",
        "rigorous_geometry", "strip_geometry",
    ),
    "grid_planes": (
        "CellPlanes", "block_min_spread", "dense_grid_normals", "dense_moment_grid",
        "fit_block_planes", "normals_from_planes", "plane_table", "smallest_eigen",
        "sparse_grid_normals", "typical_residual",
    ),
    "heading": (
        "HEADING_SOURCES", "MAX_CRAB_DEG", "check_orientation", "choose_heading",
        "describe_heading_policy", "describe_heading_use", "median_crab_deg",
        "window_headings", "wrap_angle",
    ),
    "jit": ("JIT_OPTIONS", "compiled", "inlined", "start_without_blas"),
    "landcover": ("Accuracy", "GaussianML", "Raster", "classify_cells", "stratified_split"),
    "local_trajectory": (
        "MIN_DEPTH_M", "WindowLines", "covered_by_trajectory", "geometry_on_lines",
        "laser_geometry", "served_by_trajectory", "window_lines", "windows_cover_points",
    ),
    "local_trajectory_kernels": ("below_line", "sorted_time_windows", "window_geometry"),
    "mission": ("CONFLICT_M", "ControlPoints", "Mission", "Strip", "Trajectory", "screen_samples"),
    "model": (
        "Trig", "add_geometry_normal_rows", "body_columns", "body_normal_rows",
        "boresight_matrix", "correct_geometry", "correct_points", "correct_points_exact",
        "design_matrix", "exact_correction", "geometry_design_matrix", "geometry_normal_rows",
        "geometry_offsets", "normal_design_rows", "point_offsets",
    ),
    "normals": (
        "CELL_SPACINGS", "GridNormals", "MIN_BLOCK_POINTS", "cell_size", "finite_rows",
        "flight_frame", "grid_normals", "mean_spacing", "no_normals",
    ),
    "normals_kernels": (
        "BLOCK_COLUMNS", "accumulate_moments", "cell_planes", "cells_without_plane",
        "centred_sums", "fit_blocks", "fit_sums", "flight_cells", "flight_to_map",
        "point_normals", "smallest_eigen_many",
    ),
    "object_tops": ("COARSE_FACTOR", "Footprints", "NO_OBJECT", "ObjectTops"),
    "overlap_grid": ("OverlapGrid", "PairQA"),
    "params": (
        "ANGLES", "ARCSEC_PER_RAD", "BORESIGHT", "LEVER_ARM", "N_PARAMETERS",
        "PARAMETER_INDEX", "PARAMETER_NAMES", "SI_UNITS", "arcsec_to_rad", "as_dict",
        "as_vector", "display_value", "format_estimate", "format_value",
        "parse_parameter_list", "rad_to_arcsec",
    ),
    "planning": (
        "FlightPlan", "MAX_SIMULATED_DENSITY", "MAX_SIMULATED_POINTS", "PLAN_KEYS",
        "ParameterPrediction", "PlanReport", "SENSOR_KEYS", "TERRAINS", "predict",
    ),
    "quality_level": (
        "Criterion", "LBS_LEVELS", "MIN_NVA_CHECK_POINTS", "QualityAssessment", "QualityLevel",
        "assess",
    ),
    "radiometry": (
        "P0_KPA", "POWER_MODELS", "RAYLEIGH_550_PER_KM", "RadiometricModel", "T0_K",
        "atmospheric_alpha", "constant_from_target", "cos_incidence", "describe_alpha",
        "extinction_coefficient", "kim_q", "power_ratio", "rayleigh_alpha",
        "two_way_transmittance", "volume_returns",
    ),
    "raster_terrain": ("RasterTerrain",),
    "ray_casting": ("RayHits", "cast_rays"),
    "scanning": (
        "INTENSITY_K", "LineScan", "PULSE_BLOCK", "Scanner", "WAVELENGTH_NM",
        "pulse_and_scan_rates", "scan_line", "swath_width", "triangle",
    ),
    "simulate": ("CONTROL_CLEAR_RADIUS_M", "SimulatedMission", "simulate_mission"),
    "simulated_trajectory_errors": (
        "BETWEEN_STRIPS", "StripTrajectoryError", "TRAJECTORY_ERROR_MODEL",
        "draw_trajectory_errors", "read_trajectory_errors", "trajectory_errors_record",
    ),
    "simulation_spec": (
        "DEFAULT_BIASES", "FOV_DEG", "FlightSpec", "HIGH", "LEAD_S", "LINE_ATTITUDE_KEYS",
        "LOW", "NoiseSpec", "OPTION_NAMES", "SCENARIOS", "SPEED_MPS", "SensorSpec",
        "SimulationSpec", "SiteSpec", "TURN_S", "TYPICAL_TRAJECTORY_ERRORS",
        "TrajectoryErrorSpec", "check_biases", "crab_wind", "normalise_lines",
        "scenario_lines",
    ),
    "simulation_truth": (
        "BIAS_CONVENTION", "line_attitude_record", "line_summary", "rough_air_record",
        "truth_config",
    ),
    "strip_blocks": ("StripBlocks", "strip_gram"),
    "strip_matching": ("PairMatcher",),
    "strip_normals": (
        "NormalsTask", "STREAM_START_POINTS", "STREAM_START_SECONDS", "StripNormals",
        "new_moment_grid",
    ),
    "strip_pairs": (
        "FootprintGrid", "PreparedStrip", "StripPair", "find_pair", "footprint_keys",
        "ground_speed", "height_agreement", "no_overlap_reason", "outside_strips",
        "stratified_sample",
    ),
    "surface": (
        "ASPHALT", "CLASS_NAMES", "CLASS_REFLECTANCE", "GRASS", "ROOF", "SOIL", "Surface",
        "TREE",
    ),
    "swath_differences": (
        "BlockGrid", "CellHeights", "DzStatistics", "MAX_CELL_SPREAD_M", "MIN_CELL_POINTS",
        "PairDifference", "SMOOTH_SLOPE_DEG", "SwathDifferences", "cell_heights",
    ),
    "terrain": ("Ground", "LandCover", "PATCH_CELL", "TERRAIN_KINDS", "Terrain"),
    "terrain_objects": (
        "BUILDING_CELL", "Buildings", "ClearTest", "FLAT_ROOF", "GABLE_ROOF", "GroundHeight",
        "HIP_ROOF", "ROOF_TYPE_NAMES", "SHED_ROOF", "TREE_CELL", "Trees",
    ),
    "thinning": ("first_per_cell",),
    "thinning_kernels": ("first_in_cells", "first_in_grid"),
    "tin": ("GridLocator", "PatchMatches", "Tin", "TinQuality", "delaunay", "match_to_tin"),
    "tin_kernels": (
        "best_patches", "grid_lists", "locate_points", "shifted_queries", "tin_quality",
        "triangle_boxes",
    ),
    "trajectory_buffer": ("TrajectoryBuffer",),
    "trajectory_errors": (
        "AUTO_SIGMA0_RATIO", "POSE_BETWEEN_STRIPS", "POSE_BEYOND_STRIPS", "POSE_IN_STRIP",
        "SPLINE_INTERPOLATION", "StripBasis", "StripError", "TrajectoryCorrection",
        "TrajectoryErrorSettings", "TrajectoryEstimate", "TrajectoryModel", "TrajectoryRows",
        "TrajectoryState", "error_columns", "trajectory_corrections",
    ),
    "trajectory_estimation": ("EstimatedTrajectory", "StripEstimate", "estimate_trajectory"),
    "trajectory_fallback": ("level_fallback",),
    "trajectory_rays": ("RayBudget", "RayCollector", "Rays", "rays_from_returns"),
    "trajectory_segments": (
        "EstimateSettings", "SegmentFit", "SegmentQuality", "fit_segment", "flight_problems",
        "grade", "legendre", "segment_edges",
    ),
    "units": (
        "LENGTH_UNITS", "TIME_UNITS", "finite_or_none", "format_cm", "format_number",
        "format_percent", "parse_quantity", "status_value",
    ),
}
__getattr__, __dir__, __all__ = lazy_exports(__name__, _EXPORTS)
# --- end of exports ---
