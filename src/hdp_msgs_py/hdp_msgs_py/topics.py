"""Default topic names and their QoS: the one place the graph's wiring is written down.

Every name is remappable (`--ros-args -r /hdp/instruction:=/my/instruction`).
"""

import functools
import typing

INSTRUCTION = '/hdp/instruction'
STATUS = '/hdp/status'
OUTCOME = '/hdp/outcome'            # std_msgs/String JSON, see hdp_msgs_py.outcome
NEXT_BEST_POSE = '/hdp/next_best_pose'
NEXT_BEST_POSE_MARKER = '/hdp/next_best_pose_marker'   # visualization_msgs/Marker, for RViz/Foxglove
PLANNER_CLOUD = '/hdp/planner/cloud'      # sensor_msgs/PointCloud2: what the agent saw (publish_cloud)
JOINT_STATES = '/joint_states'
ARM_TRAJECTORY = '/panda_arm_controller/joint_trajectory'
GRIPPER_TRAJECTORY = '/panda_gripper_controller/joint_trajectory'
# The same commands as actions, as real controllers take them: joint_trajectory_controller's
# control_msgs/FollowJointTrajectory and franka_gripper's control_msgs/GripperCommand.
ARM_ACTION = '/panda_arm_controller/follow_joint_trajectory'
GRIPPER_ACTION = '/franka_gripper/gripper_action'
TF_STATIC = '/tf_static'
TF = '/tf'
ROBOT_DESCRIPTION = '/robot_description'   # std_msgs/String URDF, latched (the sim's; robot_state_publisher's on a robot)
CLOCK = '/clock'
CAMERAS = ('front', 'side')
# The simulator's episode control (sim_bridge_node only; a real robot has none).
SIM_RESET = '/hdp/sim/reset'          # std_msgs/String JSON {"task", "seed", "variation"}
SIM_EPISODE = '/hdp/sim/episode'      # std_msgs/String JSON of the running episode (latched)
SIM_SUCCESS = '/hdp/sim/success'      # std_msgs/Bool: the task's success condition, 2 Hz
SIM_CAMERAS = '/hdp/sim/cameras'      # std_msgs/String "front,side": the cameras that publish (fault injection)

# Planner <-> controller, one segment at a time (see the hdp_planner and hdp_controller READMEs).
# The NBP's header.stamp is the segment's key: its gripper goal carries the same stamp, and
# the controller answers each NBP exactly once with it.
NEXT_BEST_GRIPPER = '/hdp/next_best_gripper'   # sensor_msgs/JointState, see GRIPPER_GOAL_JOINT
SEGMENT_RESULT = '/hdp/segment_result'         # std_msgs/Header: the NBP's stamp, frame_id the outcome
GRIPPER_GOAL_JOINT = 'panda_gripper'           # the goal's one name; position 0.08 m open, 0.0 closed
SEGMENT_DONE = 'done'                          # the arm arrived and the gripper acted
SEGMENT_FAILED = 'failed: '                    # followed by the reason; nothing moved, or it stopped
NBP_FRAME = 'world'                            # the only frame an NBP may be given in
# An operator's stop: planner_node serves STOP (std_srvs/Trigger), ends the running instruction
# 'stopped' and sends HOLD (std_msgs/Header, frame_id the reason) to controller_node, which holds the arm.
STOP = '/hdp/stop'
HOLD = '/hdp/hold'
DIAGNOSTICS = '/diagnostics'    # diagnostic_msgs/DiagnosticArray, 1 Hz from every node (hdp_ros.diagnostics)


def color_image(camera: str) -> str:
    return f'/camera/{camera}/color/image_raw'


def depth_image(camera: str) -> str:
    return f'/camera/{camera}/aligned_depth_to_color/image_raw'


def camera_info(camera: str) -> str:
    return f'/camera/{camera}/color/camera_info'


# image_transport publishes each transport at '<raw topic>/<transport name>', as
# realsense2_camera's streams appear with the compressed plugins installed
# (hdp_msgs_py.image_transport encodes and decodes them).
def color_image_compressed(camera: str) -> str:
    """sensor_msgs/CompressedImage, the 'compressed' transport (JPEG) of color_image."""
    return f'{color_image(camera)}/compressed'


def depth_image_compressed(camera: str) -> str:
    """sensor_msgs/CompressedImage, the 'compressedDepth' transport (16-bit PNG) of depth_image."""
    return f'{depth_image(camera)}/compressedDepth'


# QoS as ROS 2 uses it: cameras best effort, commands and state reliable, static
# transforms latched for late joiners; /hdp/status kept like /rosout, so an observer that
# joins (or is discovered) after a node said something, such as its start-up 'ready', still
# receives the recent lines. Written as plain policies, so that code without rclpy (recorded
# episodes) reads them; `topics.SENSOR_QOS` etc. are rclpy profiles, made on first use.
class QosPolicies(typing.NamedTuple):
    depth: int
    reliability: str           # member names shared by rclpy's and rosbags' enums
    durability: str


QOS_POLICIES = {
    'SENSOR_QOS': QosPolicies(5, 'BEST_EFFORT', 'VOLATILE'),
    'COMMAND_QOS': QosPolicies(10, 'RELIABLE', 'VOLATILE'),
    # Instructions and their outcomes: few, but they may come in bursts (a script, a dashboard),
    # and every one is answered; a history of 10 dropped 33 of 50 instructions sent 20 ms apart.
    'INSTRUCTION_QOS': QosPolicies(100, 'RELIABLE', 'VOLATILE'),
    'LATCHED_QOS': QosPolicies(1, 'RELIABLE', 'TRANSIENT_LOCAL'),
    'STATUS_QOS': QosPolicies(100, 'RELIABLE', 'TRANSIENT_LOCAL'),
    # tf2's static listener keeps 100: on a real robot several publishers latch onto /tf_static
    # (robot_state_publisher, each camera driver, the calibration), and depth 1 would keep one.
    'TF_STATIC_QOS': QosPolicies(100, 'RELIABLE', 'TRANSIENT_LOCAL'),
    'TF_QOS': QosPolicies(100, 'RELIABLE', 'VOLATILE'),         # tf2's
    'DIAGNOSTICS_QOS': QosPolicies(10, 'RELIABLE', 'VOLATILE'),  # diagnostic_updater's, a little deeper
}


@functools.cache
def _qos_profile(name: str):
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    policies = QOS_POLICIES[name]
    return QoSProfile(depth=policies.depth, reliability=ReliabilityPolicy[policies.reliability],
                      durability=DurabilityPolicy[policies.durability])


def __getattr__(name: str):
    if name in QOS_POLICIES:
        return _qos_profile(name)
    raise AttributeError(f'module {__name__!r} has no attribute {name!r}')
