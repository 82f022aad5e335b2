"""The graph in one process, on sim time: an evaluation episode runs the nodes' own logic.

    SimBridge (the simulated robot, as sim_bridge_node runs it)
      -- joint states, camera frames, /tf_static, task success -->  PlannerLoop (planner_node's)
      -- gripper goal + NBP -->  SegmentController (controller_node's)
      -- arm / finger trajectories --> SimBridge;  segment results --> PlannerLoop

Each physics step (TIME_STEP) the bridge steps; at the graph's rates (the bridge's joint-state,
camera and success rates, the nodes' timer periods) messages are handed over at once, with no
transport. Every refusal, budget, timeout and gripper rule is the nodes' own: this module only
moves messages and reads the records the logic returns. What the graph has and this lacks is
wall-clock time: predictions and plans take none here, unless ``think_s`` holds each trajectory
back that long while the world runs on (as it does while the nodes think).
"""

from __future__ import annotations

import dataclasses

from hdp_controller.inputs import FilteredDepth
from hdp_controller.segment_controller import ArmCommand, FingerCommand, SegmentController, SegmentResult
from hdp_controller.segment_planning import PLAN_ATTEMPTS, REACH_TOLERANCE_DEG, REACH_TOLERANCE_M, PlanReport
from hdp_controller.trajectory import VELOCITY_SCALE
from hdp_data.depth_filters import FilterSettings
from hdp_msgs_py.outcome import Outcome, StatusLine
from hdp_planner.planner_logic import DEFAULT_MIN_CONFIDENCE, Observations, PlannerLoop, Prediction, SegmentGoal
from hdp_sim_bridge.bridge import SimBridge
from hdp_sim_bridge.sensor_model import SensorSettings
from hdp_sim_bridge.world import TIME_STEP

# The graph's rates (hdp_bringup/config/hdp_graph.yaml and the nodes' timers), in Hz of sim time.
JOINT_STATE_HZ = 120.0
CAMERA_HZ = 2.0
SUCCESS_HZ = 2.0              # sim_bridge_node's /hdp/sim/success timer
PLANNER_HZ = 10.0             # planner_node's step timer
CONTROLLER_HZ = 20.0          # controller_node's step timer
CONTROLLER_CAMERA = 'front'   # RK-Diffuser's camera, as controller_node subscribes to it


@dataclasses.dataclass
class GraphSettings:
    """The nodes' parameters an evaluation may set; defaults are the graph's (hdp_graph.yaml)."""
    max_segments: int = 8
    min_confidence: float = DEFAULT_MIN_CONFIDENCE
    camera_timeout_s: float = 5.0
    result_timeout_s: float = 60.0
    reach_tolerance: tuple[float, float] | None = (REACH_TOLERANCE_M, REACH_TOLERANCE_DEG)
    plan_attempts: int = PLAN_ATTEMPTS
    velocity_scale: float = VELOCITY_SCALE
    segment_timeout_s: float = 10.0
    carry_on_unsettled: bool = True         # the graph's `unsettled: carry_on`
    camera_hz: float = CAMERA_HZ
    think_s: float = 0.0
    # sim_bridge_node's sensor_profile, extrinsic_error_mm/_deg and latency_ms; the bridge is built with it
    sensor: SensorSettings = dataclasses.field(default_factory=SensorSettings)
    # the depth filter both learned nodes run on their cameras' depth (hdp_data.depth_filters); None: off
    depth_filter: FilterSettings | None = None
    # planner_node's refine_extrinsics: each camera checked against the robot's body per instruction
    refine_extrinsics: bool = False


@dataclasses.dataclass
class EpisodeLog:
    """What the logic said during one instruction: its outcome, each prediction, each plan
    (controller's PlanReport) and every status line, prefixed by the node that said it."""
    outcome: Outcome | None = None
    predictions: list = dataclasses.field(default_factory=list)    # Prediction
    plans: list = dataclasses.field(default_factory=list)          # PlanReport
    failed_plan: PlanReport | None = None                          # the plan a refusal came with
    status: list = dataclasses.field(default_factory=list)         # 'planner: ...', 'controller: ...'
    sim_seconds: float = 0.0


def _every(rate_hz: float) -> int:
    """Physics steps between two events at ``rate_hz``."""
    return max(1, round(1.0 / (rate_hz * TIME_STEP)))


