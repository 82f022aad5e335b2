"""The high-level next-best-pose agent: language, voxels, rotations, augmentation, training, checkpoints, CLI.

Fast and single-threaded: the networks here are tiny versions of the real one.
"""

import dataclasses
import inspect
import json
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from hdp_msgs_py.conversions import Intrinsics, quat_to_matrix
from hdp_learning.curves import read_curves
from hdp_data.workspace import WORKSPACE
from hdp_planner import checkpoint, language, rotations, voxels
from hdp_planner.agent import NextBestPoseAgent
from hdp_planner.dataset import KeyframeDataset, draw_move
from hdp_planner.model import ModelConfig, NextBestPoseNet, proprio_vector
from hdp_planner.train import TrainConfig, losses, train, training_batch
from hdp_sim_bridge.tasks import TASKS

pytestmark = pytest.mark.unit

torch.set_num_threads(1)

TINY = dict(grid_size=8, channels=(4, 8, 8), language_dim=16, head_hidden=32)
HDP = [sys.executable, '-m', 'hdp_tools.cli.main']


@pytest.fixture(scope='module')
def episodes(tmp_path_factory):
    """One recorded reach_target episode (seed 21), small images: training data for the CLI."""
    data = tmp_path_factory.mktemp('agent') / 'episodes'
    collected = subprocess.run([*HDP, 'collect', '--tasks', 'reach_target', '--episodes', '1', '--seed-start', '21',
                                '--out', str(data), '--width', '64', '--height', '48'],
                               capture_output=True, text=True, timeout=300)
    assert collected.returncode == 0, collected.stderr
    return data


def tiny_model(seed=0) -> NextBestPoseNet:
    torch.manual_seed(seed)
    return NextBestPoseNet(ModelConfig(vocabulary=tuple(language.task_vocabulary()), **TINY))


def synthetic_episode(rng, task='open_drawer', samples=2, seed=0) -> dict:
    """An episode's samples as episode_samples returns them: a box of points per observation."""
    clouds = [rng.uniform(WORKSPACE[0] + 0.1, WORKSPACE[1] - 0.1, (200, 3)).astype(np.float32) for _ in range(samples)]
    quat = rotations.euler_to_quat(rng.uniform(-1, 1, (samples, 3)))
    return {'xyz': np.concatenate(clouds), 'rgb': rng.integers(0, 256, (200 * samples, 3), dtype=np.uint8),
            'starts': np.arange(samples + 1) * 200, 'joint_positions': np.zeros((samples, 7)),
            'gripper_open': np.ones(samples, bool), 'target_xyz': np.stack([c[0] for c in clouds]).astype(np.float64),
            'target_quat': quat, 'target_open': np.arange(samples) % 2 == 0, 'task': np.array(task),
            'variation': np.array(1), 'seed': np.array(seed)}


# --- language -----------------------------------------------------------------------

def test_tokenizer_lowercases_strips_punctuation_and_maps_unknown_words_to_unk():
    tokenizer = language.Tokenizer(['open', 'the', 'drawer'], max_words=6)
    ids = tokenizer.encode(['Open the FRIDGE!', ''])
    open_, the = tokenizer.ids['open'], tokenizer.ids['the']
    assert ids[0].tolist() == [open_, the, 1, 0, 0, 0]
    assert ids[1].tolist() == [1, 0, 0, 0, 0, 0]          # no words: a lone <unk>
    assert tokenizer.encode(['the ' * 10]).shape == (1, 6)


def test_vocabulary_covers_every_phrasing_and_variation():
    tokenizer = language.Tokenizer(language.task_vocabulary())
    for cls in TASKS.values():
        for template in cls.phrasings:
            for variation in cls.variations:
                assert 1 not in tokenizer.encode([template.replace('{}', variation)])[0].tolist()


def test_heldout_phrasings_are_never_drawn_for_training():
    rng = np.random.default_rng(0)
    for name, cls in TASKS.items():
        (heldout,) = language.heldout_phrasings(name)
        assert heldout == cls.phrasings[-1]
        assert heldout not in language.training_phrasings(name)
        variation = len(cls.variations) - 1
        task = cls()
        task.variation = variation
        heldout_text = task.instruction(rng, (heldout,))
        drawn = {language.instruction(name, variation, language.training_phrasings(name), rng) for _ in range(100)}
        assert heldout_text not in drawn and len(drawn) == len(cls.phrasings) - 1
    dataset = KeyframeDataset([synthetic_episode(rng)])
    bottom_heldout = 'slide the middle drawer open'
    assert all(dataset.item(0, rng).instruction != bottom_heldout for _ in range(50))
    assert dataset.item(0, rng, heldout=True).instruction == bottom_heldout


