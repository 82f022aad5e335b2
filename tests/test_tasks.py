"""Each task: random layout from the seed, >= 3 phrasings, not solved at the start, solved by its expert."""

import numpy as np
import pytest

from hdp_sim_bridge.experts import reachable_scene, run_expert
from hdp_sim_bridge.tasks import TASKS, make_task
from hdp_sim_bridge.world import PandaWorld


@pytest.fixture(scope='module')
def world():
    with PandaWorld() as w:
        yield w


@pytest.mark.parametrize('name', sorted(TASKS))
def test_expert_solves_and_start_is_unsolved(world, name):
    task, rng, _ = reachable_scene(world, name, 11)
    assert len(task.phrasings) >= 3
    assert not task.success(world)
    result = run_expert(world, task, rng)
    assert result.success, result.reason


@pytest.mark.parametrize('name', sorted(TASKS))
def test_seed_randomises_the_layout(world, name):
    poses = []
    for seed in (1, 2):
        world.reset(seed)
        task = make_task(name)
        task.reset(world, np.random.default_rng(seed), 0)
        poses.append(np.concatenate([np.asarray(world.client.getBasePositionAndOrientation(b)[0])
                                     for b in task.bodies.values()]))
    assert not np.allclose(poses[0], poses[1])


def test_bad_variation_and_task_refused(world):
    with pytest.raises(ValueError, match='variations 0..2'):
        make_task('open_drawer').reset(world, np.random.default_rng(0), 3)
    with pytest.raises(ValueError, match='unknown task'):
        make_task('make_tea')
