"""GauSem on a real ROS 2 install: ``ros2 launch gausem gausem.launch.py params:=<file> segmentation:=false``.

Starts tracking_mapping, loop_detection and pose_graph (and segmentation when ``segmentation:=true``, for a
``semantics.segmenter: dinov2`` set-up) with one parameter file. Without ``launch_ros`` use ``gausem-launch``.
"""
import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.conditions import IfCondition
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

NODES = {"tracking_mapping": "gausem-tracking-mapping", "loop_detection": "gausem-loop-detection",
         "pose_graph": "gausem-pose-graph"}


def generate_launch_description():
    default_params = os.path.join(get_package_share_directory("gausem"), "params", "synthetic.yaml")
    params = LaunchConfiguration("params")
    use_sim_time = LaunchConfiguration("use_sim_time")
    nodes = [Node(package="gausem", executable=executable, name=name, output="screen",
                  parameters=[params, {"use_sim_time": use_sim_time}])
             for name, executable in NODES.items()]
    nodes.append(Node(package="gausem", executable="gausem-segmentation", name="segmentation", output="screen",
                      parameters=[params, {"use_sim_time": use_sim_time}],
                      condition=IfCondition(LaunchConfiguration("segmentation"))))
    return LaunchDescription([
        DeclareLaunchArgument("params", default_value=default_params, description="ROS parameter file"),
        DeclareLaunchArgument("use_sim_time", default_value="false", description="true when replaying a bag"),
        DeclareLaunchArgument("segmentation", default_value="false", description="run the segmentation node"),
        *nodes,
    ])
