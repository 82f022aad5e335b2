"""Low-level evaluation (Table 2 setting): observations, the planner and pose+IK baselines,
oracle NBPs, episodes, the results table and `hdp eval low-level`."""

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from hdp_controller.baselines import PlannerPolicy, PoseIKPolicy
from hdp_eval.low_level_eval import distinct_nbps, evaluate, markdown_table, oracle_episode, run_episode
from hdp_controller.low_level import HORIZON, PlanResult
from hdp_controller.observation import points_from_messages
from hdp_eval.observation import front_camera, front_points, segment_request
from hdp_motion import panda, planning
from hdp_data import workspace
from hdp_msgs_py import conversions
from hdp_data.episodes import read_episode
from hdp_sim_bridge.collect import record_episode
from hdp_sim_bridge.experts import reachable_scene
from hdp_sim_bridge.world import PandaWorld

pytestmark = pytest.mark.sim

HDP = [sys.executable, '-m', 'hdp_tools.cli.main']
SEED = 5000       # a seed the planner solves for reach_target and open_drawer


@pytest.fixture(scope='module')
def world():
    with PandaWorld() as w:
        yield w


@pytest.fixture(scope='module')
def oracles(world):
    return {task: oracle_episode(task, SEED, world) for task in ('reach_target', 'open_drawer')}


def straight_line(request) -> np.ndarray:
    """A pose sampler: HORIZON poses from the start to the goal position at the goal's orientation."""
    s = np.linspace(0.0, 1.0, HORIZON)[:, None]
    xyz = (1 - s) * request.start_pose[:3] + s * request.goal_pose[:3]
    return np.hstack([xyz, np.repeat(request.goal_pose[None, 3:], HORIZON, axis=0)])


class AlwaysIKError:
    name = 'always_ik_error'

    def plan(self, request, scene=None):
        return PlanResult(None, failure='ik_error', ik_error=True)


class BeyondTheLimits:
    """Plans a path out of the joint limits: controller_node's timing refuses it, so must the evaluation."""
    name = 'beyond_limits'

    def plan(self, request, scene=None):
        return PlanResult(np.vstack([request.q, panda.UPPER + 0.01]))


# --- observation -------------------------------------------------------------------

def test_front_points_are_a_fixed_size_workspace_cloud_and_match_the_message_path(world):
    reachable_scene(world, 'open_drawer', SEED)
    camera = front_camera()
    assert (camera.intrinsics.width, camera.intrinsics.height) == (128, 96)
    points = front_points(world, camera, 512, np.random.default_rng(1))
    assert points.shape == (512, 3) and points.dtype == np.float32
    assert workspace.in_workspace(points).all()
    _, depth = camera.render(world.client)
    from_messages = points_from_messages(conversions.numpy_to_image(depth, '16UC1'), camera.camera_info(),
                                         camera.transform_stamped(), 512, np.random.default_rng(1))
    np.testing.assert_array_equal(points, from_messages)


def test_segment_request_reads_the_world_state(world):
    """As controller_node reads /joint_states: the start pose by FK of the joints, the gripper's
    state from the fingers' width (panda.reads_open), not from the last command."""
    reachable_scene(world, 'reach_target', SEED)
    goal = np.array([0.5, 0.0, 1.0, 1.0, 0.0, 0.0, 0.0])
    request = segment_request(world, goal, True, np.zeros((4, 3)))
    xyz, quat = world.ee_pose()
    np.testing.assert_allclose(request.start_pose[:3], xyz, atol=1e-6)
    assert abs(abs(np.dot(request.start_pose[3:], quat)) - 1) < 1e-6
    np.testing.assert_allclose(request.q, world.joint_positions())
    assert request.gripper_width == pytest.approx(world.gripper_width())
    assert request.gripper_open is True and request.goal_gripper_open is True
    world.command_gripper(False)
    assert segment_request(world, goal, True, np.zeros((4, 3))).gripper_open is True     # the fingers not moved yet
    world.step(240)
    assert world.gripper_width() < 0.01
    request = segment_request(world, goal, True, np.zeros((4, 3)))
    assert request.gripper_open is False and request.goal_gripper_open is True
    assert request.points.dtype == np.float32 and request.goal_pose.shape == (7,)


