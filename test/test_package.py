"""Packaging of lidarcal_ros: package.xml, colcon build, pip install, scripts, DDS confinement."""

from __future__ import annotations

import ast
import os
import re
import shutil
import stat
import subprocess
import sys
import textwrap
import time
import tomllib
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Any

import pytest

from lidarcal_ros.ros import environment as ros_environment

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = "lidarcal_ros"
VENV_BIN = Path(sys.executable).parent  # not resolved: the venv's bin, not the base interpreter
NODE_EXECUTABLES = ("lidarcal_calibrator", "lidarcal_corrector", "lidarcal_flight_config")
EXECUTABLES = ("lidarcal", *NODE_EXECUTABLES)
#: What a package copy needs for building (tests, scripts, bags... are not part of the package).
PACKAGE_FILES = (
    "package.xml", "setup.py", "setup.cfg", "pyproject.toml", "resource", "config", "launch",
    PACKAGE,
)
FASTDDS_NS = "{http://www.eprosima.com}"

#: Third-party top-level module -> (rosdep key in package.xml, PyPI name in requirements.txt).
#: ``None`` as PyPI name: not installable from PyPI here (launch is not in the venv).
THIRD_PARTY: dict[str, tuple[str, str | None]] = {
    "numpy": ("python3-numpy", "numpy"),
    "scipy": ("python3-scipy", "scipy"),
    "numba": ("python3-numba", "numba"),
    "yaml": ("python3-yaml", "PyYAML"),
    "tqdm": ("python3-tqdm", "tqdm"),
    "triangle": ("python3-triangle-pip", "triangle"),
    "pyproj": ("python3-pyproj", "pyproj"),
    "rosbags": ("python3-rosbags-pip", "rosbags"),
    "mcap": ("python3-mcap-pip", "mcap"),
    "mcap_ros2": ("python3-mcap-ros2-support-pip", "mcap-ros2-support"),
    "laspy": ("python3-laspy-pip", "laspy"),
    "lazrs": ("python3-lazrs-pip", "lazrs"),
    "tifffile": ("python3-tifffile", "tifffile"),
    "matplotlib": ("python3-matplotlib", "matplotlib"),
    "PIL": ("python3-pil", "pillow"),
    "ruamel": ("python3-ruamel.yaml", "ruamel.yaml"),
    "backports": ("python3-backports-zstd-pip", "backports.zstd"),  # only backports.zstd
    "dask": ("python3-dask-pip", "dask"),
    "distributed": ("python3-distributed-pip", "distributed"),
    "fsspec": ("python3-fsspec-pip", "fsspec"),
    "lz4": ("python3-lz4", "lz4"),
    # no wheel: scripts/build-tf2-msgs builds vendor/tf2_msgs into the venv
    "tf2_msgs": ("tf2_msgs", None),
    "launch": ("launch", None),
    "launch_ros": ("launch_ros", None),
}
#: ROS packages importable as Python modules: key = module name, wheel = ros-<name>.
#: Standard library of Python versions newer than 3.11 (imported behind version checks).
NEWER_STDLIB = frozenset({"compression"})  # 3.14
ROS_MODULES = frozenset({
    "rclpy", "ament_index_python", "builtin_interfaces", "rcl_interfaces", "std_msgs",
    "sensor_msgs", "geometry_msgs", "nav_msgs", "std_srvs", "diagnostic_msgs", "rosgraph_msgs",
})


def _dependency_key(module: str) -> tuple[str, str | None]:
    if module in ROS_MODULES:
        return module, "ros-" + module.replace("_", "-")
    if module in THIRD_PARTY:
        return THIRD_PARTY[module]
    raise KeyError(module)


def _package_xml() -> ET.Element:
    return ET.parse(ROOT / "package.xml").getroot()


def _exec_dependencies() -> set[str]:
    root = _package_xml()
    return {e.text.strip() for tag in ("depend", "exec_depend") for e in root.iter(tag) if e.text}


