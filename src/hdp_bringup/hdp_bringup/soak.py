"""`hdp bench soak`: the whole graph over many episodes, a fault injected every tenth, as a day
on a robot would go.

The graph runs as `hdp demo` runs it (demo.watcher), episode after episode across tasks, with
one fault in every FAULT_EVERY episodes, in turn:

    camera_stop      the side camera stops (/hdp/sim/cameras) for the whole episode; the
                     planner must end it naming that camera
    controller_kill  controller_node is SIGKILLed when its next trajectory is out (in this
                     episode, or the next one that sends a trajectory), and started again; the
                     planner must report the missing result and go on with the new controller
    bad_nbp          an NBP with a NaN position goes to the controller before the episode;
                     it must be refused with a result naming the invalid pose
    bad_reset        a reset to a variation the task does not have goes to the bridge before
                     the episode's own reset; it must be rejected on /hdp/status

It reports success over all episodes and over those without a fault, every node's resident
memory (VmRSS) after the first episode (warmed up; for a restarted controller, after the
episode that follows its restart) and at the end, every refusal and rejection the nodes said,
and for each fault whether its real cause was reported, with the line that said it.
"""

from __future__ import annotations

import contextlib
import json
import os
import random
import sys
import time
from pathlib import Path

from hdp_msgs_py import topics
from hdp_msgs_py.msg import Header, Point, Pose, PoseStamped, Quaternion, String, Time
from hdp_msgs_py.outcome import Outcome

from .demo.cli import pick_domain
from .demo.cpu import cpu_seconds, read_stats
from .demo.watcher import DemoNode, GraphDown, Interrupted, run_episode, wait_for_graph, watched_graph
from .launch_cli import NODES, default_params_file, node_commands

FAULTS = ('camera_stop', 'controller_kill', 'bad_nbp', 'bad_reset')
FAULT_EVERY = 10
DEFAULT_TASKS = 'reach_target,open_drawer,pick_up_cup'
# The planner waits this long for a result before it re-observes: a killed controller costs it.
RESULT_TIMEOUT_S = 30.0
CAUSES = {   # what a node must say (a substring of a /hdp/status line or a result) to have named the cause
    'camera_stop': 'camera side timed out',
    'controller_kill': 'no result from the controller',
    'bad_nbp': 'invalid pose: position must be finite',
    'bad_reset': 'rejected reset: ',
}


