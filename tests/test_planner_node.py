"""planner_node: instruction validation, the observe -> predict -> send -> wait loop, the node as
a process (refusals, camera timeout, segments against a stand-in controller), and `hdp launch`.

No trained checkpoint is used: the processes load a tiny untrained agent written to tmp_path.
Run as a script, this file is the stand-in controller: `python test_planner_node.py controller`.
"""

import json
import os
import re
import signal
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
import rclpy
import torch

from hdp_motion import panda
from hdp_msgs_py import conversions, topics
from hdp_msgs_py.msg import Header, JointState, TFMessage, Time, TransformStamped
from hdp_msgs_py.outcome import Outcome, StatusLine
from hdp_planner.agent import NextBestPose
from hdp_planner.grounding import Reading
from hdp_planner.planner_logic import (MAX_INSTRUCTION_CHARS, InstructionRefused, Observations, PlannerLoop,
                                       Prediction, SegmentGoal, validate_instruction)

pytestmark = pytest.mark.unit

torch.set_num_threads(1)

VOCABULARY = ('open', 'the', 'drawer', 'red', 'cup', 'pick', 'up', 'to', 'and')


# --- instructions -------------------------------------------------------------------------

@pytest.mark.parametrize('text, reason', [
    ('', 'empty'), ('   \n', 'empty'),
    ('open the drawer ' * 20, f'more than {MAX_INSTRUCTION_CHARS}'),
    ('make me a sandwich', 'names anything the agent was trained on'),
    ('the the and to up', 'names anything'),           # filler words alone name no task
])
def test_instructions_are_refused_with_a_reason(text, reason):
    with pytest.raises(InstructionRefused, match=reason):
        validate_instruction(text, VOCABULARY)


def test_valid_instructions_are_stripped_and_may_have_unknown_words():
    assert validate_instruction('  Open the RED drawer, please!\n', VOCABULARY) == 'Open the RED drawer, please!'
    assert validate_instruction('cup ' + 'x' * (MAX_INSTRUCTION_CHARS - 4), VOCABULARY)


def test_without_a_vocabulary_only_empty_and_overlong_instructions_are_refused():
    """A sentence-encoder agent reads words no template had; its confidence refuses the rest."""
    assert validate_instruction(' uncover the saucepan ', None) == 'uncover the saucepan'
    for text, reason in (('  ', 'empty'), ('x' * (MAX_INSTRUCTION_CHARS + 1), 'more than')):
        with pytest.raises(InstructionRefused, match=reason):
            validate_instruction(text, None)


# --- the loop, with a fake agent and synthetic frames ---------------------------------------------

class FakeAgent:
    def __init__(self):
        self.calls = []
        self.clouds = []          # the cloud each prediction saw (xyz, colours), one of its own per call

    def read(self, instruction):
        return Reading(instruction, False, None, 0.0)

    def predict(self, frames, infos, to_world, instruction, proprio):
        self.calls.append((frames, infos, to_world, instruction, proprio))
        self.clouds.append((np.full((2, 3), len(self.calls), np.float32), np.zeros((2, 3), np.uint8)))
        return NextBestPose(np.array([0.5, 0.1, 0.9]), np.array([1.0, 0.0, 0.0, 0.0]), len(self.calls) % 2 == 0, 0.75,
                            self.clouds[-1])


def _stamp(seconds: float) -> Time:
    return conversions.seconds_to_time(seconds)


def feed_frames(observations: Observations, seconds: float, cameras=topics.CAMERAS) -> None:
    """Colour, depth, camera_info, extrinsics and a joint state, all stamped ``seconds``."""
    for camera in cameras:
        header = Header(stamp=_stamp(seconds), frame_id=f'{camera}_optical')
        observations.on_color(camera, conversions.numpy_to_image(np.zeros((4, 6, 3), np.uint8), 'rgb8', header))
        observations.on_depth(camera, conversions.numpy_to_image(np.full((4, 6), 900, np.uint16), '16UC1', header))
        observations.on_info(camera, conversions.intrinsics_to_camera_info(
            conversions.Intrinsics(5.0, 5.0, 3.0, 2.0, 6, 4), f'{camera}_optical', _stamp(seconds)))
        observations.on_tf_static(TFMessage(transforms=[TransformStamped(
            header=Header(frame_id='world'), child_frame_id=f'{camera}_optical',
            transform=conversions.matrix_to_transform(np.eye(4)))]))
    observations.on_joint_state(JointState(header=Header(stamp=_stamp(seconds)),
                                           name=list(panda.ARM_JOINTS + panda.FINGER_JOINTS),
                                           position=[*panda.HOME, 0.04, 0.04]))


def _loop(**kwargs) -> PlannerLoop:
    return PlannerLoop(FakeAgent(), VOCABULARY, **{'max_segments': 3, 'camera_timeout_s': 2.0,
                                                   'result_timeout_s': 10.0, **kwargs})


def _result(stamp, text='done'):
    return Header(stamp=stamp, frame_id=text)


_KINDS = {Prediction: 'prediction', SegmentGoal: 'segment_goal', Outcome: 'outcome'}


def _kinds(outputs) -> list[str]:
    """Each record's kind: 'prediction', 'segment_goal', 'outcome', or a StatusLine's 'info' /
    'error'; any other record is an error."""
    return [('error' if o.error else 'info') if type(o) is StatusLine else _KINDS[type(o)] for o in outputs]


def _texts(outputs, kind=None):
    """The status lines' texts, all or those of ``kind`` ('info' or 'error')."""
    assert kind in (None, 'info', 'error')
    return [o.text for o in outputs if type(o) is StatusLine and kind in (None, 'error' if o.error else 'info')]


def _outcomes(outputs) -> list[tuple]:
    """(instruction, result, segments) of each outcome, after a JSON round trip as on the wire."""
    return [(o.instruction, o.result, o.segments) for o in
            (Outcome.from_json(o.to_json()) for o in outputs if type(o) is Outcome)]


def _sent(outputs) -> SegmentGoal:
    """The one SegmentGoal of a step that predicted and sent a segment (after its Prediction,
    before its status line); its gripper goal and NBP carry one stamp."""
    assert _kinds(outputs) == ['prediction', 'segment_goal', 'info'], _kinds(outputs)
    goal = outputs[1]
    assert goal.gripper_goal.header.stamp == goal.nbp.header.stamp
    return goal


def test_an_instruction_read_as_a_training_one_says_so_and_the_agent_is_asked_with_the_typed_words():
    loop = _loop()
    loop.agent.read = lambda text: Reading('open the top drawer', True, 'open_drawer', 0.9)
    feed_frames(loop.observations, 1.0)
    assert _texts(loop.on_instruction('pull out the top drawer', now_s=100.0)) == [
        "instruction 'pull out the top drawer': up to 3 segments, read as 'open the top drawer' (similarity 0.90)"]
    loop.step(100.1, 5_000_000_000)
    assert loop.agent.calls[0][3] == 'pull out the top drawer'      # the agent grounds it itself


