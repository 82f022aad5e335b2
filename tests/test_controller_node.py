"""controller_node: NBP validation, trajectories inside the limits, segment completion, and the
node as a process next to sim_bridge_node (method 'planner', so no checkpoint is needed).

Run as a script, this file is the probe the process test starts: `python test_controller_node.py probe`.
"""

import functools
import json
import math
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
import rclpy
import torch

from hdp_motion import panda
from hdp_msgs_py import conversions, topics
from hdp_msgs_py.msg import (Header, JointState, JointTrajectory, Point, Pose, PoseStamped, Quaternion, TFMessage,
                             Time)

pytestmark = pytest.mark.unit

torch.set_num_threads(1)

@functools.cache
def home_pose() -> np.ndarray:
    """(7,) panda_grasptarget at panda.HOME, where the sim's arm starts."""
    from hdp_motion import kinematics
    return kinematics.fk_pose(torch.as_tensor(panda.HOME, dtype=torch.float64)).numpy()


REACHING_Q = panda.HOME + 0.1      # where FakePolicy's plans end by default


def reachable_goal() -> np.ndarray:
    """The hand at REACHING_Q: a few cm from home, above the table, in the workspace."""
    from hdp_motion import kinematics
    return kinematics.fk_pose(torch.as_tensor(REACHING_Q, dtype=torch.float64)).numpy()


def nbp(xyz, quat, stamp_sec: int = 1, frame_id: str = 'world'):
    """A PoseStamped as given, unchecked (conversions.xyz_quat_to_pose_stamped refuses NaN)."""
    x, y, z = map(float, xyz)
    qx, qy, qz, qw = map(float, quat)
    return PoseStamped(header=Header(stamp=Time(sec=stamp_sec), frame_id=frame_id), pose=Pose(
        position=Point(x=x, y=y, z=z), orientation=Quaternion(x=qx, y=qy, z=qz, w=qw)))


def gripper_goal_msg(is_open: bool, stamp_sec: int = 1, width=None):
    width = (0.08 if is_open else 0.0) if width is None else width
    return JointState(header=Header(stamp=Time(sec=stamp_sec)), name=[topics.GRIPPER_GOAL_JOINT], position=[width])


def joint_state_msg(q, qd=None, fingers=(0.04, 0.04), stamp_sec: int = 0):
    return JointState(header=Header(stamp=Time(sec=stamp_sec)), name=list(panda.ARM_JOINTS + panda.FINGER_JOINTS),
                      position=[*map(float, q), *fingers],
                      velocity=[*map(float, np.zeros(7) if qd is None else qd), 0.0, 0.0])


# --- validation ---------------------------------------------------------------------------

def test_a_valid_nbp_becomes_position_and_unit_quaternion():
    from hdp_controller.inputs import validate_nbp
    goal = reachable_goal()
    pose = validate_nbp(nbp(goal[:3], goal[3:]))
    assert pose.shape == (7,) and np.allclose(pose, goal, atol=1e-9)


@pytest.mark.parametrize('xyz, quat, frame, reason', [
    ((math.nan, 0.0, 1.0), (1, 0, 0, 0), 'world', 'position must be finite'),
    ((0.4, 0.0, math.inf), (1, 0, 0, 0), 'world', 'position must be finite'),
    ((0.4, 0.0, 1.0), (math.nan, 0, 0, 1), 'world', 'quaternion must be finite'),
    ((0.4, 0.0, 1.0), (0.5, 0, 0, 0), 'world', 'quaternion must be unit'),
    ((0.4, 0.0, 1.0), (1.0, 0, 0, 0.1), 'world', 'quaternion must be unit'),
    ((0.4, 0.0, 1.0), (0, 0, 0, 0), 'world', 'zero norm'),
    ((1.5, 0.0, 1.0), (1, 0, 0, 0), 'world', 'outside the workspace'),
    ((0.4, 0.0, 0.70), (1, 0, 0, 0), 'world', 'outside the workspace'),     # under the table top
    ((0.4, 0.0, 1.0), (1, 0, 0, 0), 'panda_link0', "is not 'world'"),
])
def test_invalid_nbps_are_refused_with_the_reason(xyz, quat, frame, reason):
    from hdp_controller.inputs import SegmentRefused, validate_nbp
    with pytest.raises(SegmentRefused, match=reason):
        validate_nbp(nbp(xyz, quat, frame_id=frame))


def test_gripper_goals_are_validated():
    from hdp_controller.inputs import gripper_goal
    assert gripper_goal(gripper_goal_msg(True)) is True
    assert gripper_goal(gripper_goal_msg(False)) is False
    for bad in (gripper_goal_msg(True, width=0.2), gripper_goal_msg(True, width=math.nan),
                JointState(name=['panda_finger_joint1'], position=[0.04]),
                JointState(name=[topics.GRIPPER_GOAL_JOINT], position=[])):
        with pytest.raises(ValueError):
            gripper_goal(bad)


def test_the_gripper_is_read_from_its_fingers_and_commanded_as_a_finger_trajectory():
    """panda.reads_open: open when (nearly) fully open, so fingers closed on a handle read closed.
    conversions.finger_trajectory: both fingers to the open or shut position in 0.5 s, start now."""
    assert panda.reads_open(panda.GRIPPER_OPEN_WIDTH) and panda.reads_open(panda.GRIPPER_OPEN_WIDTH - 0.004)
    assert not panda.reads_open(0.06) and not panda.reads_open(0.0)
    opening = conversions.finger_trajectory(True)
    names, positions, times, _ = conversions.parse_joint_trajectory(opening)
    assert names == list(panda.FINGER_JOINTS) and positions.tolist() == [[panda.FINGER_MAX] * 2]
    assert times.tolist() == [0.5] and opening.header.stamp == Time()            # the zero stamp: start now
    shut = conversions.finger_trajectory(False, ('fr3_finger_joint1', 'fr3_finger_joint2'), stamp=Time(sec=2))
    assert list(shut.joint_names) == ['fr3_finger_joint1', 'fr3_finger_joint2'] and shut.header.stamp == Time(sec=2)
    assert conversions.parse_joint_trajectory(shut)[1].tolist() == [[0.0, 0.0]]
    assert conversions.time_to_ns(Time(sec=3, nanosec=7)) == 3_000_000_007


def test_arm_state_reads_joints_by_name_in_any_order():
    from hdp_controller.inputs import arm_state
    q = panda.HOME + 0.1
    msg = joint_state_msg(q, qd=np.arange(7) * 0.01, fingers=(0.01, 0.02))
    msg.name, msg.position, msg.velocity = msg.name[::-1], msg.position[::-1], msg.velocity[::-1]
    state = arm_state(msg, panda.ARM_JOINTS, panda.FINGER_JOINTS)
    assert np.allclose(state.q, q) and np.allclose(state.qd, np.arange(7) * 0.01)
    assert state.gripper_width == pytest.approx(0.03)
    msg.name = [n.replace('panda_joint7', 'elbow') for n in msg.name]
    with pytest.raises(ValueError, match='panda_joint7'):
        arm_state(msg, panda.ARM_JOINTS, panda.FINGER_JOINTS)


# --- trajectories -------------------------------------------------------------------------

class FakePolicy:
    """A LowLevelPolicy that returns the joints it was given (or fails)."""
    name = 'fake'

    def __init__(self, joints=None, failure=None):
        self.joints, self.failure, self.requests = joints, failure, []

    def plan(self, request, scene=None):
        from hdp_controller.low_level import PlanResult
        self.requests.append(request)
        if self.failure:
            return PlanResult(None, failure=self.failure)
        return PlanResult(np.asarray(self.joints, dtype=float))


