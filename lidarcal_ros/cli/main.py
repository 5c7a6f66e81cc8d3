"""``lidarcal``: the command line's parser and the running of one command.

Each command group is a module of its own beside this one, what they share is
:mod:`~lidarcal_ros.cli.common`. Exit statuses: :data:`~lidarcal_ros.cli.exit_status.EXIT_STATUSES`
and docs/interface.md, "Exit statuses".
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import sys
from collections.abc import Iterator, Sequence
from typing import NoReturn

from lidarcal_ros import __version__
from lidarcal_ros.cli.bag_commands import add_import_command, add_recover_command
from lidarcal_ros.cli.calibration_commands import (
    add_calibrate_command,
    add_evaluate_command,
    add_report_command,
)
from lidarcal_ros.cli.correction_commands import add_correct_command
from lidarcal_ros.cli.exit_status import EXIT_STATUSES, end_process, run_command
from lidarcal_ros.cli.ros_commands import add_record_command, add_replay_command, add_run_command
from lidarcal_ros.cli.simulation_commands import add_plan_command, add_simulate_command
from lidarcal_ros.core.allocator import single_malloc_arena

__all__ = ["CommandLogFormatter", "build_parser", "command_log_lines", "console_main",
           "main"]


def build_parser() -> argparse.ArgumentParser:
    """The ``lidarcal`` argument parser, every command on it."""
    parser = argparse.ArgumentParser(
        prog="lidarcal",
        description="Airborne LiDAR calibration (quasi-rigorous, Habib et al. 2011) and "
                    "radiometric correction for ROS 2.",
        epilog="exit status: " + "; ".join(f"{code} {meaning}"
                                           for code, meaning in EXIT_STATUSES.items()),
    )
    parser.add_argument("--version", action="version", version=f"lidarcal {__version__}")
    parser.add_argument("-v", "--verbose", action="count", default=0,
                        help="more log output (-vv for debug)")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    add_simulate_command(sub)
    add_calibrate_command(sub)
    add_correct_command(sub)
    add_report_command(sub)
    add_replay_command(sub)
    add_run_command(sub)
    add_record_command(sub)
    add_plan_command(sub)
    add_evaluate_command(sub)
    add_import_command(sub)
    add_recover_command(sub)
    return parser


class CommandLogFormatter(logging.Formatter):
    """Log records as ``lidarcal COMMAND: warning: MESSAGE`` lines, like the error line
    (with the logger's name too when verbose)."""

    def __init__(self, command: str, *, names: bool) -> None:
        super().__init__()
        self.prefix = f"lidarcal {command}: "
        self.names = names

    def formatMessage(self, record: logging.LogRecord) -> str:
        """The record's line: the command prefix, the level in lower case, the logger's name when
        verbose, the message."""
        name = f"{record.name}: " if self.names else ""
        return f"{self.prefix}{record.levelname.lower()}: {name}{record.getMessage()}"


@contextlib.contextmanager
def command_log_lines(command: str, verbose: int) -> Iterator[None]:
    """Log records of the command to stderr as :class:`CommandLogFormatter` lines, for the
    command's duration (``main`` may be called more than once in a process)."""
    root = logging.getLogger()
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(CommandLogFormatter(command, names=verbose > 0))
    level = root.level
    root.addHandler(handler)
    root.setLevel(logging.WARNING - 10 * min(verbose, 2))
    try:
        yield
    finally:
        root.removeHandler(handler)
        root.setLevel(level)


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``lidarcal`` console script (exit statuses: docs/interface.md)."""
    parser = build_parser()
    args = parser.parse_args(argv)
    args.argv = list(sys.argv[1:] if argv is None else argv)  # (a report records it)
    with command_log_lines(args.command, args.verbose):
        return run_command(args)


def console_main() -> NoReturn:
    """Entry point of the ``lidarcal`` console script and of ``python -m lidarcal_ros``:
    :func:`main`, then the process ends (:func:`~lidarcal_ros.cli.exit_status.end_process`)."""
    # (the command's threads share one heap: less memory kept, docs/internals.md)
    single_malloc_arena()
    end_process(main())


if __name__ == "__main__":  # pragma: no cover
    console_main()
