"""What planner_node does between messages, without ROS: one instruction, segment after segment.

    instruction -> validate -> [observe (fresh frames from both cameras) -> predict the NBP
    -> send gripper goal + NBP -> wait for the controller's result] until success or
    max_segments

The protocol with the controller is in the package README: the NBP's header.stamp keys the
segment; the gripper goal carries the same stamp; the controller answers on
/hdp/segment_result with it. ``PlannerLoop`` returns what to publish as records: SegmentGoal
(the gripper goal and the NBP), Prediction (each prediction's confidence, time and cloud),
StatusLine, and Outcome once per instruction, when it ends or is refused.
Times are seconds on the node's clock.
"""

from __future__ import annotations

import collections
import dataclasses
import time
from pathlib import Path

import numpy as np

from hdp_motion import panda
from hdp_learning import checkpoints
from hdp_msgs_py import conversions, topics
from hdp_msgs_py.conversions import time_to_ns
from hdp_msgs_py.msg import Header, JointState, PoseStamped, Time
from hdp_msgs_py.outcome import Outcome, StatusLine

from .language import words

MAX_INSTRUCTION_CHARS = 256
# Words every phrasing shares; an instruction made of these alone names no task.
FILLER_WORDS = frozenset({'a', 'an', 'and', 'it', 'of', 'off', 'the', 'to', 'up', 'with'})
DEFAULT_CHECKPOINT_NAME = 'hdp_nbp_agent_11tasks.pt'      # the eleven-task agent
FRAME_LEAD_S = 1.0       # how far a frame's stamp may run ahead of the latest joint state
# The agent's confidence in its first NBP below which an instruction is refused. Chosen for the
# default (eleven-task) agent on the validation seeds 900-919 (`hdp eval hierarchy --agents hdp
# --tasks all --episodes 20 --seed-start 900 --phrasings seen,heldout --min-confidence 0`): the
# highest threshold that refused no seen-phrasing episode that succeeds (the lowest such
# confidence was 0.056; 0.08, chosen for the six-task agent, would have refused 3 successes and
# nothing else). The six-task hdp_nbp_agent.pt was calibrated at 0.08: pass it with the file.
DEFAULT_MIN_CONFIDENCE = 0.05
# What an instruction that comes while another runs does (planner_node's `queue_policy`):
# replace: the newest instruction wins; the running one ends 'replaced' at the next segment
#   boundary, and one still waiting to start is 'replaced' at once.
# queue: it waits its turn, first in first out, up to `max_queued`; beyond that it is refused.
# refuse: it is refused ('busy'); the running one goes on.
QUEUE_POLICIES = ('replace', 'queue', 'refuse')
DEFAULT_MAX_QUEUED = 10


def default_checkpoint() -> Path:
    """$HDP_MODELS_DIR/hdp_nbp_agent_11tasks.pt, else the repository's models/hdp_nbp_agent_11tasks.pt."""
    return checkpoints.default_path(DEFAULT_CHECKPOINT_NAME)


class InstructionRefused(ValueError):
    """Why an instruction starts no motion."""


def validate_instruction(text: str, vocabulary) -> str:
    """The instruction stripped of surrounding space, or InstructionRefused: empty, longer than
    MAX_INSTRUCTION_CHARS, or without a word of ``vocabulary`` beyond the filler words
    (``vocabulary`` None: no word check)."""
    stripped = text.strip()
    if not stripped:
        raise InstructionRefused('the instruction is empty')
    if len(stripped) > MAX_INSTRUCTION_CHARS:
        raise InstructionRefused(f'the instruction has {len(stripped)} characters, '
                                 f'more than {MAX_INSTRUCTION_CHARS}')
    if vocabulary is None:
        return stripped
    content = set(vocabulary) - FILLER_WORDS
    if not any(w in content for w in words(stripped)):
        raise InstructionRefused(f'no word of {stripped!r} names anything the agent was trained on '
                                 f'(words such as {", ".join(sorted(content)[:6])}, ...)')
    return stripped


