"""`hdp demo`: the whole graph on one task, watched from outside, with its figures.

Starts sim_bridge_node, planner_node and controller_node as `hdp launch` does
(launch_cli.running_nodes), waits until they are connected, sends the episode's
instruction and follows the segment protocol from the outside: next-best pose ->
JointTrajectory -> segment result. Nothing here is part of the control loop; the demo
only listens, and it listens to the cameras and /joint_states best effort so that a slow
demo process never holds the graph back.

Per segment it splits the time into observe + predict (the previous result, or the
instruction, -> the NBP), controller (NBP -> JointTrajectory) and execution (trajectory ->
segment result), all on the demo's wall clock, so every stage includes the hops between
processes a user would see. CPU per node is utime + stime from /proc of each node process
and its children over the episode. The pure parts (EpisodeLog, cpu accounting, statistics,
the writers) are tested without a graph.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import random
import re
import signal
import sys
import time
from pathlib import Path

import numpy as np
import rclpy

from hdp_motion import panda
from hdp_msgs_py import conversions, ros, topics
from hdp_msgs_py.msg import Bool, Header, Image, JointState, JointTrajectory, PoseStamped, String

from .launch_cli import NODES, default_params_file, node_commands, running_nodes

METHODS = ('rkd', 'planner', 'pose_ik', 'joint')      # controller_node's `method` parameter
SAMPLERS = ('ddim', 'ddpm')                            # controller_node's `sampler` parameter
DEFAULT_SEED = 1000            # evaluation seeds start here, apart from every training seed
STARTUP_TIMEOUT_S = 300.0      # three processes importing torch and loading checkpoints on a busy CPU
SCENE_TIMEOUT_S = 60.0         # for a (reset) scene to show a frame and its success report
STAGES = ('observe_predict_s', 'controller_s', 'execution_s')
STAGE_LABELS = {'observe_predict_s': 'observe + predict (result -> NBP)',
                'controller_s': 'controller (NBP -> trajectory)',
                'execution_s': 'execution (trajectory -> result)',
                'episode_s': 'episode (instruction -> success)'}
GIF_WIDTH = 320                # px; the front camera is scaled down to keep the GIF small
GIF_SPEEDUP = 2.0              # the GIF plays sim time this many times faster
SAFE_DOMAINS = range(1, 102)   # ROS_DOMAIN_IDs whose ports stay below Linux's ephemeral range


# --- domain -------------------------------------------------------------------------------------

def pick_domain(env, rng: random.Random) -> tuple[int, bool]:
    """(ROS_DOMAIN_ID, picked): the environment's, else one drawn from SAFE_DOMAINS so that the
    demo's graph does not meet another graph on this machine (discovery is localhost-only)."""
    text = (env.get('ROS_DOMAIN_ID') or '').strip()
    if not text:
        return rng.choice(SAFE_DOMAINS), True
    if not text.isdigit() or int(text) > 232:
        raise ValueError(f'ROS_DOMAIN_ID must be an integer 0..232, got {text!r}')
    return int(text), False


# --- segments and episodes ----------------------------------------------------------------------

