"""The eleven tasks of the paper's Table 1, built procedurally in PyBullet.

A task places its objects at a random pose in front of the robot, gives an
instruction in one of several phrasings, checks success the way RLBench does,
and lists the expert's waypoints from the objects' current state. Waypoints
that follow a hinge are a chain of poses the arm moves through without
stopping (an arc), so keyframes fall only where the expert rests.

Object frames: +x points from the object towards the robot, z up.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from hdp_motion.rotations import quat_to_matrix
from hdp_data import instructions
from hdp_msgs_py.conversions import matrix_to_quat

from . import objects
from .world import TABLE_TOP_Z

_DOWN = np.array([0.0, 0.0, -1.0])


@dataclasses.dataclass
class Waypoint:
    """Where the expert goes next, then what the gripper does there.

    ``poses``: one (xyz, quat_xyzw) to reach, or several to pass through in
    order without stopping (``path='via'``). ``path='linear'`` demands a
    straight line; ``'any'`` allows a planner when a straight line fails.
    """
    poses: list
    gripper: str | None = None          # 'open' | 'close' | None, after arriving
    path: str = 'any'                   # 'any' | 'linear' | 'via'


def grasp_quat(approach, closing, flip: bool = False) -> np.ndarray:
    """Gripper orientation (x, y, z, w): hand z along ``approach``, fingers close along
    ``closing`` (or its opposite when ``flip``: the same grasp, the wrist turned 180 deg)."""
    z = np.asarray(approach, float) / np.linalg.norm(approach)
    closing = -np.asarray(closing, float) if flip else np.asarray(closing, float)
    y = closing - np.dot(closing, z) * z
    y /= np.linalg.norm(y)
    return matrix_to_quat(np.column_stack([np.cross(y, z), y, z]))


def rotate_about(pose, pivot, axis, angle: float):
    """A pose carried rigidly around the line through ``pivot`` along ``axis``."""
    xyz, quat = pose
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    rot = np.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * k @ k
    new_xyz = pivot + rot @ (np.asarray(xyz) - pivot)
    return new_xyz, matrix_to_quat(rot @ quat_to_matrix(quat))


def arc(pose, pivot, axis, angle: float, step: float = math.radians(7.5), hand_turn: float = 1.0) -> list:
    """Poses along a rotation about a hinge, excluding the start, ending at ``angle``.

    The hand turns by ``hand_turn`` times the hinge angle: 1 carries it rigidly
    (a grasp), less lets a pushing hand pitch only part of the way.
    """
    n = max(2, math.ceil(abs(angle) / step))
    poses = []
    for k in range(1, n + 1):
        xyz, _ = rotate_about(pose, pivot, axis, angle * k / n)
        _, quat = rotate_about(pose, pivot, axis, hand_turn * angle * k / n)
        poses.append((xyz, quat))
    return poses


class Task:
    name = ''
    variations: tuple = ('',)
    phrasings: tuple = ()
    yaw_range = math.radians(20)    # random yaw around "facing the robot"
    distance = (0.55, 0.65)         # object distance in front of the robot base (m)
    lateral = 0.12                  # +- y (m)

    # Bodies the expert deliberately touches (grasp targets): straight-line moves
    # into contact ignore them.
    touched_roles: tuple = ()

    def __init__(self):
        self.bodies: dict[str, int] = {}
        self.variation = 0
        self.base_pose = None

    # -- building ----------------------------------------------------------------------
    def reset(self, world, rng: np.random.Generator, variation: int) -> None:
        if not 0 <= variation < len(self.variations):
            raise ValueError(f'{self.name} has variations 0..{len(self.variations) - 1}, got {variation}')
        self.variation, self.bodies = variation, {}
        base_xyz, _ = world.client.getBasePositionAndOrientation(world.robot)
        x = base_xyz[0] + rng.uniform(*self.distance)
        y = base_xyz[1] + rng.uniform(-self.lateral, self.lateral)
        yaw = math.pi + rng.uniform(-self.yaw_range, self.yaw_range)
        self.base_pose = (np.array([x, y, TABLE_TOP_Z]), yaw)
        self.build(world, rng)

    def build(self, world, rng) -> None:
        raise NotImplementedError

    def instruction(self, rng: np.random.Generator, phrasings=None) -> str:
        return instructions.instruction(self.name, self.variation, phrasings or self.phrasings, rng)

    def success(self, world) -> bool:
        raise NotImplementedError

    def waypoints(self, world, flip: bool = False) -> list[Waypoint]:
        """The expert's waypoints; ``flip`` turns every grasp 180 deg about its approach
        axis (the same grasp for a parallel gripper, another wrist angle)."""
        raise NotImplementedError

    def on_step(self, world) -> None:
        """Called after every physics step (the door uses it for its lock)."""

    @property
    def touched(self) -> set[int]:
        return {self.bodies[r] for r in self.touched_roles if r in self.bodies}

    # -- helpers -------------------------------------------------------------------------
    def frame(self):
        """Object axes in the world: (origin, x_axis, y_axis)."""
        origin, yaw = self.base_pose
        return origin, np.array([math.cos(yaw), math.sin(yaw), 0.0]), np.array([-math.sin(yaw), math.cos(yaw), 0.0])

    def load(self, world, name: str, urdf: str, xyz=None, yaw=None, fixed=True) -> int:
        origin, base_yaw = self.base_pose
        body = world.client.loadURDF(objects.urdf_file(urdf), list(origin if xyz is None else xyz),
                                     world.client.getQuaternionFromEuler([0, 0, base_yaw if yaw is None else yaw]),
                                     useFixedBase=fixed)
        for j in range(world.client.getNumJoints(body)):     # free joints: no locking motor
            world.client.setJointMotorControl2(body, j, world.client.VELOCITY_CONTROL, force=0.2)
        world.add_task_body(body)
        self.bodies[name] = body
        return body

    def joint(self, world, body: str, joint_name: str) -> int:
        client, body_id = world.client, self.bodies[body]
        for j in range(client.getNumJoints(body_id)):
            if client.getJointInfo(body_id, j)[1].decode() == joint_name:
                return j
        raise KeyError(joint_name)

    def joint_position(self, world, body: str, joint_name: str) -> float:
        return world.client.getJointState(self.bodies[body], self.joint(world, body, joint_name))[0]

    def link_pose(self, world, body: str, joint_name: str):
        """World pose of the child link of ``joint_name`` (its URDF frame)."""
        state = world.client.getLinkState(self.bodies[body], self.joint(world, body, joint_name),
                                          computeForwardKinematics=True)
        return np.array(state[4]), np.array(state[5])


class ReachTarget(Task):
    name = 'reach_target'
    variations = instructions.TASKS[name].variations
    phrasings = instructions.TASKS[name].phrasings
    radius = 0.03

    def build(self, world, rng):
        client = world.client
        names = [self.variations[self.variation]]
        others = [c for c in self.variations if c != names[0]]
        names += list(rng.choice(others, size=2, replace=False))     # 2 distractors
        origin, _ = self.base_pose
        centres = []
        while len(centres) < 3:
            c = origin + np.array([rng.uniform(-0.2, 0.0), rng.uniform(-0.15, 0.15), rng.uniform(0.08, 0.35)])
            if all(np.linalg.norm(c - o) > 0.12 for o in centres):
                centres.append(c)
        for role, colour, centre in zip(('target', 'distractor0', 'distractor1'), names, centres):
            visual = client.createVisualShape(client.GEOM_SPHERE, radius=self.radius,
                                              rgbaColor=[*objects.COLOURS[colour], 1])
            body = client.createMultiBody(0, -1, visual, list(centre))   # no collision, as in RLBench
            world.add_task_body(body)
            self.bodies[role] = body

    def target(self, world) -> np.ndarray:
        return np.array(world.client.getBasePositionAndOrientation(self.bodies['target'])[0])

    def success(self, world):
        return bool(np.linalg.norm(world.ee_pose()[0] - self.target(world)) < self.radius)

    def waypoints(self, world, flip=False):
        _, x_axis, _ = self.frame()
        return [Waypoint([(self.target(world), grasp_quat(_DOWN, np.cross(x_axis, _DOWN), flip))])]


class PickUpCup(Task):
    touched_roles = ('cup',)
    name = 'pick_up_cup'
    variations = instructions.TASKS[name].variations
    phrasings = instructions.TASKS[name].phrasings
    size = (0.028, 0.10)     # radius, height: narrower than the 8 cm gripper opening

    def build(self, world, rng):
        client = world.client
        colours = [self.variations[self.variation],
                   rng.choice([c for c in self.variations if c != self.variations[self.variation]])]
        origin, _ = self.base_pose
        spots = [origin + np.array([rng.uniform(-0.15, -0.05), rng.uniform(-0.12, 0.12), 0.0])]
        while len(spots) < 2:
            s = origin + np.array([rng.uniform(-0.15, -0.05), rng.uniform(-0.18, 0.18), 0.0])
            if np.linalg.norm(s[:2] - spots[0][:2]) > 0.12:
                spots.append(s)
        for role, colour, spot in zip(('cup', 'distractor'), colours, spots):
            shape = client.createCollisionShape(client.GEOM_CYLINDER, radius=self.size[0], height=self.size[1])
            visual = client.createVisualShape(client.GEOM_CYLINDER, radius=self.size[0], length=self.size[1],
                                              rgbaColor=[*objects.COLOURS[colour], 1])
            body = client.createMultiBody(0.15, shape, visual, list(spot + [0, 0, self.size[1] / 2]))
            client.changeDynamics(body, -1, lateralFriction=1.0)
            world.add_task_body(body)
            self.bodies[role] = body
        self.start_z = spots[0][2] + self.size[1] / 2

    def success(self, world):
        z = world.client.getBasePositionAndOrientation(self.bodies['cup'])[0][2]
        return world.grasped_body() == self.bodies['cup'] and z > self.start_z + 0.05

    def waypoints(self, world, flip=False):
        xyz = np.array(world.client.getBasePositionAndOrientation(self.bodies['cup'])[0])
        _, x_axis, y_axis = self.frame()
        quat = grasp_quat(_DOWN, y_axis, flip)
        grasp = xyz + np.array([0, 0, 0.015])
        return [Waypoint([(grasp + [0, 0, 0.12], quat)]),
                Waypoint([(grasp, quat)], 'close', 'linear'),
                Waypoint([(grasp + [0, 0, 0.15], quat)], None, 'linear')]


class OpenDrawer(Task):
    touched_roles = ('cabinet',)
    name = 'open_drawer'
    variations = instructions.TASKS[name].variations
    phrasings = instructions.TASKS[name].phrasings
    distance = (0.80, 0.88)

    def build(self, world, rng):
        self.load(world, 'cabinet', objects.cabinet())

    def _joint(self):
        return f'drawer_{self.variations[self.variation]}'

    def success(self, world):
        return self.joint_position(world, 'cabinet', self._joint()) > 0.15

    def waypoints(self, world, flip=False):
        _, x_axis, _ = self.frame()
        link_xyz, _ = self.link_pose(world, 'cabinet', self._joint())
        handle = link_xyz + objects.drawer_handle_offset() * x_axis
        quat = grasp_quat(-x_axis, [0, 0, 1], flip)       # horizontal approach, fingers close vertically
        return [Waypoint([(handle + 0.10 * x_axis, quat)]),
                Waypoint([(handle, quat)], 'close', 'linear'),
                Waypoint([(handle + 0.20 * x_axis, quat)], None, 'linear')]


class _HingedLid(Task):
    """Lift something hinged at its back by pushing under its front edge.

    The closed hand slides under the protruding edge and lifts it along the
    hinge's arc past vertical, where gravity takes over. The hand pitches down
    by half the hinge angle on the way, which keeps the wrist off its limits.
    """
    body_name = joint_name = ''
    open_angle = 0.0      # how far the expert swings it (rad)
    push_x = 0.0          # x of the push point under the edge, in the hinged link's frame
    pitch = 0.6           # downward tilt of the pushing hand (tan of the angle)

    def hinge(self, world):
        pivot, _ = self.link_pose(world, self.body_name, self.joint_name)
        _, _, y_axis = self.frame()
        return pivot, -y_axis          # URDF axis (0, -1, 0): positive angle lifts the front

    def waypoints(self, world, flip=False):
        _, x_axis, _ = self.frame()
        pivot, axis = self.hinge(world)
        link_xyz, link_quat = self.link_pose(world, self.body_name, self.joint_name)
        under = link_xyz + quat_to_matrix(link_quat) @ np.array([self.push_x, 0, -0.012])
        # Pitched down (a level hand this low is at the wrist's limit), fingers side by
        # side so the hand's 20 cm span stays horizontal, clear of the table.
        approach = -x_axis + self.pitch * _DOWN
        quat = grasp_quat(approach, np.cross([0, 0, 1], x_axis), flip)
        swing = self.open_angle - self.joint_position(world, self.body_name, self.joint_name)
        return [Waypoint([(under + 0.07 * x_axis, quat)], 'close'),     # in front of the edge, below it
                Waypoint([(under, quat)], None, 'linear'),
                Waypoint(arc((under, quat), pivot, axis, swing, hand_turn=0.5), None, 'via')]


class OpenBox(_HingedLid):
    touched_roles = ('box',)
    name = 'open_box'
    phrasings = instructions.TASKS[name].phrasings
    body_name, joint_name = 'box', 'lid'
    open_angle = math.radians(100)    # past vertical: gravity opens it the rest of the way
    distance = (0.58, 0.66)

    push_x = 0.175         # under the lip, 1.5 cm in front of the box's front wall

    def build(self, world, rng):
        self.load(world, 'box', objects.hinged_box())

    def success(self, world):
        return self.joint_position(world, 'box', 'lid') > math.pi / 2


class ToiletSeatUp(_HingedLid):
    touched_roles = ('toilet',)
    name = 'toilet_seat_up'
    phrasings = instructions.TASKS[name].phrasings
    body_name, joint_name = 'toilet', 'seat'
    open_angle = math.radians(96)     # past vertical: it falls back against the cistern
    distance = (0.56, 0.64)

    push_x = 0.23          # under the seat's front, which overhangs the bowl

    def build(self, world, rng):
        self.load(world, 'toilet', objects.toilet())

    def success(self, world):
        return self.joint_position(world, 'toilet', 'seat') > 1.40


class OpenDoor(Task):
    touched_roles = ('door',)
    name = 'open_door'
    phrasings = instructions.TASKS[name].phrasings
    distance = (0.66, 0.72)
    yaw_range = math.radians(15)
    unlock_angle = math.radians(25)

    def build(self, world, rng):
        self.load(world, 'door', objects.door())

    def on_step(self, world):
        # The door is locked until the handle has turned far enough, as in RLBench.
        locked = self.joint_position(world, 'door', 'handle') < self.unlock_angle
        world.client.setJointMotorControl2(self.bodies['door'], self.joint(world, 'door', 'door'),
                                           world.client.VELOCITY_CONTROL, targetVelocity=0,
                                           force=500.0 if locked else 0.2)

    def success(self, world):
        return self.joint_position(world, 'door', 'door') > math.radians(25)

    def waypoints(self, world, flip=False):
        _, x_axis, y_axis = self.frame()
        handle_xyz, handle_quat = self.link_pose(world, 'door', 'handle')
        lever = quat_to_matrix(handle_quat)
        grip = handle_xyz + lever @ np.array([0.07, 0.07, 0.0])     # on the lever bar, near its tip
        # Pitched 45 deg down, fingers either side of the bar: a posture the Panda
        # holds low over the table with room left in every joint for the turn.
        approach = -x_axis + _DOWN
        grasp = (grip, grasp_quat(approach, np.cross(approach, y_axis), flip))
        turn = arc(grasp, handle_xyz, -lever[:, 0], math.radians(40))
        hinge_xyz, _ = self.link_pose(world, 'door', 'door')
        pull = arc(turn[-1], hinge_xyz, [0, 0, 1], math.radians(40))
        return [Waypoint([(grip - 0.10 * approach / np.linalg.norm(approach), grasp[1])]),
                Waypoint([grasp], 'close', 'linear'),
                Waypoint(turn, None, 'via'),
                Waypoint(pull, 'open', 'via')]


class TakeLidOffSaucepan(Task):
    touched_roles = ('lid',)
    name = 'take_lid_off_saucepan'
    phrasings = instructions.TASKS[name].phrasings
    lift = 0.08           # the lid this far above the pan, held, is off (RLBench: a sensor above the pan)

    def build(self, world, rng):
        origin, _ = self.base_pose
        self.load(world, 'pan', objects.saucepan())
        self.load(world, 'lid', objects.saucepan_lid(), xyz=origin + [0, 0, objects.PAN_HEIGHT], fixed=False)
        self.start_z = origin[2] + objects.PAN_HEIGHT

    def _lid(self, world):
        xyz, quat = world.client.getBasePositionAndOrientation(self.bodies['lid'])
        return np.array(xyz), np.array(quat)

    def success(self, world):
        return world.grasped_body() == self.bodies['lid'] and self._lid(world)[0][2] > self.start_z + self.lift

    def waypoints(self, world, flip=False):
        lid_xyz, lid_quat = self._lid(world)
        _, _, y_axis = self.frame()
        knob = lid_xyz + quat_to_matrix(lid_quat) @ [0, 0, 0.012 + 0.6 * objects.LID_KNOB[1]]
        quat = grasp_quat(_DOWN, y_axis, flip)
        return [Waypoint([(knob + [0, 0, 0.10], quat)]),
                Waypoint([(knob, quat)], 'close', 'linear'),
                Waypoint([(knob + [0, 0, 0.15], quat)], None, 'linear')]


class _GraspedHinge(Task):
    """Grasp a handle on a hinged part and carry it round the hinge (the grasp is rigid)."""
    body_name = joint_name = ''
    make_urdf = staticmethod(lambda: '')
    swing = 0.0           # how far the expert carries it (rad)
    open_above = 0.0      # the hinge angle past which it counts as open (RLBench's)

    def build(self, world, rng):
        self.load(world, self.body_name, self.make_urdf())

    def success(self, world):
        return self.joint_position(world, self.body_name, self.joint_name) > self.open_above

    def handle(self, world):
        """(grasp point, approach direction, closing direction) in the world."""
        raise NotImplementedError

    def hinge_axis(self, world):
        """The joint's axis in the world (positive: opening)."""
        raise NotImplementedError

    def waypoints(self, world, flip=False):
        point, approach, closing = self.handle(world)
        grasp = (point, grasp_quat(approach, closing, flip))
        pivot, _ = self.link_pose(world, self.body_name, self.joint_name)
        swing = self.swing - self.joint_position(world, self.body_name, self.joint_name)
        return [Waypoint([(point - 0.10 * approach, grasp[1])]),
                Waypoint([grasp], 'close', 'linear'),
                Waypoint(arc(grasp, pivot, self.hinge_axis(world), swing), None, 'via')]