def test_a_segment_sends_gripper_goal_and_nbp_with_one_stamp_then_waits_for_fresh_frames():
    loop = _loop()
    feed_frames(loop.observations, 1.0)
    assert 'up to 3 segments' in _texts(loop.on_instruction('open the drawer', now_s=100.0))[0]
    out = loop.step(100.1, 5_000_000_000)
    assert _kinds(out) == ['prediction', 'segment_goal', 'info']
    prediction, goal, pose = out[0], out[1].gripper_goal, out[1].nbp
    assert goal.header.stamp == pose.header.stamp == Time(sec=5)
    assert prediction.confidence == 0.75 and prediction.seconds >= 0.0
    assert prediction.cloud is loop.agent.clouds[0]                           # what the agent saw, for a viewer
    assert goal.name == [topics.GRIPPER_GOAL_JOINT] and list(goal.position) == [0.0]      # first call: close
    assert pose.header.frame_id == 'world' and pose.pose.position.x == pytest.approx(0.5)
    frames, infos, to_world, instruction, (q, gripper_open) = loop.agent.calls[0]
    assert instruction == 'open the drawer' and np.allclose(q, panda.HOME) and gripper_open is True
    assert frames['front'][0].shape == (4, 6, 3) and frames['side'][1].dtype == np.uint16
    assert to_world['side'].child_frame_id == 'side_optical'
    assert loop.step(101.0, 6_000_000_000) == []                              # waiting for the result

    assert loop.on_result(_result(Time(sec=4)), 101.0) == []                  # someone else's segment
    loop.observations.on_joint_state(JointState(header=Header(stamp=_stamp(1.5)), name=list(panda.ARM_JOINTS +
                                     panda.FINGER_JOINTS), position=[*panda.HOME, 0.0, 0.0]))
    line = _texts(loop.on_result(_result(pose.header.stamp), 102.5))[0]
    assert line == 'segment 1: pose (0.500, 0.100, 0.900) gripper close -> done in 2.4 s'
    assert loop.gripper_open is False
    assert loop.step(102.6, 7_000_000_000) == []                              # the frames are from before
    feed_frames(loop.observations, 2.0)
    out = loop.step(102.7, 7_000_000_000)
    assert _sent(out).nbp.header.stamp == Time(sec=7) and loop.agent.calls[1][4][1] is False
    assert out[0].cloud is loop.agent.clouds[1]                               # this prediction's cloud


def test_the_loop_ends_on_success_reported_after_the_segment():
    loop = _loop()
    loop.on_success(True)                                   # stale: from before the instruction
    feed_frames(loop.observations, 1.0)
    loop.on_instruction('open the drawer', 0.0)
    assert loop.step(0.1, 1) == []                          # waits for a fresh success report
    loop.on_success(False)
    stamp = _sent(loop.step(0.2, 2)).nbp.header.stamp
    loop.on_result(_result(stamp), 1.0)
    loop.on_success(True)
    out = loop.step(1.1, 3)
    assert _texts(out) == ["instruction 'open the drawer': task succeeded after 1 segments"]
    assert _outcomes(out) == [('open the drawer', 'succeeded', 1)]
    assert loop.instruction is None and loop.step(1.2, 4) == []


def test_max_segments_ends_the_loop_on_a_robot_without_success_reports():
    loop = _loop(max_segments=2)
    loop.on_instruction('pick up the red cup', 0.0)
    for i in range(2):
        feed_frames(loop.observations, 1.0 + i)
        stamp = _sent(loop.step(0.1 + i, 10 + i)).nbp.header.stamp
        loop.on_result(_result(stamp), 0.5 + i)
    out = loop.step(3.0, 20)
    assert _texts(out, 'info') == ["instruction 'pick up the red cup': 2 segments done (this robot reports no success)"]
    assert _outcomes(out) == [('pick up the red cup', 'ended', 2)]


def test_frames_of_the_clock_before_a_reset_never_count_as_fresh():
    """A simulator reset restarts sim time. The side camera's last frame of the old episode
    (stamped 20 s) must not pass for a fresh one of the new episode, whose clock is at 1 s."""
    observations = Observations()
    feed_frames(observations, 20.0)                                        # the old episode
    observations.on_joint_state(JointState(header=Header(stamp=_stamp(0.5)), name=list(
        panda.ARM_JOINTS + panda.FINGER_JOINTS), position=[*panda.HOME, 0.04, 0.04]))     # reset: back to 0.5 s
    assert 'side camera colour' in observations.missing(0)                 # dropped with the old clock
    feed_frames(observations, 1.0, cameras=('front',))                     # the side camera stopped
    late = conversions.numpy_to_image(np.zeros((4, 6, 3), np.uint8), 'rgb8', Header(stamp=_stamp(20.5)))
    observations.on_color('side', late)                                    # an old-clock frame, in flight
    assert observations.missing(500_000_000) == ['side camera colour', 'side camera depth']
    feed_frames(observations, 1.5)
    assert observations.missing(500_000_000) == []


def test_camera_timeout_stops_the_instruction_and_names_the_camera():
    loop = _loop()
    feed_frames(loop.observations, 1.0, cameras=('front',))
    loop.on_instruction('open the drawer', 10.0)
    assert loop.step(11.9, 1) == []
    out = loop.step(12.1, 2)
    assert _texts(out, 'error') == ["instruction 'open the drawer': camera side timed out after 2.0 s "
                                    "(no fresh side camera colour, side camera depth, side camera_info)"]
    assert _outcomes(out) == [('open the drawer', 'failed', 0)]
    assert loop.instruction is None and loop.agent.calls == []


def test_a_missing_result_is_reported_and_the_loop_re_observes_and_sends_a_fresh_nbp():
    loop = _loop()
    feed_frames(loop.observations, 1.0)
    loop.on_instruction('open the drawer', 0.0)
    lost = _sent(loop.step(0.1, 1)).nbp.header.stamp
    loop.gripper_open = True                                  # as if an earlier segment had opened it
    assert loop.step(10.1, 2) == []                           # within result_timeout_s
    loop.observations.on_joint_state(JointState(header=Header(stamp=_stamp(1.5)), name=list(panda.ARM_JOINTS +
                                     panda.FINGER_JOINTS), position=[*panda.HOME, 0.04, 0.04]))
    out = loop.step(10.2, 3)
    assert _texts(out, 'error') == ['segment 1: no result from the controller within 10.0 s '
                                    '(is controller_node running?); re-observing']
    assert loop.instruction == 'open the drawer' and loop.segment is None
    assert loop.step(10.3, 4) == []                           # the frames are from before the timeout
    feed_frames(loop.observations, 2.0)                       # fingers at 0.08 m: open
    out = loop.step(10.4, 5)
    assert _sent(out).nbp.header.stamp != lost and 'segment 2: sent' in _texts(out)[0]
    assert loop.agent.calls[1][4][1] is True                  # the gripper state read from the fingers again
    assert loop.on_result(_result(lost), 11.0) == []          # the lost segment's late result is ignored
    assert _texts(loop.on_result(_result(out[1].nbp.header.stamp), 12.0))[0].startswith('segment 2: pose')