def _request(q=panda.HOME):
    from hdp_controller.inputs import ArmState
    from hdp_controller.segment_planning import segment_request
    return segment_request(ArmState(np.asarray(q, float), np.zeros(7), 0.08), True, reachable_goal(), False,
                           np.zeros((0, 3), np.float32))


def test_segment_request_starts_at_the_forward_kinematics_of_the_joints():
    request = _request()
    assert np.allclose(request.start_pose, home_pose())
    assert request.gripper_open is True and request.goal_gripper_open is False


def test_joint_trajectories_stay_inside_position_and_velocity_limits():
    from hdp_controller.segment_planning import plan_segment
    rng = np.random.default_rng(0)
    for trial in range(20):
        scale = rng.uniform(0.1, 1.0)
        joints = rng.uniform(panda.LOWER, panda.UPPER, (int(rng.integers(1, 64)), 7))
        msg, _ = plan_segment(FakePolicy(joints), _request(), panda.ARM_JOINTS, scale)
        names, positions, times, velocities = conversions.parse_joint_trajectory(msg)
        assert names == list(panda.ARM_JOINTS)
        assert np.allclose(positions[0], panda.HOME) and times[0] == 0.0
        assert panda.within_limits(positions, tol=1e-9)
        implied = np.abs(np.diff(positions, axis=0)) / np.diff(times)[:, None]
        assert np.all(implied <= panda.VELOCITY_LIMITS * scale * 1.001)
        assert np.all(np.abs(velocities) <= panda.VELOCITY_LIMITS * scale + 1e-9)
        assert np.all(velocities[-1] == 0.0)


def test_out_of_limit_or_failed_plans_are_refused_never_sent():
    from hdp_controller.inputs import SegmentRefused
    from hdp_controller.segment_planning import plan_segment
    beyond = np.vstack([panda.HOME, panda.UPPER + np.array([0, 0, 0, 0, 0, 0.01, 0])])
    with pytest.raises(SegmentRefused, match='outside the joint position limits'):
        plan_segment(FakePolicy(beyond), _request(), panda.ARM_JOINTS, 0.5)
    with pytest.raises(SegmentRefused, match='finite'):
        plan_segment(FakePolicy([[math.nan] * 7]), _request(), panda.ARM_JOINTS, 0.5)
    with pytest.raises(SegmentRefused, match=r'fake found no trajectory \(no_path\)'):
        plan_segment(FakePolicy(failure='no_path'), _request(), panda.ARM_JOINTS, 0.5)


def test_a_plan_that_ends_away_from_its_nbp_is_refused_with_the_distance():
    from hdp_controller.inputs import SegmentRefused
    from hdp_controller.segment_planning import plan_segment
    far = np.vstack([panda.HOME, panda.HOME + np.array([0.6, 0, 0, 0, 0, 0, 0])])   # swings 20+ cm aside
    with pytest.raises(SegmentRefused, match=r'fake plan ends 0\.\d+ m and [\d.]+ deg from the NBP '
                                              r'\(tolerance 0\.100 m, 15\.0 deg\)'):
        plan_segment(FakePolicy(far), _request(), panda.ARM_JOINTS, 0.5, (0.1, 15.0))
    turned = np.vstack([panda.HOME, REACHING_Q + np.array([0, 0, 0, 0, 0, 0, 0.5])])  # the hand turned 29 deg
    with pytest.raises(SegmentRefused, match=r'0\.00\d m and 28\.6 deg'):
        plan_segment(FakePolicy(turned), _request(), panda.ARM_JOINTS, 0.5, (0.1, 15.0))
    half_turn = REACHING_Q - np.array([0, 0, 0, 0, 0, 0, math.pi])     # the same grasp: fingers swapped
    plan_segment(FakePolicy([half_turn]), _request(), panda.ARM_JOINTS, 0.5, (0.01, 1.0))
    exact, report = plan_segment(FakePolicy([REACHING_Q]), _request(), panda.ARM_JOINTS, 0.5, (0.001, 0.1))
    assert np.allclose(exact.points[-1].positions, REACHING_Q)
    assert report.method == 'fake' and report.draws == 1 and report.failure is None and not report.ik_error
    assert report.reach_error == pytest.approx((0.0, 0.0), abs=1e-6) and report.seconds >= 0.0


def test_check_reach_refuses_a_miss_beyond_either_tolerance_and_none_checks_nothing():
    from hdp_controller.inputs import SegmentRefused
    from hdp_controller.segment_planning import check_reach
    check_reach('fake', (0.1, 15.0), (0.1, 15.0))                  # on the tolerance: kept
    check_reach('fake', (5.0, 180.0), None)                        # nothing to check
    with pytest.raises(SegmentRefused, match=r'fake plan ends 0\.101 m and 1\.0 deg from the NBP '
                                              r'\(tolerance 0\.100 m, 15\.0 deg\): the NBP is not reachable as given'):
        check_reach('fake', (0.101, 1.0), (0.1, 15.0))
    with pytest.raises(SegmentRefused, match=r'0\.010 m and 15\.1 deg'):
        check_reach('fake', (0.01, 15.1), (0.1, 15.0))


def test_a_refused_plan_carries_how_it_was_planned():
    """SegmentRefused.report: the draws and how far the kept plan ended when the reach check (or
    the timing) refuses it; the policy's failure and ik_error when it found no plan."""
    from hdp_controller.inputs import SegmentRefused
    from hdp_controller.low_level import PlanResult
    from hdp_controller.segment_planning import PlanReport, plan_segment, reach_error
    far = np.vstack([panda.HOME, panda.HOME + np.array([0.6, 0, 0, 0, 0, 0, 0])])
    policy = DrawingPolicy([far, far, far])
    with pytest.raises(SegmentRefused, match='plan ends') as refused:
        plan_segment(policy, _request(), panda.ARM_JOINTS, 0.5, (0.1, 15.0), attempts=3)
    report = refused.value.report
    assert isinstance(report, PlanReport) and report.method == 'fake' and report.draws == 3 == len(policy.requests)
    assert report.reach_error == pytest.approx(reach_error(far[-1], reachable_goal()))
    assert report.reach_error[0] > 0.1 and report.failure is None and not report.ik_error
    assert str(refused.value).startswith(f'fake plan ends {report.reach_error[0]:.3f} m')

    beyond = np.vstack([panda.HOME, panda.UPPER + np.array([0, 0, 0, 0, 0, 0.01, 0])])
    with pytest.raises(SegmentRefused, match='outside the joint position limits') as refused:
        plan_segment(FakePolicy(beyond), _request(), panda.ARM_JOINTS, 0.5)
    assert refused.value.report.draws == 1 and refused.value.report.reach_error is not None

    with pytest.raises(SegmentRefused, match=r'fake found no trajectory \(no_path\)') as refused:
        plan_segment(FakePolicy(failure='no_path'), _request(), panda.ARM_JOINTS, 0.5, (0.1, 15.0), attempts=3)
    report = refused.value.report
    assert (report.method, report.draws, report.failure, report.ik_error) == ('fake', 1, 'no_path', False)
    assert report.reach_error is None

    class NoIK(FakePolicy):
        def plan(self, request, scene=None):
            return PlanResult(None, failure='ik_error', ik_error=True)
    with pytest.raises(SegmentRefused, match=r'fake found no trajectory \(ik_error\)') as refused:
        plan_segment(NoIK(), _request(), panda.ARM_JOINTS, 0.5)
    assert refused.value.report.failure == 'ik_error' and refused.value.report.ik_error is True
    assert SegmentRefused('why').report is None                    # refused before planning: no report