# --- baselines ---------------------------------------------------------------------------

def _request_to(world, xyz, quat):
    return segment_request(world, np.concatenate([xyz, quat]), True, np.zeros((1, 3)))


def test_pose_ik_follows_a_reachable_line_and_flags_an_unreachable_pose(world):
    reachable_scene(world, 'reach_target', SEED)
    xyz, quat = world.ee_pose()
    request = _request_to(world, xyz + [0.1, 0.05, -0.05], quat)
    plan = PoseIKPolicy(straight_line).plan(request)          # the standalone scene
    assert plan.ok and plan.joints.shape == (HORIZON + 1, 7) and plan.poses.shape == (HORIZON, 7)
    np.testing.assert_allclose(plan.joints[0], request.q)
    end, _ = planning.ee_pose(world.client_id, world.robot, plan.joints[-1])
    np.testing.assert_allclose(end, request.goal_pose[:3], atol=2e-3)

    far = PoseIKPolicy(lambda r: np.tile(np.r_[2.0, 0.0, 1.0, quat], (HORIZON, 1))).plan(request)
    assert not far.ok and far.failure == 'ik_error' and far.ik_error and far.poses is not None


def test_planner_plans_in_free_space_and_reports_no_path(world):
    reachable_scene(world, 'reach_target', SEED)
    xyz, quat = world.ee_pose()
    plan = PlannerPolicy().plan(_request_to(world, xyz + [0.1, 0.0, 0.0], quat))
    assert plan.ok and plan.extras['kind'] == 'linear'
    end, _ = planning.ee_pose(world.client_id, world.robot, plan.joints[-1])
    np.testing.assert_allclose(end, xyz + [0.1, 0.0, 0.0], atol=2e-3)
    here = PlannerPolicy().plan(_request_to(world, xyz, quat))       # e.g. a repeated keyframe
    assert here.ok and here.extras['kind'] == 'none' and here.joints.shape == (1, 7)
    lost = PlannerPolicy().plan(_request_to(world, [2.0, 0.0, 1.0], quat))
    assert not lost.ok and lost.failure == 'no_path' and not lost.ik_error
    rrt = PlannerPolicy(straight_first=False)          # the paper's Planner row: RRT-Connect even here
    searched = rrt.plan(_request_to(world, xyz + [0.1, 0.0, 0.0], quat))
    assert rrt.name == 'planner_rrt' and searched.ok and searched.extras['kind'] == 'rrt'
    end, _ = planning.ee_pose(world.client_id, world.robot, searched.joints[-1])
    np.testing.assert_allclose(end, xyz + [0.1, 0.0, 0.0], atol=2e-3)


# --- oracle and episodes -----------------------------------------------------------------

def test_oracle_of_reach_target_ends_where_the_expert_ended(world):
    oracle = oracle_episode('reach_target', SEED, world)
    assert oracle.expert_success and len(oracle.nbps) >= 1
    pose, gripper_open = oracle.nbps[-1]
    xyz, quat = world.ee_pose()                   # the world is where the expert left it
    np.testing.assert_allclose(pose[:3], xyz, atol=1e-3)
    assert abs(abs(np.dot(pose[3:], quat)) - 1) < 1e-6 and gripper_open


def test_oracle_nbps_are_the_keyframes_of_the_recorded_demo(world, tmp_path):
    summary = record_episode(world, 'open_drawer', 7, tmp_path, width=32, height=24)
    episode = read_episode(summary.path)
    keyframes = episode.keyframes()
    recorded = [(np.concatenate(planning.ee_pose(world.client_id, world.robot, episode.joint_states.position[k])),
                 bool(episode.joint_states.gripper_open[k])) for k in keyframes]
    oracle = oracle_episode('open_drawer', 7, world)
    expected = distinct_nbps(recorded)
    assert len(oracle.nbps) == len(expected) >= 3
    for (pose, gripper_open), (xyz_quat, recorded_open) in zip(oracle.nbps, expected):
        np.testing.assert_allclose(pose[:3], xyz_quat[:3], atol=1e-6)
        assert gripper_open == recorded_open


