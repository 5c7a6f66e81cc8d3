"""``lidarcal import --dask``: each LAS/LAZ file read by a worker into sorted runs, merged here.

A worker reads one file as :func:`~lidarcal_ros.pipeline.importing.points.read_points` reads
it (its points into time-sorted runs spilled into a folder beside the output, which the
workers must share, and its counts, point sources and rays); this process adopts the runs and
merges the rest in the files' order, so the bag written from them is the serial import's.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

from lidarcal_ros.io.survey.las_reader import LasFileInfo
from lidarcal_ros.pipeline.executor import Executor, results_in_turn
from lidarcal_ros.pipeline.importing.options import ImportOptions
from lidarcal_ros.pipeline.importing.points import (
    PointsFrame,
    PointsRead,
    Progress,
    RunStore,
    check_points_read,
    merge_read,
    new_read,
    read_file,
)

__all__ = ["read_in_parts"]


def _read_one(info: LasFileInfo, frame: PointsFrame, options: ImportOptions,
              folder: str) -> PointsRead:
    """One file read (on a worker), its points all spilled as runs under ``folder``."""
    from lidarcal_ros.errors import InputError

    if not os.path.isdir(folder) or not os.path.exists(info.path):
        raise InputError(f"{info.path}: it or {folder} not found on this Dask worker: the "
                         "workers must see the inputs and the output's folder at the same "
                         "paths (a shared file system)")
    store = RunStore(options.memory_points, Path(folder))
    read = new_read([info], store, frame, options)
    try:
        read_file(read, info, options, lambda n: None)
        store.spill_all()
    except BaseException:
        store.cleanup()
        raise
    return read


def read_in_parts(infos: list[LasFileInfo], store: RunStore, frame: PointsFrame,
                  options: ImportOptions, progress: Progress, executor: Executor
                  ) -> PointsRead:
    """:func:`~lidarcal_ros.pipeline.importing.points.read_points` with each file read by
    ``executor``'s workers; the runs' folder (beside ``store``'s) is removed with ``store``.
    """
    read = new_read(infos, store, frame, options)
    folder = tempfile.mkdtemp(prefix=".lidarcal-import-parts-", dir=store.directory)
    store.also_remove(Path(folder))
    futures = [executor.submit(_read_one, info, frame, options, folder,
                               key=f"lidarcal-import-{folder}-{i}")
               for i, info in enumerate(infos)]
    for i, part in enumerate(results_in_turn(futures)):
        merge_read(read, part)
        progress("reading", (i + 1) / len(futures))
    check_points_read(read, options)
    return read
