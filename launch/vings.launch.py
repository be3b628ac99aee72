"""ROS 2 launch file (for real ROS 2 installs with `ros2 launch`): the same graph `vings launch` starts.

    ros2 launch vings_ros vings.launch.py params_file:=/path/vings.yaml use_sim_time:=true

The nodes are those of vings_ros/registry.py that `vings launch` starts by default, in its start
order (the reverse of the registry order).
"""
import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, SetEnvironmentVariable
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

from vings_ros import registry


def generate_launch_description():
    share = get_package_share_directory("vings_ros")
    default_params = os.path.join(share, "params", "vings.yaml")
    params = LaunchConfiguration("params_file")
    sim_time = LaunchConfiguration("use_sim_time")
    common = dict(package="vings_ros", output="screen",
                  parameters=[params, {"use_sim_time": sim_time}])
    nodes = [n for n in reversed(registry.NODES) if n.launch is registry.Launch.ALWAYS]
    return LaunchDescription([
        DeclareLaunchArgument("params_file", default_value=default_params),
        DeclareLaunchArgument("use_sim_time", default_value="false"),
        # Same-host shared-memory transport (see docs/ros.md); unset for cross-host graphs.
        SetEnvironmentVariable("FASTRTPS_DEFAULT_PROFILES_FILE",
                               os.path.join(os.path.dirname(registry.__file__), "config", "fastdds_shm.xml")),
        *(Node(executable=n.name, name=n.name, **common) for n in nodes),
    ])
