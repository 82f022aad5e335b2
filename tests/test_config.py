"""hdp_learning.config: the one --config mechanism of every trainer (sections of dataclasses,
defaults < file < flags, unknown sections and keys refused in one line naming the known ones)."""

import dataclasses
import subprocess
import sys
from pathlib import Path

import pytest

from hdp_learning.config import ConfigError, as_dict, load_sections

pytestmark = pytest.mark.unit

ROOT = Path(__file__).resolve().parents[1]


@dataclasses.dataclass(frozen=True)
class Model:
    vocabulary: tuple
    width: int = 4
    sizes: tuple = (1, 2)
    rate: float = 0.1
    name: str = 'small'
    shared: bool = False

    def __post_init__(self):
        if self.name not in ('small', 'large'):
            raise ValueError(f'name {self.name!r} is not small or large')


@dataclasses.dataclass
class Train:
    steps: int = 10
    lr: float = 1e-3


SECTIONS = {'model': Model, 'train': Train}


def load(tmp_path, text, **kwargs):
    path = tmp_path / 'c.yaml'
    path.write_text(text)
    return load_sections(path, SECTIONS, **kwargs)


def test_defaults_then_file_then_overrides(tmp_path):
    configs = load(tmp_path, 'model: {width: 8, sizes: [3, 4, 5], rate: 1}\ntrain: {steps: 20, lr: 0.5}\n',
                   defaults={'model': {'vocabulary': ('a',), 'width': 2}},
                   overrides={'train': {'steps': 30, 'lr': None}})        # None: a flag not given
    assert configs == {'model': Model(('a',), 8, (3, 4, 5), 1.0), 'train': Train(30, 0.5)}
    assert isinstance(configs['model'].rate, float) and isinstance(configs['model'].sizes, tuple)
    assert as_dict(configs) == {'model': {'vocabulary': ['a'], 'width': 8, 'sizes': [3, 4, 5], 'rate': 1.0,
                                          'name': 'small', 'shared': False}, 'train': {'steps': 30, 'lr': 0.5}}
    assert load_sections(None, {'train': Train}) == {'train': Train()}                   # no file: the defaults
    assert load(tmp_path, '', defaults={'model': {'vocabulary': ()}})['train'] == Train()   # an empty file too
    assert load(tmp_path, 'train:\n', defaults={'model': {'vocabulary': ()}})['train'] == Train()


@pytest.mark.parametrize('text, message', [
    ('model: {vocabulary: [a], widht: 3}\n', 'model: unknown key widht; known: vocabulary, width, sizes, rate, name, '
                                              'shared'),
    ('train: {step: 3, rate: 2}\n', 'train: unknown keys rate, step; known: steps, lr'),
    ('optimiser: {}\nschedule: {}\n', 'unknown sections optimiser, schedule; known: model, train'),
    ('- model\n', 'expected a mapping of sections (model, train)'),
    ('train: 5\n', 'section train must be a mapping of keys to values'),
    ('train: {steps: [1\n', 'not YAML'),
    ('train: {lr: 5e-4}\n', "train.lr: expected a number, got '5e-4' (YAML reads 5e-4 as a string: "
                            'write 0.0005 or 5.0e-4)'),
    ('train: {steps: 2.5}\n', 'train.steps: expected an integer, got 2.5'),
    ('train: {steps: true}\n', 'train.steps: expected an integer, got True'),
    ('model: {vocabulary: [a], sizes: 3}\n', 'model.sizes: expected a list, got 3'),
    ('model: {width: 3}\n', 'model: missing vocabulary'),
    ('model: {vocabulary: [a], name: huge}\n', "model: name 'huge' is not small or large"),
])
def test_refusals_are_one_line_naming_the_file_and_what_is_known(tmp_path, text, message):
    with pytest.raises(ConfigError) as refused:
        load(tmp_path, text, defaults=None if 'missing' in message else {'model': {'vocabulary': ('a',)}})
    assert str(refused.value).startswith(f'{tmp_path / "c.yaml"}: ') and message in str(refused.value)
    assert '\n' not in str(refused.value)


