"""vings_ros: ROS 2 nodes, the `vings` command line, replay and launcher."""