def fault_of(episode: int, every: int = FAULT_EVERY) -> str | None:
    """The fault injected in episode ``episode`` (0-based): one in every ``every``, in FAULTS order."""
    if every < 1 or (episode + 1) % every:
        return None
    return FAULTS[((episode + 1) // every - 1) % len(FAULTS)]


def rss_mib(pid: int, proc: Path = Path('/proc')) -> float | None:
    """Resident memory of process ``pid`` in MiB (VmRSS), None when it is gone."""
    try:
        text = (proc / str(pid) / 'status').read_text()
    except OSError:
        return None
    kib = next((int(line.split()[1]) for line in text.splitlines() if line.startswith('VmRSS:')), None)
    return None if kib is None else round(kib / 1024.0, 1)


def memory_report(start: dict, end: dict) -> dict:
    """node -> {'start_mib', 'end_mib', 'growth_percent'} for the processes measured both times."""
    return {name: {'start_mib': start[name], 'end_mib': end[name],
                   'growth_percent': round(100.0 * (end[name] - start[name]) / start[name], 1)}
            for name in start if start.get(name) and end.get(name)}


class SoakNode(DemoNode):
    """The demo's watcher, keeping every /hdp/status line and segment result, and able to kill
    the controller on its next trajectory."""

    def __init__(self):
        super().__init__(on_segment=lambda segment: None)
        self.lines: list[tuple[float, str]] = []          # (monotonic s, status line or result)
        self.outcomes: list = []                          # every well-formed /hdp/outcome
        self.on_next_trajectory = None
        self.cameras = self.create_publisher(String, topics.SIM_CAMERAS, topics.COMMAND_QOS)
        self.nbp = self.create_publisher(PoseStamped, topics.NEXT_BEST_POSE, topics.COMMAND_QOS)

    def _on_status(self, msg):
        super()._on_status(msg)
        self.lines.append((time.monotonic(), msg.data))

    def _on_result(self, msg):
        super()._on_result(msg)
        self.lines.append((time.monotonic(), f'result {msg.stamp.sec}.{msg.stamp.nanosec:09d}: {msg.frame_id}'))

    def _on_outcome(self, msg):
        super()._on_outcome(msg)
        with contextlib.suppress(ValueError):            # a malformed one was logged by the watcher
            self.outcomes.append(Outcome.from_json(msg.data))

    def _on_trajectory(self, msg):
        super()._on_trajectory(msg)
        hook, self.on_next_trajectory = self.on_next_trajectory, None
        if hook is not None:
            hook()

    def said(self, since: float, text: str) -> str | None:
        return next((line for t, line in self.lines if t >= since and text in line), None)


def configure(parser) -> None:
    """Run the HDP graph over many episodes with faults injected; report success, memory and refusals."""
    parser.add_argument('--episodes', type=int, default=100, help='episodes (default 100)')
    parser.add_argument('--tasks', default=DEFAULT_TASKS, help=f'comma-separated, in turn (default {DEFAULT_TASKS})')
    parser.add_argument('--seed', type=int, default=1000, help='first scene seed (default 1000: evaluation seeds)')
    parser.add_argument('--fault-every', type=int, default=FAULT_EVERY,
                        help=f'one fault in this many episodes, in turn: {", ".join(FAULTS)} (default {FAULT_EVERY})')
    parser.add_argument('--timeout', type=float, default=240.0, metavar='S', help='seconds per episode (default 240)')
    parser.add_argument('--out', type=Path, default=Path('soak_out'), help='output directory (default soak_out/)')
    parser.add_argument('-p', '--param', action='append', default=[], metavar='NODE:NAME:=VALUE',
                        help='override a node parameter, e.g. sim_bridge_node:camera_width:=128 (repeatable)')
    parser.set_defaults(func=run)


def run(args) -> int:
    from hdp_data.instructions import TASKS       # the task names, without loading the simulator
    tasks = [t.strip() for t in args.tasks.split(',') if t.strip()]
    problem = None
    if not tasks or any(t not in TASKS for t in tasks):
        problem = f'unknown task in {args.tasks!r}; tasks: {", ".join(TASKS)}'
    elif args.episodes < 1 or args.fault_every < 1 or args.seed < 0 or not args.timeout > 0:
        problem = '--episodes and --fault-every must be >= 1, --seed >= 0 and --timeout > 0'
    try:
        domain, _ = pick_domain(os.environ, random.Random())
        commands = node_commands(list(NODES), default_params_file(), [
            f'planner_node:result_timeout_s:={RESULT_TIMEOUT_S}', *args.param])
    except ValueError as err:
        problem = problem or str(err)
    if problem:
        print(f'hdp bench soak: {problem}', file=sys.stderr)
        return 2

    def say(text: str) -> None:
        print(f'[soak] {text}', flush=True)
    logs = args.out / 'logs'
    logs.mkdir(parents=True, exist_ok=True)
    for name in NODES:
        (logs / f'{name}.log').unlink(missing_ok=True)
    say(f'ROS_DOMAIN_ID={domain}; node output: {logs}/<node>.log')
    started = time.monotonic()
    report = {'episodes': [], 'faults': [], 'unexpected_exits': []}
    try:
        with watched_graph(commands, logs, domain, SoakNode, say) as session:
            _soak(session, args, tasks, report, started, say)
            code = 0
    except Interrupted as why:
        say(f'{why}: stopped the nodes')
        code = 130
    except GraphDown as why:
        say(f'{why}; stopped the nodes (see {logs}/)')
        report['unexpected_exits'].append(str(why))
        code = 1
    report['wall_s'] = round(time.monotonic() - started, 1)
    _summarise(report)
    (args.out / 'soak.json').write_text(json.dumps(report, indent=1))
    say(format_report(report))
    say(f'wrote {args.out / "soak.json"}')
    faults_ok = all(f['reported'] for f in report['faults'])
    return code or (0 if faults_ok else 1)


def _soak(session, args, tasks, report, started, say) -> None:
    node, procs = session.node, session.procs
    wait_for_graph(session, say, started)
    # Start RSS is read once every task has run (its shapes allocated, its code loaded): after
    # the first pass over the tasks, and for a restarted controller after its first episode.
    report['rss_start'], warm_up = {}, {name: min(len(tasks), args.episodes) - 1 for name in procs}
    ticks = os.sysconf('SC_CLK_TCK')

    def cpu_sample():
        return cpu_seconds({name: p.pid for name, p in procs.items()}, read_stats(), ticks)

    def restart_controller():
        session.restart('controller_node')
        report['controller_restarts'] = report.get('controller_restarts', 0) + 1
    try:
        _episodes(session, args, tasks, report, restart_controller, cpu_sample, warm_up, say)
    finally:                # an interrupted or broken soak still reports what it saw
        report['rss_end'] = {name: rss_mib(p.pid) for name, p in procs.items()}
        report['refusals'] = [line for _, line in node.lines if 'refused' in line or 'rejected' in line]


def _episodes(session, args, tasks, report, restart_controller, cpu_sample, warm_up, say) -> None:
    node, procs = session.node, session.procs
    for i in range(args.episodes):
        task, seed, fault = tasks[i % len(tasks)], args.seed + i, fault_of(i, args.fault_every)
        since = time.monotonic()
        if fault == 'bad_reset':
            node.reset.publish(String(data=json.dumps({'task': task, 'seed': seed, 'variation': 999})))
            session.spin_until(lambda: node.said(since, CAUSES[fault]), 10.0)
        if fault == 'bad_nbp':
            nan = PoseStamped(header=Header(stamp=Time(sec=1 + i), frame_id=topics.NBP_FRAME), pose=Pose(
                position=Point(x=float('nan'), y=0.0, z=1.0), orientation=Quaternion(w=1.0)))
            node.nbp.publish(nan)
            session.spin_until(lambda: node.said(since, CAUSES[fault]), 10.0)
        node.episode = None
        node.reset.publish(String(data=json.dumps({'task': task, 'seed': seed})))
        if fault == 'camera_stop':
            node.cameras.publish(String(data='front'))
        if fault == 'controller_kill':
            node.on_next_trajectory = restart_controller      # armed until a trajectory goes out
        kills = report.get('controller_restarts', 0)
        record, _ = run_episode(session, seed, None, args.timeout, cpu_sample, say)
        killed = report.get('controller_restarts', 0) > kills
        if fault == 'controller_kill' and not killed:
            fault = None                                      # no trajectory went out: still armed
        fault = 'controller_kill' if killed else fault
        if fault == 'camera_stop':
            node.cameras.publish(String(data='front,side'))
        for name in [name for name, due in warm_up.items() if due <= i]:
            report['rss_start'][name] = rss_mib(procs[name].pid)
            del warm_up[name]
        if fault == 'controller_kill':
            session.spin_until(lambda: node.said(since, 'controller_node: ready'), 120.0)
            warm_up['controller_node'] = i + 1
        line = node.said(since, CAUSES[fault]) if fault else None
        if fault:
            report['faults'].append({'episode': i, 'fault': fault, 'reported': line is not None, 'line': line})
        report['episodes'].append({key: record[key] for key in ('task', 'seed', 'instruction', 'outcome', 'reason',
                                                                'success', 'wall_s')}
                                  | {'fault': fault, 'rss_mib': {name: rss_mib(p.pid) for name, p in procs.items()}})
        say(f"{i + 1}/{args.episodes} {task} seed {seed}{f' [{fault}]' if fault else ''}: {record['outcome']}"
            + (f' ({record["reason"]})' if not record['success'] else '')
            + (f'; cause reported: {line is not None}' if fault else ''))
        if record['outcome'] == 'timeout':            # the planner may still be at it: wait for its outcome
            session.spin_until(lambda: any(o.instruction == record['instruction'] for o in node.outcomes), 120.0)


def _summarise(report: dict) -> None:
    episodes = report['episodes']
    clean = [e for e in episodes if not e['fault']]
    report['success'] = {'all': f"{sum(e['success'] for e in episodes)}/{len(episodes)}",
                         'without_fault': f"{sum(e['success'] for e in clean)}/{len(clean)}"}
    report['memory'] = memory_report(report.get('rss_start', {}), report.get('rss_end', {}))


def format_report(report: dict) -> str:
    """The soak's figures as the bringup README quotes them."""
    lines = [f"episodes: {len(report['episodes'])}, success {report['success']['all']} "
             f"({report['success']['without_fault']} without a fault), {report['wall_s']:.0f} s",
             f"faults reported with their cause: {sum(f['reported'] for f in report['faults'])}"
             f"/{len(report['faults'])}",
             f"nodes that died unasked: {len(report['unexpected_exits'])}",
             '', '| node | RSS at start (MiB) | at end | growth |', '|---|---|---|---|']
    lines += [f"| {name} | {m['start_mib']:.0f} | {m['end_mib']:.0f} | {m['growth_percent']:+.1f}% |"
              for name, m in report['memory'].items()]
    lines += ['', f"refusals and rejections said: {len(report.get('refusals', []))}"]
    return '\n'.join(lines)
