"""Motion planning for the scripted experts and the "Planner" baseline (PyBullet + OMPL).

Only what plans imports this module: it loads PyBullet and OMPL.

RLBench's rule, on a pybullet Panda: reach a pose by a straight Cartesian
line if one exists, else by IK to a goal configuration and OMPL RRT-Connect.
Everything takes a pybullet client id, the Panda's body id (pybullet_data
``franka_panda/panda.urdf``: arm joints 0-6, grasp target link 11) and obstacle
body ids, so it works with any world.

Planning resets the arm's joints to query IK and collisions; every public
function puts the arm (and an attached body) back as it found it, joint
velocities included, so planning never disturbs the simulation. Collision
queries use ``getClosestPoints`` only, never ``performCollisionDetection``,
which would leave contact manifolds of planning poses behind for the next step.

Joint configurations are (7,) arrays, paths (N, 7), in radians; poses are
xyz (3,) in metres and quaternions (4,) in pybullet's x, y, z, w order.
"""

import contextlib
import math

import numpy as np
import pybullet as p
from ompl import base as ob, geometric as og, util as ou

from .panda import ARM_JOINT_IDS, EE_LINK_ID, FINGER_JOINT_IDS, FINGER_MAX, HOME, LOWER, ROBOT_BASE, UPPER
from .rotations import quat_angle

# The rigid hand: panda_link8, panda_hand, the grasp target, and the fingers.
# A grasped body touches these, so they never collide with it.
HAND_LINKS = frozenset({7, 8, 9, 10, 11})

MARGIN = 0.005            # m: closer than this to an obstacle counts as collision
IK_POS_TOL = 1e-3         # m
IK_ROT_TOL = math.radians(1.0)
RRT_RESOLUTION = 0.02     # rad: joint-space step at which motions are checked
# pybullet collides convex hulls of the meshes. panda_link5's hull fills the
# recess the real link has for the wrist, so it overlaps panda_link7 and the
# hand whenever joint 6 < ~0.7 rad, which the real arm does freely.
_HULL_OVERLAPS = frozenset({(4, 6), (4, 8)})


# ----------------------------------------------------------------- state

def _set_arm(client, robot, q, qd=(0.0,) * 7):
    p.resetJointStatesMultiDof(robot, ARM_JOINT_IDS, [[x] for x in q], [[x] for x in qd],
                               physicsClientId=client)


def arm_positions(client, robot) -> np.ndarray:
    """The arm's joint positions, (7,)."""
    return np.array([s[0] for s in p.getJointStates(robot, ARM_JOINT_IDS, physicsClientId=client)])


@contextlib.contextmanager
def preserved_state(client, robot, attached=None):
    """Restore the arm's joint positions and velocities (and the attached
    body's base pose and velocity) on exit: planning only ever moves those."""
    arm = p.getJointStates(robot, ARM_JOINT_IDS, physicsClientId=client)
    if attached is not None:
        pose = p.getBasePositionAndOrientation(attached, physicsClientId=client)
        twist = p.getBaseVelocity(attached, physicsClientId=client)
    try:
        yield
    finally:
        _set_arm(client, robot, [s[0] for s in arm], [s[1] for s in arm])
        if attached is not None:
            p.resetBasePositionAndOrientation(attached, *pose, physicsClientId=client)
            p.resetBaseVelocity(attached, *twist, physicsClientId=client)


def ee_pose(client, robot, q=None) -> tuple[np.ndarray, np.ndarray]:
    """Forward kinematics of the grasp target: (xyz (3,), quat_xyzw (4,)).
    With q (7,), for that configuration, leaving the arm as it was."""
    if q is not None:
        with preserved_state(client, robot):
            _set_arm(client, robot, q)
            return ee_pose(client, robot)
    state = p.getLinkState(robot, EE_LINK_ID, computeForwardKinematics=True,
                           physicsClientId=client)
    return np.array(state[4]), np.array(state[5])


def _overlap(box_a, box_b) -> bool:
    """Whether two pybullet AABBs ((min xyz), (max xyz)) intersect."""
    return all(lo_a <= hi_b and lo_b <= hi_a
               for lo_a, hi_a, lo_b, hi_b in zip(*box_a, *box_b))


# ----------------------------------------------------------------- IK