@pytest.mark.unit
def test_repeated_nbps_are_merged():
    pose = np.array([0.5, 0.0, 1.0, 1.0, 0.0, 0.0, 0.0])
    nudged = pose + np.array([0.001, 0, 0, 0, 0, 0, 0])
    moved = pose + np.array([0.05, 0, 0, 0, 0, 0, 0])
    nbps = [(pose, True), (nudged, True), (nudged, False), (moved, False), (moved, False)]
    assert [(p[0], o) for p, o in distinct_nbps(nbps)] == [(0.5, True), (0.501, False), (0.55, False)]


@pytest.mark.parametrize('task', ['reach_target', 'open_drawer'])
def test_planner_solves_oracle_episodes(world, oracles, task):
    record = run_episode(PlannerPolicy(), oracles[task], world=world)
    assert record.success and record.failure is None and not record.ik_error
    assert 1 <= len(record.plan_times) <= len(oracles[task].nbps)
    assert len(record.joint_paths) == len(record.plan_times) == len(record.reach_errors)
    # The planner solves IK for each NBP: its plans end on them.
    assert max(m for m, _ in record.reach_errors) < 0.01 and max(d for _, d in record.reach_errors) < 2.0


def test_pose_ik_on_a_straight_line_reaches_the_target(world, oracles):
    record = run_episode(PoseIKPolicy(straight_line), oracles['reach_target'], world=world)
    assert record.success and len(record.joint_paths[0]) == HORIZON + 2    # current joints first


def test_a_plan_out_of_the_joint_limits_is_refused_as_controller_node_refuses_it(world, oracles):
    record = run_episode(BeyondTheLimits(), oracles['reach_target'], world=world)
    assert not record.success and not record.ik_error
    assert record.failure.startswith('beyond_limits trajectory refused: ')
    assert 'outside the joint position limits' in record.failure
    assert len(record.plan_times) == 1 and record.joint_paths == [] and record.reach_errors == []


def test_always_failing_ik_gives_zero_success_and_full_ik_error():
    results = evaluate({'always_ik_error': AlwaysIKError()}, ['reach_target'], 2, SEED, progress=False)
    assert markdown_table(results).splitlines()[-1] == '| always_ik_error | 0% / 100% | 0% / 100% |'
    records = results['methods']['always_ik_error']['reach_target']['records']
    assert [r['failure'] for r in records] == ['ik_error', 'ik_error']


@pytest.mark.unit
def test_overlapping_training_seeds_raise():
    planner = PlannerPolicy()
    planner.training_seeds = {'reach_target': [5001, 5002, 7]}
    with pytest.raises(ValueError, match='reach_target seeds 5001-5002'):
        evaluate({'planner': planner}, ['reach_target'], 3, 5000, progress=False)
    with pytest.raises(ValueError, match='unknown task'):
        evaluate({'planner': PlannerPolicy()}, ['fly'], 1, 0, progress=False)
    with pytest.raises(ValueError, match='episodes >= 1'):
        evaluate({'planner': PlannerPolicy()}, ['reach_target'], 0, 0, progress=False)


@pytest.mark.dds
def test_workers_give_the_serial_results():
    def outcome(workers):
        results = evaluate({'planner': PlannerPolicy()}, ['reach_target'], 2, SEED, workers, progress=False)
        return [(r['seed'], r['success'], r['failure'], r['joint_paths'])
                for r in results['methods']['planner']['reach_target']['records']]
    assert outcome(2) == outcome(1)


