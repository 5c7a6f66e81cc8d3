"""A directory served over HTTP on loopback (127.0.0.1, a free port) for the tests of inputs
named by URL; each request's method and path are logged."""

from __future__ import annotations

import functools
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from http.server import SimpleHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any


class _LoggingHandler(SimpleHTTPRequestHandler):
    requests: list[tuple[str, str]]

    def log_message(self, format: str, *args: Any) -> None:  # (quiet)
        pass

    def send_head(self) -> Any:
        self.requests.append((self.command, self.path))
        return super().send_head()


@contextmanager
def served(root: Path) -> Iterator[tuple[str, list[tuple[str, str]]]]:
    """``root`` on ``http://127.0.0.1:PORT``: that base URL and the requests made."""
    requests: list[tuple[str, str]] = []
    handler = type("Handler", (_LoggingHandler,), {"requests": requests})
    server = ThreadingHTTPServer(("127.0.0.1", 0),
                                 functools.partial(handler, directory=str(root)))
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}", requests
    finally:
        server.shutdown()
        server.server_close()
        thread.join(timeout=10)