def test_word_encoder_shapes_and_padding():
    encoder = language.WordEncoder(language.task_vocabulary(), dim=16).eval()
    tokens, pooled = encoder(['open the top drawer', 'open box'])
    assert tokens.shape == (2, language.MAX_WORDS, 16) and pooled.shape == (2, 16)
    assert torch.all(tokens[1, 2:] == 0)


# --- voxels ------------------------------------------------------------------------

def test_point_lands_in_its_voxel_with_mean_colour_and_position():
    lower, upper = voxels.workspace_bounds(1)
    edge = (upper - lower)[0] / 16
    corner = lower[0] + torch.tensor([3, 5, 7]) * edge
    xyz = torch.stack([corner + 0.25 * edge, corner + 0.75 * edge])
    rgb = torch.tensor([[1.0, -1.0, -1.0], [-1.0, -1.0, 1.0]])
    grid = voxels.voxelise(xyz, rgb, torch.zeros(2, dtype=torch.long), lower, upper)
    assert grid.shape == (1, voxels.CHANNELS, 16, 16, 16)
    cell = grid[0, :, 3, 5, 7]
    assert cell[6] == 1 and grid[0, 6].sum() == 1                          # one occupied voxel
    assert torch.allclose(cell[3:6], torch.tensor([0.0, -1.0, 0.0]))       # mean colour
    centre = (corner + 0.5 * edge - lower[0]) / (upper - lower)[0] * 2 - 1
    assert torch.allclose(cell[:3], centre, atol=1e-6)                     # mean position, normalised
    assert torch.allclose(cell[7:], torch.tensor([3, 5, 7]) / 15 * 2 - 1)  # voxel index
    index, offset = voxels.voxel_of(xyz[:1], lower, upper)
    assert index.item() == (3 * 16 + 5) * 16 + 7
    assert torch.allclose(voxels.position_of(index, offset, lower, upper), xyz[:1], atol=1e-6)


def test_points_outside_the_grid_are_dropped_and_batches_kept_apart():
    centre = torch.tensor([[0.5, 0.0, 1.0], [0.6, 0.1, 1.0]])
    lower, upper = voxels.fine_bounds(centre)
    xyz = torch.tensor([[0.5, 0.0, 1.0], [0.9, 0.0, 1.0], [0.6, 0.1, 1.0]])
    grid = voxels.voxelise(xyz, torch.zeros(3, 3), torch.tensor([0, 0, 1]), lower, upper)
    assert grid[:, 6].sum(dim=(1, 2, 3)).tolist() == [1.0, 1.0]


def test_camera_points_unproject_with_their_colours():
    intrinsics = Intrinsics(100.0, 100.0, 1.0, 1.0, 3, 3)
    depth = np.zeros((3, 3), np.float32)
    depth[1, 1], depth[0, 2] = 2.0, 1.0
    rgb = np.zeros((3, 3, 3), np.uint8)
    rgb[1, 1], rgb[0, 2] = (255, 0, 0), (0, 255, 0)
    camera_to_world = np.eye(4)
    camera_to_world[:3, 3] = (0.5, 0.0, 1.0)
    xyz, colours = voxels.camera_points(rgb, depth, intrinsics, camera_to_world)
    assert np.allclose(xyz, [[0.51, -0.01, 2.0], [0.5, 0.0, 3.0]])
    assert colours.tolist() == [[0, 255, 0], [255, 0, 0]]


# --- rotations and augmentation ---------------------------------------------------------

def test_rotation_bins_round_trip():
    rng = np.random.default_rng(0)
    bins = np.stack([rng.integers(0, 72, 500), rng.integers(19, 54, 500), rng.integers(0, 72, 500)], -1)
    assert np.array_equal(rotations.quat_to_bins(rotations.bins_to_quat(bins)), bins)
    quat = rotations.euler_to_quat(rng.uniform([-math.pi, -1.4, -math.pi], [math.pi, 1.4, math.pi], (500, 3)))
    error = rotations.angle_between(rotations.bins_to_quat(rotations.quat_to_bins(quat)), quat)
    assert np.degrees(error).max() <= 3 * 2.5 + 1e-6      # at most half a bin per axis, composed
    assert np.degrees(error).mean() < 3.0


