"""sim_bridge_node: a simulated Panda and two D415 cameras, with the topics of the real ones.

It is the graph's clock: it publishes /clock from simulation time and keeps
its own timers on the wall clock, stepping physics at ``real_time_factor``. /diagnostics
(hdp_ros.diagnostics) says whether it keeps up: the real-time factor achieved, the cameras' rates.
"""

import dataclasses
import json
import math
import time

import numpy as np
from control_msgs.action import FollowJointTrajectory, GripperCommand
from rclpy.action import ActionServer, CancelResponse, GoalResponse
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy.task import Future

from hdp_motion import panda
from hdp_msgs_py import image_transport, topics
from hdp_ros import diagnostics, ros
from hdp_msgs_py.conversions import duration_to_seconds
from hdp_msgs_py.msg import (Bool, CameraInfo, Clock, CompressedImage, Image, JointState, JointTrajectory, String,
                             TFMessage)

from .bridge import SimBridge, parse_reset
from .robot_state import robot_description
from .sensor_model import D415, PROFILES, SensorSettings, profile_named
from .world import TIME_STEP

_MAX_STEPS_PER_TICK = 48              # catch up at most 0.2 s of sim time per tick
# joint_trajectory_controller's defaults when a goal sets none: its goal time tolerance, and a
# goal tolerance per joint (rad) that an arm at rest on its last point meets.
DEFAULT_GOAL_TOLERANCE = 0.02
DEFAULT_GOAL_TIME_TOLERANCE = 1.0
GRIPPER_SETTLE_S = 3.0                 # franka_gripper's moves end within this (sim time)
GRIPPER_STILL_S = 0.2                  # fingers unmoved this long have stopped (on the target or an object)
GRIPPER_REACHED = 0.005                # m of width: franka_gripper's grasp epsilon
SLOW_RTF = 0.8                         # /diagnostics warns below this fraction of the factor asked
CAMERA_TIMEOUT_S = 5.0                 # planner_node's camera_timeout_s: silent longer, its work fails
_TOO_SLOW = 'lower camera_width/camera_height, camera_rate_hz or real_time_factor'


def gripper_goal_width(command) -> float:
    """The width (m) a control_msgs/GripperCommand asks for, or ValueError.

    As franka_gripper's gripper_action: ``position`` is half the width (one finger's
    joint), ``max_effort`` the grasp force in N. The simulated fingers close with their
    own force (world.FINGER_FORCE), so max_effort is checked but not applied.
    """
    half = panda.GRIPPER_OPEN_WIDTH / 2
    if not math.isfinite(command.position) or not -1e-6 <= command.position <= half + 1e-6:
        raise ValueError(f'position (half the width) must be within [0, {half}] m, got {command.position}')
    if not math.isfinite(command.max_effort) or command.max_effort < 0:
        raise ValueError(f'max_effort must be a finite force >= 0 N, got {command.max_effort}')
    return 2 * command.position


def _sensor_settings(p: dict) -> SensorSettings:
    """The cameras' sensor model from the node's parameters, or StartupError."""
    try:
        d415 = {name[len('d415.'):]: value for name, value in p.items() if name.startswith('d415.')}
        profile = profile_named(p['sensor_profile'], **(d415 if p['sensor_profile'] == 'd415' else {}))
        return SensorSettings(profile, p['extrinsic_error_mm'], p['extrinsic_error_deg'], p['latency_ms'])
    except ValueError as err:
        raise ros.StartupError(f'bad sensor parameters: {err}') from None


