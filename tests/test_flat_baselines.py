"""The flat baselines of Table 1 (hdp_planner.flat): dataset at the flat rate, Diffusion Policy and
ACT networks, training, checkpoints, `hdp train flat`, and the closed-loop harness's flat rows."""

import dataclasses
import re
import subprocess
import sys

import numpy as np
import pytest
import torch

from hdp_learning.checkpoints import CheckpointError
from hdp_learning.curves import read_curves
from hdp_data.episodes import list_episodes, read_episode
from hdp_planner.flat import checkpoint
from hdp_planner.flat.act import ACTConfig, ACTNet
from hdp_planner.flat.dataset import CONTROL_PERIOD_S, FlatDataset, downscale, load_flat_samples
from hdp_planner.flat.diffusion_policy import ConditionalUnet1D, DiffusionPolicyConfig, DiffusionPolicyNet
from hdp_planner.flat.encoders import observation_tensors
from hdp_planner.flat.policy import FlatObservation, FlatPolicy
from hdp_planner.flat.train import FlatTrainConfig, train

pytestmark = pytest.mark.dds

HDP = [sys.executable, '-m', 'hdp_tools.cli.main']
# Small and with the learned word encoder (no MiniLM load) unless a test is about the defaults.
DP = DiffusionPolicyConfig(language_encoder='words', channels=(8, 8, 8), keypoints=8, down_dims=(16, 32),
                           step_embed_dim=16, n_groups=4, horizon=8, n_action_steps=4, inference_steps=3)
ACT = ACTConfig(language_encoder='words', channels=(8, 8, 8), d_model=32, heads=2, encoder_layers=1,
                decoder_layers=1, feedforward=64, latent_dim=8, horizon=10, dropout=0.0)


@pytest.fixture(scope='module')
def episodes(tmp_path_factory):
    out = tmp_path_factory.mktemp('flat_episodes')
    result = subprocess.run([*HDP, 'collect', '--tasks', 'reach_target', '--episodes', '2', '--seed-start', '11',
                             '--out', str(out), '--width', '64', '--height', '48'],
                            text=True, capture_output=True, timeout=300)
    assert result.returncode == 0, result.stderr
    return out


@pytest.fixture(scope='module')
def checkpoints(episodes, tmp_path_factory):
    """A 2-step checkpoint of each policy (tiny configs), trained through ``train``."""
    out = tmp_path_factory.mktemp('flat_checkpoints')
    paths = {}
    for name, config in (('diffusion_policy', DP), ('act', ACT)):
        paths[name] = out / f'{name}.pt'
        train(name, episodes, paths[name], config, FlatTrainConfig(steps=2, batch=4, warmup=1),
              cache=out / 'cache', log=lambda *_: None, progress=False)
    return paths


def _dataset(episodes, config, tmp_path):
    return FlatDataset.from_directory(episodes, config.n_obs, config.horizon, config.image_width, config.image_height,
                                      cache_dir=tmp_path / 'cache', progress=False)


# --- dataset ------------------------------------------------------------------------------

