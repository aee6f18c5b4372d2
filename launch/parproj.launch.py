"""Launch parproj_node: its parameters file, two common parameters, and the input remaps.

    ros2 launch parproj_ros parproj.launch.py params_file:=/path/my_params.yaml heights:=true \
        left_strips_topic:=/fore/image_strip right_strips_topic:=/aft/image_strip

Arguments (``ros2 launch parproj_ros parproj.launch.py --show-args`` lists them):

- ``params_file``: a ``--params-file`` for the node (default: the installed
  ``share/parproj_ros/config/parproj_node.yaml``, every parameter at its default);
- ``frame_id``, ``heights``: these parameters, set after ``params_file`` (so they win over it,
  their defaults too: a ``frame_id`` or ``heights`` in ``params_file`` is overridden, and the
  node WARNs when such a value is reset to the default; give them here); their defaults are
  the parameter table's (parproj_ros/core/params.py);
- ``<input>_topic``: where the node's inputs come from (remaps of ``navigation``,
  ``left/image_strip``, ``right/image_strip``, ``gcp`` and ``pairs``; the strip remaps apply with
  the default views ``left``/``right``);
- ``log_level``: the node's ROS log level.

The launch package has no wheel where this project is developed: ``ros2 launch`` itself was not
run there. tests/ros/test_launch_file.py executes this file with a stand-in of the launch API and
checks every parameter and remap against the parameter table and the topic contract; the colcon
test starts the installed node with the same parameters and remaps (docs/ros.md).
"""

from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration, PathJoinSubstitution
from launch_ros.actions import Node
from launch_ros.parameter_descriptions import ParameterValue
from launch_ros.substitutions import FindPackageShare

from launch import LaunchDescription

#: Remapped inputs: (the node's topic, the launch argument, what it carries).
REMAPS = (
    ("navigation", "navigation_topic", "platform pose and velocity (nav_msgs/Odometry)"),
    ("left/image_strip", "left_strips_topic", "the left view's scan-line strips (Image)"),
    ("right/image_strip", "right_strips_topic", "the right view's scan-line strips (Image)"),
    ("gcp", "gcp_topic", "ground control points (parproj_msgs/GroundControlPoints)"),
    ("pairs", "pairs_topic", "single-camera pair selection (parproj_msgs/PairSelection)"),
)

#: Parameters set from launch arguments: (name, type, default as text, what it does).
PARAMETERS = (
    ("frame_id", str, "", "object frame of the outputs; '' = the frame of the inputs"),
    ("heights", bool, "false", "disparity, height image and DSM of every pair"),
)


def generate_launch_description() -> LaunchDescription:
    """The node with its parameters file, parameters and remaps, and their launch arguments."""
    default_params = PathJoinSubstitution(
        [FindPackageShare("parproj_ros"), "config", "parproj_node.yaml"]
    )
    arguments = [
        DeclareLaunchArgument(
            "params_file",
            default_value=default_params,
            description="parameters file of parproj_node (every parameter, docs/node.md)",
        ),
        DeclareLaunchArgument("log_level", default_value="info", description="ROS log level"),
    ]
    arguments += [
        DeclareLaunchArgument(arg, default_value=default, description=what)
        for arg, _type, default, what in PARAMETERS
    ]
    arguments += [
        DeclareLaunchArgument(arg, default_value=topic, description=what)
        for topic, arg, what in REMAPS
    ]
    node = Node(
        package="parproj_ros",
        executable="parproj_node",
        name="parproj_node",
        output="screen",
        parameters=[
            LaunchConfiguration("params_file"),
            {
                name: ParameterValue(LaunchConfiguration(name), value_type=type_)
                for name, type_, _default, _what in PARAMETERS
            },
        ],
        remappings=[(topic, LaunchConfiguration(arg)) for topic, arg, _what in REMAPS],
        ros_arguments=["--log-level", LaunchConfiguration("log_level")],
    )
    return LaunchDescription([*arguments, node])
