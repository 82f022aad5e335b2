"""The simulated robot behind sim_bridge_node, without ROS: testable on its own.

Holds one PandaWorld with a task scene, follows arm trajectories like
joint_trajectory_controller (trajectory_follower), takes gripper commands, and
turns the state into the messages a real Panda + two RealSense D415s publish.
"""

from __future__ import annotations

import json

import numpy as np

from hdp_motion import panda
from hdp_data import instructions
from hdp_msgs_py import conversions
from hdp_msgs_py.msg import Clock, Header, TFMessage, Time

from .cameras import CameraRig, default_cameras
from .collect import joint_state
from .experts import reachable_scene
from .robot_state import LinkTransforms
from .sensor_model import SensorSettings
from .tasks import TASKS
from .trajectory_follower import accept
from .world import TIME_STEP, PandaWorld


def parse_reset(text: str) -> dict:
    """A reset request, JSON: {"task": name, "seed": int, "variation": int (optional)}."""
    try:
        request = json.loads(text)
    except json.JSONDecodeError as err:
        raise ValueError(f'reset request is not JSON ({err.msg}): {text[:80]!r}') from None
    if not isinstance(request, dict) or set(request) - {'task', 'seed', 'variation'}:
        raise ValueError('reset request must be {"task": ..., "seed": ..., "variation": ...}')
    if request.get('task') not in TASKS:
        raise ValueError(f'unknown task {request.get("task")!r}; tasks: {", ".join(TASKS)}')
    for key in ('seed', 'variation'):
        if key in request and (type(request[key]) is not int or request[key] < 0):
            raise ValueError(f'{key} must be a non-negative integer')
    if 'variation' in request:
        check_variation(request['task'], request['variation'])
    return request


def check_variation(task: str, variation: int) -> None:
    """ValueError unless ``task`` has ``variation``: checked before a reset touches the scene."""
    count = len(instructions.TASKS[task].variations)
    if not 0 <= variation < count:
        raise ValueError(f'{task} has variations 0..{count - 1}, got {variation}')


def parse_cameras(text: str, known) -> tuple[str, ...]:
    """The cameras a /hdp/sim/cameras request keeps publishing: comma-separated names of ``known``,
    '' for none. Anything else is refused whole, so a typo never silences a camera by accident."""
    names = [name.strip() for name in text.split(',')] if text.strip() else []
    bad = [name for name in names if name not in known]
    if bad:
        raise ValueError(f'unknown camera(s) {bad} in {text[:80]!r}; cameras: {", ".join(known)} '
                         f'(comma-separated, "" for none)')
    return tuple(name for name in known if name in names)


def gripper_target(msg) -> bool:
    """Whether a gripper JointTrajectory (finger joints, m per finger) asks to open."""
    names, positions, _, _ = conversions.parse_joint_trajectory(msg)
    if sorted(names) != sorted(panda.FINGER_JOINTS):
        raise ValueError(f'gripper trajectory must name {list(panda.FINGER_JOINTS)}, got {names}')
    target = positions[-1]
    if np.any(target < -1e-6) or np.any(target > panda.FINGER_MAX + 1e-6):
        raise ValueError(f'finger positions must be within [0, {panda.FINGER_MAX}] m, got {target.tolist()}')
    return bool(np.mean(target) >= panda.FINGER_MAX / 2)


