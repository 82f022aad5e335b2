"""The HDP graph in the loop: sim_bridge_node, planner_node and controller_node as processes on the
released eleven-task checkpoints (models/hdp_nbp_agent_11tasks.pt, models/rk_diffuser_11tasks.pt), driven and watched from
this process through hdp_ros.ros, on a ROS domain of their own.

The graph starts once for the module (torch imports and two checkpoints in three processes take
10-30 s on two cores); each test starts a fresh episode on /hdp/sim/reset and waits for its instruction to
end before the next test begins. Cameras run at 128x96, the size both levels were trained and
evaluated at (hdp_controller.observation.CAMERA_SIZE).
"""

import collections
import json
import math
import os
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import rclpy

import conftest
from hdp_controller.observation import CAMERA_SIZE
from hdp_motion import panda
from hdp_msgs_py import conversions, topics
from hdp_ros import ros
from hdp_msgs_py.msg import Bool, Header, Image, JointTrajectory, Point, Pose, PoseStamped, Quaternion, String, Time
from hdp_eval.hierarchy_eval import episode_instruction
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.qos import QoSProfile

pytestmark = [pytest.mark.dds, pytest.mark.timeout(900)]

REPO = Path(__file__).resolve().parents[1]
PARAMS = REPO / 'src' / 'hdp_bringup' / 'config' / 'hdp_graph.yaml'
# As `hdp launch` starts them: the lifecycle manager brings the two managed nodes to active.
PACKAGES = {'sim_bridge_node': 'hdp_sim_bridge', 'planner_node': 'hdp_planner', 'controller_node': 'hdp_controller',
            'lifecycle_manager': 'hdp_bringup'}
# Twice the longest healthy segment measured here (10.4 s: RK-Diffuser planning, motion and
# settling on a loaded 2-core machine), so only a dead controller runs into it.
RESULT_TIMEOUT_S = 20.0
OVERRIDES = {
    'sim_bridge_node': (f'camera_width:={CAMERA_SIZE[0]}', f'camera_height:={CAMERA_SIZE[1]}', 'camera_rate_hz:=4.0'),
    'planner_node': (f'result_timeout_s:={RESULT_TIMEOUT_S}',),
    'controller_node': (),
    'lifecycle_manager': ('node_names:=[controller_node,planner_node]',),
}
START_TIMEOUT_S = 240.0          # three processes importing torch on a busy 2-core machine
EPISODE_TIMEOUT_S = 300.0        # 8 segments of plan + motion, with room for a slow machine
QUIET_S = 3.0                    # how long "nothing moved" is watched for after a refusal
SETTLE_FRAMES = 5                # per camera after a reset or a camera stop: 1.25 s of sim time at 4 Hz

# Measured on this graph over the evaluation seeds 1000-1009 (seen phrasings; `hdp demo --task T
# --episodes 10 --seed 1000` with these cameras). With the checkpoints of 2026-12-01: reach_target
# succeeded on 8 (not 1001, 1005), open_drawer on 5 (1003, 1004, 1007, 1008, 1009). With the
# RK-Diffuser of 2026-12-02 (and the simulator whose arm follows streamed paths): reach_target on
# the same 8, open_drawer on 5 (1000, 1003, 1004, 1007, 1008); with its refinement smoothing the
# samples, reach_target on 9 (not 1005), open_drawer on 8 (not 1002, 1005). With the eleven-task
# pair of 2026-12-05 (`hdp demo --task T --episodes 20 --seed 1000 --phrasing seen`, 640x480, seeds
# 1000-1019): reach_target on 14 (1003, 1011 and 1005 in one segment), open_drawer on 17 (not the
# refused 1003, 1004, 1006). Three of the successes per task, and a task passes when one of them
# succeeds: a rare unlucky episode does not fail CI, a broken graph fails all three. The steadiest
# seed goes first.
SUCCESS_SEEDS = {'reach_target': (1003, 1011, 1005), 'open_drawer': (1012, 1010, 1008)}
# Several segments (approach, grasp, pull), so the restarted controller has work left to do; the
# recovery is checked strictly on every try, the task's success on one of two.
KILL_TASK, KILL_SEEDS = 'open_drawer', (1008, 1014)


