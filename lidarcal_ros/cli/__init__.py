"""The ``lidarcal`` command line."""

# --- exports (generated from the modules' __all__; test/test_exports.py checks) ---
from lidarcal_ros.exports import lazy_exports

_EXPORTS = {
    "bag_commands": ("add_import_command", "add_recover_command", "cmd_import", "cmd_recover"),
    "calibration_commands": (
        "add_calibrate_command", "add_evaluate_command", "add_report_command", "cmd_calibrate",
        "cmd_evaluate", "cmd_report",
    ),
    "common": ("add_bag_and_calibration_arguments", "add_quiet_option", "progress_bar"),
    "correction_commands": ("add_correct_command", "cmd_correct"),
    "exit_status": (
        "EXIT_BAD_INPUT", "EXIT_INTERNAL_ERROR", "EXIT_INTERRUPTED", "EXIT_NOTHING_ESTIMATED",
        "EXIT_NOT_CONVERGED", "EXIT_OK", "EXIT_STATUSES", "EXIT_USAGE", "end_process",
        "run_command",
    ),
    "main": ("CommandLogFormatter", "build_parser", "command_log_lines", "console_main"),
    "ros_commands": (
        "NODE_CHOICES", "add_record_arguments", "add_record_command", "add_replay_arguments",
        "add_replay_command", "add_run_arguments", "add_run_command", "check_ros_parameters",
        "cmd_record", "cmd_replay", "cmd_run", "supervise",
    ),
    "simulation_commands": (
        "add_plan_command", "add_simulate_command", "cmd_plan", "cmd_simulate",
    ),
}
__getattr__, __dir__, __all__ = lazy_exports(__name__, _EXPORTS)
# --- end of exports ---
