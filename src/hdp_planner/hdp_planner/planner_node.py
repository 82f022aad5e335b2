"""planner_node: an instruction -> next-best poses for the controller, one segment at a time.

A managed (lifecycle) node: configure loads the agent and warms it up, activate starts
taking instructions, deactivate ends the running one ('stopped') and holds the arm, cleanup
lets the agent go; an instruction that comes while the node is not active is refused on
/hdp/outcome, and at shutdown the running and waiting ones end 'shutdown'. The logic is
planner_logic.PlannerLoop; this node wires it to topics and parameters. A
10 Hz timer advances the loop, and the agent predicts inside that callback (a few tens of
milliseconds on a CPU core). Timeouts run on the node's clock (the graph's YAML keeps this
node on wall time); a second timer on the steady clock fails the running instruction when
/joint_states stop or the node's clock stands still (hdp_ros.liveness), so a dead simulator
or robot driver is named within state_timeout_s instead of being blamed on the controller.
/diagnostics (hdp_ros.diagnostics), also on the steady clock, says how the node stands.
"""

import functools
import time

import torch
from rclpy.clock import Clock, ClockType
from std_srvs.srv import Trigger

from hdp_data import depth_filters
from hdp_learning import checkpoints
from hdp_motion import panda
from hdp_motion.body import body_surface
from hdp_msgs_py import conversions, topics
from hdp_ros import diagnostics, image_input, ros
from hdp_ros.liveness import ROBOT_HINT, Liveness
from hdp_msgs_py.msg import (Bool, CameraInfo, Header, JointState, Marker, PointCloud2, PoseStamped, String,
                             TFMessage)
from hdp_msgs_py.outcome import Outcome, StatusLine

from . import visualisation
from .agent import NextBestPoseAgent
from .planner_logic import (DEFAULT_MAX_QUEUED, DEFAULT_MIN_CONFIDENCE, QUEUE_POLICIES, Observations, PlannerLoop,
                            Prediction, SegmentGoal, default_checkpoint)

_STEP_S = 0.1
_WATCH_S = 0.5
# Least rates /diagnostics expects: the 10 Hz step reads /joint_states (the sim sends 120 Hz);
# the sim's cameras stream 2 Hz by default.
_JOINT_STATE_HZ = 10.0
_CAMERA_HZ = 2.0


def _limits(p: dict) -> dict:
    """PlannerLoop.configure()'s arguments from the node's parameters."""
    return {name: p[name] for name in ('max_segments', 'camera_timeout_s', 'result_timeout_s', 'min_confidence',
                                       'queue_policy', 'max_queued')}


