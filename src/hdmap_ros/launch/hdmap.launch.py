"""Launch the hdmap node suite on stock ROS 2 Jazzy.

    ros2 launch hdmap_ros hdmap.launch.py                       # mapping nodes, waiting for /fleet/drives
    ros2 launch hdmap_ros hdmap.launch.py bag:=/path/to/bag rate:=10.0

Arguments: ``params_file`` (default: the package's config/hdmap.yaml), ``bag`` (empty: no player;
feed /fleet/drives yourself, e.g. with ``ros2 bag play``), ``rate`` (a float; ``rate:=10`` works),
``state_dir`` (where the SQLite stores live; default ``$ROS_HOME/hdmap``, ``~/.ros/hdmap``),
``namespace`` (every node and topic under it: topic names are relative).
"""

import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.conditions import IfCondition
from launch.substitutions import LaunchConfiguration, PathJoinSubstitution, PythonExpression
from launch_ros.actions import Node
from launch_ros.parameter_descriptions import ParameterValue


def generate_launch_description() -> LaunchDescription:
    default_params = os.path.join(get_package_share_directory("hdmap_ros"), "config", "hdmap.yaml")
    params = LaunchConfiguration("params_file")
    state = LaunchConfiguration("state_dir")
    bag = LaunchConfiguration("bag")
    ns = LaunchConfiguration("namespace")
    ros_home = os.environ.get("ROS_HOME") or os.path.join(os.path.expanduser("~"), ".ros")

    def node(name, extra=None):
        return Node(
            package="hdmap_ros",
            executable=name,
            name=name,
            namespace=ns,
            output="screen",
            parameters=[params] + ([extra] if extra else []),
        )

    return LaunchDescription(
        [
            DeclareLaunchArgument("params_file", default_value=default_params, description="Node parameters (YAML)."),
            DeclareLaunchArgument(
                "state_dir",
                default_value=os.path.join(ros_home, "hdmap"),
                description="Directory of the SQLite stores.",
            ),
            DeclareLaunchArgument("namespace", default_value="", description="Namespace of every node and topic."),
            DeclareLaunchArgument("bag", default_value="", description="Fleet bag to replay ('' = none)."),
            DeclareLaunchArgument("rate", default_value="1.0", description="Replay speed factor."),
            node("drive_ingestor"),
            node("segment_mapper", {"db_path": PathJoinSubstitution([state, "segment_mapper.db"])}),
            node(
                "map_stitcher",
                {
                    "db_path": PathJoinSubstitution([state, "map_stitcher.db"]),
                    "drive_db_path": PathJoinSubstitution([state, "segment_mapper.db"]),
                },
            ),
            node("map_publisher"),
            Node(
                package="hdmap_ros",
                executable="bag_player",
                name="bag_player",
                namespace=ns,
                output="screen",
                # a float even when given as rate:=10 (an integer to YAML; the node declares a double)
                parameters=[
                    params,
                    {"bag": bag, "rate": ParameterValue(LaunchConfiguration("rate"), value_type=float)},
                ],
                condition=IfCondition(PythonExpression(["'", bag, "' != ''"])),
            ),
        ]
    )
