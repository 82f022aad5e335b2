"""The closed-loop hierarchy harness (Table 1 setting), with stand-in agents so it needs no checkpoint."""

import subprocess
import sys

import numpy as np
import pytest

from hdp_controller.baselines import PlannerPolicy
from hdp_controller.low_level import PlanResult
from hdp_eval.low_level_eval import oracle_episode
from hdp_planner import language
from hdp_eval.closed_loop import GraphSettings
from hdp_eval.hierarchy_eval import episode_instruction, evaluate, markdown_table, run_episode
from hdp_planner.agent import NextBestPose
from hdp_planner.grounding import Reading

pytestmark = pytest.mark.sim

HDP = [sys.executable, '-m', 'hdp_tools.cli.main']


class StandInAgent:
    """What the planner's loop needs of an agent, with no checkpoint: instructions read as given."""
    vocabulary = None

    def read(self, instruction):
        return Reading(instruction, False, None, 0.0)


class ReplayAgent(StandInAgent):
    """Predicts the expert's keyframes one after another, and records what it was shown."""

    def __init__(self, oracle):
        self.nbps, self.calls = oracle.nbps, []

    def predict(self, frames, infos, to_world, instruction, proprio):
        self.calls.append((sorted(frames), instruction, proprio))
        pose, is_open = self.nbps[min(len(self.calls), len(self.nbps)) - 1]
        return NextBestPose(pose[:3], pose[3:], is_open, 1.0)


class StuckAgent(StandInAgent):
    def __init__(self, confidence=1.0):
        self.confidence = confidence

    def predict(self, frames, infos, to_world, instruction, proprio):
        return NextBestPose(np.array([0.5, 0.0, 1.1]), np.array([1.0, 0.0, 0.0, 0.0]), True, self.confidence)


def test_agent_with_planner_solves_reach_target_and_re_observes_each_segment():
    oracle = oracle_episode('reach_target', 4001)
    agent = ReplayAgent(oracle)
    record = run_episode('nbp_planner', agent, PlannerPolicy(), 'reach_target', 4001)
    assert record.success and record.outcome == 'succeeded' and record.failure is None
    assert record.segments == len(oracle.nbps) == len(record.confidences)
    frames, instruction, (q, gripper_open) = agent.calls[0]
    assert frames == ['front', 'side'] and instruction == record.instruction and len(q) == 7
    # The nodes' own words: the planner sent each segment, the controller planned and ran it.
    assert any(line.startswith('planner: segment 1: sent pose') for line in record.status)
    assert any(line.startswith('controller: segment') and line.endswith(': done') for line in record.status)


def test_think_s_holds_each_trajectory_back_while_the_world_runs():
    oracle = oracle_episode('reach_target', 4001)
    prompt = run_episode('nbp_planner', ReplayAgent(oracle), PlannerPolicy(), 'reach_target', 4001)
    slow = run_episode('nbp_planner', ReplayAgent(oracle), PlannerPolicy(), 'reach_target', 4001,
                       settings=GraphSettings(think_s=1.0))
    assert slow.success and slow.sim_seconds >= prompt.sim_seconds + 1.0 * slow.segments - 0.1


def test_segment_budget_ends_an_episode():
    record = run_episode('nbp_planner', StuckAgent(), PlannerPolicy(), 'open_drawer', 4002,
                         settings=GraphSettings(max_segments=2))
    assert not record.success and record.segments == 2
    assert (record.outcome, record.failure) == ('failed', '2 segments done without success')


class StayPolicy:
    """A low level whose every plan stays where the arm is: it ends as far from the NBP as the hand."""
    name = 'stay'

    def plan(self, request, scene=None):
        return PlanResult(np.repeat(np.asarray(request.q, dtype=float)[None], 4, axis=0))


def test_a_plan_ending_beyond_the_reach_tolerance_is_refused_as_controller_node_would():
    kept = run_episode('stay', StuckAgent(), StayPolicy(), 'open_drawer', 4002,
                       settings=GraphSettings(max_segments=2, reach_tolerance=None))
    assert kept.failure == '2 segments done without success' and len(kept.reach_errors) == 2
    metres, degrees = kept.reach_errors[0]
    assert metres > 0.05 and degrees >= 0.0
    tight = (metres - 0.01, 180.0)
    refused = run_episode('stay', StuckAgent(), StayPolicy(), 'open_drawer', 4002,
                          settings=GraphSettings(max_segments=2, reach_tolerance=tight, plan_attempts=1))
    assert refused.outcome == 'failed' and refused.failure.startswith('segment 1 failed: stay plan ends')
    assert 'the NBP is not reachable as given' in refused.failure
    assert refused.reach_errors == [(metres, degrees)] and refused.plan_draws == [1] and refused.segments == 1
    redrawn = run_episode('stay', StuckAgent(), StayPolicy(), 'open_drawer', 4002,
                          settings=GraphSettings(max_segments=2, reach_tolerance=tight, plan_attempts=3))
    assert 'not reachable' in redrawn.failure and redrawn.plan_draws == [3]      # it never moves
    loose = run_episode('stay', StuckAgent(), StayPolicy(), 'open_drawer', 4002,
                        settings=GraphSettings(max_segments=2, reach_tolerance=(metres + 0.01, degrees + 1.0)))
    assert loose.failure == '2 segments done without success'