class Graph:
    """The three node processes and this process's node that drives and records them.

    Every message on the watched topics is kept with its arrival time (time.monotonic()), so a
    test asks "what came since t" and waits on conditions with deadlines, never on sleeps.
    """

    WATCHED = ((String, topics.STATUS), (String, topics.SIM_EPISODE), (Bool, topics.SIM_SUCCESS),
               (PoseStamped, topics.NEXT_BEST_POSE), (Header, topics.SEGMENT_RESULT),
               (JointTrajectory, topics.ARM_TRAJECTORY),
               *((Image, topics.color_image(camera)) for camera in topics.CAMERAS))

    def __init__(self, domain: int, log_dir: Path):
        self.env = dict(os.environ, ROS_DOMAIN_ID=str(domain), PYTHONUNBUFFERED='1', OMP_NUM_THREADS='1')
        self.log_dir, self.procs = log_dir, {}
        self.instructions = []                               # (text, sent at) not yet seen to end
        self.seen = collections.defaultdict(list)            # topic -> [(arrival s, msg)]
        self._changed = threading.Condition(threading.RLock())
        ros.init(args=[], domain_id=domain)
        self.node = ros.Node('graph_test')
        for msg_type, topic in self.WATCHED:
            qos = {topics.SIM_EPISODE: topics.LATCHED_QOS, topics.STATUS: topics.STATUS_QOS}.get(
                topic, topics.SENSOR_QOS if msg_type is Image else QoSProfile(depth=100))
            keep = (lambda msg: msg.header) if msg_type is Image else (lambda msg: msg)   # frames: when, not pixels
            self.node.create_subscription(msg_type, topic, lambda msg, topic=topic, keep=keep: self._record(
                topic, keep(msg)), qos)
        self.pub = {topic: self.node.create_publisher(String, topic, 10)
                    for topic in (topics.INSTRUCTION, topics.SIM_RESET, topics.SIM_CAMERAS)}
        self.pub[topics.NEXT_BEST_POSE] = self.node.create_publisher(PoseStamped, topics.NEXT_BEST_POSE,
                                                                     topics.COMMAND_QOS)
        self._executor = SingleThreadedExecutor()
        self._executor.add_node(self.node)
        self._spinning = True
        self._spinner = threading.Thread(target=self._spin, daemon=True)
        self._spinner.start()

    # -- this process's node ---------------------------------------------------------------
    def _spin(self):
        while self._spinning and rclpy.ok():
            try:
                self._executor.spin_once(timeout_sec=0.1)
            except ExternalShutdownException:
                return

    def _record(self, topic, msg):
        with self._changed:
            self.seen[topic].append((time.monotonic(), msg))
            self._changed.notify_all()

    def since(self, topic: str, t: float) -> list:
        with self._changed:
            return [msg for arrived, msg in self.seen[topic] if arrived >= t]

    def status(self, t: float = 0.0, prefix: str = '') -> list[str]:
        return [m.data for m in self.since(topics.STATUS, t) if m.data.startswith(prefix)]

    def wait(self, what: str, predicate, timeout: float):
        """predicate()'s first truthy value, or an AssertionError with what the graph said."""
        with self._changed:
            value = self._changed.wait_for(predicate, timeout)
        if not value:
            raise AssertionError(f'no {what} within {timeout:.0f} s\n{self.report()}')
        return value

    def quiet(self, topic: str, t: float, seconds: float = QUIET_S) -> list:
        """What arrives on ``topic`` from t until ``seconds`` after now: an absence is watched for a while."""
        with self._changed:
            self._changed.wait_for(lambda: self.since(topic, t), seconds)
        return self.since(topic, t)

    def publish(self, topic: str, msg) -> float:
        t = time.monotonic()
        self.pub[topic].publish(msg)
        return t

    def report(self) -> str:
        lines = '\n'.join(self.status()[-40:])
        logs = '\n'.join(f'--- {path.name} (tail)\n' + '\n'.join(path.read_text(errors='replace').splitlines()[-15:])
                         for path in sorted(self.log_dir.glob('*.log')))
        return f'status:\n{lines}\n{logs}'

    # -- the node processes ----------------------------------------------------------------
    def start(self, name: str) -> float:
        """Start one node the way `hdp launch` does: this Python, the graph's YAML, the test's overrides."""
        command = [sys.executable, '-m', f'{PACKAGES[name]}.{name}', '--ros-args', '--params-file', str(PARAMS)]
        for override in OVERRIDES[name]:
            command += ['-p', override]
        with open(self.log_dir / f'{name}.log', 'a') as log:
            self.procs[name] = subprocess.Popen(command, env=self.env, stdout=log, stderr=subprocess.STDOUT,
                                                start_new_session=True)
        return time.monotonic()

    def wait_ready(self, name: str, t: float) -> None:
        self.wait(f'{name} ready', lambda: self.status(t, f'{name}: ready') or self._died(name), START_TIMEOUT_S)
        assert self.procs[name].poll() is None, f'{name} exited\n{self.report()}'

    def _died(self, name: str) -> bool:
        return self.procs[name].poll() is not None

    def kill(self, name: str) -> None:
        self.procs[name].send_signal(signal.SIGKILL)
        self.procs[name].wait(timeout=30)

    def close(self) -> None:
        running = [p for p in self.procs.values() if p.poll() is None]
        for proc in running:
            proc.send_signal(signal.SIGINT)
        for proc in running:
            try:
                proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(timeout=10)
        self._spinning = False
        self._spinner.join(timeout=5)
        self.node.destroy_node()
        rclpy.try_shutdown()

    # -- episodes --------------------------------------------------------------------------
    def new_episode(self, task: str, seed: int) -> dict:
        """Reset the sim and wait until both cameras show the new scene; returns /hdp/sim/episode."""
        for text, sent in self.instructions:       # a test that failed may have left one running
            self.wait(f'end of {text!r}', lambda: self.end_of(text, sent), EPISODE_TIMEOUT_S)
        self.instructions.clear()
        t = self.publish(topics.SIM_RESET, String(data=json.dumps({'task': task, 'seed': seed})))

        def announced():
            with self._changed:
                return next(((arrived, e) for arrived, e in ((a, json.loads(m.data)) for a, m in
                                                             self.seen[topics.SIM_EPISODE] if a >= t)
                             if e['task'] == task and e['seed'] == seed), None)

        shown, episode = self.wait(f'episode {task} seed {seed}', announced, 60)
        self.wait_frames(shown, topics.CAMERAS)
        return episode

    def wait_frames(self, t: float, cameras) -> None:
        """Wait until ``cameras`` have sent SETTLE_FRAMES frames since t.

        The planner judges frames by their stamps against the last joint state it processed; a
        reset restarts sim time and a process on a busy machine lags, so the graph is given a
        second of sim time to leave the old scene's (or a stopped camera's) last frames behind.
        """
        self.wait(f'{SETTLE_FRAMES} frames from {", ".join(cameras)}', lambda: all(
            len(self.since(topics.color_image(c), t)) >= SETTLE_FRAMES for c in cameras), 60)

    def end_of(self, instruction: str, t: float):
        """The planner's last line for this instruction (success, budget, failure, timeout), if said."""
        prefix = f'planner_node: instruction {instruction!r}: '
        return next((s for s in self.status(t, prefix) if not s.startswith(prefix + 'up to')), None)

    def instruct(self, instruction: str) -> float:
        t = self.publish(topics.INSTRUCTION, String(data=instruction))
        self.instructions.append((instruction, t))
        return t

    def wait_end(self, instruction: str, t: float) -> str:
        return self.wait(f'end of {instruction!r}', lambda: self.end_of(instruction, t), EPISODE_TIMEOUT_S)

    def run(self, instruction: str) -> tuple[float, str]:
        """Send the instruction; (when it was sent, the planner's final line) once it ends."""
        t = self.instruct(instruction)
        return t, self.wait_end(instruction, t)

    def seen_success(self, t: float) -> bool:
        return any(m.data for m in self.since(topics.SIM_SUCCESS, t))


