"""controller_node's commands as actions, as real controllers take them.

The arm: joint_trajectory_controller's control_msgs/FollowJointTrajectory. Each segment's
trajectory is one goal with a goal tolerance per joint; a refused goal or an aborted one
fails that segment with the controller's words, and a segment that ends otherwise
(superseded by a newer NBP, timed out, the robot gone) cancels its goal. A goal that succeeds
changes nothing: the segment is done when the arm is seen still at its last waypoint and the
gripper has acted, on either interface.

The gripper: franka_gripper's control_msgs/GripperCommand (position = half the width). Closing
on an object ends 'aborted' there (the fingers stop short of the width asked for) while the
object is held, so results are only logged; the fingers' widths decide, as on the topic.
"""

from __future__ import annotations

import collections
import uuid

from action_msgs.msg import GoalStatus
from control_msgs.action import FollowJointTrajectory, GripperCommand
from control_msgs.msg import JointTolerance
from rclpy.action import ActionClient
from unique_identifier_msgs.msg import UUID

from hdp_msgs_py import topics
from hdp_msgs_py.conversions import seconds_to_duration, time_to_ns

from .execution import GOAL_TOLERANCE, PREEMPTED

GOAL_TIME_TOLERANCE_S = 1.0        # after the trajectory's end, for the arm to come within tolerance
GRIPPER_MAX_EFFORT = 20.0          # N, franka_gripper's grasp force


class ArmAction:
    """Sends each segment's JointTrajectory as a FollowJointTrajectory goal and follows it."""

    def __init__(self, node, name: str, joint_names, send, arm_failed):
        self._name, self._joint_names = name, tuple(joint_names)
        self._send, self._arm_failed = send, arm_failed       # the node's output path, the logic's hook
        self._client = ActionClient(node, FollowJointTrajectory, name)
        self._active = None                                    # (segment stamp, ClientGoalHandle or None)
        self._goal_ids: collections.deque[bytes] = collections.deque(maxlen=16)    # ours, newest last

    def owns(self, goal_id: bytes) -> bool:
        """Whether the goal of this id (16 bytes, unique_identifier_msgs/UUID) is one we sent."""
        return bytes(goal_id) in self._goal_ids

    def send(self, stamp, trajectory) -> None:
        self._cancel()
        if not self._client.server_is_ready():
            self._send(self._arm_failed(stamp, f'no FollowJointTrajectory server on {self._name}'))
            return
        goal = FollowJointTrajectory.Goal(
            trajectory=trajectory, goal_time_tolerance=seconds_to_duration(GOAL_TIME_TOLERANCE_S),
            goal_tolerance=[JointTolerance(name=name, position=GOAL_TOLERANCE) for name in self._joint_names])
        self._active = (stamp, None)
        goal_id = uuid.uuid4().bytes
        self._goal_ids.append(goal_id)
        self._client.send_goal_async(goal, goal_uuid=UUID(uuid=list(goal_id))).add_done_callback(
            lambda future: self._on_response(stamp, future))

    def segment_ended(self, result_header) -> None:
        """A segment result went out: if it was not 'done', the segment's goal is cancelled."""
        if self._active is None or time_to_ns(self._active[0]) != time_to_ns(result_header.stamp):
            return
        if result_header.frame_id == topics.SEGMENT_DONE:
            self._active = None
        else:
            self._cancel()

    def cancel(self) -> None:
        """Hold the arm (an operator's stop): cancelling its goal makes the controller hold position."""
        self._cancel()

    def _cancel(self) -> None:
        if self._active is not None and self._active[1] is not None:
            self._active[1].cancel_goal_async()
        self._active = None

    def _on_response(self, stamp, future) -> None:
        handle = future.result()
        if not handle.accepted:
            self._send(self._arm_failed(stamp, 'the arm controller rejected the trajectory'))
            return
        if self._active is not None and time_to_ns(self._active[0]) == time_to_ns(stamp):
            self._active = (stamp, handle)
        else:                                   # the segment ended while the goal was on its way
            handle.cancel_goal_async()
            return
        handle.get_result_async().add_done_callback(lambda f: self._on_result(stamp, f))

    def _on_result(self, stamp, future) -> None:
        response = future.result()
        result, why = response.result, response.result.error_string or 'no reason given'
        ours = self._active is not None and time_to_ns(self._active[0]) == time_to_ns(stamp)
        if response.status == GoalStatus.STATUS_ABORTED and 'preempt' in why.lower():
            self._send(self._arm_failed(stamp, f'{PREEMPTED} (the arm controller: {why})'))
        elif response.status == GoalStatus.STATUS_ABORTED:
            self._send(self._arm_failed(stamp, f'the arm controller aborted the trajectory: {why} '
                                               f'(error_code {result.error_code})'))
        elif response.status == GoalStatus.STATUS_CANCELED and ours:      # we cancel only what we let go
            self._send(self._arm_failed(stamp, f'{PREEMPTED} (the arm controller cancelled our goal)'))


class GripperAction:
    """Sends each gripper command as a GripperCommand goal (franka_gripper's gripper_action)."""

    def __init__(self, node, name: str):
        self._node, self._name = node, name
        self._client = ActionClient(node, GripperCommand, name)

    def send(self, finger_trajectory) -> None:
        """The finger JointTrajectory the controller logic makes -> a goal of the same width."""
        finger = float(finger_trajectory.points[-1].positions[0])           # m per finger = half the width
        if not self._client.server_is_ready():
            self._node.get_logger().error(f'no GripperCommand server on {self._name}')
            return
        goal = GripperCommand.Goal()
        goal.command.position, goal.command.max_effort = finger, GRIPPER_MAX_EFFORT
        self._client.send_goal_async(goal).add_done_callback(self._on_response)

    def _on_response(self, future) -> None:
        if not future.result().accepted:
            self._node.get_logger().error('the gripper refused the command')
