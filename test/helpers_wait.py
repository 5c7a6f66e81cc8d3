"""Waiting for something another thread or process does, in tests."""

from __future__ import annotations

import time
from collections.abc import Callable


def wait_until(cond: Callable[[], bool], timeout: float, what: str, *,
               poll_s: float = 0.05, state: Callable[[], str] | None = None) -> None:
    """Return once ``cond()`` holds; fail naming ``what`` after ``timeout`` seconds, with
    ``state()`` (what was there instead) when given, so a timeout in CI explains itself."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if cond():
            return
        time.sleep(poll_s)
    seen = f" ({state()})" if state is not None else ""
    raise AssertionError(f"timed out after {timeout:.0f} s waiting for {what}{seen}")
