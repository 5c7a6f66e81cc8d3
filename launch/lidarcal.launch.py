"""Launch the lidarcal_ros nodes: calibrator, corrector and flight-configuration server.

    ros2 launch lidarcal_ros lidarcal.launch.py [params_file:=/path/to/flight_config.yaml]

All three nodes read their parameters from ``params_file`` (default: the installed
``share/lidarcal_ros/config/flight_config.yaml``). DDS stays on this machine: the launch process
and every node get the loopback-only Fast DDS profile, ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``
and one shared ``ROS_DOMAIN_ID`` (see :mod:`lidarcal_ros.ros.environment`).
"""

from __future__ import annotations

import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, SetEnvironmentVariable
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

from lidarcal_ros.ros.environment import configure_ros_environment

PACKAGE = "lidarcal_ros"
NODE_EXECUTABLES = ("lidarcal_calibrator", "lidarcal_corrector", "lidarcal_flight_config")


def generate_launch_description() -> LaunchDescription:
    """The three lidarcal nodes, each given the ``params_file`` argument (default: the package's
    config/flight_config.yaml), DDS confined to this machine."""
    # Confine this launch process (it may start rclpy itself) and, through the environment the
    # nodes inherit, every node; one domain id for all so the nodes see each other.
    ros_environment = configure_ros_environment()
    default_params = os.path.join(
        get_package_share_directory(PACKAGE), "config", "flight_config.yaml"
    )
    params_file = LaunchConfiguration("params_file")

    actions: list = [
        DeclareLaunchArgument(
            "params_file",
            default_value=default_params,
            description="Flight configuration YAML passed to every node with --params-file",
        ),
    ]
    actions += [SetEnvironmentVariable(name, value) for name, value in ros_environment.items()]
    actions += [
        Node(
            package=PACKAGE,
            executable=executable,
            output="screen",
            emulate_tty=True,
            parameters=[params_file],
        )
        for executable in NODE_EXECUTABLES
    ]
    return LaunchDescription(actions)
