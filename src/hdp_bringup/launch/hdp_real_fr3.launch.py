"""HDP on a real Franka Research 3 with two RealSense D415s, on ROS 2 Jazzy's franka_ros2.
UNTESTED on hardware: no robot and no ROS 2 launch here. What can be checked without them is
(tests/test_real_robot.py: what it starts, with which parameters, topic and frame names).

    ros2 launch hdp_bringup hdp_real_fr3.launch.py robot_ip:=172.16.0.2 \
        front_serial:=_123456789012 side_serial:=_210987654321 \
        front_extrinsics:="0.75 0.0 1.35 -0.653 0.653 -0.271 0.271" side_extrinsics:="..."

What it starts:
- franka_bringup's franka.launch.py with robot_type (fr3) and our controllers YAML
  (config/hdp_fr3_controllers.yaml): Jazzy's own controllers.yaml defines no joint trajectory
  controller, so ours defines `hdp_arm_controller` (joint_trajectory_controller on the effort
  interface) beside the two broadcasters franka.launch.py spawns, and a spawner for it.
  controller_node's arm trajectory is remapped onto it.
- realsense2_camera twice, as /camera/front/... and /camera/side/... (colour 640x480, depth
  aligned to colour) with their own TF off: the planner wants each camera's pose as one
  static transform world -> <camera>_color_optical_frame, from the *_extrinsics arguments
  ("x y z qx qy qz qw", your hand-eye calibration).
- world -> base: franka_description's URDF gives <robot>_link0 the parent `base`, so the arm's
  mounting in HDP's world frame is published onto `base` (base_pose, default the simulator's:
  (0, 0, 0.75), facing +x), never onto link0, which would give it a second parent.
- planner_node and controller_node with config/hdp_real_fr3.yaml: the FR3's joint names
  (fr3_joint1..7, fr3_finger_joint1/2) and joint limits (controller_node's robot_type).

A Panda (FER) cannot run on Jazzy's franka_ros2: it builds against libfranka 0.20.5
(dependency.repos), and a FER's firmware speaks only to libfranka < 0.10 (Franka's
compatibility matrix). controller_node commands both as actions (config/hdp_real_fr3.yaml):
FollowJointTrajectory to hdp_arm_controller, GripperCommand to franka_gripper's gripper_action.
"""

import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, IncludeLaunchDescription, OpaqueFunction
from launch.launch_description_sources import PythonLaunchDescriptionSource
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

from hdp_bringup.launch_cli import MANAGED, MANAGER
from hdp_motion.panda import ROBOT_BASE

CAMERAS = ('front', 'side')
ARM_CONTROLLER = 'hdp_arm_controller'
ROBOT_TYPE = 'fr3'           # franka_ros2's robot_type; a FER cannot run on Jazzy (see above)
ARGUMENTS = {
    'robot_ip': ('172.16.0.2', 'the robot controller (FCI) address'),
    'use_fake_hardware': ('false', "franka_ros2's fake hardware, to try the wiring without a robot"),
    'base_pose': (' '.join(str(v) for v in (*ROBOT_BASE, 0, 0, 0, 1)), 'world -> base: x y z qx qy qz qw'),
    'front_serial': ('', 'serial number of the front D415, e.g. _123456789012'),
    'side_serial': ('', 'serial number of the side D415'),
    'front_extrinsics': ('', 'world -> front_color_optical_frame: x y z qx qy qz qw'),
    'side_extrinsics': ('', 'world -> side_color_optical_frame: x y z qx qy qz qw'),
}


def static_transform(parent: str, child: str, pose: str) -> Node:
    x, y, z, qx, qy, qz, qw = pose.split()
    return Node(package='tf2_ros', executable='static_transform_publisher', name=f'{child}_tf',
                arguments=['--x', x, '--y', y, '--z', z, '--qx', qx, '--qy', qy, '--qz', qz, '--qw', qw,
                           '--frame-id', parent, '--child-frame-id', child])


def camera(name: str, serial: str) -> Node:
    """realsense2_camera as /camera/<name>/...: color/image_raw, aligned_depth_to_color/image_raw,
    color/camera_info, frames <name>_color_optical_frame (realsense-ros 4.x names)."""
    return Node(package='realsense2_camera', executable='realsense2_camera_node', namespace='camera', name=name,
                parameters=[{'camera_name': name, 'serial_no': serial, 'align_depth.enable': True,
                             'rgb_camera.color_profile': '640x480x30', 'depth_module.depth_profile': '640x480x30',
                             'publish_tf': False}], output='screen')


def _nodes(context):
    arg = {name: LaunchConfiguration(name).perform(context) for name in ARGUMENTS}
    share = get_package_share_directory('hdp_bringup')
    params = os.path.join(share, 'config', 'hdp_real_fr3.yaml')
    robot = {'joint_prefix': ROBOT_TYPE, 'robot_type': ROBOT_TYPE}
    franka = IncludeLaunchDescription(
        PythonLaunchDescriptionSource(os.path.join(
            get_package_share_directory('franka_bringup'), 'launch', 'franka.launch.py')),
        launch_arguments={'robot_type': ROBOT_TYPE, 'robot_ip': arg['robot_ip'], 'load_gripper': 'true',
                          'use_fake_hardware': arg['use_fake_hardware'],
                          'controllers_yaml': os.path.join(share, 'config', 'hdp_fr3_controllers.yaml')}.items())
    arm_controller = Node(package='controller_manager', executable='spawner', arguments=[ARM_CONTROLLER])
    transforms = [static_transform('world', 'base', arg['base_pose'])] + [
        static_transform('world', f'{name}_color_optical_frame', arg[f'{name}_extrinsics']) for name in CAMERAS]
    hdp = [
        Node(package='hdp_planner', executable='planner_node', name='planner_node',
             parameters=[params, {'joint_prefix': ROBOT_TYPE}], output='screen'),
        Node(package='hdp_controller', executable='controller_node', name='controller_node',
             parameters=[params, robot], output='screen',
             remappings=[('/panda_arm_controller/joint_trajectory', f'/{ARM_CONTROLLER}/joint_trajectory')]),
        # Brings both to active, controller first (its section of the params file: autostart, timeouts).
        Node(package='hdp_bringup', executable=MANAGER, name=MANAGER, output='screen',
             parameters=[params, {'node_names': list(MANAGED)}]),
    ]
    return [franka, arm_controller, *[camera(name, arg[f'{name}_serial']) for name in CAMERAS], *transforms, *hdp]


def generate_launch_description():
    return LaunchDescription(
        [DeclareLaunchArgument(name, default_value=default, description=description)
         for name, (default, description) in ARGUMENTS.items()]
        + [OpaqueFunction(function=_nodes)])
