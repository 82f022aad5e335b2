"""controller_node: each next-best pose -> a JointTrajectory for the arm, then the gripper, then a result.

A managed (lifecycle) node: configure loads the low level and warms it up, activate starts
taking NBPs, deactivate (and shutdown) fails the running segment and holds the arm (cancels
the FollowJointTrajectory goal, or sends joint_trajectory_controller's hold point), cleanup
lets the model go; an NBP that comes while the node is not active is answered 'failed'. The
logic is segment_controller.SegmentController; this node wires it to topics and
parameters. A 20 Hz timer advances the segment. Planning runs inside that timer
callback: the executor is single-threaded, so messages wait in their readers meanwhile
(the latest joint state and camera frames are all the node keeps), and the arm is at rest
while a segment is planned, so there is nothing to react to until the trajectory is out.
A second timer runs on the steady clock: under use_sim_time the first one stops with the
simulator, and the watchdog (hdp_ros.liveness) then fails the segment, naming the cause.
/diagnostics (hdp_ros.diagnostics), also on the steady clock, says how the node stands.
"""


import collections
import time

import torch
from action_msgs.msg import GoalStatus, GoalStatusArray
from rclpy.action.graph import get_action_client_names_and_types_by_node
from rclpy.clock import Clock, ClockType
from rclpy.qos import qos_profile_action_status_default

from hdp_data import depth_filters
from hdp_motion import panda
from hdp_msgs_py import topics
from hdp_ros import diagnostics, image_input, ros
from hdp_ros.liveness import ROBOT_HINT, Liveness
from hdp_msgs_py.msg import CameraInfo, Header, JointState, JointTrajectory, PoseStamped, TFMessage
from hdp_msgs_py.outcome import StatusLine

from .action_clients import ArmAction, GripperAction
from .inputs import FilteredDepth
from .methods import LEARNED, METHODS
from .policy import load_policy
from .segment_controller import ArmCommand, FingerCommand, HoldArm, SegmentController, SegmentResult
from .segment_planning import PLAN_ATTEMPTS, REACH_TOLERANCE_DEG, REACH_TOLERANCE_M, warm_up
from .trajectory import VELOCITY_SCALE

_STEP_S = 0.05
_WATCH_S = 0.5
_CAMERA = 'front'              # RK-Diffuser sees the front camera only, as in training
INTERFACES = ('topic', 'action')
# Least rates /diagnostics expects: the 20 Hz step follows the arm on /joint_states (the sim sends
# 120 Hz, a robot's broadcaster as much or more); the sim's cameras stream 2 Hz by default.
_JOINT_STATE_HZ = 20.0
_CAMERA_HZ = 2.0
_CAMERA_HINT = f'is sim_bridge_node (or the {_CAMERA} camera driver) running, and its camera selected?'


def _segment_settings(p: dict) -> dict:
    """SegmentController.configure()'s arguments from the node's parameters."""
    return {'velocity_scale': p['velocity_scale'], 'segment_timeout_s': p['segment_timeout_s'],
            'reach_tolerance': (p['reach_tolerance_m'], p['reach_tolerance_deg']),
            'plan_attempts': p['plan_attempts'], 'carry_on_unsettled': p['unsettled'] == 'carry_on'}


