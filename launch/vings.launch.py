"""ROS 2 launch file (for real ROS 2 installs with `ros2 launch`): the same graph `vings launch` starts.

    ros2 launch vings_ros vings.launch.py params_file:=/path/vings.yaml use_sim_time:=true
"""
import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, SetEnvironmentVariable
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node


def generate_launch_description():
    share = get_package_share_directory("vings_ros")
    default_params = os.path.join(share, "params", "vings.yaml")
    params = LaunchConfiguration("params_file")
    sim_time = LaunchConfiguration("use_sim_time")
    common = dict(package="vings_ros", output="screen",
                  parameters=[params, {"use_sim_time": sim_time}])
    return LaunchDescription([
        DeclareLaunchArgument("params_file", default_value=default_params),
        DeclareLaunchArgument("use_sim_time", default_value="false"),
        # Same-host shared-memory transport (see docs/ros.md); unset for cross-host graphs.
        SetEnvironmentVariable("FASTRTPS_DEFAULT_PROFILES_FILE",
                               os.path.join(os.path.dirname(__import__("vings_ros").__file__),
                                            "config", "fastdds_shm.xml")),
        Node(executable="mapper_node", name="mapper_node", **common),
        Node(executable="frontend_node", name="frontend_node", **common),
    ])
