"""hdp_motion.planning and timing on a bare pybullet Panda: IK, straight lines,
collision checking, RRT-Connect around a wall, time parameterisation."""

import math

import numpy as np
import pybullet as p
import pybullet_data
import pytest

from hdp_motion import panda, planning, timing
from hdp_motion.panda import HOME, LOWER, UPPER, VELOCITY_LIMITS

pytestmark = pytest.mark.unit

DOWN = np.array([1.0, 0.0, 0.0, 0.0])        # gripper pointing at the floor
LEFT, RIGHT = np.array([0.45, -0.3, 0.25]), np.array([0.45, 0.3, 0.25])


@pytest.fixture(scope='module')
def world():
    """A fixed Panda over a floor, a wall between LEFT and RIGHT, the arm at LEFT."""
    client = p.connect(p.DIRECT)
    p.setAdditionalSearchPath(pybullet_data.getDataPath(), physicsClientId=client)
    robot = p.loadURDF('franka_panda/panda.urdf', useFixedBase=True, physicsClientId=client)
    floor = p.loadURDF('plane.urdf', physicsClientId=client)
    wall_shape = p.createCollisionShape(p.GEOM_BOX, halfExtents=[0.2, 0.03, 0.2],
                                        physicsClientId=client)
    wall = p.createMultiBody(0, wall_shape, basePosition=[0.45, 0.0, 0.2],
                             physicsClientId=client)
    q_left = planning.solve_ik(client, robot, LEFT, DOWN, HOME)
    planning._set_arm(client, robot, q_left)
    yield client, robot, floor, wall, q_left
    p.disconnect(client)


def rotation_angle(qa, qb):
    return 2 * math.acos(min(1.0, abs(float(np.dot(qa, qb)))))


def test_ik_round_trip_on_random_reachable_poses(world):
    client, robot, *_ = world
    rng = np.random.default_rng(0)
    solved = 0
    for _ in range(40):
        q_true = np.clip(HOME + rng.uniform(-0.5, 0.5, 7), LOWER, UPPER)
        xyz, quat = planning.ee_pose(client, robot, q_true)
        q = planning.solve_ik(client, robot, xyz, quat, HOME)
        if q is None:
            continue
        solved += 1
        assert np.all(q >= LOWER) and np.all(q <= UPPER)
        xyz_q, quat_q = planning.ee_pose(client, robot, q)
        assert np.linalg.norm(xyz_q - xyz) < 1e-3
        assert rotation_angle(quat_q, quat) < math.radians(1.0)
    assert solved >= 38


def test_unreachable_pose_is_an_ik_error(world):
    client, robot, *_ = world
    assert planning.solve_ik(client, robot, [1.5, 0.0, 0.5], DOWN, HOME) is None


def test_linear_path_is_straight(world):
    client, robot, floor, _, q_left = world
    path = planning.linear_path(client, robot, q_left, RIGHT, DOWN, [floor])
    assert path is not None and np.allclose(path[0], q_left)
    # Waypoints and the joint-space midpoints between them.
    states = np.concatenate([path, (path[1:] + path[:-1]) / 2])
    line = (RIGHT - LEFT) / np.linalg.norm(RIGHT - LEFT)
    for q in states:
        xyz, quat = planning.ee_pose(client, robot, q)
        offset = xyz - LEFT
        assert np.linalg.norm(offset - np.dot(offset, line) * line) < 0.005
        assert rotation_angle(quat, DOWN) < math.radians(2.0)
    assert np.linalg.norm(planning.ee_pose(client, robot, path[-1])[0] - RIGHT) < 1e-3


