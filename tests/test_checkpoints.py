"""hdp_learning.checkpoints: the one set of rules every checkpoint is saved and loaded by."""

import os
import random
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from hdp_controller import checkpoint as rkd_checkpoint
from hdp_controller.policy import default_checkpoint as rkd_default
from hdp_learning import checkpoints
from hdp_learning.checkpoints import CheckpointError
from hdp_planner import checkpoint as agent_checkpoint
from hdp_planner.planner_logic import default_checkpoint as agent_default

pytestmark = pytest.mark.unit

MODELS = Path(__file__).resolve().parents[1] / 'models'
KIND, VERSION = 'test_kind', 3


def _payload(**extra) -> dict:
    return {'format': KIND, 'version': VERSION, 'weights': {'w': torch.arange(6.0).reshape(2, 3)}, **extra}


def _refused(path, match=None) -> str:
    """The one-line message loading ``path`` is refused with; it names the file."""
    with pytest.raises(CheckpointError, match=match) as refusal:
        checkpoints.load(path, KIND, VERSION)
    message = str(refusal.value)
    assert str(path) in message and '\n' not in message
    return message


def test_round_trip(tmp_path):
    path = tmp_path / 'sub' / 'model.pt'
    checkpoints.save(path, _payload(step=7))
    loaded = checkpoints.load(path, KIND, VERSION, {'weights': dict, 'step': int})
    assert loaded['step'] == 7 and torch.equal(loaded['weights']['w'], torch.arange(6.0).reshape(2, 3))


def test_save_is_atomic_and_leaves_no_temp_file(tmp_path, monkeypatch):
    path = tmp_path / 'model.pt'
    checkpoints.save(path, _payload(step=1))
    checkpoints.save(path, _payload(step=2))
    assert os.listdir(tmp_path) == ['model.pt']

    def crash(payload, file):
        file.write(b'half a checkpoint')
        raise KeyboardInterrupt
    monkeypatch.setattr(torch, 'save', crash)
    with pytest.raises(KeyboardInterrupt):
        checkpoints.save(path, _payload(step=3))
    assert os.listdir(tmp_path) == ['model.pt']          # the partial file is gone ...
    assert checkpoints.load(path, KIND, VERSION)['step'] == 2      # ... and the previous checkpoint whole


def test_save_refuses_a_payload_without_format_and_version(tmp_path):
    with pytest.raises(ValueError, match='format'):
        checkpoints.save(tmp_path / 'x.pt', {'weights': {}})
    assert not os.listdir(tmp_path)


