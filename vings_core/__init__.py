"""vings_core: the pure (ROS-free) library of VINGS-ROS.

Small modules with plain data in between (see :mod:`vings_core.types`). Nothing here imports rclpy.
"""
__version__ = "0.1.0"