class DrawingPolicy(FakePolicy):
    """Each plan() the next of ``draws`` (joint arrays), as a diffusion policy draws fresh noise."""

    def __init__(self, draws):
        super().__init__()
        self.draws = list(draws)

    def plan(self, request, scene=None):
        self.joints = self.draws[len(self.requests)]
        return super().plan(request, scene)


def test_a_plan_ending_away_from_its_nbp_is_drawn_again_up_to_the_attempts():
    from hdp_controller.inputs import SegmentRefused
    from hdp_controller.segment_planning import plan_segment, plan_within_reach
    far = np.vstack([panda.HOME, panda.HOME + np.array([0.6, 0, 0, 0, 0, 0, 0])])
    farther = np.vstack([panda.HOME, panda.HOME + np.array([0.9, 0, 0, 0, 0, 0, 0])])
    reaching = np.vstack([panda.HOME, REACHING_Q])
    policy = DrawingPolicy([far, reaching, far])
    msg, report = plan_segment(policy, _request(), panda.ARM_JOINTS, 0.5, (0.1, 15.0), attempts=3)
    assert np.allclose(msg.points[-1].positions, REACHING_Q) and len(policy.requests) == 2   # stops when within
    assert report.draws == 2 and report.reach_error[0] < 0.001
    with pytest.raises(SegmentRefused, match='plan ends'):
        plan_segment(DrawingPolicy([far, reaching]), _request(), panda.ARM_JOINTS, 0.5, (0.1, 15.0), attempts=1)
    plan, draws = plan_within_reach(DrawingPolicy([farther, far, farther]), _request(), (0.1, 15.0), attempts=3)
    assert draws == 3 and np.allclose(plan.joints, far)                  # none within: the nearest
    plan, draws = plan_within_reach(DrawingPolicy([far, reaching]), _request(), None, attempts=3)
    assert draws == 1 and np.allclose(plan.joints, far)                  # nothing to check: one draw
    failing = FakePolicy(failure='no_path')
    assert plan_within_reach(failing, _request(), (0.1, 15.0), attempts=3)[1] == 1


def test_planner_method_reaches_the_goal_pose_within_limits():
    from hdp_motion import kinematics
    from hdp_controller.baselines import PlannerPolicy
    from hdp_controller.segment_planning import plan_segment
    msg, _ = plan_segment(PlannerPolicy(), _request(), panda.ARM_JOINTS, 0.5)
    _, positions, _, _ = conversions.parse_joint_trajectory(msg)
    assert panda.within_limits(positions)
    end = kinematics.fk_pose(torch.as_tensor(positions[-1])).numpy()
    assert np.linalg.norm(end[:3] - reachable_goal()[:3]) < 0.01


# --- segment completion ---------------------------------------------------------------------

def _state(q, qd=None, width=0.08):
    from hdp_controller.inputs import ArmState
    return ArmState(np.asarray(q, float), np.zeros(7) if qd is None else np.asarray(qd, float), width)


def test_a_segment_is_done_when_the_arm_is_still_at_the_end_and_the_fingers_settle():
    from hdp_controller.execution import SegmentExecution
    goal = panda.HOME + 0.2
    run = SegmentExecution(goal, duration_s=2.0, start_s=10.0, timeout_s=5.0, gripper_open=False)
    assert run.update(11.0, _state(goal)) == (False, None)                    # before the trajectory's end
    assert run.update(12.5, _state(goal + 0.05)) == (False, None)             # not there yet
    assert run.update(12.6, _state(goal, qd=np.full(7, 0.1))) == (False, None)  # there, still moving
    assert run.update(12.7, _state(goal + 0.005)) == (True, None)             # arrived: close the gripper
    assert run.update(12.8, _state(goal, width=0.08)) == (False, None)
    assert run.update(13.0, _state(goal, width=0.05)) == (False, None)        # closing
    assert run.update(13.2, _state(goal, width=0.03)) == (False, None)        # stopped on an object ...
    assert run.update(13.5, _state(goal, width=0.03)) == (False, 'done')      # ... for 0.2 s: done


def test_segment_timeouts_and_no_gripper_action():
    from hdp_controller.execution import BLOCKED_STILL_S, SegmentExecution
    goal = panda.HOME + 0.2
    moving = np.full(7, 0.05)
    stuck = SegmentExecution(goal, 1.0, 0.0, timeout_s=2.0, gripper_open=None)
    assert stuck.update(2.9, _state(goal + 0.1, moving)).result is None
    result = stuck.update(3.1, _state(goal + 0.1, moving)).result
    assert result.startswith('failed: the arm did not come to rest') and '0.100 rad' in result
    # carry_on (the simulated graph's choice): arrived where it is, the gripper acts, then done.
    sliding = SegmentExecution(goal, 1.0, 0.0, timeout_s=2.0, gripper_open=False, carry_on=True)
    assert sliding.update(2.9, _state(goal + 0.1, moving)) == (False, None)
    assert sliding.update(3.1, _state(goal + 0.1, moving)) == (True, None)
    assert sliding.unsettled == pytest.approx((0.1, 0.05)) and sliding.short_by is None
    assert sliding.update(3.2, _state(goal + 0.1, moving, width=0.0)) == (False, 'done')
    # Still but short (a drawer's end stop): done once it has been still for BLOCKED_STILL_S.
    blocked = SegmentExecution(goal, 1.0, 0.0, timeout_s=2.0, gripper_open=None)
    assert blocked.update(1.2, _state(goal + 0.03)).result is None
    assert blocked.update(1.2 + BLOCKED_STILL_S / 2, _state(goal + 0.03)).result is None
    assert blocked.update(1.2 + BLOCKED_STILL_S, _state(goal + 0.03)).result == 'done'
    assert blocked.short_by == pytest.approx(0.03)
    # Pressed on a stop, the velocities jitter; no progress for BLOCKED_STILL_S is what counts.
    from hdp_controller.execution import BLOCKED_BAND
    pressed = SegmentExecution(goal, 1.0, 0.0, timeout_s=2.0, gripper_open=None)
    jitter = [(goal + 0.03 + sign * BLOCKED_BAND / 3, np.full(7, 0.08 * sign)) for sign in (1, -1) * 5]
    times = 1.2 + np.arange(len(jitter)) * BLOCKED_STILL_S / 8
    results = [pressed.update(t, _state(q, qd)).result for t, (q, qd) in zip(times[:9], jitter)]
    assert results == [None] * 8 + ['done']
    creeping = SegmentExecution(goal, 1.0, 0.0, timeout_s=2.0, gripper_open=None)
    for i, t in enumerate(np.arange(1.2, 2.9, 0.1)):                # progress of 2 band widths per 0.5 s
        assert creeping.update(t, _state(goal + 0.1 - i * BLOCKED_BAND * 0.4, moving)).result is None
    assert SegmentExecution(goal, 1.0, 0.0, 2.0, None).update(1.5, _state(goal)) == (False, 'done')
    dead_gripper = SegmentExecution(goal, 1.0, 0.0, 2.0, gripper_open=True)
    assert dead_gripper.update(1.0, _state(goal, width=0.0)).send_gripper
    assert dead_gripper.update(3.0, _state(goal, width=0.0)).result is None
    assert dead_gripper.update(4.1, _state(goal, width=0.0)).result.startswith('failed: the gripper did not open')
    opening = SegmentExecution(goal, 1.0, 0.0, 2.0, gripper_open=True)
    opening.update(1.0, _state(goal, width=0.0))
    assert opening.update(1.5, _state(goal, width=0.0795)).result == 'done'