def test_wall_blocks_the_line_and_rrt_connect_goes_around(world):
    client, robot, floor, wall, q_left = world
    obstacles = [floor, wall]
    assert planning.linear_path(client, robot, q_left, RIGHT, DOWN, obstacles) is None
    q_right = planning.linear_path(client, robot, q_left, RIGHT, DOWN, [floor])[-1]

    path = planning.rrt_connect(client, robot, q_left, q_right, obstacles, seed=3)
    assert path is not None
    assert np.allclose(path[0], q_left) and np.allclose(path[-1], q_right)
    assert np.all(path >= LOWER) and np.all(path <= UPPER)
    assert np.max(np.linalg.norm(np.diff(path, axis=0), axis=1)) <= planning.RRT_RESOLUTION + 1e-9
    # Every waypoint and three states between each pair, without any margin.
    between = [a + s * (b - a) for a, b in zip(path[:-1], path[1:]) for s in (0.25, 0.5, 0.75)]
    touching = planning.collision_checker(client, robot, obstacles, margin=0.0)
    with planning.preserved_state(client, robot):
        assert all(touching(q) for q in [*path, *between])

    again = planning.rrt_connect(client, robot, q_left, q_right, obstacles, seed=3)
    assert np.array_equal(path, again)
    rough = planning.rrt_connect(client, robot, q_left, q_right, obstacles, seed=3, simplify=False)
    assert rough is not None and len(rough) > len(path)


def test_plan_to_pose_prefers_a_straight_line(world):
    client, robot, floor, wall, q_left = world
    path, kind = planning.plan_to_pose(client, robot, q_left, RIGHT, DOWN, [floor])
    assert kind == 'linear'
    path, kind = planning.plan_to_pose(client, robot, q_left, RIGHT, DOWN, [floor, wall])
    assert kind == 'rrt'
    assert np.linalg.norm(planning.ee_pose(client, robot, path[-1])[0] - RIGHT) < 1e-3


def test_planning_leaves_the_simulated_robot_alone(world):
    client, robot, floor, wall, q_left = world
    velocities = np.linspace(0.1, 0.7, 7)
    planning._set_arm(client, robot, q_left, velocities)
    planning.plan_to_pose(client, robot, q_left, RIGHT, DOWN, [floor, wall])
    planning.solve_ik(client, robot, RIGHT, DOWN, HOME)
    states = p.getJointStates(robot, panda.ARM_JOINT_IDS, physicsClientId=client)
    assert np.array_equal([s[0] for s in states], q_left)
    assert np.allclose([s[1] for s in states], velocities)
    planning._set_arm(client, robot, q_left)


def test_attached_body_moves_with_the_hand(world):
    client, robot, floor, _, q_left = world
    # A 30 cm rod held across the fingers at LEFT; its ends stick out of the hand.
    rod_shape = p.createCollisionShape(p.GEOM_BOX, halfExtents=[0.15, 0.01, 0.01],
                                       physicsClientId=client)
    rod = p.createMultiBody(0.1, rod_shape, basePosition=LEFT, physicsClientId=client)
    post_shape = p.createCollisionShape(p.GEOM_BOX, halfExtents=[0.02, 0.02, 0.02],
                                        physicsClientId=client)
    post = p.createMultiBody(0, post_shape, basePosition=LEFT + [0.13, 0.0, -0.032],
                             physicsClientId=client)
    try:
        rod_pose = p.getBasePositionAndOrientation(rod, physicsClientId=client)
        with planning.preserved_state(client, robot, attached=rod):
            # Held, the rod may touch the fingers, but its end may not touch the post.
            assert planning.collision_checker(client, robot, [floor, rod], attached=rod)(q_left)
            assert planning.collision_checker(client, robot, [floor, post])(q_left)
            assert not planning.collision_checker(client, robot, [floor, post], attached=rod)(q_left)
            # Carried along: out of the post's way at HOME.
            assert planning.collision_checker(client, robot, [floor, post], attached=rod)(HOME)
        assert p.getBasePositionAndOrientation(rod, physicsClientId=client) == rod_pose
    finally:
        p.removeBody(post, physicsClientId=client)
        p.removeBody(rod, physicsClientId=client)


