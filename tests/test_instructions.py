"""The tasks' instructions are data both the simulator and the planner read (hdp_msgs_py.instructions)."""

import numpy as np
import pytest

from hdp_msgs_py import instructions
from hdp_planner import language
from hdp_sim_bridge import objects
from hdp_sim_bridge.tasks import TASKS


def test_the_simulator_names_the_variations_the_instructions_name():
    assert instructions.COLOUR_NAMES == tuple(objects.COLOURS)        # variation i is the i-th colour
    assert set(TASKS) == set(instructions.TASKS)
    for name, task in TASKS.items():
        assert (task.variations, task.phrasings) == (instructions.TASKS[name].variations,
                                                     instructions.TASKS[name].phrasings)


def test_an_instruction_names_its_variation_wherever_the_template_asks():
    rng = np.random.default_rng(0)
    two = ('grip the {} handle and pull the {} drawer open',)
    assert instructions.instruction('open_drawer', 2, two, rng) == 'grip the top handle and pull the top drawer open'
    assert instructions.instruction('open_box', 0, ('open box',), rng) == 'open box'
    task = TASKS['reach_target']()
    task.variation = 4
    assert task.instruction(np.random.default_rng(3)) == language.instruction(
        'reach_target', 4, task.phrasings, np.random.default_rng(3))


def test_the_last_phrasing_is_held_out_of_training():
    for name, task in instructions.TASKS.items():
        assert language.training_phrasings(name) + language.heldout_phrasings(name) == task.phrasings
        assert len(language.heldout_phrasings(name)) == 1


def test_task_lists_by_name_group_or_comma_list():
    assert instructions.task_names('all') == list(instructions.TASKS) and len(instructions.TASKS) == 11
    assert instructions.task_names('first_six') == ['reach_target', 'pick_up_cup', 'open_drawer', 'open_box',
                                                     'toilet_seat_up', 'open_door']
    assert instructions.task_names(' open_oven, open_grill ') == ['open_oven', 'open_grill']
    for bad in ('make_tea', 'open_oven,make_tea', '', ','):
        with pytest.raises(ValueError, match='unknown task'):
            instructions.task_names(bad)