@pytest.mark.parametrize('damage', ['truncated', 'cut in half', 'random bytes', 'empty', 'text'])
def test_damaged_files_are_refused_without_torchs_advice(tmp_path, damage):
    whole = tmp_path / 'whole.pt'
    checkpoints.save(whole, _payload())
    path = tmp_path / 'damaged.pt'
    data = whole.read_bytes()
    path.write_bytes({'truncated': data[:300], 'cut in half': data[:len(data) // 2], 'random bytes': random.Random(0).randbytes(4000),
                      'empty': b'', 'text': b'not a checkpoint'}[damage])
    message = _refused(path, 'not a readable checkpoint')
    assert 'weights_only' not in message


def test_a_file_holding_code_is_refused_unrun(tmp_path, capfd):
    class Evil:
        def __reduce__(self):
            return (print, ('pwned',))
    torch.save({**_payload(), 'x': Evil()}, tmp_path / 'evil.pt')
    message = _refused(tmp_path / 'evil.pt', 'objects other than tensors')
    assert 'weights_only' not in message and 'pwned' not in capfd.readouterr().out


def test_wrong_kind_version_and_fields_are_refused(tmp_path):
    torch.save({**_payload(), 'format': 'other_kind'}, tmp_path / 'other.pt')
    assert "is not a 'test_kind' checkpoint (it holds a 'other_kind' one)" in _refused(tmp_path / 'other.pt')
    torch.save({'weights': torch.zeros(3)}, tmp_path / 'plain.pt')
    _refused(tmp_path / 'plain.pt', 'no checkpoint kind')
    torch.save(torch.zeros(3), tmp_path / 'tensor.pt')
    _refused(tmp_path / 'tensor.pt', 'no checkpoint kind')
    torch.save({**_payload(), 'format': 'line\n' * 1000}, tmp_path / 'long.pt')
    assert len(_refused(tmp_path / 'long.pt')) < 200 + len(str(tmp_path))
    torch.save({**_payload(), 'version': 2}, tmp_path / 'old.pt')
    _refused(tmp_path / 'old.pt', 'version 2, this code reads 3')
    with pytest.raises(CheckpointError, match="'step' is missing or not of type int"):
        checkpoints.load(tmp_path / 'old.pt', KIND, 2, {'step': int})
    _refused(tmp_path / 'absent.pt', 'no such checkpoint')


def test_the_version_may_ride_on_the_format_as_in_the_first_agent_checkpoints(tmp_path):
    torch.save({'format': f'{KIND}/{VERSION}', 'weights': {}}, tmp_path / 'first.pt')
    assert checkpoints.load(tmp_path / 'first.pt', KIND, VERSION)['format'] == f'{KIND}/{VERSION}'
    torch.save({'format': f'{KIND}/1', 'weights': {}}, tmp_path / 'older.pt')
    _refused(tmp_path / 'older.pt', 'version 1, this code reads 3')


def test_an_oversized_file_is_refused_before_it_is_read(tmp_path, monkeypatch):
    path = tmp_path / 'big.pt'
    checkpoints.save(path, _payload())
    monkeypatch.setattr(checkpoints, 'MAX_BYTES', path.stat().st_size - 1)
    monkeypatch.setattr(torch, 'load', lambda *args, **kwargs: pytest.fail('read despite its size'))
    _refused(path, 'over the')


def test_weights_are_checked_against_the_model(tmp_path):
    model = torch.nn.Linear(3, 2)
    weights = {k: v.clone() for k, v in model.state_dict().items()}
    with pytest.raises(CheckpointError, match=r'missing \[.bias.\]'):
        checkpoints.load_weights(tmp_path / 'm.pt', model, {'weight': weights['weight']})
    with pytest.raises(CheckpointError, match=r'm.pt: weights do not match the config: weight has the wrong shape'):
        checkpoints.load_weights(tmp_path / 'm.pt', model, {**weights, 'weight': torch.zeros(3, 2)})
    with pytest.raises(CheckpointError, match='NaN'):
        checkpoints.load_weights(tmp_path / 'm.pt', model, {**weights, 'bias': torch.tensor([0.0, float('nan')])})
    checkpoints.load_weights(tmp_path / 'm.pt', torch.nn.Linear(3, 2), weights)


def test_hdp_models_dir_is_honoured_by_both_packages(tmp_path, monkeypatch):
    monkeypatch.delenv('HDP_MODELS_DIR', raising=False)
    assert checkpoints.models_dir() == MODELS
    assert (rkd_default(), agent_default()) == (MODELS / 'rk_diffuser_11tasks.pt', MODELS / 'hdp_nbp_agent_11tasks.pt')
    monkeypatch.setenv('HDP_MODELS_DIR', str(tmp_path))
    assert (rkd_default(), agent_default()) == (tmp_path / 'rk_diffuser_11tasks.pt', tmp_path / 'hdp_nbp_agent_11tasks.pt')
    assert checkpoints.default_path('x.pt') == tmp_path / 'x.pt'


def test_the_released_checkpoints_load_through_their_packages():
    rkd, payload = rkd_checkpoint.load_model(MODELS / 'rk_diffuser.pt')
    assert payload['version'] == rkd_checkpoint.VERSION and not rkd.training
    agent, stored = agent_checkpoint.load_model(MODELS / 'hdp_nbp_agent.pt')
    assert stored['format'] == 'hdp_planner.next_best_pose/1' and stored['step'] > 0 and not agent.training


def test_each_package_refuses_the_other_ones_checkpoint():
    with pytest.raises(CheckpointError, match="hdp_nbp_agent.pt is not a 'hdp_rk_diffuser' checkpoint "
                                              r"\(it holds a 'hdp_planner.next_best_pose' one\)"):
        rkd_checkpoint.load_model(MODELS / 'hdp_nbp_agent.pt')
    with pytest.raises(CheckpointError, match="rk_diffuser.pt is not a 'hdp_planner.next_best_pose' checkpoint"):
        agent_checkpoint.load_model(MODELS / 'rk_diffuser.pt')


@pytest.mark.dds
def test_importing_the_checkpoint_rules_loads_no_torch():
    probe = 'import sys, hdp_learning.checkpoints; print("torch" in sys.modules)'
    result = subprocess.run([sys.executable, '-c', probe], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0 and result.stdout.strip() == 'False', result.stderr


def test_a_bare_checkpoint_name_is_the_released_file_of_that_name(tmp_path, monkeypatch):
    monkeypatch.setenv('HDP_MODELS_DIR', str(tmp_path / 'models'))
    monkeypatch.chdir(tmp_path)
    assert checkpoints.resolve('hdp_nbp_agent_11tasks_d415.pt') == tmp_path / 'models' / 'hdp_nbp_agent_11tasks_d415.pt'
    (tmp_path / 'mine.pt').write_bytes(b'')
    assert checkpoints.resolve('mine.pt') == Path('mine.pt')              # a file here wins
    assert checkpoints.resolve('runs/agent.pt') == Path('runs/agent.pt')  # a path stays a path
