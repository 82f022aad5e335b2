"""What each task's instructions say, as data: its variations and phrasing templates, and how
an instruction is drawn. The simulator's tasks and the planner's language code both read it,
so the planner knows the tasks' words without the simulator.

A template's ``{}`` are filled with the variation's name (every one of them, so 'grip the {}
handle and pull the {} drawer open' names one drawer twice). The last phrasing of every task
is held out of training.
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


TASKS = {
    'reach_target': TaskLanguage(COLOUR_NAMES, (
        'reach the {} target', 'touch the {} ball with the panda gripper', 'reach the {} sphere')),
    'pick_up_cup': TaskLanguage(COLOUR_NAMES, (
        'pick up the {} cup', 'lift the {} cup off the table', 'grasp the {} cup and lift it')),
    'open_drawer': TaskLanguage(DRAWER_NAMES, (
        'open the {} drawer', 'grip the {} handle and pull the {} drawer open', 'slide the {} drawer open')),
    'open_box': TaskLanguage(('',), ('open box', 'open the box lid', 'raise the lid of the box')),
    'toilet_seat_up': TaskLanguage(('',), (
        'lift toilet seat up', 'put the toilet seat up', 'raise the toilet seat')),
    'open_door': TaskLanguage(('',), (
        'open the door', 'use the handle to open the door', 'turn the handle and pull the door open')),
    'take_lid_off_saucepan': TaskLanguage(('',), (
        'take lid off the saucepan', 'remove the lid from the pan',
        'using the handle, lift the lid off of the pan', 'uncover the saucepan')),
    'open_grill': TaskLanguage(('',), (
        'open the grill', 'open the bbq', 'grasp the handle and raise the cover up to open the grill',
        'open the barbecue')),
    'open_microwave': TaskLanguage(('',), (
        'open microwave', 'open the microwave door', 'swing the microwave door open',
        'pull the microwave door open')),
    'open_oven': TaskLanguage(('',), (
        'open the oven', 'open the oven door', 'pull the oven door down',
        'grab hold of the handle and pull the oven door open')),
    'put_knife_on_chopping_board': TaskLanguage(('',), (
        'put the knife on the chopping board', 'place the knife on the chopping board',
        'pick up the knife and leave it on the chopping board',
        'move the knife from the holder to the chopping board')),
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


def instruction(task: str, variation: int, phrasings, rng: np.random.Generator) -> str:
    """An instruction for ``variation`` of ``task`` in one of ``phrasings``, drawn with ``rng``."""
    template = rng.choice(list(phrasings))
    return template.format(*[TASKS[task].variations[variation]] * template.count('{}'))
