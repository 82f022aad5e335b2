"""The graph from outside: the demo's node, and one episode driven through it.

The demo listens to the cameras and /joint_states best effort, so that a slow demo process
never holds the graph back, and learns how each instruction ended from /hdp/outcome.
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import time
from pathlib import Path

import numpy as np
import rclpy
import rclpy.executors

from hdp_motion import panda
from hdp_data import instructions
from hdp_msgs_py import conversions, topics
from hdp_ros import ros
from hdp_msgs_py.conversions import time_to_ns
from hdp_msgs_py.msg import Bool, Header, Image, JointState, JointTrajectory, PoseStamped, String
from hdp_msgs_py.outcome import Outcome

from ..launch_cli import MANAGED, NODES, running_nodes, start_node
from .cpu import cpu_usage
from .episode_log import EpisodeLog, stall_report
from .media import GIF_WIDTH

SCENE_TIMEOUT_S = 60.0         # for a (reset) scene to show a frame and its success report
STARTUP_TIMEOUT_S = 300.0      # three processes importing torch and loading checkpoints on a busy CPU


class Interrupted(Exception):
    """SIGINT or SIGTERM: stop the nodes and exit."""


class GraphDown(Exception):
    """A node process exited, or the graph or a scene did not come up in time."""


class DemoNode(ros.Node):
    """The demo's view of the graph; callbacks feed the EpisodeLog of the running instruction."""

    def __init__(self, on_segment):
        super().__init__('hdp_demo')
        self.on_segment = on_segment
        self.log: EpisodeLog | None = None
        self.episode: dict | None = None      # the latest /hdp/sim/episode
        self.success: bool | None = None      # the latest /hdp/sim/success since that episode
        self.frame = None                     # (sim stamp s, rgb) the latest front frame since then
        self.ready: set[str] = set()          # managed nodes that said 'ready' (activated)
        self.instruction = self.create_publisher(String, topics.INSTRUCTION, topics.COMMAND_QOS)
        self.reset = self.create_publisher(String, topics.SIM_RESET, topics.COMMAND_QOS)
        self._arm_joints = list(panda.ARM_JOINTS)
        for msg_type, topic, callback, qos in (
                (String, topics.SIM_EPISODE, self._on_episode, topics.LATCHED_QOS),
                (Bool, topics.SIM_SUCCESS, self._on_success, topics.COMMAND_QOS),
                (String, topics.STATUS, self._on_status, topics.STATUS_QOS),
                (String, topics.OUTCOME, self._on_outcome, topics.COMMAND_QOS),
                (JointState, topics.NEXT_BEST_GRIPPER, self._on_gripper_goal, topics.COMMAND_QOS),
                (PoseStamped, topics.NEXT_BEST_POSE, self._on_nbp, topics.COMMAND_QOS),
                (JointTrajectory, topics.ARM_TRAJECTORY, self._on_trajectory, topics.COMMAND_QOS),
                (Header, topics.SEGMENT_RESULT, self._on_result, topics.COMMAND_QOS),
                (Image, topics.color_image('front'), self._on_frame, topics.SENSOR_QOS),
                (JointState, topics.JOINT_STATES, self._on_joints, topics.SENSOR_QOS)):
            self.create_subscription(msg_type, topic, callback, qos)

    def not_connected(self) -> list[str]:
        """What is not matched yet between the demo and the nodes (empty: the graph is up).

        By node name, not by count: the demo's own subscriptions (and a recorder's) are on
        these topics too, and counting them once let an instruction go out before
        planner_node could hear it.
        """
        def publishes(node_name, topic):
            return _named(self.get_publishers_info_by_topic(topic), node_name)
        wanted = [('planner_node subscribed to ' + topics.INSTRUCTION,
                   self._delivers(self.instruction, topics.INSTRUCTION, 'planner_node')),
                  ('sim_bridge_node subscribed to ' + topics.SIM_RESET,
                   self._delivers(self.reset, topics.SIM_RESET, 'sim_bridge_node')),
                  ('controller_node subscribed to ' + topics.NEXT_BEST_POSE,
                   _named(self.get_subscriptions_info_by_topic(topics.NEXT_BEST_POSE), 'controller_node')),
                  ('controller_node publishing ' + topics.SEGMENT_RESULT,
                   publishes('controller_node', topics.SEGMENT_RESULT)),
                  ('planner_node publishing ' + topics.NEXT_BEST_POSE,
                   publishes('planner_node', topics.NEXT_BEST_POSE))]
        missing = [what for what, there in wanted if not there]
        missing += [f'{name} active (its "ready" line)' for name in MANAGED if name not in self.ready]
        if self.count_publishers(topics.STATUS) < len(NODES):
            missing.append(f'{topics.STATUS} from all {len(NODES)} nodes')
        return missing

    def _delivers(self, publisher, topic: str, node_name: str) -> bool:
        """``node_name`` subscribes to ``topic`` and ``publisher`` has matched every subscription
        the graph knows of there, so a message published now reaches it."""
        subscriptions = self.get_subscriptions_info_by_topic(topic)
        return _named(subscriptions, node_name) and publisher.get_subscription_count() >= len(subscriptions)

    def scene_missing(self) -> list[str]:
        """What the current scene has not shown yet: the episode, a front frame, a success report."""
        return [what for what, there in (
            ('the episode on ' + topics.SIM_EPISODE, self.episode is not None),
            ('a front camera frame', self.frame is not None),
            ('a success report (false) for the new scene', self.success is False)) if not there]

    def now(self) -> float:
        return time.monotonic()

    def _on_episode(self, msg):
        self.episode, self.success, self.frame = json.loads(msg.data), None, None

    def _on_success(self, msg):
        self.success = bool(msg.data)
        if self.log is not None and self.success:
            self.log.success(self.now())

    def _on_status(self, msg):
        name, _, line = msg.data.partition(': ')
        if name in MANAGED and line.startswith('ready: '):      # /hdp/status is latched: heard late too
            self.ready.add(name)
        if self.log is not None:
            self.log.status.append((self.now() - self.log.start, msg.data))

    def _on_outcome(self, msg):
        if self.log is not None:
            try:
                self.log.outcomes.append(Outcome.from_json(msg.data))
            except ValueError as err:
                self.get_logger().warning(f'ignored a malformed {topics.OUTCOME}: {err}')

    def _on_gripper_goal(self, msg):
        if self.log is not None and len(msg.position) == 1:
            self.log.gripper_goal(time_to_ns(msg.header.stamp),
                                  float(msg.position[0]) >= panda.GRIPPER_OPEN_WIDTH / 2)

    def _on_nbp(self, msg):
        if self.log is not None:
            p = msg.pose.position
            self.log.nbp(self.now(), time_to_ns(msg.header.stamp), (p.x, p.y, p.z))

    def _on_trajectory(self, msg):
        if self.log is not None and msg.points:
            duration = conversions.duration_to_seconds(msg.points[-1].time_from_start)
            self.log.trajectory(self.now(), len(msg.points), duration)

    def _on_result(self, msg):
        if self.log is not None:
            segment = self.log.result(self.now(), time_to_ns(msg.stamp), msg.frame_id)
            if segment is not None:
                self.on_segment(segment)

    def _on_frame(self, msg):
        import cv2
        rgb = conversions.image_to_numpy(msg)
        height = round(rgb.shape[0] * GIF_WIDTH / rgb.shape[1])
        small = cv2.resize(rgb, (GIF_WIDTH, height), interpolation=cv2.INTER_AREA)
        self.frame = (conversions.time_to_seconds(msg.header.stamp), small)
        if self.log is not None:
            self.log.frames.append((self.now() - self.log.start, *self.frame))

    def _on_joints(self, msg):
        if self.log is not None:
            names = list(msg.name)
            if all(n in names for n in self._arm_joints):
                q = np.array([msg.position[names.index(n)] for n in self._arm_joints])
                self.log.joints.append((self.now() - self.log.start,
                                        conversions.time_to_seconds(msg.header.stamp), q))