def solve_ik(client, robot, xyz, quat_xyzw, q_seed, rounds=20,
             pos_tol=IK_POS_TOL, rot_tol=IK_ROT_TOL):
    """Joint configuration (7,) placing link 11 at the pose, or None.

    pybullet's null-space IK started at q_seed, re-solved from each candidate
    for up to `rounds` rounds until the position error is below pos_tol (m)
    and the orientation error below rot_tol (rad).
    Candidates are clamped to the Panda's limits, so a pose that needs a joint
    beyond them never converges. None is an "IK error": the pose is
    unreachable from this seed within the limits (the Pose-Diffusion+IK
    baseline counts it as a failed episode, as RLBench's IKError does).
    Collisions are not considered.
    """
    quat = np.asarray(quat_xyzw, dtype=float) / np.linalg.norm(quat_xyzw)
    # calculateInverseKinematics takes limits for every movable joint: the
    # arm's, then the two fingers', which stay where they are.
    fingers = [s[0] for s in p.getJointStates(robot, FINGER_JOINT_IDS, physicsClientId=client)]
    lower = [*LOWER, 0.0, 0.0]
    upper = [*UPPER, 0.04, 0.04]
    ranges = [hi - lo for lo, hi in zip(lower, upper)]
    q = np.clip(np.asarray(q_seed, dtype=float), LOWER, UPPER)
    with preserved_state(client, robot):
        _set_arm(client, robot, q)
        for _ in range(rounds):
            # Each call starts from the arm's current joints, so resetting
            # them to the last candidate refines it. The rest pose is that
            # candidate too: pulling towards q_seed instead holds the solver
            # back (1% vs 74% of random reachable poses solved from HOME).
            solution = p.calculateInverseKinematics(
                robot, EE_LINK_ID, list(xyz), list(quat), lowerLimits=lower,
                upperLimits=upper, jointRanges=ranges, restPoses=[*q, *fingers],
                maxNumIterations=50, residualThreshold=1e-5, physicsClientId=client)
            q = np.clip(solution[:7], LOWER, UPPER)
            _set_arm(client, robot, q)
            pos, orn = ee_pose(client, robot)
            if (np.linalg.norm(pos - xyz) < pos_tol
                    and quat_angle(orn, quat) < rot_tol):
                return q
    return None


def kinematic_scene(boxes=()) -> tuple[int, int, tuple[int, ...]]:
    """(client id, Panda body id, obstacle body ids) of a PyBullet DIRECT client holding the Panda
    at ROBOT_BASE (arm at HOME, fingers open) and static ``boxes`` ((centre xyz, half extents)
    pairs, m): a scene to plan in where no simulator runs, such as on the robot."""
    import pybullet_data
    client = p.connect(p.DIRECT)
    p.setAdditionalSearchPath(pybullet_data.getDataPath(), physicsClientId=client)
    robot = p.loadURDF('franka_panda/panda.urdf', ROBOT_BASE, useFixedBase=True, physicsClientId=client)
    _set_arm(client, robot, HOME)
    for joint in FINGER_JOINT_IDS:
        p.resetJointState(robot, joint, FINGER_MAX, physicsClientId=client)
    obstacles = tuple(
        p.createMultiBody(0.0, p.createCollisionShape(p.GEOM_BOX, halfExtents=half, physicsClientId=client),
                          basePosition=centre, physicsClientId=client)
        for centre, half in boxes)
    return client, robot, obstacles


# ----------------------------------------------------------------- collisions

def _checked_self_pairs(client, robot):
    """Link pairs that may collide: not the same rigid group (links joined by
    fixed joints), not parent and child groups, whose meshes always touch, and
    not _HULL_OVERLAPS."""
    n = p.getNumJoints(robot, physicsClientId=client)
    info = [p.getJointInfo(robot, j, physicsClientId=client) for j in range(n)]
    group = {-1: -1}                 # link -> the first link of its rigid group
    for j, i in enumerate(info):     # parents come before children in pybullet
        group[j] = group[i[16]] if i[2] == p.JOINT_FIXED else j
    parent = {group[j]: group[i[16]] for j, i in enumerate(info) if group[j] == j}
    has_shape = [link for link in range(-1, n)
                 if p.getCollisionShapeData(robot, link, physicsClientId=client)]
    pairs = []
    for a in has_shape:
        for b in has_shape:
            ga, gb = group[a], group[b]
            adjacent = parent.get(ga) == gb or parent.get(gb) == ga
            # Sibling fingers: closing on nothing they meet; not a plan's concern.
            siblings = parent.get(ga) == parent.get(gb)
            if a < b and ga != gb and not (adjacent or siblings or (a, b) in _HULL_OVERLAPS):
                pairs.append((a, b))
    return pairs