# --- the controller's state between messages ---------------------------------------------------

def _controller(policy=None, needs_points=False, **kwargs):
    from hdp_controller.segment_controller import SegmentController
    controller = SegmentController(policy or FakePolicy([REACHING_Q]), needs_points, 0.5, 5.0, **kwargs)
    controller.on_joint_state(joint_state_msg(panda.HOME))
    return controller


def _kinds(outputs):
    """Each record's kind: 'arm' (ArmCommand), 'gripper' (FingerCommand), 'result' (SegmentResult), 'hold',
    or a StatusLine's 'info' / 'error'; any other record is an error."""
    from hdp_controller.segment_controller import ArmCommand, FingerCommand, HoldArm, SegmentResult
    from hdp_msgs_py.outcome import StatusLine
    kinds = {ArmCommand: 'arm', FingerCommand: 'gripper', SegmentResult: 'result', HoldArm: 'hold'}
    return [('error' if out.error else 'info') if type(out) is StatusLine else kinds[type(out)] for out in outputs]


def test_controller_refuses_a_nan_pose_with_a_result_and_no_trajectory():
    controller = _controller()
    out = controller.on_nbp(nbp((math.nan, 0, 1), (1, 0, 0, 0), stamp_sec=7), now_s=0.0)
    assert _kinds(out) == ['error', 'result']
    assert out[1].header.stamp.sec == 7 and out[1].header.frame_id.startswith('failed: invalid pose')
    assert not out[1].done and out[1].plan is None                 # refused before any planning
    assert out[0].text.startswith('refused segment 7.000: invalid pose')
    assert controller.step(1.0) == [] and controller.pending is None


def test_controller_pairs_the_gripper_goal_by_stamp_and_reports_done():
    controller = _controller()
    goal = reachable_goal()
    assert controller.on_gripper_goal(gripper_goal_msg(False, stamp_sec=3)) == []
    assert controller.on_nbp(nbp(goal[:3], goal[3:], stamp_sec=3), now_s=0.0) == []
    out = controller.step(0.05)
    assert _kinds(out) == ['arm', 'info']
    assert out[0].stamp == Time(sec=3) and out[0].plan.method == 'fake' and out[0].plan.draws == 1
    assert out[1].text.startswith('segment 3.000: fake to (') and ', then close the gripper (planned in ' in out[1].text
    assert out[1].text.endswith(' s, 1 draw)')
    end = np.asarray(out[0].trajectory.points[-1].positions)
    controller.on_joint_state(joint_state_msg(end))
    out = controller.step(30.0)
    assert _kinds(out) == ['gripper']
    names, fingers, _, _ = conversions.parse_joint_trajectory(out[0].trajectory)
    assert names == list(panda.FINGER_JOINTS) and fingers.tolist() == [[0.0, 0.0]]
    controller.on_joint_state(joint_state_msg(end, fingers=(0.0, 0.0)))
    out = controller.step(30.2)
    assert _kinds(out) == ['info', 'result'] and out[1].header.frame_id == 'done' and out[1].header.stamp.sec == 3
    assert out[1].done and out[0].text == 'segment 3.000: done'
    # A simulator reset opens the hand behind the controller's back: the next segment reads the fingers.
    controller.on_joint_state(joint_state_msg(end, fingers=(0.04, 0.04)))
    controller.on_nbp(nbp(goal[:3], goal[3:], stamp_sec=5), now_s=31.0)
    line = controller.step(32.0)[0]
    assert 'gripper stays open' in line.text and not line.error


def test_a_robot_that_stops_answering_fails_the_running_segment_naming_why():
    controller = _controller()
    assert controller.robot_gone('no /joint_states for 5.2 s') == []            # idle: nothing to fail
    goal = reachable_goal()
    controller.on_gripper_goal(gripper_goal_msg(False, stamp_sec=3))
    controller.on_nbp(nbp(goal[:3], goal[3:], stamp_sec=3), now_s=0.0)
    assert _kinds(controller.step(0.05)) == ['arm', 'info']
    out = controller.robot_gone('no /joint_states for 5.2 s')
    assert _kinds(out) == ['error', 'result'] and out[1].header.stamp.sec == 3
    assert out[0].text == 'segment 3.000 failed: no /joint_states for 5.2 s'
    assert out[1].header.frame_id == 'failed: no /joint_states for 5.2 s' and controller.running is None


def test_an_operators_stop_holds_the_arm_where_it_is_and_fails_the_running_segment():
    from hdp_controller.segment_controller import SegmentController
    assert _kinds(SegmentController(FakePolicy([REACHING_Q]), False, 0.5, 5.0).hold('stop')) == ['hold', 'info']
    assert SegmentController(FakePolicy([REACHING_Q]), False, 0.5, 5.0).hold('stop')[0].trajectory is None
    controller = _controller()
    out = controller.hold('stopped by /hdp/stop')                    # idle: the arm is held all the same
    assert _kinds(out) == ['hold', 'info'] and out[1].text == 'holding the arm: stopped by /hdp/stop'
    goal = reachable_goal()
    controller.on_gripper_goal(gripper_goal_msg(False, stamp_sec=3))
    controller.on_nbp(nbp(goal[:3], goal[3:], stamp_sec=3), now_s=0.0)
    assert _kinds(controller.step(0.05)) == ['arm', 'info']
    moving = panda.HOME + 0.02
    controller.on_joint_state(joint_state_msg(moving, qd=np.full(7, 0.5)))
    out = controller.hold('stopped by /hdp/stop')
    assert _kinds(out) == ['hold', 'info', 'error', 'result'] and controller.running is None
    # joint_trajectory_controller's own hold command: one point where the arm is, at time 0, now.
    names, positions, times, velocities = conversions.parse_joint_trajectory(out[0].trajectory)
    assert names == list(panda.ARM_JOINTS) and np.allclose(positions, [moving]) and times.tolist() == [0.0]
    assert velocities is None and out[0].trajectory.header.stamp.sec == 0
    assert out[3].header.stamp.sec == 3 and out[3].header.frame_id == 'failed: stopped by /hdp/stop'
    assert _kinds(controller.step(0.1)) == []                       # nothing left to follow


def test_controller_without_a_gripper_goal_keeps_the_gripper_after_a_short_wait():
    from hdp_controller.segment_controller import PAIRING_WAIT_S
    controller = _controller()
    goal = reachable_goal()
    controller.on_nbp(nbp(goal[:3], goal[3:]), now_s=0.0)
    assert controller.step(PAIRING_WAIT_S / 2) == []
    out = controller.step(PAIRING_WAIT_S + 0.01)
    assert _kinds(out) == ['info', 'arm', 'info'] and 'gripper stays open' in out[0].text
    assert controller.running[1].gripper_open is None