class SimBridgeNode(ros.Node):
    PARAMETERS = {
        'task': ('reach_target', 'the task of the first episode (later ones: /hdp/sim/reset)'),
        'seed': (0, 'its seed: scene layout and variation'),
        'variation': (-1, 'its variation; -1 draws it from the seed'),
        'camera_width': (640, 'px, both cameras'),
        'camera_height': (480, 'px, both cameras'),
        'camera_rate_hz': (2.0, 'frames per second of sim time (a D415 streams 6, 15 or 30); 0 turns the '
                                'cameras off'),
        'sensor_profile': ('ideal', f'camera sensor model: {" | ".join(PROFILES)} (sensor_model.py)'),
        'extrinsic_error_mm': (0.0, 'calibration error: each camera renders from a pose this far (random '
                                    'direction, per episode) from the one /tf_static gives'),
        'extrinsic_error_deg': (0.0, 'calibration error: and turned this much (random axis, per episode)'),
        'latency_ms': (0.0, 'frames are stamped at exposure and published this much later (sim time)'),
        'publish_compressed': (True, "also offer image_transport's compressed (colour, JPEG) and compressedDepth "
                                     '(16-bit PNG) topics, each encoded only while it has a subscriber'),
        'jpeg_quality': (image_transport.DEFAULT_JPEG_QUALITY, 'compressed colour: JPEG quality, 1-100'),
        'png_level': (image_transport.DEFAULT_PNG_LEVEL, 'compressedDepth: PNG compression level, 0-9 '
                                                         '(higher: smaller, slower)'),
        **{f'd415.{field.name}': (getattr(D415, field.name), f'the d415 profile\'s {field.name}, used when '
                                  'sensor_profile is d415 (hdp_sim_bridge README: Sensor model)')
           for field in dataclasses.fields(D415) if field.name != 'name'},
        'joint_state_rate_hz': (120.0, '/joint_states per second of sim time'),
        'real_time_factor': (1.0, 'sim time per wall time; 0 runs as fast as possible'),
    }

    # Rates and compression, applied from the next tick; episodes change through /hdp/sim/reset.
    RUNTIME = frozenset({'real_time_factor', 'camera_rate_hz', 'joint_state_rate_hz', 'jpeg_quality', 'png_level'})

    @staticmethod
    def check_parameters(p: dict) -> None:
        first = {'task': p['task'], 'seed': p['seed'], **({'variation': p['variation']} if p['variation'] >= 0 else {})}
        try:
            parse_reset(json.dumps(first))
        except ValueError as err:
            raise ros.StartupError(f'bad first episode: {err}') from None
        for name in ('real_time_factor', 'camera_rate_hz'):
            if not p[name] >= 0:
                raise ros.StartupError(f'parameter {name!r} must be >= 0, got {p[name]}')
        if not p['joint_state_rate_hz'] > 0:
            raise ros.StartupError(f"parameter 'joint_state_rate_hz' must be > 0, got {p['joint_state_rate_hz']}")
        for name, low, high in (('jpeg_quality', 1, 100), ('png_level', 0, 9)):
            if not low <= p[name] <= high:
                raise ros.StartupError(f'parameter {name!r} must be within [{low}, {high}], got {p[name]}')
        _sensor_settings(p)

    def __init__(self):
        super().__init__('sim_bridge_node')
        p = self.declare_parameter_table()
        self._steps, self._wall_start = 0, time.monotonic()
        self._stepped, self._rtf_since = 0, (time.monotonic(), 0)     # steps ever, for the factor achieved
        self.apply_parameters(p)
        sensor = _sensor_settings(p)
        self.bridge = SimBridge(p['camera_width'], p['camera_height'], sensor=sensor)
        self.status = ros.Status(self)
        if not sensor.is_ideal:
            self.status.info(f'cameras: {sensor.summary()}')
        self._clock_pub = self.create_publisher(Clock, topics.CLOCK, QoSProfile(
            depth=1, reliability=ReliabilityPolicy.BEST_EFFORT))
        self._joints = self.create_publisher(JointState, topics.JOINT_STATES, topics.COMMAND_QOS)
        self._tf_static = self.create_publisher(TFMessage, topics.TF_STATIC, topics.TF_STATIC_QOS)
        self._tf = self.create_publisher(TFMessage, topics.TF, topics.TF_QOS)
        self._robot_description = self.create_publisher(String, topics.ROBOT_DESCRIPTION, topics.LATCHED_QOS)
        self._episode = self.create_publisher(String, topics.SIM_EPISODE, topics.LATCHED_QOS)
        self._success = self.create_publisher(Bool, topics.SIM_SUCCESS, 10)
        self._cameras = {name: (self.create_publisher(Image, topics.color_image(name), topics.SENSOR_QOS),
                                self.create_publisher(Image, topics.depth_image(name), topics.SENSOR_QOS),
                                self.create_publisher(CameraInfo, topics.camera_info(name), topics.SENSOR_QOS))
                         for name in self.bridge.cameras}
        self._compressed = {name: (
            self.create_publisher(CompressedImage, topics.color_image_compressed(name), topics.SENSOR_QOS),
            self.create_publisher(CompressedImage, topics.depth_image_compressed(name), topics.SENSOR_QOS))
            for name in self.bridge.cameras} if p['publish_compressed'] else {}
        self._camera_rates = {name: diagnostics.RateMeter(time.monotonic()) for name in self.bridge.cameras}
        self._arm_source: str | None = None          # what sent the arm's running trajectory, in words
        self.create_subscription(JointTrajectory, topics.ARM_TRAJECTORY, self._on_arm, 10)
        self.create_subscription(JointTrajectory, topics.GRIPPER_TRAJECTORY, self._on_gripper, 10)
        self.create_subscription(String, topics.SIM_RESET, self._on_reset, 10)
        self.create_subscription(String, topics.SIM_CAMERAS, self._on_cameras, 10)
        # The same commands as actions, as joint_trajectory_controller and franka_gripper take them.
        self._tick_waiters: list[Future] = []
        ActionServer(self, FollowJointTrajectory, topics.ARM_ACTION, self._execute_arm,
                     goal_callback=self._arm_goal, cancel_callback=lambda _: CancelResponse.ACCEPT)
        ActionServer(self, GripperCommand, topics.GRIPPER_ACTION, self._execute_gripper,
                     goal_callback=self._gripper_goal, cancel_callback=lambda _: CancelResponse.ACCEPT)

        self._reset(p['task'], p['seed'], None if p['variation'] < 0 else p['variation'])
        # Two latched messages, as a robot's calibration and robot_state_publisher each send
        # theirs; depth 100 keeps both for whoever joins later.
        self._tf_static.publish(self.bridge.tf_static())
        self._tf_static.publish(self.bridge.robot_tf_static())
        self._robot_description.publish(String(data=robot_description()))
        self.create_timer(0.005, self._tick)
        self.create_timer(0.5, lambda: self._success.publish(Bool(data=self.bridge.success())))
        diagnostics.advertise(self, self._diagnostics)

    def apply_parameters(self, p: dict) -> None:
        self._rtf = p['real_time_factor']
        if self._rtf > 0:      # the wall time at which the steps taken so far were due at the new factor
            self._wall_start = time.monotonic() - self._steps * TIME_STEP / self._rtf
        self._joint_every = max(1, round(1.0 / (p['joint_state_rate_hz'] * TIME_STEP)))
        self._camera_hz = p['camera_rate_hz']
        self._camera_every = max(1, round(1.0 / (p['camera_rate_hz'] * TIME_STEP))) if p['camera_rate_hz'] > 0 else 0
        self._jpeg_quality, self._png_level = p['jpeg_quality'], p['png_level']

    def _reset(self, task, seed, variation):
        episode = self.bridge.reset(task, seed, variation)
        self._steps, self._wall_start = 0, time.monotonic()
        self._episode.publish(String(data=json.dumps(episode)))
        self.status.info(f"episode {episode['task']} seed {seed} variation {episode['variation']}: "
                         f"{episode['instruction']!r}")

    def _on_reset(self, msg):
        try:
            request = parse_reset(msg.data)
        except ValueError as err:
            self.status.error(f'rejected reset: {err}')
            return
        self._reset(request['task'], request.get('seed', 0), request.get('variation'))

    def _on_cameras(self, msg):
        try:
            publishing = self.bridge.select_cameras(msg.data)
        except ValueError as err:
            self.status.error(f'rejected camera selection: {err}')
            return
        stopped = [name for name in self.bridge.cameras if name not in publishing]
        self.status.info(f'cameras publishing: {", ".join(publishing) or "none"}; stopped: {", ".join(stopped) or "none"}')

    def _on_arm(self, msg):
        publishers = sorted(f'{i.node_namespace.rstrip("/")}/{i.node_name}'
                            for i in self.get_publishers_info_by_topic(topics.ARM_TRAJECTORY))
        self._command_arm(msg, f'a trajectory on {topics.ARM_TRAJECTORY} (its publishers: {", ".join(publishers)})')

    def _command_arm(self, trajectory, source: str) -> bool:
        """Run ``trajectory`` (from ``source``, for the status line); False when it is rejected.
        One that replaces a trajectory still running is said to preempt it, naming both."""
        running = None if self.bridge.trajectory_done else self._arm_source
        try:
            self.bridge.command_arm(trajectory)
        except ValueError as err:
            self.status.error(f'rejected arm trajectory ({source}): {err}')
            return False
        if running is not None:
            self.status.error(f'{source} preempts {running}')
        self._arm_source = source
        self.status.info(f'executing {source}: {len(trajectory.points)} points, '
                         f'{self.bridge.trajectory.end_time - self.bridge.sim_time:.2f} s')
        return True

    def _on_gripper(self, msg):
        try:
            self.bridge.command_gripper(msg)
        except ValueError as err:
            self.status.error(f'rejected gripper command: {err}')

    def _arm_goal(self, goal):
        try:
            self.bridge.check_arm(goal.trajectory)
        except ValueError as err:
            self.status.error(f'rejected arm goal: {err}')
            return GoalResponse.REJECT
        return GoalResponse.ACCEPT

    async def _execute_arm(self, goal_handle):
        """Run the goal's trajectory (replacing any other) and answer as joint_trajectory_controller."""
        request, result = goal_handle.request, FollowJointTrajectory.Result()
        source = f'FollowJointTrajectory goal {bytes(goal_handle.goal_id.uuid).hex()[:8]}'
        if not self._command_arm(request.trajectory, source):      # the arm moved on since the goal was checked
            result.error_code, result.error_string = result.INVALID_GOAL, 'the arm moved on since the goal came'
            goal_handle.abort()
            return result
        active = self.bridge.trajectory
        tolerance = np.full(7, DEFAULT_GOAL_TOLERANCE)
        for given in request.goal_tolerance:
            if given.name in panda.ARM_JOINTS and given.position > 0:
                tolerance[list(panda.ARM_JOINTS).index(given.name)] = given.position
        time_tolerance = duration_to_seconds(request.goal_time_tolerance) or DEFAULT_GOAL_TIME_TOLERANCE
        while True:
            await self._next_tick()
            if goal_handle.is_cancel_requested:
                if self.bridge.trajectory is active:      # a superseded goal's cancel leaves the arm alone
                    self.bridge.hold()
                    self.status.info('arm goal cancelled: holding where the arm is')
                goal_handle.canceled()
                return result
            state = self.bridge.arm_goal_state(active, tolerance, time_tolerance)
            if state == 'succeeded':
                goal_handle.succeed()
                return result
            if state != 'running':
                result.error_code = result.GOAL_TOLERANCE_VIOLATED if state == 'violated' else result.INVALID_GOAL
                result.error_string = ('not within the goal tolerance in time' if state == 'violated'
                                       else 'preempted by another trajectory')
                goal_handle.abort()
                return result

    def _gripper_goal(self, goal):
        try:
            gripper_goal_width(goal.command)
        except ValueError as err:
            self.status.error(f'rejected gripper goal: {err}')
            return GoalResponse.REJECT
        return GoalResponse.ACCEPT

    async def _execute_gripper(self, goal_handle):
        """Open or close as franka_gripper's gripper_action does (gripper_goal_width); the result's
        position is half the width reached, as its command's; reached_goal when the fingers end
        within its grasp epsilon of the width asked for (closing on an object does not, and
        aborts, though the object is held)."""
        target = gripper_goal_width(goal_handle.request.command)
        result = GripperCommand.Result()
        self.bridge.world.command_gripper(target >= panda.GRIPPER_OPEN_WIDTH / 2)
        start, width, still_since = self.bridge.sim_time, self.bridge.world.gripper_width(), self.bridge.sim_time
        while self.bridge.sim_time - start < GRIPPER_SETTLE_S and self.bridge.sim_time - still_since < GRIPPER_STILL_S:
            await self._next_tick()
            if goal_handle.is_cancel_requested:
                goal_handle.canceled()
                return result
            if abs(self.bridge.world.gripper_width() - width) > 1e-4:
                width, still_since = self.bridge.world.gripper_width(), self.bridge.sim_time
        width = self.bridge.world.gripper_width()
        result.position = width / 2
        result.reached_goal = abs(width - target) <= GRIPPER_REACHED
        result.stalled = not result.reached_goal
        if result.reached_goal:
            goal_handle.succeed()
        else:
            goal_handle.abort()
        return result

    def _next_tick(self) -> Future:
        """A future done at the next physics tick: action goals wait on the simulation with it."""
        future = Future()
        self._tick_waiters.append(future)
        return future

    def _tick(self):
        """Step physics up to where the wall clock (times the real-time factor) says."""
        waiters, self._tick_waiters = self._tick_waiters, []
        for future in waiters:
            future.set_result(None)
        due = _MAX_STEPS_PER_TICK
        if self._rtf > 0:
            due = int((time.monotonic() - self._wall_start) * self._rtf / TIME_STEP) - self._steps
            if due > _MAX_STEPS_PER_TICK:     # fell behind (rendering is slow): drop the backlog
                self._wall_start += (due - _MAX_STEPS_PER_TICK) * TIME_STEP / self._rtf
                due = _MAX_STEPS_PER_TICK
        for _ in range(max(0, due)):
            self.bridge.step()
            self._steps += 1
            self._stepped += 1
            if self._steps % self._joint_every == 0:
                self._clock_pub.publish(self.bridge.clock())
                self._joints.publish(self.bridge.joint_state())
                self._tf.publish(self.bridge.robot_tf())
            if self._camera_every and self._steps % self._camera_every == 0:
                self.bridge.expose()
            for name, messages in self.bridge.delivered():
                self._camera_rates[name].tick(time.monotonic())
                for publisher, message in zip(self._cameras[name], messages):
                    publisher.publish(message)
                self._publish_compressed(name, *messages[:2])

    def _publish_compressed(self, camera: str, color, depth) -> None:
        """A frame through image_transport's compressed plugins. As they do, each is encoded only
        while its topic has a subscriber: at 640x480 a JPEG costs ~1 ms, a 16-bit PNG ~5 ms."""
        if camera not in self._compressed:
            return
        color_topic, depth_topic = self._compressed[camera]
        if color_topic.get_subscription_count():
            color_topic.publish(image_transport.encode_compressed(color, self._jpeg_quality))
        if depth_topic.get_subscription_count():
            depth_topic.publish(image_transport.encode_compressed_depth(depth, self._png_level))

    def _diagnostics(self, wall_s: float) -> list:
        name = self.get_name()
        since_s, since_steps = self._rtf_since
        self._rtf_since = (wall_s, self._stepped)
        achieved = (self._stepped - since_steps) * TIME_STEP / (wall_s - since_s)
        if self._rtf > 0 and achieved < SLOW_RTF * self._rtf:
            level, message = diagnostics.WARN, (f'real-time factor {achieved:.2f}, asked {self._rtf:g}: '
                                                f'this machine cannot keep up; {_TOO_SLOW}')
        else:
            asked = f'asked {self._rtf:g}' if self._rtf > 0 else 'asked as fast as possible'
            level, message = diagnostics.OK, f'real-time factor {achieved:.2f}, {asked}'
        out = [diagnostics.status(name, 'real-time factor', level, message,
                                  {'achieved': achieved, 'asked': self._rtf, 'sim_time_s': self.bridge.sim_time})]
        for camera, meter in self._camera_rates.items():
            expected_hz = self._camera_hz * achieved      # frames per wall second at the speed the sim runs
            if camera not in self.bridge.publishing or expected_hz <= 0:
                why = ('stopped on /hdp/sim/cameras' if camera not in self.bridge.publishing
                       else 'off (camera_rate_hz 0)' if self._camera_hz == 0 else 'the simulation is not running')
                out.append(diagnostics.status(name, f'{camera} camera', diagnostics.OK, why,
                                              {'camera_rate_hz': self._camera_hz}))
                continue
            out.append(diagnostics.topic_status(
                name, f'{camera} camera', topics.color_image(camera), meter, wall_s, expected_hz,
                max(CAMERA_TIMEOUT_S, 2 * diagnostics.STALE_PERIODS / expected_hz), f'rendering is slow; {_TOO_SLOW}'))
        episode = self.bridge.episode
        out.append(diagnostics.status(name, 'episode', diagnostics.OK,
                                      f"{episode['task']} seed {episode['seed']} variation {episode['variation']}: "
                                      f"{episode['instruction']!r}", episode))
        return out

    def destroy_node(self):
        self.bridge.close()
        super().destroy_node()


def main(args=None):
    ros.run(SimBridgeNode, args, 'sim_bridge_node')


if __name__ == '__main__':
    main()
