"""Keep ROS 2 / DDS traffic on this machine: environment set-up done before rclpy starts.

What it sets: docs/internals.md, "DDS on this machine only". Never imports rclpy.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Iterator, MutableMapping
from pathlib import Path
from typing import IO

__all__ = [
    "AUTO_DOMAIN_IDS", "DEFAULT_RMW", "FASTDDS_DEFAULT_SEGMENT_BYTES", "FASTDDS_RMWS",
    "MAX_DOMAIN_ID", "PACKAGE", "PACKAGE_DIR", "PROFILE_ENV", "PROFILE_NAME", "claim_domain_id",
    "configure_ros_environment", "domain_lock_dir", "loopback_profile_path", "pid_domain_id",
    "shared_memory_segment_bytes",
]

PACKAGE = "lidarcal_ros"
PROFILE_NAME = "loopback.xml"
PROFILE_ENV = "FASTDDS_DEFAULT_PROFILES_FILE"

#: RMW implementations that honour the Fast DDS profile.
FASTDDS_RMWS = frozenset({"rmw_fastrtps_cpp", "rmw_fastrtps_dynamic_cpp"})
DEFAULT_RMW = "rmw_fastrtps_cpp"

#: Domain ids handed out automatically: 1..100 (all safe with Linux's ephemeral port range).
AUTO_DOMAIN_IDS = range(1, 101)
#: Largest domain id Fast DDS accepts.
MAX_DOMAIN_ID = 232

#: Variables that would make DDS contact other hosts despite the LOCALHOST range.
_OFF_HOST_VARIABLES = ("ROS_STATIC_PEERS", "ROS_DISCOVERY_SERVER")

#: The installed package ``lidarcal_ros`` (the profile is looked for relative to it).
PACKAGE_DIR = Path(__file__).resolve().parents[1]

# Open lock files of domain ids claimed by this process (held until the process exits).
_claimed_domain_locks: list[IO[str]] = []


def _profile_candidates() -> Iterator[Path]:
    """Where the profile may be, most specific first (see :func:`loopback_profile_path`)."""
    # 1. Source checkout (also an editable install): <repo>/config/loopback.xml.
    repo = PACKAGE_DIR.parent
    if (repo / "package.xml").is_file() and (repo / "setup.py").is_file():
        yield repo / "config" / PROFILE_NAME
    # 2. Copy shipped inside the package by setup.py (colcon install, wheel / plain pip).
    yield PACKAGE_DIR / "_resources" / PROFILE_NAME
    # 3. Share dir of the prefix this module is installed in:
    #    <prefix>/lib/pythonX.Y/site-packages/lidarcal_ros -> <prefix>/share/lidarcal_ros/config.
    parents = PACKAGE_DIR.parents
    if len(parents) > 3 and parents[2].name == "lib":
        yield parents[3] / "share" / PACKAGE / "config" / PROFILE_NAME
    # 4. The ament index (a colcon install on AMENT_PREFIX_PATH), if ament_index_python is there.
    try:
        from ament_index_python.packages import get_package_share_directory

        share = Path(get_package_share_directory(PACKAGE))
    except Exception:  # not importable, or lidarcal_ros not in the index
        return
    yield share / "config" / PROFILE_NAME


def loopback_profile_path() -> Path:
    """Return the loopback-only Fast DDS profile of the project.

    Looks, in order, in the source checkout this module is part of (``<repo>/config``), in the
    copy shipped inside the installed package (``lidarcal_ros/_resources``), in the share dir of
    the install prefix (``<prefix>/share/lidarcal_ros/config``) and in the share dir that
    ``ament_index_python`` reports. Raises :class:`RuntimeError` if none holds the file.
    """
    candidates: list[Path] = []
    for candidate in _profile_candidates():
        if candidate.is_file():
            return candidate
        candidates.append(candidate)
    looked = ", ".join(str(c) for c in candidates)
    raise RuntimeError(
        f"{PACKAGE}: loopback DDS profile {PROFILE_NAME} not found (looked in: {looked}); "
        "refusing to start ROS without it"
    )


#: Fast DDS's shared-memory segment when a profile does not set one, bytes.
FASTDDS_DEFAULT_SEGMENT_BYTES = 512 * 1024


def shared_memory_segment_bytes(profile: str | Path | None = None) -> int | None:
    """The shared-memory segment size (bytes) of a Fast DDS profile (default: the one in
    ``FASTDDS_DEFAULT_PROFILES_FILE``): the largest ``segment_size`` of its SHM transports,
    Fast DDS's default where none is set; None when the profile cannot be read or has no SHM
    transport. Messages larger than about half of it travel as UDP fragments instead."""
    import xml.etree.ElementTree as ET

    path = profile if profile is not None else os.environ.get(PROFILE_ENV, "")
    if not path:
        return None
    try:
        root = ET.parse(path).getroot()
    except (OSError, ET.ParseError):
        return None
    sizes = []
    for descriptor in root.iter():
        if not descriptor.tag.endswith("transport_descriptor"):
            continue
        kind = next((c.text or "" for c in descriptor if c.tag.endswith("type")), "").strip()
        if kind != "SHM":
            continue
        size = next((c.text for c in descriptor if c.tag.endswith("segment_size")), None)
        try:
            sizes.append(int(size) if size else FASTDDS_DEFAULT_SEGMENT_BYTES)
        except ValueError:
            sizes.append(FASTDDS_DEFAULT_SEGMENT_BYTES)
    return max(sizes) if sizes else None


def _check_domain_id(value: int | str, origin: str) -> int:
    try:
        domain = int(value)
    except (TypeError, ValueError):
        raise RuntimeError(f"{PACKAGE}: {origin} {value!r} is not an integer") from None
    if not 0 <= domain <= MAX_DOMAIN_ID:
        raise RuntimeError(f"{PACKAGE}: {origin} {domain} is outside 0..{MAX_DOMAIN_ID}")
    return domain


def pid_domain_id(pid: int | None = None) -> int:
    """Domain id derived from a process id: 1..100."""
    return (os.getpid() if pid is None else pid) % len(AUTO_DOMAIN_IDS) + AUTO_DOMAIN_IDS.start


def domain_lock_dir() -> Path:
    """Directory of the lock files of claimed domain ids (shared with ``scripts/test``)."""
    return Path(tempfile.gettempdir()) / f"{PACKAGE}-dds-domains"


def claim_domain_id(lock_dir: Path | None = None) -> int:
    """Claim a domain id (1..100) no other claiming process on this machine holds.

    Starts at :func:`pid_domain_id` and takes the first id whose lock file can be locked
    (``flock``); the lock is held until this process exits. ``scripts/test`` takes the same
    locks from bash, so parallel test runs get different domains. Falls back to the pid-derived
    id when locking is unavailable or every id is taken.
    """
    start = pid_domain_id()
    try:
        import fcntl
    except ImportError:  # not POSIX
        return start
    directory = domain_lock_dir() if lock_dir is None else lock_dir
    try:
        directory.mkdir(parents=True, exist_ok=True)
    except OSError:
        return start
    count = len(AUTO_DOMAIN_IDS)
    for step in range(count):
        candidate = (start - AUTO_DOMAIN_IDS.start + step) % count + AUTO_DOMAIN_IDS.start
        try:
            handle = open(directory / f"{candidate}.lock", "a", encoding="utf-8")
        except OSError:
            continue
        try:
            fcntl.flock(handle.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            handle.close()
            continue
        _claimed_domain_locks.append(handle)
        return candidate
    return start


def configure_ros_environment(
    environ: MutableMapping[str, str] | None = None, *, domain_id: int | None = None
) -> dict[str, str]:
    """Confine ROS 2 / DDS to this machine; call before rclpy is imported or initialised.

    Parameters
    ----------
    environ
        Mapping to update in place; ``os.environ`` when omitted.
    domain_id
        ``ROS_DOMAIN_ID`` to set. When omitted, an id already in ``environ`` is kept (after
        checking it is an integer in 0..232), else one is derived from the pid (1..100).

    Returns
    -------
    dict
        The ROS/DDS variables as now set in ``environ``.

    Raises
    ------
    RuntimeError
        No loopback profile can be found, ``RMW_IMPLEMENTATION`` names an RMW that does not use
        Fast DDS profiles, or the domain id is invalid. The message is one line.
    """
    env: MutableMapping[str, str] = os.environ if environ is None else environ

    rmw = env.get("RMW_IMPLEMENTATION", "").strip() or DEFAULT_RMW
    if rmw not in FASTDDS_RMWS:
        raise RuntimeError(
            f"{PACKAGE}: RMW_IMPLEMENTATION={rmw} would ignore the loopback-only Fast DDS "
            f"profile; unset it or use one of {', '.join(sorted(FASTDDS_RMWS))}"
        )

    current = env.get(PROFILE_ENV, "").strip()
    profile = current if current and Path(current).is_file() else str(loopback_profile_path())

    if domain_id is not None:
        domain = _check_domain_id(domain_id, "domain_id")
    elif env.get("ROS_DOMAIN_ID", "").strip():
        domain = _check_domain_id(env["ROS_DOMAIN_ID"].strip(), "ROS_DOMAIN_ID")
    else:
        domain = pid_domain_id()

    settings = {
        "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
        PROFILE_ENV: profile,
        "SKIP_DEFAULT_XML": "1",
        "RMW_IMPLEMENTATION": rmw,
        "ROS_DOMAIN_ID": str(domain),
    }
    for name in _OFF_HOST_VARIABLES:
        env.pop(name, None)
    env.update(settings)
    return dict(settings)