def test_a_newer_nbp_supersedes_the_running_segment_and_a_repeat_is_ignored():
    """After a reset (sim time restarts) or a result timeout the planner sends its next NBP while
    the controller still runs the last segment: the newer one takes over at once."""
    controller = _controller()
    goal = reachable_goal()
    controller.on_gripper_goal(gripper_goal_msg(False, stamp_sec=3))
    controller.on_nbp(nbp(goal[:3], goal[3:], stamp_sec=3), now_s=10.0)
    assert _kinds(controller.step(10.05)) == ['arm', 'info']
    repeat = controller.on_nbp(nbp(goal[:3], goal[3:], stamp_sec=3), now_s=10.1)
    assert _kinds(repeat) == ['error'] and 'repeated' in repeat[0].text and controller.running is not None
    newer = controller.on_nbp(nbp(goal[:3], goal[3:], stamp_sec=1), now_s=0.2)    # after a reset
    assert _kinds(newer) == ['error', 'result'] and newer[1].header.stamp.sec == 3
    assert newer[1].header.frame_id == 'failed: superseded by segment 1.000'
    assert controller.running is None
    out = controller.step(0.8)
    assert _kinds(out) == ['info', 'arm', 'info'] and 'segment 1.000' in out[2].text
    # a pending segment is superseded the same way, its gripper goal forgotten
    controller.on_gripper_goal(gripper_goal_msg(True, stamp_sec=6))
    controller.on_nbp(nbp(goal[:3], goal[3:], stamp_sec=6), now_s=1.0)
    invalid = controller.on_nbp(nbp((math.nan, 0, 1), (1, 0, 0, 0), stamp_sec=7), now_s=1.01)
    assert _kinds(invalid) == ['error', 'result', 'error', 'result']
    assert [m.header.frame_id.split(':')[0] for m in invalid[1::2]] == ['failed', 'failed']
    assert [m.header.stamp.sec for m in invalid[1::2]] == [6, 7]
    assert controller.pending is None and controller.gripper_goals == {}


def test_controller_refuses_without_joint_states_or_camera():
    from hdp_controller.segment_controller import STARTUP_WAIT_S, SegmentController
    goal = reachable_goal()
    blind = SegmentController(FakePolicy([REACHING_Q]), False, 0.5, 5.0)
    blind.on_joint_state(JointState(name=list(panda.FINGER_JOINTS), position=[0.04, 0.04]))   # fingers only
    blind.on_gripper_goal(gripper_goal_msg(True))
    blind.on_nbp(nbp(goal[:3], goal[3:]), 0.0)
    assert blind.step(0.1) == []                     # the first joint state may still be on its way
    reason = blind.step(STARTUP_WAIT_S + 0.01)[1].header.frame_id
    assert reason.startswith('failed: no usable /joint_states received yet (joint state lacks')
    assert 'panda_joint1' in reason
    learned = _controller(needs_points=True)
    learned.on_gripper_goal(gripper_goal_msg(True))
    learned.on_nbp(nbp(goal[:3], goal[3:]), 0.0)
    assert learned.step(0.1) == []                   # the first frame may still be on its way
    assert 'no front camera depth' in learned.step(STARTUP_WAIT_S + 0.01)[1].header.frame_id


def test_an_nbp_that_beats_the_first_joint_state_waits_for_it():
    from hdp_controller.segment_controller import SegmentController
    goal = reachable_goal()
    controller = SegmentController(FakePolicy([REACHING_Q]), False, 0.5, 5.0)
    controller.on_gripper_goal(gripper_goal_msg(True))
    controller.on_nbp(nbp(goal[:3], goal[3:]), 0.0)
    assert controller.step(1.0) == []
    controller.on_joint_state(joint_state_msg(panda.HOME))
    assert _kinds(controller.step(1.1)) == ['arm', 'info']


def test_a_depth_image_of_the_clock_before_a_reset_is_dropped():
    controller = _controller(needs_points=True)
    controller.on_joint_state(joint_state_msg(panda.HOME, stamp_sec=20))
    old = conversions.numpy_to_image(np.full((4, 6), 900, np.uint16), '16UC1', Header(stamp=Time(sec=20)))
    controller.on_depth(old)
    assert controller.depth is old
    controller.on_joint_state(joint_state_msg(panda.HOME, stamp_sec=1))           # reset: sim time restarts
    assert controller.depth is None
    controller.on_depth(old)                                                       # late, of the old clock
    assert controller.depth is None
    new = conversions.numpy_to_image(np.full((4, 6), 900, np.uint16), '16UC1', Header(stamp=Time(sec=1)))
    controller.on_depth(new)
    assert controller.depth is new


def test_controller_builds_front_camera_points_for_learned_methods():
    from hdp_sim_bridge.cameras import default_cameras
    camera = default_cameras(32, 24)['front']
    depth = np.full((24, 32), 1500, np.uint16)
    policy = FakePolicy([REACHING_Q])
    controller = _controller(policy, needs_points=True)
    controller.on_tf_static(TFMessage(transforms=[camera.transform_stamped()]))
    goal = reachable_goal()
    controller.on_gripper_goal(gripper_goal_msg(True))
    controller.on_nbp(nbp(goal[:3], goal[3:]), 0.0)
    assert controller.step(0.1) == []                # an NBP that beats the first frame waits for it
    controller.on_depth(conversions.numpy_to_image(depth, '16UC1', Header(frame_id=camera.frame_id)))
    controller.on_camera_info(camera.camera_info(Time()))
    assert 'arm' in _kinds(controller.step(0.2))
    assert policy.requests[0].points.shape == (1024, 3)


def test_camera_info_comes_through_on_camera_info_and_a_learned_method_waits_for_it():
    from hdp_controller.segment_controller import STARTUP_WAIT_S
    from hdp_sim_bridge.cameras import default_cameras
    camera = default_cameras(32, 24)['front']
    depth = conversions.numpy_to_image(np.full((24, 32), 1500, np.uint16), '16UC1', Header(frame_id=camera.frame_id))
    goal = reachable_goal()
    policy = FakePolicy([REACHING_Q])
    controller = _controller(policy, needs_points=True)
    controller.on_tf_static(TFMessage(transforms=[camera.transform_stamped()]))
    controller.on_depth(depth)
    controller.on_gripper_goal(gripper_goal_msg(True))
    controller.on_nbp(nbp(goal[:3], goal[3:]), 0.0)
    assert controller.step(0.1) == [] and policy.requests == []        # depth, but no camera_info yet
    info = camera.camera_info(Time())
    controller.on_camera_info(info)
    assert controller.info is info
    assert _kinds(controller.step(0.2)) == ['arm', 'info'] and policy.requests[0].points.shape == (1024, 3)
    # Without camera_info the segment is refused after the start-up wait, never planned blind.
    blind = _controller(FakePolicy([REACHING_Q]), needs_points=True)
    blind.on_tf_static(TFMessage(transforms=[camera.transform_stamped()]))
    blind.on_depth(depth)
    blind.on_gripper_goal(gripper_goal_msg(True))
    blind.on_nbp(nbp(goal[:3], goal[3:]), 0.0)
    out = blind.step(STARTUP_WAIT_S + 0.01)
    assert _kinds(out) == ['error', 'result'] and blind.policy.requests == []
    assert out[1].header.frame_id == 'failed: no front camera depth and camera_info received yet'


class ScenePolicy(FakePolicy):
    """A FakePolicy that also records the scene each plan() was given."""

    def __init__(self, joints):
        super().__init__(joints)
        self.scenes = []

    def plan(self, request, scene=None):
        self.scenes.append(scene)
        return super().plan(request, scene)


def test_each_segment_plans_in_the_scene_the_callable_gives():
    """scene=: called once per segment (the evaluations' simulator scene); None leaves the policy
    its own, as on a robot."""
    scenes = iter(['scene 1', 'scene 2'])
    policy = ScenePolicy([REACHING_Q])
    controller = _controller(policy, scene=lambda: next(scenes))
    goal = reachable_goal()
    for stamp_sec in (1, 2):          # the second NBP supersedes the first segment, then plans
        controller.on_gripper_goal(gripper_goal_msg(True, stamp_sec=stamp_sec))
        controller.on_nbp(nbp(goal[:3], goal[3:], stamp_sec=stamp_sec), now_s=float(stamp_sec))
        assert _kinds(controller.step(stamp_sec + 0.05)) == ['arm', 'info']
    assert policy.scenes == ['scene 1', 'scene 2']
    default = ScenePolicy([REACHING_Q])
    controller = _controller(default)
    controller.on_gripper_goal(gripper_goal_msg(True))
    controller.on_nbp(nbp(goal[:3], goal[3:]), 0.0)
    assert _kinds(controller.step(0.05)) == ['arm', 'info'] and default.scenes == [None]


