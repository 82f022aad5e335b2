"""What each task's instructions say, as data: its variations and phrasing templates, and how
an instruction is drawn. The simulator's tasks and the planner's language code both read it,
so the planner knows the tasks' words without the simulator.

A template's ``{}`` are filled with the variation's name (every one of them, so 'grip the {}
handle and pull the {} drawer open' names one drawer twice). The last phrasing of every task
is held out of training. ``paraphrases`` are written apart from the templates (other verbs,
word orders and names for the objects) and are only ever evaluated on, never trained on.
"""

from __future__ import annotations

import dataclasses

import numpy as np

# Numbered in this order: variation i of a coloured task is COLOUR_NAMES[i].
COLOUR_NAMES = ('red', 'maroon', 'lime', 'green', 'blue', 'navy', 'yellow', 'cyan', 'magenta', 'silver',
                'gray', 'orange', 'olive', 'purple', 'teal', 'azure', 'violet', 'rose', 'black', 'white')
DRAWER_NAMES = ('bottom', 'middle', 'top')


@dataclasses.dataclass(frozen=True)
class TaskLanguage:
    variations: tuple[str, ...]
    phrasings: tuple[str, ...]
    paraphrases: tuple[str, ...]


TASKS = {
    'reach_target': TaskLanguage(COLOUR_NAMES, (
        'reach the {} target', 'touch the {} ball with the panda gripper', 'reach the {} sphere'), (
        'move the gripper to the {} ball', 'go and touch the {} sphere', 'bring your hand to the {} target',
        'tap the {} orb', 'the {} ball: put the gripper on it')),
    'pick_up_cup': TaskLanguage(COLOUR_NAMES, (
        'pick up the {} cup', 'lift the {} cup off the table', 'grasp the {} cup and lift it'), (
        'raise the {} mug from the table', 'take hold of the {} cup and pick it up', 'grab the {} cup',
        'lift up the {} mug', 'get the {} cup up into the air')),
    'open_drawer': TaskLanguage(DRAWER_NAMES, (
        'open the {} drawer', 'grip the {} handle and pull the {} drawer open', 'slide the {} drawer open'), (
        'pull out the {} drawer', 'pull open the {} drawer', 'draw the {} drawer out towards you',
        'take hold of the {} drawer handle and pull', 'the {} drawer: get it open')),
    'open_box': TaskLanguage(('',), ('open box', 'open the box lid', 'raise the lid of the box'), (
        'flip the lid of the box up', 'lift the box lid', 'swing the lid of the box open', 'pop the box open',
        'take the lid of the box and flip it open')),
    'toilet_seat_up': TaskLanguage(('',), (
        'lift toilet seat up', 'put the toilet seat up', 'raise the toilet seat'), (
        'flip up the toilet seat', 'lift the seat of the toilet', 'tip the toilet seat up',
        'move the toilet seat to the upright position', 'pull the seat of the toilet up so it stands upright')),
    'open_door': TaskLanguage(('',), (
        'open the door', 'use the handle to open the door', 'turn the handle and pull the door open'), (
        'pull the door open', 'swing the door open', 'get the door open',
        'press down the door handle and swing the door open', 'unlatch the door and open it')),
    'take_lid_off_saucepan': TaskLanguage(('',), (
        'take lid off the saucepan', 'remove the lid from the pan',
        'using the handle, lift the lid off of the pan', 'uncover the saucepan'), (
        'lift the lid off the pot', 'take the cover off the saucepan', 'grab the saucepan lid and take it off',
        'remove the cover of the pot', 'raise the lid from the cooking pot')),
    'open_grill': TaskLanguage(('',), (
        'open the grill', 'open the bbq', 'grasp the handle and raise the cover up to open the grill',
        'open the barbecue'), (
        'lift the lid of the grill', 'raise the barbecue lid', 'flip the grill cover open',
        'swing up the lid of the bbq', 'pull the grill lid up')),
    'open_microwave': TaskLanguage(('',), (
        'open microwave', 'open the microwave door', 'swing the microwave door open',
        'pull the microwave door open'), (
        'pull open the door of the microwave', 'get the microwave open', 'open up the microwave',
        'swing out the door of the microwave', 'unlatch the microwave and swing its door out')),
    'open_oven': TaskLanguage(('',), (
        'open the oven', 'open the oven door', 'pull the oven door down',
        'grab hold of the handle and pull the oven door open'), (
        'lower the oven door', 'pull down the door of the oven', 'swing the oven door down to open it',
        'get the oven open', 'drop the oven door open by its handle')),
    'put_knife_on_chopping_board': TaskLanguage(('',), (
        'put the knife on the chopping board', 'place the knife on the chopping board',
        'pick up the knife and leave it on the chopping board',
        'move the knife from the holder to the chopping board'), (
        'set the knife down on the cutting board', 'lay the knife on the chopping board',
        'take the knife out of the block and put it on the board', 'move the knife onto the cutting board',
        'transfer the knife to the chopping board')),
}

# Task lists a --tasks argument may name: 'all', or the six the simulator had first (the
# figures measured before the other five arrived are over these).
TASK_GROUPS = {'all': tuple(TASKS), 'first_six': tuple(TASKS)[:6]}


def task_names(text: str) -> list[str]:
    """'all', 'first_six' or comma-separated task names -> the names; ValueError naming the unknown."""
    names = list(TASK_GROUPS[text]) if text in TASK_GROUPS else [t.strip() for t in text.split(',') if t.strip()]
    unknown = [n for n in names if n not in TASKS]
    if unknown or not names:
        raise ValueError(f'unknown task(s) {unknown or text!r}; tasks: {", ".join(TASKS)} '
                         f'(or {" / ".join(TASK_GROUPS)})')
    return names


def fill(template: str, name: str) -> str:
    """``template`` with every ``{}`` filled with the variation's ``name``."""
    return template.format(*[name] * template.count('{}'))


def instruction(task: str, variation: int, phrasings, rng: np.random.Generator) -> str:
    """An instruction for ``variation`` of ``task`` in one of ``phrasings``, drawn with ``rng``."""
    return fill(rng.choice(list(phrasings)), TASKS[task].variations[variation])


EVALUATION_PHRASINGS = ('seen', 'heldout', 'paraphrase')


def evaluation_instruction(task: str, seed: int, variation: int, phrasing: str = 'seen') -> str:
    """The instruction of evaluation episode (task, seed), drawn with a generator seeded by the seed
    from the task's training phrasings ('seen': all but the last), its held-out one ('heldout') or
    its paraphrases: what `hdp eval hierarchy` and `hdp demo --phrasing` say, so both run the same."""
    language = TASKS[task]
    templates = {'seen': language.phrasings[:-1], 'heldout': language.phrasings[-1:],
                 'paraphrase': language.paraphrases}
    if phrasing not in templates:
        raise ValueError(f'unknown phrasing {phrasing!r}; phrasings: {", ".join(EVALUATION_PHRASINGS)}')
    return instruction(task, variation, templates[phrasing], np.random.default_rng(seed))