def test_a_first_prediction_below_min_confidence_refuses_the_instruction():
    record = run_episode('stay', StuckAgent(confidence=0.01), StayPolicy(), 'open_drawer', 4002,
                         settings=GraphSettings(min_confidence=0.05))
    assert record.outcome == 'refused' and 'below min_confidence 0.05' in record.failure
    assert record.segments == 0 and record.confidences == [0.01] and record.plan_times == []


def test_the_evaluation_refuses_by_the_nodes_rules_not_a_copy(monkeypatch):
    """A rule changed in the nodes' logic changes the evaluation's records: there is no second copy
    of it in hdp_eval. One planner rule (instruction validation) and one controller rule (the
    reach check) are replaced here by stricter ones; the records must say so."""
    from hdp_controller import segment_planning
    from hdp_controller.inputs import SegmentRefused
    from hdp_planner import planner_logic

    def no_instruction(text, vocabulary):
        raise planner_logic.InstructionRefused('a rule this test added to planner_logic')

    monkeypatch.setattr(planner_logic, 'validate_instruction', no_instruction)
    record = run_episode('stay', StuckAgent(), StayPolicy(), 'open_drawer', 4002)
    assert (record.outcome, record.failure) == ('refused', 'a rule this test added to planner_logic')
    monkeypatch.undo()

    def never_reachable(name, miss, tolerance):
        raise SegmentRefused('a rule this test added to segment_planning')

    monkeypatch.setattr(segment_planning, 'check_reach', never_reachable)
    record = run_episode('stay', StuckAgent(), StayPolicy(), 'open_drawer', 4002)
    assert record.outcome == 'failed'
    assert record.failure == 'segment 1 failed: a rule this test added to segment_planning'


def test_a_low_level_that_draws_noise_draws_each_episodes_from_its_seed():
    policy = StayPolicy()
    policy.reseed = lambda seed: seeds.append(seed)
    seeds = []
    run_episode('stay', StuckAgent(), policy, 'open_drawer', 4002, settings=GraphSettings(max_segments=1))
    run_episode('stay', StuckAgent(), policy, 'open_drawer', 4003, settings=GraphSettings(max_segments=1))
    assert seeds == [4002, 4003]


@pytest.mark.unit
def test_seen_and_heldout_instructions_differ():
    for task in ('open_drawer', 'pick_up_cup'):
        seen, heldout = (episode_instruction(task, 7, 0, p) for p in ('seen', 'heldout'))
        held = language.heldout_phrasings(task)[0]
        assert seen != heldout
        assert heldout.split()[0] == held.split()[0]


def test_paraphrase_instructions_and_all_phrasing_sets_side_by_side():
    paraphrase = episode_instruction('open_drawer', 7, 2, 'paraphrase')
    assert paraphrase in {p.format(*['top'] * p.count('{}')) for p in language.paraphrase_phrasings('open_drawer')}
    results = evaluate(StuckAgent(), {'nbp_planner': PlannerPolicy()}, ['open_box'], 1, 4003,
                       ('seen', 'heldout', 'paraphrase'), settings=GraphSettings(max_segments=1), progress=False)
    seen, heldout, paraphrase = (results['agents']['nbp_planner'][p]['open_box']['records'][0]['instruction']
                                 for p in ('seen', 'heldout', 'paraphrase'))
    assert seen in language.training_phrasings('open_box') and heldout == 'raise the lid of the box'
    assert paraphrase in language.paraphrase_phrasings('open_box')
    assert [line.split(' | ')[1] for line in markdown_table(results).splitlines()[2:]] == ['seen', 'heldout',
                                                                                          'paraphrase']


def test_evaluate_table_and_training_seed_refusal():
    planner = PlannerPolicy()
    results = evaluate(StuckAgent(), {'nbp_planner': planner}, ['reach_target'], 1, 4003,
                       settings=GraphSettings(max_segments=1), progress=False)
    table = markdown_table(results)
    assert '| nbp_planner | seen | 0 | 0.0 |' in table
    planner.training_seeds = {'reach_target': [4003]}
    with pytest.raises(ValueError, match='4003'):
        evaluate(StuckAgent(), {'nbp_planner': planner}, ['reach_target'], 1, 4003, progress=False)
    agent = StuckAgent()
    agent.training_seeds = {'reach_target': [4003]}
    with pytest.raises(ValueError, match='next-best-pose agent was trained on reach_target seeds 4003'):
        evaluate(agent, {'nbp_planner': PlannerPolicy()}, ['reach_target'], 1, 4003, progress=False)


@pytest.mark.dds
def test_cli_help():
    result = subprocess.run([*HDP, 'eval', 'hierarchy', '--help'], text=True, capture_output=True, timeout=300)
    assert result.returncode == 0 and '--phrasings' in result.stdout