@pytest.mark.unit
def test_markdown_table_layout():
    def cell(success, ik, n=4):
        return {'episodes': n, 'success_rate': success, 'ik_error_rate': ik}
    results = {'tasks': ['a', 'b', 'c'],
               'methods': {'rkd': {'a': cell(1.0, 0.0), 'b': cell(0.5, 0.25), 'c': cell(None, None, 0)},
                           'pose_ik': {'a': cell(0.25, 0.75), 'b': cell(0.0, 1.0), 'c': cell(None, None, 0)}}}
    assert markdown_table(results) == '\n'.join([
        '| method | a | b | c | overall |',
        '|---|---|---|---|---|',
        '| rkd | 100% / 0% | 50% / 25% | n/a | 75% / 12% |',
        '| pose_ik | 25% / 75% | 0% / 100% | n/a | 12% / 88% |'])


# --- command line ----------------------------------------------------------------------------

@pytest.mark.dds
def test_cli_help_and_a_planner_run():
    out = subprocess.run([*HDP, 'eval', 'low-level', '--help'], text=True, capture_output=True, check=True).stdout
    assert '--methods' in out and '--seed-start' in out and '--workers' in out
    result = subprocess.run([*HDP, 'eval', 'low-level', '--methods', 'planner', '--tasks', 'reach_target',
                             '--episodes', '1', '--seed-start', str(SEED)],
                            text=True, capture_output=True, timeout=120)
    assert result.returncode == 0, result.stderr
    assert '| method | reach_target | overall |' in result.stdout
    assert '| planner | 100% / 0% | 100% / 0% |' in result.stdout


@pytest.mark.dds
@pytest.mark.parametrize('args, message', [
    (['--tasks', 'fly'], 'unknown task'),
    (['--methods', 'magic'], 'unknown method'),
    (['--episodes', '0'], '--episodes, --workers and --threads must be >= 1'),
    (['--threads', '0'], '--episodes, --workers and --threads must be >= 1'),
    (['--seed-start', '-3'], '--seed-start must be >= 0'),
    (['--refine-steps', '0'], '--steps, --refine-steps and --rkd-draws must be >= 1'),
    (['--rkd-draws', '0'], '--steps, --refine-steps and --rkd-draws must be >= 1'),
])
def test_cli_refuses_bad_arguments(args, message):
    base = {'--tasks': 'reach_target', '--methods': 'planner', '--episodes': '1', '--seed-start': '0'}
    base.update(dict(zip(args[::2], args[1::2])))
    result = subprocess.run([*HDP, 'eval', 'low-level', *[x for kv in base.items() for x in kv]],
                            text=True, capture_output=True, timeout=60)
    assert result.returncode != 0 and message in result.stderr


@pytest.mark.dds
def test_torchrun_shards_the_episodes_and_gathers_one_result(tmp_path):
    """Two processes under torchrun take every other episode; rank 0 prints one table and writes one
    result file with every episode, as one process does."""
    args = ['eval', 'low-level', '--methods', 'planner', '--tasks', 'reach_target,open_drawer', '--episodes', '2',
            '--seed-start', str(SEED)]
    one = subprocess.run([*HDP, *args, '--json', str(tmp_path / 'one.json')], text=True, capture_output=True,
                         timeout=600)
    assert one.returncode == 0, one.stderr
    env = {**os.environ, 'MASTER_ADDR': '127.0.0.1', 'GLOO_SOCKET_IFNAME': 'lo', 'OMP_NUM_THREADS': '1'}
    two = subprocess.run([sys.executable, '-m', 'torch.distributed.run', '--standalone', '--nproc-per-node', '2',
                          '-m', 'hdp_tools.cli.main', *args, '--json', str(tmp_path / 'two.json')],
                         text=True, capture_output=True, timeout=600, env=env)
    assert two.returncode == 0, two.stderr[-3000:]
    assert two.stdout.count('| method |') == 1
    single, split = (json.loads((tmp_path / f'{n}.json').read_text()) for n in ('one', 'two'))
    assert (single['processes'], split['processes']) == (1, 2)

    def outcomes(results):
        return [(r['task'], r['seed'], r['success'], r['failure']) for task in results['methods']['planner'].values()
                for r in task['records']]
    assert len(outcomes(split)) == 4 and outcomes(split) == outcomes(single)
    assert split['skipped'] == single['skipped']
