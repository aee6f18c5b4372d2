"""The ROS-free core: parameters, results, navigation, orientation, pairing, normalization.

Nothing here imports ROS; the node (:mod:`parproj_ros.ros.node`) and the commands use it.
"""