@dataclasses.dataclass(frozen=True)
class SegmentGoal:
    """Send the controller a segment: the gripper goal first (so it is usually there when the NBP
    arrives), then the NBP; both carry the segment's stamp."""
    gripper_goal: JointState
    nbp: PoseStamped


@dataclasses.dataclass(frozen=True)
class Prediction:
    """The agent predicted: its confidence, the seconds it took, and the cloud it saw
    ((N, 3) xyz, (N, 3) colours), for a viewer."""
    confidence: float
    seconds: float
    cloud: tuple


class Observations:
    """The latest frames of each camera, the camera extrinsics and the joint state.

    Frames count as fresh when stamped at or after a joint state seen earlier: both come
    from the robot (or the sim), so no clock of this node is compared with theirs. A simulator
    reset restarts that clock: when a joint state goes back in time the frames are dropped, and
    a frame stamped more than FRAME_LEAD_S ahead of the joint states (one of the old clock, late)
    never counts as fresh.

    depth_filter: a RealSense post-processing chain (hdp_data.depth_filters.FilterSettings) each
    camera's depth goes through as it arrives, with its own temporal history; None (default): depth
    as it comes. The chain needs the camera's focal length, so a depth frame that comes before the
    camera's first camera_info is dropped.

    refine_extrinsics: whether the loop checks each camera's extrinsics against the robot's body
    (check_extrinsics) as an instruction starts; agent_inputs then gives the refined ones.
    """

    def __init__(self, cameras=topics.CAMERAS, arm_joints=panda.ARM_JOINTS, finger_joints=panda.FINGER_JOINTS,
                 depth_filter=None, refine_extrinsics: bool = False):
        # Only Observations filters depth, so the import stays with it.
        from hdp_data.depth_filters import DepthFilter
        self.cameras = tuple(cameras)
        self.arm_joints, self.finger_joints = tuple(arm_joints), tuple(finger_joints)
        self.depth_filters = {} if depth_filter is None else {c: DepthFilter(depth_filter) for c in self.cameras}
        self.color: dict = {}
        self.depth: dict = {}
        self.info: dict = {}
        self.transforms: dict = {}           # child frame -> TransformStamped, from /tf_static
        self.joint_state = None
        self.refine_extrinsics = refine_extrinsics
        self.refined: dict = {}              # camera -> (4, 4) camera_to_world the robot's body gave

    def on_color(self, camera: str, msg) -> None:
        self.color[camera] = msg

    def on_depth(self, camera: str, msg) -> None:
        if camera in self.depth_filters:
            if camera not in self.info:
                return
            depth = self.depth_filters[camera].apply(conversions.image_to_numpy(msg), float(self.info[camera].k[0]),
                                                     time_to_ns(msg.header.stamp))
            msg = conversions.numpy_to_image(depth, '16UC1', msg.header)
        self.depth[camera] = msg

    def on_info(self, camera: str, msg) -> None:
        self.info[camera] = msg

    def on_tf_static(self, msg) -> None:
        self.transforms.update({t.child_frame_id: t for t in msg.transforms})

    def on_joint_state(self, msg) -> None:
        """Keep it if it has every arm and finger joint (a partial one is some other publisher's)."""
        if set(self.arm_joints + self.finger_joints) <= set(msg.name):
            if time_to_ns(msg.header.stamp) < self.joint_stamp_ns():      # the clock restarted
                self.color.clear()
                self.depth.clear()
                self.refined.clear()         # a reset world may have its cameras elsewhere
            self.joint_state = msg

    def joint_stamp_ns(self) -> int:
        return time_to_ns(self.joint_state.header.stamp) if self.joint_state is not None else 0

    def missing(self, since_ns: int) -> list[str]:
        """What is not there yet, e.g. ['front camera colour', 'side camera extrinsics']."""
        missing = [] if self.joint_state is not None else ['/joint_states with every arm and finger joint']
        latest_ns = self.joint_stamp_ns() + int(FRAME_LEAD_S * 1e9)
        for camera in self.cameras:
            for what, frames in (('colour', self.color), ('depth', self.depth)):
                if camera not in frames or not since_ns <= time_to_ns(frames[camera].header.stamp) <= latest_ns:
                    missing.append(f'{camera} camera {what}')
            if camera not in self.info:
                missing.append(f'{camera} camera_info')
            elif self._extrinsics(camera) is None:
                missing.append(f'{camera} camera extrinsics on /tf_static')
        return missing

    def _extrinsics(self, camera: str):
        transform = self.transforms.get(self.info[camera].header.frame_id)
        return transform if transform is not None and transform.header.frame_id == topics.NBP_FRAME else None

    def arm(self) -> tuple[np.ndarray, float]:
        """(joint positions (7,) rad, gripper width m) of the latest joint state."""
        names = list(self.joint_state.name)
        position = np.asarray(self.joint_state.position, dtype=float)
        return (position[[names.index(n) for n in self.arm_joints]],
                float(sum(position[names.index(n)] for n in self.finger_joints)))

    def agent_inputs(self) -> tuple[dict, dict, dict]:
        """(camera -> (rgb (H, W, 3) uint8, depth (H, W) uint16 mm), camera -> CameraInfo,
        camera -> TransformStamped world -> optical frame), as NextBestPoseAgent.predict takes them."""
        frames = {c: (conversions.image_to_numpy(self.color[c]), conversions.image_to_numpy(self.depth[c]))
                  for c in self.cameras}
        return frames, dict(self.info), {c: self.refined.get(c, self._extrinsics(c)) for c in self.cameras}

    def check_extrinsics(self) -> dict:
        """camera -> extrinsics.ExtrinsicRefinement of its pose on /tf_static against the robot's
        body in its latest depth frame and the latest joint state; agent_inputs gives the accepted
        corrections until the next check (a refused one leaves /tf_static's pose)."""
        from .extrinsics import refine_extrinsics       # the robot's meshes: loaded only where it is on
        q, width = self.arm()
        checked = {}
        for camera in self.cameras:
            depth = conversions.image_to_numpy(self.depth[camera])
            depth_m = depth * 0.001 if depth.dtype == np.uint16 else depth.astype(np.float32)
            checked[camera] = refine_extrinsics(depth_m, conversions.camera_info_to_intrinsics(self.info[camera]),
                                                conversions.transform_to_matrix(self._extrinsics(camera)), q, width)
        self.refined = {c: r.camera_to_world for c, r in checked.items() if r.accepted}
        return checked


