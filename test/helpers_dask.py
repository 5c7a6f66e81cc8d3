"""A two-worker local Dask cluster shared by a test module (starting one takes seconds), an
executor whose task kills its own worker once, and a comparison of two results bit for bit.

Expose the cluster in a test module with a plain assignment, ``cluster = helpers_dask.cluster``.
"""

from __future__ import annotations

import dataclasses
import os
import signal
import sys
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import Any

import cloudpickle
import numpy as np
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

    def submit(self, fn: Callable[..., Any], *args: Any, key: str,
               place: str | None = None) -> TaskFuture[Any]:
        if self.part not in key or self.marker.exists():
            return self.inner.submit(fn, *args, key=key, place=place)
        return self.inner.submit(dies_once, str(self.marker), fn, *args, key=key, place=place)

    def places(self) -> list[str]:
        return self.inner.places()

    def close(self) -> None:
        pass


def differences(a: Any, b: Any, path: str = "") -> list[str]:
    """Where ``a`` and ``b`` differ, field by field (dataclasses, mappings, sequences, numpy
    arrays and numbers compared bit for bit, NaN equal to NaN): their paths, empty where
    none."""
    if dataclasses.is_dataclass(a) and not isinstance(a, type):
        if type(a) is not type(b):
            return [f"{path}: {type(a).__name__} against {type(b).__name__}"]
        return [d for f in dataclasses.fields(a)
                for d in differences(getattr(a, f.name), getattr(b, f.name),
                                     f"{path}.{f.name}")]
    if isinstance(a, Mapping):
        if not isinstance(b, Mapping) or list(a) != list(b):
            return [f"{path}: keys"]
        return [d for k in a for d in differences(a[k], b[k], f"{path}[{k!r}]")]
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        a, b = np.asarray(a), np.asarray(b)
        same = a.shape == b.shape and a.dtype == b.dtype and (
            a.tobytes() == b.tobytes() or
            (a.dtype.kind == "f" and np.array_equal(a, b, equal_nan=True)))
        return [] if same else [f"{path}: arrays"]
    if isinstance(a, list | tuple):
        if not isinstance(b, list | tuple) or len(a) != len(b):
            return [f"{path}: lengths"]
        return [d for i, (x, y) in enumerate(zip(a, b, strict=True))
                for d in differences(x, y, f"{path}[{i}]")]
    if isinstance(a, float) and isinstance(b, float) and a != a and b != b:
        return []
    return [] if a == b else [f"{path}: {a!r} against {b!r}"]