def test_yaw_quat_is_a_world_frame_rotation():
    quat = rotations.euler_to_quat([0.3, -0.7, 1.1])
    turned = rotations.yaw_quat(quat, 0.4)
    rz = np.array([[math.cos(0.4), -math.sin(0.4), 0], [math.sin(0.4), math.cos(0.4), 0], [0, 0, 1]])
    assert np.allclose(quat_to_matrix(turned), rz @ quat_to_matrix(quat))


@pytest.mark.parametrize('seed', range(5))
def test_augmentation_keeps_target_and_orientation_on_the_points(seed):
    rng = np.random.default_rng(seed)
    target = np.array([0.55, 0.1, 0.95])
    quat = rotations.euler_to_quat([2.4, 0.6, -1.2])          # a pitched grasp
    axes = quat_to_matrix(quat)
    # Markers at the target and 5 cm along the hand's x and z axes, among other points.
    markers = np.stack([target, target + 0.05 * axes[:, 0], target + 0.05 * axes[:, 2]])
    cloud = np.concatenate([markers, rng.uniform(WORKSPACE[0], WORKSPACE[1], (50, 3))]).astype(np.float32)
    move = draw_move(target, rng)
    moved, new_target, new_quat = move.points(cloud), move.points(target[None])[0], move.orientations(quat)
    new_axes = quat_to_matrix(new_quat)
    assert np.allclose(moved[0], new_target, atol=1e-5)
    assert np.allclose(moved[1], new_target + 0.05 * new_axes[:, 0], atol=1e-5)
    assert np.allclose(moved[2], new_target + 0.05 * new_axes[:, 2], atol=1e-5)
    assert np.allclose(moved[:, 2] - cloud[:, 2], moved[0, 2] - cloud[0, 2], atol=1e-5)   # only a yaw
    assert np.all(new_target > WORKSPACE[0]) and np.all(new_target < WORKSPACE[1])


# --- training, checkpoints, agent --------------------------------------------------------

def test_a_few_steps_reduce_the_loss():
    rng = np.random.default_rng(0)
    dataset = KeyframeDataset([synthetic_episode(rng, 'open_drawer', seed=5), synthetic_episode(rng, 'pick_up_cup'),
                               synthetic_episode(rng, 'open_drawer', seed=2)])
    assert dataset.training_seeds() == {'open_drawer': [2, 5], 'pick_up_cup': [0]}
    model = tiny_model()
    optimizer = torch.optim.AdamW(model.parameters(), lr=3e-3)
    items = [dataset.item(i, rng) for i in range(len(dataset))]
    batch = training_batch(items, model.config, np.random.default_rng(1))
    history = []
    for _ in range(40):
        loss = losses(model, batch)['total']
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        history.append(loss.item())
    assert history[-1] < 0.6 * history[0]


def test_checkpoint_round_trip_and_refusals(tmp_path):
    model = tiny_model().eval()
    path = tmp_path / 'agent.pt'
    checkpoint.save(path, model, torch.optim.AdamW(model.parameters()), 7, {'seed': 0}, {},
                    {'reach_target': [3, 4]})
    raw = torch.load(path, weights_only=True)
    assert raw['step'] == 7 and raw['config']['model']['channels'] == [4, 8, 8]
    loaded, stored = checkpoint.load_model(path)
    assert stored['step'] == 7 and NextBestPoseAgent.from_checkpoint(path).training_seeds == {'reach_target': [3, 4]}
    for key, value in model.state_dict().items():
        assert torch.equal(value, loaded.state_dict()[key])

    truncated = tmp_path / 'truncated.pt'
    truncated.write_bytes(path.read_bytes()[:2000])
    with pytest.raises(checkpoint.CheckpointError, match='not a readable checkpoint'):
        checkpoint.load(truncated)
    raw['config']['model']['channels'] = [4, 8, 16]
    torch.save(raw, tmp_path / 'mismatch.pt')
    with pytest.raises(checkpoint.CheckpointError, match='do not match'):
        checkpoint.load_model(tmp_path / 'mismatch.pt')
    raw['config']['model']['channels'] = [4, 8, 8]
    raw['training_seeds'] = {'reach_target': ['3']}
    torch.save(raw, tmp_path / 'bad_seeds.pt')
    with pytest.raises(checkpoint.CheckpointError, match='training_seeds'):
        checkpoint.load(tmp_path / 'bad_seeds.pt')
    torch.save({'weights': torch.zeros(3)}, tmp_path / 'other.pt')
    with pytest.raises(checkpoint.CheckpointError, match='is not a'):
        checkpoint.load(tmp_path / 'other.pt')