@pytest.mark.parametrize('scale', [1.0, 0.3])
def test_time_parameterize_respects_velocity_limits(world, scale):
    client, robot, floor, wall, q_left = world
    path, _ = planning.plan_to_pose(client, robot, q_left, RIGHT, DOWN, [floor, wall])
    path = np.concatenate([path, path[-1:]])          # a zero-length segment too
    times = timing.time_parameterize(path, velocity_scale=scale)
    assert times.shape == (len(path),) and times[0] == 0.0
    assert np.all(np.diff(times) > 0)
    speed = np.abs(np.diff(path, axis=0)) / np.diff(times)[:, None]
    assert np.all(speed <= VELOCITY_LIMITS * scale * (1 + 1e-9))


def test_resample_path_spaces_waypoints_evenly():
    path = np.array([np.zeros(7), np.full(7, 0.1), np.full(7, 0.1), np.full(7, 0.4)])
    resampled = timing.resample_path(path, 9)
    assert resampled.shape == (9, 7)
    assert np.allclose(resampled[[0, -1]], path[[0, -1]])
    assert np.allclose(np.diff(resampled, axis=0), 0.05)


def test_quat_angle_is_sign_invariant_and_agrees_with_torchs_pose_error():
    import torch

    from hdp_motion.kinematics import pose_error
    from hdp_motion.rotations import quat_angle
    quarter_turn_z = [0.0, 0.0, math.sin(math.pi / 4), math.cos(math.pi / 4)]
    assert quat_angle(DOWN, DOWN) == 0.0
    assert math.isclose(quat_angle([0, 0, 0, 1], quarter_turn_z), math.pi / 2)
    assert math.isclose(quat_angle([0, 0, 0, -3], quarter_turn_z), math.pi / 2)     # any sign and length
    rng = np.random.default_rng(0)
    qa, qb = rng.normal(size=(2, 100, 4))
    angles = quat_angle(qa, qb)
    assert angles.shape == (100,) and np.array_equal(angles, quat_angle(-qa, qb))
    poses = [torch.tensor(np.concatenate([np.zeros((100, 3)), q], 1)) for q in (qa, qb)]
    assert np.allclose(angles, pose_error(*poses)[1].numpy(), atol=1e-7)
    unit_a, unit_b = (q / np.linalg.norm(q, axis=-1, keepdims=True) for q in (qa, qb))
    assert np.allclose(angles, [rotation_angle(a, b) for a, b in zip(unit_a, unit_b)], atol=1e-9)


def test_each_robot_types_limits_are_franka_descriptions():
    """robots/fer and robots/fr3 joint_limits.yaml of franka_description (jazzy)."""
    fr3 = panda.limits_for('fr3')
    assert fr3.lower[0] == -2.7437 and fr3.upper[0] == 2.7437 and fr3.lower[5] == 0.5445 and fr3.upper[5] == 4.5169
    assert fr3.upper[3] == -0.1518 and list(fr3.velocity) == [2.62] * 4 + [5.26, 4.18, 5.26]
    assert panda.limits_for('panda') == panda.JointLimits(panda.LOWER, panda.UPPER, panda.VELOCITY_LIMITS)
    assert all(np.all(lim.lower < lim.upper) for lim in panda.ROBOT_LIMITS.values())
    assert panda.within_limits(panda.HOME, limits=fr3)
    with pytest.raises(ValueError, match='unknown robot type .ur5.; robot types: panda, fr3'):
        panda.limits_for('ur5')


def test_timing_follows_the_robots_velocity_limits():
    path = np.linspace(panda.HOME, panda.HOME + np.array([0, 0, 0, 0, 2.0, 0, 0]), 50)   # joint 5 alone
    panda_times = timing.time_parameterize(path, velocity_scale=1.0)
    fr3_times = timing.time_parameterize(path, velocity_scale=1.0, velocity_limits=panda.limits_for('fr3').velocity)
    assert fr3_times[-1] < panda_times[-1]                       # joint 5: 5.26 rad/s on the FR3, 2.61 on the Panda
    speed = np.max(np.abs(np.diff(path, axis=0)) / np.diff(fr3_times)[:, None], axis=0)
    assert speed[4] <= 5.26 + 1e-6 and speed[4] > 2.61
