"""lidarcal_ros: quasi-rigorous airborne LiDAR calibration and radiometric correction for ROS 2.

Layout (imports only run downward):

``core``
    Pure numerics (numpy/scipy, no rclpy): local trajectory, bias model, TIN matching,
    least-squares adjustment, observability, radiometry, simulator.
``io``
    Clouds, bags, calibration/config/control files. Depends on ``core`` only.
``pipeline``
    The one procedure both the CLI and the nodes drive (batch and streaming).
``cli`` / ``nodes``
    Thin front ends: argument parsing / rclpy message plumbing.
``ros``
    What a process must set before rclpy starts (DDS confined to this machine); no rclpy.

Errors derive from :class:`lidarcal_ros.errors.LidarcalError`. ARCHITECTURE.md shows the tree
and says where to add an input format, an output or a node.
"""

__version__ = "0.2.3"