def test_dataset_samples_the_flat_rate(episodes, tmp_path):
    data = _dataset(episodes, DiffusionPolicyConfig(language_encoder='words'), tmp_path)
    bags = list_episodes(episodes)
    assert len(data.episodes) == len(bags) == 2
    for bag, flat in zip(bags, data.episodes):
        js = read_episode(bag).joint_states
        steps = int(np.floor((js.t[-1] - js.t[0]) / CONTROL_PERIOD_S + 1e-9)) + 1
        assert len(flat['joint_positions']) == steps > 10
        # Step k holds the joint state at t0 + 0.1 k (120 Hz states: within one state).
        for k in (0, 5, steps - 1):
            i = np.searchsorted(js.t, js.t[0] + k * CONTROL_PERIOD_S + 1e-9, side='right') - 1
            np.testing.assert_allclose(flat['joint_positions'][k], js.position[i], atol=1e-6)
        assert flat['images_front'].shape[1:] == (48, 64, 3) and flat['images_side'].dtype == np.uint8
        # Frames only at the start and at rests: the latest one at or before each step, never going back.
        assert flat['frame_index'][0] == 0 and np.all(np.diff(flat['frame_index']) >= 0)
        # (the final rest's frame may come after the last whole control step)
        assert len(flat['images_front']) - 2 <= flat['frame_index'][-1] <= len(flat['images_front']) - 1
    assert len(data) == sum(len(e['frame_index']) - 1 for e in data.episodes)
    rng = np.random.default_rng(0)
    indices = data.draw(5, rng)
    batch = data.batch(indices, rng)
    assert batch.images.shape == (5, 2, 2, 3, 48, 64) and batch.images.dtype == np.uint8
    assert batch.proprio.shape == (5, 2, 9) and batch.actions.shape == (5, 16, 8) and batch.is_pad.shape == (5, 16)
    assert set(np.unique(batch.actions[..., 7])) <= {-1.0, 1.0}
    from hdp_planner import language
    variations = [int(data.episodes[e]['variation']) for e, _ in data.index[indices]]
    assert all(any(text == template.format(language.instructions.TASKS['reach_target'].variations[v])
                   for template in language.training_phrasings('reach_target'))
               for text, v in zip(batch.instructions, variations)), batch.instructions
    # The chunk of step k is the states at k + 1 .. k + 16, the last repeated past the end (and marked).
    e, k = data.index[indices[0]]
    joints = data.episodes[e]['joint_positions']
    last = len(joints) - 1
    expected = joints[np.minimum(np.arange(k + 1, k + 17), last)]
    np.testing.assert_allclose(batch.actions[0, :, :7], expected, atol=1e-6)
    np.testing.assert_array_equal(batch.is_pad[0], np.arange(k + 1, k + 17) > last)
    # The last sample of an episode is padded from its second action on.
    final = int(np.flatnonzero((data.index[:, 0] == e) & (data.index[:, 1] == last - 1))[0])
    padded = data.batch([final], rng)
    assert not padded.is_pad[0, 0] and padded.is_pad[0, 1:].all()


def test_dataset_decoded_by_two_processes_is_the_one_process_dataset(episodes, tmp_path):
    config = DiffusionPolicyConfig(language_encoder='words')
    shape = (config.n_obs, config.horizon, config.image_width, config.image_height)
    one = FlatDataset.from_directory(episodes, *shape, cache_dir=tmp_path / 'one', progress=False)
    two = FlatDataset.from_directory(episodes, *shape, cache_dir=tmp_path / 'two', progress=False, workers=2)
    assert len(list((tmp_path / 'two').glob('*.npz'))) == len(one.episodes) == 2
    for a, b in zip(one.episodes, two.episodes):
        assert a.keys() == b.keys() and all(np.array_equal(a[k], b[k]) for k in a)
    with pytest.raises(ValueError, match='workers'):
        FlatDataset.from_directory(episodes, *shape, cache_dir=tmp_path / 'two', progress=False, workers=0)


def test_dataset_cache_is_keyed_by_image_size(episodes, tmp_path):
    bag = list_episodes(episodes)[0]
    first = load_flat_samples(bag, tmp_path, 64, 48)
    cached = sorted(p.name for p in tmp_path.iterdir())
    again = load_flat_samples(bag, tmp_path, 64, 48)
    assert sorted(p.name for p in tmp_path.iterdir()) == cached
    np.testing.assert_array_equal(first['images_front'], again['images_front'])
    smaller = load_flat_samples(bag, tmp_path, 32, 24)
    assert smaller['images_front'].shape[1:] == (24, 32, 3) and len(list(tmp_path.iterdir())) == 2


@pytest.mark.unit
def test_downscale_averages_areas():
    image = np.zeros((4, 4, 3), np.uint8)
    image[:2, :2] = 200
    small = downscale(image, 2, 2)
    assert small.shape == (2, 2, 3) and small[0, 0, 0] == 200 and small[1, 1, 0] == 0
    image[0, 0] = 0
    assert downscale(image, 2, 2)[0, 0, 0] == 150


# --- networks --------------------------------------------------------------------------------

