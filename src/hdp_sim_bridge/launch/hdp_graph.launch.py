"""Bring up the HDP graph: sim_bridge_node, planner_node and controller_node.

    ros2 launch hdp_sim_bridge hdp_graph.launch.py

All three read their parameters from share/hdp_sim_bridge/config/hdp_graph.yaml.
"""

import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch_ros.actions import Node


def generate_launch_description():
    params = os.path.join(
        get_package_share_directory('hdp_sim_bridge'), 'config', 'hdp_graph.yaml')
    return LaunchDescription([
        Node(package='hdp_sim_bridge', executable='sim_bridge_node',
             name='sim_bridge_node', parameters=[params], output='screen'),
        Node(package='hdp_planner', executable='planner_node',
             name='planner_node', parameters=[params], output='screen'),
        Node(package='hdp_controller', executable='controller_node',
             name='controller_node', parameters=[params], output='screen'),
    ])
