"""Log lines of a lasting condition said at most once in a while.

A node's service meets the same failure at every message (a malformed stream, a backlog over
its bound, a checkpoint directory that went away): said each time it would fill the log.
"""

from __future__ import annotations

import logging
import math
import time

__all__ = ["ThrottledLog"]


class ThrottledLog:
    """Log through ``logger`` each kind of line at most once every so many seconds.

    A line's kind is its words before the first colon (``"malformed cloud skipped: ..."``):
    lines of one kind with other details after the colon count as the same condition.
    """

    def __init__(self, logger: logging.Logger) -> None:
        self.logger = logger
        self._said: dict[str, float] = {}  # kind -> when it was last said (monotonic s)

    def log(self, level: int, every_s: float, message: str) -> None:
        """Log ``message`` at ``level`` unless a line of its kind was logged less than
        ``every_s`` seconds ago."""
        kind = message.split(":", 1)[0]
        now = time.monotonic()
        if now - self._said.get(kind, -math.inf) >= every_s:
            self._said[kind] = now
            self.logger.log(level, "%s", message)
