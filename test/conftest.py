"""Shared pytest set-up of lidarcal_ros.

At import time (before any test module can import rclpy) ROS 2 / DDS is confined to this
machine with :func:`lidarcal_ros.ros.environment.configure_ros_environment`: loopback-only
Fast DDS profile, ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``, and a domain id of this run's
own. ``scripts/test`` already claims a domain id (exported as ``ROS_DOMAIN_ID``), which is kept;
a bare ``pytest`` run claims one with :func:`lidarcal_ros.ros.environment.claim_domain_id`, so
parallel runs do not see each other.

ROS integration tests take the ``ros_context`` fixture: a fresh rclpy context for the module,
shut down afterwards. Pass it to everything that takes a context::

    def test_something(ros_context):
        node = rclpy.create_node("probe", context=ros_context)
        executor = rclpy.executors.SingleThreadedExecutor(context=ros_context)

Tests that use it are marked ``ros`` automatically.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from typing import Any

import pytest

from lidarcal_ros.ros.environment import claim_domain_id, configure_ros_environment

_preset_domain = os.environ.get("ROS_DOMAIN_ID", "").strip()
ROS_SETTINGS: dict[str, str] = configure_ros_environment(
    domain_id=None if _preset_domain else claim_domain_id()
)
ROS_DOMAIN_ID = int(ROS_SETTINGS["ROS_DOMAIN_ID"])


def pytest_report_header(config: pytest.Config) -> str:
    return (
        f"ROS: domain {ROS_DOMAIN_ID}, discovery {ROS_SETTINGS['ROS_AUTOMATIC_DISCOVERY_RANGE']}, "
        f"profile {ROS_SETTINGS['FASTDDS_DEFAULT_PROFILES_FILE']}"
    )


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    for item in items:
        if "ros_context" in getattr(item, "fixturenames", ()):
            item.add_marker(pytest.mark.ros)


@pytest.fixture(scope="module")
def ros_context() -> Iterator[Any]:
    """A fresh, initialised rclpy context for one test module (DDS confined to loopback)."""
    import rclpy
    from rclpy.context import Context

    context = Context()
    rclpy.init(context=context, domain_id=ROS_DOMAIN_ID)
    try:
        yield context
    finally:
        context.try_shutdown()


@pytest.fixture()
def probe(ros_context: Any, request: pytest.FixtureRequest) -> Iterator[tuple[Any, Any]]:
    """A node of the test module's context (named after the module) and an executor that
    spins it on demand."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor

    name = request.module.__name__.rsplit(".", 1)[-1].removeprefix("test_") + "_probe"
    node = rclpy.create_node(name, context=ros_context)
    executor = SingleThreadedExecutor(context=ros_context)
    executor.add_node(node)
    try:
        yield node, executor
    finally:
        executor.shutdown()
        node.destroy_node()
