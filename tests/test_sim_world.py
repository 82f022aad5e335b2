"""hdp_sim_bridge.world: joint limits, determinism, the gripper and the kinematic grasp."""

import math
import os
import subprocess
import sys
import types
from pathlib import Path

import numpy as np
import pybullet
import pytest

from hdp_motion import panda
from hdp_motion import timing
from hdp_motion.panda import EE_LINK_ID
from hdp_sim_bridge import experts
from hdp_sim_bridge.trajectory_follower import ActiveTrajectory
from hdp_sim_bridge.world import GRASP_FORCE_LIMIT, TABLE_TOP_Z, TIME_STEP, PandaWorld

pytestmark = pytest.mark.sim

DOWN = (1.0, 0.0, 0.0, 0.0)       # grasp target z axis pointing at the table
BOX_HALF = 0.02                   # m: a 4 cm cube
BOX_XY = (0.5, 0.05)


@pytest.fixture
def world():
    with PandaWorld() as w:
        yield w


def spawn_box(world, xy=BOX_XY, mass=0.1) -> int:
    c = world.client
    half = [BOX_HALF] * 3
    box = c.createMultiBody(mass, c.createCollisionShape(pybullet.GEOM_BOX, halfExtents=half),
                            c.createVisualShape(pybullet.GEOM_BOX, halfExtents=half),
                            basePosition=(*xy, TABLE_TOP_Z + BOX_HALF))
    c.changeDynamics(box, -1, lateralFriction=1.0)
    return world.add_task_body(box)


def box_position(world, box) -> np.ndarray:
    return np.array(world.client.getBasePositionAndOrientation(box)[0])


def ik(world, xyz) -> np.ndarray:
    """(7,) joint angles putting the grasp target at ``xyz``, pointing down, within the limits."""
    q = world.client.calculateInverseKinematics(
        world.robot, EE_LINK_ID, xyz, DOWN, lowerLimits=list(panda.LOWER) + [0, 0],
        upperLimits=list(panda.UPPER) + [0.04, 0.04],
        jointRanges=list(panda.UPPER - panda.LOWER) + [0.04, 0.04],
        restPoses=list(panda.HOME) + [0.04, 0.04], maxNumIterations=200, residualThreshold=1e-6)
    return np.clip(q[:7], panda.LOWER, panda.UPPER)