@pytest.mark.dds
def test_train_continues_refuses_other_options_and_fine_tunes_with_the_union_of_seeds(episodes, tmp_path):
    data = episodes
    config = ModelConfig(vocabulary=tuple(language.task_vocabulary()), **TINY)
    options = dict(batch=2, model_config=config, cache=tmp_path / 'cache', save_every=1, log=lambda _: None,
                   progress=False)
    out = tmp_path / 'agent.pt'
    train(data, out, steps=2, **options)
    assert checkpoint.load(out)['step'] == 2 and checkpoint.load(out)['training_seeds'] == {'reach_target': [21]}
    columns, rows = read_curves(tmp_path / 'agent_curves.csv')        # the training curves beside it
    assert {'lr', 'total'} <= set(columns) and [r['step'] for r in rows] == [2]
    logged = []
    train(data, out, steps=2, **{**options, 'log': logged.append})
    assert 'continuing' in logged[0] and 'from step 2' in logged[0]
    with pytest.raises(checkpoint.CheckpointError, match='train.steps: 2 -> 3'):
        train(data, out, steps=3, **options)

    start = checkpoint.load(out)                      # as if trained on more seeds than this data holds
    start['training_seeds'] = {'reach_target': [21, 500], 'open_box': [7]}
    torch.save(start, tmp_path / 'start.pt')
    tuned = tmp_path / 'tuned.pt'
    train(data, tuned, steps=1, **options, init=tmp_path / 'start.pt')
    stored = checkpoint.load(tuned)
    assert stored['training_seeds'] == {'open_box': [7], 'reach_target': [21, 500]}
    assert stored['config']['train']['init'] == {'path': str(tmp_path / 'start.pt'), 'step': 2}
    assert torch.equal(stored['optimizer']['state'][0]['step'], torch.tensor(1.0))    # a fresh optimiser
    with pytest.raises(checkpoint.CheckpointError, match='train.init'):
        train(data, tuned, steps=1, **options)                                        # continued without --init
    other = ModelConfig(vocabulary=tuple(language.task_vocabulary()), **{**TINY, 'head_hidden': 16})
    with pytest.raises(checkpoint.CheckpointError, match='another model config'):
        train(data, tmp_path / 'x.pt', steps=1, **{**options, 'model_config': other}, init=out)


@pytest.mark.parametrize('name', ['hdp_nbp_agent', 'hdp_nbp_agent_11tasks'])
def test_train_config_defaults_are_train_defaults_and_the_released_recipe_is_the_release(name):
    """TrainConfig (the --config "train:" section) defaults to what train() and the flags did before it;
    config/NAME.yaml rebuilds models/NAME.pt's network and hyper-parameters (the vocabulary is
    today's task phrasings', which have grown since the release's six tasks)."""
    from hdp_learning.config import load_sections
    defaults = {name: p.default for name, p in inspect.signature(train).parameters.items()}
    assert {f.name: defaults[f.name] for f in dataclasses.fields(TrainConfig)} == vars(TrainConfig())
    root = Path(__file__).resolve().parents[1]
    configs = load_sections(root / f'src/hdp_planner/config/{name}.yaml', {'model': ModelConfig, 'train': TrainConfig},
                            defaults={'model': {'vocabulary': tuple(language.task_vocabulary())}})
    released = checkpoint.load(root / f'models/{name}.pt')['config']
    stored = ModelConfig.from_dict(released['model'])
    assert configs['model'] == ModelConfig(**{**vars(stored), 'vocabulary': configs['model'].vocabulary})
    assert {k: released['train'][k] for k in ('steps', 'batch', 'lr', 'seed')} == {
        'steps': 12000, 'batch': 16, 'lr': 5e-4, 'seed': 0} == {
        k: getattr(configs['train'], k) for k in ('steps', 'batch', 'lr', 'seed')}


