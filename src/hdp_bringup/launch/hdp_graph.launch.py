"""Bring up the HDP graph: sim_bridge_node, planner_node and controller_node (managed nodes,
brought to active by lifecycle_manager, controller first).

    ros2 launch hdp_bringup hdp_graph.launch.py
    ros2 launch hdp_bringup hdp_graph.launch.py task:=open_drawer seed:=3 method:=planner

Every node reads its section of `params_file` (default share/hdp_bringup/config/hdp_graph.yaml);
`task` and `seed` go to sim_bridge_node and `method` to controller_node when given. The nodes
are launch_cli.NODES, the list `hdp launch` starts without ROS 2 (it takes the same arguments
as --task, --seed, --method and --params-file).
"""

import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

from hdp_bringup.launch_cli import MANAGED, MANAGER, METHODS, NODES, launch_overrides

ARGUMENTS = {
    'task': ('', 'the simulated task (default: the params file\'s)'),
    'seed': ('', 'the scene seed (default: the params file\'s)'),
    'method': ('', f'the low level: {" | ".join(METHODS)} (default: the params file\'s)'),
    'params_file': (os.path.join(get_package_share_directory('hdp_bringup'), 'config', 'hdp_graph.yaml'),
                    'node parameters'),
}


def _nodes(context):
    value = {name: LaunchConfiguration(name).perform(context) for name in ARGUMENTS}
    overrides = launch_overrides(value['task'] or None, value['seed'] or None, value['method'] or None)
    return [Node(package=package, executable=name, name=name, output='screen',
                 parameters=[value['params_file'], overrides.get(name, {})])
            for name, package in NODES.items()] + [
        Node(package='hdp_bringup', executable=MANAGER, name=MANAGER, output='screen',
             parameters=[value['params_file'], {'node_names': list(MANAGED)}])]


def generate_launch_description():
    return LaunchDescription(
        [DeclareLaunchArgument(name, default_value=default, description=description)
         for name, (default, description) in ARGUMENTS.items()]
        + [OpaqueFunction(function=_nodes)])
