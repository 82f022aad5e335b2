"""HDP on a real Franka Panda (or FR3) with two RealSense D415s. UNTESTED: written against
franka_ros2 and realsense-ros 4.x, never run here (no robot, no ROS 2 on our machines).

    ros2 launch hdp_bringup hdp_real_panda.launch.py robot_ip:=172.16.0.2 \
        front_serial:=_123456789012 side_serial:=_210987654321 \
        front_extrinsics:="0.75 0.0 1.35 -0.653 0.653 -0.271 0.271" \
        side_extrinsics:="0.2 -0.6 1.2 ..."

What it wires up:
- franka_bringup's franka.launch.py (arm, gripper node, /joint_states at 30 Hz with the
  fingers merged in) and a spawner for its `joint_trajectory_controller`; controller_node's
  /panda_arm_controller/joint_trajectory is remapped onto that controller.
- realsense2_camera twice, as /camera/front/... and /camera/side/... (colour 640x480, depth
  aligned to colour), with publish_tf off: the planner reads each camera's pose as one
  static transform world -> <camera>_color_optical_frame, published here from the
  *_extrinsics arguments ("x y z qx qy qz qw", from your hand-eye calibration).
- The frame `world` is HDP's: the arm base (panda_link0) sits at (0, 0, 0.75) in it, as in
  the simulator and the training data; published here too.
- planner_node and controller_node with config/hdp_real_panda.yaml.

Not covered: franka_ros2 drives the gripper through the franka_gripper actions
(move/grasp), not the JointTrajectory controller_node sends on
/panda_gripper_controller/joint_trajectory; a small adapter node is needed for that.
"""

import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, IncludeLaunchDescription, OpaqueFunction
from launch.launch_description_sources import PythonLaunchDescriptionSource
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

from hdp_motion.panda import ROBOT_BASE

CAMERAS = ('front', 'side')
ROBOT_BASE_IN_WORLD = ' '.join(str(v) for v in (*ROBOT_BASE, 0, 0, 0, 1))    # x y z qx qy qz qw, facing +x


def _static_transform(parent: str, child: str, pose: str) -> Node:
    x, y, z, qx, qy, qz, qw = pose.split()
    return Node(package='tf2_ros', executable='static_transform_publisher', name=f'{child}_tf',
                arguments=['--x', x, '--y', y, '--z', z, '--qx', qx, '--qy', qy, '--qz', qz, '--qw', qw,
                           '--frame-id', parent, '--child-frame-id', child])


def _nodes(context):
    arg = {name: LaunchConfiguration(name).perform(context) for name in (
        'robot_ip', 'arm_id', 'use_fake_hardware', 'front_serial', 'side_serial',
        'front_extrinsics', 'side_extrinsics')}
    params = os.path.join(get_package_share_directory('hdp_bringup'), 'config', 'hdp_real_panda.yaml')
    prefix = {'joint_prefix': arg['arm_id']}
    franka = IncludeLaunchDescription(
        PythonLaunchDescriptionSource(os.path.join(
            get_package_share_directory('franka_bringup'), 'launch', 'franka.launch.py')),
        launch_arguments={'robot_ip': arg['robot_ip'], 'load_gripper': 'true',
                          'use_fake_hardware': arg['use_fake_hardware']}.items())
    trajectory_controller = Node(package='controller_manager', executable='spawner',
                                 arguments=['joint_trajectory_controller'])
    cameras = [IncludeLaunchDescription(
        PythonLaunchDescriptionSource(os.path.join(
            get_package_share_directory('realsense2_camera'), 'launch', 'rs_launch.py')),
        launch_arguments={'camera_namespace': 'camera', 'camera_name': camera,
                          'serial_no': arg[f'{camera}_serial'], 'align_depth.enable': 'true',
                          'rgb_camera.color_profile': '640,480,30', 'depth_module.depth_profile': '640,480,30',
                          'publish_tf': 'false'}.items())
        for camera in CAMERAS]
    transforms = [_static_transform('world', f'{arg["arm_id"]}_link0', ROBOT_BASE_IN_WORLD)] + [
        _static_transform('world', f'{camera}_color_optical_frame', arg[f'{camera}_extrinsics'])
        for camera in CAMERAS]
    hdp = [
        Node(package='hdp_planner', executable='planner_node', name='planner_node',
             parameters=[params, prefix], output='screen'),
        Node(package='hdp_controller', executable='controller_node', name='controller_node',
             parameters=[params, prefix, {'robot_type': 'fr3' if arg['arm_id'] == 'fr3' else 'panda'}],
             output='screen',
             remappings=[('/panda_arm_controller/joint_trajectory',
                          '/joint_trajectory_controller/joint_trajectory')]),
    ]
    return [franka, trajectory_controller, *cameras, *transforms, *hdp]


def generate_launch_description():
    return LaunchDescription([
        DeclareLaunchArgument('robot_ip', description='hostname or IP address of the robot (FCI)'),
        DeclareLaunchArgument('arm_id', default_value='panda', description='panda, or fr3 for an FR3'),
        DeclareLaunchArgument('use_fake_hardware', default_value='false',
                              description="franka_ros2's fake hardware: the graph without the arm"),
        DeclareLaunchArgument('front_serial', description="front D415's serial number, e.g. _123456789012"),
        DeclareLaunchArgument('side_serial', description="side D415's serial number"),
        DeclareLaunchArgument('front_extrinsics',
                              description='"x y z qx qy qz qw": front_color_optical_frame in world'),
        DeclareLaunchArgument('side_extrinsics',
                              description='"x y z qx qy qz qw": side_color_optical_frame in world'),
        OpaqueFunction(function=_nodes),
    ])
