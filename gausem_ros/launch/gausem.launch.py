"""GauSem on a real ROS 2 install: ``ros2 launch gausem gausem.launch.py params:=<file> segmentation:=false``.

Starts tracking_mapping, which closes loops itself (``loop_closure:=core``, default), or with ``loop_closure:=nodes``
also loop_detection and pose_graph; segmentation when ``segmentation:=true`` (a ``semantics.segmenter: dinov2``
set-up); one parameter file for all. Without ``launch_ros`` use ``gausem-launch``.
"""
import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.conditions import IfCondition
from launch.substitutions import LaunchConfiguration, PythonExpression
from launch_ros.actions import Node

LOOP_NODES = {"loop_detection": "gausem-loop-detection", "pose_graph": "gausem-pose-graph"}


def generate_launch_description():
    default_params = os.path.join(get_package_share_directory("gausem"), "params", "synthetic.yaml")
    params = LaunchConfiguration("params")
    use_sim_time = LaunchConfiguration("use_sim_time")
    loop_closure = LaunchConfiguration("loop_closure")
    distributed = IfCondition(PythonExpression(["'", loop_closure, "' == 'nodes'"]))
    nodes = [Node(package="gausem", executable="gausem-tracking-mapping", name="tracking_mapping", output="screen",
                  parameters=[params, {"use_sim_time": use_sim_time, "loop_closure": loop_closure}])]
    nodes += [Node(package="gausem", executable=executable, name=name, output="screen",
                   parameters=[params, {"use_sim_time": use_sim_time}], condition=distributed)
              for name, executable in LOOP_NODES.items()]
    nodes.append(Node(package="gausem", executable="gausem-segmentation", name="segmentation", output="screen",
                      parameters=[params, {"use_sim_time": use_sim_time}],
                      condition=IfCondition(LaunchConfiguration("segmentation"))))
    return LaunchDescription([
        DeclareLaunchArgument("params", default_value=default_params, description="ROS parameter file"),
        DeclareLaunchArgument("use_sim_time", default_value="false", description="true when replaying a bag"),
        DeclareLaunchArgument("segmentation", default_value="false", description="run the segmentation node"),
        DeclareLaunchArgument("loop_closure", default_value="core",
                              description="core: tracking_mapping closes loops; nodes: loop_detection + pose_graph"),
        *nodes,
    ])