@pytest.mark.unit
def test_conditional_unet_shapes():
    unet = ConditionalUnet1D(8, 20, step_embed_dim=16, down_dims=(16, 32, 64), n_groups=4)
    x = torch.randn(3, 16, 8)
    assert unet(x, torch.tensor([5, 50, 99]), torch.randn(3, 20)).shape == (3, 16, 8)
    assert unet(x, torch.tensor([7]), torch.randn(3, 20)).shape == (3, 16, 8)
    with pytest.raises(ValueError, match='divisible'):
        DiffusionPolicyConfig(horizon=10, down_dims=(16, 32, 64))


@pytest.mark.parametrize('name', ['diffusion_policy', 'act'])
def test_network_losses_and_predictions(episodes, tmp_path, name):
    config = DP if name == 'diffusion_policy' else ACT
    data = _dataset(episodes, config, tmp_path)
    net = DiffusionPolicyNet(config) if name == 'diffusion_policy' else ACTNet(config)
    net.normaliser.fit(*data.action_range())
    rng = np.random.default_rng(0)
    batch = observation_tensors(data.batch(data.draw(3, rng), rng))
    parts = net.losses(batch, torch.Generator().manual_seed(0))
    assert set(parts) == ({'noise_mse', 'total'} if name == 'diffusion_policy' else {'l1', 'kl', 'total'})
    assert all(v.shape == () and torch.isfinite(v) for v in parts.values())
    parts['total'].backward()
    assert all(p.grad is not None for p in net.parameters() if p.requires_grad)
    net.eval()
    actions = net.predict(batch)
    assert actions.shape == (3, config.horizon, 8)
    low, high = net.normaliser.low, net.normaliser.high
    assert torch.all(actions >= low - 1e-5) and torch.all(actions <= high + 1e-5)


@pytest.mark.parametrize('name', ['diffusion_policy', 'act'])
def test_training_loss_falls_on_a_tiny_batch(episodes, tmp_path, name):
    torch.manual_seed(0)
    config = DP if name == 'diffusion_policy' else ACT
    data = _dataset(episodes, config, tmp_path)
    net = DiffusionPolicyNet(config) if name == 'diffusion_policy' else ACTNet(config)
    net.normaliser.fit(*data.action_range())
    rng = np.random.default_rng(0)
    batch = observation_tensors(data.batch(data.draw(4, rng), rng))
    optimizer = torch.optim.AdamW(net.parameters(), lr=2e-3)
    key = 'noise_mse' if name == 'diffusion_policy' else 'l1'
    seen = []
    for step in range(40):
        parts = net.losses(batch, torch.Generator().manual_seed(step % 2))    # the same noise: a fixed objective
        optimizer.zero_grad()
        parts['total'].backward()
        optimizer.step()
        seen.append(float(parts[key].detach()))
    assert np.mean(seen[-4:]) < 0.5 * np.mean(seen[:2]), seen


# --- checkpoints and the policy ---------------------------------------------------------------

def test_checkpoint_round_trip_and_policy(checkpoints, episodes, tmp_path):
    for name, config in (('diffusion_policy', DP), ('act', ACT)):
        stored = checkpoint.load(checkpoints[name], name)
        assert stored['step'] == 2 and stored['optimizer'] == {}     # the last save keeps weights only
        assert stored['training_seeds'] == {'reach_target': [11, 12]}
        assert checkpoints[name].stat().st_size < 2 * 1024 ** 2
        policy = FlatPolicy.from_checkpoint(checkpoints[name])
        assert policy.name == name and policy.config == dataclasses.replace(
            config, vocabulary=policy.config.vocabulary) and policy.config.vocabulary
        rebuilt = checkpoint.build_model(stored)
        for key, tensor in rebuilt.state_dict().items():
            torch.testing.assert_close(tensor, policy.model.state_dict()[key])
        policy.reset('reach the red target', seed=3)
        rng = np.random.default_rng(0)
        images = {c: rng.integers(0, 255, (96, 128, 3), dtype=np.uint8) for c in ('front', 'side')}
        observation = FlatObservation(images,
                                      np.array([0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785]), True, 0.08)
        chunk = policy.act(observation)
        expected = config.n_action_steps if name == 'diffusion_policy' else 1
        assert chunk.shape == (expected, 8) and set(np.unique(chunk[:, 7])) <= {-1.0, 1.0}
        policy.observe(observation)
        assert policy.step == 1 and len(policy.history) == config.n_obs
        policy.reset('reach the red target', seed=3)
        np.testing.assert_allclose(policy.act(observation), chunk)           # seeded sampling repeats