def _named(endpoints, node_name: str) -> bool:
    """Whether one of these graph endpoints (TopicEndpointInfo) belongs to ``node_name``."""
    return any(e.node_name == node_name for e in endpoints)


class Session:
    """The demo node spinning while the node processes run; every wait checks both.

    ``executor`` holds ``node`` for the whole session: rclpy.spin_once(node) would add and remove
    the node on every call, rebuilding its wait set under 120 Hz joint states and camera frames.
    """

    def __init__(self, node, executor, procs: dict, stop: list, start):
        self.node, self.executor, self.procs, self.stop, self._start = node, executor, procs, stop, start

    def spin_until(self, done, timeout_s: float) -> bool:
        """Spin until ``done()``; False on timeout. Interrupted or GraphDown end the wait early."""
        deadline = time.monotonic() + timeout_s
        while not done():
            if self.stop:
                raise Interrupted(self.stop[0])
            died = next((n for n, p in self.procs.items() if p.poll() is not None), None)
            if died is not None:
                raise GraphDown(f'{died} exited with code {self.procs[died].returncode}')
            if time.monotonic() >= deadline:
                return False
            self.executor.spin_once(timeout_sec=0.1)
        return True

    def restart(self, name: str) -> None:
        """SIGKILL node ``name`` and start it again, on the graph's domain, its output appended."""
        self.procs[name].kill()
        self.procs[name].wait(timeout=30)
        self.procs[name] = self._start(name)


