"""The ROS 2 side: messages <-> arrays, the node, and the live graph (replay, recorder)."""
