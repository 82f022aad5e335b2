"""The simulated workcell: a Franka Panda on a table, in one headless PyBullet client.

World frame: z up, origin on the floor under the robot base; the robot sits
on the table's back edge at ``ROBOT_BASE`` facing +x, and tasks place their
objects in ``WORKSPACE`` in front of it. Physics runs at 240 Hz.

The world draws no random numbers: the same commands after ``reset(seed)``
give the same trajectory, and ``seed`` only seeds ``world.rng`` for the task
that randomises the scene. ``reset`` rebuilds the simulation from scratch,
so nothing (contact caches, body ids) carries over between episodes.

The arm is compliant, as under the Panda's joint impedance control: inverse
dynamics feeds forward gravity, Coriolis and the reference acceleration, and
a position servo adds at most SERVO_MIN_TORQUE + JOINT_STIFFNESS x |error|.
(The servo is a PyBullet motor with that force cap, which the solver treats
implicitly; an explicit stiff PD would be unstable at 240 Hz.) So a hand that
is held back pushes like a spring, not with the full 87 Nm.

Grasps are kinematic, as in RLBench: while the gripper closes, a task body
(or one link of it, say a drawer handle) that both fingers touch is welded
to the hand; opening releases it. The weld breaks if it carries more than
GRASP_FORCE_LIMIT for 0.1 s, which is how a trajectory that fights a hinge
loses its grip.
"""

from __future__ import annotations

import numpy as np
import pybullet
import pybullet_data
from pybullet_utils.bullet_client import BulletClient

from hdp_motion import panda
from hdp_motion.panda import ARM_JOINT_IDS, EE_LINK_ID, FINGER_JOINT_IDS, ROBOT_BASE
from hdp_data.workspace import TABLE_CENTER_XY, TABLE_HALF_EXTENTS, TABLE_TOP_Z, WORKSPACE  # noqa: F401

TIME_STEP = 1.0 / 240.0           # s
GRAVITY = -9.81                   # m/s^2


HAND_LINK = 8

ARM_FORCES = np.array([87.0, 87.0, 87.0, 87.0, 12.0, 12.0, 12.0])   # Nm, the Panda's limits
# rad/s^2: half the Franka datasheet maxima; at full maxima the 87 Nm of joint 2 saturate in
# stretched poses and the arm falls behind its reference by up to 50 mrad.
ACCELERATION_LIMITS = 0.5 * panda.ACCELERATION_LIMITS
# Nm/rad, half libfranka's joint impedance example. With the hand low over the table this is
# about 2 kN/m vertically and 0.5 kN/m sideways: a hand held 1 cm off its reference keeps its
# grasp, one held 2 cm below or ~6 cm aside of where the arm wants it loses it.
JOINT_STIFFNESS = 0.5 * np.array([600.0, 600.0, 600.0, 600.0, 250.0, 150.0, 50.0])
SERVO_MIN_TORQUE = np.array([2.0, 2.0, 2.0, 2.0, 1.0, 1.0, 1.0])   # Nm the servo may always use
POSITION_GAIN = 0.2               # PyBullet POSITION_CONTROL gain (its default is 0.1)
# rad: targets clamp this far inside panda.LOWER / UPPER, more than the servo's worst
# tracking error (~0.6 mrad), so the joints themselves stay inside.
LIMIT_MARGIN = 0.002

FINGER_FORCE = 20.0               # N per finger (the URDF's effort limit)
FINGER_SPEED = 0.1                # m/s per finger
FINGER_FRICTION = 1.0
GEAR_FORCE = 50.0                 # N, keeps the fingers mirrored

CLOSED_WIDTH = 0.002             # m: fingers this close have closed on nothing
GRASP_FORCE_LIMIT = 40.0          # N the weld may carry before the grasp counts as lost
# Consecutive steps over the limit that break it (0.1 s): a sustained fight, not the
# transient of an arm accelerating while it holds something.
GRASP_BREAK_STEPS = 24
# The weld itself may pull harder than the limit, so an overload is seen rather than
# the hand just slipping; the cap keeps a hinge fight from yanking the arm around.
GRASP_MAX_FORCE = 4 * GRASP_FORCE_LIMIT