def test_a_new_instruction_reads_the_gripper_from_the_fingers_not_the_last_goal():
    loop = _loop()
    feed_frames(loop.observations, 1.0)
    loop.on_instruction('open the drawer', 0.0)
    stamp = _sent(loop.step(0.1, 1)).nbp.header.stamp             # the fake agent: close
    loop.on_result(_result(stamp), 1.0)
    assert loop.gripper_open is False
    loop.on_instruction('open the drawer', 2.0)                   # e.g. after a sim reset: hand open
    feed_frames(loop.observations, 3.0)                           # fingers at 0.08 m
    loop.step(2.1, 2)
    assert loop.agent.calls[1][4][1] is True


def test_a_missing_result_on_the_last_segment_ends_the_instruction_after_a_last_look():
    loop = _loop(max_segments=1)
    feed_frames(loop.observations, 1.0)
    loop.on_instruction('open the drawer', 0.0)
    loop.on_success(False)
    assert _texts(loop.step(0.1, 1)) == ['segment 1: sent pose (0.500, 0.100, 0.900) gripper close (confidence 0.75)']
    assert _texts(loop.step(10.2, 2), 'error') == ['segment 1: no result from the controller within 10.0 s '
                                                   '(is controller_node running?)']
    loop.on_success(True)                                     # the lost segment finished the task after all
    assert _texts(loop.step(10.3, 3)) == ["instruction 'open the drawer': task succeeded after 1 segments"]


def test_a_missing_result_lets_a_queued_instruction_start():
    loop = _loop()
    feed_frames(loop.observations, 1.0)
    loop.on_instruction('open the drawer', 0.0)
    loop.step(0.1, 1)
    assert _texts(loop.on_instruction('pick up the cup', 1.0)) == [
        "instruction 'pick up the cup' waits: it replaces 'open the drawer' when segment 1 ends"]
    out = loop.step(10.2, 2)
    assert _texts(out) == ['segment 1: no result from the controller within 10.0 s (is controller_node running?)',
                           "instruction 'open the drawer': replaced by 'pick up the cup'"]
    assert _outcomes(out) == [('open the drawer', 'replaced', 1)]
    assert _texts(loop.step(10.3, 3))[0] == "instruction 'pick up the cup': up to 3 segments"


def test_a_failed_segment_stops_the_instruction_and_a_queued_one_starts_after_the_result():
    loop = _loop()
    feed_frames(loop.observations, 1.0)
    loop.on_instruction('open the drawer', 0.0)
    stamp = _sent(loop.step(0.1, 1)).nbp.header.stamp
    assert 'waits' in _texts(loop.on_instruction('pick up the cup', 0.2))[0]
    out = loop.on_result(_result(stamp, 'failed: no path'), 1.0)
    assert _texts(out) == ['segment 1: pose (0.500, 0.100, 0.900) gripper close -> failed: no path in 0.9 s',
                           "instruction 'open the drawer': segment 1 failed: no path"]
    assert _outcomes(out) == [('open the drawer', 'failed', 1)]
    assert _texts(loop.step(1.1, 2))[0] == "instruction 'pick up the cup': up to 3 segments"
    assert loop.instruction == 'pick up the cup' and not loop.waiting


def _burst(loop, count: int, start_s: float = 0.0) -> list:
    """``count`` distinct instructions 20 ms apart, as the probe sent them; every record returned."""
    out = []
    for i in range(count):
        out += loop.on_instruction(f'open the drawer {i}', start_s + 0.02 * i)
    return out


def test_replace_a_burst_gets_one_outcome_each_and_the_newest_runs():
    loop = _loop()                                  # queue_policy replace, the default
    out = _burst(loop, 50)
    assert [o[:2] for o in _outcomes(out)] == [(f'open the drawer {i}', 'replaced') for i in range(49)]
    assert loop.instruction is None and list(loop.waiting) == ['open the drawer 49']
    loop.step(1.0, 1)
    assert loop.instruction == 'open the drawer 49'
    out = loop.step(3.1, 2)                         # no frames: the camera timeout ends it
    assert _outcomes(out) == [('open the drawer 49', 'failed', 0)]


def test_queue_takes_instructions_in_turn_and_refuses_beyond_max_queued():
    loop = _loop(queue_policy='queue', max_queued=3)
    out = _burst(loop, 6)
    assert _outcomes(out) == [('open the drawer 4', 'refused', 0), ('open the drawer 5', 'refused', 0)]
    assert [o.reason for o in out if type(o) is Outcome] == ['queue full: 3 instructions wait (max_queued 3)'] * 2
    assert loop.instruction == 'open the drawer 0' and list(loop.waiting) == [f'open the drawer {i}' for i in (1, 2, 3)]
    ended = []
    for t in range(1, 40):                           # each times out waiting for frames, then the next starts
        ended += _outcomes(loop.step(float(t), t))
    assert [(o[0], o[1]) for o in ended] == [(f'open the drawer {i}', 'failed') for i in range(4)]


def test_refuse_keeps_the_running_instruction():
    loop = _loop(queue_policy='refuse')
    out = _burst(loop, 3)
    assert _outcomes(out) == [('open the drawer 1', 'refused', 0), ('open the drawer 2', 'refused', 0)]
    assert "busy: 'open the drawer 0' is running" in [o.reason for o in out if type(o) is Outcome][0]
    assert loop.instruction == 'open the drawer 0'


def test_stop_shutdown_and_a_lost_robot_answer_the_waiting_instructions_too():
    for end, result in (('stop', 'stopped'), ('shutdown', 'shutdown'), ('robot_gone', 'failed')):
        loop = _loop(queue_policy='queue')
        _burst(loop, 3)
        out = {'stop': lambda: loop.stop('an operator pressed stop', 1.0), 'shutdown': lambda: loop.shutdown(1.0),
               'robot_gone': lambda: loop.robot_gone('no /joint_states for 5.0 s', 1.0)}[end]()
        assert sorted(o[:2] for o in _outcomes(out)) == [(f'open the drawer {i}', result) for i in range(3)], end
        assert loop.instruction is None and not loop.waiting
        assert loop.step(2.0, 2) == []


def test_an_unknown_queue_policy_is_refused():
    with pytest.raises(ValueError, match='queue_policy must be one of replace, queue, refuse'):
        _loop(queue_policy='newest')


