"""The tasks' instructions are data both the simulator and the planner read (hdp_data.instructions)."""

import numpy as np
import pytest

from hdp_data import instructions
from hdp_planner import language
from hdp_sim_bridge import objects
from hdp_sim_bridge.tasks import TASKS

pytestmark = pytest.mark.unit


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


def test_evaluation_instructions_are_the_seeds_draw_from_each_phrasing_set():
    """What the harness and `hdp demo --phrasing` say on a seed: the same text for the same
    (task, seed, variation, phrasing), drawn from that set's templates only."""
    from hdp_eval.hierarchy_eval import episode_instruction
    for task, variation in (('reach_target', 4), ('open_drawer', 2), ('open_oven', 0)):
        sets = {'seen': language.training_phrasings(task), 'heldout': language.heldout_phrasings(task),
                'paraphrase': language.paraphrase_phrasings(task)}
        for phrasing, templates in sets.items():
            texts = {instructions.evaluation_instruction(task, seed, variation, phrasing) for seed in range(1000, 1040)}
            allowed = {t.format(*[instructions.TASKS[task].variations[variation]] * t.count('{}')) for t in templates}
            assert texts == allowed                    # 40 seeds draw every template of the set, nothing else
            assert instructions.evaluation_instruction(task, 1003, variation, phrasing) == \
                episode_instruction(task, 1003, variation, phrasing)
    with pytest.raises(ValueError, match="unknown phrasing 'nonsense'"):
        instructions.evaluation_instruction('reach_target', 1000, 0, 'nonsense')


def test_task_lists_by_name_group_or_comma_list():
    assert instructions.task_names('all') == list(instructions.TASKS) and len(instructions.TASKS) == 11
    assert instructions.task_names('first_six') == ['reach_target', 'pick_up_cup', 'open_drawer', 'open_box',
                                                     'toilet_seat_up', 'open_door']
    assert instructions.task_names(' open_oven, open_grill ') == ['open_oven', 'open_grill']
    for bad in ('make_tea', 'open_oven,make_tea', '', ','):
        with pytest.raises(ValueError, match='unknown task'):
            instructions.task_names(bad)


def _filled(task: str, templates) -> set[str]:
    """Every instruction ``templates`` give over the task's variations, as words."""
    return {' '.join(language.words(t.format(*[v] * t.count('{}')))) for t in templates
            for v in instructions.TASKS[task].variations}


def test_every_task_has_five_paraphrases_apart_from_its_templates():
    for name, task in instructions.TASKS.items():
        paraphrases = language.paraphrase_phrasings(name)
        assert len(set(paraphrases)) == len(paraphrases) >= 5, name
        named = task.variations != ('',)
        assert all(('{}' in p) == named for p in paraphrases), name      # fills its variation as templates do
        assert not set(paraphrases) & set(task.phrasings), name
        assert not _filled(name, paraphrases) & _filled(name, task.phrasings), name
        rng = np.random.default_rng(0)
        drawn = {instructions.instruction(name, int(rng.integers(len(task.variations))),
                                          language.training_phrasings(name), rng) for _ in range(300)}
        assert not drawn & {p.format(*[v] * p.count('{}')) for p in paraphrases for v in task.variations}


def test_offline_evaluation_draws_paraphrases_of_the_samples_variation():
    from hdp_planner.dataset import KeyframeDataset
    from hdp_planner.evaluate import evaluation_item
    from test_planner_agent import synthetic_episode
    rng = np.random.default_rng(0)
    dataset = KeyframeDataset([synthetic_episode(rng, 'open_drawer')])           # variation 1: middle
    middle = {p.format(*['middle'] * p.count('{}')) for p in language.paraphrase_phrasings('open_drawer')}
    drawn = {evaluation_item(dataset, 0, rng, 'paraphrase').instruction for _ in range(40)}
    assert drawn == middle
    assert evaluation_item(dataset, 0, rng, 'heldout').instruction == 'slide the middle drawer open'
    with pytest.raises(ValueError, match='unknown phrasing'):
        evaluation_item(dataset, 0, rng, 'nonsense')