class PlannerNode(ros.LifecycleNode):
    PARAMETERS = {
        **ros.LifecycleNode.LIFECYCLE_PARAMETERS,
        'checkpoint': ('', "next-best-pose agent: a path, or a file name in models/ ($HDP_MODELS_DIR); "
                           "'' = models/hdp_nbp_agent_11tasks.pt"),
        'max_segments': (8, 'segments per instruction before it has failed'),
        'camera_timeout_s': (5.0, 's to wait for fresh frames from both cameras'),
        'result_timeout_s': (60.0, 's to wait for a segment result before the next segment'),
        'min_confidence': (DEFAULT_MIN_CONFIDENCE, "an instruction whose first NBP is less confident is refused"),
        'queue_policy': ('replace', 'an instruction that comes while another runs: replace (the newest wins), '
                                    'queue (waits its turn, up to max_queued) or refuse (busy)'),
        'max_queued': (DEFAULT_MAX_QUEUED, 'instructions that may wait under queue_policy queue; more are refused'),
        'ground_instructions': (True, 'read each instruction as the nearest training one first (grounding.py; '
                                      'agents with the sentence encoder)'),
        'state_timeout_s': (5.0, 'wall-clock s without /joint_states (or a moving clock) before an instruction fails'),
        'joint_prefix': ('panda', "joint name prefix: 'fr3' for an FR3"),
        'publish_cloud': (False, 'publish the cloud each prediction saw on /hdp/planner/cloud (for a viewer)'),
        'cpu_threads': (1, "torch's CPU threads; 1 keeps this node from fighting the simulator and the other node "
                           'for two cores (rkd planned in 0.5 s with torch\'s default 2, 0.08 s with 1)'),
        'refine_extrinsics': (False, "check each camera's extrinsics against the robot's body in its depth as an "
                                     'instruction starts, and predict with the refined ones (extrinsics.py; the '
                                     "Panda's meshes: not for an FR3)"),
        'depth_filter': ('none', "'none' or 'realsense': librealsense's post-processing chain (spatial, temporal, "
                                'hole filling; hdp_data.depth_filters) on depth as it arrives, as `hdp eval '
                                "--depth-filter`; for a camera driver that does not filter"),
        'image_transport': ('raw', "'raw': the cameras' sensor_msgs/Image; 'compressed': image_transport's "
                                   'compressed (JPEG colour) and compressedDepth (16-bit PNG depth) topics, for '
                                   'a network link (hdp_ros.image_input)'),
        'camera_size': ([128, 96], 'the frame size [width, height] the agent was trained at (hdp collect --width '
                                   '--height); frames of another size are resampled to it; [0, 0] takes them as they come'),
    }

    # Read at each use by the loop (when each takes effect: the package README).
    RUNTIME = frozenset({'max_segments', 'camera_timeout_s', 'result_timeout_s', 'min_confidence', 'queue_policy',
                         'max_queued', 'state_timeout_s', 'publish_cloud'})

    @staticmethod
    def check_parameters(p: dict) -> None:
        if p['cpu_threads'] < 1:
            raise ros.StartupError(f"parameter 'cpu_threads' must be >= 1, got {p['cpu_threads']}")
        if p['max_segments'] < 1:
            raise ros.StartupError(f"parameter 'max_segments' must be >= 1, got {p['max_segments']}")
        for name in ('camera_timeout_s', 'result_timeout_s', 'state_timeout_s'):
            if not p[name] > 0:
                raise ros.StartupError(f'parameter {name!r} must be > 0, got {p[name]}')
        if p['queue_policy'] not in QUEUE_POLICIES:
            raise ros.StartupError(f"parameter 'queue_policy' must be one of {', '.join(QUEUE_POLICIES)}, "
                                   f"got {p['queue_policy']!r}")
        if p['max_queued'] < 1:
            raise ros.StartupError(f"parameter 'max_queued' must be >= 1, got {p['max_queued']}")
        if not 0.0 <= p['min_confidence'] < 1.0:
            raise ros.StartupError(f"parameter 'min_confidence' must be in [0, 1), got {p['min_confidence']}")
        if p['image_transport'] not in image_input.TRANSPORTS:
            raise ros.StartupError("parameter 'image_transport' must be one of "
                                   f"{', '.join(image_input.TRANSPORTS)}, got {p['image_transport']!r}")
        if p['depth_filter'] not in depth_filters.PRESETS:
            raise ros.StartupError("parameter 'depth_filter' must be one of "
                                   f"{', '.join(depth_filters.PRESETS)}, got {p['depth_filter']!r}")
        camera_size = tuple(p['camera_size'])
        if camera_size != (0, 0) and (len(camera_size) != 2 or min(camera_size) < 8 or max(camera_size) > 4096):
            raise ros.StartupError("parameter 'camera_size' must be [width, height] in 8..4096, or [0, 0], "
                                   f'got {list(camera_size)}')

    def __init__(self):
        super().__init__('planner_node')
        p = self.declare_parameter_table()
        self.loop = self.observations = None
        # In every state: instructions are answered (refused unless active), and the node says how it stands.
        self._outcome = self.create_publisher(String, topics.OUTCOME, topics.INSTRUCTION_QOS)
        self.create_subscription(String, topics.INSTRUCTION, self._on_instruction, topics.INSTRUCTION_QOS)
        diagnostics.advertise(self, self._diagnostics)
        if not p['autostart']:
            self.status.info(f'unconfigured: waiting for a lifecycle manager ({ros.MANAGER_HINT})')

    def configure(self, p: dict) -> None:
        camera_size = None if tuple(p['camera_size']) == (0, 0) else tuple(p['camera_size'])
        torch.set_num_threads(p['cpu_threads'])
        checkpoint = checkpoints.resolve(p['checkpoint']) if p['checkpoint'] else default_checkpoint()
        try:
            agent = NextBestPoseAgent.from_checkpoint(checkpoint, camera_size=camera_size,
                                                      ground_instructions=p['ground_instructions'])
        except ValueError as err:          # CheckpointError: missing, damaged or not ours
            raise ros.StartupError(f'cannot load the next-best-pose agent: {err}') from None
        warm_up_s = agent.warm_up()        # the first instruction pays no first-call cost
        prefix = p['joint_prefix']
        observations = Observations(topics.CAMERAS, panda.joint_names(prefix), panda.finger_joint_names(prefix),
                                    depth_filters.preset(p['depth_filter']), p['refine_extrinsics'])
        if p['refine_extrinsics']:
            body_surface(panda.HOME, panda.GRIPPER_OPEN_WIDTH)       # the meshes load now, not at the first check
        self.observations = observations           # the loop reads them; the subscriptions fill them
        self.loop = PlannerLoop(agent, agent.vocabulary, observations=observations, **_limits(p))
        self._model = {'checkpoint': checkpoint, 'device': str(agent.device), 'warm_up_s': warm_up_s}
        self._camera_timeout_s = p['camera_timeout_s']
        self._joint_rate = diagnostics.RateMeter(time.monotonic())
        self._camera_rates = {camera: diagnostics.RateMeter(time.monotonic()) for camera in topics.CAMERAS}

        self._nbp = self.create_publisher(PoseStamped, topics.NEXT_BEST_POSE, topics.COMMAND_QOS)
        self._gripper_goal = self.create_publisher(JointState, topics.NEXT_BEST_GRIPPER, topics.COMMAND_QOS)
        # For RViz and Foxglove: the NBP as a TF frame and an arrow.
        self._tf = self.create_publisher(TFMessage, topics.TF, topics.TF_QOS)
        self._marker = self.create_publisher(Marker, topics.NEXT_BEST_POSE_MARKER, topics.COMMAND_QOS)
        self._cloud = None
        self._publish_cloud(p['publish_cloud'])
        self.dropped_frames = image_input.DroppedFrames(self.get_logger())
        for camera in topics.CAMERAS:
            for kind, callback in (('color', self._on_color), ('depth', observations.on_depth)):
                image_input.subscribe(self, camera, kind, p['image_transport'],
                                      functools.partial(callback, camera), self.dropped_frames)
            self.create_subscription(CameraInfo, topics.camera_info(camera),
                                     functools.partial(observations.on_info, camera), topics.SENSOR_QOS)
        self.create_subscription(TFMessage, topics.TF_STATIC, observations.on_tf_static, topics.TF_STATIC_QOS)
        self.liveness = Liveness(p['state_timeout_s'])
        self.create_subscription(JointState, topics.JOINT_STATES, self._on_joint_state, topics.COMMAND_QOS)
        self.create_subscription(Header, topics.SEGMENT_RESULT,
                                 lambda m: self._send(self.loop.on_result(m, self._now())), topics.COMMAND_QOS)
        self.create_subscription(Bool, topics.SIM_SUCCESS, lambda m: self.loop.on_success(m.data), 10)
        self._hold = self.create_publisher(Header, topics.HOLD, topics.COMMAND_QOS)
        self.create_service(Trigger, topics.STOP, self._on_stop)
        self.create_timer(_STEP_S, self._step)
        # On the wall clock, in case this node runs on sim time and the simulator dies.
        self.create_timer(_WATCH_S, self._watch, clock=Clock(clock_type=ClockType.STEADY_TIME))
        self.status.info(f'configured: agent {checkpoint} on {agent.device} (warmed up in {warm_up_s:.2f} s)')

    def activate(self) -> None:
        self.liveness.heard(time.monotonic())     # an inactive node heard nothing it needed
        self.status.info(f'ready: agent {self._model["checkpoint"]}, up to '
                         f'{self.get_parameter("max_segments").value} segments per instruction '
                         f'(warmed up in {self._model["warm_up_s"]:.2f} s)')

    def deactivate(self, why: str, shutting_down: bool) -> None:
        now = self.get_clock().now()
        self._hold.publish(Header(stamp=now.to_msg(), frame_id=why))
        self._send(self.loop.shutdown(now.nanoseconds * 1e-9) if shutting_down
                   else self.loop.stop(why, now.nanoseconds * 1e-9))
        self.status.info(f'{"shutting down" if shutting_down else "inactive"}: {why}; arm held')

    def forget(self) -> None:
        self.loop = self.observations = None

    def apply_parameters(self, p: dict) -> None:
        if self.loop is None:              # unconfigured: configure reads them
            return
        self.loop.configure(**_limits(p))
        self.liveness.set_timeout(p['state_timeout_s'])
        self._camera_timeout_s = p['camera_timeout_s']
        self._publish_cloud(p['publish_cloud'])

    def _publish_cloud(self, on: bool) -> None:
        if on and self._cloud is None:
            self._cloud = self.create_publisher(PointCloud2, topics.PLANNER_CLOUD, topics.SENSOR_QOS)
        elif not on and self._cloud is not None:
            self.destroy_publisher(self._cloud)
            self._cloud = None

    def _now(self) -> float:
        return self.get_clock().now().nanoseconds * 1e-9

    def _on_instruction(self, msg):
        if self.active:
            self._send(self.loop.on_instruction(msg.data, self._now()))
        else:
            why = f'planner_node is {self.state_label} ({ros.MANAGER_HINT})'
            self._send([StatusLine(f'refused instruction {msg.data.strip()[:200]!r}: {why}', error=True),
                        Outcome(msg.data.strip(), 'refused', why, 0)])

    def _on_joint_state(self, msg):
        self.liveness.heard(time.monotonic())
        self._joint_rate.tick(time.monotonic())
        self.observations.on_joint_state(msg)

    def _on_color(self, camera, msg):
        self._camera_rates[camera].tick(time.monotonic())
        self.observations.on_color(camera, msg)

    def _diagnostics(self, wall_s: float) -> list:
        name = self.get_name()
        state = diagnostics.lifecycle_status(name, self.state_label, self.failure)
        if self.loop is None:
            return [state]
        out = [state, diagnostics.status(name, 'agent', diagnostics.OK,
                                  f"{self._model['checkpoint']} on {self._model['device']}", self._model),
               diagnostics.topic_status(name, 'joint states', topics.JOINT_STATES, self._joint_rate, wall_s,
                                        _JOINT_STATE_HZ, self.liveness.timeout_s, ROBOT_HINT)]
        out += [diagnostics.topic_status(name, f'{camera} camera', topics.color_image(camera), meter, wall_s,
                                         _CAMERA_HZ, self._camera_timeout_s,
                                         f'is sim_bridge_node (or the {camera} camera driver) running, and '
                                         'its camera selected?')
                for camera, meter in self._camera_rates.items()]
        running = self.loop.summary()
        message = ('idle' if running['instruction'] is None else
                   f"{running['instruction']!r}: {running['segments']} of at most {running['max_segments']} "
                   'segments sent')
        out.append(diagnostics.status(name, 'instruction', diagnostics.OK,
                                      message + (f", {running['waiting']} waiting" if running['waiting'] else ''),
                                      running))
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
            self._send(self.loop.robot_gone(problem, self._now()))

    def _on_stop(self, request, response):
        """/hdp/stop: hold the arm first (the urgent part), then end the instructions 'stopped'."""
        why = f'stopped by {topics.STOP}'
        now = self.get_clock().now()
        self._hold.publish(Header(stamp=now.to_msg(), frame_id=why))
        outputs = self.loop.stop(why, now.nanoseconds * 1e-9)
        self._send(outputs)
        stopped = [out.instruction for out in outputs if isinstance(out, Outcome)]
        response.success = True
        response.message = (f'stopped {", ".join(map(repr, stopped))}; arm held' if stopped
                            else 'nothing was running; arm held')
        return response

    def _step(self):
        if not self.active:
            return
        started = time.monotonic()
        now = self.get_clock().now().nanoseconds
        self._send(self.loop.step(now * 1e-9, now))
        if time.monotonic() - started > _WATCH_S:      # a slow prediction: no message was taken meanwhile
            self.liveness.excuse(time.monotonic())

    def _send(self, outputs):
        for out in outputs:
            match out:
                case StatusLine():
                    self.status.line(out)
                case Outcome():
                    self._outcome.publish(String(data=out.to_json()))
                case SegmentGoal():
                    self._gripper_goal.publish(out.gripper_goal)
                    self._nbp.publish(out.nbp)
                    self._tf.publish(TFMessage(transforms=[visualisation.nbp_transform(out.nbp)]))
                    self._marker.publish(visualisation.nbp_marker(out.nbp, visualisation.opens(out.gripper_goal)))
                case Prediction() if self._cloud is not None:
                    header = Header(stamp=self.get_clock().now().to_msg(), frame_id=topics.NBP_FRAME)
                    self._cloud.publish(conversions.cloud_to_pointcloud2(*out.cloud, header))


def main(args=None):
    ros.run(PlannerNode, args, 'planner_node')


if __name__ == '__main__':
    main()
