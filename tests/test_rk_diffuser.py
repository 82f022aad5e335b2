"""RK-Diffuser: kinematics, data preparation, networks, diffusion, refinement, checkpoints, training CLI."""

import json
import os
import socket
import subprocess
import sys

import numpy as np
import pytest
import torch

from hdp_controller import checkpoint
from hdp_controller.dataset import (SegmentDataset, augment, bend_goals, draw_augmentation, load_segments,
                                    resample_by_arc_length, trajectory_rank)
from hdp_controller.diffusion import TrajectoryDiffusion
from hdp_controller.low_level import HORIZON, SegmentRequest
from hdp_controller.pointnet2 import PointNet2Encoder, ball_query, farthest_point_sample
from hdp_controller.policy import conditions
from hdp_controller.refine import goal_error, pull_to_goal, refine, smooth_poses, track
from hdp_controller.rk_diffuser import (RKDConfig, RKDiffuser, goal_loss, joint_motion, joints_from_motion,
                                        smoothness_loss)
from hdp_controller.unet import TemporalUnet
from hdp_motion import kinematics, panda
from hdp_learning.curves import read_curves
from hdp_data.episodes import list_episodes, read_episode

pytestmark = pytest.mark.unit

HDP = [sys.executable, '-m', 'hdp_tools.cli.main']
SMALL = RKDConfig(unet_dim=8, point_features=16, point_width=8, n_points=64, diffusion_steps=10)


@pytest.fixture(scope='module')
def episodes(tmp_path_factory):
    out = tmp_path_factory.mktemp('rkd_episodes')
    result = subprocess.run([*HDP, 'collect', '--tasks', 'reach_target,open_drawer', '--episodes', '1',
                             '--seed-start', '11', '--out', str(out), '--width', '64', '--height', '48'],
                            text=True, capture_output=True, timeout=300)
    assert result.returncode == 0, result.stderr
    return out


@pytest.fixture(scope='module')
def segments(episodes, tmp_path_factory):
    return load_segments(episodes, n_points=64, cache_dir=tmp_path_factory.mktemp('cache'), workers=1)


def _batch(segs, n=4, seed=0, goal_sigma=0.0):
    data = SegmentDataset(segs)
    items = [data[i % len(data)] for i in range(n)]
    batch = {k: torch.stack([it[k] for it in items]) for k in items[0]}
    return augment(batch, draw_augmentation(n, torch.Generator().manual_seed(seed), goal_sigma))


# --- kinematics ---------------------------------------------------------------------------

def test_forward_kinematics_matches_pybullet():
    from hdp_motion import planning
    from hdp_sim_bridge.world import PandaWorld
    rng = np.random.default_rng(0)
    with PandaWorld() as world:
        for _ in range(5):
            q = rng.uniform(panda.LOWER, panda.UPPER)
            xyz, quat = planning.ee_pose(world.client_id, world.robot, q)
            pose = kinematics.fk_pose(torch.tensor(q, dtype=torch.float64))
            assert np.allclose(pose[:3].numpy(), xyz, atol=1e-4)
            _, angle = kinematics.pose_error(pose, torch.tensor(np.r_[xyz, quat]))
            assert angle < 1e-3


def test_quaternion_helpers_round_trip_and_continuity():
    q = torch.nn.functional.normalize(torch.randn(10, 4, dtype=torch.float64), dim=-1)
    back = kinematics.matrix_to_quat(kinematics.quat_to_matrix(q))
    assert torch.allclose(back.abs(), q.abs(), atol=1e-6) and (back[:, 3] >= 0).all()
    flipped = q.clone()
    flipped[1::2] *= -1
    smooth = kinematics.continuous_quats(flipped)
    assert smooth[0, 3] >= 0
    assert torch.allclose(kinematics.quat_to_matrix(smooth), kinematics.quat_to_matrix(q), atol=1e-6)


# --- data -------------------------------------------------------------------------------

def test_resampling_and_rank():
    path = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0]])
    out = resample_by_arc_length(path, 5)
    assert np.allclose(out[[0, 2, 4]], path) and np.allclose(out[1], [0.5, 0.0])
    assert np.allclose(resample_by_arc_length(np.zeros((3, 2)), 4), 0.0)
    assert trajectory_rank(np.linspace([0, 0, 0], [1, 0, 0], 10)) == pytest.approx(1.0)
    assert trajectory_rank(np.array([[0, 0, 0], [1, 1, 0], [2, 0, 0]], float)) == pytest.approx(2 / (2 * 2 ** 0.5))
    assert trajectory_rank(np.zeros((5, 3))) == 1.0


@pytest.mark.dds
def test_segments_end_at_the_keyframes_the_high_level_uses(episodes, segments):
    expected = 0
    for path in list_episodes(episodes):
        episode = read_episode(path)
        keyframes = episode.keyframes()
        expected += len(keyframes) - (keyframes[0] == 0)
        first = segments.seed == episode.metadata['seed']
        ends = segments.joints[first & (segments.task == episode.metadata['task'])][:, -1]
        assert np.allclose(ends, episode.joint_states.position[[k for k in keyframes if k]], atol=1e-5)
    assert len(segments) == expected
    # Poses are the FK of the joints, waypoint by waypoint.
    fk = kinematics.fk_pose(torch.from_numpy(segments.joints[0]).double())
    _, angle = kinematics.pose_error(fk, torch.from_numpy(segments.poses[0]).double())
    assert np.allclose(fk[:, :3], segments.poses[0][:, :3], atol=1e-5) and angle.max() < 1e-3
    assert segments.points.shape == (len(segments), 64, 3)
    assert segments.training_seeds() == {'open_drawer': [11], 'reach_target': [11]}


@pytest.mark.dds
def test_start_end_augmentation_stays_on_the_path(segments):
    item = SegmentDataset(segments)[0]
    plain = augment({k: v[None] for k, v in item.items()})
    assert torch.equal(plain['joints'][0], torch.from_numpy(segments.joints[0]))
    moved = [_batch(segments, 1, seed=s) for s in range(8)]
    assert any(not torch.allclose(m['joints'][0, 0], plain['joints'][0, 0]) for m in moved)
    for m in moved:
        assert torch.allclose(m['q'], m['joints'][:, 0]) and torch.allclose(m['goal_pose'], m['poses'][:, -1])
        # Never starts later than waypoint 5 or ends earlier than HORIZON - 6.
        gap_start = (m['joints'][0, 0] - plain['joints'][0, 0]).abs().max()
        assert gap_start <= (plain['joints'][0, 5] - plain['joints'][0, 0]).abs().max() + 1e-5
        gap_end = (m['joints'][0, -1] - plain['joints'][0, -1]).abs().max()
        assert gap_end <= (plain['joints'][0, -1] - plain['joints'][0, -6]).abs().max() + 1e-5


