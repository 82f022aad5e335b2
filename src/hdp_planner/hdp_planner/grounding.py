"""Reading an instruction as one the agent was trained on, before the agent sees it.

A typed instruction ("flip the lid of the box up") is matched to the nearest training template
("open the box lid") by the frozen sentence encoder, with the objects' names (the variations:
colours, drawers) taken out of both sides so that they cannot decide the match: whole sentences
that share a colour embed close even across tasks ("touch the red ball ..." lies nearest to "lift
the red cup ..." once the ball's other phrasing is left out). The variation is then read word
for word. The agent is given the template filled with that variation: an instruction it has
seen in training.

An instruction is passed through unchanged (the agent's own confidence then decides) when its
nearest template is less similar than ``min_similarity``, or when its task has variations and it
names none or several of them.

min_similarity 0.6 was chosen on the training templates alone, with no evaluation phrasing:
each template left out in turn, its nearest remaining template belongs to its own task in 25 of
27 cases with cosine >= 0.62 (the two misses: 0.34 and 0.43), and twelve off-task requests ("make
me a sandwich", "turn on the lights", ...) reach at most 0.57 ("close the window" -> "open the
door"). What it cannot tell apart is an opposite: "close the drawer" reads as "open the drawer".
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import torch

from hdp_data import instructions

from .language import training_phrasings, words
from .sentence_encoder import frozen_minilm

DEFAULT_MIN_SIMILARITY = 0.6


class Reading(NamedTuple):
    """What the agent is given for one instruction: ``text`` (a training instruction, or the
    instruction itself when ``grounded`` is False), the task read and the template's cosine."""
    text: str
    grounded: bool
    task: str | None
    similarity: float


def _without(names: set[str], text: str) -> str:
    """``text`` lower-cased, punctuation and the words in ``names`` dropped: the sentence to match."""
    return ' '.join(w for w in words(text) if w not in names)


class InstructionGrounding:
    """Instruction -> Reading over the training templates of ``tasks`` (hdp_data.instructions)."""

    def __init__(self, tasks, min_similarity: float = DEFAULT_MIN_SIMILARITY):
        if not 0.0 <= min_similarity <= 1.0:
            raise ValueError(f'min_similarity must be in [0, 1], got {min_similarity}')
        self.min_similarity = min_similarity
        self.encoder = frozen_minilm()
        self.variation_words = {w for t in tasks for name in instructions.TASKS[t].variations for w in words(name)}
        self.templates = [(task, template) for task in tasks for template in training_phrasings(task)]
        self.embeddings = self._embed([template for _, template in self.templates])   # (T, 384)
        self.read = functools.lru_cache(maxsize=1024)(self._read)

    def _embed(self, texts: list[str]) -> torch.Tensor:
        return torch.stack([sentence for _, sentence in self.encoder([_without(self.variation_words, t)
                                                                     for t in texts])])

    def _read(self, text: str) -> Reading:
        similarities = self.embeddings @ self._embed([text])[0]
        best = int(similarities.argmax())
        task, template = self.templates[best]
        similarity = float(similarities[best])
        unchanged = Reading(text, False, None, similarity)
        if similarity < self.min_similarity:
            return unchanged
        variations = instructions.TASKS[task].variations
        said = set(words(text))
        named = variations if len(variations) == 1 else [n for n in variations if set(words(n)) <= said]
        if len(named) != 1:
            return unchanged._replace(task=task)
        return Reading(instructions.fill(template, named[0]), True, task, similarity)
