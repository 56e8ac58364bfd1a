"""Launch active mapping in one process (mapper + NBV planner + keyframe selector sharing one map), and the bag.

    BAGS=$(ros2 pkg prefix roigsf_ros)/share/roigsf_ros/bags  # the sample bag, installed with the package
    ros2 launch roigsf_ros active_mapping.launch.py bag:=$BAGS/synth_room policy:=roi-gsurfisher

Needs launch and launch_ros (a full ROS 2 install); without them run ``active_mapping`` and
``bag_player`` directly (the README shows how). Parameters come from the package's config/*.yaml.
"""

from __future__ import annotations

from pathlib import Path

from ament_index_python.packages import get_package_share_directory
from launch.actions import DeclareLaunchArgument
from launch.conditions import IfCondition
from launch.substitutions import LaunchConfiguration, NotEqualsSubstitution
from launch_ros.actions import Node
from launch_ros.parameter_descriptions import ParameterValue

from launch import LaunchDescription


def generate_launch_description() -> LaunchDescription:
    """The ``active_mapping`` process with the three config files, plus ``bag_player`` when ``bag`` is given."""
    config = Path(get_package_share_directory("roigsf_ros")) / "config"
    files = [str(config / name) for name in ("mapper.yaml", "nbv.yaml", "keyframe_selector.yaml")]
    bag, rate, policy = LaunchConfiguration("bag"), LaunchConfiguration("rate"), LaunchConfiguration("policy")
    return LaunchDescription(
        [
            DeclareLaunchArgument("bag", default_value="", description="bag to play ('' = none: live camera)"),
            DeclareLaunchArgument("rate", default_value="1.0", description="playback rate factor"),
            DeclareLaunchArgument("policy", default_value="roi-gsurfisher", description="keyframe policy"),
            Node(
                package="roigsf_ros",
                executable="active_mapping",
                output="screen",
                parameters=[*files, {"policy": policy}],
            ),
            Node(
                package="roigsf_ros",
                executable="bag_player",
                output="screen",
                # The rate as a float even when given as rate:=1 (a float parameter refuses an integer).
                parameters=[
                    str(config / "bag_player.yaml"),
                    {"bag": bag, "rate": ParameterValue(rate, value_type=float)},
                ],
                condition=IfCondition(NotEqualsSubstitution(bag, "")),  # a path with a quote in it too
            ),
        ]
    )