def instruction_for(episode: dict) -> str:
    """A phrasing seen in training for this episode, as the Table 1 evaluation gives it."""
    return episode_instruction(episode['task'], episode['seed'], episode['variation'], 'seen')


@pytest.fixture(scope='module')
def graph(tmp_path_factory):
    domain = 1 + next(conftest._domains) % 199        # one domain for the module: one process, one domain
    graph = Graph(domain, tmp_path_factory.mktemp('graph_logs'))
    try:
        started = {name: graph.start(name) for name in PACKAGES}
        for name in ('planner_node', 'controller_node'):
            graph.wait_ready(name, started[name])
        graph.wait('the sim episode', lambda: graph.seen[topics.SIM_EPISODE], START_TIMEOUT_S)
        graph.wait('the planner listening', lambda: graph.pub[topics.INSTRUCTION].get_subscription_count(), 30)
        yield graph
    finally:
        graph.close()


def trajectories_since(graph: Graph, t: float) -> list:
    return graph.since(topics.ARM_TRAJECTORY, t)


# --- instructions to success --------------------------------------------------------------------

@pytest.mark.parametrize('task', SUCCESS_SEEDS)
def test_an_instruction_reaches_success(graph, task):
    outcomes = []
    for seed in SUCCESS_SEEDS[task]:
        episode = graph.new_episode(task, seed)
        instruction = instruction_for(episode)
        started = time.monotonic()
        t, end = graph.run(instruction)
        outcomes.append(f'seed {seed} {instruction!r}: {end} ({time.monotonic() - started:.0f} s)')
        if end.endswith(' segments') and 'task succeeded after' in end:
            break
    else:
        pytest.fail(f'{task}: no seed of {SUCCESS_SEEDS[task]} succeeded:\n' + '\n'.join(outcomes))
    assert graph.seen_success(t), outcomes            # the sim agrees with the planner
    sent = graph.since(topics.ARM_TRAJECTORY, t)
    assert sent and all(list(msg.joint_names) == list(panda.ARM_JOINTS) for msg in sent)
    results = graph.since(topics.SEGMENT_RESULT, t)
    assert results and results[-1].frame_id == topics.SEGMENT_DONE