@pytest.mark.dds
def test_goal_augmentation_bends_the_path_to_a_goal_fk_agrees_with(segments):
    """The start stays, the goal moves, and poses, goal pose and rank are the bent path's."""
    batch = _batch(segments, 16, seed=3)
    bends = torch.zeros(16, 7)
    bends[::2] = 0.05 * torch.randn(8, 7, generator=torch.Generator().manual_seed(0))
    joints, poses, rank = bend_goals(batch['joints'], batch['poses'], batch['rank'], bends)
    assert torch.equal(joints[1::2], batch['joints'][1::2]) and torch.equal(poses[1::2], batch['poses'][1::2])
    assert torch.allclose(joints[::2, 0], batch['joints'][::2, 0])
    assert torch.allclose(joints[::2, -1], (batch['joints'][::2, -1] + bends[::2]).clamp(
        torch.tensor(panda.LOWER, dtype=torch.float32), torch.tensor(panda.UPPER, dtype=torch.float32)), atol=1e-6)
    fk = kinematics.fk_pose(joints[::2, -1])
    _, angle = kinematics.pose_error(fk, poses[::2, -1])
    assert torch.allclose(fk[:, :3], poses[::2, -1, :3], atol=1e-5) and angle.max() < 1e-3
    assert (torch.linalg.norm(poses[::2, -1, :3] - batch['poses'][::2, -1, :3], dim=-1) > 1e-3).all()
    assert ((rank > 0) & (rank <= 1)).all()
    drawn = draw_augmentation(1000, torch.Generator().manual_seed(0), goal_sigma=0.05)
    bent = (drawn['bends'] != 0).any(1).float().mean()
    assert 0.4 < bent < 0.6 and abs(drawn['bends'][drawn['bends'] != 0].std() - 0.05) < 0.005
    assert drawn['trims'].min() == 0 and drawn['trims'].max() == 5


@pytest.mark.dds
def test_preprocessing_is_cached(episodes, tmp_path):
    first = load_segments(episodes, n_points=64, cache_dir=tmp_path, workers=1)
    assert len(list(tmp_path.glob('*.npz'))) == 1
    again = load_segments(episodes, n_points=64, cache_dir=tmp_path, workers=1)
    assert np.array_equal(first.joints, again.joints) and np.array_equal(first.task, again.task)


@pytest.mark.dds
def test_training_data_can_be_a_segments_file_and_bad_ones_are_refused(episodes, tmp_path):
    direct = load_segments(episodes, n_points=64, cache_dir=tmp_path, workers=1)
    cache, = tmp_path.glob('*.npz')
    from_file = load_segments(cache, n_points=64)
    assert np.array_equal(direct.points, from_file.points) and np.array_equal(direct.seed, from_file.seed)
    with pytest.raises(ValueError, match='points has shape'):
        load_segments(cache, n_points=128)
    half = {k: (v.astype(np.float16) if v.dtype == np.float32 else v) for k, v in vars(direct).items()}
    np.savez(tmp_path / 'half.npz', **half)          # a smaller copy to ship still trains in float32
    assert load_segments(tmp_path / 'half.npz', n_points=64).points.dtype == np.float32
    np.savez(tmp_path / 'other.npz', joints=direct.joints)
    with pytest.raises(ValueError, match='not a segments file'):
        load_segments(tmp_path / 'other.npz', n_points=64)
    (tmp_path / 'junk.npz').write_bytes(b'not a zip')
    with pytest.raises(ValueError):
        load_segments(tmp_path / 'junk.npz', n_points=64)


# --- networks ---------------------------------------------------------------------------

def test_farthest_point_sampling_and_ball_query():
    cluster = torch.cat([torch.zeros(20, 3), torch.ones(1, 3) * 5, -torch.ones(1, 3) * 5])[None]
    picked = farthest_point_sample(cluster, 3)[0].tolist()
    assert picked[0] == 0 and set(picked[1:]) == {20, 21}
    idx = ball_query(cluster, cluster[:, [20]], radius=1.0, k=4)
    assert (idx == 20).all()          # alone in its ball: the centroid repeats


def test_pointnet_encoder_sees_geometry():
    torch.manual_seed(0)
    encoder = PointNet2Encoder(out_dim=16, width=8)
    points = torch.rand(2, 256, 3) * 2 - 1
    shifted = points.clone()
    shifted[1, :64] += 0.5
    out = encoder(shifted)
    assert out.shape == (2, 16) and not torch.allclose(out[0], out[1])


def test_unet_shapes():
    net = TemporalUnet(7, 12, dim=8)
    assert net(torch.randn(3, HORIZON, 7), torch.tensor([0, 5, 9]), torch.randn(3, 12)).shape == (3, HORIZON, 7)


def test_sampling_holds_inpainted_waypoints():
    torch.manual_seed(0)
    diffusion = TrajectoryDiffusion(TemporalUnet(7, 4, dim=8), HORIZON, 7, train_steps=10)
    known = {0: torch.ones(2, 7), -1: -torch.ones(2, 7)}
    for sampler in ('ddpm', 'ddim'):
        x = diffusion.sample(torch.randn(2, 4), known, null_cond=torch.zeros(2, 4), guidance=1.2, sampler=sampler,
                             steps=5)
        assert torch.equal(x[:, 0], known[0]) and torch.equal(x[:, -1], known[-1])


def test_a_guide_corrects_every_step_and_the_sample_is_its_last_correction():
    torch.manual_seed(0)
    diffusion = TrajectoryDiffusion(TemporalUnet(7, 4, dim=8), HORIZON, 7, train_steps=10)
    seen = []

    def guide(x0):
        seen.append(x0.clone())
        return x0.clamp(-0.01, 0.01)
    for sampler in ('ddpm', 'ddim'):
        seen.clear()
        x = diffusion.sample(torch.randn(2, 4), {0: torch.zeros(2, 7)}, sampler=sampler, steps=4, guide=guide)
        assert len(seen) == 4 and x.abs().max() <= 0.01 + 1e-6 and torch.equal(x[:, 0], torch.zeros(2, 7))
        assert max(float(s.abs().max()) for s in seen) > 0.01       # the network's estimates were corrected


@pytest.mark.dds
def test_training_reduces_the_loss(segments):
    torch.manual_seed(0)
    model = RKDiffuser(SMALL)
    batch = _batch(segments, 8)
    optimizer = torch.optim.Adam(model.parameters(), lr=3e-3)
    losses = []
    draws = model.draw(8, torch.Generator().manual_seed(1))     # the same noise and steps each time: a pure fit
    for _ in range(30):
        loss, parts = model.loss(batch, draws)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        losses.append(loss.item())
    assert set(parts) == {'pose', 'joint', 'joint_to_pose'}
    assert losses[-1] < 0.5 * losses[0]