class OpenGrill(_GraspedHinge):
    touched_roles = ('grill',)
    name = 'open_grill'
    phrasings = instructions.TASKS[name].phrasings
    body_name, joint_name, make_urdf = 'grill', 'lid', staticmethod(objects.grill)
    swing, open_above = math.radians(65), math.radians(50)
    distance = (0.62, 0.70)

    def handle(self, world):
        _, x_axis, y_axis = self.frame()
        link_xyz, link_quat = self.link_pose(world, 'grill', 'lid')
        bar = link_xyz + quat_to_matrix(link_quat) @ [objects.GRILL_DEPTH + objects.GRILL_HANDLE[1], 0, 0.02]
        approach = -x_axis + 0.5 * _DOWN        # pitched down, level by the end of the lift
        return bar, approach / np.linalg.norm(approach), np.cross(approach, y_axis)

    def hinge_axis(self, world):
        return -self.frame()[2]


class OpenMicrowave(_GraspedHinge):
    touched_roles = ('microwave',)
    name = 'open_microwave'
    phrasings = instructions.TASKS[name].phrasings
    body_name, joint_name, make_urdf = 'microwave', 'door', staticmethod(objects.microwave)
    swing, open_above = math.radians(95), math.radians(80)
    distance = (0.74, 0.82)
    yaw_range = math.pi / 8

    def handle(self, world):
        _, x_axis, _ = self.frame()
        link_xyz, link_quat = self.link_pose(world, 'microwave', 'door')
        bar = link_xyz + quat_to_matrix(link_quat) @ [0.02 + objects.MICROWAVE_HANDLE[1],
                                                        objects.MICROWAVE_DOOR_WIDTH - 0.04, 0]
        return bar, -x_axis, np.cross([0, 0, 1], x_axis)

    def hinge_axis(self, world):
        return np.array([0.0, 0.0, -1.0])