@dataclasses.dataclass
class Segment:
    index: int                 # 1-based, within the instruction
    stamp: Time                # the NBP's header.stamp: the key the result comes back with
    xyz: np.ndarray            # (3,) m
    gripper_open: bool
    sent_s: float


class PlannerLoop:
    """One instruction at a time, as a state machine the node drives with step() and messages.

    idle (no instruction) -> observing (waiting for fresh frames, then predicting) ->
    waiting (a segment sent, its result due) -> observing ... -> idle. A result that does not
    come within result_timeout_s is reported and the loop observes again: the segment counts
    against the budget, and a restarted controller takes the next one.

    Every instruction gets exactly one Outcome: when it ends, or at once when it is refused,
    replaced before it started, stopped (stop()) or cut short by shutdown(). What an
    instruction arriving while another runs does is ``queue_policy`` (QUEUE_POLICIES); one
    waiting to start starts at the next step(), so a burst of instructions costs a message
    callback almost nothing. Every stop says why on /hdp/status.
    """

    def __init__(self, agent, vocabulary, max_segments: int = 8, camera_timeout_s: float = 5.0,
                 result_timeout_s: float = 60.0, observations: Observations | None = None,
                 min_confidence: float = DEFAULT_MIN_CONFIDENCE, queue_policy: str = 'replace',
                 max_queued: int = DEFAULT_MAX_QUEUED):
        self.configure(max_segments, camera_timeout_s, result_timeout_s, min_confidence, queue_policy, max_queued)
        self.agent, self.vocabulary = agent, None if vocabulary is None else tuple(vocabulary)
        self.observations = observations or Observations()
        self.instruction: str | None = None
        self.waiting: collections.deque[str] = collections.deque()    # to start, oldest first
        self.segment: Segment | None = None       # sent, result not yet back
        self.count = 0                            # segments sent for this instruction
        self.deadline_s = 0.0
        self.since_ns = 0
        self.gripper_open: bool | None = None     # the last goal reached; None: read the fingers
        self.success_heard = False                # a robot without /hdp/sim/success never sets it
        self.success: bool | None = None          # since the last segment ended; None: not yet heard
        self._last_stamp_ns = 0

    def configure(self, max_segments: int, camera_timeout_s: float, result_timeout_s: float,
                  min_confidence: float, queue_policy: str, max_queued: int) -> None:
        """The limits instructions run under, also while one runs: each is read where it applies
        (max_segments before each next segment, a timeout when its wait starts, min_confidence at
        an instruction's first NBP, queue_policy and max_queued when an instruction arrives)."""
        if queue_policy not in QUEUE_POLICIES:
            raise ValueError(f'queue_policy must be one of {", ".join(QUEUE_POLICIES)}, got {queue_policy!r}')
        self.queue_policy, self.max_queued = queue_policy, max_queued
        self.min_confidence = min_confidence
        self.max_segments = max_segments
        self.camera_timeout_s, self.result_timeout_s = camera_timeout_s, result_timeout_s

    def summary(self) -> dict:
        """What runs, for the node's diagnostics: the instruction (None when idle), the segments
        sent for it, of max_segments, and the instructions waiting."""
        return {'instruction': self.instruction, 'segments': self.count, 'max_segments': self.max_segments,
                'waiting': len(self.waiting)}

    # -- messages -------------------------------------------------------------------------
    def on_success(self, value: bool) -> None:
        self.success_heard, self.success = True, bool(value)

    def on_instruction(self, text: str, now_s: float) -> list:
        try:
            instruction = validate_instruction(text, self.vocabulary)
        except InstructionRefused as err:
            return [StatusLine(f'refused instruction: {err}', error=True),
                    Outcome(text.strip(), 'refused', str(err), 0)]
        if self.instruction is None and not self.waiting:
            return self._begin(instruction, now_s)
        if self.queue_policy == 'refuse':
            return self._refuse(instruction, f'busy: {self._busy_with()!r} is running (queue_policy refuse)')
        if self.queue_policy == 'queue':
            if len(self.waiting) >= self.max_queued:
                return self._refuse(instruction, f'queue full: {len(self.waiting)} instructions wait '
                                                 f'(max_queued {self.max_queued})')
            self.waiting.append(instruction)
            return [StatusLine(f'instruction {instruction!r} queued: {len(self.waiting)} waiting')]
        out = self._end_waiting('replaced', f'replaced by {instruction!r} before it started')
        self.waiting.append(instruction)
        if self.instruction is not None and self.segment is None:
            return out + self._stop(f'replaced by {instruction!r}', now_s, 'replaced')
        if self.segment is not None:
            out.append(StatusLine(f'instruction {instruction!r} waits: it replaces {self.instruction!r} when '
                                  f'segment {self.segment.index} ends'))
        return out

    def stop(self, why: str, now_s: float) -> list:
        """End the running instruction and every waiting one as 'stopped' (an operator's stop)."""
        out = self._end_waiting('stopped', f'not started: {why}')
        return out + (self._stop(why, now_s, 'stopped') if self.instruction is not None else [])

    def shutdown(self, now_s: float) -> list:
        """The node is going down: the running and every waiting instruction end 'shutdown'."""
        out = self._end_waiting('shutdown', 'the planner shut down before it started')
        return out + (self._stop('the planner shut down', now_s, 'shutdown') if self.instruction is not None else [])

    def on_result(self, msg, now_s: float) -> list:
        """A /hdp/segment_result (std_msgs/Header); results of other segments are ignored."""
        segment = self.segment
        if segment is None or time_to_ns(msg.stamp) != time_to_ns(segment.stamp):
            return []
        self.segment = None
        x, y, z = segment.xyz
        line = (f'segment {segment.index}: pose ({x:.3f}, {y:.3f}, {z:.3f}) gripper '
                f'{"open" if segment.gripper_open else "close"} -> {msg.frame_id} in {now_s - segment.sent_s:.1f} s')
        if msg.frame_id != topics.SEGMENT_DONE:
            return [StatusLine(line, error=True)] + self._stop(f'segment {segment.index} {msg.frame_id}', now_s,
                                                               'failed')
        self.gripper_open = segment.gripper_open
        if self._replaced_by() is not None:
            return [StatusLine(line)] + self._stop(f'replaced by {self._replaced_by()!r}', now_s, 'replaced')
        self._observe(now_s)
        return [StatusLine(line)]

    # -- the loop ------------------------------------------------------------------------------
    def step(self, now_s: float, now_ns: int) -> list:
        """Advance the loop; call it often (the node's timer). ``now_ns`` stamps a new NBP."""
        if self.instruction is None:
            if not self.waiting:
                return []
            return self._begin(self.waiting.popleft(), now_s) + self.step(now_s, now_ns)
        if self.segment is not None:
            return [] if now_s <= self.deadline_s else self._result_timed_out(now_s)
        if self.success_heard and self.success:
            return self._stop(f'task succeeded after {self.count} segments', now_s, 'succeeded')
        awaiting_success = self.success_heard and self.success is None
        if self.count >= self.max_segments:
            if awaiting_success and now_s <= self.deadline_s:
                return []
            outcome = 'without success' if self.success_heard else '(this robot reports no success)'
            return self._stop(f'{self.max_segments} segments done {outcome}', now_s,
                              'failed' if self.success_heard else 'ended')
        waiting_for = self.observations.missing(self.since_ns) + ([topics.SIM_SUCCESS] if awaiting_success else [])
        if waiting_for:
            if now_s <= self.deadline_s:
                return []
            cameras = sorted({w.split()[0] for w in waiting_for if ' camera' in w})
            subject = f'camera {", ".join(cameras)} ' if cameras else ''
            return self._stop(f'{subject}timed out after {self.camera_timeout_s:.1f} s '
                              f'(no fresh {", ".join(waiting_for)})', now_s, 'failed')
        return self._predict_and_send(now_s, now_ns)

    def robot_gone(self, why: str, now_s: float) -> list:
        """The robot stopped answering (Liveness.problem): the running instruction and every waiting
        one fail, naming why."""
        out = self._end_waiting('failed', f'not started: {why}')
        if self.instruction is None:
            return out
        self.segment = None
        return out + self._stop(why, now_s, 'failed')

    def _result_timed_out(self, now_s: float) -> list:
        """Report the missing result and go on: re-observe and send a fresh NBP while the budget lasts.

        A controller that died mid-segment (or was restarted) then only costs that segment. What
        the lost segment did is unknown, so the gripper's state is read from the fingers again.
        """
        segment, self.segment, self.gripper_open = self.segment, None, None
        line = (f'segment {segment.index}: no result from the controller within {self.result_timeout_s:.1f} s '
                f'(is controller_node running?)')
        if self._replaced_by() is not None:
            return [StatusLine(line, error=True)] + self._stop(f'replaced by {self._replaced_by()!r}', now_s,
                                                               'replaced')
        self._observe(now_s)
        return [StatusLine(line + ('; re-observing' if self.count < self.max_segments else ''), error=True)]

    def _predict_and_send(self, now_s: float, now_ns: int) -> list:
        checked = []
        try:
            q, width = self.observations.arm()
            if self.gripper_open is None:
                self.gripper_open = panda.reads_open(width)
            if self.count == 0 and self.observations.refine_extrinsics:
                checked = _extrinsics_lines(self.observations.check_extrinsics())
            started = time.perf_counter()
            nbp = self.agent.predict(*self.observations.agent_inputs(), self.instruction, (q, self.gripper_open))
        except (ValueError, RuntimeError) as err:       # bad frames or joint states; torch shape errors
            return checked + self._stop(f'cannot predict a next-best pose: {err}', now_s, 'failed')
        out = [*checked, Prediction(float(nbp.confidence), time.perf_counter() - started, nbp.cloud)]
        if self.count == 0 and nbp.confidence < self.min_confidence:
            return out + self._stop(
                f'refused: the agent cannot ground it (its first next-best pose has confidence '
                f'{nbp.confidence:.2f}, below min_confidence {self.min_confidence:.2f})', now_s, 'refused')
        self._last_stamp_ns = max(now_ns, self._last_stamp_ns + 1)     # distinct keys, even on a paused clock
        stamp = Time(sec=self._last_stamp_ns // 1_000_000_000, nanosec=self._last_stamp_ns % 1_000_000_000)
        self.count += 1
        self.segment = Segment(self.count, stamp, np.asarray(nbp.xyz, dtype=float), bool(nbp.gripper_open), now_s)
        self.deadline_s = now_s + self.result_timeout_s
        x, y, z = nbp.xyz
        goal = JointState(header=Header(stamp=stamp), name=[topics.GRIPPER_GOAL_JOINT],
                          position=[panda.GRIPPER_OPEN_WIDTH if nbp.gripper_open else 0.0])
        return out + [
            SegmentGoal(goal, conversions.xyz_quat_to_pose_stamped(nbp.xyz, nbp.quat, topics.NBP_FRAME, stamp)),
            StatusLine(f'segment {self.count}: sent pose ({x:.3f}, {y:.3f}, {z:.3f}) gripper '
                       f'{"open" if nbp.gripper_open else "close"} (confidence {nbp.confidence:.2f})')]

    def _begin(self, instruction: str, now_s: float) -> list:
        # Between instructions the world may have been reset or the hand moved by someone
        # else: the gripper's state is read from the fingers again, not carried over.
        self.instruction, self.count, self.gripper_open = instruction, 0, None
        self._observe(now_s)
        note = ''
        reading = self.agent.read(instruction)
        if reading.grounded and reading.text != instruction:
            note += f', read as {reading.text!r} (similarity {reading.similarity:.2f})'
        return [StatusLine(f'instruction {instruction!r}: up to {self.max_segments} segments{note}')]

    def _observe(self, now_s: float) -> None:
        """Wait for frames taken after now, and for a success report after now."""
        self.since_ns = self.observations.joint_stamp_ns()
        self.success = None
        self.deadline_s = now_s + self.camera_timeout_s

    def _stop(self, why: str, now_s: float, result: str) -> list:
        """End the instruction with ``result`` (outcome.RESULTS): a status line and its outcome."""
        out = [StatusLine(f'instruction {self.instruction!r}: {why}', error=result in ('failed', 'refused')),
               Outcome(self.instruction, result, why, self.count)]
        self.instruction, self.segment = None, None
        return out

    def _refuse(self, instruction: str, why: str) -> list:
        return [StatusLine(f'refused instruction {instruction!r}: {why}', error=True),
                Outcome(instruction, 'refused', why, 0)]

    def _end_waiting(self, result: str, why: str) -> list:
        """Every instruction waiting to start ends with ``result`` (each its own Outcome)."""
        out = []
        while self.waiting:
            instruction = self.waiting.popleft()
            out += [StatusLine(f'instruction {instruction!r}: {why}', error=result == 'failed'),
                    Outcome(instruction, result, why, 0)]
        return out

    def _replaced_by(self) -> str | None:
        """The instruction that replaces the running one at this segment boundary, if any."""
        return self.waiting[-1] if self.queue_policy == 'replace' and self.waiting else None

    def _busy_with(self) -> str:
        return self.instruction if self.instruction is not None else self.waiting[0]


def _extrinsics_lines(checked: dict) -> list[StatusLine]:
    """A status line per camera of Observations.check_extrinsics: the correction, or why the pose on
    /tf_static was kept unchecked (an error line: the calibration could not be confirmed)."""
    lines = []
    for camera, result in checked.items():
        if result.accepted:
            lines.append(StatusLine(f"{camera} camera extrinsics refined from the robot's body by "
                                    f'{result.translation_mm:.1f} mm / {result.rotation_deg:.2f} deg '
                                    f'({result.points} points, residual {result.residual_mm:.1f} mm)'))
        else:
            lines.append(StatusLine(f'{camera} camera extrinsics kept as /tf_static says: {result.why}', error=True))
    return lines