def test_a_time_boxed_run_saves_weights_only_and_the_next_continues_it(episodes, tmp_path):
    out, log = tmp_path / 'dp.pt', []
    config = FlatTrainConfig(steps=3, batch=4, warmup=1)
    run = dict(cache=tmp_path / 'cache', log=log.append, progress=False)
    with pytest.raises(ValueError, match='stop_after_s'):
        train('diffusion_policy', episodes, out, DP, config, stop_after_s=0, **run)
    train('diffusion_policy', episodes, out, DP, config, stop_after_s=1e-6, **run)     # one step, then out
    stopped = checkpoint.load(out)
    assert stopped['step'] == 1 and stopped['optimizer'] == {}
    assert [(r['from_step'], r['to_step'], r['fresh_optimizer']) for r in stopped['compute']] == [(0, 1, True)]
    train('diffusion_policy', episodes, out, DP, config, **run)
    assert any(re.fullmatch(rf'continuing {re.escape(str(out))} from step 1 \([0-9.]+ CPU-thread-hours so far\) '
                            r'with fresh AdamW moments \(saved without them\)', line) for line in log), log
    done = checkpoint.load(out)
    assert done['step'] == 3 and [(r['from_step'], r['to_step']) for r in done['compute']] == [(0, 1), (1, 3)]
    assert done['compute'][1]['threads'] == torch.get_num_threads() and checkpoint.thread_hours(done) > 0
    assert not torch.equal(done['model']['unet.final.1.weight'], stopped['model']['unet.final.1.weight'])


def test_checkpoint_refusals(checkpoints, episodes, tmp_path):
    with pytest.raises(CheckpointError, match="holds a 'diffusion_policy' policy, not 'act'"):
        FlatPolicy.from_checkpoint(checkpoints['diffusion_policy'], policy='act')
    other = tmp_path / 'agent.pt'
    torch.save({'format': 'hdp_planner.next_best_pose', 'version': 1}, other)
    with pytest.raises(CheckpointError, match="not a 'hdp_planner.flat_policy' checkpoint"):
        checkpoint.load(other)
    stored = checkpoint.load(checkpoints['act'])
    key = next(k for k, v in stored['model'].items() if v.ndim == 2)
    stored['model'][key] = torch.zeros(3, 3)
    bad = tmp_path / 'bad.pt'
    torch.save(stored, bad)
    with pytest.raises(CheckpointError, match='wrong shape'):
        FlatPolicy.from_checkpoint(bad)
    stored = checkpoint.load(checkpoints['act'])
    stored['training_seeds'] = {'reach_target': ['11']}
    torch.save(stored, bad)
    with pytest.raises(CheckpointError, match='training_seeds'):
        checkpoint.load(bad)
    (tmp_path / 'junk.pt').write_bytes(b'not a checkpoint')
    with pytest.raises(CheckpointError, match='not a readable checkpoint'):
        checkpoint.load(tmp_path / 'junk.pt')
    # Continuing with another config is refused, naming what changed.
    with pytest.raises(CheckpointError, match='train.batch: 4 -> 8'):
        train('act', episodes, checkpoints['act'], ACT, FlatTrainConfig(steps=2, batch=8, warmup=1),
              cache=tmp_path / 'cache', log=lambda *_: None, progress=False)


# --- the command ----------------------------------------------------------------------------

