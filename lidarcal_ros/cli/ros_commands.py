"""The ROS subcommands of ``lidarcal``: ``replay``, ``run`` and ``record``.

Each confines DDS to this machine
(:func:`lidarcal_ros.ros.environment.configure_ros_environment`) before rclpy is imported, turns
SIGINT and SIGTERM into a clean stop (exit status 0, no traceback) and passes ``--ros-args ...``
through to rclpy (remappings, ``-p``, ``--params-file``).
"""

from __future__ import annotations

import argparse
import itertools
import math
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from lidarcal_ros.cli.common import add_bag_argument, finite_float, other_paths
from lidarcal_ros.errors import ConfigError
from lidarcal_ros.io.output_files import check_output

__all__ = [
    "NODE_CHOICES", "add_record_arguments", "add_record_command", "add_replay_arguments",
    "add_replay_command", "add_run_arguments", "add_run_command", "check_ros_parameters",
    "cmd_record", "cmd_replay", "cmd_run", "supervise",
]


def _ros_argv(ros_args: list[str] | None, extra: list[str] | None = None) -> list[str]:
    args = list(extra or []) + list(ros_args or [])
    return ["lidarcal", "--ros-args", *args] if args else ["lidarcal"]


def _start_ros(argv: list[str]) -> tuple[Any, Any]:
    """Confine DDS, initialise a context with our own signal handling."""
    from lidarcal_ros.ros.environment import configure_ros_environment

    configure_ros_environment()
    from lidarcal_ros.nodes.process import start_ros

    return start_ros(argv)


# ---------------------------------------------------------------------------- replay
def add_replay_arguments(p: argparse.ArgumentParser) -> None:
    """The arguments of ``lidarcal replay`` (times in seconds)."""
    add_bag_argument(p)
    p.add_argument("--rate", type=finite_float, default=1.0,
                   help="speed factor of the original timing (default 1; 10 = ten times faster)")
    p.add_argument("--loop", action="store_true", help="start again at the end (Ctrl-C stops)")
    p.add_argument("--clock", action="store_true",
                   help="publish the bag time on /clock (for nodes with use_sim_time)")
    p.add_argument("--clock-hz", type=finite_float, default=40.0,
                   help="/clock messages per wall second (default 40)")
    p.add_argument("--start", type=finite_float, default=0.0,
                   help="start this many seconds after the bag's first message")
    p.add_argument("--duration", type=finite_float, default=None,
                   help="replay this many seconds of the bag (default: to the end)")
    p.add_argument("--topics", nargs="+", default=None, metavar="TOPIC",
                   help="replay only these topics (default: all)")
    p.add_argument("--queue", type=int, default=None,
                   help="keep-last depth of every publisher (default: each topic's 2 s of "
                   "messages at the replay's rate, 100 to 10000: a 100 Hz Odometry at "
                   "--rate 10 keeps 2000)")
    p.add_argument("--wait-for-subscribers", type=finite_float, default=30.0, metavar="SECONDS",
                   help="before the first message, wait up to this long until each played "
                   "topic the suite listens to (points, trajectory) has --min-subscribers, no "
                   "new subscriber came for 1 s and a `lidarcal run` seen has its suite up; "
                   "past it, warn naming the topics without subscribers and replay anyway "
                   "(default 30; 0: do not wait)")
    p.add_argument("--no-wait", action="store_true",
                   help="start at once, without waiting for subscribers")
    p.add_argument("--min-subscribers", type=int, default=1, metavar="N",
                   help="subscribers each waited-for topic needs (default 1)")
    p.add_argument("--linger", type=finite_float, default=2.0, metavar="SECONDS",
                   help="keep the publishers this long after the last message (default 2): a "
                   "subscriber still working through its queue loses what it has not taken "
                   "when they go")
    p.add_argument("--delay", type=finite_float, default=0.0, metavar="SECONDS",
                   help="then wait this much longer before the first message (default 0)")
    p.add_argument("--ros-args", dest="ros_args", nargs=argparse.REMAINDER, default=[],
                   help="rclpy arguments (e.g. remappings -r /lidar/points:=/other)")