# --- refusals -------------------------------------------------------------------------------------

def test_bad_instructions_are_refused_and_nothing_moves(graph):
    graph.new_episode('reach_target', 1000)
    t = time.monotonic()
    for text in ('', 'reach ' * 50, 'xyzzy plugh'):
        graph.publish(topics.INSTRUCTION, String(data=text))
    refusals = graph.wait('two refusals', lambda: (lambda r: r if len(r) == 2 else None)(
        graph.status(t, 'planner_node: refused instruction: ')), 30)
    assert refusals == ['planner_node: refused instruction: the instruction is empty',
                        'planner_node: refused instruction: the instruction has 299 characters, more than 256']
    # The sentence encoder reads any words: what grounds in nothing, the agent's confidence refuses.
    ungrounded = graph.wait('the made-up words refused', lambda: graph.status(
        t, "planner_node: instruction 'xyzzy plugh': refused: the agent cannot ground it"), 60)
    assert 'below min_confidence' in ungrounded[0], ungrounded
    assert graph.quiet(topics.ARM_TRAJECTORY, t) == []
    assert graph.since(topics.NEXT_BEST_POSE, t) == []


def test_a_nan_pose_is_rejected_with_a_status_line_and_no_trajectory(graph):
    graph.new_episode('reach_target', 1000)
    stamp = Time(sec=7)                         # no planner stamp is this old: it is wall time
    nan_pose = PoseStamped(header=Header(stamp=stamp, frame_id=topics.NBP_FRAME), pose=Pose(
        position=Point(x=math.nan, y=0.0, z=1.0), orientation=Quaternion(x=1.0, y=0.0, z=0.0, w=0.0)))
    t = graph.publish(topics.NEXT_BEST_POSE, nan_pose)
    result = graph.wait('a result for the NaN pose', lambda: next(
        (r for r in graph.since(topics.SEGMENT_RESULT, t) if r.stamp == stamp), None), 30)
    assert result.frame_id.startswith('failed: invalid pose: position must be finite'), result.frame_id
    refusal = graph.status(t, 'controller_node: refused segment 7.000: ')
    assert refusal and 'position must be finite' in refusal[0], graph.report()
    assert graph.quiet(topics.ARM_TRAJECTORY, t) == []