def stamp_ns(stamp) -> int:
    """A builtin_interfaces/Time as integer nanoseconds: the segment's key, compared exactly."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


@dataclasses.dataclass
class Segment:
    """One NBP and what became of it; times are seconds since the instruction."""
    index: int
    key: int                                   # the NBP's stamp, ns
    xyz: tuple
    gripper: str | None                        # 'open' | 'close'; None: no gripper goal with its stamp
    nbp_s: float
    observe_predict_s: float
    trajectory_s: float | None = None
    trajectory_points: int = 0
    trajectory_duration_s: float | None = None  # its time_from_start: sim time
    result_s: float | None = None
    result: str | None = None

    @property
    def controller_s(self) -> float | None:
        """NBP -> trajectory; NBP -> result when the controller refused (no trajectory)."""
        end = self.trajectory_s if self.trajectory_s is not None else self.result_s
        return None if end is None else end - self.nbp_s

    @property
    def execution_s(self) -> float | None:
        if self.trajectory_s is None or self.result_s is None:
            return None
        return self.result_s - self.trajectory_s

    def to_dict(self) -> dict:
        out = {**dataclasses.asdict(self), 'controller_s': self.controller_s, 'execution_s': self.execution_s}
        out['xyz'] = [round(v, 4) for v in self.xyz]
        return {k: round(v, 3) if isinstance(v, float) else v for k, v in out.items()}


class EpisodeLog:
    """One instruction's segments as seen from outside the graph, plus the front camera frames
    and arm joint positions for the GIF and plot. ``t`` arguments are the caller's clock
    (seconds); everything stored is relative to ``start``, the instruction's time."""

    def __init__(self, start: float):
        self.start = start
        self.segments: list[Segment] = []
        self.success_s: float | None = None
        self.frames: list[tuple[float, float, np.ndarray]] = []   # (t, sim stamp s, rgb)
        self.joints: list[tuple[float, float, np.ndarray]] = []   # (t, sim stamp s, (7,) rad)
        self.status: list[tuple[float, str]] = []
        self._goals: dict[int, bool] = {}      # gripper goals that came before their NBP
        self._mark = 0.0                       # when the planner's current observe + predict began

    def _t(self, t: float) -> float:
        return t - self.start

    @property
    def open_segment(self) -> Segment | None:
        last = self.segments[-1] if self.segments else None
        return last if last is not None and last.result is None else None

    def gripper_goal(self, key: int, is_open: bool) -> None:
        segment = next((s for s in self.segments if s.key == key), None)
        if segment is None:
            self._goals[key] = is_open
        else:
            segment.gripper = 'open' if is_open else 'close'

    def nbp(self, t: float, key: int, xyz) -> Segment:
        goal = self._goals.pop(key, None)
        segment = Segment(len(self.segments) + 1, key, tuple(float(v) for v in xyz),
                          None if goal is None else ('open' if goal else 'close'),
                          self._t(t), self._t(t) - self._mark)
        self.segments.append(segment)
        return segment

    def trajectory(self, t: float, points: int, duration_s: float) -> Segment | None:
        """The arm trajectory of the open segment (the controller plans one segment at a time)."""
        segment = self.open_segment
        if segment is not None and segment.trajectory_s is None:
            segment.trajectory_s, segment.trajectory_points = self._t(t), points
            segment.trajectory_duration_s = duration_s
        return segment

    def result(self, t: float, key: int, outcome: str) -> Segment | None:
        """The segment this result answers (by its stamp), now finished; None for another's."""
        segment = next((s for s in self.segments if s.key == key and s.result is None), None)
        if segment is not None:
            segment.result_s, segment.result = self._t(t), outcome
            self._mark = segment.result_s
        return segment

    def success(self, t: float) -> None:
        if self.success_s is None:
            self.success_s = self._t(t)


def segment_line(segment: Segment) -> str:
    """One line per finished segment, as `hdp demo` prints it."""
    x, y, z = segment.xyz

    def seconds(value):
        return '-' if value is None else f'{value:.2f} s'
    trajectory = ('' if segment.trajectory_s is None else
                  f', {segment.trajectory_points} points over {segment.trajectory_duration_s:.2f} s sim')
    return (f'segment {segment.index}: NBP ({x:.3f}, {y:.3f}, {z:.3f}) gripper {segment.gripper or "unchanged"} '
            f'-> {segment.result} at {segment.result_s:.1f} s | observe+predict {seconds(segment.observe_predict_s)}, '
            f'controller {seconds(segment.controller_s)}, execution {seconds(segment.execution_s)}{trajectory}')


def planner_outcome(line: str, instruction: str) -> tuple[str, str] | None:
    """What a /hdp/status line says about our instruction: ('refused' | 'started' | 'succeeded' |
    'ended', the planner's words), or None when it is about something else."""
    if line.startswith('planner_node: refused instruction: '):
        return 'refused', line.removeprefix('planner_node: refused instruction: ')
    prefix = f'planner_node: instruction {instruction!r}: '
    if not line.startswith(prefix):
        return None
    rest = line.removeprefix(prefix)
    if re.match(r'up to \d+ segments', rest):
        return 'started', rest
    return ('succeeded' if rest.startswith('task succeeded') else 'ended'), rest


# --- CPU ----------------------------------------------------------------------------------------