def test_a_robot_that_stops_answering_fails_the_instruction_naming_why():
    loop = _loop()
    assert loop.robot_gone('no /joint_states for 5.2 s', 0.0) == []               # idle
    feed_frames(loop.observations, 1.0)
    loop.on_instruction('open the drawer', 0.0)
    stamp = _sent(loop.step(0.1, 1)).nbp.header.stamp
    out = loop.robot_gone('no /joint_states for 5.2 s', 6.0)
    assert _texts(out, 'error') == ["instruction 'open the drawer': no /joint_states for 5.2 s"]
    assert _outcomes(out) == [('open the drawer', 'failed', 1)]
    assert loop.instruction is None and loop.on_result(_result(stamp), 7.0) == []


def test_an_instruction_the_agent_cannot_ground_is_refused_before_anything_moves():
    loop = _loop(min_confidence=0.8)                          # FakeAgent: confidence 0.75
    feed_frames(loop.observations, 1.0)
    loop.on_instruction('open the drawer', 0.0)
    out = loop.step(0.1, 1)
    assert _kinds(out) == ['prediction', 'error', 'outcome']  # no NBP, no gripper goal
    assert out[0].confidence == 0.75 and out[0].cloud is loop.agent.clouds[0]
    assert _texts(out, 'error') == ["instruction 'open the drawer': refused: the agent cannot ground it (its first "
                                    "next-best pose has confidence 0.75, below min_confidence 0.80)"]
    assert _outcomes(out) == [('open the drawer', 'refused', 0)] and loop.instruction is None
    confident = _loop(min_confidence=0.7)
    feed_frames(confident.observations, 1.0)
    confident.on_instruction('open the drawer', 0.0)
    assert _kinds(confident.step(0.1, 1)) == ['prediction', 'segment_goal', 'info']


def test_the_agent_names_its_vocabulary_only_when_it_reads_words():
    """planner_node passes agent.vocabulary to PlannerLoop: a word encoder's words, or None for the
    sentence encoder, which reads any words (its confidence refuses what it cannot act on)."""
    from hdp_planner.agent import NextBestPoseAgent
    from hdp_planner.model import ModelConfig

    class ConfigOnly(torch.nn.Module):
        def __init__(self, config):
            super().__init__()
            self.config = config
    assert NextBestPoseAgent(ConfigOnly(ModelConfig(vocabulary=VOCABULARY))).vocabulary == VOCABULARY
    sentences = NextBestPoseAgent(ConfigOnly(ModelConfig(vocabulary=VOCABULARY, language_encoder='minilm')))
    assert sentences.vocabulary is None
    loop = PlannerLoop(FakeAgent(), sentences.vocabulary)
    assert _kinds(loop.on_instruction('uncover the saucepan', 0.0)) == ['info']
    assert loop.instruction == 'uncover the saucepan'


def test_a_refused_instruction_leaves_the_running_one_alone():
    loop = _loop()
    loop.on_instruction('open the drawer', 0.0)
    out = loop.on_instruction('  fly to the moon ', 0.1)
    assert _texts(out, 'error')[0].startswith("refused instruction: no word of 'fly to the moon'")
    assert _outcomes(out) == [('fly to the moon', 'refused', 0)]
    assert loop.instruction == 'open the drawer'


def test_an_outcome_is_refused_unless_well_formed():
    good = Outcome('open the drawer', 'succeeded', 'task succeeded after 2 segments', 2)
    assert Outcome.from_json(good.to_json()) == good
    assert len(Outcome.from_json(Outcome('x' * 5000, 'refused', 'too long', 0).to_json()).instruction) == 1024
    with pytest.raises(ValueError, match='unknown outcome result'):
        Outcome('open the drawer', 'won', '', 1).to_json()
    for text in ('not json', '[]', '{"instruction": "a"}',
                 '{"instruction": "a", "result": "won", "reason": "", "segments": 1}',
                 '{"instruction": "a", "result": "failed", "reason": "", "segments": -1}',
                 '{"instruction": 3, "result": "failed", "reason": "", "segments": 1}',
                 '{"instruction": "a", "result": "failed", "reason": "", "segments": 1, "extra": 0}'):
        with pytest.raises(ValueError):
            Outcome.from_json(text)


# --- processes ---------------------------------------------------------------------------------

@pytest.mark.unit
def test_the_agent_warms_up_on_a_synthetic_view(tiny_checkpoint):
    """planner_node warms the agent up at start, so the first instruction pays no first-call cost."""
    from hdp_planner.agent import NextBestPoseAgent
    agent = NextBestPoseAgent.from_checkpoint(tiny_checkpoint, camera_size=(64, 48))
    assert agent.warm_up() > 0.0


@pytest.fixture
def tiny_checkpoint(tmp_path):
    """An untrained next-best-pose agent small enough to load and predict in a moment."""
    from hdp_planner import checkpoint, language
    from hdp_planner.model import ModelConfig, NextBestPoseNet
    torch.manual_seed(0)
    model = NextBestPoseNet(ModelConfig(vocabulary=tuple(language.task_vocabulary()), grid_size=8,
                                        channels=(4, 8, 8), language_dim=16, head_hidden=32))
    path = tmp_path / 'tiny_agent.pt'
    checkpoint.save(path, model, None, 0, {}, {}, training_seeds={})
    return path


def _env(domain: int) -> dict:
    return dict(os.environ, ROS_DOMAIN_ID=str(domain), PYTHONUNBUFFERED='1', OMP_NUM_THREADS='1')


def _stop(*procs) -> list[str]:
    for proc in procs:
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
    return [proc.communicate(timeout=30)[1] or '' for proc in procs]


def _status_listener(env, expect: int, seconds: float, *publish) -> subprocess.Popen:
    """This file as a script: publish instructions, collect /hdp/status and NBPs, print JSON."""
    return subprocess.Popen([sys.executable, __file__, 'listen', str(expect), str(seconds), *publish],
                            env=env, text=True, stdout=subprocess.PIPE, stderr=subprocess.PIPE)


