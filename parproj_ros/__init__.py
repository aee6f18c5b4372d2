"""parproj_ros: parallel-projection processing of linear array scanner scenes for ROS 2."""

__version__ = "0.1.0"