def parse_stat(text: str) -> tuple[int, int]:
    """(ppid, utime + stime + cutime + cstime in clock ticks) of a /proc/<pid>/stat line.

    The command name (field 2) may hold spaces and parentheses: fields are counted after the
    last ')'. cutime + cstime hold the children that have already exited and been waited for.
    """
    fields = text[text.rindex(')') + 2:].split()
    return int(fields[1]), sum(int(v) for v in fields[11:15])


def tree_ticks(root: int, stats: dict[int, str]) -> int | None:
    """CPU ticks of ``root`` and its live descendants, from pid -> /proc stat text; None if gone."""
    if root not in stats:
        return None
    parsed = {pid: parse_stat(text) for pid, text in stats.items()}
    children: dict[int, list[int]] = {}
    for pid, (ppid, _) in parsed.items():
        children.setdefault(ppid, []).append(pid)
    total, todo = 0, [root]
    while todo:
        pid = todo.pop()
        total += parsed[pid][1]
        todo += children.get(pid, [])
    return total


def read_stats(proc: Path = Path('/proc')) -> dict[int, str]:
    """pid -> the text of /proc/<pid>/stat, for every process still there."""
    stats = {}
    for entry in proc.iterdir():
        if entry.name.isdigit():
            with contextlib.suppress(OSError):       # gone meanwhile
                stats[int(entry.name)] = (entry / 'stat').read_text()
    return stats


def cpu_seconds(pids: dict[str, int], stats: dict[int, str], ticks_per_s: float) -> dict[str, float]:
    """name -> CPU seconds so far of that process tree; names whose process is gone are left out."""
    ticks = {name: tree_ticks(pid, stats) for name, pid in pids.items()}
    return {name: t / ticks_per_s for name, t in ticks.items() if t is not None}


def cpu_usage(before: dict[str, float], after: dict[str, float], wall_s: float) -> dict[str, dict]:
    """name -> {'cpu_s', 'cpu_percent'} between two cpu_seconds samples (100% = one core)."""
    return {name: {'cpu_s': round(after[name] - before[name], 3),
                   'cpu_percent': round(100.0 * (after[name] - before[name]) / wall_s, 1) if wall_s > 0 else None}
            for name in before if name in after}


# --- figures ------------------------------------------------------------------------------------

def stats(values) -> dict:
    """{'n', 'p50', 'p95', 'mean', 'max'} of some seconds; None each when there are none."""
    values = np.asarray([v for v in values if v is not None], dtype=float)
    if not len(values):
        return {'n': 0, 'p50': None, 'p95': None, 'mean': None, 'max': None}
    return {'n': int(len(values)), 'p50': round(float(np.percentile(values, 50)), 3),
            'p95': round(float(np.percentile(values, 95)), 3), 'mean': round(float(values.mean()), 3),
            'max': round(float(values.max()), 3)}


def figures(episodes: list[dict]) -> dict:
    """The issue's figures over episodes as summary.json holds them: stage times over all their
    segments, episode time over the successful ones, CPU per node over all of them."""
    segments = [s for e in episodes for s in e['segments']]
    out = {stage: stats(s[stage] for s in segments) for stage in STAGES}
    out['episode_s'] = stats(e['success_s'] for e in episodes if e['success'])
    wall = sum(e['wall_s'] for e in episodes)
    cpu = {}
    for name in NODES:
        spent = [e['cpu'][name]['cpu_s'] for e in episodes if name in e['cpu']]
        if spent:
            cpu[name] = {'cpu_s': round(sum(spent), 3), 'cpu_percent': round(100.0 * sum(spent) / wall, 1)}
    out['cpu'] = cpu
    out['episodes'] = len(episodes)
    out['succeeded'] = sum(bool(e['success']) for e in episodes)
    return out