@pytest.mark.dds
def test_train_cli_config_unknown_keys_and_bad_values_fail_with_one_line(tmp_path):
    config = tmp_path / 'agent.yaml'
    base = [*HDP, 'train', 'high-level', '--data', str(tmp_path), '--out', str(tmp_path / 'a.pt'), '--config',
            str(config)]
    for text, expected in [
            ('model: {grid_size: 8, channel: [4, 8, 8]}\n',
             f'hdp train high-level: bad configuration: {config}: model: unknown key channel; known: vocabulary, '
             'grid_size, channels, language_dim, max_words, fine_half_extent, head_hidden, language_encoder, proprio, '
             'language_noise'),
            ('train: {steps: 2, batch_size: 4}\n',
             f'hdp train high-level: bad configuration: {config}: train: unknown key batch_size; known: steps, '
             'batch, lr, seed, val_every, save_every, depth_augmentation, extrinsic_augmentation_mm, '
             'extrinsic_augmentation_deg'),
            ('optimiser: {lr: 0.1}\n',
             f'hdp train high-level: bad configuration: {config}: unknown section optimiser; known: model, train'),
            ('train: {lr: 5e-4}\n',
             f"hdp train high-level: bad configuration: {config}: train.lr: expected a number, got '5e-4' "
             '(YAML reads 5e-4 as a string: write 0.0005 or 5.0e-4)'),
            ('model: {language_encoder: bert}\n',
             f"hdp train high-level: bad configuration: {config}: model: language_encoder 'bert' is not one of "
             "('words', 'minilm')"),
            ('train: {save_every: 0}\n',
             'hdp train high-level: steps, batch, val_every and save_every must be >= 1 and lr > 0')]:
        config.write_text(text)
        refused = subprocess.run(base, capture_output=True, text=True, timeout=120)
        assert refused.returncode != 0 and refused.stderr.strip() == expected, refused.stderr


@pytest.mark.dds
def test_torchrun_two_processes_train_what_one_process_trains(episodes, tmp_path):
    """DDP over gloo: both ranks end with identical weights (the trainer compares their digests
    at every save and refuses to go on otherwise; the checkpoint records the digest), and two
    processes of 2 samples match one process of the combined 4 to float rounding, except in the
    parameters the loss does not depend on (below). Also: --config with flags over it, and the
    resolved config printed as JSON."""
    config = tmp_path / 'tiny.yaml'
    config.write_text('model: {grid_size: 8, channels: [4, 8, 8], language_dim: 16, head_hidden: 32}\n'
                      'train: {batch: 2, save_every: 1, lr: 0.4}\n')       # a large lr: warmup starts at lr / 200
    options = ['train', 'high-level', '--data', str(episodes), '--config', str(config), '--steps', '3',
               '--batch', '4', '--cache', str(tmp_path / 'cache'), '--threads', '1']
    one = subprocess.run([*HDP, *options, '--out', str(tmp_path / 'one.pt')], text=True, capture_output=True,
                         timeout=300)
    assert one.returncode == 0, one.stderr
    resolved = json.loads(one.stdout.splitlines()[0])
    assert resolved['train'] == {'steps': 3, 'batch': 4, 'lr': 0.4, 'seed': 0, 'val_every': 1000, 'save_every': 1,
                                 'depth_augmentation': 0.0, 'extrinsic_augmentation_mm': 0.0,
                                 'extrinsic_augmentation_deg': 0.0}
    assert resolved['model']['channels'] == [4, 8, 8] and resolved['model']['language_encoder'] == 'words'
    assert resolved['model']['vocabulary'] == language.task_vocabulary()
    env = {**os.environ, 'MASTER_ADDR': '127.0.0.1', 'GLOO_SOCKET_IFNAME': 'lo', 'OMP_NUM_THREADS': '1'}
    two = subprocess.run([sys.executable, '-m', 'torch.distributed.run', '--standalone', '--nproc-per-node', '2',
                          '-m', 'hdp_tools.cli.main', *options, '--out', str(tmp_path / 'two.pt')],
                         text=True, capture_output=True, timeout=300, env=env)
    assert two.returncode == 0, two.stderr[-3000:]
    assert two.stdout.count('"train": {') == 1          # rank 0 alone prints
    single, split = checkpoint.load(tmp_path / 'one.pt'), checkpoint.load(tmp_path / 'two.pt')
    assert (single['config']['train']['processes'], split['config']['train']['processes']) == (1, 2)
    from hdp_learning.distributed import weights_digest
    assert weights_digest(checkpoint.build_model(split)) == split['config']['train']['weights_sha256']
    # The loss is invariant to a constant added to every logit of a softmax, so the heatmaps' logit
    # biases and the attention's key bias get gradients of float rounding, which Adam scales up to
    # steps of about lr: noise, differently rounded in one process and in two. They change no output.
    noise = {'coarse_heatmap.bias': slice(None), 'fine_heatmap.bias': slice(0, 1),
             'language.layer.self_attn.in_proj_bias': slice(TINY['language_dim'], 2 * TINY['language_dim'])}
    model = tiny_model()
    rng = np.random.default_rng(3)
    dataset = KeyframeDataset([synthetic_episode(rng, 'open_drawer'), synthetic_episode(rng, 'pick_up_cup')])
    losses(model, training_batch([dataset.item(i, rng) for i in range(len(dataset))], model.config, rng))[
        'total'].backward()
    gradients = dict(model.named_parameters())
    largest = max(float(p.grad.abs().max()) for p in model.parameters() if p.grad is not None)
    assert all(float(gradients[k].grad[rows].abs().max()) < 1e-6 * largest for k, rows in noise.items())

    def difference(name):
        d = (single['model'][name].float() - split['model'][name].float()).abs()
        if name in noise:
            d[noise[name]] = 0
        return float(d.max())
    worst = max(difference(k) for k in single['model'])
    assert worst < 1e-5, f'two processes differ from one by {worst}'
    torch.manual_seed(0)                         # train()'s initial weights for seed 0
    start = NextBestPoseNet(ModelConfig.from_dict(single['config']['model'])).state_dict()
    moved = max(float((single['model'][k].float() - start[k].float()).abs().max()) for k in single['model'])
    assert moved > 1000 * worst        # three steps moved the weights far more than the two runs differ
    (_, [one_row]), (_, [two_row]) = read_curves(tmp_path / 'one_curves.csv'), read_curves(tmp_path / 'two_curves.csv')
    assert one_row['step'] == two_row['step'] == 3
    assert math.isclose(one_row['total'], two_row['total'], rel_tol=1e-5)   # the global batch's losses, both