def move_to(world, xyz, steps=480):
    """Servo the grasp target to ``xyz`` (IK re-solved from where the arm got to)."""
    for _ in range(3):
        world.command_arm(ik(world, xyz))
        world.step(steps // 3)
    assert np.linalg.norm(world.ee_pose()[0] - xyz) < 0.005


def grasp_box(world, box):
    top = box_position(world, box)
    move_to(world, top + (0, 0, 0.15))
    move_to(world, top)
    world.command_gripper(open=False)
    world.step(120)


def test_reset_state(world):
    world.step(10)
    world.command_arm(panda.UPPER)
    world.reset(seed=1)
    assert world.sim_time == 0.0
    np.testing.assert_allclose(world.joint_positions(), panda.HOME, atol=1e-9)
    assert world.gripper_width() == pytest.approx(panda.GRIPPER_OPEN_WIDTH)
    assert world.grasped_body() is None and world.task_bodies == []
    world.step(240)
    assert world.sim_time == pytest.approx(240 * TIME_STEP)
    np.testing.assert_allclose(world.joint_positions(), panda.HOME, atol=2e-3)   # it holds HOME
    assert world.ee_pose()[0][2] > TABLE_TOP_Z + 0.3


def test_reset_arm_rejects_poses_outside_the_limits(world):
    with pytest.raises(ValueError):
        world.reset_arm(panda.UPPER + 0.1)


def test_large_moves_respect_position_and_velocity_limits(world):
    # Two sweeps that drive most joints at full speed into (and past) their limits,
    # clear of the table.
    beyond_upper = panda.HOME.copy()
    beyond_upper[[0, 2, 4, 5, 6]] = [3.5, -1.0, 3.5, 4.5, -3.5]
    beyond_lower = beyond_upper.copy()
    beyond_lower[[0, 1, 3, 4, 5, 6]] = [-3.5, -2.5, 0.5, -3.5, -1.0, 3.5]
    fastest = np.zeros(7)
    for target in (beyond_upper, beyond_lower):
        world.command_arm(target)
        for _ in range(900):
            world.step()
            q = world.joint_positions()
            assert np.all(q >= panda.LOWER) and np.all(q <= panda.UPPER), q
            fastest = np.maximum(fastest, np.abs(world.joint_velocities()))
        assert np.abs(q - np.clip(target, panda.LOWER, panda.UPPER)).max() < 0.02
    assert not world.contacts_with_robot(world.table)
    assert np.all(fastest <= panda.VELOCITY_LIMITS * 1.005), fastest / panda.VELOCITY_LIMITS
    # The sweeps did reach top speed (joint 2 travels too little to get there).
    assert np.all(fastest[[0, 2, 3, 4, 5, 6]] > panda.VELOCITY_LIMITS[[0, 2, 3, 4, 5, 6]] * 0.99)


def test_max_velocity_argument_slows_the_arm(world):
    target = panda.HOME + np.array([1.0, 0.3, 0.5, 0.5, 1.0, 0.5, 1.0])
    world.command_arm(target, max_velocity=0.5)
    fastest = 0.0
    for _ in range(240):
        world.step()
        fastest = max(fastest, np.abs(world.joint_velocities()).max())
    assert 0.4 < fastest <= 0.5 * 1.01


def test_streamed_targets_are_followed_without_lag(world):
    # A smooth swing within the speed and acceleration limits, one target per step.
    amplitude, omega = 0.3, math.pi               # rad, rad/s: peak 0.94 rad/s, 3 rad/s^2
    worst = 0.0
    for k in range(1, 481):
        target = panda.HOME + amplitude * (1 - math.cos(omega * k * TIME_STEP))
        world.command_arm(target)
        world.step()
        worst = max(worst, np.abs(world.joint_positions() - target).max())
    assert worst < 0.001


def test_a_streamed_trajectory_the_arm_fell_behind_is_caught_up(world):
    # A ramp that starts at 0.8 rad/s from rest: no arm follows that velocity step, so it
    # falls behind, then must catch up rather than trail by v^2 / (2 a) (0.085 rad on joint 2,
    # which swept the fingers 1-2 cm off the experts' straight descents onto a cup).
    direction = np.array([0, 1, 0, 1, 0, 0, 0])
    lag = []
    for k in range(1, 241):                                     # 1 s
        target = panda.HOME + 0.8 * k * TIME_STEP * direction
        world.command_arm(target)
        world.step()
        lag.append(np.abs(world.joint_positions() - target).max())
    assert max(lag[:24]) > 0.005                                 # it did fall behind
    assert max(lag[120:]) < 0.005                                # and is on the ramp after 0.5 s


def test_a_timed_path_with_a_sharp_corner_is_followed_closely(world):
    # A planner's path (dense waypoints) that turns a right angle between joints 2 and 4,
    # timed and streamed as the experts stream it: the turn is taken slowly enough that the
    # arm neither trails the path nor overshoots the corner.
    ramp = np.linspace(0.0, 0.4, 21)[:, None]
    path = np.vstack([panda.HOME + ramp * [0, 1, 0, 0, 0, 0, 0],
                      panda.HOME + [0, 0.4, 0, 0, 0, 0, 0] + ramp[1:] * [0, 0, 0, 1, 0, 0, 0]])
    times = timing.time_parameterize(path, velocity_scale=0.5)
    trajectory = ActiveTrajectory(world.sim_time, times, path, timing.path_velocities(path, times, 0.5))
    worst = 0.0
    while world.sim_time < trajectory.end_time:
        target = trajectory.sample(world.sim_time + TIME_STEP)
        world.command_arm(target)
        world.step()
        worst = max(worst, np.abs(world.joint_positions() - target).max())
    assert worst < 0.002


def test_rest_waits_for_the_arm_at_its_target_not_for_a_turnaround(world):
    # Streamed away from HOME at 0.8 rad/s on joint 2, then told to rest at HOME: the joint
    # turns round, all joints still for an instant, before it gets back.
    no_task = types.SimpleNamespace(on_step=lambda world: None)
    for k in range(1, 73):                                       # 0.3 s
        world.command_arm(panda.HOME + 0.8 * k * TIME_STEP * np.array([0, 1, 0, 0, 0, 0, 0]))
        world.step()
    arrived = []
    experts.rest(world, no_task, panda.HOME, lambda: None, lambda: arrived.append(world.joint_positions()),
                 hold=0.0)
    assert len(arrived) == 1
    assert np.abs(arrived[0] - panda.HOME).max() < 0.002


def run_episode(world, seed) -> np.ndarray:
    """(T, 7 + 3) joint angles and box position over a pick-and-lift."""
    world.reset(seed)
    box = spawn_box(world)
    trace = []
    for height in (0.17, 0.02):
        world.command_arm(ik(world, (*BOX_XY, TABLE_TOP_Z + height)))
        for _ in range(200):
            world.step()
            trace.append(np.concatenate([world.joint_positions(), box_position(world, box)]))
    world.command_gripper(open=False)
    world.step(100)
    world.command_arm(ik(world, (0.4, -0.1, TABLE_TOP_Z + 0.3)))
    for _ in range(200):
        world.step()
        trace.append(np.concatenate([world.joint_positions(), box_position(world, box)]))
    return np.array(trace)


def test_same_seed_same_episode():
    with PandaWorld(seed=3) as a, PandaWorld(seed=3) as b, PandaWorld(seed=0) as used, \
            PandaWorld(seed=4) as other:
        first = run_episode(a, 3)
        assert np.array_equal(first, run_episode(b, 3))
        run_episode(used, 0)              # history before the reset must not matter
        assert np.array_equal(first, run_episode(used, 3))
        # The world draws no random numbers: only a task using world.rng makes seeds differ.
        assert np.array_equal(first, run_episode(other, 4))
        a.reset(7)
        b.reset(7)
        other.reset(8)
        draws = [w.rng.random(3) for w in (a, b, other)]
        assert np.array_equal(draws[0], draws[1]) and not np.array_equal(draws[0], draws[2])


def test_fingers_move_symmetrically(world):
    for open_ in (False, True):
        world.command_gripper(open=open_)
        for _ in range(240):
            world.step()
            left, right = world.finger_positions()
            assert abs(left - right) < 1e-3
        expected = panda.GRIPPER_OPEN_WIDTH if open_ else 0.0
        assert world.gripper_width() == pytest.approx(expected, abs=2e-3)


def test_closing_on_nothing_grasps_nothing(world):
    move_to(world, np.array([0.5, -0.2, TABLE_TOP_Z + 0.01]))     # fingers brush the table
    world.command_gripper(open=False)
    world.step(240)
    assert world.grasped_body() is None


def test_grasp_lift_and_release(world):
    box = spawn_box(world)
    world.step(60)
    start = box_position(world, box)
    grasp_box(world, box)
    assert world.grasped_body() == box
    assert 0.035 < world.gripper_width() < 0.05           # stopped on the 4 cm box

    move_to(world, start + (0, 0, 0.2))
    lifted = box_position(world, box)
    assert lifted[2] > start[2] + 0.18
    np.testing.assert_allclose(lifted, world.ee_pose()[0], atol=0.01)  # the box rides in the hand
    world.command_gripper(open=False)                      # repeating the command changes nothing
    assert world.grasped_body() == box

    world.command_gripper(open=True)
    assert world.grasped_body() is None
    world.step(240)
    assert box_position(world, box)[2] == pytest.approx(TABLE_TOP_Z + BOX_HALF, abs=0.005)
    assert world.grasp_lost_count == 0


def test_grasp_breaks_when_overloaded(world):
    box = spawn_box(world)
    # Bolt the box to the world, far stronger than the grasp.
    c = world.client
    bolt = c.createConstraint(box, -1, -1, -1, pybullet.JOINT_FIXED, (0, 0, 0), (0, 0, 0),
                              box_position(world, box))
    c.changeConstraint(bolt, maxForce=100 * GRASP_FORCE_LIMIT)
    grasp_box(world, box)
    assert world.grasped_body() == box

    world.command_arm(ik(world, box_position(world, box) + (0, 0, 0.15)))
    world.step(120)
    assert world.grasped_body() is None
    assert world.grasp_lost_count == 1
    assert world.ee_pose()[0][2] > box_position(world, box)[2] + 0.05   # the hand got away
    world.step(120)
    assert world.grasped_body() is None                    # no re-grasp until the next close


def spawn_slider(world) -> int:
    """A static base with a 4 cm cube on a free prismatic joint along x, 10 cm over the table."""
    c = world.client
    cube = c.createCollisionShape(pybullet.GEOM_BOX, halfExtents=[BOX_HALF] * 3)
    slider = c.createMultiBody(
        baseMass=0.0, baseCollisionShapeIndex=-1, basePosition=(0.55, 0.0, TABLE_TOP_Z + 0.1),
        linkMasses=[0.2], linkCollisionShapeIndices=[cube], linkVisualShapeIndices=[-1],
        linkPositions=[(0, 0, 0)], linkOrientations=[(0, 0, 0, 1)],
        linkInertialFramePositions=[(0, 0, 0)], linkInertialFrameOrientations=[(0, 0, 0, 1)],
        linkParentIndices=[0], linkJointTypes=[pybullet.JOINT_PRISMATIC],
        linkJointAxis=[(1, 0, 0)])
    c.setJointMotorControl2(slider, 0, pybullet.VELOCITY_CONTROL, force=0)   # free the joint
    return world.add_task_body(slider)


def grasp_slider(world):
    """Spawn the slider, grasp its handle from above; returns (slider id, handle position)."""
    slider = spawn_slider(world)
    handle = np.array(world.client.getLinkState(slider, 0)[4])
    move_to(world, handle + (0, 0, 0.15))
    move_to(world, handle)
    world.command_gripper(open=False)
    world.step(120)
    return slider, handle


def test_grasp_welds_the_touched_link(world):
    slider, handle = grasp_slider(world)
    assert (world.grasped_body(), world.grasped_link()) == (slider, 0)

    move_to(world, handle - (0.1, 0, 0))                     # pull the slider 10 cm
    assert world.client.getJointState(slider, 0)[0] == pytest.approx(-0.1, abs=0.01)
    assert world.grasped_body() == slider and world.grasp_lost_count == 0


def test_grasp_survives_small_fights_and_breaks_on_large_ones(world):
    slider, handle = grasp_slider(world)
    hand = world.ee_pose()[0]
    # The rail holds the handle; the compliant arm pushes it like a spring.
    world.command_arm(ik(world, hand - (0, 0, 0.01)))
    world.step(240)
    assert world.grasped_body() == slider
    world.command_arm(ik(world, hand + (0, 0.1, 0)))           # drag it 10 cm across the rail
    world.step(240)
    assert world.grasped_body() is None and world.grasp_lost_count == 1


@pytest.mark.dds
def test_a_simulator_process_leaves_no_generated_urdfs_behind(tmp_path):
    """Every collection worker and evaluation rank writes object URDFs; a finished one removes them."""
    script = ('from hdp_sim_bridge import objects; import pathlib; '
              'print(pathlib.Path(objects.urdf_file(objects.cabinet())).parent)')
    result = subprocess.run([sys.executable, '-c', script], text=True, capture_output=True, timeout=60,
                            env={**os.environ, 'TMPDIR': str(tmp_path)})
    assert result.returncode == 0, result.stderr
    folder = Path(result.stdout.strip())
    assert folder.parent == tmp_path
    assert not folder.exists()


@pytest.mark.dds
def test_the_world_loads_no_planner():
    """The simulator's world needs the Panda's joint and link indices (hdp_motion.panda), not
    hdp_motion.planning, which loads OMPL: only what plans imports that (the experts)."""
    script = ('import json, sys; import hdp_sim_bridge.world; '
              'print(json.dumps(sorted(m for m in ("ompl", "hdp_motion.planning") if m in sys.modules)))')
    result = subprocess.run([sys.executable, '-c', script], text=True, capture_output=True, timeout=60)
    assert result.returncode == 0, result.stderr
    assert result.stdout.splitlines()[-1] == '[]'