def cmd_replay(args: argparse.Namespace) -> int:
    """Run ``lidarcal replay`` with the parsed ``args``; its exit status."""
    from lidarcal_ros.io.bag.reader import open_bag
    from lidarcal_ros.pipeline.replay import Pacer, replay, replay_window

    if not (math.isfinite(args.rate) and args.rate > 0):
        raise ConfigError(f"--rate must be a positive number, got {args.rate}")
    if args.queue is not None and args.queue < 1:
        raise ConfigError(f"--queue must be at least 1, got {args.queue}")
    for option, value in (("--delay", args.delay), ("--linger", args.linger)):
        if not (math.isfinite(value) and value >= 0):
            raise ConfigError(f"{option} must be a non-negative number of seconds, got {value}")
    if not (math.isfinite(args.wait_for_subscribers) and args.wait_for_subscribers >= 0):
        raise ConfigError("--wait-for-subscribers must be a non-negative number of seconds, "
                          f"got {args.wait_for_subscribers}")
    if args.min_subscribers < 1:
        raise ConfigError(f"--min-subscribers must be at least 1, got {args.min_subscribers}")
    with open_bag(args.bag) as bag:
        if args.topics:
            unknown = [t for t in args.topics if t not in bag.topics]
            if unknown:
                raise ConfigError(f"{args.bag}: topic(s) {', '.join(unknown)} not in the bag; "
                                  f"topics present: {', '.join(bag.topics) or 'none'}")
        window = replay_window(bag.start_ns, bag.end_ns, start_s=args.start,
                               duration_s=args.duration)
        context, shutdown = _start_ros(_ros_argv(args.ros_args))
        from lidarcal_ros.nodes.player import PlayerNode

        node = None
        try:
            node = PlayerNode(bag, topics=args.topics, queue=args.queue, rate=args.rate,
                              clock=args.clock, context=context)
            pacer = Pacer(args.rate, clock=node.publish_clock if args.clock else None,
                          clock_hz=args.clock_hz, wait=shutdown.event.wait)
            if not args.no_wait and args.wait_for_subscribers > 0:
                _wait_for_suite(node, args, shutdown)
            if args.delay > 0 and not shutdown.requested:
                shutdown.event.wait(args.delay)
            topics = node.topics
            print(f"replaying {args.bag}: {window.duration_s:.1f} s of bag time at rate "
                  f"{args.rate:g} ({', '.join(topics)})", flush=True)
            stats = replay(lambda: bag.messages(topics), node.publish, window, pacer,
                           latched=node.latched, loop=args.loop,
                           stop=lambda: shutdown.requested)
            node.wait_for_all_acked(5.0)
            # Fast DDS drops the samples of a writer that goes away which a reader has
            # received but its node not yet taken: a busy subscriber would lose the tail.
            if args.linger > 0 and not shutdown.requested:
                shutdown.event.wait(args.linger)
            state = "interrupted" if stats.interrupted else "done"
            print(f"{state}: {stats.messages} messages in {stats.wall_s:.1f} s "
                  f"({stats.passes} pass{'es' if stats.passes != 1 else ''}, "
                  f"largest delay behind schedule {stats.max_lateness_s * 1000:.0f} ms"
                  + (f", {stats.clock_messages} /clock messages" if args.clock else "")
                  + ")", flush=True)
        finally:
            if node is not None:
                node.destroy_node()
            context.try_shutdown()
            shutdown.restore()
    return 0


def _wait_for_suite(node: Any, args: argparse.Namespace, shutdown: Any) -> None:
    """Wait for the subscribers of the topics the suite listens to (``--wait-for-subscribers``)
    and say in one line what was found, or warn naming what was not (then replay anyway:
    ``ros2 bag play`` plays without subscribers too, and the calibrator names the strips it
    saw only in part)."""
    waited = node.wait_topics()
    outcome = node.wait_for_subscribers(args.wait_for_subscribers,
                                        minimum=args.min_subscribers, topics=waited,
                                        stop=lambda: shutdown.requested)
    if outcome.stopped:
        return
    found = ", ".join(f"{t} ({n})" for t, n in sorted(outcome.counts.items()))
    if outcome.ready:
        suite = "; lidarcal run's suite up" if node.suite_seen else ""
        print(f"lidarcal replay: subscribers found after {outcome.waited_s:.1f} s: "
              f"{found or 'no topic to wait for'}{suite}", flush=True)
        return
    short = []
    if outcome.missing:
        short.append(f"fewer than {args.min_subscribers} subscriber(s) on "
                     f"{', '.join(outcome.missing)}")
    if outcome.suite_starting:
        short.append(f"lidarcal run's suite not up ({node.suite_waiting_for()})")
    print(f"lidarcal replay: warning: after {args.wait_for_subscribers:g} s "
          f"(--wait-for-subscribers), {'; '.join(short)}; replaying anyway", file=sys.stderr,
          flush=True)


