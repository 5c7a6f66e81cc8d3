"""Build script of lidarcal_ros: an ament_python package that also installs with plain pip.

* ``colcon build`` installs the entry points into ``lib/lidarcal_ros`` (see setup.cfg), and
  package.xml, config/ and launch/ under ``share/lidarcal_ros`` plus the ament index marker.
* Every build (colcon or wheel) also copies ``config/loopback.xml`` into the package as
  ``lidarcal_ros/_resources/loopback.xml`` so :mod:`lidarcal_ros.ros.environment` finds the
  loopback-only DDS profile in a plain ``pip install`` too. ``config/loopback.xml`` stays the
  only copy in the source tree.
"""

from __future__ import annotations

import os
import re
import shutil
from glob import glob

from setuptools import find_packages, setup
from setuptools.command.build_py import build_py

PACKAGE = "lidarcal_ros"
HERE = os.path.dirname(os.path.abspath(__file__))
PROFILE_SOURCE = os.path.join("config", "loopback.xml")
PROFILE_IN_PACKAGE = os.path.join(PACKAGE, "_resources", "loopback.xml")


def _version() -> str:
    with open(os.path.join(HERE, PACKAGE, "__init__.py"), encoding="utf-8") as handle:
        match = re.search(r'^__version__\s*=\s*"([^"]+)"', handle.read(), re.MULTILINE)
    if match is None:
        raise RuntimeError(f"no __version__ in {PACKAGE}/__init__.py")
    return match.group(1)


class BuildPyWithProfile(build_py):
    """build_py that also ships config/loopback.xml inside the package (not in editable mode)."""

    def _ships_profile(self) -> bool:
        return not getattr(self, "editable_mode", False)

    def run(self) -> None:
        """Build as build_py does, then (not in editable mode) copy config/loopback.xml into the
        built package."""
        super().run()
        if self._ships_profile():
            target = os.path.join(self.build_lib, PROFILE_IN_PACKAGE)
            self.mkpath(os.path.dirname(target))
            shutil.copyfile(os.path.join(HERE, PROFILE_SOURCE), target)

    def get_outputs(self, include_bytecode: bool = True) -> list[str]:
        """build_py's outputs, with the packaged config/loopback.xml where it is shipped."""
        outputs = list(super().get_outputs(include_bytecode))
        if self._ships_profile():
            outputs.append(os.path.join(self.build_lib, PROFILE_IN_PACKAGE))
        return outputs


def _data_files() -> list[tuple[str, list[str]]]:
    entries = [
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/config", sorted(glob("config/*.yaml") + glob("config/*.xml"))),
        (f"share/{PACKAGE}/launch", sorted(glob("launch/*.launch.py"))),
    ]
    return [(target, files) for target, files in entries if files]


setup(
    name=PACKAGE,
    version=_version(),
    description="Airborne LiDAR system calibration and radiometric correction for ROS 2",
    maintainer="lidarcal_ros maintainers",
    maintainer_email="lidarcal@example.org",
    license="Apache-2.0",
    python_requires=">=3.11",
    packages=find_packages(exclude=["test", "test.*", "bench", "bench.*"]),
    data_files=_data_files(),
    install_requires=[
        "setuptools",
        "numpy",
        "scipy",
        "numba",
        "PyYAML",
        "tqdm",
        "triangle",
        "pyproj",
        "laspy",
        "lazrs",
        "tifffile",
        "matplotlib",
        "pillow",
        "rosbags",
        "mcap",
        "mcap-ros2-support",
        "ruamel.yaml",
        "backports.zstd; python_version < '3.14'",
    ],
    extras_require={"test": ["pytest"]},
    zip_safe=False,
    cmdclass={"build_py": BuildPyWithProfile},
    entry_points={
        "console_scripts": [
            "lidarcal = lidarcal_ros.cli.main:console_main",
            "lidarcal_calibrator = lidarcal_ros.nodes.calibrator:main",
            "lidarcal_corrector = lidarcal_ros.nodes.corrector:main",
            "lidarcal_flight_config = lidarcal_ros.nodes.flight_config:main",
        ],
    },
)
