"""lidarcal_ros: quasi-rigorous airborne LiDAR calibration and radiometric correction for ROS 2.

Layers, imports only downward: ``core`` (numerics) < ``io`` (files, bags, messages) <
``pipeline`` (the procedures) < ``cli`` / ``nodes`` (front ends); ``ros`` is what a process sets
before rclpy starts. Errors derive from :class:`lidarcal_ros.errors.LidarcalError`.
ARCHITECTURE.md shows the tree and where to add things.
"""

__version__ = "0.2.3"