# ---------------------------------------------------------------------------- run
NODE_CHOICES = ("flight_config", "calibrator", "corrector")


def add_run_arguments(p: argparse.ArgumentParser) -> None:
    """The arguments of ``lidarcal run``."""
    p.add_argument("--config", type=Path,
                   help="flight configuration (ROS 2 parameters file), for every node")
    p.add_argument("--control", type=Path, help="control points CSV id,x,y,z")
    p.add_argument("--nodes", default=",".join(NODE_CHOICES),
                   help="comma-separated nodes to start (default: all three)")
    p.add_argument("--record", type=Path, metavar="OUT",
                   help="also record the output topics to this bag (.mcap or directory)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --record bag")
    p.add_argument("--single-process", action="store_true",
                   help="run the nodes in this process (one executor) instead of one process "
                   "each")
    p.add_argument("--threads", type=int, default=4,
                   help="executor threads with --single-process (default 4)")
    p.add_argument("--ros-args", dest="ros_args", nargs=argparse.REMAINDER, default=[],
                   help="rclpy arguments passed to every node (-p, -r, --params-file, ...)")


def check_ros_parameters(ros_args: list[str]) -> None:
    """Read the parameters ``--ros-args`` gives the nodes as ``--config`` reads its file,
    before anything starts: a bad value ends with one line naming it; parameters that no
    node declares (which the nodes would ignore: a misspelt key keeps its default) are named
    in one warning line per file, and one for the ``-p`` ones."""
    from lidarcal_ros.core.config import undeclared
    from lidarcal_ros.io.config_file import load_flight_config, warn_undeclared

    given: list[str] = []
    for option, value in itertools.pairwise(ros_args):
        if option == "--params-file":
            load_flight_config(value)
        elif option in ("-p", "--param") and ":=" in value:
            given.append(value.split(":=", 1)[0])
    warn_undeclared("--ros-args -p", undeclared(given))


def cmd_run(args: argparse.Namespace) -> int:
    """Run ``lidarcal run`` with the parsed ``args``; its exit status."""
    from lidarcal_ros.io.config_file import load_flight_config

    started = time.monotonic()  # (the ready line's seconds)
    names = [n.strip() for n in args.nodes.split(",") if n.strip()]
    unknown = [n for n in names if n not in NODE_CHOICES]
    if unknown or not names:
        raise ConfigError(f"--nodes: unknown node(s) {', '.join(unknown) or '(none)'}; "
                          f"choose from {', '.join(NODE_CHOICES)}")
    extra: list[str] = []
    if args.config is not None:
        load_flight_config(args.config)  # one-line reason before anything starts
        extra += ["--params-file", str(args.config)]
    check_ros_parameters(args.ros_args)
    if args.control is not None:
        from lidarcal_ros.io.survey.control import read_control_csv

        read_control_csv(args.control)
        extra += ["-p", f"calibration.control_points_file:={args.control.resolve()}"]
    if args.record is not None:
        check_output(args.record, overwrite=args.overwrite, inputs=other_paths(args, "record"),
                     directory=args.record.suffix != ".mcap")

    from lidarcal_ros.ros.environment import configure_ros_environment

    configure_ros_environment()
    argv = _ros_argv(args.ros_args, extra)
    if args.single_process:
        return _run_in_process(names, argv, args, started)
    commands = [[sys.executable, "-m", f"lidarcal_ros.nodes.{name}", *argv[1:]]
                for name in names]
    if args.record is not None:
        commands.append([sys.executable, "-m", "lidarcal_ros", "record", "-o",
                         str(args.record), *(["--overwrite"] if args.overwrite else []),
                         *(["--ros-args", *args.ros_args] if args.ros_args else [])])
    return _supervise_suite(commands, names, started)