def test_another_command_to_the_arm_fails_the_running_segment_as_preempted():
    """What controller_node tells its logic when a trajectory or a goal that is not its own reaches
    the arm: the running segment fails, naming the command; with no segment running, nothing."""
    controller = _controller()
    assert controller.preempted('a trajectory on /arm') == []
    goal = reachable_goal()
    controller.on_gripper_goal(gripper_goal_msg(True, stamp_sec=3))
    controller.on_nbp(nbp(goal[:3], goal[3:], stamp_sec=3), 0.0)
    assert _kinds(controller.step(0.05)) == ['arm', 'info']
    out = controller.preempted('FollowJointTrajectory goal 1a2b3c4d on /arm/follow_joint_trajectory')
    assert _kinds(out) == ['error', 'result'] and controller.running is None
    assert out[1].header.frame_id == ('failed: preempted by another command (FollowJointTrajectory goal 1a2b3c4d '
                                      'on /arm/follow_joint_trajectory)')
    assert out[1].header.stamp.sec == 3


def test_a_segment_planning_refuses_fails_with_its_plan_report():
    controller = _controller(FakePolicy(failure='no_path'))
    goal = reachable_goal()
    controller.on_gripper_goal(gripper_goal_msg(True, stamp_sec=4))
    controller.on_nbp(nbp(goal[:3], goal[3:], stamp_sec=4), 0.0)
    out = controller.step(0.05)
    assert _kinds(out) == ['error', 'result'] and controller.running is None
    assert out[0].text == 'refused segment 4.000: fake found no trajectory (no_path)'
    assert out[1].header.frame_id == 'failed: fake found no trajectory (no_path)' and not out[1].done
    assert out[1].plan.method == 'fake' and out[1].plan.failure == 'no_path' and out[1].plan.draws == 1


# --- controller_node as a process next to sim_bridge_node -----------------------------------------