class OpenOven(Task):
    """Pull the door down by its handle, let go, and push it down the rest of the way from above."""
    touched_roles = ('oven',)
    name = 'open_oven'
    phrasings = instructions.TASKS[name].phrasings
    distance = (0.84, 0.90)
    yaw_range = math.pi / 8
    pull = math.radians(45)
    open_angle = math.radians(85)
    stiffness = 1.5       # Nm of hinge friction: the door stays where it is left, as a sprung oven door

    def build(self, world, rng):
        self.load(world, 'oven', objects.oven())
        world.client.setJointMotorControl2(self.bodies['oven'], self.joint(world, 'oven', 'door'),
                                           world.client.VELOCITY_CONTROL, force=self.stiffness)

    def success(self, world):
        return (self.joint_position(world, 'oven', 'door') > math.radians(70)
                and world.grasped_body() is None)

    def waypoints(self, world, flip=False):
        _, x_axis, y_axis = self.frame()
        hinge, hinge_quat = self.link_pose(world, 'oven', 'door')
        door = quat_to_matrix(hinge_quat)
        bar = hinge + door @ [0.02 + objects.OVEN_HANDLE[1], 0, objects.OVEN_DOOR_HEIGHT - 0.03]
        # A hand pitched down on the bar, fingers either side of it; pulled, it turns up with
        # the door (whose outside comes to face the floor) to about level.
        approach = -door[:, 0] + 0.7 * _DOWN
        approach /= np.linalg.norm(approach)
        grasp = (bar, grasp_quat(approach, np.cross(approach, y_axis), flip))
        pull = self.pull - self.joint_position(world, 'oven', 'door')
        pulled = arc(grasp, hinge, y_axis, pull)
        # Let go, then the closed hand pointing down onto the door's inside near its top,
        # pressing it the rest of the way along the hinge's arc.
        top = rotate_about((hinge + door @ [0.0, 0, objects.OVEN_DOOR_HEIGHT - 0.04], grasp[1]),
                           hinge, y_axis, pull)[0]
        press = (top + [0, 0, 0.02], grasp_quat(_DOWN, x_axis, flip))
        let_go = pulled[-1][0] - 0.08 * (quat_to_matrix(pulled[-1][1])[:, 2]), pulled[-1][1]
        return [Waypoint([(bar - 0.10 * approach, grasp[1])]),
                Waypoint([grasp], 'close', 'linear'),
                Waypoint(pulled, 'open', 'via'),
                Waypoint([let_go], None, 'linear'),
                Waypoint([(press[0] + [0, 0, 0.10], press[1])], 'close'),
                Waypoint([press], None, 'linear'),
                Waypoint(arc(press, hinge, y_axis, self.open_angle - self.pull, hand_turn=0.0), None, 'via')]