def format_figures(figs: dict) -> str:
    """The figures as the table `hdp demo` prints and the README quotes."""
    def cell(value):
        return '-' if value is None else f'{value:.2f}'
    lines = [f"{figs['succeeded']} of {figs['episodes']} episodes succeeded, "
             f"{figs['observe_predict_s']['n']} segments; wall-clock seconds",
             '', '| stage | n | p50 | p95 | mean | max |', '|---|---|---|---|---|---|']
    for key in (*STAGES, 'episode_s'):
        s = figs[key]
        lines.append(f"| {STAGE_LABELS[key]} | {s['n']} | {cell(s['p50'])} | {cell(s['p95'])} | "
                     f"{cell(s['mean'])} | {cell(s['max'])} |")
    lines += ['', '| node | CPU s | mean CPU % (100 = one core) |', '|---|---|---|']
    lines += [f"| {name} | {c['cpu_s']:.1f} | {c['cpu_percent']:.0f} |" for name, c in figs['cpu'].items()]
    return '\n'.join(lines)


# --- writers ------------------------------------------------------------------------------------

def gif_durations_ms(stamps_s, speedup: float = GIF_SPEEDUP, last_ms: int = 1000) -> list[int]:
    """Per-frame display times that replay the frames' sim-time spacing ``speedup`` times faster."""
    gaps = np.diff(np.asarray(stamps_s, dtype=float)) * 1000.0 / speedup
    return [max(20, int(round(g))) for g in gaps] + [last_ms]


def write_gif(frames: list[np.ndarray], durations_ms: list[int], path: Path) -> None:
    """An animated GIF (looping) of RGB frames (H, W, 3) uint8."""
    from PIL import Image
    if not frames:
        raise ValueError('no frames to write')
    images = [Image.fromarray(np.ascontiguousarray(f)) for f in frames]
    images[0].save(path, save_all=True, append_images=images[1:], duration=durations_ms, loop=0)


def caption(frame: np.ndarray, text: str) -> np.ndarray:
    """A copy of an RGB frame with ``text`` on a dark band along its top."""
    import cv2
    out = np.array(frame, copy=True)
    out[:18] = (out[:18] * 0.35).astype(np.uint8)
    cv2.putText(out, text, (4, 13), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1, cv2.LINE_AA)
    return out


def ee_positions(q: np.ndarray) -> np.ndarray:
    """World positions (N, 3) of panda_grasptarget for arm joint positions (N, 7)."""
    import torch

    from hdp_motion import kinematics
    pose = kinematics.fk_pose(torch.as_tensor(np.asarray(q, dtype=np.float64).reshape(-1, 7)))
    return pose[:, :3].numpy()


def wall_to_sim(events_s, wall_s, sim_s) -> np.ndarray:
    """Times on the demo's clock -> sim time, through samples (wall_s, sim_s) taken together
    (joint states: stamped in sim time, received on the wall clock); clamped at the ends."""
    return np.interp(np.asarray(events_s, dtype=float), np.asarray(wall_s, dtype=float),
                     np.asarray(sim_s, dtype=float))