def collision_checker(client, robot, obstacles, attached=None, margin=MARGIN):
    """A function q (7,) -> True when the arm there is collision free.

    Checks the arm's links against every obstacle (all their links), the arm
    against itself (non-adjacent links), and, when `attached` is a grasped
    body id, that body, carried rigidly by the hand as it is held now, against
    the obstacles and the arm below the hand. Closer than `margin` (m) to an
    obstacle counts as collision; the arm's own links may touch but not overlap
    (their convex hulls are conservative already). The robot's fixed base is
    not checked against obstacles: it never moves, and usually stands on one.

    The function moves the arm (and the attached body) and does not put them
    back: call it inside preserved_state(client, robot, attached).
    """
    obstacles = [b for b in obstacles if b not in (robot, attached)]
    self_pairs = _checked_self_pairs(client, robot)
    links = {link for pair in self_pairs for link in pair}
    if attached is not None:
        hand = p.getLinkState(robot, 8, computeForwardKinematics=True, physicsClientId=client)
        obj = p.getBasePositionAndOrientation(attached, physicsClientId=client)
        hand_inv = p.invertTransform(hand[4], hand[5])
        in_hand = p.multiplyTransforms(*hand_inv, *obj)

    def near(body_a, body_b):
        return p.getClosestPoints(body_a, body_b, margin, physicsClientId=client)

    def valid(q) -> bool:
        _set_arm(client, robot, q)
        for body in obstacles:
            if any(c[3] != -1 for c in near(robot, body)):
                return False
        # One getClosestPoints of the robot with itself costs ~0.6 ms (every
        # link pair, meshes included): query only the pairs whose boxes meet.
        box = {link: p.getAABB(robot, link, physicsClientId=client) for link in links}
        for a, b in self_pairs:
            if _overlap(box[a], box[b]) and p.getClosestPoints(
                    robot, robot, 0.0, linkIndexA=a, linkIndexB=b, physicsClientId=client):
                return False   # hulls are conservative: links may touch, not overlap
        if attached is None:
            return True
        hand = p.getLinkState(robot, 8, computeForwardKinematics=True, physicsClientId=client)
        pose = p.multiplyTransforms(hand[4], hand[5], *in_hand)
        p.resetBasePositionAndOrientation(attached, *pose, physicsClientId=client)
        if any(near(attached, body) for body in obstacles):
            return False
        return not any(c[4] not in HAND_LINKS for c in near(attached, robot))

    return valid


# ----------------------------------------------------------------- paths

def linear_path(client, robot, q_start, xyz_goal, quat_goal, obstacles=(), step=0.01,
                rot_step=0.05, max_joint_step=0.1, attached=None, margin=MARGIN):
    """A joint path (N, 7) moving the grasp target along a straight line, or None.

    Waypoints every `step` m (and `rot_step` rad of rotation, slerped) from the
    pose at q_start to the goal, each solved by IK seeded with the previous
    solution. None when a waypoint has no IK solution, a joint moves more than
    `max_joint_step` rad between waypoints (a flip through a singularity or a
    branch change: not a straight motion) or a waypoint collides. The start
    itself is not checked: the robot is already there, possibly in contact.
    """
    q_start, xyz_goal = np.asarray(q_start, dtype=float), np.asarray(xyz_goal, dtype=float)
    quat_goal = np.asarray(quat_goal, dtype=float) / np.linalg.norm(quat_goal)
    with preserved_state(client, robot, attached):
        xyz_start, quat_start = ee_pose(client, robot, q_start)
        if np.dot(quat_start, quat_goal) < 0:   # slerp the short way round
            quat_goal = -quat_goal
        n = max(1, math.ceil(np.linalg.norm(xyz_goal - xyz_start) / step),
                math.ceil(quat_angle(quat_start, quat_goal) / rot_step))
        valid = collision_checker(client, robot, obstacles, attached, margin)
        path = [q_start]
        for s in np.linspace(0.0, 1.0, n + 1)[1:]:
            xyz = (1 - s) * xyz_start + s * xyz_goal
            quat = _slerp(quat_start, quat_goal, s)
            q = solve_ik(client, robot, xyz, quat, path[-1])
            if (q is None or np.max(np.abs(q - path[-1])) > max_joint_step
                    or not valid(q)):
                return None
            path.append(q)
    return np.array(path)


def _slerp(qa, qb, s):
    """Spherical interpolation of unit quaternions with dot(qa, qb) >= 0."""
    angle = math.acos(min(1.0, float(np.dot(qa, qb))))
    if angle < 1e-9:
        return qa
    return (math.sin((1 - s) * angle) * qa + math.sin(s * angle) * qb) / math.sin(angle)