@pytest.mark.dds
def test_goal_and_smoothness_terms_join_the_loss(segments):
    config = RKDConfig(**{**SMALL.__dict__, 'goal_loss_weight': 2.0, 'goal_loss': 'distance',
                          'smooth_loss_weight': 10.0})
    torch.manual_seed(0)
    total, parts = RKDiffuser(config).loss(_batch(segments, 4), RKDiffuser(config).draw(4))
    assert set(parts) == {'pose', 'joint', 'joint_to_pose', 'goal', 'smooth'}
    assert total.item() == pytest.approx(sum(parts.values()) + parts['goal'] + 9 * parts['smooth'], rel=1e-4)
    with pytest.raises(ValueError, match='goal_loss'):
        RKDConfig(goal_loss='l1')


def test_smoothness_loss_sees_wiggle_not_shape():
    s = torch.linspace(0, 1, HORIZON)[None, :, None].expand(2, HORIZON, 7)
    motion = s ** 2
    assert smoothness_loss(motion, motion).item() == 0
    assert smoothness_loss(motion + 0.3 * s, motion).item() == pytest.approx(0, abs=1e-9)   # a linear offset
    wiggle = 0.01 * (-1) ** torch.arange(HORIZON)[None, :, None]
    assert smoothness_loss(motion + wiggle, motion).item() > 1e-4


def test_distance_goal_loss_keeps_pulling_at_centimetres():
    """The squared error's gradient fades with the error; its square root's does not."""
    home = torch.tensor(panda.HOME, dtype=torch.float32)[None]
    position, rotation = kinematics.forward_kinematics(home)
    goal = torch.cat([position, kinematics.matrix_to_quat(rotation)], dim=-1)
    direction = torch.tensor([[0.3, -0.2, 0.1, 0.4, 0.0, 0.2, 0.0]])

    def gradient(offset, kind):
        q = (home + offset * direction).requires_grad_()
        goal_loss(q, goal, kind).backward()
        return q.grad.norm().item()

    assert gradient(0.01, 'squared') < 0.2 * gradient(0.1, 'squared')
    assert gradient(0.01, 'distance') > 0.7 * gradient(0.1, 'distance')


@pytest.mark.dds
def test_sample_returns_goal_pose_and_joints_in_limits(segments):
    model = RKDiffuser(SMALL).eval()
    batch = _batch(segments, 2)
    out = model.sample(batch, sampler='ddim', steps=3)
    assert torch.allclose(out['poses'][:, -1, :3], batch['goal_pose'][:, :3], atol=1e-5)
    assert torch.allclose(out['joints'][:, 0], batch['q'], atol=1e-5)
    assert (out['joints'] >= torch.tensor(panda.LOWER) - 1e-6).all()
    assert (out['joints'] <= torch.tensor(panda.UPPER) + 1e-6).all()


def test_joint_diffuser_works_on_the_motion_from_the_start():
    """Its target is zero at the start waypoint whatever the start joints, and maps back exactly."""
    q0 = torch.tensor(np.stack([panda.HOME, panda.UPPER]), dtype=torch.float32) - 0.1
    joints = q0[:, None] + torch.linspace(0, 1, HORIZON)[None, :, None] * torch.tensor([0.4, -0.2, 0, 0, 0.3, 0, 1.0])
    motion = joint_motion(joints, q0)
    assert torch.equal(motion[:, 0], torch.zeros(2, 7))
    assert torch.allclose(motion[0], motion[1], atol=1e-5)      # the same motion from two starts
    assert torch.allclose(joints_from_motion(motion, q0), joints, atol=1e-6)


# --- refinement ---------------------------------------------------------------------------

def test_refinement_holds_the_start_respects_limits_and_reaches_the_goal():
    torch.manual_seed(0)
    q0 = torch.tensor(panda.HOME, dtype=torch.float32)
    q1 = q0 + torch.tensor([0.3, 0.2, -0.2, 0.3, 0.1, -0.2, 0.4])
    truth = (q0 + (q1 - q0) * torch.linspace(0, 1, HORIZON)[:, None])[None]
    poses = kinematics.fk_pose(truth)
    noisy = truth + 0.05 * torch.randn_like(truth)
    noisy[:, 0] = truth[:, 0]
    refined = refine(noisy, poses)
    translation, rotation = goal_error(refined, poses[:, -1])
    assert torch.equal(refined[:, 0], truth[:, 0])
    assert translation.item() < 2e-3 and np.degrees(rotation.item()) < 0.5
    # A pose trajectory that pulls joint 4 beyond its upper limit: clamped, never past.
    beyond = truth.clone()
    beyond[..., 3] = torch.linspace(-1.0, 0.5, HORIZON)
    out = refine(truth, kinematics.fk_pose(beyond), steps=30)
    assert (out[:, 1:, 3] <= panda.UPPER[3]).all() and (out >= torch.tensor(panda.LOWER, dtype=out.dtype)).all()


def test_pulling_to_the_goal_moves_the_end_onto_it_and_keeps_the_start_and_the_shape():
    q0 = torch.tensor(panda.HOME, dtype=torch.float32)
    q1 = q0 + torch.tensor([0.4, 0.2, -0.2, 0.3, 0.1, -0.2, 0.4])
    arc = 0.1 * torch.sin(torch.linspace(0, torch.pi, HORIZON))[:, None] * torch.ones(7)
    truth = (q0 + (q1 - q0) * torch.linspace(0, 1, HORIZON)[:, None] + arc)[None]
    goal = kinematics.fk_pose(truth[:, -1])
    short = truth.clone()
    short[:, 1:] += torch.linspace(0, 1, HORIZON)[1:, None] * torch.tensor([0.1, -0.1, 0.05, 0.1, 0, 0.1, -0.1])
    assert goal_error(short, goal)[0].item() > 0.03
    pulled = pull_to_goal(short, goal)
    translation, rotation = goal_error(pulled, goal)
    assert translation.item() < 2e-3 and np.degrees(rotation.item()) < 0.5
    assert torch.equal(pulled[:, 0], short[:, 0])
    # The correction is a ramp: the trajectory's bend (its second differences) is untouched.
    assert torch.allclose(torch.diff(pulled, n=2, dim=1), torch.diff(short, n=2, dim=1), atol=1e-5)


def test_tracking_follows_a_long_pose_path_from_the_start_in_the_start_configuration():
    """track: every waypoint solved from its predecessor, so a sweep of 2 rad at the base is
    followed in one motion of the start's configuration."""
    q0 = torch.tensor(panda.HOME, dtype=torch.float32)
    q1 = q0 + torch.tensor([2.0, 0.4, -0.3, 0.6, 0.5, 1.5, 0.5])
    truth = (q0 + (q1 - q0) * torch.linspace(0, 1, HORIZON)[:, None])[None]
    tracked = track(q0[None], kinematics.fk_pose(truth))
    assert torch.equal(tracked[:, 0], q0[None])
    translation, rotation = goal_error(tracked, kinematics.fk_pose(truth[:, -1]))
    assert translation.item() < 1e-3 and np.degrees(rotation.item()) < 0.2
    assert tracked.diff(dim=1).abs().max() < 0.05                            # one motion, no jump
    assert panda.within_limits(tracked[0].numpy())