def write_plot(wall_s, sim_s, q, segments: list[Segment], success_s: float | None, title: str,
               path: Path) -> None:
    """Joint positions over sim time with each segment's execution shaded, and the end-effector
    path in 3D with the NBPs numbered (green: gripper open, red: close).

    Sim time, not the wall clock: the bridge steps physics in bursts between camera renders, so
    on the wall clock the joints would move in stairs. ``wall_s`` (s since the instruction, when
    each joint state arrived) maps the segment events onto sim time.
    """
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    q = np.asarray(q, dtype=float).reshape(-1, 7)
    sim0 = float(wall_to_sim(0.0, wall_s, sim_s))

    def at(event_s):
        return float(wall_to_sim(event_s, wall_s, sim_s)) - sim0
    fig = plt.figure(figsize=(12, 4.8))
    ax = fig.add_subplot(1, 2, 1)
    for j in range(7):
        ax.plot(np.asarray(sim_s, dtype=float) - sim0, q[:, j], lw=1.2, label=f'joint {j + 1}')
    for s in segments:
        ax.axvline(at(s.nbp_s), color='0.4', ls=':', lw=0.8)
        if s.trajectory_s is not None and s.result_s is not None:
            ax.axvspan(at(s.trajectory_s), at(s.result_s), color='C0' if s.result == 'done' else 'C3', alpha=0.08)
        ax.text(at(s.nbp_s), 1.0, f' {s.index}', transform=ax.get_xaxis_transform(), va='top', fontsize=8)
    if success_s is not None:
        ax.axvline(at(success_s), color='green', lw=1.5, label='success')
    ax.set_xlabel('sim time since the instruction, s (dotted: NBP received; shaded: execution)')
    ax.set_ylabel('joint position (rad)')
    ax.legend(fontsize=7, ncol=2, loc='lower left')
    ax3 = fig.add_subplot(1, 2, 2, projection='3d')
    if len(q):
        ee = ee_positions(q)
        ax3.plot(ee[:, 0], ee[:, 1], ee[:, 2], color='C0', lw=1.5, label='end effector')
        ax3.scatter(*ee[0], color='k', s=20, label='start')
    for s in segments:
        ax3.scatter(*s.xyz, color='green' if s.gripper == 'open' else 'red' if s.gripper == 'close' else 'gray',
                    s=40, marker='^')
        ax3.text(*s.xyz, f' {s.index}', fontsize=8)
    ax3.set_xlabel('x (m)')
    ax3.set_ylabel('y (m)')
    ax3.set_zlabel('z (m)')
    ax3.set_title('end-effector path and NBPs (^)', fontsize=9)
    ax3.legend(fontsize=7, loc='upper left')
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def write_episode_files(log: EpisodeLog, record: dict, out: Path, title: str) -> None:
    """The episode's GIF and trajectory plot, named in ``record`` (relative to ``out``)."""
    stem = f"{record['task']}_seed{record['seed']}"
    if log.frames:
        def label(t):
            index = sum(s.nbp_s <= t for s in log.segments)
            return f"{record['task']} seed {record['seed']}  t={max(t, 0.0):4.1f}s  " + (
                f'segment {index}' if index else 'observing')
        frames = [caption(rgb, label(t)) for t, _, rgb in log.frames]
        write_gif(frames, gif_durations_ms([stamp for _, stamp, _ in log.frames]), out / f'{stem}.gif')
        record['gif'] = f'{stem}.gif'
    if log.joints:
        wall, sim, q = zip(*log.joints)
        write_plot(wall, sim, np.array(q), log.segments, log.success_s, title, out / f'{stem}_trajectory.png')
        record['plot'] = f'{stem}_trajectory.png'


# --- the graph, from outside --------------------------------------------------------------------

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
        self.instruction = self.create_publisher(String, topics.INSTRUCTION, topics.COMMAND_QOS)
        self.reset = self.create_publisher(String, topics.SIM_RESET, topics.COMMAND_QOS)
        self._arm_joints = list(panda.ARM_JOINTS)
        for msg_type, topic, callback, qos in (
                (String, topics.SIM_EPISODE, self._on_episode, topics.LATCHED_QOS),
                (Bool, topics.SIM_SUCCESS, self._on_success, topics.COMMAND_QOS),
                (String, topics.STATUS, self._on_status, topics.STATUS_QOS),
                (JointState, topics.NEXT_BEST_GRIPPER, self._on_gripper_goal, topics.COMMAND_QOS),
                (PoseStamped, topics.NEXT_BEST_POSE, self._on_nbp, topics.COMMAND_QOS),
                (JointTrajectory, topics.ARM_TRAJECTORY, self._on_trajectory, topics.COMMAND_QOS),
                (Header, topics.SEGMENT_RESULT, self._on_result, topics.COMMAND_QOS),
                (Image, topics.color_image('front'), self._on_frame, topics.SENSOR_QOS),
                (JointState, topics.JOINT_STATES, self._on_joints, topics.SENSOR_QOS)):
            self.create_subscription(msg_type, topic, callback, qos)

    def not_connected(self) -> list[str]:
        """What is not matched yet between the demo and the nodes (empty: the graph is up)."""
        wanted = [('planner_node subscribed to ' + topics.INSTRUCTION, self.instruction.get_subscription_count()),
                  ('sim_bridge_node subscribed to ' + topics.SIM_RESET, self.reset.get_subscription_count()),
                  ('controller_node subscribed to ' + topics.NEXT_BEST_POSE,
                   self.count_subscribers(topics.NEXT_BEST_POSE)),
                  ('controller_node publishing ' + topics.SEGMENT_RESULT, self.count_publishers(topics.SEGMENT_RESULT)),
                  ('planner_node publishing ' + topics.NEXT_BEST_POSE, self.count_publishers(topics.NEXT_BEST_POSE))]
        missing = [what for what, count in wanted if count < 1]
        if self.count_publishers(topics.STATUS) < len(NODES):
            missing.append(f'{topics.STATUS} from all {len(NODES)} nodes')
        return missing

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
        if self.log is not None:
            self.log.status.append((self.now() - self.log.start, msg.data))

    def _on_gripper_goal(self, msg):
        if self.log is not None and len(msg.position) == 1:
            self.log.gripper_goal(stamp_ns(msg.header.stamp),
                                  float(msg.position[0]) >= panda.GRIPPER_OPEN_WIDTH / 2)

    def _on_nbp(self, msg):
        if self.log is not None:
            p = msg.pose.position
            self.log.nbp(self.now(), stamp_ns(msg.header.stamp), (p.x, p.y, p.z))

    def _on_trajectory(self, msg):
        if self.log is not None and msg.points:
            duration = conversions.duration_to_seconds(msg.points[-1].time_from_start)
            self.log.trajectory(self.now(), len(msg.points), duration)

    def _on_result(self, msg):
        if self.log is not None:
            segment = self.log.result(self.now(), stamp_ns(msg.stamp), msg.frame_id)
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


