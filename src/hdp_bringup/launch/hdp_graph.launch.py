"""Bring up the HDP graph: sim_bridge_node, planner_node and controller_node.

    ros2 launch hdp_bringup hdp_graph.launch.py

All three read their parameters from share/hdp_bringup/config/hdp_graph.yaml. The
nodes are launch_cli.NODES, the list `hdp launch` starts without ROS 2.
"""

import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch_ros.actions import Node

from hdp_bringup.launch_cli import NODES


def generate_launch_description():
    params = os.path.join(
        get_package_share_directory('hdp_bringup'), 'config', 'hdp_graph.yaml')
    return LaunchDescription([
        Node(package=package, executable=name, name=name, parameters=[params], output='screen')
        for name, package in NODES.items()
    ])