class SimBridge:
    """world: a PandaWorld to use (and leave open on close()), as an evaluation keeps one
    between episodes; None makes one of its own. sensor: how the cameras differ from ideal ones
    (sensor model, calibration error, latency); ideal by default."""

    def __init__(self, width: int = 640, height: int = 480, world: PandaWorld | None = None,
                 sensor: SensorSettings = SensorSettings()):
        self._owns_world = world is None
        self.world = world if world is not None else PandaWorld()
        self.cameras = default_cameras(width, height)      # as calibrated: CameraInfo and /tf_static
        self.sensor = sensor
        self.rig = CameraRig(self.cameras, sensor)
        self._in_flight: list[tuple[float, str, tuple]] = []    # (due s, camera, its messages), exposed
        self.publishing = tuple(self.cameras)     # cameras whose frames go out; /hdp/sim/cameras stops some
        self.task = None
        self.episode: dict = {}
        self.trajectory = None
        self._link_transforms = None

    def reset(self, task_name: str, seed: int, variation: int | None = None) -> dict:
        """A new episode; returns {task, seed, variation, instruction}. A ValueError leaves the
        running episode as it was."""
        if task_name not in TASKS:
            raise ValueError(f'unknown task {task_name!r}; tasks: {", ".join(TASKS)}')
        if variation is not None:
            check_variation(task_name, variation)
        task, rng, variation = reachable_scene(self.world, task_name, seed, variation)
        self.task, self.trajectory = task, None
        self.rig.start_episode(seed)
        self._in_flight.clear()          # the last episode's frames never arrive in this one
        self.episode = {'task': task_name, 'seed': seed, 'variation': variation,
                        'instruction': task.instruction(rng)}
        return self.episode

    def select_cameras(self, text: str) -> tuple[str, ...]:
        """Keep only the cameras named in ``text`` publishing (parse_cameras); the others go silent."""
        self.publishing = parse_cameras(text, tuple(self.cameras))
        return self.publishing

    @property
    def sim_time(self) -> float:
        return self.world.sim_time

    def check_arm(self, msg) -> None:
        """ValueError if ``msg`` would be refused by command_arm; nothing changes either way."""
        accept(msg, self.sim_time, self.world.joint_positions())

    def command_arm(self, msg) -> None:
        """Accept a JointTrajectory (replacing the running one) or raise ValueError; nothing moves on error."""
        self.trajectory = accept(msg, self.sim_time, self.world.joint_positions())

    def command_gripper(self, msg) -> None:
        self.world.command_gripper(gripper_target(msg))

    def step(self) -> None:
        if self.trajectory is not None:
            self.world.command_arm(self.trajectory.sample(self.sim_time + TIME_STEP))
        self.world.step()
        if self.task is not None:
            self.task.on_step(self.world)

    def arm_goal_state(self, active, goal_tolerance: np.ndarray, goal_time_tolerance: float) -> str:
        """How a FollowJointTrajectory goal executing ``active`` stands, as joint_trajectory_controller
        judges it: 'running' until its end time, then 'succeeded' once every joint is within
        ``goal_tolerance`` (7,) rad of the last point, 'violated' if not by ``goal_time_tolerance``
        s after the end, and 'preempted' when another trajectory replaced it."""
        if self.trajectory is not active:
            return 'preempted'
        late = self.sim_time - active.end_time
        if late < 0:
            return 'running'
        if np.all(np.abs(self.world.joint_positions() - active.positions[-1]) <= goal_tolerance):
            return 'succeeded'
        return 'violated' if late > goal_time_tolerance else 'running'

    def hold(self) -> None:
        """Stop where the arm is (a cancelled goal)."""
        self.trajectory = None
        self.world.command_arm(self.world.joint_positions())

    @property
    def trajectory_done(self) -> bool:
        return self.trajectory is None or self.sim_time >= self.trajectory.end_time

    def success(self) -> bool:
        return bool(self.task is not None and self.task.success(self.world))

    # -- messages ------------------------------------------------------------------------
    def clock(self) -> Clock:
        return Clock(clock=conversions.seconds_to_time(self.sim_time))

    def joint_state(self):
        return joint_state(self.world, self.sim_time)

    def tf_static(self) -> TFMessage:
        """The cameras' extrinsics (world -> optical frame), as a real setup's calibration gives them."""
        return TFMessage(transforms=[c.transform_stamped() for c in self.cameras.values()])

    def robot_tf_static(self) -> TFMessage:
        """world -> panda_link0 and the arm's fixed joints, as robot_state_publisher latches them."""
        return TFMessage(transforms=self._links().static(Time()))

    def robot_tf(self) -> TFMessage:
        """The arm's and fingers' movable joints now, as robot_state_publisher sends them on /tf."""
        return TFMessage(transforms=self._links().moving(conversions.seconds_to_time(self.sim_time)))

    def _links(self) -> LinkTransforms:
        if self._link_transforms is None or self._link_transforms.robot != self.world.robot:
            self._link_transforms = LinkTransforms(self.world.client_id, self.world.robot)
        return self._link_transforms

    def camera_messages(self, name: str):
        """(colour rgb8 Image, depth 16UC1 Image, CameraInfo) of one camera exposed now, stamped now."""
        camera = self.cameras[name]
        rgb, depth = self.rig.render(self.world.client, name, round(self.sim_time / TIME_STEP))
        stamp = conversions.seconds_to_time(self.sim_time)
        header = Header(stamp=stamp, frame_id=camera.frame_id)
        return (conversions.numpy_to_image(rgb, 'rgb8', header),
                conversions.numpy_to_image(depth, '16UC1', header), camera.camera_info(stamp))

    def expose(self) -> None:
        """Every publishing camera takes a frame now, stamped now; it is delivered (``delivered``)
        the sensor's latency later, at the first physics step at or after that."""
        due = self.sim_time + self.sensor.latency_ms * 1e-3
        self._in_flight += [(due, name, self.camera_messages(name)) for name in self.publishing]

    def delivered(self) -> list[tuple[str, tuple]]:
        """The exposed frames due by now, oldest first, each once: [(camera, (colour, depth, CameraInfo))]."""
        now = self.sim_time + 1e-9
        due = [(name, messages) for at, name, messages in self._in_flight if at <= now]
        if due:
            self._in_flight = [frame for frame in self._in_flight if frame[0] > now]
        return due

    def close(self) -> None:
        if self._owns_world:
            self.world.close()