class Session:
    """The demo node spinning while the node processes run; every wait checks both."""

    def __init__(self, node, procs: dict, stop: list):
        self.node, self.procs, self.stop = node, procs, stop

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
            rclpy.spin_once(self.node, timeout_sec=0.1)
        return True


def run_episode(session: Session, seed: int, instruction: str | None, timeout_s: float,
                cpu_sample, say) -> tuple[dict, EpisodeLog]:
    """One instruction on the current scene: (its summary record, its EpisodeLog).

    The scene is ready when it has shown a front frame and reported no success since it was
    set; the instruction then goes out and the episode ends with the planner's last word on it
    (success, failure, timeout) or after ``timeout_s``.
    """
    node = session.node
    if not session.spin_until(lambda: not node.scene_missing() and node.episode['seed'] == seed, SCENE_TIMEOUT_S):
        raise GraphDown(f'the scene of seed {seed} did not come up within {SCENE_TIMEOUT_S:.0f} s '
                        f'(waiting for {", ".join(node.scene_missing())})')
    episode = dict(node.episode)
    text = (instruction or episode['instruction']).strip()
    say(f"episode {episode['task']} seed {seed} variation {episode['variation']}: {text!r}")
    before = cpu_sample()
    log = EpisodeLog(node.now())
    log.frames.append((0.0, *node.frame))           # the scene before anything moves
    node.log = log
    node.instruction.publish(String(data=text))
    outcome = None

    def finished() -> bool:
        nonlocal outcome
        for _, line in log.status:
            verdict = planner_outcome(line, text)
            if verdict is not None and verdict[0] != 'started':
                outcome = verdict
                return True
        return False
    ended = session.spin_until(finished, timeout_s)
    wall_s = node.now() - log.start
    node.log = None
    cpu = cpu_usage(before, cpu_sample(), wall_s)
    if not ended:
        outcome = ('timeout', f'no end within {timeout_s:.0f} s')
    record = {'task': episode['task'], 'seed': seed, 'variation': episode['variation'], 'instruction': text,
              'outcome': outcome[0], 'reason': outcome[1],
              'success': outcome[0] == 'succeeded',
              'success_s': log.success_s, 'wall_s': round(wall_s, 3),
              'segments': [s.to_dict() for s in log.segments], 'cpu': cpu,
              'status': [f'{t:7.2f} {line}' for t, line in log.status]}
    return record, log


# --- the command --------------------------------------------------------------------------------