class PandaWorld:
    """A Panda on a table in its own PyBullet DIRECT client; several can coexist.

    Tasks add bodies through ``world.client`` and register them with
    ``add_task_body``, which makes them graspable; reset removes them. Angles
    in rad, lengths in m, quaternions (x, y, z, w).
    """

    def __init__(self, seed: int = 0):
        self.client = BulletClient(connection_mode=pybullet.DIRECT)
        self.client.setAdditionalSearchPath(pybullet_data.getDataPath())
        self.reset(seed)

    # --- episode --------------------------------------------------------------------

    def reset(self, seed: int = 0) -> None:
        """Rebuild the scene: robot at HOME, gripper open, nothing grasped, no task bodies.

        ``self.rng`` becomes ``np.random.default_rng(seed)`` for the task's use.
        """
        c = self.client
        c.resetSimulation()
        c.setPhysicsEngineParameter(fixedTimeStep=TIME_STEP, deterministicOverlappingPairs=1)
        c.setGravity(0, 0, GRAVITY)
        self.plane = c.loadURDF('plane.urdf')
        self.table = self._make_table()
        # Not URDF_USE_INERTIA_FROM_FILE: the file's inertias are placeholders (0.1 kg m^2
        # everywhere); PyBullet's, from the collision shapes, are plausible.
        self.robot = c.loadURDF('franka_panda/panda.urdf', ROBOT_BASE, useFixedBase=True)
        self._setup_robot()
        self.rng = np.random.default_rng(seed)
        self.task_bodies: list[int] = []
        self.grasp_lost_count = 0       # grasps broken by overload since reset
        self._steps = 0
        self._grasp = None              # (body id, link index, constraint id) while holding
        self._grasp_armed = False       # the current close may still grasp
        self._overload_steps = 0
        self.reset_arm(panda.HOME)
        for joint in FINGER_JOINT_IDS:
            c.resetJointState(self.robot, joint, panda.FINGER_MAX, 0.0)
        self._set_fingers(panda.FINGER_MAX)
        self._gripper_open = True

    def _make_table(self) -> int:
        c = self.client
        half = TABLE_HALF_EXTENTS
        table = c.createMultiBody(
            baseMass=0.0,
            baseCollisionShapeIndex=c.createCollisionShape(pybullet.GEOM_BOX, halfExtents=half),
            baseVisualShapeIndex=c.createVisualShape(pybullet.GEOM_BOX, halfExtents=half,
                                                     rgbaColor=(0.72, 0.58, 0.42, 1.0)),
            basePosition=(*TABLE_CENTER_XY, TABLE_TOP_Z - half[2]))
        c.changeDynamics(table, -1, lateralFriction=1.0)
        return table

    def _setup_robot(self) -> None:
        c, robot = self.client, self.robot
        # The URDF's limits are a little wider than the real robot's: enforce the real ones.
        for joint, low, high in zip(ARM_JOINT_IDS, panda.LOWER, panda.UPPER):
            c.changeDynamics(robot, joint, jointLowerLimit=low, jointUpperLimit=high)
        for joint in FINGER_JOINT_IDS:
            c.changeDynamics(robot, joint, lateralFriction=FINGER_FRICTION)
        gear = c.createConstraint(robot, FINGER_JOINT_IDS[0], robot, FINGER_JOINT_IDS[1],
                                  jointType=pybullet.JOINT_GEAR, jointAxis=(1, 0, 0),
                                  parentFramePosition=(0, 0, 0), childFramePosition=(0, 0, 0))
        c.changeConstraint(gear, gearRatio=-1, erp=0.1, maxForce=GEAR_FORCE)

    @property
    def client_id(self) -> int:
        """The raw PyBullet client id, for functions that take one (motion planning)."""
        return self.client._client

    def add_task_body(self, body_id: int) -> int:
        """Register a task's body: it becomes graspable until reset. Returns ``body_id``."""
        self.task_bodies.append(body_id)
        return body_id

    @property
    def sim_time(self) -> float:
        """Seconds simulated since reset."""
        return self._steps * TIME_STEP

    def step(self, n: int = 1) -> None:
        """Advance ``n`` physics steps of TIME_STEP: arm reference, physics, grasp."""
        for _ in range(n):
            # PyBullet sets a joint's velocity, then moves it by velocity x dt: servo toward
            # where the reference starts this step, at the velocity it moves with in it.
            start = self._q_ref
            self._advance_reference()
            self._servo_arm(start)
            self.client.stepSimulation()
            self._steps += 1
            self._update_grasp()

    # --- arm ------------------------------------------------------------------------

    def reset_arm(self, q) -> None:
        """Teleport the arm to ``q`` (7,) at zero velocity and hold it there."""
        q = np.asarray(q, dtype=float)
        if q.shape != (7,) or not panda.within_limits(q):
            raise ValueError(f'reset_arm needs 7 joint positions within the Panda limits, got {q}')
        for joint, angle in zip(ARM_JOINT_IDS, q):
            self.client.resetJointState(self.robot, joint, angle, 0.0)
        self._q_ref, self._v_ref, self._a_ref = q.copy(), np.zeros(7), np.zeros(7)
        self.command_arm(q)
        self._last_goal = self._goal

    def command_arm(self, q_target, max_velocity=None) -> None:
        """Move the arm toward ``q_target`` (7,) rad; the target holds until the next command.

        The target is clamped to LIMIT_MARGIN inside the joint limits. No joint
        moves faster than its cap: ``max_velocity`` (scalar or (7,) rad/s) or
        panda.VELOCITY_LIMITS, whichever is lower. Each step a joint reference
        jumps onto the target if it can within that cap and ACCELERATION_LIMITS,
        else moves toward it with a trapezoidal profile; the compliant servo
        tracks the reference to within about 1 mrad in free motion. So a far
        target is reached at full speed, a trajectory streamed a target per
        step (within the limits) is followed without lag, and one the arm fell
        behind is caught up (the chase adds the streamed target's velocity).
        """
        self._goal = np.clip(np.asarray(q_target, dtype=float), panda.LOWER + LIMIT_MARGIN,
                             panda.UPPER - LIMIT_MARGIN)
        self._speed_cap = panda.VELOCITY_LIMITS if max_velocity is None else np.minimum(
            np.broadcast_to(np.asarray(max_velocity, dtype=float), (7,)), panda.VELOCITY_LIMITS)

    @property
    def arm_reference_settled(self) -> bool:
        """Whether the arm's reference has come to rest on the commanded target. The joints
        follow it there unless something blocks them (pushing against a hinge); a joint
        turning round is still for an instant, but its reference is not settled."""
        return bool(np.all(np.abs(self._goal - self._q_ref) < 1e-9) and np.all(self._v_ref == 0))

    def _advance_reference(self) -> None:
        error = self._goal - self._q_ref
        dv = ACCELERATION_LIMITS * TIME_STEP
        # The goal's own motion (zero for a fixed goal, else as streamed; a jump is not motion).
        v_goal = (self._goal - self._last_goal) / TIME_STEP
        v_goal = np.where(np.abs(v_goal) <= self._speed_cap, v_goal, 0.0)
        self._last_goal = self._goal
        # The goal's velocity plus the fastest closing velocity from which the joint can still
        # come to rest on it, slowing by dv a step: |error| = v^2 / (2 a) + v dt / 2. Without
        # the goal's velocity, a streamed trajectory was chased with a lag of v^2 / (2 a):
        # 0.12 rad at half speed, enough to sweep the fingers 1-2 cm off a straight descent.
        v_close = np.sqrt(2 * ACCELERATION_LIMITS * np.abs(error) + (dv / 2) ** 2) - dv / 2
        v_stop = np.clip(v_goal + np.sign(error) * v_close, -self._speed_cap, self._speed_cap)
        v_chase = self._v_ref + np.clip(v_stop - self._v_ref, -dv, dv)
        # Where the goal is one feasible step away, land on it exactly, if the next step can
        # then match the goal's own motion.
        v_onto = error / TIME_STEP
        onto = ((np.abs(v_onto) <= self._speed_cap) & (np.abs(v_onto - self._v_ref) <= dv)
                & (np.abs(v_onto - v_goal) <= dv))
        v_new = np.where(onto, v_onto, v_chase)
        self._a_ref = (v_new - self._v_ref) / TIME_STEP
        self._v_ref = v_new
        self._q_ref = np.where(onto, self._goal, self._q_ref + v_new * TIME_STEP)

    def _servo_arm(self, position: np.ndarray) -> None:
        """Inverse-dynamics torque, plus a force-capped servo toward ``position`` (7,)."""
        c = self.client
        states = c.getJointStates(self.robot, ARM_JOINT_IDS + FINGER_JOINT_IDS)
        q, v = [s[0] for s in states], [s[1] for s in states]
        feedforward = c.calculateInverseDynamics(self.robot, q, v, [*self._a_ref, 0.0, 0.0])[:7]
        feedforward = np.clip(feedforward, -ARM_FORCES, ARM_FORCES)
        servo_cap = np.minimum(SERVO_MIN_TORQUE + JOINT_STIFFNESS * np.abs(position - q[:7]),
                               ARM_FORCES - np.abs(feedforward))
        for joint in ARM_JOINT_IDS:
            # A TORQUE_CONTROL torque lasts one step and adds to the motor's force.
            c.setJointMotorControl2(self.robot, joint, pybullet.TORQUE_CONTROL,
                                    force=feedforward[joint])
            c.setJointMotorControl2(
                self.robot, joint, pybullet.POSITION_CONTROL, targetPosition=position[joint],
                targetVelocity=self._v_ref[joint], maxVelocity=self._speed_cap[joint],
                force=servo_cap[joint], positionGain=POSITION_GAIN, velocityGain=1.0)

    @property
    def gripper_commanded_open(self) -> bool:
        """The last gripper command (open or closed), not the measured width: fingers closed on a
        handle are not fully shut, and the keyframe rule (and so the training data) uses the command."""
        return bool(self._gripper_open)

    def joint_positions(self) -> np.ndarray:
        """Arm joint angles, (7,) rad."""
        return np.array([s[0] for s in self.client.getJointStates(self.robot, ARM_JOINT_IDS)])

    def joint_velocities(self) -> np.ndarray:
        """Arm joint velocities, (7,) rad/s."""
        return np.array([s[1] for s in self.client.getJointStates(self.robot, ARM_JOINT_IDS)])

    def ee_pose(self) -> tuple[np.ndarray, np.ndarray]:
        """World pose of panda_grasptarget: position (3,) m, quaternion (4,) x, y, z, w."""
        state = self.client.getLinkState(self.robot, EE_LINK_ID, computeForwardKinematics=True)
        return np.array(state[4]), np.array(state[5])

    # --- gripper and grasp ---------------------------------------------------------------

    def command_gripper(self, open: bool) -> None:
        """Open (width 0.08 m, releasing any grasp) or close the gripper.

        Repeating the current command changes nothing. Each close may grasp
        once: the first task body both fingers touch while closing is welded
        to the hand, and the fingers stop there.
        """
        open = bool(open)
        if open == self._gripper_open:
            return
        self._gripper_open = open
        self._grasp_armed = not open
        if open:
            self._release()
        self._set_fingers(panda.FINGER_MAX if open else 0.0)

    def _set_fingers(self, position: float) -> None:
        for joint in FINGER_JOINT_IDS:
            self.client.setJointMotorControl2(self.robot, joint, pybullet.POSITION_CONTROL,
                                              targetPosition=position, maxVelocity=FINGER_SPEED,
                                              force=FINGER_FORCE)

    def finger_positions(self) -> np.ndarray:
        """The two finger joints, (2,) m each."""
        return np.array([s[0] for s in self.client.getJointStates(self.robot, FINGER_JOINT_IDS)])

    def gripper_width(self) -> float:
        """Distance between the fingers, m (sum of the two finger joints)."""
        return float(self.finger_positions().sum())

    def grasped_body(self) -> int | None:
        """Id of the body welded to the hand, or None."""
        return None if self._grasp is None else self._grasp[0]

    def grasped_link(self) -> int | None:
        """Link of the grasped body that is welded to the hand (-1: its base), or None."""
        return None if self._grasp is None else self._grasp[1]

    def contacts_with_robot(self, body_id: int, link: int | None = None) -> list:
        """PyBullet contact points between ``body_id`` and the robot (or one robot link)."""
        if link is None:
            return self.client.getContactPoints(self.robot, body_id)
        return self.client.getContactPoints(self.robot, body_id, linkIndexA=link)

    def _update_grasp(self) -> None:
        if self._grasp is not None:
            self._check_overload()
        elif self._grasp_armed:
            pinched = self._pinched_link()
            if pinched is not None:
                self._attach(*pinched)
            elif self.gripper_width() < CLOSED_WIDTH:
                # Closed on nothing: a grasp happens while closing, as in RLBench, so a
                # closed hand can push things without welding itself to them.
                self._grasp_armed = False

    def _pinched_link(self) -> tuple[int, int] | None:
        """(body, link) of a task body that both fingers touch, or None."""
        contacts = [self.client.getContactPoints(self.robot, linkIndexA=finger)
                    for finger in FINGER_JOINT_IDS]
        touched = [{(c[2], c[4]) for c in points if c[2] in self.task_bodies}
                   for points in contacts]
        both = touched[0] & touched[1]
        return min(both) if both else None

    def _com_pose(self, body: int, link: int):
        """World pose of a link's centre of mass, the frame constraints are expressed in."""
        if link == -1:
            return self.client.getBasePositionAndOrientation(body)
        return self.client.getLinkState(body, link, computeForwardKinematics=True)[:2]

    def _attach(self, body: int, link: int) -> None:
        """Weld ``link`` of ``body`` to the hand at their current relative pose."""
        c = self.client
        inv_pos, inv_orn = c.invertTransform(*self._com_pose(self.robot, HAND_LINK))
        rel_pos, rel_orn = c.multiplyTransforms(inv_pos, inv_orn, *self._com_pose(body, link))
        constraint = c.createConstraint(self.robot, HAND_LINK, body, link, pybullet.JOINT_FIXED,
                                        jointAxis=(0, 0, 0), parentFramePosition=rel_pos,
                                        childFramePosition=(0, 0, 0),
                                        parentFrameOrientation=rel_orn)
        c.changeConstraint(constraint, maxForce=GRASP_MAX_FORCE)
        # Stop squeezing: the weld holds the body, and finger forces would only load the weld.
        self._set_fingers(float(np.mean(self.finger_positions())))
        self._grasp = (body, link, constraint)
        self._grasp_armed = False
        self._overload_steps = 0

    def _check_overload(self) -> None:
        force = np.linalg.norm(self.client.getConstraintState(self._grasp[2])[:3])
        self._overload_steps = self._overload_steps + 1 if force > GRASP_FORCE_LIMIT else 0
        if self._overload_steps >= GRASP_BREAK_STEPS:
            self._release()
            self.grasp_lost_count += 1
            self._set_fingers(0.0)      # still commanded closed: close on whatever is left

    def _release(self) -> None:
        if self._grasp is not None:
            self.client.removeConstraint(self._grasp[2])
            self._grasp = None

    # --- lifetime -------------------------------------------------------------------------

    def close(self) -> None:
        """Disconnect the PyBullet client (idempotent)."""
        if self.client is not None:
            self.client.disconnect()
            self.client = None

    def __enter__(self) -> PandaWorld:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