def test_tracking_keeps_the_joints_off_their_limits_where_least_motion_drifts_into_one():
    """Least-motion steps alone follow this path into a jump of 0.34 rad with a joint 0.18 rad from
    its limit; the null-space step towards mid-range keeps it one motion, well inside the limits."""
    q0 = torch.tensor(panda.HOME, dtype=torch.float32)
    q1 = q0 + torch.tensor([2.0, 0.4, -0.3, 0.6, 0.5, 2.1, -0.5])          # joint 6 ends 0.08 rad from its limit
    truth = (q0 + (q1 - q0) * torch.linspace(0, 1, HORIZON)[:, None])[None]
    tracked = track(q0[None], kinematics.fk_pose(truth))[0]
    translation, _ = goal_error(tracked[None], kinematics.fk_pose(truth[:, -1]))
    assert translation.item() < 1e-3 and tracked.diff(dim=0).abs().max() < 0.1
    margin = np.minimum(tracked.numpy() - panda.LOWER, panda.UPPER - tracked.numpy())
    assert margin.min() > 0.3


def test_refinement_keeps_a_joint_trajectory_that_ends_on_the_goal_turned_half_a_turn():
    """The Panda hand's fingers are alike: the goal turned half a turn about the approach axis
    is the same grasp. A joint trajectory that ends there is kept, not wound back through half
    a turn of the wrist (which here would also run joint 7 into its limit)."""
    q0 = torch.tensor(panda.HOME, dtype=torch.float32)
    q1 = q0 + torch.tensor([0.3, 0.2, -0.2, 0.3, 0.1, -0.2, 1.7])      # joint 7 at 2.49 of its 2.90
    ramp = torch.linspace(0, 1, HORIZON)[:, None]
    poses = kinematics.fk_pose((q0 + (q1 - q0) * ramp)[None])
    turned = q1 - torch.tensor([0, 0, 0, 0, 0, 0, torch.pi])         # joint 7 turns the hand about z
    sampled = (q0 + (turned - q0) * ramp)[None]
    refined = refine(sampled, poses)
    translation, rotation = goal_error(refined, poses[:, -1])
    assert translation.item() < 1e-3 and np.degrees(rotation.item()) < 0.5
    assert (refined - sampled).abs().max() < 0.05
    # goal_error counts the turned grasp as reached, and nothing else
    assert goal_error(turned[None, None], poses[:, -1])[1].item() < 1e-3
    assert np.degrees(goal_error(q0[None, None], poses[:, -1])[1].item()) > 10


def test_refinement_makes_up_for_a_joint_held_at_its_limit_with_the_others():
    """A pose trajectory that joint 6 alone would follow past its upper limit: the joint stays
    at the limit and the other six reach the goal (clamping alone would stop short)."""
    q = torch.tensor(panda.HOME, dtype=torch.float64) + torch.tensor([0.3, 0.2, -0.2, 0.3, 0.4, 0, 0.4])
    q[5] = panda.UPPER[5] - 0.05
    beyond = q.clone()
    beyond[5] = panda.UPPER[5] + 0.03
    ramp = torch.linspace(0, 1, HORIZON, dtype=torch.float64)[:, None]
    poses = kinematics.fk_pose((q + (beyond - q) * ramp)[None])
    refined = refine(q.expand(1, HORIZON, 7).clone(), poses)
    translation, rotation = goal_error(refined, poses[:, -1])
    assert (refined[..., 5] <= panda.UPPER[5]).all()
    assert translation.item() < 2e-3 and np.degrees(rotation.item()) < 0.5


def test_refinement_smooths_a_wobbling_sample_so_it_executes_at_speed():
    """Diffuser samples wobble from waypoint to waypoint (here 2 mm and 0.03 rad, alternating). Timed
    as they are, every wobble is a turn the arm slows for; refined from the smoothed samples, the
    path takes about as long as the clean one and still ends on the goal."""
    from hdp_motion.timing import time_parameterize
    q0 = torch.tensor(panda.HOME, dtype=torch.float64)
    ramp = torch.linspace(0, 1, HORIZON, dtype=torch.float64)[:, None]
    truth = (q0 + torch.tensor([0.4, 0.3, -0.3, 0.4, 0.2, -0.3, 0.5], dtype=torch.float64) * ramp)[None]
    wobble = torch.tensor([(-1.0) ** t for t in range(HORIZON)], dtype=torch.float64)[None, :, None]
    wobble[:, [0, -1]] = 0
    poses = kinematics.fk_pose(truth)
    poses[..., :3] += 0.002 * wobble
    sampled = truth + 0.03 * wobble

    def duration(joints):
        return time_parameterize(joints[0].numpy(), 0.5)[-1]
    smoothed, raw = refine(sampled, poses), refine(sampled, poses, smoothing=0)
    assert duration(smoothed) < 1.3 * duration(truth) and duration(raw) > 2 * duration(truth)
    translation, rotation = goal_error(smoothed, poses[:, -1])
    assert translation.item() < 1e-3 and np.degrees(rotation.item()) < 0.5
    assert torch.equal(smoothed[:, 0], truth[:, 0])
    on_path = torch.linalg.norm(kinematics.fk_pose(smoothed[0])[:, :3] - kinematics.fk_pose(truth[0])[:, :3], dim=-1)
    assert on_path.max() < 2e-3


def test_a_waypoint_refined_into_a_joint_limit_is_refined_again_from_its_predecessor():
    """A recorded sample (open_box validation seed 911, the lid's arc, the fast sampler): each
    waypoint refined on its own, the last ends 23 cm from the goal with joints 5 and 6 at their
    limits while every other lies on its target. Refined again from its predecessor, it
    reaches the goal in the same motion."""
    from pathlib import Path
    sample = np.load(Path(__file__).parent / 'data' / 'open_box_911_lid_arc_sample.npz')
    joints, poses = torch.as_tensor(sample['joints'])[None], torch.as_tensor(sample['poses'])[None]
    refined = refine(joints, poses)
    translation, rotation = goal_error(refined, poses[:, -1])
    assert translation.item() < 1e-3 and np.degrees(rotation.item()) < 0.5
    along = torch.linalg.norm(kinematics.fk_pose(refined[0])[:, :3] - poses[0, :, :3], dim=-1)
    assert along.max() < 0.01
    assert np.abs(np.diff(refined[0].numpy(), axis=0)).max() < 0.2


