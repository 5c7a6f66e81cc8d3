"""What several ``lidarcal`` commands share: options, bag and calibration arguments, progress."""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path
from typing import Any

from lidarcal_ros.io.url_cache import source_of

__all__ = ["add_bag_and_calibration_arguments", "add_bag_argument", "add_dask_option",
           "add_quiet_option", "finite_float", "other_paths", "progress_bar"]


def add_dask_option(p: Any) -> None:
    """``--dask local[:N]|tcp://HOST:PORT`` of the commands that can run on a Dask cluster."""
    p.add_argument("--dask", metavar="local[:N]|tcp://HOST:PORT",
                   help="run the work in parts on Dask: local:N starts N worker processes on "
                   "this machine (127.0.0.1 only; local: one per core), tcp://HOST:PORT uses "
                   "a running scheduler whose workers share this command's paths and have "
                   "this package installed (README, 'On a Dask cluster'); the same output")


def finite_float(text: str) -> float:
    """An option's number, refused unless finite: Python's ``float`` reads "nan", "inf" and
    "1e400" (inf) without a word, and none of them is a rate, a span or a size."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"expected a finite number, got {text!r}")
    return value


def add_quiet_option(p: Any) -> None:
    """``-q/--quiet`` of the commands that show progress."""
    p.add_argument("-q", "--quiet", action="store_true",
                   help="no progress bar (it shows only on a terminal anyway)")


def add_bag_argument(p: Any) -> None:
    """The input bag of a command: a path, or a URL kept as given (a Path would fold
    ``s3://`` into ``s3:/``), which the readers fetch."""
    p.add_argument("bag", type=source_of,
                   help="rosbag2 directory or .mcap file: a path, or a URL (s3://, https://...) "
                   "that fsspec reads here (each process reading it keeps a copy: "
                   "docs/interface.md)")


def add_bag_and_calibration_arguments(p: Any) -> None:
    """The arguments of the commands that read a mission bag with a calibration."""
    add_bag_argument(p)
    p.add_argument("--calibration", required=True, type=Path,
                   help="calibration YAML (lidarcal calibrate)")


def other_paths(args: Any, output: str) -> list[Path]:
    """Every path of the parsed ``args`` but the one of the argument ``output``: the inputs
    and other outputs an output must not overwrite (``-o ctl.csv --control ctl.csv``)."""
    paths = []
    for name, value in vars(args).items():
        values = value if isinstance(value, list | tuple) else [value]
        paths += [v for v in values if isinstance(v, Path) and name != output]
    return paths


def progress_bar(enabled: bool) -> tuple[Any, Any]:
    """A tqdm-backed progress callback (stderr; silent when not a terminal) and the function
    closing it."""
    if not enabled:
        return None, lambda: None
    from tqdm import tqdm

    bar = tqdm(total=100, unit="%", file=sys.stderr, leave=False,
               bar_format="{desc:<28} {bar} {elapsed}", disable=None)

    def update(stage: str, fraction: float) -> None:
        bar.set_description_str(stage)
        bar.n = int(round(100 * max(0.0, min(1.0, fraction))))
        bar.refresh()

    return update, bar.close
