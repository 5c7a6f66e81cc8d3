"""A two-worker local Dask cluster shared by a test module (starting one takes seconds).

Expose it in a test module with a plain assignment, ``cluster = helpers_dask.cluster``.
"""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from lidarcal_ros.pipeline.executor import DaskExecutor, open_executor


@pytest.fixture(scope="module")
def cluster() -> Iterator[DaskExecutor]:
    """``--dask local:2``'s executor, for the module; shut down after it."""
    with open_executor("local:2") as executor:
        assert isinstance(executor, DaskExecutor)
        yield executor
