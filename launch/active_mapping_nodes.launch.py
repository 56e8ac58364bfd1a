"""Launch the mapper, NBV planner and keyframe selector as three processes (the map travels on /roigsf/map).

    BAGS=$(ros2 pkg prefix roigsf_ros)/share/roigsf_ros/bags  # the sample bag, installed with the package
    ros2 launch roigsf_ros active_mapping_nodes.launch.py bag:=$BAGS/synth_room

Same topics and parameters as active_mapping.launch.py; use it to run the nodes on different
machines or to restart one of them alone (a restarted mapper resumes with ``load_map``).
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
    """``mapper``, ``nbv_planner`` and ``keyframe_selector`` processes, plus ``bag_player`` when ``bag`` is given."""
    config = Path(get_package_share_directory("roigsf_ros")) / "config"
    bag, rate, policy = LaunchConfiguration("bag"), LaunchConfiguration("rate"), LaunchConfiguration("policy")
    load_map = LaunchConfiguration("load_map")
    return LaunchDescription(
        [
            DeclareLaunchArgument("bag", default_value="", description="bag to play ('' = none: live camera)"),
            DeclareLaunchArgument("rate", default_value="1.0", description="playback rate factor"),
            DeclareLaunchArgument("policy", default_value="roi-gsurfisher", description="keyframe policy"),
            DeclareLaunchArgument("load_map", default_value="", description="saved map for the mapper to resume"),
            Node(
                package="roigsf_ros",
                executable="mapper",
                name="mapper",
                output="screen",
                parameters=[str(config / "mapper.yaml"), {"load_map": load_map}],
            ),
            Node(
                package="roigsf_ros",
                executable="nbv_planner",
                name="nbv_planner",
                output="screen",
                parameters=[str(config / "nbv.yaml")],
            ),
            Node(
                package="roigsf_ros",
                executable="keyframe_selector",
                name="keyframe_selector",
                output="screen",
                parameters=[str(config / "keyframe_selector.yaml"), {"policy": policy}],
            ),
            Node(
                package="roigsf_ros",
                executable="bag_player",
                output="screen",
                # Both camera nodes (mapper, selector) before the first message: with the file's one, the first to
                # match started it, and the other missed the first frames. The rate as a float even when given as
                # rate:=1 (a float parameter refuses an integer).
                parameters=[
                    str(config / "bag_player.yaml"),
                    # 30 s: three processes importing torch and open3d at once can outlast the default 10 s
                    {
                        "bag": bag,
                        "rate": ParameterValue(rate, value_type=float),
                        "wait_for_subscribers": 2,
                        "wait_timeout_s": 30.0,
                    },
                ],
                condition=IfCondition(NotEqualsSubstitution(bag, "")),  # a path with a quote in it too
            ),
        ]
    )
