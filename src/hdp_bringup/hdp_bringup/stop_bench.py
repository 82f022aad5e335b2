"""`hdp bench stop`: how fast /hdp/stop brings the moving arm to rest, on the whole graph.

The graph runs as `hdp demo` runs it (demo.watcher). Each trial resets the task (a new seed),
sends its instruction, waits until the arm moves (max |joint velocity| on /joint_states above
MOVING rad/s), calls /hdp/stop (std_srvs/Trigger) and measures until the first /joint_states
whose max |velocity| is below STILL rad/s ("velocity ~0").

Two clocks, because no one clock sees both ends: the request is taken on this process's wall
clock (time.monotonic), so the stop latency is request -> that joint state's arrival here, which
counts the way back over DDS too (an upper bound by about a millisecond on loopback); and the
joint states' own stamps (the simulator's clock) give the arm's side alone: the first still
state's stamp minus that of the latest state seen before the request. The Trigger's answer and
the outcome 'stopped' on /hdp/outcome are timed on the wall clock as well.
"""

from __future__ import annotations

import json
import os
import random
import sys
import time
from pathlib import Path

import numpy as np
from std_srvs.srv import Trigger

from hdp_motion import panda
from hdp_msgs_py import conversions, topics
from hdp_msgs_py.msg import String
from hdp_msgs_py.outcome import Outcome

from .demo.cli import pick_domain
from .demo.watcher import DemoNode, GraphDown, Interrupted, wait_for_graph, watched_graph
from .launch_cli import NODES, default_params_file, node_commands

MOVING = 0.2          # rad/s: the arm is moving (max over the arm's joints)
STILL = 0.05          # rad/s: the arm is at rest ("velocity ~0")
GOAL_MS = 100.0
MOVE_TIMEOUT_S = 180.0     # for the arm to start moving: the agent predicts and the controller plans on a CPU
STOP_TIMEOUT_S = 5.0


class StopNode(DemoNode):
    """The demo's watcher, keeping each /joint_states' arrival and /hdp/outcome, with a /hdp/stop client."""

    def __init__(self):
        super().__init__(on_segment=lambda segment: None)
        self.states: list[tuple[float, float, float]] = []    # (arrival monotonic s, stamp s, max |qd| rad/s)
        self.outcomes: list[Outcome] = []
        self.stop = self.create_client(Trigger, topics.STOP)

    def _on_joints(self, msg):
        super()._on_joints(msg)
        names = list(msg.name)
        if len(msg.velocity) == len(names) and all(n in names for n in panda.ARM_JOINTS):
            speed = max(abs(msg.velocity[names.index(n)]) for n in panda.ARM_JOINTS)
            self.states.append((time.monotonic(), conversions.time_to_seconds(msg.header.stamp), speed))

    def _on_outcome(self, msg):
        super()._on_outcome(msg)
        try:
            self.outcomes.append(Outcome.from_json(msg.data))
        except ValueError:
            pass                   # logged by the watcher

    def speed(self) -> float:
        return self.states[-1][2] if self.states else 0.0


def configure(parser) -> None:
    """Measure /hdp/stop's latency on the HDP graph: request -> the arm's velocity ~0."""
    parser.add_argument('--trials', type=int, default=5, help='stops measured (default 5)')
    parser.add_argument('--task', default='open_drawer', help='the task each trial resets to (default open_drawer)')
    parser.add_argument('--seed', type=int, default=1000, help='first scene seed (default 1000)')
    parser.add_argument('--out', type=Path, default=Path('stop_out'),
                        help='node logs go to OUT/logs (default stop_out/)')
    parser.add_argument('--json', action='store_true', help='print the report as JSON')
    parser.add_argument('-p', '--param', action='append', default=[], metavar='NODE:NAME:=VALUE',
                        help='override a node parameter, e.g. sim_bridge_node:camera_width:=128 (repeatable)')
    parser.set_defaults(func=run)


def run(args) -> int:
    from hdp_data.instructions import TASKS
    problem = None
    if args.task not in TASKS:
        problem = f'unknown task {args.task!r}; tasks: {", ".join(TASKS)}'
    elif args.trials < 1 or args.seed < 0:
        problem = '--trials must be >= 1 and --seed >= 0'
    try:
        domain, _ = pick_domain(os.environ, random.Random())
        commands = node_commands(list(NODES), default_params_file(), args.param)
    except ValueError as err:
        problem = problem or str(err)
    if problem:
        print(f'hdp bench stop: {problem}', file=sys.stderr)
        return 2

    def say(text: str) -> None:
        print(f'[stop] {text}', file=sys.stderr if args.json else sys.stdout, flush=True)
    logs = args.out / 'logs'
    logs.mkdir(parents=True, exist_ok=True)
    say(f'ROS_DOMAIN_ID={domain}; node output: {logs}/<node>.log')
    trials, code = [], 0
    try:
        with watched_graph(commands, logs, domain, StopNode, say) as session:
            wait_for_graph(session, say, time.monotonic())
            for i in range(args.trials):
                trials.append(_trial(session, args.task, args.seed + i, say))
    except Interrupted as why:
        say(f'{why}: stopped the nodes')
        code = 130
    except GraphDown as why:
        say(f'{why}; stopped the nodes (see {logs}/)')
        code = 1
    report = summarise(trials)
    print(json.dumps(report, indent=1) if args.json else format_report(report), flush=True)
    return code or (0 if report['measured'] == len(trials) and trials else 1)


