"""A two-worker local Dask cluster shared by a test module (starting one takes seconds), and
an executor whose task kills its own worker once.

Expose the cluster in a test module with a plain assignment, ``cluster = helpers_dask.cluster``.
"""

from __future__ import annotations

import os
import signal
import sys
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import cloudpickle
import pytest

from lidarcal_ros.pipeline.executor import DaskExecutor, TaskFuture, open_executor

# (the workers unpickle this module's functions by value: they cannot import a test helper)
cloudpickle.register_pickle_by_value(sys.modules[__name__])


@pytest.fixture(scope="module")
def cluster() -> Iterator[DaskExecutor]:
    """``--dask local:2``'s executor, for the module; shut down after it."""
    with open_executor("local:2") as executor:
        assert isinstance(executor, DaskExecutor)
        yield executor


def dies_once(marker: str, fn: Callable[..., Any], *args: Any) -> Any:
    """``fn(*args)``, but the first call anywhere (no ``marker`` file yet) kills its own
    worker process instead."""
    try:
        os.close(os.open(marker, os.O_CREAT | os.O_EXCL | os.O_WRONLY))
    except FileExistsError:
        return fn(*args)
    os.kill(os.getpid(), signal.SIGKILL)
    raise AssertionError("not reached")


class KillingExecutor:
    """``inner``, whose first task with ``part`` in its key kills the worker it runs on (the
    marker file ``marker`` written then)."""

    def __init__(self, inner: DaskExecutor, marker: Path, part: str = "") -> None:
        self.inner, self.marker, self.part = inner, marker, part
        self.workers, self.description = inner.workers, inner.description

    def submit(self, fn: Callable[..., Any], *args: Any, key: str) -> TaskFuture[Any]:
        if self.part not in key or self.marker.exists():
            return self.inner.submit(fn, *args, key=key)
        return self.inner.submit(dies_once, str(self.marker), fn, *args, key=key)

    def close(self) -> None:
        pass