def configure(parser) -> None:
    """Run the HDP graph on one task and show it: segments, a GIF, a trajectory plot, figures.

    Starts sim_bridge_node, planner_node and controller_node (as `hdp launch`), waits until they
    are connected, sends the episode's instruction and prints one line per segment. Writes to
    OUT: <task>_seed<S>.gif (front camera), <task>_seed<S>_trajectory.png (joints over time,
    end-effector path and NBPs), summary.json (segments, stage times, CPU per node) and the
    nodes' output in logs/. Exit 0 when every episode succeeded, 1 on a failure or timeout,
    2 on bad arguments or a refused instruction, 130 on Ctrl-C; the nodes are stopped on every exit.
    """
    parser.add_argument('--task', required=True, metavar='TASK',
                        help='e.g. reach_target or open_drawer (an unknown name lists the six tasks)')
    parser.add_argument('--instruction', default=None,
                        help="what to say (default: the episode's own instruction for the task and seed)")
    parser.add_argument('--seed', type=int, default=DEFAULT_SEED,
                        help=f'scene seed (default {DEFAULT_SEED}: evaluation seeds, never trained on)')
    parser.add_argument('--episodes', type=int, default=1,
                        help='episodes on seeds SEED, SEED+1, ...; the sim is reset between them and the '
                             'graph stays up, so the figures get p50/p95 (default 1)')
    parser.add_argument('--out', type=Path, default=Path('demo_out'), help='output directory (default demo_out/)')
    parser.add_argument('--method', choices=METHODS, default='rkd', help='low-level method (default rkd)')
    parser.add_argument('--sampler', choices=SAMPLERS, default='ddim',
                        help='RK-Diffuser sampler: ddim (5 steps, unguided), ddpm (100, guided) (default ddim)')
    parser.add_argument('--timeout', type=float, default=180.0, metavar='S',
                        help='seconds per episode, instruction to the end (default 180)')
    parser.add_argument('--params-file', type=Path, default=None,
                        help=f'node parameters (default: {default_params_file()})')
    parser.add_argument('--json', action='store_true',
                        help='print summary.json on stdout (progress goes to stderr)')
    parser.epilog = ('ROS_DOMAIN_ID: the environment\'s if set, else a free-looking one is picked at random '
                     f'from {SAFE_DOMAINS.start}..{SAFE_DOMAINS.stop - 1} and printed.')
    parser.set_defaults(func=run)


def argument_problem(args, tasks) -> str | None:
    """Why these arguments cannot run, or None."""
    if args.task not in tasks:
        return f'unknown task {args.task!r}; tasks: {", ".join(tasks)}'
    if args.instruction is not None and not args.instruction.strip():
        return '--instruction is empty'
    if args.seed < 0 or args.episodes < 1 or not args.timeout > 0:
        return '--seed must be >= 0, --episodes >= 1 and --timeout > 0'
    params = args.params_file or default_params_file()
    if not params.is_file():
        return f'no parameter file {params}'
    return None


def json_stdout():
    """The real stdout, for the summary alone: fd 1 goes to stderr from now on, so what C libraries
    print there (pybullet's banners, flushed at exit) cannot mix into the JSON."""
    sys.stdout.flush()
    real = os.fdopen(os.dup(1), 'w')
    os.dup2(2, 1)
    return real


def run(args) -> int:
    from hdp_sim_bridge.tasks import TASKS
    json_out = json_stdout() if args.json else None
    say_to = sys.stderr if args.json else sys.stdout

    def say(text: str) -> None:
        print(f'[demo] {text}', file=say_to, flush=True)

    problem = argument_problem(args, TASKS)
    try:
        domain, picked = pick_domain(os.environ, random.Random())
    except ValueError as err:
        problem = problem or str(err)
    if problem:
        print(f'hdp demo: {problem}', file=sys.stderr)
        return 2
    overrides = [f'sim_bridge_node:task:={args.task}', f'sim_bridge_node:seed:={args.seed}',
                 f'controller_node:method:={args.method}', f'controller_node:sampler:={args.sampler}']
    commands = node_commands(list(NODES), args.params_file or default_params_file(), overrides)
    logs = args.out / 'logs'
    logs.mkdir(parents=True, exist_ok=True)
    say(f'ROS_DOMAIN_ID={domain} ' + ('(picked at random; set ROS_DOMAIN_ID to choose)' if picked
                                       else '(from the environment)'))
    say(f'node output: {logs}/<node>.log')

    ros.init(args=[], domain_id=domain)
    stop: list[str] = []

    def on_signal(signum, frame):
        stop.append(signal.Signals(signum).name)     # the first ends the demo; later ones wait for the stop
    previous = {sig: signal.signal(sig, on_signal) for sig in (signal.SIGINT, signal.SIGTERM)}
    records, logs_by_episode, code = [], [], 1
    started = time.monotonic()
    node = DemoNode(lambda segment: say(segment_line(segment)))
    try:
        with contextlib.ExitStack() as files:
            def output(name):
                return files.enter_context(open(logs / f'{name}.log', 'w'))
            env = dict(os.environ, ROS_DOMAIN_ID=str(domain))
            with running_nodes(commands, output, say, env) as procs:
                code = _run(Session(node, procs, stop), args, procs, records, logs_by_episode, started, say)
    except Interrupted as why:
        say(f'{why}: stopped the nodes')
        code = 130
    except GraphDown as why:
        say(f'{why}; stopped the nodes (see {logs}/)')
        code = 1
    finally:
        for sig, handler in previous.items():       # the runtime's, which shutdown replaces in turn
            signal.signal(sig, handler)
        node.destroy_node()
        rclpy.try_shutdown()
    if records:
        _write_outputs(args, domain, picked, records, logs_by_episode, started, say, json_out)
    return code