@contextlib.contextmanager
def watched_graph(commands: dict, logs: Path, domain: int, make_node, say):
    """The node processes (name -> command line) running on ``domain`` with their output in
    logs/<node>.log, and a Session of ``make_node()`` watching them. SIGINT and SIGTERM end any
    wait with Interrupted; the nodes are stopped and rclpy shut down on leaving, however."""
    ros.init(args=[], domain_id=domain)
    stop: list[str] = []

    def on_signal(signum, frame):
        stop.append(signal.Signals(signum).name)     # the first ends the wait; later ones wait for the stop
    previous = {sig: signal.signal(sig, on_signal) for sig in (signal.SIGINT, signal.SIGTERM)}
    node = make_node()
    executor = rclpy.executors.SingleThreadedExecutor()
    executor.add_node(node)
    try:
        with contextlib.ExitStack() as files:
            def output(name):
                return files.enter_context(open(logs / f'{name}.log', 'a'))
            env = dict(os.environ, ROS_DOMAIN_ID=str(domain))
            def start(name):
                return start_node(name, commands[name], output, say, env)
            with running_nodes(commands, output, say, env) as procs:
                yield Session(node, executor, procs, stop, start)
    finally:
        for sig, handler in previous.items():       # the runtime's, which shutdown replaces in turn
            signal.signal(sig, handler)
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown()


def wait_for_graph(session: Session, say, started: float) -> None:
    """Until every node is connected to the watcher (GraphDown after STARTUP_TIMEOUT_S)."""
    node = session.node
    say('waiting for the nodes to load their models and connect ...')
    if not session.spin_until(lambda: not node.not_connected(), STARTUP_TIMEOUT_S):
        raise GraphDown(f'the graph did not connect within {STARTUP_TIMEOUT_S:.0f} s '
                        f'(missing: {", ".join(node.not_connected())})')
    say(f'graph up after {time.monotonic() - started:.1f} s')


def run_episode(session: Session, seed: int, instruction: str | None, timeout_s: float,
                cpu_sample, say, phrasing: str | None = None) -> tuple[dict, EpisodeLog]:
    """One instruction on the current scene: (its summary record, its EpisodeLog).

    The instruction is ``instruction``, else the evaluation harness's for this seed in ``phrasing``
    (instructions.evaluation_instruction), else the episode's own (the bridge's).

    The scene is ready when it has shown a front frame and reported no success since it was
    set; the instruction then goes out and the episode ends with the planner's outcome for it
    on /hdp/outcome, or after ``timeout_s`` ('timeout').
    """
    node = session.node
    if not session.spin_until(lambda: not node.scene_missing() and node.episode['seed'] == seed, SCENE_TIMEOUT_S):
        raise GraphDown(f'the scene of seed {seed} did not come up within {SCENE_TIMEOUT_S:.0f} s '
                        f'(waiting for {", ".join(node.scene_missing())})')
    episode = dict(node.episode)
    if instruction is None and phrasing is not None:
        instruction = instructions.evaluation_instruction(episode['task'], seed, episode['variation'], phrasing)
    text = (instruction or episode['instruction']).strip()
    say(f"episode {episode['task']} seed {seed} variation {episode['variation']}: {text!r}")
    before = cpu_sample()
    log = EpisodeLog(node.now())
    log.frames.append((0.0, *node.frame))           # the scene before anything moves
    node.log = log
    node.instruction.publish(String(data=text))

    def ours():
        return next((o for o in log.outcomes if o.instruction == text), None)
    ended = session.spin_until(lambda: ours() is not None, timeout_s)
    wall_s = node.now() - log.start
    node.log = None
    cpu = cpu_usage(before, cpu_sample(), wall_s)
    result, reason = (ours()[1:3] if ended else ('timeout', f'no outcome within {timeout_s:.0f} s'))
    record = {'task': episode['task'], 'seed': seed, 'variation': episode['variation'], 'instruction': text,
              'outcome': result, 'reason': reason,
              'success': result == 'succeeded',
              'success_s': log.success_s, 'wall_s': round(wall_s, 3),
              'segments': [s.to_dict() for s in log.segments], 'cpu': cpu,
              'status': [f'{t:7.2f} {line}' for t, line in log.status]}
    if not ended:
        record['stall'] = stall_report(log, node.now())
    return record, log


