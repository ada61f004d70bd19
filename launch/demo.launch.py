"""The demo graph on a ROS 2 Jazzy install: simulator, three centroiders side by side, recorder.

    ros2 launch lgs_wfs_ros demo.launch.py [frames:=2000] [output:=bags/demo.mcap]

Each centroider runs in its own namespace (/cog, /cmf, /ann) reading the simulator's /wfs topics
(frame, sensor, and true_slopes for its slope_error series). Every node publishes its state
on /diagnostics. Open config/foxglove_layout.json in Foxglove (with foxglove_bridge, or on
the recorded bag) to see the frame, the slopes pictures and the error series together.
"""

import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, SetEnvironmentVariable
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

ALGORITHMS = ("cog", "cmf", "ann")


def generate_launch_description():
    share = get_package_share_directory("lgs_wfs_ros")
    params = os.path.join(share, "config", "demo.yaml")
    frames = LaunchConfiguration("frames")
    output = LaunchConfiguration("output")
    actions = [
        DeclareLaunchArgument("frames", default_value="2000", description="frames to simulate"),
        DeclareLaunchArgument("output", default_value="bags/demo.mcap", description="bag path"),
        SetEnvironmentVariable("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST"),
        SetEnvironmentVariable("FASTRTPS_DEFAULT_PROFILES_FILE",
                               os.path.join(share, "config", "fastdds_profile.xml")),
        Node(package="lgs_wfs_ros", executable="simulator_node", namespace="wfs",
             parameters=[params, {"frames": frames}]),
        Node(package="lgs_wfs_ros", executable="recorder_node", namespace="wfs",
             parameters=[params, {"output": output,
                                  "topics": ["/wfs/frame", "/wfs/true_slopes", "/wfs/sensor"]
                                  + [f"/{a}/{t}" for a in ALGORITHMS
                                     for t in ("slopes", "centroider")]}]),
    ]
    for name in ALGORITHMS:
        actions.append(Node(
            package="lgs_wfs_ros", executable="centroider_node", namespace=name,
            parameters=[params, {"algorithm": name}],
            remappings=[("frame", "/wfs/frame"), ("sensor", "/wfs/sensor"),
                        ("true_slopes", "/wfs/true_slopes")]))
    return LaunchDescription(actions)