def test_agent_predicts_a_pose_from_camera_frames(tmp_path):
    path = tmp_path / 'agent.pt'
    checkpoint.save(path, tiny_model(), None, 0, {}, {}, {})
    agent = NextBestPoseAgent.from_checkpoint(path)
    intrinsics = Intrinsics(60.0, 60.0, 31.5, 23.5, 64, 48)
    looking_down = np.eye(4)
    looking_down[:3, :3] = np.diag([1.0, -1.0, -1.0])            # optical z pointing down
    looking_down[:3, 3] = (0.5, 0.0, 1.6)
    depth = np.full((48, 64), 700, np.uint16)                   # mm: a surface 0.9 m above the floor
    rgb = np.full((48, 64, 3), 128, np.uint8)
    pose = agent.predict({'front': (rgb, depth)}, {'front': intrinsics}, {'front': looking_down},
                         'open the top drawer', (np.zeros(7), True))
    assert pose.xyz.shape == (3,) and np.all(pose.xyz >= WORKSPACE[0] - 0.2) and np.all(pose.xyz <= WORKSPACE[1] + 0.2)
    assert pose.quat.shape == (4,) and math.isclose(np.linalg.norm(pose.quat), 1.0, abs_tol=1e-6)
    assert isinstance(pose.gripper_open, bool) and 0 < pose.confidence <= 1


def test_frames_of_another_size_are_resampled_to_the_training_size():
    """A 640 x 480 render resampled to 128 x 96 is the 128 x 96 render: the same intrinsics, the
    same depth but at a few edge pixels, colours within a few levels; the agent then predicts from
    the cloud a native 128 x 96 frame gives."""
    from hdp_planner.agent import resample_frame
    from hdp_sim_bridge import experts
    from hdp_sim_bridge.cameras import default_cameras
    from hdp_sim_bridge.world import PandaWorld
    big, small = default_cameras(640, 480), default_cameras(128, 96)
    with PandaWorld() as world:
        experts.reachable_scene(world, 'open_drawer', 1006)
        frames = {size: {c: cam.render(world.client) for c, cam in cameras.items()}
                  for size, cameras in (('big', big), ('small', small))}
    for camera in big:
        rgb, depth, intrinsics = resample_frame(*frames['big'][camera], big[camera].intrinsics, (128, 96))
        assert dataclasses.astuple(intrinsics) == pytest.approx(dataclasses.astuple(small[camera].intrinsics))
        assert depth.shape == (96, 128)
        assert np.mean(np.abs(depth.astype(float) - frames['small'][camera][1]) > 10) < 0.005      # mm
        assert np.abs(rgb.astype(float) - frames['small'][camera][0]).mean() < 5
    same = resample_frame(*frames['small']['front'], small['front'].intrinsics, (128, 96))
    assert same[0] is frames['small']['front'][0] and same[2] is small['front'].intrinsics
    agent = NextBestPoseAgent(tiny_model(), camera_size=(128, 96))
    clouds = [agent.predict(frames[size], {c: cam.intrinsics for c, cam in cameras.items()},
                            {c: cam.camera_to_world for c, cam in cameras.items()}, 'open the middle drawer',
                            (np.zeros(7), True)).cloud[0] for size, cameras in (('big', big), ('small', small))]
    assert abs(len(clouds[0]) - len(clouds[1])) < 0.01 * len(clouds[1])