def test_pose_smoothing_treats_q_and_minus_q_as_one_rotation():
    poses = kinematics.fk_pose(torch.tensor(panda.HOME, dtype=torch.float64).expand(1, 8, 7))
    flipped = poses.clone()
    flipped[:, 1::2, 3:] *= -1
    smoothed = smooth_poses(flipped, 4)
    assert torch.allclose(smoothed[..., 3:].abs(), poses[..., 3:].abs(), atol=1e-9)     # not averaged to zero


def test_conditions_canonicalise_quaternion_signs():
    request = SegmentRequest(q=panda.HOME, qd=np.zeros(7), gripper_width=0.08, gripper_open=True,
                             start_pose=np.array([0.5, 0, 1.0, 0, 0, 0.6, -0.8]),
                             goal_pose=np.array([0.5, 0.1, 1.0, 0, 0, -0.6, 0.8]), points=np.zeros((8, 3)))
    batch = conditions(request)
    assert batch['start_pose'][0, 6] > 0 and torch.dot(batch['start_pose'][0, 3:], batch['goal_pose'][0, 3:]) > 0
    assert batch['rank'].item() == 1.0


# --- checkpoints and CLI ---------------------------------------------------------------------

def test_checkpoint_round_trip_and_refusals(tmp_path):
    model = RKDiffuser(SMALL)
    path = tmp_path / 'model.pt'
    checkpoint.save(path, model, {'training_seeds': {'reach_target': [1, 2]}})
    loaded, payload = checkpoint.load_model(path)
    assert payload['training_seeds'] == {'reach_target': [1, 2]}
    for name, tensor in model.state_dict().items():
        assert torch.equal(tensor, loaded.state_dict()[name])
    (tmp_path / 'junk.pt').write_bytes(b'not a checkpoint')
    with pytest.raises(checkpoint.CheckpointError, match='not a loadable'):
        checkpoint.read(tmp_path / 'junk.pt')

    class Evil:
        def __reduce__(self):
            return (print, ('pwned',))
    torch.save({'format': checkpoint.FORMAT, 'version': checkpoint.VERSION, 'config': {}, 'model': {}, 'x': Evil()},
               tmp_path / 'evil.pt')
    with pytest.raises(checkpoint.CheckpointError):
        checkpoint.read(tmp_path / 'evil.pt')
    payload = torch.load(path, weights_only=True)
    torch.save({**payload, 'version': 1}, tmp_path / 'absolute_joints.pt')    # the joint diffuser's first form
    with pytest.raises(checkpoint.CheckpointError, match='version 1, this code reads 2'):
        checkpoint.load_model(tmp_path / 'absolute_joints.pt')
    payload['model']['pose.net.final.1.weight'] = torch.zeros(3)
    torch.save(payload, tmp_path / 'shape.pt')
    with pytest.raises(checkpoint.CheckpointError, match='wrong shape'):
        checkpoint.load_model(tmp_path / 'shape.pt')


@pytest.mark.dds
def test_validation_losses_go_into_the_curves_and_training_episodes_are_refused(episodes, tmp_path):
    from hdp_controller.train import TrainConfig, train
    segs = load_segments(episodes, n_points=64, cache_dir=tmp_path, workers=1)
    held_out = {**vars(segs), 'seed': segs.seed + 1000}          # the same segments as if never trained on
    np.savez(tmp_path / 'val.npz', **held_out)
    model_config = RKDConfig(unet_dim=8, point_features=16, point_width=8, n_points=64, diffusion_steps=10)
    train_config = TrainConfig(steps=4, batch_size=2, save_every=2, warmup_steps=1)
    quiet = lambda *a, **k: None                                  # noqa: E731
    out = train(episodes, tmp_path / 'rkd.pt', model_config, train_config, cache_dir=tmp_path,
                val_data=tmp_path / 'val.npz', log=quiet)
    columns, rows = read_curves(tmp_path / 'rkd_curves.csv')
    assert {'val_pose', 'val_joint', 'val_joint_to_pose'} <= set(columns)
    assert [r['step'] for r in rows if r['val_joint'] is not None] == [2, 4]      # at every save
    assert all(np.isfinite(r['val_pose']) and r['val_pose'] > 0 for r in rows if r['val_pose'] is not None)
    assert out.is_file()
    with pytest.raises(ValueError, match='holds training episodes'):
        train(episodes, tmp_path / 'leak.pt', model_config, train_config, cache_dir=tmp_path,
              val_data=episodes, log=quiet)


