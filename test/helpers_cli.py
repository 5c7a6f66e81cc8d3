"""Running ``lidarcal`` from tests and checking its answer to bad input.

``run`` calls ``main([...])`` in-process (stdout and stderr through ``capsys``);
``run_process`` runs ``python -m lidarcal_ros`` for the real exit status and stderr.
``one_line_error`` checks the bad-input contract (exit 1, exactly one line
``lidarcal COMMAND: error: REASON``) and returns the reason; ``warning_lines`` checks that
stderr holds nothing but ``lidarcal COMMAND: warning: ...`` lines and returns their texts.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from lidarcal_ros.cli.main import main


def run(capsys: pytest.CaptureFixture[str], *args: Any) -> tuple[int, str, str]:
    """``lidarcal ARGS`` in-process: exit status, stdout, stderr."""
    capsys.readouterr()
    rc = main([str(a) for a in args])
    out, err = capsys.readouterr()
    return rc, out, err


def run_process(*args: Any, cwd: Path) -> subprocess.CompletedProcess[str]:
    """``python -m lidarcal_ros ARGS`` in a fresh interpreter."""
    return subprocess.run([sys.executable, "-m", "lidarcal_ros", *(str(a) for a in args)],
                          capture_output=True, text=True, cwd=cwd, timeout=120, check=False)


def one_line_error(rc: int, err: str, command: str = "calibrate") -> str:
    """Check the bad-input contract; return the reason (after ``error: ``)."""
    assert rc == 1, f"exit status {rc}; stderr: {err!r}"
    assert "Traceback" not in err
    lines = err.splitlines()
    assert len(lines) == 1, f"stderr is not one line: {err!r}"
    prefix = f"lidarcal {command}: error: "
    assert lines[0].startswith(prefix), lines[0]
    return lines[0][len(prefix):]


def warning_lines(err: str, command: str) -> list[str]:
    """The texts of stderr's ``lidarcal COMMAND: warning: TEXT`` lines, checking that stderr
    holds nothing else."""
    prefix = f"lidarcal {command}: warning: "
    lines = err.splitlines()
    assert all(line.startswith(prefix) for line in lines), f"not only warnings: {err!r}"
    return [line[len(prefix):] for line in lines]


def run_on_a_terminal(*args: Any, cwd: Path) -> tuple[int, str]:
    """``python -m lidarcal_ros ARGS`` with its stderr on a pseudo-terminal (as a user at a
    terminal sees it): exit status and everything written to the terminal."""
    import fcntl
    import os
    import pty
    import struct
    import termios
    import threading

    master, slave = pty.openpty()
    # A terminal of 24 x 120 characters (a new pseudo-terminal has none: no room for a bar).
    fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 24, 120, 0, 0))
    seen = bytearray()

    def drain() -> None:
        while True:
            try:
                data = os.read(master, 65536)
            except OSError:  # the terminal closed with the process
                return
            if not data:
                return
            seen.extend(data)

    reader = threading.Thread(target=drain)
    reader.start()
    try:
        proc = subprocess.run([sys.executable, "-m", "lidarcal_ros", *(str(a) for a in args)],
                              stdout=subprocess.DEVNULL, stderr=slave, cwd=cwd, timeout=300,
                              check=False)
    finally:
        os.close(slave)
        reader.join(timeout=10)
        os.close(master)
    return proc.returncode, seen.decode(errors="replace")