def _trial(session, task: str, seed: int, say) -> dict:
    node = session.node
    node.episode = None
    node.reset.publish(String(data=json.dumps({'task': task, 'seed': seed})))
    if not session.spin_until(lambda: not node.scene_missing() and node.episode['seed'] == seed, 60.0):
        raise GraphDown(f'the scene of seed {seed} did not come up ({", ".join(node.scene_missing())})')
    text = node.episode['instruction']
    node.outcomes.clear()
    node.instruction.publish(String(data=text))
    record = {'seed': seed, 'instruction': text}
    if not session.spin_until(lambda: node.speed() > MOVING or node.outcomes, MOVE_TIMEOUT_S) or node.outcomes:
        record['problem'] = (f'the instruction ended {node.outcomes[0].result} before the arm moved'
                             if node.outcomes else f'the arm did not move within {MOVE_TIMEOUT_S:.0f} s')
        say(f'seed {seed}: {record["problem"]}')
        return record
    record['speed_at_stop'] = round(node.speed(), 3)
    last_stamp, seen = node.states[-1][1], len(node.states)
    requested = time.monotonic()
    answer = node.stop.call_async(Trigger.Request())
    answered_at = None

    def first_still():
        return next((s for s in node.states[seen:] if s[2] < STILL), None)

    def stopped():
        return next((o for o in node.outcomes if o.instruction == text), None)

    def done():
        nonlocal answered_at
        if answered_at is None and answer.done():
            answered_at = time.monotonic()
        return answered_at is not None and first_still() is not None and stopped() is not None
    session.spin_until(done, STOP_TIMEOUT_S)
    still, outcome = first_still(), stopped()
    record.update(
        trigger_ms=None if answered_at is None else round(1e3 * (answered_at - requested), 1),
        answer=None if answered_at is None else answer.result().message,
        outcome=None if outcome is None else outcome.result,
        latency_ms=None if still is None else round(1e3 * (still[0] - requested), 1),
        sim_latency_ms=None if still is None else round(1e3 * (still[1] - last_stamp), 1))
    say(f"seed {seed}: moving at {record['speed_at_stop']} rad/s; still after {record['latency_ms']} ms "
        f"(sim stamps {record['sim_latency_ms']} ms); Trigger answered in {record['trigger_ms']} ms; "
        f"outcome {record['outcome']}")
    session.spin_until(lambda: False, 1.0)           # the held arm settles before the next reset
    return record


def summarise(trials: list[dict]) -> dict:
    measured = [t for t in trials if t.get('latency_ms') is not None]

    def stats(key):
        values = [t[key] for t in measured if t.get(key) is not None]
        return {'p50': round(float(np.median(values)), 1), 'max': round(float(max(values)), 1)} if values else None
    return {'moving_rad_s': MOVING, 'still_rad_s': STILL, 'goal_ms': GOAL_MS, 'trials': trials,
            'measured': len(measured), 'stopped_outcomes': sum(t.get('outcome') == 'stopped' for t in trials),
            'latency_ms': stats('latency_ms'), 'sim_latency_ms': stats('sim_latency_ms'),
            'trigger_ms': stats('trigger_ms')}


def format_report(report: dict) -> str:
    def line(name, key):
        s = report[key]
        return f'{name}: p50 {s["p50"]:.1f} ms, max {s["max"]:.1f} ms' if s else f'{name}: not measured'
    return '\n'.join([
        f"stops measured: {report['measured']}/{len(report['trials'])}, outcome 'stopped': "
        f"{report['stopped_outcomes']}/{len(report['trials'])} (moving > {report['moving_rad_s']} rad/s, "
        f"still < {report['still_rad_s']} rad/s)",
        line('request -> arm still (wall clock, at arrival here)', 'latency_ms'),
        line('last state before -> first still state (joint-state stamps)', 'sim_latency_ms'),
        line('Trigger answered', 'trigger_ms'),
        f"goal <= {report['goal_ms']:.0f} ms: "
        + ('met' if report['latency_ms'] and report['latency_ms']['max'] <= report['goal_ms'] else 'not met')])