class InProcessGraph:
    """One episode of the graph on ``bridge`` (already reset to its scene): planner_node's and
    controller_node's logic around it, wired as hdp_graph.launch.py wires the nodes.

    agent: a NextBestPoseAgent. policy: a LowLevelPolicy. scene: a callable giving the planning
    baselines' collision scene (the simulator's), or None."""

    def __init__(self, bridge: SimBridge, agent, policy, needs_points: bool, settings: GraphSettings,
                 scene=None):
        self.bridge, self.settings = bridge, settings
        self.observations = Observations(depth_filter=settings.depth_filter,       # as planner_node: it fills them
                                         refine_extrinsics=settings.refine_extrinsics)
        self.planner = PlannerLoop(agent, agent.vocabulary, settings.max_segments, settings.camera_timeout_s,
                                   settings.result_timeout_s, self.observations, settings.min_confidence)
        self.controller = SegmentController(
            policy, needs_points=needs_points, velocity_scale=settings.velocity_scale,
            segment_timeout_s=settings.segment_timeout_s, reach_tolerance=settings.reach_tolerance,
            carry_on_unsettled=settings.carry_on_unsettled, plan_attempts=settings.plan_attempts, scene=scene)
        self.controller_depth = None if settings.depth_filter is None else FilteredDepth(settings.depth_filter)
        self.log = EpisodeLog()
        self._held_back: list[tuple[float, ArmCommand]] = []      # trajectories due after think_s
        self._steps = 0
        tf_static = bridge.tf_static()
        self.observations.on_tf_static(tf_static)
        self.controller.on_tf_static(tf_static)
        self._publish_joint_state()

    @property
    def now_s(self) -> float:
        return self.bridge.sim_time

    def run(self, instruction: str, max_sim_s: float) -> EpisodeLog:
        """Give ``instruction`` and run until the planner's outcome for it; RuntimeError if none
        comes within ``max_sim_s`` of sim time (the logic guarantees one: that would be a bug)."""
        start = self.now_s
        self._from_planner(self.planner.on_instruction(instruction, self.now_s))
        every = {name: _every(hz) for name, hz in (('joints', JOINT_STATE_HZ), ('cameras', self.settings.camera_hz),
                                                   ('success', SUCCESS_HZ), ('planner', PLANNER_HZ),
                                                   ('controller', CONTROLLER_HZ))}
        while self.log.outcome is None:
            if self.now_s - start > max_sim_s:
                raise RuntimeError(f'no outcome for {instruction!r} after {max_sim_s:.0f} s of sim time; '
                                   f'last status lines: {self.log.status[-3:]}')
            self._release_held_back()
            self.bridge.step()
            self._steps += 1
            if self._steps % every['joints'] == 0:
                self._publish_joint_state()
            if self._steps % every['cameras'] == 0:
                self.bridge.expose()
            self._deliver_frames()
            if self._steps % every['success'] == 0:
                self.planner.on_success(self.bridge.success())
            if self._steps % every['controller'] == 0:
                self._from_controller(self.controller.step(self.now_s))
            if self._steps % every['planner'] == 0:
                now_ns = round(self.now_s * 1e9)
                self._from_planner(self.planner.step(now_ns * 1e-9, now_ns))
        self.log.sim_seconds = round(self.now_s - start, 3)
        return self.log

    # -- the bridge's publications ---------------------------------------------------------
    def _publish_joint_state(self) -> None:
        msg = self.bridge.joint_state()
        self.observations.on_joint_state(msg)
        self.controller.on_joint_state(msg)

    def _deliver_frames(self) -> None:
        """The frames the bridge exposed that are due now (at once, or the sensor's latency later)."""
        for name, (color, depth, info) in self.bridge.delivered():
            self.observations.on_color(name, color)
            self.observations.on_info(name, info)      # first: a depth filter needs the focal length
            self.observations.on_depth(name, depth)
            if name == CONTROLLER_CAMERA:
                self.controller.on_camera_info(info)
                if self.controller_depth is not None:
                    self.controller_depth.on_camera_info(info)
                    depth = self.controller_depth.filtered(depth)
                self.controller.on_depth(depth)

    # -- the nodes' publications -------------------------------------------------------------
    def _from_planner(self, outputs) -> None:
        for out in outputs:
            match out:
                case StatusLine():
                    self.log.status.append(f'planner: {out.text}')
                case Prediction():
                    self.log.predictions.append(out)
                case SegmentGoal():
                    self._from_controller(self.controller.on_gripper_goal(out.gripper_goal))
                    self._from_controller(self.controller.on_nbp(out.nbp, self.now_s))
                case Outcome():
                    self.log.outcome = out

    def _from_controller(self, outputs) -> None:
        for out in outputs:
            match out:
                case StatusLine():
                    self.log.status.append(f'controller: {out.text}')
                case ArmCommand():
                    self.log.plans.append(out.plan)
                    self._held_back.append((self.now_s + self.settings.think_s, out))
                case FingerCommand():
                    self.bridge.command_gripper(out.trajectory)
                case SegmentResult():
                    if out.plan is not None:
                        self.log.plans.append(out.plan)
                        self.log.failed_plan = out.plan
                    self._from_planner(self.planner.on_result(out.header, self.now_s))

    def _release_held_back(self) -> None:
        while self._held_back and self._held_back[0][0] <= self.now_s + 1e-9:
            _, command = self._held_back.pop(0)
            try:
                self.bridge.command_arm(command.trajectory)
            except ValueError as err:        # as sim_bridge_node: said, and the segment times out
                self.log.status.append(f'sim_bridge: rejected arm trajectory: {err}')