class ControllerNode(ros.LifecycleNode):
    PARAMETERS = {
        **ros.LifecycleNode.LIFECYCLE_PARAMETERS,
        'method': ('rkd', f'low-level method: {" | ".join(METHODS)}'),
        'checkpoint': ('', "RK-Diffuser checkpoint; '' = models/rk_diffuser_11tasks.pt ($HDP_MODELS_DIR)"),
        'sampler': ('ddim', 'ddim (5 steps, fast) | ddpm (100 steps)'),
        'cpu_threads': (1, "torch's CPU threads; 1 keeps this node from fighting the simulator and the other node "
                           'for two cores (rkd planned in 0.5 s with torch\'s default 2, 0.08 s with 1)'),
        'device': ('cpu', 'where the diffusers sample: cpu | cuda | cuda:N | auto (refinement stays on the CPU)'),
        'segment_timeout_s': (10.0, 's after the trajectory ends for the arm to come to rest'),
        'unsettled': ('fail', "an arm not at rest segment_timeout_s after the trajectory's end: fail the segment, "
                              'or carry_on from where it is (as the experts and hdp eval hierarchy do)'),
        'state_timeout_s': (5.0, 'wall-clock s without /joint_states (or a moving clock) before a segment fails'),
        'robot_type': ('panda', 'panda | fr3: the joint limits trajectories are refined, checked and timed against'),
        'velocity_scale': (VELOCITY_SCALE, "fraction of the robot's velocity limits, (0, 1]"),
        'reach_tolerance_m': (REACH_TOLERANCE_M, 'a plan ending farther from its NBP is refused (m)'),
        'reach_tolerance_deg': (REACH_TOLERANCE_DEG, 'a plan ending turned farther from its NBP is refused (deg)'),
        'plan_attempts': (PLAN_ATTEMPTS, 'plans drawn (fresh noise each) before one ending beyond the tolerance '
                                         'is refused'),
        'joint_prefix': ('panda', "joint name prefix: 'fr3' for an FR3"),
        'depth_filter': ('none', "'none' or 'realsense': librealsense's post-processing chain (spatial, temporal, "
                                'hole filling; hdp_data.depth_filters) on depth as it arrives, as `hdp eval '
                                "--depth-filter`; for a camera driver that does not filter"),
        'image_transport': ('raw', "'raw': the cameras' sensor_msgs/Image; 'compressed': image_transport's "
                                   'compressed (JPEG colour) and compressedDepth (16-bit PNG depth) topics, for '
                                   'a network link (hdp_ros.image_input)'),
        'arm_interface': ('topic', "topic: JointTrajectory to the controller's topic; action: FollowJointTrajectory"),
        'arm_action': (topics.ARM_ACTION, "FollowJointTrajectory action: a JTC's <controller>/follow_joint_trajectory"),
        'gripper_interface': ('topic', 'topic: JointTrajectory of the fingers; action: GripperCommand (franka)'),
        'gripper_action': (topics.GRIPPER_ACTION, 'the GripperCommand action (franka_gripper serves gripper_action)'),
    }

    # Read when a segment starts: a change reaches the next segment (and liveness at once).
    RUNTIME = frozenset({'velocity_scale', 'segment_timeout_s', 'unsettled', 'state_timeout_s', 'reach_tolerance_m',
                         'reach_tolerance_deg', 'plan_attempts'})

    @staticmethod
    def check_parameters(p: dict) -> None:
        if p['cpu_threads'] < 1:
            raise ros.StartupError(f"parameter 'cpu_threads' must be >= 1, got {p['cpu_threads']}")
        if p['method'] not in METHODS:
            raise ros.StartupError(f"parameter 'method' must be one of {', '.join(METHODS)}, got {p['method']!r}")
        if not 0.0 < p['velocity_scale'] <= 1.0:
            raise ros.StartupError(f"parameter 'velocity_scale' must be in (0, 1], got {p['velocity_scale']}")
        if p['unsettled'] not in ('fail', 'carry_on'):
            raise ros.StartupError(f"parameter 'unsettled' must be fail or carry_on, got {p['unsettled']!r}")
        if p['image_transport'] not in image_input.TRANSPORTS:
            raise ros.StartupError("parameter 'image_transport' must be one of "
                                   f"{', '.join(image_input.TRANSPORTS)}, got {p['image_transport']!r}")
        if p['depth_filter'] not in depth_filters.PRESETS:
            raise ros.StartupError("parameter 'depth_filter' must be one of "
                                   f"{', '.join(depth_filters.PRESETS)}, got {p['depth_filter']!r}")
        for name in ('arm_interface', 'gripper_interface'):
            if p[name] not in INTERFACES:
                raise ros.StartupError(f"parameter {name!r} must be topic or action, got {p[name]!r}")
        for name in ('segment_timeout_s', 'state_timeout_s', 'reach_tolerance_m', 'reach_tolerance_deg'):
            if not p[name] > 0.0:
                raise ros.StartupError(f'parameter {name!r} must be > 0, got {p[name]}')
        if p['plan_attempts'] < 1:
            raise ros.StartupError(f"parameter 'plan_attempts' must be >= 1, got {p['plan_attempts']}")
        try:
            panda.limits_for(p['robot_type'])
        except ValueError as err:
            raise ros.StartupError(f"parameter 'robot_type': {err}") from None

    def __init__(self):
        super().__init__('controller_node')
        p = self.declare_parameter_table()
        self.logic = self.arm_action = self.gripper_action = self._depth_filter = None
        # In every state: each NBP is answered (failed unless active), and the node says how it stands.
        self._result = self.create_publisher(Header, topics.SEGMENT_RESULT, topics.COMMAND_QOS)
        self.create_subscription(PoseStamped, topics.NEXT_BEST_POSE, self._on_nbp, topics.COMMAND_QOS)
        diagnostics.advertise(self, self._diagnostics)
        if not p['autostart']:
            self.status.info(f'unconfigured: waiting for a lifecycle manager ({ros.MANAGER_HINT})')

    def configure(self, p: dict) -> None:
        limits = panda.limits_for(p['robot_type'])
        torch.set_num_threads(p['cpu_threads'])
        try:
            policy = load_policy(p['method'], p['checkpoint'] or None, sampler=p['sampler'], limits=limits,
                                 device=p['device'])
        except ValueError as err:          # CheckpointError: missing, damaged or not ours; a device not here
            raise ros.StartupError(f"cannot load the {p['method']} policy: {err}") from None
        arm_joints = panda.joint_names(p['joint_prefix'])
        warm_up_s = warm_up(policy, arm_joints, limits)    # the first segment pays no first-call cost
        self.logic = SegmentController(
            policy, needs_points=p['method'] in LEARNED, arm_joints=arm_joints,
            finger_joints=panda.finger_joint_names(p['joint_prefix']), limits=limits, **_segment_settings(p))

        self._arm = self.create_publisher(JointTrajectory, topics.ARM_TRAJECTORY, topics.COMMAND_QOS)
        self._gripper = self.create_publisher(JointTrajectory, topics.GRIPPER_TRAJECTORY, topics.COMMAND_QOS)
        # As real robots take commands: joint_trajectory_controller's and franka_gripper's actions.
        # (Parameters rather than remapping: rcl remaps action names only since 2024, rcl#1170.)
        self.arm_action = (ArmAction(self, p['arm_action'], arm_joints, self._send, self.logic.arm_failed)
                           if p['arm_interface'] == 'action' else None)
        self.gripper_action = (GripperAction(self, p['gripper_action']) if p['gripper_interface'] == 'action'
                               else None)
        # Our segment is ours: any other command to the arm, on its topic or as a goal of its action,
        # ends the running segment (the arm controller follows the newest command, and says nothing).
        self._arm_action_name = p['arm_action']
        self._own_trajectories: collections.deque = collections.deque(maxlen=8)   # what we published
        self._foreign_goals: set[bytes] = set()
        self._arm_topic = self.create_subscription(JointTrajectory, topics.ARM_TRAJECTORY, self._on_arm_trajectory,
                                                   topics.COMMAND_QOS)
        self.create_subscription(GoalStatusArray, f"{p['arm_action']}/_action/status", self._on_arm_goals,
                                 qos_profile_action_status_default)
        # planner_node's /hdp/stop: frame_id says why.
        self.create_subscription(Header, topics.HOLD, lambda m: self._send(self.logic.hold(m.frame_id)),
                                 topics.COMMAND_QOS)
        self.create_subscription(JointState, topics.NEXT_BEST_GRIPPER,
                                 lambda m: self._send(self.logic.on_gripper_goal(m)), topics.COMMAND_QOS)
        self.liveness = Liveness(p['state_timeout_s'])
        self._joint_rate = diagnostics.RateMeter(time.monotonic())
        self._depth_rate = diagnostics.RateMeter(time.monotonic()) if p['method'] in LEARNED else None
        self._last_plan = None             # the last ArmCommand's PlanReport, for /diagnostics
        self._model = {'method': p['method'], 'checkpoint': p['checkpoint'] or 'default',
                       'device': str(policy.device) if p['method'] in LEARNED else 'cpu', 'warm_up_s': warm_up_s,
                       'sampler': p['sampler'] if p['method'] in LEARNED else ''}
        self.create_subscription(JointState, topics.JOINT_STATES, self._on_joint_state, topics.COMMAND_QOS)
        self.dropped_frames = image_input.DroppedFrames(self.get_logger())
        settings = depth_filters.preset(p['depth_filter'])
        self._depth_filter = None if settings is None else FilteredDepth(settings)
        image_input.subscribe(self, _CAMERA, 'depth', p['image_transport'], self._on_depth, self.dropped_frames)
        self.create_subscription(CameraInfo, topics.camera_info(_CAMERA), self._on_camera_info, topics.SENSOR_QOS)
        self.create_subscription(TFMessage, topics.TF_STATIC, self.logic.on_tf_static, topics.TF_STATIC_QOS)
        self.create_timer(_STEP_S, self._step)
        # On the wall clock: under use_sim_time the timer above stops with the simulator.
        self.create_timer(_WATCH_S, self._watch, clock=Clock(clock_type=ClockType.STEADY_TIME))
        self.status.info(f"configured: method {p['method']} on {self._model['device']} "
                         f'(warmed up in {warm_up_s:.2f} s)')

    def activate(self) -> None:
        self.liveness.heard(time.monotonic())     # an inactive node heard nothing it needed
        sampler = f" ({self._model['sampler']} sampler)" if self._model['sampler'] else ''
        self.status.info(f"ready: method {self._model['method']}{sampler}, velocity scale "
                         f"{self.get_parameter('velocity_scale').value} "
                         f"(warmed up in {self._model['warm_up_s']:.2f} s)")

    def deactivate(self, why: str, shutting_down: bool) -> None:
        self._send(self.logic.hold(why))
        self.status.info(f'{"shutting down" if shutting_down else "inactive"}: {why}')

    def forget(self) -> None:
        self.logic = self.arm_action = self.gripper_action = self._depth_filter = None

    def apply_parameters(self, p: dict) -> None:
        if self.logic is None:             # unconfigured: configure reads them
            return
        self.logic.configure(**_segment_settings(p))
        self.liveness.set_timeout(p['state_timeout_s'])

    def _on_arm_trajectory(self, msg):
        if not any(msg == own for own in self._own_trajectories):
            self._send(self.logic.preempted(f'a trajectory on {self._arm_topic.topic_name}; '
                                            f'{self._other_commanders()}'))

    def _on_arm_goals(self, msg):
        for status in msg.status_list:
            goal_id = bytes(status.goal_info.goal_id.uuid)
            if (status.status not in (GoalStatus.STATUS_ACCEPTED, GoalStatus.STATUS_EXECUTING)
                    or goal_id in self._foreign_goals
                    or (self.arm_action is not None and self.arm_action.owns(goal_id))):
                continue
            self._foreign_goals.add(goal_id)
            self._send(self.logic.preempted(f'FollowJointTrajectory goal {goal_id.hex()[:8]} on '
                                            f'{self._arm_action_name}; {self._other_commanders()}'))

    def _other_commanders(self) -> str:
        """Who else may command the arm, from the ROS graph: other publishers of its trajectory
        topic and other clients of its FollowJointTrajectory action."""
        me = self.get_fully_qualified_name()
        found = {f'{_qualified(i.node_namespace, i.node_name)} ({self._arm_topic.topic_name})'
                 for i in self.get_publishers_info_by_topic(self._arm_topic.topic_name)}
        for name, namespace in self.get_node_names_and_namespaces():
            clients = get_action_client_names_and_types_by_node(self, name, namespace)
            if any(action == self._arm_action_name for action, _ in clients):
                found.add(f'{_qualified(namespace, name)} ({self._arm_action_name} client)')
        found = sorted(f for f in found if not f.startswith(me + ' '))
        return f'other commanders of the arm: {", ".join(found)}' if found else 'no other commander on the ROS graph'

    def _now(self) -> float:
        return self.get_clock().now().nanoseconds * 1e-9

    def _step(self):
        if not self.active:
            return
        started = time.monotonic()
        self._send(self.logic.step(self._now()))
        if time.monotonic() - started > _WATCH_S:      # it planned: no message was taken meanwhile
            self.liveness.excuse(time.monotonic())

    def _on_joint_state(self, msg):
        self.liveness.heard(time.monotonic())
        self._joint_rate.tick(time.monotonic())
        self.logic.on_joint_state(msg)

    def _on_camera_info(self, msg):
        if self._depth_filter is not None:
            self._depth_filter.on_camera_info(msg)
        self.logic.on_camera_info(msg)

    def _on_depth(self, msg):
        if self._depth_rate is not None:
            self._depth_rate.tick(time.monotonic())
        if self._depth_filter is not None:
            try:
                msg = self._depth_filter.filtered(msg)
            except ValueError as err:              # not 16UC1 millimetres: nothing the chain can read
                self.dropped_frames.dropped(topics.depth_image(_CAMERA), str(err))
                return
            if msg is None:                        # before the first camera_info: the chain needs its focal length
                return
        self.logic.on_depth(msg)

    def _diagnostics(self, wall_s: float) -> list:
        name = self.get_name()
        state = diagnostics.lifecycle_status(name, self.state_label, self.failure)
        if self.logic is None:
            return [state]
        timeout_s = self.liveness.timeout_s
        out = [state, diagnostics.status(name, 'model', diagnostics.OK,
                                  f"{self._model['method']} on {self._model['device']}", self._model),
               diagnostics.topic_status(name, 'joint states', topics.JOINT_STATES, self._joint_rate, wall_s,
                                        _JOINT_STATE_HZ, timeout_s, ROBOT_HINT)]
        if self._depth_rate is not None:
            out.append(diagnostics.topic_status(name, f'{_CAMERA} depth', topics.depth_image(_CAMERA),
                                                self._depth_rate, wall_s, _CAMERA_HZ, timeout_s, _CAMERA_HINT))
        plan = self._last_plan
        if plan is None:
            out.append(diagnostics.status(name, 'last segment', diagnostics.OK, 'no segment planned yet'))
        else:
            out.append(diagnostics.status(name, 'last segment', diagnostics.OK,
                                          f'planned in {plan.seconds:.2f} s, {plan.draws} draw(s)',
                                          {'seconds': plan.seconds, 'draws': plan.draws, 'method': plan.method}))
        return out + [diagnostics.liveness_status(name, self.liveness, wall_s, self._now())]

    def _watch(self):
        if not self.active:
            return
        stalled = self.liveness.stalled(time.monotonic())
        if stalled is not None:
            self.status.error(stalled)
            return
        problem = self.liveness.problem(time.monotonic(), self._now())
        if problem is not None:
            self._send(self.logic.robot_gone(problem))

    def _on_nbp(self, msg):
        if self.active:
            self._send(self.logic.on_nbp(msg, self._now()))
            return
        why = f'controller_node is {self.state_label} ({ros.MANAGER_HINT})'
        self._send([StatusLine(f'refused segment: {why}', error=True),
                    SegmentResult(Header(stamp=msg.header.stamp, frame_id=topics.SEGMENT_FAILED + why))])

    def _publish_arm(self, trajectory) -> None:
        self._own_trajectories.append(trajectory)       # our own copy comes back to _on_arm_trajectory
        self._arm.publish(trajectory)

    def _send(self, outputs):
        for out in outputs:
            match out:
                case StatusLine():
                    self.status.line(out)
                case ArmCommand():
                    self._last_plan = out.plan
                    if self.arm_action is not None:
                        self.arm_action.send(out.stamp, out.trajectory)
                    else:
                        self._publish_arm(out.trajectory)
                case HoldArm() if self.arm_action is not None:
                    self.arm_action.cancel()
                case HoldArm() if out.trajectory is not None:
                    self._publish_arm(out.trajectory)
                case FingerCommand() if self.gripper_action is not None:
                    self.gripper_action.send(out.trajectory)
                case FingerCommand():
                    self._gripper.publish(out.trajectory)
                case SegmentResult():
                    if self.arm_action is not None:
                        self.arm_action.segment_ended(out.header)
                    self._result.publish(out.header)


def _qualified(namespace: str, name: str) -> str:
    return f'{namespace.rstrip("/")}/{name}'


def main(args=None):
    ros.run(ControllerNode, args, 'controller_node')


if __name__ == '__main__':
    main()