def _run(session: Session, args, procs, records, logs_by_episode, started, say) -> int:
    """Wait for the graph, run the episodes; the exit code (2: the planner refused the instruction)."""
    node = session.node
    say('waiting for the nodes to load their models and connect ...')
    if not session.spin_until(lambda: not node.not_connected(), STARTUP_TIMEOUT_S):
        raise GraphDown(f'the graph did not connect within {STARTUP_TIMEOUT_S:.0f} s '
                        f'(missing: {", ".join(node.not_connected())})')
    say(f'graph up after {time.monotonic() - started:.1f} s')
    ticks = os.sysconf('SC_CLK_TCK')
    pids = {name: proc.pid for name, proc in procs.items()}

    def cpu_sample():
        return cpu_seconds(pids, read_stats(), ticks)
    for i in range(args.episodes):
        seed = args.seed + i
        if i:
            node.episode = None
            node.reset.publish(String(data=json.dumps({'task': args.task, 'seed': seed})))
        record, log = run_episode(session, seed, args.instruction, args.timeout, cpu_sample, say)
        records.append(record)
        logs_by_episode.append(log)
        if record['outcome'] == 'refused':
            say(f"planner_node refused the instruction: {record['reason']}")
            return 2
        if record['outcome'] == 'timeout':        # the planner may still be at it: a reset would mislead it
            say(f"seed {seed}: TIMEOUT ({record['reason']}); no further episodes")
            return 1
        verdict = 'succeeded' if record['success'] else f"FAILED ({record['outcome']}: {record['reason']})"
        when = f" in {record['success_s']:.1f} s" if record['success'] else ''
        say(f"seed {seed}: {verdict}{when}, {len(record['segments'])} segments")
    return 0 if all(r['success'] for r in records) else 1


def _write_outputs(args, domain, picked, records, logs_by_episode, started, say, json_out) -> None:
    """Each episode's GIF and plot (none for a refused instruction: nothing moved), summary.json,
    and the figures table when there were segments to measure."""
    figs = figures(records)
    for record, log in zip(records, logs_by_episode):
        if record['outcome'] != 'refused':
            title = (f"{record['task']} seed {record['seed']}: {record['instruction']!r} ({args.method}, "
                     f"{args.sampler}) -> {'success' if record['success'] else record['outcome']}")
            write_episode_files(log, record, args.out, title)
    summary = {'task': args.task, 'method': args.method, 'sampler': args.sampler, 'ros_domain_id': domain,
               'ros_domain_id_picked': picked, 'total_wall_s': round(time.monotonic() - started, 1),
               'figures': figs, 'episodes': records}
    (args.out / 'summary.json').write_text(json.dumps(summary, indent=1))
    if figs['observe_predict_s']['n']:
        say('figures:\n' + format_figures(figs))
    files = [f for r in records for f in (r.get('gif'), r.get('plot')) if f]
    say(f"wrote {', '.join(str(args.out / f) for f in [*files, 'summary.json'])}")
    if json_out is not None:
        print(json.dumps(summary, indent=1), file=json_out, flush=True)