def test_proprio_vector_scales_to_the_joint_limits():
    from hdp_motion import panda
    assert np.allclose(proprio_vector(panda.LOWER, False), [-1] * 8)
    assert np.allclose(proprio_vector(panda.UPPER, True), [1] * 8)


def test_hand_vector_scales_the_position_over_the_workspace_and_keeps_two_axes():
    from hdp_planner.model import hand_vector
    vector = hand_vector(WORKSPACE, np.array([[0, 0, 0, 1.0], [0, 0, 0, 1.0]]), [True, False])
    assert vector.shape == (2, 10)
    assert np.allclose(vector[:, 0], [1, -1])
    assert np.allclose(vector[0, 1:4], -1) and np.allclose(vector[1, 1:4], 1)
    assert np.allclose(vector[:, 4:], [1, 0, 0, 0, 1, 0])       # the x and y axes of the identity


@pytest.mark.parametrize('seed', range(3))
def test_hand_proprio_moves_with_the_augmented_scene(seed):
    """The hand's pose relative to the target is what the scene shows; augmentation must keep it."""
    from hdp_motion import panda
    from hdp_planner.model import hand_pose
    rng = np.random.default_rng(seed)
    episode = synthetic_episode(rng)
    episode['joint_positions'] = np.stack([panda.HOME, panda.HOME + 0.2])
    dataset = KeyframeDataset([episode], proprio='hand')
    hand_xyz, hand_quat = hand_pose(episode['joint_positions'])
    for s in range(2):
        plain, moved = dataset.item(s, rng), dataset.item(s, rng, augmented=True)
        assert plain.proprio.shape == moved.proprio.shape == (10,)
        for item in (plain, moved):
            position = WORKSPACE[0] + (item.proprio[1:4] + 1) / 2 * (WORKSPACE[1] - WORKSPACE[0])
            x_axis, y_axis = item.proprio[4:7], item.proprio[7:10]
            target_axes = quat_to_matrix(item.target_quat)
            # The target seen from the hand, and the target's axes in the hand's: unchanged.
            hand_axes = np.stack([x_axis, y_axis, np.cross(x_axis, y_axis)], 1)
            assert np.allclose(hand_axes.T @ (item.target_xyz - position),
                               quat_to_matrix(hand_quat[s]).T @ (episode['target_xyz'][s] - hand_xyz[s]), atol=1e-4)
            assert np.allclose(hand_axes.T @ target_axes,
                               quat_to_matrix(hand_quat[s]).T @ quat_to_matrix(episode['target_quat'][s]), atol=1e-4)
        assert not np.allclose(plain.proprio, moved.proprio)


def test_an_agent_trained_on_the_hand_pose_reads_it_from_the_joint_positions():
    from hdp_motion import panda
    from hdp_planner.model import hand_pose, hand_vector
    torch.manual_seed(0)
    model = NextBestPoseNet(ModelConfig(vocabulary=tuple(language.task_vocabulary()), proprio='hand', **TINY))
    seen = []
    model.proprio.register_forward_hook(lambda module, inputs, output: seen.append(inputs[0]))
    intrinsics = Intrinsics(100.0, 100.0, 31.5, 23.5, 64, 48)
    depth = np.full((48, 64), 0.8, np.float32)
    looking_down_at_the_table = np.eye(4)
    looking_down_at_the_table[:3, 3] = [0.5, 0.0, WORKSPACE[0, 2] - 0.6]
    NextBestPoseAgent(model).predict({'front': (np.zeros((48, 64, 3), np.uint8), depth)}, {'front': intrinsics},
                                     {'front': looking_down_at_the_table}, 'open the middle drawer', (panda.HOME, False))
    assert np.allclose(seen[0].numpy(), hand_vector(*hand_pose(panda.HOME[None]), [False]), atol=1e-6)
    with pytest.raises(ValueError, match="proprio 'elbow' is not one of"):
        ModelConfig(vocabulary=('open',), proprio='elbow')