def _node_names(choices: list[str]) -> list[str]:
    """The ROS node names of ``choices`` (of :data:`NODE_CHOICES`)."""
    from lidarcal_ros.core.config import CALIBRATOR_NODE, CORRECTOR_NODE, FLIGHT_CONFIG_NODE

    names = {"flight_config": FLIGHT_CONFIG_NODE, "calibrator": CALIBRATOR_NODE,
             "corrector": CORRECTOR_NODE}
    return [names[c] for c in choices]


def _announce(line: str) -> None:
    print(line, flush=True)


def _supervise_suite(commands: list[list[str]], names: list[str], started: float) -> int:
    """:func:`supervise` the node processes, watching from this process (a
    :class:`~lidarcal_ros.nodes.suite.SuiteMonitor` of its own context, no ``--ros-args``)
    when they are up."""
    import rclpy
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.signals import SignalHandlerOptions

    from lidarcal_ros.nodes.suite import SuiteMonitor

    context = Context()
    rclpy.init(args=["lidarcal"], context=context,
               signal_handler_options=SignalHandlerOptions.NO)
    monitor = SuiteMonitor(_node_names(names), started=started,
                           announce=_announce, context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(monitor)
    try:
        return supervise(commands, tick=lambda seconds: executor.spin_once(
            timeout_sec=seconds))
    finally:
        executor.shutdown()
        monitor.destroy_node()
        context.try_shutdown()


def _run_in_process(names: list[str], argv: list[str], args: argparse.Namespace,
                    started: float) -> int:
    from lidarcal_ros.nodes.process import run_main
    from lidarcal_ros.nodes.suite import SuiteMonitor

    factories: list[Any] = []
    if "flight_config" in names:
        from lidarcal_ros.nodes.flight_config import FlightConfigNode

        factories.append(FlightConfigNode)
    if "calibrator" in names:
        from lidarcal_ros.nodes.calibrator import CalibratorNode

        factories.append(CalibratorNode)
    if "corrector" in names:
        from lidarcal_ros.nodes.corrector import CorrectorNode

        factories.append(CorrectorNode)
    if args.record is not None:
        from lidarcal_ros.nodes.recorder import RecorderNode

        out, overwrite = args.record, args.overwrite
        factories.append(lambda context: RecorderNode(out, overwrite=overwrite,
                                                      context=context))
    suite = _node_names(names)
    factories.append(lambda context: SuiteMonitor(suite, started=started, announce=_announce,
                                                  context=context))
    return run_main(factories, argv, threads=args.threads)


def supervise(commands: list[list[str]], *, grace_s: float = 15.0,
              tick: Callable[[float], Any] | None = None) -> int:
    """Run ``commands`` as child processes until SIGINT / SIGTERM or until one ends.

    ``tick(seconds)`` (e.g. an executor's ``spin_once``) is called in the loop instead of
    sleeping between looks at the children.

    A signal is passed on to every child as SIGTERM (Ctrl-C in a terminal reaches them
    directly too); when a child ends on its own, the others are stopped. Children still running
    ``grace_s`` after being asked to stop are killed. Returns 0 when the suite was stopped by a
    signal and every child exited cleanly, else the first non-zero child status.
    """
    import signal
    import subprocess

    from lidarcal_ros.nodes.process import Shutdown

    shutdown = Shutdown().install()
    procs = []
    names: dict[int, str] = {}
    try:
        for cmd in commands:
            procs.append(subprocess.Popen(cmd))
            names[procs[-1].pid] = " ".join(cmd[2:4])
        first_exit: int | None = None
        while not shutdown.requested:
            codes = [p.poll() for p in procs]
            ended = [c for c in codes if c is not None]
            if ended:
                first_exit = next((c for c in ended if c != 0), ended[0])
                print(f"lidarcal run: a node exited with status {ended[0]}; stopping the "
                      "others", file=sys.stderr)
                break
            if tick is not None:
                tick(0.2)
            else:
                shutdown.event.wait(0.2)
        for p in procs:
            if p.poll() is None:
                p.send_signal(signal.SIGTERM)
        deadline = time.monotonic() + grace_s
        status = 0 if first_exit is None else first_exit
        for p in procs:
            try:
                code = p.wait(timeout=max(deadline - time.monotonic(), 0.1))
            except subprocess.TimeoutExpired:
                p.kill()
                code = p.wait()
                print(f"lidarcal run: {names[p.pid]} did not stop in {grace_s:.0f} s; "
                      "killed", file=sys.stderr)
            if code not in (0, -signal.SIGTERM, -signal.SIGINT) and status == 0:
                status = code if code > 0 else 1
        return status
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.wait()
        shutdown.restore()


# ---------------------------------------------------------------------------- record
def add_record_arguments(p: argparse.ArgumentParser) -> None:
    """The arguments of ``lidarcal record`` (duration in seconds)."""
    p.add_argument("-o", "--output", required=True, type=Path,
                   help="output bag: .mcap file or rosbag2 directory")
    p.add_argument("--topics", nargs="+", default=None, metavar="TOPIC",
                   help="topics to record (default: corrected points, estimate, calibration "
                   "YAML, diagnostics)")
    p.add_argument("--duration", type=finite_float, default=None,
                   help="stop after this many seconds (default: until Ctrl-C / SIGTERM)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output")
    p.add_argument("--ros-args", dest="ros_args", nargs=argparse.REMAINDER, default=[],
                   help="rclpy arguments")


def cmd_record(args: argparse.Namespace) -> int:
    """Run ``lidarcal record`` with the parsed ``args``; its exit status."""
    check_output(args.output, overwrite=args.overwrite, directory=args.output.suffix != ".mcap",
                 inputs=other_paths(args, "output"))
    if args.duration is not None and not (math.isfinite(args.duration) and args.duration > 0):
        raise ConfigError(f"--duration must be a positive number of seconds, got "
                          f"{args.duration}")
    context, shutdown = _start_ros(_ros_argv(args.ros_args))
    from lidarcal_ros.nodes.process import spin_nodes
    from lidarcal_ros.nodes.recorder import DEFAULT_TOPICS, RecorderNode

    node = None
    timer = None
    try:
        node = RecorderNode(args.output, args.topics or DEFAULT_TOPICS,
                            overwrite=args.overwrite, context=context)
        if args.duration is not None:
            timer = threading.Timer(args.duration, shutdown.event.set)
            timer.daemon = True
            timer.start()
        spin_nodes([node], context, shutdown, threads=2)
    finally:
        if timer is not None:
            timer.cancel()
        if node is not None:
            node.close()
            counts = ", ".join(f"{t}: {n}" for t, n in node.counts.items())
            print(f"recorded to {args.output} ({counts})", flush=True)
            node.destroy_node()
        context.try_shutdown()
        shutdown.restore()
    return 0


# ---------------------------------------------------------------------------- the subcommands
def add_replay_command(sub: Any) -> None:
    """The ``lidarcal replay`` command and its arguments, on the subparsers ``sub``."""
    p = sub.add_parser("replay", help="publish a bag to live topics with its original timing",
                       description="Publish a bag's messages (raw CDR) on their topics with "
                       "the original timing scaled by --rate; --clock publishes /clock for "
                       "nodes with use_sim_time.")
    add_replay_arguments(p)
    p.set_defaults(func=cmd_replay)


def add_run_command(sub: Any) -> None:
    """The ``lidarcal run`` command and its arguments, on the subparsers ``sub``."""
    p = sub.add_parser("run", help="start the node suite (calibrator, corrector, flight config)",
                       description="Start lidarcal_flight_config, lidarcal_calibrator and "
                       "lidarcal_corrector in this process; Ctrl-C or SIGTERM stops them "
                       "cleanly.")
    add_run_arguments(p)
    p.set_defaults(func=cmd_run)


def add_record_command(sub: Any) -> None:
    """The ``lidarcal record`` command and its arguments, on the subparsers ``sub``."""
    p = sub.add_parser("record", help="record live topics (default: the outputs) to MCAP",
                       description="Record topics (raw CDR, with their types and durability) "
                       "into a rosbag2 MCAP bag; Ctrl-C or SIGTERM finishes the bag.")
    add_record_arguments(p)
    p.set_defaults(func=cmd_record)