@pytest.mark.parametrize('name', ['diffusion_policy', 'act'])
def test_train_flat_cli(episodes, tmp_path, name):
    out = tmp_path / f'{name}.pt'
    config = tmp_path / 'small.yaml'
    small = DP if name == 'diffusion_policy' else ACT
    model = {k: list(v) if isinstance(v, tuple) else v for k, v in dataclasses.asdict(small).items()
             if k not in ('vocabulary', 'language_encoder')}
    import yaml
    config.write_text(yaml.safe_dump({'model': model, 'train': {'warmup': 1, 'val_samples': 4}}))
    args = ['train', 'flat', '--policy', name, '--data', str(episodes), '--out', str(out), '--config', str(config),
            '--steps', '2', '--batch', '4', '--threads', '1', '--val-data', str(episodes), '--val-every', '2',
            '--cache', str(tmp_path / 'cache')]
    if name == 'diffusion_policy':
        args += ['--language-encoder', 'words']          # act runs the default, the frozen MiniLM
    result = subprocess.run([*HDP, *args], text=True, capture_output=True, timeout=600)
    assert result.returncode == 0, result.stderr[-2000:]
    assert f'checkpoint: {out}' in result.stdout
    stored = checkpoint.load(out, name)
    assert stored['step'] == 2 and stored['config']['train']['batch'] == 4
    assert stored['config']['model']['language_encoder'] == ('words' if name == 'diffusion_policy' else 'minilm')
    assert 0 <= stored['metrics']['validation']['gripper_accuracy'] <= 1
    columns, rows = read_curves(out.with_name(f'{name}_curves.csv'))
    assert 'total' in columns and 'val_joint_error_rad' in columns and rows[0]['step'] == 2
    config.write_text('model:\n  horizn: 8\n')
    refused = subprocess.run([*HDP, *args[:8], '--config', str(config)], text=True, capture_output=True, timeout=120)
    assert refused.returncode != 0 and 'unknown key horizn' in refused.stderr and not refused.stdout


def test_harness_under_torchrun_shards_episodes_and_writes_one_result(checkpoints, tmp_path):
    """Two processes take every other episode; rank 0 prints one table and writes every record, in the
    order one process writes them, with the same outcomes (flat policies draw their noise per episode)."""
    import json
    import os
    args = ['eval', 'hierarchy', '--agents', 'diffusion_policy,act', '--tasks', 'reach_target', '--episodes', '2',
            '--seed-start', '1000', '--phrasings', 'seen,heldout', '--flat-max-seconds', '0.5',
            '--flat-diffusion-policy-checkpoint', str(checkpoints['diffusion_policy']),
            '--flat-act-checkpoint', str(checkpoints['act']), '--flat-act-ensemble', '0']
    one = subprocess.run([*HDP, *args, '--json', str(tmp_path / 'one.json')], text=True, capture_output=True,
                         timeout=600)
    assert one.returncode == 0, one.stderr[-3000:]
    env = {**os.environ, 'MASTER_ADDR': '127.0.0.1', 'GLOO_SOCKET_IFNAME': 'lo', 'OMP_NUM_THREADS': '1'}
    two = subprocess.run([sys.executable, '-m', 'torch.distributed.run', '--standalone', '--nproc-per-node', '2',
                          '-m', 'hdp_tools.cli.main', *args, '--json', str(tmp_path / 'two.json')],
                         text=True, capture_output=True, timeout=600, env=env)
    assert two.returncode == 0, two.stderr[-3000:]
    assert two.stdout.count('| agent |') == 1 and '2 process(es)' in two.stdout
    single, split = (json.loads((tmp_path / f'{n}.json').read_text()) for n in ('one', 'two'))
    assert (single['processes'], split['processes']) == (1, 2)
    assert split['flat']['execution']['act'] == {'n_action_steps': ACT.horizon, 'ensemble': 0.0}   # the whole chunk

    def records(results):
        return [(r['agent'], r['seed'], r['phrasing'], r['control_steps'], r['joint_travel_rad'])
                for rows in results['agents'].values() for tasks in rows.values() for r in tasks['reach_target']['records']]
    assert len(records(split)) == 8 and records(split) == records(single)


def test_dense_camera_episodes_train_a_policy_shown_every_frame(tmp_path):
    """Episodes recorded with --camera-rate 10: every control step has its own frame, the checkpoint
    records the rate, and the policy asks the harness for a frame every control step."""
    out = tmp_path / 'dense'
    result = subprocess.run([*HDP, 'collect', '--tasks', 'reach_target', '--episodes', '1', '--seed-start', '11',
                             '--out', str(out), '--width', '32', '--height', '24', '--camera-rate', '10'],
                            text=True, capture_output=True, timeout=300)
    assert result.returncode == 0, result.stderr
    data = _dataset(out, DP, tmp_path)
    frames = data.episodes[0]['frame_index']
    assert data.camera_rate_hz() == 10 and len(set(frames[1:-1].tolist())) == len(frames) - 2   # one per step
    train('act', out, tmp_path / 'act.pt', ACT, FlatTrainConfig(steps=1, batch=2, warmup=1),
          cache=tmp_path / 'cache', log=lambda *_: None, progress=False)
    policy = FlatPolicy.from_checkpoint(tmp_path / 'act.pt')
    assert policy.data_camera_rate_hz == 10 and policy.cameras_as_trained == 'every'


