"""Input/output: PointCloud2 bytes, MCAP bags, calibration, configuration and control files."""

# --- exports (generated from the modules' __all__; test/test_exports.py checks) ---
from lidarcal_ros.exports import lazy_exports

_EXPORTS = {
    "bag_format": (
        "NS_PER_SECOND", "ODOMETRY", "POINTCLOUD2", "POSE_STAMPED", "add_standard_types",
        "empty_typestore", "make_qos", "normalize_msgtype", "ns_to_seconds", "seconds_to_ns",
        "stamp_seconds", "standard_typestore",
    ),
    "bag_reader": ("BagReader", "ReadableMcap", "TopicInfo", "open_bag"),
    "bag_recovery": ("RecoveredBag", "bag_files", "recover_bag"),
    "bag_writer": ("BagWriter",),
    "calibration_file": (
        "CalibrationRecord", "ROOT_KEY", "calibration_document", "read_calibration",
        "read_trajectory_block", "trajectory_document", "write_calibration",
    ),
    "cloud_columns": (
        "COORDINATE_WARNING_FRACTION", "CloudColumns", "DEFAULT_COORDINATE_TOLERANCE_M",
        "TIME_ALIASES", "extract_columns", "extract_xyz", "float32_step", "float32_warning",
        "resolve_time_field", "time_span",
    ),
    "config_file": ("flatten", "load_flight_config", "read_parameters_file", "warn_undeclared"),
    "control": ("COLUMNS", "MAX_COORDINATE_M", "read_control_csv", "write_control_csv"),
    "digest": ("total_size",),
    "dsm_file": ("read_dsm",),
    "html_elements": (
        "FigureRenderer", "Progress", "escape", "facts_table", "html_section", "html_table",
        "note",
    ),
    "html_report": ("figure_ids", "render_html", "write_html_report"),
    "las": (
        "ADJUSTED_GPS_OFFSET", "EXTRA_DIMENSIONS", "GPS_EPOCH_UNIX", "LasChunkWriter",
        "LasStats", "SCALE_M", "adjusted_gps_to_unix", "leap_seconds", "parse_crs",
        "unix_to_adjusted_gps",
    ),
    "las_kernels": (
        "INTENSITY_FLOAT", "INTENSITY_NONE", "INTENSITY_U16", "INTENSITY_U8", "fill_records",
        "rows_to_write",
    ),
    "las_reader": (
        "CHUNK_POINTS", "GpsTimeType", "LasChunk", "LasFileError", "LasFileInfo", "crs_units",
        "inspect_las", "iter_las_chunks", "quiet_laspy_errors",
    ),
    "mcap_chunk_copy": (
        "COPYABLE_COMPRESSIONS", "ChunkCopy", "CopiedChannel", "adopt_and_copy",
        "plan_chunk_copy",
    ),
    "mcap_chunk_reader": ("chunk_messages", "in_time_order"),
    "mcap_chunk_writer": (
        "BagWriterBackend", "CHUNK_BYTES", "ThreadedMcapStorage", "ZSTD_LEVEL",
        "chunk_index_record", "compress_parts",
    ),
    "mission_bag": ("read_mission", "strip_point_array", "time_chunk_bounds", "write_mission_bag"),
    "output_files": (
        "EXISTS", "check_output", "os_reason", "remove_quietly", "temporary_beside",
        "write_text",
    ),
    "plan_file": ("read_flight_plan",),
    "pointcloud": (
        "DATATYPE_NAMES", "DATATYPE_TO_NUMPY", "FLOAT32", "FLOAT64", "FieldTuple", "INT16",
        "INT32", "INT8", "NUMPY_TO_DATATYPE", "UINT16", "UINT32", "UINT8",
        "array_to_cloud_parts", "cloud_dtype", "cloud_to_array", "make_point_dtype",
        "point_fields",
    ),
    "pointcloud_kernels": ("all_finite_xyz", "finite_range", "gather_columns", "gather_xyz"),
    "prefetch": ("WriteBehind", "prefetched"),
    "report_content": (
        "BiasEntry", "EvaluationSection", "FlightMap", "InputFile", "MapRaster", "PairSection",
        "Provenance", "RadiometrySection", "ReportContent", "SlopeClass", "StripRow",
        "TrajectorySection",
    ),
    "report_figures": (
        "DIFFERENCE_CMAP", "FIGURE_DPI", "PAIR_POINTS_PER_CELL", "correlation_figure",
        "flight_map_figure", "new_figure", "pair_figure", "pair_limit_cm", "png_base64",
        "reflectance_figure", "swath_figure", "vmr_figure",
    ),
    "report_sections": (
        "block_html", "calibration_html", "control_html", "evaluation_html", "pairs_html",
        "provenance_html", "quality_html", "radiometry_html", "summary_html", "swath_html",
        "trajectory_html",
    ),
    "ros_messages": (
        "CloudMessage", "ESTIMATE_COLUMN_LABEL", "ESTIMATE_ROWS", "ESTIMATE_ROW_LABEL",
        "Estimate", "LEVEL_NAMES", "StatusSpec", "calibration_yaml", "cloud_cdr",
        "cloud_cdr_parts", "cloud_header_cdr", "deserialize", "estimate_matrix",
        "estimate_row_label", "estimate_status", "flatten_values", "geometry_status",
        "is_dense_byte", "pair_level", "parse_cloud", "parse_estimate", "qa_statuses",
        "qa_summary", "serialize", "stamp_ns", "typestore", "warm_up_cloud_codec",
        "worst_level",
    ),
    "shared_ring": ("SharedRing",),
    "strip_accumulator": ("StripAccumulator", "is_nondecreasing"),
    "trajectory_crs": ("make_transformer", "map_heading", "map_orientation", "project"),
    "trajectory_files": (
        "SBET_DTYPE", "SBET_FIELDS", "SBET_RECORD_BYTES", "TIME_BASES", "TimeBase",
        "TrajectoryFile", "TrajectoryFileError", "WEEK_S", "gps_to_unix", "gps_week_of_unix",
        "read_ascii_trajectory", "read_sbet", "read_trajectory_file", "to_gps_seconds",
        "write_ascii_trajectory", "write_sbet",
    ),
    "trajectory_messages": (
        "TRAJECTORY_TYPES", "TrajectorySamples", "moved_message", "trajectory_sample",
    ),
    "yaml_file": ("read_yaml",),
}
__getattr__, __dir__, __all__ = lazy_exports(__name__, _EXPORTS)
# --- end of exports ---
