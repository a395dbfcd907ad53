"""ROS 2 launch file of the vernier_ros detector node with params/detector.yaml.

    ros2 launch launch_scripts/detector.launch.py [image:=/camera/image_raw]
        [params_file:=/path/to/detector.yaml] [namespace:=/microscope] [log_level:=info]

Uses the installed package's parameter file when vernier_ros is built with colcon, otherwise
the one next to this file (running from a source checkout).
"""

from pathlib import Path

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node


def default_params_file():
    try:
        from ament_index_python.packages import get_package_share_directory

        installed = Path(get_package_share_directory("vernier_ros")) / "params" / "detector.yaml"
        if installed.is_file():
            return str(installed)
    except Exception:  # noqa: BLE001 - not installed: fall back to the source tree
        pass
    return str(Path(__file__).resolve().parent.parent / "params" / "detector.yaml")


def generate_launch_description():
    return LaunchDescription([
        DeclareLaunchArgument("params_file", default_value=default_params_file(),
                              description="ROS 2 parameter file of the node"),
        DeclareLaunchArgument("image", default_value="image",
                              description="sensor_msgs/Image topic to measure"),
        DeclareLaunchArgument("namespace", default_value="",
                              description="namespace of the node"),
        DeclareLaunchArgument("log_level", default_value="info",
                              description="debug, info, warn or error"),
        Node(
            package="vernier_ros",
            executable="detector",
            name="vernier_detector",
            namespace=LaunchConfiguration("namespace"),
            parameters=[LaunchConfiguration("params_file")],
            remappings=[("image", LaunchConfiguration("image"))],
            arguments=["--ros-args", "--log-level", LaunchConfiguration("log_level")],
            output="screen",
        ),
    ])