def test_inference_choices_change_on_a_copy_that_shares_the_weights(checkpoints):
    """What validation chooses between without retraining: ACT ensembled or open-loop (LeRobot's
    default runs the whole chunk), Diffusion Policy's DDIM steps."""
    act = FlatPolicy.from_checkpoint(checkpoints['act'])
    chunked = act.with_execution(ensemble=0.0, n_action_steps=act.config.horizon)
    assert (act.config.ensemble, act.config.n_action_steps) == (ACT.ensemble, 1)              # unchanged
    assert chunked.model.head.weight is act.model.head.weight and chunked.model.config is chunked.config
    chunked.reset('reach the red target', seed=3)
    observation = FlatObservation({c: np.zeros((96, 128, 3), np.uint8) for c in ('front', 'side')},
                                  np.array([0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785]), True, 0.08)
    assert chunked.act(observation).shape == (act.config.horizon, 8)
    with pytest.raises(ValueError, match='exceeds the horizon'):
        act.with_execution(n_action_steps=act.config.horizon + 1)
    with pytest.raises(ValueError, match=r"cannot change \['inference_steps'\]"):
        act.with_execution(inference_steps=5)
    dp = FlatPolicy.from_checkpoint(checkpoints['diffusion_policy'])
    assert dp.with_execution(inference_steps=5).model.config.inference_steps == 5 != dp.model.config.inference_steps
    with pytest.raises(ValueError, match='inference_steps must be >= 1'):
        dp.with_execution(inference_steps=0)


# --- the harness ----------------------------------------------------------------------------

def test_harness_runs_the_flat_rows(checkpoints):
    from hdp_eval.hierarchy_eval import FLAT_AGENTS, evaluate, markdown_table, run_flat_episode
    policies = {name: FlatPolicy.from_checkpoint(checkpoints[name]) for name in FLAT_AGENTS}
    results = evaluate(None, {}, ['reach_target'], 1, 1000, flat=policies, flat_max_seconds=1.0, progress=False)
    for name, policy in policies.items():
        record = results['agents'][name]['seen']['reach_target']['records'][0]
        assert record['agent'] == name and record['seed'] == 1000 and record['phrasing'] == 'seen'
        assert record['segments'] == 0 and record['control_steps'] >= 1 and record['camera_frames'] >= 1
        if not record['success']:
            assert record['failure'] == 'time budget spent' and record['control_steps'] == 10
            assert abs(record['sim_seconds'] - 1.0) < 0.01
        per_query = policy.config.n_action_steps
        assert record['queries'] == -(-record['control_steps'] // per_query) == len(record['predict_times'])
        assert record['joint_travel_rad'] > 0.01                  # the arm moved
    assert results['flat']['max_seconds'] == 1.0
    assert results['flat']['execution'] == {'diffusion_policy': {'n_action_steps': DP.n_action_steps,
                                                                 'inference_steps': DP.inference_steps},
                                            'act': {'n_action_steps': 1, 'ensemble': ACT.ensemble}}
    assert results['flat']['cameras'] == {'diffusion_policy': 'rest', 'act': 'rest'}     # as trained
    assert '| act | seen |' in markdown_table(results)
    # 'every' renders a frame each control step.
    record = run_flat_episode('act', policies['act'], 'reach_target', 1000, max_seconds=0.3, cameras_when='every')
    assert record.camera_frames == record.control_steps == 3
    # Training seeds are refused, as for the hierarchical rows.
    with pytest.raises(ValueError, match='act was trained on reach_target seeds 11-12'):
        evaluate(None, {}, ['reach_target'], 3, 10, flat={'act': policies['act']}, progress=False)