class PutKnifeOnChoppingBoard(Task):
    touched_roles = ('knife', 'board')
    name = 'put_knife_on_chopping_board'
    phrasings = instructions.TASKS[name].phrasings
    distance = (0.50, 0.58)
    lateral = 0.08
    board_y = -0.16       # the board's centre beside the block, in the task frame

    def build(self, world, rng):
        origin, _, y_axis = self.frame()
        block = origin + 0.08 * y_axis
        self.load(world, 'block', objects.knife_block(), xyz=block)
        self.load(world, 'board', objects.chopping_board(), xyz=origin + self.board_y * y_axis)
        _, yaw = self.base_pose
        handle_z = objects.KNIFE_BLOCK_HEIGHT + objects.KNIFE_HANDLE[2] / 2 + 0.001
        self.load(world, 'knife', objects.knife(), xyz=block - 0.03 * y_axis + [0, 0, handle_z], yaw=yaw,
                  fixed=False)
        world.client.changeDynamics(self.bodies['knife'], -1, lateralFriction=1.0)

    def _on_board(self, world) -> bool:
        origin, x_axis, y_axis = self.frame()
        knife = np.array(world.client.getBasePositionAndOrientation(self.bodies['knife'])[0])
        local = knife - (origin + self.board_y * y_axis)
        half_x, half_y, thickness = np.array(objects.CHOPPING_BOARD) / 2 * [1, 1, 2]
        return bool(abs(local @ x_axis) < half_x and abs(local @ y_axis) < half_y
                    and local[2] < thickness + objects.KNIFE_HANDLE[2])

    def success(self, world):
        return world.grasped_body() is None and self._on_board(world)

    def waypoints(self, world, flip=False):
        origin, _, y_axis = self.frame()
        knife_xyz, knife_quat = world.client.getBasePositionAndOrientation(self.bodies['knife'])
        handle = np.array(knife_xyz) + [0, 0, 0.006]
        across = quat_to_matrix(knife_quat)[:, 0]           # fingers close across the handle
        quat = grasp_quat(_DOWN, across, flip)
        board = origin + self.board_y * y_axis
        place = np.array([board[0], board[1], handle[2]]) - [0, 0, objects.KNIFE_BLOCK_HEIGHT
                                                            - objects.CHOPPING_BOARD[2] - 0.008]
        place -= 0.08 * y_axis                               # the knife's middle over the board's
        return [Waypoint([(handle + [0, 0, 0.10], quat)]),
                Waypoint([(handle, quat)], 'close', 'linear'),
                Waypoint([(handle + [0, 0, 0.10], quat)], None, 'linear'),
                Waypoint([(place + [0, 0, 0.08], quat)]),
                Waypoint([(place, quat)], 'open', 'linear')]


TASKS = {cls.name: cls for cls in (ReachTarget, PickUpCup, OpenDrawer, OpenBox, ToiletSeatUp, OpenDoor,
                                   TakeLidOffSaucepan, OpenGrill, OpenMicrowave, OpenOven,
                                   PutKnifeOnChoppingBoard)}


def make_task(name: str) -> Task:
    if name not in TASKS:
        raise ValueError(f'unknown task {name!r}; tasks: {", ".join(TASKS)}')
    return TASKS[name]()