@contextlib.contextmanager
def _quiet_ompl():
    """Silence OMPL's log (its planners report every solve at INFO)."""
    level = ou.getLogLevel()
    ou.setLogLevel(ou.LOG_NONE)
    try:
        yield
    finally:
        ou.setLogLevel(level)


def rrt_connect(client, robot, q_start, q_goal, obstacles, timeout=5.0, seed=0,
                simplify=True, attached=None, margin=MARGIN, resolution=RRT_RESOLUTION):
    """A collision-free joint path (N, 7) from q_start to q_goal, or None.

    OMPL RRT-Connect in the joint space bounded by the Panda's limits, with
    collision_checker as the state validity checker and motions checked every
    `resolution` rad (joint-space distance). With `simplify` the path is
    shortcut and smoothed by OMPL's PathSimplifier; without it, it keeps the
    planner's detours, which is how some planner paths stay sub-optimal. The
    result is interpolated to one state per `resolution`: every returned state
    was validity-checked. None also when q_start or q_goal is invalid (a start
    touching an obstacle counts: leave that obstacle out, or back off first).

    Deterministic for a given seed (>= 0) and world as long as the search
    finishes within `timeout` (s): OMPL's seed generator is reseeded on every
    call and the planner and simplifier are single-threaded. A search cut
    short by the timeout depends on wall time; it returns None.
    """
    q_start, q_goal = (np.clip(q, LOWER, UPPER) for q in (q_start, q_goal))
    space = ob.RealVectorStateSpace(7)
    bounds = ob.RealVectorBounds(7)
    bounds.low, bounds.high = LOWER.tolist(), UPPER.tolist()
    space.setBounds(bounds)
    with preserved_state(client, robot, attached), _quiet_ompl():
        # Reseeding after the first OMPL RNG exists logs an error but works:
        # RNGs created afterwards (planner, samplers, simplifier) take their
        # seeds from the reseeded generator.
        ou.RNG.setSeed(seed + 1)       # OMPL ignores a seed of 0
        setup = og.SimpleSetup(space)
        valid = collision_checker(client, robot, obstacles, attached, margin)
        setup.setStateValidityChecker(lambda s: valid(s[0:7]))
        info = setup.getSpaceInformation()
        # OMPL takes the resolution as a fraction of the space's extent.
        info.setStateValidityCheckingResolution(resolution / space.getMaximumExtent())
        setup.setPlanner(og.RRTConnect(info))
        start, goal = space.allocState(), space.allocState()
        start[0:7], goal[0:7] = q_start.tolist(), q_goal.tolist()
        setup.setStartAndGoalStates(start, goal)
        setup.solve(timeout)
        if not setup.haveExactSolutionPath():
            return None
        if simplify:
            setup.simplifySolution()   # no duration: simplifyMax, deterministic
        path = setup.getSolutionPath()
        path.interpolate()             # one state per checked motion segment
        return np.array([s[0:7] for s in path.getStates()])


def plan_to_pose(client, robot, q_start, xyz, quat, obstacles, timeout=5.0, seed=0,
                 simplify=True, attached=None, margin=MARGIN, ik_attempts=20, straight_first=True):
    """RLBench's rule: (path (N, 7), 'linear') when a straight line works,
    else (path, 'rrt') from RRT-Connect to an IK goal, else None.
    ``straight_first`` False: RRT-Connect only (the paper's Planner row).

    The goal configuration is IK seeded from q_start first, then from up to
    ik_attempts - 1 random seeds (drawn from `seed`), and must be collision
    free. Arguments as for linear_path and rrt_connect.
    """
    path = linear_path(client, robot, q_start, xyz, quat, obstacles,
                       attached=attached, margin=margin) if straight_first else None
    if path is not None:
        return path, 'linear'
    rng = np.random.default_rng(seed)
    with preserved_state(client, robot, attached):
        valid = collision_checker(client, robot, obstacles, attached, margin)
        for attempt in range(ik_attempts):
            q_seed = q_start if attempt == 0 else rng.uniform(LOWER, UPPER)
            q_goal = solve_ik(client, robot, xyz, quat, q_seed)
            if q_goal is not None and valid(q_goal):
                break
        else:
            return None
    path = rrt_connect(client, robot, q_start, q_goal, obstacles, timeout, seed,
                       simplify, attached, margin)
    return None if path is None else (path, 'rrt')