def _probe_beside_the_sim(ros_domain: int, probe: str, timeout_s: float, *controller_parameters):
    """Run this file's ``probe`` mode beside sim_bridge_node (reach_target seed 3, 64x48 cameras) and
    controller_node (method planner, sim time, the given parameters); (the probe's JSON facts, None
    when the controller exited cleanly, else its stderr)."""
    env = dict(os.environ, ROS_DOMAIN_ID=str(ros_domain), PYTHONUNBUFFERED='1', OMP_NUM_THREADS='1')
    bridge = subprocess.Popen([sys.executable, '-m', 'hdp_sim_bridge.sim_bridge_node', '--ros-args',
                               '-p', 'camera_width:=64', '-p', 'camera_height:=48', '-p', 'camera_rate_hz:=2.0',
                               '-p', 'task:=reach_target', '-p', 'seed:=3'],
                              env=env, text=True, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    parameters = [arg for parameter in ('autostart:=true', 'method:=planner', 'use_sim_time:=true',
                                        *controller_parameters) for arg in ('-p', parameter)]
    controller = subprocess.Popen([sys.executable, '-m', 'hdp_controller.controller_node', '--ros-args',
                                   *parameters], env=env, text=True, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        run = subprocess.run([sys.executable, __file__, probe], env=env, text=True, capture_output=True,
                             timeout=timeout_s)
    finally:
        for proc in (controller, bridge):
            proc.send_signal(signal.SIGINT)
        errors = [proc.communicate(timeout=20)[1] for proc in (controller, bridge)]
    assert run.returncode == 0, run.stderr + '\n'.join(errors)
    return json.loads(run.stdout.strip().splitlines()[-1]), None if controller.returncode == 0 else errors[0]


@pytest.mark.dds
@pytest.mark.parametrize('interface', ['topic', 'action'])
def test_controller_node_executes_an_nbp_and_refuses_a_nan_one(ros_domain, interface):
    """Sim in the loop, on either interface: the JointTrajectory topic, or the
    FollowJointTrajectory and GripperCommand actions the sim serves as JTC and franka_gripper do."""
    facts, controller_err = _probe_beside_the_sim(ros_domain, 'probe', 90, f'arm_interface:={interface}',
                                                  f'gripper_interface:={interface}')
    assert facts['nan_result'].startswith('failed: invalid pose: position must be finite')
    assert any('refused segment 1.000' in s for s in facts['status'])
    # The segment's own outcome first: on a loaded machine its status lines say why it failed.
    assert facts['result'] == 'done' and facts['result_stamp'] in (2, 3, 4), facts['status']
    if interface == 'topic':
        assert facts['trajectories'] == 1                             # the NaN pose sent none
        assert facts['within_limits'] and facts['first_point_error'] < 0.05
    else:
        assert facts['trajectories'] == 0                             # all went as goals
        assert any('sim_bridge_node: executing FollowJointTrajectory goal' in s for s in facts['status'])
    assert facts['arm_error'] < 0.02                                  # at the last waypoint
    assert facts['ee_error_m'] < 0.01                                 # so at the NBP
    assert facts['gripper_width'] < 0.005                             # closed, as asked
    assert controller_err is None


def probe() -> None:
    """Drive a running controller_node + sim_bridge_node; print what happened as one JSON line."""
    from hdp_motion import kinematics
    from hdp_ros import ros
    from hdp_msgs_py.msg import JointTrajectory, String
    ros.init(args=sys.argv)
    node = ros.Node('controller_probe')
    seen = {'status': [], 'trajectories': [], 'results': [], 'joints': None}
    node.create_subscription(String, topics.STATUS, lambda m: seen['status'].append(m.data), topics.STATUS_QOS)
    trajectory_sub = node.create_subscription(JointTrajectory, topics.ARM_TRAJECTORY,
                                              seen['trajectories'].append, 10)
    result_sub = node.create_subscription(Header, topics.SEGMENT_RESULT, seen['results'].append, 10)
    node.create_subscription(JointState, topics.JOINT_STATES, lambda m: seen.__setitem__('joints', m), 10)
    pose_pub = node.create_publisher(PoseStamped, topics.NEXT_BEST_POSE, topics.COMMAND_QOS)
    gripper_pub = node.create_publisher(JointState, topics.NEXT_BEST_GRIPPER, topics.COMMAND_QOS)

    def spin(seconds, until):
        end = time.monotonic() + seconds
        while time.monotonic() < end and not until():
            rclpy.spin_once(node, timeout_sec=0.05)
        return until()

    # The controller is up when both its inputs and both its outputs are matched with ours.
    assert spin(60, lambda: seen['joints'] is not None and pose_pub.get_subscription_count() > 0
                and gripper_pub.get_subscription_count() > 0 and result_sub.get_publisher_count() > 0
                and trajectory_sub.get_publisher_count() > 0), 'controller_node did not come up'
    time.sleep(0.5)
    facts = {}
    gripper_pub.publish(gripper_goal_msg(False, stamp_sec=1))
    pose_pub.publish(nbp((math.nan, 0.0, 1.0), (1, 0, 0, 0), stamp_sec=1))
    assert spin(20, lambda: seen['results']), 'no result for the NaN pose'
    facts['nan_result'] = seen['results'][0].frame_id

    goal = reachable_goal()
    # The probe's own /joint_states says nothing about the controller's: on a loaded machine the
    # controller may not have heard the robot yet, and it refuses by design; then ask again.
    for stamp_sec in (2, 3, 4):
        gripper_pub.publish(gripper_goal_msg(False, stamp_sec=stamp_sec))
        pose_pub.publish(nbp(goal[:3], goal[3:], stamp_sec=stamp_sec))
        assert spin(45, lambda: len(seen['results']) >= stamp_sec), 'no result for the reachable pose'
        result = seen['results'][-1]
        if not result.frame_id.startswith('failed: no usable /joint_states received yet'):
            break
        spin(1.0, lambda: False)
    facts.update(result=result.frame_id, result_stamp=result.stamp.sec, trajectories=len(seen['trajectories']))
    names = list(seen['joints'].name)
    position = np.asarray(seen['joints'].position, dtype=float)
    q = position[[names.index(n) for n in panda.ARM_JOINTS]]
    end = kinematics.fk_pose(torch.as_tensor(q, dtype=torch.float64)).numpy()
    facts.update(ee_error_m=float(np.linalg.norm(end[:3] - goal[:3])), arm_error=0.0,
                 gripper_width=float(sum(position[names.index(n)] for n in panda.FINGER_JOINTS)))
    if seen['trajectories']:
        _, positions, _, _ = conversions.parse_joint_trajectory(seen['trajectories'][0])
        facts.update(within_limits=panda.within_limits(positions),
                     first_point_error=float(np.max(np.abs(positions[0] - panda.HOME))),
                     arm_error=float(np.max(np.abs(q - positions[-1]))))
    spin(0.5, lambda: False)
    facts['status'] = seen['status']
    print(json.dumps(facts), flush=True)
    node.destroy_node()
    rclpy.try_shutdown()


@pytest.mark.dds
@pytest.mark.parametrize('interface', ['topic', 'action'])
def test_another_command_moving_the_arm_mid_segment_fails_the_segment_preempted(ros_domain, interface):
    """The probe's intruder: while controller_node's slow segment runs, another client sends the
    sim's arm a FollowJointTrajectory goal (all joints, joint 1 to -1.5 rad in 3 s). The segment
    fails 'preempted by another command', never 'done (... blocked)', and the sim bridge says on
    /hdp/status what preempted what."""
    facts, controller_err = _probe_beside_the_sim(ros_domain, 'intrude', 120, 'velocity_scale:=0.05',
                                                  f'arm_interface:={interface}')
    result = facts['result']
    assert result.startswith('failed: preempted by another command ('), facts
    if interface == 'topic':            # seen on the action's status; the graph names who else commands the arm
        assert result.startswith('failed: preempted by another command (FollowJointTrajectory goal '), result
        assert '/intruder_probe (/panda_arm_controller/follow_joint_trajectory client)' in result, result
    preempts = [s for s in facts['status'] if s.startswith('sim_bridge_node: FollowJointTrajectory goal')
                and ' preempts ' in s]
    assert preempts, facts['status']
    assert facts['intruder_status'] == 'succeeded'           # the other command did move the arm
    assert controller_err is None


def intrude() -> None:
    """Send a slow segment, then another client's arm goal mid-segment; print the segment's result."""
    from control_msgs.action import FollowJointTrajectory
    from rclpy.action import ActionClient

    from hdp_msgs_py.msg import JointTrajectory, JointTrajectoryPoint, String
    from hdp_ros import ros
    ros.init(args=sys.argv)
    node = ros.Node('intruder_probe')
    seen = {'status': [], 'results': [], 'joints': None, 'moving': False}
    node.create_subscription(String, topics.STATUS, lambda m: seen['status'].append(m.data), topics.STATUS_QOS)
    result_sub = node.create_subscription(Header, topics.SEGMENT_RESULT, seen['results'].append, 10)
    node.create_subscription(JointState, topics.JOINT_STATES, lambda m: seen.__setitem__('joints', m), 10)
    pose_pub = node.create_publisher(PoseStamped, topics.NEXT_BEST_POSE, topics.COMMAND_QOS)
    gripper_pub = node.create_publisher(JointState, topics.NEXT_BEST_GRIPPER, topics.COMMAND_QOS)
    intruder = ActionClient(node, FollowJointTrajectory, topics.ARM_ACTION)

    def spin(seconds, until):
        end = time.monotonic() + seconds
        while time.monotonic() < end and not until():
            rclpy.spin_once(node, timeout_sec=0.05)
        return until()

    assert spin(60, lambda: seen['joints'] is not None and pose_pub.get_subscription_count() > 0
                and result_sub.get_publisher_count() > 0 and intruder.server_is_ready()), 'graph did not come up'
    time.sleep(0.5)
    goal = reachable_goal()
    for stamp_sec in (2, 3, 4):          # as the probe above: a controller that has not heard the arm refuses
        gripper_pub.publish(gripper_goal_msg(False, stamp_sec=stamp_sec))
        pose_pub.publish(nbp(goal[:3], goal[3:], stamp_sec=stamp_sec))
        if spin(5, lambda: any('executing' in s and 'sim_bridge_node' in s for s in seen['status'])):
            break
        assert seen['results'] and seen['results'][-1].frame_id.startswith('failed: no usable /joint_states'), \
            seen['status']
    spin(0.5, lambda: False)
    assert not seen['results'] or seen['results'][-1].stamp.sec != stamp_sec, 'the segment ended too soon'
    q = np.asarray(seen['joints'].position, dtype=float)[[list(seen['joints'].name).index(n)
                                                           for n in panda.ARM_JOINTS]]
    target = q.copy()
    target[0] = -1.5
    trajectory = JointTrajectory(joint_names=list(panda.ARM_JOINTS), points=[JointTrajectoryPoint(
        positions=target.tolist(), time_from_start=conversions.seconds_to_duration(3.0))])
    future = intruder.send_goal_async(FollowJointTrajectory.Goal(trajectory=trajectory))
    assert spin(10, future.done) and future.result().accepted, 'the intruding goal was not accepted'
    outcome = future.result().get_result_async()
    assert spin(30, lambda: any(r.stamp.sec == stamp_sec for r in seen['results'])), seen['status']
    spin(20, outcome.done)
    spin(0.5, lambda: False)
    from action_msgs.msg import GoalStatus
    print(json.dumps({'result': next(r.frame_id for r in seen['results'] if r.stamp.sec == stamp_sec),
                      'intruder_status': 'succeeded' if outcome.done() and outcome.result().status ==
                      GoalStatus.STATUS_SUCCEEDED else 'not succeeded', 'status': seen['status']}), flush=True)
    node.destroy_node()
    rclpy.try_shutdown()


if __name__ == '__main__' and sys.argv[1:2] == ['probe']:
    probe()
if __name__ == '__main__' and sys.argv[1:2] == ['intrude']:
    intrude()


@pytest.mark.dds
def test_controller_node_refuses_an_unknown_robot_type_at_start_with_one_line(ros_domain):
    env = dict(os.environ, ROS_DOMAIN_ID=str(ros_domain))
    proc = subprocess.run([sys.executable, '-m', 'hdp_controller.controller_node', '--ros-args',
                           '-p', 'method:=planner', '-p', 'robot_type:=ur5'],
                          env=env, text=True, capture_output=True, timeout=60)
    assert proc.returncode == 1
    assert "parameter 'robot_type': unknown robot type 'ur5'; robot types: panda, fr3" in proc.stderr
    assert 'Traceback' not in proc.stderr


class _FakeGoalHandle:
    def __init__(self, accepted=True):
        from rclpy.task import Future
        self.accepted, self.cancelled, self.result = accepted, 0, Future()

    def cancel_goal_async(self):
        self.cancelled += 1

    def get_result_async(self):
        return self.result


class _FakeActionClient:
    """Stands in for rclpy's ActionClient: records goals, the test answers them."""
    made = []

    def __init__(self, node, action_type, name):
        self.name, self.goals, self.ready = name, [], True
        _FakeActionClient.made.append(self)

    def server_is_ready(self):
        return self.ready

    def send_goal_async(self, goal, goal_uuid=None):
        from rclpy.task import Future
        future = Future()
        self.goals.append((goal, future))
        return future


def test_the_arm_action_fails_a_segment_on_refusal_or_abort_and_cancels_one_that_ended(monkeypatch):
    from types import SimpleNamespace

    from action_msgs.msg import GoalStatus
    from control_msgs.action import FollowJointTrajectory

    from hdp_controller import action_clients
    from hdp_controller.execution import GOAL_TOLERANCE
    from hdp_msgs_py.outcome import StatusLine
    monkeypatch.setattr(action_clients, 'ActionClient', _FakeActionClient)
    failed, sent = [], []
    arm = action_clients.ArmAction(None, topics.ARM_ACTION, panda.ARM_JOINTS, sent.append,
                                   lambda stamp, why: failed.append((stamp.sec, why)) or [StatusLine(why, True)])
    client = _FakeActionClient.made[-1]
    assert client.name == topics.ARM_ACTION

    arm.send(Time(sec=1), JointTrajectory())                       # refused by the controller
    goal, future = client.goals[-1]
    assert [t.position for t in goal.goal_tolerance] == [GOAL_TOLERANCE] * 7
    assert [t.name for t in goal.goal_tolerance] == list(panda.ARM_JOINTS)
    future.set_result(_FakeGoalHandle(accepted=False))
    assert failed[-1] == (1, 'the arm controller rejected the trajectory')
    assert sent[-1] == [StatusLine('the arm controller rejected the trajectory', error=True)]   # to the node

    arm.send(Time(sec=2), JointTrajectory())                       # accepted, then aborted
    handle = _FakeGoalHandle()
    client.goals[-1][1].set_result(handle)
    result = FollowJointTrajectory.Result(error_code=-5, error_string='not within the goal tolerance in time')
    handle.result.set_result(SimpleNamespace(status=GoalStatus.STATUS_ABORTED, result=result))
    assert failed[-1] == (2, 'the arm controller aborted the trajectory: not within the goal tolerance in time '
                             '(error_code -5)')

    arm.send(Time(sec=3), JointTrajectory())                       # superseded: its goal is cancelled
    handle = _FakeGoalHandle()
    client.goals[-1][1].set_result(handle)
    arm.segment_ended(Header(stamp=Time(sec=3), frame_id='failed: superseded by segment 4.000'))
    assert handle.cancelled == 1
    arm.send(Time(sec=4), JointTrajectory())                       # done: nothing to cancel
    handle = _FakeGoalHandle()
    client.goals[-1][1].set_result(handle)
    arm.segment_ended(Header(stamp=Time(sec=4), frame_id=topics.SEGMENT_DONE))
    arm.send(Time(sec=5), JointTrajectory())
    assert handle.cancelled == 0 and len(failed) == 2

    arm.send(Time(sec=7), JointTrajectory())                       # an operator's stop: cancelled
    handle = _FakeGoalHandle()
    client.goals[-1][1].set_result(handle)
    arm.cancel()
    arm.segment_ended(Header(stamp=Time(sec=7), frame_id='failed: stopped by /hdp/stop'))
    assert handle.cancelled == 1
    arm.cancel()                                                   # nothing active: nothing to cancel
    assert handle.cancelled == 1

    # Another client's goal preempts ours: the sim aborts it, a JTC may cancel it.
    for sec, status, why in ((8, GoalStatus.STATUS_ABORTED, 'preempted by another trajectory'),
                             (9, GoalStatus.STATUS_CANCELED, '')):
        arm.send(Time(sec=sec), JointTrajectory())
        handle = _FakeGoalHandle()
        client.goals[-1][1].set_result(handle)
        result = FollowJointTrajectory.Result(error_code=-1, error_string=why)
        handle.result.set_result(SimpleNamespace(status=status, result=result))
    assert failed[-2:] == [(8, 'preempted by another command (the arm controller: preempted by another trajectory)'),
                           (9, 'preempted by another command (the arm controller cancelled our goal)')]

    client.ready = False                                           # no controller at all
    arm.send(Time(sec=6), JointTrajectory())
    assert failed[-1] == (6, f'no FollowJointTrajectory server on {topics.ARM_ACTION}')


@pytest.mark.dds
def test_a_controller_that_was_stopped_says_so_instead_of_blaming_the_robot(ros_domain):
    """SIGSTOP controller_node for longer than state_timeout_s while sim_bridge_node runs on: when it
    continues, it names its own gap (the probe saw it blame the bridge: 'no /joint_states ...')."""
    env = dict(os.environ, ROS_DOMAIN_ID=str(ros_domain), PYTHONUNBUFFERED='1', OMP_NUM_THREADS='1')
    bridge = subprocess.Popen([sys.executable, '-m', 'hdp_sim_bridge.sim_bridge_node', '--ros-args',
                               '-p', 'camera_rate_hz:=0.0'], env=env, stdout=subprocess.DEVNULL,
                              stderr=subprocess.DEVNULL)
    controller = subprocess.Popen([sys.executable, '-m', 'hdp_controller.controller_node', '--ros-args',
                                   '-p', 'autostart:=true',
                                   '-p', 'method:=planner', '-p', 'state_timeout_s:=2.0'], env=env,
                                  stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    echo = None
    try:
        time.sleep(8.0)                                  # both up, joint states flowing
        echo = subprocess.Popen([sys.executable, '-m', 'hdp_tools.cli.main', 'topic', 'echo', topics.STATUS,
                                 'std_msgs/msg/String', '--qos-durability', 'volatile', '--timeout', '20'],
                                env=env, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
        time.sleep(3.0)
        controller.send_signal(signal.SIGSTOP)
        time.sleep(4.0)                                  # twice state_timeout_s, the bridge publishing on
        controller.send_signal(signal.SIGCONT)
        time.sleep(3.0)
    finally:
        for proc in (controller, bridge):
            proc.send_signal(signal.SIGCONT)
            proc.send_signal(signal.SIGINT)
        controller_err = controller.communicate(timeout=30)[1]
        bridge.communicate(timeout=30)
        if echo is not None:
            echo.terminate()
    lines = echo.communicate(timeout=10)[0]
    assert 'controller_node: this node itself did not run for' in lines, lines + controller_err
    assert 'no /joint_states' not in lines + controller_err


@pytest.mark.unit
def test_warm_up_plans_one_segment_from_home_and_takes_a_refusal_in_its_stride():
    from hdp_controller.segment_planning import warm_up
    for policy in (FakePolicy([panda.HOME]), FakePolicy(failure='no_path')):
        assert warm_up(policy) >= 0.0
        request, = policy.requests
        np.testing.assert_allclose(request.q, panda.HOME)
        assert np.linalg.norm(request.goal_pose[:3] - request.start_pose[:3]) == pytest.approx(0.05)
        assert request.points.shape == (1024, 3) and np.all(np.isfinite(request.points))