@pytest.mark.dds
def test_planner_node_refuses_bad_instructions_and_reports_a_camera_timeout(ros_domain, tiny_checkpoint):
    env = _env(ros_domain)
    planner = subprocess.Popen([sys.executable, '-m', 'hdp_planner.planner_node', '--ros-args',
                                '-p', 'autostart:=true',
                                '-p', f'checkpoint:={tiny_checkpoint}', '-p', 'camera_timeout_s:=2.0'],
                               env=env, text=True, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        listener = _status_listener(env, 4, 45, '', 'open the drawer ' * 20, 'make me a sandwich',
                                    'open the middle drawer')
        out, err = listener.communicate(timeout=60)
    finally:
        planner_err, = _stop(planner)
    assert listener.returncode == 0, err + planner_err
    facts = json.loads(out.strip().splitlines()[-1])
    refusals = [s for s in facts['status'] if 'refused instruction' in s]
    assert refusals == ['planner_node: refused instruction: the instruction is empty',
                        'planner_node: refused instruction: the instruction has 319 characters, more than 256',
                        "planner_node: refused instruction: no word of 'make me a sandwich' names anything the "
                        "agent was trained on (words such as azure, ball, barbecue, bbq, black, blue, ...)"]
    timeout = [s for s in facts['status'] if 'timed out' in s]
    assert timeout and timeout[0].startswith("planner_node: instruction 'open the middle drawer': "
                                             'camera front, side timed out after 2.0 s')
    assert facts['nbps'] == 0
    assert [(o['instruction'][:20], o['result'], o['segments']) for o in facts['outcomes']] == [
        ('', 'refused', 0), ('open the drawer open', 'refused', 0), ('make me a sandwich', 'refused', 0),
        ('open the middle draw', 'failed', 0)]
    assert facts['outcomes'][3]['reason'].startswith('camera front, side timed out after 2.0 s')
    assert planner.returncode == 0, planner_err


@pytest.mark.dds
@pytest.mark.parametrize('policy, camera_timeout_s', [('replace', 0.3), ('queue', 2.5)])
def test_a_burst_of_fifty_instructions_gets_fifty_outcomes(ros_domain, tiny_checkpoint, policy, camera_timeout_s):
    """The probe's burst: 50 instructions 20 ms apart. Each is answered once on /hdp/outcome: under
    replace all but the last are replaced (the last fails: no camera publishes); under queue
    (max_queued 10) the overflow is refused at once and the others run in turn, each failing after
    camera_timeout_s, which frees a place every 2.5 s (how many get one depends on how long the
    burst takes on a loaded machine: at most 11 + its seconds / 2.5)."""
    env = _env(ros_domain)
    planner = subprocess.Popen([sys.executable, '-m', 'hdp_planner.planner_node', '--ros-args',
                                '-p', 'autostart:=true',
                                '-p', f'checkpoint:={tiny_checkpoint}', '-p', f'camera_timeout_s:={camera_timeout_s}',
                                '-p', f'queue_policy:={policy}', '-p', 'max_queued:=10'],
                               env=env, text=True, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        sender = subprocess.Popen([sys.executable, __file__, 'burst', '50', '0.02', '45'], env=env, text=True,
                                  stdout=subprocess.PIPE, stderr=subprocess.PIPE)
        out, err = sender.communicate(timeout=90)
    finally:
        planner_err, = _stop(planner)
    assert sender.returncode == 0, err + planner_err
    outcomes = json.loads(out.strip().splitlines()[-1])['outcomes']
    assert sorted(o['instruction'] for o in outcomes) == sorted(f'open the drawer {i}' for i in range(50))
    results = [o['result'] for o in outcomes]
    if policy == 'replace':
        assert sorted(results) == ['failed'] + ['replaced'] * 49
        assert next(o for o in outcomes if o['result'] == 'failed')['instruction'] == 'open the drawer 49'
    else:
        refused = [o for o in outcomes if o['result'] == 'refused']
        assert len(refused) >= 30 and results.count('failed') == 50 - len(refused)
        assert {o['reason'] for o in refused} == {'queue full: 10 instructions wait (max_queued 10)'}


@pytest.mark.dds
@pytest.mark.parametrize('transport, depth_filter', [('raw', 'none'), ('compressed', 'realsense')])
def test_planner_node_sends_segments_to_a_controller_until_max_segments(ros_domain, tiny_checkpoint, transport,
                                                                         depth_filter):
    """Both image transports: the raw Images, or image_transport's compressed and compressedDepth
    topics the bridge offers, decoded to the same Images (the cloud the planner saw says so); the
    second also through the RealSense post-processing chain."""
    env = _env(ros_domain)
    bridge = subprocess.Popen([sys.executable, '-m', 'hdp_sim_bridge.sim_bridge_node', '--ros-args',
                               '-p', 'camera_width:=64', '-p', 'camera_height:=48', '-p', 'camera_rate_hz:=4.0',
                               '-p', 'task:=open_drawer', '-p', 'seed:=1'],
                              env=env, text=True, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    planner = subprocess.Popen([sys.executable, '-m', 'hdp_planner.planner_node', '--ros-args',
                                '-p', 'autostart:=true',
                                '-p', f'checkpoint:={tiny_checkpoint}', '-p', 'max_segments:=2',
                                '-p', 'camera_timeout_s:=20.0', '-p', 'publish_cloud:=true',
                                '-p', f'image_transport:={transport}', '-p', f'depth_filter:={depth_filter}',
                                '-p', 'min_confidence:=0.0'],     # untrained: its confidence means nothing
                               env=env, text=True, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        controller = subprocess.run([sys.executable, __file__, 'controller'], env=env, text=True,
                                    capture_output=True, timeout=90)
    finally:
        errors = _stop(planner, bridge)
    assert controller.returncode == 0, controller.stderr + '\n'.join(errors)
    facts = json.loads(controller.stdout.strip().splitlines()[-1])
    assert len(facts['segments']) == 2
    for segment in facts['segments']:
        assert segment['gripper_stamp'] == segment['stamp'] and segment['frame'] == 'world'
        assert segment['in_workspace'] and segment['gripper_width'] in (0.0, panda.GRIPPER_OPEN_WIDTH)
        assert segment['tf_frame'] == 'hdp_next_best_pose' and np.allclose(segment['marker_tip'], segment['xyz'])
    assert facts['clouds'] >= 2 and facts['cloud_points'] > 100 and facts['cloud_in_workspace']
    assert facts['segments'][1]['stamp'] > facts['segments'][0]['stamp']
    status = [s for s in facts['status'] if s.startswith('planner_node')]
    done = r'planner_node: segment {}: pose \(-?[\d.]+, -?[\d.]+, [\d.]+\) gripper (open|close) -> done in [\d.]+ s'
    assert any(re.fullmatch(done.format(1), s) for s in status), status
    assert any(re.fullmatch(done.format(2), s) for s in status), status
    assert status[-1] == "planner_node: instruction 'open the middle drawer': 2 segments done without success"
    assert facts['outcomes'] == [{'instruction': 'open the middle drawer', 'result': 'failed',
                                  'reason': '2 segments done without success', 'segments': 2}]
    assert planner.returncode == 0, errors[0]


@pytest.mark.dds
def test_hdp_stop_ends_the_instruction_stopped_and_holds_the_moving_arm(ros_domain, tiny_checkpoint):
    """The whole chain of /hdp/stop: planner_node answers it and ends its instruction 'stopped';
    controller_node, told on /hdp/hold, holds the arm mid-segment on the sim bridge. The planner's
    instruction waits for camera frames (the probe silences the cameras); the probe itself sends
    the slow segment that is running when it calls /hdp/stop."""
    env = _env(ros_domain)
    bridge = subprocess.Popen([sys.executable, '-m', 'hdp_sim_bridge.sim_bridge_node', '--ros-args',
                               '-p', 'camera_width:=64', '-p', 'camera_height:=48', '-p', 'camera_rate_hz:=2.0',
                               '-p', 'task:=reach_target', '-p', 'seed:=3'],
                              env=env, text=True, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    controller = subprocess.Popen([sys.executable, '-m', 'hdp_controller.controller_node', '--ros-args',
                                   '-p', 'autostart:=true',
                                   '-p', 'method:=planner', '-p', 'use_sim_time:=true', '-p', 'velocity_scale:=0.03'],
                                  env=env, text=True, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    planner = subprocess.Popen([sys.executable, '-m', 'hdp_planner.planner_node', '--ros-args',
                                '-p', 'autostart:=true',
                                '-p', f'checkpoint:={tiny_checkpoint}', '-p', 'camera_timeout_s:=120.0'],
                               env=env, text=True, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        probe = subprocess.run([sys.executable, __file__, 'stopper'], env=env, text=True, capture_output=True,
                               timeout=150)
    finally:
        errors = _stop(planner, controller, bridge)
    assert probe.returncode == 0, probe.stderr + '\n'.join(errors)
    facts = json.loads(probe.stdout.strip().splitlines()[-1])
    assert facts['response'] == [True, "stopped 'open the middle drawer'; arm held"], facts['status']
    assert facts['outcomes'] == [{'instruction': 'open the middle drawer', 'result': 'stopped',
                                  'reason': 'stopped by /hdp/stop', 'segments': 0}]
    assert facts['moving_at_stop'] > 0.02                          # it was stopped mid-segment ...
    assert facts['still_after_s'] is not None and facts['drift_after'] < 0.005, facts   # ... and stays put
    assert facts['result'] == 'failed: stopped by /hdp/stop', facts['status']
    assert 'controller_node: holding the arm: stopped by /hdp/stop' in facts['status']
    assert facts['second_response'] == [True, 'nothing was running; arm held']
    assert planner.returncode == 0 and controller.returncode == 0, errors


@pytest.mark.dds
def test_after_a_stalled_controller_continues_the_planner_acts_on_its_result_at_once(ros_domain):
    """The probe's SIGSTOP: controller_node stopped mid-segment for longer than its state_timeout_s,
    then continued. It names its own stall (not the bridge), finishes the segment, and planner_node
    ends the instruction on that result at once, not after its own result_timeout_s (60 s)."""
    env = _env(ros_domain)
    bridge = subprocess.Popen([sys.executable, '-m', 'hdp_sim_bridge.sim_bridge_node', '--ros-args',
                               '-p', 'camera_width:=64', '-p', 'camera_height:=48', '-p', 'camera_rate_hz:=2.0',
                               '-p', 'task:=open_drawer', '-p', 'seed:=1'],
                              env=env, text=True, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    controller = subprocess.Popen([sys.executable, '-m', 'hdp_controller.controller_node', '--ros-args',
                                   '-p', 'autostart:=true', '-p', 'method:=planner', '-p', 'use_sim_time:=true',
                                   '-p', 'velocity_scale:=0.1', '-p', 'state_timeout_s:=2.0'],
                                  env=env, text=True, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    planner = subprocess.Popen([sys.executable, '-m', 'hdp_planner.planner_node', '--ros-args',
                                '-p', 'autostart:=true', '-p', 'max_segments:=1', '-p', 'result_timeout_s:=60.0',
                                '-p', 'camera_timeout_s:=30.0'],        # the released agent: a reachable NBP
                               env=env, text=True, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    listener = None
    try:
        listener = _status_listener(env, 1, 150, 'open the middle drawer')
        first = subprocess.run([sys.executable, '-m', 'hdp_tools.cli.main', 'topic', 'echo', '--once',
                                '--timeout', '90', topics.ARM_TRAJECTORY, 'trajectory_msgs/msg/JointTrajectory'],
                               env=env, text=True, capture_output=True, timeout=120)
        assert first.returncode == 0, first.stderr
        controller.send_signal(signal.SIGSTOP)
        time.sleep(5.0)                                  # over twice state_timeout_s; the sim runs on
        controller.send_signal(signal.SIGCONT)
        continued = time.time()
        out, err = listener.communicate(timeout=150)
    finally:
        controller.send_signal(signal.SIGCONT)
        errors = _stop(planner, controller, bridge)
        if listener is not None and listener.poll() is None:
            listener.kill()
    facts = json.loads(out.strip().splitlines()[-1])
    outcome, = facts['outcomes']
    assert outcome['instruction'] == 'open the middle drawer' and outcome['segments'] == 1, facts['status']
    assert outcome['wall_s'] - continued < 20.0, (outcome['wall_s'] - continued, facts['status'])
    assert any(s.startswith('controller_node: this node itself did not run for') for s in facts['status'])
    assert not any('no /joint_states' in s for s in facts['status']), facts['status']
    assert not any('no result from the controller' in s for s in facts['status']), facts['status']
    assert planner.returncode == 0, errors[0]


# --- hdp launch -----------------------------------------------------------------------------------

def _graph_yaml(tmp_path, planner_checkpoint) -> str:
    path = tmp_path / 'graph.yaml'
    path.write_text(f"""
sim_bridge_node:
  ros__parameters: {{camera_width: 64, camera_height: 48, camera_rate_hz: 2.0}}
planner_node:
  ros__parameters: {{checkpoint: '{planner_checkpoint}'}}
controller_node:
  ros__parameters: {{use_sim_time: true, method: rkd}}
""")
    return str(path)


def _launch(ros_domain, params, *extra) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, '-m', 'hdp_tools.cli.main', 'launch', '--params-file', params, *extra],
                            env=_env(ros_domain), text=True, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)


def _collect_lines(proc) -> tuple[list[str], threading.Thread]:
    """The process's output lines, appended as they come by a reader thread (ends at EOF)."""
    lines = []
    reader = threading.Thread(target=lambda: lines.extend(line.rstrip('\n') for line in proc.stdout), daemon=True)
    reader.start()
    return lines, reader


@pytest.mark.dds
def test_hdp_launch_starts_the_graph_prefixes_output_and_stops_on_sigint(ros_domain, tmp_path, tiny_checkpoint):
    params = _graph_yaml(tmp_path, tiny_checkpoint)
    launch = _launch(ros_domain, params, '-p', 'controller_node:method:=planner')
    lines, reader = _collect_lines(launch)
    ready = ('[sim_bridge_node] ', '[planner_node] ', '[controller_node] ')
    end = time.monotonic() + 60
    while time.monotonic() < end and launch.poll() is None and not all(
            any(line.startswith(p) and ('ready' in line or 'episode' in line) for line in list(lines)) for p in ready):
        time.sleep(0.2)
    launch.send_signal(signal.SIGINT)
    launch.wait(timeout=40)
    reader.join(timeout=5)
    text = '\n'.join(lines)
    assert launch.returncode == 0, text
    assert any(line.startswith('[controller_node] ') and 'ready: method planner' in line for line in lines), text
    assert any(line.startswith('[planner_node] ') and 'ready: agent' in line for line in lines), text
    assert any(line.startswith('[sim_bridge_node] ') and 'episode reach_target' in line for line in lines), text
    assert '[launch] SIGINT: stopping the nodes' in text


@pytest.mark.dds
def test_hdp_launch_exit_on_node_exit_stops_the_graph_when_a_node_dies(ros_domain, tmp_path, tiny_checkpoint):
    params = _graph_yaml(tmp_path, tiny_checkpoint)
    launch = _launch(ros_domain, params, '--nodes', 'planner_node,controller_node', '--exit-on-node-exit',
                     '-p', 'controller_node:method:=planner', '-p', 'planner_node:max_segments:=0')
    out, _ = launch.communicate(timeout=60)
    assert launch.returncode == 1, out
    assert "[planner_node] [ERROR] [planner_node]: parameter 'max_segments' must be >= 1, got 0" in out
    assert '[launch] planner_node exited with code 1; stopping the other nodes' in out


def _wait_for(lines, proc, predicate, seconds: float) -> bool:
    end = time.monotonic() + seconds
    while time.monotonic() < end and proc.poll() is None and not predicate('\n'.join(lines)):
        time.sleep(0.2)
    return predicate('\n'.join(lines))


@pytest.mark.dds
def test_hdp_launch_keeps_the_other_nodes_by_default_and_respawns_on_request(ros_domain, tmp_path, tiny_checkpoint):
    """As ros2 launch: a node that dies leaves the rest running (the lifecycle manager brings up
    the controller without it); --respawn starts it again."""
    params = _graph_yaml(tmp_path, tiny_checkpoint)
    launch = _launch(ros_domain, params, '--nodes', 'planner_node,controller_node',
                     '-p', 'controller_node:method:=planner', '-p', 'planner_node:max_segments:=0',
                     '-p', 'lifecycle_manager:service_timeout_s:=5.0')
    lines, reader = _collect_lines(launch)
    assert _wait_for(lines, launch, lambda text: '[launch] planner_node exited with code 1; 2 node(s) keep running'
                     in text and 'ready: method planner' in text, 90), '\n'.join(lines)
    assert launch.poll() is None                      # the controller still runs
    launch.send_signal(signal.SIGINT)
    launch.wait(timeout=40)
    reader.join(timeout=5)
    assert launch.returncode == 1, '\n'.join(lines)       # a node failed
    assert "[launch] nodes that did not exit cleanly: {'planner_node': 1}" in lines, '\n'.join(lines)

    launch = _launch(ros_domain, params, '--nodes', 'planner_node', '--respawn', 'planner_node',
                     '--respawn-delay', '0.2', '-p', 'planner_node:max_segments:=0')
    lines, reader = _collect_lines(launch)
    assert _wait_for(lines, launch, lambda text: text.count('[launch] started planner_node') >= 3, 120), \
        '\n'.join(lines)
    launch.send_signal(signal.SIGINT)
    launch.wait(timeout=40)
    reader.join(timeout=5)
    assert '[launch] planner_node exited with code 1; respawning it in 0.2 s' in lines
    bad = subprocess.run([sys.executable, '-m', 'hdp_tools.cli.main', 'launch', '--respawn', 'planner_node',
                          '--nodes', 'controller_node'], capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and "--respawn names node(s) not started: ['planner_node']" in bad.stderr


# --- helper processes -------------------------------------------------------------------------------

def _node(name):
    from hdp_ros import ros
    from hdp_msgs_py.msg import String
    ros.init(args=sys.argv)
    node = ros.Node(name)
    status = []
    node.create_subscription(String, topics.STATUS, lambda m: status.append(m.data), topics.STATUS_QOS)
    return node, status


def _spin(node, seconds: float, until=lambda: False) -> bool:
    end = time.monotonic() + seconds
    while time.monotonic() < end and not until():
        rclpy.spin_once(node, timeout_sec=0.05)
    return until()


def listen(expect: int, seconds: float, *instructions: str) -> None:
    """Publish each instruction once the planner listens; report status lines and NBPs seen."""
    from hdp_msgs_py.msg import PoseStamped, String
    node, status = _node('planner_listener')
    nbps, outcomes = [], []
    node.create_subscription(PoseStamped, topics.NEXT_BEST_POSE, nbps.append, 10)
    node.create_subscription(String, topics.OUTCOME,
                             lambda m: outcomes.append({**json.loads(m.data), 'wall_s': time.time()}), 10)
    instruction = node.create_publisher(String, topics.INSTRUCTION, 10)
    assert _spin(node, 60, lambda: instruction.get_subscription_count() > 0), 'planner_node did not come up'
    _spin(node, 0.5)
    for text in instructions:
        instruction.publish(String(data=text))
        _spin(node, 0.2)
    _spin(node, seconds, lambda: len(outcomes) >= expect)
    _spin(node, 0.5)
    print(json.dumps({'status': status, 'nbps': len(nbps), 'outcomes': outcomes}), flush=True)
    node.destroy_node()
    rclpy.try_shutdown()


def burst(count: int, interval_s: float, seconds: float) -> None:
    """Publish ``count`` instructions ``interval_s`` apart once the planner listens; print the outcomes."""
    from hdp_msgs_py.msg import String
    node, status = _node('instruction_burst')
    outcomes = []
    node.create_subscription(String, topics.OUTCOME, lambda m: outcomes.append(json.loads(m.data)),
                             topics.INSTRUCTION_QOS)
    instruction = node.create_publisher(String, topics.INSTRUCTION, topics.INSTRUCTION_QOS)
    assert _spin(node, 60, lambda: instruction.get_subscription_count() > 0), 'planner_node did not come up'
    _spin(node, 0.5)
    for i in range(count):
        instruction.publish(String(data=f'open the drawer {i}'))
        _spin(node, interval_s)
    _spin(node, seconds, lambda: len(outcomes) >= count)
    print(json.dumps({'status': status, 'outcomes': outcomes}), flush=True)
    node.destroy_node()
    rclpy.try_shutdown()


def controller() -> None:
    """Stand in for controller_node: answer each NBP 'done' after a moment; report what came."""
    from hdp_data import workspace
    from hdp_msgs_py.msg import Marker, PointCloud2, PoseStamped, String, TFMessage
    node, status = _node('fake_controller')
    goals, poses, outcomes = {}, [], []
    node.create_subscription(String, topics.OUTCOME, lambda m: outcomes.append(json.loads(m.data)), 10)
    node.create_subscription(JointState, topics.NEXT_BEST_GRIPPER,
                             lambda m: goals.__setitem__(conversions.time_to_seconds(m.header.stamp), m), 10)
    node.create_subscription(PoseStamped, topics.NEXT_BEST_POSE, poses.append, 10)
    markers, frames, clouds = [], [], []          # what RViz and Foxglove draw
    node.create_subscription(Marker, topics.NEXT_BEST_POSE_MARKER, markers.append, 10)
    node.create_subscription(PointCloud2, topics.PLANNER_CLOUD, clouds.append, topics.SENSOR_QOS)
    node.create_subscription(TFMessage, topics.TF, lambda m: frames.extend(m.transforms), topics.TF_QOS)
    results = node.create_publisher(Header, topics.SEGMENT_RESULT, 10)
    instruction = node.create_publisher(String, topics.INSTRUCTION, 10)
    assert _spin(node, 60, lambda: instruction.get_subscription_count() > 0 and results.get_subscription_count() > 0
                 ), 'planner_node did not come up'
    _spin(node, 0.5)
    instruction.publish(String(data='open the middle drawer'))
    segments = []
    for _ in range(2):
        assert _spin(node, 30, lambda: len(poses) > len(segments)), f'no NBP; status: {status}'
        pose = poses[len(segments)]
        stamp = conversions.time_to_seconds(pose.header.stamp)
        _spin(node, 0.3)
        goal = goals.get(stamp)
        xyz, _ = conversions.pose_to_xyz_quat(pose)
        marker = next((m for m in markers if m.header.stamp == pose.header.stamp), None)
        frame = next((t for t in frames if t.header.stamp == pose.header.stamp), None)
        segments.append({'marker_tip': [marker.points[1].x, marker.points[1].y, marker.points[1].z] if marker else None,
                         'tf_frame': frame.child_frame_id if frame else None, 'xyz': xyz.tolist(),
                         'stamp': stamp, 'frame': pose.header.frame_id, 'gripper_stamp': stamp if goal else None,
                         'gripper_width': float(goal.position[0]) if goal else None,
                         'in_workspace': bool(workspace.in_workspace(xyz[None], above_table=0.0)[0])})
        results.publish(Header(stamp=pose.header.stamp, frame_id=topics.SEGMENT_DONE))
    _spin(node, 15, lambda: outcomes and any('segments done' in s for s in status))
    xyz, _ = conversions.pointcloud2_to_cloud(clouds[-1]) if clouds else (np.zeros((0, 3)), None)
    print(json.dumps({'segments': segments, 'status': status, 'outcomes': outcomes, 'clouds': len(clouds),
                      'cloud_points': len(xyz), 'cloud_in_workspace': bool(workspace.in_workspace(xyz).all())}),
          flush=True)
    node.destroy_node()
    rclpy.try_shutdown()


def stopper() -> None:
    """Run a slow segment on controller_node + sim_bridge_node while planner_node waits with an
    instruction; call /hdp/stop mid-segment; report the answer, the outcome and the arm's motion."""
    from std_srvs.srv import Trigger

    from hdp_motion import kinematics
    from hdp_msgs_py.msg import PoseStamped, String
    node, status = _node('stop_probe')
    outcomes, results, joints = [], [], []
    node.create_subscription(String, topics.OUTCOME, lambda m: outcomes.append(json.loads(m.data)),
                             topics.INSTRUCTION_QOS)
    node.create_subscription(Header, topics.SEGMENT_RESULT, results.append, 10)
    node.create_subscription(JointState, topics.JOINT_STATES, joints.append, 10)
    instruction = node.create_publisher(String, topics.INSTRUCTION, topics.INSTRUCTION_QOS)
    cameras = node.create_publisher(String, topics.SIM_CAMERAS, topics.COMMAND_QOS)
    pose = node.create_publisher(PoseStamped, topics.NEXT_BEST_POSE, topics.COMMAND_QOS)
    gripper = node.create_publisher(JointState, topics.NEXT_BEST_GRIPPER, topics.COMMAND_QOS)
    stop = node.create_client(Trigger, topics.STOP)
    assert _spin(node, 90, lambda: stop.service_is_ready() and node.count_subscribers(topics.HOLD) >= 1
                 and min(p.get_subscription_count() for p in (instruction, cameras, pose, gripper)) > 0
                 and joints), f'the graph did not come up; status: {status}'

    def arm(msg):
        names = list(msg.name)
        return (np.array([msg.position[names.index(n)] for n in panda.ARM_JOINTS]),
                np.array([msg.velocity[names.index(n)] for n in panda.ARM_JOINTS]))

    def call():
        future = stop.call_async(Trigger.Request())
        assert _spin(node, 10, future.done), 'no answer from /hdp/stop'
        return [future.result().success, future.result().message]
    cameras.publish(String(data=''))                 # the instruction waits for frames: it stays running
    _spin(node, 1.0)
    instruction.publish(String(data='open the middle drawer'))
    goal = kinematics.fk_pose(torch.as_tensor(panda.HOME + 0.1, dtype=torch.float64)).numpy()
    for stamp_sec in (1, 2, 3):                      # a controller that has not heard the robot yet refuses
        gripper.publish(JointState(header=Header(stamp=Time(sec=stamp_sec)), name=[topics.GRIPPER_GOAL_JOINT],
                                   position=[panda.GRIPPER_OPEN_WIDTH]))
        pose.publish(conversions.xyz_quat_to_pose_stamped(goal[:3], goal[3:], topics.NBP_FRAME, Time(sec=stamp_sec)))
        if _spin(node, 20, lambda: results or np.abs(arm(joints[-1])[1]).max() > 0.03):
            if not results:
                break
            results.clear()
    moving = float(np.abs(arm(joints[-1])[1]).max())
    response = call()
    stopped_at = len(joints)
    assert _spin(node, 10, lambda: results and outcomes), f'no result or outcome; status: {status}'
    _spin(node, 1.0, lambda: any(np.abs(arm(m)[1]).max() < 0.01 for m in joints[stopped_at:]))
    still = next((i for i, m in enumerate(joints[stopped_at:], stopped_at) if np.abs(arm(m)[1]).max() < 0.01), None)
    _spin(node, 1.0)
    drift = float(np.abs(arm(joints[-1])[0] - arm(joints[still])[0]).max()) if still is not None else None
    facts = {'response': response, 'moving_at_stop': moving, 'outcomes': outcomes, 'result': results[0].frame_id,
             'still_after_s': None if still is None else conversions.time_to_seconds(joints[still].header.stamp)
             - conversions.time_to_seconds(joints[stopped_at].header.stamp),
             'drift_after': drift, 'second_response': call(), 'status': status}
    print(json.dumps(facts), flush=True)
    node.destroy_node()
    rclpy.try_shutdown()


if __name__ == '__main__':
    {'listen': lambda: listen(int(sys.argv[2]), float(sys.argv[3]), *sys.argv[4:]),
     'burst': lambda: burst(int(sys.argv[2]), float(sys.argv[3]), float(sys.argv[4])),
     'controller': controller, 'stopper': stopper}[sys.argv[1]]()