def _requirement_names() -> set[str]:
    names = set()
    for line in (ROOT / "requirements.txt").read_text().splitlines():
        line = line.split("#", 1)[0].strip()
        if line:
            names.add(_normalise(re.split(r"[=<>!~\[; ]", line, maxsplit=1)[0]))
    return names


def _normalise(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def _imported_top_level(path: Path) -> set[str]:
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    modules: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            modules.update(alias.name.split(".")[0] for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            modules.add(node.module.split(".")[0])
    return modules


def _third_party_imports() -> dict[str, set[str]]:
    """Third-party top-level modules imported by the package and the launch files -> files."""
    files = sorted((ROOT / PACKAGE).rglob("*.py")) + sorted((ROOT / "launch").glob("*.py"))
    found: dict[str, set[str]] = {}
    for path in files:
        for module in _imported_top_level(path):
            if module in sys.stdlib_module_names or module in NEWER_STDLIB or module == PACKAGE:
                continue
            found.setdefault(module, set()).add(str(path.relative_to(ROOT)))
    return found


def _copy_package(destination: Path) -> Path:
    destination.mkdir(parents=True)
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc", "*.egg-info", "_resources")
    for name in PACKAGE_FILES:
        source = ROOT / name
        if source.is_dir():
            shutil.copytree(source, destination / name, ignore=ignore)
        elif source.exists():
            shutil.copy2(source, destination / name)
    return destination


def _run(command: list[str], *, cwd: Path, env: dict[str, str] | None = None, what: str) -> str:
    result = subprocess.run(
        command, cwd=cwd, env=env, capture_output=True, text=True, timeout=600, check=False
    )
    if result.returncode != 0:
        pytest.fail(
            f"{what} failed (exit {result.returncode}): {' '.join(command)}\n"
            f"--- stdout ---\n{result.stdout[-4000:]}\n--- stderr ---\n{result.stderr[-4000:]}"
        )
    return result.stdout


def _isolated_env(**extra: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k not in {"PYTHONPATH", "AMENT_PREFIX_PATH"}}
    env.update(extra)
    return env


def _profile_from(site_packages: Path, cwd: Path, *, env_extra: dict[str, str]) -> dict[str, str]:
    """Import lidarcal_ros from ``site_packages`` in a fresh interpreter; report where it found
    the module and the profile."""
    code = textwrap.dedent(
        """
        import sys
        import lidarcal_ros, lidarcal_ros.ros.environment as r
        print("module=" + lidarcal_ros.__file__)
        print("profile=" + str(r.loopback_profile_path()))
        print("rclpy=" + str("rclpy" in sys.modules))
        """
    )
    env = _isolated_env(PYTHONPATH=str(site_packages), **env_extra)
    out = _run([sys.executable, "-c", code], cwd=cwd, env=env, what="importing lidarcal_ros")
    return dict(line.split("=", 1) for line in out.splitlines() if "=" in line)


# --- (a) package.xml -------------------------------------------------------------------------


def test_package_xml_is_valid_format_3() -> None:
    from catkin_pkg.package import parse_package

    package = parse_package(str(ROOT / "package.xml"))
    package.validate()
    assert package.package_format == 3
    assert package.name == PACKAGE
    assert package.get_build_type() == "ament_python"
    assert package.licenses == ["Apache-2.0"]
    assert package.maintainers and package.description.strip()
    from lidarcal_ros import __version__

    assert package.version == __version__
    test_deps = {d.name for d in package.test_depends}
    assert "python3-pytest" in test_deps
    assert not {d.name for d in package.exec_depends} & {"rosbag2", "rosbag2_py"}


def test_package_xml_declares_every_imported_third_party_module() -> None:
    declared = _exec_dependencies()
    requirements = _requirement_names()
    problems = []
    for module, files in sorted(_third_party_imports().items()):
        where = ", ".join(sorted(files))
        try:
            key, pypi = _dependency_key(module)
        except KeyError:
            problems.append(
                f"{module} (imported in {where}) has no rosdep key in test_package.py: add it "
                "to THIRD_PARTY/ROS_MODULES and declare it in package.xml"
            )
            continue
        if key not in declared:
            problems.append(f"{module} (imported in {where}): <exec_depend>{key}</exec_depend>")
        if pypi is not None and _normalise(pypi) not in requirements:
            problems.append(f"{module} (imported in {where}): {pypi} missing in requirements.txt")
    assert not problems, "undeclared dependencies:\n" + "\n".join(problems)


def test_import_scan_sees_third_party_imports(tmp_path: Path) -> None:
    sample = tmp_path / "sample.py"
    sample.write_text(
        "import os\nimport numpy as np\nfrom scipy import linalg\nfrom . import sibling\n"
        "from lidarcal_ros.errors import LidarcalError\nimport sensor_msgs.msg\n"
    )
    assert _imported_top_level(sample) == {
        "os", "numpy", "scipy", "lidarcal_ros", "sensor_msgs"
    }


def test_setup_py_matches_package_xml() -> None:
    tree = ast.parse((ROOT / "setup.py").read_text())
    strings = {n.value for n in ast.walk(tree) if isinstance(n, ast.Constant)}
    for executable, target in (
        ("lidarcal", "lidarcal_ros.cli.main:console_main"),
        ("lidarcal_calibrator", "lidarcal_ros.nodes.calibrator:main"),
        ("lidarcal_corrector", "lidarcal_ros.nodes.corrector:main"),
        ("lidarcal_flight_config", "lidarcal_ros.nodes.flight_config:main"),
    ):
        assert f"{executable} = {target}" in strings
    setup_cfg = (ROOT / "setup.cfg").read_text()
    assert "script_dir=$base/lib/lidarcal_ros" in setup_cfg
    assert "install_scripts=$base/lib/lidarcal_ros" in setup_cfg
    with (ROOT / "pyproject.toml").open("rb") as handle:
        assert "build-system" not in tomllib.load(handle)


def test_requirements_are_fully_pinned() -> None:
    lines = [
        line.split("#", 1)[0].strip()
        for line in (ROOT / "requirements.txt").read_text().splitlines()
    ]
    lines = [line for line in lines if line]
    unpinned = [line for line in lines if not re.fullmatch(r"[A-Za-z0-9_.\-]+==[^=\s]+", line)]
    assert not unpinned, f"not pinned with ==: {unpinned}"
    names = _requirement_names()
    for needed in (
        "ros-rclpy", "ros-sensor-msgs", "ros-geometry-msgs", "ros-nav-msgs", "ros-std-srvs",
        "ros-diagnostic-msgs", "ros-rmw-fastrtps-cpp", "ros-ament-package", "rosbags", "mcap",
        "mcap-ros2-support", "numpy", "scipy", "pyyaml", "tqdm", "laspy", "lazrs", "pyproj",
        "pytest", "ruff", "mypy", "colcon-core", "colcon-ros", "colcon-python-setup-py",
        "setuptools",
    ):
        assert needed in names, needed


# --- launch file and scripts -----------------------------------------------------------------


def test_launch_file_is_valid_python_naming_the_node_executables() -> None:
    source = (ROOT / "launch" / "lidarcal.launch.py").read_text()
    tree = ast.parse(source)  # not imported: launch is not installed here
    functions = {n.name for n in tree.body if isinstance(n, ast.FunctionDef)}
    assert "generate_launch_description" in functions
    strings = {n.value for n in ast.walk(tree) if isinstance(n, ast.Constant)}
    assert set(NODE_EXECUTABLES) <= strings
    assert "flight_config.yaml" in strings


@pytest.mark.parametrize(
    "script", ["scripts/bootstrap", "scripts/test", "scripts/sample", ".ci/run"]
)
def test_scripts_are_executable_bash(script: str) -> None:
    path = ROOT / script
    assert path.read_text().startswith("#!/usr/bin/env bash\n")
    assert path.stat().st_mode & stat.S_IXUSR, f"{script} is not executable"
    _run(["bash", "-n", str(path)], cwd=ROOT, what=f"bash -n {script}")


# --- (c) DDS confinement ---------------------------------------------------------------------


def _assert_loopback_only(profile: Path) -> None:
    root = ET.parse(profile).getroot()
    descriptors = {}
    for descriptor in root.iter(f"{FASTDDS_NS}transport_descriptor"):
        transport_id = descriptor.findtext(f"{FASTDDS_NS}transport_id", "").strip()
        descriptors[transport_id] = descriptor
    participants = list(root.iter(f"{FASTDDS_NS}participant"))
    assert participants, "no participant profile"
    assert any(p.get("is_default_profile") == "true" for p in participants)
    for participant in participants:
        rtps = participant.find(f"{FASTDDS_NS}rtps")
        assert rtps is not None
        assert rtps.findtext(f"{FASTDDS_NS}useBuiltinTransports", "").strip() == "false"
        used = [e.text.strip() for e in rtps.iter(f"{FASTDDS_NS}transport_id") if e.text]
        assert used, "no userTransports"
        for transport_id in used:
            descriptor = descriptors[transport_id]
            kind = descriptor.findtext(f"{FASTDDS_NS}type", "").strip()
            assert kind in {"SHM", "UDPv4"}, f"transport {transport_id} of type {kind}"
            if kind == "UDPv4":
                whitelist = descriptor.find(f"{FASTDDS_NS}interfaceWhiteList")
                assert whitelist is not None, f"{transport_id}: UDP without interfaceWhiteList"
                entries = [(e.text or "").strip() for e in whitelist]
                entries += [e.get("name", "") for e in whitelist if e.get("name")]
                addresses = {entry for entry in entries if entry}
                assert addresses == {"127.0.0.1"}, f"{transport_id} whitelist {addresses}"


def test_project_profile_is_loopback_only() -> None:
    _assert_loopback_only(ROOT / "config" / "loopback.xml")


def test_configure_ros_environment_confines_dds() -> None:
    env: dict[str, str] = {"ROS_STATIC_PEERS": "192.0.2.1", "ROS_DISCOVERY_SERVER": "x:11811"}
    settings = ros_environment.configure_ros_environment(env)
    assert env["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "LOCALHOST"
    assert "ROS_STATIC_PEERS" not in env and "ROS_DISCOVERY_SERVER" not in env
    assert env["RMW_IMPLEMENTATION"] == "rmw_fastrtps_cpp"
    assert env["SKIP_DEFAULT_XML"] == "1"
    assert 1 <= int(env["ROS_DOMAIN_ID"]) <= 100
    profile = Path(env["FASTDDS_DEFAULT_PROFILES_FILE"])
    assert profile.is_file()
    _assert_loopback_only(profile)
    assert settings == {k: env[k] for k in settings}


def test_this_test_process_is_confined() -> None:
    assert os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "LOCALHOST"
    _assert_loopback_only(Path(os.environ["FASTDDS_DEFAULT_PROFILES_FILE"]))
    assert os.environ["ROS_DOMAIN_ID"].strip().isdigit()


def test_configure_keeps_existing_profile_and_domain(tmp_path: Path) -> None:
    own = tmp_path / "own.xml"
    own.write_text("<dds/>")
    env = {"FASTDDS_DEFAULT_PROFILES_FILE": str(own), "ROS_DOMAIN_ID": "17"}
    ros_environment.configure_ros_environment(env)
    assert env["FASTDDS_DEFAULT_PROFILES_FILE"] == str(own)
    assert env["ROS_DOMAIN_ID"] == "17"
    env = {"FASTDDS_DEFAULT_PROFILES_FILE": str(tmp_path / "missing.xml")}
    ros_environment.configure_ros_environment(env, domain_id=42)
    assert Path(env["FASTDDS_DEFAULT_PROFILES_FILE"]) == ros_environment.loopback_profile_path()
    assert env["ROS_DOMAIN_ID"] == "42"


@pytest.mark.parametrize(
    ("env", "domain_id", "message"),
    [
        ({"RMW_IMPLEMENTATION": "rmw_cyclonedds_cpp"}, None, "RMW_IMPLEMENTATION"),
        ({"ROS_DOMAIN_ID": "abc"}, None, "not an integer"),
        ({}, 500, "outside"),
    ],
)
def test_configure_refuses_unsafe_settings(
    env: dict[str, str], domain_id: int | None, message: str
) -> None:
    with pytest.raises(RuntimeError, match=message) as error:
        ros_environment.configure_ros_environment(env, domain_id=domain_id)
    assert "\n" not in str(error.value)


def test_missing_profile_raises_one_line(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(ros_environment, "PACKAGE_DIR", tmp_path / "site" / PACKAGE)
    monkeypatch.setenv("AMENT_PREFIX_PATH", str(tmp_path / "nowhere"))
    with pytest.raises(RuntimeError, match="loopback DDS profile") as error:
        ros_environment.loopback_profile_path()
    assert "\n" not in str(error.value)
    env: dict[str, str] = {}
    with pytest.raises(RuntimeError):
        ros_environment.configure_ros_environment(env)
    assert "FASTDDS_DEFAULT_PROFILES_FILE" not in env


def test_profile_found_through_ament_index(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    pytest.importorskip("ament_index_python")
    prefix = tmp_path / "prefix"
    marker = prefix / "share" / "ament_index" / "resource_index" / "packages" / PACKAGE
    marker.parent.mkdir(parents=True)
    marker.touch()
    profile = prefix / "share" / PACKAGE / "config" / "loopback.xml"
    profile.parent.mkdir(parents=True)
    shutil.copy(ROOT / "config" / "loopback.xml", profile)
    monkeypatch.setattr(ros_environment, "PACKAGE_DIR", tmp_path / "elsewhere" / PACKAGE)
    monkeypatch.setenv("AMENT_PREFIX_PATH", str(prefix))
    assert ros_environment.loopback_profile_path() == profile


def test_claimed_domain_ids_are_distinct(tmp_path: Path) -> None:
    first = ros_environment.claim_domain_id(tmp_path)
    second = ros_environment.claim_domain_id(tmp_path)
    assert first != second
    assert {first, second} <= set(ros_environment.AUTO_DOMAIN_IDS)


def test_the_ros_environment_does_not_import_rclpy() -> None:
    for module in (ROOT / PACKAGE / "ros").glob("*.py"):
        assert not {"rclpy"} & _imported_top_level(module), module


@pytest.mark.ros
def test_ros_context_publishes_over_loopback(ros_context: Any) -> None:
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from std_msgs.msg import String

    node = rclpy.create_node("lidarcal_package_probe", context=ros_context)
    executor = SingleThreadedExecutor(context=ros_context)
    executor.add_node(node)
    received: list[str] = []
    try:
        node.create_subscription(String, "probe", lambda m: received.append(m.data), 10)
        publisher = node.create_publisher(String, "probe", 10)
        deadline = time.monotonic() + 10.0
        while not received and time.monotonic() < deadline:
            publisher.publish(String(data="hello"))
            executor.spin_once(timeout_sec=0.1)
    finally:
        executor.shutdown()
        node.destroy_node()
    assert received and received[0] == "hello"


# --- (b) colcon build and plain pip install --------------------------------------------------


@pytest.mark.parametrize("symlink", [False, True], ids=["copy", "symlink-install"])
def test_colcon_build_installs_ament_python_package(tmp_path: Path, symlink: bool) -> None:
    colcon = VENV_BIN / "colcon"
    if not colcon.exists():
        pytest.fail(f"colcon not found next to {sys.executable} (run scripts/bootstrap)")
    source = _copy_package(tmp_path / "src" / PACKAGE)
    build, install, log = tmp_path / "build", tmp_path / "install", tmp_path / "log"
    env = _isolated_env(
        COLCON_HOME=str(tmp_path / "colcon_home"),
        PATH=f"{VENV_BIN}{os.pathsep}{os.environ['PATH']}",
    )
    started = time.monotonic()
    _run(
        [
            str(colcon), "--log-base", str(log), "build",
            "--base-paths", str(source.parent),
            "--build-base", str(build), "--install-base", str(install),
            *(["--symlink-install"] if symlink else []),
        ],
        cwd=tmp_path, env=env, what="colcon build",
    )
    elapsed = time.monotonic() - started

    prefix = install / PACKAGE
    for executable in EXECUTABLES:
        script = prefix / "lib" / PACKAGE / executable
        assert script.is_file(), f"missing entry point {script}"
        assert os.access(script, os.X_OK)
    share = prefix / "share" / PACKAGE
    assert (share / "package.xml").is_file()
    assert (share / "config" / "loopback.xml").is_file()
    assert (share / "launch" / "lidarcal.launch.py").is_file()
    marker = prefix / "share" / "ament_index" / "resource_index" / "packages" / PACKAGE
    assert marker.is_file()
    assert elapsed < 300, f"colcon build took {elapsed:.0f} s"

    ament = {"AMENT_PREFIX_PATH": str(prefix)}
    if symlink:
        # colcon's setup.sh puts the build dir (symlinks into the source) on PYTHONPATH.
        found = _profile_from(build / PACKAGE, tmp_path, env_extra=ament)
        assert Path(found["profile"]) == source / "config" / "loopback.xml"
        return
    # The installed ros.environment finds the profile: inside the package, else in the share dir.
    site_packages = next(prefix.glob("lib/python3*/site-packages"))
    found = _profile_from(site_packages, tmp_path, env_extra=ament)
    assert Path(found["module"]).is_relative_to(site_packages)
    assert Path(found["profile"]) == site_packages / PACKAGE / "_resources" / "loopback.xml"
    assert found["rclpy"] == "False"
    (site_packages / PACKAGE / "_resources" / "loopback.xml").unlink()
    found = _profile_from(site_packages, tmp_path, env_extra=ament)
    assert Path(found["profile"]) == share / "config" / "loopback.xml"


def test_plain_pip_install_ships_the_profile(tmp_path: Path) -> None:
    source = _copy_package(tmp_path / "src")
    target = tmp_path / "target"
    _run(
        [
            sys.executable, "-m", "pip", "install", "--quiet", "--no-deps",
            "--no-build-isolation", "--no-compile", "--target", str(target), str(source),
        ],
        cwd=tmp_path, env=_isolated_env(PIP_DISABLE_PIP_VERSION_CHECK="1"), what="pip install",
    )
    found = _profile_from(target, tmp_path, env_extra={})
    assert Path(found["module"]).is_relative_to(target)
    assert Path(found["profile"]) == target / PACKAGE / "_resources" / "loopback.xml"
    _assert_loopback_only(Path(found["profile"]))


def test_project_profile_has_a_shared_memory_segment_for_large_clouds(tmp_path: Path) -> None:
    """Clouds of several MB must go through shared memory: with Fast DDS's default 512 KiB
    segment they travel as UDP fragments and the trajectory queues behind them."""
    from lidarcal_ros.ros.environment import (
        FASTDDS_DEFAULT_SEGMENT_BYTES,
        shared_memory_segment_bytes,
    )

    project = shared_memory_segment_bytes(ROOT / "config" / "loopback.xml")
    assert project is not None  # the project profile has an SHM transport
    assert project >= 64 * 2**20
    default = tmp_path / "default.xml"
    default.write_text(
        '<dds xmlns="http://www.eprosima.com"><profiles><transport_descriptors>'
        "<transport_descriptor><transport_id>shm</transport_id><type>SHM</type>"
        "</transport_descriptor></transport_descriptors></profiles></dds>")
    assert shared_memory_segment_bytes(default) == FASTDDS_DEFAULT_SEGMENT_BYTES
    assert shared_memory_segment_bytes(tmp_path / "missing.xml") is None
