"""The exit statuses of ``lidarcal`` and the one line a failed command prints.

:func:`run_command` runs a parsed command and turns what it raises into its exit status and
one line on stderr (``lidarcal COMMAND: error: REASON``); what each status means is in
:data:`EXIT_STATUSES` and the docstring of :mod:`lidarcal_ros.cli.main`.
"""

from __future__ import annotations

import argparse
import atexit
import logging
import os
import signal
import sys
import threading
from types import FrameType
from typing import NoReturn

from lidarcal_ros.errors import LidarcalError, brief

__all__ = [
    "EXIT_BAD_INPUT", "EXIT_INTERNAL_ERROR", "EXIT_INTERRUPTED", "EXIT_NOTHING_ESTIMATED",
    "EXIT_NOT_CONVERGED", "EXIT_OK", "EXIT_STATUSES", "EXIT_TERMINATED", "EXIT_USAGE",
    "Terminated", "end_process", "run_command",
]

logger = logging.getLogger("lidarcal")

EXIT_OK = 0
EXIT_BAD_INPUT = 1
EXIT_USAGE = 2
EXIT_INTERNAL_ERROR = 3
EXIT_NOT_CONVERGED = 4
#: ``calibrate --write-identity`` estimated nothing and wrote a calibration moving no point.
EXIT_NOTHING_ESTIMATED = 5
EXIT_INTERRUPTED = 130
EXIT_TERMINATED = 128 + signal.SIGTERM

#: What each exit status means (``lidarcal --help`` prints this).
EXIT_STATUSES: dict[int, str] = {
    EXIT_OK: "success",
    EXIT_BAD_INPUT: "bad input or an output that cannot be written (one line on stderr)",
    EXIT_USAGE: "usage error",
    EXIT_INTERNAL_ERROR: "internal error (a bug; -vv for the traceback)",
    EXIT_NOT_CONVERGED: "calibrate: the adjustment did not converge (calibration written "
                        "with converged: false, and why)",
    EXIT_NOTHING_ESTIMATED: "calibrate --write-identity: nothing could be estimated "
                            "(calibration written that moves no point)",
    EXIT_INTERRUPTED: "interrupted (SIGINT, Ctrl-C; no output left)",
    EXIT_TERMINATED: "terminated (SIGTERM; no output left)",
}


class Terminated(BaseException):
    """SIGTERM arrived: unwinds the command as Ctrl-C does, so that every output in progress
    is removed on the way out."""


def _raise_terminated(signum: int, frame: FrameType | None) -> None:
    raise Terminated




def _signal_within(exc: BaseException) -> BaseException | None:
    """The Ctrl-C or SIGTERM an exception wraps (a compiled loop's dispatcher reports the
    signal's exception, raised while it ran, as the cause of a SystemError); None if none."""
    seen: set[int] = set()
    cause: BaseException | None = exc
    while cause is not None and id(cause) not in seen:
        if isinstance(cause, KeyboardInterrupt | Terminated):
            return cause
        seen.add(id(cause))
        cause = cause.__cause__ or cause.__context__
    return None


def run_command(args: argparse.Namespace) -> int:
    """Run the command ``args.func`` of the parsed ``args``; its exit status, with what it
    raises told in one line on stderr (a traceback only at ``-vv``, for a bug)."""
    # A batch command's SIGTERM (a job scheduler's stop, `kill`) ends it as Ctrl-C does, not
    # with the default handler's instant death that would leave temporary files behind.
    on_main = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGTERM, _raise_terminated) if on_main else None
    try:
        return int(args.func(args))
    except Terminated:
        print(f"lidarcal {args.command}: terminated", file=sys.stderr)
        return EXIT_TERMINATED
    except LidarcalError as exc:
        print(f"lidarcal {args.command}: error: {brief(str(exc))}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except KeyboardInterrupt:
        print(f"lidarcal {args.command}: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except OSError as exc:  # a file the command reads or writes
        from lidarcal_ros.io.output_files import os_reason

        where = f"{exc.filename}: " if exc.filename else ""
        print(f"lidarcal {args.command}: error: {brief(where + os_reason(exc))}",
              file=sys.stderr)
        return EXIT_BAD_INPUT
    except Exception as exc:  # a bug: still one line, traceback with -vv
        stop = _signal_within(exc)
        if stop is not None:  # the signal, re-raised by numba's dispatcher as SystemError
            word, status = ("terminated", EXIT_TERMINATED) if isinstance(stop, Terminated) \
                else ("interrupted", EXIT_INTERRUPTED)
            print(f"lidarcal {args.command}: {word}", file=sys.stderr)
            return status
        logger.debug("traceback", exc_info=True)
        text = brief(str(exc))
        print(f"lidarcal {args.command}: internal error: {type(exc).__name__}: {text} "
              "(rerun with -vv for the traceback)", file=sys.stderr)
        return EXIT_INTERNAL_ERROR
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)


def end_process(status: int) -> NoReturn:
    """End the ``lidarcal`` process with ``status`` once a command has returned.

    The exit handlers run (logging's flush, multiprocessing's children, coverage, temporary
    directories), then standard output and error are flushed and the process ends without
    the interpreter's teardown: with numba's compiler and the bag libraries loaded, freeing
    every module's objects one by one takes 0.15-0.3 s, a sixth of a one-million-point
    ``lidarcal correct``, and gives the system nothing it does not reclaim at once.
    Where that teardown matters it is kept: a thread that is not a daemon still runs (the
    interpreter waits for it), ROS was started (its participants say goodbye to the others
    as they are destroyed), or a profiler or tracer is attached (``python -m cProfile``
    writes its figures after the program's end).
    """
    others = [t for t in threading.enumerate()
              if t is not threading.main_thread() and not t.daemon and t.is_alive()]
    if others or "rclpy" in sys.modules or sys.getprofile() or sys.gettrace():
        sys.exit(status)
    atexit._run_exitfuncs()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):  # a closed pipe (``lidarcal ... | head``): nothing to do
            pass
    os._exit(status)
