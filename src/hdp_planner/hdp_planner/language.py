"""Instructions: the task phrasings, a closed-vocabulary word tokenizer and a small learned encoder.

The training language is closed (the task phrasings x their variations, under
100 words), so WordEncoder embeds words from scratch; any other word is <unk>.
Encoders sit behind ``InstructionEncoder`` (texts in, token features and a
pooled vector out): sentence_encoder.SentenceEncoder, a frozen pretrained
all-MiniLM-L6-v2, is the other one (the agent's ``language_encoder``).

The last phrasing of every task is held out: training draws only from the
others. Each task also has a paraphrase set written apart from the templates,
never trained on; the evaluations report all three.
"""

from __future__ import annotations

import re

import numpy as np
import torch
from torch import nn

from hdp_data import instructions

PAD, UNK = '<pad>', '<unk>'
MAX_WORDS = 16


def words(text: str) -> list[str]:
    """Lower-case words of ``text``, punctuation dropped: 'Open the Box!' -> ['open', 'the', 'box']."""
    return re.sub(r'[^a-z0-9 ]+', ' ', text.lower()).split()


def training_phrasings(task: str) -> tuple[str, ...]:
    """The phrasing templates of ``task`` that training draws from: all but the last."""
    return instructions.TASKS[task].phrasings[:-1]


def heldout_phrasings(task: str) -> tuple[str, ...]:
    """The phrasing template of ``task`` kept out of training (its last) for the held-out evaluation."""
    return instructions.TASKS[task].phrasings[-1:]


def paraphrase_phrasings(task: str) -> tuple[str, ...]:
    """The paraphrase templates of ``task``: other verbs, word orders and object names, never trained on."""
    return instructions.TASKS[task].paraphrases


def instruction(task: str, variation: int, phrasings, rng: np.random.Generator) -> str:
    """An instruction for ``variation`` of ``task`` in one of ``phrasings``."""
    return instructions.instruction(task, variation, phrasings, rng)


def task_vocabulary() -> list[str]:
    """Sorted words of every task's phrasings filled with every variation."""
    vocabulary = set()
    for task in instructions.TASKS.values():
        for template in task.phrasings:
            for variation in task.variations:
                vocabulary.update(words(template.replace('{}', variation)))
    return sorted(vocabulary)


class Tokenizer:
    """Words -> ids over a fixed vocabulary; id 0 pads, id 1 is any unknown word."""

    def __init__(self, vocabulary, max_words: int = MAX_WORDS):
        self.vocabulary = [PAD, UNK] + [w for w in vocabulary if w not in (PAD, UNK)]
        self.ids = {w: i for i, w in enumerate(self.vocabulary)}
        self.max_words = max_words

    def __len__(self) -> int:
        return len(self.vocabulary)

    def encode(self, texts) -> torch.Tensor:
        """(B, max_words) int64 ids of B texts, padded with 0 and cut at max_words words.

        A text without words becomes a lone <unk>, so every row has a token to attend to.
        """
        ids = torch.zeros(len(texts), self.max_words, dtype=torch.int64)
        for row, text in enumerate(texts):
            tokens = [self.ids.get(w, 1) for w in words(text)[:self.max_words]] or [1]
            ids[row, :len(tokens)] = torch.tensor(tokens, dtype=torch.int64)
        return ids


class InstructionEncoder(nn.Module):
    """Texts -> (token features (B, L, dim) zero at padding, pooled (B, dim)).

    The seam for a pretrained encoder: subclasses set ``dim`` and implement forward.
    """
    dim: int

    def forward(self, texts) -> tuple[torch.Tensor, torch.Tensor]:
        raise NotImplementedError


class WordEncoder(InstructionEncoder):
    """Learned word + position embeddings, one transformer layer, masked mean pooling.

    In training, ``word_dropout`` of the words become <unk>, so that id learns
    to stand for a word never seen (as a held-out phrasing's may be).
    """

    def __init__(self, vocabulary, dim: int = 64, max_words: int = MAX_WORDS, word_dropout: float = 0.1):
        super().__init__()
        self.tokenizer = Tokenizer(vocabulary, max_words)
        self.dim, self.word_dropout = dim, word_dropout
        self.embedding = nn.Embedding(len(self.tokenizer), dim, padding_idx=0)
        self.position = nn.Parameter(torch.zeros(max_words, dim))
        # No dropout: on CPU it forces PyTorch's slow attention path.
        self.layer = nn.TransformerEncoderLayer(dim, nhead=4, dim_feedforward=2 * dim, dropout=0.0,
                                                batch_first=True, norm_first=True)
        nn.init.normal_(self.embedding.weight, std=0.02)
        nn.init.normal_(self.position, std=0.02)

    def forward(self, texts) -> tuple[torch.Tensor, torch.Tensor]:
        ids = self.tokenizer.encode(texts).to(self.position.device)
        valid = ids > 0
        if self.training and self.word_dropout > 0:
            dropped = valid & (torch.rand(ids.shape, device=ids.device) < self.word_dropout)
            ids = ids.masked_fill(dropped, 1)
        features = self.layer(self.embedding(ids) + self.position, src_key_padding_mask=~valid)
        features = features * valid[..., None]
        pooled = features.sum(1) / valid.sum(1, keepdim=True).clamp(min=1)
        return features, pooled