def test_an_nbp_the_arm_cannot_reach_is_refused_with_its_distance_and_nothing_moves(graph):
    """The hand pointing up, 3 cm above the table: the plan ends far from it, so nothing is sent."""
    graph.new_episode('reach_target', 1000)
    stamp = Time(sec=8)
    up = PoseStamped(header=Header(stamp=stamp, frame_id=topics.NBP_FRAME), pose=Pose(
        position=Point(x=0.7, y=0.3, z=0.78), orientation=Quaternion(x=0.0, y=0.0, z=0.0, w=1.0)))
    t = graph.publish(topics.NEXT_BEST_POSE, up)
    result = graph.wait('a result for the unreachable pose', lambda: next(
        (r for r in graph.since(topics.SEGMENT_RESULT, t) if r.stamp == stamp), None), 60)
    assert re.fullmatch(r'failed: rkd plan ends [\d.]+ m and [\d.]+ deg from the NBP \(tolerance 0.100 m, '
                        r'15.0 deg\): the NBP is not reachable as given', result.frame_id), result.frame_id
    assert graph.quiet(topics.ARM_TRAJECTORY, t) == []


def test_a_camera_that_stops_is_named_in_the_planner_timeout(graph):
    episode = graph.new_episode('reach_target', 1000)
    try:
        t = graph.publish(topics.SIM_CAMERAS, String(data='front'))
        stopped = graph.wait('the bridge stopping the side camera', lambda: next(
            (arrived for arrived, m in graph.seen[topics.STATUS] if arrived >= t and m.data ==
             'sim_bridge_node: cameras publishing: front; stopped: side'), None), 30)
        graph.wait_frames(stopped, ('front',))
        instruction = instruction_for(episode)
        sent, end = graph.run(instruction)
        assert end.startswith(f"planner_node: instruction {instruction!r}: camera side timed out after 5.0 s "
                              '(no fresh side camera colour, side camera depth'), end
        assert graph.since(topics.NEXT_BEST_POSE, sent) == [] and trajectories_since(graph, sent) == []
        assert graph.since(topics.color_image('side'), stopped + 1.0) == []    # one frame may be in flight
        graph.publish(topics.SIM_CAMERAS, String(data='front,sdie'))
        graph.wait('a refused camera selection', lambda: graph.status(
            t, "sim_bridge_node: rejected camera selection: unknown camera(s) ['sdie']"), 30)
    finally:
        t = graph.publish(topics.SIM_CAMERAS, String(data='front,side'))
        graph.wait('both cameras back', lambda: graph.status(
            t, 'sim_bridge_node: cameras publishing: front, side; stopped: none'), 30)


# --- what an independent ROS 2 peer sees -----------------------------------------------------------