def test_a_missing_file_is_refused_in_one_line(tmp_path):
    with pytest.raises(ConfigError, match=r'nothing\.yaml: cannot read it \(No such file or directory\)$'):
        load_sections(tmp_path / 'nothing.yaml', SECTIONS)


def test_overrides_are_checked_like_the_file(tmp_path):
    with pytest.raises(ConfigError, match=r'train: unknown key batch; known: steps, lr'):
        load_sections(None, {'train': Train}, overrides={'train': {'batch': 4}})


@pytest.mark.dds
def test_the_loader_and_the_launcher_helpers_import_no_torch():
    probe = 'import sys, hdp_learning.config, hdp_learning.distributed; print("torch" in sys.modules)'
    result = subprocess.run([sys.executable, '-c', probe], capture_output=True, text=True, timeout=60)
    assert result.stdout.strip() == 'False', result.stderr


@pytest.mark.dds
def test_a_process_group_left_open_is_closed_before_the_interpreter_exits(tmp_path):
    """The evaluations join torchrun's group and return without stop(); left to the interpreter's
    teardown, gloo's threads were freed while joinable and a rank aborted at exit (3 two-process runs
    in 12 here, "terminate called without an active exception"). Eight runs must all exit cleanly."""
    import os
    script = tmp_path / 'gather.py'
    script.write_text('from hdp_learning import distributed\n'
                      'rank, world, _ = distributed.start()\n'
                      'print(distributed.gather(rank, world))\n')
    env = {**os.environ, 'MASTER_ADDR': '127.0.0.1', 'GLOO_SOCKET_IFNAME': 'lo', 'OMP_NUM_THREADS': '1'}
    for _ in range(8):
        run = subprocess.run([sys.executable, '-m', 'torch.distributed.run', '--standalone', '--nproc-per-node', '2',
                              str(script)], capture_output=True, text=True, timeout=120, env=env)
        assert run.returncode == 0 and run.stdout.count('[0, 1]') == 2, run.stderr[-2000:]


def test_the_low_level_configs_load_as_before():
    """The released RK-Diffuser configs give what RKDConfig.from_dict and TrainConfig(**) gave."""
    import yaml

    from hdp_controller.rk_diffuser import RKDConfig
    from hdp_controller.train import TrainConfig
    for path in sorted((ROOT / 'src/hdp_controller/config').glob('*.yaml')):
        values = yaml.safe_load(path.read_text())
        configs = load_sections(path, {'model': RKDConfig, 'train': TrainConfig})
        assert configs['model'] == RKDConfig.from_dict(values.get('model') or {}), path
        assert configs['train'] == TrainConfig(**(values.get('train') or {})), path


@pytest.mark.parametrize('name, parameters', [('flat_diffusion_policy_11tasks', 5_923_656),
                                              ('flat_act_11tasks', 2_185_480)])
def test_the_flat_recipes_load_and_build_the_networks_their_cards_name(name, parameters):
    """Every key of the 100-a-task recipes is known, and the network is the size the README states."""
    from hdp_planner.flat.checkpoint import build_network, config_class
    from hdp_planner.flat.train import FlatTrainConfig
    policy = name[len('flat_'):-len('_11tasks')]
    configs = load_sections(ROOT / f'src/hdp_planner/config/{name}.yaml',
                            {'model': config_class(policy), 'train': FlatTrainConfig})
    network = build_network(policy, configs['model'])
    assert sum(p.numel() for p in network.parameters() if p.requires_grad) == parameters


@pytest.mark.dds
def test_low_level_cli_refuses_an_unknown_key_in_one_line(tmp_path):
    config = tmp_path / 'rkd.yaml'
    config.write_text('train: {steps: 2, batch: 4}\n')
    refused = subprocess.run([sys.executable, '-m', 'hdp_tools.cli.main', 'train', 'low-level', '--data',
                              str(tmp_path), '--out', str(tmp_path / 'r.pt'), '--config', str(config)],
                             capture_output=True, text=True, timeout=120)
    assert refused.returncode != 0
    assert refused.stderr.strip() == (
        f'hdp train low-level: bad configuration: {config}: train: unknown key batch; known: steps, batch_size, lr, '
        'weight_decay, warmup_steps, ema_decay, save_every, seed, goal_augment'), refused.stderr
