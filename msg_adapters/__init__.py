"""Conversions between ROS 2 messages and vings_core types (numpy / torch)."""