def test_the_ladder_runs_both_tables_on_every_rung_with_its_sensor():
    from hdp_eval import ladder
    rungs = ladder.rungs(extrinsic_mm=5.0, extrinsic_deg=1.0, latency_ms=60.0, camera_hz=15.0)
    assert [r.name for r in rungs] == ['ideal', 'd415', '+ 5 mm / 1 deg', '+ 60 ms at 15 Hz']
    results = ladder.evaluate(StuckAgent(), {'nbp_planner': PlannerPolicy()}, {'planner': PlannerPolicy()},
                              ['reach_target'], 1, 4003, rungs, GraphSettings(max_segments=1), progress=False)
    sensors = [r['sensor'] for r in results['rungs']]
    assert [s['profile']['name'] for s in sensors] == ['ideal', 'd415', 'd415', 'd415']
    assert [(s['extrinsic_error_mm'], s['latency_ms']) for s in sensors] == [(0, 0), (0, 0), (5, 0), (5, 60)]
    assert [r['camera_hz'] for r in results['rungs']] == [GraphSettings().camera_hz] * 3 + [15.0]
    # The hierarchy's episodes ran under each rung's cameras: the agent's one segment, then out of budget.
    for rung in results['rungs']:
        record, = rung['table1']['agents']['nbp_planner']['seen']['reach_target']['records']
        assert record['segments'] == 1 and not record['success']
    assert ladder.overall(results) == {'nbp_planner': [0.0] * 4, 'planner (Table 2)': [100.0] * 4}
    table = ladder.markdown_table(results)
    assert '| planner (Table 2) | 100.0 | 100.0 | 100.0 | 100.0 | +0.0 |' in table
    assert '**+ 60 ms at 15 Hz** (cameras at 15 Hz)' in table
    with pytest.raises(ValueError, match='at least one rung'):
        ladder.evaluate(StuckAgent(), {'nbp_planner': PlannerPolicy()}, {}, ['reach_target'], 1, 4003, [])


def _ladder_results(rung_successes: list[dict]) -> dict:
    """A ladder's results with one Table 1 row 'hdp' whose (task, seed) -> (success, segments,
    failure) are given per rung."""
    rungs = []
    for i, episodes in enumerate(rung_successes):
        per_task = {}
        for (task, seed), (success, segments, failure) in episodes.items():
            per_task.setdefault(task, {'records': []})['records'].append(
                {'task': task, 'seed': seed, 'success': success, 'segments': segments, 'failure': failure,
                 'confidences': [0.1 * seed + 0.01 * i, 0.9]})
        rungs.append({'name': f'rung {i}', 'table1': {'agents': {'hdp': {'seen': per_task}}}, 'table2': None})
    return {'rungs': rungs}


@pytest.mark.unit
def test_the_ladder_keeps_the_rungs_asked_for_in_its_order():
    from hdp_eval import ladder
    assert [r.name for r in ladder.rungs(only=('latency', 'ideal'))] == ['ideal', '+ 60 ms at 15 Hz']
    with pytest.raises(ValueError, match='unknown rung.*lag: choose from ideal, d415'):
        ladder.rungs(only=('ideal', 'lag'))


@pytest.mark.unit
def test_the_ladder_says_where_a_rung_loses_the_first_rungs_successes():
    from hdp_eval import ladder
    ideal = {('open_oven', 1): (True, 3, None), ('open_oven', 2): (True, 3, None),
             ('stack_blocks', 1): (True, 4, None), ('stack_blocks', 2): (False, 2, 'time budget spent')}
    noisy = {('open_oven', 1): (False, 1, 'controller failed: no path (goal 0.41 m away)'),
             ('open_oven', 2): (False, 1, 'controller failed: no path (goal 0.12 m away)'),
             ('stack_blocks', 1): (False, 2, "refused: confidence 0.21 below 0.3 for 'stack'"),
             ('stack_blocks', 2): (True, 4, None)}
    results = _ladder_results([ideal, noisy])
    loss, = ladder.losses(results)
    assert (loss['rung'], loss['row'], loss['lost'], loss['gained']) == ('rung 1', 'hdp', 3, 1)
    assert loss['by_task'] == {'open_oven': 2, 'stack_blocks': 1}
    assert loss['by_segments_run'] == {1: 2, 2: 1}
    # The same cause with other numbers counts as one reason.
    assert loss['by_reason'] == {'controller failed: no path': 2, 'refused: confidence N below N for': 1}
    text = ladder.losses_markdown(results)
    assert text.startswith('- **hdp, rung 1**: lost 3 of the first rung\'s successes, gained 1.')
    assert '2 x "controller failed: no path"' in text
    # A rung that changes nothing says nothing.
    assert ladder.losses_markdown(_ladder_results([ideal, ideal])) == ''
    # The successes' first confidences: seed 1 on rung 0 (0.10), seed 2 on rung 1 (0.21).
    assert ladder.least_confident_success(results) == {'hdp': pytest.approx(0.1)}


@pytest.mark.dds
def test_ladder_cli_refuses_nothing_to_run():
    result = subprocess.run([*HDP, 'eval', 'ladder', '--seed-start', '6000', '--agents', '', '--methods', ''],
                            text=True, capture_output=True, timeout=300)
    assert result.returncode != 0 and 'nothing to run: give --agents or --methods' in result.stderr