@pytest.mark.dds
def test_train_cli_runs_and_resumes(episodes, tmp_path):
    config = tmp_path / 'small.yaml'
    config.write_text('model: {unet_dim: 8, point_features: 16, point_width: 8, n_points: 64, diffusion_steps: 10}\n'
                      'train: {batch_size: 2, save_every: 2, warmup_steps: 1}\n')
    out = tmp_path / 'rkd.pt'
    options = ['--data', str(episodes), '--config', str(config), '--cache', str(tmp_path / 'cache')]
    base = [*HDP, 'train', 'low-level', '--out', str(out), *options]
    first = subprocess.run([*base, '--steps', '2'], text=True, capture_output=True, timeout=300)
    assert first.returncode == 0, first.stderr
    assert checkpoint.read(out)['training']['step'] == 2
    columns, rows = read_curves(tmp_path / 'rkd_curves.csv')           # the training curves beside it
    assert 'lr' in columns and len(columns) > 2 and [r['step'] for r in rows] == [2]
    again = subprocess.run([*base, '--steps', '2'], text=True, capture_output=True, timeout=300)
    assert again.returncode == 0 and 'resuming from' in again.stdout
    other = subprocess.run([*base, '--steps', '4'], text=True, capture_output=True, timeout=300)
    assert other.returncode != 0 and 'another configuration' in other.stderr
    resume = tmp_path / 'rkd.pt.resume'
    kept = resume.read_bytes()
    for damaged in (os.urandom(3000), kept[:len(kept) // 2]):
        resume.write_bytes(damaged)
        refused = subprocess.run([*base, '--steps', '2'], text=True, capture_output=True, timeout=300)
        assert refused.returncode == 1 and refused.stderr.strip().splitlines()[-1] == (
            f'hdp train low-level: {resume} is not a readable checkpoint (not a loadable torch file: '
            'truncated, damaged or of another format)'), refused.stderr
        assert 'Traceback' not in refused.stderr and 'weights_only' not in refused.stderr
    resume.unlink()
    fresh = subprocess.run([*base, '--steps', '4'], text=True, capture_output=True, timeout=300)
    assert fresh.returncode == 0 and checkpoint.read(out)['training']['step'] == 4
    tuned = tmp_path / 'tuned.pt'
    fine = subprocess.run([*HDP, 'train', 'low-level', '--out', str(tuned), *options, '--steps', '2',
                           '--init', str(out)],
                          text=True, capture_output=True, timeout=300)
    assert fine.returncode == 0, fine.stderr
    assert checkpoint.read(tuned)['training']['init'] == {
        'path': str(out), 'step': 4, 'wall_time_s': checkpoint.read(out)['training']['wall_time_s'],
        'training_seeds': {'open_drawer': [11], 'reach_target': [11]}}
    start = torch.load(out, weights_only=True)        # as if trained on seeds this data does not hold
    start['training_seeds'] = {'open_box': [7], 'reach_target': [11, 500]}
    torch.save(start, tmp_path / 'start.pt')
    again = subprocess.run([*HDP, 'train', 'low-level', '--out', str(tmp_path / 'tuned2.pt'), *options,
                            '--steps', '1', '--init', str(tmp_path / 'start.pt')],
                           text=True, capture_output=True, timeout=300)
    assert again.returncode == 0, again.stderr
    assert checkpoint.read(tmp_path / 'tuned2.pt')['training_seeds'] == {
        'open_box': [7], 'open_drawer': [11], 'reach_target': [11, 500]}
    mismatch = subprocess.run([*HDP, 'train', 'low-level', '--out', str(tmp_path / 'x.pt'), '--data', str(episodes),
                               '--init', str(out)],
                              text=True, capture_output=True, timeout=300)
    assert mismatch.returncode != 0 and 'another model config' in mismatch.stderr
    bad = subprocess.run([*HDP, 'train', 'low-level', '--data', str(tmp_path), '--out', str(out)],
                         text=True, capture_output=True, timeout=120)
    assert bad.returncode != 0 and 'no successful episodes' in bad.stderr
    missing = subprocess.run([*HDP, 'train', 'low-level', '--data', str(tmp_path / 'nowhere'), '--out', str(out)],
                             text=True, capture_output=True, timeout=120)
    assert missing.returncode != 0 and 'is not a directory of episodes' in missing.stderr
    assert 'Traceback' not in missing.stderr


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(('127.0.0.1', 0))
        return probe.getsockname()[1]


def _torchrun(launch: str, arguments: list, env: dict, port: int) -> list:
    """Run ``python -m hdp_tools.cli.main ARGUMENTS`` as two torchrun ranks: both in one launcher
    ('standalone'), or one per launcher, as two machines join (torchrun's c10d rendezvous; here
    both on loopback, the first launcher hosting the store). Returns the launchers' results."""
    run = [sys.executable, '-m', 'torch.distributed.run']
    command = ['-m', 'hdp_tools.cli.main', *arguments]
    if launch == 'standalone':
        return [subprocess.run([*run, '--standalone', '--nproc-per-node', '2', *command],
                               text=True, capture_output=True, timeout=120, env=env)]
    # is_host named: both launchers on one host would otherwise race to host the store.
    nodes = [[*run, '--nnodes', '2', '--nproc-per-node', '1', '--rdzv-backend', 'c10d',
              '--rdzv-endpoint', f'127.0.0.1:{port}', '--rdzv-id', f'hdp-test-{port}',
              '--rdzv-conf', f'is_host={int(host)}', *command] for host in (True, False)]
    launchers = [subprocess.Popen(node, text=True, stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env)
                 for node in nodes]
    results = []
    for node, launcher in zip(nodes, launchers):
        try:
            out, err = launcher.communicate(timeout=120)
        except subprocess.TimeoutExpired:
            launcher.kill()
            out, err = launcher.communicate()
            err += '\n(killed after 120 s)'
        results.append(subprocess.CompletedProcess(node, launcher.returncode, out, err))
    return results


@pytest.mark.dds
@pytest.mark.parametrize('launch', ['standalone', 'two_nodes'])
def test_torchrun_two_processes_train_what_one_process_trains(episodes, tmp_path, launch):
    """DDP over gloo: both ranks end with identical weights (the trainer compares their
    digests at every save and refuses to go on otherwise), and two processes of 2 samples
    match one process of the combined 4 to float rounding (gradients averaged in another order),
    whether torchrun starts both or two launchers meet by rendezvous as two machines would."""
    config = tmp_path / 'small.yaml'
    config.write_text('model: {unet_dim: 8, point_features: 16, point_width: 8, n_points: 64, diffusion_steps: 10}\n'
                      'train: {batch_size: 4, save_every: 1, warmup_steps: 1, goal_augment: 0.05}\n')
    options = ['train', 'low-level', '--data', str(episodes), '--config', str(config), '--steps', '3',
               '--cache', str(tmp_path / 'cache'), '--threads', '1']
    one = subprocess.run([*HDP, *options, '--out', str(tmp_path / 'one.pt')],
                         text=True, capture_output=True, timeout=300)
    assert one.returncode == 0, one.stderr
    env = {**os.environ, 'MASTER_ADDR': '127.0.0.1', 'GLOO_SOCKET_IFNAME': 'lo', 'OMP_NUM_THREADS': '1'}
    for launcher in _torchrun(launch, [*options, '--out', str(tmp_path / 'two.pt')], env, free_port()):
        assert launcher.returncode == 0, launcher.stderr[-3000:]
    single, split = checkpoint.read(tmp_path / 'one.pt'), checkpoint.read(tmp_path / 'two.pt')
    assert (single['training']['processes'], split['training']['processes']) == (1, 2)
    assert single['model'].keys() == split['model'].keys()
    worst = max(float((single['model'][k].float() - split['model'][k].float()).abs().max()) for k in single['model'])
    assert worst < 1e-4, f'two processes differ from one by {worst}'
    moved = max(float((single['model'][k].float() - RKDiffuser(RKDConfig(
        unet_dim=8, point_features=16, point_width=8, n_points=64, diffusion_steps=10)).state_dict()[k].float()
        ).abs().max()) for k in single['model'] if single['model'][k].is_floating_point())
    assert moved > 100 * worst       # three steps moved the weights far more than the two runs differ
    assert (tmp_path / 'one_curves.csv').is_file() and (tmp_path / 'two_curves.csv').is_file()


@pytest.mark.dds
def test_sample_quality_measures_a_perfect_sampler_as_perfect_and_refuses_training_seeds(episodes, segments,
                                                                                       tmp_path):
    from hdp_eval.sample_quality import measure, summary

    class Demonstrated:           # "samples" the demonstrations themselves: no goal error, nothing to refine
        done = 0

        def sample(self, batch, *args):
            rows = slice(self.done, self.done + len(batch['q']))
            self.done += len(batch['q'])
            return {'joints': torch.from_numpy(segments.joints[rows]), 'poses': torch.from_numpy(segments.poses[rows])}

        def parameters(self):
            yield torch.zeros(1)

    rows = measure(Demonstrated(), segments, 'ddim', 5, 1.0, refine_steps=5, batch_size=3, seed=0)
    figures = summary(rows)
    assert len(rows) == len(segments) and figures['within'] == 100.0
    assert figures['goal_cm'] < 0.01 and figures['goal_deg'] < 0.1 and figures['refine_moves_cm'] < 0.5
    model = RKDiffuser(SMALL).eval()
    checkpoint.save(tmp_path / 'other.pt', model, {'training_seeds': {'reach_target': [12]}})
    checkpoint.save(tmp_path / 'same.pt', model, {'training_seeds': {'reach_target': [11]}})
    base = [*HDP, 'eval', 'samples', '--data', str(episodes), '--cache', str(tmp_path / 'cache'), '--refine-steps', '2']
    ran = subprocess.run([*base, '--checkpoint', str(tmp_path / 'other.pt'), '--json', str(tmp_path / 's.json')],
                         text=True, capture_output=True, timeout=300)
    assert ran.returncode == 0, ran.stderr
    assert '| open_drawer |' in ran.stdout and '| reach_target |' in ran.stdout and '| **all** |' in ran.stdout
    untrained = summary(json.loads((tmp_path / 's.json').read_text())['segments'])
    assert untrained['goal_cm'] > 1.0          # an untrained joint diffuser misses: the measure can fail
    refused = subprocess.run([*base, '--checkpoint', str(tmp_path / 'same.pt')], text=True, capture_output=True,
                             timeout=300)
    assert refused.returncode != 0 and 'was trained on episodes' in refused.stderr and 'reach_target 11' in refused.stderr


# --- policies, trajectories, figures --------------------------------------------------------

def _request(q=panda.HOME):
    from hdp_motion.kinematics import fk_pose as fk
    start = fk(torch.tensor(q, dtype=torch.float32)).numpy()
    goal = fk(torch.tensor(np.asarray(q) + [0.2, 0.1, 0.0, 0.2, 0.0, -0.1, 0.3], dtype=torch.float32)).numpy()
    return SegmentRequest(q=np.asarray(q), qd=np.zeros(7), gripper_width=0.08, gripper_open=True, start_pose=start,
                          goal_pose=goal, points=np.random.default_rng(0).uniform([0.3, -0.2, 0.8], [0.6, 0.2, 1.0],
                                                                                  (64, 3)))


def test_learned_policies_from_a_checkpoint(tmp_path):
    from hdp_controller.policy import load_policy
    path = tmp_path / 'small.pt'
    checkpoint.save(path, RKDiffuser(SMALL), {'training_seeds': {'reach_target': [0]}})
    request = _request()
    rkd = load_policy('rkd', path, 'ddim', steps=2)
    plan = rkd.plan(request)
    # Untrained, yet the refinement lands the last waypoint on the NBP, inside the limits.
    assert plan.ok and plan.joints.shape == (HORIZON, 7) and np.allclose(plan.joints[0], request.q, atol=1e-5)
    assert plan.extras['goal_error_m'] < 2e-3 and panda.within_limits(plan.joints)
    assert rkd.training_seeds == {'reach_target': [0]}
    joint = load_policy('joint', path, 'ddim', steps=2).plan(request)
    assert joint.ok and panda.within_limits(joint.joints)
    # Untrained too, goal guidance lands the joint sample's end on the NBP; the raw sample does not.
    guided = load_policy('joint_guided', path, 'ddim', steps=2)
    plan = guided.plan(request)
    assert guided.name == 'joint_guided' and plan.ok and panda.within_limits(plan.joints)
    assert plan.extras['goal_error_m'] < 5e-3 < joint.extras['goal_error_m']
    # The fast sampler skips classifier-free guidance (one encoding per sample, not two);
    # the full one guides. Both refine alike.
    for sampler, encodings in (('ddim', 1), ('ddpm', 2)):
        policy = load_policy('rkd', path, sampler, steps=2)
        calls = []
        policy.model.encoder.register_forward_hook(lambda *_: calls.append(1))
        policy.plan(request)
        assert len(calls) == encodings and policy.refine_steps == 50
    tuned = load_policy('rkd', path, 'ddim', steps=3, guidance=1.5, refine_steps=7)
    assert (tuned.steps, tuned.guidance, tuned.refine_steps) == (3, 1.5, 7)
    with pytest.raises(ValueError, match='unknown low-level method'):
        load_policy('magic', path)


@pytest.mark.parametrize('errors_m, from_start_m, draws, kept', [
    ([0.001], None, 1, 0.001),                  # refined onto the NBP: one draw
    ([0.2, 0.05, 0.001], None, 3, 0.001),       # stalled twice, then converged
    ([0.2, 0.05, 0.1], 0.002, 3, 0.002),        # never converged: tracked from the start, which is nearer
    ([0.2, 0.05, 0.1], 0.3, 3, 0.05),           # tracking no nearer: the nearest of the three draws
])
def test_rkd_draws_again_while_refinement_leaves_the_end_off_the_nbp(tmp_path, errors_m, from_start_m, draws, kept):
    from hdp_controller.low_level import PlanResult
    from hdp_controller.policy import load_policy
    path = tmp_path / 'small.pt'
    checkpoint.save(path, RKDiffuser(SMALL), {'training_seeds': {}})

    def planned(error_m, **extras):
        return PlanResult(np.zeros((2, 7)), extras={'goal_error_m': error_m, 'goal_error_deg': 1.0, **extras})

    for method in ('rkd', 'rkd_redraw', 'rkd_single'):
        policy = load_policy(method, path, 'ddim', steps=2)
        queue, from_start = list(errors_m), []
        policy._plan_once = lambda request, goal: planned(queue.pop(0))
        policy._from_start = lambda request, nearest, goal: from_start.append(1) or planned(from_start_m)
        plan = policy.plan(_request())
        assert policy.name == method
        if method == 'rkd_single':   # the paper's single draw, refined once from its own sample
            assert plan.extras['draws'] == 1 and plan.extras['goal_error_m'] == errors_m[0] and not from_start
            continue
        assert plan.extras['draws'] == draws
        if method == 'rkd_redraw':   # the nearest draw, never tracked
            assert plan.extras['goal_error_m'] == min(errors_m) and not from_start
            continue
        assert plan.extras['goal_error_m'] == kept
        assert len(from_start) == (from_start_m is not None)
        assert plan.extras['from_start'] == (kept == from_start_m)


def test_rkd_tracked_from_the_start_reaches_a_pose_path_its_joint_sample_did_not(tmp_path):
    """The fallback of a segment whose every draw stalled: the nearest draw's poses, tracked from
    the arm's own configuration, reach the NBP inside the limits."""
    from hdp_controller.low_level import PlanResult
    from hdp_controller.policy import conditions, load_policy
    from hdp_motion.kinematics import fk_pose as fk
    path = tmp_path / 'small.pt'
    checkpoint.save(path, RKDiffuser(SMALL), {'training_seeds': {}})
    policy = load_policy('rkd', path, 'ddim', steps=2)
    request = _request()
    goal_q = np.asarray(panda.HOME) + [0.2, 0.1, 0.0, 0.2, 0.0, -0.1, 0.3]       # _request's goal
    poses = fk(torch.tensor(np.linspace(panda.HOME, goal_q, HORIZON), dtype=torch.float32)).numpy()
    stalled = PlanResult(np.zeros((HORIZON, 7)), poses=poses, extras={'goal_error_m': 0.2, 'goal_error_deg': 40.0,
                                                                      'draws': 3})
    plan = policy._from_start(request, stalled, torch.as_tensor(conditions(request)['goal_pose']))
    assert plan.extras['draws'] == 3 and plan.extras['goal_error_m'] < 2e-3 and plan.extras['goal_error_deg'] < 0.5
    assert np.allclose(plan.joints[0], request.q, atol=1e-5) and panda.within_limits(plan.joints)
    assert np.abs(np.diff(plan.joints, axis=0)).max() < 0.1          # one motion, no configuration jump


def test_an_evaluation_episode_draws_the_same_noise_whatever_ran_before_it(tmp_path):
    from hdp_controller.baselines import PlannerPolicy
    from hdp_controller.low_level import start_episode
    from hdp_controller.policy import load_policy
    path = tmp_path / 'small.pt'
    checkpoint.save(path, RKDiffuser(SMALL), {'training_seeds': {}})
    request = _request()
    for method in ('joint', 'pose_ik'):
        policy = load_policy(method, path, 'ddim', steps=2)
        sample = (lambda: policy.plan(request).joints) if method == 'joint' else (lambda: policy.pose_sampler(request))
        start_episode(policy, 1000)
        first = sample()
        sample()                                   # another segment, or another episode's
        start_episode(policy, 1000)
        assert np.array_equal(sample(), first)
        start_episode(policy, 1001)
        assert not np.array_equal(sample(), first)
    start_episode(PlannerPolicy(), 1000)           # nothing to reseed: seeded per request


def test_joint_trajectory_is_timed_within_limits_and_refuses_bad_waypoints():
    from hdp_controller.trajectory import TrajectoryError, joint_trajectory
    from hdp_msgs_py.conversions import parse_joint_trajectory
    path = np.linspace(panda.HOME, panda.HOME + 0.5, 20)
    names, positions, times, velocities = parse_joint_trajectory(joint_trajectory(panda.HOME, path))
    assert list(names) == list(panda.ARM_JOINTS) and np.allclose(positions[0], panda.HOME)
    speed = np.abs(np.diff(positions, axis=0)) / np.diff(times)[:, None]
    assert np.all(speed <= panda.VELOCITY_LIMITS + 1e-6) and np.all(np.abs(velocities) <= panda.VELOCITY_LIMITS)
    beyond = path.copy()
    beyond[-1, 3] = panda.UPPER[3] + 0.1
    with pytest.raises(TrajectoryError, match='outside the joint position limits'):
        joint_trajectory(panda.HOME, beyond)
    with pytest.raises(TrajectoryError, match='finite'):
        joint_trajectory(panda.HOME, np.full((3, 7), np.nan))


def test_an_arm_read_a_hair_beyond_a_limit_gets_a_trajectory_the_bridge_accepts():
    """The arm pressed on a limit reads slightly past it; point 0 (the current joints) goes out
    on the limit, which sim_bridge_node (as joint_trajectory_controller) accepts."""
    from hdp_controller.trajectory import joint_trajectory
    from hdp_sim_bridge.trajectory_follower import accept
    current = panda.HOME.copy()
    current[4] = panda.UPPER[4] + 1e-7
    goal = np.linspace(current, np.concatenate([panda.HOME[:4], [2.5], panda.HOME[5:]]), 10)
    msg = joint_trajectory(current, goal[1:])
    accept(msg, 0.0, current)           # raised 'panda_joint5 = 2.8973 rad is above its limit' before


def test_a_plan_that_starts_where_a_pressed_arm_reads_is_accepted_onto_the_limit():
    """A hinge pushes joint 7 2.3 mrad past its limit; a plan tracked from there (refine.track
    starts at the arm's reading) goes out on the limit. Further past than the arm is, it is refused."""
    from hdp_controller.trajectory import PRESSED_TOLERANCE, TrajectoryError, joint_trajectory
    from hdp_msgs_py.conversions import parse_joint_trajectory
    current = panda.HOME.copy()
    current[6] = panda.UPPER[6] + 0.0023
    plan = np.linspace(current, np.concatenate([panda.HOME[:6], [2.0]]), 10)
    positions = parse_joint_trajectory(joint_trajectory(current, plan))[1]
    assert positions[:, 6].max() == panda.UPPER[6]
    further = plan.copy()
    further[3, 6] = panda.UPPER[6] + 0.005
    with pytest.raises(TrajectoryError, match=r'0.0050 rad outside .*joint 7'):
        joint_trajectory(current, further)
    # An arm reading far past a limit is a fault, not a press: nothing is planned from it.
    current[6] = panda.UPPER[6] + 2 * PRESSED_TOLERANCE
    with pytest.raises(TrajectoryError, match='joint 7'):
        joint_trajectory(current, np.linspace(current, panda.HOME, 10))


def test_fig4_plot_writes_a_png(tmp_path):
    from hdp_eval.figures import plot
    line = np.linspace([0.4, 0.0, 1.0], [0.6, 0.1, 0.9], HORIZON)
    segment = {'poses': line, 'joint_fk': line + 0.01, 'refined_fk': line, 'planner_fk': line[::4]}
    plot(segment, 'test', tmp_path / 'fig.png')
    assert (tmp_path / 'fig.png').read_bytes()[:8] == b'\x89PNG\r\n\x1a\n'


def test_a_robot_types_limits_refuse_refine_and_time_what_goes_to_it():
    """The FR3's joint 6 cannot go below 0.5445 rad (the Panda's to -0.0175): a path there is
    fine for a Panda and refused for an FR3, naming the joint; refinement keeps inside the FR3's."""
    from hdp_controller.trajectory import TrajectoryError, joint_trajectory
    fr3 = panda.limits_for('fr3')
    low_wrist = np.concatenate([panda.HOME[:5], [0.2], panda.HOME[6:]])
    path = np.linspace(panda.HOME, low_wrist, 10)[1:]
    joint_trajectory(panda.HOME, path)                                    # a Panda may
    with pytest.raises(TrajectoryError, match=r'joint 6: \[0.5445, 4.5169\]'):
        joint_trajectory(panda.HOME, path, limits=fr3)
    joints = torch.tensor(np.linspace(panda.HOME, low_wrist, HORIZON)[None], dtype=torch.float32)
    refined = refine(joints, kinematics.fk_pose(joints), steps=10, limits=fr3)[0, 1:].numpy()
    assert np.all(refined >= fr3.lower - 1e-6) and np.all(refined <= fr3.upper + 1e-6)
    joint_trajectory(panda.HOME, refined, limits=fr3)                     # accepted as refined