@pytest.mark.dds
@pytest.mark.parametrize('command', [['train', 'high-level'], ['eval', 'high-level-offline']])
def test_cli_help(command):
    result = subprocess.run([sys.executable, '-m', 'hdp_tools.cli.main', *command, '--help'],
                            capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr
    assert '--data' in result.stdout


def test_an_episode_whose_cameras_never_pair_says_so(monkeypatch):
    """No frame with every camera's colour and depth before a keyframe: one clear error naming the
    bag, not a numpy one (a recording whose cameras ran apart)."""
    from types import SimpleNamespace

    from hdp_motion import panda
    from hdp_data.episodes import JointStates
    from hdp_planner import dataset
    t = np.linspace(0.0, 2.0, 50)
    still = np.zeros((50, 7))
    states = JointStates(t, np.tile(panda.HOME, (50, 1)), still, np.full(50, 0.08), np.ones(50, bool))
    episode = SimpleNamespace(path='demos/open_drawer_0001', joint_states=states, keyframes=lambda: [0, 49])
    monkeypatch.setattr(dataset, 'camera_geometry', lambda episode: ({}, {}))
    monkeypatch.setattr(dataset, 'camera_frames', lambda episode: [])
    with pytest.raises(ValueError, match=r"demos/open_drawer_0001: no sample: no frame with every camera's"):
        dataset.episode_samples(episode)


def test_keyframe_metrics_split_each_task_by_where_in_the_episode_a_sample_is():
    from hdp_planner.dataset import KeyframeDataset
    from hdp_planner.evaluate import keyframe_metrics, task_metrics
    dataset = KeyframeDataset([{'task': 'open_grill', 'target_open': [1, 0, 0]},
                               {'task': 'open_grill', 'target_open': [1, 0, 0]},
                               {'task': 'reach_target', 'target_open': [1]}])
    errors = {'translation_cm': np.array([1.0, 0.5, 8.0, 3.0, 0.5, 6.0, 2.0]),
              'rotation_deg': np.zeros(7), 'rotation_symmetric_deg': np.zeros(7), 'gripper_accuracy': np.ones(7)}
    by_keyframe = keyframe_metrics(dataset, errors)
    assert list(by_keyframe) == ['open_grill keyframe 0', 'open_grill keyframe 1', 'open_grill keyframe 2',
                                 'reach_target keyframe 0']
    first = by_keyframe['open_grill keyframe 0']
    assert (first['translation_cm'], first['samples']) == (2.0, 2)
    assert by_keyframe['open_grill keyframe 2']['translation_cm'] == 7.0
    assert task_metrics(dataset, errors)['open_grill']['translation_cm'] == pytest.approx(19 / 6, abs=1e-4)


def test_a_stop_the_gripper_change_follows_at_the_same_pose_is_one_goal():
    from hdp_planner.dataset import merge_stops_into_gripper_changes
    down = [0.0, 1.0, 0.0, 0.0]                                   # xyzw, the hand pointing down
    turned = rotations.yaw_quat(np.array(down), math.radians(30))
    xyz = [[0.5, 0.0, 1.0],       # pre-grasp, open
           [0.5, 0.0, 0.9],       # the arm's stop at the grasp, still open
           [0.5, 0.0, 0.903],     # the gripper closing there, 3 mm and two frames later
           [0.5, 0.0, 1.1],       # lift, closed
           [0.6, 0.0, 1.1],       # a stop with the gripper opening 10 cm on: two goals
           [0.6, 0.0, 1.1],       # a stop turned 30 deg before the gripper closes: two goals
           [0.6, 0.0, 1.1]]
    quat = [down] * 5 + [turned, down]
    gripper_open = [True, True, False, False, True, True, False]
    assert merge_stops_into_gripper_changes(xyz, quat, gripper_open).tolist() == [
        True, False, True, True, True, True, True]
    assert merge_stops_into_gripper_changes([[0.5, 0.0, 1.0]], [down], [True]).tolist() == [True]