def test_a_plain_cyclonedds_rosbags_peer_decodes_the_graph(graph):
    reader = subprocess.Popen([sys.executable, str(Path(__file__).with_name('interop_reader.py')), '120'],
                              env=graph.env, text=True, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        assert reader.stdout.readline().strip() == 'ready', reader.stderr.read() if reader.poll() else ''
        episode = graph.new_episode('reach_target', SUCCESS_SEEDS['reach_target'][0])
        t, end = graph.run(instruction_for(episode))
        out, err = reader.communicate(timeout=60)
    finally:
        if reader.poll() is None:
            reader.kill()
            reader.communicate()
    assert reader.returncode == 0, err
    facts = json.loads(out.strip().splitlines()[-1])
    joints = facts['joint_states']
    assert len(joints['name']) >= 7 and set(panda.ARM_JOINTS) <= set(joints['name'])
    assert len(joints['position']) == len(joints['name']) and all(map(math.isfinite, joints['position']))
    nbp = facts['next_best_pose']
    assert nbp['frame_id'] == 'world' and all(map(math.isfinite, nbp['position'] + nbp['orientation']))
    assert abs(np.linalg.norm(nbp['orientation']) - 1.0) < 1e-3
    planner_nbp = next(m for m in graph.since(topics.NEXT_BEST_POSE, t)
                       if [m.header.stamp.sec, m.header.stamp.nanosec] == nbp['stamp'])
    assert np.allclose(conversions.pose_to_xyz_quat(planner_nbp)[0], nbp['position'])
    trajectory = facts['joint_trajectory']
    assert trajectory['joint_names'] == [f'panda_joint{i}' for i in range(1, 8)]
    assert trajectory['points'] >= 2 and trajectory['finite'] and trajectory['times_increasing']

    discovery = subprocess.run([sys.executable, str(Path(__file__).with_name('discovery_reader.py'))],
                               env=graph.env, text=True, capture_output=True, timeout=60)
    assert discovery.returncode == 0, discovery.stderr
    names = {n['name'] for n in json.loads(discovery.stdout)}
    assert set(PACKAGES) <= names, names


# --- a controller that dies mid-task ---------------------------------------------------------------

def test_a_killed_controller_is_reported_and_a_restarted_one_finishes_the_task(graph):
    outcomes = []
    for seed in KILL_SEEDS:
        episode = graph.new_episode(KILL_TASK, seed)
        instruction = instruction_for(episode)
        t = graph.instruct(instruction)
        graph.wait('the first trajectory', lambda: trajectories_since(graph, t), 120)
        graph.kill('controller_node')                     # SIGKILL while the segment runs
        killed = time.monotonic()
        restarted = graph.start('controller_node')
        lost = graph.wait('the planner reporting the missing result', lambda: graph.status(
            killed, 'planner_node: segment 1: no result from the controller'), RESULT_TIMEOUT_S + 60)
        assert lost[0] == (f'planner_node: segment 1: no result from the controller within {RESULT_TIMEOUT_S:.1f} s '
                           '(is controller_node running?); re-observing'), lost
        graph.wait_ready('controller_node', restarted)
        end = graph.wait_end(instruction, t)
        done_after_restart = [r for r in graph.since(topics.SEGMENT_RESULT, restarted)
                              if r.frame_id == topics.SEGMENT_DONE]
        assert done_after_restart and trajectories_since(graph, restarted), graph.report()
        outcomes.append(f'seed {seed}: {end}')
        if 'task succeeded after' in end:
            assert graph.seen_success(killed)
            return
    pytest.fail('no seed succeeded after the restart:\n' + '\n'.join(outcomes) + f'\n{graph.report()}')


# --- a simulator that dies mid-segment (last: the graph runs on a restarted bridge afterwards) ------

def test_a_dead_simulator_is_named_by_the_controller_and_the_planner_within_seconds(graph):
    episode = graph.new_episode(KILL_TASK, KILL_SEEDS[0])
    instruction = instruction_for(episode)
    t = graph.instruct(instruction)
    graph.wait('the first trajectory', lambda: trajectories_since(graph, t), 120)
    graph.kill('sim_bridge_node')                  # /joint_states and /clock stop with it
    killed = time.monotonic()
    failed = graph.wait('the controller naming the dead simulator', lambda: [
        s for s in graph.status(killed, 'controller_node: segment ') if 'failed: no /joint_states for' in s], 30)
    end = graph.wait_end(instruction, t)
    noticed_s = time.monotonic() - killed
    assert 'is sim_bridge_node (or the robot driver) running?' in failed[0], failed
    assert 'no /joint_states for' in end and 'is sim_bridge_node' in end, end       # not the controller blamed
    assert noticed_s < 15.0, f'noticed after {noticed_s:.1f} s'
    assert not graph.status(killed, 'planner_node: segment 1: no result from the controller'), graph.report()
    restarted = graph.start('sim_bridge_node')
    graph.wait('the restarted simulator', lambda: graph.since(topics.SIM_EPISODE, restarted), START_TIMEOUT_S)
